"""The power of a diagnosis on one run: the smallest effect of each kind its tests could reveal (the minimum
detectable effect at the run's own standard errors), in the effects' parameter units.

On a trained run a geometric cause is named only when its frame t beats its placebos too (`residual.calibration`:
the permuted velocity fields' sequential rank p, and for a few placebos, such as the readout's wrong row times and
the distortion's wrong centres, the Student-t tail of `beat_placebos`). Where the placebos spread wider than the
frame test's own t distribution, the |t| a name needs is theirs, and the smallest testable effect is measured
against it (`placebo_critical_t`): the table says "testable" only where the run's own calibrated test could name it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.stats as sps

from egobench.diagnose.estimators import CAUSES
from egobench.effects import EFFECTS
from egobench.residual.calibration import PLACEBO_MAX, prediction_bound
from egobench.residual.estimation import CauseResult

#: Power of the minimum detectable effect (probability of detecting an effect of that size).
MDE_POWER = 0.8
#: The list-valued placebo statistics a calibration record may carry (`beat_placebos`' inputs).
PLACEBO_LISTS = ("placebo_t", "placebo_centre_t")


class DetectionScale(NamedTuple):
    """A test's between-frame standard error and degrees of freedom, its placebo calibrations' records on the same
    t scale (`_placebo_records`; none for the photometric tests' standard errors), and whether the test is
    one-sided (a positive statistic only, as exposure blur's)."""

    se: float
    df: int
    placebos: tuple = ()
    one_sided: bool = False


def geometric_standard_errors(results: list[CauseResult]) -> dict:
    """{cause: `DetectionScale`} of the geometric causes' tested parameter (between-frame spread), with the placebo
    records merged into each result."""
    return {r.name: DetectionScale(r.internal["frame_se"], r.internal["frame_df"], _placebo_records(r),
                                   bool(getattr(CAUSES.get(r.name), "one_sided", False)))
            for r in results if r.testable and "frame_se" in r.internal}


def _placebo_records(result: CauseResult) -> tuple:
    """The placebo calibrations merged into a result's params (`merge_record`: its ``calibration*`` dicts) whose
    real statistic is the frame test's own t; a placebo of another statistic (exposure blur's velocity placebo
    reads the residual before its shift-conditioned fit) is on another scale and is left out."""
    t = result.statistic
    if t is None:
        return ()
    return tuple(v for k, v in result.params.items() if k.startswith("calibration") and isinstance(v, dict)
                 and isinstance(v.get("first_order_t"), (int, float))
                 and math.isclose(float(v["first_order_t"]), float(t), rel_tol=1e-9, abs_tol=1e-12))


def placebo_critical_t(record: dict, level: float, one_sided: bool = False) -> float:
    """The smallest t (|t| for a two-sided test) that one placebo record lets pass below ``level`` (0 when the
    record holds no statistics; the larger of its two forms when it holds both):

    - a few placebo statistics (`PLACEBO_LISTS`, finite ones, at least two): above every one of them and beyond
      their Student-t prediction tail (`beat_placebos`);
    - a sequential rank p (`sequential_rank_p`: placebo_t_mean, placebo_t_sd, placebo_n): its p takes the values
      k / (1 + `PLACEBO_MAX`), so the level it must reach is the largest of them below ``level`` (inf where there is
      none); the placebos' mean (|mean| two-sided) + sd sqrt(1 + 1/n) times the Student-t quantile of that level
      (two-sided: its half) on n - 1 degrees of freedom, the prediction tail of n draws (an early stop leaves few)."""
    out = 0.0
    for key in PLACEBO_LISTS:
        ts = np.asarray(record.get(key) or [], dtype=np.float64)
        a = np.abs(ts[np.isfinite(ts)])
        if a.size >= 2:
            out = max(out, float(a.max()), prediction_bound(a.mean(), a.std(ddof=1), a.size, level))
    mean, sd, n = record.get("placebo_t_mean"), record.get("placebo_t_sd"), record.get("placebo_n")
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in (mean, sd, n)) or n < 2:
        return out
    k = math.ceil(level * (1 + PLACEBO_MAX)) - 1  # the largest k / (1 + PLACEBO_MAX) strictly below level
    if k < 1:
        return math.inf
    reach = k / (1 + PLACEBO_MAX)
    centre = float(mean) if one_sided else abs(float(mean))
    return max(out, prediction_bound(centre, float(sd), int(n), reach if one_sided else reach / 2))


def _mde_multiplier(alpha: float, m: int, scale: DetectionScale) -> float:
    """The frame t an effect needs to be named with power `MDE_POWER`: the larger of the frame test's own
    critical t (alpha / m; two-sided unless the test is one-sided) and its placebos' (`placebo_critical_t`), plus
    the power's t quantile."""
    df = max(int(scale.df), 2)
    level = alpha / max(m, 1)
    own = float(sps.t.isf(level if scale.one_sided else level / 2, df))
    critical = max([own] + [placebo_critical_t(p, level, scale.one_sided) for p in scale.placebos])
    return critical + float(sps.t.ppf(MDE_POWER, df))


def smallest_testable(se: dict, ctx, alpha: float, m: int) -> dict:
    """Smallest effect of each kind this run could reveal (power MDE_POWER at level alpha / m, its placebos
    included), in the effect's parameter units (see egobench.effects). ``se``: {cause: `DetectionScale`}."""
    out = {}
    for name, scale in se.items():
        s = scale.se
        if not (s is not None and math.isfinite(s) and s > 0):
            continue
        mult = _mde_multiplier(alpha, m, scale)
        if not math.isfinite(mult):
            continue
        smallest = EFFECTS[name].smallest_testable(mult * s, s, ctx) if name in EFFECTS else None
        if smallest is not None:
            out[name] = smallest
    return out
