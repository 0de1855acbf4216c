"""The argument groups of the CPU kernels: named tuples (numba passes each field as an argument of its own, so
the arrays in them keep their noalias marks and the loops their vectorization), so that no kernel or helper
takes more than eight parameters. The backends build the kernels' groups (`egobench.render.cpu_backend`);
the kernels read their fields once, before their loops. The helpers' groups are built inside the kernels;
those built per pair, intersection or pixel hold scalars only (numba reference-counts the arrays a tuple
holds, and in those loops it did not always prune the counts: two atomic updates per pair in `project_bwd`).
Shapes: I poses (images), N Gaussians or surfels, M intersections, Iout output images of H x W pixels, P
pixels of a tile's state; "compute dtype" is the inputs' float32 or float64."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# ------------------------------------------------------------------------------------------
# projection
# ------------------------------------------------------------------------------------------


class Splats(NamedTuple):
    """The Gaussians (3DGS) or surfels (2DGS) the projection reads: means [N, 3], quats [N, 4] (w, x, y, z;
    normalised by the kernels), scales [N, 3] (linear; a surfel's third is unused). The forwards' dtype is
    the inputs' (float32 or float64), the backwards' float64."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray


class View(NamedTuple):
    """The poses and camera of a projection: viewmats [I, 4, 4] world-to-camera (the splats' dtype), cam [4]
    float64 (fx, fy, cx, cy; gsplat's pixels: centres at +0.5), width and height (int, pixels), eps2d (float:
    the 3DGS low-pass dilation of the 2D covariance; unread by 2DGS), near and far (float: the depths kept)."""

    viewmats: np.ndarray
    cam: np.ndarray
    width: int
    height: int
    eps2d: float
    near: float
    far: float


class Projected(NamedTuple):
    """The 3DGS projection's outputs (written by `project_fwd`), the splats' dtype: means2d [I, N, 2],
    conics [I, N, 3] (inverse 2D covariance a, b, c), depths [I, N], radii [I, N, 2] int32 (x, y; 0 where
    culled), normals [I, N, 3] (camera frame, facing the camera; [I, 0, 3] when no normals are rendered)."""

    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    radii: np.ndarray
    normals: np.ndarray


class ProjectedSurfels(NamedTuple):
    """The 2DGS projection's outputs (written by `project_fwd_2dgs`), the splats' dtype: means2d [I, N, 2],
    tsl [I, N, 9] (ray transform M, row-major), depths [I, N], radii [I, N, 2] int32 (gsplat's AABB; 0 where
    culled), normals [I, N, 3] (camera frame, facing the camera)."""

    means2d: np.ndarray
    tsl: np.ndarray
    depths: np.ndarray
    radii: np.ndarray
    normals: np.ndarray


class ProjectedGrads(NamedTuple):
    """Upstream gradients of `Projected`, channel first (`reduce_isect_grad`'s layout), each in its own float
    dtype (widened to float64 as read): means2d [2, I, N], conics [3, I, N], depths [I, N], normals [3, I, N]
    ([3, I, 0] when no normals are rendered)."""

    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    normals: np.ndarray


class ProjectedSurfelGrads(NamedTuple):
    """Upstream gradients of `ProjectedSurfels`, channel first, each in its own float dtype: means2d
    [2, I, N], tsl [9, I, N], depths [I, N], normals [3, I, N]."""

    means2d: np.ndarray
    tsl: np.ndarray
    depths: np.ndarray
    normals: np.ndarray


class SplatGrads(NamedTuple):
    """What a projection backward writes, float64: means [N, 3], quats [N, 4], scales [N, 3] (dL/d each
    Splats field) and view_parts [chunks, I, 12] (per chunk of `CHUNK` Gaussians, the partial dL/d
    viewmats[:3, :4], row-major; zeros on entry; the caller adds the chunks in order)."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    view_parts: np.ndarray


class Pair(NamedTuple):
    """One (pose, Gaussian) pair of a projection backward (ints): i the pose, n the Gaussian, ax the column of
    its rotation that is its normal. (Scalars only: a tuple holding arrays, built per pair, costs reference
    counts that numba does not prune there.)"""

    i: int
    n: int
    ax: int


class Ewa(NamedTuple):
    """A pair's EWA screen projection (floats): the Jacobian J = [[j00, 0, -j00 tx], [0, j11, -j11 ty]] (j00 =
    fx / z, j11 = fy / z, tx, ty the clamped x / z and y / z) and eps2d, the low-pass dilation added to the 2D
    covariance."""

    j00: float
    j11: float
    tx: float
    ty: float
    eps2d: float


# ------------------------------------------------------------------------------------------
# binning
# ------------------------------------------------------------------------------------------


class Footprints(NamedTuple):
    """The projected pairs the binning reads: means2d [I, N, 2] (gsplat's pixels), radii [I, N, 2] int32 (0:
    culled), depths [I, N] (float32 or float64)."""

    means2d: np.ndarray
    radii: np.ndarray
    depths: np.ndarray


class TileGrid(NamedTuple):
    """The image's tiles (ints): tile_size pixels a side, tiles_x per row, tiles_y per column."""

    tile_size: int
    tiles_x: int
    tiles_y: int


class Rects(NamedTuple):
    """The visible pairs (`visible_rects`), one row each: rect [nv, 4] int32 their tile ranges (x0, x1, y0,
    y1), vis [nv] int64 their flat ids (image * N + Gaussian, ascending), keys [nv] their depths (the
    depths' dtype)."""

    rect: np.ndarray
    vis: np.ndarray
    keys: np.ndarray


class SortedPairs(NamedTuple):
    """The visible pairs in depth order: rect [nv, 4] int32 and vis [nv] int64 (`Rects`), perm [nv] int64 their
    order (front to back)."""

    rect: np.ndarray
    vis: np.ndarray
    perm: np.ndarray


class BinLayout(NamedTuple):
    """The (image, tile) bins: N (Gaussians per image), tiles_x (tiles per row), bin_needed [I, tiles] bool
    (the bins some output pixel reads)."""

    N: int
    tiles_x: int
    bin_needed: np.ndarray


# ------------------------------------------------------------------------------------------
# compositing
# ------------------------------------------------------------------------------------------


class Tables(NamedTuple):
    """The 3DGS compositing's per (image, Gaussian) rows, row image * N + Gaussian, compute dtype: tab
    [I * N, TAB_COLS] (`gaussian_table`), feats [I * N, Cf] (`feature_table`: colour, depth (, normal))."""

    tab: np.ndarray
    feats: np.ndarray


class SurfelTables(NamedTuple):
    """The 2DGS compositing's per (image, surfel) inputs, compute dtype: tsl [I, N, 9] ray transforms, tab
    [I * N, TAB_COLS] (`surfel_table`), feats [I * N, Cf] (colour, depth, normal; the depth in DEPTH_CH)."""

    tsl: np.ndarray
    tab: np.ndarray
    feats: np.ndarray


class Tiles(NamedTuple):
    """What the compositing visits: flat_ids [M] int64 (image * N + Gaussian per intersection, sorted by
    (bin, depth)), bin_start [I * tiles + 1] int64 (each bin's first intersection), bins [NB] int64 (the bins
    to composite), pix_view [Iout, H, W] int64 (the image each output pixel is composited under), tile_size
    (int, pixels), tiles_x (int, tiles per row), cw (int, `column_group`)."""

    flat_ids: np.ndarray
    bin_start: np.ndarray
    bins: np.ndarray
    pix_view: np.ndarray
    tile_size: int
    tiles_x: int
    cw: int


class Constants(NamedTuple):
    """The compositing loops' constants in the compute dtype: kc (`compute_constants`), centres [max(W, H) +
    tile_size] (pixel index + 0.5)."""

    kc: np.ndarray
    centres: np.ndarray


class Composite(NamedTuple):
    """The compositing forward's per-pixel outputs, zeros on entry: feat [Iout, H, W, C] (sum w f; 2DGS adds
    the depth distortion as the last channel), T [Iout, H, W] (the transmittance left), last [Iout, H, W]
    int32 (one past the last intersection composited). Compute dtype but last."""

    feat: np.ndarray
    T: np.ndarray
    last: np.ndarray


class BackwardPixels(NamedTuple):
    """The compositing backward's per-pixel inputs: the forward's T [Iout, H, W] and last [Iout, H, W] int32
    (`Composite`), and the loss's gradients g_feat [Iout, H, W, C] (dL/d feat; 2DGS: Cf channels, 2 dL/d
    distortion, the forward's accumulated depth) and g_T [Iout, H, W] (dL/dT). Compute dtype but last."""

    T: np.ndarray
    last: np.ndarray
    g_feat: np.ndarray
    g_T: np.ndarray


class Tile(NamedTuple):
    """The tile of one bin (ints): i its image, o the output image, pixel bounds [x0, x1) x [y0, y1) (x1, y1
    clipped to the image), ts the tile size, cw the column group width (`column_group`)."""

    i: int
    o: int
    x0: int
    y0: int
    x1: int
    y1: int
    ts: int
    cw: int


class IsectGrad(NamedTuple):
    """A 3DGS intersection's sums over its pixels (compute dtype): dL/d mean x, y (mx, my), a, b, c (dL/d conic
    a, b, c are a / 2, b, c / 2) and dL/d log opacity (lo)."""

    mx: float
    my: float
    a: float
    b: float
    c: float
    lo: float


class SurfelIsectGrad(NamedTuple):
    """A 2DGS intersection's sums over its pixels (compute dtype): dL/d centre x, y (mx, my), dL/d log
    opacity (lo), and the depth distortion's dL/d depth (z)."""

    mx: float
    my: float
    lo: float
    z: float


class SurfelTableInputs(NamedTuple):
    """What `surfel_table` reads: means2d [I, N, 2], tsl [I, N, 9], log_opac [N] (compute dtype), and
    m2_rows [I * N, 2], tsl_rows [I * N, 9] (means2d and tsl as row views)."""

    means2d: np.ndarray
    tsl: np.ndarray
    log_opac: np.ndarray
    m2_rows: np.ndarray
    tsl_rows: np.ndarray
