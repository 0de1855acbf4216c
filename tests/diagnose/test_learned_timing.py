"""egobench.diagnose.learned_timing: the timing a run learned with its scene, judged against its floors."""

from __future__ import annotations

import json

import pytest

from egobench.diagnose.learned_timing import judge_timing, learned_timing_of, timing_markdown
from egobench.effects import EFFECTS

TIME_OFFSET_FLOOR_MS = EFFECTS["time_offset"].learned_timing[1]
READOUT_ERROR_FLOOR_MS = EFFECTS["readout"].learned_timing[1]


def test_a_learned_value_names_its_cause_from_its_floor_the_largest_multiple_first():
    quiet = judge_timing({"time_offset_ms": 0.99 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": -0.99 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert quiet["named"] == [] and "nothing" in timing_markdown(quiet)
    both = judge_timing({"time_offset_ms": -1.5 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": 2.5 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert both["named"] == ["readout", "time_offset"]
    assert both["time_offset_error_s"] == pytest.approx(-1.5e-3 * TIME_OFFSET_FLOOR_MS)
    assert both["readout_s_estimated"] == pytest.approx(0.008 + 2.5e-3 * READOUT_ERROR_FLOOR_MS)
    assert [d["multiple"] for d in both["detail"]] == pytest.approx([2.5, 1.5])
    assert both["readout_relative_error"] == pytest.approx(2.5e-3 * READOUT_ERROR_FLOOR_MS / 0.008)
    assert "readout_s_estimated" in timing_markdown(both) and "named: readout, time_offset" in timing_markdown(both)
    exact = judge_timing({"time_offset_ms": TIME_OFFSET_FLOOR_MS, "readout_error_ms": 0.0}, 0.008)
    assert exact["named"] == ["time_offset"]  # from the floor on


def test_a_runs_learned_timing_is_read_from_its_record_or_refused_by_name(tmp_path):
    (tmp_path / "train.json").write_text(json.dumps({"learned_timing": None}))
    assert learned_timing_of(tmp_path) is None
    (tmp_path / "train.json").write_text(json.dumps({"learned_timing": {"time_offset_ms": 1.0, "readout_error_ms": 2.0}}))
    assert learned_timing_of(tmp_path) == {"time_offset_ms": 1.0, "readout_error_ms": 2.0}
    (tmp_path / "train.json").write_text(json.dumps({"learned_timing": {"time_offset_ms": "x", "readout_error_ms": 2.0}}))
    with pytest.raises(ValueError, match=r"train.json: field 'learned_timing.time_offset_ms': expected a number"):
        learned_timing_of(tmp_path)
    assert learned_timing_of(tmp_path / "nowhere") is None


def test_a_run_that_learned_no_timing_is_trained_once_more_with_it_and_reused_after(tmp_path, monkeypatch):
    """`timing_of_run`: the run's own learned timing where it has one; otherwise its method, config and seed trained
    with learn_timing into WORK_DIR/run, once (a complete run there is reused)."""
    import dataclasses

    from egobench.diagnose import learned_timing
    from egobench.train.config import TrainConfig

    own = tmp_path / "own"
    own.mkdir()
    (own / "train.json").write_text(json.dumps({"learned_timing": {"time_offset_ms": 2.9, "readout_error_ms": 0.1}}))
    assert learned_timing.timing_of_run(tmp_path / "rec", own, tmp_path / "work") == (
        {"time_offset_ms": 2.9, "readout_error_ms": 0.1}, own)

    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "train.json").write_text(json.dumps({"learned_timing": None}))
    config = TrainConfig(iterations=800, seed=1185)
    run = dataclasses.make_dataclass("Run", ["spec", "config"])(
        dataclasses.make_dataclass("Spec", ["name", "calibration"])("ours", "online"), config)
    calls = []

    def fake_train(recording, method, cfg, out, resume, progress):
        calls.append((recording, method, cfg, out, resume))
        out.mkdir(parents=True)
        (out / "train.json").write_text(json.dumps({"complete": True, "learned_timing": {
            "time_offset_ms": 0.1, "readout_error_ms": 3.4}}))

    monkeypatch.setattr(learned_timing, "load_trained_run", lambda run_dir, device, where: run)
    monkeypatch.setattr(learned_timing, "load_recording", lambda path, calibration: ("recording", path, calibration))
    monkeypatch.setattr(learned_timing, "train", fake_train)
    for _ in range(2):  # the second call reuses the complete run
        learned, where = learned_timing.timing_of_run(tmp_path / "rec", plain, tmp_path / "work")
        assert learned == {"time_offset_ms": 0.1, "readout_error_ms": 3.4} and where == tmp_path / "work" / "run"
    assert len(calls) == 1
    with pytest.raises(ValueError, match="learn_timing.json: this folder holds the timing run of"):
        learned_timing.timing_of_run(tmp_path / "other_rec", plain, tmp_path / "work")
    recording, method, cfg, out, resume = calls[0]
    assert recording == ("recording", tmp_path / "rec", "online") and method == "ours" and resume == "auto"
    assert cfg == dataclasses.replace(config, learn_timing=True) and cfg.seed == 1185


def test_diagnose_judges_the_timing_the_run_learned_or_trains_it_under_learn_timing(tmp_path, monkeypatch):
    import argparse
    import types

    from egobench.diagnose import cli

    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    src = types.SimpleNamespace(context=types.SimpleNamespace(readout_s=0.008))
    run = tmp_path / "run"
    run.mkdir()
    (run / "train.json").write_text(json.dumps({"learned_timing": None}))
    args = parser.parse_args(["rec", "--run", str(run), "--out", str(tmp_path / "out"), "--no-progress"])
    assert cli._learned_timing(args, tmp_path / "rec", run, tmp_path / "out", src) is None  # learned none, not asked

    def fake(rec, run_dir, work_dir, progress):
        assert work_dir == tmp_path / "out" / "learn_timing" and not progress
        return {"time_offset_ms": 2.7, "readout_error_ms": 0.3}, work_dir / "run"

    monkeypatch.setattr(cli, "timing_of_run", fake)
    args = parser.parse_args(["rec", "--run", str(run), "--out", str(tmp_path / "out"), "--learn-timing", "--no-progress"])
    judged = cli._learned_timing(args, tmp_path / "rec", run, tmp_path / "out", src)
    assert judged["named"] == ["time_offset"] and judged["time_offset_error_s"] == pytest.approx(0.0027)
    assert judged["learned_in"] == str(tmp_path / "out" / "learn_timing" / "run")


def test_learn_timing_needs_a_trained_run(tmp_path):
    import argparse

    from egobench.diagnose import cli

    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    (tmp_path / "rec").mkdir()
    args = parser.parse_args([str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--learn-timing", "--no-progress"])
    with pytest.raises(ValueError, match="--learn-timing: the timing is learned with a trained run's scene"):
        cli._diagnose_recording(args, cli.DiagnosisConfig(), tmp_path / "out")
