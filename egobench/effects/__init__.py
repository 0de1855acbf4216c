"""One object per physical effect, one file each: the list the simulator hides, the trainer ablates and
the diagnosis looks for (docs/effects.md).

The registry `EFFECTS` is the only list of effects; the simulator, the synthetic cases, the sweeps,
the calibration of the nulls and the report loop over it and call each effect's hooks
(`egobench.effects.base.Effect`) instead of branching on its name. Adding an effect: its file here,
its line below, its test (docs/effects.md).
"""

from __future__ import annotations

import numpy as np

from egobench.effects.base import Effect, Sampling, Value
from egobench.effects.distortion import DISTORTION
from egobench.effects.exposure_blur import EXPOSURE_BLUR
from egobench.effects.exposure_metadata import EXPOSURE_METADATA
from egobench.effects.noise import NOISE
from egobench.effects.readout import READOUT
from egobench.effects.response import RESPONSE
from egobench.effects.time_offset import TIME_OFFSET
from egobench.effects.vignette import VIGNETTE
from egobench.effects.white_balance import WHITE_BALANCE

#: The registry, keyed by effect name (order: geometry/timing first, then photometric; the order
#: seeds `sample_hidden_effects`' streams, so a new effect goes at the end).
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    READOUT, TIME_OFFSET, EXPOSURE_BLUR, VIGNETTE, RESPONSE, WHITE_BALANCE, EXPOSURE_METADATA, NOISE, DISTORTION)}


def get_effect(name: str) -> Effect:
    """The effect called ``name``; ValueError listing the known names otherwise."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise ValueError(f"effect: unknown name {name!r}; expected one of {sorted(EFFECTS)}") from None


def sample_hidden_effects(names: list[str], seed: int) -> dict[str, Value]:
    """Seeded hidden values for several effects, each drawn from its own stream (order-independent)."""
    out: dict[str, Value] = {}
    for name in names:
        effect = get_effect(name)
        index = list(EFFECTS).index(name)
        out[name] = effect.sample_hidden(np.random.default_rng([int(seed), index]))
    return out


__all__ = ["EFFECTS", "Effect", "Sampling", "Value", "get_effect", "sample_hidden_effects"]
