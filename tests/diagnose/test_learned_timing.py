"""egobench.diagnose.learned_timing: the timing a run learned with its scene, judged against its floors."""

from __future__ import annotations

import json

import pytest

from egobench.diagnose.learned_timing import (READOUT_ERROR_FLOOR_MS, TIME_OFFSET_FLOOR_MS, judge_timing,
                                              learned_timing_of, timing_markdown)


def test_a_learned_value_names_its_cause_from_its_floor_the_largest_multiple_first():
    quiet = judge_timing({"time_offset_ms": 0.99 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": -0.99 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert quiet["named"] == [] and "nothing" in timing_markdown(quiet)
    both = judge_timing({"time_offset_ms": -1.5 * TIME_OFFSET_FLOOR_MS, "readout_error_ms": 2.5 * READOUT_ERROR_FLOOR_MS}, 0.008)
    assert both["named"] == ["readout", "time_offset"]
    assert both["time_offset_error_s"] == pytest.approx(-1.5e-3 * TIME_OFFSET_FLOOR_MS)
    assert both["readout_s_estimated"] == pytest.approx(0.008 + 2.5e-3 * READOUT_ERROR_FLOOR_MS)
    assert [d["multiple"] for d in both["detail"]] == pytest.approx([2.5, 1.5])
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
