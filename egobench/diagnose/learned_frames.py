"""The per-frame values a run learned with its scene (`TrainConfig.learn_frame_exposure`), judged by their effects
(`Effect.learned_per_frame`, `Effect.judge_learned_frames`): a cause is named where frames stand out of the bulk of
the run's own frames and correcting them gains on pixels they were not fitted on.

Why: with one exposure correction per training frame, a wrong record is the frame's own parameter rather than
something the shared scene absorbs; on 60 exploratory runs of set 90's seeds the altered frames' learned scales
stood out where the residual's records test had named 6 of 10 (results/diagnosis/README.md, "2026-12-07: the
exposure learned per frame").

The gain: as the residual route's frame-local causes (`egobench.diagnose.gain`), a flagged frame's correction (one
scale) is estimated on its even pixels and scored on its odd ones (`Effect.learned_frames_gain`), and the cause is
named only where that within-frame gain exceeds `gain.FRAME_LOCAL_GAIN_FLOOR_DB` (the same floor, the same mean
over the diagnosis's frames). What is held out is the correction, not the scene: the run, and the scale it learned,
saw every pixel, as the residual route's run did. A flagged frame at the bulk's centre that its own pixels ask no
scale of gains nothing, and is model error the scale traded against the scene's colours (measured on a null's last
frame: results/diagnosis/README.md, "2026-12-07: the learned per-frame exposure's within-frame gain"). Without
renders (`judge_learned_frames` with no source) the verdict is the flags alone and says so; where the gain cannot
be measured, nothing is named, with the reason.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from egobench.diagnose.core import within_frame_masks
from egobench.diagnose.gain import FRAME_LOCAL_GAIN_FLOOR_DB, refusal
from egobench.effects import EFFECTS

if TYPE_CHECKING:  # the renders' type only: the module reads nothing of the source's own
    from egobench.diagnose.sources import Sources

#: effect -> its learned values' key in train.json
LEARNED = {name: e.learned_per_frame for name, e in EFFECTS.items() if e.learned_per_frame is not None}
#: What the within-frame gain is scored on, in a refusal's words (`gain.refusal`).
SCORED_ON = "within-frame PSNR (flagged frames corrected from their even pixels)"


def judge_learned_frames(run_dir: str | Path, source: Sources | None = None, border_px: int = 2) -> dict | None:
    """The causes a run's per-frame learned values name -> {"named", "detail": {cause: verdict}}, or None when the
    run learned none (or has no train.json). With ``source`` (`sources.run_source` of the run), each verdict with
    flagged frames carries its within-frame gain ("within_frame_gain_db"), and a cause whose gain does not exceed
    the floor is not named ("not_named", the reason); without it, the flags alone name ("gain": "not measured")."""
    path = Path(run_dir) / "train.json"
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    detail, named = {}, []
    for cause, key in LEARNED.items():
        learned = record.get(key)
        if learned is None:
            continue
        if not isinstance(learned, dict) or not isinstance(learned.get("frames"), list) or \
                not isinstance(learned.get("log_scale"), list):
            raise ValueError(f"{path}: field '{key}': expected {{'frames': [...], 'log_scale': [...]}}, got {learned!r}")
        try:
            verdict = EFFECTS[cause].judge_learned_frames(learned["frames"], learned["log_scale"])
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        detail[cause] = verdict
        if verdict["flagged_frames"] and _earns_name(cause, verdict, learned, source, border_px):
            named.append(cause)
    if not detail:
        return None
    return {"named": named, "detail": detail}


def _earns_name(cause: str, verdict: dict, learned: dict, source: Sources | None, border_px: int) -> bool:
    """Whether a verdict with flagged frames names its cause: its within-frame gain on ``source`` exceeds the floor
    (recorded in the verdict, in place); without a source, by its flags alone."""
    if source is None:
        verdict["gain"] = "not measured (no renders)"
        return True
    fit_mask, eval_mask = within_frame_masks(source.context, border_px)
    by_frame = {int(f): float(v) for f, v in zip(learned["frames"], learned["log_scale"])}
    try:
        gain = EFFECTS[cause].learned_frames_gain(source.measured, source.predicted, source.context, verdict,
                                                  by_frame, fit_mask, eval_mask)
    except ValueError as e:
        gain, why = None, f"the within-frame gain could not be measured ({e}): not named"
    else:
        why = "none of the flagged frames is among the diagnosed frames (--max-frames): no gain measured, not named"
    if gain is None:
        verdict["not_named"] = why
        return False
    verdict.update(within_frame_gain_db=float(gain["gain_db"]), gain_frames=int(gain["frames"]),
                   gain_floor_db=FRAME_LOCAL_GAIN_FLOOR_DB)
    reason = refusal(verdict["within_frame_gain_db"], None, 0.0, SCORED_ON, FRAME_LOCAL_GAIN_FLOOR_DB)
    if reason is not None:
        verdict["not_named"] = reason
    return reason is None


def frames_markdown(judged: dict) -> str:
    """The report's section on per-frame values learned with the scene."""
    lines = ["\n## Per-frame values learned with the scene\n"]
    for cause, v in judged["detail"].items():
        lines.append(f"- {cause}: frames flagged beyond {v['threshold']:.3f} (log) from the bulk's centre "
                     f"{v['centre']:+.3f} (robust sd {v['bulk_sd']:.3f}): {', '.join(map(str, v['flagged_frames'])) or 'none'}")
        lines += [f"  - frame {f}: record error {e:+.2f}" for f, e in v["record_error"].items()]
        if "within_frame_gain_db" in v:
            lines.append(f"  - within-frame gain of correcting them {v['within_frame_gain_db']:+.4f} dB "
                         f"(named above {v['gain_floor_db']} dB)")
        if "not_named" in v:
            lines.append(f"  - {v['not_named']}")
    lines.append(f"- named: {', '.join(judged['named']) or 'nothing'}")
    return "\n".join(lines) + "\n"


__all__ = ["LEARNED", "SCORED_ON", "frames_markdown", "judge_learned_frames"]
