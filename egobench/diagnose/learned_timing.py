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

The floors (`Effect.learned_timing`, in each effect's file) are constants chosen on those exploratory runs, before
the fresh set that tested them (set 90): they are not the run's own (issue 72's floors from the run itself). Beside
each learned value the record gives its standard error on the run (`timing_pulls`: the training frames' pulls on
it with the scene held as trained, a block sandwich) and t. That t does not decide, measured on 100 runs of sets
89 and 90 (results/diagnosis/README.md, "2026-12-07: the learned timing's standard error from the run"): the
frames' scatter leaves out what training's co-adaptation adds, so a null learned an offset of 0.19 ms at t 4.6,
while two readout errors of 2.9-3.4 ms stood at t 2.2-2.3. Retrained with four other seeds, nulls learned the
same 0.1-0.3 ms offsets again: a bias of the recording and the model, not noise, so the floors are a size, the
smallest timing error worth naming.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.stats import t as student_t

from egobench.data.reader import load_recording
from egobench.diagnose.timing_pulls import TimedRun, frame_pulls, sandwich_standard_error
from egobench.effects import EFFECTS
from egobench.io_utils import claim_work_dir
from egobench.model.motion_sampling import TIMING_FIELDS
from egobench.train import train
from egobench.train.checkpoint import load_trained_run

#: effect -> (its learned value's key in train.json's ``learned_timing``, the floor in ms from which it is named):
#: the effects learned with the scene (`Effect.learned_timing`)
FLOORS = {name: e.learned_timing for name, e in EFFECTS.items() if e.learned_timing is not None}


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


def timing_of_run(recording_dir: str | Path, run_dir: str | Path, work_dir: str | Path,
                  progress: bool = False) -> tuple[dict, Path]:
    """The timing ``run_dir`` learned, and where -> (learned, run folder). A run that learned none is trained once
    more, its method with its config and seed and ``learn_timing`` on, into WORK_DIR/run (a complete run there is
    reused, a partial one resumed): the timing that run learns is the user's run's (`egobench diagnose
    --learn-timing`; a second training, as `--lens-check`'s)."""
    learned = learned_timing_of(run_dir)
    if learned is not None:
        return learned, Path(run_dir)
    run = load_trained_run(run_dir, None, f"learned timing of {run_dir}")
    claim_work_dir(work_dir, "learn_timing.json",
                   {"run": str(Path(run_dir).resolve()), "recording": str(Path(recording_dir).resolve())}, "the timing run")
    retrained = Path(work_dir) / "run"
    done = retrained / "train.json"
    if not (done.is_file() and json.loads(done.read_text()).get("complete")):
        recording = load_recording(recording_dir, calibration=run.spec.calibration)
        train(recording, run.spec.name, replace(run.config, learn_timing=True), retrained, resume="auto",
              progress=progress)
    learned = learned_timing_of(retrained)
    if learned is None:
        raise ValueError(f"{done}: a run trained with learn_timing recorded no learned_timing")
    return learned, retrained


def timing_evidence(timed: TimedRun, progress: bool = False) -> dict:
    """The learned timing's standard errors on its run -> {"se_ms": {key: ms}, "df", "frames"} (`timing_pulls`:
    the run's training frames' pulls on it, the scene held as trained)."""
    pulls, curvature = frame_pulls(timed, progress=progress)
    se, df = sandwich_standard_error(pulls, curvature)
    return {"se_ms": dict(zip(TIMING_FIELDS, map(float, se))), "df": int(df), "frames": int(pulls.shape[0])}


def judge_timing(learned: dict, stated_readout_s: float, evidence: dict | None = None) -> dict:
    """The causes a learned timing names -> the record: the learned values, the floors, the named causes (the
    largest multiple of its floor first), each with its estimate, and every learned effect's estimate in the
    residual diagnosis's keys (`Effect.learned_estimate`). With ``evidence`` (`timing_evidence`), each learned
    value's standard error on the run, t and two-sided p on ``evidence["df"]`` degrees of freedom ("tests";
    reported, not deciding: module doc)."""
    detail, estimates, tests = [], {}, {}
    for cause, (key, floor) in FLOORS.items():
        value = float(learned[key])
        estimate = EFFECTS[cause].learned_estimate(value, stated_readout_s)
        estimates.update(estimate)
        if evidence is not None:
            tests[cause] = _t_test(value, evidence, key)
        if abs(value) >= floor:
            detail.append({"cause": cause, "learned_ms": value, "floor_ms": floor, "multiple": abs(value) / floor,
                           "estimate": estimate})
    detail.sort(key=lambda d: -d["multiple"])
    record = {"learned": {key: float(learned[key]) for key, _ in FLOORS.values()},
              "floors_ms": {cause: floor for cause, (_, floor) in FLOORS.items()},
              "named": [d["cause"] for d in detail], "detail": detail, **estimates}
    if evidence is not None:
        record.update(tests=tests, df=int(evidence["df"]), frames=evidence.get("frames"))
    return record


def _t_test(value: float, evidence: dict, key: str) -> dict:
    """A learned value against its standard error on the run -> {"se_ms", "t", "p"} (two-sided, t(df))."""
    se = float(evidence["se_ms"][key])
    if not (np.isfinite(se) and se > 0):
        raise ValueError(f"learned timing evidence: field 'se_ms.{key}': expected a positive standard error (ms), "
                         f"got {se!r}")
    t_value = value / se
    return {"se_ms": se, "t": t_value, "p": float(2.0 * student_t.sf(abs(t_value), int(evidence["df"])))}


def timing_markdown(judged: dict) -> str:
    """The report's section on a learned timing."""
    lines = ["\n## The timing learned with the scene\n"]
    for cause, floor in judged["floors_ms"].items():
        line = f"- {cause}: learned {judged['learned'][FLOORS[cause][0]]:+.3f} ms, named from {floor} ms"
        test = judged.get("tests", {}).get(cause)
        if test is not None:
            line += (f" (standard error {test['se_ms']:.3f} ms from the run's frames, t({judged['df']}) = "
                     f"{test['t']:+.2f}, p {test['p']:.3g}; reported, not deciding)")
        lines.append(line)
    held_out = judged.get("held_out")
    if held_out is not None:
        lines.append(f"- held-out gain of rendering with the learned timing rather than the stated one: "
                     f"{held_out['gain_db']:+.4f} dB over {held_out['frames']} frames (reported, not deciding)")
    lines.append(f"- named: {', '.join(judged['named']) or 'nothing'}")
    lines += [f"- {d['cause']}: " + ", ".join(f"{k} {v:.6g}" for k, v in d["estimate"].items()) for d in judged["detail"]]
    return "\n".join(lines) + "\n"


__all__ = ["FLOORS", "judge_timing", "learned_timing_of", "timing_evidence",
           "timing_markdown", "timing_of_run"]
