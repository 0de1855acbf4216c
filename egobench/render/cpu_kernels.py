"""numba kernels of the compiled CPU backend (3DGS; gsplat 1.5.3 semantics, as torch_backend.py).

Projection (forward and backward, per Gaussian), tile binning (sequential counting sort: the
intersection order is (bin, depth, Gaussian index), as the torch backend's stable sorts), and
tile compositing (forward front to back, backward back to front recovering T by division, as
gsplat's CUDA kernels). Inside a tile the loop runs Gaussian-major over the pixels of the
Gaussian's opacity-aware bounding box only, with per-pixel state in tile-local arrays, so the
cost follows the Gaussian-pixel pairs that matter rather than tiles x candidates.

Determinism: parallel loops (``prange``) only write disjoint slices (one tile, one Gaussian, or
one fixed chunk of Gaussians); every sum over Gaussians or intersections is then reduced
sequentially in a fixed order, so results do not depend on the number of threads.
Compiled once per dtype and cached on disk (numba ``cache=True``: ``__pycache__`` beside this
file, or numba's user-wide cache directory / ``NUMBA_CACHE_DIR`` when that is not writable).
Threads: numba's OpenMP layer where it exists (see below); the caller sets the count (torch's).
Pixel coordinates: gsplat's (centre of pixel (u, v) at (u + 0.5, v + 0.5)).
"""

from __future__ import annotations

import math

import os

# Workers run one thread each when Snakemake runs jobs side by side: Snakemake exports
# OMP_NUM_THREADS={threads} to every shell job (config resources.<step>.threads, default 1); torch
# reads it, `cpu_backend` sets numba's count to torch's on every call, and numba's pool is capped to
# it as well (`host.cap_numba_pool`, run by ``import egobench`` before numba loads).
# EGOBENCH_RASTER_THREADS, when set, gives the kernels their own count instead (`host.raster_threads`).
import numba
import numpy as np
import llvmlite.binding as ll
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.core.compiler import Compiler
from numba.extending import intrinsic, overload

# Threading layer: OpenMP first. numba's workqueue workers sleep after every parallel loop, and on the 2-core
# VM a worker idle for a few ms took ~1 ms to wake; training calls ~8 parallel kernels a step between torch
# operations, so its kernels barely scaled (ours_2dgs at 128 px: 26.6 it/s on 2 threads against 26.4 on
# 1). OpenMP's workers spin briefly first: 44.0-47.3 it/s, 1.58x (512 px: 1.78-1.84x). With the other core
# busy it is ~30 % slower than workqueue (both below one thread). results/speed/README.md, "numba's
# threading layer".
# An explicit NUMBA_THREADING_LAYER is respected; where OpenMP is missing numba takes the next layer.
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
    numba.config.THREADING_LAYER = "default"


def _start_pool_keeping_torch_threads() -> None:
    """Starts numba's thread pool now. Starting its OpenMP layer sets the OpenMP thread count of the
    process, which torch shares (one libgomp is loaded), so torch's own count is put back; numba gives
    each parallel loop its own count (`numba.set_num_threads`)."""
    import torch

    torch_threads = torch.get_num_threads()
    numba.get_num_threads()  # starts the pool
    if torch.get_num_threads() != torch_threads:
        torch.set_num_threads(torch_threads)


_start_pool_keeping_torch_threads()

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_STOP = 1e-4
EXTENT_SIGMAS = 3.33
SIGMA_SKIP = 5.55  # exp(-5.55) < 1/255: pairs with a larger exponent are skipped without exp()
CHUNK = 256  # Gaussians per chunk of the projection backward's pose-gradient partial sums


@njit(cache=True, inline="always")
def quat_rotmat(qw, qx, qy, qz, R):
    """Normalised quaternion -> rotation matrix R [3, 3] (filled in place; scratch reused: no
    allocation per Gaussian), the normalised components and 1/|q|."""
    nrm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    inv = 1.0 / max(nrm, 1e-12)
    w, x, y, z = qw * inv, qx * inv, qy * inv, qz * inv
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R, w, x, y, z, inv


@njit(cache=True, inline="always")
def _argmin3(s0, s1, s2):
    a = 0
    if s1 < s0:
        a = 1
    if s2 < (s1 if a == 1 else s0):
        a = 2
    return a


@njit(cache=True, inline="always")
def _clip_limits(cam, width, height):
    """Bounds of x/z (right, left) and y/z (down, up) beyond which the EWA Jacobian is evaluated at
    the bound (gsplat: the image plus 30 % of the half field of view) -> (lxp, lxn, lyp, lyn)."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lxp = (width - cx) / fx + 0.3 * tan_fovx
    lxn = cx / fx + 0.3 * tan_fovx
    lyp = (height - cy) / fy + 0.3 * tan_fovy
    lyn = cy / fy + 0.3 * tan_fovy
    return lxp, lxn, lyp, lyn


#: The projection's per-chunk scratch: rows of CHUNK entries in one flat array each, indexed with unsigned
#: offsets (no wrap-around code), so that the Gaussian loop reads and writes at unit stride through few base
#: pointers and LLVM vectorizes it (8 float64 lanes); row k starts at ROW[k].
ROW = tuple(np.uint64(k * CHUNK) for k in range(16))
_U1, _U2, _U3 = np.uint64(1), np.uint64(2), np.uint64(3)


@njit(cache=True, inline="always")
def gather_chunk(means, quats, scales, n0, L, normal_axis, R, g_in, g_rot):
    """Per-Gaussian inputs of Gaussians [n0, n0 + L) -> g_in [6 CHUNK] (input dtype: rows 0-2 the mean, 3-5
    the scales), g_rot [>= 12 CHUNK] (rows 0-8 the rotation matrix row-major, 9-11 its column of the
    normal: normal_axis, or the shortest axis where it is -1)."""
    for j in range(L):
        n = n0 + j
        R, _, _, _, _, _ = quat_rotmat(quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3], R)
        ax = _argmin3(scales[n, 0], scales[n, 1], scales[n, 2]) if normal_axis < 0 else normal_axis
        for r in range(3):
            for c in range(3):
                g_rot[(r * 3 + c) * CHUNK + j] = R[r, c]
            g_rot[(9 + r) * CHUNK + j] = R[r, ax]
            g_in[r * CHUNK + j] = means[n, r]
            g_in[(3 + r) * CHUNK + j] = scales[n, r]


@njit(cache=True, inline="always")
def _gather_extents(opac, n0, L, g_rot):
    """g_rot rows 12-13 for Gaussians [n0, n0 + L): the opacity-aware extent in sigmas, and 1 where the
    opacity reaches ALPHA_MIN (else 0)."""
    for j in range(L):
        ext = EXTENT_SIGMAS
        op = opac[n0 + j]
        if op >= ALPHA_MIN:
            ext = min(ext, math.sqrt(2.0 * math.log(op / ALPHA_MIN)))
        g_rot[12 * CHUNK + j] = ext
        g_rot[13 * CHUNK + j] = 1.0 if op >= ALPHA_MIN else 0.0


@njit(cache=True, inline="always")
def chunk_scratch(ch, N, dtype, n_rot, n_out):
    """Chunk ch of N Gaussians -> (first Gaussian n0, count L, g_in [6 CHUNK] of dtype, g_rot [n_rot CHUNK],
    out [n_out CHUNK]): the scratch of `gather_chunk` and a per-pose loop."""
    n0 = ch * CHUNK
    return n0, min(N, n0 + CHUNK) - n0, np.empty(6 * CHUNK, dtype), np.empty(n_rot * CHUNK), np.empty(n_out * CHUNK)


@njit(cache=True, inline="always")
def view_rows(V):
    """World-to-camera V [4, 4] -> its first three rows as 12 scalars (row-major)."""
    return (V[0, 0], V[0, 1], V[0, 2], V[0, 3], V[1, 0], V[1, 1], V[1, 2], V[1, 3],
            V[2, 0], V[2, 1], V[2, 2], V[2, 3])


@njit(cache=True, inline="always")
def view_point(v, m0, m1, m2):
    """World point (m0, m1, m2) in the camera frame of one pose (`view_rows` v) -> (x, y, z)."""
    return (v[0] * m0 + v[1] * m1 + v[2] * m2 + v[3], v[4] * m0 + v[5] * m1 + v[6] * m2 + v[7],
            v[8] * m0 + v[9] * m1 + v[10] * m2 + v[11])


@njit(cache=True, inline="always")
def camera_point(V, means, n):
    """Camera-frame centre (x, y, z) of Gaussian n under world-to-camera V [4, 4]."""
    return view_point(view_rows(V), means[n, 0], means[n, 1], means[n, 2])


@njit(cache=True, inline="always")
def rotated_axis(v, r0, r1, r2, sc):
    """A Gaussian's axis (r0, r1, r2) (a column of its rotation) scaled by sc, in the camera frame of one
    pose (`view_rows` v) -> V[:3, :3] r sc (3 scalars)."""
    return ((v[0] * r0 + v[1] * r1 + v[2] * r2) * sc, (v[4] * r0 + v[5] * r1 + v[6] * r2) * sc,
            (v[8] * r0 + v[9] * r1 + v[10] * r2) * sc)


@njit(cache=True, inline="always")
def chunk_camera_point(v, g_in, j):
    """Camera-frame centre (x, y, z) of chunk entry j (`gather_chunk`) under one pose (`view_rows`)."""
    R_ = ROW
    return view_point(v, g_in[j], g_in[R_[1] + j], g_in[R_[2] + j])


@njit(cache=True, inline="always")
def _project_chunk(v, g_in, g_rot, L, cam, lims, eps2d, near, far, width, height, out):
    """One pose (v: `view_rows`) and the chunk's Gaussians (`gather_chunk`, `_gather_extents`) -> out [8 CHUNK]: rows
    u, v, depth, conic (3), radii x, y (0 where culled). Branch-free: the loop vectorizes."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lxp, lxn, lyp, lyn = lims
    R_ = ROW
    for jj in range(L):
        j = np.uint64(jj)
        x, y, z = chunk_camera_point(v, g_in, j)
        in_depth = (z >= near) & (z <= far)
        zs = z if in_depth else 1.0
        inv_z = 1.0 / zs
        tx = min(max(x * inv_z, -lxn), lxp)
        ty = min(max(y * inv_z, -lyn), lyp)
        j00, j11 = fx * inv_z, fy * inv_z
        c00 = eps2d
        c11 = eps2d
        c01 = 0.0
        for c in range(3):
            mc0, mc1, mc2 = rotated_axis(v, g_rot[R_[c] + j], g_rot[R_[3 + c] + j], g_rot[R_[6 + c] + j],
                                         g_in[R_[3 + c] + j])
            a0 = j00 * (mc0 - tx * mc2)
            a1 = j11 * (mc1 - ty * mc2)
            c00 += a0 * a0
            c11 += a1 * a1
            c01 += a0 * a1
        det = c00 * c11 - c01 * c01
        valid = in_depth & (det > 0)
        det_s = det if valid else 1.0
        u = fx * x * inv_z + cx
        w = fy * y * inv_z + cy
        out[j], out[R_[1] + j], out[R_[2] + j] = u, w, z
        out[R_[3] + j], out[R_[4] + j], out[R_[5] + j] = c11 / det_s, -c01 / det_s, c00 / det_s
        rx = math.ceil(g_rot[R_[12] + j] * math.sqrt(max(c00, 0.0)))
        ry = math.ceil(g_rot[R_[12] + j] * math.sqrt(max(c11, 0.0)))
        valid = valid & (g_rot[R_[13] + j] != 0.0) & ((rx > 0) | (ry > 0))
        keep = valid & (u + rx > 0) & (u - rx < width) & (w + ry > 0) & (w - ry < height)
        out[R_[6] + j] = rx if keep else 0.0
        out[R_[7] + j] = ry if keep else 0.0


@njit(cache=True, inline="always")
def _scatter_chunk(out, q0, L, means2d, depths, conics, radii):
    """`_project_chunk`'s rows -> flat outputs at entries [q0, q0 + L) (entry = pose * N + Gaussian):
    means2d [2 per entry], depths, conics [3], radii [2] int32."""
    R_ = ROW
    for jj in range(L):
        j = np.uint64(jj)
        q = q0 + j
        means2d[q * _U2], means2d[q * _U2 + _U1], depths[q] = out[j], out[R_[1] + j], out[R_[2] + j]
        conics[q * _U3], conics[q * _U3 + _U1], conics[q * _U3 + _U2] = out[R_[3] + j], out[R_[4] + j], out[R_[5] + j]
        radii[q * _U2], radii[q * _U2 + _U1] = np.int32(out[R_[6] + j]), np.int32(out[R_[7] + j])


@njit(cache=True, inline="always")
def normals_chunk(v, g_in, g_rot, L, q0, normals):
    """Camera-frame normals (g_rot's normal axis, facing the camera) of the chunk under one pose ->
    flat normals [3 per entry] at entries [q0, q0 + L)."""
    R_ = ROW
    for jj in range(L):
        j = np.uint64(jj)
        x, y, z = chunk_camera_point(v, g_in, j)
        nx, ny, nz = rotated_axis(v, g_rot[R_[9] + j], g_rot[R_[10] + j], g_rot[R_[11] + j], 1.0)  # (x 1.0: exact)
        sgn = 1.0 if -(nx * x + ny * y + nz * z) > 0 else -1.0
        q = q0 + j
        normals[q * _U3], normals[q * _U3 + _U1], normals[q * _U3 + _U2] = sgn * nx, sgn * ny, sgn * nz


@njit(cache=True, parallel=True)
def project_fwd(means, quats, scales, opac, viewmats, cam, width, height, eps2d, near, far, want_normal,
                means2d, conics, depths, radii, normals):
    """means [N,3], quats [N,4], scales [N,3], opac [N], viewmats [I,4,4], cam (fx, fy, cx, cy)
    -> fills means2d [I,N,2], conics [I,N,3], depths [I,N], radii [I,N,2] int32, normals [I,N,3].
    Per chunk of Gaussians: their inputs gathered once, then per pose a vectorized loop over them
    (`_project_chunk`; 3-4x faster on 6 poses than a scalar loop per Gaussian, bitwise the same)."""
    N = means.shape[0]
    I = viewmats.shape[0]
    lims = _clip_limits(cam, width, height)
    m2f, conf, depf, radf = means2d.reshape(I * N * 2), conics.reshape(I * N * 3), depths.reshape(I * N), \
        radii.reshape(I * N * 2)
    nrmf = normals.reshape(normals.size)
    for ch in prange((N + CHUNK - 1) // CHUNK):
        n0, L, g_in, g_rot, out = chunk_scratch(ch, N, means.dtype, 14, 8)
        gather_chunk(means, quats, scales, n0, L, -1, np.empty((3, 3)), g_in, g_rot)
        _gather_extents(opac, n0, L, g_rot)
        for i in range(I):
            v = view_rows(viewmats[i])
            q0 = np.uint64(i * N + n0)
            _project_chunk(v, g_in, g_rot, L, cam, lims, eps2d, near, far, width, height, out)
            _scatter_chunk(out, q0, L, m2f, depf, conf, radf)
            if want_normal:
                normals_chunk(v, g_in, g_rot, L, q0, nrmf)


@njit(cache=True, inline="always")
def _or_nonzero(live, a, n0, L):
    """live[j] |= a[n0 + j] != 0 for j < L (live, a: 1D rows; unsigned indices: the loop vectorizes)."""
    for jj in range(L):
        j = np.uint64(jj)
        live[j] = live[j] | (a[np.uint64(n0) + j] != 0.0)


@njit(cache=True, inline="always")
def live_pairs(g_means2d, g_second, g_depths, g_normals, with_normals, n0, L, live):
    """live [I, >= L] bool: whether any upstream gradient of (pose i, Gaussian n0 + j), j < L, is non-zero
    (every projection-backward term is linear in them; most pairs of a rolling-shutter render reach no
    pixel and are skipped). Channel-first gradients: g_means2d [2,I,N], g_second [k,I,N] (conics or ray
    transforms), g_depths [I,N], g_normals [3,I,N] (read when with_normals). Channel by channel at unit
    stride: a test per pair read up to 15 channels I*N apart, ~3 ms of a 128 px 2DGS step's 3.4 ms."""
    for i in range(g_depths.shape[0]):
        row = live[i]
        for j in range(L):
            row[j] = False
        _or_nonzero(row, g_depths[i], n0, L)
        for c in range(g_means2d.shape[0]):
            _or_nonzero(row, g_means2d[c, i], n0, L)
        for c in range(g_second.shape[0]):
            _or_nonzero(row, g_second[c, i], n0, L)
        if with_normals:
            for c in range(g_normals.shape[0]):
                _or_nonzero(row, g_normals[c, i], n0, L)


@njit(cache=True, inline="always")
def live_chunk(ch, N, g_means2d, g_second, g_depths, g_normals, with_normals):
    """Chunk ch of N Gaussians -> (first Gaussian n0, count L, `live_pairs`' mask [I, CHUNK] for them):
    the projection backwards' per-chunk start."""
    n0 = ch * CHUNK
    L = min(N, n0 + CHUNK) - n0
    live = np.empty((g_depths.shape[0], CHUNK), np.bool_)
    live_pairs(g_means2d, g_second, g_depths, g_normals, with_normals, n0, L, live)
    return n0, L, live


@njit(cache=True, inline="always")
def any_live(live, j):
    """Whether column j of `live_pairs`' mask has a live pose."""
    for i in range(live.shape[0]):
        if live[i, j]:
            return True
    return False


@njit(cache=True, inline="always")
def zero_gaussian_grads(g_means, g_quats, g_scales, n):
    """The gradients of a Gaussian without any live pair: zeros."""
    for b in range(3):
        g_means[n, b] = 0.0
        g_scales[n, b] = 0.0
    for b in range(4):
        g_quats[n, b] = 0.0


@njit(cache=True, inline="always")
def _cov2d_rows(V, R, scales, n, j00, j11, tx, ty, eps2d, Mc, A0, A1):
    """Fills Mc [3, 3] = V[:3, :3] R diag(s) and the rows A0, A1 [3] of J Mc (J: EWA Jacobian with
    j00, j11, tx, ty) -> 2D covariance (c00, c11, c01) with the eps2d dilation."""
    v = view_rows(V)
    for c in range(3):
        Mc[0, c], Mc[1, c], Mc[2, c] = rotated_axis(v, R[0, c], R[1, c], R[2, c], scales[n, c])
        A0[c] = j00 * (Mc[0, c] - tx * Mc[2, c])
        A1[c] = j11 * (Mc[1, c] - ty * Mc[2, c])
    c00 = eps2d + A0[0] * A0[0] + A0[1] * A0[1] + A0[2] * A0[2]
    c11 = eps2d + A1[0] * A1[0] + A1[1] * A1[1] + A1[2] * A1[2]
    c01 = A0[0] * A1[0] + A0[1] * A1[1] + A0[2] * A1[2]
    return c00, c11, c01


@njit(cache=True, inline="always")
def _conic_grad(gA, gB, gC, c00, c11, c01, det, valid):
    """dL/d conic (a, b, c) = inverse covariance -> dL/d covariance (g00, g11, g01); culled entries
    pass the gradient of torch's det = 1 substitute."""
    if valid:
        S = (gA * c11 - gB * c01 + gC * c00) / (det * det)
        return gC / det - S * c11, gA / det - S * c00, -gB / det + 2.0 * S * c01
    return gC, gA, -gB


@njit(cache=True, inline="always")
def _cov2d_rows_grad(g00, g11, g01, A0, A1, Mc, j00, j11, tx, ty, gMc):
    """Backward of `_cov2d_rows`: fills gMc [3, 3] -> (dL/dj00, dL/dj11, dL/dtx, dL/dty)."""
    g_j00 = 0.0
    g_j11 = 0.0
    g_tx = 0.0
    g_ty = 0.0
    gMc[:] = 0.0
    for c in range(3):
        ga0 = 2.0 * g00 * A0[c] + g01 * A1[c]
        ga1 = 2.0 * g11 * A1[c] + g01 * A0[c]
        gMc[0, c] += j00 * ga0
        gMc[2, c] -= j00 * tx * ga0 + j11 * ty * ga1
        gMc[1, c] += j11 * ga1
        g_tx -= j00 * ga0 * Mc[2, c]
        g_ty -= j11 * ga1 * Mc[2, c]
        g_j00 += ga0 * (Mc[0, c] - tx * Mc[2, c])
        g_j11 += ga1 * (Mc[1, c] - ty * Mc[2, c])
    return g_j00, g_j11, g_tx, g_ty


@njit(cache=True, inline="always")
def normal_grad(V, R, ax, x, y, z, g_normals, i, n, gnw):
    """Normal sgn * V[:3, :3] R[:, ax] (facing the camera at (x, y, z)): fills gnw [3] = dL/dR[:, ax]
    from g_normals[:, i, n] [3] -> sgn."""
    nx = V[0, 0] * R[0, ax] + V[0, 1] * R[1, ax] + V[0, 2] * R[2, ax]
    ny = V[1, 0] * R[0, ax] + V[1, 1] * R[1, ax] + V[1, 2] * R[2, ax]
    nz = V[2, 0] * R[0, ax] + V[2, 1] * R[1, ax] + V[2, 2] * R[2, ax]
    sgn = 1.0 if -(nx * x + ny * y + nz * z) > 0 else -1.0
    for r in range(3):
        for b in range(3):
            gnw[b] += V[r, b] * sgn * g_normals[r, i, n]
    return sgn


@njit(cache=True, inline="always")
def add_view_and_mean_grads(V, R, scales, means, n, gpc, gMc, sgn, g_normals, i, ax, want_normal, gv, gm):
    """p_c = V m + t, Mc = V R diag(s), normal = sgn V R[:, ax]: adds dL/dV[:3, :4] (row-major) to
    gv [12] and dL/dm to gm [3], from gpc = dL/dp_c, gMc [3, 3], g_normals[:, i, n] [3]."""
    for r in range(3):
        gv[r * 4 + 3] += gpc[r]
        for b in range(3):
            gm[b] += V[r, b] * gpc[r]
            gv[r * 4 + b] += gpc[r] * means[n, b]
            acc = 0.0
            for c in range(3):
                acc += gMc[r, c] * R[b, c] * scales[n, c]
            gv[r * 4 + b] += acc
            if want_normal:
                gv[r * 4 + b] += sgn * g_normals[r, i, n] * R[b, ax]


@njit(cache=True, inline="always")
def add_rot_scale_grads(V, R, scales, n, gMc, gnw, ax, gR, gs):
    """Mc = V R diag(s): adds dL/dR to gR [3, 3] (with the normal's gnw on column ax) and dL/ds to gs [3]."""
    for b in range(3):
        for c in range(3):
            gM = V[0, b] * gMc[0, c] + V[1, b] * gMc[1, c] + V[2, b] * gMc[2, c]
            gR[b, c] += gM * scales[n, c]
            gs[c] += gM * R[b, c]
        gR[b, ax] += gnw[b]


@njit(cache=True, inline="always")
def quat_grad(gR, qw, qx, qy, qz, qinv, g_quats, n):
    """dL/dR [3, 3] -> g_quats[n] = dL/dq through R(q / |q|) (qw..qz normalised, qinv = 1/|q|)."""
    gw = 2.0 * (qx * (gR[2, 1] - gR[1, 2]) + qy * (gR[0, 2] - gR[2, 0]) + qz * (gR[1, 0] - gR[0, 1]))
    gxx = (2.0 * qy * (gR[0, 1] + gR[1, 0]) + 2.0 * qz * (gR[0, 2] + gR[2, 0])
           - 4.0 * qx * (gR[1, 1] + gR[2, 2]) + 2.0 * qw * (gR[2, 1] - gR[1, 2]))
    gyy = (2.0 * qx * (gR[0, 1] + gR[1, 0]) + 2.0 * qz * (gR[1, 2] + gR[2, 1])
           - 4.0 * qy * (gR[0, 0] + gR[2, 2]) + 2.0 * qw * (gR[0, 2] - gR[2, 0]))
    gzz = (2.0 * qx * (gR[0, 2] + gR[2, 0]) + 2.0 * qy * (gR[1, 2] + gR[2, 1])
           - 4.0 * qz * (gR[0, 0] + gR[1, 1]) + 2.0 * qw * (gR[1, 0] - gR[0, 1]))
    dot = gw * qw + gxx * qx + gyy * qy + gzz * qz
    g_quats[n, 0] = (gw - qw * dot) * qinv
    g_quats[n, 1] = (gxx - qx * dot) * qinv
    g_quats[n, 2] = (gyy - qy * dot) * qinv
    g_quats[n, 3] = (gzz - qz * dot) * qinv


@njit(cache=True, parallel=True)
def project_bwd(means, quats, scales, viewmats, cam, width, height, eps2d, near, far, want_normal,
                g_means2d, g_conics, g_depths, g_normals,
                g_means, g_quats, g_scales, g_view_parts):
    """Backward of `project_fwd` for every entry (culled ones included, as torch's graph). Upstream
    gradients channel first (`reduce_isect_grad`'s layout): g_means2d [2,I,N], g_conics [3,I,N], g_depths
    [I,N], g_normals [3,I,N] (or [3,I,0]). Fills g_means [N,3], g_quats [N,4], g_scales [N,3] and
    g_view_parts [chunks, I, 12] (per-chunk partial dL/d viewmat[:3, :4], reduced in chunk order by the
    caller)."""
    N = means.shape[0]
    I = viewmats.shape[0]
    fx, fy = cam[0], cam[1]
    lxp, lxn, lyp, lyn = _clip_limits(cam, width, height)
    n_chunks = g_view_parts.shape[0]
    for ch in prange(n_chunks):
        R = np.empty((3, 3))  # scratch, reused for every Gaussian of the chunk
        gR = np.empty((3, 3))
        gs = np.empty(3)
        gm = np.empty(3)
        Mc = np.empty((3, 3))
        A0 = np.empty(3)
        A1 = np.empty(3)
        gMc = np.empty((3, 3))
        gnw = np.empty(3)
        n0, L, live = live_chunk(ch, N, g_means2d, g_conics, g_depths, g_normals, want_normal)
        for n in range(n0, n0 + L):
            if not any_live(live, n - n0):
                zero_gaussian_grads(g_means, g_quats, g_scales, n)
                continue
            R, qw, qx, qy, qz, qinv = quat_rotmat(quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3], R)
            ax = _argmin3(scales[n, 0], scales[n, 1], scales[n, 2])
            gR[:] = 0.0
            gs[:] = 0.0
            gm[:] = 0.0
            for i in range(I):
                if not live[i, n - n0]:
                    continue
                V = viewmats[i]
                x, y, z = camera_point(V, means, n)
                in_depth = z >= near and z <= far
                zs = z if in_depth else 1.0
                inv_z = 1.0 / zs
                rtx, rty = x * inv_z, y * inv_z
                tx = min(max(rtx, -lxn), lxp)
                ty = min(max(rty, -lyn), lyp)
                j00, j11 = fx * inv_z, fy * inv_z
                c00, c11, c01 = _cov2d_rows(V, R, scales, n, j00, j11, tx, ty, eps2d, Mc, A0, A1)
                det = c00 * c11 - c01 * c01
                g00, g11, g01 = _conic_grad(g_conics[0, i, n], g_conics[1, i, n], g_conics[2, i, n], c00, c11, c01,
                                            det, in_depth and det > 0)
                # means2d = (fx x / zs + cx, fy y / zs + cy); depth = z
                gx = g_means2d[0, i, n] * fx * inv_z
                gy = g_means2d[1, i, n] * fy * inv_z
                g_inv_z = g_means2d[0, i, n] * fx * x + g_means2d[1, i, n] * fy * y
                gz = g_depths[i, n]
                g_j00, g_j11, g_tx, g_ty = _cov2d_rows_grad(g00, g11, g01, A0, A1, Mc, j00, j11, tx, ty, gMc)
                g_inv_z += fx * g_j00 + fy * g_j11
                if rtx >= -lxn and rtx <= lxp:
                    gx += g_tx * inv_z
                    g_inv_z += g_tx * x
                if rty >= -lyn and rty <= lyp:
                    gy += g_ty * inv_z
                    g_inv_z += g_ty * y
                if in_depth:
                    gz -= g_inv_z * inv_z * inv_z
                gnw[:] = 0.0
                sgn = normal_grad(V, R, ax, x, y, z, g_normals, i, n, gnw) if want_normal else 0.0
                add_view_and_mean_grads(V, R, scales, means, n, (gx, gy, gz), gMc, sgn, g_normals, i, ax,
                                         want_normal, g_view_parts[ch, i], gm)
                add_rot_scale_grads(V, R, scales, n, gMc, gnw, ax, gR, gs)
            for b in range(3):
                g_means[n, b] = gm[b]
                g_scales[n, b] = gs[b]
            quat_grad(gR, qw, qx, qy, qz, qinv, g_quats, n)


@njit(cache=True)
def needed_bins(pixel_pose, tile_size, tiles_x, bin_needed):
    """bin_needed [I, tiles] bool |= the (pose, tile) bins that some pixel of pixel_pose [H, W] (pose index
    per pixel, 0..I-1) lies in. A pass over the pixels, a store only where the pose changes along a tile's row."""
    H, W = pixel_pose.shape
    for y in range(H):
        row = (y // tile_size) * tiles_x
        for tx in range(tiles_x):
            last = -1
            for x in range(tx * tile_size, min(W, (tx + 1) * tile_size)):
                p = pixel_pose[y, x]
                if p != last:
                    bin_needed[p, row + tx] = True
                    last = p


def bin_tiles(means2d, radii, depths, tile_size, tiles_x, tiles_y, bin_needed):
    """Intersections sorted by (bin, depth, Gaussian index): means2d [I,N,2], radii [I,N,2],
    depths [I,N], bin_needed [I, tiles] bool -> (flat_ids [M] int64 (image * N + Gaussian),
    bin_start [I * tiles + 1] int64). The depth order is a stable LSD radix sort of the depths'
    bit patterns (positive floats order like their bits), ties by (image, Gaussian)."""
    rect, vis, keys = visible_rects(means2d, radii, depths, tile_size, tiles_x, tiles_y, bin_needed)
    perm = _radix_order(keys.view(np.uint32 if keys.dtype == np.float32 else np.uint64), keys.dtype.itemsize * 8)
    return fill_bins(rect, vis, perm, depths.shape[1], tiles_x, bin_needed)


#: bits per pass of `_radix_order` (a 2048-bucket histogram stays in L1)
RADIX_BITS = 11


@njit(cache=True)
def _radix_order(ukeys, bits):
    """The stable ascending order [n] int64 of unsigned keys [n] (``bits`` wide): an LSD radix sort,
    RADIX_BITS per pass; equal keys keep their order."""
    n = ukeys.shape[0]
    perm, spare = np.arange(n), np.empty(n, np.int64)
    mask = (1 << RADIX_BITS) - 1
    for shift in range(0, bits, RADIX_BITS):
        start = np.zeros(mask + 2, np.int64)
        for j in range(n):
            start[((ukeys[j] >> shift) & mask) + 1] += 1
        for d in range(mask + 1):
            start[d + 1] += start[d]
        for j in range(n):
            q = perm[j]
            d = (ukeys[q] >> shift) & mask
            spare[start[d]] = q
            start[d] += 1
        perm, spare = spare, perm
    return perm


#: the fewest (image, Gaussian) pairs per thread for which `visible_rects` splits the work
RECT_PART_MIN = 4096


@njit(cache=True)
def _needed_boxes(bin_needed, tiles_x, tiles_y):
    """Per image, the bounding box of its needed bins in tiles -> (bx0, bx1, by0, by1) [I] (empty when
    none is needed): each image's tile ranges are clipped to it (as torch_backend)."""
    I = bin_needed.shape[0]
    bx0, bx1 = np.full(I, tiles_x, np.int64), np.zeros(I, np.int64)
    by0, by1 = np.full(I, tiles_y, np.int64), np.zeros(I, np.int64)
    for i in range(I):
        for t in range(tiles_x * tiles_y):
            if bin_needed[i, t]:
                tx, ty = t % tiles_x, t // tiles_x
                bx0[i], bx1[i] = min(bx0[i], tx), max(bx1[i], tx + 1)
                by0[i], by1[i] = min(by0[i], ty), max(by1[i], ty + 1)
    return bx0, bx1, by0, by1


@njit(cache=True)
def _rects_part(means2d, radii, depths, tile_size, tiles_x, tiles_y, boxes, k0, k1, rect, vis, keys):
    """The visible pairs among k0 <= k < k1 (k = image * N + Gaussian), in k order: their tile rectangles
    (x0, x1, y0, y1), k and depth written to rect, vis, keys from row k0 on -> their count."""
    N = depths.shape[1]
    if k1 <= k0:  # no pairs (also N = 0)
        return 0
    bx0, bx1, by0, by1 = boxes
    nv = k0
    for ii in range(k0 // N, (k1 + N - 1) // N):
        i = np.uint64(ii)
        x_lo, x_hi, y_lo, y_hi = bx0[i], bx1[i], by0[i], by1[i]
        for nn in range(max(k0 - ii * N, 0), min(k1 - ii * N, N)):
            n = np.uint64(nn)  # unsigned: no negative-index wraparound in the loads
            if radii[i, n, 0] <= 0 or radii[i, n, 1] <= 0:
                continue
            # rows first: with motion sampling most pairs miss their pose's band of rows
            my, ry = means2d[i, n, 1] / tile_size, radii[i, n, 1] / tile_size
            y0 = max(max(min(int(math.floor(my - ry)), tiles_y), 0), y_lo)
            y1 = min(max(min(int(math.ceil(my + ry)), tiles_y), 0), y_hi)
            if y1 <= y0:
                continue
            mx, rx = means2d[i, n, 0] / tile_size, radii[i, n, 0] / tile_size
            x0 = max(max(min(int(math.floor(mx - rx)), tiles_x), 0), x_lo)
            x1 = min(max(min(int(math.ceil(mx + rx)), tiles_x), 0), x_hi)
            if x1 <= x0:
                continue
            rect[nv, 0], rect[nv, 1], rect[nv, 2], rect[nv, 3] = x0, x1, y0, y1
            vis[nv] = ii * N + nn
            keys[nv] = depths[i, n]
            nv += 1
    return nv - k0


@njit(cache=True, parallel=True)
def _tile_rects(means2d, radii, depths, tile_size, tiles_x, tiles_y, boxes, parts, rect, vis, keys):
    """`_rects_part` over ``parts`` ranges of pairs in parallel (rows from each range's first pair on),
    then packed in order -> the count: the same rows as one range, for any number of parts."""
    total = depths.size
    counts = np.empty(parts, np.int64)
    for c in prange(parts):
        counts[c] = _rects_part(means2d, radii, depths, tile_size, tiles_x, tiles_y, boxes, c * total // parts,
                                (c + 1) * total // parts, rect, vis, keys)
    nv = counts[0]
    for c in range(1, parts):  # in order, each range moved down (never past its own rows): sequential
        k0 = c * total // parts
        for q in range(counts[c]):
            rect[nv + q, 0], rect[nv + q, 1] = rect[k0 + q, 0], rect[k0 + q, 1]
            rect[nv + q, 2], rect[nv + q, 3] = rect[k0 + q, 2], rect[k0 + q, 3]
            vis[nv + q], keys[nv + q] = vis[k0 + q], keys[k0 + q]
        nv += counts[c]
    return nv


def visible_rects(means2d, radii, depths, tile_size, tiles_x, tiles_y, bin_needed):
    """Tile rectangles [nv, 4] int32 (x0, x1, y0, y1) of the nv visible (image, Gaussian) pairs, their
    flat ids (ascending) and depths; the pairs in one range per kernel thread (one range: no parallel
    loop), the same result for any thread count."""
    boxes = _needed_boxes(bin_needed, tiles_x, tiles_y)
    rect, vis = np.empty((depths.size, 4), np.int32), np.empty(depths.size, np.int64)
    keys = np.empty(depths.size, depths.dtype)
    parts = min(numba.get_num_threads(), depths.size // RECT_PART_MIN)
    if parts <= 1:
        nv = _rects_part(means2d, radii, depths, tile_size, tiles_x, tiles_y, boxes, 0, depths.size, rect, vis, keys)
    else:
        nv = _tile_rects(means2d, radii, depths, tile_size, tiles_x, tiles_y, boxes, parts, rect, vis, keys)
    return rect[:nv], vis[:nv], keys[:nv]


#: the fewest depth-sorted visible pairs (entries of perm) per kernel thread for which `fill_bins` splits
#: the work; its serial prefix is O(threads x bins), small beside the fill at every size measured
FILL_PART_MIN = 4096


@njit(cache=True, inline="always")
def _bin_walk(rect, vis, perm, j0, j1, N, tiles_x, bin_needed, slot, flat_ids, place):
    """The intersections of the sorted entries j0 <= j < j1 (entry j: visible pair perm[j]; rect [nv, 4] its
    tiles, vis [nv] its flat id) with needed bins: counted into slot [I * tiles] (place False), or written
    at flat_ids[slot[b]], slot[b] advanced (place True)."""
    n_tiles = bin_needed.shape[1]
    for j in range(j0, j1):
        q = perm[j]
        k = vis[q]
        i = k // N
        for ty in range(rect[q, 2], rect[q, 3]):
            for tx in range(rect[q, 0], rect[q, 1]):
                t = ty * tiles_x + tx
                if bin_needed[i, t]:
                    b = i * n_tiles + t
                    if place:
                        flat_ids[slot[b]] = k
                    slot[b] += 1


@njit(cache=True)
def _slots_from_counts(counts):
    """counts [parts, bins] (each range's intersections per bin) -> (flat_ids [M] unfilled, bin_start
    [bins + 1]); counts become each range's first slot in every bin (ranges in order within a bin)."""
    n_bins = counts.shape[1]
    bin_start = np.empty(n_bins + 1, np.int64)
    s = 0
    for b in range(n_bins):
        bin_start[b] = s
        for p in range(counts.shape[0]):
            c = counts[p, b]
            counts[p, b] = s
            s += c
    bin_start[n_bins] = s
    return np.empty(s, np.int64), bin_start


@njit(cache=True)
def _fill_bins(rect, vis, perm, N, tiles_x, bin_needed):
    """Counting sort by bin of the visible pairs' intersections, the pairs taken in the order ``perm``
    (front to back; read through perm: a numpy [nv, 4] gather cost ~0.27 ms at 128 px) -> (flat_ids,
    bin_start), on one thread."""
    slot = np.zeros((1, bin_needed.size), np.int64)
    _bin_walk(rect, vis, perm, 0, perm.shape[0], N, tiles_x, bin_needed, slot[0], slot[0], False)
    flat_ids, bin_start = _slots_from_counts(slot)
    _bin_walk(rect, vis, perm, 0, perm.shape[0], N, tiles_x, bin_needed, slot[0], flat_ids, True)
    return flat_ids, bin_start


@njit(cache=True, parallel=True)
def _fill_bins_parts(rect, vis, perm, N, tiles_x, bin_needed, parts):
    """`_fill_bins` with the sorted entries cut into ``parts`` contiguous ranges, counted and written in
    parallel: the same arrays for any number of parts (a bin's entries stay in sorted order)."""
    nv = perm.shape[0]
    slot = np.zeros((parts, bin_needed.size), np.int64)
    for p in prange(parts):
        _bin_walk(rect, vis, perm, p * nv // parts, (p + 1) * nv // parts, N, tiles_x, bin_needed, slot[p],
                  slot[p], False)
    flat_ids, bin_start = _slots_from_counts(slot)
    for p in prange(parts):
        _bin_walk(rect, vis, perm, p * nv // parts, (p + 1) * nv // parts, N, tiles_x, bin_needed, slot[p],
                  flat_ids, True)
    return flat_ids, bin_start


def fill_bins(rect, vis, perm, N, tiles_x, bin_needed):
    """rect [nv, 4] int32 and vis [nv] (`visible_rects`), perm [nv] their depth order, bin_needed [I, tiles]
    -> (flat_ids [M] int64, bin_start [I * tiles + 1] int64): one range of entries per kernel thread (one
    range: no parallel loop), the same result for any thread count."""
    parts = min(numba.get_num_threads(), perm.shape[0] // FILL_PART_MIN)
    if parts <= 1:
        return _fill_bins(rect, vis, perm, N, tiles_x, bin_needed)
    return _fill_bins_parts(rect, vis, perm, N, tiles_x, bin_needed, parts)


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

COLUMN_GROUP = 8  # columns per contiguous block of a tile's state (tile sizes that are multiples of 8)
SIGMA_ROW = 5.56  # exponent bound of the rows a Gaussian can reach (> SIGMA_SKIP: a safe superset)
#: Taylor coefficients of exp, highest degree first (degree 13)
_EXP_COEFS = tuple(1.0 / math.factorial(d) for d in range(13, -1, -1))


def compute_constants(dtype) -> np.ndarray:
    """Constants of the compositing loops in the compute dtype (float32 inputs are composited in
    float32, as the torch backend and gsplat do; float64 in float64): numba types each pixel's
    arithmetic from these, so no float64 literal widens a float32 loop (8 lanes instead of 4)."""
    return np.array((0.5, 1.0, ALPHA_MAX, 0.0, 0.0625, 6.0) + _EXP_COEFS + (ALPHA_MIN, T_STOP, SIGMA_SKIP), dtype=dtype)


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


@njit(cache=True, inline="always")
def _extent(A, B, C, lo, r_axis, along_x):
    """Half-extent in pixels (1-pixel margin) of the ellipse d^T Q d <= 2 (SIGMA_ROW + log o) along x
    or y (Q = [[A, B], [B, C]]: Sigma_xx = C / det, Sigma_yy = A / det), at most the screen radius + 1."""
    ext = r_axis + 1.0
    det = A * C - B * B
    if det > 0.0 and A > 0.0 and C > 0.0:
        var = (C if along_x else A) / det
        ext = min(ext, math.sqrt(max(2.0 * (SIGMA_ROW + lo) * var, 0.0)) + 1.0)
    return ext


def column_group(tile_size: int) -> int:
    """Width of the column groups of a tile's state (see `raster_fwd`)."""
    for cw in (COLUMN_GROUP, 4):
        if tile_size % cw == 0:
            return cw
    return tile_size


@njit(cache=True, inline="always")
def _state_index(r, c, ts, cw):
    """State index of tile-local pixel (row r, column c): column groups of cw columns, each a
    contiguous [ts rows, cw] block."""
    return (c // cw) * (ts * cw) + r * cw + (c % cw)


@njit(cache=True, inline="always")
def _tile_centres(centres, x0, y0, ts, cw, cxt, cyt):
    """Pixel-centre coordinates of a tile's state entries, compute dtype."""
    for r in range(ts):
        for c in range(ts):
            q = _state_index(r, c, ts, cw)
            cxt[q] = centres[x0 + c]
            cyt[q] = centres[y0 + r]


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


#: columns of `gaussian_table`
TAB_COLS = 16


@njit(cache=True)
def rows_needed(flat_ids, n_rows):
    """Which of n_rows (image, Gaussian) table rows the compositing reads: flat_ids [K] (`bin_tiles`)
    -> bool [n_rows]. With motion sampling each pose's rows cover a band of the image, so only ~10 %
    of the rows are read (results/speed/README.md, "Tables for the rows read")."""
    needed = np.zeros(n_rows, np.bool_)
    for k in range(flat_ids.shape[0]):
        needed[flat_ids[k]] = True
    return needed


#: the feature rows' layout (`feature_table`): colour 0-2, depth 3, normal 4-6
DEPTH_CH = 3


@njit(cache=True, parallel=True)
def feature_table(colors, depths, normals, needed, out):
    """The compositing's per (image, Gaussian) features, only in the rows some intersection reads:
    colors [N, 3], depths [I, N], normals [I, N, 3] or [I, 0, 3], needed [I*N] bool (`rows_needed`)
    -> out [I*N, 4 (+ 3)] rows image * N + Gaussian: colour, depth (, normal); the other rows are left
    as they were (a 128 px training step reads ~11 % of them)."""
    I, N = depths.shape
    want_normal = normals.shape[1] > 0
    for ch in prange((N + CHUNK - 1) // CHUNK):
        for i in range(I):
            for n in range(ch * CHUNK, min(N, (ch + 1) * CHUNK)):
                g = i * N + n
                if not needed[g]:
                    continue
                out[g, 0], out[g, 1], out[g, 2], out[g, 3] = colors[n, 0], colors[n, 1], colors[n, 2], depths[i, n]
                if want_normal:
                    out[g, 4], out[g, 5], out[g, 6] = normals[i, n, 0], normals[i, n, 1], normals[i, n, 2]


@njit(cache=True, inline="always")
def needed_rows(needed, g0, g1, rows):
    """The rows g in [g0, g1) with needed[g] -> their count L, rows[:L] (branch-free; rows holds g1 - g0).
    The table kernels then read each needed row's inputs with a prefetch `GATHER_AHEAD` rows ahead: ~11 %
    of the rows are needed in a 128 px step, too sparse for the hardware prefetchers."""
    L = 0
    for g in range(g0, g1):
        rows[L] = g
        L += 1 if needed[g] else 0
    return L


@njit(cache=True, inline="always")
def row_ahead(rows, j, L):
    """The row `GATHER_AHEAD` entries after entry j of `needed_rows`' rows[:L] (the last one near the end):
    the row whose inputs the table kernels prefetch while they read entry j's."""
    return rows[min(j + GATHER_AHEAD, L - 1)]


@njit(cache=True, parallel=True)
def gaussian_table(means2d, conics, radii, log_opac, needed, tab):
    """Per (image, Gaussian) constants of the compositing loops, computed once instead of once per
    tile intersection: means2d [I,N,2], conics [I,N,3], radii [I,N,2], log_opac [N], needed [I*N]
    bool (`rows_needed`) -> tab [I*N, TAB_COLS] (compute dtype; rows not needed are left as they
    were), row image * N + Gaussian: 0-1 centre (x, y), 2-4 conic (A, B, C), 5 log opacity, 6-7
    footprint half-extents (x, y) (`_extent`), 8-14 the ellipse of `band_rows` (usable (1/0), C R2,
    det, 1/C, x half-extent xe, x offset of the topmost point dxt, its y offset dyt)."""
    I, N = means2d.shape[0], log_opac.shape[0]
    n_chunks = (N + CHUNK - 1) // CHUNK
    m2_rows, con_rows, rad_rows = means2d.reshape((I * N, 2)), conics.reshape((I * N, 3)), radii.reshape((I * N, 2))
    for ch in prange(n_chunks):
        rows = np.empty(CHUNK, np.int64)
        for i in range(I):
            L = needed_rows(needed, i * N + ch * CHUNK, i * N + min(N, (ch + 1) * CHUNK), rows)
            for j in range(L):
                ahead = row_ahead(rows, j, L)
                prefetch_row(m2_rows, ahead)
                prefetch_whole_row(con_rows, ahead)
                prefetch_row(rad_rows, ahead)
                g = rows[j]
                n = g - i * N
                A, B, C, lo = conics[i, n, 0], conics[i, n, 1], conics[i, n, 2], log_opac[n]
                tab[g, 0] = means2d[i, n, 0]
                tab[g, 1] = means2d[i, n, 1]
                tab[g, 2] = A
                tab[g, 3] = B
                tab[g, 4] = C
                tab[g, 5] = lo
                tab[g, 6] = _extent(A, B, C, lo, radii[i, n, 0], True)
                tab[g, 7] = _extent(A, B, C, lo, radii[i, n, 1], False)
                # the ellipse d^T Q d <= R2, slightly enlarged
                band_constants(float(A), float(B), float(C), 2.0 * (SIGMA_ROW + float(lo)) + 0.05, tab, g)
                tab[g, 15] = 0.0


@njit(cache=True, inline="always")
def floor_int(x):
    """int(floor(x)), rounded in float64 (exact for a float32 x): numba floors a float32 by calling a C
    helper per value, a float64 with one rounding instruction."""
    return int(math.floor(np.float64(x)))


@njit(cache=True, inline="always")
def ceil_int(x):
    """int(ceil(x)), rounded in float64 (as `floor_int`)."""
    return int(math.ceil(np.float64(x)))


@njit(cache=True, inline="always")
def band_values(A, B, C, r2):
    """`band_constants`' seven values for the ellipse d^T Q d <= r2, Q = [[A, B], [B, C]] (float64;
    branch-free, so loops over ellipses vectorize)."""
    det = A * C - B * B
    ok = (det > 0.0) & (A > 0.0) & (C > 0.0) & (r2 > 0.0)
    dets, As, Cs = (det, A, C) if ok else (1.0, 1.0, 1.0)
    dyt = math.sqrt(max(r2, 0.0) * As / dets)
    return 1.0 if ok else 0.0, Cs * r2, dets, 1.0 / Cs, math.sqrt(max(Cs * r2 / dets, 0.0)), -B / As * dyt, dyt


@njit(cache=True, inline="always")
def band_constants(A, B, C, r2, tab, g):
    """Columns 8-14 of table row g (read by `band_rows`) for the ellipse d^T Q d <= r2, Q = [[A, B],
    [B, C]] (float64): usable (1/0), C r2, det Q, 1/C, x half-extent, x and y offsets of the topmost point."""
    v = band_values(A, B, C, r2)
    for c in range(7):
        tab[g, 8 + c] = v[c]


@njit(cache=True, inline="always")
def band_rows(tab, g, x0, y0, qa, qb, ra, rb):
    """Rows [ra, rb) narrowed to those whose pixel centres in tile-local columns [qa, qb) can lie in
    the ellipse d^T Q d <= R2 of `gaussian_table` row g (a superset, 0.25-pixel margins). Over a band
    of columns the ellipse's top y_hi(dx) = (-B dx + sqrt(C R2 - det dx^2)) / C is concave, largest at
    the column nearest the topmost point (dxt, dyt); its bottom likewise at the one nearest (-dxt, -dyt)."""
    if tab[g, 8] == 0.0 or ra >= rb:
        return ra, rb
    mx, my, B = float(tab[g, 0]), float(tab[g, 1]), float(tab[g, 3])
    cr2, det, inv_c, xe = float(tab[g, 9]), float(tab[g, 10]), float(tab[g, 11]), float(tab[g, 12])
    dxt, dyt = float(tab[g, 13]), float(tab[g, 14])
    a = max(x0 + qa + 0.5 - mx, -xe)
    b = min(x0 + qb - 0.5 - mx, xe)
    if a > b + 0.25:  # the band lies beside the ellipse
        return ra, ra
    b = max(a, b)
    if a <= dxt and dxt <= b:
        y_hi = dyt
    else:
        dt = min(max(dxt, a), b)
        y_hi = (-B * dt + math.sqrt(max(cr2 - det * dt * dt, 0.0))) * inv_c
    if a <= -dxt and -dxt <= b:
        y_lo = -dyt
    else:
        db = min(max(-dxt, a), b)
        y_lo = (-B * db - math.sqrt(max(cr2 - det * db * db, 0.0))) * inv_c
    # rows whose centre y0 + r + 0.5 lies in [my + y_lo, my + y_hi], with a 0.25-pixel margin
    lo_r = min(max(my + y_lo - y0 - 0.75, -1.0), rb + 1.0)
    hi_r = min(max(my + y_hi - y0 - 0.25, -1.0), rb + 1.0)
    return max(ra, ceil_int(lo_r)), min(rb, floor_int(hi_r) + 1)


@njit(cache=True, inline="always")
def _footprint_tab(tab, g, x0, y0, ts, W, H):
    """Tile-local rows [ra, rb) and columns [ca, cb) the ellipse of `gaussian_table` row g can reach."""
    mx, my, ex, ey = tab[g, 0], tab[g, 1], float(tab[g, 6]), float(tab[g, 7])
    ra = max(0, floor_int(my - ey) - y0)
    rb = min(min(ts, H - y0), ceil_int(my + ey) - y0)
    ca = max(0, floor_int(mx - ex) - x0)
    cb = min(min(ts, W - x0), ceil_int(mx + ex) - x0)
    return ra, rb, ca, cb


@njit(cache=True, inline="always")
def bin_tile(b, n_tiles, tiles_x, ts, W, H, Iout):
    """Bin b (image i, tile t) -> (i, output image o, tile pixel bounds x0, y0, x1, y1)."""
    i, t = b // n_tiles, b % n_tiles
    o = 0 if Iout == 1 else i
    x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
    return i, o, x0, y0, min(x0 + ts, W), min(y0 + ts, H)


@njit(cache=True, inline="always")
def tile_of_bin(b, pix_view, ts, tiles_x):
    """`bin_tile` of bin b, its sizes read from the view map pix_view [Iout, H, W] (ts-pixel tiles, tiles_x
    per row) -> (i, o, x0, y0, x1, y1)."""
    Iout, H, W = pix_view.shape
    return bin_tile(b, tiles_x * ((H + ts - 1) // ts), tiles_x, ts, W, H, Iout)


@njit(cache=True, inline="always")
def _start_tile_fwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, one, T, row_active):
    """T = 1 at the tile's pixels whose view is i (counted per row in row_active) -> pixels to composite."""
    n_active = 0
    for v in range(y0, y1):
        for u in range(x0, x1):
            if pix_view[o, v, u] == i:
                T[_state_index(v - y0, u - x0, ts, cw)] = one
                row_active[v - y0] += 1
                n_active += 1
    return n_active


@njit(cache=True, inline="always")
def retire_stopped(row_active, sbuf, ra, rb, ca, cb, ts, cw):
    """Subtracts the pixels the last Gaussian stopped (sbuf) in rows [ra, rb), columns [ca, cb) from row_active."""
    for q in range(ca // cw, (cb - 1) // cw + 1):
        for r in range(ra, rb):
            base = q * ts * cw + r * cw
            for j in range(cw):
                row_active[r] -= sbuf[base + j]


@njit(cache=True, inline="always")
def finish_tile_fwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, T, last, acc, out_feat, out_T, out_last):
    """Writes the tile's state (|T|, last, accumulated features) to the output pixels whose view is i."""
    for v in range(y0, y1):
        for u in range(x0, x1):
            if pix_view[o, v, u] != i:
                continue
            p = _state_index(v - y0, u - x0, ts, cw)
            out_T[o, v, u] = abs(T[p])
            out_last[o, v, u] = last[p]
            for c in range(acc.shape[0]):
                out_feat[o, v, u, c] = acc[c, p]


@njit(cache=True, inline="always")
def _start_tile_bwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, out_T, out_last, g_T, g_feat, T, gTT, last, gF,
                    k_end):
    """Loads the forward's final T, last and the output gradients of the tile's pixels whose view is i
    into the tile state -> one past the last intersection to visit."""
    for v in range(y0, y1):
        for u in range(x0, x1):
            if pix_view[o, v, u] != i:
                continue
            p = _state_index(v - y0, u - x0, ts, cw)
            T[p] = out_T[o, v, u]
            gTT[p] = g_T[o, v, u] * out_T[o, v, u]
            last[p] = out_last[o, v, u]
            k_end = max(k_end, last[p])
            for c in range(gF.shape[0]):
                gF[c, p] = g_feat[o, v, u, c]
    return k_end


@njit(cache=True, inline="always")
def _write_isect_grad(isect_grad, k, half, gmx, gmy, ga, gb, gc, glo, gf):
    """Row k of isect_grad: dL/d (mean x, y, conic a, b, c, log opacity, features gf)."""
    isect_grad[k, 0] = gmx
    isect_grad[k, 1] = gmy
    isect_grad[k, 2] = half * ga
    isect_grad[k, 3] = gb
    isect_grad[k, 4] = half * gc
    isect_grad[k, 5] = glo
    for c in range(gf.shape[0]):
        isect_grad[k, 6 + c] = gf[c]


@njit(cache=True, inline="always")
def feature_dot_channels(ebuf, gF, feats, g, pa, pb, zero):
    """ebuf[p] = sum_c dL/dF[c, p] * feats[g, c] over state entries [pa, pb), one pass per channel."""
    for pp in range(pa, pb):
        ebuf[np.uint64(pp)] = zero
    for c in range(feats.shape[1]):
        fc = feats[g, c]
        for pp in range(pa, pb):
            ebuf[np.uint64(pp)] += gF[c, np.uint64(pp)] * fc


@njit(cache=True, inline="always")
def feature_dot(ebuf, gF, feats, g, pa, pb, zero):
    """ebuf[p] = sum_c dL/dF[c, p] * feats[g, c] over state entries [pa, pb) (dL/dw through the features).
    Seven channels (colour, depth, normal) in one pass, the same sums in the same order as
    `feature_dot_channels` (its seven passes cost 3-4 ms more in the 2DGS backward at σ 2.5 px)."""
    if feats.shape[1] != 7:
        feature_dot_channels(ebuf, gF, feats, g, pa, pb, zero)
        return
    f0, f1, f2, f3 = feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3]
    f4, f5, f6 = feats[g, 4], feats[g, 5], feats[g, 6]
    for pp in range(pa, pb):
        p = np.uint64(pp)
        e = zero + gF[0, p] * f0
        e += gF[1, p] * f1
        e += gF[2, p] * f2
        e += gF[3, p] * f3
        e += gF[4, p] * f4
        e += gF[5, p] * f5
        e += gF[6, p] * f6
        ebuf[p] = e


@njit(cache=True, inline="always")
def add_feature_grads(gf, wbuf, gF, pa, pb, zero):
    """gf[c] += sum_p w[p] * dL/dF[c, p] over state entries [pa, pb)."""
    for c in range(gf.shape[0]):
        sc = zero
        for pp in range(pa, pb):
            sc += wbuf[np.uint64(pp)] * gF[c, np.uint64(pp)]
        gf[c] += sc


@njit(cache=True, inline="always")
def trim_rows_active(ra, rb, row_active):
    """Rows [ra, rb) narrowed to start and end at rows with pixels still compositing."""
    while ra < rb and row_active[ra] == 0:
        ra += 1
    while rb > ra and row_active[rb - 1] == 0:
        rb -= 1
    return ra, rb


@njit(cache=True, inline="always")
def _tile_base(centres, x0, y0, ts, cw, kc):
    """Tile state every pass uses: T [P] and last [P] int32 (zeros), pixel centres cxt, cyt [P]."""
    P = ts * ts
    cxt = np.empty(P, kc.dtype)
    cyt = np.empty(P, kc.dtype)
    _tile_centres(centres, x0, y0, ts, cw, cxt, cyt)
    return np.zeros(P, kc.dtype), np.zeros(P, np.int32), cxt, cyt  # int32 last: as many SIMD lanes as float32


@njit(cache=True, inline="always")
def tile_state_fwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, Cf, kc, centres):
    """Per-tile state of the forward (compute dtype, `_state_index` layout) -> (T [P] (1 at the pixels
    whose view is i), acc [Cf, P], last [P] int32, pixel centres cxt, cyt [P], weights wbuf [P],
    stop flags sbuf [P] int32, row_active [ts] pixels still compositing per row, their number)."""
    P = ts * ts
    T, last, cxt, cyt = _tile_base(centres, x0, y0, ts, cw, kc)
    acc = np.zeros((Cf, P), kc.dtype)
    wbuf = np.empty(P, kc.dtype)
    sbuf = np.zeros(P, np.int32)  # 1 where the last Gaussian stopped the pixel
    row_active = np.zeros(ts, np.int64)
    n_active = _start_tile_fwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, kc[1], T, row_active)
    return T, acc, last, cxt, cyt, wbuf, sbuf, row_active, n_active


@njit(cache=True, inline="always", fastmath=FASTMATH)
def accumulate_features(acc, wbuf, feats, g, pa, pb):
    """acc[c, p] += w[p] * feats[g, c] over state entries [pa, pb)."""
    for c in range(feats.shape[1]):  # one loop per channel: an inner channel loop would stop the vectorizer
        fc = feats[g, c]
        for pp in range(pa, pb):
            acc[c, np.uint64(pp)] += wbuf[np.uint64(pp)] * fc


@njit(cache=True, inline="always")
def tile_state_bwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, Cf, kc, centres, out_T, out_last, g_T, g_feat, k_begin):
    """Per-tile state of the backward, loaded from the forward's results (`_start_tile_bwd`) -> (T,
    gTT, suffix, gF [Cf, P], last, cxt, cyt, ebuf, wbuf, gf [Cf], one past the last intersection to visit)."""
    P = ts * ts
    T, last, cxt, cyt = _tile_base(centres, x0, y0, ts, cw, kc)
    gTT = np.zeros(P, kc.dtype)
    suffix = np.zeros(P, kc.dtype)
    gF = np.zeros((Cf, P), kc.dtype)
    k_end = _start_tile_bwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, out_T, out_last, g_T, g_feat, T, gTT, last,
                            gF, k_begin)
    return (T, gTT, suffix, gF, last, cxt, cyt, np.empty(P, kc.dtype), np.empty(P, kc.dtype), np.empty(Cf, kc.dtype),
            k_end)


@njit(cache=True, inline="always")
def state_rows(ts, cw):
    """Tile row of each state entry (`_state_index` layout) -> [ts * ts] int32."""
    rows = np.empty(ts * ts, np.int32)
    for idx in range(ts * ts):
        rows[idx] = (idx % (ts * cw)) // cw
    return rows


@njit(cache=True, inline="always")
def composited_any(rows_hit, k):
    """Whether intersection k was composited into any pixel (a non-empty `rows_hit` range); if not,
    every term of its backward is zero and its `isect_grad` row stays as allocated (zeros)."""
    for q in range(rows_hit.shape[1]):
        if rows_hit[k, q, 0] < rows_hit[k, q, 1]:
            return True
    return False


@njit(cache=True, inline="always")
def track_rows(w, row, r_lo, r_hi, zero, ts32, no_row):
    """The running first and last rows (r_lo, r_hi) of a column group's pixels with weight w > 0 (selects:
    the pixel loop around it still vectorizes); the forward's `rows_hit` records, read by the backward."""
    r_a = row if w > zero else ts32
    r_b = row if w > zero else no_row
    return (r_a if r_a < r_lo else r_lo), (r_b if r_b > r_hi else r_hi)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def composite_pixel(s, Tp, last_p, k1, kc):
    """One front-to-back step at a pixel with transmittance Tp (> 0 while compositing, -T once
    stopped, 0 for pixels of other views) and exponent s = sigma - log o: gsplat's rules (alpha =
    min(0.999, exp(-s)), skip alpha <= 1/255, stop before T <= 1e-4) -> (weight w, new T, new
    last (k1 if composited), stopped here). Branch-free (selects), so pixel loops vectorize."""
    one, zero = kc[1], kc[3]
    alpha = min(_exp_neg(s, kc), kc[2])
    ok = (s <= kc[22]) & (alpha > kc[20]) & (Tp > zero)
    T_next = Tp * (one - alpha)
    stop = ok & (T_next <= kc[21])
    comp = ok & (T_next > kc[21])
    return (alpha * Tp if comp else zero), (T_next if comp else (-Tp if stop else Tp)), \
        (k1 if comp else last_p), stop


@njit(cache=True, inline="always", fastmath=FASTMATH)
def uncomposite_pixel(s, Tp, last_p, k32, kc):
    """Back-to-front step of `raster_bwd`'s pixel loop: T before intersection k32 recovered by division
    (as gsplat) -> (weight w (0 unless composited), T before, T_exc, alpha / (1 - alpha),
    whether the exponent gets a gradient (composited and alpha below the clamp))."""
    one, zero = kc[1], kc[3]
    ex = _exp_neg(s, kc)
    alpha = min(ex, kc[2])
    ok = (s <= kc[22]) & (alpha > kc[20]) & (k32 < last_p)
    inv_one_m = one / (one - alpha)
    T_exc = Tp * inv_one_m
    return (alpha * T_exc if ok else zero), (T_exc if ok else Tp), T_exc, alpha * inv_one_m, ok & (ex < kc[2])


@njit(cache=True, inline="always", fastmath=FASTMATH)
def exponent_grad(e, w, a_ratio, live, sp, gTT_p, zero):
    """dL/ds of a pair from e = dL/dw, the suffix sp = sum_{j>k} e_j w_j and dL/dT_final T_final:
    -> (G, the suffix including this pair); G = 0 where the pair did not get a gradient."""
    G = a_ratio * (sp + gTT_p) - e * w
    return (G if live else zero), sp + e * w


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _exponent(dx, dy, hA, B, hC, lo):
    """sigma - log o of a pixel at offset (dx, dy) from the centre (hA = A / 2, hC = C / 2)."""
    return (hA * dx + B * dy) * dx + hC * dy * dy - lo


@njit(**BIN_BODY)
def _fwd_bin(b, tab, feats, flat_ids, bin_start, pix_view, tile_size, tiles_x, cw, kc, centres, out_feat, out_T,
             out_last, rows_hit, rowt):
    """`raster_fwd` on bin b (image i, tile t): its `prange` body as a function of its own, so that numba's
    parfor passes compile it once (`BIN_BODY`: the 3DGS set compiles ~20 % faster and runs as fast;
    results/speed/README.md, 2026-11-28)."""
    H, W = pix_view.shape[1], pix_view.shape[2]
    Cf = feats.shape[1]
    ts = tile_size
    zero, no_row, ts32 = kc[3], np.int32(-1), np.int32(ts)
    i, o, x0, y0, x1, y1 = tile_of_bin(b, pix_view, ts, tiles_x)
    T, acc, last, cxt, cyt, wbuf, sbuf, row_active, n_active = tile_state_fwd(pix_view, o, i, x0, y0, x1, y1,
                                                                               ts, cw, Cf, kc, centres)
    for k in range(bin_start[b], bin_start[b + 1]):
        if n_active == 0:
            break
        g = flat_ids[k]
        gp = flat_ids[min(k + PREFETCH_AHEAD, bin_start[b + 1] - 1)]
        prefetch_row(tab, gp)
        prefetch_row(feats, gp)
        mx, my, A, B, C, lo = tab[g, 0], tab[g, 1], tab[g, 2], tab[g, 3], tab[g, 4], tab[g, 5]
        hA, hC = kc[0] * A, kc[0] * C
        ra, rb, ca, cb = _footprint_tab(tab, g, x0, y0, ts, W, H)
        ra, rb = trim_rows_active(ra, rb, row_active)
        if ra >= rb or ca >= cb:
            continue
        k1 = np.int32(k + 1)
        for q in range(ca // cw, (cb - 1) // cw + 1):
            # rows of this column group the ellipse can reach (fewer than the footprint's)
            qra, qrb = band_rows(tab, g, x0, y0, max(ca, q * cw), min(cb, q * cw + cw), ra, rb)
            if qra >= qrb:
                continue
            pa, pb = q * ts * cw + qra * cw, q * ts * cw + qrb * cw
            stopped = 0
            r_lo, r_hi = ts32, no_row
            # (accumulating the features in this loop measured slower: 7.7 against 7.1 ms)
            for pp in range(pa, pb):  # unsigned index: no wraparound test; branch-free: vectorizes
                p = np.uint64(pp)
                s = _exponent(cxt[p] - mx, cyt[p] - my, hA, B, hC, lo)
                w, T[p], last[p], stop = composite_pixel(s, T[p], last[p], k1, kc)
                wbuf[p] = w
                sbuf[p] = 1 if stop else 0
                stopped += 1 if stop else 0
                r_lo, r_hi = track_rows(w, rowt[p], r_lo, r_hi, zero, ts32, no_row)
            accumulate_features(acc, wbuf, feats, g, pa, pb)
            rows_hit[k, q, 0], rows_hit[k, q, 1] = r_lo, r_hi + 1
            if stopped:
                n_active -= stopped
                retire_stopped(row_active, sbuf, qra, qrb, q * cw, q * cw + 1, ts, cw)
    finish_tile_fwd(pix_view, o, i, x0, y0, x1, y1, ts, cw, T, last, acc, out_feat, out_T, out_last)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_fwd(tab, feats, flat_ids, bin_start, bins, pix_view, tile_size, tiles_x,
               cw, kc, centres, out_feat, out_T, out_last, rows_hit):
    """Front-to-back compositing of each bin (image i, tile t) in ``bins`` into the output pixels
    whose view is i (pix_view [Iout,H,W]). tab [I*N, TAB_COLS] `gaussian_table` (centres, conics,
    log opacities, footprints); feats [I*N, Cf] per (image, Gaussian) features; cw
    `column_group`; kc `compute_constants`; centres [max(W, H) + tile_size] pixel centres
    (index + 0.5), compute dtype. Writes out_feat [Iout,H,W,Cf] (sum w f), out_T [Iout,H,W]
    (composited transmittance) and out_last [Iout,H,W] (one past the last composited intersection).
    Per-pixel state: T > 0 while compositing, -T once stopped, 0 for pixels of other views; stored
    in column groups (`_state_index`) so that the pixels a Gaussian can reach in a group (its
    ellipse's rows, trimmed to rows still compositing) are one contiguous range, updated by one
    branch-free loop (it vectorizes). rows_hit [M, ts // cw, 2] int16 (zeros on entry): per intersection
    and column group, the rows [first, last + 1) it was composited into (w > 0), else an empty range;
    the backward visits only those."""
    rowt = state_rows(tile_size, cw)  # the same for every tile
    for jb in prange(bins.shape[0]):
        _fwd_bin(bins[jb], tab, feats, flat_ids, bin_start, pix_view, tile_size, tiles_x, cw, kc, centres, out_feat,
                 out_T, out_last, rows_hit, rowt)


@njit(**BIN_BODY)
def _bwd_bin(b, tab, feats, flat_ids, bin_start, pix_view, tile_size, tiles_x, cw, kc, centres, out_T, out_last, g_feat,
             g_T, isect_grad, rows_hit):
    """`raster_bwd` on bin b: its `prange` body, compiled as `_fwd_bin` is."""
    Cf = feats.shape[1]
    ts = tile_size
    zero = kc[3]
    i, o, x0, y0, x1, y1 = tile_of_bin(b, pix_view, ts, tiles_x)
    T, gTT, suffix, gF, last, cxt, cyt, ebuf, wbuf, gf, k_end = tile_state_bwd(
        pix_view, o, i, x0, y0, x1, y1, ts, cw, Cf, kc, centres, out_T, out_last, g_T, g_feat, bin_start[b])
    for k in range(k_end - 1, bin_start[b] - 1, -1):
        g = flat_ids[k]
        gp = flat_ids[max(k - PREFETCH_AHEAD, bin_start[b])]
        prefetch_row(tab, gp)
        prefetch_row(feats, gp)
        if not composited_any(rows_hit, k):
            continue
        mx, my, A, B, C, lo = tab[g, 0], tab[g, 1], tab[g, 2], tab[g, 3], tab[g, 4], tab[g, 5]
        hA, hC = kc[0] * A, kc[0] * C
        gmx = zero
        gmy = zero
        ga = zero
        gb = zero
        gc = zero
        glo = zero
        k32 = np.int32(k)
        for c in range(Cf):
            gf[c] = zero
        for q in range(rows_hit.shape[1]):
            qra, qrb = rows_hit[k, q, 0], rows_hit[k, q, 1]
            if qra >= qrb:
                continue
            pa, pb = q * ts * cw + qra * cw, q * ts * cw + qrb * cw
            if Cf == 4:  # colour + depth: dL/dw and the feature gradients in the same pass
                f0, f1, f2, f3 = feats[g, 0], feats[g, 1], feats[g, 2], feats[g, 3]
                s0 = zero
                s1 = zero
                s2 = zero
                s3 = zero
                for pp in range(pa, pb):  # unsigned index: no wraparound test; branch-free: vectorizes
                    p = np.uint64(pp)
                    dx = cxt[p] - mx
                    dy = cyt[p] - my
                    s = _exponent(dx, dy, hA, B, hC, lo)
                    w, T[p], T_exc, a_ratio, live = uncomposite_pixel(s, T[p], last[p], k32, kc)
                    e = gF[0, p] * f0 + gF[1, p] * f1 + gF[2, p] * f2 + gF[3, p] * f3
                    G, suffix[p] = exponent_grad(e, w, a_ratio, live, suffix[p], gTT[p], zero)
                    gmx -= G * (A * dx + B * dy)
                    gmy -= G * (B * dx + C * dy)
                    ga += G * dx * dx
                    gb += G * dx * dy
                    gc += G * dy * dy
                    glo -= G
                    s0 += w * gF[0, p]
                    s1 += w * gF[1, p]
                    s2 += w * gF[2, p]
                    s3 += w * gF[3, p]
                gf[0] += s0
                gf[1] += s1
                gf[2] += s2
                gf[3] += s3
                continue
            feature_dot(ebuf, gF, feats, g, pa, pb, zero)
            for pp in range(pa, pb):
                p = np.uint64(pp)
                dx = cxt[p] - mx
                dy = cyt[p] - my
                s = _exponent(dx, dy, hA, B, hC, lo)
                w, T[p], T_exc, a_ratio, live = uncomposite_pixel(s, T[p], last[p], k32, kc)
                wbuf[p] = w
                G, suffix[p] = exponent_grad(ebuf[p], w, a_ratio, live, suffix[p], gTT[p], zero)
                gmx -= G * (A * dx + B * dy)
                gmy -= G * (B * dx + C * dy)
                ga += G * dx * dx
                gb += G * dx * dy
                gc += G * dy * dy
                glo -= G
            add_feature_grads(gf, wbuf, gF, pa, pb, zero)
        _write_isect_grad(isect_grad, k, kc[0], gmx, gmy, ga, gb, gc, glo, gf)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_bwd(tab, feats, flat_ids, bin_start, bins, pix_view, tile_size, tiles_x,
               cw, kc, centres, out_T, out_last, g_feat, g_T, isect_grad, rows_hit):
    """Back-to-front backward of `raster_fwd` (T recovered by division, as gsplat): isect_grad
    [M, 6 + Cf] per intersection (dL/d mean x, y; dL/d conic a, b, c; dL/d log opacity; dL/d features).
    rows_hit: the forward's; the pixels outside those rows were not composited into (zero terms)."""
    for jb in prange(bins.shape[0]):
        _bwd_bin(bins[jb], tab, feats, flat_ids, bin_start, pix_view, tile_size, tiles_x, cw, kc, centres, out_T,
                 out_last, g_feat, g_T, isect_grad, rows_hit)


@njit(cache=True)
def _first_touch_slots(flat_ids, M, n_out):
    """Accumulator slots of the rows intersections reach, in order of first touch: flat_ids [M] ->
    (slot [n_out] int32 (-1: no intersection), rows [n_rows] (slot -> row))."""
    slot = np.full(n_out, -1, np.int32)
    rows = np.empty(M, np.int64)
    n_rows = 0
    for k in range(M):
        if slot[flat_ids[k]] < 0:
            slot[flat_ids[k]] = n_rows
            rows[n_rows] = flat_ids[k]
            n_rows += 1
    return slot, rows[:n_rows]


@njit(cache=True, parallel=True)
def ordered_sum(block, out):
    """block [k, m, n] -> out [n, k] (C-contiguous): the sum over m, from +0.0 adding 0, 1, ..., m - 1 in
    order in the block's dtype (torch's order along a non-innermost axis of fewer than 24 entries, signed
    zeros included, except on the last columns its vector loop leaves), per entry the same bits for any
    thread count and vector width. Chunks of n in parallel; the loops over them vectorize."""
    k, m, n = block.shape
    for ch in prange((n + CHUNK - 1) // CHUNK):
        n0 = ch * CHUNK
        L = min(n, n0 + CHUNK) - n0
        acc = np.empty(CHUNK, block.dtype)
        for c in range(k):
            for j in range(L):
                acc[j] = 0.0
            for i in range(m):
                for j in range(L):
                    acc[j] += block[c, i, n0 + j]
            for j in range(L):
                out[n0 + j, c] = acc[j]


@njit(cache=True, parallel=True)
def alpha_depth(depth_sum, trans, one, lo, alpha, depth):
    """Per pixel [P]: alpha = one - trans, depth = depth_sum / clamp(alpha, min=lo), in the arrays' dtype
    (``one``, ``lo`` of that dtype): torch's rsub, clamp (NaN passes through) and div, the same bits."""
    for p in prange(trans.shape[0]):
        a = one - trans[p]
        alpha[p] = a
        depth[p] = depth_sum[p] / (lo if a < lo else a)


@njit(cache=True, parallel=True)
def alpha_depth_grad(depth_sum, alpha, g_alpha, g_depth, lo, g_sum, g_trans):
    """Backward of `alpha_depth` as torch's autograd takes it, the same bits: div's dL/d sum = g / den and
    dL/d den = -g ((sum / den) / den), clamp's where(alpha >= lo, ., 0), the alpha's own gradient added,
    rsub's negation. g_depth [P], g_alpha [P] (no rows: no gradient) -> g_sum, g_trans [P]."""
    zero = lo - lo
    with_alpha = g_alpha.shape[0] > 0
    for p in prange(alpha.shape[0]):
        a = alpha[p]
        den = lo if a < lo else a
        g = g_depth[p]
        g_sum[p] = g / den
        ga = -g * ((depth_sum[p] / den) / den) if a >= lo else zero
        g_trans[p] = -(g_alpha[p] + ga) if with_alpha else -ga


@njit(cache=True, parallel=True)
def pack_pixel_grads(out, g_rgb, g_depth, g_normal, g_dist, fwd_feat):
    """The raster backward's per-pixel input out [P, C] (C = 4 or 7; 9 for 2DGS) from the gradients of the
    forward's outputs, in one pass: channels 0-2 g_rgb [P, 3], 3 g_depth [P, 1], 4-6 g_normal [P, 3]; for
    C = 9 also 7 = 2 g_dist [P] (dL/d distortion) and 8 = the forward's depth fwd_feat[:, DEPTH_CH]. An input
    with no rows stands for zeros (an output no loss read)."""
    P, C = out.shape
    for p in prange(P):
        for c in range(3):
            out[p, c] = g_rgb[p, c] if g_rgb.shape[0] else 0.0
        out[p, 3] = g_depth[p, 0] if g_depth.shape[0] else 0.0
        if C >= 7:
            for c in range(3):
                out[p, 4 + c] = g_normal[p, c] if g_normal.shape[0] else 0.0
        if C == 9:
            out[p, 7] = g_dist[p] + g_dist[p] if g_dist.shape[0] else 0.0
            out[p, 8] = fwd_feat[p, DEPTH_CH]


@njit(cache=True, parallel=True)
def reduce_isect_grad(isect_grad, flat_ids, M, out, absgrad, parts=1):
    """Per-intersection gradients [M, C] -> per (image, Gaussian) sums written to out [C, I*N]
    (channel first, so that each parameter's gradient is one contiguous block for the projection
    backward; every entry is written, rows no intersection reaches with zeros, so out may come
    uninitialised; its own dtype): each row's sum is taken in float64 in intersection order, only
    for the rows some intersection reaches (~10 % of them with motion sampling), then rounded to
    out's dtype. absgrad [I*N, 2] sums |dL/d mean| per intersection (zeros on entry; an empty [0, 2]
    array: not asked for, skipped). parts (numba's thread count): each part owns a range of rows
    (accumulator slots) and scans every intersection for its own, so a row's terms are added in the
    same order whatever the count (bit-identical results); the output is written a channel per thread."""
    C = isect_grad.shape[1]
    slot, rows = _first_touch_slots(flat_ids, M, out.shape[1])
    n_rows = rows.shape[0]
    acc = np.zeros((n_rows, C))
    want_abs = absgrad.shape[0] > 0
    for part in prange(parts):
        s0, s1 = part * n_rows // parts, (part + 1) * n_rows // parts
        for k in range(M):
            g = flat_ids[k]
            s = slot[g]
            if s < s0 or s >= s1:
                continue
            for c in range(C):
                acc[s, c] += isect_grad[k, c]
            if want_abs:
                absgrad[g, 0] += abs(isect_grad[k, 0])
                absgrad[g, 1] += abs(isect_grad[k, 1])
    for c in prange(C):
        out[c, :] = 0
        for s in range(n_rows):
            out[c, rows[s]] = acc[s, c]
