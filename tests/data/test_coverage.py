"""Held-out coverage (egobench.data.coverage): a held-out frame is covered where a training frame saw
its surfaces; checked against poses whose answer is known, and against an independent dense count."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from egobench.data.coverage import (
    _gt_depth,
    _lift,
    _seen_in,
    heldout_coverage,
    training_view_count,
)
from egobench.data.reader import load_recording
from tests.helpers import small_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = small_recording(tmp_path_factory.mktemp("cov") / "rec", "indoor", 5, n_frames=17, size=32)
    return load_recording(path, "online")


def _with_pose(rec, index: int, T: torch.Tensor):
    frames = [dataclasses.replace(f, T_world_camera=T) if f.index == index else f for f in rec.frames]
    return dataclasses.replace(rec, frames=frames)


def test_a_frame_sees_itself_and_nothing_behind_it(recording):
    f = recording.test_frames[0]
    depth = _gt_depth(recording, f)
    pts = _lift(recording, f, depth, 2)
    assert len(pts) > 100
    assert _seen_in(recording, f, depth, pts).mean() > 0.98  # its own surfaces, its own depth
    turned = f.T_world_camera.clone()
    turned[:3, :3] = turned[:3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=turned.dtype))  # 180 deg yaw
    assert not _seen_in(recording, dataclasses.replace(f, T_world_camera=turned), depth, pts).any()


def test_coverage_is_one_when_a_training_frame_shares_the_pose_and_less_when_it_turns_away(recording, monkeypatch):
    import egobench.data.coverage as cov

    test = recording.test_frames[1]  # frame 8: its neighbours 7 and 9 are training frames
    same = _with_pose(recording, 7, test.T_world_camera.clone())
    base = cov._gt_depth  # frame 7 now stands where 8 does; give it 8's ground-truth depth too
    monkeypatch.setattr(cov, "_gt_depth", lambda rec, f: base(rec, test) if f.index == 7 else base(rec, f))
    assert heldout_coverage(same)[test.index] > 0.98
    monkeypatch.setattr(cov, "_gt_depth", base)
    away = test.T_world_camera.clone()
    away[:3, :3] = away[:3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=away.dtype))
    # the held-out frame turned away: its surfaces (from its own depth, lifted with the turned pose)
    # lie behind where it looks, in no training frame's view that the original depth agrees with
    lone = _with_pose(recording, test.index, away)
    assert heldout_coverage(lone)[test.index] < heldout_coverage(recording)[test.index]


def test_coverage_matches_a_dense_reference(recording):
    cov = heldout_coverage(recording, stride=1)
    assert set(cov) == {f.index for f in recording.test_frames}
    f = recording.test_frames[0]
    pts = _lift(recording, f, _gt_depth(recording, f), 1)
    seen = np.zeros(len(pts), bool)
    for g in recording.train_frames:  # the same rule, one training frame at a time, no shortcuts
        seen |= _seen_in(recording, g, _gt_depth(recording, g), pts)
    assert cov[f.index] == pytest.approx(seen.mean(), abs=1e-12)


def test_coverage_needs_ground_truth(recording):
    with pytest.raises(ValueError, match="ground-truth depth"):
        heldout_coverage(dataclasses.replace(recording, ground_truth=None))


def test_training_view_count_is_the_number_of_training_frames_that_hold_each_surface(recording):
    """Every training frame moved to the held-out frame's pose holds each of its surfaces: the count is
    the number of training frames wherever the pixel has depth and lies in the valid area, else 0; one
    of them turned 180 deg holds none; a coarse grid repeats its samples' counts blockwise, also where the
    image is not a whole number of blocks."""
    f = recording.test_frames[0]
    depth = _gt_depth(recording, f)
    depth[:4] = 0.0  # no surface rendered in the top rows
    stacked = dataclasses.replace(recording, frames=[
        dataclasses.replace(g, T_world_camera=f.T_world_camera.clone()) if g.index % 8 else g for g in recording.frames])
    n_train = len(stacked.train_frames)
    count = training_view_count(stacked, f, depth)
    valid = recording.mask.numpy().astype(bool) & (depth > 0)
    assert count.shape == depth.shape and n_train == 14
    assert np.all(count[valid] == n_train) and np.all(count[depth == 0] == 0)
    away = f.T_world_camera.clone()
    away[:3, :3] = away[:3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=away.dtype))
    one_away = _with_pose(stacked, stacked.train_frames[0].index, away)
    assert np.all(training_view_count(one_away, f, depth)[valid] == n_train - 1)
    real = training_view_count(recording, f, depth)
    coarse = training_view_count(recording, f, depth, max_grid=8)  # stride 4: samples at 2, 6, ..., 30
    assert np.array_equal(coarse, np.repeat(np.repeat(real[2::4, 2::4], 4, 0), 4, 1))
    # stride 6 leaves a short last block (30..31): it is sampled at its last pixel, and the map keeps [H, W]
    short = training_view_count(recording, f, depth, max_grid=6)
    at = np.array([3, 9, 15, 21, 27, 31])
    assert short.shape == depth.shape == (32, 32)
    assert np.array_equal(short, np.repeat(np.repeat(real[np.ix_(at, at)], 6, 0), 6, 1)[:32, :32])
    assert real[valid].min() < real[valid].max() <= n_train  # the real walk: some surfaces in few views or none
