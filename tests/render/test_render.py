"""Tests of the torch rasterizer against independent oracles (egobench/render)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egobench.camera.pinhole import Pinhole
from egobench.render import render, render_rolling_shutter_reference
from egobench.render.torch_backend import project_2dgs, project_3dgs, gsplat_K
from egobench.render.types import Gaussians


# ----------------------------------------------------------------------------------------------
# scenes
# ----------------------------------------------------------------------------------------------


def make_scene(n: int, cam: Pinhole, seed: int, dtype=torch.float64, sigma_px=(1.0, 4.0), opacity_logit=1.0) -> Gaussians:
    """Random Gaussians in front of an identity camera, screen sizes of a few pixels."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g, dtype=torch.float64) * 3 + 1.5
    u = (torch.rand(n, generator=g, dtype=torch.float64) * 1.2 - 0.1) * cam.width
    v = (torch.rand(n, generator=g, dtype=torch.float64) * 1.2 - 0.1) * cam.height
    means = torch.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1)
    lo, hi = sigma_px
    s_px = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    scales = s_px * z[:, None] / cam.fx
    return Gaussians(
        means=means.to(dtype),
        quats=torch.randn(n, 4, generator=g, dtype=torch.float64).to(dtype),
        log_scales=scales.log().to(dtype),
        opacity_logits=(opacity_logit + torch.randn(n, generator=g, dtype=torch.float64)).to(dtype),
        colors=(torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.4 - 0.2).to(dtype),
    )


def pose(rx=0.0, ry=0.0, t=(0.0, 0.0, 0.0), dtype=torch.float64) -> torch.Tensor:
    """Camera-to-world pose from small rotations about x and y (radians)."""
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    Rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float64)
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = Ry @ Rx
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T.to(dtype)


CAM = Pinhole(fx=14.0, fy=15.0, cx=7.5, cy=5.5, width=16, height=12)


# ----------------------------------------------------------------------------------------------
# the per-pixel oracle, written directly from gsplat 1.5.3's CUDA rules (numpy float64, loops)
# ----------------------------------------------------------------------------------------------


def _rotmat(q):
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def oracle(g: Gaussians, cam: Pinhole, T_wc: torch.Tensor, mode="3dgs", bg=None, tile=16):
    """Slow reference: rgb [H, W, 3], alpha [H, W], depth [H, W], normal [H, W, 3], distortion [H, W]."""
    means = g.means.detach().numpy().astype(np.float64)
    quats = g.quats.detach().numpy().astype(np.float64)
    scales = np.exp(g.log_scales.detach().numpy().astype(np.float64))
    opac = 1 / (1 + np.exp(-g.opacity_logits.detach().numpy().astype(np.float64)))
    cols = g.colors.detach().numpy().astype(np.float64)
    Twc = T_wc.detach().numpy().astype(np.float64)
    Rcw = Twc[:3, :3].T
    tcw = -Rcw @ Twc[:3, 3]
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5
    W, H = cam.width, cam.height
    tiles_x = math.ceil(W / tile)
    items = []  # (depth, idx, params)
    for i in range(len(means)):
        mc = Rcw @ means[i] + tcw
        z = mc[2]
        R = Rcw @ _rotmat(quats[i])
        if mode == "3dgs":
            if z < 0.01 or z > 1e10:
                continue
            cov = R @ np.diag(scales[i] ** 2) @ R.T
            lxp = (W - cx) / fx + 0.3 * 0.5 * W / fx
            lxn = cx / fx + 0.3 * 0.5 * W / fx
            lyp = (H - cy) / fy + 0.3 * 0.5 * H / fy
            lyn = cy / fy + 0.3 * 0.5 * H / fy
            tx = z * min(lxp, max(-lxn, mc[0] / z))
            ty = z * min(lyp, max(-lyn, mc[1] / z))
            J = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
            c2 = J @ cov @ J.T + 0.3 * np.eye(2)
            det = np.linalg.det(c2)
            if det <= 0 or opac[i] < 1 / 255:
                continue
            ext = min(3.33, math.sqrt(2 * math.log(opac[i] * 255)))
            rx, ry = math.ceil(ext * math.sqrt(c2[0, 0])), math.ceil(ext * math.sqrt(c2[1, 1]))
            mx, my = fx * mc[0] / z + cx, fy * mc[1] / z + cy
            conic = np.linalg.inv(c2)
            n = R[:, int(np.argmin(scales[i]))]
            extra = conic
        else:
            if z <= 0.01 or z >= 1e10:
                continue
            Kg = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
            Tsl = Kg @ np.stack([R[:, 0] * scales[i, 0], R[:, 1] * scales[i, 1], mc], axis=1)
            d = Tsl[2, 0] ** 2 + Tsl[2, 1] ** 2 - Tsl[2, 2] ** 2
            if d == 0:
                continue
            f = np.array([1, 1, -1]) / d
            mx = (Tsl[0] * Tsl[2] * f).sum()
            my = (Tsl[1] * Tsl[2] * f).sum()
            ex = math.sqrt(max(1e-4, mx * mx - (Tsl[0] ** 2 * f).sum()))
            ey = math.sqrt(max(1e-4, my * my - (Tsl[1] ** 2 * f).sum()))
            rx, ry = math.ceil(3.33 * ex), math.ceil(3.33 * ey)
            n = R[:, 2]
            extra = Tsl
        if mx + rx <= 0 or mx - rx >= W or my + ry <= 0 or my - ry >= H:
            continue
        if n @ mc > 0:
            n = -n
        tmin = (max(0, math.floor(mx / tile - rx / tile)), max(0, math.floor(my / tile - ry / tile)))
        tmax = (math.ceil(mx / tile + rx / tile), math.ceil(my / tile + ry / tile))
        items.append((z, i, mx, my, extra, n, tmin, tmax))
    items.sort(key=lambda it: (it[0], it[1]))
    rgb = np.zeros((H, W, 3)); alpha = np.zeros((H, W)); depth = np.zeros((H, W))
    normal = np.zeros((H, W, 3)); dist = np.zeros((H, W))
    for v in range(H):
        for u in range(W):
            px, py = u + 0.5, v + 0.5
            ttx, tty = u // tile, v // tile
            T = 1.0
            acc = np.zeros(3); accz = 0.0; accn = np.zeros(3); dis = 0.0; avz = 0.0
            for z, i, mx, my, extra, n, tmin, tmax in items:
                if not (tmin[0] <= ttx < tmax[0] and tmin[1] <= tty < tmax[1]):
                    continue
                if mode == "3dgs":
                    dx, dy = mx - px, my - py
                    a, b, c = extra[0, 0], extra[0, 1], extra[1, 1]
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                else:
                    Tsl = extra
                    hu = px * Tsl[2] - Tsl[0]
                    hv = py * Tsl[2] - Tsl[1]
                    cr = np.cross(hu, hv)
                    if cr[2] == 0:
                        continue
                    g3 = (cr[0] / cr[2]) ** 2 + (cr[1] / cr[2]) ** 2
                    g2 = 2.0 * ((mx - px) ** 2 + (my - py) ** 2)
                    sigma = 0.5 * min(g3, g2)
                al = min(0.999, opac[i] * math.exp(-sigma))
                if sigma < 0 or al < 1 / 255:
                    continue
                if T * (1 - al) <= 1e-4:
                    break
                vis = al * T
                acc += vis * cols[i]; accz += vis * z; accn += vis * n
                dis += 2 * (vis * z * (1 - T) - vis * avz); avz += vis * z
                T *= 1 - al
            rgb[v, u] = acc + (0 if bg is None else T * bg)
            alpha[v, u] = 1 - T
            depth[v, u] = accz / max(1 - T, 1e-10)
            normal[v, u] = accn
            dist[v, u] = dis
    return rgb, alpha, depth, normal, dist


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_per_pixel_oracle(mode, seed):
    g = make_scene(30 if mode == "3dgs" else 60, CAM, seed, opacity_logit=2.0)
    T = pose(0.05, -0.04, (0.02, -0.01, 0.1))
    bg = np.array([0.2, 0.5, 0.9])
    out = render(g, CAM, T, mode=mode, background=torch.tensor(bg), backend="torch", want_normal=True, tile_size=8)
    rgb, alpha, depth, normal, dist = oracle(g, CAM, T, mode=mode, bg=bg, tile=8)
    assert alpha.max() > 0.999 and alpha.min() < 0.95  # opaque (early stop) and translucent pixels
    np.testing.assert_allclose(out.rgb[0].numpy(), rgb, atol=1e-6)
    np.testing.assert_allclose(out.alpha[0, ..., 0].numpy(), alpha, atol=1e-6)
    np.testing.assert_allclose(out.depth[0, ..., 0].numpy(), depth, atol=1e-6)
    np.testing.assert_allclose(out.normal[0].numpy(), normal, atol=1e-6)
    if mode == "2dgs":
        np.testing.assert_allclose(out.extras["distortion"][0, ..., 0].numpy(), dist, atol=1e-6)


def test_early_stop_rule_is_exclusive():
    """Three identical opaque Gaussians at one pixel: alpha 0.999 each -> only the first counts."""
    cam = Pinhole(fx=10, fy=10, cx=1.0, cy=1.0, width=3, height=3)  # pixel (1, 1) on the axis
    n = 3
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]], dtype=torch.float64),
        quats=torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
        log_scales=torch.full((n, 3), math.log(0.5), dtype=torch.float64),
        opacity_logits=torch.full((n,), 20.0, dtype=torch.float64),
        colors=torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], dtype=torch.float64),
    )
    out = render(g, cam, torch.eye(4, dtype=torch.float64), backend="torch")
    # T after the first = 0.001 > 1e-4; the second would give 1e-6 -> stops, not composited
    np.testing.assert_allclose(out.alpha[0, 1, 1, 0].item(), 0.999, atol=1e-9)
    np.testing.assert_allclose(out.rgb[0, 1, 1].numpy(), [0.999, 0, 0], atol=1e-9)
    np.testing.assert_allclose(out.depth[0, 1, 1, 0].item(), 2.0, atol=1e-9)


def test_tile_size_does_not_change_3dgs():
    g = make_scene(40, CAM, 3)
    T = pose(0.02, 0.03)
    a = render(g, CAM, T, backend="torch", tile_size=16)
    b = render(g, CAM, T, backend="torch", tile_size=4)
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-10, rtol=0)
    torch.testing.assert_close(a.depth, b.depth, atol=1e-10, rtol=0)


def test_batch_equals_single_renders():
    g = make_scene(25, CAM, 4)
    Ts = torch.stack([pose(0.0, 0.0), pose(0.05, 0.02, (0.1, 0, 0))])
    out = render(g, CAM, Ts, backend="torch")
    for b in range(2):
        single = render(g, CAM, Ts[b], backend="torch")
        torch.testing.assert_close(out.rgb[b], single.rgb[0], atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------------------------
# projection against gsplat's pure-torch reference
# ----------------------------------------------------------------------------------------------


def test_projection_matches_gsplat_torch_impl():
    pytest.importorskip("packaging", reason="gsplat's torch reference imports packaging")
    impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat not installed")
    g = make_scene(50, CAM, 5)
    T = pose(0.1, -0.2, (0.05, 0.0, -0.2))
    viewmat = torch.linalg.inv(T)[None]
    K = gsplat_K(CAM, torch.float64, "cpu")
    scales = g.log_scales.exp()
    ours = project_3dgs(g.means, g.quats, scales, viewmat, K, CAM.width, CAM.height)
    covars, _ = impl._quat_scale_to_covar_preci(g.quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = impl._fully_fused_projection(g.means, covars, viewmat, K[None], CAM.width, CAM.height)
    keep = radii[0].amin(-1) > 0
    assert keep.sum() > 20
    torch.testing.assert_close(ours.radii[0], radii[0].to(torch.int32))
    torch.testing.assert_close(ours.means2d[0][keep], means2d[0][keep], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ours.depths[0][keep], depths[0][keep], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ours.conics[0][keep], conics[0][keep], rtol=1e-10, atol=1e-10)


def test_projection_2dgs_matches_gsplat_torch_impl():
    pytest.importorskip("packaging", reason="gsplat's torch reference imports packaging")
    impl = pytest.importorskip("gsplat.cuda._torch_impl_2dgs", reason="gsplat not installed")
    g = make_scene(50, CAM, 6)
    T = pose(-0.1, 0.15, (0.0, 0.05, -0.1))
    viewmat = torch.linalg.inv(T)[None]
    K = gsplat_K(CAM, torch.float64, "cpu")
    scales = g.log_scales.exp()
    ours = project_2dgs(g.means, g.quats, scales, viewmat, K, CAM.width, CAM.height)
    radii, means2d, depths, M, normals = impl._fully_fused_projection_2dgs(
        g.means, g.quats, scales, viewmat, K[None], CAM.width, CAM.height)
    keep = radii[0].amin(-1) > 0
    assert keep.sum() > 20
    torch.testing.assert_close(ours.radii[0], radii[0].to(torch.int32))
    torch.testing.assert_close(ours.means2d[0][keep], means2d[0][keep], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ours.ray_transforms[0][keep], M[0][keep], rtol=1e-10, atol=1e-10)
    # gsplat's torch reference keeps scale 3 in the normal; its CUDA kernel (and we) use the unit axis
    torch.testing.assert_close(ours.normals[0][keep], torch.nn.functional.normalize(normals[0][keep], dim=-1),
                               rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_gradcheck_full_render(mode):
    cam = Pinhole(fx=9.0, fy=9.0, cx=4.0, cy=3.5, width=9, height=8)
    g = make_scene(5, cam, 11, sigma_px=(1.0, 2.5), opacity_logit=0.0)
    T = pose(0.03, 0.02)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    weights = torch.randn(1, 8, 9, 11, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(means, quats, log_scales, opacity_logits, colors):
        gg = Gaussians(means, quats, log_scales, opacity_logits, colors)
        out = render(gg, cam, T, mode=mode, background=bg, backend="torch", want_normal=True, tile_size=4)
        maps = [out.rgb, out.alpha, out.depth, out.normal]
        if mode == "2dgs":
            maps.append(out.extras["distortion"])
        return (torch.cat(maps, -1) * weights[..., : sum(m.shape[-1] for m in maps)]).sum()

    inputs = tuple(t.clone().requires_grad_(True) for t in g.tensors().values())
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_backward_recompute_equals_stored(mode, monkeypatch):
    """The compositing backward replays the forward's chunks when they fit in memory and
    recomputes them otherwise: both must give the same gradients (multi-chunk, early-stopping bins)."""
    from egobench.render import torch_composite

    cam = Pinhole(fx=20.0, fy=20.0, cx=15.5, cy=9.5, width=32, height=20)
    g = make_scene(400, cam, 5, sigma_px=(1.0, 3.0), opacity_logit=2.0)
    w = torch.randn(1, 20, 32, 11, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def run():
        inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = render(Gaussians(**inputs), cam, torch.eye(4, dtype=torch.float64), mode=mode, backend="torch",
                     want_normal=True, tile_size=8)
        maps = [out.rgb, out.alpha, out.depth, out.normal]
        if mode == "2dgs":
            maps.append(out.extras["distortion"])
        m = torch.cat(maps, -1)
        (m * w[..., : m.shape[-1]]).sum().backward()
        return m.detach(), {k: v.grad for k, v in inputs.items()}

    stored = run()
    monkeypatch.setattr(torch_composite, "_store_fits", lambda plan: False)
    recomputed = run()
    torch.testing.assert_close(stored[0], recomputed[0], atol=0, rtol=0)
    for k in stored[1]:
        torch.testing.assert_close(stored[1][k], recomputed[1][k], atol=1e-12, rtol=1e-12)


def test_stable_argsort_matches_torch_sort():
    """The CPU radix argsort used for tile binning equals torch's stable sort, ties included."""
    from egobench.render.torch_backend import _stable_argsort

    g = torch.Generator().manual_seed(3)
    for dtype in (torch.float32, torch.float64):
        v = (torch.rand(5000, generator=g, dtype=torch.float64) * 50 + 1e-3).to(dtype)
        v[::7] = v[3]  # ties must keep index order
        v[1::11] = torch.tensor(1e-30, dtype=dtype)
        assert torch.equal(_stable_argsort(v), torch.sort(v, stable=True).indices)
    b = torch.randint(0, 1 << 16, (7000,), generator=g)
    assert torch.equal(_stable_argsort(b), torch.sort(b, stable=True).indices)
    assert _stable_argsort(torch.zeros(0)).numel() == 0


# ----------------------------------------------------------------------------------------------
# rolling shutter
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode,index_kind", [("3dgs", "random"), ("2dgs", "random"), ("3dgs", "bands"), ("3dgs", "columns")])
def test_rolling_shutter_equals_reference(mode, index_kind):
    cam = Pinhole(fx=20.0, fy=20.0, cx=15.5, cy=9.5, width=32, height=20)
    g = make_scene(60, cam, 7, dtype=torch.float64)
    Ts = torch.stack([pose(0.0, 0.01 * k, (0.01 * k, 0, 0)) for k in range(3)])
    if index_kind == "random":
        idx = torch.randint(0, 3, (20, 32), generator=torch.Generator().manual_seed(1))
    elif index_kind == "bands":  # R(u)-ordered rows: contiguous bands not aligned with tiles
        idx = torch.round(torch.arange(20) / 19 * 2).long()[:, None].expand(20, 32).contiguous()
    else:  # a rotated sensor: bands of columns
        idx = torch.round(torch.arange(32) / 31 * 2).long()[None, :].expand(20, 32).contiguous()
    w = torch.randn(1, 20, 32, 3, dtype=torch.float64)

    def run(fn):
        inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = fn(Gaussians(**inputs), cam, Ts, pixel_pose_index=idx, mode=mode, backend="torch", tile_size=8)
        loss = (out.rgb * w).sum() + out.depth.sum() + out.alpha.sum()
        loss.backward()
        return out, {k: v.grad for k, v in inputs.items()}

    a, ga = run(render)
    b, gb = run(render_rolling_shutter_reference)
    assert a.rgb.shape == (1, 20, 32, 3)
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-10, rtol=0)
    torch.testing.assert_close(a.depth, b.depth, atol=1e-10, rtol=0)
    torch.testing.assert_close(a.alpha, b.alpha, atol=1e-10, rtol=0)
    for k in ga:
        torch.testing.assert_close(ga[k], gb[k], atol=1e-9, rtol=1e-7)


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_error():
    g = make_scene(5, CAM, 0)
    T = torch.eye(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="T_world_camera"):
        render(g, CAM, torch.eye(3, dtype=torch.float64))
    bad = T.clone(); bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="T_world_camera"):
        render(g, CAM, bad)
    m = g.means.clone(); m[0, 0] = float("inf")
    with pytest.raises(ValueError, match="means"):
        render(Gaussians(m, g.quats, g.log_scales, g.opacity_logits, g.colors), CAM, T)
    q = g.quats.clone(); q[1] = 0
    with pytest.raises(ValueError, match="quats"):
        render(Gaussians(g.means, q, g.log_scales, g.opacity_logits, g.colors), CAM, T)
    with pytest.raises(ValueError, match="colors"):
        render(Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors[:, :2]), CAM, T)
    with pytest.raises(ValueError, match="pixel_pose_index"):
        render(g, CAM, T, pixel_pose_index=torch.zeros(3, 3, dtype=torch.long))
    with pytest.raises(ValueError, match="pixel_pose_index"):
        render(g, CAM, T[None].repeat(2, 1, 1), pixel_pose_index=torch.full((12, 16), 2))
    with pytest.raises(ValueError, match="mode"):
        render(g, CAM, T, mode="nerf")
    with pytest.raises(ValueError, match="background"):
        render(g, CAM, T, background=torch.zeros(4, dtype=torch.float64))


def test_no_nan_with_gaussians_behind_and_at_camera():
    g = make_scene(20, CAM, 9)
    means = g.means.clone()
    means[:5, 2] = -means[:5, 2]  # behind
    means[5, :] = 0.0  # at the camera centre
    gg = Gaussians(means.requires_grad_(True), g.quats, g.log_scales, g.opacity_logits, g.colors)
    out = render(gg, CAM, torch.eye(4, dtype=torch.float64), backend="torch")
    (out.rgb.sum() + out.depth.sum()).backward()
    assert torch.isfinite(out.rgb).all() and torch.isfinite(gg.means.grad).all()


def test_means2d_grad_and_absgrad():
    g = make_scene(30, CAM, 12, dtype=torch.float32)
    inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    out = render(Gaussians(**inputs), CAM, torch.eye(4), backend="torch", absgrad=True, tile_size=8)
    assert out.means2d.shape == (1, 30, 2) and out.radii.shape == (1, 30)
    # egobench pixel convention: a Gaussian on the optical axis projects to (cx, cy)
    (out.rgb.sum() * 0.5 + (out.rgb**2).sum()).backward()
    grad, absgrad = out.means2d.grad, out.means2d.absgrad
    visible = out.radii[0] > 0
    assert grad is not None and torch.isfinite(grad).all()
    assert float(grad[0][visible].abs().sum()) > 0 and float(grad[0][~visible].abs().sum()) == 0
    assert bool((absgrad >= grad.abs() - 1e-6).all())  # per-tile absolute values bound the sum
    m = torch.tensor([[0.0, 0.0, 2.0]])
    one = Gaussians(m, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), -3.0), torch.zeros(1), torch.ones(1, 3))
    torch.testing.assert_close(render(one, CAM, torch.eye(4), backend="torch").means2d[0, 0],
                               torch.tensor([CAM.cx, CAM.cy]))


def test_resolve_backend_rules(monkeypatch):
    import egobench.render as R

    assert R.resolve_backend("auto", "cpu") == "cpu" and R.resolve_backend("torch", "cpu") == "torch"  # numba loads here
    with pytest.raises(ValueError, match="needs CUDA"):
        R.resolve_backend("gsplat", "cpu")
    with pytest.raises(ValueError, match="backend must be"):
        R.resolve_backend("cuda", "cpu")
    # on CUDA, auto follows whether gsplat's extension loads
    monkeypatch.setattr(R, "gsplat_cuda_available", lambda: True)
    assert R.resolve_backend("auto", "cuda") == "gsplat" and R.resolve_backend("torch", "cuda") == "torch"
    monkeypatch.setattr(R, "gsplat_cuda_available", lambda: False)
    assert R.resolve_backend("auto", "cuda") == "torch"
