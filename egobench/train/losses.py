"""Training losses: the photometric loss on valid pixels (0.8 L1 + 0.2 (1 - SSIM)) and the 2DGS
regularisers (normal consistency, distortion; PAPER-NOTES §7)."""

from __future__ import annotations

import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.train.config import TrainConfig


def photometric_loss(pred: Tensor, gt: Tensor, mask3: Tensor, n_mask: float, ssim_lambda: float) -> Tensor:
    """(1 - l) L1 + l (1 - SSIM) of ``pred`` vs ``gt`` [H, W, 3] over the valid pixels ``mask3`` [H, W, 1]
    (``n_mask``: their count x 3)."""
    from egobench.metrics import ssim_loss

    l1 = ((pred - gt).abs() * mask3).sum() / n_mask
    ssim_term = ssim_loss((pred * mask3)[None], (gt * mask3)[None])
    return (1 - ssim_lambda) * l1 + ssim_lambda * ssim_term


def depth_normals(depth: Tensor, camera: Pinhole) -> Tensor:
    """Normals from a depth map [H, W] by central differences of the back-projected points -> [H, W, 3],
    facing the camera (negative z for a surface seen from the front) like the rendered normals
    (gsplat's ``depth_to_normal``: cross(d/drow, d/dcolumn)); zero on the border rows/columns."""
    grid = camera.pixel_grid(dtype=depth.dtype, device=depth.device)
    pts = camera.unproject(grid) * depth[..., None]  # [H, W, 3]
    d_col = torch.zeros_like(pts)
    d_row = torch.zeros_like(pts)
    d_col[:, 1:-1] = pts[:, 2:] - pts[:, :-2]  # along +u (camera +x)
    d_row[1:-1] = pts[2:] - pts[:-2]  # along +v (camera +y)
    n = torch.linalg.cross(d_row, d_col, dim=-1)  # y x x = -z: towards the camera
    return torch.nn.functional.normalize(n, dim=-1)


def twodgs_regularisers(outs: list, cam: Pinhole, config: TrainConfig, it: int, mask3: Tensor) -> Tensor:
    """2DGS losses at iteration ``it``: normal consistency (rendered normal vs depth normal, weighted by
    alpha, from ``normal_start_iter``) and distortion (from ``dist_start_iter``)."""
    o = outs[0]
    total = o.rgb.new_zeros(())
    if config.normal_lambda > 0 and it >= config.normal_start_iter and o.normal is not None:
        depth_n = depth_normals(o.depth[0, ..., 0], cam)
        rend_n = torch.nn.functional.normalize(o.normal[0], dim=-1)
        err = (1 - (rend_n * depth_n).sum(-1)) * o.alpha[0, ..., 0].detach()
        total = total + config.normal_lambda * (err * mask3[..., 0]).sum() / mask3[..., 0].sum().clamp_min(1)
    if config.dist_lambda > 0 and it >= config.dist_start_iter and o.extras and "distortion" in o.extras:
        total = total + config.dist_lambda * o.extras["distortion"].mean()
    return total
