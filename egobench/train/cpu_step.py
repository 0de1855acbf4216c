"""The compiled CPU training step: one frame's loss and every Gaussian gradient in one pass of compiled
kernels, with no autograd graph (issue 67; docs/cpu-rasterizer.md, "The compiled training step").

The autograd path of `egobench.train.loop` runs the same kernels behind torch's custom Functions: the
projection, the rasterizer, the alpha-depth pass, the exposure and the photometric loss each an autograd
node, with the render's input checks, pose matrices and the Functions' wrappers between them (~4 ms of a
19 ms step at 128 px on one thread). Here the forward calls the kernels in order, keeps what the backward
reads, and the backward calls their backwards in reverse with each upstream gradient in the layout the
next kernel reads: the per-intersection gradients stay channel first from the rasterizer to the
projection, the rendered depth and alpha are not formed (the photometric loss reads neither), and the
parameters' gradients are written straight into ``.grad``. The autograd path stays the oracle (it is
what a GPU and every other method run); tests/train/test_cpu_step.py checks values and gradients against
it.

What it covers (`unsupported_reason` names what it does not): 3DGS on the compiled CPU backend, float32
or float64, one exposure sample, poses the run does not optimise, no learnt lens shading, and the
trainer's formation (the gamma exposure of `egobench.model.gamma_exposure`, or a clamp for methods
without formation). That is every 3DGS method of the paper's tables but 3DGS-on-the-move.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from egobench.model.formation import FormationModel, GammaResponse
from egobench.model.gamma_exposure import Exposed, ExposureCurve, _expose_bwd, _expose_fwd
from egobench.model.methods import MethodSpec
from egobench.render import cpu_backend as cb
from egobench.render.cpu_backend import ck
from egobench.metrics import SSIM_SIGMA, SSIM_WINDOW, gaussian_taps
from egobench.render import world_to_camera
from egobench.render import kernel_build
from egobench.render.types import Gaussians
from egobench.train.photometric import _loss_and_grad

#: environment variable: "autograd" trains through torch's autograd even where the compiled step applies
#: (the oracle, and the old path of a speed comparison); unset or "auto": the compiled step where it applies
STEP_ENV = "EGOBENCH_TRAIN_STEP"
STEP_CHOICES = ("auto", "autograd")


def requested_step() -> str:
    """`STEP_ENV`'s value ("auto" when unset); another value is a named error."""
    value = os.environ.get(STEP_ENV, "auto") or "auto"
    if value not in STEP_CHOICES:
        raise ValueError(f"{STEP_ENV}={value!r}: expected one of {', '.join(STEP_CHOICES)}")
    return value


def unsupported_reason(spec: MethodSpec, backend: str, formation, learn_shading: bool,
                       dtype: torch.dtype = torch.float32) -> str | None:
    """Why the compiled step cannot train this run (None: it can); the autograd path trains it then."""
    if backend != "cpu":
        return f"the rasterizer backend is {backend!r}, not the compiled CPU backend"
    if spec.splat_mode != "3dgs":
        return f"splat mode {spec.splat_mode!r} (the compiled step renders 3DGS)"
    if spec.pose_optimisation or spec.render_exposure_samples != 1:
        return "the method optimises poses or averages exposure samples"
    if learn_shading:
        return "the run learns a lens shading"
    if dtype not in (torch.float32, torch.float64):
        return f"dtype {dtype}"
    if spec.formation and not _gamma_formation(formation):
        return "the formation is not the trainer's gamma exposure (exposure, vignette, no white balance)"
    return None


def _gamma_formation(formation) -> bool:
    cfg = getattr(formation, "config", None)
    return (isinstance(formation, FormationModel) and isinstance(formation.response, GammaResponse)
            and cfg.exposure_gain and cfg.vignette and not cfg.white_balance)


@dataclass
class FrameTarget:
    """What one training frame is compared with, as the kernels read it: the captured image and the valid
    mask as rows [H, W * 3] in the parameters' dtype, and the exposure scale k V per pixel [H * W]."""

    gt_rows: np.ndarray
    mask_rows: np.ndarray
    scale: np.ndarray
    n_mask: float
    ssim_lambda: float


@dataclass
class StepOutput:
    """A compiled step's results: the loss (a 0-d tensor), the rendered scene colour [H, W, 3], the
    densification carriers (means2d [K, N, 2] with ``.grad``, radii [K, N]) and the seconds spent
    rendering forward and backward (the trainer's raster share)."""

    loss: Tensor
    rgb: Tensor
    carriers: list[tuple[Tensor, Tensor]]
    render_fwd_s: float
    render_bwd_s: float


def frame_target(gt: Tensor, mask3: Tensor, k: Tensor, vignette: Tensor, n_mask: float, ssim_lambda: float,
                 dtype: torch.dtype) -> FrameTarget:
    """The kernels' view of a frame: gt [H, W, 3] in 0..1, mask3 [H, W, 3], k (0-d), vignette [H, W]."""
    H, W, C = gt.shape
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"training images must be at least {SSIM_WINDOW}x{SSIM_WINDOW} for SSIM, got {W}x{H}")
    rows = [t.detach().to(dtype).reshape(H, W * C).contiguous().numpy() for t in (gt, mask3)]
    scale = (k.to(dtype) * vignette.to(dtype)).reshape(H * W).contiguous().numpy()  # the formation's k x V
    return FrameTarget(rows[0], rows[1], scale, float(n_mask), float(ssim_lambda))


@dataclass
class _Splats:
    """The Gaussians as the kernels read them (views of the parameters, no copies where the dtype allows):
    means, quats, linear scales, log-opacity and colours; ``scales`` and ``log_sigmoid`` (torch) are kept for
    the activations' backwards."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    log_opac: np.ndarray
    opac: np.ndarray
    colors: np.ndarray
    scales_t: Tensor
    logits_t: Tensor
    log_sigmoid_buffer: Tensor


def _splats(g: Gaussians) -> _Splats:
    """The activations the render applies (exp of the log-scales, log-sigmoid of the opacity logits), in
    torch's ops, so that the values are the autograd path's bits."""
    scales = torch.exp(g.log_scales.detach())
    logits = g.opacity_logits.detach()
    log_opac, buffer = torch.ops.aten.log_sigmoid_forward(logits)
    np_of = cb.contiguous_numpy
    return _Splats(np_of(g.means), np_of(g.quats), scales.numpy(), log_opac.numpy(), log_opac.exp().numpy(),
                   np_of(g.colors), scales, logits, buffer)


@dataclass
class _Rendered:
    """What the forward keeps for the backward."""

    viewmats: np.ndarray
    m2: np.ndarray  # [I, N, 2] projected centres, gsplat's pixels
    radii: np.ndarray  # [I, N, 2] int32
    setup: object  # `cpu_backend.RasterSetup`
    tab: np.ndarray
    pix_view: np.ndarray
    out_T: np.ndarray
    out_last: np.ndarray
    rows_hit: np.ndarray


def _render(sp: _Splats, camera, poses: Tensor, ppi: Tensor | None) -> tuple[np.ndarray, _Rendered]:
    """`render_cpu`'s forward without autograd: poses [K, 4, 4] camera-to-world -> the summed colour
    [H, W, 3] (no background) and what the backward reads."""
    H, W, dt = camera.height, camera.width, sp.means.dtype
    viewmats = cb.contiguous_numpy(world_to_camera(poses.to(torch.from_numpy(sp.means).dtype)))
    I, N = viewmats.shape[0], sp.means.shape[0]
    m2, con = np.empty((I, N, 2), dt), np.empty((I, N, 3), dt)
    dep, rad, nrm = np.empty((I, N), dt), np.empty((I, N, 2), np.int32), np.zeros((I, 0, 3), dt)
    ck.project_fwd(ck.Splats(sp.means, sp.quats, sp.scales), sp.opac,
                   cb.view_args(viewmats, cb.camera_array(camera), W, H), False, ck.Projected(m2, con, dep, rad, nrm))
    m2 -= cb.GSPLAT_PIXEL_OFFSET  # egobench's pixels and back, as the autograd path's carrier does (same bits)
    m2 += m2.dtype.type(cb.GSPLAT_PIXEL_OFFSET)
    ts = cb.DEFAULT_TILE
    pix_view, bin_needed = cb.pixel_views(ppi, I, H, W, ts)
    from_np = torch.from_numpy
    st = cb.raster_setup(m2, from_np(rad), from_np(dep), from_np(sp.colors), from_np(nrm), pix_view, bin_needed, ts)
    out_feat = np.zeros((1, H, W, st.feats.shape[1]), dt)
    out_T, out_last = np.zeros((1, H, W), dt), np.zeros((1, H, W), np.int32)
    tab = cb.table_buffer(I * N, dt)
    ck.gaussian_table(m2, con, rad, sp.log_opac, st.needed, tab)
    rows_hit = cb.rows_hit_buffer(st.flat_ids.shape[0], ts, st.cw)
    ck.raster_fwd(ck.Tables(tab, st.feats), st.tiles(pix_view, ts), st.constants(),
                  ck.Composite(out_feat, out_T, out_last), rows_hit)
    rgb = np.ascontiguousarray(out_feat[0, ..., :ck.DEPTH_CH])
    return rgb, _Rendered(viewmats, m2, rad, st, tab, pix_view, out_T, out_last, rows_hit)


def _render_backward(g: Gaussians, sp: _Splats, camera, r: _Rendered, g_rgb: np.ndarray,
                     g_T: np.ndarray) -> Tensor:
    """d loss / d (summed colour [H, W, 3], transmittance [H, W]) -> every Gaussian parameter's ``.grad``;
    returns d loss / d means2d [I, N, 2] (the densification carrier's gradient)."""
    import numba

    st, (I, N) = r.setup, r.m2.shape[:2]
    Cf, dt = st.feats.shape[1], sp.means.dtype
    gF = np.empty(r.out_T.shape + (Cf,), dt)
    P = r.out_T.size
    ck.pack_pixel_grads(gF.reshape(P, Cf), g_rgb.reshape(P, 3), np.empty((0, 1), dt), np.empty((0, 3), dt),
                        np.empty((0,), dt), np.empty((0, 0), dt))
    isect = np.zeros((st.flat_ids.shape[0], 6 + Cf), st.kc.dtype)
    ck.raster_bwd(ck.Tables(r.tab, st.feats), st.tiles(r.pix_view, cb.DEFAULT_TILE), st.constants(),
                  ck.BackwardPixels(r.out_T, r.out_last, gF, g_T.reshape(r.out_T.shape)), isect, r.rows_hit)
    per = np.empty((isect.shape[1], I * N), dt)  # channel first: [C, I x N]
    ck.reduce_isect_grad(isect, st.flat_ids, st.flat_ids.shape[0], per, np.zeros((0, 2)), numba.get_num_threads())
    per = per.reshape(-1, I, N)
    g_colors = np.empty((N, 3), dt)
    ck.ordered_sum(per[6:9], g_colors)
    gm, gq, gs = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
    gv_parts = np.zeros((max(1, math.ceil(N / ck.CHUNK)), I, 12))
    wide = ck.Splats(*(a.astype(np.float64) for a in (sp.means, sp.quats, sp.scales)))
    view = cb.view_args(r.viewmats.astype(np.float64), cb.camera_array(camera), camera.width, camera.height)
    ck.project_bwd(wide, view, False, ck.ProjectedGrads(per[0:2], per[2:5], per[9], np.zeros((3, I, 0), dt)),
                   ck.SplatGrads(gm, gq, gs, gv_parts))
    tdt = torch.from_numpy(sp.means[:0]).dtype
    g.means.grad = torch.from_numpy(gm).to(tdt)
    g.quats.grad = torch.from_numpy(gq).to(tdt)
    g.log_scales.grad = torch.from_numpy(gs).to(tdt) * sp.scales_t
    g_logop = torch.from_numpy(per[5]).sum(0)
    g.opacity_logits.grad = torch.ops.aten.log_sigmoid_backward(g_logop, sp.logits_t, sp.log_sigmoid_buffer)
    g.colors.grad = torch.from_numpy(g_colors)
    return torch.from_numpy(per[0:2]).permute(1, 2, 0)


@dataclass
class _Formed:
    """The predicted image [P, 3] and its partials by the scene colour (the exposure's ``dx``; for a clamp,
    1 inside [0, 1] and 0 outside)."""

    pred: np.ndarray
    dx: np.ndarray
    ds: np.ndarray | None


def _form(rgb: np.ndarray, spec: MethodSpec, formation, scale: np.ndarray) -> _Formed:
    """The method's image formation of the scene colour rgb [H, W, 3]: `FormationModel.predict`'s gamma
    exposure with the per-pixel scale k V, or a clamp to [0, 1] for methods without formation."""
    x = rgb.reshape(-1, 3)
    if not spec.formation:
        inside = ((x >= 0) & (x <= 1)).astype(x.dtype)  # torch's clamp passes the gradient at 0 and 1
        return _Formed(np.clip(x, 0, 1), inside, None)
    resp = formation.response
    curve = ExposureCurve(bool(spec.scene_gamma), bool(formation.config.clamp), float(resp.gamma),
                          float(resp.toe_linear) ** (1.0 / float(resp.gamma)), float(resp.toe_linear))
    out, dx, ds = (np.empty_like(x) for _ in range(3))
    _expose_fwd(x, scale, np.empty_like(scale), curve, Exposed(out, dx, ds))
    return _Formed(out, dx, ds)


def _formation_backward(f: _Formed, g_pred: np.ndarray) -> np.ndarray:
    """d loss / d prediction [P, 3] -> d loss / d scene colour [P, 3]."""
    if f.ds is None:
        return g_pred * f.dx
    g_x, g_s = np.empty_like(f.dx), np.empty(f.dx.shape[0], f.dx.dtype)
    _expose_bwd(g_pred, f.dx, f.ds, g_x, g_s)
    return g_x


def _taps(dtype: np.dtype) -> np.ndarray:
    return gaussian_taps(SSIM_WINDOW, float(SSIM_SIGMA), torch.from_numpy(np.empty(0, dtype)).dtype,
                         torch.device("cpu")).numpy()


def frame_step(g: Gaussians, camera, poses: Tensor, ppi: Tensor | None, spec: MethodSpec, formation,
               target: FrameTarget, background: Tensor) -> StepOutput:
    """One training frame through the compiled kernels: the loss, and every Gaussian parameter's gradient
    written into its ``.grad`` (replacing any). poses [K, 4, 4] camera-to-world (K rolling-shutter samples
    gathered by ``ppi`` [H, W], or one pose and ``ppi`` None); background [3] in scene colour."""
    kernel_build.ensure_built(g.means.dtype, "3dgs")
    t0 = time.perf_counter()
    cb.set_threads()  # for every kernel below (`raster_setup` sets them again)
    sp = _splats(g)
    rgb, rendered = _render(sp, camera, poses, ppi)
    bg = background.to(g.means.dtype).numpy()
    if bg.any():  # rgb + T bg, as `composite_output`
        rgb += rendered.out_T[0, ..., None] * bg
    t_fwd = time.perf_counter() - t0
    formed = _form(rgb, spec, formation, target.scale)
    H, W = camera.height, camera.width
    value, g_pred = _loss_and_grad(formed.pred.reshape(H, W * 3), target.gt_rows, target.mask_rows, 3,
                                   target.n_mask, target.ssim_lambda, _taps(formed.pred.dtype))
    g_rgb = _formation_backward(formed, g_pred.reshape(-1, 3))
    t1 = time.perf_counter()
    g_T = (g_rgb * bg).sum(-1) if bg.any() else np.zeros(rendered.out_T.shape, g_rgb.dtype)
    g_m2 = _render_backward(g, sp, camera, rendered, g_rgb, g_T)
    carrier = torch.from_numpy(rendered.m2)  # the values are unread: densification reads the gradient
    carrier.grad = g_m2
    radii = cb.radius_max(torch.from_numpy(rendered.radii))
    loss = torch.tensor(value, dtype=g.means.dtype)
    return StepOutput(loss, torch.from_numpy(rgb), [(carrier, radii)], t_fwd, time.perf_counter() - t1)
