"""Differentiable Gaussian rasterization behind one function, `render`.

Backends: ``torch`` (egobench/render/torch_backend.py, pure torch, CPU or CUDA, gsplat 1.5.3
semantics: the oracle), ``gsplat`` (gsplat 1.5.3 CUDA kernels, egobench/render/gsplat_backend.py)
and ``cpu`` (compiled numba kernels, egobench/render/cpu_backend.py; 3DGS and 2DGS).
``backend="auto"`` picks gsplat when the inputs are on CUDA and gsplat's CUDA extension loads, and
cpu for CPU tensors when numba loads (else torch, with a one-line reason on stderr).
"""

from __future__ import annotations

import functools
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.render.types import Gaussians, RenderOutput, SplatMode

__all__ = ["render", "render_rolling_shutter_reference", "Gaussians", "RenderOutput", "gsplat_cuda_available",
           "resolve_backend"]

Backend = Literal["auto", "torch", "gsplat", "cpu"]


@functools.lru_cache(maxsize=1)
def gsplat_cuda_available() -> bool:
    """True when CUDA is present and gsplat's CUDA extension can be loaded."""
    if not torch.cuda.is_available():
        return False
    try:
        from gsplat.cuda._backend import _C  # noqa: F401

        return _C is not None
    except Exception:  # ImportError, build failure: fall back to the torch backend
        return False


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """The backend `render(backend=...)` uses for tensors on ``device``: "gsplat", "cpu" or "torch".
    (Loading gsplat's CUDA extension the first time may JIT-compile it: minutes.) "cpu" (or "auto" on
    the CPU) falls back to "torch" with a one-line reason on stderr when numba cannot be loaded."""
    if backend not in ("auto", "torch", "gsplat", "cpu"):
        raise ValueError(f"render: backend must be 'auto', 'torch', 'gsplat' or 'cpu', got {backend!r}")
    on_cpu = torch.device(device).type == "cpu"
    gsplat_ok = not on_cpu and torch.device(device).type == "cuda" and gsplat_cuda_available()
    if backend == "gsplat" and not gsplat_ok:
        raise ValueError("render: backend='gsplat' needs CUDA tensors and gsplat 1.5.3's CUDA extension")
    if backend == "cpu" and not on_cpu:
        raise ValueError(f"render: backend='cpu' needs CPU tensors, got device {torch.device(device)}")
    if backend == "cpu" or (backend == "auto" and on_cpu):
        from egobench.render import cpu_backend

        reason = cpu_backend.load_error()
        if reason is None:
            return "cpu"
        cpu_backend.warn_fallback(reason)
        return "torch"
    if backend == "auto":
        return "gsplat" if gsplat_ok else "torch"
    return backend


_GAUSSIAN_TENSORS = ("means", "quats", "log_scales", "opacity_logits", "colors")


def _gaussians_valid(g: Gaussians) -> bool:
    """Every tensor finite and no zero quaternion: compiled passes on the CPU (`egobench.render.finite`);
    elsewhere one host sync, where a NaN or inf entry makes a sum NaN or inf (a tenth of the cost of
    isfinite(t).all()) and a sum that overflows from finite entries answers False."""
    from egobench.render.finite import all_finite, has_zero_row  # numba: loaded when a render needs it

    tensors = [getattr(g, name).detach() for name in _GAUSSIAN_TENSORS]
    quats = tensors[1]
    if quats.device.type == "cpu" and quats.dtype in (torch.float32, torch.float64):
        return all_finite(tensors) and not has_zero_row(quats)
    checks = [torch.isfinite(t.sum()) for t in tensors]
    checks.append(~((quats * quats).sum(-1) == 0).any())
    return bool(torch.stack(checks).all())


def _check_gaussians(g: Gaussians) -> int:
    if not isinstance(g, Gaussians):
        raise ValueError(f"render: gaussians must be an egobench.render.types.Gaussians, got {type(g).__name__}")
    means = g.means
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"render: gaussians.means must have shape [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    expected = {"quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,), "colors": (n, 3)}
    for name, shape in expected.items():
        t = getattr(g, name)
        if not isinstance(t, Tensor) or tuple(t.shape) != shape:
            got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"render: gaussians.{name} must have shape {list(shape)} (N = {n}), got {got}")
        if t.dtype != means.dtype or t.device != means.device:
            raise ValueError(f"render: gaussians.{name} must have the dtype/device of means ({means.dtype}, {means.device}), "
                             f"got {t.dtype}, {t.device}")
    if not means.dtype.is_floating_point:
        raise ValueError(f"render: gaussians.means must be a floating-point tensor, got {means.dtype}")
    if not _gaussians_valid(g):  # name the culprit only on failure
        for name in _GAUSSIAN_TENSORS:
            if not bool(torch.isfinite(getattr(g, name).detach()).all()):  # (not: a sum that overflowed)
                raise ValueError(f"render: gaussians.{name} must be finite (no NaN/inf)")
        from egobench.render.finite import has_zero_row

        if has_zero_row(g.quats):
            raise ValueError("render: gaussians.quats must be non-zero quaternions (w, x, y, z); found a zero quaternion")
    return n


def _check_poses(T_world_camera: Tensor, means: Tensor) -> Tensor:
    if not isinstance(T_world_camera, Tensor):
        raise ValueError("render: T_world_camera must be a tensor of shape [4, 4] or [B, 4, 4]")
    T = T_world_camera
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] == 0:
        raise ValueError(f"render: T_world_camera must have shape [4, 4] or [B, 4, 4] with B >= 1, got {tuple(T_world_camera.shape)}")
    host = T.detach().to(torch.float64).cpu().numpy()  # [B, 4, 4]: one copy (one sync on a GPU), checked there
    if not np.isfinite(host).all():
        raise ValueError("render: T_world_camera must be finite (no NaN/inf) camera-to-world poses")
    if not np.allclose(host[:, 3, :], [0.0, 0.0, 0.0, 1.0], rtol=1e-5, atol=1e-6):  # torch.allclose's rule
        raise ValueError("render: T_world_camera must be homogeneous rigid transforms (last row [0, 0, 0, 1])")
    return T.to(device=means.device, dtype=means.dtype)


def world_to_camera(T_world_camera: Tensor) -> Tensor:
    """Camera-to-world [B, 4, 4] -> world-to-camera [B, 4, 4] (rigid inverse, differentiable)."""
    R = T_world_camera[:, :3, :3]
    t = T_world_camera[:, :3, 3]
    Rt = R.transpose(1, 2)
    top = torch.cat([Rt, -(Rt @ t[:, :, None])], dim=2)  # [B, 3, 4]
    bottom = torch.zeros_like(T_world_camera[:, 3:, :])
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=1)


def render(
    gaussians: Gaussians,
    camera: Pinhole,
    T_world_camera: Tensor,  # [4, 4] or [B, 4, 4] camera-to-world, OpenCV axes
    *,
    pixel_pose_index: Tensor | None = None,  # [H, W] int64 in 0..B-1: rolling shutter, one image
    mode: SplatMode = "3dgs",
    background: Tensor | None = None,  # [3]
    backend: Backend = "auto",
    want_normal: bool = False,
    tile_size: int | None = None,
    absgrad: bool = False,
) -> RenderOutput:
    """Render Gaussians into B images, or into one rolling-shutter image.

    Without ``pixel_pose_index``: B images, one per pose. With it: one image ([1, H, W, ...])
    whose pixel (v, u) is composited entirely under pose ``pixel_pose_index[v, u]``; means2d and
    radii then hold one row per pose sample ([B, N, 2], [B, N]).
    Colours are used as given (no clamping); rgb = sum w c + background * (1 - alpha);
    depth = sum w z / alpha (0 where alpha = 0); normal (2DGS, or 3DGS with want_normal) is the
    alpha-weighted camera-frame normal facing the camera. 2DGS puts the depth-distortion map in
    ``extras["distortion"]`` ([B, H, W, 1]).
    ``tile_size`` does not change 3DGS results (the opacity-aware radius bounds every pixel with
    alpha >= 1/255). None picks the fastest measured size: 16 on CUDA (gsplat's), 4 for the torch
    backend on CPU (about 2x faster there than 16), 16 for the compiled cpu backend.
    The cpu backend renders float32 and float64; for other dtypes it hands the call to the torch
    backend and says so in ``extras["cpu_fallback"]``.
    """
    if mode not in ("3dgs", "2dgs"):
        raise ValueError(f"render: mode must be '3dgs' or '2dgs', got {mode!r}")
    if not isinstance(camera, Pinhole):
        raise ValueError(f"render: camera must be an egobench.camera.pinhole.Pinhole, got {type(camera).__name__}")
    n = _check_gaussians(gaussians)
    means = gaussians.means
    chosen, cpu_fallback, tile_size = _choose_backend(backend, mode, means, tile_size)
    T = _check_poses(T_world_camera, means)
    B = T.shape[0]
    H, W = camera.height, camera.width
    background = _check_background(background, means)
    if pixel_pose_index is not None:
        pixel_pose_index = _check_pixel_pose_index(pixel_pose_index, H, W, B, means.device)

    if n == 0:
        return _empty_output(B if pixel_pose_index is None else 1, H, W, means, background, mode, want_normal)
    viewmats = world_to_camera(T)
    if chosen == "gsplat":
        from egobench.render import gsplat_backend

        return gsplat_backend.render_gsplat(gaussians, camera, viewmats, pixel_pose_index=pixel_pose_index,
                                            mode=mode, background=background, want_normal=want_normal,
                                            tile_size=tile_size, absgrad=absgrad)
    if chosen == "cpu" and mode == "2dgs":
        from egobench.render import cpu_backend_2dgs

        return cpu_backend_2dgs.render_cpu_2dgs(gaussians, camera, viewmats, pixel_pose_index=pixel_pose_index,
                                                background=background, tile_size=tile_size, absgrad=absgrad)
    if chosen == "cpu":
        from egobench.render import cpu_backend

        return cpu_backend.render_cpu(gaussians, camera, viewmats, pixel_pose_index=pixel_pose_index,
                                      background=background, want_normal=want_normal, tile_size=tile_size,
                                      absgrad=absgrad)
    from egobench.render import torch_backend

    res = torch_backend.rasterize(
        means, gaussians.quats, gaussians.scales, F.logsigmoid(gaussians.opacity_logits), gaussians.colors,
        viewmats, camera, mode=mode, pixel_pose_index=pixel_pose_index, want_normal=want_normal,
        tile_size=tile_size, absgrad=absgrad,
    )
    return _torch_output(res, background, mode, tile_size, cpu_fallback)


def _choose_backend(backend: str, mode: str, means: Tensor, tile_size: int | None) -> tuple[str, str | None, int]:
    """-> (backend that renders, why the cpu backend handed over to torch or None, tile size in pixels)."""
    chosen = resolve_backend(backend, means.device)
    cpu_fallback = None
    if chosen == "cpu":
        from egobench.render import cpu_backend

        cpu_fallback = cpu_backend.unsupported_reason(mode, means.dtype)
        if cpu_fallback is not None:
            chosen = "torch"
    if tile_size is None:
        tile_size = 16 if (means.is_cuda or chosen == "cpu") else 4
    if int(tile_size) != tile_size or tile_size <= 0:
        raise ValueError(f"render: tile_size must be a positive integer, got {tile_size}")
    return chosen, cpu_fallback, int(tile_size)


def _check_background(background: Tensor | None, means: Tensor) -> Tensor | None:
    """background [3] (or None) -> on the dtype/device of means."""
    if background is None:
        return None
    if not isinstance(background, Tensor) or tuple(background.shape) != (3,):
        raise ValueError(f"render: background must be a tensor of shape [3], got "
                         f"{tuple(background.shape) if isinstance(background, Tensor) else type(background).__name__}")
    if not bool(torch.isfinite(background).all()):
        raise ValueError("render: background must be finite")
    return background.to(device=means.device, dtype=means.dtype)


def _check_pixel_pose_index(idx: Tensor, H: int, W: int, B: int, device: torch.device) -> Tensor:
    """pixel_pose_index [H, W] integers in 0..B-1 -> int64 on `device`."""
    if not isinstance(idx, Tensor) or tuple(idx.shape) != (H, W):
        raise ValueError(f"render: pixel_pose_index must have shape [H, W] = [{H}, {W}], got "
                         f"{tuple(idx.shape) if isinstance(idx, Tensor) else type(idx).__name__}")
    if idx.dtype.is_floating_point or idx.dtype == torch.bool or idx.is_complex():
        raise ValueError(f"render: pixel_pose_index must be an integer tensor (int64), got {idx.dtype}")
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= B):
        raise ValueError(f"render: pixel_pose_index values must lie in 0..{B - 1} (B = {B} poses), "
                         f"got range {int(idx.min())}..{int(idx.max())}")
    return idx.to(device=device, dtype=torch.long)


def _torch_output(res, background: Tensor | None, mode: str, tile_size: int, cpu_fallback: str | None) -> RenderOutput:
    """torch_backend.RasterResult -> RenderOutput (background, normalised depth, 2DGS extras)."""
    feats, trans = res.features, res.transmittance[..., None]
    alpha = 1.0 - trans
    rgb = feats[..., :3]
    if background is not None:
        rgb = rgb + trans * background
    depth = feats[..., 3:4] / alpha.clamp(min=1e-10)
    normal = feats[..., 4:7] if feats.shape[-1] >= 7 else None
    radii = res.projection.radii.amax(-1)
    extras = {"backend": "torch", "tile_size": tile_size}
    if cpu_fallback is not None:
        extras["cpu_fallback"] = cpu_fallback
    means2d = res.means2d
    if mode == "2dgs":
        extras["distortion"] = res.distortion[..., None]
        if res.densify_2dgs is not None:  # as the gsplat backend: means2d carries gsplat's gradient_2dgs
            extras["means2d_values"] = res.means2d
            means2d = res.densify_2dgs
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, means2d=means2d, radii=radii, extras=extras)


def _empty_output(b, H, W, means, background, mode, want_normal) -> RenderOutput:
    z = means.new_zeros(b, H, W, 1)
    rgb = means.new_zeros(b, H, W, 3) + (background if background is not None else 0.0)
    normal = means.new_zeros(b, H, W, 3) if (mode == "2dgs" or want_normal) else None
    extras = {"distortion": z.clone()} if mode == "2dgs" else {}
    return RenderOutput(rgb=rgb, alpha=z, depth=z.clone(), normal=normal, means2d=means.new_zeros(b, 0, 2),
                        radii=torch.zeros(b, 0, dtype=torch.int32, device=means.device), extras=extras)


def gather_pixels(images: Tensor, pixel_pose_index: Tensor) -> Tensor:
    """images [K, H, W, C], index [H, W] -> [1, H, W, C] with pixel (v, u) from image index[v, u]."""
    K, H, W, C = images.shape
    idx = pixel_pose_index.to(images.device).long()[None, :, :, None].expand(1, H, W, C)
    return torch.gather(images, 0, idx)


def render_rolling_shutter_reference(
    gaussians: Gaussians,
    camera: Pinhole,
    T_world_camera: Tensor,  # [K, 4, 4]
    pixel_pose_index: Tensor,  # [H, W] int64 in 0..K-1
    **kwargs,
) -> RenderOutput:
    """The simple (K-fold cost) oracle: render K global-shutter images, then gather per pixel."""
    out = render(gaussians, camera, T_world_camera, **kwargs)
    g = functools.partial(gather_pixels, pixel_pose_index=pixel_pose_index)
    extras = dict(out.extras or {})
    if "distortion" in extras:
        extras["distortion"] = g(extras["distortion"])
    return RenderOutput(rgb=g(out.rgb), alpha=g(out.alpha), depth=g(out.depth),
                        normal=None if out.normal is None else g(out.normal),
                        means2d=out.means2d, radii=out.radii, extras=extras)
