"""egobench.diagnose.learned_timing: the timing a run learned with its scene, judged against its floors, with its
standard error on the run beside it; egobench.diagnose.timing_pulls: that standard error."""

from __future__ import annotations

import argparse
import dataclasses
import json
import types

import numpy as np
import pytest
import torch
from scipy.stats import t as student_t

from egobench.diagnose import cli, learned_timing, timing_pulls
from egobench.diagnose.learned_timing import judge_timing, learned_timing_of, timing_markdown
from egobench.diagnose.timing_pulls import (TimedRun, block_length, frame_pulls, held_out_timing_gain,
                                            sandwich_standard_error)
from egobench.effects import EFFECTS
from egobench.train.config import TrainConfig

TIME_OFFSET_FLOOR_MS = EFFECTS["time_offset"].learned_timing[1]
READOUT_ERROR_FLOOR_MS = EFFECTS["readout"].learned_timing[1]
EVIDENCE = {"se_ms": {"time_offset_ms": 0.2, "readout_error_ms": 0.5}, "df": 13, "frames": 42}


def test_a_learned_value_names_its_cause_from_its_floor_the_largest_multiple_first():
    quiet = judge_timing({"time_offset_ms": 0.99 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": -0.99 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert quiet["named"] == [] and "nothing" in timing_markdown(quiet) and "tests" not in quiet
    both = judge_timing({"time_offset_ms": -1.5 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": 2.5 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert both["named"] == ["readout", "time_offset"]
    assert both["time_offset_error_s"] == pytest.approx(-1.5e-3 * TIME_OFFSET_FLOOR_MS)
    assert both["readout_s_estimated"] == pytest.approx(0.008 + 2.5e-3 * READOUT_ERROR_FLOOR_MS)
    assert [d["multiple"] for d in both["detail"]] == pytest.approx([2.5, 1.5])
    assert both["readout_relative_error"] == pytest.approx(2.5e-3 * READOUT_ERROR_FLOOR_MS / 0.008)
    assert "readout_s_estimated" in timing_markdown(both) and "named: readout, time_offset" in timing_markdown(both)
    exact = judge_timing({"time_offset_ms": TIME_OFFSET_FLOOR_MS, "readout_error_ms": 0.0}, 0.008)
    assert exact["named"] == ["time_offset"]  # from the floor on


def test_the_runs_standard_error_is_reported_beside_the_floor_and_does_not_decide():
    """With the run's evidence: each learned value's t and two-sided p on t(df); a value at t 15 under its floor
    is not named, a value over its floor at t 0.5 is."""
    judged = judge_timing({"time_offset_ms": 3.0 * EVIDENCE["se_ms"]["time_offset_ms"] * 5, "readout_error_ms": 0.25},
                          0.008, EVIDENCE)
    assert judged["named"] == ["time_offset"] and judged["df"] == 13 and judged["frames"] == 42
    assert judged["tests"]["time_offset"]["t"] == pytest.approx(15.0)
    assert judged["tests"]["readout"]["p"] == pytest.approx(2.0 * student_t.sf(0.5, 13))
    assert "t(13) = +0.50" in timing_markdown(judged) and "not deciding" in timing_markdown(judged)
    strong = judge_timing({"time_offset_ms": 0.0, "readout_error_ms": 0.9 * READOUT_ERROR_FLOOR_MS}, 0.008,
                          dict(EVIDENCE, se_ms={"time_offset_ms": 0.2, "readout_error_ms": 0.01}))
    assert strong["named"] == [] and strong["tests"]["readout"]["t"] > 100
    with pytest.raises(ValueError, match="field 'se_ms.readout_error_ms': expected a positive standard error"):
        judge_timing({"time_offset_ms": 0.0, "readout_error_ms": 3.4}, 0.008,
                     dict(EVIDENCE, se_ms={"time_offset_ms": 0.2, "readout_error_ms": 0.0}))


def test_the_block_length_is_newey_and_wests_rule_of_thumb():
    assert [block_length(n) for n in (1, 10, 42, 100, 1000)] == [1, 2, 3, 4, 6]


def test_the_block_sandwich_matches_the_estimators_spread_over_draws():
    """A linear model of 42 frames in capture order whose pixels' noise is shared by neighbouring frames (a moving
    average over 2 frames), whose frames see much the same content and differ in noise: over 4000 draws, the spread
    of the Gauss-Newton estimate from 0 matches the block sandwich's standard error (rms over the draws), and the frames-as-independent
    sandwich (one frame a block) is too small for such a run."""
    rng = np.random.default_rng(7)
    n, m, p = 42, 60, 2
    J = rng.normal(size=(1, m, p)) + 0.3 * rng.normal(size=(n, m, p))  # frames see much the same content
    noise_sd = rng.uniform(0.5, 2.0, size=n)[:, None]
    H = np.einsum("nmi,nmj->nij", J, J)
    Hi = np.linalg.inv(H.sum(0))
    estimates, variances, iid = [], [], []
    for _ in range(4000):
        shared = rng.normal(size=(n + 1, m))
        r = noise_sd * (shared[:-1] + shared[1:]) / np.sqrt(2.0)  # true value 0, evaluated at 0
        g = np.einsum("nmi,nm->ni", J, r)
        estimates.append(-Hi @ g.sum(0))
        se, df = sandwich_standard_error(g, H)
        variances.append(se ** 2)
        gc = g - g.mean(0)
        iid.append(np.diag(Hi @ (gc.T @ gc) @ Hi * n / (n - 1)))
    spread = np.std(np.array(estimates), axis=0)
    assert df == 13
    assert np.sqrt(np.mean(variances, axis=0)) == pytest.approx(spread, rel=0.1)
    assert np.all(np.sqrt(np.mean(iid, axis=0)) < 0.75 * spread)


def test_the_pulls_need_a_run_that_learned_a_timing(tmp_path, monkeypatch):
    monkeypatch.setattr(timing_pulls, "load_trained_run", lambda run_dir, device, where: object())
    monkeypatch.setattr(timing_pulls, "learned_timing_ms", lambda run: None)
    with pytest.raises(ValueError, match="checkpoint.pt: field 'extra.timing': the run learned no timing"):
        TimedRun(tmp_path / "rec", tmp_path / "run")
    with pytest.raises(ValueError, match="at least 3 blocks"):
        sandwich_standard_error(np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)))


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

    loaded = []

    def fake_timed_run(rec, run_dir, **inputs):  # loaded once, for both the evidence and the held-out gain
        assert run_dir == tmp_path / "out" / "learn_timing" / "run"
        assert inputs == {"device": None, "trajectory_path": None, "semidense_path": None}
        loaded.append(run_dir)
        return "timed run"

    def fake_evidence(timed, progress):
        assert timed == "timed run" and not progress
        return EVIDENCE

    monkeypatch.setattr(cli, "timing_of_run", fake)
    monkeypatch.setattr(cli, "TimedRun", fake_timed_run)
    monkeypatch.setattr(cli, "timing_evidence", fake_evidence)
    monkeypatch.setattr(cli, "held_out_timing_gain", lambda timed, progress: {"gain_db": 0.02, "frames": 6})
    args = parser.parse_args(["rec", "--run", str(run), "--out", str(tmp_path / "out"), "--learn-timing", "--no-progress"])
    judged = cli._learned_timing(args, tmp_path / "rec", run, tmp_path / "out", src)
    assert judged["named"] == ["time_offset"] and judged["tests"]["time_offset"]["t"] == pytest.approx(13.5) and judged["time_offset_error_s"] == pytest.approx(0.0027)
    assert judged["learned_in"] == str(tmp_path / "out" / "learn_timing" / "run") and judged["df"] == 13
    assert judged["held_out"] == {"gain_db": 0.02, "frames": 6} and "+0.0200 dB over 6 frames" in timing_markdown(judged)
    assert len(loaded) == 1

    def no_evidence(timed, progress):
        raise ValueError("the frames' summed curvature in the timing is singular")

    monkeypatch.setattr(cli, "timing_evidence", no_evidence)  # reported only: the floors still judge
    judged = cli._learned_timing(args, tmp_path / "rec", run, tmp_path / "out", src)
    assert judged["named"] == ["time_offset"] and "tests" not in judged and "singular" in judged["tests_unavailable"]
    assert judged["held_out"] == {"gain_db": 0.02, "frames": 6}

    def unloadable(rec, run_dir, **inputs):
        raise ValueError("trained at 32x32, the recording is 64x64")

    monkeypatch.setattr(cli, "TimedRun", unloadable)  # neither report: both say why, the floors still judge
    judged = cli._learned_timing(args, tmp_path / "rec", run, tmp_path / "out", src)
    assert judged["named"] == ["time_offset"] and "tests" not in judged and "held_out" not in judged
    assert "32x32" in judged["tests_unavailable"] and "32x32" in judged["held_out_unavailable"]


def test_learn_timing_needs_a_trained_run(tmp_path):
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    (tmp_path / "rec").mkdir()
    args = parser.parse_args([str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--learn-timing", "--no-progress"])
    with pytest.raises(ValueError, match="--learn-timing: the timing is learned with a trained run's scene"):
        cli._diagnose_recording(args, cli.DiagnosisConfig(), tmp_path / "out")


def _linear_run(monkeypatch, F: int = 10):
    """A run whose render is linear in the timing, I_i(tau) = A_i + B_i tau on the mask (the stated timing: A_i),
    patched into `timing_pulls` -> (its `TimedRun`, A, B, M, tau, mask, training frames, held-out frames)."""
    rng = np.random.default_rng(3)
    H, W = 4, 5
    mask = torch.from_numpy(rng.random((H, W)) > 0.3)
    A, B, M = (torch.from_numpy(rng.normal(size=shape)) for shape in ((F, H, W, 3), (F, H, W, 3, 2), (F, H, W, 3)))
    tau = torch.tensor([0.7, -1.3], dtype=torch.float64)
    frames = [types.SimpleNamespace(index=i) for i in range(F) if i % 8 != 0]
    held_out = [types.SimpleNamespace(index=i) for i in range(F) if i % 8 == 0]
    rec = types.SimpleNamespace(train_frames=frames, test_frames=held_out, load_image=lambda f: M[f.index])

    def predict(f, n, maps):
        assert n == f.index + 1  # the frame's own pose samples
        shift = 0.0 if maps.timing_ms is None else B[f.index] @ maps.timing_ms
        return types.SimpleNamespace(image=A[f.index] + shift)

    renderer = types.SimpleNamespace(recording=rec, maps=types.SimpleNamespace(mask=mask, timing_ms=tau),
                                     pose_samples=lambda fs: [f.index + 1 for f in fs], predict=predict)
    for name, value in {"load_trained_run": lambda run_dir, device, where: "run", "learned_timing_ms": lambda r: tau,
                        "run_renderer": lambda path, run, what, *inputs: renderer,
                        "replace": lambda maps, timing_ms: types.SimpleNamespace(timing_ms=timing_ms)}.items():
        monkeypatch.setattr(timing_pulls, name, value)
    return TimedRun("rec", "run"), A, B, M, tau, mask, frames, held_out


def test_the_pulls_and_curvatures_of_a_render_linear_in_the_timing_are_exact(monkeypatch):
    """`frame_pulls` on a run whose render is linear in the timing, I_i(tau) = A_i + B_i tau on the mask: each
    training frame's pull is B_i^T (I_i(tau) - M_i) and its curvature B_i^T B_i, in capture order (the held-out
    frames left out)."""
    timed, A, B, M, tau, mask, frames, _ = _linear_run(monkeypatch)
    pulls, curvature = frame_pulls(timed)
    assert pulls.shape == (len(frames), 2)
    for i, f in enumerate(frames):
        Bm = B[f.index][mask].reshape(-1, 2)
        r = (A[f.index] + B[f.index] @ tau - M[f.index])[mask].reshape(-1)
        assert pulls[i] == pytest.approx((Bm.T @ r).numpy(), rel=1e-9, abs=1e-9)
        assert curvature[i] == pytest.approx((Bm.T @ Bm).numpy(), rel=1e-9, abs=1e-9)


def test_the_held_out_gain_of_a_learned_timing_compares_the_held_out_frames_with_and_without_it(monkeypatch):
    """`held_out_timing_gain` on the linear run: the mean over the held-out frames (and only them) of
    10 log10(MSE without the timing / MSE with it) on the mask."""
    timed, A, B, M, tau, mask, _, held_out = _linear_run(monkeypatch, F=17)
    expected = [10.0 * np.log10(((A[i] - M[i])[mask] ** 2).mean().item() /
                                ((A[i] + B[i] @ tau - M[i])[mask] ** 2).mean().item()) for i in (0, 8, 16)]
    gain = held_out_timing_gain(timed)
    assert [f.index for f in held_out] == [0, 8, 16] and gain["frames"] == 3
    assert gain["gain_db"] == pytest.approx(float(np.mean(expected)), rel=1e-12)
