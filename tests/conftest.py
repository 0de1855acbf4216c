"""Shared test settings: the real Aria sample files and determinism."""

from __future__ import annotations

import os

# One thread per process, as Snakemake runs its workers (set before torch and numpy load their thread
# pools): torch's and OpenBLAS's pools spinning on the suite's small arrays cost more than they give,
# and the other cores run the other pytest-xdist workers and the background jobs (`tests.background`)
# (warm suite on 2 cores, one process: 333-338 s with the libraries' defaults, 283-319 s like this).
# numba's pool keeps every core, so the thread-count tests still compare 1 against 2 (the compiled
# kernels otherwise follow torch's count). Subprocesses (the CLI, the workflow's jobs) inherit these
# unless they are set already.
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
    """Submit the background jobs of the selected tests (a module's ``BACKGROUND``: test name -> job)
    now (`tests.background`), so that their subprocesses (a cold numba compile, the CI workflow) overlap
    the rest of the suite on a second core; each test then waits for its job. A module's
    ``background_wanted(config)``, where defined, may say that its jobs are not needed up front (a test
    can still start its job when it asks for it).

    The tests marked slow run first, in their order, so that under pytest-xdist the long ones start while
    short ones are left to fill both workers at the end (collected in file order, the CI workflow's 45 s
    test came last and one worker ran it alone)."""
    items[:] = slow_first(items)
    if background.UNDER_XDIST:
        return  # every xdist worker collects every test: a job starts when its test asks for it (`background.start`)
    for item in items:
        module = getattr(item, "module", None)
        if module is not None and getattr(module, "background_wanted", lambda config: True)(config):
            background.start(module, getattr(item, "originalname", item.name))


def slow_first(items: list) -> list:
    """``items`` with the ones marked slow first, each group in its own order (a stable sort: every xdist
    worker collects the same order, as xdist requires)."""
    return sorted(items, key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session", autouse=True)
def _kernels_warmed_up(request, tmp_path_factory) -> None:
    """The suite's thread set-up, as an entry point's (`egobench.host`): numba's pool started once, in egobench's
    threading layer, with torch's thread count kept (NUMBA_NUM_THREADS is set above). Then, on a cold numba cache
    under pytest-xdist, the first two workers compile the 3DGS and 2DGS kernels (float32 and float64), one set
    each, before their first test (`background.warm_up`); the tests then load them."""
    from egobench.host import start_kernel_pool

    start_kernel_pool()
    background.warm_up(request.session, tmp_path_factory)


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
