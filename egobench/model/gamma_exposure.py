"""The trainer's exposure through the gamma response, ``clamp(encode(decode(x) * s), 0, 1)``, as one compiled
CPU pass with its derivatives (`FormationModel.predict` with `GammaResponse`; the torch ops there are
the oracle and every other device's path).

decode and encode are exact inverses on the power law, so where both stay on it the exposure is
``x * s ** (1 / gamma)``: one power per pixel (``s`` is per pixel, shared by the three channels)
instead of two per channel. Pixels on the linear toe (display values below ~0.005 at gamma 2.2) take
the general formula. The result agrees with the torch ops to float rounding, not bit for bit.
On one thread the torch ops took 0.76 ms forward and 1.12 ms backward at 128 px.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from egobench.render.cpu_backend import set_threads


class ExposureCurve(NamedTuple):
    """What `expose_fwd` computes: decode (bool: decode x before scaling), clamp (bool: clip the result to
    [0, 1]), and the toed gamma curve: gamma (float, the exponent), y0 (float, the display value where the toe
    ends), x0 (float, the linear value where it ends; y0 = x0 ** (1 / gamma))."""

    decode: bool
    clamp: bool
    gamma: float
    y0: float
    x0: float


class Exposed(NamedTuple):
    """What `expose_fwd` writes, each [P, 3] in x's dtype: out (the exposed colour), dx and ds (the partials
    of each output by its own x and by the pixel's s)."""

    out: np.ndarray
    dx: np.ndarray
    ds: np.ndarray


@njit(cache=True, inline="always")
def _encode(z, gamma, x0, slope):
    """(encode(z), d encode / dz) of the toed gamma curve (toe below x0, slope y0 / x0)."""
    if z >= x0:
        e = z ** (1.0 / gamma)
        return e, e / (gamma * z)
    return z * slope, slope


@njit(cache=True, parallel=True)
def expose_fwd(x, s, r, curve, exposed):
    """x [P, 3], s [P] (scale >= 0), curve (`ExposureCurve`) -> exposed (`Exposed`): out [P, 3] and the
    partials dx, ds [P, 3] of each output by its own x and by the pixel's s (zero where the clamp cuts). The
    toe: linear values below x0, display values below y0 = x0 ** (1 / gamma), on the line of slope y0 / x0.
    r [P] (scratch, x's dtype): s ** (1 / gamma) with
    decode, a float64 power rounded to r's dtype. It is computed here, by glibc's pow, and not by numpy:
    numpy's power takes other code, and gives other bits, on AVX-512 and AVX2 machines (docs/reproducibility.md,
    2026-11-29); it costs ~0.25 ms more at 128 px on one thread."""
    decode, clamp, gamma, y0, x0 = curve.decode, curve.clamp, curve.gamma, curve.y0, curve.x0
    out, dx, ds = exposed.out, exposed.dx, exposed.ds
    slope = y0 / x0
    for p in prange(x.shape[0]):
        if decode:  # only the power law reads r
            r[p] = np.float64(s[p]) ** (1.0 / gamma)
        sp, rp = np.float64(s[p]), (np.float64(r[p]) if decode else 0.0)
        for c in range(3):
            xv = np.float64(x[p, c])
            if decode and xv >= y0 and xv * rp >= y0:  # both on the power law
                e, gx, gs = xv * rp, rp, xv * rp / (gamma * sp)
            else:
                if not decode:
                    lin, dlin = xv, 1.0
                elif xv >= y0:
                    lin = xv**gamma
                    dlin = gamma * lin / xv
                else:
                    lin, dlin = xv / slope, 1.0 / slope
                e, dedz = _encode(lin * sp, gamma, x0, slope)
                gx, gs = dedz * sp * dlin, dedz * lin
            if clamp and (e < 0.0 or e > 1.0):  # torch's clamp passes the gradient at 0 and 1
                e, gx, gs = min(max(e, 0.0), 1.0), 0.0, 0.0
            out[p, c], dx[p, c], ds[p, c] = e, gx, gs


@njit(cache=True, parallel=True)
def expose_bwd(g, dx, ds, g_x, g_s):
    """g [P, 3] -> g_x = g dx [P, 3], g_s [P] = sum over channels of g ds."""
    for p in prange(g.shape[0]):
        acc = 0.0
        for c in range(3):
            g_x[p, c] = g[p, c] * dx[p, c]
            acc += g[p, c] * ds[p, c]
        g_s[p] = acc


class _GammaExposeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, s, gamma, toe_linear, decode, clamp):
        H, W, _ = x.shape
        x_np = x.detach().contiguous().view(H * W, 3).numpy()
        s_np = s.detach().expand(H, W, 1).contiguous().view(H * W).numpy()
        r_np = np.empty_like(s_np)
        y0 = toe_linear ** (1.0 / gamma)
        out, dx, ds = (np.empty_like(x_np) for _ in range(3))
        set_threads()
        expose_fwd(x_np, s_np, r_np, ExposureCurve(decode, clamp, gamma, y0, toe_linear), Exposed(out, dx, ds))
        ctx.partials, ctx.s_shape = (dx, ds), s.shape
        return torch.from_numpy(out).view(H, W, 3)

    @staticmethod
    def backward(ctx, g):
        dx, ds = ctx.partials
        H, W, _ = g.shape
        g_x, g_s = np.empty_like(dx), np.empty(dx.shape[0], dtype=dx.dtype)
        expose_bwd(g.contiguous().view(H * W, 3).numpy(), dx, ds, g_x, g_s)
        g_scale = None
        if ctx.needs_input_grad[1]:
            g_scale = torch.from_numpy(g_s).view(H, W, 1).sum_to_size(ctx.s_shape)
        return torch.from_numpy(g_x).view(H, W, 3), g_scale, None, None, None, None


def compiled_exposure_applies(x: Tensor, scale: Tensor) -> bool:
    """Does `gamma_expose` take this image (CPU float32/float64 [H, W, 3]) and scale (broadcastable to
    [H, W, 1], of the image's dtype)?"""
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) or x.dim() != 3 or x.shape[2] != 3:
        return False
    if scale.dtype != x.dtype or scale.device != x.device or scale.dim() > 3:
        return False
    return all(a in (1, b) for a, b in zip(reversed(scale.shape), (1, x.shape[1], x.shape[0])))


def gamma_expose(x: Tensor, scale: Tensor, gamma: float, toe_linear: float, *, decode: bool, clamp: bool) -> Tensor:
    """x [H, W, 3] scene colour, scale (>= 0, broadcastable to [H, W, 1]) -> encode(decode(x) * scale)
    ([H, W, 3]; without decode: encode(x * scale)), clamped to [0, 1] with ``clamp``; the toed gamma
    curve of `GammaResponse` (exponent ``gamma``, toe ``toe_linear``). Differentiable in x and scale."""
    if not compiled_exposure_applies(x, scale):
        raise ValueError(f"gamma_expose: expected a CPU float [H, W, 3] image and a scale broadcastable to [H, W, 1] "
                         f"of its dtype, got {list(x.shape)} {x.dtype} {x.device} and {list(scale.shape)} {scale.dtype}")
    if not (math.isfinite(gamma) and gamma > 0 and 0 < toe_linear < 1):
        raise ValueError(f"gamma_expose: expected gamma > 0 and toe_linear in (0, 1), got {gamma!r}, {toe_linear!r}")
    return _GammaExposeCPU.apply(x, scale, float(gamma), float(toe_linear), bool(decode), bool(clamp))
