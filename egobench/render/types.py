"""Data types shared by every rasterizer backend (the contract of `render`)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Literal

import torch
from torch import Tensor

SplatMode = Literal["3dgs", "2dgs"]


@dataclass
class Gaussians:
    """A set of N Gaussians (3DGS) or surfels (2DGS) in world coordinates.

    Parameters are stored unconstrained, as the optimiser sees them (gsplat convention).
    """

    means: Tensor  # [N, 3] world positions, metres
    quats: Tensor  # [N, 4] rotation quaternions (w, x, y, z), not necessarily unit
    log_scales: Tensor  # [N, 3] log of the standard deviations along the local axes, metres (2DGS uses the first two)
    opacity_logits: Tensor  # [N] logit of opacity
    colors: Tensor  # [N, 3] colour in the method's scene-colour space (0..1 nominal; gamma or linear)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:  # [N, 3]
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:  # [N]
        return torch.sigmoid(self.opacity_logits)

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def detach(self) -> "Gaussians":
        return replace(self, **{k: v.detach() for k, v in self.tensors().items()})

    def to(self, device: torch.device | str) -> "Gaussians":
        return replace(self, **{k: v.to(device) for k, v in self.tensors().items()})

    def index(self, keep: Tensor) -> "Gaussians":
        """The subset selected by a boolean mask or index tensor."""
        return replace(self, **{k: v[keep] for k, v in self.tensors().items()})


@dataclass
class RenderOutput:
    """What a rasterizer returns for B images of H x W pixels."""

    rgb: Tensor  # [B, H, W, 3] composited colour (scene-colour space), background added
    alpha: Tensor  # [B, H, W, 1] accumulated opacity
    depth: Tensor  # [B, H, W, 1] expected depth (camera z), alpha-weighted and normalised by alpha
    normal: Tensor | None = None  # [B, H, W, 3] alpha-weighted normals in camera frame (2DGS; 3DGS when asked)
    means2d: Tensor | None = None  # [B, N, 2] projected means, retaining grad for densification statistics; 2DGS: gsplat's gradient_2dgs carrier (zeros; values in extras["means2d_values"])
    radii: Tensor | None = None  # [B, N] screen-space radius in pixels, 0 where culled
    extras: dict | None = None  # backend-specific (2DGS distortion map, timings)


def first_image(x: Tensor) -> Tensor:
    """``x[0]`` of a [B, ...] render output; for B = 1 a view whose backward is a view too (``x[0]``'s backward
    writes the gradient into a new zero tensor of x's shape: a pass over the image per use)."""
    return x.squeeze(0) if x.shape[0] == 1 else x[0]
