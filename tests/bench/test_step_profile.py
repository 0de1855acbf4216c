"""`egobench.bench.step_profile`: the split of a training step into compiled kernels and the glue between them."""

import pytest
import torch

from egobench.bench import step_profile as sp


def _events():
    """Two steps (times in s) and debris the split must ignore: a call before any step, an unfinished step."""
    return [("early", -1.0, -0.5),
            (sp.STEP, 0.0, 0.0), ("k1", 0.001, 0.004), ("k2", 0.005, 0.006), (sp.END, 0.010, 0.0),
            (sp.STEP, 1.0, 0.0), ("k1", 1.002, 1.003), (sp.END, 1.005, 0.0),
            (sp.STEP, 2.0, 0.0), ("k1", 2.001, 2.002)]


def test_the_split_of_hand_made_steps():
    r = sp.step_breakdown(_events())
    assert r["steps"] == 2
    assert r["step_ms"] == pytest.approx(7.5)  # median of 10 and 5 ms
    assert r["kernels_ms"] == pytest.approx(2.5)  # of 4 and 1
    assert r["between_kernels_ms"] == pytest.approx(5.0)  # of 6 and 4
    assert r["kernel_calls_per_step"] == 1.5
    assert r["kernel_ms_per_step"] == pytest.approx({"k1": 2.0, "k2": 0.5})
    assert r["largest_gaps_ms_per_step"] == pytest.approx(
        {"k2 -> step end": 2.0, "step start -> k1": 1.5, "k1 -> step end": 1.0, "k1 -> k2": 0.5})
    assert list(r["largest_gaps_ms_per_step"])[0] == "k2 -> step end"  # largest first


def test_the_first_steps_can_be_left_out_and_none_left_is_an_error():
    r = sp.step_breakdown(_events(), skip=1)
    assert (r["steps"], r["step_ms"], r["kernels_ms"]) == (1, pytest.approx(5.0), pytest.approx(1.0))
    with pytest.raises(ValueError, match="no complete training step after the first 2"):
        sp.step_breakdown(_events(), skip=2)


def test_the_clock_times_each_kernel_call_and_puts_every_kernel_back():
    from egobench.render import finite
    from egobench.train import loop

    tensors = [torch.ones(5), torch.zeros(3)]
    assert finite.all_finite(tensors)  # compiled (or loaded) before the clock, as the clock asks
    originals = {name: getattr(finite, name) for name in sp._dispatchers(finite)}
    assert {"_finite_row", "_zero_row"} <= set(originals)
    step = loop.train_step
    events = []
    with sp.kernel_clock(events):
        assert finite._finite_row is not originals["_finite_row"]
        assert finite.all_finite(tensors) and not finite.has_zero_row(torch.ones(2, 4))
    assert [e[0] for e in events] == ["_finite_row", "_finite_row", "_zero_row"]
    assert all(t0 <= t1 for _, t0, t1 in events)
    assert {name: getattr(finite, name) for name in originals} == originals
    assert loop.train_step is step


def test_a_profiled_run_splits_its_steps_and_trains_the_same_bits(tmp_path):
    from egobench.bench import _timed_training, train_config, train_scene, warm_up

    rec = train_scene(tmp_path / "rec", 24, 300)
    cfg = train_config(24, 6)
    warm_up(rec, "ours", cfg, 1, tmp_path / "warm")
    _timed_training(rec, "ours", cfg, 1, tmp_path / "plain")
    events = []
    with sp.kernel_clock(events):
        _timed_training(rec, "ours", cfg, 1, tmp_path / "clocked")
    r = sp.step_breakdown(events)
    assert r["steps"] == 6
    assert {"project_fwd", "raster_fwd", "raster_bwd", "project_bwd"} <= set(r["kernel_ms_per_step"])
    assert 0 < r["kernels_ms"] < r["step_ms"] and r["between_kernels_ms"] > 0
    plain, clocked = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=True) for d in ("plain", "clocked"))
    for name, value in plain["params"].items():
        assert torch.equal(value, clocked["params"][name]), name


def test_the_command_prints_a_split_per_thread_count_with_the_host(capsys):
    import json

    assert sp.main(["--resolution", "24", "--points", "300", "--iterations", "10", "--threads", "1"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert (rec["benchmark"], rec["method"], rec["resolution"], list(rec["by_threads"])) == (
        "step_profile", "ours", 24, ["1"])
    row = rec["by_threads"]["1"]
    assert row["steps"] == 9  # the first tenth (one step) left out
    # medians of per-step quantities: kernel time <= step time in every step, so these orders hold on any
    # host and load (median(t - k) is not median(t) - median(k))
    assert 0 <= row["between_kernels_ms"] <= row["step_ms"] and 0 < row["kernels_ms"] <= row["step_ms"]
    assert {"cpu_model", "vector_isa", "kernel_target"} <= set(rec["host"])
