"""2DGS (surfels) in the compiled CPU backend: the autograd glue of `egobench.render.cpu.surfels`, with the
semantics of torch_backend.py's 2DGS path (checked against it in tests/render/test_render_cpu_2dgs.py).

Outputs: colour, alpha, depth, camera-frame normals, the depth distortion map
(``extras["distortion"]``), radii, the projected centres (``extras["means2d_values"]``, with
``absgrad``) and gsplat's ``gradient_2dgs`` densification carrier as ``means2d``; gradients of every
surfel parameter and of the poses; rolling shutter through ``pixel_pose_index``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.render import cpu as ck
from egobench.render import cpu_backend as cb
from egobench.render.cpu import surfels as k2
from egobench.render.types import Gaussians, RenderOutput


class _Project2DGS(torch.autograd.Function):
    """(means, quats, scales, viewmats) -> means2d [I,N,2] (gsplat pixels minus ``pixel_offset``: 0.5 gives
    egobench's), ray transforms [I,N,9], depths [I,N], normals [I,N,3]; radii [I,N,2] int32 (not differentiable)."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, cam, width, height, pixel_offset=0.0):
        I, N = viewmats.shape[0], means.shape[0]
        dt = cb.contiguous_numpy(means).dtype
        m2, tsl = np.empty((I, N, 2), dt), np.empty((I, N, 9), dt)
        dep, nrm = np.empty((I, N), dt), np.empty((I, N, 3), dt)
        rad = np.empty((I, N, 2), dtype=np.int32)
        cb.set_threads()
        splats = ck.Splats(cb.contiguous_numpy(means), cb.contiguous_numpy(quats), cb.contiguous_numpy(scales))
        k2.project_fwd_2dgs(splats, cb.view_args(cb.contiguous_numpy(viewmats), cam, width, height),
                            ck.ProjectedSurfels(m2, tsl, dep, rad, nrm))
        ctx.save_for_backward(means, quats, scales, viewmats)
        ctx.cam, ctx.image_size = cam, (width, height)
        if pixel_offset:
            m2 -= pixel_offset  # in the compute dtype, as torch would subtract it
        radii = torch.from_numpy(rad)
        ctx.mark_non_differentiable(radii)
        return (*[torch.from_numpy(a) for a in (m2, tsl, dep, nrm)], radii)

    @staticmethod
    def backward(ctx, g_m2, g_tsl, g_dep, g_nrm, _g_radii):
        means, quats, scales, viewmats = ctx.saved_tensors
        I, N = viewmats.shape[0], means.shape[0]

        dt_np = cb.contiguous_numpy(means).dtype
        grads = tuple(cb.upstream_grad(g, shape, dt_np) for g, shape in
                      ((g_m2, (I, N, 2)), (g_tsl, (I, N, 9)), (g_dep, (I, N)), (g_nrm, (I, N, 3))))
        gm, gq, gs = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
        gv_parts = np.zeros((max(1, math.ceil(N / k2.CHUNK)), I, 12))
        cb.set_threads()
        splats = ck.Splats(*(cb.contiguous_numpy(t).astype(np.float64) for t in (means, quats, scales)))
        view = cb.view_args(cb.contiguous_numpy(viewmats).astype(np.float64), ctx.cam, *ctx.image_size)
        k2.project_bwd_2dgs(splats, view, ck.ProjectedSurfelGrads(*grads), ck.SplatGrads(gm, gq, gs, gv_parts))
        dt = means.dtype
        gv = cb.pose_grad(gv_parts, dt) if ctx.needs_input_grad[3] else None
        return (torch.from_numpy(gm).to(dt), torch.from_numpy(gq).to(dt), torch.from_numpy(gs).to(dt), gv,
                None, None, None, None)


class _Rasterize2DGS(torch.autograd.Function):
    """(means2d (egobench pixels), ray transforms [I,N,9], log_opacity,
    colors, depths, normals) -> sums of w rgb [Iout,H,W,3], w depth [Iout,H,W,1] and w normal [Iout,H,W,3]
    (`feature_outputs`), transmittance [Iout,H,W], distortion [Iout,H,W].
    ``carrier`` [I,N,2] (or None): gsplat's gradient_2dgs leaf; it does not change the output and
    gets (dL/dM[0, 2], dL/dM[1, 2]) M[2, 2], as torch_backend.densify_carrier_2dgs would give it."""

    @staticmethod
    def forward(ctx, means2d, tsl, log_opac, colors, depths, normals, radii, pix_view, bin_needed, tile_size,
                absgrad_target, carrier):
        I, N = depths.shape
        m2 = cb.gsplat_pixels(means2d)
        st = cb.raster_setup(m2, radii, depths, colors, normals, pix_view, bin_needed, tile_size)
        c = cb.composite_fwd(st, pix_view, tile_size, m2, cb.contiguous_numpy(log_opac), tsl=cb.contiguous_numpy(tsl))
        ctx.state = (c, st, pix_view, tile_size, absgrad_target)
        ctx.shapes = (I, N, colors.dtype)
        ctx.set_materialize_grads(False)  # unused outputs: zeros written here, not allocated by autograd
        Cf, feat = st.feats.shape[1], torch.from_numpy(c.out_feat)
        return (*cb.feature_outputs(c.out_feat[..., :Cf]), torch.from_numpy(c.out_T), feat[..., Cf])

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_normal, g_T, g_dist):
        c, st, pix_view, ts, ab = ctx.state
        I, N, dt = ctx.shapes
        Cf = st.feats.shape[1]
        g_state = cb.pixel_grads(Cf + 2, c.out_T, g_rgb, g_depth, g_normal, g_dist, c.out_feat)  # + 2 dL/d dist, depth
        gT = np.zeros(c.out_T.shape, c.out_T.dtype) if g_T is None else cb.contiguous_numpy(g_T)
        isect = cb.composite_bwd(c, st, pix_view, ts, g_state, gT)
        per = cb.reduce_intersections(isect, st.flat_ids, I, N, dt, ab)
        f0 = 12  # the features' first channel: colour, depth, normal
        g_carrier = None
        if ctx.needs_input_grad[11]:  # gsplat's gradient_2dgs: (dL/dM[0, 2], dL/dM[1, 2]) * M[2, 2]
            # from rows 4 and 7 of the channel-first block, in the carrier's own layout (no copy by autograd)
            g_carrier = torch.from_numpy(carrier_grad(per.permute(2, 0, 1).reshape(per.shape[2], I * N).numpy(), c.tsl))
        return (per[..., 0:2], per[..., 2:11], per[..., 11].sum(0), cb.pose_sums(per, f0, f0 + 3), per[..., f0 + 3],
                per[..., f0 + 4:f0 + 7], None, None, None, None, None, g_carrier)


def carrier_grad(per_cf: np.ndarray, tsl: np.ndarray) -> np.ndarray:
    """gsplat's gradient_2dgs carrier [I, N, 2], (dL/dM[0, 2], dL/dM[1, 2]) M[2, 2], from the channel-first
    intersection sums [C, I * N] (rows 4 and 7: the ray transforms' translation column) and the ray transforms
    tsl [I, N, 9]."""
    I, N = tsl.shape[:2]
    carrier = np.empty((I, N, 2), per_cf.dtype)
    k2.carrier_grad(per_cf[4], per_cf[7], tsl.reshape(I * N, 9), carrier.reshape(I * N, 2))
    return carrier


def render_cpu_2dgs(gaussians: Gaussians, camera: Pinhole, viewmats: Tensor, *, pixel_pose_index: Tensor | None,
                    background: Tensor | None, tile_size: int, absgrad: bool) -> RenderOutput:
    """2DGS render with the compiled kernels; same contract as the torch path of `render` for
    mode="2dgs". viewmats [I, 4, 4] world-to-camera; pixel_pose_index [H, W] or None."""
    cb.prepare_kernels(gaussians.means.dtype, "2dgs")
    H, W = camera.height, camera.width
    I = viewmats.shape[0]
    means2d_out, tsl, depths, normals, radii = _Project2DGS.apply(  # means2d_out: egobench's pixels
        gaussians.means, gaussians.quats, gaussians.scales, viewmats, cb.camera_array(camera), W, H,
        cb.GSPLAT_PIXEL_OFFSET)
    # gsplat's gradient_2dgs carrier (torch_backend.densify_carrier_2dgs: zeros added to the ray transforms'
    # translation column), its gradient given by the rasterizer's backward rather than by torch ops on [I, N, 3, 3]
    carrier = torch.zeros((I, means2d_out.shape[1], 2), dtype=tsl.dtype, requires_grad=True) if tsl.requires_grad else None
    if carrier is None and means2d_out.requires_grad:  # with a carrier nothing reads this gradient
        means2d_out.retain_grad()
    ts = int(tile_size)
    pix_view, bin_needed = cb.pixel_views(pixel_pose_index, I, H, W, ts)
    holder = [means2d_out] if absgrad and means2d_out.requires_grad else None
    rgb_sum, depth_sum, normal, trans, dist = _Rasterize2DGS.apply(
        means2d_out, tsl, F.logsigmoid(gaussians.opacity_logits), gaussians.colors, depths, normals, radii, pix_view,
        bin_needed, ts, holder, carrier)
    rgb, alpha, depth = cb.composite_output(rgb_sum, depth_sum, trans, background)
    extras = {"backend": "cpu", "tile_size": ts, "distortion": dist[..., None]}
    means2d = means2d_out
    if carrier is not None:  # as the torch and gsplat backends: means2d carries gsplat's gradient_2dgs
        extras["means2d_values"] = means2d_out
        means2d = carrier
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, means2d=means2d,
                        radii=cb.radius_max(radii), extras=extras)
