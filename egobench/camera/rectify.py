"""Rectification of a (fisheye) source camera into a pinhole camera by an inverse warp.

For every destination pixel: unproject in the pinhole camera, rotate into the source camera
(``R_src_dst``), project with the source model. The resulting source coordinates ``map_uv``
resample images (bilinear), index images (nearest), the vignette and the row-time ratio
``R(u) = src row / (H_src - 1)`` (paper Eq. 4), which becomes non-linear in the rectified image.
Pixel centres are at integer coordinates in both cameras, which is exactly
``grid_sample(align_corners=True)`` with ``x_norm = 2 u / (W - 1) - 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench import portable_math as pm
from egobench.camera.base import CameraModel
from egobench.camera.pinhole import Pinhole

#: Paper: 2880 x 2880 fisheye rectified to 2400 x 2400 pinhole with f = 1200.
PAPER_RECTIFIED_SIZE_RATIO = 2400 / 2880
PAPER_FOCAL_PER_WIDTH = 0.5


def default_pinhole_for(
    src: CameraModel, width: int | None = None, height: int | None = None, focal: float | None = None
) -> Pinhole:
    """Pinhole with the paper's proportions: size = src size * 2400/2880, f = width / 2, centred."""
    width = round(src.width * PAPER_RECTIFIED_SIZE_RATIO) if width is None else int(width)
    height = round(src.height * PAPER_RECTIFIED_SIZE_RATIO) if height is None else int(height)
    focal = PAPER_FOCAL_PER_WIDTH * width if focal is None else float(focal)
    return Pinhole(fx=focal, fy=focal, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)


def readout_range(readout_rows: tuple[int, int] | None, height: int) -> tuple[int, int]:
    """(first, last) raw row a rolling shutter reads: ``readout_rows``, or every row of ``height``."""
    return (0, height - 1) if readout_rows is None else (int(readout_rows[0]), int(readout_rows[1]))


@dataclass
class Rectification:
    """An inverse warp from ``src`` to the pinhole ``dst`` (build it with ``Rectification.build``)."""

    src: CameraModel  # source (raw, distorted) camera
    dst: Pinhole  # destination (rectified) camera
    R_src_dst: Tensor  # [3, 3] float64 rotation from dst camera coordinates to src camera coordinates
    map_uv: Tensor  # [H, W, 2] float32 source pixel (u, v) sampled by each destination pixel
    valid: Tensor  # [H, W] bool: in front of src, inside the src image, and a valid src projection

    @classmethod
    def build(cls, src: CameraModel, dst: Pinhole, R_src_dst: Tensor | np.ndarray | None = None) -> "Rectification":
        """Compute the warp map (float64 inside, stored float32)."""
        if not isinstance(dst, Pinhole):
            raise ValueError(f"Rectification.build(dst): expected a Pinhole camera, got {type(dst).__name__}")
        for attr in ("width", "height", "project"):
            if not hasattr(src, attr):
                raise ValueError(f"Rectification.build(src): expected a camera model with .{attr}, got {type(src).__name__}")
        if R_src_dst is None:
            R = torch.eye(3, dtype=torch.float64)
        else:
            R = torch.as_tensor(R_src_dst, dtype=torch.float64)
            if R.shape != (3, 3) or not bool(torch.isfinite(R).all()):
                raise ValueError(f"Rectification.build(R_src_dst): expected a finite [3, 3] rotation, got shape {tuple(R.shape)}")
            if float((R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max()) > 1e-6 or float(torch.linalg.det(R)) <= 0:
                raise ValueError("Rectification.build(R_src_dst): not a rotation matrix (R^T R != I or det <= 0)")
        rays_dst = dst.unproject(dst.pixel_grid(dtype=torch.float64))  # [H, W, 3]
        rays_src = pm.matmul(rays_dst, R.T)
        uv, ok = src.project(rays_src)
        uv = uv.to(torch.float64)
        u, v = uv[..., 0], uv[..., 1]
        inside = (u >= 0) & (u <= src.width - 1) & (v >= 0) & (v <= src.height - 1)
        valid = ok & inside & (rays_src[..., 2] > 0) & torch.isfinite(uv).all(-1)
        map_uv = torch.where(valid[..., None], uv, torch.zeros_like(uv)).to(torch.float32)
        return cls(src=src, dst=dst, R_src_dst=R, map_uv=map_uv, valid=valid)

    # ---- resampling ----------------------------------------------------------------------------
    def _grid(self) -> Tensor:
        """Normalised grid_sample coordinates [1, H, W, 2] (align_corners=True convention)."""
        w_s, h_s = self.src.width, self.src.height
        scale = self.map_uv.new_tensor([2.0 / max(w_s - 1, 1), 2.0 / max(h_s - 1, 1)])
        return (self.map_uv * scale - 1.0)[None]

    def warp(self, image, mode: Literal["bilinear", "nearest"] = "bilinear"):
        """Resample a source image into the rectified camera; invalid pixels become 0.

        image: [H_s, W_s, C] or [B, H_s, W_s, C] (also [H_s, W_s]) float tensor or numpy array.
        "bilinear" interpolates (images); "nearest" copies the nearest source pixel exactly
        (index/label images, any dtype). Returns the same container type, [.., H, W, C].
        """
        if mode not in ("bilinear", "nearest"):
            raise ValueError(f"Rectification.warp(mode): expected 'bilinear' or 'nearest', got {mode!r}")
        is_numpy = isinstance(image, np.ndarray)
        x = torch.from_numpy(np.ascontiguousarray(image)) if is_numpy else image
        if not isinstance(x, Tensor):
            raise ValueError(f"Rectification.warp(image): expected a torch tensor or numpy array, got {type(image).__name__}")
        squeeze_channel = x.ndim == 2
        if squeeze_channel:
            x = x[..., None]
        batched = x.ndim == 4
        if x.ndim not in (3, 4) or x.shape[-3:-1] != (self.src.height, self.src.width):
            raise ValueError(
                f"Rectification.warp(image): expected shape [H_s, W_s, C] or [B, H_s, W_s, C] with "
                f"H_s, W_s = {self.src.height}, {self.src.width}; got {tuple(np.shape(image))}"
            )
        xb = x if batched else x[None]
        if mode == "nearest":
            iu = self.map_uv[..., 0].round().long().clamp(0, self.src.width - 1)
            iv = self.map_uv[..., 1].round().long().clamp(0, self.src.height - 1)
            out = xb[:, iv, iu]  # [B, H, W, C]
            out = torch.where(self.valid[None, ..., None], out, torch.zeros((), dtype=out.dtype))
        else:
            if not xb.dtype.is_floating_point:
                raise ValueError(f"Rectification.warp(image): bilinear mode needs a float image, got {xb.dtype}; use mode='nearest' for labels")
            inp = xb.permute(0, 3, 1, 2)
            grid = self._grid().to(inp.dtype).expand(inp.shape[0], -1, -1, -1)
            out = F.grid_sample(inp, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
            out = out.permute(0, 2, 3, 1)
            out = torch.where(self.valid[None, ..., None], out, torch.zeros((), dtype=out.dtype))
        if not batched:
            out = out[0]
        if squeeze_channel:
            out = out[..., 0]
        return out.numpy() if is_numpy else out

    def warp_vignette(self, vignette_src) -> Tensor:
        """Lens shading [H_s, W_s] (0..1) -> rectified [H, W] float32 (0 outside valid)."""
        v = torch.as_tensor(np.asarray(vignette_src) if not isinstance(vignette_src, Tensor) else vignette_src)
        if v.ndim != 2:
            raise ValueError(f"Rectification.warp_vignette: expected a [H_s, W_s] image, got shape {tuple(v.shape)}")
        return self.warp(v.to(torch.float32), mode="bilinear")

    def row_time_ratio(self, readout_rows: tuple[int, int] | None = None) -> Tensor:
        """R(u) = (source row - a) / (b - a) per rectified pixel, [H, W] float32 in [0, 1]; 0 outside valid.
        ``readout_rows`` (a, b): the first and last raw row the rolling shutter reads (default: the whole
        sensor, 0 and H_s - 1)."""
        a, b = readout_range(readout_rows, self.src.height)
        ratio = (self.map_uv[..., 1] - a) / max(b - a, 1)
        return torch.where(self.valid, ratio.clamp(0.0, 1.0), torch.zeros_like(ratio))

    @property
    def mask(self) -> Tensor:
        """Valid rectified pixels [H, W] bool (alias of ``valid``)."""
        return self.valid
