"""Compiler internals of the CPU kernels: the fast-math flags and the noalias pipeline of split loop bodies, a
branch-free exp, and LLVM intrinsics (prefetch, a scalar-loop hint). The threads are set up by `egobench.host`
(`setup_threads` at an entry point, `start_kernel_pool` before the first kernel runs)."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path


import llvmlite.binding as ll
from llvmlite import ir
from numba import njit, types
from numba.core import caching, cgutils
from numba.core.compiler import Compiler
from numba.extending import intrinsic, overload

#: numba's list of cache locators (its class is public from numba 0.62)
_CACHE_IMPL = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
#: the folder of this package's kernel modules
PACKAGE_DIR = Path(__file__).resolve().parent


def source_hash(folder: Path) -> str:
    """SHA-256 of the names and text of every Python module in ``folder``."""
    h = hashlib.sha256()
    for path in sorted(Path(folder).glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def package_source_hash() -> str:
    """`source_hash` of this package: the source stamp of each of its kernels (computed once per process)."""
    return source_hash(PACKAGE_DIR)


class SourceHashLocator(caching._CacheLocator):
    """numba's cache locator for this package's kernels: the one numba would pick (``NUMBA_CACHE_DIR``, the
    in-tree ``__pycache__``, the user-wide folder), with the source stamp replaced by `package_source_hash`.
    numba stamps a cache with its own file's modification time only, but the kernels inline helpers of the
    package's other modules: an edited helper now recompiles every kernel that might inline it."""

    def __init__(self, inner):
        self._inner = inner

    def ensure_cache_path(self):
        self._inner.ensure_cache_path()

    def get_cache_path(self):
        return self._inner.get_cache_path()

    def get_source_stamp(self):
        return package_source_hash()

    def get_disambiguator(self):
        return self._inner.get_disambiguator()

    @classmethod
    def from_function(cls, py_func, py_file):
        if Path(py_file).resolve().parent != PACKAGE_DIR:
            return None
        for other in _CACHE_IMPL._locator_classes:
            inner = None if other is cls else other.from_function(py_func, py_file)
            if inner is not None:
                return cls(inner)
        return None


if SourceHashLocator not in _CACHE_IMPL._locator_classes:  # before the package's kernels are decorated
    _CACHE_IMPL._locator_classes.insert(0, SourceHashLocator)


#: fast-math flags of the compositing loops: reassociation and FMA contraction let LLVM vectorize
#: the per-row loops (results stay deterministic: the compiled order is fixed); no nnan/ninf
FASTMATH = {"reassoc", "contract", "nsz"}


class NoAliasCompiler(Compiler):
    """numba's compiler with every array argument marked noalias, as numba compiles a parfor's loop body
    (without it, the split 2DGS bodies ran ~1.5x slower: an exploration of 2026-11-28). Only for functions that
    never write an array argument overlapping another one."""

    def define_pipelines(self):
        self.state.flags.noalias = True
        return super().define_pipelines()


#: the compile options of a `prange` body split into a function of its own: those numba gives a parfor
#: body (fast-math, numpy's error model: no division test; noalias arguments), so it vectorizes as one
BIN_BODY = dict(cache=True, fastmath=FASTMATH, error_model="numpy", pipeline_class=NoAliasCompiler)


def _exp_neg(s, kc):
    """exp(-s) for s in [0, 6] (s clamped to <= 6), branch-free so that loops vectorize: a Taylor
    polynomial of exp(x / 16), |x / 16| <= 0.375, squared four times; degree 13 in float64
    (relative error ~1e-15), degree 8 in float32 (~1e-8, below float32 rounding). kc:
    `compute_constants` (its dtype picks the degree at compile time)."""
    raise NotImplementedError("numba-only: called from the compiled kernels")


@overload(_exp_neg, inline="always", fastmath=FASTMATH)
def _exp_neg_impl(s, kc):
    if kc.dtype == types.float32:
        def impl32(s, kc):
            x = -min(s, kc[5]) * kc[4]
            # unrolled by hand: a loop here would be the innermost loop and stop the vectorizer;
            # Estrin's scheme (pairs, then powers x^2, x^4, x^8): a dependency chain half as long
            # as Horner's, which is what bounds the short per-Gaussian pixel loops
            x2 = x * x
            x4 = x2 * x2
            q0 = kc[18] * x + kc[19]
            q1 = kc[16] * x + kc[17]
            q2 = kc[14] * x + kc[15]
            q3 = kc[12] * x + kc[13]
            r0 = q1 * x2 + q0
            r1 = q3 * x2 + q2
            p = (r1 * x4 + r0) + kc[11] * (x4 * x4)
            p = p * p
            p = p * p
            p = p * p
            return p * p
        return impl32

    def impl64(s, kc):
        x = -min(s, kc[5]) * kc[4]
        p = kc[6] * x + kc[7]
        p = p * x + kc[8]
        p = p * x + kc[9]
        p = p * x + kc[10]
        p = p * x + kc[11]
        p = p * x + kc[12]
        p = p * x + kc[13]
        p = p * x + kc[14]
        p = p * x + kc[15]
        p = p * x + kc[16]
        p = p * x + kc[17]
        p = p * x + kc[18]
        p = p * x + kc[19]
        p = p * p
        p = p * p
        p = p * p
        return p * p
    return impl64


#: intersections ahead whose table and feature rows the compositing loops prefetch (the rows are
#: read in depth order, scattered over the table: without it a cache miss starts every intersection)
PREFETCH_AHEAD = 6
#: rows ahead that the table kernels prefetch (`needed_rows`)
GATHER_AHEAD = 8


@intrinsic
def scalar_loop(typingctx):
    """An empty inline assembly statement with a side effect: placed in a loop body, it stops LLVM from
    vectorizing that loop (and costs nothing). For copies whose vector form LLVM builds from scatter or
    gather instructions, slower than scalar stores on AMD Zen 4."""
    def codegen(context, builder, signature, args):
        builder.asm(ir.FunctionType(ir.VoidType(), []), "", "", [], True)
        return context.get_dummy_value()
    return types.void(), codegen


@intrinsic
def prefetch_at(typingctx, arr, row, col):
    """Software prefetch (read, all cache levels) of the line holding arr[row, col] (2D C-contiguous)."""
    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = [context.cast(builder, args[k], signature.args[k], types.intp) for k in (1, 2)]
        ptr = cgutils.get_item_pointer2(context, builder, ary.data, cgutils.unpack_tuple(builder, ary.shape),
                                        cgutils.unpack_tuple(builder, ary.strides), aryty.layout, idx,
                                        wraparound=False, boundscheck=False)
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        # the intrinsic's name mangles the pointer type: "p0" for opaque pointers (LLVM >= 17), "p0i8"
        # for typed ones
        name = "llvm.prefetch.p0" if ll.llvm_version_info[0] >= 17 else "llvm.prefetch.p0i8"
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), name)
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()
    return types.void(arr, row, col), codegen


@njit(cache=True, inline="always")
def prefetch_row(arr, row):
    """Software prefetch of the start of row `row` of a 2D C-contiguous array."""
    prefetch_at(arr, row, 0)


@njit(cache=True, inline="always")
def prefetch_whole_row(arr, row):
    """Software prefetch of row `row` of a 2D C-contiguous array whose rows are at most 64 bytes: its first
    and its last element, since such a row may straddle two cache lines (half of the 36-byte
    ray-transform rows do)."""
    prefetch_at(arr, row, 0)
    prefetch_at(arr, row, arr.shape[1] - 1)
