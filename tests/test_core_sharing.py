"""The probe of whether two kernel threads share a cache, and how the benchmarks report it."""

from __future__ import annotations

import json

import numba
import numpy as np
import pytest
import torch

from egobench import bench
from egobench import core_sharing as cs


@pytest.mark.parametrize("threads", [1, 2])
def test_each_thread_reads_its_own_row_or_the_others(threads):
    """Rows differ ((t + 1) value + j), so a swapped or mixed row would change the sums; integer-valued
    float64 sums are exact in any order."""
    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("numba's pool has one thread")
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        buf, out = np.zeros((2, 1000)), np.zeros(2)
        cs.write_rows(buf, 5.0)
        np.testing.assert_array_equal(buf, [5.0 + np.arange(1000), 10.0 + np.arange(1000)])
        rows = [5.0 * 1000 + 499500.0, 10.0 * 1000 + 499500.0]
        cs.read_rows(buf, 0, out)
        assert out.tolist() == rows
        cs.read_rows(buf, 1, out)
        assert out.tolist() == rows[::-1]
    finally:
        numba.set_num_threads(before)


def test_classify_by_the_cross_to_own_ratio():
    assert cs.classify(24e-6, 24.2e-6) == {"own_read_us": 24.0, "cross_read_us": 24.2, "cross_to_own": 1.01,
                                           "shared_cache": True}
    assert cs.classify(25.4e-6, 89.8e-6)["shared_cache"] is False  # the 2026-11-29 Zen 4 VM's two dies: ratio 3.54
    assert cs.classify(10e-6, 15e-6)["shared_cache"] is True and cs.classify(10e-6, 15.1e-6)["shared_cache"] is False
    assert cs.classify(10e-6, 15.004e-6) == {"own_read_us": 10.0, "cross_read_us": 15.0, "cross_to_own": 1.5,
                                             "shared_cache": True}  # the state follows the recorded ratio
    # three significant digits whatever the size: a CI probe of 2026-11-29, preempted, read 0.0032 (once rounded to 0.0)
    assert cs.classify(31e-3, 99.3e-6)["cross_to_own"] == 0.0032


@pytest.mark.parametrize("a, b, want", [(True, True, True), (False, False, False), (True, False, None),
                                        (None, None, None), (None, True, None)])
def test_bracket_agrees_only_where_both_probes_do(a, b, want):
    rec = cs.bracket({"shared_cache": a}, {"shared_cache": b})
    assert rec["shared_cache"] is want and rec["before"] == {"shared_cache": a}


def test_describe_names_the_state_for_the_training_summary():
    assert cs.describe(None) == ""
    shared = cs.bracket({"shared_cache": True}, {"shared_cache": True})
    assert cs.describe(shared) == "; kernel threads on one shared cache"
    assert "separate caches" in cs.describe(cs.bracket({"shared_cache": False}, {"shared_cache": False}))
    assert "changed during the run" in cs.describe(cs.bracket({"shared_cache": True}, {"shared_cache": False}))


def test_split_by_sharing_medians_each_state_apart():
    got = cs.split_by_sharing([1.6, 1.2, 1.65, 1.3], [True, False, True, None])
    assert got == {"shared_cache": {"median": 1.625, "rounds": 2}, "not_shared": {"median": 1.2, "rounds": 1}}
    assert cs.split_by_sharing([1.6], [None])["shared_cache"] == {"median": None, "rounds": 0}


def test_probe_needs_two_threads_and_restores_the_count(monkeypatch):
    if numba.config.NUMBA_NUM_THREADS >= 2:
        before = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            rec = cs.probe(repeats=3)
            assert numba.get_num_threads() == 1  # the probe ran on two and put the count back
        finally:
            numba.set_num_threads(before)
        assert rec["own_read_us"] > 0 and rec["cross_read_us"] > 0
        # the record's times (~10-25 us for 2 MB) are rounded to 0.1 us, its ratio to three digits: they agree
        assert rec["cross_to_own"] == pytest.approx(rec["cross_read_us"] / rec["own_read_us"], rel=0.02)
        assert rec["shared_cache"] is (rec["cross_to_own"] <= cs.SHARED_MAX_RATIO)
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    assert cs.probe() == {"shared_cache": None, "reason": "numba's pool has one thread (NUMBA_NUM_THREADS=1)"}


def test_bench_train_reports_each_rounds_core_sharing(monkeypatch, two_kernel_threads):
    """Each row carries its run's record (train.json's `train.core_sharing`); a round counts as shared (or
    not) where its two-thread run's probes agreed, and the speed-ups are also given apart by state."""
    import egobench.train

    from tests.bench.test_bench import _train_result

    speed = {("ours", 1): [30.0, 20.0, 33.0], ("ours", 2): [45.0, 40.0, 33.0],
             ("ours_2dgs", 1): [20.0, 10.0, 30.0], ("ours_2dgs", 2): [36.0, 10.0, 30.0]}
    # the 2-thread runs in order: ours r0, ours_2dgs r0, ours_2dgs r1, ours r1, ours r2, ours_2dgs r2
    states = iter([True, False, None, False, True, True])
    calls = []

    def fake_train(rec, method, cfg, out_dir, progress):
        if cfg.iterations == bench.WARMUP_ITERATIONS:
            return _train_result(1.0)
        key = (method, torch.get_num_threads())
        calls.append(key)
        sharing = {"shared_cache": next(states)} if key[1] == 2 else None
        return _train_result(speed[key][sum(c == key for c in calls) - 1], sharing)

    monkeypatch.setattr(egobench.train, "train", fake_train)
    rec = bench.bench_train("cpu", sides=(16,), iterations=5, methods=("ours", "ours_2dgs"), threads=(1, 2), rounds=3)
    assert next(states, "done") == "done"
    assert all(r["core_sharing"] is None for r in rec["results"] if r["threads"] == 1)
    sp = {x["method"]: x for x in rec["thread_speedup"]}
    assert sp["ours"]["per_round_shared_cache"] == [True, False, True]
    assert sp["ours"]["by_core_sharing"] == {"shared_cache": {"median": 1.25, "rounds": 2},
                                             "not_shared": {"median": 2.0, "rounds": 1}}
    assert sp["ours_2dgs"]["per_round_shared_cache"] == [False, None, True]
    assert sp["ours_2dgs"]["by_core_sharing"] == {"shared_cache": {"median": 1.0, "rounds": 1},
                                                  "not_shared": {"median": 1.8, "rounds": 1}}


@pytest.mark.parametrize("kernel_threads, backend, probes", [(2, "cpu", 2), (1, "cpu", 0), (2, "torch", 0)])
def test_training_probes_its_iterations_where_the_kernels_run_on_two_threads(tmp_path, monkeypatch, kernel_threads,
                                                                             backend, probes):
    """train.json's `train.core_sharing`: a probe before and after the iterations (`bracket` of the two) where
    the compiled kernels run on two threads; None, with no probe, on one thread, on the torch backend, or
    when a finished run is resumed (no iteration runs)."""
    from egobench.host import RASTER_THREADS_ENV
    from egobench.sim.plane import plane_recording
    from egobench.train import TrainConfig, train

    if kernel_threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("numba's pool has one thread")
    seen = iter([{"shared_cache": True, "n": 0}, {"shared_cache": True, "n": 1}])
    monkeypatch.setattr(cs, "probe", lambda: next(seen))
    monkeypatch.setenv(RASTER_THREADS_ENV, str(kernel_threads))
    rec = plane_recording(tmp_path / "rec", size=32, n_frames=9, n_points=300)
    cfg = TrainConfig(iterations=2, max_side=32, device="cpu", backend=backend, refine_start_frac=1.0)
    res = train(rec, "ours", cfg, tmp_path / "run", progress=False)
    want = cs.bracket({"shared_cache": True, "n": 0}, {"shared_cache": True, "n": 1}) if probes else None
    assert res.record["train"]["core_sharing"] == want
    assert len(list(seen)) == 2 - probes
    again = train(rec, "ours", cfg, tmp_path / "run", resume=True, progress=False)  # a probe now: StopIteration
    assert again.iterations == 2 and again.record["train"]["core_sharing"] is None


def test_train_cli_says_where_the_kernel_threads_sat(tmp_path, monkeypatch, capsys, two_kernel_threads):
    """`egobench train`'s summary line names the state its two kernel threads were probed in."""
    import egobench.data.reader
    from egobench.cli import main
    from egobench.host import RASTER_THREADS_ENV
    from egobench.sim.plane import plane_recording

    monkeypatch.setattr(cs, "probe", lambda: {"shared_cache": False})
    monkeypatch.setenv(RASTER_THREADS_ENV, "2")
    rec = plane_recording(tmp_path / "rec", size=32, n_frames=9, n_points=300)  # not the authors' layout: handed over
    monkeypatch.setattr(egobench.data.reader, "recording_from_args", lambda *a: rec)
    assert main(["train", "--recording", str(tmp_path / "rec"), "--method", "ours", "--out", str(tmp_path / "run"),
                 "--iterations", "2", "--no-progress"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("trained ours: 2 iterations") and "; kernel threads on separate caches" in line
    assert json.loads((tmp_path / "run" / "train.json").read_text())["train"]["core_sharing"]["shared_cache"] is False
