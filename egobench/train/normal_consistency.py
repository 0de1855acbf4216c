"""2DGS normal consistency (docs/paper-notes.md §6): the rendered normals against the normals of the rendered
depth, weighted by alpha, averaged over the valid pixels. `normal_consistency` runs a compiled CPU
kernel (forward and hand-written backward) for CPU tensors and `normal_consistency_torch`, the
oracle, elsewhere; on a 128 px step the torch ops took 4.6 ms (forward + backward), ~8 % of an
`ours_2dgs` step (results/speed/README.md, "The projection vectorized").
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.host import start_kernel_pool
from egobench.render.cpu_backend import contiguous_numpy

#: F.normalize's eps: x / max(|x|, NORM_EPS)
NORM_EPS = 1e-12


def depth_normals(depth: Tensor, camera: Pinhole) -> Tensor:
    """Normals from a depth map [H, W] by central differences of the back-projected points -> [H, W, 3],
    facing the camera (negative z for a surface seen from the front) like the rendered normals
    (gsplat's ``depth_to_normal``: cross(d/drow, d/dcolumn)); zero on the border rows/columns."""
    grid = camera.pixel_grid(dtype=depth.dtype, device=depth.device)
    pts = camera.unproject(grid) * depth[..., None]  # [H, W, 3]
    d_col = torch.zeros_like(pts)
    d_row = torch.zeros_like(pts)
    d_col[:, 1:-1] = pts[:, 2:] - pts[:, :-2]  # along +u (camera +x)
    d_row[1:-1] = pts[2:] - pts[:-2]  # along +v (camera +y)
    n = torch.linalg.cross(d_row, d_col, dim=-1)  # y x x = -z: towards the camera
    return torch.nn.functional.normalize(n, dim=-1)


def normal_consistency_torch(depth: Tensor, normal: Tensor, alpha: Tensor, mask: Tensor, camera: Pinhole) -> Tensor:
    """sum_p mask alpha (1 - n_rendered . n_depth) / max(sum mask, 1) (unit normals; alpha is not
    differentiated): depth [H, W], normal [H, W, 3], alpha, mask [H, W] -> scalar."""
    depth_n = depth_normals(depth, camera)
    rend_n = torch.nn.functional.normalize(normal, dim=-1)
    err = (1 - (rend_n * depth_n).sum(-1)) * alpha.detach()
    return (err * mask).sum() / mask.sum().clamp_min(1)


class RenderedMaps(NamedTuple):
    """The maps `_nc_inputs` reads, any float dtype, read as they come (strided views too): depth [H, W],
    normal [H, W, 3] (rendered), alpha [H, W], mask [H, W]."""

    depth: np.ndarray
    normal: np.ndarray
    alpha: np.ndarray
    mask: np.ndarray


class NCInputs(NamedTuple):
    """The kernels' float64 inputs (`_nc_inputs` writes them): P [H, W, 3] back-projected points, N [H, W, 3]
    rendered normals, wts [H, W] alpha mask / mask count."""

    P: np.ndarray
    N: np.ndarray
    wts: np.ndarray


@njit(cache=True, inline="always")
def _unit(x, y, z):
    """(x, y, z) / max(|(x, y, z)|, NORM_EPS) -> (unit vector, the divisor)."""
    s = max(math.sqrt(x * x + y * y + z * z), NORM_EPS)
    return x / s, y / s, z / s, s


@njit(cache=True, inline="always")
def _depth_normal(P, v, u):
    """cross(P[v+1, u] - P[v-1, u], P[v, u+1] - P[v, u-1]) at an interior pixel -> (n0, n1, n2, a0, a1, a2,
    b0, b1, b2), flat (numba's parfor analysis rejects nested tuples in a prange body)."""
    a0, a1, a2 = P[v + 1, u, 0] - P[v - 1, u, 0], P[v + 1, u, 1] - P[v - 1, u, 1], P[v + 1, u, 2] - P[v - 1, u, 2]
    b0, b1, b2 = P[v, u + 1, 0] - P[v, u - 1, 0], P[v, u + 1, 1] - P[v, u - 1, 1], P[v, u + 1, 2] - P[v, u - 1, 2]
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0, a0, a1, a2, b0, b1, b2


@njit(cache=True, inline="always")
def _unit_grad(gx, gy, gz, x, y, z, s):
    """Backward of `_unit` at unit output (x, y, z) with divisor s: dL/d input from dL/d output."""
    if s > NORM_EPS:
        d = x * gx + y * gy + z * gz
        return (gx - x * d) / s, (gy - y * d) / s, (gz - z * d) / s
    return gx / s, gy / s, gz / s


@njit(cache=True, parallel=True)
def _nc_inputs(maps, rays, mask_count, out):
    """maps (`RenderedMaps`: depth, alpha, mask [H, W], normal [H, W, 3], any float dtype), rays [H, W, 3]
    float64 -> out (`NCInputs`): P = rays depth [H, W, 3], N = normal [H, W, 3] and wts = alpha mask /
    mask_count [H, W] in float64 (the torch ops' operations, in one pass)."""
    depth, normal, alpha, mask = maps.depth, maps.normal, maps.alpha, maps.mask
    P, N, wts = out.P, out.N, out.wts
    H, W = wts.shape
    for v in prange(H):
        for u in range(W):
            d = np.float64(depth[v, u])  # numba's float() keeps a float32 a float32
            for c in range(3):
                P[v, u, c] = rays[v, u, c] * d
                N[v, u, c] = normal[v, u, c]
            wts[v, u] = np.float64(alpha[v, u]) * np.float64(mask[v, u]) / mask_count


@njit(cache=True, parallel=True)
def _nc_forward(P, N, wts):
    """P [H, W, 3] back-projected points, N [H, W, 3] rendered normals, wts [H, W] alpha mask / count
    (float64) -> sum_p wts (1 - unit(N) . unit(depth normal)) (depth normal 0 on the border). The
    terms in parallel over rows, their sum in pixel order (the same bits for any thread count)."""
    H, W = wts.shape
    terms = np.empty((H, W))
    for v in prange(H):
        for u in range(W):
            dot = 0.0
            if 0 < v < H - 1 and 0 < u < W - 1:
                n0, n1, n2 = _depth_normal(P, v, u)[:3]
                d0, d1, d2, _ = _unit(n0, n1, n2)
                r0, r1, r2, _ = _unit(N[v, u, 0], N[v, u, 1], N[v, u, 2])
                dot = r0 * d0 + r1 * d1 + r2 * d2
            terms[v, u] = wts[v, u] * (1.0 - dot)
    total = 0.0
    for v in range(H):
        for u in range(W):
            total += terms[v, u]
    return total


@njit(cache=True, inline="always")
def _nc_row_grads(P, N, wts, g, g_normal, ga, gb, v):
    """Per pixel of row v: g_normal [H, W, 3], and dL/da, dL/db [H, W, 3] of its depth normal a x b
    (a, b: `_depth_normal`'s central differences); zero on the border."""
    H, W = wts.shape
    for u in range(W):
        for c in range(3):
            g_normal[v, u, c] = ga[v, u, c] = gb[v, u, c] = 0.0
        if not (0 < v < H - 1 and 0 < u < W - 1):
            continue
        n0, n1, n2, a0, a1, a2, b0, b1, b2 = _depth_normal(P, v, u)
        d0, d1, d2, sd = _unit(n0, n1, n2)
        r0, r1, r2, sr = _unit(N[v, u, 0], N[v, u, 1], N[v, u, 2])
        w = -g * wts[v, u]
        g_normal[v, u, 0], g_normal[v, u, 1], g_normal[v, u, 2] = _unit_grad(w * d0, w * d1, w * d2, r0, r1, r2, sr)
        gn0, gn1, gn2 = _unit_grad(w * r0, w * r1, w * r2, d0, d1, d2, sd)
        # n = a x b: dL/da = b x gn, dL/db = gn x a
        ga[v, u, 0], ga[v, u, 1], ga[v, u, 2] = b1 * gn2 - b2 * gn1, b2 * gn0 - b0 * gn2, b0 * gn1 - b1 * gn0
        gb[v, u, 0], gb[v, u, 1], gb[v, u, 2] = gn1 * a2 - gn2 * a1, gn2 * a0 - gn0 * a2, gn0 * a1 - gn1 * a0


@njit(cache=True, inline="always")
def _gathered(ga, gb, v, u, H, W, c):
    """dL/dP[v, u, c]: +ga above, +gb left, -gb right, -ga below (zero terms where a neighbour is missing;
    adding a zero to a sum that started at +0.0 leaves its bits unchanged)."""
    s = 0.0
    if v > 0:
        s += ga[v - 1, u, c]
    if u > 0:
        s += gb[v, u - 1, c]
    if u < W - 1:
        s -= gb[v, u + 1, c]
    if v < H - 1:
        s -= ga[v + 1, u, c]
    return s


@njit(cache=True, parallel=True)
def _nc_backward(P, rays, N, wts, g, g_depth, g_normal):
    """Backward of `_nc_forward` for upstream gradient g -> fills g_depth [H, W] and g_normal [H, W, 3].
    Each point gathers its four neighbours' terms (a = P[v+1] - P[v-1] along rows, b = P[u+1] - P[u-1]
    along columns) in the order a scatter over pixels in row-major order would add them, so the sums
    are the same bits as that scatter's, for any thread count."""
    H, W = wts.shape
    ga, gb = np.empty((H, W, 3)), np.empty((H, W, 3))
    for v in prange(H):
        _nc_row_grads(P, N, wts, g, g_normal, ga, gb, v)
    for v in prange(H):
        for u in range(W):
            s0, s1 = _gathered(ga, gb, v, u, H, W, 0), _gathered(ga, gb, v, u, H, W, 1)
            s2 = _gathered(ga, gb, v, u, H, W, 2)
            g_depth[v, u] = rays[v, u, 0] * s0 + rays[v, u, 1] * s1 + rays[v, u, 2] * s2


@functools.lru_cache(maxsize=8)
def _rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> Tensor:
    """Pinhole rays (z = 1) of every pixel centre [H, W, 3], float64 (read only: shared between calls)."""
    cam = Pinhole(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height)
    return cam.unproject(cam.pixel_grid(dtype=torch.float64))


def nc_forward_arrays(maps: RenderedMaps, rays: np.ndarray, mask_count: float) -> tuple[float, NCInputs]:
    """The compiled forward on arrays (maps as they come, strided views too; rays [H, W, 3] float64) -> (the
    value, in float64; what `nc_backward_arrays` reads)."""
    H, W = maps.depth.shape
    inputs = NCInputs(np.empty((H, W, 3)), np.empty((H, W, 3)), np.empty((H, W)))
    start_kernel_pool()
    _nc_inputs(maps, rays, mask_count, inputs)
    return _nc_forward(*inputs), inputs


def nc_backward_arrays(inputs: NCInputs, rays: np.ndarray, g: float, depth_dtype, normal_dtype):
    """The compiled backward for upstream gradient g -> (d/d depth [H, W], d/d normal [H, W, 3]) in the given
    dtypes (float64 sums, stored rounded)."""
    g_depth, g_normal = np.empty(inputs.wts.shape, depth_dtype), np.empty(inputs.N.shape, normal_dtype)
    _nc_backward(inputs.P, rays, inputs.N, inputs.wts, g, g_depth, g_normal)
    return g_depth, g_normal


def rays_of(camera: Pinhole) -> np.ndarray:
    """`_rays` of the camera as an array (shared between calls: read only)."""
    return contiguous_numpy(_rays(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height))


class _NormalConsistencyCPU(torch.autograd.Function):
    """`normal_consistency_torch` with compiled kernels (float64 inside): (depth, normal, alpha, mask, rays,
    mask count); gradients of depth and normal in their own dtypes."""

    @staticmethod
    def forward(ctx, depth, normal, alpha, mask, rays, mask_count):
        # the normal and the mask as they come (training: channel views), strided: no copies
        maps = RenderedMaps(contiguous_numpy(depth), normal.detach().numpy(), contiguous_numpy(alpha),
                            mask.detach().numpy())
        rays_np = contiguous_numpy(rays)
        value, inputs = nc_forward_arrays(maps, rays_np, mask_count)
        ctx.arrs, ctx.dtypes = (inputs, rays_np), (maps.depth.dtype, maps.normal.dtype)
        return torch.tensor(value, dtype=depth.dtype)

    @staticmethod
    def backward(ctx, g):
        inputs, rays = ctx.arrs
        g_depth, g_normal = nc_backward_arrays(inputs, rays, float(g), *ctx.dtypes)
        return torch.from_numpy(g_depth), torch.from_numpy(g_normal), None, None, None, None


def normal_consistency(depth: Tensor, normal: Tensor, alpha: Tensor, mask: Tensor, camera: Pinhole) -> Tensor:
    """`normal_consistency_torch`'s value and gradients (depth, normal); compiled on the CPU."""
    if depth.device.type != "cpu":
        return normal_consistency_torch(depth, normal, alpha, mask, camera)
    rays = _rays(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    mask_count = float(mask.sum().clamp_min(1))  # the torch oracle's divisor, in its dtype
    return _NormalConsistencyCPU.apply(depth, normal, alpha.detach(), mask, rays, mask_count)
