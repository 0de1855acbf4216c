"""Elementary functions and convolutions whose bits do not depend on the CPU's vector width.

numpy picks its own vector code at import (AVX2 or AVX-512, its "dispatch targets"), and its float64
``exp``, ``log``, ``arctan2`` (and ``tan``, ``arccos``, ``power``, ...) give other bits under each; float64
``sin``, ``cos``, ``hypot`` and ``sqrt`` do not (results/cross_isa/README.md, 2026-11-29). These take Python's
``math``, that is glibc's libm, element by element: the same code on every x86-64 machine with FMA. The
simulator calls them where its outputs (poses, points) are written at full precision. About 50 ns an
element: for arrays of up to ~10^5 values, not for images. numpy's ``convolve`` sums through its BLAS
(OpenBLAS, whose kernels differ between AVX2 and AVX-512 machines and between CPU models); `convolve_valid`
adds shifted copies. Likewise numpy's ``@``, ``dot`` and ``linalg.norm`` of one vector call OpenBLAS's
``dgemm``/``ddot``, whose kernels (chosen by CPU model: ``Haswell``, ``SkylakeX``, ``SapphireRapids``, ...) sum in
other orders, and torch's ``@`` calls MKL, which picks its kernels by CPU vendor; `matmul`, `vecdot`, `dot` and
`norm` add in a fixed order with elementwise operations (numpy or torch).
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


def norm(v) -> float:
    """The Euclidean norm of a 1-D float64 vector (``math.hypot``: no BLAS, the same bits on every machine)."""
    return math.hypot(*np.asarray(v, dtype=np.float64).ravel().tolist())


def dot(a, b) -> float:
    """The dot product of two 1-D float64 vectors of one length: the products summed exactly (``math.fsum``)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"dot: expected two 1-D vectors of one length, got {a.shape} and {b.shape}")
    return math.fsum((a * b).tolist())


def _operand(x):
    """A numpy array or torch tensor as it is; anything else (lists, scalars) as a float64 array."""
    return x if hasattr(x, "shape") and hasattr(x, "ndim") else np.asarray(x, dtype=np.float64)


def matmul(a, b):
    """``a @ b`` for (batched) matrices [..., M, K] @ [..., K, N] -> [..., M, N], numpy arrays or torch tensors
    (autograd included): the K products added in index order with elementwise operations, each rounded once
    (IEEE), so the bits are the same on every CPU. numpy's ``@`` calls OpenBLAS and torch's calls MKL, both of
    which pick kernels by CPU model or vendor."""
    a, b = _operand(a), _operand(b)
    if a.ndim < 2 or b.ndim < 2 or a.shape[-1] != b.shape[-2]:
        raise ValueError(f"matmul: expected [..., M, K] and [..., K, N] matrices, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k:k + 1] * b[..., k:k + 1, :]
    return out


def vecdot(a, b):
    """Σ_k a[..., k] b[..., k] over the last axis (broadcast), numpy or torch, added in index order (as `matmul`):
    the portable ``a @ v`` for [..., K] @ [K] and ``einsum("...ij,...j->...i")`` as ``vecdot(A, v[..., None, :])``."""
    a, b = _operand(a), _operand(b)
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"vecdot: expected operands with one last-axis length, got {tuple(a.shape)} and {tuple(b.shape)}")
    out = a[..., 0] * b[..., 0]
    for k in range(1, a.shape[-1]):
        out = out + a[..., k] * b[..., k]
    return out
