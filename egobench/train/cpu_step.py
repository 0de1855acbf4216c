"""The compiled CPU training step: one frame's loss and every Gaussian gradient in one pass of compiled
kernels, with no autograd graph (issue 67; docs/cpu-rasterizer.md, "The compiled training step").

The autograd path of `egobench.train.loop` runs the same kernels behind torch's custom Functions: the
projection, the rasterizer, the alpha-depth pass, the exposure and the photometric loss each an autograd
node, with the render's input checks, pose matrices and the Functions' wrappers between them (~4 ms of a
19 ms step at 128 px on one thread; results/speed/README.md, 2026-12-05). Here the forward calls the kernels
in order, keeps what the backward reads, and the backward calls their backwards in reverse with each
upstream gradient in the layout the next kernel reads: the per-intersection gradients stay channel first
from the rasterizer to the projection, the rendered depth and alpha are formed only where 2DGS's normal
consistency reads them, and the parameters' gradients are written straight into ``.grad``. The autograd
path stays the oracle (it is what a GPU and every other method run); tests/train/test_cpu_step.py checks
values and gradients against it: the same bits.

What it covers (`unsupported_reason` names what it does not): 3DGS and 2DGS on the compiled CPU backend
(the render: `egobench.train.cpu_render`), float32 or float64, one exposure sample, poses the run does not
optimise, no learnt lens shading, the trainer's formation (the gamma exposure of
`egobench.model.gamma_exposure`, or a clamp for methods without formation), and 2DGS's normal consistency and
distortion (`egobench.train.losses`'s schedule). That is every method of the paper's tables but
3DGS-on-the-move.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from egobench.metrics import SSIM_SIGMA, SSIM_WINDOW, gaussian_taps
from egobench.model.formation import FormationModel, GammaResponse
from egobench.model.gamma_exposure import Exposed, ExposureCurve, expose_bwd, expose_fwd
from egobench.model.methods import MethodSpec
from egobench.render import cpu_backend as cb
from egobench.render import kernel_build
from egobench.render.cpu_backend import ck
from egobench.render.types import Gaussians
from egobench.train.config import TrainConfig
from egobench.train.cpu_render import PixelGrads, Rendered, activations, render_bwd, render_fwd
from egobench.train.normal_consistency import RenderedMaps, nc_backward_arrays, nc_forward_arrays, rays_of
from egobench.train.photometric import loss_and_grad

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


#: TrainConfig's model extensions learned with the scene, which the compiled step does not carry -> what each learns
LEARNED_EXTENSIONS = {"learn_shading": "a lens shading",
                      "learn_timing": "a timing correction (its gradient reaches the poses)",
                      "learn_frame_exposure": "a per-frame exposure correction"}


def unsupported_reason(spec: MethodSpec, backend: str, formation, config) -> str | None:
    """Why the compiled step cannot train this run of ``config`` (None: it can); the autograd path trains it then."""
    if backend != "cpu":
        return f"the rasterizer backend is {backend!r}, not the compiled CPU backend"
    if spec.pose_optimisation or spec.render_exposure_samples != 1:
        return "the method optimises poses or averages exposure samples"
    learned = next((what for flag, what in LEARNED_EXTENSIONS.items() if getattr(config, flag)), None)
    if learned is not None:
        return f"the run learns {learned}"
    if spec.formation and not _gamma_formation(formation):
        return "the formation is not the trainer's gamma exposure (exposure, vignette, no white balance)"
    return None


def _gamma_formation(formation) -> bool:
    cfg = getattr(formation, "config", None)
    return (isinstance(formation, FormationModel) and isinstance(formation.response, GammaResponse)
            and cfg.exposure_gain and cfg.vignette and not cfg.white_balance)


@dataclass
class RunInputs:
    """What every compiled step of a run reads unchanged, prepared once (`run_inputs`): the valid mask as
    rows [H, W * 3] in the parameters' dtype and as a map [H, W] (a view), its counts as the photometric loss
    (valid pixels x 3) and the normal consistency (valid pixels, at least 1) divide by them, the loss's SSIM
    weight and blur taps, the background [3], and for 2DGS the camera's rays [H, W, 3] and the regularisers'
    weights and first iterations (`egobench.train.losses.twodgs_regularisers`'s schedule)."""

    mask_rows: np.ndarray
    mask: np.ndarray
    n_mask: float
    mask_count: float
    ssim_lambda: float
    taps: np.ndarray
    background: np.ndarray
    rays: np.ndarray | None = None
    normal: tuple[float, int] = (0.0, 0)  # (weight, first iteration)
    dist: tuple[float, int] = (0.0, 0)

    def weights(self, it: int) -> tuple[float, float]:
        """The normal consistency's and the distortion's weights at iteration ``it`` (0: off)."""
        return tuple(w if w > 0 and it >= start else 0.0 for w, start in (self.normal, self.dist))


def run_inputs(mask3: Tensor, n_mask: float, config: TrainConfig, camera, surfels: bool,
               dtype: torch.dtype = torch.float32) -> RunInputs:
    """`RunInputs` of a run: mask3 [H, W, 3] (0/1) and n_mask (its sum) as the trainer holds them."""
    H, W, C = mask3.shape
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"training images must be at least {SSIM_WINDOW}x{SSIM_WINDOW} for SSIM, got {W}x{H}")
    mask = mask3[..., 0]
    taps = gaussian_taps(SSIM_WINDOW, float(SSIM_SIGMA), dtype, torch.device("cpu")).numpy()
    run = RunInputs(mask3.to(dtype).reshape(H, W * C).contiguous().numpy(), mask.numpy(), float(n_mask),
                    float(mask.sum().clamp_min(1)), float(config.ssim_lambda), taps,
                    torch.tensor(config.background, dtype=dtype).numpy())
    if surfels:
        run.rays = rays_of(camera)
        run.normal = (float(config.normal_lambda), config.normal_start_iter)
        run.dist = (float(config.dist_lambda), config.dist_start_iter)
    return run


@dataclass
class FrameTarget:
    """What one training frame is compared with, as the kernels read it: the captured image as rows
    [H, W * 3] in the parameters' dtype and the exposure scale k V per pixel [H * W]."""

    gt_rows: np.ndarray
    scale: np.ndarray


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


def frame_target(gt: Tensor, k: Tensor, vignette: Tensor, dtype: torch.dtype) -> FrameTarget:
    """The kernels' view of a frame: gt [H, W, 3] in 0..1, k (0-d), vignette [H, W]."""
    H, W, C = gt.shape
    rows = gt.detach().to(dtype).reshape(H, W * C).contiguous().numpy()
    scale = (k.to(dtype) * vignette.to(dtype)).reshape(H * W).contiguous().numpy()  # the formation's k x V
    return FrameTarget(rows, scale)


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
    expose_fwd(x, scale, np.empty_like(scale), curve, Exposed(out, dx, ds))
    return _Formed(out, dx, ds)


def _formation_backward(f: _Formed, g_pred: np.ndarray) -> np.ndarray:
    """d loss / d prediction [P, 3] -> d loss / d scene colour [P, 3]."""
    if f.ds is None:
        return g_pred * f.dx
    g_x, g_s = np.empty_like(f.dx), np.empty(f.dx.shape[0], f.dx.dtype)
    expose_bwd(g_pred, f.dx, f.ds, g_x, g_s)
    return g_x


def _normal_consistency(r: Rendered, run: RunInputs, weight: float, px: PixelGrads, tdt: torch.dtype) -> Tensor:
    """The normal consistency of the rendered depth (normalised by alpha, `ck.alpha_depth`) and normals,
    times ``weight`` -> the weighted term; its gradients join ``px`` (the summed depth's
    and the transmittance's through the alpha-depth backward, the normals')."""
    H, W = r.comp.out_T.shape[1:]
    d, t = np.ascontiguousarray(r.comp.out_feat[0, ..., ck.DEPTH_CH]).reshape(-1), r.comp.out_T.reshape(-1)
    alpha, depth = np.empty_like(t), np.empty_like(t)
    one, floor = t.dtype.type(1.0), t.dtype.type(cb.ALPHA_MIN)
    ck.alpha_depth(d, t, one, floor, alpha, depth)
    maps = RenderedMaps(depth.reshape(H, W), r.comp.out_feat[0, ..., ck.DEPTH_CH + 1:ck.DEPTH_CH + 4],
                        alpha.reshape(H, W), run.mask)
    value, inputs = nc_forward_arrays(maps, run.rays, run.mask_count)
    g = float(torch.ones((), dtype=tdt) * weight)  # autograd's upstream gradient: 1 x lambda
    g_depth, g_normal = nc_backward_arrays(inputs, run.rays, g, t.dtype, t.dtype)
    g_sum, g_trans = np.empty_like(alpha), np.empty_like(alpha)
    ck.alpha_depth_grad(d, alpha, np.empty((0,), t.dtype), g_depth.reshape(-1), floor, g_sum, g_trans)
    px.depth, px.normal = g_sum.reshape(-1, 1), g_normal.reshape(-1, 3)
    px.T = g_trans.reshape(px.T.shape) + px.T if px.T.any() else g_trans.reshape(px.T.shape)
    return weight * torch.tensor(value, dtype=tdt)


def _distortion(r: Rendered, weight: float, px: PixelGrads, tdt: torch.dtype) -> Tensor:
    """The mean depth distortion times ``weight`` -> the weighted term; its gradient
    (lambda / pixels at every pixel, as autograd's mean backward computes it) into ``px.dist``."""
    dist = torch.from_numpy(r.comp.out_feat)[..., -1][..., None]  # the autograd path's view of the distortion map
    P = r.comp.out_T.size
    px.dist = ((torch.ones((), dtype=tdt) * weight).expand(P) / P).numpy()
    return weight * dist.mean()


def _surfel_loss(loss: Tensor, r: Rendered, run: RunInputs, it: int, px: PixelGrads) -> Tensor:
    """The photometric ``loss`` plus 2DGS's regularisers at iteration ``it``, summed as `twodgs_regularisers`
    sums them."""
    total = torch.zeros((), dtype=loss.dtype)
    normal, dist = run.weights(it)
    if normal > 0:
        total = total + _normal_consistency(r, run, normal, px, loss.dtype)
    if dist > 0:
        total = total + _distortion(r, dist, px, loss.dtype)
    return loss + total


def _pixel_grads(g_rgb: np.ndarray, out_T: np.ndarray, bg: np.ndarray) -> PixelGrads:
    """The photometric loss's per-pixel gradients: the colour's, and the transmittance's through the
    background (rgb + T bg; zeros for a black one)."""
    dt = g_rgb.dtype
    g_T = (g_rgb * bg).sum(-1).reshape(out_T.shape) if bg.any() else np.zeros(out_T.shape, dt)
    return PixelGrads(g_rgb, np.empty((0, 1), dt), np.empty((0, 3), dt), np.empty((0,), dt), g_T)


def frame_step(g: Gaussians, camera, poses: Tensor, ppi: Tensor | None, spec: MethodSpec, formation,
               run: RunInputs, target: FrameTarget, it: int) -> StepOutput:
    """One training frame at iteration ``it`` through the compiled kernels: the loss, and every Gaussian
    parameter's gradient written into its ``.grad`` (replacing any). poses [K, 4, 4] camera-to-world (K
    rolling-shutter samples gathered by ``ppi`` [H, W], or one pose and ``ppi`` None)."""
    surfels = spec.splat_mode == "2dgs"
    if run.taps.dtype != cb.contiguous_numpy(g.means).dtype:
        raise ValueError(f"frame_step: the run inputs are {run.taps.dtype}, the Gaussians {g.means.dtype}; "
                         "build them with run_inputs(..., dtype=) of the parameters")
    kernel_build.ensure_built(g.means.dtype, spec.splat_mode)
    t0 = time.perf_counter()
    cb.set_threads()  # for every kernel below (`raster_setup` sets them again)
    a = activations(g)
    rendered = render_fwd(a, camera, poses, ppi, surfels)
    rgb = np.ascontiguousarray(rendered.comp.out_feat[0, ..., :ck.DEPTH_CH])
    bg = run.background
    if bg.any():  # rgb + T bg, as `composite_output`
        rgb += rendered.comp.out_T[0, ..., None] * bg
    t_fwd = time.perf_counter() - t0
    formed = _form(rgb, spec, formation, target.scale)
    H, W = camera.height, camera.width
    value, g_pred = loss_and_grad(formed.pred.reshape(H, W * 3), target.gt_rows, run.mask_rows, 3, run.n_mask,
                                   run.ssim_lambda, run.taps)
    loss = torch.tensor(value, dtype=g.means.dtype)
    px = _pixel_grads(_formation_backward(formed, g_pred.reshape(-1, 3)), rendered.comp.out_T, bg)
    if surfels:
        loss = _surfel_loss(loss, rendered, run, it, px)
    t1 = time.perf_counter()
    carrier = torch.from_numpy(rendered.m2)  # its values are unread: densification reads its gradient
    carrier.grad = render_bwd(g, a, camera, rendered, px)
    radii = cb.radius_max(torch.from_numpy(rendered.radii))
    return StepOutput(loss, torch.from_numpy(rgb), [(carrier, radii)], t_fwd, time.perf_counter() - t1)
