"""The compiled CPU rasterizer gives the same bits whether a process compiles its kernels or loads them
from numba's on-disk cache: a seed must fix a run's result whichever job of a workflow compiles first."""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from tests import background

SETS = background.WARM_UP_SETS  # 3DGS and 2DGS, float32 (the training dtype)
#: pytest's cache key of the last compile's digests ({"key": `background.compile_key`, "sets": ...})
RECORD = "egobench/compiled-kernel-digests"


def _cold_then_warm() -> dict:
    """The digests of a process that compiles into an empty cache and of one that loads from it (run in
    the background, `tests.background`)."""
    tmp = Path(tempfile.mkdtemp(prefix="egobench_numba_cache_"))
    try:
        cache = str(tmp / "numba_cache")
        cold = background.kernel_digests(SETS, NUMBA_CACHE_DIR=cache)
        return {"cold": cold, "warm": background.kernel_digests(SETS, NUMBA_CACHE_DIR=cache)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


BACKGROUND = {"test_compiled_and_cached_kernels_give_the_same_bits": _cold_then_warm}


def _compiled_and_loaded(tmp_path_factory, recorded: dict | None) -> tuple[dict, dict]:
    """(digests of a process that compiled the kernels, of one that loaded them). The compiling one is, in
    order: this session's warm-up on a cold cache (`background.warm_up`); a compile recorded for the same
    source, libraries and CPU (an earlier session's); a compile into an empty folder. The loading one reads
    the suite's cache where it serves every kernel, else that empty folder."""
    compiled = background.cold_warm_up(tmp_path_factory) or recorded
    if compiled is not None:
        loaded = background.kernel_digests(SETS)
        if not any(loaded[s]["misses"] for s in SETS):
            return compiled, loaded
    job = background.start(sys.modules[__name__], "test_compiled_and_cached_kernels_give_the_same_bits").result(
        timeout=1300)
    return job["cold"], job["warm"]


def test_compiled_and_cached_kernels_give_the_same_bits(tmp_path_factory, request):
    """Before the surfel backward dropped 'contract' and 'nsz', its geometric gradients differed in the
    last bits between the compiling process and the cached code (the first 2DGS job of a suite trained
    to 19.38 dB, the same job on a warm cache to 19.23). The compile's digests are kept in pytest's cache,
    so that a warm suite compares against them instead of compiling every kernel again."""
    cache = getattr(request.config, "cache", None)  # None with -p no:cacheprovider
    key, record = background.compile_key(), cache.get(RECORD, None) if cache else None
    compiled, loaded = _compiled_and_loaded(tmp_path_factory, record["sets"] if record and record["key"] == key
                                            else None)
    for mode in SETS:
        assert compiled[mode]["misses"] >= len(background.RASTER_KERNELS) and compiled[mode]["hits"] == 0, mode
        assert loaded[mode]["hits"] >= len(background.RASTER_KERNELS) and loaded[mode]["misses"] == 0, mode
        assert compiled[mode]["digest"] == loaded[mode]["digest"], mode
    if cache:
        cache.set(RECORD, {"key": key, "sets": {mode: compiled[mode] for mode in SETS}})
