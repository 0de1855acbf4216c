"""A learnable radial lens shading: the model extension for an unmodelled vignette (issue 15).

A trained model absorbs a fixed lens shading that its calibration does not state (results/diagnosis/README.md:
the residual keeps 6-30 % of it), so the residual cannot show it. Trained jointly with the scene, a
shading S(u) = exp(a2 r^2 + a4 r^4) multiplying the stated vignette takes it back: r is the distance
from the principal point (optionally moved by a fraction of the image, a placebo centre) over the
distance of the farthest image corner, so ``corner_attenuation`` = 1 - exp(a2 + a4) is the extra
darkening at that corner, the diagnosis's parametrisation. `TrainConfig.learn_shading` switches it on;
the two coefficients are the run's ``extra["shading"]`` and renders of the run apply them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole

#: Name of the coefficients [a2, a4] among a run's extra trainables.
KEY = "shading"


def _centre(camera: Pinhole, centre_offset: tuple[float, float]) -> tuple[float, float]:
    return camera.cx + centre_offset[0] * camera.width, camera.cy + centre_offset[1] * camera.height


def farthest_corner(camera: Pinhole, centre_offset: tuple[float, float] = (0.0, 0.0)) -> tuple[int, int]:
    """(u, v) of the image corner pixel farthest from the (shifted) principal point: where r = 1."""
    cx, cy = _centre(camera, centre_offset)
    corners = [(0, 0), (camera.width - 1, 0), (0, camera.height - 1), (camera.width - 1, camera.height - 1)]
    return max(corners, key=lambda c: (c[0] - cx) ** 2 + (c[1] - cy) ** 2)


def radius2(camera: Pinhole, centre_offset: tuple[float, float] = (0.0, 0.0)) -> Tensor:
    """[H, W] float32: squared distance of each pixel centre from the principal point shifted by
    ``centre_offset`` x (width, height), over that of the farthest image corner."""
    cx, cy = _centre(camera, centre_offset)
    v, u = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                          torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    x, y = farthest_corner(camera, centre_offset)
    return (((u - cx) ** 2 + (v - cy) ** 2) / ((x - cx) ** 2 + (y - cy) ** 2)).float()


def radius2_of(camera: Pinhole, config) -> Tensor:
    """`radius2` about the centre a `TrainConfig` places the learnable shading at."""
    return radius2(camera, (config.shading_centre_dx, config.shading_centre_dy))


def shading(r2: Tensor, coeffs: Tensor) -> Tensor:
    """exp(a2 r^2 + a4 r^4) [H, W] for r2 [H, W] and coeffs [2] = (a2, a4)."""
    return torch.exp(coeffs[0] * r2 + coeffs[1] * r2 * r2)


def corner_attenuation(coeffs) -> float:
    """1 - S at the farthest corner (r = 1): the learned extra darkening there."""
    a = [float(c) for c in coeffs]
    return 1.0 - math.exp(a[0] + a[1])


def learned_vignette(vignette: Tensor, camera: Pinhole, extra: dict, config) -> Tensor:
    """The stated vignette [H, W] times the run's learned shading (unchanged when it learned none)."""
    if KEY not in extra:
        return vignette
    r2 = radius2_of(camera, config).to(vignette.device)
    return vignette * shading(r2, extra[KEY].detach().to(vignette.device)).to(vignette.dtype)
