"""Whether a significant cause earns its name: the gain of its extension on what it was not fitted on.

A cause is named only when modelling it improves frames or pixels it was not fitted on (core, step 3). The
decision is taken from the run itself, not from a constant calibrated on other sweeps:

* every path: the scored gain (the mean over the scored frames of their PSNR gain) is positive, and a cause
  that changes frames one by one (exposure metadata) changes at least one (`Cause.nothing_to_name`);
* a trained run, a cause with one estimate for all frames (time offset, readout, vignette, ...): the gain on
  the held-out frames beats the gains of the cause's own placebo extensions of those frames
  (`Cause.gain_placebo`: the same estimate along each frame's image motion turned away from its direction
  for a motion-driven cause, the same change with its tiles shuffled for any other), a one-sided rank p
  below the diagnosis's alpha. A
  placebo has the size and make-up of the real extension, so what a change of that size earns on this
  run's residual by chance (its model error included) is the floor, whatever the run's size or quality;
* a trained run, a cause with one parameter per frame (`Cause.frame_local`): scored on every frame's odd
  pixels, each frame's parameter from its own even pixels, and named only above FRAME_LOCAL_GAIN_FLOOR_DB.
  This is the one constant floor left: with a positive gain alone, 2 of 19 of egobench's confirmatory 'ours'
  runs (auto-exposed outdoor walks) named exposure metadata on one or two frames of model error, and a
  placebo of random other frames is no null for it (the flagged frames are selected for their deviation,
  so their own-scale gain beats random frames' whether or not a record is wrong).

The record behind the rule: results/diagnosis/README.md, "2026-12-05: floors from the run".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egobench.residual.calibration import PLACEBO_STOP, sequential_rank_p
from egobench.residual.estimation import Cause, CauseResult
from egobench.residual.signatures import DiagnosisContext, psnr

#: The within-frame gain a frame-local cause must exceed on a trained run (dB, mean over the frames).
FRAME_LOCAL_GAIN_FLOOR_DB = 0.05
#: Placebo extensions drawn at most for one gain test (smallest p 1 / 500; Besag-Clifford stop at PLACEBO_STOP).
GAIN_PLACEBOS = 499


def per_frame_psnr(images: np.ndarray, measured: np.ndarray, idx: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """PSNR (dB) of ``images`` against ``measured`` [F, H, W, 3] in each frame of ``idx`` on ``mask`` [H, W]."""
    return np.array([psnr(images[i:i + 1], measured[i:i + 1], mask) for i in np.asarray(idx).tolist()])


def per_frame_gains(new: np.ndarray, current: np.ndarray, measured: np.ndarray, idx: np.ndarray,
                    mask: np.ndarray) -> np.ndarray:
    """PSNR gain (dB) of ``new`` over ``current`` against ``measured`` [F, H, W, 3] in each frame of ``idx`` on
    ``mask`` [H, W] -> [len(idx)]; their mean is the scored gain (`signatures.psnr` averages frames' PSNR)."""
    return per_frame_psnr(new, measured, idx, mask) - per_frame_psnr(current, measured, idx, mask)


@dataclass
class GainTest:
    """The scored gain against its placebos (p 0 and no placebo where none was drawn)."""

    gain_db: float
    p_value: float
    placebo_mean_db: float
    placebo_n: int

    def to_params(self) -> dict:
        return {"gain_placebo_p": self.p_value, "gain_placebo_mean_db": self.placebo_mean_db,
                "gain_placebo_n": self.placebo_n}


def gain_placebo_test(cause: Cause, result: CauseResult, ctx: DiagnosisContext, current: np.ndarray,
                      extended: np.ndarray, measured: np.ndarray, idx: np.ndarray, mask: np.ndarray,
                      seed: int) -> GainTest:
    """Rank p (one-sided, `sequential_rank_p`) of the mean gain of ``extended`` over ``current`` on the frames
    ``idx`` against the gains of the cause's placebo extensions of those frames (`Cause.gain_placebo`)."""
    idx = np.asarray(idx)
    pred, ext, meas = current[idx], extended[idx], measured[idx]
    local = np.arange(idx.size)
    before = per_frame_psnr(pred, meas, local, mask)  # once: every draw scores against the same prediction
    real = float((per_frame_psnr(ext, meas, local, mask) - before).mean())
    rng = np.random.default_rng(seed)

    def draw(_k: int) -> float:
        placebo = cause.gain_placebo(pred, ext, result, ctx, idx, rng)
        return float((per_frame_psnr(placebo, meas, local, mask) - before).mean())

    p, _, gains = sequential_rank_p(real, draw, one_sided=True, stop=PLACEBO_STOP, n_max=GAIN_PLACEBOS)
    return GainTest(real, p, float(np.mean(gains)), len(gains))


def refusal(gain_db: float, test: GainTest | None, alpha: float, scored_on: str, floor_db: float = 0.0
            ) -> str | None:
    """Why a cause whose extension gains ``gain_db`` on what it was scored on is not named (None: it is), given
    its placebo test (None where the path has none) and the floor the gain must exceed (0: positive)."""
    if not gain_db > floor_db:
        if floor_db > 0:
            return f"{scored_on} gain {gain_db:+.4f} dB <= {floor_db} dB (FRAME_LOCAL_GAIN_FLOOR_DB): not named"
        return f"{scored_on} gain {gain_db:+.4f} dB is not positive: not named"
    if test is not None and not test.p_value < alpha:
        return (f"{scored_on} gain {gain_db:+.4f} dB does not beat the gains of its {test.placebo_n} placebo "
                f"extensions (mean {test.placebo_mean_db:+.4f} dB; rank p {test.p_value:.3g} >= alpha {alpha}): "
                "not named")
    return None


__all__ = ["FRAME_LOCAL_GAIN_FLOOR_DB", "GAIN_PLACEBOS", "GainTest", "gain_placebo_test", "per_frame_gains",
           "per_frame_psnr", "refusal"]
