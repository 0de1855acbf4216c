"""Pure-torch tile rasterizer with gsplat 1.5.3 semantics (CPU and CUDA, any float dtype).

Pipeline (all vectorised; the only Python loops run over chunks of depth-sorted candidates
and over groups of tiles, never over Gaussians, tiles or pixels):

1. `project_3dgs` / `project_2dgs`: gsplat's fully fused projection (EWA with the Jacobian
   clamp at 1.3 tan(fov), eps2d dilation, near/far culling, opacity-aware radius rule of the
   CUDA kernel) for I view matrices at once, through autograd.
2. `intersect_tiles`: gsplat's tile ranges floor/ceil((mean -/+ radius) / tile), one
   intersection per (image, tile, Gaussian), sorted by (bin, depth). Only bins that some output
   pixel needs are kept: this is how the rolling-shutter path renders each pixel under its own
   pose only.
3. Per intersection, the Gaussian's exponent sigma(pixel) - log(opacity) is written as a
   polynomial in tile-local pixel coordinates (6 coefficients for 3DGS; for 2DGS the ray-splat
   cross product is linear in the pixel, 9 coefficients, plus the 2D low-pass filter). A tile
   chunk then costs one batched matmul to evaluate every (pixel, candidate) exponent.
4. `_Composite` (`torch_composite.py`): front-to-back compositing with gsplat's rules (alpha = min(0.999, o exp(-s)),
   skip alpha < 1/255, stop before the Gaussian that would bring T to <= 1e-4), with a hand-written
   backward that replays the forward's per-chunk intermediates when they fit in `_Plan.store_elems`
   and otherwise recomputes each chunk (no per-pair storage), as gsplat's CUDA kernels do.

CPU speed notes (fixed per-call cost matters for small images): gathers use index_select (several
times faster than advanced indexing, forward and backward), exponents are capped before exp()
(denormal results are ~30x slower), tile binning sorts with a numpy radix sort, and the
projection keeps 3-vector axes leading so reductions add whole [I, N] slabs.

Coordinates: internally gsplat's pixel convention (centre of pixel (i, j) at (i+0.5, j+0.5));
callers pass egobench intrinsics and the conversion cx+0.5 happens here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.render.torch_composite import ALPHA_MIN, _Plan, _tile_phi, composite

#: gsplat 1.5.3 constants (docs/paper-notes.md §7)
EPS2D = 0.3  # 2D covariance dilation, pixels^2
NEAR_PLANE = 0.01  # metres
#: the near plane of the INRIA 3DGS code and the viewers built on it, metres: they hide what lies nearer
VIEWER_NEAR_PLANE = 0.2
FAR_PLANE = 1e10  # metres
EXTENT_SIGMAS = 3.33  # screen radius in standard deviations (upper bound)
FILTER_INV_SQUARE_2DGS = 2.0  # 2DGS low-pass filter: sigma_2d = 2 |d|^2 / 2


def _quat_to_rot_matrix() -> tuple[Tensor, Tensor]:
    """[16, 9] map from q_i q_j (i * 4 + j, (w, x, y, z) = 0..3) to R - I (row-major), and vec(I)."""
    w, x, y, z = range(4)
    terms = [  # (R entry, [(+-1, i, j)]) of R - I = 2 * (...)
        [(-1, y, y), (-1, z, z)], [(1, x, y), (-1, w, z)], [(1, x, z), (1, w, y)],
        [(1, x, y), (1, w, z)], [(-1, x, x), (-1, z, z)], [(1, y, z), (-1, w, x)],
        [(1, x, z), (-1, w, y)], [(1, y, z), (1, w, x)], [(-1, x, x), (-1, y, y)],
    ]
    C = torch.zeros(16, 9, dtype=torch.float64)
    for e, ts in enumerate(terms):
        for sgn, i, j in ts:
            C[i * 4 + j, e] += 2.0 * sgn
    return C, torch.eye(3, dtype=torch.float64).reshape(9)


_QUAT_TO_ROT, _EYE9 = _quat_to_rot_matrix()


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """quats [..., 4] (w, x, y, z), any norm > 0 -> rotation matrices [..., 3, 3]."""
    q = F.normalize(quats, p=2, dim=-1)
    qq = (q[..., :, None] * q[..., None, :]).reshape(q.shape[:-1] + (16,))  # q_i q_j, i * 4 + j
    # R = I + (2 q_i q_j) combined by a constant [16, 9] matrix: one product + one GEMM (few autograd nodes)
    R = torch.matmul(qq, _QUAT_TO_ROT.to(dtype=q.dtype, device=q.device)) + _EYE9.to(dtype=q.dtype, device=q.device)
    return R.reshape(q.shape[:-1] + (3, 3))


def gsplat_K(camera: Pinhole, dtype: torch.dtype, device: torch.device | str) -> Tensor:
    """Intrinsics [3, 3] in gsplat's pixel convention (cx + 0.5, cy + 0.5)."""
    return torch.tensor(
        [[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]],
        dtype=dtype, device=device,
    )


@dataclass
class Projection:
    """Per-view screen-space Gaussians (I views of N Gaussians), gsplat pixel convention."""

    means2d: Tensor  # [I, N, 2] projected centres, pixels (centres of pixels at +0.5)
    depths: Tensor  # [I, N] camera z of the centres, metres
    radii: Tensor  # [I, N, 2] int32 screen radii per axis, pixels; 0 where culled
    conics: Tensor | None = None  # [I, N, 3] (a, b, c) of the inverse 2D covariance (3DGS)
    ray_transforms: Tensor | None = None  # [I, N, 3, 3] rows u_M, v_M, w_M of K [R s0 | R s1 | mean] (2DGS)
    normals: Tensor | None = None  # [I, N, 3] unit normals in camera frame, facing the camera


def _viewmat_parts(viewmats: Tensor) -> tuple[Tensor, Tensor]:
    return viewmats[:, :3, :3], viewmats[:, :3, 3]  # [I, 3, 3], [I, 3]


def face_camera(normals_c: Tensor, means_c: Tensor) -> Tensor:
    """Flip normals [I, N, 3] so that dot(-n, mean_c) > 0 (gsplat's rule)."""
    cos = -(normals_c * means_c).sum(-1, keepdim=True)
    return torch.where(cos > 0, normals_c, -normals_c)


def project_3dgs(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3] standard deviations, metres
    viewmats: Tensor,  # [I, 4, 4] T_camera_world
    K: Tensor,  # [3, 3] gsplat convention
    width: int,
    height: int,
    *,
    opacities: Tensor | None = None,  # [N]; given -> gsplat CUDA's opacity-aware radius
    eps2d: float = EPS2D,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    want_normal: bool = False,
) -> Projection:
    """gsplat 1.5.3 `fully_fused_projection` (pinhole, EWA) for I views, differentiable."""
    # Layout: the 3-vector axes lead ([3, I, N], [3, 3, I, N]) so that per-(view, Gaussian) scalars
    # broadcast over leading axes and reductions add whole [I, N] slabs (fast on CPU, also backward).
    R_cw, t_cw = _viewmat_parts(viewmats)
    means_cT = torch.einsum("iab,nb->ain", R_cw, means) + t_cw.T[:, :, None]  # [3, I, N] camera frame
    R = quat_to_rotmat(quats)  # [N, 3, 3]
    M = R * scales[:, None, :]  # [N, 3, 3]: cov = M M^T
    # camera-frame factor R_cw M for every view as one GEMM ([I*3, 3] x [3, N*3])
    McT = torch.einsum("iab,nbc->acin", R_cw, M)  # [3, 3, I, N]: Mc[i, n] = R_cw[i] M[n], cov_c = Mc Mc^T

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y, z = means_cT.unbind(0)  # [I, N] each
    in_depth = (z >= near_plane) & (z <= far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # safe z: no inf/NaN in culled entries' graphs
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    inv_z = 1.0 / zs
    tx = torch.clamp(x * inv_z, min=-lim_x_neg, max=lim_x_pos)  # clamped x/z (gsplat's tx / z)
    ty = torch.clamp(y * inv_z, min=-lim_y_neg, max=lim_y_pos)
    # J = [[j00, 0, j02], [0, j11, j12]] = [[fx/z, 0, -fx tx/z^2], ...]; cov2d = (J Mc)(J Mc)^T
    j00, j11 = fx * inv_z, fy * inv_z
    Mc0, Mc1, Mc2 = McT.unbind(0)  # rows of Mc, [3, I, N] (unbind: one gradient buffer, not three zero-filled)
    a0 = j00 * (Mc0 - tx * Mc2)  # [3, I, N] row 0 of J Mc
    a1 = j11 * (Mc1 - ty * Mc2)  # [3, I, N] row 1 of J Mc
    c00 = (a0 * a0).sum(0) + eps2d
    c11 = (a1 * a1).sum(0) + eps2d
    c01 = (a0 * a1).sum(0)
    det = c00 * c11 - c01 * c01
    valid = in_depth & (det > 0)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_s, -c01 / det_s, c00 / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        extend = torch.full_like(z, EXTENT_SIGMAS)
        if opacities is not None:
            op = opacities.detach().to(z.dtype)[None, :].expand_as(z)
            valid = valid & (op >= ALPHA_MIN)
            extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_MIN) / ALPHA_MIN)))
        rx = torch.ceil(extend * torch.sqrt(c00.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c11.detach().clamp_min(0)))
        valid = valid & ((rx > 0) | (ry > 0))
        m2 = means2d.detach()
        inside = (m2[..., 0] + rx > 0) & (m2[..., 0] - rx < width) & (m2[..., 1] + ry > 0) & (m2[..., 1] - ry < height)
        keep = valid & inside
        radii = torch.stack([rx, ry], dim=-1) * keep[..., None]
        radii = radii.to(torch.int32)

    normals = None
    if want_normal:
        # shortest axis of each Gaussian, in camera frame, facing the camera
        axis = torch.argmin(scales.detach(), dim=-1)  # [N]
        n_world = torch.gather(R, 2, axis[:, None, None].expand(-1, 3, 1))[..., 0]  # [N, 3]
        normals = face_camera(torch.einsum("iab,nb->ina", R_cw, n_world), means_cT.permute(1, 2, 0))
    return Projection(means2d=means2d, depths=z, radii=radii, conics=conics, normals=normals)


def project_2dgs(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3]; the first two are the surfel's standard deviations
    viewmats: Tensor,  # [I, 4, 4] T_camera_world
    K: Tensor,  # [3, 3] gsplat convention
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
) -> Projection:
    """gsplat 1.5.3 `fully_fused_projection_2dgs` (ray transforms and AABB), differentiable."""
    R_cw, t_cw = _viewmat_parts(viewmats)
    means_c = torch.einsum("iab,nb->ina", R_cw, means) + t_cw[:, None, :]  # [I, N, 3]
    R = quat_to_rotmat(quats)  # [N, 3, 3]
    R_c = torch.einsum("iab,nbc->inac", R_cw, R)  # [I, N, 3, 3]
    T_cl = torch.stack([R_c[..., 0] * scales[:, 0, None], R_c[..., 1] * scales[:, 1, None], means_c], dim=-1)
    T_sl = torch.einsum("ab,inbc->inac", K, T_cl)  # [I, N, 3, 3]: rows u_M, v_M, w_M
    z = means_c[..., 2]
    Mw = T_sl[..., 2, :]
    d = Mw[..., 0] ** 2 + Mw[..., 1] ** 2 - Mw[..., 2] ** 2
    valid = (d != 0) & (z > near_plane) & (z < far_plane)
    d_s = torch.where(valid, d, torch.ones_like(d))
    f = torch.stack([1.0 / d_s, 1.0 / d_s, -1.0 / d_s], dim=-1)  # [I, N, 3]
    Muv = T_sl[..., :2, :]  # [I, N, 2, 3]
    means2d = (Muv * Mw[..., None, :] * f[..., None, :]).sum(-1)  # [I, N, 2]
    with torch.no_grad():
        half_ext = means2d.detach() ** 2 - (Muv.detach() ** 2 * f.detach()[..., None, :]).sum(-1)
        radius = torch.ceil(EXTENT_SIGMAS * torch.sqrt(half_ext.clamp_min(1e-4)))
        rx, ry = radius.unbind(-1)
        m2 = means2d.detach()
        inside = (m2[..., 0] + rx > 0) & (m2[..., 0] - rx < width) & (m2[..., 1] + ry > 0) & (m2[..., 1] - ry < height)
        radii = (radius * (valid & inside)[..., None]).to(torch.int32)
    normals = face_camera(R_c[..., 2], means_c)
    return Projection(means2d=means2d, depths=z, radii=radii, ray_transforms=T_sl, normals=normals)


@dataclass
class TileBins:
    """Depth-sorted intersections grouped by (image, tile) bin."""

    tile_size: int
    tiles_x: int
    tiles_y: int
    flat_ids: Tensor  # [M] int64 index into I*N (image * N + gaussian), sorted by (bin, depth)
    isect_bins: Tensor  # [M] int64 global bin (image * tiles + tile) of each intersection
    bin_ids: Tensor  # [NB] int64 global ids of the bins to render, ascending
    bin_pos: Tensor  # [I * tiles] int64 position of each global bin in bin_ids, -1 if not rendered
    starts: Tensor  # [NB] int64 first intersection of each rendered bin
    lengths: Tensor  # [NB] int64 number of intersections of each rendered bin


def _radix_argsort_cpu(keys: np.ndarray, bits: int) -> np.ndarray:
    """Stable argsort of unsigned integer keys by LSD passes of numpy's 16-bit radix sort."""
    perm = None
    for shift in range(0, bits, 16):
        digit = ((keys >> shift) & 0xFFFF).astype(np.uint16)
        p = np.argsort(digit if perm is None else digit[perm], kind="stable")
        perm = p if perm is None else perm[p]
    return perm if perm is not None else np.zeros(0, dtype=np.int64)


def _stable_argsort(values: Tensor) -> Tensor:
    """Stable argsort of a 1-D tensor of positive finite floats (depths) or non-negative ints < 2^16.

    On CPU a radix sort (positive IEEE floats order like their bit patterns): about 10x faster than
    torch.sort there; elsewhere torch.sort(stable=True)."""
    if values.device.type != "cpu" or values.numel() == 0:
        return torch.sort(values, stable=True).indices
    if values.dtype.is_floating_point:
        itype, bits = {torch.float32: (torch.int32, 32), torch.float64: (torch.int64, 64)}.get(values.dtype, (None, 0))
        if itype is None:
            return torch.sort(values, stable=True).indices
        keys = values.contiguous().view(itype).numpy().view(np.uint32 if bits == 32 else np.uint64)
    else:
        keys, bits = values.numpy().astype(np.uint16), 16
    return torch.from_numpy(_radix_argsort_cpu(keys, bits).astype(np.int64, copy=False))


@torch.no_grad()
def intersect_tiles(
    means2d: Tensor,  # [I, N, 2] gsplat pixel convention
    radii: Tensor,  # [I, N, 2] int
    depths: Tensor,  # [I, N]
    tile_size: int,
    width: int,
    height: int,
    bin_needed: Tensor | None = None,  # [I, tiles] bool: bins some output pixel uses (None = all)
) -> TileBins:
    """gsplat's `isect_tiles` + `isect_offset_encode`, restricted to the needed bins."""
    device = means2d.device
    I, N = depths.shape
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    m = means2d.detach()
    r = radii.to(m.dtype)
    valid = (radii > 0).all(-1)  # [I, N]

    def tile_range(centre: Tensor, radius: Tensor, n_ax: int) -> tuple[Tensor, Tensor]:
        tm, tr = centre / tile_size, radius / tile_size  # [I, N]
        return torch.floor(tm - tr).clamp_(0, n_ax).long(), torch.ceil(tm + tr).clamp_(0, n_ax).long()

    x_lo, x_hi = tile_range(m[..., 0], r[..., 0], tiles_x)  # [I, N] first / one-past-last tile column
    y_lo, y_hi = tile_range(m[..., 1], r[..., 1], tiles_y)
    if bin_needed is not None:
        # clip each image's tile ranges to the bounding box of its needed bins (rolling shutter:
        # a pose sample owns a band of rows), so that intersections are not generated K-fold
        need = bin_needed.reshape(I, tiles_y, tiles_x)
        clipped = []
        for lo_, hi_, reduce_dim, n_ax in ((x_lo, x_hi, 1, tiles_x), (y_lo, y_hi, 2, tiles_y)):
            used = need.any(dim=reduce_dim)  # [I, n_ax] (x: any over tile rows; y: any over tile columns)
            ar = torch.arange(n_ax, device=device)
            first = torch.where(used, ar, n_ax).amin(-1)
            last = torch.where(used, ar + 1, 0).amax(-1)
            clipped += [torch.maximum(lo_, first[:, None]), torch.minimum(hi_, last[:, None])]
        x_lo, x_hi, y_lo, y_hi = clipped
    ext_x = (x_hi - x_lo).clamp_min(0)
    counts = (ext_x * (y_hi - y_lo).clamp_min(0) * valid).reshape(-1)  # [I * N]
    # generate each image's intersections front to back (stable depth order: ties broken by Gaussian
    # index, like gsplat's radix sort); a stable sort by bin alone then gives the (bin, depth) order.
    # Only (image, Gaussian) pairs with intersections are sorted (images are mixed: bins separate them).
    vis = torch.nonzero(counts).reshape(-1)  # [V] ascending global ids
    order = vis[_stable_argsort(depths.detach().reshape(-1)[vis])]  # [V] front to back within each image
    counts_o = counts[order]
    total = int(counts_o.sum())
    # per visible pair: first bin of its rectangle, rectangle width, offset of its first intersection
    base_o = (order // N) * n_tiles + y_lo.reshape(-1)[order] * tiles_x + x_lo.reshape(-1)[order]
    w_o = ext_x.reshape(-1)[order]
    first_o = torch.cumsum(counts_o, 0) - counts_o
    rep = torch.repeat_interleave(counts_o, output_size=total)  # [M0] index into the visible pairs
    owner = order.index_select(0, rep)  # [M0] global (image, Gaussian) id
    w_r = w_o.index_select(0, rep)
    local = torch.arange(total, device=device) - first_o.index_select(0, rep)
    row = torch.div(local, w_r, rounding_mode="floor")
    n_bins_all = I * n_tiles
    bins = base_o.index_select(0, rep) + row * tiles_x + (local - row * w_r)  # [M0]
    if bin_needed is not None:
        keep = torch.nonzero(bin_needed.reshape(-1).index_select(0, bins)).reshape(-1)
        owner, bins = owner.index_select(0, keep), bins.index_select(0, keep)
    if bins.device.type == "cpu" and n_bins_all <= 1 << 16:
        perm = _stable_argsort(bins)  # 16-bit radix sort
    else:
        perm = torch.sort(bins, stable=True).indices
    flat_ids = owner.index_select(0, perm)
    isect_bins = bins.index_select(0, perm)
    if bin_needed is None:
        bin_ids = torch.arange(n_bins_all, device=device)
    else:
        bin_ids = torch.nonzero(bin_needed.reshape(-1)).reshape(-1)
    bin_pos = torch.full((n_bins_all,), -1, dtype=torch.long, device=device)
    bin_pos[bin_ids] = torch.arange(bin_ids.numel(), device=device)
    per_bin = torch.bincount(isect_bins, minlength=n_bins_all)  # [I * tiles]
    lengths = per_bin[bin_ids]
    starts = (torch.cumsum(per_bin, 0) - per_bin)[bin_ids]
    return TileBins(tile_size, tiles_x, tiles_y, flat_ids, isect_bins, bin_ids, bin_pos, starts, lengths)


# ------------------------------------------------------------------------------------------
# compositing kernel
# ------------------------------------------------------------------------------------------


def _tile_origins(bins: TileBins, isect_bins: Tensor, dtype) -> Tensor:
    """[M, 2] gsplat-pixel coordinates of the centre of each intersection's tile."""
    n_tiles = bins.tiles_x * bins.tiles_y
    t = isect_bins % n_tiles
    ox = (t % bins.tiles_x).to(dtype) * bins.tile_size + 0.5 * bins.tile_size
    oy = (t // bins.tiles_x).to(dtype) * bins.tile_size + 0.5 * bins.tile_size
    return torch.stack([ox, oy], -1)


def coefficients_3dgs(m_local: Tensor, conics: Tensor, log_opacity: Tensor) -> Tensor:
    """Exponent sigma - log(o) as coefficients of (1, x, y, x^2, xy, y^2) in tile-local pixels.

    m_local [M, 2] centre minus tile centre, conics [M, 3] (a, b, c), log_opacity [M] -> [M, 7]
    (the 7th column, log(o), is not evaluated: it tells where alpha can reach the 0.999 clamp).
    """
    mx, my = m_local.unbind(-1)
    a, b, c = conics.unbind(-1)
    c1 = -(a * mx + b * my)  # -(Q m)_x
    c2 = -(c * my + b * mx)  # -(Q m)_y
    c0 = -0.5 * (mx * c1 + my * c2) - log_opacity  # m^T Q m / 2 - log(o), from the same products
    return torch.stack([c0, c1, c2, 0.5 * a, b, 0.5 * c, log_opacity], dim=-1)


def coefficients_2dgs(m_local: Tensor, T_sl: Tensor, origin: Tensor, log_opacity: Tensor) -> Tensor:
    """Ray-splat intersection as linear functions of tile-local pixels (gsplat's h_u x h_v).

    m_local [M, 2], T_sl [M, 3, 3] (rows u_M, v_M, w_M), origin [M, 2] tile centres, log_opacity [M]
    -> [M, 14]: cross-product coefficients [3 comp x (1, x, y)], 2D-filter coefficients of
    (1, x, y, x^2 + y^2), log(opacity).
    """
    U, V, W = T_sl[:, 0], T_sl[:, 1], T_sl[:, 2]
    Up = origin[:, 0, None] * W - U  # h_u = x_local * W + Up
    Vp = origin[:, 1, None] * W - V
    C0 = torch.linalg.cross(Up, Vp)
    C1 = torch.linalg.cross(W, Vp)
    C2 = torch.linalg.cross(Up, W)
    cross = torch.stack([C0, C1, C2], dim=-1)  # [M, 3 comp, 3 phi]
    mx, my = m_local.unbind(-1)
    k = FILTER_INV_SQUARE_2DGS
    g2 = torch.stack([k * (mx * mx + my * my), -2 * k * mx, -2 * k * my, torch.full_like(mx, k)], -1)
    return torch.cat([cross.reshape(-1, 9), g2, log_opacity[:, None]], dim=-1)


# ------------------------------------------------------------------------------------------
# entry point of the backend
# ------------------------------------------------------------------------------------------


@dataclass
class RasterResult:
    """Raw backend output before `render` wraps it into a RenderOutput."""

    features: Tensor  # [Iout, H, W, Cf] sum of w * (rgb, depth, normal...)
    transmittance: Tensor  # [Iout, H, W] composited transmittance
    distortion: Tensor  # [Iout, H, W] 2DGS depth distortion (zeros for 3DGS)
    projection: Projection
    means2d: Tensor  # [I, N, 2] egobench pixel convention (grad-retaining)
    densify_2dgs: Tensor | None = None  # [I, N, 2] 2DGS: zeros whose gradient is gsplat's gradient_2dgs


def densify_carrier_2dgs(T_sl: Tensor, track: bool) -> tuple[Tensor, Tensor | None]:
    """gsplat 1.5.3's 2DGS densification signal: a zero [I, N, 2] leaf whose gradient is
    (dL/dM[0, 2], dL/dM[1, 2]) * z, with M = T_sl the ray transform (its translation column is the
    homogeneous projected centre, so this is the image-plane gradient of the centre at fixed depth;
    RasterizeToPixels2DGSBwd.cu ``v_densify``). In 2DGS the centre enters the image only through M,
    so ``means2d.grad`` alone would carry just the small 2D-filter part. Adds exact zeros to M."""
    if not track:
        return T_sl, None
    carrier = torch.zeros(T_sl.shape[:-2] + (2,), dtype=T_sl.dtype, device=T_sl.device, requires_grad=True)
    z = T_sl[..., 2, 2].detach()[..., None]  # [I, N, 1]
    col = torch.cat([carrier * z, torch.zeros_like(z)], dim=-1)  # [I, N, 3]: added to column 2
    zero = torch.zeros_like(col)
    return T_sl + torch.stack([zero, zero, col], dim=-1), carrier


def rasterize(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    log_opacity: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    viewmats: Tensor,  # [I, 4, 4] T_camera_world
    camera: Pinhole,
    *,
    mode: Literal["3dgs", "2dgs"] = "3dgs",
    pixel_pose_index: Tensor | None = None,  # [H, W] int64 in 0..I-1 -> one output image
    want_normal: bool = False,
    tile_size: int = 16,
    absgrad: bool = False,
    chunk: int = 32,
    max_pairs: int = 1 << 22,
) -> RasterResult:
    """Project, bin and composite; returns accumulated features per output pixel."""
    dtype, device = means.dtype, means.device
    I, N = viewmats.shape[0], means.shape[0]
    proj, means2d_out, means2d_g = _project(mode, means, quats, scales, log_opacity, viewmats, camera, want_normal)
    ts = int(tile_size)
    pix_local, out_bins, bin_needed = _pixel_bins(camera, ts, I, pixel_pose_index, device)
    bins = intersect_tiles(means2d_g, proj.radii, proj.depths, ts, camera.width, camera.height, bin_needed)
    flat_out, T_init = _initial_transmittance(bins, out_bins, pix_local, ts * ts, dtype)

    ids = bins.flat_ids
    origin = _tile_origins(bins, bins.isect_bins, dtype)
    m_isect, g_geom, lo, feat, densify_2dgs = _gather_intersections(mode, proj, means2d_g, log_opacity, colors, ids,
                                                                    I, N, want_normal)
    if absgrad and m_isect.requires_grad:
        _track_absgrad(m_isect, ids, means2d_out, I * N)
    m_local = m_isect - origin
    lo = lo[:, 0]
    if mode == "3dgs":
        coef = coefficients_3dgs(m_local, g_geom, lo)
    else:
        coef = coefficients_2dgs(m_local, g_geom.reshape(-1, 3, 3), origin, lo)
    # feat [M, Cf]: colour, depth (channel 3), normal
    plan = _Plan(mode=mode, starts=bins.starts, lengths=bins.lengths, T_init=T_init,
                 phi=_tile_phi(ts, dtype, device), depth_channel=3, chunk=chunk, max_pairs=max_pairs)
    Fb, Tb, Db = composite(coef, feat, plan)
    Cf = feat.shape[1]
    fo = flat_out.reshape(-1)
    features = Fb.reshape(-1, Cf).index_select(0, fo).reshape(flat_out.shape + (Cf,))  # [Iout, H, W, Cf]
    trans = Tb.reshape(-1).index_select(0, fo).reshape(flat_out.shape)
    dist = Db.reshape(-1).index_select(0, fo).reshape(flat_out.shape)
    return RasterResult(features=features, transmittance=trans, distortion=dist, projection=proj, means2d=means2d_out,
                        densify_2dgs=densify_2dgs)


def _project(mode: str, means: Tensor, quats: Tensor, scales: Tensor, log_opacity: Tensor, viewmats: Tensor,
             camera: Pinhole, want_normal: bool) -> tuple[Projection, Tensor, Tensor]:
    """-> (projection, means2d [I, N, 2] in egobench pixels (grad-retaining, for densification
    statistics), the same in gsplat pixels (+0.5) that the binning and compositing use)."""
    K = gsplat_K(camera, means.dtype, means.device)
    if mode == "3dgs":
        proj = project_3dgs(means, quats, scales, viewmats, K, camera.width, camera.height,
                            opacities=log_opacity.detach().exp(), want_normal=want_normal)
    else:
        proj = project_2dgs(means, quats, scales, viewmats, K, camera.width, camera.height)
    means2d_out = proj.means2d - 0.5
    if means2d_out.requires_grad:
        means2d_out.retain_grad()
    return proj, means2d_out, means2d_out + 0.5


def _pixel_bins(camera: Pinhole, ts: int, I: int, pixel_pose_index: Tensor | None,
                device) -> tuple[Tensor, Tensor, Tensor | None]:
    """Where each output pixel is composited: -> (pix_local [H, W] row-major index inside its tile,
    out_bins [Iout, H, W] bin (image * n_tiles + tile) it reads, bin_needed [I, n_tiles] bool or None
    for all bins)."""
    tiles_x, tiles_y = math.ceil(camera.width / ts), math.ceil(camera.height / ts)
    n_tiles = tiles_x * tiles_y
    vv, uu = torch.meshgrid(torch.arange(camera.height, device=device), torch.arange(camera.width, device=device),
                            indexing="ij")
    pix_tile = (vv // ts) * tiles_x + (uu // ts)  # [H, W]
    pix_local = (vv % ts) * ts + (uu % ts)  # [H, W]
    if pixel_pose_index is None:
        out_bins = torch.arange(I, device=device)[:, None, None] * n_tiles + pix_tile[None]  # [I, H, W]
        return pix_local, out_bins, None
    out_bins = (pixel_pose_index.to(device).long() * n_tiles + pix_tile)[None]  # [1, H, W]
    bin_needed = torch.zeros(I * n_tiles, dtype=torch.bool, device=device)
    bin_needed[out_bins.reshape(-1)] = True
    return pix_local, out_bins, bin_needed.reshape(I, n_tiles)


def _initial_transmittance(bins: TileBins, out_bins: Tensor, pix_local: Tensor, P: int,
                           dtype) -> tuple[Tensor, Tensor]:
    """-> (flat_out [Iout, H, W] index of each output pixel into [NB * P], T_init [NB, P]: 1 for
    pixels to render, 0 for bin pixels no output pixel reads)."""
    pos = bins.bin_pos[out_bins]  # [Iout, H, W]
    flat_out = pos * P + pix_local  # [Iout, H, W] into [NB * P]
    T_init = torch.zeros(bins.bin_ids.numel() * P, dtype=dtype, device=out_bins.device)
    T_init[flat_out.reshape(-1)] = 1.0
    return flat_out, T_init.reshape(-1, P)


def _gather_intersections(mode: str, proj: Projection, means2d_g: Tensor, log_opacity: Tensor, colors: Tensor,
                          ids: Tensor, I: int, N: int, want_normal: bool):
    """Per-intersection inputs, ids [M] into I * N -> (means2d [M, 2] gsplat pixels, geometry [M, 3]
    conics (3DGS) or [M, 9] ray transforms (2DGS), log opacity [M, 1], features [M, Cf] (colour,
    depth, normal), 2DGS densification carrier or None)."""
    # one gather for every per-(image, Gaussian) quantity (index_select: its backward is a single
    # index_add, both far cheaper on CPU than several advanced-indexing gathers)
    densify_2dgs = None
    if mode == "3dgs":
        geom = proj.conics.reshape(-1, 3)
    else:
        T_sl, densify_2dgs = densify_carrier_2dgs(proj.ray_transforms, proj.ray_transforms.requires_grad)
        geom = T_sl.reshape(-1, 9)
    n_geom = geom.shape[1]
    per_view = [means2d_g.reshape(-1, 2), geom]  # [I * N, ...]
    per_gaussian = [log_opacity[:, None], colors]  # [N, ...]
    tail = [proj.depths.reshape(-1, 1)]
    if proj.normals is not None and (mode == "2dgs" or want_normal):
        tail.append(proj.normals.reshape(-1, 3))
    if I == 1:  # one table, one gather
        gathered = torch.cat(per_view + per_gaussian + tail, dim=1).index_select(0, ids)
        Cf = gathered.shape[1] - 3 - n_geom
        # split (its backward is one cat) rather than slices (each slice's backward zero-fills [M, ...])
        m_isect, g_geom, lo, feat = gathered.split([2, n_geom, 1, Cf], dim=1)
    else:  # per-Gaussian columns gathered from [N, 4] instead of being repeated I times
        n_tail = sum(t.shape[1] for t in tail)
        g_view = torch.cat(per_view + tail, dim=1).index_select(0, ids)
        m_isect, g_geom, g_tail = g_view.split([2, n_geom, n_tail], dim=1)
        lo, g_col = torch.cat(per_gaussian, dim=1).index_select(0, ids % N).split([1, colors.shape[1]], dim=1)
        feat = torch.cat([g_col, g_tail], dim=1)
    return m_isect, g_geom, lo, feat, densify_2dgs


def _track_absgrad(m_isect: Tensor, ids: Tensor, means2d_out: Tensor, n_rows: int) -> None:
    """Sets means2d_out.absgrad [I, N, 2] in the backward: sum over intersections of |dL/dmeans2d|."""
    buf = torch.zeros(n_rows, 2, dtype=m_isect.dtype, device=m_isect.device)

    def _hook(grad, ids=ids, buf=buf, out=means2d_out):
        buf.index_add_(0, ids, grad.abs())
        out.absgrad = buf.reshape(out.shape)

    m_isect.register_hook(_hook)
