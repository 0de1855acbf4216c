"""egobench/render/gsplat_backend.py checked on the CPU against emulations of gsplat 1.5.3's CUDA rasterizers.

`render(..., backend="gsplat")` calls gsplat's CUDA `rasterization` / `rasterization_2dgs`, which
cannot run without a GPU. Here both are replaced by CPU emulations (`fake_rasterization`,
`fake_rasterization_2dgs`) that

* first bind the arguments they receive to the REAL functions' signatures (a misspelt or
  misplaced argument in the wrapper fails exactly as it would on a GPU), and reproduce the
  assertions / dtype requirements of gsplat's Python code and CUDA kernels (float32 only);
* project with gsplat's own pure-torch reference code (`gsplat.cuda._torch_impl`,
  `_torch_impl_2dgs`), patched where the CUDA kernels differ from it (opacity-aware radius of
  ProjectionEWA3DGSFused.cu; unit 2DGS normals of Projection2DGSFused.cu; undefined (here NaN)
  means2d of culled Gaussians, as the kernels leave `at::empty` memory unwritten);
* composite densely (every pixel x every Gaussian, autograd for the backward), following
  RasterizeToPixels3DGSFwd.cu / RasterizeToPixels2DGSFwd.cu: pixel centre (j + 0.5, i + 0.5),
  depth order (stable), only Gaussians with radii > 0 in the tiles their bounding box touches,
  alpha = min(0.999, o exp(-sigma)), skip sigma < 0 or alpha < 1/255, stop before the Gaussian that
  would bring T to <= 1e-4; 2DGS: ray-splat intersection, min with the 2D low-pass filter,
  normals, distortion and median depth from the last colour channel.

Tile culling: for 3DGS it never changes the image (the opacity-aware radius bounds every pixel
with alpha >= 1/255; `test_tile_culling_matters_only_for_2dgs`); for 2DGS it can (the 3.33 x extent
box of the projected splat is not an exact bound of its alpha >= 1/255 region under perspective;
in that test's scene one pixel in 1280 changes, by 6.5e-4 in alpha, at tile size 4), so the
emulation applies it.
Not emulated: packed mode, SH colours, antialiased mode, absgrad, distributed, camera models
other than pinhole. The 2DGS densification carrier's gradient is dL/dM[0:2, 2] * z (CUDA reads
that accumulator racily, i.e. possibly before all pixels have added to it).
The autouse fixture makes any call into gsplat's CUDA extension fail, so the fakes are pure torch.

Reference: `render(..., backend="torch")` (itself tested against a per-pixel oracle in
tests/render/test_render.py).
"""

from __future__ import annotations

import inspect
import math
import sys
import types

import pytest
import torch

gsplat = pytest.importorskip("gsplat", reason="gsplat 1.5.3 not installed")
pytest.importorskip("packaging", reason="gsplat's torch reference imports packaging")
from gsplat.cuda import _torch_impl, _torch_impl_2dgs  # noqa: E402
from gsplat.utils import depth_to_normal  # noqa: E402

import egobench.render as er  # noqa: E402
from egobench.camera.pinhole import Pinhole  # noqa: E402
from egobench.render import render  # noqa: E402
from egobench.render.types import Gaussians  # noqa: E402
from tests.render.test_render import make_scene, pose  # noqa: E402

REAL_RASTERIZATION = gsplat.rasterization
REAL_RASTERIZATION_2DGS = gsplat.rasterization_2dgs

ALPHA_THRESHOLD = 1.0 / 255.0  # include/Common.h
ALPHA_MAX = 0.999
T_STOP = 1e-4
FILTER_INV_SQUARE_2DGS = 2.0
#: set False (monkeypatch) to composite every Gaussian with radii > 0 at every pixel
TILE_CULLING = True
#: every call the fakes received: (name, bound arguments with defaults applied)
CALLS: list[tuple[str, dict]] = []


# ----------------------------------------------------------------------------------------------
# the emulations
# ----------------------------------------------------------------------------------------------


def _bind(real, args, kwargs) -> dict:
    """Bind to the REAL gsplat function's signature (TypeError exactly where gsplat would raise one)."""
    bound = inspect.signature(real).bind(*args, **kwargs)
    bound.apply_defaults()
    return dict(bound.arguments)


def _require(name: str, a: dict, **expected) -> None:
    for k, v in expected.items():
        assert a[k] == v, f"{name}: this emulation supports {k}={v!r} only, got {a[k]!r}"


def _check_float32(name: str, a: dict, keys) -> None:
    """gsplat's CUDA kernels read float32 (`data_ptr<float>()`); anything else raises there."""
    for k in keys:
        t = a[k]
        if t is None:
            continue
        assert isinstance(t, torch.Tensor), f"{name}: {k} must be a tensor, got {type(t).__name__}"
        assert t.dtype == torch.float32, f"{name}: {k} must be float32 for the CUDA kernels, got {t.dtype}"
        assert t.device.type == "cpu", f"{name}: {k} on {t.device}: the emulation runs on the CPU"


def _check_common(name: str, a: dict) -> tuple[int, int]:
    means, quats, scales, opac = a["means"], a["quats"], a["scales"], a["opacities"]
    viewmats, Ks = a["viewmats"], a["Ks"]
    assert means.dim() == 2, f"{name}: only unbatched inputs are emulated, means {tuple(means.shape)}"
    N, C = means.shape[0], viewmats.shape[-3]
    assert means.shape == (N, 3), means.shape
    assert quats.shape == (N, 4), quats.shape
    assert scales.shape == (N, 3), scales.shape
    assert opac.shape == (N,), opac.shape
    assert viewmats.shape == (C, 4, 4), viewmats.shape
    assert Ks.shape == (C, 3, 3), Ks.shape
    assert isinstance(a["width"], int) and isinstance(a["height"], int), (type(a["width"]), type(a["height"]))
    assert isinstance(a["tile_size"], int) and a["tile_size"] > 0, a["tile_size"]
    assert a["render_mode"] in ("RGB", "D", "ED", "RGB+D", "RGB+ED"), a["render_mode"]
    return N, C


def _pixels(W: int, H: int):
    """Integer pixel indices (column j, row i) [P] in row-major order (P = H * W)."""
    i, j = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    return j.reshape(-1), i.reshape(-1)


def _tile_mask(means2d: torch.Tensor, radii: torch.Tensor, tile_size: int, W: int, H: int) -> torch.Tensor:
    """[I, P, N] bool: Gaussian n is in the tile list of pixel p (IntersectTile.cu), radii > 0."""
    valid = (radii > 0).all(-1)  # [I, N]
    j, i = _pixels(W, H)
    tw, th = math.ceil(W / tile_size), math.ceil(H / tile_size)
    m = torch.where(valid[..., None], means2d.detach(), torch.zeros_like(means2d))
    r = radii.to(torch.float32)
    tx, ty = m[..., 0] / float(tile_size), m[..., 1] / float(tile_size)
    rx, ry = r[..., 0] / float(tile_size), r[..., 1] / float(tile_size)
    x0, x1 = torch.floor(tx - rx).clamp(0, tw), torch.ceil(tx + rx).clamp(0, tw)
    y0, y1 = torch.floor(ty - ry).clamp(0, th), torch.ceil(ty + ry).clamp(0, th)
    ptx = (j // tile_size).to(torch.float32)[None, :, None]
    pty = (i // tile_size).to(torch.float32)[None, :, None]
    mask = valid[:, None, :]
    if TILE_CULLING:
        mask = mask & (ptx >= x0[:, None]) & (ptx < x1[:, None]) & (pty >= y0[:, None]) & (pty < y1[:, None])
    return mask.expand(means2d.shape[0], H * W, means2d.shape[1])


def _composite(sigma: torch.Tensor, ok: torch.Tensor, opac: torch.Tensor):
    """Front-to-back compositing of depth-SORTED Gaussians along the last axis.

    sigma [I, P, N] (finite), ok [I, P, N] bool (valid pair), opac [I, N] ->
    vis [I, P, N] (alpha * T before), T_before [I, P, N], T_final [I, P], included [I, P, N]."""
    alpha = torch.clamp_max(opac[:, None, :] * torch.exp(-sigma), ALPHA_MAX)
    ok = ok & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    a0 = torch.where(ok, alpha, torch.zeros_like(alpha)).detach()
    # exclusive early stop: T is non-increasing, so "stop before the first Gaussian that brings T to
    # <= 1e-4" drops exactly the Gaussians whose T-after (counting every earlier valid one) is <= 1e-4
    included = ok & (torch.cumprod(1.0 - a0, dim=-1) > T_STOP)
    a = torch.where(included, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - a, dim=-1)
    T_before = torch.cat([torch.ones_like(T_after[..., :1]), T_after[..., :-1]], dim=-1)
    T_final = T_after[..., -1] if a.shape[-1] else torch.ones(a.shape[:-1], dtype=a.dtype)
    return a * T_before, T_before, T_final, included


def _sort_by_depth(depths: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """[I, N] -> [I, N] stable depth order (isect ids: image | tile | depth bits; ties by Gaussian)."""
    key = torch.where(valid, depths.detach(), torch.full_like(depths, float("inf")))
    return torch.sort(key, dim=-1, stable=True).indices


def _take(x: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Gather [I, N, ...] along N by order [I, N]."""
    idx = order.reshape(order.shape + (1,) * (x.dim() - 2)).expand_as(x)
    return torch.gather(x, 1, idx)


def _colors_and_backgrounds(a: dict, C: int, N: int, depths: torch.Tensor):
    """`rasterization` (3DGS) in rendering.py: colours [N, D] or [C, N, D] -> [C, N, D]; depth channel appended per render_mode."""
    colors, bgs, mode = a["colors"], a["backgrounds"], a["render_mode"]
    assert (colors.dim() == 2 and colors.shape[:-1] == (N,)) or (colors.dim() == 3 and colors.shape[:-1] == (C, N)), colors.shape
    if colors.dim() == 2:
        colors = torch.broadcast_to(colors[None], (C, N, colors.shape[-1]))
    D = colors.shape[-1]
    if bgs is not None:
        assert bgs.shape == (C, D), f"backgrounds must be [C, D] = [{C}, {D}], got {tuple(bgs.shape)}"
    if mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat([colors, depths[..., None]], dim=-1)
        bgs = None if bgs is None else torch.cat([bgs, torch.zeros(C, 1)], dim=-1)
    elif mode in ("D", "ED"):
        colors = depths[..., None]
        bgs = None if bgs is None else torch.zeros(C, 1)
    return colors, bgs


def _finish(render_colors, render_alphas, mode):
    if mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)
    return render_colors


def fake_rasterization(*args, **kwargs):
    """CPU emulation of `gsplat.rasterization` (3DGS, packed=False, classic, post-activation colours).

    Returns (render_colors [C, H, W, D'], render_alphas [C, H, W, 1], meta) like gsplat 1.5.3;
    meta["means2d"] [C, N, 2] (NaN where culled), meta["radii"] [C, N, 2] int32."""
    a = _bind(REAL_RASTERIZATION, args, kwargs)
    CALLS.append(("rasterization", a))
    _require("rasterization", a, packed=False, sh_degree=None, rasterize_mode="classic", covars=None,
             distributed=False, camera_model="pinhole", with_ut=False, with_eval3d=False, segmented=False,
             radial_coeffs=None, tangential_coeffs=None, thin_prism_coeffs=None, ftheta_coeffs=None,
             viewmats_rs=None, absgrad=False)
    _check_float32("rasterization", a, ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds"])
    N, C = _check_common("rasterization", a)
    W, H, ts = a["width"], a["height"], a["tile_size"]
    means, quats, scales, opac, viewmats, Ks = (a[k] for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks"))

    # projection: gsplat's pure-torch reference ...
    covars, _ = _torch_impl._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    _, means2d, depths, conics, _ = _torch_impl._fully_fused_projection(
        means, covars, viewmats, Ks, W, H, eps2d=a["eps2d"], near_plane=a["near_plane"], far_plane=a["far_plane"])
    # ... with the CUDA kernel's culling and opacity-aware radius (ProjectionEWA3DGSFused.cu)
    with torch.no_grad():
        means_c, covars_c = _torch_impl._world_to_cam(means, covars, viewmats)
        _, cov2d = _torch_impl._persp_proj(means_c, covars_c, Ks, W, H)
        c00, c11 = cov2d[..., 0, 0] + a["eps2d"], cov2d[..., 1, 1] + a["eps2d"]
        det = c00 * c11 - cov2d[..., 0, 1] * cov2d[..., 1, 0]
        op = opac.detach()[None].expand(C, N)
        extend = torch.clamp_max(torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)), 3.33)
        rx, ry = torch.ceil(extend * torch.sqrt(c00.clamp_min(0))), torch.ceil(extend * torch.sqrt(c11.clamp_min(0)))
        m = means2d.detach()
        valid = ((depths >= a["near_plane"]) & (depths <= a["far_plane"]) & (det > 0) & (op >= ALPHA_THRESHOLD)
                 & ~((rx <= a["radius_clip"]) & (ry <= a["radius_clip"]))
                 & ~((m[..., 0] + rx <= 0) | (m[..., 0] - rx >= W) | (m[..., 1] + ry <= 0) | (m[..., 1] - ry >= H)))
        radii = (torch.stack([rx, ry], -1) * valid[..., None]).to(torch.int32)
    # culled entries are unwritten at::empty memory in gsplat: NaN here, so nobody may rely on them
    means2d = torch.where(valid[..., None], means2d, torch.full_like(means2d, float("nan")))

    colors, bgs = _colors_and_backgrounds(a, C, N, depths)
    # dense compositing (RasterizeToPixels3DGSFwd.cu)
    order = _sort_by_depth(depths, valid)
    pair = _tile_mask(means2d, radii, ts, W, H)  # [C, P, N]
    pair = torch.gather(pair, 2, order[:, None, :].expand_as(pair))
    m_s = _take(torch.where(valid[..., None], means2d, torch.zeros_like(means2d)), order)  # [C, N, 2]
    con_s = _take(torch.where(valid[..., None], conics, torch.zeros_like(conics)), order)  # [C, N, 3]
    j, i = _pixels(W, H)
    px, py = j.to(torch.float32) + 0.5, i.to(torch.float32) + 0.5
    dx = m_s[:, None, :, 0] - px[None, :, None]  # [C, P, N]
    dy = m_s[:, None, :, 1] - py[None, :, None]
    sigma = 0.5 * (con_s[:, None, :, 0] * dx * dx + con_s[:, None, :, 2] * dy * dy) + con_s[:, None, :, 1] * dx * dy
    sigma = torch.where(pair, sigma, torch.full_like(sigma, 1e3))
    opac_s = _take(torch.broadcast_to(opac[None], (C, N)), order)
    vis, _, T, _ = _composite(sigma, pair, opac_s)
    feats = _take(colors, order)
    out = torch.einsum("cpn,cnd->cpd", vis, feats)
    if bgs is not None:
        out = out + T[..., None] * bgs[:, None, :]
    render_colors = out.reshape(C, H, W, -1)
    render_alphas = (1.0 - T).reshape(C, H, W, 1)
    meta = {"radii": radii, "means2d": means2d, "depths": depths, "conics": conics,
            "opacities": torch.broadcast_to(opac[None], (C, N)), "width": W, "height": H, "tile_size": ts,
            "tile_width": math.ceil(W / ts), "tile_height": math.ceil(H / ts), "n_cameras": C}
    return _finish(render_colors, render_alphas, a["render_mode"]), render_alphas, meta


def fake_rasterization_2dgs(*args, **kwargs):
    """CPU emulation of `gsplat.rasterization_2dgs` (packed=False, post-activation colours).

    Returns (colors, alphas, normals (WORLD frame, as gsplat), normals_from_depth, distort
    [C, H, W, 1], median [C, H, W, 1], meta with "gradient_2dgs", "means2d", "radii")."""
    a = _bind(REAL_RASTERIZATION_2DGS, args, kwargs)
    CALLS.append(("rasterization_2dgs", a))
    _require("rasterization_2dgs", a, packed=False, sh_degree=None, absgrad=False, depth_mode="expected")
    _check_float32("rasterization_2dgs", a, ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds"])
    N, C = _check_common("rasterization_2dgs", a)
    if a["distloss"]:
        assert a["render_mode"] in ("D", "ED", "RGB+D", "RGB+ED"), "distloss requires depth rendering"
    W, H, ts = a["width"], a["height"], a["tile_size"]
    means, quats, scales, opac, viewmats, Ks = (a[k] for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks"))

    radii, means2d, depths, M, _ = _torch_impl_2dgs._fully_fused_projection_2dgs(
        means, quats, scales, viewmats, Ks, W, H, near_plane=a["near_plane"], far_plane=a["far_plane"])
    with torch.no_grad():
        r = radii.to(torch.float32)
        radii = (r * ~((r[..., 0] <= a["radius_clip"]) & (r[..., 1] <= a["radius_clip"]))[..., None]).to(torch.int32)
    valid = (radii > 0).all(-1)
    # CUDA normal: R_cw R(q)[:, 2] (unit; the torch reference keeps scale 3 in it), facing the camera
    R_c = torch.einsum("cij,njk->cnik", viewmats[:, :3, :3], _torch_impl._quat_to_rotmat(quats))
    means_c = torch.einsum("cij,nj->cni", viewmats[:, :3, :3], means) + viewmats[:, None, :3, 3]
    n_c = R_c[..., 2]
    normals = torch.where(((-n_c * means_c).sum(-1, keepdim=True) > 0), n_c, -n_c)
    means2d = torch.where(valid[..., None], means2d, torch.full_like(means2d, float("nan")))
    densify = torch.zeros_like(means2d, requires_grad=True)  # gsplat: zeros_like(means2d, requires_grad=True)

    # colours exactly as rasterization_2dgs handles them (rendering.py): its [N, D] -> [C, N, D]
    # broadcast is commented out ("TODO"), so per-Gaussian colours [N, D] fail in torch.cat / the
    # rasterize_to_pixels_2dgs assertion, as on a GPU
    colors, bgs, mode = a["colors"], a["backgrounds"], a["render_mode"]
    assert (colors.dim() == 2 and colors.shape[:-1] == (N,)) or (colors.dim() == 3 and colors.shape[:-1] == (C, N)), colors.shape
    if mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat((colors, depths[..., None]), dim=-1)
        bgs = None if bgs is None else torch.cat((bgs, torch.zeros_like(bgs[..., :1])), dim=-1)
    elif mode in ("D", "ED"):
        colors = depths[..., None]
    assert colors.shape[:-2] == (C,), f"rasterize_to_pixels_2dgs: colors.shape[:-2] must be (C,), got {tuple(colors.shape)}"
    if bgs is not None:
        assert bgs.shape == (C, colors.shape[-1]), f"rasterize_to_pixels_2dgs: backgrounds {tuple(bgs.shape)}"
    order = _sort_by_depth(depths, valid)
    pair = _tile_mask(means2d, radii, ts, W, H)
    pair = torch.gather(pair, 2, order[:, None, :].expand_as(pair))
    # densification carrier: d loss / d densify = d loss / d M[0:2, 2] * z (RasterizeToPixels2DGSBwd.cu)
    z_w = M[..., 2, 2].detach()
    shift = torch.stack([densify[..., 0] * z_w, densify[..., 1] * z_w, torch.zeros_like(z_w)], -1)  # [C, N, 3]
    M = M + shift[..., :, None] * torch.tensor([0.0, 0.0, 1.0])
    M_s = _take(torch.where(valid[..., None, None], M, torch.zeros_like(M)), order)  # [C, N, 3, 3]
    m_s = _take(torch.where(valid[..., None], means2d, torch.zeros_like(means2d)), order)
    j, i = _pixels(W, H)
    px = (j.to(torch.float32) + 0.5)[None, :, None, None]
    py = (i.to(torch.float32) + 0.5)[None, :, None, None]
    h_u = px * M_s[:, None, :, 2, :] - M_s[:, None, :, 0, :]  # [C, P, N, 3]
    h_v = py * M_s[:, None, :, 2, :] - M_s[:, None, :, 1, :]
    cr = torch.linalg.cross(h_u, h_v, dim=-1)
    nz = cr[..., 2] != 0
    cz = torch.where(nz, cr[..., 2], torch.ones_like(cr[..., 2]))
    g3 = (cr[..., 0] / cz) ** 2 + (cr[..., 1] / cz) ** 2
    dx = m_s[:, None, :, 0] - px[..., 0]
    dy = m_s[:, None, :, 1] - py[..., 0]
    g2 = FILTER_INV_SQUARE_2DGS * (dx * dx + dy * dy)
    pair = pair & nz
    sigma = torch.where(pair, 0.5 * torch.minimum(g3, g2), torch.full_like(g3, 1e3))
    opac_s = _take(torch.broadcast_to(opac[None], (C, N)), order)
    vis, T_before, T, inc = _composite(sigma, pair, opac_s)
    feats = _take(colors, order)  # [C, N, D]
    out = torch.einsum("cpn,cnd->cpd", vis, feats)
    if bgs is not None:
        out = out + T[..., None] * bgs[:, None, :]
    n_cam = torch.einsum("cpn,cnk->cpk", vis, _take(normals, order))  # camera frame
    depth_ch = feats[..., -1]  # c_ptr[CDIM - 1]: the last colour channel
    if a["distloss"]:
        vd = vis * depth_ch[:, None, :]
        acc_before = torch.cumsum(vd, dim=-1) - vd
        distort = (2.0 * (vd * (1.0 - T_before) - vis * acc_before)).sum(-1)
    else:
        distort = torch.zeros_like(T)
    with torch.no_grad():
        last = torch.where(inc & (T_before > 0.5), torch.arange(N)[None, None, :], torch.full_like(inc, -1, dtype=torch.long))
        last = last.amax(-1) if N else torch.full(T.shape, -1)
    median = torch.gather(depth_ch[:, None, :].expand(-1, H * W, -1), 2, last.clamp_min(0)[..., None])[..., 0]
    median = torch.where(last >= 0, median, torch.zeros_like(median))

    render_alphas = (1.0 - T).reshape(C, H, W, 1)
    render_colors = _finish(out.reshape(C, H, W, -1), render_alphas, a["render_mode"])
    normals_from_depth = None
    if a["render_mode"] in ("RGB+ED", "RGB+D"):
        normals_from_depth = depth_to_normal(render_colors[..., -1:], torch.linalg.inv(viewmats), Ks).squeeze(0)
    render_normals = torch.einsum("cij,chwj->chwi", torch.linalg.inv(viewmats)[..., :3, :3], n_cam.reshape(C, H, W, 3))
    meta = {"radii": radii, "means2d": means2d, "depths": depths, "ray_transforms": M, "normals": normals,
            "opacities": torch.broadcast_to(opac[None], (C, N)), "gradient_2dgs": densify, "width": W, "height": H,
            "tile_size": ts, "tile_width": math.ceil(W / ts), "tile_height": math.ceil(H / ts), "n_cameras": C,
            "render_distort": distort.reshape(C, H, W, 1)}
    return (render_colors, render_alphas, render_normals, normals_from_depth, distort.reshape(C, H, W, 1),
            median.reshape(C, H, W, 1), meta)


# ----------------------------------------------------------------------------------------------
# fixtures: no CUDA anywhere; route render(backend="gsplat") on CPU tensors to the fakes
# ----------------------------------------------------------------------------------------------


class _NoCudaBackend(types.ModuleType):
    def __getattr__(self, name):
        if name.startswith("__"):  # module introspection (inspect.getmodule, pickling)
            raise AttributeError(name)
        raise AssertionError(f"gsplat's CUDA extension was called ({name}) -- the emulation must be pure torch")


@pytest.fixture(autouse=True)
def _no_gsplat_cuda(monkeypatch):
    """Any `from gsplat.cuda._backend import _C` (every CUDA op of gsplat) fails loudly."""
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", _NoCudaBackend("gsplat.cuda._backend"))
    CALLS.clear()
    yield


@pytest.fixture
def fake_gsplat(monkeypatch):
    """render(backend="gsplat") on CPU tensors reaches the wrapper, and the wrapper the fakes.

    Only the routing is patched: `resolve_backend` answers "gsplat" when asked for it (the real one
    requires CUDA); "auto" and "torch" keep the real answer."""
    real_resolve = er.resolve_backend
    monkeypatch.setattr(er, "resolve_backend",
                        lambda backend, device: "gsplat" if backend == "gsplat" else real_resolve(backend, device))
    monkeypatch.setattr(gsplat, "rasterization", fake_rasterization)
    monkeypatch.setattr(gsplat, "rasterization_2dgs", fake_rasterization_2dgs)


CAM = Pinhole(fx=36.0, fy=38.0, cx=17.3, cy=14.8, width=40, height=32)  # principal point off centre (19.5, 15.5)
BG = (0.2, 0.5, 0.9)


def _scene(n=200, seed=0, dtype=torch.float32, T=None) -> Gaussians:
    """make_scene's Gaussians (built in front of an identity camera) moved into the frame of camera pose T."""
    g = make_scene(n, CAM, seed, dtype=torch.float64, sigma_px=(0.6, 3.5), opacity_logit=0.5)
    if T is not None:
        R, t = T[:3, :3].to(torch.float64), T[:3, 3].to(torch.float64)
        means = g.means @ R.T + t
        # rotate each Gaussian with the camera: q_world = q_R * q (Hamilton), q_R from the small rotation R
        w1 = torch.sqrt(1 + R[0, 0] + R[1, 1] + R[2, 2]) / 2
        x1, y1, z1 = (R[2, 1] - R[1, 2]) / (4 * w1), (R[0, 2] - R[2, 0]) / (4 * w1), (R[1, 0] - R[0, 1]) / (4 * w1)
        w2, x2, y2, z2 = torch.nn.functional.normalize(g.quats, dim=-1).unbind(-1)
        quats = torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                             w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)
        g = Gaussians(means, quats, g.log_scales, g.opacity_logits, g.colors)
    return Gaussians(**{k: v.to(dtype) for k, v in g.tensors().items()})


POSE = pose(0.06, -0.05, (0.03, -0.02, 0.1))


def _run(g: Gaussians, T, backend, *, mode, weights_seed=0, **kw):
    """render + a weighted loss over every output map + backward -> (out, {param: grad})."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    gg = Gaussians(**leaves)
    dtype = g.means.dtype
    out = render(gg, CAM, T.to(dtype), mode=mode, backend=backend, background=torch.tensor(BG, dtype=dtype), **kw)
    if out.means2d.requires_grad:
        out.means2d.retain_grad()
    gen = torch.Generator().manual_seed(weights_seed)
    maps = [out.rgb, out.alpha, 0.1 * out.depth] + ([out.normal] if out.normal is not None else [])
    if mode == "2dgs":
        maps.append(out.extras["distortion"])
    m = torch.cat(maps, -1)
    loss = (m * torch.randn(m.shape, generator=gen, dtype=torch.float64).to(dtype)).sum()
    loss.backward()
    return out, {k: v.grad for k, v in leaves.items()}


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


#: map tolerances (absolute; depth and distortion 5x, they are ~1.5..4.5 m): float32 on both sides, or
#: float32 gsplat vs the float64 torch backend; measured maxima are 3-10x below (see the report)
ATOL = {"3dgs": 5e-6, "2dgs": 2e-5}
#: relative L2 error of each parameter's gradient
GRAD_RTOL = {"3dgs": 2e-5, "2dgs": 2e-4}


def _assert_maps_close(a, b, mode, atol=None):
    """gsplat wrapper (a) vs torch backend (b): float32 compositing, different summation order."""
    atol = ATOL[mode] if atol is None else atol
    torch.testing.assert_close(a.rgb, b.rgb, atol=atol, rtol=0)
    torch.testing.assert_close(a.alpha, b.alpha, atol=atol, rtol=0)
    torch.testing.assert_close(a.depth, b.depth, atol=5 * atol, rtol=0)
    if b.normal is not None:
        assert a.normal is not None, "wrapper returned no normal map"
        torch.testing.assert_close(a.normal, b.normal, atol=atol, rtol=0)
    if mode == "2dgs":
        torch.testing.assert_close(a.extras["distortion"], b.extras["distortion"], atol=5 * atol, rtol=0)


# ----------------------------------------------------------------------------------------------
# the fakes themselves: analytic images, and no CUDA
# ----------------------------------------------------------------------------------------------


def test_real_gsplat_functions_need_cuda_here():
    """The sentinel works: gsplat's real rasterizer goes to its CUDA extension (so the fakes, which run
    under the same fixture, do not)."""
    g = _scene(5)
    with pytest.raises(AssertionError, match="CUDA extension was called"):
        REAL_RASTERIZATION(g.means, g.quats, g.scales, g.opacities, g.colors, torch.eye(4)[None],
                           torch.eye(3)[None], 8, 8, packed=False)


def test_fake_3dgs_single_isotropic_gaussian_is_analytic():
    """One isotropic Gaussian on the optical axis: cov2d = (f s / z)^2 I + 0.3 I, centred on (cx, cy)."""
    f, s, z, o = 30.0, 0.1, 2.0, 0.8
    W, H, cx, cy = 24, 20, 11.3, 9.7  # gsplat convention principal point
    col = torch.tensor([[0.9, 0.3, 0.1]])
    bg = torch.tensor([[0.1, 0.2, 0.7, 0.0]])  # [C, D] incl. an extra channel
    colors = torch.cat([col, torch.tensor([[0.5]])], -1)  # a 4th feature channel
    Ks = torch.tensor([[[f, 0, cx], [0, f, cy], [0, 0, 1.0]]])
    img, alpha, meta = fake_rasterization(
        torch.tensor([[0.0, 0.0, z]]), torch.tensor([[0.3, -0.5, 0.2, 0.7]]), torch.full((1, 3), s),
        torch.tensor([o]), colors, torch.eye(4)[None], Ks, W, H, backgrounds=bg, render_mode="RGB+ED", packed=False)
    var = (f * s / z) ** 2 + 0.3
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64), indexing="xy")
    r2 = (jj + 0.5 - cx) ** 2 + (ii + 0.5 - cy) ** 2
    a = (o * torch.exp(-0.5 * r2 / var)).clamp_max(0.999)
    a = torch.where(a >= 1 / 255, a, torch.zeros_like(a))
    assert (a == 0).any() and float(a.max()) > 0.7  # the image has both regimes
    torch.testing.assert_close(alpha[0, ..., 0].double(), a, atol=1e-6, rtol=0)
    ref = a[..., None] * colors[0].double() + (1 - a[..., None]) * bg[0].double()
    torch.testing.assert_close(img[0, ..., :4].double(), ref, atol=1e-6, rtol=0)
    # expected depth = (a z) / (1 - (1 - a)): float32 1 - T loses ~6e-8 absolute in a, i.e. 2e-5 relative at a = 1/255
    torch.testing.assert_close(img[0, ..., 4].double(), torch.where(a > 0, z, 0.0).double(), atol=1e-4, rtol=0)
    ext = min(3.33, math.sqrt(2 * math.log(o * 255)))
    assert meta["radii"].tolist() == [[[math.ceil(ext * math.sqrt(var))] * 2]]
    torch.testing.assert_close(meta["means2d"], torch.tensor([[[cx, cy]]]), atol=1e-6, rtol=0)


def test_fake_3dgs_depth_order_and_exclusive_early_stop():
    """Two opaque Gaussians on one pixel, given back to front: the front one counts (T = 0.001), the
    back one would bring T to 1e-6 <= 1e-4 and is dropped. A nearer faint one whose bounding box covers
    the pixel but whose alpha there is 0.02 exp(-5.8^2 / (2 * 9.3)) = 0.0033 < 1/255 is skipped."""
    cx = cy = 1.5  # pixel (1, 1)'s centre
    Ks = torch.tensor([[[10.0, 0, cx], [0, 10.0, cy], [0, 0, 1]]])
    means = torch.tensor([[0.0, 0, 4.0], [0.0, 0, 2.0], [0.58, 0, 1.0]])
    scales = torch.tensor([[0.3] * 3, [0.3] * 3, [0.3] * 3])
    img, alpha, meta = fake_rasterization(
        means, torch.tensor([[1.0, 0, 0, 0]] * 3), scales, torch.tensor([1.0, 1.0, 0.02]),
        torch.eye(3), torch.eye(4)[None], Ks, 3, 3, backgrounds=torch.tensor([[0.0, 0.0, 0.5]]), packed=False)
    assert meta["radii"][0, 2].tolist() == [6, 6]  # ceil(sqrt(2 ln(0.02 * 255)) * sqrt(9.3)) >= 5.8 px
    assert alpha[0, 1, 1, 0].item() == pytest.approx(0.999, abs=1e-6)
    torch.testing.assert_close(img[0, 1, 1], torch.tensor([0.0, 0.999, 0.0005]), atol=1e-6, rtol=0)


def test_fake_2dgs_single_surfel_and_distortion_are_analytic():
    """Surfels facing the camera on the axis: s_uv = (p - c) z / (f s); sigma = 0.5 min(|s|^2, 2 |p - c|^2);
    normal (0, 0, -1); for two surfels the distortion at the centre is 2 vis2 a1 (z2 - z1)."""
    f, W, H, cx, cy = 30.0, 24, 20, 11.3, 9.7
    Ks = torch.tensor([[[f, 0, cx], [0, f, cy], [0, 0, 1.0]]])
    (z1, s1, o1), (z2, s2, o2) = (2.0, 0.1, 0.4), (3.0, 0.2, 0.9)
    out = fake_rasterization_2dgs(
        torch.tensor([[0.0, 0, z2], [0.0, 0, z1]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
        torch.tensor([[s2, s2, 1e-3], [s1, s1, 1e-3]]), torch.tensor([o2, o1]), torch.tensor([[[0.0, 1, 0], [1.0, 0, 0]]]),
        torch.eye(4)[None], Ks, W, H, render_mode="RGB+ED", distloss=True, packed=False, tile_size=8)
    img, alpha, normals, _, distort, median, meta = out
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64), indexing="xy")
    r2 = (jj + 0.5 - cx) ** 2 + (ii + 0.5 - cy) ** 2

    def alpha_of(z, s, o):
        a = (o * torch.exp(-0.5 * torch.minimum(r2 * (z / (f * s)) ** 2, 2 * r2))).clamp_max(0.999)
        return torch.where(a >= 1 / 255, a, torch.zeros_like(a))

    a1, a2 = alpha_of(z1, s1, o1), alpha_of(z2, s2, o2)
    vis2 = a2 * (1 - a1)
    torch.testing.assert_close(alpha[0, ..., 0].double(), 1 - (1 - a1) * (1 - a2), atol=1e-6, rtol=0)
    torch.testing.assert_close(img[0, ..., 0].double(), a1, atol=1e-6, rtol=0)
    torch.testing.assert_close(img[0, ..., 1].double(), vis2, atol=1e-6, rtol=0)
    torch.testing.assert_close(normals[0, ..., 2].double(), -(a1 + vis2), atol=1e-6, rtol=0)
    torch.testing.assert_close(distort[0, ..., 0].double(), 2 * vis2 * a1 * (z2 - z1), atol=1e-5, rtol=0)
    med = torch.where(a1 > 0, torch.where(1 - a1 > 0.5, torch.where(a2 > 0, z2, z1), z1), torch.where(a2 > 0, z2, 0.0))
    torch.testing.assert_close(median[0, ..., 0].double(), med.double(), atol=1e-6, rtol=0)
    assert meta["gradient_2dgs"].shape == (1, 2, 2) and meta["gradient_2dgs"].requires_grad
    torch.testing.assert_close(meta["means2d"][0], torch.tensor([[cx, cy], [cx, cy]]), atol=1e-5, rtol=0)


def test_tile_culling_matters_only_for_2dgs(monkeypatch):
    """3DGS: identical images with and without the tile lists (the opacity-aware radius bounds every
    pixel with alpha >= 1/255). 2DGS: the box does not strictly bound the ray-splat footprint, so tiles
    matter (here: a surfel with radii (7, 8) reaches a pixel (6, 8.1) px away, g3 = 10.6 < 3.33^2)."""
    g = _scene(300, 3, T=POSE)
    vm = torch.linalg.inv(POSE.float())[None]
    K = torch.tensor([[[CAM.fx, 0, CAM.cx + 0.5], [0, CAM.fy, CAM.cy + 0.5], [0, 0, 1]]])
    args = (g.means, g.quats, g.scales, g.opacities, g.colors, vm, K, CAM.width, CAM.height)
    culled = fake_rasterization(*args, packed=False, tile_size=4, render_mode="RGB+ED")
    args2 = args[:4] + (g.colors[None],) + args[5:]  # 2DGS needs [C, N, D] colours (see the fake)
    culled2 = fake_rasterization_2dgs(*args2, tile_size=4, render_mode="RGB+ED")
    monkeypatch.setattr(sys.modules[__name__], "TILE_CULLING", False)
    dense = fake_rasterization(*args, packed=False, tile_size=4, render_mode="RGB+ED")
    dense2 = fake_rasterization_2dgs(*args2, tile_size=4, render_mode="RGB+ED")
    assert torch.equal(culled[0], dense[0]) and torch.equal(culled[1], dense[1])
    assert float((culled2[1] - dense2[1]).detach().abs().max()) > 1e-4


def test_fake_2dgs_rejects_per_gaussian_colors_like_gsplat():
    """gsplat 1.5.3's rasterization_2dgs does not broadcast [N, D] colours (rendering.py: the broadcast
    is commented out): torch.cat with the [C, N, 1] depths fails, and without depth the assertion of
    rasterize_to_pixels_2dgs does. The emulation must fail the same way."""
    g = _scene(10, 0)
    args = (g.means, g.quats, g.scales, g.opacities, g.colors, torch.eye(4)[None],
            torch.tensor([[[30.0, 0, 8], [0, 30.0, 8], [0, 0, 1]]]), 16, 16)
    with pytest.raises(RuntimeError, match="same number of dimensions"):
        fake_rasterization_2dgs(*args, render_mode="RGB+ED")
    with pytest.raises(AssertionError, match="colors.shape"):
        fake_rasterization_2dgs(*args, render_mode="RGB")
    fake_rasterization_2dgs(*args[:4], g.colors[None], *args[5:], render_mode="RGB+ED")  # [C, N, D] works


# ----------------------------------------------------------------------------------------------
# the wrapper against the torch backend
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
@pytest.mark.parametrize("tile_size", [16, 4])
def test_wrapper_matches_torch_backend(fake_gsplat, mode, tile_size):
    g = _scene(200, 1, T=POSE)
    a, ga = _run(g, POSE, "gsplat", mode=mode, want_normal=True, tile_size=tile_size)
    b, gb = _run(g, POSE, "torch", mode=mode, want_normal=True, tile_size=tile_size)
    assert a.extras["backend"] == "gsplat" and [c[0] for c in CALLS] == ["rasterization" if mode == "3dgs" else "rasterization_2dgs"]
    assert a.rgb.shape == (1, CAM.height, CAM.width, 3) and a.rgb.dtype == torch.float32
    assert float(b.alpha.detach().max()) > 0.95 and float(b.alpha.detach().min()) < 0.5  # near-opaque and see-through
    _assert_maps_close(a, b, mode)
    torch.testing.assert_close(a.radii, b.radii, atol=0, rtol=0)
    for k in ga:  # the wrapper's casts / concatenations / rotations are on the autograd path
        assert _rel(ga[k], gb[k]) < GRAD_RTOL[mode], (k, _rel(ga[k], gb[k]))


def test_wrapper_call_arguments(fake_gsplat):
    """What the wrapper hands gsplat: Ks with cx + 0.5, world-to-camera viewmats, backgrounds padded
    with zeros for the normal channels, colours [B, N, 6] with camera-frame normals, float32."""
    g = _scene(50, 2, T=POSE)
    Ts = torch.stack([POSE, pose(0.0, 0.1, (0.05, 0, 0))]).float()
    render(g, CAM, Ts, backend="gsplat", want_normal=True, tile_size=16,
           background=torch.tensor(BG))
    render(g, CAM, Ts, backend="gsplat", mode="2dgs", tile_size=8,
           background=torch.tensor(BG))
    (n3, a3), (n2, a2) = CALLS
    K = torch.tensor([[CAM.fx, 0, CAM.cx + 0.5], [0, CAM.fy, CAM.cy + 0.5], [0, 0, 1]])
    for a in (a3, a2):
        torch.testing.assert_close(a["Ks"], K.expand(2, 3, 3), atol=0, rtol=0)
        torch.testing.assert_close(a["viewmats"], torch.linalg.inv(Ts.double()).float(), atol=1e-6, rtol=0)
        assert (a["width"], a["height"], a["packed"], a["render_mode"]) == (CAM.width, CAM.height, False, "RGB+ED")
        torch.testing.assert_close(a["opacities"], g.opacities, atol=0, rtol=0)
    assert a3["tile_size"] == 16 and a2["tile_size"] == 8 and a2["distloss"] is True
    assert torch.equal(a3["backgrounds"], torch.tensor([list(BG) + [0.0] * 3] * 2))
    assert a2["backgrounds"].shape == (2, 3) and a3["colors"].shape == (2, 50, 6) and a2["colors"].shape == (2, 50, 3)
    torch.testing.assert_close(a3["colors"][..., :3], g.colors.expand(2, -1, -1), atol=0, rtol=0)
    n = a3["colors"][..., 3:]
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(2, 50), atol=1e-6, rtol=0)


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_wrapper_rolling_shutter(fake_gsplat, mode):
    """pixel_pose_index over 3 poses: the wrapper renders 3 images and gathers per pixel."""
    g = _scene(250, 4, T=POSE)
    Ts = torch.stack([POSE @ pose(0.0, 0.02 * k, (0.03 * k, 0.01 * k, 0)) for k in range(3)]).float()
    idx = torch.randint(0, 3, (CAM.height, CAM.width), generator=torch.Generator().manual_seed(5))
    a, ga = _run(g, Ts, "gsplat", mode=mode, pixel_pose_index=idx, want_normal=True, tile_size=8)
    b, gb = _run(g, Ts, "torch", mode=mode, pixel_pose_index=idx, want_normal=True, tile_size=8)
    assert a.rgb.shape == (1, CAM.height, CAM.width, 3) and a.radii.shape == (3, 250)
    _assert_maps_close(a, b, mode)
    torch.testing.assert_close(a.radii, b.radii, atol=0, rtol=0)
    for k in ga:
        assert _rel(ga[k], gb[k]) < GRAD_RTOL[mode], (k, _rel(ga[k], gb[k]))
    # the gather really mixes poses: differs from every single-pose image
    full = render(g, CAM, Ts, mode=mode, backend="gsplat", tile_size=8,
                  background=torch.tensor(BG))
    for k in range(3):
        assert float((full.rgb[k] - a.rgb[0]).detach().abs().max()) > 0.05


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_wrapper_float64(fake_gsplat, mode):
    """float64 Gaussians and poses: outputs come back float64 and gradients reach the float64 leaves."""
    g = _scene(200, 6, dtype=torch.float64, T=POSE)
    a, ga = _run(g, POSE.double(), "gsplat", mode=mode, want_normal=True, tile_size=8)
    b, gb = _run(g, POSE.double(), "torch", mode=mode, want_normal=True, tile_size=8)
    for t in (a.rgb, a.alpha, a.depth, a.normal) + ((a.extras["distortion"],) if mode == "2dgs" else ()):
        assert t.dtype == torch.float64
    assert CALLS[0][1]["means"].dtype == torch.float32 and CALLS[0][1]["viewmats"].dtype == torch.float32
    # float32 gsplat vs float64 reference: 2DGS's ray-splat cross product loses more digits than 3DGS's conic
    _assert_maps_close(a, b, mode, atol=ATOL["3dgs"] if mode == "3dgs" else 1e-4)
    for k in ga:
        assert ga[k] is not None and ga[k].dtype == torch.float64, k
        assert float(ga[k].abs().max()) > 0, k
        assert _rel(ga[k], gb[k]) < GRAD_RTOL[mode], (k, _rel(ga[k], gb[k]))


def test_wrapper_means2d_convention_3dgs(fake_gsplat):
    """3DGS means2d: gsplat's tensor, values = egobench projection + 0.5 exactly (float32 rounding),
    gradient = the torch backend's means2d gradient (the densification signal), radii equal."""
    g = _scene(300, 7, T=POSE)
    a, _ = _run(g, POSE, "gsplat", mode="3dgs", tile_size=8)
    b, _ = _run(g, POSE, "torch", mode="3dgs", tile_size=8)
    assert a.extras["means2d_convention"] == "gsplat (+0.5)"
    keep = a.radii[0] > 0
    assert int(keep.sum()) > 200 and torch.equal(keep, b.radii[0] > 0)
    # independent float64 projection in egobench's convention (pixel centre (i, j))
    Tcw = torch.linalg.inv(POSE.double())
    mc = g.means.double() @ Tcw[:3, :3].T + Tcw[:3, 3]
    uv = torch.stack([CAM.fx * mc[:, 0] / mc[:, 2] + CAM.cx, CAM.fy * mc[:, 1] / mc[:, 2] + CAM.cy], -1)
    torch.testing.assert_close(a.means2d[0][keep].double(), uv[keep] + 0.5, atol=2e-5, rtol=0)
    torch.testing.assert_close(b.means2d[0][keep].double(), uv[keep], atol=2e-5, rtol=0)
    assert torch.isnan(a.means2d[0][~keep]).all()  # culled: undefined in gsplat (NaN in the emulation)
    assert a.means2d.grad is not None
    torch.testing.assert_close(a.means2d.grad[0][keep], b.means2d.grad[0][keep], atol=2e-5, rtol=1e-4)
    assert (a.means2d.grad[0][~keep] == 0).all()


def test_wrapper_means2d_2dgs_is_the_gradient_carrier(fake_gsplat):
    """2DGS: means2d is gsplat's `gradient_2dgs` (zeros, requires grad, gets the densification
    gradient); the projected centres (+0.5) are in extras["means2d_values"]."""
    g = _scene(300, 8, T=POSE)
    a, _ = _run(g, POSE, "gsplat", mode="2dgs", tile_size=8)
    b, _ = _run(g, POSE, "torch", mode="2dgs", tile_size=8)
    keep = a.radii[0] > 0
    assert int(keep.sum()) > 200 and torch.equal(a.radii, b.radii)
    assert a.means2d.shape == (1, 300, 2) and a.means2d.is_leaf and (a.means2d == 0).all()
    assert a.means2d.grad is not None and float(a.means2d.grad[0][keep].abs().max()) > 0
    mv = a.extras["means2d_values"][0]
    torch.testing.assert_close(mv[keep] - 0.5, b.extras["means2d_values"][0][keep].detach(), atol=2e-5, rtol=0)
    # the torch backend returns the same carrier (so CPU and GPU 2DGS runs densify alike): its
    # gradient equals gsplat's v_densify = (dL/dM[0, 2], dL/dM[1, 2]) * z
    assert b.means2d.shape == (1, 300, 2) and b.means2d.is_leaf and (b.means2d == 0).all()
    ga, gb = a.means2d.grad[0][keep], b.means2d.grad[0][keep]
    assert float((gb - ga).norm() / ga.norm()) < 1e-4  # float32 summation order
    assert (b.means2d.grad[0][~keep] == 0).all()
    # and it is not the filter-only gradient of the projected centres (what it was before)
    filt = b.extras["means2d_values"].grad
    assert filt is None or float((filt[0][keep] - b.means2d.grad[0][keep]).abs().max()) > 1e-3
