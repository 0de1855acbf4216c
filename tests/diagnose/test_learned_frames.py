"""A per-frame exposure learned with the scene (`TrainConfig.learn_frame_exposure`): the trainer's parameter, the run's
renders, and the diagnosis's verdict on it (`egobench.diagnose.learned_frames`, `ExposureMetadata.judge_learned_frames`)."""

from __future__ import annotations

import json
import math
import types

import numpy as np
import pytest
import torch

from egobench.diagnose.learned_frames import frames_markdown, judge_learned_frames
from egobench.effects import EFFECTS
from egobench.effects.exposure_metadata import FLAG_MIN_LOG
from egobench.model import frame_exposure
from egobench.model.predict import run_normaliser
from egobench.train import cpu_step, train
from egobench.train.checkpoint import load_trained_run
from egobench.train.config import TrainConfig
from tests.checks.test_independent_writer import writer

METADATA = EFFECTS["exposure_metadata"]


def test_frames_off_the_bulk_beyond_its_own_scatter_and_the_single_frame_floor_are_flagged():
    rng = np.random.default_rng(5)
    frames = list(range(1, 43))
    values = rng.normal(0.0, 0.02, size=42) + 0.3  # the gauge: a shared offset is the scene's
    altered = [3, 10, 11, 25, 40]
    for f, e in zip(altered, (0.25, -0.2, 0.25, -0.2, 0.25)):
        values[f - 1] = 0.3 - math.log1p(e)  # the record is the true exposure times 1 + e
    verdict = METADATA.judge_learned_frames(frames, values)
    assert verdict["flagged_frames"] == altered
    assert verdict["record_error"]["3"] == pytest.approx(0.25, abs=0.03)
    assert verdict["record_error"]["10"] == pytest.approx(-0.2, abs=0.03)
    assert verdict["threshold"] == pytest.approx(max(4.0 * verdict["bulk_sd"], FLAG_MIN_LOG))
    # a frame beyond four of the bulk's sds but under the 15 % single-frame floor is model error
    quiet = rng.normal(0.0, 0.01, size=42)
    quiet[7] = 0.9 * FLAG_MIN_LOG
    assert METADATA.judge_learned_frames(frames, quiet)["flagged_frames"] == []
    with pytest.raises(ValueError, match="expected finite log scales, one per listed frame"):
        METADATA.judge_learned_frames(frames, values[:-1])


def test_a_runs_learned_frames_are_judged_from_its_record_or_refused_by_field(tmp_path):
    assert judge_learned_frames(tmp_path) is None
    (tmp_path / "train.json").write_text(json.dumps({"learned_frame_exposure": None}))
    assert judge_learned_frames(tmp_path) is None
    values = [0.0] * 20 + [-0.3]
    (tmp_path / "train.json").write_text(json.dumps({"learned_frame_exposure": {"frames": list(range(21)),
                                                                                 "log_scale": values}}))
    judged = judge_learned_frames(tmp_path)
    assert judged["named"] == ["exposure_metadata"] and judged["detail"]["exposure_metadata"]["flagged_frames"] == [20]
    assert "frame 20: record error +0.35" in frames_markdown(judged)
    (tmp_path / "train.json").write_text(json.dumps({"learned_frame_exposure": {"frames": [1, 2], "log_scale": "x"}}))
    with pytest.raises(ValueError, match="train.json: field 'learned_frame_exposure': expected"):
        judge_learned_frames(tmp_path)


def _stack(rng, n_frames: int = 8, size: int = 16):
    """Linear radiance [F, H, W, 3] of a scene and a diagnosis context for it; the stack's frames are the
    recording's odd ones (index 2 j + 1), so a position taken for an index shows."""
    linear = rng.uniform(0.05, 0.5, size=(n_frames, size, size, 3))
    ctx = types.SimpleNamespace(frame_index=2 * np.arange(n_frames) + 1, gamma_assumed=2.2,
                                valid=np.ones((size, size), bool))
    return linear, ctx


def _display(linear):
    return np.clip(linear, 0.0, 1.0) ** (1.0 / 2.2)


def test_the_within_frame_gain_of_a_wrong_record_learned_per_frame_is_its_frames_psnr_gain():
    """Recording frame 7 (the stack's fourth) has a record 25 % off, and the run learned it: its render matches the
    capture. Recording frame 11 learned a scale its capture does not need (model error). Every frame carries the
    bulk's shared scale c, the scene's share. Taken to the centre and re-scaled from its even pixels, frame 7 gains
    what an independent PSNR says, frame 11 next to nothing, each averaged over the stack's frames; a flagged frame
    outside the stack is not scored."""
    rng = np.random.default_rng(8)
    linear, ctx = _stack(rng)
    c = 0.3
    noise = rng.normal(0.0, 0.01, size=linear.shape)
    measured = np.clip(_display(linear) + noise, 0.0, 1.0)
    measured[3] = np.clip(_display(linear[3] * 1.25) + noise[3], 0.0, 1.0)
    predicted = _display(linear).copy()
    predicted[3], predicted[5] = _display(linear[3] * 1.25), _display(linear[5] * math.exp(0.2))
    learned = {int(f): c for f in ctx.frame_index} | {7: c + math.log(1.25), 11: c + 0.2}
    even = (np.add.outer(np.arange(16), np.arange(16)) % 2) == 0
    score = ~even

    def frame_psnr(a, b):
        return -10.0 * np.log10(((a - b)[score] ** 2).mean())

    gain = METADATA.learned_frames_gain(measured, predicted, ctx, {"centre": c, "flagged_frames": [7, 4]}, learned,
                                        even, score)
    expected = (frame_psnr(_display(linear[3] * 1.25), measured[3]) - frame_psnr(_display(linear[3]), measured[3])) / 8
    assert gain["frames"] == 1 and gain["gain_db"] == pytest.approx(expected, rel=1e-3) and gain["gain_db"] > 0.5
    model_error = METADATA.learned_frames_gain(measured, predicted, ctx, {"centre": c, "flagged_frames": [11]},
                                               learned, even, score)
    assert abs(model_error["gain_db"]) < 0.01 * gain["gain_db"]
    assert METADATA.learned_frames_gain(measured, predicted, ctx, {"centre": c, "flagged_frames": [4]}, learned,
                                        even, score) is None


def test_learned_frames_are_named_only_where_their_within_frame_gain_clears_the_floor(tmp_path):
    """With the run's renders, the frames' flags name the cause only above `gain.FRAME_LOCAL_GAIN_FLOOR_DB`: a
    frame whose learned scale the capture does not need is refused, with the reason and its gain recorded; a flagged
    frame the diagnosis did not render names nothing, saying so."""
    rng = np.random.default_rng(9)
    linear, ctx = _stack(rng, n_frames=21)
    measured = np.clip(_display(linear) + rng.normal(0.0, 0.01, size=linear.shape), 0.0, 1.0)
    predicted = _display(linear).copy()
    predicted[20] = _display(linear[20] * math.exp(-0.3))  # learned, not needed
    frames = [int(f) for f in ctx.frame_index]
    (tmp_path / "train.json").write_text(json.dumps({"learned_frame_exposure": {"frames": frames,
                                                                                 "log_scale": [0.0] * 20 + [-0.3]}}))
    source = types.SimpleNamespace(measured=measured, predicted=predicted, context=ctx)
    judged = judge_learned_frames(tmp_path, source, border_px=0)
    verdict = judged["detail"]["exposure_metadata"]
    assert judged["named"] == [] and verdict["flagged_frames"] == [41] and abs(verdict["within_frame_gain_db"]) < 0.01
    assert "FRAME_LOCAL_GAIN_FLOOR_DB" in verdict["not_named"] and "within-frame gain" in frames_markdown(judged)
    measured[20] = np.clip(_display(linear[20] * math.exp(-0.3)) + rng.normal(0.0, 0.01, size=linear[20].shape), 0, 1)
    judged = judge_learned_frames(tmp_path, source, border_px=0)  # now the capture is that much darker: a record
    assert judged["named"] == ["exposure_metadata"] and judged["detail"]["exposure_metadata"]["within_frame_gain_db"] > 0.05
    shorter = types.SimpleNamespace(measured=measured[:20], predicted=predicted[:20],
                                    context=types.SimpleNamespace(**{**vars(ctx), "frame_index": ctx.frame_index[:20]}))
    judged = judge_learned_frames(tmp_path, shorter, border_px=0)
    assert judged["named"] == [] and "--max-frames" in judged["detail"]["exposure_metadata"]["not_named"]


def test_a_runs_renders_take_its_learned_exposure_and_the_frames_that_learned_none_the_median():
    """Training frames (matched by the checkpoint's ``extra_frames``) take their own learned scale; held-out frames,
    which learned none, the median one (the share every frame has, which the scene could have taken instead)."""
    frames = [types.SimpleNamespace(index=i, exposure_s=1e-3, gain=1.0) for i in range(10)]
    recording = types.SimpleNamespace(frames=frames, train_frames=[f for f in frames if f.index % 8])
    scale = torch.tensor([-0.2, 0.1, 0.0, 0.05, -0.1, 0.3, -0.05, 0.2])
    trained = [f.index for f in recording.train_frames]
    spec = types.SimpleNamespace(formation=True)
    run = types.SimpleNamespace(spec=spec, path="run", checkpoint={"extra": {frame_exposure.KEY: scale},
                                                                   "extra_frames": trained[::-1]})
    k_of = run_normaliser(recording, run)
    assert [float(k_of[i]) for i in trained[::-1]] == pytest.approx(torch.exp(scale).tolist())
    assert float(k_of[0]) == float(k_of[8]) == pytest.approx(math.exp(float(scale.median())))
    run.checkpoint = {"extra": {frame_exposure.KEY: scale[:5]}, "extra_frames": trained}
    with pytest.raises(ValueError, match="field 'extra.frame_exposure': 5 values for 8 frames in 'extra_frames'"):
        run_normaliser(recording, run)
    run.checkpoint = {"extra": {frame_exposure.KEY: scale}}
    with pytest.raises(ValueError, match="field 'extra_frames' is missing: expected the recording's frame indices"):
        run_normaliser(recording, run)
    run.checkpoint = {"extra": {frame_exposure.KEY: scale}, "extra_frames": [20] + trained[1:]}
    with pytest.raises(ValueError, match=r"field 'extra_frames': frames \[20\] are not in the recording"):
        run_normaliser(recording, run)


def test_the_compiled_step_refuses_a_per_frame_exposure():
    reason = cpu_step.unsupported_reason(types.SimpleNamespace(pose_optimisation=False, render_exposure_samples=1),
                                         "cpu", None, TrainConfig(learn_frame_exposure=True))
    assert reason == "the run learns a per-frame exposure correction"


def test_training_learns_a_scale_per_training_frame_and_records_it(tmp_path):
    """A short run of a writer recording whose records are wrong on a quarter of the frames: train.json lists every
    training frame with its learned log scale, and the checkpoint carries them for the run's renders."""
    assert writer.main(["--out", str(tmp_path / "rec"), "--seed", "3", "--size", "32", "--frames", "12",
                        "--exposure-error", "1.25", "--exposure-fraction", "0.25"]) == 0
    rec_dir = next((tmp_path / "rec").glob("camera-rgb-rectified-*"))
    config = TrainConfig(iterations=40, max_side=48, motion_warmup_frac=0.0, refine_start_frac=1.0, max_gaussians=2000,
                         learn_frame_exposure=True)
    train(rec_dir, "ours", config, tmp_path / "run", progress=False)
    learned = json.loads((tmp_path / "run" / "train.json").read_text())["learned_frame_exposure"]
    assert learned["frames"] == [i for i in range(12) if i % 8] and len(learned["log_scale"]) == 10
    assert np.ptp(learned["log_scale"]) > 0  # each frame moved its own way
    run = load_trained_run(tmp_path / "run", None, "test")
    assert run.checkpoint["extra"][frame_exposure.KEY].tolist() == pytest.approx(learned["log_scale"])
