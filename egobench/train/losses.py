"""Training losses: the photometric loss on valid pixels (0.8 L1 + 0.2 (1 - SSIM)) and the 2DGS
regularisers (normal consistency, distortion; PAPER-NOTES §7)."""

from __future__ import annotations

from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.train.config import TrainConfig
from egobench.train.normal_consistency import normal_consistency


def photometric_loss(pred: Tensor, gt: Tensor, mask3: Tensor, n_mask: float, ssim_lambda: float) -> Tensor:
    """(1 - l) L1 + l (1 - SSIM) of ``pred`` vs ``gt`` [H, W, 3] over the valid pixels ``mask3`` [H, W, 1]
    (``n_mask``: their count x 3)."""
    from egobench.metrics import ssim_loss

    l1 = ((pred - gt).abs() * mask3).sum() / n_mask
    ssim_term = ssim_loss((pred * mask3)[None], (gt * mask3)[None])
    return (1 - ssim_lambda) * l1 + ssim_lambda * ssim_term


def twodgs_regularisers(outs: list, cam: Pinhole, config: TrainConfig, it: int, mask3: Tensor) -> Tensor:
    """2DGS losses at iteration ``it``: normal consistency (rendered normal vs depth normal, weighted by
    alpha, from ``normal_start_iter``) and distortion (from ``dist_start_iter``)."""
    o = outs[0]
    total = o.rgb.new_zeros(())
    if config.normal_lambda > 0 and it >= config.normal_start_iter and o.normal is not None:
        nc = normal_consistency(o.depth[0, ..., 0], o.normal[0], o.alpha[0, ..., 0], mask3[..., 0], cam)
        total = total + config.normal_lambda * nc
    if config.dist_lambda > 0 and it >= config.dist_start_iter and o.extras and "distortion" in o.extras:
        total = total + config.dist_lambda * o.extras["distortion"].mean()
    return total
