"""The gain of an absorbed effect against the simulator's truth (egobench.diagnose.truth, issue 27 item 5)."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import numpy as np
import pytest


def test_the_radiance_error_ignores_a_global_scale_and_measures_the_rest():
    from egobench.diagnose.truth import log_radiance_error

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 5.0, (200, 3))
    w = np.ones(200)
    assert log_radiance_error(7.3 * truth, truth, w) == pytest.approx(0.0, abs=1e-12)
    sign = np.where(np.arange(200) % 2 == 0, 1.0, -1.0)[:, None]
    assert log_radiance_error(2.0 * truth * np.exp(0.1 * sign), truth, w) == pytest.approx(math.expm1(0.1), rel=1e-9)
    # a zero weight removes a pixel: a wild pixel there changes nothing
    wild = truth.copy()
    wild[0] *= 50.0
    w0 = w.copy()
    w0[0] = 0.0
    assert log_radiance_error(wild, truth, w0) == pytest.approx(0.0, abs=1e-12)


def test_a_trained_runs_scene_is_nearer_its_own_views_radiance_than_other_views(tmp_path):
    """The run's scene colour is compared with the clean radiance of the same held-out view: swapping
    the views' truth files makes the error far larger (the renders, poses and truth line up)."""
    from egobench.diagnose.truth import held_out_radiance_error
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig
    from egobench.train import preset_config, train

    rec = tmp_path / "rec"
    simulate_recording(SimConfig.from_overrides("indoor", 3, {"n_frames": 17, "rectified_size": 24, "motion": "fast",
                                                                "readout_s": 0.01626}), rec, progress=False)
    tc = replace(preset_config("cpu"), max_side=0, device="cpu").scaled_to(250)
    train(rec, "ours", tc, tmp_path / "run", progress=False)
    own = held_out_radiance_error(rec, tmp_path / "run")
    radiance = rec / "ground_truth" / "radiance"
    shutil.move(radiance / "00000.npy", tmp_path / "a.npy")  # held out: frames 0, 8, 16; rotate their truths
    shutil.move(radiance / "00008.npy", radiance / "00000.npy")
    shutil.move(radiance / "00016.npy", radiance / "00008.npy")
    shutil.move(tmp_path / "a.npy", radiance / "00016.npy")
    swapped = held_out_radiance_error(rec, tmp_path / "run")
    assert own < 0.5 and swapped > 1.5 * own
    (radiance / "00008.npy").unlink()
    with pytest.raises(FileNotFoundError, match="00008.npy"):
        held_out_radiance_error(rec, tmp_path / "run")
