"""Trained-run calibration (issue 15): a named cause must be significant against a null that
includes the trained model's own error, not only the sensor noise.

The cell-level tests of the estimators treat 4 x 4-pixel blocks as independent units. A trained
model's error is spatially correlated and differs from frame to frame, so on a trained run those
tests call almost anything significant (exposure metadata first, every time). Each effect therefore
calibrates its own test with placebos built from the run's own residual (`Cause.trained_placebos`, in
the effect's file; the shared machinery in `egobench.residual.calibration`):

* photometric causes (`Effect.trained_placebo` "photometric"): their coefficients fitted in every frame
  separately and tested ACROSS frames (frames are the units: the between-frame spread contains the model
  error), at the render's resolution, each against placebos of its own kind (wrong centres of the
  shading, the two halves of each frame for the exposure records, exposure changes for the response);
* static radial causes ("radial_centres"): the same statistic about wrong centres;
* motion-driven causes ("velocity_permutation"): the same statistic with the frames' velocity fields
  permuted (and, for some, further placebos of their own).

This module decides which placebos run and in what order, and returns their records; the diagnosis
(`egobench.diagnose.core`) merges them (`merge_record`): a calibrated p-value is the larger of the cause's
own and its placebos'. Noise and white balance have no test on a trained run (`Effect.trained_run_untestable`).
"""

from __future__ import annotations

from egobench.diagnose.estimators import CAUSES, assumed_noise_variance
from egobench.diagnose.power import DetectionScale
from egobench.effects import EFFECTS
from egobench.effects.base import TRAINED_PLACEBO_ORDER
from egobench.residual.calibration import PlaceboRecord, TrainedRunEvidence
from egobench.residual.estimation import CauseResult, ResidualData


def trained_run_records(data: ResidualData, results: list[CauseResult], draws: int, seed: int
                        ) -> tuple[list[tuple[CauseResult, PlaceboRecord]], dict[str, DetectionScale]]:
    """The placebo records of the testable causes in ``results`` on a trained run, in the order they are merged
    (`TRAINED_PLACEBO_ORDER`, then the results' order), and the between-frame standard errors of the photometric
    tests {cause: `DetectionScale`} (for the smallest testable effects; computed when any photometric cause is
    testable). ``draws``: the permutation tests' placebo draws; ``seed``: the round's placebo seed."""
    evidence = TrainedRunEvidence(data, draws, seed, assumed_noise_variance)
    testable = [r for r in results if r.testable]
    records = [(r, record) for kind in TRAINED_PLACEBO_ORDER for r in testable
               if EFFECTS[r.name].trained_placebo == kind for record in CAUSES[r.name].trained_placebos(r, evidence)]
    se: dict[str, DetectionScale] = {}
    if any(EFFECTS[r.name].trained_placebo == "photometric" for r in testable):
        for name, cause in CAUSES.items():
            s = cause.trained_standard_error(evidence)
            if s is not None:
                se[name] = DetectionScale(*s)
    return records, se


def mark_untestable_on_trained_run(results: list[CauseResult], data: ResidualData | None = None) -> None:
    """Mark the causes a trained run cannot show not testable (in place): those it never can
    (`Effect.trained_run_untestable`), and those this run's ``data`` cannot (`Cause.untestable_on_trained_run`)."""
    for r in results:
        reason = EFFECTS[r.name].trained_run_untestable if r.name in EFFECTS else None
        if reason is None and data is not None and r.name in CAUSES:
            reason = CAUSES[r.name].untestable_on_trained_run(data)
        if reason is not None and r.testable:
            r.testable, r.reason = False, reason


__all__ = ["mark_untestable_on_trained_run", "trained_run_records"]
