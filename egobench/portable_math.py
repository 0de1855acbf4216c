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

torch's CPU ``sqrt``, ``sin``, ``cos`` and ``atan2`` run in MKL's vector math, which is not correctly rounded and
picks its code by CPU vendor: 0.8 % of float64 square roots differ from IEEE's on an Intel Xeon, 1.2 % on an AMD
EPYC Zen 4, and not the same ones (results/cross_isa/README.md, 2026-12-07). `sqrt`, `sin`, `cos` and `atan2`
take float64 CPU tensors to numpy's correctly rounded square root and glibc's functions, autograd included.
"""

from __future__ import annotations

import math

import numpy as np
import torch


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


def _portable(x) -> bool:
    """Whether a torch tensor takes the portable path (float64 on the CPU); other dtypes and devices keep torch's."""
    return x.dtype == torch.float64 and x.device.type == "cpu"


def _numpy_call(fn, *tensors):
    """``fn`` over the tensors' values as numpy arrays -> a float64 tensor (0-d included)."""
    return torch.from_numpy(np.asarray(fn(*(t.detach().numpy() for t in tensors)), dtype=np.float64))


class _Sqrt(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        y = _numpy_call(np.sqrt, x)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g):
        (y,) = ctx.saved_tensors
        return g * 0.5 / y


class _Trig(torch.autograd.Function):
    """sin or cos (``name``) through numpy; the derivative through the other one."""

    @staticmethod
    def forward(ctx, x, name):
        ctx.save_for_backward(x)
        ctx.name = name
        return _numpy_call(np.sin if name == "sin" else np.cos, x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return (g * cos(x) if ctx.name == "sin" else -g * sin(x)), None


class _Atan2(torch.autograd.Function):
    @staticmethod
    def forward(ctx, y, x):
        ctx.save_for_backward(y, x)
        return _numpy_call(arctan2, y, x)

    @staticmethod
    def backward(ctx, g):
        y, x = ctx.saved_tensors
        r2 = x * x + y * y
        return g * x / r2, -g * y / r2


def sqrt(x):
    """The square root of a torch tensor; float64 on the CPU correctly rounded (numpy's, IEEE), the same bits on
    every x86-64 machine (torch's is MKL's vector math there); autograd included."""
    return _Sqrt.apply(x) if _portable(x) else torch.sqrt(x)


def sin(x):
    """The sine of a torch tensor; float64 on the CPU numpy's (its float64 sine does not follow its dispatch)."""
    return _Trig.apply(x, "sin") if _portable(x) else torch.sin(x)


def cos(x):
    """The cosine of a torch tensor; float64 on the CPU numpy's (its float64 cosine does not follow its dispatch)."""
    return _Trig.apply(x, "cos") if _portable(x) else torch.cos(x)


def atan2(y, x):
    """The angle of (x, y) of torch tensors of one shape; float64 on the CPU glibc's ``atan2`` element by
    element (`arctan2`, about 50 ns an element: for poses, not images)."""
    if not (_portable(y) and _portable(x)):
        return torch.atan2(y, x)
    y, x = torch.broadcast_tensors(y, x)
    return _Atan2.apply(y.contiguous(), x.contiguous())
