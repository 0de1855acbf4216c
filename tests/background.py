"""Background jobs of selected tests (a cold numba compile, the CI workflow end to end): conftest
starts them after collection, one at a time on one worker thread, so that their subprocesses overlap
the rest of the suite on a second core; each test then waits for its own job's result. A test module
declares its jobs as ``BACKGROUND = {test name: job}``."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from types import ModuleType

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
