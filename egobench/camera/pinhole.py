"""Pinhole camera (the rectified camera every trainer and rasterizer works in).

Pixel convention (one for all of egobench's camera models, as in projectaria-tools): the
centre of pixel (column i, row j) has coordinates (u, v) = (i, j), so an image centred on
the optical axis has cx = (W - 1) / 2. gsplat puts pixel centres at (i + 0.5, j + 0.5); the
rasterizer converts (cx_gsplat = cx + 0.5), nothing else needs to.
Axes are OpenCV: x right, y down, z forward, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Pinhole:
    """An ideal pinhole camera of ``width`` x ``height`` pixels (focal lengths in pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (value > 0 and value < float("inf")):
                raise ValueError(f"Pinhole.{name}: expected a positive finite focal length in pixels, got {value}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value <= 0:
                raise ValueError(f"Pinhole.{name}: expected a positive integer, got {value}")

    @property
    def K(self) -> Tensor:  # [3, 3], float64
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64
        )

    def scaled(self, factor: float) -> "Pinhole":
        """The same camera at ``factor`` times the resolution (pixel-centre convention kept)."""
        w, h = round(self.width * factor), round(self.height * factor)
        sx, sy = w / self.width, h / self.height
        return Pinhole(
            fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
            width=w, height=h,
        )

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """points_cam [..., 3] -> (pixels [..., 2], valid [...]: z > 0)."""
        if points_cam.shape[-1] != 3:
            raise ValueError(f"Pinhole.project: points_cam must have shape [..., 3], got {tuple(points_cam.shape)}")
        z = points_cam[..., 2]
        valid = z > 1e-9
        zs = torch.where(valid, z, torch.ones_like(z))
        u = self.fx * points_cam[..., 0] / zs + self.cx
        v = self.fy * points_cam[..., 1] / zs + self.cy
        return torch.stack([u, v], dim=-1), valid

    def unproject(self, pixels: Tensor) -> Tensor:
        """pixels [..., 2] -> rays [..., 3] with z = 1 (not unit length)."""
        if pixels.shape[-1] != 2:
            raise ValueError(f"Pinhole.unproject: pixels must have shape [..., 2], got {tuple(pixels.shape)}")
        x = (pixels[..., 0] - self.cx) / self.fx
        y = (pixels[..., 1] - self.cy) / self.fy
        return torch.stack([x, y, torch.ones_like(x)], dim=-1)

    def pixel_grid(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        """Pixel-centre coordinates [H, W, 2] as (u, v)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=dtype, device=device),
            torch.arange(self.width, dtype=dtype, device=device),
            indexing="ij",
        )
        return torch.stack([u, v], dim=-1)

    def to_dict(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, w=self.width, h=self.height)
