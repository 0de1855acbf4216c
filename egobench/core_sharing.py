"""Do two kernel threads share a last-level cache right now? A probe for two-thread timings.

On a VM the two vCPUs may sit on one die of the host (one L3) or on two, and the hypervisor moves them:
on a Zen 4 VM (2026-11-29) the core-to-core latency switched between ~30-45 ns and ~170 ns within seconds,
and `ours` at 128 px trained at 85-90 it/s on two threads in the first state and 67-69 it/s in the
second (results/speed/README.md, 2026-11-29). A two-thread number means little without the state it ran in.

The probe: each of two threads writes a buffer of its own (larger than a core's L2), then each reads
either its own buffer or the other thread's. Where the cores share the L3 both reads run at L3 speed
(ratio ~1.0); across dies the other's lines come over the interconnect (ratio ~3-3.5 there).
`prange(2)` on a pool of two or more threads gives iteration t to thread t in both kernels (numba's
static split of the iteration space), so "own" and "other" are the same threads in both.
"""

from __future__ import annotations

import statistics
import time
from contextlib import contextmanager

import numpy as np
from numba import njit, prange

from egobench.host import start_kernel_pool

#: bytes each thread writes and reads: past a Zen 4 / Zen 5 core's 1 MB L2, well inside one die's L3
PROBE_BYTES = 2 << 20
#: cross / own read-time ratio up to which the two threads are taken to share one cache
SHARED_MAX_RATIO = 1.5


@njit(parallel=True, cache=True)
def write_rows(buf, value):
    """buf [2, n] float64: thread t writes row t with (t + 1) value + column index."""
    for t in prange(2):
        for j in range(buf.shape[1]):
            buf[t, j] = (t + 1) * value + j


@njit(parallel=True, cache=True, fastmath=True)
def read_rows(buf, cross, out):
    """out [2]: thread t sums row 1 - t (cross = 1) or its own row t (cross = 0) of buf [2, n]."""
    for t in prange(2):
        src = (1 - t) * cross + t * (1 - cross)
        s = 0.0
        for j in range(buf.shape[1]):
            s += buf[src, j]
        out[t] = s


def _best_read_s(buf: np.ndarray, cross: int, repeats: int) -> float:
    """Fewest seconds of `read_rows` right after `write_rows` refreshed both rows: the best of `repeats`, since a
    thread descheduled by other work on the box only ever adds time (a median of three once read 31 ms)."""
    out = np.zeros(2)
    times = []
    for r in range(repeats):
        write_rows(buf, float(r))
        t0 = time.perf_counter()
        read_rows(buf, cross, out)
        times.append(time.perf_counter() - t0)
    return min(times)


def classify(own_s: float, cross_s: float) -> dict:
    """Read times (seconds) -> the probe's record: times in microseconds, their ratio, shared or not."""
    ratio = float(f"{cross_s / own_s:.3g}")  # three significant digits; the state follows the ratio as recorded
    return {"own_read_us": round(own_s * 1e6, 1), "cross_read_us": round(cross_s * 1e6, 1),
            "cross_to_own": ratio, "shared_cache": bool(ratio <= SHARED_MAX_RATIO)}


def probe(repeats: int = 15, nbytes: int = PROBE_BYTES) -> dict:
    """Measure now (a few milliseconds; a process's first call loads the two kernels from numba's cache,
    ~0.25 s, or compiles them, ~1 s once per machine: a Zen 4 VM) -> `classify`'s record, or
    {"shared_cache": None, "reason": ...} where numba's pool has one thread (the probe needs two)."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        return {"shared_cache": None, "reason": "numba's pool has one thread (NUMBA_NUM_THREADS=1)"}
    start_kernel_pool()
    before = numba.get_num_threads()
    numba.set_num_threads(2)
    try:
        buf = np.zeros((2, nbytes // 8))
        _best_read_s(buf, 0, 2)  # compile or load, first touch
        _best_read_s(buf, 1, 2)
        return classify(_best_read_s(buf, 0, repeats), _best_read_s(buf, 1, repeats))
    finally:
        numba.set_num_threads(before)


def bracket(before: dict, after: dict) -> dict:
    """The probes taken before and after a timed run -> {"before", "after", "shared_cache"}: True or False
    where both agree, None where they differ (the placement changed during the run) or none could run."""
    a, b = before.get("shared_cache"), after.get("shared_cache")
    return {"before": before, "after": after, "shared_cache": a if a is not None and a == b else None}


@contextmanager
def bracketing(enabled: bool = True):
    """Probe before and after the block; yields a dict that holds `bracket`'s record once the block has run
    (stays empty when not ``enabled``)."""
    record: dict = {}
    before = probe() if enabled else None
    yield record
    if enabled:
        record.update(bracket(before, probe()))


def describe(record: dict | None) -> str:
    """`bracket`'s record (or None: not probed) -> a few words for a one-line summary ("" when not probed)."""
    if not record:
        return ""
    state = record.get("shared_cache")
    if state is None:
        return "; kernel threads' cache sharing changed during the run or was not measured"
    return "; kernel threads on one shared cache" if state else "; kernel threads on separate caches (other die)"


def split_by_sharing(values: list[float], shared: list[bool | None]) -> dict:
    """Per-round values and the bracketed state of each round's multi-thread run -> the medians of the rounds
    whose threads shared a cache and of those whose did not (None where no round was), with their counts."""
    out = {}
    for key, state in (("shared_cache", True), ("not_shared", False)):
        mine = [v for v, s in zip(values, shared) if s is state]
        out[key] = {"median": round(statistics.median(mine), 3) if mine else None, "rounds": len(mine)}
    return out
