"""The compiled closest-hit kernel: `raycast`'s intersection tests, one ray at a time in one numba loop.

The torch functions of `raycast` (`_hit_rects`, `_hit_boxes_dense`, `_hit_spheres`, `_hit_boxes`,
`_hit_cylinders`) test every ray against every primitive of a kind as [rays, primitives] tensors, and the
culled kinds gather (ray, primitive) pairs; at the simulator's sizes that is a third of a recording's time in
tensor temporaries and index lists. This kernel walks the same kinds in the same order for one ray at a time,
and repeats their arithmetic operation for operation: the same products added in the same order (the order of
`portable_math.matmul`, of `_dot3` and of torch's row sums), each operation rounded once, no fused multiply-add
and no reassociation (numba without fast-math, serial), with one exception: its square root is IEEE's, where
torch's CPU ``sqrt`` is MKL's vector math, which is not correctly rounded. So it returns the bits of the torch
path with an IEEE square root: every ray's t and primitive id, on every x86-64 machine
(tests/sim/test_raycast_kernel.py checks it on every scene kind); against torch's own square root an ulp of t
differs on about one sphere or cylinder hit in ten thousand. The torch functions stay the reference and the
path for other dtypes, GPU tensors, autograd and inputs of other shapes.

Ties are broken as the torch path breaks them: a dense kind keeps the first primitive of the kind at the
smallest t (torch's ``min(dim)``), a culled kind the largest primitive id (`raycast._reduce_pairs`), and a
kind replaces the best hit so far only when strictly closer. A culled kind culls against the best t at the
start of the kind, as the torch path does.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit
from torch import Tensor

_RECT_EPS = 1e-12  # |d.n| below which a ray is parallel to a rectangle (`_hit_rects`)
_SLAB_TINY = {np.float64: 1e-30, np.float32: 1e-20}  # smallest |direction| component of a slab test (`_slab`)
_CYL_EPS = 1e-18  # `_hit_cylinders`'s degenerate-quadratic and parallel-cap thresholds
# The kernel's constants, in the rays' dtype (float32 arithmetic stays float32 only with float32 operands; torch
# rounds a Python scalar to the tensor's dtype). K_SLAB_FILL is what `_slab` puts in place of a direction
# component below K_SLAB_TINY: ``torch.where(dl < 0, -tiny, tiny)`` of two Python scalars is a float32 tensor,
# so float64 rays get float32(1e-30), not 1e-30.
K_ZERO, K_ONE, K_TWO, K_INF, K_RECT_EPS, K_SLAB_TINY, K_SLAB_FILL, K_CYL_EPS = range(8)


def kernel_constants(dtype: type) -> tuple:
    """The constants tuple (indexed by the K_* names) in ``dtype`` (np.float32 or np.float64)."""
    tiny = _SLAB_TINY[dtype]
    return tuple(dtype(v) for v in (0.0, 1.0, 2.0, math.inf, _RECT_EPS, tiny, np.float32(tiny), _CYL_EPS))


class RectTable(NamedTuple):
    """Rectangles [P]: unit normal N, in-plane axes U and V [P, 3], half sizes H [P, 2], the centre's
    coordinates along U, V and N (cU, cV, cN [P]) and primitive ids [P] (`Scene._pack`'s "rect")."""

    N: np.ndarray
    U: np.ndarray
    V: np.ndarray
    H: np.ndarray
    cU: np.ndarray
    cV: np.ndarray
    cN: np.ndarray
    ids: np.ndarray


class DenseBoxTable(NamedTuple):
    """Boxes tested against every ray [P]: rotations as columns Rflat [3, 3P], R^T c as cR [P, 3], half sizes
    H [P, 3] and ids [P] (`Scene._pack`'s "box_big")."""

    Rflat: np.ndarray
    cR: np.ndarray
    H: np.ndarray
    ids: np.ndarray


class SphereTable(NamedTuple):
    """Spheres [P]: centres C [P, 3], |c|^2 - r^2 as c2r2 [P] and ids [P] (`Scene._pack`'s "sphere")."""

    C: np.ndarray
    c2r2: np.ndarray
    ids: np.ndarray


class CulledTable(NamedTuple):
    """Boxes or cylinders behind bounding spheres (`Scene._pack`'s "box", "cylinder"): per primitive [P] the
    centre C [P, 3], rotation R [P, 3, 3], box half sizes H [P, 3], cylinder radius r and half height h, the
    bounding sphere's |c|^2 - r^2 and radius (c2r2_bound, r_bound), ids; per group [G] (none: G = 0) the group
    sphere's centre G_C [G, 3], G_c2r2 and radius G_r, and its members G_members [G, M] (-1: none)."""

    C: np.ndarray
    R: np.ndarray
    H: np.ndarray
    r: np.ndarray
    h: np.ndarray
    c2r2_bound: np.ndarray
    r_bound: np.ndarray
    ids: np.ndarray
    G_C: np.ndarray
    G_c2r2: np.ndarray
    G_r: np.ndarray
    G_members: np.ndarray


class KernelTables(NamedTuple):
    """A scene's tables in the rays' dtype (`kernel_tables`), one per kind in `Scene.intersect`'s order, and
    the kernel's constants (`kernel_constants`)."""

    rect: RectTable
    box_big: DenseBoxTable
    sphere: SphereTable
    box: CulledTable
    cylinder: CulledTable
    k: tuple


# Small helpers are inlined into the kinds' loops: a numba call that takes arrays costs two atomic reference
# counts per array, which at these sizes costs more than the tests themselves.
_inline = njit(cache=True, error_model="numpy", inline="always")
_kernel = njit(cache=True, error_model="numpy")


@_inline
def _slab_axis(ol, dl, h, k):
    """One axis of `raycast._slab`: (min, max) of the two plane crossings."""
    if abs(dl) < k[K_SLAB_TINY]:
        dl = -k[K_SLAB_FILL] if dl < 0 else k[K_SLAB_FILL]
    inv = k[K_ONE] / dl
    t1 = (-h - ol) * inv
    t2 = (h - ol) * inv
    return min(t1, t2), max(t1, t2)


@_inline
def _slab_t(o0, o1, o2, d0, d1, d2, h0, h1, h2, k):
    """`raycast._slab` for one ray in a box's frame: the entry (or, from inside, the exit) t, inf on a miss."""
    lo0, hi0 = _slab_axis(o0, d0, h0, k)
    lo1, hi1 = _slab_axis(o1, d1, h1, k)
    lo2, hi2 = _slab_axis(o2, d2, h2, k)
    tn = max(max(lo0, lo1), lo2)
    tf = min(min(hi0, hi1), hi2)
    t = tn if tn > 0 else tf
    return t if (tf >= tn and t > 0) else k[K_INF]


@_inline
def _dot(a0, a1, a2, b0, b1, b2):
    """a . b added in index order (`portable_math.matmul`, `raycast._dot3`, torch's row sum of three)."""
    return a0 * b0 + a1 * b1 + a2 * b2


@_inline
def _first_min(t, j, tmin, jmin):
    """The running minimum of a dense kind, the first index among equal t (as torch's ``min(dim)``)."""
    if t < tmin or jmin < 0:
        return t, j
    return tmin, jmin


@_inline
def _fold_dense(T, I, i, tmin, jmin, ids):
    """A dense kind's closest primitive replaces ray i's best hit only when strictly closer."""
    if jmin >= 0 and tmin < T[i]:
        T[i], I[i] = tmin, ids[jmin]


@_kernel
def _rects(O, D, T, I, tab, k):
    """`raycast._hit_rects`: every ray against every rectangle (`RectTable`); the first rectangle at the
    smallest t."""
    N, U, V, H, cU, cV, cN, ids = tab.N, tab.U, tab.V, tab.H, tab.cU, tab.cV, tab.cN, tab.ids
    eps = k[K_RECT_EPS]
    for i in range(O.shape[0]):
        o0, o1, o2, d0, d1, d2 = O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2]
        tmin = k[K_INF]
        jmin = -1
        for j in range(N.shape[0]):
            dn = _dot(d0, d1, d2, N[j, 0], N[j, 1], N[j, 2])
            on = _dot(o0, o1, o2, N[j, 0], N[j, 1], N[j, 2])
            par = not abs(dn) > eps
            t = (cN[j] - on) / (eps if par else dn)
            pu = _dot(o0, o1, o2, U[j, 0], U[j, 1], U[j, 2]) - cU[j] + t * _dot(d0, d1, d2, U[j, 0], U[j, 1], U[j, 2])
            pv = _dot(o0, o1, o2, V[j, 0], V[j, 1], V[j, 2]) - cV[j] + t * _dot(d0, d1, d2, V[j, 0], V[j, 1], V[j, 2])
            if par or not (t > 0 and abs(pu) <= H[j, 0] and abs(pv) <= H[j, 1]):
                t = k[K_INF]
            tmin, jmin = _first_min(t, j, tmin, jmin)
        _fold_dense(T, I, i, tmin, jmin, ids)


@_kernel
def _dense_boxes(O, D, T, I, tab, k):
    """`raycast._hit_boxes_dense`: R^T o - R^T c and R^T d as ``o @ Rflat - cR`` and ``d @ Rflat``, a slab test
    against every box (`DenseBoxTable`); the first box at the smallest t."""
    Rflat, cR, H, ids = tab.Rflat, tab.cR, tab.H, tab.ids
    for i in range(O.shape[0]):
        o0, o1, o2, d0, d1, d2 = O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2]
        tmin = k[K_INF]
        jmin = -1
        for p in range(H.shape[0]):
            c0, c1, c2 = 3 * p, 3 * p + 1, 3 * p + 2
            t = _slab_t(_dot(o0, o1, o2, Rflat[0, c0], Rflat[1, c0], Rflat[2, c0]) - cR[p, 0],
                        _dot(o0, o1, o2, Rflat[0, c1], Rflat[1, c1], Rflat[2, c1]) - cR[p, 1],
                        _dot(o0, o1, o2, Rflat[0, c2], Rflat[1, c2], Rflat[2, c2]) - cR[p, 2],
                        _dot(d0, d1, d2, Rflat[0, c0], Rflat[1, c0], Rflat[2, c0]),
                        _dot(d0, d1, d2, Rflat[0, c1], Rflat[1, c1], Rflat[2, c1]),
                        _dot(d0, d1, d2, Rflat[0, c2], Rflat[1, c2], Rflat[2, c2]), H[p, 0], H[p, 1], H[p, 2], k)
            tmin, jmin = _first_min(t, p, tmin, jmin)
        _fold_dense(T, I, i, tmin, jmin, ids)


@_kernel
def _spheres(O, D, T, I, tab, k):
    """`raycast._hit_spheres`: every ray against every sphere (`SphereTable`); the first sphere at the smallest
    t."""
    C, c2r2, ids = tab.C, tab.c2r2, tab.ids
    for i in range(O.shape[0]):
        o0, o1, o2, d0, d1, d2 = O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2]
        s_do = _dot(d0, d1, d2, o0, o1, o2)
        s_oo = _dot(o0, o1, o2, o0, o1, o2)
        tmin = k[K_INF]
        jmin = -1
        for j in range(C.shape[0]):
            b = s_do - _dot(d0, d1, d2, C[j, 0], C[j, 1], C[j, 2])
            c = s_oo - k[K_TWO] * _dot(o0, o1, o2, C[j, 0], C[j, 1], C[j, 2]) + c2r2[j]
            disc = b * b - c
            sq = np.sqrt(max(disc, k[K_ZERO]))
            t0 = -b - sq
            t = t0 if t0 > 0 else -b + sq
            if not (disc >= 0 and t > 0):
                t = k[K_INF]
            tmin, jmin = _first_min(t, j, tmin, jmin)
        _fold_dense(T, I, i, tmin, jmin, ids)


@_inline
def _bound_hit(o0, o1, o2, d0, d1, d2, c0, c1, c2, c2r2, r, best_t, k):
    """`raycast._sphere_mask` for one ray and one bounding sphere (the matmul form)."""
    b = _dot(d0, d1, d2, o0, o1, o2) - _dot(d0, d1, d2, c0, c1, c2)
    c = _dot(o0, o1, o2, o0, o1, o2) - k[K_TWO] * _dot(o0, o1, o2, c0, c1, c2) + c2r2
    return b * b >= c and (b < 0 or c < 0) and -b - r < best_t


@_inline
def _member_kept(o0, o1, o2, d0, d1, d2, c0, c1, c2, rb, best_t):
    """The member test of `raycast._bounding_sphere_candidates` for one ray and one primitive (the `_dot3` form)."""
    oc0, oc1, oc2 = o0 - c0, o1 - c1, o2 - c2
    b = _dot(d0, d1, d2, oc0, oc1, oc2)
    c = _dot(oc0, oc1, oc2, oc0, oc1, oc2) - rb * rb
    return b * b >= c and (b < 0 or c < 0) and -b - rb < best_t


@_inline
def _cylinder_t(o0, o1, o2, d0, d1, d2, r, h, k):
    """The closest positive t of `raycast._hit_cylinders` (side, then caps) in a cylinder's frame, inf on a miss."""
    eps = k[K_CYL_EPS]
    a = d0 * d0 + d1 * d1
    b = o0 * d0 + o1 * d1
    c = o0 * o0 + o1 * o1 - r * r
    disc = b * b - a * c
    good = disc >= 0 and a > eps
    sq = np.sqrt(max(disc, k[K_ZERO]))
    a_safe = a if a > eps else k[K_ONE]
    best = k[K_INF]
    for ts in ((-b - sq) / a_safe, (-b + sq) / a_safe):
        if good and ts > 0 and abs(o2 + ts * d2) <= h:
            best = min(best, ts)
    dz_ok = abs(d2) > eps
    dz_safe = d2 if dz_ok else eps
    for sgn in (-k[K_ONE], k[K_ONE]):
        tc = (sgn * h - o2) / dz_safe
        x = o0 + tc * d0
        y = o1 + tc * d1
        if dz_ok and tc > 0 and x * x + y * y <= r * r:
            best = min(best, tc)
    return best


@_inline
def _exact_t(o0, o1, o2, d0, d1, d2, cyl, C, R, H, r, h, p, k):
    """A box's slab t or a cylinder's t for primitive p, in its frame (`raycast._local_pairs`: R^T (o - c), R^T d)."""
    oc0, oc1, oc2 = o0 - C[p, 0], o1 - C[p, 1], o2 - C[p, 2]
    l0 = _dot(R[p, 0, 0], R[p, 1, 0], R[p, 2, 0], oc0, oc1, oc2)
    l1 = _dot(R[p, 0, 1], R[p, 1, 1], R[p, 2, 1], oc0, oc1, oc2)
    l2 = _dot(R[p, 0, 2], R[p, 1, 2], R[p, 2, 2], oc0, oc1, oc2)
    m0 = _dot(R[p, 0, 0], R[p, 1, 0], R[p, 2, 0], d0, d1, d2)
    m1 = _dot(R[p, 0, 1], R[p, 1, 1], R[p, 2, 1], d0, d1, d2)
    m2 = _dot(R[p, 0, 2], R[p, 1, 2], R[p, 2, 2], d0, d1, d2)
    if cyl:
        return _cylinder_t(l0, l1, l2, m0, m1, m2, r[p], h[p], k)
    return _slab_t(l0, l1, l2, m0, m1, m2, H[p, 0], H[p, 1], H[p, 2], k)


@_inline
def _largest_id_min(t, pid, tmin, idmax, best_t):
    """The running minimum of a culled kind, the largest primitive id among equal t below best_t
    (`raycast._reduce_pairs`)."""
    if t < tmin:
        return t, pid
    if t == tmin and t < best_t and pid > idmax:
        return tmin, pid
    return tmin, idmax


@_kernel
def _culled(O, D, T, I, cyl, tab, k):
    """`raycast._hit_boxes` (cyl False) or `_hit_cylinders` (cyl True) on a `CulledTable`: bounding-sphere
    culling (two levels when groups exist) against the ray's best t before the kind, then the exact test, folded
    as `raycast._reduce_pairs` folds (the smallest t; among equal t the largest primitive id)."""
    C, R, H, r, h, c2r2b, rb, ids = tab.C, tab.R, tab.H, tab.r, tab.h, tab.c2r2_bound, tab.r_bound, tab.ids
    GC, Gc2r2, Gr, Gmem = tab.G_C, tab.G_c2r2, tab.G_r, tab.G_members
    n_groups = GC.shape[0]
    for i in range(O.shape[0]):
        o0, o1, o2, d0, d1, d2 = O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2]
        best_t = T[i]
        tmin = k[K_INF]
        idmax = -1
        for g in range(n_groups if n_groups > 0 else C.shape[0]):
            if n_groups > 0:
                if not _bound_hit(o0, o1, o2, d0, d1, d2, GC[g, 0], GC[g, 1], GC[g, 2], Gc2r2[g], Gr[g], best_t, k):
                    continue
                n_members = Gmem.shape[1]
            else:
                if not _bound_hit(o0, o1, o2, d0, d1, d2, C[g, 0], C[g, 1], C[g, 2], c2r2b[g], rb[g], best_t, k):
                    continue
                n_members = 1
            for m in range(n_members):
                p = Gmem[g, m] if n_groups > 0 else g
                if p < 0 or (n_groups > 0 and not _member_kept(o0, o1, o2, d0, d1, d2, C[p, 0], C[p, 1], C[p, 2],
                                                                 rb[p], best_t)):
                    continue
                t = _exact_t(o0, o1, o2, d0, d1, d2, cyl, C, R, H, r, h, p, k)
                tmin, idmax = _largest_id_min(t, ids[p], tmin, idmax, best_t)
        if tmin < best_t:
            T[i], I[i] = tmin, idmax


@_kernel
def _misses_at_infinity(T, I, k):
    """Shadow rays: a ray that met nothing before its t_max reports t = inf (as `Scene.intersect` does)."""
    for i in range(T.shape[0]):
        if I[i] < 0:
            T[i] = k[K_INF]


def closest_hits(O, D, T, I, tables: KernelTables, shadow: bool) -> None:
    """Every ray's closest hit, into T [N] and I [N] (T holds t_max for shadow rays, inf otherwise; I -1). The
    kinds in `Scene.intersect`'s order: rects, big boxes, spheres, boxes, cylinders."""
    k = tables.k
    _rects(O, D, T, I, tables.rect, k)
    _dense_boxes(O, D, T, I, tables.box_big, k)
    _spheres(O, D, T, I, tables.sphere, k)
    _culled(O, D, T, I, False, tables.box, k)
    _culled(O, D, T, I, True, tables.cylinder, k)
    if shadow:
        _misses_at_infinity(T, I, k)


def _arr(q: dict | None, key: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """A packed table as a contiguous numpy array; an empty one of ``shape``'s trailing sizes where absent."""
    if q is None or key not in q:
        return np.zeros((0,) + shape, dtype=dtype)
    return np.ascontiguousarray(q[key].numpy())


def kernel_tables(pk: dict, torch_dtype: torch.dtype) -> KernelTables:
    """`Scene._pack`'s CPU tables of ``torch_dtype`` (float32 or float64) as the kernel's tables (empty ones for
    absent kinds) and its `kernel_constants`."""
    dtype = torch.empty(0, dtype=torch_dtype).numpy().dtype.type

    def a(q, key, shape, kind=dtype):
        return _arr(q, key, shape, kind)

    i8 = np.int64
    rq, bb, sp = pk.get("rect"), pk.get("box_big"), pk.get("sphere")
    rect = RectTable(N=a(rq, "N", (3,)), U=a(rq, "U", (3,)), V=a(rq, "V", (3,)), H=a(rq, "H", (2,)),
                     cU=a(rq, "cU", ()), cV=a(rq, "cV", ()), cN=a(rq, "cN", ()), ids=a(rq, "ids", (), i8))
    rflat = np.zeros((3, 0), dtype=dtype) if bb is None else a(bb, "Rflat", ())  # [3, 3P]
    box_big = DenseBoxTable(Rflat=rflat, cR=a(bb, "cR", (3,)), H=a(bb, "H", (3,)), ids=a(bb, "ids", (), i8))
    sphere = SphereTable(C=a(sp, "C", (3,)), c2r2=a(sp, "c2r2", ()), ids=a(sp, "ids", (), i8))

    def culled(q):
        return CulledTable(C=a(q, "C", (3,)), R=a(q, "R", (3, 3)), H=a(q, "H", (3,)), r=a(q, "r", ()), h=a(q, "h", ()),
                           c2r2_bound=a(q, "c2r2_bound", ()), r_bound=a(q, "r_bound", ()), ids=a(q, "ids", (), i8),
                           G_C=a(q, "G_C", (3,)), G_c2r2=a(q, "G_c2r2", ()), G_r=a(q, "G_r", ()),
                           G_members=a(q, "G_members", (1,), i8))

    return KernelTables(rect, box_big, sphere, culled(pk.get("box")), culled(pk.get("cylinder")),
                        kernel_constants(dtype))


def intersect_compiled(tables: KernelTables, origins: Tensor, directions: Tensor,
                       t_max: Tensor | None) -> tuple[Tensor, Tensor]:
    """`Scene.intersect` through `closest_hits`: CPU origins and unit directions [N, 3] of the tables' dtype,
    t_max [N] of that dtype or None (`scene._compiled_cast_applies` checks) -> (t [N], primitive id [N] int64),
    misses t = inf and id = -1."""
    o = np.ascontiguousarray(origins.detach().numpy())
    d = np.ascontiguousarray(directions.detach().numpy())
    n = o.shape[0]
    t = np.full(n, math.inf, dtype=o.dtype) if t_max is None else np.array(t_max.detach().numpy(), dtype=o.dtype)
    ids = np.full(n, -1, dtype=np.int64)
    if n:
        closest_hits(o, d, t, ids, tables, t_max is not None)
    return torch.from_numpy(t), torch.from_numpy(ids)
