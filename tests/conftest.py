"""Shared test settings: the real Aria sample files and determinism."""

from __future__ import annotations

import functools
import os

# One thread per process, as Snakemake runs its workers (set before torch and numpy load their thread
# pools): torch's and OpenBLAS's pools spinning on the suite's small arrays cost more than they give,
# and the background jobs (`tests.background`) get the second core (warm suite on 2 cores: 333-338 s
# with the libraries' defaults, 283-319 s like this). numba's pool keeps every core, so the thread-count tests
# still compare 1 against 2 (the compiled kernels otherwise follow torch's count). Subprocesses (the
# CLI, the workflow's jobs) inherit these unless they are set already.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", str(os.cpu_count() or 1))

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

from tests import background  # noqa: E402


REPO_ROOT = Path(__file__).resolve().parents[1]
#: Real Project Aria files (see ../shared/data/NOTICE.md); override with EGOBENCH_SHARED_DATA.
SHARED_DATA = Path(os.environ.get("EGOBENCH_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """The folder with aria_mps_sample/ and adt_sample/, or skip the test with the reason."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real Aria sample data not found at {SHARED_DATA} (set EGOBENCH_SHARED_DATA)")
    return SHARED_DATA


@pytest.hookimpl(trylast=True)  # after -m / -k deselection: only the tests that will run
def pytest_collection_modifyitems(config, items):
    """Queue the background jobs of the selected tests now (`tests.background`), so that their
    subprocesses overlap the rest of the suite on a second core: first the modules' ``BACKGROUND``
    jobs (kernel compiles and long end-to-end runs, which the suite reaches late), then the tests marked
    ``background``, each in test order; the suite takes back those the worker has not started."""
    for item in items:
        if getattr(item, "module", None) is not None:
            background.start(item.module, getattr(item, "originalname", item.name))
    for item in items:
        if item.get_closest_marker("background") and not background.INLINE:
            background.submit(item.nodeid, functools.partial(background.run_test, item.nodeid))


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """A test marked ``background`` reports the outcome of its run in the background; it runs here
    instead when the background worker has not started it yet."""
    if not pyfuncitem.get_closest_marker("background") or background.INLINE:
        return None
    nodeid = pyfuncitem.nodeid
    outcome, text = background.take(nodeid, lambda: ("inline", ""))
    if outcome == "inline":
        return None  # pytest calls the test function here
    if outcome == "skipped":
        pytest.skip(text)
    if outcome == "failed":
        pytest.fail(f"(run in the background, tests/background.py)\n{text}", pytrace=False)
    return True


@pytest.fixture
def two_kernel_threads() -> None:
    """Skip, saying why, where numba's pool has one thread: a 1-against-2-thread test would compare 1 with 1."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba's pool has one thread (NUMBA_NUM_THREADS / OMP_NUM_THREADS=1): nothing to compare")


@pytest.fixture(autouse=True)
def _deterministic_torch():
    torch.manual_seed(0)
    yield
