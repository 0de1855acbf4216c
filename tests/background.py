"""Background jobs of selected tests (a cold numba compile, the CI workflow end to end): conftest
submits them after collection, one at a time on one worker thread, so that their subprocesses overlap
the rest of the suite on a second core; each test then waits for its own job's result."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="egobench-test-background")
_JOBS: dict[str, Future] = {}


def submit(key: str, job: Callable[[], object]) -> Future:
    """The background job ``key`` (submitted once: ``job()`` on the worker thread) -> its future."""
    if key not in _JOBS:
        _JOBS[key] = _POOL.submit(job)
    return _JOBS[key]


def key_of(module_name: str, test_name: str) -> str:
    return f"{module_name}::{test_name}"
