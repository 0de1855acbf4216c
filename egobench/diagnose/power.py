"""The power of a diagnosis on one run: the smallest effect of each kind its tests could reveal (the minimum
detectable effect at the run's own standard errors), in the effects' parameter units."""

from __future__ import annotations

import math

import scipy.stats as sps

from egobench.effects import EFFECTS
from egobench.residual.estimation import CauseResult

#: Power of the minimum detectable effect (probability of detecting an effect of that size).
MDE_POWER = 0.8


def geometric_standard_errors(results: list[CauseResult]) -> dict:
    """{cause: (se, df)} of the geometric causes' tested parameter (between-frame spread)."""
    return {r.name: (r.internal["frame_se"], r.internal["frame_df"]) for r in results
            if r.testable and "frame_se" in r.internal}


def _mde_multiplier(alpha: float, m: int, df: int) -> float:
    df = max(int(df), 2)
    return float(sps.t.ppf(1 - alpha / (2 * max(m, 1)), df) + sps.t.ppf(MDE_POWER, df))


def smallest_testable(se: dict, ctx, alpha: float, m: int) -> dict:
    """Smallest effect of each kind this run could reveal (power MDE_POWER at level alpha / m),
    in the effect's parameter units (see egobench.effects)."""
    out = {}
    for name, (s, df) in se.items():
        if not (s is not None and math.isfinite(s) and s > 0):
            continue
        d = _mde_multiplier(alpha, m, df) * s
        smallest = EFFECTS[name].smallest_testable(d, s, ctx) if name in EFFECTS else None
        if smallest is not None:
            out[name] = smallest
    return out
