"""2DGS (surfels) in the compiled CPU backend (egobench/render/cpu_backend_2dgs.py) against the torch
backend (the oracle): every output map (colour, alpha, depth, normal, distortion), radii, projected
centres, and the gradients of every input (Gaussian parameters, poses, gsplat's gradient_2dgs
carrier), on random scenes with edge cases, global and rolling shutter; finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from egobench.camera.pinhole import Pinhole
from egobench.render import render
from egobench.render.types import Gaussians
from tests.render.test_render import make_scene, pose
from tests.render.test_render_cpu import CAM, edge_case_scene, visited_pixels


def surfel_scene(seed: int, dtype=torch.float64) -> Gaussians:
    """`edge_case_scene` (behind, at the centre, near plane, off-screen, huge, flat/needle/point,
    opaque, transparent) plus surfels seen edge-on (normal perpendicular to the viewing ray: the
    ray-splat intersection degenerates) and nearly edge-on, and a 'needle' surfel (one axis ~0)."""
    g = edge_case_scene(seed, torch.float64)
    means, quats, ls = g.means.clone(), g.quats.clone(), g.log_scales.clone()
    for j in range(40, 46):  # rotate local z (the normal) to be perpendicular to the ray to the centre
        ray = means[j] / means[j].norm()
        side = torch.linalg.cross(ray, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        side = side / side.norm()
        normal = torch.linalg.cross(ray, side) if j < 43 else torch.linalg.cross(ray, side) + 0.05 * ray
        normal = normal / normal.norm()
        axis = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), normal)
        angle = math.acos(float(normal[2].clamp(-1, 1)))
        axis = axis / axis.norm()
        quats[j] = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), axis * math.sin(angle / 2)])
        ls[j, :2] = math.log(0.3)
    ls[46, 0] = -30.0  # needle surfel: one tangent axis ~0
    ls[16:30, :2] += math.log(2.0)  # opaque surfels large enough to stop pixels early (T <= 1e-4)
    out = Gaussians(means=means, quats=quats, log_scales=ls, opacity_logits=g.opacity_logits, colors=g.colors)
    return Gaussians(**{k: v.to(dtype) for k, v in out.tensors().items()})


def run2(g: Gaussians, cam: Pinhole, T: torch.Tensor, backend: str, weights_seed: int = 0, **kw):
    """Render 2DGS and backpropagate a random weighting of every output map (distortion included);
    -> (maps [..., 9], gradients (inputs, poses, gradient_2dgs carrier), output)."""
    inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    Tg = T.clone().requires_grad_(True)
    out = render(Gaussians(**inputs), cam, Tg, backend=backend, mode="2dgs", **kw)
    m = torch.cat([out.rgb, out.alpha, out.depth, out.normal, out.extras["distortion"]], -1)
    w = torch.randn(m.shape, generator=torch.Generator().manual_seed(weights_seed), dtype=torch.float64).to(m.dtype)
    ((m * w).sum() + (out.means2d * 0.0).sum()).backward()
    grads = {k: v.grad for k, v in inputs.items()}
    grads["T_world_camera"] = Tg.grad
    grads["gradient_2dgs"] = out.means2d.grad
    return m.detach(), grads, out


def assert_same(a, b, atol_map=1e-10, rtol=1e-8, atol_grad=1e-9):
    (ma, ga, oa), (mb, gb, ob) = a, b
    assert oa.extras["backend"] == "cpu" and ob.extras["backend"] == "torch"
    torch.testing.assert_close(ma, mb, atol=atol_map, rtol=rtol)
    torch.testing.assert_close(oa.radii, ob.radii, atol=0, rtol=0)
    torch.testing.assert_close(oa.extras["means2d_values"].detach(), ob.extras["means2d_values"].detach(),
                               atol=atol_map, rtol=rtol)
    for k in gb:
        assert ga[k] is not None and gb[k] is not None, k
        scale = float(gb[k].abs().max()) + 1.0
        torch.testing.assert_close(ga[k], gb[k], atol=atol_grad * scale, rtol=rtol, msg=lambda s, k=k: f"{k}: {s}")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_2dgs_matches_torch_backend(seed):
    g = surfel_scene(seed)
    T = pose(0.04, -0.03, (0.02, -0.01, 0.05))
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    cpu = run2(g, CAM, T, "cpu", seed, background=bg, tile_size=8)
    ref = run2(g, CAM, T, "torch", seed, background=bg, tile_size=8)
    alpha = cpu[2].alpha.detach()
    assert float(alpha.max()) > 0.999 and float(alpha.min()) < 0.5  # early-stopped and translucent pixels
    assert float(cpu[2].extras["distortion"].detach().abs().max()) > 1e-3  # the distortion term is exercised
    assert 0 < int((cpu[2].radii > 0).sum()) < g.means.shape[0]  # some surfels culled
    assert float(cpu[1]["gradient_2dgs"].abs().max()) > 0
    assert_same(cpu, ref)


@pytest.mark.parametrize("tile_size", [4, 16])
def test_2dgs_batch_of_poses_and_tile_sizes(tile_size):
    """2DGS results depend on the tile size only through rounding (tile-local coordinates)."""
    g = surfel_scene(3)
    Ts = torch.stack([pose(0.0, 0.0), pose(0.05, 0.02, (0.1, 0, 0)), pose(-0.03, 0.06, (0.0, 0.05, -0.1))])
    cpu = run2(g, CAM, Ts, "cpu", 1, tile_size=tile_size)
    ref = run2(g, CAM, Ts, "torch", 1, tile_size=tile_size)
    assert cpu[0].shape == (3, CAM.height, CAM.width, 9)
    assert_same(cpu, ref)


@pytest.mark.parametrize("index_kind", ["random", "bands"])
def test_2dgs_rolling_shutter_matches_torch_backend(index_kind):
    g = surfel_scene(4)
    K = 3
    Ts = torch.stack([pose(0.0, 0.02 * k, (0.01 * k, 0, 0)) for k in range(K)])
    H, W = CAM.height, CAM.width
    if index_kind == "random":
        idx = torch.randint(0, K, (H, W), generator=torch.Generator().manual_seed(1))
    else:  # rows ordered by readout, bands not aligned with tiles
        idx = torch.round(torch.arange(H) / (H - 1) * (K - 1)).long()[:, None].expand(H, W).contiguous()
    cpu = run2(g, CAM, Ts, "cpu", 2, pixel_pose_index=idx, tile_size=8)
    ref = run2(g, CAM, Ts, "torch", 2, pixel_pose_index=idx, tile_size=8)
    assert cpu[0].shape == (1, H, W, 9) and cpu[2].means2d.shape == (K, g.means.shape[0], 2)
    assert_same(cpu, ref)


def test_2dgs_gradcheck_against_finite_differences():
    """An independent check of the hand-written backward (projection, compositing, distortion)."""
    cam = Pinhole(fx=9.0, fy=9.0, cx=4.0, cy=3.5, width=9, height=8)
    g = make_scene(5, cam, 12, sigma_px=(1.0, 2.5), opacity_logit=0.0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    weights = torch.randn(1, 8, 9, 9, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(means, quats, log_scales, opacity_logits, colors, T):
        out = render(Gaussians(means, quats, log_scales, opacity_logits, colors), cam, T, background=bg,
                     backend="cpu", mode="2dgs", tile_size=4)
        maps = torch.cat([out.rgb, out.alpha, out.depth, out.normal, out.extras["distortion"]], -1)
        return (maps * weights).sum()

    inputs = tuple(t.clone().requires_grad_(True) for t in g.tensors().values()) + (pose(0.03, 0.02).requires_grad_(True),)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_2dgs_float32_matches_torch_backend_in_float32():
    """float32 is composited in float32 (as the torch backend and gsplat). Compared with the torch
    backend at the same precision: near-edge-on surfels make float32 and float64 disagree by design
    (the camera-facing sign of a normal perpendicular to the ray), in both backends alike. Scales of
    e^-30 (surfels 13-15, 46) overflow float32's intersection in both backends: left to float64."""
    keep = torch.ones(70, dtype=torch.bool)
    keep[[13, 14, 15, 46]] = False
    g32 = Gaussians(**{k: v.float() for k, v in surfel_scene(5).index(keep).tensors().items()})
    T = pose(0.01, 0.02).float()
    a = run2(g32, CAM, T, "cpu", 3, tile_size=16)
    b = run2(g32, CAM, T, "torch", 3, tile_size=16)
    assert a[0].dtype == torch.float32 and a[1]["means"].dtype == torch.float32
    torch.testing.assert_close(a[0], b[0], atol=2e-4, rtol=1e-4)
    for k in b[1]:
        scale = float(b[1][k].abs().max())
        torch.testing.assert_close(a[1][k], b[1][k], atol=1e-3 * scale, rtol=1e-3, msg=lambda s, k=k: f"{k}: {s}")


def test_2dgs_absgrad_matches_torch_backend():
    g = surfel_scene(6)
    outs = []
    for backend in ("cpu", "torch"):
        inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = render(Gaussians(**inputs), CAM, pose(0.02, 0.01), backend=backend, mode="2dgs", absgrad=True,
                     tile_size=8)
        (out.rgb.sum() * 0.5 + (out.rgb ** 2).sum()).backward()
        outs.append(out.extras["means2d_values"].absgrad)
    assert float(outs[0].abs().sum()) > 0
    torch.testing.assert_close(outs[0], outs[1], atol=1e-10, rtol=1e-8)


def test_2dgs_no_gradient_tracking_and_no_visible_surfel():
    g = make_scene(20, CAM, 10)
    out = render(g, CAM, pose(), backend="cpu", mode="2dgs")  # no grad: means2d is the plain centre
    ref = render(g, CAM, pose(), backend="torch", mode="2dgs", tile_size=16)
    assert out.extras["backend"] == "cpu" and "means2d_values" not in out.extras
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-10, rtol=1e-8)
    torch.testing.assert_close(out.means2d, ref.means2d, atol=1e-10, rtol=1e-8)
    behind = Gaussians(g.means * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), g.quats, g.log_scales,
                       g.opacity_logits, g.colors)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)
    m, grads, out = run2(behind, CAM, pose(), "cpu", 0, background=bg)
    assert bool((out.radii == 0).all()) and bool((out.alpha == 0).all())
    torch.testing.assert_close(out.rgb, bg.expand_as(out.rgb))
    for k in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert bool((grads[k] == 0).all()), k


def test_2dgs_pixel_bound_holds_every_visible_pixel():
    """The pixels a surfel's loop visits in a tile (`_footprint_surfel` narrowed per column group by
    `_surfel_band_rows`, both from `surfel_table`) contain every pixel where the exponent allows
    alpha > 1/255, computed independently per pixel from gsplat's formula; the footprint's branches
    (exact box, whole tile for discs crossing the camera plane) are exercised, and the bands cut rows."""
    import numpy as np

    from egobench.render import cpu_backend, cpu_backend_2dgs, cpu as ck
    from egobench.render.cpu import surfels
    from egobench.render import world_to_camera

    ts, n_checked, n_whole, n_cut = 16, 0, 0, 0
    cw, surfel_band_rows = ck.column_group(ts), surfels._surfel_band_rows
    for seed in range(3):
        g = surfel_scene(seed)
        lo = torch.nn.functional.logsigmoid(g.opacity_logits).numpy()
        m2, tsl, dep, _, rad = cpu_backend_2dgs._Project2DGS.apply(
            g.means, g.quats, g.scales, world_to_camera(pose(0.04, -0.03, (0.02, -0.01, 0.05))[None]),
            cpu_backend.camera_array(CAM), CAM.width, CAM.height)
        m2, tsl = m2.numpy(), tsl.numpy()
        tab = np.empty((m2.shape[1], ck.TAB_COLS), m2.dtype)
        surfels.surfel_table(m2, tsl, lo, np.ones(m2.shape[1], bool), tab)
        pix_view, need = cpu_backend.pixel_views(None, 1, CAM.height, CAM.width, ts)
        tiles_x = math.ceil(CAM.width / ts)
        flat, starts = ck.bin_tiles(m2, rad.numpy(), dep.numpy(), ts, tiles_x, need.shape[1] // tiles_x, need)
        for b in range(need.shape[1]):
            x0, y0 = (b % tiles_x) * ts, (b // tiles_x) * ts
            py, px = np.meshgrid(np.arange(y0, y0 + ts) + 0.5, np.arange(x0, x0 + ts) + 0.5, indexing="ij")
            for n in flat[starts[b]:starts[b + 1]]:
                U, V, Wr = tsl[0, n].astype(np.float64).reshape(3, 3)
                h_u = px[..., None] * Wr - U
                h_v = py[..., None] * Wr - V
                X, Y, Z = np.moveaxis(np.cross(h_u, h_v), -1, 0)
                with np.errstate(divide="ignore", invalid="ignore"):
                    g3 = np.where(Z != 0, (X * X + Y * Y) / (Z * Z), np.inf)
                g2 = 2.0 * ((px - m2[0, n, 0]) ** 2 + (py - m2[0, n, 1]) ** 2)
                reach = 0.5 * np.minimum(g3, g2) - lo[n] <= 5.55
                reach &= (py < CAM.height) & (px < CAM.width)
                ra, rb, ca, cb = surfels._footprint_surfel(tab, n, x0, y0, ts, CAM.width, CAM.height)
                band = lambda qa, qb, r0, r1: surfel_band_rows(tab, n, x0, y0, qa, qb, r0, r1)  # noqa: E731
                visited, cut = visited_pixels((ra, rb, ca, cb), band, reach.shape, cw)
                n_cut += cut
                assert not (reach & ~visited).any(), (seed, b, n)
                n_checked += int(reach.any())
                r2 = 2.0 * (ck.SIGMA_ROW + lo[n])  # the disc crosses the camera plane: whole tile
                whole = r2 > 0 and not (Wr[2] > 0 and r2 * (Wr[0] ** 2 + Wr[1] ** 2) < Wr[2] ** 2)
                n_whole += int(whole)
                if whole:
                    assert (ra, rb, ca, cb) == (0, min(ts, CAM.height - y0), 0, min(ts, CAM.width - x0))
    assert n_checked > 100 and n_whole > 0 and n_cut > 20


def test_2dgs_deterministic_across_threads(two_kernel_threads):
    """Parallel loops write disjoint slices and every sum is reduced in a fixed order: bit-identical
    outputs and gradients for 1 and 2 threads."""
    cam = Pinhole(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
    g = Gaussians(**{k: v.float() for k, v in make_scene(500, cam, 8).tensors().items()})
    before = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            results.append(run2(g, cam, pose(0.01, 0.0).float(), "cpu", 4))
    finally:
        torch.set_num_threads(before)
    for other in results[1:]:
        assert torch.equal(results[0][0], other[0])
        for k in results[0][1]:
            assert torch.equal(results[0][1][k], other[1][k]), k


def test_one_pass_feature_dot_is_the_per_channel_loops():
    """`ck.feature_dot` (seven channels in one pass) gives `feature_dot_channels`' sums (one pass
    per channel) bit for bit, float32 and float64, on every state range it is given."""
    import numpy as np

    from egobench.render import cpu as ck

    rng = np.random.default_rng(5)
    n_features = 7  # colour, depth, normal
    for dt in (np.float32, np.float64):
        gF = (rng.normal(size=(n_features + 2, 256)) * 10.0 ** rng.integers(-6, 6, size=(1, 256))).astype(dt)
        feats = rng.normal(size=(40, n_features)).astype(dt)
        for g, (pa, pb) in [(3, (0, 256)), (17, (40, 88)), (39, (128, 136)), (0, (8, 8))]:
            ref, one = np.full(256, 7.0, dt), np.full(256, 7.0, dt)
            ck.feature_dot_channels(ref, gF, feats, g, pa, pb, dt(0.0))
            ck.feature_dot(one, gF, feats, g, pa, pb, dt(0.0))
            np.testing.assert_array_equal(one, ref)
            seq = np.zeros(pb - pa, dt)  # numpy, channel by channel in the compute dtype
            for c in range(n_features):
                seq = seq + gF[c, pa:pb] * feats[g, c]
            np.testing.assert_array_equal(one[pa:pb], seq)
            assert (one[:pa] == 7.0).all() and (one[pb:] == 7.0).all()


def test_2dgs_outputs_no_loss_reads_get_zero_gradients():
    """With a loss on the colour only, autograd hands the rasterizer no gradient for depth, normal,
    transmittance and distortion (it does not materialise zeros); the backward must treat them as zeros:
    the gradients equal those of the same loss plus zero-weighted terms on every other output map."""
    g, T = surfel_scene(3), pose(0.03, -0.02)[None]
    w = torch.randn((1, CAM.height, CAM.width, 3), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = []
    for extra in (False, True):
        inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = render(Gaussians(**inputs), CAM, T, backend="cpu", mode="2dgs")
        loss = (out.rgb * w).sum()
        if extra:
            loss = loss + 0.0 * sum(m.sum() for m in (out.alpha, out.depth, out.normal, out.extras["distortion"]))
        loss.backward()
        grads.append({k: v.grad for k, v in inputs.items()})
    for k in grads[0]:
        assert torch.equal(grads[0][k], grads[1][k]), k
    assert float(grads[0]["means"].abs().sum()) > 0
