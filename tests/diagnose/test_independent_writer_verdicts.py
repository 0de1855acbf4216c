"""Verdicts on recordings egobench did not write: each test hides one effect (or none) in a recording of
scripts/independent_writer.py at the conditions of the independent-writer sweeps (64 px, 48 frames, a fixed
1 ms exposure at gain 1, a flat stated vignette, a stated 8 ms readout), trains 'ours' for 800 iterations and
diagnoses the run, all through scripts/independent_sweep.py's own harness (one thread each, as in the sweeps;
training and diagnosis in the test's process, the sweep's commands and bits without a process start-up each),
and requires the verdict. The seeds are cases of the third seed set (results/diagnosis/README.md, "2026-12-05:
geometric causes beside the structure the run leaves"), chosen where the verdict has a margin (gains of +0.2 to
+1.8 dB, 11 of 12 altered frames flagged), so that a run on another x86-64 machine, whose training moves by its
float rounding, keeps it.
"""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from egobench.diagnose.gain import FRAME_LOCAL_GAIN_FLOOR_DB

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "independent_sweep.py"


def _load_sweep():
    spec = importlib.util.spec_from_file_location("independent_sweep", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


sweep = _load_sweep()
GEOMETRIC = sweep.GEOMETRIC


def _diagnosis(case_dir: Path) -> dict:
    return json.loads((case_dir / "diag" / "diagnosis.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("effect,seed", [("null", 141), ("vignette", 228), ("exposure_metadata", 423),
                                         ("time_offset", 522)])
def test_the_diagnosis_gives_the_verdict_on_an_independent_writers_recording(tmp_path, effect, seed):
    row = sweep.run_case(tmp_path, effect, seed, seed_set=3, in_process=True)
    d = _diagnosis(tmp_path / "cases" / f"{effect}_{seed}")
    named = [n["name"] for n in d["named"]]
    if effect == "null":  # nothing hidden: nothing named
        assert named == [] and d["verdict"] == "reconstruction error dominates"
        return
    assert named[0] == effect and not row["wrong_first"], named
    if effect == "vignette":  # a 40 % corner shading: never a geometric cause
        assert not set(named) & GEOMETRIC
    if effect == "exposure_metadata":  # wrong records on a quarter of the frames: half of them flagged, none wrong
        altered = row["altered_frames"].split()
        assert row["flagged_altered"] >= len(altered) / 2 and row["flagged_wrong"] == 0
    if effect == "time_offset":  # 3 ms: named with the right sign, its gain beating its placebo extensions
        params = d["named"][0]["params"]
        assert 0.0005 < params["time_offset_error_s"] < 0.0035
        assert params["gain_placebo_p"] < d["config"]["alpha"]


@pytest.mark.slow
def test_a_readout_is_named_where_the_run_renders_the_shutter_in_sub_pixel_steps(tmp_path):
    """The same conditions with 'ours' trained at 1/16 px of row shear a pose sample (`TrainConfig.pose_sample_step_px`;
    about 14 samples a moving frame where the released rule gives about one): a readout 1.5 x the stated is testable,
    named first and estimated within 25 %. Seed 1140 of set 84 (results/diagnosis/README.md, "2026-12-06: the shutter
    rendered in sub-pixel steps", exploratory): t 9.9, +0.18 dB beating every placebo extension, 10.2 ms of 12."""
    row = sweep.run_case(tmp_path, "readout", 1140, seed_set=84, in_process=True,
                         train_set=("pose_sample_step_px=0.0625", "max_pose_samples=32"))
    d = _diagnosis(tmp_path / "cases" / "readout_1140")
    named = [n["name"] for n in d["named"]]
    assert named[:1] == ["readout"] and not row["wrong_first"], named
    params = d["named"][0]["params"]
    assert abs(params["readout_s_estimated"] - 1.5 * sweep.STATED_READOUT_S) <= 0.25 * 1.5 * sweep.STATED_READOUT_S
    assert params["gain_placebo_p"] < d["config"]["alpha"]


@pytest.mark.slow
def test_a_readout_the_scene_absorbs_is_named_through_the_timing_learned_with_it(tmp_path):
    """Seed 1185 of set 89: a readout 1.5 x the stated that the run's residual no longer shows (its frame t 2.2, not
    named at 800 iterations). Trained with `TrainConfig.learn_timing`, the run learns a readout error near the
    hidden 4 ms (3.36 ms on an Intel Xeon; results/diagnosis/README.md, "2026-12-07: the timing learned with the
    scene") and no time offset (0.12 ms): the readout is named first, estimated within 25 %, with its standard error on the
    run's frames beside it."""
    row = sweep.run_case(tmp_path, "readout", 1185, seed_set=89, in_process=True,
                         train_set=("pose_sample_step_px=0.0625", "max_pose_samples=32", "learn_timing=true"))
    timing = _diagnosis(tmp_path / "cases" / "readout_1185")["learned_timing"]
    assert timing["named"] == ["readout"] and row["first"] == "readout" and not row["wrong_first"]
    assert timing["tests"]["readout"]["se_ms"] > 0 and timing["df"] == 13  # the run's standard error, reported
    assert abs(timing["readout_s_estimated"] - 1.5 * sweep.STATED_READOUT_S) <= 0.25 * 1.5 * sweep.STATED_READOUT_S
    assert abs(timing["learned"]["time_offset_ms"]) < 0.5
    assert timing["held_out"]["frames"] == 6  # its held-out gain, reported beside it


@pytest.mark.slow
def test_wrong_records_the_scene_absorbs_are_named_through_the_exposure_learned_per_frame(tmp_path):
    """Seed 1294 of set 90: records x 1.25 or x 0.75 on a quarter of the frames, which the residual's records test
    did not name there (p_adj 0.071). Trained with `TrainConfig.learn_frame_exposure`, each altered training frame's
    learned scale stands out of the bulk (results/diagnosis/README.md, "2026-12-07: the exposure learned per frame")
    and correcting them gains within their frames: the records are named first, with at least half the altered frames flagged and at most 2 wrong."""
    row = sweep.run_case(tmp_path, "exposure_metadata", 1294, seed_set=90, in_process=True,
                         train_set=("pose_sample_step_px=0.0625", "max_pose_samples=32", "learn_timing=true",
                                    "learn_frame_exposure=true"))
    frames = _diagnosis(tmp_path / "cases" / "exposure_metadata_1294")["learned_frames"]
    assert frames["named"] == ["exposure_metadata"] and row["first"] == "exposure_metadata" and not row["wrong_first"]
    assert frames["detail"]["exposure_metadata"]["within_frame_gain_db"] > FRAME_LOCAL_GAIN_FLOOR_DB  # what names it
    altered = set(map(int, row["altered_frames"].split()))
    assert row["flagged_altered"] >= 0.5 * len(altered) and row["flagged_wrong"] <= 2
