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

from egobench.effects import EFFECTS
from egobench.residual.calibration import PLACEBO_MAX
from egobench.residual.estimation import CauseResult

#: Power of the minimum detectable effect (probability of detecting an effect of that size).
MDE_POWER = 0.8
#: The list-valued placebo statistics a calibration record may carry (`beat_placebos`' inputs).
PLACEBO_LISTS = ("placebo_t", "placebo_centre_t")


class DetectionScale(NamedTuple):
    """A test's between-frame standard error and degrees of freedom, and its placebo calibrations' records (the
    ``calibration*`` dicts of the cause's params; none for the photometric tests' standard errors)."""

    se: float
    df: int
    placebos: tuple = ()


def geometric_standard_errors(results: list[CauseResult]) -> dict:
    """{cause: `DetectionScale`} of the geometric causes' tested parameter (between-frame spread), with the placebo
    records merged into each result."""
    return {r.name: DetectionScale(r.internal["frame_se"], r.internal["frame_df"], _placebo_records(r))
            for r in results if r.testable and "frame_se" in r.internal}


def _placebo_records(result: CauseResult) -> tuple:
    """The placebo calibrations merged into a result's params (`merge_record`): its ``calibration*`` dicts."""
    return tuple(v for k, v in result.params.items() if k.startswith("calibration") and isinstance(v, dict))


def placebo_critical_t(record: dict, level: float) -> float:
    """The smallest |t| that one placebo record lets pass at ``level`` (0 when the record holds no statistics): for
    a few placebo statistics, above every one of them and beyond their Student-t prediction tail (`beat_placebos`);
    for a sequential rank p, |mean| + sd times the normal quantile of the two-sided level, or inf where the level
    is below the smallest rank p the test can give, 1 / (1 + `PLACEBO_MAX`)."""
    for key in PLACEBO_LISTS:
        ts = record.get(key)
        if isinstance(ts, list) and len(ts) >= 2:
            a = np.abs(np.asarray(ts, dtype=np.float64))
            n = a.size
            tail = a.mean() + a.std(ddof=1) * math.sqrt(1.0 + 1.0 / n) * float(sps.t.isf(level, n - 1))
            return float(max(a.max(), tail))
    mean, sd = record.get("placebo_t_mean"), record.get("placebo_t_sd")
    if mean is None or sd is None or not (math.isfinite(mean) and math.isfinite(sd)):
        return 0.0
    if level < 1.0 / (1 + PLACEBO_MAX):
        return math.inf
    return abs(float(mean)) + float(sd) * float(sps.norm.isf(level / 2))


def _mde_multiplier(alpha: float, m: int, scale: DetectionScale) -> float:
    """The frame t an effect needs to be named with power `MDE_POWER`: the larger of the frame test's own
    critical t (two-sided, alpha / m) and its placebos' (`placebo_critical_t`), plus the power's t quantile."""
    df = max(int(scale.df), 2)
    level = alpha / max(m, 1)
    critical = max([float(sps.t.ppf(1 - level / 2, df))] + [placebo_critical_t(p, level) for p in scale.placebos])
    return critical + float(sps.t.ppf(MDE_POWER, df))


def smallest_testable(se: dict, ctx, alpha: float, m: int) -> dict:
    """Smallest effect of each kind this run could reveal (power MDE_POWER at level alpha / m, its placebos
    included), in the effect's parameter units (see egobench.effects). ``se``: {cause: `DetectionScale` or (se, df)}."""
    out = {}
    for name, value in se.items():
        scale = value if isinstance(value, DetectionScale) else DetectionScale(*value)
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
