"""`predict.RunRenderer`, the one setup of a trained run's renders, and the diagnosis's size check before it."""

from __future__ import annotations

import types
from pathlib import Path

import pytest

from egobench.diagnose import sources
from egobench.model import predict


def _camera(side: int):
    return types.SimpleNamespace(width=side, height=side)


def test_pose_samples_follow_the_runs_rule_at_the_runs_size(monkeypatch):
    """A run trained at half the recording's width counts its pose samples from half the recording's pixel motion:
    `sample_counts` gets the run's width over the recording's, with the run's method and sampling rule."""
    seen = []

    def counts(recording, frames, spec, sampling, pixel_scale):
        seen.append((recording, list(frames), spec, sampling, pixel_scale))
        return [7] * len(frames)

    monkeypatch.setattr(predict, "sample_counts", counts)
    spec, rule = object(), object()
    run = types.SimpleNamespace(camera=_camera(24), spec=spec, config=types.SimpleNamespace(pose_sampling=rule))
    recording = types.SimpleNamespace(camera=_camera(48))
    r = predict.RunRenderer(run, recording, maps=None, k_of={}, formation=None, settings=None)
    assert r.pose_samples(["f0", "f1"]) == [7, 7]
    assert seen == [(recording, ["f0", "f1"], spec, rule, 0.5)]


def test_a_run_trained_at_another_size_is_refused_by_name(monkeypatch):
    """The diagnosis compares full-resolution renders: a run trained at 24 px on a 48 px recording is refused with its
    path, both sizes and what needed the renders, before any render is set up."""
    monkeypatch.setattr(sources, "load_recording", lambda *a, **k: types.SimpleNamespace(camera=_camera(48)))
    monkeypatch.setattr(predict.RunRenderer, "of", classmethod(lambda cls, *a: pytest.fail("set up anyway")))
    run = types.SimpleNamespace(camera=_camera(24), spec=types.SimpleNamespace(calibration="online"),
                                path=Path("runs") / "ours")
    with pytest.raises(ValueError, match=r"ours: trained at 24x24, the recording is 48x48; full-resolution renders "
                                         r"are needed for the learned timing"):
        sources.run_renderer("rec", run, "the learned timing")
