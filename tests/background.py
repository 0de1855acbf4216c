"""Background jobs of selected tests (a cold numba compile, the CI workflow end to end): conftest
starts them after collection, one at a time on one worker thread in the order of the tests, so that
their subprocesses overlap the rest of the suite on a second core; each test then waits for its own
job's result. A test module declares its jobs as ``BACKGROUND = {test name: job}``. Under pytest-xdist
(the default, pyproject's addopts) every worker collects every test, so conftest submits nothing and a
job starts when its test asks for it; the other workers keep the other cores busy."""

from __future__ import annotations

import os
import subprocess
import sys
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


# Renders the edge-case scenes of tests.test_render_cpu{,_2dgs} in {dtype}, global and rolling shutter,
# and backpropagates: every compiled kernel of {modes} for that dtype.
_RENDER_SCRIPT = """
import torch
from tests.test_render import pose
from tests.test_render_cpu import CAM, edge_case_scene, run
from tests.test_render_cpu_2dgs import run2, surfel_scene
Ts = torch.stack([pose(0.0, 0.02 * k, (0.01 * k, 0, 0)) for k in range(2)]).to(torch.{dtype})
idx = (torch.arange(CAM.height) >= CAM.height // 2).long()[:, None].expand(CAM.height, CAM.width).contiguous()
for T, kw in ((Ts[0], {{}}), (Ts, {{"pixel_pose_index": idx}})):
    if "3dgs" in {modes!r}:
        run(edge_case_scene(3, torch.{dtype}), CAM, T, "cpu", **kw)
    if "2dgs" in {modes!r}:
        run2(surfel_scene(3, torch.{dtype}), CAM, T, "cpu", **kw)
"""


def compile_kernels(dtype: str, modes: tuple[str, ...]):
    """A job that compiles the CPU rasterizer's kernels of ``modes`` ("3dgs", "2dgs") for ``dtype``
    ("float32", "float64") into numba's cache in a subprocess -> its CompletedProcess. On a cold cache
    the compiles (~40 s per mode and dtype here) then run on the second core, and the tests that need
    those kernels, waiting for the job first, load them instead of compiling them again; on a warm
    cache the job only loads them."""
    script = _RENDER_SCRIPT.format(dtype=dtype, modes=tuple(modes))
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
