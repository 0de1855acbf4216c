"""The compiled training step's render (`egobench.train.cpu_step`): the compiled CPU backend's kernels for 3DGS
and 2DGS called in order, forward and backward, without autograd. The same kernels and inputs as
`egobench.render.cpu_backend` and `cpu_backend_2dgs` behind their custom Functions, so the same bits; what
the Functions' wrappers did between the kernels is done here once, with each upstream gradient in the
layout the next kernel reads (the intersection gradients channel first from the rasterizer's reduction to
the projection's backward), and the parameters' gradients are written into their ``.grad``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from egobench.render import cpu_backend as cb
from egobench.render import cpu_backend_2dgs as cb2
from egobench.render import world_to_camera
from egobench.render.cpu_backend import ck
from egobench.render.cpu import surfels as k2
from egobench.render.types import Gaussians


@dataclass
class Activations:
    """The Gaussians as the kernels read them (views of the parameters where the dtype allows): means,
    quats, linear scales, log-opacity, opacity and colours; the torch tensors the activations' backwards
    read (the scales, the opacity logits and log-sigmoid's buffer)."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    log_opac: np.ndarray
    opac: np.ndarray
    colors: np.ndarray
    scales_t: Tensor
    logits_t: Tensor
    log_sigmoid_buffer: Tensor


def activations(g: Gaussians) -> Activations:
    """The activations the render applies (exp of the log-scales, log-sigmoid of the opacity logits), in
    torch's own ops: the autograd path's bits."""
    scales = torch.exp(g.log_scales.detach())
    logits = g.opacity_logits.detach()
    log_opac, buffer = torch.ops.aten.log_sigmoid_forward(logits)
    np_of = cb.contiguous_numpy
    return Activations(np_of(g.means), np_of(g.quats), scales.numpy(), log_opac.numpy(), log_opac.exp().numpy(),
                       np_of(g.colors), scales, logits, buffer)


@dataclass
class Rendered:
    """What the forward keeps for the backward: the projection (m2 [I, N, 2] in gsplat's pixels, radii
    [I, N, 2] int32), the binning, and the compositing (`cb.Composited`: ``out_feat`` [1, H, W, C], the summed
    colour, depth (and normal), 2DGS's distortion last; ``tsl`` [I, N, 9], 2DGS's ray transforms)."""

    viewmats: np.ndarray
    m2: np.ndarray
    radii: np.ndarray
    setup: cb.RasterSetup
    pix_view: np.ndarray
    comp: cb.Composited

    @property
    def surfels(self) -> bool:
        return self.comp.tsl is not None


def render_fwd(a: Activations, camera, poses: Tensor, ppi: Tensor | None, surfels: bool) -> Rendered:
    """`render_cpu`'s (``surfels``: `render_cpu_2dgs`'s) forward: poses [K, 4, 4] camera-to-world, K pose
    samples gathered by ``ppi`` [H, W] (or one pose and None) -> `Rendered`."""
    H, W, dt = camera.height, camera.width, a.means.dtype
    viewmats = cb.contiguous_numpy(world_to_camera(poses.to(a.scales_t.dtype)))
    I, N = viewmats.shape[0], a.means.shape[0]
    m2, dep, rad = np.empty((I, N, 2), dt), np.empty((I, N), dt), np.empty((I, N, 2), np.int32)
    view, splats = cb.view_args(viewmats, cb.camera_array(camera), W, H), ck.Splats(a.means, a.quats, a.scales)
    if surfels:
        tsl, nrm, con = np.empty((I, N, 9), dt), np.empty((I, N, 3), dt), None
        k2.project_fwd_2dgs(splats, view, ck.ProjectedSurfels(m2, tsl, dep, rad, nrm))
    else:
        tsl, nrm, con = None, np.zeros((I, 0, 3), dt), np.empty((I, N, 3), dt)
        ck.project_fwd(splats, a.opac, view, False, ck.Projected(m2, con, dep, rad, nrm))
    m2 -= cb.GSPLAT_PIXEL_OFFSET  # egobench's pixels and back, as the autograd path's carrier (the same bits)
    m2 += m2.dtype.type(cb.GSPLAT_PIXEL_OFFSET)
    ts, from_np = cb.DEFAULT_TILE, torch.from_numpy
    pix_view, bin_needed = cb.pixel_views(ppi, I, H, W, ts)
    st = cb.raster_setup(m2, from_np(rad), from_np(dep), from_np(a.colors), from_np(nrm), pix_view, bin_needed, ts)
    comp = cb.composite_fwd(st, pix_view, ts, m2, a.log_opac, conics=con, radii=rad, tsl=tsl)
    return Rendered(viewmats, m2, rad, st, pix_view, comp)


@dataclass
class PixelGrads:
    """d loss / d the render's per-pixel outputs, [H, W] images flattened to rows of P pixels; an array with
    no rows: no loss read that output. rgb [P, 3], depth [P, 1] (the summed depth), normal [P, 3],
    dist [P] (2DGS's distortion), T [1, H, W] (the transmittance; zeros when none)."""

    rgb: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    dist: np.ndarray
    T: np.ndarray


def _isect_grads(r: Rendered, px: PixelGrads) -> np.ndarray:
    """The rasterizer's backward -> per (image, Gaussian) sums, channel first [C, I, N]."""
    st, c, (I, N) = r.setup, r.comp, r.m2.shape[:2]
    dt, P = c.out_T.dtype, c.out_T.size
    n_in = st.feats.shape[1] + (2 if r.surfels else 0)  # 2DGS: + 2 dL/d distortion and the forward's depth
    g_state = np.empty((P, n_in), dt)
    fwd = c.out_feat.reshape(P, -1) if r.surfels else np.empty((0, 0), dt)
    ck.pack_pixel_grads(g_state, px.rgb, px.depth, px.normal, px.dist, fwd)
    isect = cb.composite_bwd(c, st, r.pix_view, cb.DEFAULT_TILE, g_state.reshape(c.out_T.shape + (n_in,)), px.T)
    return cb.intersection_sums(isect, st.flat_ids, I * N, dt).reshape(-1, I, N)


def render_bwd(g: Gaussians, a: Activations, camera, r: Rendered, px: PixelGrads) -> Tensor:
    """The render's backward: every Gaussian parameter's ``.grad`` (replaced) from the per-pixel gradients;
    returns the densification carrier's gradient [I, N, 2] (3DGS: d loss / d means2d; 2DGS: gsplat's
    gradient_2dgs, (dL/dM[0, 2], dL/dM[1, 2]) M[2, 2])."""
    per = _isect_grads(r, px)
    I, N = r.m2.shape[:2]
    c = 12 if r.surfels else 6  # the colour's first channel
    g_colors = np.empty((N, 3), per.dtype)
    ck.ordered_sum(per[c:c + 3], g_colors)
    gm, gq, gs = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
    grads = ck.SplatGrads(gm, gq, gs, np.zeros((max(1, math.ceil(N / ck.CHUNK)), I, 12)))
    wide = ck.Splats(*(x.astype(np.float64) for x in (a.means, a.quats, a.scales)))
    view = cb.view_args(r.viewmats.astype(np.float64), cb.camera_array(camera), camera.width, camera.height)
    if r.surfels:
        k2.project_bwd_2dgs(wide, view, ck.ProjectedSurfelGrads(per[0:2], per[2:11], per[c + 3], per[c + 4:c + 7]),
                            grads)
        g_carrier = torch.from_numpy(cb2.carrier_grad(per.reshape(per.shape[0], I * N), r.comp.tsl))
    else:
        ck.project_bwd(wide, view, False, ck.ProjectedGrads(per[0:2], per[2:5], per[9], np.zeros((3, I, 0), per.dtype)),
                       grads)
        g_carrier = torch.from_numpy(per[0:2]).permute(1, 2, 0)
    _write_grads(g, a, gm, gq, gs, per[c - 1], g_colors)
    return g_carrier


def _write_grads(g: Gaussians, a: Activations, gm, gq, gs, g_log_opac: np.ndarray, g_colors: np.ndarray) -> None:
    """The projection's float64 gradients rounded to the parameters' dtype, chained through the activations
    (exp: times the scales; log-sigmoid: its own backward, the poses' sum first), into ``.grad``."""
    tdt = a.scales_t.dtype
    g.means.grad = torch.from_numpy(gm).to(tdt)
    g.quats.grad = torch.from_numpy(gq).to(tdt)
    g.log_scales.grad = torch.from_numpy(gs).to(tdt) * a.scales_t
    g.opacity_logits.grad = torch.ops.aten.log_sigmoid_backward(torch.from_numpy(g_log_opac).sum(0), a.logits_t,
                                                                 a.log_sigmoid_buffer)
    g.colors.grad = torch.from_numpy(g_colors)
