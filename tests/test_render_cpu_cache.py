"""The compiled CPU rasterizer gives the same bits in every process, whichever job of a workflow meets a
cold numba cache first: that process builds the kernels in a child (`egobench.render.kernel_build`) and
then loads them, as every later process does. (A process that compiles a parallel kernel itself runs
other machine code than the cached one: docs/cpu-rasterizer.md.)"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from egobench.render import kernel_build
from tests import background

SETS = background.WARM_UP_SETS  # 3DGS and 2DGS, float32 (the training dtype)
#: pytest's cache key of the last cold build's digests ({"key": `background.compile_key`, "sets": ...})
RECORD = "egobench/kernel-build-digests"


def _cold_then_warm() -> dict:
    """The digests of a process on an empty cache (it builds in a child) and of one that finds the build
    (run in the background, `tests.background`)."""
    tmp = Path(tempfile.mkdtemp(prefix="egobench_numba_cache_"))
    try:
        cache = str(tmp / "numba_cache")
        cold = background.kernel_digests(SETS, NUMBA_CACHE_DIR=cache)
        return {"cold": cold, "warm": background.kernel_digests(SETS, NUMBA_CACHE_DIR=cache)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


BACKGROUND = {"test_a_cold_cache_is_built_in_a_child_and_every_process_loads_it": _cold_then_warm}


def _cold_and_warm(tmp_path_factory, recorded: dict | None) -> tuple[dict, dict]:
    """(digests of a process that met a cold cache, of one that found the build). The cold one is, in
    order: this session's warm-up on a cold cache (`background.warm_up`); a cold build recorded for the same
    source, libraries and CPU (an earlier session's); a build into an empty folder. The warm one reads the
    suite's cache where the build is there and serves every kernel, else that empty folder."""
    cold = background.cold_warm_up(tmp_path_factory) or recorded
    if cold is not None:
        warm = background.kernel_digests(SETS)
        if all(warm[s]["built"] == "marker" and not warm[s]["misses"] for s in SETS):
            return cold, warm
    job = background.start(sys.modules[__name__],
                           "test_a_cold_cache_is_built_in_a_child_and_every_process_loads_it").result(timeout=1300)
    return job["cold"], job["warm"]


def test_a_cold_cache_is_built_in_a_child_and_every_process_loads_it(tmp_path_factory, request):
    """The process on a cold cache built the kernels in a child and loaded every one (no kernel compiled in
    it); a later process found the build, loaded every kernel and gives the same bits. The cold build's
    digests are kept in pytest's cache, so that a warm suite compares against them instead of building
    into an empty folder again."""
    cache = getattr(request.config, "cache", None)  # None with -p no:cacheprovider
    key, record = background.compile_key(), cache.get(RECORD, None) if cache else None
    cold, warm = _cold_and_warm(tmp_path_factory, record["sets"] if record and record["key"] == key else None)
    for mode in SETS:
        assert cold[mode]["built"] == "child" and warm[mode]["built"] == "marker", (mode, cold[mode], warm[mode])
        for process in (cold, warm):
            assert process[mode]["hits"] >= len(kernel_build.KERNELS) and process[mode]["misses"] == 0, mode
        assert cold[mode]["digest"] == warm[mode]["digest"], mode
    if cache:
        cache.set(RECORD, {"key": key, "sets": {mode: cold[mode] for mode in SETS}})
