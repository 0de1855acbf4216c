"""The compiled CPU backend (egobench/render/cpu_backend.py) against the torch backend (the oracle,
itself checked against a per-pixel gsplat oracle in test_render.py): outputs and gradients of every
input, on random scenes with edge cases, global and rolling shutter; determinism; fallbacks."""

from __future__ import annotations

import math
import re
import sys

import numpy as np
import pytest
import torch

from egobench.camera.pinhole import Pinhole
from egobench.render import render, resolve_backend
from egobench.render.types import Gaussians
from tests import background
from tests.render.test_render import make_scene, pose

CAM = Pinhole(fx=20.0, fy=21.0, cx=17.3, cy=10.6, width=37, height=22)  # partial tiles at 8 and 16
NAMES = ("means", "quats", "log_scales", "opacity_logits", "colors")


def edge_case_scene(seed: int, dtype=torch.float64) -> Gaussians:
    """Random Gaussians plus: behind the camera, at the camera centre, on the near plane, off-screen
    beyond the border, huge (covering the image), degenerate (flat / needle / point-like), opaque
    (alpha at the 0.999 clamp, early stop), nearly transparent (opacity < 1/255)."""
    g = make_scene(70, CAM, seed, dtype=torch.float64, sigma_px=(0.5, 4.0), opacity_logit=0.5)
    means, ls, ol = g.means.clone(), g.log_scales.clone(), g.opacity_logits.clone()
    means[0:4, 2] = -means[0:4, 2]  # behind
    means[4] = 0.0  # at the camera centre
    means[5, 2] = 0.0100001  # just beyond the near plane
    means[6:9, 0] = means[6:9, 2] * 1.2  # off-screen to the right (still within the Jacobian clamp)
    means[9:11, 1] = -means[9:11, 2] * 3.0  # far off-screen: clamp of the EWA Jacobian
    ls[11:13] = math.log(1.5)  # huge: sigma of 10-20 pixels, the whole image
    ol[11:13] = -3.0
    ls[13, 2] = -30.0  # flat
    ls[14, 1:] = -30.0  # needle
    ls[15] = -30.0  # point-like: only the eps2d dilation remains
    ol[16:30] = 12.0  # opaque: alpha clamps at 0.999, pixels stop early
    ol[30:34] = -7.0  # below 1/255: culled by the opacity-aware radius
    out = Gaussians(means=means, quats=g.quats, log_scales=ls, opacity_logits=ol, colors=g.colors)
    return Gaussians(**{k: v.to(dtype) for k, v in out.tensors().items()})


def run(g: Gaussians, cam: Pinhole, T: torch.Tensor, backend: str, weights_seed: int = 0, **kw):
    """Render, backpropagate a random weighting of every output map; -> (maps, gradients, output)."""
    inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    Tg = T.clone().requires_grad_(True)
    out = render(Gaussians(**inputs), cam, Tg, backend=backend, **kw)
    maps = [out.rgb, out.alpha, out.depth] + ([out.normal] if out.normal is not None else [])
    m = torch.cat(maps, -1)
    w = torch.randn(m.shape, generator=torch.Generator().manual_seed(weights_seed), dtype=torch.float64).to(m.dtype)
    loss = (m * w).sum() + (out.means2d * 0.0).sum()
    loss.backward()
    grads = {k: v.grad for k, v in inputs.items()}
    grads["T_world_camera"] = Tg.grad
    grads["means2d"] = out.means2d.grad
    return m.detach(), grads, out


def assert_same(a, b, atol_map=1e-10, rtol=1e-8, atol_grad=1e-9):
    (ma, ga, oa), (mb, gb, ob) = a, b
    torch.testing.assert_close(ma, mb, atol=atol_map, rtol=rtol)
    torch.testing.assert_close(oa.radii, ob.radii, atol=0, rtol=0)
    torch.testing.assert_close(oa.means2d.detach(), ob.means2d.detach(), atol=atol_map, rtol=rtol)
    for k in ga:
        assert ga[k] is not None and gb[k] is not None, k
        scale = float(gb[k].abs().max()) + 1.0
        torch.testing.assert_close(ga[k], gb[k], atol=atol_grad * scale, rtol=rtol, msg=lambda s, k=k: f"{k}: {s}")


BACKGROUND = {"test_3dgs_matches_torch_backend": background.compile_kernels("float64", ("3dgs", "2dgs"))}


@pytest.fixture(autouse=True, scope="module")
def _float64_kernels_cached():
    """This module's tests (float64) start once a background job has the float64 kernels in numba's
    cache, so that they load them rather than compile them on this core."""
    background.wait_for_kernels(sys.modules[__name__], "test_3dgs_matches_torch_backend")


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("want_normal", [False, True])
def test_3dgs_matches_torch_backend(seed, want_normal):
    g = edge_case_scene(seed)
    T = pose(0.04, -0.03, (0.02, -0.01, 0.05))
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    kw = dict(background=bg, want_normal=want_normal, tile_size=8)
    cpu = run(g, CAM, T, "cpu", seed, **kw)
    ref = run(g, CAM, T, "torch", seed, **kw)
    assert cpu[2].extras["backend"] == "cpu" and ref[2].extras["backend"] == "torch"
    alpha = cpu[2].alpha.detach()
    assert float(alpha.max()) > 0.999 and float(alpha.min()) < 0.5  # early-stopped and translucent pixels
    assert int((cpu[2].radii > 0).sum()) < g.means.shape[0]  # some Gaussians culled
    assert_same(cpu, ref)


@pytest.mark.parametrize("tile_size", [4, 16, 32])
def test_batch_of_poses_and_tile_sizes(tile_size):
    g = edge_case_scene(3)
    Ts = torch.stack([pose(0.0, 0.0), pose(0.05, 0.02, (0.1, 0, 0)), pose(-0.03, 0.06, (0.0, 0.05, -0.1))])
    cpu = run(g, CAM, Ts, "cpu", 1, tile_size=tile_size, want_normal=True)
    ref = run(g, CAM, Ts, "torch", 1, tile_size=8, want_normal=True)  # 3DGS results do not depend on tiles
    assert cpu[0].shape == (3, CAM.height, CAM.width, 8)
    assert_same(cpu, ref)


@pytest.mark.parametrize("index_kind", ["random", "bands", "columns"])
def test_rolling_shutter_matches_torch_backend(index_kind):
    g = edge_case_scene(4)
    K = 3
    Ts = torch.stack([pose(0.0, 0.02 * k, (0.01 * k, 0, 0)) for k in range(K)])
    H, W = CAM.height, CAM.width
    if index_kind == "random":
        idx = torch.randint(0, K, (H, W), generator=torch.Generator().manual_seed(1))
    elif index_kind == "bands":  # rows ordered by readout, bands not aligned with tiles
        idx = torch.round(torch.arange(H) / (H - 1) * (K - 1)).long()[:, None].expand(H, W).contiguous()
    else:
        idx = torch.round(torch.arange(W) / (W - 1) * (K - 1)).long()[None, :].expand(H, W).contiguous()
    cpu = run(g, CAM, Ts, "cpu", 2, pixel_pose_index=idx, tile_size=16)
    ref = run(g, CAM, Ts, "torch", 2, pixel_pose_index=idx, tile_size=8)
    assert cpu[0].shape == (1, H, W, 5) and cpu[2].means2d.shape == (K, g.means.shape[0], 2)
    assert_same(cpu, ref)


def test_gradcheck_against_finite_differences():
    """An independent check of the hand-written backward (projection and compositing)."""
    cam = Pinhole(fx=9.0, fy=9.0, cx=4.0, cy=3.5, width=9, height=8)
    g = make_scene(5, cam, 11, sigma_px=(1.0, 2.5), opacity_logit=0.0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    weights = torch.randn(1, 8, 9, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(means, quats, log_scales, opacity_logits, colors, T):
        out = render(Gaussians(means, quats, log_scales, opacity_logits, colors), cam, T, background=bg,
                     backend="cpu", want_normal=True, tile_size=4)
        return (torch.cat([out.rgb, out.alpha, out.depth, out.normal], -1) * weights).sum()

    inputs = tuple(t.clone().requires_grad_(True) for t in g.tensors().values()) + (pose(0.03, 0.02).requires_grad_(True),)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_float32_close_to_float64_oracle():
    g64 = edge_case_scene(5)
    g32 = Gaussians(**{k: v.float() for k, v in g64.tensors().items()})
    T = pose(0.01, 0.02)
    a = run(g32, CAM, T.float(), "cpu", 3, tile_size=16)
    b = run(g64, CAM, T, "torch", 3, tile_size=8)
    assert a[0].dtype == torch.float32 and a[1]["means"].dtype == torch.float32
    torch.testing.assert_close(a[0].double(), b[0], atol=2e-4, rtol=1e-4)
    for k in ("colors", "opacity_logits", "means2d"):
        scale = float(b[1][k].abs().max())
        torch.testing.assert_close(a[1][k].double(), b[1][k], atol=2e-4 * scale, rtol=1e-3)


def test_absgrad_matches_torch_backend_at_equal_tile_size():
    g = edge_case_scene(6)
    T = pose(0.02, 0.01)
    outs = []
    for backend in ("cpu", "torch"):
        inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = render(Gaussians(**inputs), CAM, T, backend=backend, absgrad=True, tile_size=8)
        (out.rgb.sum() * 0.5 + (out.rgb ** 2).sum()).backward()
        outs.append(out.means2d.absgrad)
    assert float(outs[0].abs().sum()) > 0
    torch.testing.assert_close(outs[0], outs[1], atol=1e-10, rtol=1e-8)


def test_deterministic_across_runs_and_threads(two_kernel_threads):
    g = Gaussians(**{k: v.float() for k, v in make_scene(3000, Pinhole(fx=60.0, fy=60.0, cx=63.5, cy=47.5, width=128,
                                                                             height=96), 8).tensors().items()})
    cam = Pinhole(fx=60.0, fy=60.0, cx=63.5, cy=47.5, width=128, height=96)
    T = pose(0.01, 0.0).float()
    before = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            results.append(run(g, cam, T, "cpu", 4))
    finally:
        torch.set_num_threads(before)
    for other in results[1:]:
        assert torch.equal(results[0][0], other[0])
        for k in results[0][1]:
            assert torch.equal(results[0][1][k], other[1][k]), k


def test_other_dtypes_are_handed_to_torch_backend_explicitly():
    g = Gaussians(**{k: v.to(torch.bfloat16) for k, v in make_scene(20, CAM, 2).tensors().items()})
    a = render(g, CAM, pose(), backend="cpu")
    b = render(g, CAM, pose(), backend="torch")
    assert a.extras["backend"] == "torch" and "bfloat16" in a.extras["cpu_fallback"]
    torch.testing.assert_close(a.rgb, b.rgb, atol=0, rtol=0)


def test_backend_choice_and_fallback(monkeypatch, capsys):
    from egobench.render import cpu_backend

    assert resolve_backend("auto", "cpu") == "cpu" and resolve_backend("cpu", "cpu") == "cpu"
    with pytest.raises(ValueError, match="needs CPU tensors"):
        resolve_backend("cpu", "cuda")
    monkeypatch.setattr(cpu_backend, "load_error", lambda: "ImportError: No module named 'numba'")
    cpu_backend.warn_fallback.cache_clear()
    assert resolve_backend("auto", "cpu") == "torch" and resolve_backend("cpu", "cpu") == "torch"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No module named 'numba'" in err[0] and "torch backend" in err[0]
    g = make_scene(10, CAM, 1)
    assert render(g, CAM, pose(), backend="cpu").extras["backend"] == "torch"


def test_no_visible_gaussian_gives_background_and_zero_gradients():
    g = make_scene(20, CAM, 10)
    g = Gaussians(g.means * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), g.quats, g.log_scales,
                  g.opacity_logits, g.colors)  # all behind the camera
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)
    m, grads, out = run(g, CAM, pose(), "cpu", 0, background=bg)
    assert bool((out.radii == 0).all()) and bool((out.alpha == 0).all())
    torch.testing.assert_close(out.rgb, bg.expand_as(out.rgb))
    for k in NAMES:
        assert bool((grads[k] == 0).all()), k


#: a child process as a Snakemake job runs: the entry point's thread set-up, one render, then its thread counts
THREADS_CHILD = ("from egobench.host import setup_threads\n"
                 "setup_threads()\n"  # what an entry point (the CLI a Snakemake job runs) does first
                 "import torch\n"
                 "from egobench.render import render\n"
                 "from tests.render.test_render_cpu import make_scene, CAM, pose\n"
                 "out = render(make_scene(20, CAM, 0), CAM, pose(), backend='cpu')\n"
                 "import numba\n"
                 "print(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS, numba.get_num_threads())\n")


def _thread_counts(env: dict) -> list[str]:
    """`THREADS_CHILD` under ``env`` -> [torch threads, numba's pool size, numba's threads]."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(env, PYTHONPATH=root + os.pathsep + env.get("PYTHONPATH", ""))
    res = subprocess.run([sys.executable, "-c", THREADS_CHILD], env=env, cwd=root, capture_output=True, text=True,
                         check=True)
    return res.stdout.split()


def test_one_thread_per_worker_from_omp_num_threads():
    """Snakemake exports OMP_NUM_THREADS={threads} to each job: torch and the compiled kernels
    then use that many threads (numba's pool is capped by the entry point's `setup_threads`, its count
    follows torch)."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    assert _thread_counts(dict(env, OMP_NUM_THREADS="1")) == ["1", "1", "1"]


def visited_pixels(box, band_rows, shape, cw):
    """The tile pixels a compositing loop visits [ts, ts] bool: the box (rows ra:rb, columns ca:cb)
    narrowed per column group of cw by band_rows(qa, qb, ra, rb) -> (mask, groups whose rows were cut)."""
    import numpy as np

    ra, rb, ca, cb = box
    visited, n_cut = np.zeros(shape, dtype=bool), 0
    for q in range(ca // cw, (cb - 1) // cw + 1 if cb > ca else 0):
        qa, qb = max(ca, q * cw), min(cb, q * cw + cw)
        qra, qrb = band_rows(qa, qb, ra, rb)
        visited[qra:qrb, qa:qb] = True
        n_cut += int(qrb - qra < rb - ra)
    return visited, n_cut


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_band_rows_hold_every_visible_pixel(dtype):
    """The rows the compositing loops visit per 8-column group (`_footprint_tab` narrowed by
    `band_rows`, from `gaussian_table`) contain every pixel whose exponent allows alpha > 1/255,
    computed independently per pixel in float64; the band must also cut rows somewhere (else the
    test would not exercise it)."""
    import numpy as np

    from egobench.render import world_to_camera, cpu_backend, cpu as ck

    ts, cw, n_checked, n_cut = 16, ck.column_group(16), 0, 0
    for seed in range(3):
        g = edge_case_scene(seed, dtype)
        lo = torch.nn.functional.logsigmoid(g.opacity_logits).numpy()
        m2, con, dep, _, rad = cpu_backend._Project.apply(
            g.means, g.quats, g.scales, world_to_camera(pose(0.03, -0.02)[None].to(dtype)),
            torch.sigmoid(g.opacity_logits).detach(), cpu_backend.camera_array(CAM), CAM.width, CAM.height, False)
        m2, con, rad = m2.numpy(), con.numpy(), rad.numpy()
        tab = np.empty((m2.shape[1], ck.TAB_COLS), m2.dtype)
        ck.gaussian_table(m2, con, rad, lo, np.ones(m2.shape[1], bool), tab)
        pix_view, need = cpu_backend.pixel_views(None, 1, CAM.height, CAM.width, ts)
        tiles_x = math.ceil(CAM.width / ts)
        flat, starts = ck.bin_tiles(m2, rad, dep.numpy(), ts, tiles_x, need.shape[1] // tiles_x, need)
        for b in range(need.shape[1]):
            x0, y0 = (b % tiles_x) * ts, (b // tiles_x) * ts
            py, px = np.meshgrid(np.arange(y0, y0 + ts) + 0.5, np.arange(x0, x0 + ts) + 0.5, indexing="ij")
            for n in flat[starts[b]:starts[b + 1]]:
                A, B, C = (float(v) for v in con[0, n])
                dx, dy = px - float(m2[0, n, 0]), py - float(m2[0, n, 1])
                reach = 0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy) - float(lo[n]) <= 5.55
                reach &= (py < CAM.height) & (px < CAM.width)
                box = ck._footprint_tab(tab, n, x0, y0, ts, CAM.width, CAM.height)
                visited, cut = visited_pixels(box, lambda qa, qb, ra, rb: ck.band_rows(
                    tab, n, x0, y0, qa, qb, ra, rb), reach.shape, cw)
                n_cut += cut
                assert not (reach & ~visited).any(), (seed, b, n)
                n_checked += int(reach.any())
    assert n_checked > 100 and n_cut > 20


def test_finite_check_is_exact_when_the_sum_overflows():
    """`render` checks finiteness through the sum of each parameter tensor; finite entries whose sum
    overflows float32 must still pass, and a NaN among them must still be named."""
    g = Gaussians(**{k: v.float() for k, v in edge_case_scene(0).tensors().items()})
    colors = g.colors.clone()
    colors[:4] = 3e38  # finite; their sum is inf in float32
    assert not torch.isfinite(colors.sum())
    out = render(Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, colors), CAM, pose(), backend="cpu")
    assert out.rgb.shape == (1, CAM.height, CAM.width, 3)
    colors[5, 1] = float("nan")
    with pytest.raises(ValueError, match="colors must be finite"):
        render(Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, colors), CAM, pose(), backend="cpu")


def test_raster_threads_env_gives_the_kernels_their_own_count():
    """EGOBENCH_RASTER_THREADS sets the kernels' threads independently of torch's (torch at 1,
    numba at 2: the pool is sized from it by `setup_threads`); without it numba follows torch; a bad value
    is a ValueError naming the variable."""
    import os

    from egobench.render import cpu_backend

    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_NUM_THREADS", cpu_backend.RASTER_THREADS_ENV)}
    env["OMP_NUM_THREADS"] = "1"
    outs = [_thread_counts(dict(env, **({cpu_backend.RASTER_THREADS_ENV: value} if value else {})))
            for value in ("2", None)]
    assert outs == [["1", "2", "2"], ["1", "1", "1"]]
    os.environ[cpu_backend.RASTER_THREADS_ENV] = "two"
    try:
        with pytest.raises(ValueError, match="EGOBENCH_RASTER_THREADS must be a positive integer"):
            cpu_backend.raster_threads()
    finally:
        del os.environ[cpu_backend.RASTER_THREADS_ENV]


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_stage_profiler_reports_every_stage_of_the_binned_scene(mode):
    """`python -m egobench.bench.cpu_profile` (docs/cpu-rasterizer.md's profile): every stage is
    timed, the sum is the sum of the listed stages, the intersection count is the binning's, and the
    work counts are those of the forward's rows_hit (composited intersections, backward pixels)."""
    import numpy as np

    from egobench import bench
    from egobench.bench import cpu_profile
    from egobench.render import cpu_backend, cpu_backend_2dgs, cpu as ck

    st = cpu_profile.stage_times(sigma_px=1.5, width=32, n=300, repeats=1, mode=mode)
    assert all(st[k] >= 0 for k in cpu_profile.STAGES + ("bin_tiles",)) and st["render_fwd_bwd (bench step)"] > 0
    assert st["sum_of_stages"] == pytest.approx(sum(st[k] for k in cpu_profile.STAGES), abs=0.01)
    spec = bench._case_spec((32, 300, 1.5))
    g = bench.bench_scene(spec)
    cam = cpu_backend.camera_array(bench.bench_camera(spec))
    with torch.no_grad():
        if mode == "3dgs":
            m2, _, dep, _, rad = cpu_backend._Project.apply(g.means, g.quats, g.scales, torch.eye(4)[None],
                                                            torch.sigmoid(g.opacity_logits), cam, 32, 32, False)
        else:
            m2, _, dep, _, rad = cpu_backend_2dgs._Project2DGS.apply(g.means, g.quats, g.scales, torch.eye(4)[None],
                                                                     cam, 32, 32)
    need = np.ones((1, 4), dtype=np.bool_)
    flat, _ = ck.bin_tiles(m2.numpy(), rad.numpy(), dep.numpy(), 16, 2, 2, need)
    assert st["intersections"] == flat.shape[0] > 0
    assert 0 < st["intersections_composited"] < st["intersections"]
    assert st["backward_pixel_evals"] % ck.column_group(16) == 0
    assert st["intersections_composited"] <= st["backward_pixel_evals"] <= st["intersections_composited"] * 16 * 16


def test_profiler_work_counts_read_rows_hit():
    """`cpu_profile._work`: composited intersections are those with a non-empty row range in some
    column group, and the backward's pixel evaluations are their rows times the group width."""
    from egobench.bench import cpu_profile

    rows_hit = np.array([[[0, 0], [2, 5]], [[0, 0], [0, 0]], [[1, 2], [3, 3]]], np.int16)  # 3 intersections, 2 groups
    assert cpu_profile._work(rows_hit, 8) == {"intersections": 3, "intersections_composited": 2,
                                              "backward_pixel_evals": (3 + 1) * 8}


def _tile_rects_reference(means2d, radii, depths, tile_size, tiles_x, tiles_y, bin_needed):
    """`ck.visible_rects` in plain Python: visible pairs in (image, Gaussian) order, tile ranges
    clipped to each image's box of needed bins."""
    rects, vis, keys = [], [], []
    I, N = depths.shape
    for i in range(I):
        t = np.flatnonzero(bin_needed[i])
        tx, ty = t % tiles_x, t // tiles_x
        box = (tx.min(), tx.max() + 1, ty.min(), ty.max() + 1) if t.size else (tiles_x, 0, tiles_y, 0)
        for n in range(N):
            if radii[i, n, 0] <= 0 or radii[i, n, 1] <= 0:
                continue
            (mx, my), (rx, ry) = means2d[i, n] / tile_size, radii[i, n] / tile_size
            x0 = max(max(min(math.floor(mx - rx), tiles_x), 0), box[0])
            x1 = min(max(min(math.ceil(mx + rx), tiles_x), 0), box[1])
            y0 = max(max(min(math.floor(my - ry), tiles_y), 0), box[2])
            y1 = min(max(min(math.ceil(my + ry), tiles_y), 0), box[3])
            if x1 > x0 and y1 > y0:
                rects.append((x0, x1, y0, y1)), vis.append(i * N + n), keys.append(depths[i, n])
    return np.array(rects, np.int32).reshape(-1, 4), np.array(vis, np.int64), np.array(keys, depths.dtype)


def test_tile_rects_and_gradient_sums_match_plain_references():
    """`visible_rects` against a plain-Python rectangle list (an image that needs no bin gives none; the
    pairs cut into 1, 2, 3 or 7 ranges, across image boundaries, as threads would) and
    `reduce_isect_grad` against numpy's in-order np.add.at: the same numbers bit for bit, for any
    number of parts (threads)."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(4)
    I, N, ts, tiles_x, tiles_y = 5, 300, 16, 6, 4
    means2d = rng.uniform(-20, 110, size=(I, N, 2)).astype(np.float32)
    radii = rng.integers(-2, 25, size=(I, N, 2)).astype(np.int32)
    depths = rng.uniform(0.5, 9.0, size=(I, N)).astype(np.float32)
    bin_needed = rng.random((I, tiles_x * tiles_y)) < 0.7
    bin_needed[2] = False
    want = _tile_rects_reference(means2d, radii, depths, ts, tiles_x, tiles_y, bin_needed)
    for got, ref in zip(ck.visible_rects(means2d, radii, depths, ts, tiles_x, tiles_y, bin_needed), want):
        np.testing.assert_array_equal(got, ref)
    boxes = ck._needed_boxes(bin_needed, tiles_x, tiles_y)
    for parts in (2, 3, 7):
        out = ck.Rects(np.empty((I * N, 4), np.int32), np.empty(I * N, np.int64), np.empty(I * N, depths.dtype))
        nv = ck._tile_rects(ck.Footprints(means2d, radii, depths), ck.TileGrid(ts, tiles_x, tiles_y), boxes, parts, out)
        for got, ref in zip(out, want):
            np.testing.assert_array_equal(got[:nv], ref)
    assert 0 < len(want[1]) < I * N and not np.any(want[1] // N == 2)
    flat_ids, bin_start = ck.bin_tiles(means2d[:, :0], radii[:, :0], depths[:, :0], ts, tiles_x, tiles_y, bin_needed)
    assert flat_ids.shape == (0,) and bin_start.shape == (I * tiles_x * tiles_y + 1,) and not bin_start.any()
    M = 4000
    flat_ids = rng.integers(0, I * N, size=M).astype(np.int64)
    isect = rng.normal(size=(M, 10)).astype(np.float32)
    sums, abs_want = np.zeros((I * N, 10)), np.zeros((I * N, 2))
    np.add.at(sums, flat_ids, isect.astype(np.float64))  # unbuffered, in index order
    np.add.at(abs_want, flat_ids, np.abs(isect[:, :2]).astype(np.float64))
    assert len(np.unique(flat_ids)) < I * N  # rows no intersection reaches stay zero
    # summed in float64, then rounded once; every entry written (out starts as NaN); one part or
    # several (threads) give the same bits
    for dtype, parts in ((np.float64, 1), (np.float32, 1), (np.float32, 3), (np.float64, 7)):
        out, absgrad = np.full((10, I * N), np.nan, dtype), np.zeros((I * N, 2))  # channel first
        ck.reduce_isect_grad(isect, flat_ids, M, out, absgrad, parts)
        np.testing.assert_array_equal(out, sums.T.astype(dtype))
        np.testing.assert_array_equal(absgrad, abs_want)


def test_fill_bins_matches_a_plain_counting_sort_for_any_number_of_ranges(monkeypatch):
    """`fill_bins`' kernels against a plain-Python bucket sort (entries in perm order, each into every
    needed bin of its rectangle): the same flat_ids and bin_start whether the sorted entries are one range
    or cut into 2, 3 or 7, on as many threads as numba's pool has (up to 2; the dispatcher splitting too);
    an image needing no bin gets none."""
    import numba

    from egobench.render import cpu as ck

    rng = np.random.default_rng(11)
    I, N, tiles_x, tiles_y, nv = 4, 500, 5, 3, 1500
    x0, y0 = rng.integers(0, tiles_x, nv), rng.integers(0, tiles_y, nv)
    rect = np.stack([x0, x0 + rng.integers(1, 3, nv), y0, y0 + rng.integers(1, 3, nv)], 1)
    rect = np.minimum(rect, [tiles_x, tiles_x, tiles_y, tiles_y]).astype(np.int32)
    vis = np.sort(rng.choice(I * N, nv, replace=False)).astype(np.int64)
    perm = rng.permutation(nv).astype(np.int64)
    bin_needed = rng.random((I, tiles_x * tiles_y)) < 0.6
    bin_needed[1] = False
    bins = [[] for _ in range(I * tiles_x * tiles_y)]
    for q in perm:
        i = vis[q] // N
        for ty in range(rect[q, 2], rect[q, 3]):
            for tx in range(rect[q, 0], rect[q, 1]):
                if bin_needed[i, ty * tiles_x + tx]:
                    bins[i * tiles_x * tiles_y + ty * tiles_x + tx].append(vis[q])
    want_ids = np.array([k for b in bins for k in b], np.int64)
    want_start = np.concatenate([[0], np.cumsum([len(b) for b in bins])])
    assert 0 < len(want_ids) and not any(bins[tiles_x * tiles_y:2 * tiles_x * tiles_y])
    monkeypatch.setattr(ck, "FILL_PART_MIN", 100)  # the dispatcher splits these 1500 entries
    before = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        got = [ck._fill_bins(rect, vis, perm, N, tiles_x, bin_needed), ck.fill_bins(rect, vis, perm, N, tiles_x,
                                                                                    bin_needed)]
        got += [ck._fill_bins_parts(rect, vis, perm, N, tiles_x, bin_needed, parts) for parts in (2, 3, 7)]
    finally:
        numba.set_num_threads(before)
    for flat_ids, bin_start in got:
        np.testing.assert_array_equal(flat_ids, want_ids)
        np.testing.assert_array_equal(bin_start, want_start)


def test_pose_sums_add_the_poses_in_order_contiguous_on_any_number_of_threads():
    """`pose_sums` (compiled, `ck.ordered_sum`): the bits (signed zeros included) of the poses added in order
    from +0.0 (a numpy loop) for 1-17 poses, float32 and float64, on one and two threads, torch's sum to
    rounding (torch adds a block's last columns in another order), returned contiguous (so autograd keeps it
    as the parameter's gradient); `pose_grad` adds its chunks as the numpy loop it replaced did."""
    import numba

    from egobench.render import cpu_backend as cb

    rng = np.random.default_rng(5)
    before = numba.get_num_threads()
    try:
        for threads in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(threads)
            for dtype in (torch.float32, torch.float64):
                for I in (1, 2, 6, 8, 13, 17):
                    N = 700  # three chunks, the last partial
                    block = rng.standard_normal((10, I, N)) * (rng.random((10, I, N)) < 0.3)
                    block[6, :, :50] = -0.0  # columns of negative zeros: torch's sum gives +0.0
                    per = torch.from_numpy(block).to(dtype).permute(1, 2, 0)  # reduce_intersections' view
                    got = cb.pose_sums(per, 6, 9)
                    assert got.is_contiguous() and got.shape == (N, 3) and got.dtype == dtype
                    in_order = np.zeros((N, 3), got.numpy().dtype)
                    for i in range(I):
                        in_order += per[i, :, 6:9].numpy()
                    assert np.array_equal(got.numpy().view(np.uint8), in_order.view(np.uint8)), (threads, I)
                    torch.testing.assert_close(got, per.permute(2, 0, 1)[6:9].sum(1).T)
            parts = rng.standard_normal((9, 3, 12))
            want = parts[0].copy()
            for c in range(1, 9):
                want += parts[c]
            gv = cb.pose_grad(parts, torch.float64)
            assert torch.equal(gv[:, :3, :], torch.from_numpy(want.reshape(3, 3, 4)))
            assert torch.equal(gv[:, 3, :], torch.zeros(3, 4, dtype=torch.float64))
    finally:
        numba.set_num_threads(before)


def _copied(a):
    """A kernel argument copied: an array, a named tuple of them (field by field), or as it is."""
    if isinstance(a, np.ndarray):
        return np.copy(a)
    if isinstance(a, tuple) and hasattr(a, "_fields"):
        return type(a)(*(_copied(x) for x in a))
    return a


def _captured_raster(monkeypatch, mode: str, sigma_px: float):
    """Kernel arguments of one render + backward (mode "3dgs" or "2dgs") on an `egobench bench raster`
    scene (64 px, 1500 Gaussians, float32) -> backward args; the last two are isect_grad and the
    forward's rows_hit."""
    from egobench import bench
    from egobench.render import cpu as ck
    from egobench.render.cpu import surfels as k2

    mod, name = (k2, "raster_bwd_2dgs") if mode == "2dgs" else (ck, "raster_bwd")
    kernel, got = getattr(mod, name), {}

    def keep(*args):
        kernel(*args)
        got["bwd"] = [_copied(a) for a in args]

    monkeypatch.setattr(mod, name, keep)
    spec = bench._case_spec((64, 1500, sigma_px))
    w = torch.randn(1, 64, 64, 3, generator=torch.Generator().manual_seed(3))
    bench._step(bench.bench_scene(spec), bench.bench_camera(spec), torch.eye(4)[None], w, mode=mode, backend="cpu")()
    return got["bwd"], kernel


def _backward_with_rows(kernel, bwd_args, rows_hit):
    args = [_copied(a) for a in bwd_args[:-1]] + [rows_hit]
    args[-2][:] = 0
    kernel(*args)
    return args[-2]


def test_rows_needed_marks_exactly_the_binned_rows():
    from egobench.render import cpu as ck

    flat = np.array([7, 3, 7, 0, 12, 3], np.int64)
    np.testing.assert_array_equal(ck.rows_needed(flat, 14), np.isin(np.arange(14), flat))
    assert not ck.rows_needed(flat[:0], 5).any()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_floor_and_ceil_in_float64_are_the_float32_values_floor_and_ceil(dtype):
    """`floor_int` / `ceil_int` (rounded in float64, no C helper call for a float32): the integers
    math.floor / math.ceil give, at integers, halves, negatives, signed zeros and values near 2^23."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(3)
    vals = np.concatenate([[0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 2.0**23 - 0.5, -(2.0**23) + 0.5, 1e-30, -1e-30],
                           rng.uniform(-300, 300, 200), np.round(rng.uniform(-50, 50, 20))]).astype(dtype)
    for v in vals:
        assert ck.floor_int(v) == math.floor(float(v)), v
        assert ck.ceil_int(v) == math.ceil(float(v)), v


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_table_buffer_rows_start_on_cache_lines(dtype):
    """`table_buffer`: [rows, TAB_COLS] of the dtype, C-contiguous and writeable, its first byte on a
    64-byte boundary (so every float32 row is one cache line) for any row count, rows not overlapping."""
    from egobench.render import cpu_backend, cpu as ck

    held = [np.empty(k, np.uint8) for k in (1, 17, 33)]  # shift the allocator's next address
    for rows in (1, 3, 1000, 120_000):
        tab = cpu_backend.table_buffer(rows, dtype)
        assert tab.shape == (rows, ck.TAB_COLS) and tab.dtype == dtype
        assert tab.flags.c_contiguous and tab.flags.writeable
        assert tab.ctypes.data % cpu_backend.CACHE_LINE == 0
        tab[:] = np.arange(rows, dtype=dtype)[:, None]
        assert (tab[-1] == rows - 1).all() and (tab[0] == 0).all()
    del held


def test_needed_rows_lists_the_needed_rows_of_a_range_in_order():
    """`needed_rows`: the rows g in [g0, g1) with needed[g], ascending, for empty, sparse and full ranges."""
    from egobench.render import cpu as ck

    need = np.random.default_rng(5).random(700) < 0.11
    need[600:] = True
    rows = np.empty(700, np.int64)
    for g0, g1 in ((0, 700), (13, 269), (600, 700), (5, 5), (300, 301)):
        L = ck.needed_rows(need, g0, g1, rows)
        np.testing.assert_array_equal(rows[:L], g0 + np.nonzero(need[g0:g1])[0])


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_tables_fill_only_the_rows_needed(mode):
    """The Gaussian / surfel table fills the rows `rows_needed` marks, each exactly as a full table,
    and leaves the others as they were."""
    from egobench.render import world_to_camera, cpu_backend, cpu_backend_2dgs, cpu as ck
    from egobench.render.cpu import surfels

    g = edge_case_scene(5)
    Ts = world_to_camera(torch.stack([pose(0.0, 0.03 * k, (0.01 * k, 0, 0)) for k in range(3)]))
    lo = torch.nn.functional.logsigmoid(g.opacity_logits).numpy()
    if mode == "3dgs":
        m2, con, _, _, rad = cpu_backend._Project.apply(g.means, g.quats, g.scales, Ts, torch.sigmoid(g.opacity_logits),
                                                       cpu_backend.camera_array(CAM), CAM.width, CAM.height, False)
        fill = lambda need, tab: ck.gaussian_table(m2.numpy(), con.numpy(), rad.numpy(), lo, need, tab)
    else:
        m2, tsl, _, _, _ = cpu_backend_2dgs._Project2DGS.apply(g.means, g.quats, g.scales, Ts,
                                                                cpu_backend.camera_array(CAM), CAM.width, CAM.height)
        fill = lambda need, tab: surfels.surfel_table(m2.numpy(), tsl.numpy(), lo, need, tab)
    rows = m2.shape[0] * m2.shape[1]
    need = np.random.default_rng(0).random(rows) < 0.3
    full, part = np.zeros((rows, ck.TAB_COLS)), np.full((rows, ck.TAB_COLS), np.nan)
    fill(np.ones(rows, bool), full)
    fill(need, part)
    np.testing.assert_array_equal(part[need], full[need])
    assert np.isnan(part[~need]).all() and 0 < need.sum() < rows


@pytest.mark.parametrize("with_normals", [False, True])
def test_live_pairs_marks_the_pairs_with_any_upstream_gradient(with_normals):
    """`live_pairs` (the projection backwards skip the other pairs exactly): a pair is live when any
    channel of any gradient is non-zero at it, the normals only when asked for; a block [n0, n0 + L)."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(7)
    I, N, n0, L = 4, 300, 37, 200
    sparse = lambda *shape: rng.normal(size=shape) * (rng.random(shape) < 0.03)
    g_m2, g_second, g_dep, g_nrm = sparse(2, I, N), sparse(9, I, N), sparse(I, N), sparse(3, I, N)
    live = np.ones((I, 256), bool)
    ck.live_pairs(g_m2, g_second, g_dep, g_nrm, with_normals, n0, L, live)
    want = (g_m2 != 0).any(0) | (g_second != 0).any(0) | (g_dep != 0)
    if with_normals:
        want |= (g_nrm != 0).any(0)
    np.testing.assert_array_equal(live[:, :L], want[:, n0:n0 + L])
    assert 0 < want[:, n0:n0 + L].sum() < I * L
    only_normals = ((g_nrm != 0).any(0) & ~want)[:, n0:n0 + L]
    assert with_normals or (only_normals.any() and not live[:, :L][only_normals].any())


@pytest.mark.parametrize("with_normals", [False, True])
def test_feature_table_fills_the_needed_rows_with_colour_depth_normal(with_normals):
    """`feature_table` writes each needed row image * N + Gaussian as (colour, depth[, normal]) of that
    image and Gaussian (the layout the kernels read) and leaves the other rows as they were."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(2)
    I, N = 3, 700
    colors = rng.random((N, 3)).astype(np.float32)
    depths = rng.uniform(1, 9, (I, N)).astype(np.float32)
    normals = rng.normal(size=(I, N if with_normals else 0, 3)).astype(np.float32)
    need = rng.random(I * N) < 0.2
    out = np.full((I * N, 7 if with_normals else 4), np.nan, np.float32)
    ck.feature_table(colors, depths, normals, need, out)
    want = np.concatenate([np.broadcast_to(colors, (I, N, 3)), depths[..., None]] + ([normals] if with_normals else []),
                          -1).reshape(I * N, -1)
    np.testing.assert_array_equal(out[need], want[need])
    assert np.isnan(out[~need]).all() and 0 < need.sum() < I * N


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_uninitialised_buffers_are_never_read(monkeypatch, mode):
    """Every buffer the CPU backend takes from np.empty (the tables fill only the rows the binning
    needs) is written before it is read: with np.empty returning NaN (floats) or extreme values
    (integers), a rolling-shutter render and its gradients are bitwise the same (a table row read but
    not filled changes them; a mask that drops half the needed rows fails this)."""
    g = edge_case_scene(6)
    K = 4
    Ts = torch.stack([pose(0.0, 0.02 * k, (0.01 * k, 0, 0)) for k in range(K)])
    idx = torch.round(torch.arange(CAM.height) / (CAM.height - 1) * (K - 1)).long()[:, None]
    idx = idx.expand(CAM.height, CAM.width).contiguous()
    ref = run(g, CAM, Ts, "cpu", 3, pixel_pose_index=idx, mode=mode)
    empty = np.empty

    def garbage_empty(shape, dtype=float, **kw):
        out, dt = empty(shape, dtype, **kw), np.dtype(dtype)
        out.fill(np.nan if dt.kind == "f" else True if dt.kind == "b" else np.iinfo(dt).min if dt.kind in "iu" else 0)
        return out

    monkeypatch.setattr(np, "empty", garbage_empty)
    got = run(g, CAM, Ts, "cpu", 3, pixel_pose_index=idx, mode=mode)
    torch.testing.assert_close(got[0], ref[0], rtol=0, atol=0)
    for k, v in ref[1].items():
        torch.testing.assert_close(got[1][k], v, rtol=0, atol=0, msg=lambda m, k=k: f"{k}: {m}")


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_backward_visits_only_the_rows_the_forward_composited(monkeypatch, mode):
    """The forward records, per intersection and column group, the rows it composited into
    (rows_hit); the backward over only those rows equals the backward over every row of the tile
    (the other pixels' terms are zero), and each recorded range is tight: without its first row the
    intersection's gradient changes. The records skip most of the tiles' rows."""
    from egobench.render.cpu_backend import DEFAULT_TILE

    bwd_args, kernel = _captured_raster(monkeypatch, mode, 2.5)
    rows, ts = bwd_args[-1], DEFAULT_TILE
    assert rows.shape[1] == ts // 8 and rows.min() >= 0 and rows.max() <= ts
    hit = rows[:, :, 1] > rows[:, :, 0]
    every_row = np.zeros_like(rows)
    every_row[:, :, 1] = ts
    g_rows = _backward_with_rows(kernel, bwd_args, rows)
    np.testing.assert_array_equal(g_rows, bwd_args[-2])  # the render's own backward
    g_all = _backward_with_rows(kernel, bwd_args, every_row)
    np.testing.assert_allclose(g_rows, g_all, rtol=1e-4, atol=1e-6 * float(np.abs(g_all).max()))
    shrunk = rows.copy()
    shrunk[:, :, 0] += hit
    changed = (_backward_with_rows(kernel, bwd_args, shrunk) != g_rows).any(1)
    assert hit.any(1).sum() > 300 and changed[hit.any(1)].mean() > 0.99 and not changed[~hit.any(1)].any()
    visited = (rows[:, :, 1] - rows[:, :, 0]).clip(min=0).sum()  # rows of 8 pixels
    assert visited < 0.5 * hit.any(1).sum() * ts * rows.shape[1]


@pytest.mark.parametrize("mode", ["3dgs", "2dgs"])
def test_projection_backward_reads_float32_gradients_as_float64_copies(monkeypatch, mode):
    """The projection backward gets the upstream gradients in their own dtype (no float64 copies of
    [I, N, 9] arrays a step): every value is widened to float64 as it is read, so its outputs equal,
    bit for bit, those from float64 copies of the same gradients (normals and pose gradients included)."""
    from egobench.render import cpu as ck
    from egobench.render.cpu import surfels as k2

    mod, name = (k2, "project_bwd_2dgs") if mode == "2dgs" else (ck, "project_bwd")
    kernel, got = getattr(mod, name), {}

    def keep(*args):
        got["args"] = [_copied(a) for a in args]
        kernel(*args)

    monkeypatch.setattr(mod, name, keep)
    g = Gaussians(**{k: v.float() for k, v in make_scene(400, CAM, 3).tensors().items()})
    inputs = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    T = torch.stack([pose(0.02, -0.01), pose(-0.01, 0.03)]).float().requires_grad_(True)
    kw = {"mode": "2dgs"} if mode == "2dgs" else {"want_normal": True}
    out = render(Gaussians(**inputs), CAM, T, backend="cpu", **kw)
    w = torch.randn(out.rgb.shape, generator=torch.Generator().manual_seed(2))
    ((out.rgb * w).sum() + out.normal.sum() + out.depth.sum()).backward()
    args = got["args"]
    upstream = args[-2]  # (ck.ProjectedGrads / ProjectedSurfelGrads): means2d, conics / ray transforms, depths, normals
    assert len(upstream) == 4 and all(a.dtype == np.float32 for a in upstream)
    outs = []
    for widen in (False, True):
        run = [_copied(a) for a in args]
        if widen:
            run[-2] = type(upstream)(*(a.astype(np.float64) for a in run[-2]))
        for a in run[-1]:  # ck.SplatGrads: means, quats, scales, pose parts
            a[:] = 0
        kernel(*run)
        outs.append(list(run[-1]))
    for a, b in zip(*outs):
        np.testing.assert_array_equal(a, b)
    assert all(np.abs(a).max() > 0 for a in outs[0])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_radix_order_is_numpys_stable_argsort(dtype):
    """`_radix_order` of positive floats' bit patterns: the stable ascending order (ties keep their
    index order), for empty, one and many keys with ties across every radix digit."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(7)
    uint = np.uint32 if dtype == np.float32 else np.uint64
    for n in (0, 1, 5000):
        keys = (rng.integers(1, 40, n) * 0.37).astype(dtype)  # many ties
        keys[: n // 3] = rng.random(n // 3).astype(dtype) * 1e4 + 1e-3  # spread over exponents
        order = ck._radix_order(keys.view(uint), keys.dtype.itemsize * 8)
        np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))


def _divide(a, b, out):
    for i in range(out.shape[0]):
        out[i] = a[i] / b[i]


def test_per_bin_bodies_compile_with_a_parfor_bodys_flags():
    """`BIN_BODY` gives a plain function what numba gives a parfor body: array arguments marked noalias
    and numpy's error model (no zero-division test), so that a division loop vectorizes; a plain
    fast-math function keeps the test and only its return slots are noalias. The 3DGS per-bin bodies use it."""
    from numba import njit

    from egobench.render import cpu as ck

    x = np.linspace(1.0, 2.0, 64, dtype=np.float32)
    irs = {}
    for name, options in (("bin", {**ck.BIN_BODY, "cache": False}), ("plain", {"fastmath": ck.FASTMATH})):
        fn = njit(**options)(_divide)
        out = np.empty_like(x)
        fn(x, x[::-1].copy(), out)
        np.testing.assert_allclose(out, x / x[::-1], rtol=1e-6)
        irs[name] = next(iter(fn.inspect_llvm().values()))
    head = {k: next(line for line in ir.splitlines() if line.startswith("define") and "_divide" in line)
            for k, ir in irs.items()}
    assert head["bin"].count("noalias") >= head["plain"].count("noalias") + 3  # a, b and out's data
    assert "ZeroDivisionError" in irs["plain"] and "ZeroDivisionError" not in irs["bin"]
    assert re.search(r"<\d+ x float>", irs["bin"])
    for kernel in (ck._fwd_bin, ck._bwd_bin):
        assert kernel._compiler.pipeline_class is ck.NoAliasCompiler
        assert kernel.targetoptions["error_model"] == "numpy"


def test_needed_bins_are_the_bins_of_the_pixels():
    """`ck.needed_bins` (a store only where the pose changes along a tile's row) marks exactly the
    (pose, tile) bins some pixel lies in: against numpy fancy indexing, for per-row poses (a rolling
    shutter), random per-pixel poses, and an image whose sides are not multiples of the tile size."""
    from egobench.render import cpu as ck

    rng = np.random.default_rng(3)
    H, W, ts, I = 37, 45, 16, 5
    tiles_x, tiles_y = math.ceil(W / ts), math.ceil(H / ts)
    tile_of = (np.arange(H)[:, None] // ts) * tiles_x + (np.arange(W)[None, :] // ts)
    rows = np.repeat((np.arange(H) * I // H)[:, None], W, axis=1)
    for ppi in (rows, rng.integers(0, I, (H, W)), np.zeros((H, W), np.int64)):
        want = np.zeros((I, tiles_y * tiles_x), bool)
        want[ppi.reshape(-1), tile_of.reshape(-1)] = True
        got = np.zeros_like(want)
        ck.needed_bins(np.ascontiguousarray(ppi, dtype=np.int64), ts, tiles_x, got)
        assert np.array_equal(got, want)
    assert want.sum() == tiles_x * tiles_y  # the last case: pose 0 everywhere, every tile


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_alpha_and_depth_are_the_torch_ops_bit_for_bit(dtype):
    """`cpu_backend.composite_output`'s compiled alpha and depth (rsub, clamp, div and their backwards in one
    pass each) give the bits of the torch ops they replace: values and gradients, with pixels where the
    clamp holds (T = 1, alpha below 1e-10), with and without a loss on alpha, and with a background."""
    from egobench.render import cpu_backend

    g = torch.Generator().manual_seed(7)
    trans = torch.rand(1, 9, 11, generator=g, dtype=dtype)
    trans[0, :2] = 1.0  # alpha 0: the clamp's branch
    depth_sum = torch.rand(1, 9, 11, 1, generator=g, dtype=dtype) * (1.0 - trans[..., None]) * 4.0
    w_alpha, w_depth = (torch.randn(1, 9, 11, 1, generator=g, dtype=dtype) for _ in range(2))
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=dtype)
    for on_alpha in (False, True):
        got, want = [], []
        for compiled, out in ((True, got), (False, want)):
            d, t = depth_sum.clone().requires_grad_(), trans.clone().requires_grad_()
            if compiled:
                rgb, alpha, depth = cpu_backend.composite_output(torch.zeros(1, 9, 11, 3, dtype=dtype), d, t, bg)
            else:
                alpha = 1.0 - t[..., None]
                depth, rgb = d / alpha.clamp(min=1e-10), t[..., None] * bg
            loss = (depth * w_depth).sum() + rgb.sum() + ((alpha * w_alpha).sum() if on_alpha else 0.0)
            loss.backward()
            out += [alpha.detach(), depth.detach(), d.grad, t.grad]
        for a, b in zip(got, want):  # bit patterns (signed zeros too)
            assert a.dtype == b.dtype == dtype and a.shape == b.shape
            assert np.array_equal(a.contiguous().numpy().view(np.uint8), b.contiguous().numpy().view(np.uint8))
        assert float(want[3][0, :2].abs().sum()) > 0  # the clamped pixels still pass the alpha/background terms


def test_every_kernel_is_stamped_with_the_hash_of_the_whole_package(tmp_path):
    """numba stamps a cache with its own file's mtime; the kernels inline helpers of other modules, so egobench's
    locator stamps each kernel of `egobench.render.cpu` with a hash of every module there: a change to any one
    module (a planted byte) changes every kernel's stamp, and a file outside the package keeps numba's own."""
    import shutil

    from egobench.render import cpu as ck
    from egobench.render.cpu import compiler
    from egobench.render.cpu import surfels as k2

    for kernel in (ck.project_fwd, ck.needed_bins, ck.raster_bwd, k2.raster_fwd_2dgs):
        locator = kernel._cache._impl.locator
        assert isinstance(locator, compiler.SourceHashLocator)
        assert locator.get_source_stamp() == compiler.source_hash(compiler.PACKAGE_DIR)
    copy = tmp_path / "cpu"
    shutil.copytree(compiler.PACKAGE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert compiler.source_hash(copy) == compiler.package_source_hash()
    (copy / "binning.py").write_text((copy / "binning.py").read_text() + "\n")
    assert compiler.source_hash(copy) != compiler.package_source_hash()
    outside = compiler.SourceHashLocator.from_function(test_every_kernel_is_stamped_with_the_hash_of_the_whole_package,
                                                      __file__)
    assert outside is None
