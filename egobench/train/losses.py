"""The 2DGS regularisers of the training loss (normal consistency, distortion; docs/paper-notes.md §6). The
photometric loss (0.8 L1 + 0.2 (1 - SSIM) on the valid pixels) is `egobench.train.photometric`."""

from __future__ import annotations

from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.render.types import first_image
from egobench.train.config import TrainConfig
from egobench.train.normal_consistency import normal_consistency


def twodgs_regularisers(outs: list, cam: Pinhole, config: TrainConfig, it: int, mask3: Tensor) -> Tensor:
    """2DGS losses at iteration ``it``: normal consistency (rendered normal vs depth normal, weighted by
    alpha, from ``normal_start_iter``) and distortion (from ``dist_start_iter``)."""
    o = outs[0]
    total = o.rgb.new_zeros(())
    if config.normal_lambda > 0 and it >= config.normal_start_iter and o.normal is not None:
        nc = normal_consistency(first_image(o.depth).squeeze(-1), first_image(o.normal),
                                first_image(o.alpha).squeeze(-1), mask3[..., 0], cam)
        total = total + config.normal_lambda * nc
    if config.dist_lambda > 0 and it >= config.dist_start_iter and o.extras and "distortion" in o.extras:
        total = total + config.dist_lambda * o.extras["distortion"].mean()
    return total
