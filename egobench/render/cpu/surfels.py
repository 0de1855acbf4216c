"""numba kernels of the compiled CPU backend for 2DGS surfels (gsplat 1.5.3 semantics, as
torch_backend.py's `project_2dgs`, `coefficients_2dgs` and the 2DGS path of `torch_composite._Composite`).

Projection: ray transform M = K [R_c s0 | R_c s1 | mean_c] (rows u_M, v_M, w_M), the centre and
AABB radius from M's dual conic, the camera-facing normal (third rotation axis); the backward
reuses the 3DGS helpers of `egobench.render.cpu` (a surfel is Mc = V R diag(s) with a zero third column).
Compositing: per pixel the ray-splat intersection h_u x h_v (linear in the pixel, evaluated
relative to the tile centre as the torch backend), min(3D, 2D low-pass) exponent, the 3DGS
compositing rules, plus the depth distortion 2 sum_{j<k} w_j w_k (z_k - z_j). The tile loop, state
layout, binning and gradient reduction are the 3DGS kernels' (`egobench.render.cpu`: determinism, threads).
The forward records which rows of each column group a surfel was composited into (``rows_hit``); the
backward visits only those (a surfel's box footprint holds 4-6x the pixels it composites into).

Caching: these kernels inline helpers of the package's other modules; their cache is stamped with a hash of
every module of the package (`compiler.SourceHashLocator`), so an edited helper recompiles them too.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from egobench.render import cpu as ck
from egobench.render.cpu import (CHUNK, EXTENT_SIGMAS, FASTMATH, SIGMA_ROW, accumulate_features, add_feature_grads,
                                 add_mean_grads, add_normal_view_grads, add_rot_scale_grads, add_view_grads, bin_tile,
                                 camera_point, composite_pixel, exponent_grad, feature_dot, finish_tile_fwd,
                                 normal_grad, quat_grad, quat_rotmat, retire_stopped, state_rows, tile_state_bwd,
                                 tile_state_fwd, track_rows, trim_rows_active, uncomposite_pixel)
from egobench.render.cpu.args import Pair, SurfelIsectGrad, SurfelTableInputs


FILTER_2D = 2.0  # 2D low-pass filter: exponent FILTER_2D |pixel - centre|^2 / 2 (gsplat's FILTER_INV_SQUARE)
DEPTH_CH = ck.DEPTH_CH  # feature channel holding the depth (`composite.feature_table`'s layout)

__all__ = ["project_fwd_2dgs", "project_bwd_2dgs", "raster_fwd_2dgs", "raster_bwd_2dgs", "CHUNK"]


@njit(cache=True, inline="always")
def _axis(v, r0, r1, r2, sc, cam):
    """One column of the ray transform M = K [R_c s0 | R_c s1 | mean_c] for one pose (`ck.view_rows` v),
    (r0, r1, r2) a column of the surfel's rotation, sc its scale along it -> (M[0, c], M[1, c], M[2, c])."""
    t0, t1, t2 = ck.rotated_axis(v, r0, r1, r2, sc)
    return cam[0] * t0 + cam[2] * t2, cam[1] * t1 + cam[3] * t2, t2


@njit(cache=True, inline="always")
def _ray_transform(V, R, scales, means, n, cam, M):
    """Fills M [3, 3] = K [R_c[:, 0] s0 | R_c[:, 1] s1 | mean_c] (R_c = V[:3, :3] R) -> camera-frame
    centre (x, y, z)."""
    x, y, z = camera_point(V, means, n)
    v = ck.view_rows(V)
    for c in range(2):
        M[0, c], M[1, c], M[2, c] = _axis(v, R[0, c], R[1, c], R[2, c], scales[n, c], cam)
    M[0, 2], M[1, 2], M[2, 2] = cam[0] * x + cam[2] * z, cam[1] * y + cam[3] * z, z
    return x, y, z


@njit(cache=True, inline="always")
def _surfel_centre(u, v, w, z, near, far):
    """Ray transform M (rows u, v, w: 3 floats each) of a surfel at camera depth z -> projected centre (m0,
    m1), dual-conic scale d (f = (1, 1, -1) / d; 1 where culled, as torch's substitute) and whether it is
    valid (d != 0, near < z < far). Branch-free."""
    u0, u1, u2 = u
    v0, v1, v2 = v
    w0, w1, w2 = w
    d = w0 * w0 + w1 * w1 - w2 * w2
    valid = (d != 0) & (z > near) & (z < far)
    d_s = d if valid else 1.0
    return (u0 * w0 + u1 * w1 - u2 * w2) / d_s, (v0 * w0 + v1 * w1 - v2 * w2) / d_s, d_s, valid


@njit(cache=True, inline="always")
def _axis_column(v, g_in, g_rot, c, j, cam):
    """Column c (0, 1) of the ray transform of chunk entry j under one pose (`ck.view_rows`) -> `_axis`."""
    R_ = ck.ROW
    return _axis(v, g_rot[R_[c] + j], g_rot[R_[3 + c] + j], g_rot[R_[6 + c] + j], g_in[R_[3 + c] + j], cam)


@njit(cache=True, inline="always")
def _project_chunk_2dgs(v, g_in, g_rot, L, view, out):
    """One pose (v: `ck.view_rows`) and a chunk of surfels (`ck.gather_chunk`) -> out [14 CHUNK]: rows
    centre x, y, depth, radii x, y (0 where culled), then the ray transform M (9, row-major), as
    `_ray_transform`, `_surfel_centre` and gsplat's AABB. view: `View` (its camera, image size, near, far).
    Branch-free: the loop vectorizes."""
    cam = view.cam
    near, far = view.near, view.far
    width, height = view.width, view.height
    R_ = ck.ROW
    for jj in range(L):
        j = np.uint64(jj)
        x, y, z = ck.chunk_camera_point(v, g_in, j)
        u0, v0, w0 = _axis_column(v, g_in, g_rot, 0, j, cam)
        u1, v1, w1 = _axis_column(v, g_in, g_rot, 1, j, cam)
        u2, v2 = cam[0] * x + cam[2] * z, cam[1] * y + cam[3] * z
        w2 = np.float64(z)
        m0, m1, d_s, valid = _surfel_centre((u0, u1, u2), (v0, v1, v2), (w0, w1, w2), z, near, far)
        h0 = m0 * m0 - (u0 * u0 + u1 * u1 - u2 * u2) / d_s
        h1 = m1 * m1 - (v0 * v0 + v1 * v1 - v2 * v2) / d_s
        rx = math.ceil(EXTENT_SIGMAS * math.sqrt(max(h0, 1e-4)))
        ry = math.ceil(EXTENT_SIGMAS * math.sqrt(max(h1, 1e-4)))
        keep = valid & (m0 + rx > 0) & (m0 - rx < width) & (m1 + ry > 0) & (m1 - ry < height)
        out[j], out[R_[1] + j], out[R_[2] + j] = m0, m1, z
        out[R_[3] + j], out[R_[4] + j] = (rx if keep else 0.0), (ry if keep else 0.0)
        out[R_[5] + j], out[R_[6] + j], out[R_[7] + j] = u0, u1, u2
        out[R_[8] + j], out[R_[9] + j], out[R_[10] + j] = v0, v1, v2
        out[R_[11] + j], out[R_[12] + j], out[R_[13] + j] = w0, w1, w2


@njit(cache=True, inline="always")
def _scatter_chunk_2dgs(out, q0, L, means2d, depths, radii, tsl):
    """`_project_chunk_2dgs`'s rows -> flat outputs at entries [q0, q0 + L) (entry = pose * N + surfel):
    means2d [2 per entry], depths, radii [2] int32, tsl [9]. The ray transforms are copied in a scalar loop
    (`ck.scalar_loop`): vectorized, it was 9 scatter instructions per 8 entries, ~45 % of this kernel on
    AMD Zen 4."""
    R_ = ck.ROW
    u1, u2, u9 = np.uint64(1), np.uint64(2), np.uint64(9)
    for jj in range(L):
        j = np.uint64(jj)
        q = q0 + j
        means2d[q * u2], means2d[q * u2 + u1], depths[q] = out[j], out[R_[1] + j], out[R_[2] + j]
        radii[q * u2], radii[q * u2 + u1] = np.int32(out[R_[3] + j]), np.int32(out[R_[4] + j])
    for jj in range(L):
        j = np.uint64(jj)
        q = q0 + j
        ck.scalar_loop()
        for c in range(9):
            tsl[q * u9 + np.uint64(c)] = out[R_[5 + c] + j]


@njit(cache=True, parallel=True)
def project_fwd_2dgs(splats, view, out):
    """splats `Splats` (means [N,3], quats [N,4], scales [N,3]: first two used), view `View` (viewmats
    [I,4,4], cam (fx, fy, cx, cy), width, height, near, far) -> fills out `ProjectedSurfels`: means2d
    [I,N,2], tsl [I,N,9] (ray transform, row-major), depths [I,N], radii [I,N,2] int32 (gsplat's AABB, 0
    where culled), normals [I,N,3] (camera frame, facing the camera).
    Per chunk of surfels: inputs gathered once, then per pose a vectorized loop (as `ck.project_fwd`)."""
    means, viewmats = splats.means, view.viewmats
    N, I = means.shape[0], viewmats.shape[0]
    m2f, tslf, depf = out.means2d.reshape(I * N * 2), out.tsl.reshape(I * N * 9), out.depths.reshape(I * N)
    radf, nrmf = out.radii.reshape(I * N * 2), out.normals.reshape(I * N * 3)
    for ch in prange((N + CHUNK - 1) // CHUNK):
        n0, L, g_in, g_rot, rows = ck.chunk_scratch(ch, N, means.dtype, 12, 14)
        ck.gather_chunk(splats, n0, L, 2, np.empty((3, 3)), g_in, g_rot)
        for i in range(I):
            v = ck.view_rows(viewmats[i])
            q0 = np.uint64(i * N + n0)
            _project_chunk_2dgs(v, g_in, g_rot, L, view, rows)
            _scatter_chunk_2dgs(rows, q0, L, m2f, depf, radf, tslf)
            ck.normals_chunk(v, g_in, g_rot, L, q0, nrmf)


@njit(cache=True, inline="always")
def _ray_transform_grad(M, centre, g_means2d, g_tsl, pair, cam, gMc, gpc):
    """dL/dM of a pair (`Pair`: i, n; M: its ray transform, centre: `_surfel_centre`'s result) from the
    rasterizer, g_tsl[:, i, n] [9], and from the centre, g_means2d[:, i, n] [2] -> gMc [3, 3] = dL/d(V R
    diag(s)) (third column 0: a surfel's normal axis has no scale) and gpc [3] = dL/d mean_c (the depth's
    gradient is added by the caller)."""
    _, _, d_s, valid = centre
    i, n = pair.i, pair.n
    s = (1.0, 1.0, -1.0)
    gq = np.empty(3)  # dL/dq, q = (w_M * s) / d: m_j = u_M^T q, v_M^T q
    P = 0.0
    for c in range(3):
        gq[c] = g_means2d[0, i, n] * M[0, c] + g_means2d[1, i, n] * M[1, c]
        P += gq[c] * s[c] * M[2, c] / d_s
    gM = np.empty((3, 3))
    for c in range(3):
        q = s[c] * M[2, c] / d_s
        gM[0, c] = g_tsl[c, i, n] + g_means2d[0, i, n] * q
        gM[1, c] = g_tsl[3 + c, i, n] + g_means2d[1, i, n] * q
        gw = s[c] * (gq[c] - 2.0 * P * M[2, c]) / d_s if valid else gq[c] * s[c]
        gM[2, c] = g_tsl[6 + c, i, n] + gw
    # M = K T_cl: rows 0, 1 scaled by fx, fy; row 2 also feeds rows 0, 1 through cx, cy
    for c in range(3):
        g0, g1 = cam[0] * gM[0, c], cam[1] * gM[1, c]
        g2 = cam[2] * gM[0, c] + cam[3] * gM[1, c] + gM[2, c]
        if c < 2:
            gMc[0, c], gMc[1, c], gMc[2, c] = g0, g1, g2
        else:
            gpc[0], gpc[1], gpc[2] = g0, g1, g2
            gMc[0, 2], gMc[1, 2], gMc[2, 2] = 0.0, 0.0, 0.0


@njit(cache=True, parallel=True)
def project_bwd_2dgs(splats, view, upstream, grads):
    """Backward of `project_fwd_2dgs` (every entry with an upstream gradient, culled ones as torch's
    graph); splats (`Splats`) and view (`View`) in float64. Upstream gradients (`ProjectedSurfelGrads`)
    channel first: means2d [2,I,N], tsl [9,I,N], depths [I,N], normals [3,I,N]. Fills grads (`SplatGrads`):
    means [N,3], quats [N,4], scales [N,3] and view_parts [chunks, I, 12] (per-chunk partial dL/d
    viewmat[:3, :4], reduced in chunk order by the caller)."""
    means, quats, scales = splats.means, splats.quats, splats.scales
    viewmats, cam, near, far = view.viewmats, view.cam, view.near, view.far
    g_means2d, g_tsl, g_depths, g_normals = upstream.means2d, upstream.tsl, upstream.depths, upstream.normals
    g_means, g_quats, g_scales, g_view_parts = grads.means, grads.quats, grads.scales, grads.view_parts
    N, I = means.shape[0], viewmats.shape[0]
    for ch in prange(g_view_parts.shape[0]):
        R = np.empty((3, 3))
        M = np.empty((3, 3))
        gR = np.empty((3, 3))
        gMc = np.empty((3, 3))
        gs = np.empty(3)
        gm = np.empty(3)
        gpc = np.empty(3)
        gnw = np.empty(3)
        n0, L, live = ck.live_chunk(ch, N, g_means2d, g_tsl, g_depths, g_normals, True)
        for n in range(n0, n0 + L):
            if not ck.any_live(live, n - n0):
                ck.zero_gaussian_grads(g_means, g_quats, g_scales, n)
                continue
            R, qw, qx, qy, qz, qinv = quat_rotmat(quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3], R)
            gR[:] = 0.0
            gs[:] = 0.0
            gm[:] = 0.0
            for i in range(I):
                if not live[i, n - n0]:
                    continue
                V = viewmats[i]
                pair = Pair(i, n, 2)
                x, y, z = _ray_transform(V, R, scales, means, n, cam, M)
                centre = _surfel_centre((M[0, 0], M[0, 1], M[0, 2]), (M[1, 0], M[1, 1], M[1, 2]),
                                        (M[2, 0], M[2, 1], M[2, 2]), z, near, far)
                _ray_transform_grad(M, centre, g_means2d, g_tsl, pair, cam, gMc, gpc)
                gpc[2] += g_depths[i, n]
                gnw[:] = 0.0
                sgn = normal_grad(V, R, pair, (x, y, z), g_normals, gnw)
                gv = g_view_parts[ch, i]
                add_mean_grads(V, gpc, gm)
                add_view_grads(R, scales, means, n, gpc, gMc, gv)
                add_normal_view_grads(R, pair, sgn, g_normals, gv)
                add_rot_scale_grads(V, R, scales, pair, gMc, gnw, gR, gs)
            for b in range(3):
                g_means[n, b] = gm[b]
                g_scales[n, b] = gs[b]
            quat_grad(gR, qw, qx, qy, qz, qinv, g_quats, n)


# ------------------------------------------------------------------------------------------
# compositing
# ------------------------------------------------------------------------------------------


@njit(cache=True, parallel=True)
def carrier_grad(g_m02, g_m12, tsl, out):
    """gsplat's gradient_2dgs: dL/dM[0, 2], dL/dM[1, 2] [K] and the ray transforms tsl [K, 9] ->
    out [K, 2] = (dL/dM[0, 2], dL/dM[1, 2]) M[2, 2] (K = images x surfels)."""
    for k in prange(out.shape[0]):
        m22 = tsl[k, 8]
        out[k, 0] = g_m02[k] * m22
        out[k, 1] = g_m12[k] * m22


@njit(cache=True, inline="always")
def _cross_coefs(tsl, gi, n, ox, oy, cc):
    """Fills cc [9] with h_u x h_v = C0 + lx C1 + ly C2 (lx, ly pixel minus tile centre (ox, oy)):
    cc = (C0, C1, C2), C0 = Up x Vp, C1 = W x Vp, C2 = Up x W, Up = ox W - U, Vp = oy W - V."""
    W0, W1, W2 = tsl[gi, n, 6], tsl[gi, n, 7], tsl[gi, n, 8]
    u0, u1, u2 = ox * W0 - tsl[gi, n, 0], ox * W1 - tsl[gi, n, 1], ox * W2 - tsl[gi, n, 2]
    v0, v1, v2 = oy * W0 - tsl[gi, n, 3], oy * W1 - tsl[gi, n, 4], oy * W2 - tsl[gi, n, 5]
    cc[0], cc[1], cc[2] = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    cc[3], cc[4], cc[5] = W1 * v2 - W2 * v1, W2 * v0 - W0 * v2, W0 * v1 - W1 * v0
    cc[6], cc[7], cc[8] = u1 * W2 - u2 * W1, u2 * W0 - u0 * W2, u0 * W1 - u1 * W0
    return u0, u1, u2, v0, v1, v2


@njit(cache=True, inline="always")
def _axis_range(lo_c, hi_c, tile_lo, n_px, ts):
    """Pixel interval [lo_c, hi_c] -> tile-local [a, b)."""
    return max(0, ck.floor_int(lo_c) - tile_lo), min(min(ts, n_px - tile_lo), ck.ceil_int(hi_c) - tile_lo)


#: the image ellipse in `surfel_table` is enlarged by this factor (its area) for the band rows: a
#: margin for the compute dtype's rounding of the table and of the per-pixel exponent
BAND_ENLARGE = 1.01


@njit(cache=True, inline="always")
def _image_ellipse(U, V, W, r2):
    """Image of the disc u^2 + v^2 <= r2 of a surfel from its dual conic H diag(r2, r2, -1) H^T (H: the
    ray transform's rows U, V, W, 3 float64 each) -> (centre cx, cy, Sxx, Syy, Sxy, ok): the ellipse
    (p - c)^T S^-1 (p - c) <= 1; ok False (and zeros) where the disc crosses the camera plane (no
    bounded image). Branch-free."""
    U0, U1, U2 = U
    V0, V1, V2 = V
    W0, W1, W2 = W
    d = r2 * (W0 * W0 + W1 * W1) - W2 * W2
    ok = (W2 > 0.0) & (d < 0.0)
    d = d if ok else -1.0
    cx = (r2 * (U0 * W0 + U1 * W1) - U2 * W2) / d
    cy = (r2 * (V0 * W0 + V1 * W1) - V2 * W2) / d
    sxx = cx * cx - (r2 * (U0 * U0 + U1 * U1) - U2 * U2) / d
    syy = cy * cy - (r2 * (V0 * V0 + V1 * V1) - V2 * V2) / d
    sxy = cx * cy - (r2 * (U0 * V0 + U1 * V1) - U2 * V2) / d
    return (cx if ok else 0.0), (cy if ok else 0.0), (sxx if ok else 0.0), (syy if ok else 0.0), \
        (sxy if ok else 0.0), ok


@njit(cache=True, inline="always")
def _gather_needed(inputs, needed, i, n0, n1, rows, src):
    """The needed table rows g = i N + n, n in [n0, n1) of `surfel_table`'s inputs (`SurfelTableInputs`:
    means2d, tsl, log_opac, and m2_rows, tsl_rows, means2d and tsl as [I*N, ·] row views) -> their count
    L; rows [L] the row numbers and
    src [13 CHUNK] (float64) their inputs: rows 0-8 the ray transform, 9-10 the projected centre,
    11 the exponent bound e = SIGMA_ROW + log o, 12 the log opacity log o. The ray-transform and centre
    rows are prefetched `ck.GATHER_AHEAD` rows ahead (`ck.needed_rows`): without it, the first load of
    each row missed cache, half of `surfel_table`'s time in a 128 px training step."""
    means2d, tsl, log_opac = inputs.means2d, inputs.tsl, inputs.log_opac
    m2_rows, tsl_rows = inputs.m2_rows, inputs.tsl_rows
    N = log_opac.shape[0]
    L = ck.needed_rows(needed, i * N + n0, i * N + n1, rows)
    for j in range(L):
        ahead = ck.row_ahead(rows, j, L)
        ck.prefetch_whole_row(tsl_rows, ahead)
        ck.prefetch_row(m2_rows, ahead)
        n = rows[j] - i * N
        for c in range(9):
            src[c * CHUNK + j] = float(tsl[i, n, c])
        src[9 * CHUNK + j] = float(means2d[i, n, 0])
        src[10 * CHUNK + j] = float(means2d[i, n, 1])
        src[11 * CHUNK + j] = SIGMA_ROW + float(log_opac[n])
        src[12 * CHUNK + j] = log_opac[n]
    return L


@njit(cache=True, inline="always")
def _surfel_rows(src, L, out):
    """`_gather_needed`'s inputs -> out [ck.TAB_COLS CHUNK]: the table's columns (`surfel_table`), column
    c in out's row c. Branch-free: the loop vectorizes."""
    R_ = ck.ROW
    for jj in range(L):
        j = np.uint64(jj)
        e, mx, my = src[R_[11] + j], src[R_[9] + j], src[R_[10] + j]
        cx, cy, sxx, syy, sxy, ok = _image_ellipse((src[j], src[R_[1] + j], src[R_[2] + j]),
                                                   (src[R_[3] + j], src[R_[4] + j], src[R_[5] + j]),
                                                   (src[R_[6] + j], src[R_[7] + j], src[R_[8] + j]), 2.0 * e)
        ok = ok & (e > 0.0)
        out[j], out[R_[1] + j] = (cx if ok else mx), (cy if ok else my)
        out[R_[2] + j], out[R_[3] + j], out[R_[4] + j] = mx, -sxy, my
        out[R_[5] + j] = math.sqrt(e) + 1.0 if e > 0.0 else -1.0  # filter disc: FILTER_2D |d|^2 / 2 <= e
        out[R_[6] + j] = math.sqrt(max(sxx, 0.0)) + 1.0 if ok else -1.0
        out[R_[7] + j] = math.sqrt(max(syy, 0.0)) + 1.0 if ok else -1.0
        # Q = adj S, r2 = det S: the ellipse without dividing by det S (tiny for surfels seen edge-on)
        b = ck.band_values(syy, -sxy, sxx, (sxx * syy - sxy * sxy) * BAND_ENLARGE if ok else 0.0)
        out[R_[8] + j], out[R_[9] + j], out[R_[10] + j], out[R_[11] + j] = b[0], b[1], b[2], b[3]
        out[R_[12] + j], out[R_[13] + j], out[R_[14] + j], out[R_[15] + j] = b[4], b[5], b[6], src[R_[12] + j]


@njit(cache=True, parallel=True)
def surfel_table(means2d, tsl, log_opac, needed, tab):
    """Per (image, surfel) bounds of the pixels it can reach (alpha > 1/255), computed once instead of
    once per tile intersection: means2d [I,N,2], tsl [I,N,9], log_opac [N], needed [I*N] bool
    (`ck.rows_needed`) -> tab [I*N, ck.TAB_COLS] (compute dtype; rows not needed are left as they
    were), row image * N + surfel. The pixels are the union of the 2D filter's disc and
    the image ellipse of the disc u^2 + v^2 <= 2 (SIGMA_ROW + log o). Columns: 0-1 the ellipse's
    centre; 2, 4 the projected centre (x, y); 5 the filter disc's radius + 1 (-1: no pixel is
    reached); 6-7 the ellipse's half-extents + 1 (-1: the disc crosses the camera plane, every pixel
    of a tile); 3, 8-14 the ellipse's `ck.band_constants` (B of Q = adj S, r2 = det S), as
    `ck.band_rows` reads them; 15 the log opacity (the compositing loops read the centre and it from this
    row, one cache line, instead of two more random rows). Per chunk of surfels and pose: the needed rows
    gathered, computed in a vectorized loop, written back."""
    I, N = means2d.shape[0], log_opac.shape[0]
    m2_rows, tsl_rows = means2d.reshape((I * N, 2)), _tsl_rows(tsl)
    for ch in prange((N + CHUNK - 1) // CHUNK):
        rows = np.empty(CHUNK, np.int64)
        src = np.empty(13 * CHUNK)
        out = np.empty(ck.TAB_COLS * CHUNK)
        inputs = SurfelTableInputs(means2d, tsl, log_opac, m2_rows, tsl_rows)
        for i in range(I):
            L = _gather_needed(inputs, needed, i, ch * CHUNK, min(N, (ch + 1) * CHUNK), rows, src)
            _surfel_rows(src, L, out)
            for j in range(L):
                for c in range(ck.TAB_COLS):
                    tab[rows[j], c] = out[c * CHUNK + j]


@njit(cache=True, inline="always")
def _footprint_surfel(tab, g, x0, y0, ts, W, H):
    """Tile-local rows [ra, rb) and columns [ca, cb) that `surfel_table` row g can reach: the box of
    the filter's disc and the ellipse (1-pixel margins), the whole tile where the disc crosses the
    camera plane, nothing where the opacity is below 1/255 everywhere."""
    rf = float(tab[g, 5])
    if rf < 0.0:
        return 0, 0, 0, 0
    hx, hy = float(tab[g, 6]), float(tab[g, 7])
    if hx < 0.0:
        return 0, min(ts, H - y0), 0, min(ts, W - x0)
    mx, my, cx, cy = float(tab[g, 2]), float(tab[g, 4]), float(tab[g, 0]), float(tab[g, 1])
    ra, rb = _axis_range(min(my - rf, cy - hy), max(my + rf, cy + hy), y0, H, ts)
    ca, cb = _axis_range(min(mx - rf, cx - hx), max(mx + rf, cx + hx), x0, W, ts)
    return ra, rb, ca, cb


@njit(cache=True, inline="always")
def _surfel_band_rows(tab, g, x0, y0, qa, qb, ra, rb):
    """Rows [ra, rb) narrowed to those whose pixels in tile-local columns [qa, qb) can lie in the
    ellipse (`ck.band_rows`) or in the filter's disc (its box where the columns meet it)."""
    era, erb = ck.band_rows(tab, g, x0, y0, qa, qb, ra, rb)
    mx, my, rf = float(tab[g, 2]), float(tab[g, 4]), float(tab[g, 5])
    if x0 + qa + 0.5 - mx > rf or mx - (x0 + qb - 0.5) > rf:
        return era, erb
    dra = max(ra, ck.floor_int(my - rf) - y0)
    drb = min(rb, ck.ceil_int(my + rf) - y0)
    if dra >= drb:
        return era, erb
    if era >= erb:
        return dra, drb
    return min(era, dra), max(erb, drb)


@njit(cache=True, inline="always")
def _tile_local(cxt, cyt, x0, y0, ts):
    """Pixel centres relative to the tile centre (x0 + ts / 2, y0 + ts / 2), compute dtype (exact)
    -> (lxt, lyt [P], tile centre ox, oy)."""
    ox, oy = x0 + 0.5 * ts, y0 + 0.5 * ts
    lxt = np.empty_like(cxt)
    lyt = np.empty_like(cyt)
    for p in range(cxt.shape[0]):
        lxt[p] = cxt[p] - ox
        lyt[p] = cyt[p] - oy
    return lxt, lyt, ox, oy


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _surfel_exponent(lx, ly, dx, dy, cc, lo, kc):
    """Exponent s = min(|uv|^2 of h_u x h_v, FILTER_2D |d|^2) / 2 - log o at one pixel (lx, ly tile-local;
    dx, dy from the projected centre; cc: the 9 `_cross_coefs` as a tuple) -> (s, X, Y, 1/Z (0 where
    Z = 0), g3 = |uv|^2, whether the 3D term is the smaller)."""
    zero = kc[3]
    X = cc[0] + lx * cc[3] + ly * cc[6]
    Y = cc[1] + lx * cc[4] + ly * cc[7]
    Z = cc[2] + lx * cc[5] + ly * cc[8]
    nz = Z != zero
    iz = kc[1] / (Z if nz else kc[1])
    iz = iz if nz else zero
    g3 = (X * X + Y * Y) * (iz * iz)
    g2 = (kc[1] + kc[1]) * (dx * dx + dy * dy)  # FILTER_2D = 2
    use3 = nz & (g3 <= g2)
    return kc[0] * (g3 if use3 else g2) - lo, X, Y, iz, g3, use3


@njit(cache=True)  # not inlined: numba's parfor analysis rejects its nested tuple there
def _surfel(tab, tsl, g, N, ox, oy, cc):
    """Entry g = image * N + surfel -> (image gi, surfel n, centre mx, my and log opacity (`surfel_table`
    row g), the 9 cross coefficients as a tuple (compute dtype), Up, Vp (for the backward))."""
    gi, n = g // N, g % N
    up_vp = _cross_coefs(tsl, gi, n, ox, oy, cc)
    c9 = (cc[0], cc[1], cc[2], cc[3], cc[4], cc[5], cc[6], cc[7], cc[8])
    return gi, n, tab[g, 2], tab[g, 4], tab[g, 15], c9, up_vp


@njit(cache=True, inline="always")
def _tsl_rows(tsl):
    """tsl [I, N, 9] -> its rows as an [I*N, 9] view (row image * N + surfel)."""
    I, N = tsl.shape[0], tsl.shape[1]
    return tsl.reshape((I * N, 9))


@njit(cache=True, inline="always")
def _prefetch_surfel(tab, tsl_rows, feats, g):
    """Software prefetch of what an intersection with row g reads: its table row (one line:
    `cpu_backend.table_buffer`), ray transform and features (both ends: a row may straddle two lines).
    Rows are random across [I*N, ·] arrays (4.3 MB of ray transforms for 6 poses x 20 000 surfels, beyond
    L2); in a 128 px training step the forward measured 7.2 -> 6.4 ms and the backward 8.2 -> 6.7 ms with
    prefetching (2026-11-26), and the forward ~10 % less again with whole rows and the table aligned (2026-11-29)."""
    ck.prefetch_row(tab, g)
    ck.prefetch_whole_row(tsl_rows, g)
    ck.prefetch_whole_row(feats, g)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_fwd_2dgs(tables, tiles, consts, out, rows_hit):
    """`composite.raster_fwd` for surfels (tiles: `Tiles`, consts: `Constants`, as there). tables
    (`SurfelTables`): tsl [I, N, 9] ray transforms, tab [I*N, ck.TAB_COLS] `surfel_table` (the rows each
    column group visits), feats [I*N, Cf] with the depth in channel DEPTH_CH; out (`Composite`): feat
    [Iout, H, W, Cf + 1] gets sum w f and, in its last channel, the depth distortion 2 sum_k w_k (z_k W_k -
    A_k) (W_k, A_k: sums of w_j, w_j z_j over earlier j); T and last as `composite.raster_fwd`'s.
    rows_hit [M, ts // cw, 2] int16 (zeros on entry): for each intersection and column group, the tile
    rows [first, last + 1) holding a pixel it was composited into (w > 0), or an empty range; the
    backward visits only those."""
    tsl, tab, feats, kc = tables.tsl, tables.tab, tables.feats, consts.kc
    flat_ids, bin_start, bins, pix_view, tile_size, tiles_x, cw = tiles.flat_ids, tiles.bin_start, tiles.bins, \
        tiles.pix_view, tiles.tile_size, tiles.tiles_x, tiles.cw
    Iout, H, W = pix_view.shape
    N = tsl.shape[1]
    Cf = feats.shape[1]
    n_tiles = tiles_x * ((H + tile_size - 1) // tile_size)
    ts = tile_size
    one, zero = kc[1], kc[3]
    no_row, ts32 = np.int32(-1), np.int32(ts)
    rowt = state_rows(ts, cw)  # the same for every tile
    tsl_rows = _tsl_rows(tsl)
    for jb in prange(bins.shape[0]):
        b = bins[jb]
        tile = bin_tile(b, n_tiles, tiles_x, ts, W, H, Iout, cw)
        x0, y0 = tile.x0, tile.y0
        T, acc, last, cxt, cyt, wbuf, sbuf, row_active, n_active = tile_state_fwd(pix_view, tile, Cf + 1, consts)
        lxt, lyt, ox, oy = _tile_local(cxt, cyt, x0, y0, ts)
        cc = np.empty(9, kc.dtype)
        for k in range(bin_start[b], bin_start[b + 1]):
            if n_active == 0:
                break
            # flat_ids[k] is read where it is used: held in a local, the forward measured 12.5 -> 15.3 ms (σ 2.5)
            gp = flat_ids[min(k + ck.PREFETCH_AHEAD, bin_start[b + 1] - 1)]
            _prefetch_surfel(tab, tsl_rows, feats, gp)
            ra, rb, ca, cb = _footprint_surfel(tab, flat_ids[k], x0, y0, ts, W, H)
            ra, rb = trim_rows_active(ra, rb, row_active)
            if ra >= rb or ca >= cb:
                continue
            gi, n, mx, my, lo, c9, _ = _surfel(tab, tsl, flat_ids[k], N, ox, oy, cc)
            zk = feats[flat_ids[k], DEPTH_CH]
            k1 = np.int32(k + 1)
            for q in range(ca // cw, (cb - 1) // cw + 1):
                qra, qrb = _surfel_band_rows(tab, flat_ids[k], x0, y0, max(ca, q * cw), min(cb, q * cw + cw), ra, rb)
                if qra >= qrb:
                    continue
                pa, pb = q * ts * cw + qra * cw, q * ts * cw + qrb * cw
                stopped = 0
                r_lo, r_hi = ts32, no_row  # rows composited into (selects: the loop still vectorizes)
                for pp in range(pa, pb):
                    p = np.uint64(pp)
                    s, _, _, _, _, _ = _surfel_exponent(lxt[p], lyt[p], cxt[p] - mx, cyt[p] - my, c9, lo, kc)
                    Tp = T[p]
                    w, T[p], last[p], stop = composite_pixel(s, Tp, last[p], k1, kc)
                    wbuf[p] = w
                    r_lo, r_hi = track_rows(w, rowt[p], r_lo, r_hi, zero, ts32, no_row)
                    acc[Cf, p] += (w + w) * (zk * (one - Tp) - acc[DEPTH_CH, p])  # before the depth update
                    sbuf[p] = 1 if stop else 0
                    stopped += 1 if stop else 0
                accumulate_features(acc, wbuf, feats, flat_ids[k], pa, pb)
                rows_hit[k, q, 0], rows_hit[k, q, 1] = r_lo, r_hi + 1
                if stopped:
                    n_active -= stopped
                    retire_stopped(row_active, sbuf, qra, qrb, q * cw, q * cw + 1, ts, cw)
        finish_tile_fwd(pix_view, tile, T, last, acc, out)


@njit(cache=True, inline="always")
def _write_surfel_grad(isect_grad, k, ac, up_vp, w_row, origin, sums, gf):
    """Row k of isect_grad from dL/d cross coefficients ac [9] (C0, C1, C2; `_cross_coefs`' Up, Vp as up_vp,
    its ray transform's row W as w_row, the tile centre (ox, oy) as origin) and the intersection's sums
    (`SurfelIsectGrad`): dL/d (centre x, y; ray transform rows U, V, W; log opacity; features gf [Cf], plus
    the sums' z on the depth)."""
    u0, u1, u2, v0, v1, v2 = up_vp
    W0, W1, W2 = w_row
    ox, oy = origin
    gmx, gmy, glo, gz = sums.mx, sums.my, sums.lo, sums.z
    # C0 = Up x Vp, C1 = W x Vp, C2 = Up x W: d(a x b).g / da = b x g, / db = g x a
    gu0 = v1 * ac[2] - v2 * ac[1] + W1 * ac[8] - W2 * ac[7]
    gu1 = v2 * ac[0] - v0 * ac[2] + W2 * ac[6] - W0 * ac[8]
    gu2 = v0 * ac[1] - v1 * ac[0] + W0 * ac[7] - W1 * ac[6]
    gv0 = ac[1] * u2 - ac[2] * u1 + ac[4] * W2 - ac[5] * W1
    gv1 = ac[2] * u0 - ac[0] * u2 + ac[5] * W0 - ac[3] * W2
    gv2 = ac[0] * u1 - ac[1] * u0 + ac[3] * W1 - ac[4] * W0
    gw0 = v1 * ac[5] - v2 * ac[4] + ac[7] * u2 - ac[8] * u1 + ox * gu0 + oy * gv0
    gw1 = v2 * ac[3] - v0 * ac[5] + ac[8] * u0 - ac[6] * u2 + ox * gu1 + oy * gv1
    gw2 = v0 * ac[4] - v1 * ac[3] + ac[6] * u1 - ac[7] * u0 + ox * gu2 + oy * gv2
    isect_grad[k, 0], isect_grad[k, 1], isect_grad[k, 11] = gmx, gmy, glo
    isect_grad[k, 2], isect_grad[k, 3], isect_grad[k, 4] = -gu0, -gu1, -gu2
    isect_grad[k, 5], isect_grad[k, 6], isect_grad[k, 7] = -gv0, -gv1, -gv2
    isect_grad[k, 8], isect_grad[k, 9], isect_grad[k, 10] = gw0, gw1, gw2
    for c in range(gf.shape[0]):
        isect_grad[k, 12 + c] = gf[c] + (gz if c == DEPTH_CH else 0.0)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_bwd_2dgs(tables, tiles, consts, px, isect_grad, rows_hit):
    """Back-to-front backward of `raster_fwd_2dgs` (tables, tiles, consts: the forward's). px
    (`BackwardPixels`): the forward's T and last, g_T, and g_feat [Iout, H, W, Cf + 2]: dL/dF (Cf channels),
    2 dL/d distortion, the forward's accumulated depth. isect_grad [M, 12 + Cf] per intersection:
    dL/d centre x, y; ray transform (9, row-major); log opacity; features (zeros on entry). rows_hit: the
    forward's; the pixels outside those rows were not composited into, so their terms are zero, and an
    intersection without any row is skipped (41 % of them in a 128 px `ours_2dgs` step)."""
    tsl, tab, feats, kc = tables.tsl, tables.tab, tables.feats, consts.kc
    flat_ids, bin_start, bins, pix_view, tile_size, tiles_x, cw = tiles.flat_ids, tiles.bin_start, tiles.bins, \
        tiles.pix_view, tiles.tile_size, tiles.tiles_x, tiles.cw
    Iout, H, W = pix_view.shape
    N = tsl.shape[1]
    Cf = feats.shape[1]
    n_tiles = tiles_x * ((H + tile_size - 1) // tile_size)
    ts = tile_size
    half, one, zero = kc[0], kc[1], kc[3]
    tsl_rows = _tsl_rows(tsl)
    for jb in prange(bins.shape[0]):
        b = bins[jb]
        tile = bin_tile(b, n_tiles, tiles_x, ts, W, H, Iout, cw)
        x0, y0 = tile.x0, tile.y0
        T, gTT, suffix, gF, last, cxt, cyt, ebuf, wbuf, _, k_end = tile_state_bwd(pix_view, tile, Cf + 2, consts, px,
                                                                                  bin_start[b])
        gf = np.empty(Cf, kc.dtype)  # feature gradients only (gF's last two rows are distortion state)
        lxt, lyt, ox, oy = _tile_local(cxt, cyt, x0, y0, ts)
        w_after = np.zeros_like(T)  # sum of w_j over the later j
        z_after = np.zeros_like(T)  # sum of w_j z_j over the later j
        cc = np.empty(9, kc.dtype)
        ac = np.empty(9, kc.dtype)
        for k in range(k_end - 1, bin_start[b] - 1, -1):
            g = flat_ids[k]
            _prefetch_surfel(tab, tsl_rows, feats, flat_ids[max(k - ck.PREFETCH_AHEAD, bin_start[b])])
            if not ck.composited_any(rows_hit, k):  # every term zero: its isect_grad row stays zeros
                continue
            gi, n, mx, my, lo, c9, up_vp = _surfel(tab, tsl, g, N, ox, oy, cc)
            zk = feats[g, DEPTH_CH]
            k32 = np.int32(k)
            a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = gmx = gmy = glo = gz = zero
            gf[:] = zero
            for q in range(rows_hit.shape[1]):
                ra, rb = rows_hit[k, q, 0], rows_hit[k, q, 1]
                if ra >= rb:
                    continue
                pa, pb = q * ts * cw + ra * cw, q * ts * cw + rb * cw
                feature_dot(ebuf, gF, feats, g, pa, pb, zero)
                for pp in range(pa, pb):
                    p = np.uint64(pp)
                    lx, ly, dx, dy = lxt[p], lyt[p], cxt[p] - mx, cyt[p] - my
                    s, X, Y, iz, g3, use3 = _surfel_exponent(lx, ly, dx, dy, c9, lo, kc)
                    w, T[p], T_exc, a_ratio, live = uncomposite_pixel(s, T[p], last[p], k32, kc)
                    wbuf[p] = w
                    gD2, wa, za = gF[Cf, p], w_after[p], z_after[p]
                    W_exc = one - T_exc
                    A_exc = gF[Cf + 1, p] - za - w * zk
                    e = ebuf[p] + gD2 * ((zk * W_exc - A_exc) + (za - zk * wa))
                    gz += gD2 * w * (W_exc - wa)
                    w_after[p] = wa + w
                    z_after[p] = za + w * zk
                    G, suffix[p] = exponent_grad(e, w, a_ratio, live, suffix[p], gTT[p], zero)
                    G3 = half * G if use3 else zero
                    G2 = half * G - G3
                    t = (G3 + G3) * iz * iz
                    gX, gY, gZ = t * X, t * Y, -(G3 + G3) * g3 * iz
                    a0 += gX
                    a1 += gY
                    a2 += gZ
                    a3 += lx * gX
                    a4 += lx * gY
                    a5 += lx * gZ
                    a6 += ly * gX
                    a7 += ly * gY
                    a8 += ly * gZ
                    gmx -= (G2 + G2) * (dx + dx)  # d/dm of FILTER_2D |pixel - m|^2
                    gmy -= (G2 + G2) * (dy + dy)
                    glo -= G
                add_feature_grads(gf, wbuf, gF, pa, pb, zero)
            ac[0], ac[1], ac[2], ac[3], ac[4], ac[5], ac[6], ac[7], ac[8] = a0, a1, a2, a3, a4, a5, a6, a7, a8
            _write_surfel_grad(isect_grad, k, ac, up_vp, (tsl[gi, n, 6], tsl[gi, n, 7], tsl[gi, n, 8]), (ox, oy),
                               SurfelIsectGrad(gmx, gmy, glo, gz), gf)
