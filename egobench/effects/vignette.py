"""Lens shading beyond the calibrated vignette: an extra radial falloff toward the corners."""

from __future__ import annotations

import math

from egobench.effects.base import Effect
from egobench.model.formation import radial_vignette


class Vignette(Effect):
    identifiability = (
        "only when the views move points across the image (a surface seen near the centre in one frame "
        "and near a corner in another); a trained model otherwise absorbs the shading into the colours")
    trained_magnitudes = (0.35,)
    in_trained_sweep = True
    on_adt = True
    learned_by_shading_extension = True
    hidden_on_raw_sensor = True
    error_unit = "fraction"

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"vignette_strength": float(value)}

    def _parameter_error(self, value, params):
        return abs(params["corner_attenuation"] - value)

    def synth_photometric(self, truth, value, shape):
        truth["vignette"] = truth["vignette"] * radial_vignette(shape, float(value), power=4.0).numpy()

    def smallest_testable(self, d, se, ctx):
        return {"corner_attenuation": 1.0 - math.exp(-d)}

    def plot_signature(self, ax, plot):
        ax.plot(plot["binned"]["x"], plot["binned"]["y"], "o", label="data (binned)")
        ax.plot(plot["curve_r"], plot["curve"], "-", label="fit")
        ax.set_xlabel(plot["xlabel"]), ax.set_ylabel(plot["ylabel"]), ax.legend(fontsize=7)
        return True


VIGNETTE = Vignette(
    name="vignette",
    description="Lens shading not contained in the calibrated vignette image: an extra radial "
    "falloff (formation.radial_vignette, cos^4-like) attenuating the corners by this fraction.",
    parameter="corner_attenuation", unit="fraction", nominal=0.0,
    plausible_range=(0.20, 0.50), sampling="uniform",
    formation_switch="vignette",
    signature="A smooth, radially symmetric, multiplicative darkening of the captured image relative to "
    "the prediction, identical in every frame and view-independent, growing towards the corners.",
)
