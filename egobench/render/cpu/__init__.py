"""The compiled CPU backend's numba kernels (3DGS; gsplat 1.5.3 semantics, as torch_backend.py), in rooms:
`compiler` (numba set-up, fast-math, intrinsics), `projection`, `binning`, `composite`, and `surfels` (2DGS);
`args` holds the named tuples that group the kernels' arguments (no kernel takes more than eight).
This package namespace holds every kernel, helper and argument group of the first five (the backends call
them as ``ck.*``).

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

from egobench.render.cpu.args import (  # noqa: F401
    BackwardPixels, BinLayout, Composite, Constants, Ewa, Footprints, IsectGrad, Pair, Projected, ProjectedGrads, ProjectedSurfelGrads, ProjectedSurfels, Rects, SortedPairs, SplatGrads, Splats, SurfelIsectGrad, SurfelTableInputs, SurfelTables, Tables, Tile, TileGrid, Tiles, View,
)
from egobench.render.cpu.compiler import (  # noqa: F401
    BIN_BODY, FASTMATH, GATHER_AHEAD, NoAliasCompiler, PREFETCH_AHEAD, _exp_neg, _exp_neg_impl, prefetch_at, prefetch_row, prefetch_whole_row, scalar_loop,
)
from egobench.render.cpu.projection import (  # noqa: F401
    ALPHA_MAX, ALPHA_MIN, CHUNK, EXTENT_SIGMAS, ROW, SIGMA_SKIP, T_STOP, _U1, _U2, _U3, _argmin3, _clip_limits, _conic_grad, _cov2d_rows, _cov2d_rows_grad, _gather_extents, _or_nonzero, _project_chunk, _scatter_chunk, add_mean_grads, add_normal_view_grads, add_rot_scale_grads, add_view_grads, any_live, camera_point, chunk_camera_point, chunk_scratch, gather_chunk, live_chunk, live_pairs, normal_grad, normals_chunk, project_bwd, project_fwd, quat_grad, quat_rotmat, rotated_axis, view_point, view_rows, zero_gaussian_grads,
)
from egobench.render.cpu.binning import (  # noqa: F401
    FILL_PART_MIN, RADIX_BITS, RECT_PART_MIN, _bin_walk, _fill_bins, _fill_bins_parts, _needed_boxes, _radix_order, _rects_part, _slots_from_counts, _tile_rects, bin_tiles, fill_bins, needed_bins, visible_rects,
)
from egobench.render.cpu.composite import (  # noqa: F401
    COLUMN_GROUP, DEPTH_CH, SIGMA_ROW, TAB_COLS, _EXP_COEFS, _bwd_bin, _exponent, _extent, _first_touch_slots, _footprint_tab, _fwd_bin, _start_tile_bwd, _start_tile_fwd, _state_index, _tile_base, _tile_centres, _write_isect_grad, accumulate_features, add_feature_grads, alpha_depth, alpha_depth_grad, band_constants, band_rows, band_values, bin_tile, ceil_int, column_group, composite_pixel, composited_any, compute_constants, exponent_grad, feature_dot, feature_dot_channels, feature_table, finish_tile_fwd, floor_int, gaussian_table, needed_rows, ordered_sum, pack_pixel_grads, raster_bwd, raster_fwd, reduce_isect_grad, retire_stopped, row_ahead, rows_needed, state_rows, tile_of_bin, tile_state_bwd, tile_state_fwd, track_rows, trim_rows_active, uncomposite_pixel,
)
