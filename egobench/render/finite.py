"""Are these tensors all finite; has this [N, C] tensor a zero row? One pass per tensor and one answer:
compiled for CPU float tensors (branch-free loops LLVM vectorizes), torch reductions and a single host
sync elsewhere (a CUDA run does not stall on each tensor). The trainer's divergence test asks the first
three times a step (its float64 sums took ~0.5 ms of a 128 px CPU step) and `render` both of its
Gaussians at every call."""

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


@njit(cache=True)
def _zero_row(a):
    """Has the 2-D array ``a`` a row whose squared norm, summed in its dtype, is zero?"""
    found = False
    for n in range(a.shape[0]):
        s = a[n, 0] * a[n, 0]
        for c in range(1, a.shape[1]):
            s += a[n, c] * a[n, c]
        found |= s == 0.0
    return found


def has_zero_row(t: Tensor) -> bool:
    """Does some row of ``t`` [N, C] (C >= 1) have a squared norm of zero in its dtype (every entry zero,
    or so small that the squares underflow)?"""
    if t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64):
        return bool(t.shape[0]) and bool(_zero_row(t.detach().contiguous().numpy()))
    t = t.detach()
    return bool(((t * t).sum(-1) == 0).any())
