"""Ideal equidistant fisheye camera: image radius r = f * theta (no distortion)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.camera.base import check_pixels, check_points, scaled_size


@dataclass(frozen=True)
class Equidistant:
    """Equidistant fisheye of ``width`` x ``height`` pixels; pixel centres at integers."""

    f: float  # focal length, pixels per radian of off-axis angle
    cx: float  # principal point column, pixels
    cy: float  # principal point row, pixels
    width: int  # image width, pixels
    height: int  # image height, pixels
    max_theta: float = math.pi / 2  # largest valid off-axis angle, radians (<= pi)

    def __post_init__(self) -> None:
        if not (self.f > 0 and self.f < float("inf")):
            raise ValueError(f"Equidistant.f: expected a positive finite focal length in pixels, got {self.f}")
        for name in ("cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Equidistant.{name}: expected a finite value, got {getattr(self, name)}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value <= 0:
                raise ValueError(f"Equidistant.{name}: expected a positive integer, got {value}")
        if not (0 < self.max_theta <= math.pi):
            raise ValueError(f"Equidistant.max_theta: expected an angle in (0, pi] radians, got {self.max_theta}")

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """points_cam [..., 3] -> (pixels [..., 2], valid [...]: theta < max_theta)."""
        check_points(points_cam, "Equidistant.project")
        xy, z = points_cam[..., :2], points_cam[..., 2]
        r2 = (xy * xy).sum(-1)
        nonzero = r2 > 0
        r = pm.sqrt(torch.where(nonzero, r2, torch.ones_like(r2)))
        theta = pm.atan2(r, z)
        z_safe = torch.where(z != 0, z, torch.ones_like(z))
        scale = torch.where(nonzero, theta / r, 1.0 / z_safe)
        uv = self.f * scale[..., None] * xy + xy.new_tensor([self.cx, self.cy])
        valid = (theta < self.max_theta) & (nonzero | (z > 0))
        return uv, valid

    def unproject(self, pixels: Tensor) -> Tensor:
        """pixels [..., 2] -> unit rays [..., 3]."""
        check_pixels(pixels, "Equidistant.unproject")
        d = (pixels - pixels.new_tensor([self.cx, self.cy])) / self.f
        theta2 = (d * d).sum(-1)
        nonzero = theta2 > 0
        theta = pm.sqrt(torch.where(nonzero, theta2, torch.ones_like(theta2)))
        sinc = torch.where(nonzero, pm.sin(theta) / theta, torch.ones_like(theta))
        cos = torch.where(nonzero, pm.cos(theta), torch.ones_like(theta))
        return torch.cat([sinc[..., None] * d, cos[..., None]], -1)

    def scaled(self, factor: float) -> "Equidistant":
        """The same lens at ``factor`` times the resolution (pixel-centre convention kept)."""
        w, h, sx, sy = scaled_size(self.width, self.height, factor, "Equidistant")
        if abs(sx - sy) > 1e-9 * max(sx, sy):
            raise ValueError(f"Equidistant.scaled(factor): factor {factor} changes the aspect ratio ({w}x{h})")
        return Equidistant(self.f * sx, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, w, h, self.max_theta)
