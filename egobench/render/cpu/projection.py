"""Projection of 3D Gaussians to the image, forward and backward (per Gaussian, in fixed chunks), and the
rasterization constants shared by every kernel (gsplat 1.5.3's)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from egobench.render.cpu.args import Ewa, Pair

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
def gather_chunk(splats, n0, L, normal_axis, R, g_in, g_rot):
    """Per-Gaussian inputs of Gaussians [n0, n0 + L) of splats (`Splats`) -> g_in [6 CHUNK] (input dtype: rows
    0-2 the mean, 3-5 the scales), g_rot [>= 12 CHUNK] (rows 0-8 the rotation matrix row-major, 9-11 its
    column of the normal: normal_axis, or the shortest axis where it is -1). R [3, 3]: scratch."""
    means, quats, scales = splats.means, splats.quats, splats.scales
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
def _project_chunk(v, g_in, g_rot, L, view, lims, out):
    """One pose (v: `view_rows`) and the chunk's Gaussians (`gather_chunk`, `_gather_extents`) -> out [8 CHUNK]: rows
    u, v, depth, conic (3), radii x, y (0 where culled). view: `View` (its camera, image size, eps2d, near,
    far); lims: `_clip_limits`. Branch-free: the loop vectorizes."""
    cam = view.cam
    eps2d, near, far = view.eps2d, view.near, view.far
    width, height = view.width, view.height
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
def project_fwd(splats, opac, view, want_normal, out):
    """splats `Splats` (means [N,3], quats [N,4], scales [N,3]), opac [N], view `View` (viewmats [I,4,4],
    cam (fx, fy, cx, cy), width, height, eps2d, near, far) -> fills out `Projected`: means2d [I,N,2],
    conics [I,N,3], depths [I,N], radii [I,N,2] int32, normals [I,N,3] (with want_normal; else [I,0,3]).
    Per chunk of Gaussians: their inputs gathered once, then per pose a vectorized loop over them
    (`_project_chunk`; 3-4x faster on 6 poses than a scalar loop per Gaussian, bitwise the same)."""
    means, viewmats = splats.means, view.viewmats
    N = means.shape[0]
    I = viewmats.shape[0]
    lims = _clip_limits(view.cam, view.width, view.height)
    m2f, conf, depf, radf = out.means2d.reshape(I * N * 2), out.conics.reshape(I * N * 3), \
        out.depths.reshape(I * N), out.radii.reshape(I * N * 2)
    nrmf = out.normals.reshape(out.normals.size)
    for ch in prange((N + CHUNK - 1) // CHUNK):
        n0, L, g_in, g_rot, rows = chunk_scratch(ch, N, means.dtype, 14, 8)
        gather_chunk(splats, n0, L, -1, np.empty((3, 3)), g_in, g_rot)
        _gather_extents(opac, n0, L, g_rot)
        for i in range(I):
            v = view_rows(viewmats[i])
            q0 = np.uint64(i * N + n0)
            _project_chunk(v, g_in, g_rot, L, view, lims, rows)
            _scatter_chunk(rows, q0, L, m2f, depf, conf, radf)
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
def _cov2d_rows(V, R, scales, n, ewa, Mc, A0, A1):
    """Fills Mc [3, 3] = V[:3, :3] R diag(s) (s: scales[n]) and the rows A0, A1 [3] of J Mc (ewa: `Ewa`, J and
    eps2d) -> 2D covariance (c00, c11, c01) with the eps2d dilation."""
    j00, j11, tx, ty, eps2d = ewa.j00, ewa.j11, ewa.tx, ewa.ty, ewa.eps2d
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
def _cov2d_rows_grad(g_cov, A0, A1, Mc, ewa, gMc):
    """Backward of `_cov2d_rows` from g_cov = dL/d covariance (g00, g11, g01), its A0, A1, Mc and ewa (`Ewa`):
    fills gMc [3, 3] -> (dL/dj00, dL/dj11, dL/dtx, dL/dty)."""
    g00, g11, g01 = g_cov
    j00, j11, tx, ty = ewa.j00, ewa.j11, ewa.tx, ewa.ty
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
def normal_grad(V, R, pair, pc, g_normals, gnw):
    """Normal sgn * V[:3, :3] R[:, ax] of a pair (`Pair`: i, n, ax), facing the camera at its camera-frame
    centre pc (x, y, z): fills gnw [3] = dL/dR[:, ax] from g_normals[:, i, n] [3] -> sgn."""
    i, n, ax = pair.i, pair.n, pair.ax
    x, y, z = pc
    nx = V[0, 0] * R[0, ax] + V[0, 1] * R[1, ax] + V[0, 2] * R[2, ax]
    ny = V[1, 0] * R[0, ax] + V[1, 1] * R[1, ax] + V[1, 2] * R[2, ax]
    nz = V[2, 0] * R[0, ax] + V[2, 1] * R[1, ax] + V[2, 2] * R[2, ax]
    sgn = 1.0 if -(nx * x + ny * y + nz * z) > 0 else -1.0
    for r in range(3):
        for b in range(3):
            gnw[b] += V[r, b] * sgn * g_normals[r, i, n]
    return sgn


@njit(cache=True, inline="always")
def add_mean_grads(V, gpc, gm):
    """p_c = V m + t: adds dL/dm = V[:3, :3]^T gpc to gm [3] (gpc = dL/dp_c), pose row by pose row."""
    for r in range(3):
        for b in range(3):
            gm[b] += V[r, b] * gpc[r]


@njit(cache=True, inline="always")
def add_view_grads(R, scales, means, n, gpc, gMc, gv):
    """p_c = V m + t, Mc = V R diag(s) (m, s: row n of means, scales): adds dL/dV[:3, :4] (row-major) to gv
    [12] from gpc = dL/dp_c and gMc [3, 3] = dL/dMc; for each entry, the term of p_c, then that of Mc."""
    for r in range(3):
        gv[r * 4 + 3] += gpc[r]
        for b in range(3):
            gv[r * 4 + b] += gpc[r] * means[n, b]
            acc = 0.0
            for c in range(3):
                acc += gMc[r, c] * R[b, c] * scales[n, c]
            gv[r * 4 + b] += acc


@njit(cache=True, inline="always")
def add_normal_view_grads(R, pair, sgn, g_normals, gv):
    """normal = sgn V[:3, :3] R[:, ax] of a pair (`Pair`: i, n, ax): adds its dL/dV[:3, :3] to gv [12] from
    g_normals[:, i, n] [3]; after `add_view_grads`, each entry's last term (the order of one pass over
    the entries adding all three)."""
    i, n, ax = pair.i, pair.n, pair.ax
    for r in range(3):
        for b in range(3):
            gv[r * 4 + b] += sgn * g_normals[r, i, n] * R[b, ax]


@njit(cache=True, inline="always")
def add_rot_scale_grads(V, R, scales, pair, gMc, gnw, gR, gs):
    """Mc = V R diag(s) of a pair (`Pair`: n, ax; s: scales[n]): adds dL/dR to gR [3, 3] (with the normal's
    gnw on column ax) and dL/ds to gs [3]."""
    n, ax = pair.n, pair.ax
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
def project_bwd(splats, view, want_normal, upstream, grads):
    """Backward of `project_fwd` for every entry (culled ones included, as torch's graph); splats (`Splats`)
    and view (`View`) in float64. Upstream gradients (`ProjectedGrads`) channel first (`reduce_isect_grad`'s
    layout): means2d [2,I,N], conics [3,I,N], depths [I,N], normals [3,I,N] (or [3,I,0]). Fills grads
    (`SplatGrads`): means [N,3], quats [N,4], scales [N,3] and view_parts [chunks, I, 12] (per-chunk partial
    dL/d viewmat[:3, :4], reduced in chunk order by the caller)."""
    means, quats, scales = splats.means, splats.quats, splats.scales
    viewmats, cam, eps2d, near, far = view.viewmats, view.cam, view.eps2d, view.near, view.far
    g_means2d, g_conics, g_depths, g_normals = upstream.means2d, upstream.conics, upstream.depths, upstream.normals
    g_means, g_quats, g_scales, g_view_parts = grads.means, grads.quats, grads.scales, grads.view_parts
    N = means.shape[0]
    I = viewmats.shape[0]
    fx, fy = cam[0], cam[1]
    lxp, lxn, lyp, lyn = _clip_limits(cam, view.width, view.height)
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
                pair = Pair(i, n, ax)
                x, y, z = camera_point(V, means, n)
                in_depth = z >= near and z <= far
                zs = z if in_depth else 1.0
                inv_z = 1.0 / zs
                rtx, rty = x * inv_z, y * inv_z
                tx = min(max(rtx, -lxn), lxp)
                ty = min(max(rty, -lyn), lyp)
                ewa = Ewa(fx * inv_z, fy * inv_z, tx, ty, eps2d)
                c00, c11, c01 = _cov2d_rows(V, R, scales, n, ewa, Mc, A0, A1)
                det = c00 * c11 - c01 * c01
                g_cov = _conic_grad(g_conics[0, i, n], g_conics[1, i, n], g_conics[2, i, n], c00, c11, c01, det,
                                    in_depth and det > 0)
                # means2d = (fx x / zs + cx, fy y / zs + cy); depth = z
                gx = g_means2d[0, i, n] * fx * inv_z
                gy = g_means2d[1, i, n] * fy * inv_z
                g_inv_z = g_means2d[0, i, n] * fx * x + g_means2d[1, i, n] * fy * y
                gz = g_depths[i, n]
                g_j00, g_j11, g_tx, g_ty = _cov2d_rows_grad(g_cov, A0, A1, Mc, ewa, gMc)
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
                sgn = normal_grad(V, R, pair, (x, y, z), g_normals, gnw) if want_normal else 0.0
                gpc, gv = (gx, gy, gz), g_view_parts[ch, i]
                add_mean_grads(V, gpc, gm)
                add_view_grads(R, scales, means, n, gpc, gMc, gv)
                if want_normal:
                    add_normal_view_grads(R, pair, sgn, g_normals, gv)
                add_rot_scale_grads(V, R, scales, pair, gMc, gnw, gR, gs)
            for b in range(3):
                g_means[n, b] = gm[b]
                g_scales[n, b] = gs[b]
            quat_grad(gR, qw, qx, qy, qz, qinv, g_quats, n)
