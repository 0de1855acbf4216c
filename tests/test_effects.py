"""Tests of the effect registry (egobench.effects)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from egobench.effects import EFFECTS, Effect, get_effect, sample_hidden_effects
from egobench.formation import FormationConfig

NAMES = ["readout", "time_offset", "exposure_blur", "vignette", "response", "white_balance",
         "exposure_metadata", "noise", "distortion"]


def test_every_name_present_and_described():
    assert sorted(EFFECTS) == sorted(NAMES)
    config_fields = {f.name for f in dataclasses.fields(FormationConfig)}
    for name, effect in EFFECTS.items():
        assert effect.name == name
        assert effect.description and effect.signature and effect.parameter and effect.unit
        assert effect.signature.rstrip().endswith(".")
        assert effect.formation_switch is None or effect.formation_switch in config_fields
        json.dumps(effect.to_dict())


def test_ranges_follow_issue_6():
    assert EFFECTS["response"].nominal == 2.2 and EFFECTS["response"].plausible_range == (1.6, 2.8)
    assert EFFECTS["time_offset"].unit == "s" and EFFECTS["time_offset"].plausible_range == (1e-3, 5e-3)
    assert EFFECTS["readout"].plausible_range == (0.2, 0.6)
    assert EFFECTS["vignette"].plausible_range == (0.2, 0.5)
    assert EFFECTS["exposure_blur"].plausible_range == (4e-3, 10e-3)
    assert EFFECTS["exposure_metadata"].plausible_range == (0.1, 0.3)
    assert EFFECTS["white_balance"].plausible_range == (0.8, 1.25) and EFFECTS["white_balance"].size == 3
    for name in ("time_offset", "readout", "exposure_metadata", "distortion"):
        assert EFFECTS[name].nominal == 0.0


@pytest.mark.parametrize("name", NAMES)
def test_sample_hidden_within_range_and_seeded(name):
    effect = EFFECTS[name]
    rng = np.random.default_rng(123)
    draws = [effect.sample_hidden(rng) for _ in range(300)]
    lo, hi = effect.plausible_range
    for value in draws:
        assert effect.in_range(value)
        values = value if isinstance(value, tuple) else (value,)
        assert len(values) == effect.size
        mags = [abs(v) for v in values] if effect.sampling == "signed" else list(values)
        assert all(lo <= m <= hi for m in mags)
    flat = np.array(draws, dtype=float).reshape(len(draws), -1)
    # the draws spread over the range (not a constant), and signed effects take both signs
    mags = np.abs(flat) if effect.sampling == "signed" else flat
    assert mags.min() < lo + 0.2 * (hi - lo) and mags.max() > hi - 0.2 * (hi - lo)
    if effect.sampling == "signed":
        assert (flat < 0).any() and (flat > 0).any()
    # seeded: the same seed gives the same value, another seed another value
    assert effect.sample_hidden(np.random.default_rng(5)) == effect.sample_hidden(np.random.default_rng(5))
    assert effect.sample_hidden(5) == effect.sample_hidden(np.random.default_rng(5))
    assert effect.sample_hidden(5) != effect.sample_hidden(6)


def test_in_range_rejects_values_outside():
    assert not EFFECTS["response"].in_range(2.9)
    assert not EFFECTS["time_offset"].in_range(0.0)
    assert EFFECTS["time_offset"].in_range(-2e-3)
    assert not EFFECTS["white_balance"].in_range((1.0, 1.0))
    assert not EFFECTS["white_balance"].in_range((1.0, 1.0, 1.5))


def test_errors():
    with pytest.raises(ValueError, match="rng"):
        EFFECTS["noise"].sample_hidden("seed")
    with pytest.raises(ValueError, match="unknown name"):
        get_effect("lens_flare")
    with pytest.raises(ValueError, match="plausible_range"):
        Effect(name="x", description="d", parameter="p", unit="1", nominal=0.0, plausible_range=(2.0, 1.0),
               sampling="uniform", signature="s.")
    with pytest.raises(ValueError, match="log_uniform"):
        Effect(name="x", description="d", parameter="p", unit="1", nominal=0.0, plausible_range=(0.0, 1.0),
               sampling="log_uniform", signature="s.")


def test_sample_hidden_effects_is_seeded_and_order_independent():
    a = sample_hidden_effects(["response", "noise", "white_balance"], seed=3)
    b = sample_hidden_effects(["white_balance", "response", "noise"], seed=3)
    c = sample_hidden_effects(["response", "noise", "white_balance"], seed=4)
    assert a == b and a != c
    assert all(EFFECTS[k].in_range(v) for k, v in a.items())
