"""Tile compositing, forward (front to back) and backward (back to front, recovering T by division): the
Gaussian and feature tables, the per-tile state, the bin bodies and the gradient reductions."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from egobench.render.cpu.args import IsectGrad, Tile
from egobench.render.cpu.compiler import (
    BIN_BODY,
    FASTMATH,
    GATHER_AHEAD,
    PREFETCH_AHEAD,
    _exp_neg,
    prefetch_row,
    prefetch_whole_row,
)
from egobench.render.cpu.projection import ALPHA_MAX, ALPHA_MIN, CHUNK, SIGMA_SKIP, T_STOP

COLUMN_GROUP = 8  # columns per contiguous block of a tile's state (tile sizes that are multiples of 8)
SIGMA_ROW = 5.56  # exponent bound of the rows a Gaussian can reach (> SIGMA_SKIP: a safe superset)
#: Taylor coefficients of exp, highest degree first (degree 13)
_EXP_COEFS = tuple(1.0 / math.factorial(d) for d in range(13, -1, -1))


def compute_constants(dtype) -> np.ndarray:
    """Constants of the compositing loops in the compute dtype (float32 inputs are composited in
    float32, as the torch backend and gsplat do; float64 in float64): numba types each pixel's
    arithmetic from these, so no float64 literal widens a float32 loop (8 lanes instead of 4)."""
    return np.array((0.5, 1.0, ALPHA_MAX, 0.0, 0.0625, 6.0) + _EXP_COEFS + (ALPHA_MIN, T_STOP, SIGMA_SKIP), dtype=dtype)


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
def bin_tile(b, n_tiles, tiles_x, ts, W, H, Iout, cw):
    """Bin b (image i, tile t) -> its `Tile` (i, output image o, tile pixel bounds x0, y0, x1, y1, ts, cw)."""
    i, t = b // n_tiles, b % n_tiles
    o = 0 if Iout == 1 else i
    x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
    return Tile(i, o, x0, y0, min(x0 + ts, W), min(y0 + ts, H), ts, cw)


@njit(cache=True, inline="always")
def tile_of_bin(b, pix_view, ts, tiles_x, cw):
    """`bin_tile` of bin b, its sizes read from the view map pix_view [Iout, H, W] (ts-pixel tiles, tiles_x
    per row, column groups of cw) -> its `Tile`."""
    Iout, H, W = pix_view.shape
    return bin_tile(b, tiles_x * ((H + ts - 1) // ts), tiles_x, ts, W, H, Iout, cw)


@njit(cache=True, inline="always")
def _start_tile_fwd(pix_view, tile, one, T, row_active):
    """T = 1 at the tile's (`Tile`) pixels whose view is i (counted per row in row_active) -> pixels to composite."""
    i, o, x0, y0, x1, y1, ts, cw = tile.i, tile.o, tile.x0, tile.y0, tile.x1, tile.y1, tile.ts, tile.cw
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
def finish_tile_fwd(pix_view, tile, T, last, acc, out):
    """Writes the tile's (`Tile`) state (|T|, last, accumulated features) to the output pixels whose view is
    i (out: `Composite`)."""
    i, o, x0, y0, x1, y1, ts, cw = tile.i, tile.o, tile.x0, tile.y0, tile.x1, tile.y1, tile.ts, tile.cw
    out_feat, out_T, out_last = out.feat, out.T, out.last
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
def _start_tile_bwd(pix_view, tile, px, T, gTT, last, gF, k_end):
    """Loads the forward's final T, last and the output gradients (px: `BackwardPixels`) of the tile's
    (`Tile`) pixels whose view is i into the tile state -> one past the last intersection to visit (k_end
    on entry: at least)."""
    i, o, x0, y0, x1, y1, ts, cw = tile.i, tile.o, tile.x0, tile.y0, tile.x1, tile.y1, tile.ts, tile.cw
    out_T, out_last = px.T, px.last
    g_feat, g_T = px.g_feat, px.g_T
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
def _write_isect_grad(isect_grad, k, half, sums, gf):
    """Row k of isect_grad: dL/d (mean x, y, conic a, b, c, log opacity, features gf) from the intersection's
    sums (`IsectGrad`; half: 0.5 in the compute dtype)."""
    gmx, gmy, ga, gb, gc, glo = sums.mx, sums.my, sums.a, sums.b, sums.c, sums.lo
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
def tile_state_fwd(pix_view, tile, Cf, consts):
    """Per-tile state of the forward (compute dtype, `_state_index` layout; tile: `Tile`, consts:
    `Constants`) -> (T [P] (1 at the pixels whose view is i), acc [Cf, P], last [P] int32, pixel centres
    cxt, cyt [P], weights wbuf [P], stop flags sbuf [P] int32, row_active [ts] pixels still compositing
    per row, their number)."""
    kc, ts = consts.kc, tile.ts
    P = ts * ts
    T, last, cxt, cyt = _tile_base(consts.centres, tile.x0, tile.y0, ts, tile.cw, kc)
    acc = np.zeros((Cf, P), kc.dtype)
    wbuf = np.empty(P, kc.dtype)
    sbuf = np.zeros(P, np.int32)  # 1 where the last Gaussian stopped the pixel
    row_active = np.zeros(ts, np.int64)
    n_active = _start_tile_fwd(pix_view, tile, kc[1], T, row_active)
    return T, acc, last, cxt, cyt, wbuf, sbuf, row_active, n_active


@njit(cache=True, inline="always", fastmath=FASTMATH)
def accumulate_features(acc, wbuf, feats, g, pa, pb):
    """acc[c, p] += w[p] * feats[g, c] over state entries [pa, pb)."""
    for c in range(feats.shape[1]):  # one loop per channel: an inner channel loop would stop the vectorizer
        fc = feats[g, c]
        for pp in range(pa, pb):
            acc[c, np.uint64(pp)] += wbuf[np.uint64(pp)] * fc


@njit(cache=True, inline="always")
def tile_state_bwd(pix_view, tile, Cf, consts, px, k_begin):
    """Per-tile state of the backward (tile: `Tile`, consts: `Constants`), loaded from the forward's results
    and the output gradients (px: `BackwardPixels`; `_start_tile_bwd`) -> (T, gTT, suffix, gF [Cf, P], last,
    cxt, cyt, ebuf, wbuf, gf [Cf], one past the last intersection to visit (at least k_begin))."""
    kc, ts = consts.kc, tile.ts
    P = ts * ts
    T, last, cxt, cyt = _tile_base(consts.centres, tile.x0, tile.y0, ts, tile.cw, kc)
    gTT = np.zeros(P, kc.dtype)
    suffix = np.zeros(P, kc.dtype)
    gF = np.zeros((Cf, P), kc.dtype)
    k_end = _start_tile_bwd(pix_view, tile, px, T, gTT, last, gF, k_begin)
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
def _fwd_bin(b, tables, tiles, consts, out, rows_hit, rowt):
    """`raster_fwd` on bin b (image i, tile t): its `prange` body as a function of its own, so that numba's
    parfor passes compile it once (`BIN_BODY`: the 3DGS set compiles ~20 % faster and runs as fast;
    results/speed/README.md, 2026-11-28)."""
    tab, feats, kc = tables.tab, tables.feats, consts.kc
    flat_ids, bin_start, pix_view, ts, tiles_x, cw = tiles.flat_ids, tiles.bin_start, tiles.pix_view, \
        tiles.tile_size, tiles.tiles_x, tiles.cw
    H, W = pix_view.shape[1], pix_view.shape[2]
    Cf = feats.shape[1]
    zero, no_row, ts32 = kc[3], np.int32(-1), np.int32(ts)
    tile = tile_of_bin(b, pix_view, ts, tiles_x, cw)
    x0, y0 = tile.x0, tile.y0
    T, acc, last, cxt, cyt, wbuf, sbuf, row_active, n_active = tile_state_fwd(pix_view, tile, Cf, consts)
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
    finish_tile_fwd(pix_view, tile, T, last, acc, out)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_fwd(tables, tiles, consts, out, rows_hit):
    """Front-to-back compositing of each bin (image i, tile t) in ``tiles.bins`` into the output pixels
    whose view is i (`Tiles`: pix_view [Iout,H,W], intersections flat_ids by bin_start, tile_size, tiles_x,
    cw `column_group`). tables (`Tables`): tab [I*N, TAB_COLS] `gaussian_table` (centres, conics, log
    opacities, footprints), feats [I*N, Cf] per (image, Gaussian) features; consts (`Constants`): kc
    `compute_constants`, centres [max(W, H) + tile_size] pixel centres (index + 0.5), compute dtype.
    Writes out (`Composite`): feat [Iout,H,W,Cf] (sum w f), T [Iout,H,W] (composited transmittance) and
    last [Iout,H,W] (one past the last composited intersection).
    Per-pixel state: T > 0 while compositing, -T once stopped, 0 for pixels of other views; stored
    in column groups (`_state_index`) so that the pixels a Gaussian can reach in a group (its
    ellipse's rows, trimmed to rows still compositing) are one contiguous range, updated by one
    branch-free loop (it vectorizes). rows_hit [M, ts // cw, 2] int16 (zeros on entry): per intersection
    and column group, the rows [first, last + 1) it was composited into (w > 0), else an empty range;
    the backward visits only those."""
    rowt = state_rows(tiles.tile_size, tiles.cw)  # the same for every tile
    bins = tiles.bins
    for jb in prange(bins.shape[0]):
        _fwd_bin(bins[jb], tables, tiles, consts, out, rows_hit, rowt)


@njit(**BIN_BODY)
def _bwd_bin(b, tables, tiles, consts, px, isect_grad, rows_hit):
    """`raster_bwd` on bin b: its `prange` body, compiled as `_fwd_bin` is."""
    tab, feats, kc = tables.tab, tables.feats, consts.kc
    flat_ids, bin_start, pix_view, ts, tiles_x, cw = tiles.flat_ids, tiles.bin_start, tiles.pix_view, \
        tiles.tile_size, tiles.tiles_x, tiles.cw
    Cf = feats.shape[1]
    zero = kc[3]
    tile = tile_of_bin(b, pix_view, ts, tiles_x, cw)
    T, gTT, suffix, gF, last, cxt, cyt, ebuf, wbuf, gf, k_end = tile_state_bwd(pix_view, tile, Cf, consts, px,
                                                                                bin_start[b])
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
        _write_isect_grad(isect_grad, k, kc[0], IsectGrad(gmx, gmy, ga, gb, gc, glo), gf)


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def raster_bwd(tables, tiles, consts, px, isect_grad, rows_hit):
    """Back-to-front backward of `raster_fwd` (T recovered by division, as gsplat; tables, tiles, consts: the
    forward's) from px (`BackwardPixels`: the forward's T and last, dL/d feat, dL/dT): isect_grad
    [M, 6 + Cf] per intersection (dL/d mean x, y; dL/d conic a, b, c; dL/d log opacity; dL/d features).
    rows_hit: the forward's; the pixels outside those rows were not composited into (zero terms)."""
    bins = tiles.bins
    for jb in prange(bins.shape[0]):
        _bwd_bin(bins[jb], tables, tiles, consts, px, isect_grad, rows_hit)


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
