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


def _recorded(config) -> dict | None:
    """The recorded cold build's digests by set, if pytest's cache holds one for this source, these
    libraries and this CPU (`background.compile_key`), else None."""
    cache = getattr(config, "cache", None)  # None with -p no:cacheprovider
    record = cache.get(RECORD, None) if cache else None
    return record["sets"] if record and record["key"] == background.compile_key() else None


def background_wanted(config) -> bool:
    """Start the empty-folder build at collection only where no cold build is recorded for this source
    (conftest; without this a `-n 0` run built it for ~90 s even when the record made it unneeded)."""
    return _recorded(config) is None


def _cold_and_warm(tmp_path_factory, recorded: dict | None) -> tuple[dict, dict]:
    """(digests of a process that met a cold cache, of one that found the build). The cold one is, in
    order: this run's warm-up on a cold cache (`background.warm_up`); a cold build recorded for the same
    source, libraries and CPU (an earlier run's); a build into an empty folder. The warm one reads the
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
    cold, warm = _cold_and_warm(tmp_path_factory, _recorded(request.config))
    for mode in SETS:
        assert cold[mode]["built"] == "child" and warm[mode]["built"] == "marker", (mode, cold[mode], warm[mode])
        for process in (cold, warm):
            assert process[mode]["hits"] >= len(kernel_build.KERNELS) and process[mode]["misses"] == 0, mode
        assert cold[mode]["digest"] == warm[mode]["digest"], mode
    if getattr(request.config, "cache", None):
        request.config.cache.set(RECORD, {"key": background.compile_key(), "sets": {mode: cold[mode] for mode in SETS}})


class _Cache:
    """pytest's cache, as far as the record uses it (get)."""

    def __init__(self, values: dict):
        self.values = values

    def get(self, key, default):
        return self.values.get(key, default)


def test_the_empty_folder_build_is_started_up_front_only_without_a_record_for_this_source():
    """A `-n 0` run with a cold build recorded for this source does not build again at collection;
    without one (no cache, no record, a record of other source) it does."""
    from types import SimpleNamespace

    sets = {mode: {"digest": "d", "hits": 4, "misses": 0, "built": "child"} for mode in SETS}
    key = background.compile_key()
    assert background_wanted(SimpleNamespace(cache=None))
    assert background_wanted(SimpleNamespace(cache=_Cache({})))
    assert background_wanted(SimpleNamespace(cache=_Cache({RECORD: {"key": "an older source", "sets": sets}})))
    assert not background_wanted(SimpleNamespace(cache=_Cache({RECORD: {"key": key, "sets": sets}})))
    assert _recorded(SimpleNamespace(cache=_Cache({RECORD: {"key": key, "sets": sets}}))) == sets
