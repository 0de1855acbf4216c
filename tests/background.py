"""Background jobs of selected tests, run on a second core while the suite goes on: a module's
``BACKGROUND = {test name: job}`` (a cold numba compile, the CI workflow end to end), and every test
marked ``background`` (run whole in a pytest subprocess, `run_test`). conftest submits them after
collection, in the order of the tests, to one worker thread. A test that reaches its job before the
worker has started it takes the job back and runs it itself (`result`), so the suite never waits on a
queue; ``EGOBENCH_TESTS_INLINE=1`` runs every marked test in its own process (e.g. under a debugger)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]
_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="egobench-test-background")
_JOBS: dict[str, tuple[object, Future]] = {}
INLINE = os.environ.get("EGOBENCH_TESTS_INLINE") == "1"


def submit(key: str, job) -> None:
    """Queues ``job`` (a callable) under ``key``, once."""
    if key not in _JOBS:
        _JOBS[key] = (job, _POOL.submit(job))


def start(module: ModuleType, test_name: str) -> None:
    """Queues the background job that ``module`` declares for its test ``test_name``, if any."""
    job = getattr(module, "BACKGROUND", {}).get(test_name)
    if job is not None:
        submit(f"{module.__name__}::{test_name}", job)


def take(key: str, job=None, timeout: float = 1800):
    """The value of the job queued under ``key``: waited for when the worker has started it, run here
    when it has not (or was never queued: ``job`` then, which must be given)."""
    job, future = _JOBS.pop(key, (job, None))
    if future is None or future.cancel():
        return job()
    return future.result(timeout=timeout)


def result(module: ModuleType, test_name: str, timeout: float = 1800):
    """The value of the job that ``module`` declares for ``test_name`` (`take`)."""
    return take(f"{module.__name__}::{test_name}", module.BACKGROUND[test_name], timeout)


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
    error output, if that compile failed."""
    done = result(module, test_name, timeout=1300)
    assert done.returncode == 0, done.stderr[-2000:]


def run_test(nodeid: str) -> tuple[str, str]:
    """One test run whole in a pytest subprocess (`run_script`'s environment, marked tests inline)
    -> (outcome "passed" / "failed" / "skipped", the failure's or skip's text)."""
    with tempfile.TemporaryDirectory(prefix="egobench_test_") as tmp:
        report = Path(tmp) / "report.xml"
        env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONPATH=str(REPO),
                   EGOBENCH_TESTS_INLINE="1")
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}",
                               nodeid], cwd=REPO, env=env, capture_output=True, text=True, timeout=1500)
        cases = list(ET.parse(report).getroot().iter("testcase")) if report.is_file() else []
    if done.returncode not in (0, 1) or len(cases) != 1:
        return "failed", f"pytest subprocess for {nodeid}: exit {done.returncode}\n{(done.stdout + done.stderr)[-3000:]}"
    for tag, outcome in (("failure", "failed"), ("error", "failed"), ("skipped", "skipped")):
        found = cases[0].find(tag)
        if found is not None:
            return outcome, (found.text or found.get("message") or "")[-4000:]
    return "passed", ""
