"""Camera response: the sensor pipeline's true gamma against the assumed 2.2."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect


class Response(Effect):
    identifiability = (
        "on a trained run only through exposure x gain changes across frames (std of log exposure x gain "
        "at least 0.05) or a known non-flat vignette; a fixed exposure lets the colours absorb any tone "
        "curve")
    multiplicative = True
    trained_magnitudes = (0.45,)
    in_trained_sweep = True
    on_adt = True
    error_unit = "gamma"

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"response_gamma": float(value)}

    def sweep_value(self, magnitude, rng):
        sign = self.draw_sign(rng)
        return self.nominal * math.exp(sign * magnitude)

    def trained_value(self, magnitude, rng):  # gamma = 2.2 +- magnitude
        sign = self.draw_sign(rng)
        return self.nominal + sign * magnitude

    def _parameter_error(self, value, params):
        return abs(params["gamma"] - value)

    def synth_photometric(self, truth, value, shape):
        truth["gamma"] = float(value)

    def smallest_testable(self, d, se, ctx):
        g = ctx.gamma_assumed
        return {"gamma_deviation": max(abs(g / (1.0 - d) - g) if d < 1 else math.inf, abs(g / (1.0 + d) - g))}

    def plot_signature(self, ax, plot):
        x = np.asarray(plot["binned"]["x"])
        ax.plot(x, plot["binned"]["y"], "o", label="data (binned)")
        ax.plot(x, plot["slope"] * (x - plot["x0"]), "-", label="fit")
        ax.set_xlabel(plot["xlabel"]), ax.set_ylabel(plot["ylabel"]), ax.legend(fontsize=7)
        return True


RESPONSE = Response(
    name="response",
    description="Camera response phi: the true gamma of the sensor pipeline versus the assumed 2.2.",
    parameter="gamma", unit="1", nominal=2.2,
    plausible_range=(1.6, 2.8), sampling="uniform",
    formation_switch="response",
    signature="A monotone, intensity-dependent bias: a curved (not straight) scatter of captured versus "
    "predicted values, mid-tones off while black and white agree, and exposure changes not "
    "explained by a single scale.",
)
