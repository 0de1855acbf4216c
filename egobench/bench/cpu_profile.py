"""Per-stage timing of the compiled CPU backend (3DGS and 2DGS) on a `egobench bench raster` scene.

``python -m egobench.bench.cpu_profile [--mode 3dgs|2dgs|both] [--sigma 2.5] [--repeats 41] [--threads 1]``: times each
stage of one forward + backward in isolation (median of repeats of process CPU time, or wall time
with ``--wall``; stages are re-run on the same inputs, so each one's time excludes the others'),
then the whole `render` + `loss.backward()` step of `egobench bench raster` and the part of it
outside the kernels (torch glue, autograd, conversions, allocations), and the work the compositing did
(intersections, those composited, the backward's pixel evaluations). ``--mode both``: each, and the
2DGS / 3DGS ratio of every stage and count. Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import numpy as np
import torch
import torch.nn.functional as F

from egobench import bench
from egobench.host import host_info, setup_threads
from egobench.render import cpu as ck
from egobench.render import cpu_backend as cb
from egobench.render import render
from egobench.render.cpu import surfels as k2


#: the clock of `_median_ms`: process CPU time (all threads) by default, which a shared machine's
#: other jobs disturb much less than wall time; ``--wall`` switches to wall time
CLOCK = {"fn": time.process_time}


def _median_ms(fn, repeats: int, warmup: int = 3) -> float:
    clock = CLOCK["fn"]
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        times.append((clock() - t0) * 1e3)
    return statistics.median(times)


def _work(rows_hit: np.ndarray, cw: int) -> dict:
    """Work counts from the forward's rows_hit [M, groups, 2]: intersections, those composited into any
    pixel (the backward visits only these), and the backward's pixel evaluations (rows x cw)."""
    span = np.clip(rows_hit[..., 1].astype(np.int64) - rows_hit[..., 0], 0, None)
    return {"intersections": int(rows_hit.shape[0]), "intersections_composited": int((span > 0).any(1).sum()),
            "backward_pixel_evals": int(span.sum()) * cw}


def _stages_3dgs(g, cam, width: int, n: int, tile_size: int, repeats: int) -> tuple[dict, dict]:
    """(stage -> median ms, work counts) of the 3DGS kernels on one pose."""
    means, quats, scales = (t.detach().numpy() for t in (g.means, g.quats, g.scales))
    opac = torch.sigmoid(g.opacity_logits).detach().numpy()
    lo = F.logsigmoid(g.opacity_logits).detach().numpy()
    vm, ca, I, N = np.eye(4, dtype=np.float32)[None], cb.camera_array(cam), 1, n
    m2, con = np.empty((I, N, 2), np.float32), np.empty((I, N, 3), np.float32)
    dep, rad, nrm = np.empty((I, N), np.float32), np.empty((I, N, 2), np.int32), np.zeros((I, 0, 3), np.float32)
    splats, view, proj = ck.Splats(means, quats, scales), cb.view_args(vm, ca, width, width), \
        ck.Projected(m2, con, dep, rad, nrm)
    out = {"project_fwd": _median_ms(lambda: ck.project_fwd(splats, opac, view, False, proj), repeats)}
    st, pix_view, setup_ms, bin_ms = _setup(m2, rad, dep, g.colors.detach(), nrm, width, tile_size, repeats)
    out["bin_tiles"], out["raster_setup(incl. bin_tiles)"] = bin_ms, setup_ms
    tab = cb.table_buffer(I * N, np.float32)
    out["table"] = _median_ms(lambda: ck.gaussian_table(m2, con, rad, lo, st.needed, tab), repeats)
    Cf = st.feats.shape[1]
    of, oT, ol = np.zeros((I, width, width, Cf), np.float32), np.zeros((I, width, width), np.float32), \
        np.zeros((I, width, width), np.int32)
    rows_hit = cb.rows_hit_buffer(st.flat_ids.shape[0], tile_size, st.cw)
    common = (ck.Tables(tab, st.feats), st.tiles(pix_view, tile_size), st.constants())
    out["raster_fwd"] = _median_ms(lambda: ck.raster_fwd(*common, ck.Composite(of, oT, ol), rows_hit), repeats)
    rng = np.random.default_rng(0)
    gF, gT = rng.standard_normal(of.shape).astype(np.float32), rng.standard_normal(oT.shape).astype(np.float32)
    isect = np.zeros((st.flat_ids.shape[0], 6 + Cf), np.float32)
    px = ck.BackwardPixels(oT, ol, gF, gT)
    out["raster_bwd"] = _median_ms(lambda: ck.raster_bwd(*common, px, isect, rows_hit), repeats)
    out["reduce_isect_grad"] = _reduce_ms(isect, st.flat_ids, I * N, repeats)
    # channel first, as `reduce_isect_grad` writes them
    grads = ck.ProjectedGrads(rng.standard_normal((2, I, N)), rng.standard_normal((3, I, N)),
                              rng.standard_normal((I, N)), np.zeros((3, I, 0)))
    splats64, vm64, res = _projection_bwd_buffers(means, quats, scales, vm, ck.CHUNK)
    view64 = cb.view_args(vm64, ca, width, width)
    out["project_bwd"] = _median_ms(lambda: ck.project_bwd(splats64, view64, False, grads, res), repeats)
    return out, _work(rows_hit, st.cw)


def _stages_2dgs(g, cam, width: int, n: int, tile_size: int, repeats: int) -> tuple[dict, dict]:
    """(stage -> median ms, work counts) of the 2DGS kernels on one pose (colour, depth, normal and the
    depth distortion, as `render(mode="2dgs")` composites them)."""
    means, quats, scales = (t.detach().numpy() for t in (g.means, g.quats, g.scales))
    lo = F.logsigmoid(g.opacity_logits).detach().numpy()
    vm, ca, I, N = np.eye(4, dtype=np.float32)[None], cb.camera_array(cam), 1, n
    m2, tsl, dep = np.empty((I, N, 2), np.float32), np.empty((I, N, 9), np.float32), np.empty((I, N), np.float32)
    nrm, rad = np.empty((I, N, 3), np.float32), np.empty((I, N, 2), np.int32)
    splats, view, proj = ck.Splats(means, quats, scales), cb.view_args(vm, ca, width, width), \
        ck.ProjectedSurfels(m2, tsl, dep, rad, nrm)
    out = {"project_fwd": _median_ms(lambda: k2.project_fwd_2dgs(splats, view, proj), repeats)}
    st, pix_view, setup_ms, bin_ms = _setup(m2, rad, dep, g.colors.detach(), nrm, width, tile_size, repeats)
    out["bin_tiles"], out["raster_setup(incl. bin_tiles)"] = bin_ms, setup_ms
    tab = cb.table_buffer(I * N, np.float32)
    out["table"] = _median_ms(lambda: k2.surfel_table(m2, tsl, lo, st.needed, tab), repeats)
    Cf = st.feats.shape[1]
    of, oT, ol = np.zeros((I, width, width, Cf + 1), np.float32), np.zeros((I, width, width), np.float32), \
        np.zeros((I, width, width), np.int32)
    rows_hit = cb.rows_hit_buffer(st.flat_ids.shape[0], tile_size, st.cw)
    common = (ck.SurfelTables(tsl, tab, st.feats), st.tiles(pix_view, tile_size), st.constants())
    out["raster_fwd"] = _median_ms(lambda: k2.raster_fwd_2dgs(*common, ck.Composite(of, oT, ol), rows_hit), repeats)
    rng = np.random.default_rng(0)
    g_state = rng.standard_normal((I, width, width, Cf + 2)).astype(np.float32)
    g_state[..., Cf + 1] = of[..., k2.DEPTH_CH]  # the forward's depth, as the backend passes it
    gT = rng.standard_normal(oT.shape).astype(np.float32)
    isect = np.zeros((st.flat_ids.shape[0], 12 + Cf), np.float32)
    px = ck.BackwardPixels(oT, ol, g_state, gT)
    out["raster_bwd"] = _median_ms(lambda: k2.raster_bwd_2dgs(*common, px, isect, rows_hit), repeats)
    out["reduce_isect_grad"] = _reduce_ms(isect, st.flat_ids, I * N, repeats)
    grads = ck.ProjectedSurfelGrads(rng.standard_normal((2, I, N)), rng.standard_normal((9, I, N)),
                                    rng.standard_normal((I, N)), rng.standard_normal((3, I, N)))
    splats64, vm64, res = _projection_bwd_buffers(means, quats, scales, vm, k2.CHUNK)
    view64 = cb.view_args(vm64, ca, width, width)
    out["project_bwd"] = _median_ms(lambda: k2.project_bwd_2dgs(splats64, view64, grads, res), repeats)
    return out, _work(rows_hit, st.cw)


def _setup(m2, rad, dep, colors, nrm, width: int, tile_size: int, repeats: int):
    """(`raster_setup`'s result, its pixel views, its median ms, `bin_tiles`' median ms)."""
    pix_view, bin_needed = cb.pixel_views(None, 1, width, width, tile_size)
    tiles_x = math.ceil(width / tile_size)
    args = (m2, torch.from_numpy(rad), torch.from_numpy(dep), colors, torch.from_numpy(nrm), pix_view,
            bin_needed, tile_size)
    st = cb.raster_setup(*args)
    bin_ms = _median_ms(lambda: ck.bin_tiles(m2, rad, dep, tile_size, tiles_x, tiles_x, bin_needed), repeats)
    return st, pix_view, _median_ms(lambda: cb.raster_setup(*args), repeats), bin_ms


def _projection_bwd_buffers(means, quats, scales, vm, chunk: int) -> tuple:
    """The projection backward's float64 inputs (`ck.Splats`, viewmats) and its outputs (`ck.SplatGrads`)."""
    N, I = means.shape[0], vm.shape[0]
    res = ck.SplatGrads(np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3)),
                        np.zeros((max(1, math.ceil(N / chunk)), I, 12)))
    return ck.Splats(*(a.astype(np.float64) for a in (means, quats, scales))), vm.astype(np.float64), res


def _reduce_ms(isect: np.ndarray, flat_ids: np.ndarray, rows: int, repeats: int) -> float:
    import numba

    out = np.empty((isect.shape[1], rows), np.float32)
    return _median_ms(lambda: ck.reduce_isect_grad(isect, flat_ids, flat_ids.shape[0], out, np.zeros((0, 2)),
                                                   numba.get_num_threads()), repeats)


#: the stages whose sum is ``sum_of_stages`` (``bin_tiles`` is inside ``raster_setup``)
STAGES = ("project_fwd", "raster_setup(incl. bin_tiles)", "table", "raster_fwd", "raster_bwd", "reduce_isect_grad",
          "project_bwd")


def stage_times(sigma_px: float = 2.5, width: int = 128, n: int = 20000, repeats: int = 41,
                tile_size: int = cb.DEFAULT_TILE, mode: str = "3dgs") -> dict:
    """-> {stage: median ms, and the work counts} of the compiled backend's stages on the benchmark
    scene (float32, one pose), mode "3dgs" or "2dgs"; the whole bench step and the glue outside the
    kernels (step - stages)."""
    spec = bench._case_spec((width, n, sigma_px))
    cam, g = bench.bench_camera(spec), bench.bench_scene(spec)
    cb.set_threads()
    cb.prepare_kernels(g.means.dtype, mode)  # time the cached kernels that every render runs
    stages = {"3dgs": _stages_3dgs, "2dgs": _stages_2dgs}[mode]
    out, work = stages(g, cam, width, n, tile_size, repeats)
    out["sum_of_stages"] = sum(out[k] for k in STAGES)
    params = {k: v.detach().requires_grad_(True) for k, v in g.tensors().items()}
    wts = torch.randn(1, width, width, 3, generator=torch.Generator().manual_seed(1))

    def step():
        o = render(bench.Gaussians(**params), cam, torch.eye(4), backend="cpu", tile_size=tile_size, mode=mode)
        ((o.rgb * wts).sum() + 0.01 * o.depth.sum()).backward()

    out["render_fwd_bwd (bench step)"] = _median_ms(step, repeats)
    out["glue = step - stages"] = out["render_fwd_bwd (bench step)"] - out["sum_of_stages"]
    out = {k: round(v, 3) for k, v in out.items()}
    out.update(work)
    out["ns_per_backward_pixel_eval"] = round(out["raster_bwd"] * 1e6 / max(1, work["backward_pixel_evals"]), 2)
    return out


def main(argv: list[str] | None = None) -> int:
    setup_threads()  # an entry point (python -m)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mode", choices=("3dgs", "2dgs", "both"), default="3dgs",
                   help="splat type (both: each and the ratio)")
    p.add_argument("--sigma", type=float, default=2.5, help="median screen sigma, pixels")
    p.add_argument("--repeats", type=int, default=41)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--wall", action="store_true", help="wall time instead of process CPU time")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.wall:
        CLOCK["fn"] = time.perf_counter
    modes = ("3dgs", "2dgs") if a.mode == "both" else (a.mode,)
    rec = {"sigma_px": a.sigma, "threads": a.threads, "clock": "wall" if a.wall else "process CPU",
           "host": host_info()}
    for m in modes:
        rec[f"stages_ms_{m}"] = stage_times(a.sigma, repeats=a.repeats, mode=m)
    if a.mode == "both":
        r3, r2 = rec["stages_ms_3dgs"], rec["stages_ms_2dgs"]
        rec["ratio_2dgs_to_3dgs"] = {k: round(r2[k] / r3[k], 2) for k in r3 if r3[k] > 0}
    print(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
