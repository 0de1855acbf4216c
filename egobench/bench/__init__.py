"""`egobench bench raster|train|cast`: micro-benchmarks printed as JSON.

``raster``: forward+backward time of `egobench.render.render` (median of repeats after warm-up)
on random but realistic scenes (sub-pixel and several-pixel Gaussians), for each backend asked
(on the CPU by default the compiled ``cpu`` backend beside the ``torch`` oracle), the first
backend's scaling from 1 to 2 kernel threads (torch at one, as `egobench train` runs), and the
cost of a rolling-shutter render (K pose samples) relative to a global-shutter render of the same image.
``train``: iterations/s, rasterizer time share and peak memory of `egobench.train.train` with and
without motion sampling on the synthetic `egobench.sim.plane.plane_recording` (or a given recording), at one or more
resolutions; ``--resolution 2400 --points 1000000 --device cuda`` is the paper-scale case.
``cast``: the simulator's ray casting (`egobench.sim.world.Scene.cast`, the cost of simulating a
frame): 128 x 128 rays x 8 temporal samples from inside the indoor scene in one call.
Where the compiled CPU kernels run on two or more threads, a timing is bracketed by `egobench.core_sharing`'s
probe (do the two threads share a cache? on a VM that changes within seconds and decides the two-thread
speed-up): a training run brackets its own iterations (train.json's ``train.core_sharing``), `bench raster`
its thread scaling.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import statistics
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

import egobench.train  # `egobench.train.train`, looked up at each call (tests replace it)
from egobench import core_sharing
from egobench.camera.pinhole import Pinhole
from egobench.core_sharing import split_by_sharing
from egobench.host import RASTER_THREADS_ENV, host_info, keep_freed_memory
from egobench.model.methods import get_method
from egobench.render import render
from egobench.render.types import Gaussians
from egobench.sim.capture import raw
from egobench.sim.plane import plane_recording
from egobench.sim.world import make_scene
from egobench.train import TrainConfig


@dataclass
class SceneSpec:
    """A random scene in front of an identity camera (stated in the benchmark's JSON)."""

    width: int  # image width = height, pixels
    num_gaussians: int  # number of Gaussians
    focal_px: float  # focal length, pixels (~ 80 deg field of view)
    depth_range_m: tuple[float, float]  # centres uniform in depth over this range, metres
    margin: float  # centres uniform over the image plus this fraction beyond each border
    sigma_px_median: float  # median screen-space standard deviation of the scales, pixels
    sigma_log_std: float  # log-normal spread of the per-axis scales
    opacity_logit_mean: float  # opacity logits ~ N(mean, 1)
    seed: int


def bench_camera(spec: SceneSpec) -> Pinhole:
    w = spec.width
    return Pinhole(fx=spec.focal_px, fy=spec.focal_px, cx=(w - 1) / 2, cy=(w - 1) / 2, width=w, height=w)


def bench_scene(spec: SceneSpec, device: str = "cpu", dtype: torch.dtype = torch.float32) -> Gaussians:
    """Gaussians spread through the frustum; screen sizes of a few pixels."""
    g = torch.Generator().manual_seed(spec.seed)
    n, w = spec.num_gaussians, spec.width
    z0, z1 = spec.depth_range_m
    z = z0 + (z1 - z0) * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * (1 + 2 * spec.margin) - spec.margin) * w
    v = (torch.rand(n, generator=g) * (1 + 2 * spec.margin) - spec.margin) * w
    c = (w - 1) / 2
    means = torch.stack([(u - c) / spec.focal_px * z, (v - c) / spec.focal_px * z, z], -1)
    s_px = spec.sigma_px_median * torch.exp(spec.sigma_log_std * torch.randn(n, 3, generator=g))
    scales = s_px * z[:, None] / spec.focal_px
    out = Gaussians(
        means=means, quats=torch.randn(n, 4, generator=g), log_scales=scales.log(),
        opacity_logits=spec.opacity_logit_mean + torch.randn(n, generator=g), colors=torch.rand(n, 3, generator=g),
    )
    return Gaussians(**{k: t.to(device=device, dtype=dtype) for k, t in out.tensors().items()})


def rolling_shutter_poses(K: int, readout_s: float, deg_per_s: float, device: str = "cpu") -> torch.Tensor:
    """[K, 4, 4] camera-to-world poses of K samples spread over the readout (yaw at deg_per_s)."""
    t = (torch.arange(K, dtype=torch.float64) + 0.5) / K * readout_s - readout_s / 2
    ang = torch.deg2rad(torch.tensor(deg_per_s, dtype=torch.float64)) * t
    T = torch.eye(4, dtype=torch.float64).repeat(K, 1, 1)
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = ang.cos(), ang.sin(), -ang.sin(), ang.cos()
    return T.to(device=device, dtype=torch.float32)


def row_index_image(K: int, H: int, W: int, device: str = "cpu") -> torch.Tensor:
    """[H, W] pose-sample index round(R * (K - 1)) with R = row / (H - 1) (the authors' rule)."""
    r = torch.arange(H, dtype=torch.float64) / max(H - 1, 1)
    return torch.round(r * (K - 1)).long()[:, None].expand(H, W).contiguous().to(device)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_fwd_bwd(fn, device: str, repeats: int, warmup: int = 2) -> dict:
    """Median / min wall time (ms) of fn() (which runs forward and backward)."""
    for _ in range(warmup):
        fn()
    times, cpu = [], []
    for _ in range(repeats):
        _sync(device)
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return {"median_ms": round(statistics.median(times), 2), "min_ms": round(min(times), 2),
            "cpu_median_ms": round(statistics.median(cpu), 2), "repeats": repeats}


def _step(g: Gaussians, cam: Pinhole, T: torch.Tensor, weights: torch.Tensor, **kw):
    params = {k: v.detach().requires_grad_(True) for k, v in g.tensors().items()}

    def fn():
        out = render(Gaussians(**params), cam, T, **kw)
        loss = (out.rgb * weights).sum() + 0.01 * out.depth.sum()
        loss.backward()
        return out

    return fn


#: (image width = height, number of Gaussians, median screen sigma in pixels) of the timed cases:
#: sub-pixel Gaussians and realistic several-pixel ones (the cost grows with the covered area)
RASTER_CASES = ((64, 2000, 0.8), (128, 20000, 0.8), (128, 20000, 2.5))


def default_backends(backend: str, device: str) -> tuple[str, ...]:
    """Backends a raster benchmark times: "auto" on the CPU compares the compiled backend with the
    torch oracle; otherwise the one asked for."""
    if backend == "auto" and not device.startswith("cuda"):
        return ("cpu", "torch")
    return (backend,)


def _case_spec(case: tuple) -> SceneSpec:
    width, n = case[0], case[1]
    sigma = case[2] if len(case) > 2 else 0.8
    return SceneSpec(width=width, num_gaussians=n, focal_px=0.6 * width, depth_range_m=(2.0, 8.0), margin=0.1,
                     sigma_px_median=sigma, sigma_log_std=0.3, opacity_logit_mean=0.0, seed=0)


def _time_backends(g, cam, T, w, backends, tile_size, device, repeats, **kw) -> dict:
    out = {}
    for b in backends:
        out[b] = time_fwd_bwd(_step(g, cam, T, w, backend=b, tile_size=tile_size, **kw), device, repeats)
    return out


def bench_raster_both(device: str = "cpu", **kw) -> dict:
    """3DGS and 2DGS on the same scenes: both records, and per case the 2DGS / 3DGS time ratio (first
    backend) and each mode's thread speed-up, side by side (issue 32's targets)."""
    r3, r2 = bench_raster(device, mode="3dgs", **kw), bench_raster(device, mode="2dgs", **kw)
    ratios = [{"image": a["image"], "sigma_px_median": a["scene"]["sigma_px_median"], "ms_3dgs": a["median_ms"],
               "ms_2dgs": b["median_ms"], "ratio_2dgs_to_3dgs": round(b["median_ms"] / a["median_ms"], 3)}
              for a, b in zip(r3["cases"], r2["cases"])]
    scaling = {"3dgs": r3.get("thread_scaling", {}), "2dgs": r2.get("thread_scaling", {})}
    speedup = {m: {**{k: v for k, v in ts.items() if k.startswith("speedup_")},
                   "shared_cache": ts.get("core_sharing", {}).get("shared_cache")} for m, ts in scaling.items()}
    return {"benchmark": "raster", "mode": "both", "ratio_2dgs_to_3dgs": ratios, "thread_speedup": speedup,
            "3dgs": r3, "2dgs": r2}


def bench_raster(device: str = "cpu", repeats: int = 7, backend: str = "auto", tile_size: int | None = None,
                 cases: tuple[tuple, ...] = RASTER_CASES, backends: tuple[str, ...] | None = None,
                 scaling_threads: tuple[int, ...] = (1, 2), mode: str = "3dgs") -> dict:
    """The rasterizer benchmark record (see module docstring). Every case is timed for each backend
    (top-level timings: the first); the first backend's thread scaling (CPU) and the rolling-shutter
    comparison use the last case's scene. tile_size None: each backend's default. mode: "3dgs" or
    "2dgs" (the same scenes rendered as surfels: the first two scales are the surfel's axes)."""
    backends = tuple(backends or default_backends(backend, device))
    result: dict = {
        "benchmark": "raster", "torch": torch.__version__, "threads": torch.get_num_threads(), "device": device,
        "backend": backends[0], "backends": list(backends), "tile_size": tile_size, "mode": mode, "cases": [],
        "note": "wall time of forward+backward (colour and depth losses), median of repeats after 2 warm-up runs "
                "(cpu_median_ms: process CPU time, all threads); noisy on a shared machine",
    }
    T = torch.eye(4, device=device)
    for c in cases:
        spec = _case_spec(c)
        cam = bench_camera(spec)
        g = bench_scene(spec, device)
        w = torch.randn(1, spec.width, spec.width, 3, generator=torch.Generator().manual_seed(1)).to(device)
        with torch.no_grad():
            probe = render(g, cam, T, backend=backends[0], tile_size=tile_size, mode=mode)
        r = probe.radii[probe.radii > 0].float()
        case = {"image": f"{spec.width}x{spec.width}", "scene": asdict(spec),
                "visible_gaussians": int(r.numel()), "mean_screen_radius_px": round(float(r.mean()), 2),
                "mean_alpha": round(float(probe.alpha.mean()), 3)}
        timed = _time_backends(g, cam, T, w, backends, tile_size, device, repeats, mode=mode)
        case.update(timed[backends[0]])
        case["by_backend"] = timed
        if len(backends) > 1:
            case["speedup_vs_" + backends[1]] = round(timed[backends[1]]["median_ms"] / timed[backends[0]]["median_ms"], 2)
        result["cases"].append(case)

    import numba

    if not device.startswith("cuda") and scaling_threads and max(scaling_threads) > numba.config.NUMBA_NUM_THREADS:
        result["thread_scaling"] = {"skipped": f"numba's pool has {numba.config.NUMBA_NUM_THREADS} thread(s) "
                                               f"(NUMBA_NUM_THREADS / OMP_NUM_THREADS when it loaded)"}
    elif not device.startswith("cuda") and scaling_threads:
        scaling = {}
        with core_sharing.bracketing() as sharing:
            for n_threads in scaling_threads:
                with cpu_threads(n_threads, torch_n=1):
                    scaling[str(n_threads)] = time_fwd_bwd(_step(g, cam, T, w, backend=backends[0],
                                                                 tile_size=tile_size, mode=mode), device, repeats)
        result["thread_scaling"] = {"backend": backends[0], "image": case["image"], "policy": RASTER_THREAD_POLICY,
                                    "sigma_px_median": spec.sigma_px_median, "by_threads": scaling,
                                    "core_sharing": sharing}
        first, last = str(scaling_threads[0]), str(scaling_threads[-1])
        result["thread_scaling"][f"speedup_{last}_vs_{first}"] = round(
            scaling[first]["median_ms"] / scaling[last]["median_ms"], 3)

    # rolling shutter: K = 8 samples over a 16 ms readout at 300 deg/s, on the last scene
    K, readout_s, speed = 8, 0.016, 300.0
    Ts = rolling_shutter_poses(K, readout_s, speed, device)
    idx = row_index_image(K, cam.height, cam.width, device)
    b0 = backends[0]
    gs = time_fwd_bwd(_step(g, cam, Ts[K // 2], w, backend=b0, tile_size=tile_size, mode=mode), device, repeats)
    rs = time_fwd_bwd(_step(g, cam, Ts, w, backend=b0, tile_size=tile_size, pixel_pose_index=idx, mode=mode), device,
                      repeats)
    ref = time_fwd_bwd(_step(g, cam, Ts, w[:1].expand(K, -1, -1, -1), backend=b0, tile_size=tile_size, mode=mode),
                       device, max(1, repeats // 2), warmup=1)
    result["rolling_shutter"] = {
        "backend": b0, "image": f"{cam.width}x{cam.height}", "pose_samples": K, "readout_s": readout_s,
        "yaw_deg_per_s": speed, "global_shutter_ms": gs["median_ms"], "rolling_shutter_ms": rs["median_ms"],
        "ratio": round(rs["median_ms"] / gs["median_ms"], 3),
        "cpu_ratio": round(rs["cpu_median_ms"] / max(gs["cpu_median_ms"], 1e-9), 3),
        "render_K_images_ms": ref["median_ms"],
    }
    return result


#: how each benchmark's thread scaling sets threads: the raster benchmark scales the compiled kernels
#: alone (with numba's workqueue layer torch's spinning pool competed with them; under the OpenMP layer
#: torch at N threads measured the same as at 1, results/speed/README.md, 2026-11-26); the training
#: benchmark times what `egobench train` does by default on the CPU
RASTER_THREAD_POLICY = "torch 1 thread, compiled kernels N (the kernels' own scaling)"
TRAIN_THREAD_POLICY = "torch N threads, compiled kernels N (egobench.host.default_threads)"


@contextmanager
def cpu_threads(n: int, torch_n: int | None = None):
    """Within: the compiled kernels at ``n`` threads and torch at ``torch_n`` (default ``n``); 0 leaves
    both as they are. numba's pool must hold ``n`` (NUMBA_NUM_THREADS, or OMP_NUM_THREADS when numba
    first loads). Both counts are restored after."""
    if not n:
        yield
        return
    import numba

    if n > numba.config.NUMBA_NUM_THREADS:
        raise ValueError(f"--scaling/threads {n}: numba's pool has {numba.config.NUMBA_NUM_THREADS} threads "
                         f"(set NUMBA_NUM_THREADS={n} or leave OMP_NUM_THREADS unset)")
    before, saved = torch.get_num_threads(), os.environ.get(RASTER_THREADS_ENV)
    torch.set_num_threads(n if torch_n is None else torch_n)
    os.environ[RASTER_THREADS_ENV] = str(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
        if saved is None:
            os.environ.pop(RASTER_THREADS_ENV, None)
        else:
            os.environ[RASTER_THREADS_ENV] = saved


#: untimed training iterations of each method before `bench_train` times it: without them the first
#: timed run of a method paid its kernels' compilation (cold numba cache: most of a 100-iteration run)
#: or cache loading (warm: 4-12 % of it at 128 px on a Zen 4 box).
WARMUP_ITERATIONS = 3


def train_scene(folder, side: int, n_points: int):
    """The training benchmark's recording: `egobench.sim.plane.plane_recording` (17 frames, a textured plane,
    ``n_points`` semi-dense points) at ``side`` px, written to ``folder``."""
    return plane_recording(folder, size=side, n_frames=17, angular_speed_rad_s=6.0, frame_interval_s=0.01,
                           n_points=n_points)


def train_config(side: int, iterations: int, device: str = "cpu", backend: str = "auto"):
    """The training benchmark's `TrainConfig`: no motion warm-up and no densification (the Gaussian count stays)."""
    return TrainConfig(iterations=iterations, max_side=side, device=device, backend=backend,
                       motion_warmup_frac=0.0, refine_start_frac=1.0)


def warm_up(rec, method: str, cfg, n_threads: int, out_dir) -> None:
    """`WARMUP_ITERATIONS` untimed iterations of ``method`` (threads: `cpu_threads`): its kernels compiled or
    loaded, first-touch allocations made, before any timing."""
    with cpu_threads(n_threads):
        egobench.train.train(rec, method, dataclasses.replace(cfg, iterations=WARMUP_ITERATIONS), out_dir, progress=False)


def _timed_training(rec, method: str, cfg, n_threads: int, out_dir) -> dict:
    """One timed training run (threads: `cpu_threads`) -> its benchmark row (it/s, the rasterizer's share,
    peak memory: CUDA's allocator peak or the process's max RSS so far)."""
    device = cfg.device
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    with cpu_threads(n_threads):
        res = egobench.train.train(rec, method, cfg, out_dir, progress=False)
    if device.startswith("cuda"):
        peak, kind = torch.cuda.max_memory_allocated() / 2**20, "cuda max_memory_allocated"
    else:
        peak, kind = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "process max RSS (cumulative)"
    spec = get_method(method)
    return {"method": method, "threads": n_threads or torch.get_num_threads(),
            "motion_sampling": spec.motion_sampling == "adaptive", "splat_mode": spec.splat_mode,
            "resolution": cfg.max_side, "iterations": cfg.iterations, "iters_per_s": round(res.iters_per_s, 3),
            "raster_time_share": round(res.raster_time_share, 3), "num_gaussians": res.num_gaussians,
            "pose_samples_mean": res.record["motion_samples"]["mean"],
            "peak_memory_mib": round(peak, 1), "peak_memory_kind": kind,
            "core_sharing": res.record["train"]["core_sharing"]}  # where two threads sat decides their speed-up


def bench_train(device: str = "cpu", backend: str = "auto", sides: tuple[int, ...] = (64, 128),
                iterations: int = 30, recording: str | None = None, n_points: int = 4000,
                methods: tuple[str, ...] = ("no_motion_sampling", "ours"), threads: tuple[int, ...] = (),
                rounds: int = 1) -> dict:
    """The training benchmark record: one row per (resolution, method[, threads]) with iterations/s,
    the rasterizer's share of the step time, the Gaussian count and peak memory (CUDA: the allocator's
    peak for that run; CPU: the process's max RSS so far). No densification (refine_start_frac=1),
    so the Gaussian count stays ``n_points`` (or the recording's semi-dense point count).
    ``threads`` (CPU): time every case at each of these thread counts, torch's and the kernels' alike
    (`cpu_threads`, as `egobench train` runs by default). The record's
    ``ratio_2dgs_to_3dgs`` pairs each 2DGS method with its 3DGS twin (time per iteration), and
    ``thread_speedup`` gives each case's it/s at the last thread count over the first. Each method
    first trains `WARMUP_ITERATIONS` untimed iterations at each resolution. ``rounds`` > 1 times every
    case that many times, the order of the cases reversed every other round (drift weighs on both
    ends alike); ratios and speed-ups are then taken within each round and given as the median over
    rounds with the per-round values (a noisy machine: compare like with like, in the same round)."""
    for method in methods:
        get_method(method)  # an unknown name fails before any work

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for side in sides:
            rec = recording or train_scene(Path(tmp) / f"rec{side}", side, n_points)
            cfg = train_config(side, iterations, device, backend)
            for method in dict.fromkeys(methods):  # compile or load the method's kernels before any timing
                warm_up(rec, method, cfg, (threads or (0,))[0], Path(tmp) / f"warmup_{method}{side}")
            cases = [(m, t) for m in methods for t in (threads or (0,))]
            for rnd, (method, n_threads) in [(r, c) for r in range(rounds) for c in (cases[::-1] if r % 2 else cases)]:
                out_dir = Path(tmp) / f"{method}{side}t{n_threads}r{rnd}"
                results.append({**_timed_training(rec, method, cfg, n_threads, out_dir), "round": rnd})
    return {"benchmark": "train", "device": device, "backend": backend, "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "recording": str(recording) if recording else f"plane_recording (17 frames, textured plane, {n_points} points)",
            "thread_policy": TRAIN_THREAD_POLICY if threads else None, "rounds": rounds,
            "warmup": f"{WARMUP_ITERATIONS} untimed iterations of each method at each resolution first (kernel "
                      "compilation or cache loading, first-touch allocations)",
            "results": results, "ratio_2dgs_to_3dgs": train_2dgs_ratios(results),
            "thread_speedup": train_thread_speedups(results)}


#: Each 2DGS method and the 3DGS method it differs from only in the splat.
TWIN_3DGS = {"ours_2dgs": "ours", "2dgs_no_motion_sampling": "no_motion_sampling"}


def _over_rounds(per_round: list[float]) -> dict:
    """Per-round values -> their median (3 decimals) and the values themselves."""
    return {"median": round(statistics.median(per_round), 3), "per_round": [round(v, 3) for v in per_round]}


def train_2dgs_ratios(rows: list[dict]) -> list[dict]:
    """Time per iteration of each 2DGS method over its 3DGS twin's, per (resolution, threads), taken within
    each round: ``ratio_2dgs_to_3dgs`` is the median over rounds, ``per_round`` the values."""
    speed = {(r["method"], r["resolution"], r["threads"], r.get("round", 0)): r["iters_per_s"] for r in rows}
    rounds = sorted({k[3] for k in speed})
    out = []
    for m2, side, t in dict.fromkeys(k[:3] for k in speed):
        m3 = TWIN_3DGS.get(m2)
        per = [speed[(m3, side, t, r)] / speed[(m2, side, t, r)] for r in rounds
               if (m2, side, t, r) in speed and (m3, side, t, r) in speed]
        if per:
            agg = _over_rounds(per)
            out.append({"method_2dgs": m2, "method_3dgs": m3, "resolution": side, "threads": t,
                        "ratio_2dgs_to_3dgs": agg["median"], "per_round": agg["per_round"]})
    return out


def train_thread_speedups(rows: list[dict]) -> list[dict]:
    """it/s at the most threads over it/s at the fewest, per (method, resolution) timed at several, taken
    within each round: the median over rounds and ``per_round``; ``per_round_shared_cache`` whether that
    round's multi-thread run had its threads on one shared cache (`core_sharing.bracket`), and the
    medians of the rounds that had and had not (``by_core_sharing``)."""
    out = []
    for method, side in dict.fromkeys((r["method"], r["resolution"]) for r in rows):
        mine = [r for r in rows if (r["method"], r["resolution"]) == (method, side)]
        counts = sorted({r["threads"] for r in mine})
        if len(counts) > 1:
            lo, hi = counts[0], counts[-1]
            per, shared = [], []
            for rnd in dict.fromkeys(r.get("round", 0) for r in mine):
                by_t = {r["threads"]: r for r in mine if r.get("round", 0) == rnd}
                per.append(by_t[hi]["iters_per_s"] / by_t[lo]["iters_per_s"])
                shared.append((by_t[hi].get("core_sharing") or {}).get("shared_cache"))
            agg = _over_rounds(per)
            out.append({"method": method, "resolution": side, "threads": [lo, hi],
                        f"speedup_{hi}_vs_{lo}": agg["median"], "per_round": agg["per_round"],
                        "per_round_shared_cache": shared, "by_core_sharing": split_by_sharing(per, shared)})
    return out


def bench_cast(device: str = "cpu", repeats: int = 7, kind: str = "indoor", side: int = 128,
               samples: int = 8, chunks: tuple[int, ...] = ()) -> dict:
    """The ray-casting benchmark record: side x side x samples rays from near the walk region's
    centre in random directions through `Scene.cast` (texture footprint of a side-pixel image).
    ``chunks``: also time `cast_chunked` over the same rays with each chunk size (rays per
    Scene.cast call, as the simulator's frames are cast), to show where per-call overhead ends."""
    scene = make_scene(kind, 0)
    rng = np.random.default_rng(0)
    n = side * side * samples
    eye = torch.tensor(scene.walk_region.center_point, dtype=torch.float32)
    origins = (eye + 0.01 * torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32)).contiguous().to(device)
    directions = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32), dim=-1)
    directions = directions.to(device)
    timing = time_fwd_bwd(lambda: scene.cast(origins, directions, pixel_angle_rad=1 / side), device, repeats,
                          warmup=1)
    by_chunk = {str(c): _time_cast_chunked(scene, origins, directions, 1 / side, c, device, repeats) for c in chunks}
    return {"benchmark": "cast", "device": device, "torch": torch.__version__, "threads": torch.get_num_threads(),
            "scene": f"{kind}_0", "rays": n, "image": f"{side}x{side}", "temporal_samples": samples,
            "median_ms": timing["median_ms"], "min_ms": timing["min_ms"],
            "cpu_median_ms": timing["cpu_median_ms"], "repeats": repeats,
            "rays_per_s": round(n / (timing["median_ms"] * 1e-3)), "by_chunk": by_chunk,
            "intersect": _time_intersect(scene, origins, directions, device, repeats, timing["median_ms"]),
            "note": "wall time of one Scene.cast call, median of repeats after 1 warm-up; noisy on a shared machine; "
                    "intersect: the closest-hit tests alone on the same rays, by backend (Scene.cast takes "
                    "'compiled' on the CPU, 'torch' elsewhere), and their share of the cast: what a faster ray "
                    "caster could remove"}


def _time_intersect(scene, origins, directions, device: str, repeats: int, cast_ms: float) -> dict:
    """`Scene.intersect` alone over the cast's rays, per backend that applies here: median ms, rays/s and the share
    of one `Scene.cast` call's ``cast_ms``."""
    unit = torch.nn.functional.normalize(directions, dim=-1)
    out = {}
    for backend in (("compiled", "torch") if str(device) == "cpu" else ("torch",)):
        t = time_fwd_bwd(lambda: scene.intersect(origins, unit, backend=backend), device, repeats, warmup=1)
        out[backend] = {"median_ms": t["median_ms"], "rays_per_s": round(origins.shape[0] / (t["median_ms"] * 1e-3)),
                        "share_of_cast": round(t["median_ms"] / cast_ms, 4)}
    return out


def _time_cast_chunked(scene, origins, directions, pixel_angle_rad: float, chunk: int, device: str,
                       repeats: int) -> dict:
    """`cast_chunked` over all rays with ``chunk`` rays per Scene.cast call: median ms and rays/s."""
    if chunk < 1:
        raise ValueError(f"--chunk: expected a positive integer, got {chunk}")
    saved = raw.CAST_CHUNK, raw.CAST_CHUNK_GPU
    raw.CAST_CHUNK = raw.CAST_CHUNK_GPU = chunk
    try:
        t = time_fwd_bwd(lambda: raw.cast_chunked(scene, origins, directions, pixel_angle_rad=pixel_angle_rad),
                         device, repeats, warmup=1)
    finally:
        raw.CAST_CHUNK, raw.CAST_CHUNK_GPU = saved
    return {"median_ms": t["median_ms"], "rays_per_s": round(origins.shape[0] / (t["median_ms"] * 1e-3))}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", choices=["raster", "train", "cast"], help="which benchmark")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats (median reported)")
    parser.add_argument("--backend", action="append", choices=["auto", "torch", "gsplat", "cpu"],
                        help="rasterizer backend (repeatable: raster times each; default: cpu and torch on the CPU, "
                             "auto elsewhere; train uses the first)")
    parser.add_argument("--tile-size", type=int, default=None,
                        help="tile size in pixels (default: each backend's, see egobench.render.render)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--mode", choices=["3dgs", "2dgs", "both"], default="3dgs",
                        help="raster benchmark: splat type (both: each, with the 2DGS / 3DGS time ratio per case)")
    parser.add_argument("--side", type=int, default=128, help="cast benchmark: image side (rays: side^2 x 8)")
    parser.add_argument("--chunk", type=int, action="append", default=[],
                        help="cast benchmark: also time the chunked cast with this many rays per call (repeatable)")
    train = parser.add_argument_group("train benchmark")
    train.add_argument("--resolution", type=int, action="append",
                       help="training image side in pixels (repeatable; default 64 and 128; paper: 2400)")
    train.add_argument("--iterations", type=int, default=30, help="training iterations per case")
    train.add_argument("--points", type=int, default=4000,
                       help="initial Gaussians of the synthetic recording (kept: no densification)")
    train.add_argument("--recording", default=None, help="a recording folder instead of the synthetic one")
    train.add_argument("--method", action="append",
                       help="method to train (repeatable; default no_motion_sampling and ours; e.g. ours_2dgs)")
    train.add_argument("--rounds", type=int, default=1,
                       help="time every case this many times, alternating their order; ratios and speed-ups "
                            "per round, reported as medians with the per-round values")
    parser.add_argument("--scaling", default="",
                        help="comma-separated thread counts (e.g. 1,2,4). train: every case at each, torch's and "
                             "the compiled kernels' alike, as `egobench train` sets them; raster (CPU): the last "
                             "case's kernels at each, torch at one (default 1,2)")


def run(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda: CUDA is not available on this machine")
    if args.repeats < 1:
        raise ValueError(f"--repeats: expected a positive integer, got {args.repeats}")
    chosen = args.backend if isinstance(args.backend, (list, tuple)) else [args.backend or "auto"]
    chosen = chosen or ["auto"]
    threads = _scaling_threads(args.scaling)
    if args.what == "raster":
        backends = default_backends(chosen[0], args.device) if len(chosen) == 1 else tuple(chosen)
        kw = dict(repeats=args.repeats, backend=chosen[0], tile_size=args.tile_size, backends=backends,
                  scaling_threads=threads or (1, 2))
        _report(bench_raster_both(args.device, **kw) if args.mode == "both" else
                bench_raster(args.device, mode=args.mode, **kw))
        return 0
    if args.what == "cast":
        _report(bench_cast(args.device, args.repeats, side=args.side, chunks=tuple(args.chunk)))
        return 0
    for name in ("iterations", "points", "rounds"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: expected a positive integer, got {getattr(args, name)}")
    sides = tuple(args.resolution or (64, 128))
    if min(sides) < 8:
        raise ValueError(f"--resolution: expected at least 8 pixels, got {min(sides)}")
    methods = tuple(args.method or ("no_motion_sampling", "ours"))
    if not args.device.startswith("cuda"):
        keep_freed_memory()  # as `egobench train` runs on the CPU (host.allocator in the record)
    _report(bench_train(args.device, chosen[0], sides, args.iterations, args.recording, args.points, methods,
                        threads, args.rounds))
    return 0


def _scaling_threads(text: str) -> tuple[int, ...]:
    """--scaling's comma-separated thread counts ("" -> ())."""
    parts = [t.strip() for t in text.split(",") if t.strip()]
    if not all(t.isdigit() for t in parts) or any(int(t) < 1 for t in parts):
        raise ValueError(f"--scaling: expected comma-separated positive thread counts, got {text!r}")
    return tuple(int(t) for t in parts)


def _report(result: dict) -> None:
    """Print a benchmark's JSON with the machine it ran on (CPU model, kernel target, torch's ISA, versions)."""
    print(json.dumps({**result, "host": host_info()}, indent=2))
