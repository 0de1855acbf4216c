"""The timing a run learned with its scene (`TrainConfig.learn_timing`), judged: a time offset or a readout error
named where the learned value clears its floor.

Why a learned timing: a residual test on a trained run sees only the share of a timing error that the scene did
not absorb, and training absorbs more the longer it runs. At 64 px the readout's median frame t fell from 4.5 to
1.9 between 400 and 3200 iterations, and leaving each frame out of its model's training did not bring it back
(results/diagnosis/README.md, "2026-12-07: the timing tests against training length"). Learned with the scene,
as the model's own parameters (`motion_sampling.timed_poses`), the same errors come back nearly whole: on 40
exploratory runs of set 89's seeds a hidden 3 ms offset was learned as 2.34-3.02 ms and a readout 4 ms long as
2.86-4.37 ms, while nulls and 40 % vignettes learned at most 0.26 ms of offset and 0.89 ms of readout error
("2026-12-07: the timing learned with the scene").

The floors are constants chosen on those exploratory runs, before the fresh set that tests them: they are not yet
the run's own (issue 72's floors from the run itself). A run-derived null for a learned parameter, such as the
timing learned along placebo twists, is the step after.
"""

from __future__ import annotations

import json
from pathlib import Path

#: |learned time offset| (ms) from which a time offset is named (exploratory nulls and vignettes: at most 0.26)
TIME_OFFSET_FLOOR_MS = 1.0
#: |learned readout error| (ms) from which a readout error is named (exploratory nulls, vignettes and time
#: offsets: at most 1.12)
READOUT_ERROR_FLOOR_MS = 2.0
#: cause -> (the learned value's key in train.json's ``learned_timing``, its floor in ms)
FLOORS = {"time_offset": ("time_offset_ms", TIME_OFFSET_FLOOR_MS), "readout": ("readout_error_ms", READOUT_ERROR_FLOOR_MS)}


def learned_timing_of(run_dir: str | Path) -> dict | None:
    """The timing correction a run learned (train.json's ``learned_timing``: time offset and readout error, ms), or
    None when the run did not learn one (or has no train.json: a checkpoint alone says nothing of it)."""
    path = Path(run_dir) / "train.json"
    if not path.is_file():
        return None
    learned = json.loads(path.read_text()).get("learned_timing")
    if learned is None:
        return None
    for key, _ in FLOORS.values():
        if not isinstance(learned.get(key), (int, float)):
            raise ValueError(f"{path}: field 'learned_timing.{key}': expected a number (ms), got {learned.get(key)!r}")
    return learned


def judge_timing(learned: dict, stated_readout_s: float) -> dict:
    """The causes a learned timing names -> the record: the learned values, the floors, the named causes (the
    largest multiple of its floor first) and their estimates in the diagnosis's units."""
    detail = []
    for cause, (key, floor) in FLOORS.items():
        value = float(learned[key])
        if abs(value) >= floor:
            detail.append({"cause": cause, "learned_ms": value, "floor_ms": floor, "multiple": abs(value) / floor})
    detail.sort(key=lambda d: -d["multiple"])
    return {"learned": {k: float(learned[k]) for k, _ in FLOORS.values()},
            "floors_ms": {cause: floor for cause, (_, floor) in FLOORS.items()},
            "named": [d["cause"] for d in detail], "detail": detail,
            "time_offset_error_s": float(learned["time_offset_ms"]) * 1e-3,
            "readout_s_estimated": float(stated_readout_s) + float(learned["readout_error_ms"]) * 1e-3}


def timing_markdown(judged: dict) -> str:
    """The report's section on a learned timing."""
    lines = ["\n## The timing learned with the scene\n",
             f"- learned time offset {judged['learned']['time_offset_ms']:+.3f} ms (named from "
             f"{TIME_OFFSET_FLOOR_MS} ms), readout error {judged['learned']['readout_error_ms']:+.3f} ms (named from "
             f"{READOUT_ERROR_FLOOR_MS} ms)",
             f"- named: {', '.join(judged['named']) or 'nothing'}"]
    if "readout" in judged["named"]:
        lines.append(f"- readout {judged['readout_s_estimated'] * 1e3:.2f} ms")
    return "\n".join(lines) + "\n"


__all__ = ["FLOORS", "READOUT_ERROR_FLOOR_MS", "TIME_OFFSET_FLOOR_MS", "judge_timing", "learned_timing_of",
           "timing_markdown"]
