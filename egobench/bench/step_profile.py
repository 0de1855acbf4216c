"""Where a CPU training step's time goes: inside the compiled kernels, and between them.

``python -m egobench.bench.step_profile [--method ours] [--resolution 128] [--points 20000] [--iterations 150]
[--threads 1,2]``: trains `egobench bench train`'s scene (the textured plane, no densification) and times, in
wall time, every training step and every call of a compiled kernel (each numba dispatcher of the loaded
``egobench`` modules, wrapped at its module attribute for the timed run only). Per thread count it reports
the median step, the time inside kernel calls and the time between them: the Python and torch glue that a
second thread does not shorten (issue 32 item 2). Each kernel's and each gap's (kernel -> next kernel)
mean ms a step come with it. Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

from egobench.bench import _scaling_threads, _timed_training, train_config, train_scene, warm_up
from egobench.host import host_info, keep_freed_memory, setup_threads
from egobench.train import loop

#: the mark of a training step's start and end in the event list (not a kernel name)
STEP, END = "<step>", "<end>"


def _dispatchers(module) -> list[str]:
    """Names of the numba dispatchers of egobench's own kernels bound in ``module``: those it defines and those it
    re-exports (the package `egobench.render.cpu` holds its rooms' kernels, and the backends call them there)."""
    from numba.core.dispatcher import Dispatcher

    return [name for name, v in vars(module).items()
            if isinstance(v, Dispatcher) and str(getattr(v.py_func, "__module__", "")).startswith("egobench.")]


def _timed(name: str, fn, events: list):
    def call(*args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        events.append((name, t0, time.perf_counter()))
        return out
    return call


@contextmanager
def kernel_clock(events: list):
    """Within: every compiled kernel of the loaded ``egobench`` modules and the trainer's ``train_step`` append
    (name, start, end) to ``events`` (steps as `STEP` and `END` marks); the originals are put back on exit.
    Kernels must be compiled (or loaded) before: a kernel compiled within would see a wrapper as a global."""
    patched = []
    for mod in [m for k, m in list(sys.modules.items()) if k.startswith("egobench.") and m is not None]:
        for name in _dispatchers(mod):
            patched.append((mod, name, getattr(mod, name)))
            setattr(mod, name, _timed(name, getattr(mod, name), events))
    step = loop.train_step

    def marked_step(*args, **kwargs):
        events.append((STEP, time.perf_counter(), 0.0))
        out = step(*args, **kwargs)
        events.append((END, time.perf_counter(), 0.0))
        return out

    loop.train_step = marked_step
    try:
        yield
    finally:
        loop.train_step = step
        for mod, name, original in patched:
            setattr(mod, name, original)


def _steps(events: list) -> list[list]:
    """The event list cut into steps: [(STEP, t), (kernel, t0, t1)..., (END, t)] each."""
    steps, cur = [], None
    for ev in events:
        if ev[0] == STEP:
            cur = [ev]
        elif cur is not None:
            cur.append(ev)
            if ev[0] == END:
                steps.append(cur)
                cur = None
    return steps


def step_breakdown(events: list, skip: int = 0, top: int = 12) -> dict:
    """Events of `kernel_clock` -> per-step medians (ms) of the step, the kernels and the glue between them,
    each kernel's and each gap's mean ms a step (largest ``top`` gaps), over the steps after the first ``skip``."""
    steps = _steps(events)[skip:]
    if not steps:
        raise ValueError(f"step_breakdown: no complete training step after the first {skip}")
    totals, kernel_ms, gap_ms = [], defaultdict(float), defaultdict(float)
    for s in steps:
        inside, prev, prev_end = 0.0, "step start", s[0][1]
        for name, t0, t1 in s[1:-1]:
            gap_ms[f"{prev} -> {name}"] += 1e3 * (t0 - prev_end)
            kernel_ms[name] += 1e3 * (t1 - t0)
            inside += t1 - t0
            prev, prev_end = name, t1
        gap_ms[f"{prev} -> step end"] += 1e3 * (s[-1][1] - prev_end)
        totals.append((1e3 * (s[-1][1] - s[0][1]), 1e3 * inside))
    n = len(steps)
    step_med = statistics.median(t for t, _ in totals)
    kern_med = statistics.median(k for _, k in totals)
    gaps = sorted(((round(v / n, 3), k) for k, v in gap_ms.items()), reverse=True)
    return {"steps": n, "step_ms": round(step_med, 3), "kernels_ms": round(kern_med, 3),
            "between_kernels_ms": round(statistics.median(t - k for t, k in totals), 3),
            "kernel_calls_per_step": round(sum(len(s) - 2 for s in steps) / n, 1),
            "kernel_ms_per_step": {k: round(v / n, 3) for k, v in sorted(kernel_ms.items(), key=lambda kv: -kv[1])},
            "largest_gaps_ms_per_step": {k: v for v, k in gaps[:top]}}


def profile_training(method: str = "ours", side: int = 128, n_points: int = 20000, iterations: int = 150,
                     threads: tuple[int, ...] = (1, 2)) -> dict:
    """`step_breakdown` of one timed training run per thread count (after `bench.warm_up`), on `egobench bench
    train`'s scene and settings (`bench.train_scene`, `bench.train_config`); the first tenth of the steps is left
    out (allocations)."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        rec = train_scene(Path(tmp) / "rec", side, n_points)
        cfg = train_config(side, iterations)
        for n in threads:
            warm_up(rec, method, cfg, n, Path(tmp) / f"w{n}")
            events: list = []
            with kernel_clock(events):
                row = _timed_training(rec, method, cfg, n, Path(tmp) / f"t{n}")
            out[str(n)] = {"iters_per_s": row["iters_per_s"], "core_sharing": row["core_sharing"],
                           **step_breakdown(events, skip=max(1, iterations // 10))}
    return out


def main(argv: list[str] | None = None) -> int:
    setup_threads()  # an entry point (python -m)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--method", default="ours")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--iterations", type=int, default=150)
    p.add_argument("--threads", type=_scaling_threads, default=(1, 2), help="thread counts, e.g. 1,2")
    a = p.parse_args(argv)
    keep_freed_memory()  # as `egobench train` and `bench train`
    per_threads = profile_training(a.method, a.resolution, a.points, a.iterations, a.threads)
    print(json.dumps({"benchmark": "step_profile", "method": a.method, "resolution": a.resolution,
                      "points": a.points, "iterations": a.iterations, "clock": "wall",
                      "by_threads": per_threads, "host": host_info()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
