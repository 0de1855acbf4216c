"""Tests of the effect registry (egobench.effects)."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import egobench
from egobench.effects import EFFECTS, Effect, get_effect, sample_hidden_effects
from egobench.model.formation import FormationConfig

#: the nine effects of issue 6, in registry order (a new effect is appended: docs/effects.md)
NAMES = ["readout", "time_offset", "exposure_blur", "vignette", "response", "white_balance",
         "exposure_metadata", "noise", "distortion"]


def test_every_name_present_and_described():
    assert list(EFFECTS)[:len(NAMES)] == NAMES
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


# ------------------------------------------------------------------------------------------------
# One home per effect: every user of an effect calls its hooks (issue 33)


def _names_in(node) -> list[str]:
    """Effect names written as a literal in ``node``, or in a tuple, list or set literal it is."""
    if isinstance(node, ast.Constant) and node.value in EFFECTS:
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [e.value for e in node.elts if isinstance(e, ast.Constant) and e.value in EFFECTS]
    return []


def _effect_name_uses(source: str, every_use: bool) -> list[tuple[int, str, str]]:
    """(line, kind, name) of each effect name in ``source`` that decides by name: a comparison (==, !=), and with
    ``every_use`` also a membership test (in, not in), a subscript, a dict key or a .get/.pop/.setdefault key."""
    kinds = (ast.Eq, ast.NotEq, ast.In, ast.NotIn) if every_use else (ast.Eq, ast.NotEq)
    found = []
    for node in ast.walk(ast.parse(source)):
        names, kind = [], type(node).__name__
        if isinstance(node, ast.Compare) and any(isinstance(op, kinds) for op in node.ops):
            names = [n for side in [node.left, *node.comparators] for n in _names_in(side)]
        elif every_use and isinstance(node, ast.Subscript):
            names = _names_in(node.slice)
        elif every_use and isinstance(node, ast.Dict):
            names = [n for k in node.keys if k is not None for n in _names_in(k)]
        elif (every_use and isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr in ("get", "pop", "setdefault") and node.args):
            names, kind = _names_in(node.args[0]), "Call"
        found += [(node.lineno, kind, n) for n in names]
    return found


#: Where every use of an effect name counts (the diagnosis loops over the registry and calls the effects'
#: hooks); elsewhere in egobench/ only comparisons count ("distortion" also names a 2DGS loss, "noise" a texture,
#: "white_balance" a SimConfig field).
EVERY_USE = ("diagnose",)


def _effect_name_branches(root) -> list[str]:
    """Effect names that decide by name in egobench/ outside egobench/effects/ (ast scan; `_effect_name_uses`)."""
    found = []
    for path in sorted(Path(root).rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[:1] == ("effects",):
            continue
        every = rel.parts[:1] in [(p,) for p in EVERY_USE]
        found += [f"{rel}:{line} {kind} {name!r}" for line, kind, name in _effect_name_uses(path.read_text(), every)]
    return found


def test_no_branch_on_an_effect_name_outside_its_own_file():
    root = Path(egobench.__file__).parent
    assert _effect_name_branches(root) == []
    # the scan finds what it looks for: a planted branch is reported
    probe = root.parent / "tests" / "fixtures" / "effect_branch_probe"
    assert _effect_name_branches(probe) == ["probe.py:2 Compare 'vignette'"]


def test_the_diagnosis_scan_catches_a_planted_example_of_each_use():
    planted = {
        'by_name["vignette"].reason = "x"': "Subscript",
        'if "response" in by_name: pass': "Compare",
        'if name not in ("noise", "white_balance"): pass': "Compare",
        'se = {"exposure_metadata": (1.0, 2)}': "Dict",
        'r = by_name.get("readout")': "Call",
        'ok = name != "distortion"': "Compare",
    }
    for line, kind in planted.items():
        uses = _effect_name_uses(line, every_use=True)
        assert uses and {k for _l, k, _n in uses} == {kind}, line
    assert _effect_name_uses('x = by_name["vignette"]', every_use=False) == []
    assert _effect_name_uses('x = name == "time_offset"', every_use=False) == [(1, "Compare", "time_offset")]
    assert _effect_name_uses('x = d["gamma"]; y = "frames" in d', every_use=True) == []


def test_the_hooks_carry_what_the_sweeps_and_the_simulator_did_by_name():
    e = EFFECTS
    # the simulator: each effect's hidden value becomes its SimConfig fields
    assert e["readout"].sim_overrides(0.3) == {"readout_scale": 1.3}
    assert e["exposure_metadata"].sim_overrides(-0.2, 0.5) == {"exposure_metadata_error": -0.2,
                                                                "exposure_metadata_fraction": 0.5}
    assert e["white_balance"].sim_overrides([1.1, 1.0, 0.9]) == {"white_balance": (1.1, 1.0, 0.9)}
    # sweep magnitudes: fractions of the range's low end, its middle and its top; log-deviations for the
    # multiplicative parameters (noise: factor 0.5-2 around 1 -> |log 0.5| = log 2 both ways)
    assert e["vignette"].sweep_magnitudes((0.5, 1.0)) == pytest.approx([0.1, 0.2, 0.35, 0.5])
    assert e["noise"].sweep_magnitudes((0.5, 1.0)) == pytest.approx([0.346574, 0.693147])
    # hidden values: the same sign draw for every effect; response is multiplicative in the synthetic
    # sweep and additive in the trained one
    draws = {name: eff.sweep_value(0.2, np.random.default_rng(5)) for name, eff in e.items()}
    sign = 1.0 if np.random.default_rng(5).random() < 0.5 else -1.0
    assert draws["readout"] == sign * 0.2 and draws["vignette"] == 0.2
    assert draws["response"] == pytest.approx(2.2 * np.exp(sign * 0.2))
    assert e["response"].trained_value(0.2, np.random.default_rng(5)) == pytest.approx(2.2 + sign * 0.2)
    wb = e["white_balance"].trained_value(0.1, np.random.default_rng(5))
    assert wb[1] == 1.0 and wb[0] * wb[2] == pytest.approx(1.0)
    # parameter errors, in each effect's unit; a missing estimate is None, not an exception
    assert e["exposure_blur"].parameter_error(0.008, {"exposure_s": 0.006}) == pytest.approx(0.25)
    assert e["white_balance"].parameter_error((1.2, 1.0, 0.8), {"channel_gains_relative_to_green": [1.2, 1, 0.88]}) \
        == pytest.approx(0.1)
    assert e["distortion"].parameter_error(0.01, {}) is None
    assert {n: e[n].error_unit for n in NAMES} == {
        "readout": "fraction", "time_offset": "s", "exposure_blur": "relative", "vignette": "fraction",
        "response": "gamma", "white_balance": "relative", "exposure_metadata": "fraction", "noise": "relative",
        "distortion": "relative"}


def test_synthetic_injection_hooks():
    R = np.linspace(0.0, 1.0, 5)[:, None] * np.ones((5, 3))
    t_model = (R - 0.5) * 0.01
    t_true = EFFECTS["readout"].synth_row_times(t_model, R, 0.5, 0.01)
    np.testing.assert_allclose(t_true[-1] - t_true[0], 0.015)  # the readout is 1.5 times longer
    np.testing.assert_allclose(t_true[0], t_model[0])  # from the same read start
    np.testing.assert_allclose(EFFECTS["time_offset"].synth_row_times(t_model, R, 0.002, 0.01), t_model + 0.002)
    np.testing.assert_array_equal(EFFECTS["vignette"].synth_row_times(t_model, R, 0.3, 0.01), t_model)
    k = np.ones(24)
    affected = EFFECTS["exposure_metadata"].synth_exposure(k, np.random.default_rng(0), 0.2, 0.25)
    assert 8 in affected and len(affected) == 6 and np.allclose(k[affected], 1.2) and (k == 1.2).sum() == 6
    assert EFFECTS["noise"].synth_exposure(np.ones(24), np.random.default_rng(0), 0.2, 0.25) == []
    # exposure blur averages the image over the exposure: a linear-in-time image keeps its mean
    blurred = EFFECTS["exposure_blur"].synth_irradiance(lambda t, d: t[None, :, :, None] * np.ones(3), t_model, None, 0.008)
    np.testing.assert_allclose(blurred[0, :, :, 0], t_model, atol=1e-15)


def test_exposure_blur_instants_are_the_velocity_times_each_sub_exposure_time():
    """The blur's warp parts (made one at a time when read): n_sub equal weights, displacement = pixel
    velocity x (tau x T) at the sub-exposure instants tau in (-1/2, 1/2), symmetric about the row's time."""
    from types import SimpleNamespace

    from egobench.effects.exposure_blur import ExposureBlurCause

    velocity = np.random.default_rng(0).normal(size=(3, 4, 5, 2)).astype(np.float32) * 100.0
    ctx = SimpleNamespace(pixel_velocity_px_s=velocity)
    cause = ExposureBlurCause()
    parts = cause.displacement(np.array([0.009]), ctx, np.array([2, 0]), (2, 4, 5, 3))
    assert len(parts) == cause.n_sub == 9
    times = [(k + 0.5) / 9 - 0.5 for k in range(9)]
    for (weight, disp), t in zip(parts, times, strict=True):
        assert weight == 1.0 / 9 and disp.dtype == np.float64
        np.testing.assert_allclose(disp, velocity[[2, 0]].astype(np.float64) * (t * 0.009), rtol=1e-15)
    np.testing.assert_allclose(parts[0][1], -parts[8][1], rtol=1e-15)  # symmetric instants
    assert not parts[4][1].any()  # the middle instant is the row's own time
    with pytest.raises(IndexError):
        parts[9]
