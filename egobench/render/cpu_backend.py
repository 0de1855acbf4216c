"""Compiled CPU backend of `render` (``backend="cpu"``): numba kernels (the package egobench/render/cpu/)
behind two autograd functions, projection and rasterization, with gsplat 1.5.3 / torch_backend.py
semantics (checked against the torch backend in tests/render/test_render_cpu.py).

Supported: 3DGS colour, alpha, depth, normals (``want_normal``), means2d (densification carrier,
``absgrad``), radii, rolling shutter (``pixel_pose_index`` with K pose samples), gradients of
every Gaussian parameter and of the poses; 2DGS likewise plus the distortion map and gsplat's
``gradient_2dgs`` carrier (egobench/render/cpu_backend_2dgs.py). Not supported: dtypes other than
float32/float64: `unsupported_reason` says so and `render` then uses the torch backend for that
call, recording the reason in ``extras["cpu_fallback"]``.
"""

from __future__ import annotations

import functools
import math
import sys
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.host import RASTER_THREADS_ENV, kernel_threads, raster_threads, start_kernel_pool  # noqa: F401  (re-exported)
from egobench.render import kernel_build
from egobench.render.types import Gaussians, RenderOutput

try:  # the numba kernels; when they cannot load, `load_error` says why and `render` uses the torch backend
    from egobench.render import cpu as ck
except Exception as _exc:  # ImportError (numba missing), llvmlite load failure
    ck, _LOAD_ERROR = None, f"{type(_exc).__name__}: {_exc}".splitlines()[0]
else:
    _LOAD_ERROR = None
    from egobench.render.cpu import surfels as k2

#: gsplat 1.5.3 projection constants (as torch_backend)
EPS2D, NEAR_PLANE, FAR_PLANE = 0.3, 0.01, 1e10
#: gsplat's pixel centres sit at (i + 0.5, j + 0.5), egobench's at (i, j): gsplat's = egobench's + this
GSPLAT_PIXEL_OFFSET = 0.5
#: bytes per cache line (x86-64 and most Arm cores)
CACHE_LINE = 64
#: default tile size of this backend (measured: results/speed/README.md)
DEFAULT_TILE = 16


@functools.lru_cache(maxsize=1)
def load_error() -> str | None:
    """None when the numba kernels import (and so can compile); else a one-line reason."""
    return _LOAD_ERROR


@functools.lru_cache(maxsize=None)
def warn_fallback(reason: str) -> None:
    """Print a fallback reason once per process."""
    print(f"egobench render: compiled CPU backend unavailable ({reason}); using the torch backend", file=sys.stderr)


def unsupported_reason(mode: str, dtype: torch.dtype = torch.float32) -> str | None:
    """Why this backend cannot render a call (None: it can)."""
    if mode not in ("3dgs", "2dgs"):
        return f"the compiled CPU backend renders modes '3dgs' and '2dgs', not {mode!r}"
    if dtype not in (torch.float32, torch.float64):
        return f"the compiled CPU backend renders float32 and float64, not {dtype}"
    return None


def contiguous_numpy(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def set_threads() -> None:
    """numba's thread count: `host.kernel_threads` (`raster_threads`, at most numba's pool size); the pool is
    started first, in egobench's threading layer (`host.start_kernel_pool`)."""
    import numba

    start_kernel_pool()
    numba.set_num_threads(kernel_threads())


def pose_grad(gv_parts: np.ndarray, dt: torch.dtype) -> Tensor:
    """Per-chunk partial dL/d viewmat[:3, :4] [chunks, I, 12] -> dL/d viewmats [I, 4, 4], summed in
    chunk order (deterministic for any thread count)."""
    chunks, I = gv_parts.shape[:2]
    part = np.empty((I * 12, 1))
    ck.ordered_sum(gv_parts.reshape(1, chunks, I * 12), part)
    gv = torch.zeros(gv_parts.shape[1], 4, 4, dtype=dt)
    gv[:, :3, :] = torch.from_numpy(part.reshape(-1, 3, 4)).to(dt)
    return gv


@dataclass
class RasterSetup:
    """Binning and kernel inputs shared by the 3DGS and 2DGS rasterization functions."""

    flat_ids: np.ndarray  # [M] int64 image * N + Gaussian, sorted by (bin, depth)
    bin_start: np.ndarray  # [I * tiles + 1] int64
    bins: np.ndarray  # [NB] int64 bins to render
    needed: np.ndarray  # [I * N] bool: the rows some intersection reads (`ck.rows_needed`)
    feats: np.ndarray  # [I * N, Cf] colour, depth (, normal); only the needed rows are filled
    tiles_x: int
    cw: int  # `ck.column_group`
    kc: np.ndarray  # `ck.compute_constants`
    centres: np.ndarray  # pixel centres (index + 0.5), compute dtype

    def tiles(self, pix_view: np.ndarray, tile_size: int):
        """The compositing kernels' `ck.Tiles` for pix_view [Iout,H,W] and tile_size."""
        return ck.Tiles(self.flat_ids, self.bin_start, self.bins, pix_view, tile_size, self.tiles_x, self.cw)

    def constants(self):
        """The compositing kernels' `ck.Constants` (kc, centres)."""
        return ck.Constants(self.kc, self.centres)


def raster_setup(m2: np.ndarray, radii: Tensor, depths: Tensor, colors: Tensor, normals: Tensor,
                 pix_view: np.ndarray, bin_needed: np.ndarray, tile_size: int) -> RasterSetup:
    """m2 [I,N,2] (gsplat pixels), radii [I,N,2], depths [I,N], colors [N,3], normals [I,N,3] or
    [I,0,3]; pix_view [Iout,H,W]; bin_needed [I, tiles] -> intersections and kernel constants."""
    I, N = depths.shape
    _, H, W = pix_view.shape
    tiles_x, tiles_y = math.ceil(W / tile_size), math.ceil(H / tile_size)
    set_threads()  # the binning splits its work by numba's thread count
    flat_ids, bin_start = ck.bin_tiles(m2, contiguous_numpy(radii), contiguous_numpy(depths), tile_size, tiles_x, tiles_y, bin_needed)
    if flat_ids.shape[0] >= 2**31 - 1:  # per-pixel indices are int32
        raise ValueError(f"render(backend='cpu'): {flat_ids.shape[0]} tile intersections exceed 2^31 - 1; "
                         "use a larger tile_size or backend='torch'")
    bins = np.nonzero(bin_needed.reshape(-1))[0].astype(np.int64)
    needed = ck.rows_needed(flat_ids, I * N)
    feats = np.empty((I * N, 4 + (3 if normals.shape[1] else 0)), dtype=m2.dtype)
    ck.feature_table(contiguous_numpy(colors), contiguous_numpy(depths), contiguous_numpy(normals), needed, feats)
    centres = (np.arange(max(W, H) + tile_size) + 0.5).astype(m2.dtype)
    return RasterSetup(flat_ids, bin_start, bins, needed, feats, tiles_x, ck.column_group(tile_size),
                       ck.compute_constants(m2.dtype), centres)


def view_args(viewmats: np.ndarray, cam: np.ndarray, width: int, height: int):
    """A projection kernel's `ck.View`: viewmats [I, 4, 4] world-to-camera, cam (`camera_array`), the image size,
    and gsplat's EPS2D, NEAR_PLANE, FAR_PLANE."""
    return ck.View(viewmats, cam, width, height, EPS2D, NEAR_PLANE, FAR_PLANE)


def upstream_grad(g: Tensor | None, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """An upstream gradient [I, N, k] (or [I, N]) for a projection backward kernel, channel first [k, I, N]
    and in its own dtype (the kernel widens every value to float64 as it reads it); zeros where there is
    none. The rasterizer's gradients (`reduce_intersections`) are already channel first underneath, so
    this is a view, not a copy (their [I, N, k] views were 1.8 ms of copies a 128 px 2DGS step)."""
    if len(shape) == 2:
        return np.zeros(shape, dtype=dtype) if g is None else contiguous_numpy(g)
    if g is None:
        return np.zeros((shape[2], shape[0], shape[1]), dtype=dtype)
    return contiguous_numpy(g.permute(2, 0, 1))


def table_buffer(rows: int, dtype: np.dtype) -> np.ndarray:
    """An uninitialised [rows, TAB_COLS] table (`gaussian_table`, `surfel_table`) whose rows start on
    `CACHE_LINE` boundaries: one line per row in float32 (two in float64), so the compositing loops'
    prefetch of a row's start brings the whole row. numpy's buffers start 16 bytes into a line (glibc),
    which split every row over two lines."""
    nbytes = rows * ck.TAB_COLS * np.dtype(dtype).itemsize
    raw = np.empty(nbytes + CACHE_LINE, np.uint8)
    start = -raw.ctypes.data % CACHE_LINE
    return raw[start:start + nbytes].view(dtype).reshape(rows, ck.TAB_COLS)


def rows_hit_buffer(n_intersections: int, tile_size: int, cw: int) -> np.ndarray:
    """The forward's record of the rows each intersection was composited into, per column group of cw
    columns: [M, tile_size // cw, 2] int16 (row ranges; zeros: empty), read by the backward."""
    return np.zeros((n_intersections, tile_size // cw, 2), dtype=np.int16)


@dataclass
class Composited:
    """What the compositing forward (`composite_fwd`) keeps for its backward: the table of the needed rows, the
    summed features [Iout, H, W, C] (2DGS: the distortion last), the transmittance and last index [Iout, H, W],
    the rows each intersection was composited into, and 2DGS's ray transforms [I, N, 9] (3DGS: None)."""

    tab: np.ndarray
    out_feat: np.ndarray
    out_T: np.ndarray
    out_last: np.ndarray
    rows_hit: np.ndarray
    tsl: np.ndarray | None = None


def composite_fwd(st: RasterSetup, pix_view: np.ndarray, tile_size: int, m2: np.ndarray, log_opac: np.ndarray, *,
                  conics: np.ndarray | None = None, radii: np.ndarray | None = None,
                  tsl: np.ndarray | None = None) -> Composited:
    """The compositing forward of 3DGS (``conics`` [I, N, 3], ``radii`` [I, N, 2]) or 2DGS (``tsl``): the table of
    the rows some intersection reads, then front-to-back compositing. m2 [I, N, 2]: gsplat's pixels. The one
    home of this kernel sequence: the autograd Functions and the compiled training step both call it."""
    Iout, H, W = pix_view.shape
    Cf = st.feats.shape[1]
    out_feat = np.zeros((Iout, H, W, Cf + (1 if tsl is not None else 0)), dtype=m2.dtype)
    out_T = np.zeros((Iout, H, W), dtype=m2.dtype)
    out_last = np.zeros((Iout, H, W), dtype=np.int32)
    rows_hit = rows_hit_buffer(st.flat_ids.shape[0], tile_size, st.cw)
    set_threads()
    tab = table_buffer(m2.shape[0] * m2.shape[1], m2.dtype)
    tiles, composite = st.tiles(pix_view, tile_size), ck.Composite(out_feat, out_T, out_last)
    if tsl is not None:
        k2.surfel_table(m2, tsl, log_opac, st.needed, tab)
        k2.raster_fwd_2dgs(ck.SurfelTables(tsl, tab, st.feats), tiles, st.constants(), composite, rows_hit)
    else:
        ck.gaussian_table(m2, conics, radii, log_opac, st.needed, tab)
        ck.raster_fwd(ck.Tables(tab, st.feats), tiles, st.constants(), composite, rows_hit)
    return Composited(tab, out_feat, out_T, out_last, rows_hit, tsl)


def composite_bwd(c: Composited, st: RasterSetup, pix_view: np.ndarray, tile_size: int, g_state: np.ndarray,
                  g_T: np.ndarray) -> np.ndarray:
    """The compositing backward: per-pixel gradients g_state [Iout, H, W, n] (`pixel_grads`) and of the
    transmittance g_T [Iout, H, W] -> per-intersection gradient rows [M, 6 + Cf] (2DGS: [M, 12 + Cf])."""
    surfels = c.tsl is not None
    isect = np.zeros((st.flat_ids.shape[0], (12 if surfels else 6) + st.feats.shape[1]), st.kc.dtype)
    set_threads()
    tiles, pixels = st.tiles(pix_view, tile_size), ck.BackwardPixels(c.out_T, c.out_last, g_state, g_T)
    if surfels:
        k2.raster_bwd_2dgs(ck.SurfelTables(c.tsl, c.tab, st.feats), tiles, st.constants(), pixels, isect, c.rows_hit)
    else:
        ck.raster_bwd(ck.Tables(c.tab, st.feats), tiles, st.constants(), pixels, isect, c.rows_hit)
    return isect


def intersection_sums(isect: np.ndarray, flat_ids: np.ndarray, n_rows: int, dtype: np.dtype,
                      absg: np.ndarray | None = None) -> np.ndarray:
    """Per-intersection gradient rows [M, C] -> per (image x Gaussian) sums, channel first [C, n_rows] in
    ``dtype`` (intersection order; zeros where no intersection); ``absg`` [n_rows, 2] (float64), when given,
    gets the sums of |row[:2]| (gsplat's absgrad)."""
    import numba

    per = np.empty((isect.shape[1], n_rows), dtype)  # every entry written
    ck.reduce_isect_grad(isect, flat_ids, flat_ids.shape[0], per, np.zeros((0, 2)) if absg is None else absg,
                         numba.get_num_threads())
    return per


def reduce_intersections(isect: np.ndarray, flat_ids: np.ndarray, I: int, N: int, dt: torch.dtype,
                         absgrad_holder: list | None) -> Tensor:
    """`intersection_sums` as per (image, Gaussian) sums [I, N, C] (a view of the channel-first [C, I, N]
    block); sets absgrad_holder[0].absgrad [I, N, 2] (sum of |row[:2]|) when a holder is given."""
    absg = np.zeros((I * N, 2)) if absgrad_holder is not None else None
    per = torch.from_numpy(intersection_sums(isect, flat_ids, I * N, torch.empty(0, dtype=dt).numpy().dtype, absg))
    if absgrad_holder is not None:  # gsplat's absgrad attribute
        absgrad_holder[0].absgrad = torch.from_numpy(absg).reshape(I, N, 2).to(dt)
    return per.reshape(isect.shape[1], I, N).permute(1, 2, 0)


def pose_sums(per: Tensor, c0: int, c1: int) -> Tensor:
    """Channels [c0, c1) of `reduce_intersections`' [I, N, C] view summed over the poses -> [N, c1 - c0],
    contiguous (autograd keeps it as the parameter's gradient instead of copying a transposed view): one
    compiled pass over the channel-first block underneath, the poses added in order (`ck.ordered_sum`)."""
    block = contiguous_numpy(per.permute(2, 0, 1)[c0:c1])  # [c1 - c0, I, N], a view of the block
    out = np.empty((block.shape[2], c1 - c0), block.dtype)
    ck.ordered_sum(block, out)
    return torch.from_numpy(out)


def pixel_views(pixel_pose_index: Tensor | None, I: int, H: int, W: int, ts: int) -> tuple[np.ndarray, np.ndarray]:
    """-> (pix_view [Iout, H, W] int64: the image (pose) each output pixel is composited under,
    bin_needed [I, tiles] bool: the (image, tile) bins some output pixel reads); pixel_pose_index [H, W] holds
    0..I-1 (checked by `render`)."""
    tiles_x, tiles_y = math.ceil(W / ts), math.ceil(H / ts)
    if pixel_pose_index is None:
        pix_view = np.ascontiguousarray(np.broadcast_to(np.arange(I, dtype=np.int64)[:, None, None], (I, H, W)))
        return pix_view, np.ones((I, tiles_y * tiles_x), dtype=np.bool_)
    ppi = np.ascontiguousarray(pixel_pose_index.detach().cpu().long().numpy())
    bin_needed = np.zeros((I, tiles_y * tiles_x), dtype=np.bool_)
    ck.needed_bins(ppi, ts, tiles_x, bin_needed)
    return ppi[None], bin_needed


class _Project(torch.autograd.Function):
    """(means, quats, scales, viewmats) -> means2d [I,N,2] (gsplat pixels minus ``pixel_offset``: 0.5 gives
    egobench's), conics [I,N,3], depths [I,N], normals [I,N,3]; radii [I,N,2] int32 (not differentiable)."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, opac, cam, width, height, want_normal, pixel_offset=0.0):
        I, N = viewmats.shape[0], means.shape[0]
        dt = means.dtype
        m2 = np.empty((I, N, 2), dtype=contiguous_numpy(means).dtype)
        con = np.empty((I, N, 3), dtype=m2.dtype)
        dep = np.empty((I, N), dtype=m2.dtype)
        rad = np.empty((I, N, 2), dtype=np.int32)
        nrm = np.zeros((I, N, 3) if want_normal else (I, 0, 3), dtype=m2.dtype)
        splats = ck.Splats(contiguous_numpy(means), contiguous_numpy(quats), contiguous_numpy(scales))
        ck.project_fwd(splats, contiguous_numpy(opac), view_args(contiguous_numpy(viewmats), cam, width, height),
                       want_normal, ck.Projected(m2, con, dep, rad, nrm))
        ctx.save_for_backward(means, quats, scales, viewmats)
        ctx.args = (cam, width, height, want_normal)
        if pixel_offset:
            m2 -= pixel_offset  # in the compute dtype, as torch would subtract it
        radii = torch.from_numpy(rad)
        ctx.mark_non_differentiable(radii)
        outs = [torch.from_numpy(a).to(dt) for a in (m2, con, dep, nrm)]
        return (*outs, radii)

    @staticmethod
    def backward(ctx, g_m2, g_con, g_dep, g_nrm, _g_radii):
        means, quats, scales, viewmats = ctx.saved_tensors
        cam, width, height, want_normal = ctx.args
        I, N = viewmats.shape[0], means.shape[0]

        dt_np = contiguous_numpy(means).dtype
        g_m2, g_con = upstream_grad(g_m2, (I, N, 2), dt_np), upstream_grad(g_con, (I, N, 3), dt_np)
        g_dep = upstream_grad(g_dep, (I, N), dt_np)
        g_nrm = upstream_grad(g_nrm if want_normal else None, (I, N if want_normal else 0, 3), dt_np)
        gm, gq, gs = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))  # float64 (one compiled variant)
        n_chunks = max(1, math.ceil(N / ck.CHUNK))
        gv_parts = np.zeros((n_chunks, I, 12))
        set_threads()
        splats = ck.Splats(*(contiguous_numpy(t).astype(np.float64) for t in (means, quats, scales)))
        view = view_args(contiguous_numpy(viewmats).astype(np.float64), cam, width, height)
        ck.project_bwd(splats, view, want_normal, ck.ProjectedGrads(g_m2, g_con, g_dep, g_nrm),
                       ck.SplatGrads(gm, gq, gs, gv_parts))
        dt = means.dtype
        gv = pose_grad(gv_parts, dt) if ctx.needs_input_grad[3] else None
        return (torch.from_numpy(gm).to(dt), torch.from_numpy(gq).to(dt), torch.from_numpy(gs).to(dt), gv,
                None, None, None, None, None, None)


def gsplat_pixels(means2d: Tensor) -> np.ndarray:
    """Projected centres [I,N,2] in egobench's pixels -> a new array in gsplat's (+ `GSPLAT_PIXEL_OFFSET`),
    added in their dtype: the values torch's ``means2d + 0.5`` gives, without an autograd node."""
    m2 = contiguous_numpy(means2d)
    return m2 + m2.dtype.type(GSPLAT_PIXEL_OFFSET)


class _Rasterize(torch.autograd.Function):
    """(means2d (egobench pixels), conics, log_opacity, colors, depths, normals) -> sums of w rgb [Iout,H,W,3],
    w depth [Iout,H,W,1] and w normal [Iout,H,W,3 or 0] (`feature_outputs`), transmittance [Iout,H,W]."""

    @staticmethod
    def forward(ctx, means2d, conics, log_opac, colors, depths, normals, radii, pix_view, bin_needed, tile_size,
                absgrad_target):
        I, N = depths.shape
        m2 = gsplat_pixels(means2d)
        st = raster_setup(m2, radii, depths, colors, normals, pix_view, bin_needed, tile_size)
        c = composite_fwd(st, pix_view, tile_size, m2, contiguous_numpy(log_opac), conics=contiguous_numpy(conics),
                          radii=contiguous_numpy(radii))
        ctx.state = (c, st, pix_view, tile_size, absgrad_target)
        ctx.has_normals = bool(normals.shape[1])
        ctx.shapes = (I, N, colors.dtype)
        ctx.set_materialize_grads(False)  # unused outputs: zeros written here, not allocated by autograd
        return (*feature_outputs(c.out_feat), torch.from_numpy(c.out_T))

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_normal, g_T):
        c, st, pix_view, ts, ab = ctx.state
        I, N, dt = ctx.shapes
        gF = pixel_grads(st.feats.shape[1], c.out_T, g_rgb, g_depth, g_normal)
        gT = np.zeros(c.out_T.shape, c.out_T.dtype) if g_T is None else contiguous_numpy(g_T)
        isect = composite_bwd(c, st, pix_view, ts, gF, gT)
        per = reduce_intersections(isect, st.flat_ids, I, N, dt, ab)
        g_normals = per[..., 10:13] if ctx.has_normals else None
        return (per[..., 0:2], per[..., 2:5], per[..., 5].sum(0), pose_sums(per, 6, 9), per[..., 9],
                g_normals, None, None, None, None, None)


def prepare_kernels(dtype: torch.dtype, mode: str) -> None:
    """Before a render's first kernel: numba's pool started (loading a parallel kernel starts it) and the kernel
    set of ``dtype`` and ``mode`` ("3dgs" or "2dgs") built in a child and loaded here, so every process runs the
    same machine code (`kernel_build`)."""
    start_kernel_pool()
    kernel_build.ensure_built(dtype, mode)


def render_cpu(gaussians: Gaussians, camera: Pinhole, viewmats: Tensor, *, pixel_pose_index: Tensor | None,
               background: Tensor | None, want_normal: bool, tile_size: int, absgrad: bool) -> RenderOutput:
    """3DGS render with the compiled kernels; same contract as the torch path of `render` (2DGS:
    `cpu_backend_2dgs.render_cpu_2dgs`). viewmats [I, 4, 4] world-to-camera; pixel_pose_index [H, W] or None."""
    prepare_kernels(gaussians.means.dtype, "3dgs")
    means = gaussians.means
    H, W = camera.height, camera.width
    I = viewmats.shape[0]
    log_opac = F.logsigmoid(gaussians.opacity_logits)
    # means2d_out in egobench's pixel convention (gsplat's - 0.5), retained for densification statistics
    means2d_out, conics, depths, normals, radii = _Project.apply(
        means, gaussians.quats, gaussians.scales, viewmats, log_opac.detach().exp(), camera_array(camera), W, H,
        bool(want_normal), GSPLAT_PIXEL_OFFSET)
    if means2d_out.requires_grad:
        means2d_out.retain_grad()
    ts = int(tile_size)
    pix_view, bin_needed = pixel_views(pixel_pose_index, I, H, W, ts)
    holder = [means2d_out] if absgrad and means2d_out.requires_grad else None
    rgb_sum, depth_sum, normal, trans = _Rasterize.apply(means2d_out, conics, log_opac, gaussians.colors, depths,
                                                         normals, radii, pix_view, bin_needed, ts, holder)
    rgb, alpha, depth = composite_output(rgb_sum, depth_sum, trans, background)
    normal = normal if want_normal else None
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, normal=normal, means2d=means2d_out,
                        radii=radius_max(radii), extras={"backend": "cpu", "tile_size": ts})


def radius_max(radii: Tensor) -> Tensor:
    """radii [I, N, 2] int32 (x, y) -> [I, N], the larger (numpy: a third of ``amax(-1)``'s time)."""
    r = radii.numpy()
    return torch.from_numpy(np.maximum(r[..., 0], r[..., 1]))


def camera_array(camera: Pinhole) -> np.ndarray:
    """(fx, fy, cx, cy) in gsplat's pixel convention (centres at +0.5), float64."""
    return np.array([camera.fx, camera.fy, camera.cx + GSPLAT_PIXEL_OFFSET, camera.cy + GSPLAT_PIXEL_OFFSET],
                    dtype=np.float64)


def feature_outputs(out_feat: np.ndarray) -> tuple[Tensor, Tensor, Tensor]:
    """The rasterizer's feature buffer [Iout,H,W,Cf] (sum w (rgb, depth, normal)) -> its rgb [..., 3], depth
    [..., 1] and normal [..., Cf - 4] channels: separate outputs, so that autograd hands back one gradient per
    channel group instead of adding zero-padded full-width ones. Depth and normal are views; rgb is copied
    out once, contiguous, for its readers (the exposure, the divergence check) that would each copy it.
    The layout is `ck.feature_table`'s: colour before the depth channel, the normal after it."""
    feat = torch.from_numpy(out_feat)
    rgb = torch.from_numpy(np.ascontiguousarray(out_feat[..., :ck.DEPTH_CH]))
    return rgb, feat[..., ck.DEPTH_CH:ck.DEPTH_CH + 1], feat[..., ck.DEPTH_CH + 1:]


def pixel_grads(n_channels: int, out_T: np.ndarray, g_rgb: Tensor | None, g_depth: Tensor | None,
                g_normal: Tensor | None, g_dist: Tensor | None = None,
                out_feat: np.ndarray | None = None) -> np.ndarray:
    """The gradients of `feature_outputs`' outputs (None: zeros) -> the raster backward's per-pixel input
    [Iout,H,W,n_channels] (`ck.pack_pixel_grads`; 2DGS adds 2 dL/d distortion and ``out_feat``'s
    depth)."""
    P, dt = out_T.size, out_T.dtype

    def rows(g: Tensor | None, *row: int) -> np.ndarray:  # [P, *row]; no rows for None
        return np.empty((0, *row), dt) if g is None else contiguous_numpy(g).reshape(P, *row)

    out = np.empty(out_T.shape + (n_channels,), dt)
    fwd = np.empty((0, 0), dt) if out_feat is None else out_feat.reshape(P, -1)
    ck.pack_pixel_grads(out.reshape(P, n_channels), rows(g_rgb, 3), rows(g_depth, 1),
                        rows(g_normal if n_channels >= 7 else None, 3), rows(g_dist), fwd)
    return out


#: the smallest alpha that normalises a depth (the torch path's ``alpha.clamp(min=1e-10)``)
ALPHA_MIN = 1e-10


class _AlphaDepth(torch.autograd.Function):
    """(sum w depth [..., 1], transmittance [...]) -> alpha = 1 - T and depth = sum w depth / clamp(alpha,
    ALPHA_MIN), both [..., 1]: the torch path's rsub, clamp and div and their backwards, one compiled pass
    each (`ck.alpha_depth`, the same bits)."""

    @staticmethod
    def forward(ctx, depth_sum, trans):
        d, t = contiguous_numpy(depth_sum).reshape(-1), contiguous_numpy(trans).reshape(-1)
        alpha, depth = np.empty_like(t), np.empty_like(t)
        ck.alpha_depth(d, t, t.dtype.type(1.0), t.dtype.type(ALPHA_MIN), alpha, depth)
        alpha_t = torch.from_numpy(alpha).view(depth_sum.shape)
        ctx.save_for_backward(alpha_t)  # autograd's version check: an alpha changed in place is an error
        ctx.sums, ctx.shapes = d, (depth_sum.shape, trans.shape)
        ctx.set_materialize_grads(False)
        return alpha_t, torch.from_numpy(depth).view(depth_sum.shape)

    @staticmethod
    def backward(ctx, g_alpha, g_depth):
        (alpha_t,), d, (sum_shape, trans_shape) = ctx.saved_tensors, ctx.sums, ctx.shapes
        if g_depth is None:  # only the alpha's own gradient: rsub's negation
            return None, None if g_alpha is None else (-g_alpha).reshape(trans_shape)
        alpha = alpha_t.numpy().reshape(-1)
        ga = np.empty((0,), alpha.dtype) if g_alpha is None else contiguous_numpy(g_alpha).reshape(-1)
        g_sum, g_trans = np.empty_like(alpha), np.empty_like(alpha)
        ck.alpha_depth_grad(d, alpha, ga, contiguous_numpy(g_depth).reshape(-1), alpha.dtype.type(ALPHA_MIN),
                            g_sum, g_trans)
        return torch.from_numpy(g_sum).view(sum_shape), torch.from_numpy(g_trans).view(trans_shape)


def composite_output(rgb_sum: Tensor, depth_sum: Tensor, trans: Tensor,
                     background: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """sums of w rgb [Iout,H,W,3] and w depth [Iout,H,W,1], transmittance [Iout,H,W] -> (rgb with the
    background, alpha [..., 1], depth normalised by alpha [..., 1]), as the torch path of `render`."""
    alpha, depth = _AlphaDepth.apply(depth_sum, trans)
    rgb = rgb_sum
    if background is not None and bool(background.any()):  # a black background adds nothing (the default)
        rgb = rgb + trans[..., None] * background
    return rgb, alpha, depth
