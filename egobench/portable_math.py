"""Elementary functions and convolutions whose bits do not depend on the CPU's vector width.

numpy picks its own vector code at import (AVX2 or AVX-512, its "dispatch targets"), and its float64
``exp``, ``log``, ``arctan2`` (and ``tan``, ``arccos``, ``power``, ...) give other bits under each; float64
``sin``, ``cos``, ``hypot`` and ``sqrt`` do not (docs/reproducibility.md, stop 62). These take Python's
``math``, that is glibc's libm, element by element: the same code on every x86-64 machine with FMA. The
simulator calls them where its outputs (poses, points) are written at full precision. About 50 ns an
element: for arrays of up to ~10^5 values, not for images. numpy's ``convolve`` sums through its BLAS
(OpenBLAS, whose kernels differ between AVX2 and AVX-512 machines); `convolve_valid` adds shifted copies.
"""

from __future__ import annotations

import math

import numpy as np


def _elementwise(fn, *arrays) -> np.ndarray:
    """fn over broadcast float64 arrays -> float64 array of their broadcast shape."""
    args = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays))
    shape = args[0].shape
    flat = [a.ravel() for a in args]
    return np.fromiter(map(fn, *flat), dtype=np.float64, count=flat[0].size).reshape(shape)


def exp(x) -> np.ndarray:
    """e ** x, float64, glibc's ``exp``."""
    return _elementwise(math.exp, x)


def log(x) -> np.ndarray:
    """Natural logarithm, float64, glibc's ``log`` (x > 0; ``math`` raises ValueError on x <= 0)."""
    return _elementwise(math.log, x)


def arctan2(y, x) -> np.ndarray:
    """The angle of (x, y) in (-pi, pi], float64, glibc's ``atan2``."""
    return _elementwise(math.atan2, y, x)


def convolve_valid(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``np.convolve(x, kernel, mode="valid")`` for 1-D float64 x [N] and kernel [K] (K <= N) -> [N - K + 1]:
    the kernel's taps added one after another as scaled shifted copies of x (exact elementwise products and
    sums, in a fixed order)."""
    x, kernel = np.asarray(x, dtype=np.float64), np.asarray(kernel, dtype=np.float64)
    if x.ndim != 1 or kernel.ndim != 1 or not 1 <= kernel.size <= x.size:
        raise ValueError(f"convolve_valid: expected 1-D x [N] and kernel [K] with 1 <= K <= N, got {x.shape} and "
                         f"{kernel.shape}")
    n = x.size - kernel.size + 1
    out = np.zeros(n)
    for m in range(kernel.size):
        out += kernel[kernel.size - 1 - m] * x[m:m + n]
    return out
