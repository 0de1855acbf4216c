"""The library of candidate causes the diagnosis tests: one estimator per effect of
`egobench.effects.EFFECTS` (each defined in its effect's file, `Effect.cause_class`; the shared
machinery is egobench.residual.estimation), instantiated once, in the registry's order."""

from __future__ import annotations

from egobench.effects import EFFECTS
from egobench.residual.estimation import Cause

#: effect name -> its estimator, in the order of egobench.effects.EFFECTS.
CAUSES: dict[str, Cause] = {name: effect.cause_class() for name, effect in EFFECTS.items()}


def variance_model_cause() -> Cause:
    """The estimator of the effect that models the residual's variance, not its mean (`Effect.variance_model`)."""
    return next(CAUSES[name] for name, effect in EFFECTS.items() if effect.variance_model)


def assumed_noise_variance(predicted, ctx, frames):
    """The assumed noise's per-pixel variance of ``predicted`` [f, H, W, 3] (frames: positions in ``ctx``)."""
    return variance_model_cause().variance(predicted, None, ctx, frames)
