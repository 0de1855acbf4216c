"""Tests of the benchmark helpers and the `egobench bench` verb (tiny sizes)."""

from __future__ import annotations

import argparse
import json
import math
import sys

import pytest
import torch

from egobench import bench
from tests import background

# The suite's first 2DGS float32 render: compiled on the second core from the suite's start.
BACKGROUND = {"test_bench_raster_2dgs_renders_surfels": background.compile_kernels("float32", ("2dgs",))}


def test_row_index_image_bands():
    idx = bench.row_index_image(8, 64, 5)
    assert idx.shape == (64, 5) and idx.dtype == torch.long
    assert int(idx[0, 0]) == 0 and int(idx[-1, 0]) == 7
    assert bool((idx.diff(dim=0) >= 0).all())  # rows in readout order: contiguous bands
    assert set(idx[:, 0].tolist()) == set(range(8))


def test_rolling_shutter_poses_span_the_readout():
    T = bench.rolling_shutter_poses(8, 0.016, 300.0)
    yaw = torch.atan2(T[:, 0, 2], T[:, 0, 0])
    span = math.degrees(float(yaw[-1] - yaw[0]))
    assert span == pytest.approx(300.0 * 0.016 * 7 / 8, rel=1e-5)
    assert torch.allclose(T[:, :3, :3] @ T[:, :3, :3].transpose(1, 2), torch.eye(3).expand(8, 3, 3), atol=1e-6)


def test_bench_scene_has_few_pixel_radii():
    spec = bench.SceneSpec(width=64, num_gaussians=500, focal_px=38.4, depth_range_m=(2.0, 8.0), margin=0.1,
                           sigma_px_median=0.8, sigma_log_std=0.3, opacity_logit_mean=0.0, seed=0)
    from egobench.render import render

    out = render(bench.bench_scene(spec), bench.bench_camera(spec), torch.eye(4), backend="torch")
    r = out.radii[out.radii > 0].float()
    assert r.numel() > 400 and 2.0 < float(r.mean()) < 6.0


def test_bench_raster_record_small():
    rec = bench.bench_raster("cpu", repeats=1, backend="torch", tile_size=8, cases=((16, 60),))
    json.dumps(rec, allow_nan=False)
    assert rec["torch"] == torch.__version__ and rec["device"] == "cpu"
    case = rec["cases"][0]
    assert case["image"] == "16x16" and case["median_ms"] > 0 and case["scene"]["num_gaussians"] == 60
    rs = rec["rolling_shutter"]
    assert rs["pose_samples"] == 8 and rs["ratio"] > 0


def test_bench_raster_compares_backends_and_threads(two_kernel_threads):
    rec = bench.bench_raster("cpu", repeats=1, cases=((16, 40, 2.5),))
    assert rec["backends"] == ["cpu", "torch"]  # on the CPU, auto compares the compiled backend with torch
    case = rec["cases"][0]
    assert set(case["by_backend"]) == {"cpu", "torch"} and case["scene"]["sigma_px_median"] == 2.5
    assert case["median_ms"] == case["by_backend"]["cpu"]["median_ms"]
    assert case["speedup_vs_torch"] == pytest.approx(
        case["by_backend"]["torch"]["median_ms"] / case["by_backend"]["cpu"]["median_ms"], abs=0.01)
    assert set(rec["thread_scaling"]["by_threads"]) == {"1", "2"} and rec["rolling_shutter"]["backend"] == "cpu"


def test_bench_raster_2dgs_renders_surfels():
    """--mode 2dgs times the same scenes as surfels (a different image than 3DGS) on both backends."""
    background.wait_for_kernels(sys.modules[__name__], "test_bench_raster_2dgs_renders_surfels")
    kw = dict(repeats=1, cases=((16, 40, 2.5),), scaling_threads=())
    rec2, rec3 = bench.bench_raster("cpu", mode="2dgs", **kw), bench.bench_raster("cpu", **kw)
    assert rec2["mode"] == "2dgs" and set(rec2["cases"][0]["by_backend"]) == {"cpu", "torch"}
    assert rec2["cases"][0]["mean_alpha"] != rec3["cases"][0]["mean_alpha"]


def test_bench_train_rejects_unknown_method():
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        bench.bench_train("cpu", sides=(16,), iterations=1, methods=("nope",))


def test_bench_cli_rejects_bad_repeats():
    args = argparse.Namespace(what="raster", device="cpu", repeats=0, backend="torch", tile_size=8, threads=0)
    with pytest.raises(ValueError, match="--repeats"):
        bench.run(args)


def test_bench_train_cli_small(capsys):
    """`egobench bench train` end to end through the CLI parser, at a tiny size."""
    from egobench.cli import main

    assert main(["bench", "train", "--resolution", "48", "--iterations", "2", "--points", "300"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["benchmark"] == "train" and "300 points" in rec["recording"]
    from egobench.host import cpu_model

    # every number comes with the machine: CPU model, the kernels' LLVM target, torch's vector ISA
    assert rec["host"]["cpu_model"] == cpu_model() and rec["host"]["kernel_target"]
    assert rec["host"]["torch_cpu_capability"] in ("DEFAULT", "AVX2", "AVX512", "NO AVX", "ZVECTOR", "VSX")
    rows = {r["method"]: r for r in rec["results"]}
    assert set(rows) == {"no_motion_sampling", "ours"}
    for r in rows.values():
        assert r["resolution"] == 48 and r["iterations"] == 2 and r["iters_per_s"] > 0
        assert r["num_gaussians"] == 300 and r["peak_memory_mib"] > 0
    # fast yaw: motion sampling renders more than one pose sample per frame; the baseline one
    assert rows["ours"]["pose_samples_mean"] > 1.0 and rows["no_motion_sampling"]["pose_samples_mean"] == 1.0


@pytest.mark.parametrize("flag, value", [("--iterations", "0"), ("--points", "0"), ("--resolution", "4"),
                                         ("--rounds", "0")])
def test_bench_train_rejects_bad_arguments(flag, value):
    from egobench.cli import main

    assert main(["bench", "train", flag, value]) != 0


def test_bench_train_pairs_2dgs_with_its_3dgs_twin_and_times_thread_counts():
    rec = bench.bench_train("cpu", sides=(16,), iterations=2, methods=("ours", "ours_2dgs"), threads=(1, 2))
    rows = {(r["method"], r["threads"]): r["iters_per_s"] for r in rec["results"]}
    assert set(rows) == {("ours", 1), ("ours", 2), ("ours_2dgs", 1), ("ours_2dgs", 2)}
    assert [(x["method_2dgs"], x["method_3dgs"], x["threads"]) for x in rec["ratio_2dgs_to_3dgs"]] == [
        ("ours_2dgs", "ours", 1), ("ours_2dgs", "ours", 2)]
    for x in rec["ratio_2dgs_to_3dgs"]:
        assert x["ratio_2dgs_to_3dgs"] == round(rows[("ours", x["threads"])] / rows[("ours_2dgs", x["threads"])], 3)
    for x in rec["thread_speedup"]:
        assert x["speedup_2_vs_1"] == round(rows[(x["method"], 2)] / rows[(x["method"], 1)], 3)
    assert torch.get_num_threads() == rec["threads"]  # restored


def _train_result(iters_per_s: float, core_sharing: dict | None = None):
    """What a faked `egobench.train.train` returns: the fields `bench_train` reads."""
    import types

    return types.SimpleNamespace(iters_per_s=iters_per_s, raster_time_share=0.5, num_gaussians=7,
                                 record={"motion_samples": {"mean": 1.0}, "train": {"core_sharing": core_sharing}})


def test_bench_train_warms_each_method_up_before_timing_it(monkeypatch):
    """The first timed run of a method once paid its kernels' compilation or cache loading: each method
    now trains untimed first (once, at the first thread count), and only the timed runs make rows."""
    import egobench.train

    calls = []

    def fake_train(rec, method, cfg, out_dir, progress):
        calls.append((method, cfg.iterations, torch.get_num_threads()))
        return _train_result(float(len(calls)))

    monkeypatch.setattr(egobench.train, "train", fake_train)
    rec = bench.bench_train("cpu", sides=(16,), iterations=5, methods=("ours", "ours_2dgs", "ours"), threads=(2, 1))
    w = bench.WARMUP_ITERATIONS
    assert calls[:2] == [("ours", w, 2), ("ours_2dgs", w, 2)]
    assert calls[2:] == [("ours", 5, 2), ("ours", 5, 1), ("ours_2dgs", 5, 2), ("ours_2dgs", 5, 1),
                         ("ours", 5, 2), ("ours", 5, 1)]
    assert [r["iters_per_s"] for r in rec["results"]] == [3.0, 4.0, 5.0, 6.0, 7.0, 8.0]  # timed runs only
    assert str(w) in rec["warmup"]


def test_bench_train_rounds_alternate_the_order_and_compare_within_each_round(monkeypatch):
    """--rounds 3: the cases run forward, backward, forward; each ratio and speed-up is taken within its
    round, and the record gives the median over rounds with the per-round values."""
    import egobench.train

    calls = []
    speed = {("ours", 1): [30.0, 20.0, 33.0], ("ours", 2): [45.0, 40.0, 33.0],
             ("ours_2dgs", 1): [20.0, 10.0, 30.0], ("ours_2dgs", 2): [36.0, 10.0, 30.0]}

    def fake_train(rec, method, cfg, out_dir, progress):
        if cfg.iterations == bench.WARMUP_ITERATIONS:
            return _train_result(1.0)
        key = (method, torch.get_num_threads())
        calls.append(key)
        rnd = sum(c == key for c in calls) - 1
        return _train_result(speed[key][rnd])

    monkeypatch.setattr(egobench.train, "train", fake_train)
    rec = bench.bench_train("cpu", sides=(16,), iterations=5, methods=("ours", "ours_2dgs"), threads=(1, 2), rounds=3)
    forward = [("ours", 1), ("ours", 2), ("ours_2dgs", 1), ("ours_2dgs", 2)]
    assert calls == forward + forward[::-1] + forward
    assert [r["round"] for r in rec["results"]] == [0] * 4 + [1] * 4 + [2] * 4 and rec["rounds"] == 3
    ratio1 = [x for x in rec["ratio_2dgs_to_3dgs"] if x["threads"] == 1][0]
    assert ratio1["per_round"] == [1.5, 2.0, 1.1] and ratio1["ratio_2dgs_to_3dgs"] == 1.5
    sp = {x["method"]: x for x in rec["thread_speedup"]}
    assert sp["ours"]["per_round"] == [1.5, 2.0, 1.0] and sp["ours"]["speedup_2_vs_1"] == 1.5
    assert sp["ours_2dgs"]["per_round"] == [1.8, 1.0, 1.0] and sp["ours_2dgs"]["speedup_2_vs_1"] == 1.0


@pytest.mark.parametrize("what", ["train", "raster"])
@pytest.mark.parametrize("value", ["0", "1,x", "-2"])
def test_bench_rejects_bad_thread_counts(what, value):
    from egobench.cli import main

    assert main(["bench", what, "--scaling", value]) != 0


@pytest.mark.parametrize("mode", ["3dgs", "both"])
def test_bench_raster_passes_scaling_threads(monkeypatch, capsys, mode):
    """`bench raster --scaling 1,4,16` times the kernels at those counts (it once ignored the flag: 1,2)."""
    from egobench.cli import main

    seen = []
    monkeypatch.setattr(bench, "bench_raster", lambda device, **kw: seen.append(kw["scaling_threads"]) or {"cases": []})
    assert main(["bench", "raster", "--backend", "cpu", "--mode", mode, "--scaling", "1,4,16"]) == 0
    assert main(["bench", "raster", "--backend", "cpu", "--mode", mode]) == 0
    per_call = 2 if mode == "both" else 1
    assert seen == [(1, 4, 16)] * per_call + [(1, 2)] * per_call
    capsys.readouterr()


def test_bench_cast_record(capsys):
    """`egobench bench cast` (the simulator's ray-casting time; was a wall-clock bound in test_world)."""
    from egobench.cli import main

    rec = bench.bench_cast("cpu", repeats=1, side=8, samples=2)
    json.dumps(rec, allow_nan=False)
    assert rec["rays"] == 8 * 8 * 2 and rec["image"] == "8x8" and rec["scene"] == "indoor_0"
    assert rec["median_ms"] > 0 and rec["rays_per_s"] == round(128 / (rec["median_ms"] * 1e-3))
    assert set(rec["intersect"]) == {"compiled", "torch"}  # both closest-hit backends apply to CPU rays
    for t in rec["intersect"].values():
        assert t["share_of_cast"] == round(t["median_ms"] / rec["median_ms"], 4)
        assert t["rays_per_s"] == round(128 / (t["median_ms"] * 1e-3))
    assert main(["bench", "cast", "--repeats", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["benchmark"] == "cast" and out["rays"] == 128 * 128 * 8


def test_bench_cast_times_each_chunk_size_and_restores_the_simulators():
    """--chunk N times the chunked cast with N rays a call; the simulator's chunk sizes come back after."""
    from egobench.sim.capture import raw

    before = raw.CAST_CHUNK, raw.CAST_CHUNK_GPU
    rec = bench.bench_cast("cpu", repeats=1, side=8, samples=2, chunks=(16, 1000))
    assert set(rec["by_chunk"]) == {"16", "1000"} and (raw.CAST_CHUNK, raw.CAST_CHUNK_GPU) == before
    for c in rec["by_chunk"].values():
        assert c["rays_per_s"] == round(128 / (c["median_ms"] * 1e-3))
    with pytest.raises(ValueError, match="--chunk: expected a positive integer"):
        bench.bench_cast("cpu", repeats=1, side=8, samples=2, chunks=(0,))


def test_bench_cast_times_the_closest_hits_of_the_casts_rays_by_backend(monkeypatch):
    """The intersect timing calls `Scene.intersect` with the cast's rays, unit directions, and each backend."""
    from egobench.sim.world.scene import Scene

    seen, real = [], Scene.intersect

    def spy(self, origins, directions, t_max=None, backend="auto"):
        seen.append((backend, origins.shape[0], float((directions.norm(dim=-1) - 1).abs().max())))
        return real(self, origins, directions, t_max, backend)

    monkeypatch.setattr(Scene, "intersect", spy)
    bench.bench_cast("cpu", repeats=2, side=4, samples=2)
    explicit = [(b, n) for b, n, _ in seen if b != "auto"]  # Scene.cast's own calls take "auto"
    assert explicit == [("compiled", 32)] * 3 + [("torch", 32)] * 3  # one warm-up and two repeats each
    assert max(err for *_, err in seen) < 1e-6


def test_chunked_cast_does_not_depend_on_the_chunk_size():
    """Splitting the rays into Scene.cast calls of any size gives the same radiance, bit for bit
    (the GPU's chunk size changed from 2^18 to 2^22 rays on that ground)."""
    import numpy as np

    from egobench.sim.capture import raw
    from egobench.sim.world import make_scene

    scene = make_scene("outdoor", 0)
    rng = np.random.default_rng(3)
    n = 3000
    o = torch.tensor(scene.walk_region.center_point, dtype=torch.float32).expand(n, 3).contiguous()
    d = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32), dim=-1)
    saved = raw.CAST_CHUNK
    try:
        outs = []
        for chunk in (n, 257, 64):
            raw.CAST_CHUNK = chunk
            outs.append(raw.cast_chunked(scene, o, d, ("radiance", "depth_t"), pixel_angle_rad=1e-3))
    finally:
        raw.CAST_CHUNK = saved
    for other in outs[1:]:
        assert torch.equal(other["radiance"], outs[0]["radiance"]) and torch.equal(other["depth_t"], outs[0]["depth_t"])


def test_bench_raster_both_gives_the_2dgs_to_3dgs_ratio_and_thread_speedups(two_kernel_threads):
    rec = bench.bench_raster_both("cpu", repeats=1, backend="cpu", backends=("cpu",), cases=((16, 40, 2.5), (24, 60)))
    assert rec["mode"] == "both" and rec["3dgs"]["mode"] == "3dgs" and rec["2dgs"]["mode"] == "2dgs"
    for row, a, b in zip(rec["ratio_2dgs_to_3dgs"], rec["3dgs"]["cases"], rec["2dgs"]["cases"]):
        assert row["image"] == a["image"] == b["image"]
        assert row["ratio_2dgs_to_3dgs"] == pytest.approx(b["median_ms"] / a["median_ms"], abs=1e-3)
    for mode in ("3dgs", "2dgs"):
        by = rec[mode]["thread_scaling"]["by_threads"]
        assert rec["thread_speedup"][mode]["speedup_2_vs_1"] == pytest.approx(
            by["1"]["median_ms"] / by["2"]["median_ms"], abs=1e-3)
        sharing = rec[mode]["thread_scaling"]["core_sharing"]  # probed before and after the scaling runs
        assert rec["thread_speedup"][mode]["shared_cache"] is sharing["shared_cache"]
        assert {"before", "after"} <= set(sharing) and "cross_to_own" in sharing["before"]
