"""Per-stage timing of the compiled CPU backend (3DGS) on a `egobench bench raster` scene.

``python -m egobench.bench.cpu_profile [--sigma 2.5] [--repeats 41] [--threads 1]``: times each
stage of one forward + backward in isolation (median of repeats of process CPU time, or wall time
with ``--wall``; stages are re-run on the same inputs, so each one's time excludes the others'),
then the whole `render` + `loss.backward()` step of `egobench bench raster` and the part of it
outside the kernels (torch glue, autograd, conversions, allocations). Prints JSON.
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
from egobench.render import cpu_backend as cb


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


def stage_times(sigma_px: float = 2.5, width: int = 128, n: int = 20000, repeats: int = 41,
                tile_size: int = cb.DEFAULT_TILE) -> dict:
    """-> {stage: median ms} of the compiled backend's stages on the benchmark scene (float32)."""
    from egobench.render import cpu_kernels as ck
    from egobench.render import render

    spec = bench._case_spec((width, n, sigma_px))
    cam = bench.bench_camera(spec)
    g = bench.bench_scene(spec)
    T = torch.eye(4)[None]
    wts = torch.randn(1, width, width, 3, generator=torch.Generator().manual_seed(1))
    cb.set_threads()
    means, quats, scales = (t.detach().numpy() for t in (g.means, g.quats, g.scales))
    opac = torch.sigmoid(g.opacity_logits).detach().numpy()
    lo = F.logsigmoid(g.opacity_logits).detach().numpy()
    vm = T.numpy()
    ca = cb.camera_array(cam)
    I, N = 1, n
    m2 = np.empty((I, N, 2), np.float32)
    con = np.empty((I, N, 3), np.float32)
    dep = np.empty((I, N), np.float32)
    rad = np.empty((I, N, 2), np.int32)
    nrm = np.zeros((I, 0, 3), np.float32)
    args = (means, quats, scales, opac, vm, ca, width, width, cb.EPS2D, cb.NEAR_PLANE, cb.FAR_PLANE, False,
            m2, con, dep, rad, nrm)
    out = {}
    out["project_fwd"] = _median_ms(lambda: ck.project_fwd(*args), repeats)
    pix_view, bin_needed = cb.pixel_views(None, I, width, width, tile_size)
    tiles_x = math.ceil(width / tile_size)
    out["pixel_views"] = _median_ms(lambda: cb.pixel_views(None, I, width, width, tile_size), repeats)
    out["bin_tiles"] = _median_ms(lambda: ck.bin_tiles(m2, rad, dep, tile_size, tiles_x, tiles_x, bin_needed), repeats)
    t_m2, t_rad, t_dep, t_col = torch.from_numpy(m2), torch.from_numpy(rad), torch.from_numpy(dep), g.colors.detach()
    t_nrm = torch.from_numpy(nrm)
    st = cb.raster_setup(t_m2, t_rad, t_dep, t_col, t_nrm, pix_view, bin_needed, tile_size)
    out["raster_setup(incl. bin_tiles)"] = _median_ms(
        lambda: cb.raster_setup(t_m2, t_rad, t_dep, t_col, t_nrm, pix_view, bin_needed, tile_size), repeats)
    Cf = st.feats.shape[1]
    of = np.zeros((I, width, width, Cf), np.float32)
    oT = np.zeros((I, width, width), np.float32)
    ol = np.zeros((I, width, width), np.int32)
    tab = np.empty((I * N, ck.TAB_COLS), np.float32)
    out["gaussian_table"] = _median_ms(lambda: ck.gaussian_table(m2, con, rad, lo, ck.rows_needed(st.flat_ids, I * N),
                                                                 tab), repeats)
    rows_hit = cb.rows_hit_buffer(st.flat_ids.shape[0], tile_size, st.cw)
    fargs = (tab, st.feats, st.flat_ids, st.bin_start, st.bins, pix_view, tile_size, st.tiles_x, st.cw,
             st.kc, st.centres, of, oT, ol, rows_hit)
    out["raster_fwd"] = _median_ms(lambda: ck.raster_fwd(*fargs), repeats)
    rng = np.random.default_rng(0)
    gF = rng.standard_normal(of.shape).astype(np.float32)
    gT = rng.standard_normal(oT.shape).astype(np.float32)
    isect = np.zeros((st.flat_ids.shape[0], 6 + Cf), np.float32)
    bargs = (tab, st.feats, st.flat_ids, st.bin_start, st.bins, pix_view, tile_size, st.tiles_x, st.cw,
             st.kc, st.centres, oT, ol, gF, gT, isect, rows_hit)
    out["raster_bwd"] = _median_ms(lambda: ck.raster_bwd(*bargs), repeats)
    absg = np.zeros((I * N, 2))
    out["reduce_isect_grad"] = _median_ms(
        lambda: ck.reduce_isect_grad(isect, st.flat_ids, st.flat_ids.shape[0], np.zeros((isect.shape[1], I * N),
                                                                                         np.float32), absg), repeats)
    g_m2 = rng.standard_normal((2, I, N))  # channel first, as `reduce_isect_grad` writes them
    g_con = rng.standard_normal((3, I, N))
    g_dep = rng.standard_normal((I, N))
    gm, gq, gs = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
    gv = np.zeros((max(1, math.ceil(N / ck.CHUNK)), I, 12))
    pb = (means.astype(np.float64), quats.astype(np.float64), scales.astype(np.float64), vm.astype(np.float64), ca,
          width, width, cb.EPS2D, cb.NEAR_PLANE, cb.FAR_PLANE, False, g_m2, g_con, g_dep, np.zeros((3, I, 0)),
          gm, gq, gs, gv)
    out["project_bwd"] = _median_ms(lambda: ck.project_bwd(*pb), repeats)
    kernels = sum(out[k] for k in ("project_fwd", "raster_setup(incl. bin_tiles)", "gaussian_table", "raster_fwd",
                                   "raster_bwd", "reduce_isect_grad", "project_bwd"))
    out["sum_of_stages"] = kernels
    params = {k: v.detach().requires_grad_(True) for k, v in g.tensors().items()}

    def step():
        o = render(bench.Gaussians(**params), cam, T[0], backend="cpu", tile_size=tile_size)
        ((o.rgb * wts).sum() + 0.01 * o.depth.sum()).backward()

    out["render_fwd_bwd (bench step)"] = _median_ms(step, repeats)
    out["glue = step - stages"] = out["render_fwd_bwd (bench step)"] - kernels
    out["intersections"] = int(st.flat_ids.shape[0])
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sigma", type=float, default=2.5, help="median screen sigma, pixels")
    p.add_argument("--repeats", type=int, default=41)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--wall", action="store_true", help="wall time instead of process CPU time")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.wall:
        CLOCK["fn"] = time.perf_counter
    print(json.dumps({"sigma_px": a.sigma, "threads": a.threads, "clock": "wall" if a.wall else "process CPU",
                      "stages_ms": stage_times(a.sigma, repeats=a.repeats)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
