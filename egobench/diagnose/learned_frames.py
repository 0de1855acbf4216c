"""The per-frame values a run learned with its scene (`TrainConfig.learn_frame_exposure`), judged by their effects
(`Effect.learned_per_frame`, `Effect.judge_learned_frames`): a cause is named where frames stand out of the bulk of
the run's own frames.

Why: with one exposure correction per training frame, a wrong record is the frame's own parameter rather than
something the shared scene absorbs; on 60 exploratory runs of set 90's seeds the altered frames' learned scales
stood out where the residual's records test had named 6 of 10 (results/diagnosis/README.md, "2026-12-07: the
exposure learned per frame").
"""

from __future__ import annotations

import json
from pathlib import Path

from egobench.effects import EFFECTS

#: effect -> its learned values' key in train.json
LEARNED = {name: e.learned_per_frame for name, e in EFFECTS.items() if e.learned_per_frame is not None}


def judge_learned_frames(run_dir: str | Path) -> dict | None:
    """The causes a run's per-frame learned values name -> {"named", "detail": {cause: verdict}}, or None when the
    run learned none (or has no train.json)."""
    path = Path(run_dir) / "train.json"
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    detail = {}
    for cause, key in LEARNED.items():
        learned = record.get(key)
        if learned is None:
            continue
        if not isinstance(learned, dict) or not isinstance(learned.get("frames"), list) or \
                not isinstance(learned.get("log_scale"), list):
            raise ValueError(f"{path}: field '{key}': expected {{'frames': [...], 'log_scale': [...]}}, got {learned!r}")
        try:
            detail[cause] = EFFECTS[cause].judge_learned_frames(learned["frames"], learned["log_scale"])
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
    if not detail:
        return None
    return {"named": [cause for cause, v in detail.items() if v["flagged_frames"]], "detail": detail}


def frames_markdown(judged: dict) -> str:
    """The report's section on per-frame values learned with the scene."""
    lines = ["\n## Per-frame values learned with the scene\n"]
    for cause, v in judged["detail"].items():
        lines.append(f"- {cause}: frames flagged beyond {v['threshold']:.3f} (log) from the bulk's centre "
                     f"{v['centre']:+.3f} (robust sd {v['bulk_sd']:.3f}): {', '.join(map(str, v['flagged_frames'])) or 'none'}")
        lines += [f"  - frame {f}: record error {e:+.2f}" for f, e in v["record_error"].items()]
    lines.append(f"- named: {', '.join(judged['named']) or 'nothing'}")
    return "\n".join(lines) + "\n"


__all__ = ["LEARNED", "frames_markdown", "judge_learned_frames"]
