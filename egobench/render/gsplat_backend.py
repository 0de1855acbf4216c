"""gsplat 1.5.3 CUDA backend: `gsplat.rasterization` / `rasterization_2dgs` behind `render`'s API.

Conversions done here: egobench's integer-centred principal point becomes gsplat's cx + 0.5;
camera-to-world poses arrive already inverted (view matrices); packed=False and
render_mode="RGB+ED" (expected depth = accumulated z / alpha). gsplat works in float32, so
float64 inputs are cast (gradients flow back through the cast).

Rolling shutter on this backend is the simple form: render one image per pose sample (batched
in one gsplat call) and gather each pixel from its own sample. gsplat's kernels are fast enough
that the K-fold cost is acceptable on a GPU; the torch backend bins per (pose sample, tile).

``means2d`` in the returned RenderOutput is gsplat's own tensor (values in gsplat's pixel
convention, +0.5 from egobench's) so that ``.grad`` and ``.absgrad`` work as the gsplat
densification strategies expect; for 2DGS it is gsplat's ``gradient_2dgs`` carrier (zeros whose
gradient is the densification signal), and the projected centres are in
``extras["means2d_values"]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.render import gather_pixels
from egobench.render.torch_backend import face_camera, gsplat_K, quat_to_rotmat
from egobench.render.types import Gaussians, RenderOutput

NEAR_PLANE = 0.01
EPS2D = 0.3


def _gather(images: Tensor, index: Tensor | None) -> Tensor:
    """[K, H, W, C] -> [1, H, W, C] per-pixel pose sample (`gather_pixels`), or as is without an index."""
    return images if index is None else gather_pixels(images, index)


def _shortest_axis_normals(g: Gaussians, viewmats: Tensor) -> Tensor:
    """[C, N, 3] camera-frame unit normals (shortest axis) facing each camera."""
    R = quat_to_rotmat(g.quats)
    axis = torch.argmin(g.log_scales.detach(), dim=-1)
    n_world = torch.gather(R, 2, axis[:, None, None].expand(-1, 3, 1))[..., 0]
    R_cw, t_cw = viewmats[:, :3, :3], viewmats[:, :3, 3]
    means_c = torch.einsum("iab,nb->ina", R_cw, g.means) + t_cw[:, None, :]
    return face_camera(torch.einsum("iab,nb->ina", R_cw, n_world), means_c)


def render_gsplat(
    gaussians: Gaussians,
    camera: Pinhole,
    viewmats: Tensor,  # [B, 4, 4] T_camera_world
    *,
    pixel_pose_index: Tensor | None = None,  # [H, W] int64
    mode: str = "3dgs",
    background: Tensor | None = None,  # [3]
    want_normal: bool = False,
    tile_size: int = 16,
    absgrad: bool = False,
) -> RenderOutput:
    """Render with gsplat's CUDA kernels; same outputs as the torch backend."""
    import gsplat

    out_dtype = gaussians.means.dtype
    g = Gaussians(**{k: v.float() for k, v in gaussians.tensors().items()})
    vm = viewmats.float()
    B = vm.shape[0]
    W, H = camera.width, camera.height
    Ks = gsplat_K(camera, torch.float32, vm.device)[None].expand(B, 3, 3).contiguous()
    bg = None if background is None else background.float()
    extras: dict = {"backend": "gsplat", "tile_size": tile_size, "means2d_convention": "gsplat (+0.5)"}
    if mode == "3dgs":
        colors = g.colors
        n_extra = 0
        if want_normal:
            colors = torch.cat([colors[None].expand(B, -1, -1), _shortest_axis_normals(g, vm)], dim=-1)  # [B, N, 6]
            n_extra = 3
        backgrounds = None
        if bg is not None:
            backgrounds = torch.cat([bg, bg.new_zeros(n_extra)])[None].expand(B, -1).contiguous()
        img, alpha, meta = gsplat.rasterization(
            g.means, g.quats, g.scales, g.opacities, colors, vm, Ks, W, H,
            near_plane=NEAR_PLANE, eps2d=EPS2D, packed=False, tile_size=tile_size,
            backgrounds=backgrounds, render_mode="RGB+ED", absgrad=absgrad, rasterize_mode="classic",
        )
        rgb, depth = img[..., :3], img[..., -1:]
        normal = img[..., 3:6] if want_normal else None
        means2d = meta["means2d"]
        radii = meta["radii"]
    elif mode == "2dgs":
        backgrounds = None if bg is None else bg[None].expand(B, -1).contiguous()
        # per-view colours [B, N, 3]: gsplat 1.5.3's rasterization_2dgs does not broadcast [N, D] colours
        # (its broadcast is commented out; torch.cat with the [B, N, 1] depths would fail)
        colors_2dgs = g.colors[None].expand(B, -1, -1)
        img, alpha, normals_world, _normals_from_depth, distort, _median, meta = gsplat.rasterization_2dgs(
            g.means, g.quats, g.scales, g.opacities, colors_2dgs, vm, Ks, W, H,
            near_plane=NEAR_PLANE, packed=False, tile_size=tile_size, backgrounds=backgrounds,
            render_mode="RGB+ED", absgrad=absgrad, distloss=True,
        )
        rgb, depth = img[..., :3], img[..., -1:]
        # gsplat rotates the accumulated normals to world; egobench returns them in camera frame
        normal = torch.einsum("bij,bhwj->bhwi", vm[:, :3, :3], normals_world)
        extras["distortion"] = distort
        extras["means2d_values"] = meta["means2d"]
        means2d = meta["gradient_2dgs"]
        radii = meta["radii"]
    else:
        raise ValueError(f"render_gsplat: mode must be '3dgs' or '2dgs', got {mode!r}")
    radii = radii.amax(-1) if radii.ndim == 3 else radii
    idx = None if pixel_pose_index is None else pixel_pose_index.to(vm.device).long()
    if idx is not None and "distortion" in extras:
        extras["distortion"] = _gather(extras["distortion"], idx)
    cast = (lambda t: t.to(out_dtype)) if out_dtype != torch.float32 else (lambda t: t)
    if "distortion" in extras:
        extras["distortion"] = cast(extras["distortion"])
    return RenderOutput(
        rgb=cast(_gather(rgb, idx)), alpha=cast(_gather(alpha, idx)), depth=cast(_gather(depth, idx)),
        normal=None if normal is None else cast(_gather(normal, idx)),
        means2d=means2d, radii=radii, extras=extras,
    )
