"""Are these tensors all finite? One pass per tensor and one answer for all of them: compiled for CPU
float tensors (a branch-free loop LLVM vectorizes), one float64 sum per tensor and a single host sync
elsewhere (a CUDA run does not stall on each tensor). The trainer asks this three times a step; the
float64 sums took ~0.5 ms of a 128 px CPU step."""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor


@njit(cache=True)
def _finite_row(a):
    """All of the 1-D array ``a`` finite? (v - v is 0 for a finite v and NaN for an infinity or NaN.)"""
    bad = False
    for j in range(a.shape[0]):
        bad |= (a[j] - a[j]) != 0.0
    return not bad


def all_finite(tensors: list[Tensor]) -> bool:
    """True when every element of every tensor is finite (no NaN, no infinity)."""
    rest = []
    for t in tensors:
        if t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64):
            if t.numel() and not _finite_row(t.detach().contiguous().view(-1).numpy()):
                return False
        else:
            rest.append(t.detach())
    # A NaN or an infinity anywhere makes the sum non-finite; a sum that overflows from finite values
    # answers False, and the caller's exact search then finds nothing to name.
    return not rest or bool(torch.isfinite(torch.stack([t.sum(dtype=torch.float64) for t in rest]).sum()))
