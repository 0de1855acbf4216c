"""Tile binning: which (pose, tile) bins each projected Gaussian touches, in (bin, depth, index) order (a
sequential counting sort and a radix sort of depth keys, as the torch backend's stable sorts)."""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from egobench.render.cpu.args import BinLayout, Footprints, Rects, SortedPairs, TileGrid


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
def _rects_part(pairs, grid, boxes, k0, k1, out):
    """The visible pairs (`Footprints`) among k0 <= k < k1 (k = image * N + Gaussian), in k order: their tile
    rectangles (x0, x1, y0, y1) in the grid (`TileGrid`), clipped to each image's boxes (`_needed_boxes`), k and
    depth written to out (`Rects`: rect, vis, keys) from row k0 on -> their count."""
    means2d, radii, depths = pairs.means2d, pairs.radii, pairs.depths
    tile_size, tiles_x, tiles_y = grid.tile_size, grid.tiles_x, grid.tiles_y
    rect, vis, keys = out.rect, out.vis, out.keys
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
def _tile_rects(pairs, grid, boxes, parts, out):
    """`_rects_part` over ``parts`` ranges of pairs in parallel (rows from each range's first pair on),
    then packed in order -> the count: the same rows as one range, for any number of parts."""
    rect, vis, keys = out.rect, out.vis, out.keys
    total = pairs.depths.size
    counts = np.empty(parts, np.int64)
    for c in prange(parts):
        counts[c] = _rects_part(pairs, grid, boxes, c * total // parts, (c + 1) * total // parts, out)
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
    """`Rects` of the nv visible (image, Gaussian) pairs: tile rectangles [nv, 4] int32 (x0, x1, y0, y1),
    their flat ids (ascending) and depths; the pairs in one range per kernel thread (one range: no parallel
    loop), the same result for any thread count."""
    boxes = _needed_boxes(bin_needed, tiles_x, tiles_y)
    pairs, grid = Footprints(means2d, radii, depths), TileGrid(tile_size, tiles_x, tiles_y)
    out = Rects(np.empty((depths.size, 4), np.int32), np.empty(depths.size, np.int64),
                np.empty(depths.size, depths.dtype))
    parts = min(numba.get_num_threads(), depths.size // RECT_PART_MIN)
    if parts <= 1:
        nv = _rects_part(pairs, grid, boxes, 0, depths.size, out)
    else:
        nv = _tile_rects(pairs, grid, boxes, parts, out)
    return Rects(out.rect[:nv], out.vis[:nv], out.keys[:nv])


#: the fewest depth-sorted visible pairs (entries of perm) per kernel thread for which `fill_bins` splits
#: the work; its serial prefix is O(threads x bins), small beside the fill at every size measured
FILL_PART_MIN = 4096


@njit(cache=True, inline="always")
def _bin_walk(pairs, j0, j1, layout, slot, flat_ids, place):
    """The intersections of the sorted entries j0 <= j < j1 (`SortedPairs`; entry j: visible pair perm[j],
    rect [nv, 4] its tiles, vis [nv] its flat id) with the needed bins (`BinLayout`): counted into slot
    [I * tiles] (place False), or written at flat_ids[slot[b]], slot[b] advanced (place True)."""
    rect, vis, perm = pairs.rect, pairs.vis, pairs.perm
    N, tiles_x, bin_needed = layout.N, layout.tiles_x, layout.bin_needed
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
    pairs, layout = SortedPairs(rect, vis, perm), BinLayout(N, tiles_x, bin_needed)
    slot = np.zeros((1, bin_needed.size), np.int64)
    _bin_walk(pairs, 0, perm.shape[0], layout, slot[0], slot[0], False)
    flat_ids, bin_start = _slots_from_counts(slot)
    _bin_walk(pairs, 0, perm.shape[0], layout, slot[0], flat_ids, True)
    return flat_ids, bin_start


@njit(cache=True, parallel=True)
def _fill_bins_parts(rect, vis, perm, N, tiles_x, bin_needed, parts):
    """`_fill_bins` with the sorted entries cut into ``parts`` contiguous ranges, counted and written in
    parallel: the same arrays for any number of parts (a bin's entries stay in sorted order)."""
    nv = perm.shape[0]
    slot = np.zeros((parts, bin_needed.size), np.int64)
    for p in prange(parts):
        _bin_walk(SortedPairs(rect, vis, perm), p * nv // parts, (p + 1) * nv // parts,
                  BinLayout(N, tiles_x, bin_needed), slot[p], slot[p], False)
    flat_ids, bin_start = _slots_from_counts(slot)
    for p in prange(parts):
        _bin_walk(SortedPairs(rect, vis, perm), p * nv // parts, (p + 1) * nv // parts,
                  BinLayout(N, tiles_x, bin_needed), slot[p], flat_ids, True)
    return flat_ids, bin_start


def fill_bins(rect, vis, perm, N, tiles_x, bin_needed):
    """rect [nv, 4] int32 and vis [nv] (`visible_rects`), perm [nv] their depth order, bin_needed [I, tiles]
    -> (flat_ids [M] int64, bin_start [I * tiles + 1] int64): one range of entries per kernel thread (one
    range: no parallel loop), the same result for any thread count."""
    parts = min(numba.get_num_threads(), perm.shape[0] // FILL_PART_MIN)
    if parts <= 1:
        return _fill_bins(rect, vis, perm, N, tiles_x, bin_needed)
    return _fill_bins_parts(rect, vis, perm, N, tiles_x, bin_needed, parts)
