"""Background jobs of selected tests (a cold numba compile, the CI workflow end to end): conftest
starts them after collection, one at a time on one worker thread in the order of the tests, so that
their subprocesses overlap the rest of the suite on a second core; each test then waits for its own
job's result. A test module declares its jobs as ``BACKGROUND = {test name: job}``. Under pytest-xdist
(the default, pyproject's addopts) every worker collects every test, so conftest submits nothing and a
job starts when its test asks for it; the other workers keep the other cores busy. A worker's jobs are its
own, so on a cold numba cache the first two workers compile the rasterizer's kernel sets once each before
their first test, coordinated through files (`warm_up`)."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]
#: in a pytest-xdist worker (every worker collects every test; the other workers use the other cores)
UNDER_XDIST = bool(os.environ.get("PYTEST_XDIST_WORKER"))
_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="egobench-test-background")
_JOBS: dict[str, Future] = {}


def start(module: ModuleType, test_name: str) -> Future | None:
    """The background job of ``module``'s test ``test_name`` (submitted once) -> its future; None when
    the module declares none for that test."""
    job = getattr(module, "BACKGROUND", {}).get(test_name)
    if job is None:
        return None
    key = f"{module.__name__}::{test_name}"
    if key not in _JOBS:
        _JOBS[key] = _POOL.submit(job)
    return _JOBS[key]


def compile_kernels(dtype: str, modes: tuple[str, ...]):
    """A job that compiles the CPU rasterizer's kernels of ``modes`` ("3dgs", "2dgs") for ``dtype``
    ("float32", "float64") into numba's cache in a subprocess -> its CompletedProcess. On a cold cache
    the compiles (~40 s per mode and dtype here) then run on the second core, and the tests that need
    those kernels, waiting for the job first, load them instead of compiling them again; on a warm
    cache the job only loads them."""
    script = render_script(modes, (dtype,))
    return lambda: run_script(script, timeout=1200)


def run_script(script: str, timeout: float, **env: str) -> subprocess.CompletedProcess:
    """``python -c script`` in the repository (importable as such), one thread, with ``env`` added to
    this process's environment (e.g. NUMBA_CACHE_DIR) -> its CompletedProcess (output captured)."""
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO), **env)
    return subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)


def wait_for_kernels(module: ModuleType, test_name: str) -> None:
    """Waits for the `compile_kernels` job that ``module`` declares for ``test_name``; fails, with its
    error output, if that compile failed. Kept under xdist: skipping it (the test compiling the kernels
    in its own worker) measured slower on a cold cache, 425.0 s against 389.6-406.5 s of fresh-clone pytest."""
    done = start(module, test_name).result(timeout=1300)
    assert done.returncode == 0, done.stderr[-2000:]


# Renders the edge-case scene of each set in {modes} in each dtype of {dtypes}, global and rolling shutter,
# and backpropagates (every compiled kernel of that set and dtype); prints one JSON line: per set and dtype,
# one digest of every map and gradient, numba's cache hits and misses of the set's rasterizer kernels
# (`kernel_build.KERNELS`) in this process, and how the kernels came to be there (`kernel_build.BUILT`).
RENDER_SCRIPT = """
import hashlib, json, torch
from egobench.render import kernel_build
from tests.render.test_render import pose
from tests.render.test_render_cpu import CAM, edge_case_scene, run
from tests.render.test_render_cpu_2dgs import run2, surfel_scene
sets = {{"3dgs": (run, edge_case_scene), "2dgs": (run2, surfel_scene)}}
idx = (torch.arange(CAM.height) >= CAM.height // 2).long()[:, None].expand(CAM.height, CAM.width).contiguous()
def counts(mode):
    stats = [d.stats for d in kernel_build.kernel_dispatchers(mode)]
    return (sum(sum(s.cache_hits.values()) for s in stats), sum(sum(s.cache_misses.values()) for s in stats))
out = {{}}
for mode in {modes!r}:
    render, scene = sets[mode]
    for name in {dtypes!r}:
        dtype, before, h = getattr(torch, name), counts(mode), hashlib.sha1()
        T = pose(0.1, -0.05, (0.02, 0.0, 0.0)).to(dtype)
        Ts = torch.stack([T, pose(0.0, 0.02, (0.01, 0, 0)).to(dtype)])
        for pose_, kw in ((T, {{}}), (Ts, {{"pixel_pose_index": idx}})):
            maps, grads, _ = render(scene(3, dtype), CAM, pose_, "cpu", **kw)
            h.update(maps.numpy().tobytes())
            for g in sorted(grads):
                if grads[g] is not None:
                    h.update(g.encode() + grads[g].numpy().tobytes())
        hits, misses = (x - y for x, y in zip(counts(mode), before))
        built = kernel_build.BUILT.get((name, mode))
        out[mode + "-" + name] = {{"digest": h.hexdigest(), "hits": hits, "misses": misses, "built": built}}
print(json.dumps(out))
"""


def render_script(modes: tuple[str, ...], dtypes: tuple[str, ...]) -> str:
    """`RENDER_SCRIPT` for the sets ``modes`` ("3dgs", "2dgs") in ``dtypes`` ("float32", "float64")."""
    return RENDER_SCRIPT.format(modes=tuple(modes), dtypes=tuple(dtypes))


def kernel_digests(modes: tuple[str, ...], **env: str) -> dict:
    """Renders the float32 kernel sets ``modes`` ("3dgs", "2dgs") in a subprocess (`RENDER_SCRIPT`; ``env``
    added, e.g. NUMBA_CACHE_DIR) -> {set: {"digest", "hits", "misses", "built"}}; fails with its error output."""
    done = run_script(render_script(modes, ("float32",)), timeout=1200, **env)
    assert done.returncode == 0, done.stderr[-2000:]
    return _float32_records(done.stdout)


def _float32_records(stdout: str) -> dict:
    """`RENDER_SCRIPT`'s output -> its float32 records by set."""
    records = json.loads(stdout.strip().splitlines()[-1])
    return {key.removesuffix("-float32"): r for key, r in records.items() if key.endswith("-float32")}


#: the kernel sets an xdist suite compiles at its start, one per worker, float32 and float64 (`warm_up`)
WARM_UP_SETS = ("3dgs", "2dgs")
#: a test run this small (a file, a -k selection) compiles only what its tests use
WARM_UP_MIN_TESTS = 100


def _warm_up_folder(tmp_path_factory) -> Path:
    """The folder of the warm-up records, shared by the run's xdist workers."""
    return tmp_path_factory.getbasetemp().parent / "egobench-kernel-warm-up"


def _cached(kernel_set: str) -> bool:
    """Has ``kernel_set`` ("3dgs", "2dgs") been built for float32 and float64 into numba's cache for this
    source, these libraries and this CPU (`kernel_build.marker_path`)?"""
    from egobench.render import kernel_build

    return all(kernel_build.marker_path(dtype, kernel_set).is_file() for dtype in ("float32", "float64"))


def warm_up(session, tmp_path_factory) -> None:
    """On a cold cache, under pytest-xdist, at a worker's first test: workers gw0 and gw1 each compile one
    kernel set of `WARM_UP_SETS` into the suite's numba cache (`RENDER_SCRIPT`, float32 then float64, on
    their own core) and wait for each other, so that no two processes compile the same set side by side
    and the tests load them; the float32 records (digests, cache hits and misses) serve the cold/warm
    cache test (`cold_warm_up`).
    gw0 decides which sets the cache lacks, for both."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    helpers = min(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0")), len(WARM_UP_SETS))
    index = int(worker.removeprefix("gw")) if worker.startswith("gw") else helpers
    if index >= helpers or len(session.items) < WARM_UP_MIN_TESTS:
        return
    folder = _warm_up_folder(tmp_path_factory)
    if index == 0:
        folder.mkdir(exist_ok=True)
        _write_atomically(folder / "cold.json", json.dumps([s for s in WARM_UP_SETS if not _cached(s)]))
    cold = json.loads(_wait_for(folder / "cold.json"))
    mine = cold[index::helpers]
    if mine:
        done = run_script(render_script(mine, ("float32", "float64")), timeout=1200)
        record = _float32_records(done.stdout) if done.returncode == 0 else {}
        _write_atomically(folder / f"{worker}.json", json.dumps({"sets": record, "error": done.stderr[-2000:]}))
    for k in range(min(helpers, len(cold))):
        _wait_for(folder / f"gw{k}.json")


def cold_warm_up(tmp_path_factory) -> dict | None:
    """The warm-up's records {set: {"digest", "hits", "misses", "built"}} when this run's warm-up built
    every set of `WARM_UP_SETS` in a child (`warm_up`, `kernel_build`); None when it did not run or found a
    set built. Fails with the warm-up's error output where a compile failed."""
    folder = _warm_up_folder(tmp_path_factory)
    cold = folder / "cold.json"
    if not cold.is_file() or set(json.loads(cold.read_text())) != set(WARM_UP_SETS):
        return None
    sets = {}
    for path in sorted(folder.glob("gw*.json")):
        record = json.loads(path.read_text())
        assert record["sets"], f"{path.name}: the warm-up's compile failed: {record['error']}"
        sets.update(record["sets"])
    if set(sets) != set(WARM_UP_SETS) or any(r["built"] != "child" for r in sets.values()):
        return None
    return sets


def compile_key() -> str:
    """What the digests of `RENDER_SCRIPT` depend on, as one hash: the kernels' build key
    (`kernel_build.build_key`: their source, Python, numba, llvmlite, the CPU, numba's settings), the rest of
    egobench's source and the torch version."""
    import torch

    from egobench.render import kernel_build

    h = hashlib.sha256(f"{kernel_build.build_key()}\0{torch.__version__}".encode())
    for path in sorted((REPO / "egobench").rglob("*.py")):
        h.update(path.relative_to(REPO).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _write_atomically(path: Path, text: str) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    partial.replace(path)


def _wait_for(path: Path, timeout: float = 1300.0) -> str:
    """The text of ``path`` once another worker has written it; fails after ``timeout`` s, naming it."""
    deadline = time.monotonic() + timeout
    while not path.is_file():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path}: no kernel warm-up record after {timeout:.0f} s (its worker stopped?)")
        time.sleep(0.5)
    return path.read_text()
