"""Shared test settings: the real Aria sample files and determinism."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

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
    """Start the background work of the selected tests' modules (a module's ``start_background()``)
    now, so that their single-threaded subprocesses (a cold numba compile) overlap the rest of the
    suite on a second core; the tests then wait for it."""
    started = set()
    for item in items:
        module = getattr(item, "module", None)
        start = getattr(module, "start_background", None)
        if start is not None and module not in started:
            started.add(module)
            start()


@pytest.fixture(autouse=True)
def _deterministic_torch():
    torch.manual_seed(0)
    yield
