"""`textures.value_noise` compiled: the same arithmetic, point by point in one numba loop, and the same bits.

The torch version makes about twenty [N] temporaries a call, and the simulator calls it some nine thousand times
a recording (every noise and grain octave of every texture lookup): a sixth of a recording's time on one thread.
Here each point's lattice cell, smoothstep weights, four hashed table values and the footprint fade are the torch
version's operations in its order, each rounded once in the points' dtype (float32 or float64; numba without
fast-math), so the result equals it bit for bit (tests/sim/test_noise_kernel.py). The torch version stays the
reference and the path for autograd and GPU tensors.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

#: the lattice hash's multipliers (`textures.value_noise`)
HASH_X, HASH_Y = 0x2C9277B5, 0x1B873593


#: the kernel's constants 0, 1/2, 1, 3/2, 2, 3 per dtype (a float64 literal would turn float32 arithmetic float64)
_CONSTANTS = {dt: tuple(dt(v) for v in (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)) for dt in (np.float32, np.float64)}


@njit(cache=True, error_model="numpy")
def _value_noise(uv, scale, table, e, has_e, out, k):
    """out[n] = value noise of uv[n] (k: 0, 1/2, 1, 3/2, 2, 3 in uv's dtype; ``scale`` too)."""
    zero, half, one, one_half, two, three = k
    mask = table.shape[0] - 1
    for n in range(uv.shape[0]):
        px = uv[n, 0] / scale
        py = uv[n, 1] / scale
        cx = np.floor(px)
        cy = np.floor(py)
        x = px - cx
        y = py - cy
        fx = x * x * (three - two * x)
        fy = y * y * (three - two * y)
        ix = np.int64(cx)
        iy = np.int64(cy)
        hx0, hx1 = ix * HASH_X, (ix + 1) * HASH_X
        hy0, hy1 = iy * HASH_Y, (iy + 1) * HASH_Y
        a = table[(hx0 ^ hy0) & mask]
        b = table[(hx1 ^ hy0) & mask]
        c = table[(hx0 ^ hy1) & mask]
        d = table[(hx1 ^ hy1) & mask]
        v = (a + (b - a) * fx) * (one - fy) + (c + (d - c) * fx) * fy
        if has_e:
            fade = min(max(one_half - e[n] / scale, zero), one)
            v = half + fade * (v - half)
        out[n] = v


def value_noise(uv: Tensor, scale_m: float, table: Tensor, e: Tensor | None) -> Tensor:
    """`textures.value_noise` for float32 or float64 CPU tensors uv [N, 2] (and e [N], of uv's dtype) with the
    lattice ``table`` of that dtype -> [N]."""
    pts = np.ascontiguousarray(uv.detach().numpy())
    dt = pts.dtype.type
    out = np.empty(pts.shape[0], dtype=dt)
    foot = np.zeros(0, dtype=dt) if e is None else np.ascontiguousarray(e.detach().expand(pts.shape[0]).numpy())
    _value_noise(pts, dt(scale_m), table.numpy(), foot, e is not None, out, _CONSTANTS[dt])
    return torch.from_numpy(out)
