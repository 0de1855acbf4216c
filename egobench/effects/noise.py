"""Sensor noise stronger or weaker than the device profile says."""

from __future__ import annotations

import math

from egobench.effects.base import Effect


class Noise(Effect):
    identifiability = (
        "not on a trained run: the model's own high-frequency error adds variance at every signal level; "
        "against ground truth or a twin only")
    multiplicative = True
    trained_magnitudes = (0.5,)
    on_adt = True
    variance_model = True
    trained_run_untestable = ("not identifiable from a trained run: the model's own high-frequency error adds residual "
                              "variance at every signal level, exactly as a stronger sensor noise would")

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"noise_std_factor": float(value)}

    def sweep_value(self, magnitude, rng):
        sign = self.draw_sign(rng)
        return self.nominal * math.exp(sign * magnitude)

    def trained_value(self, magnitude, rng):
        sign = self.draw_sign(rng)
        return math.exp(sign * magnitude)

    def _parameter_error(self, value, params):
        return abs(params["noise_std_factor"] / value - 1.0)

    def synth_photometric(self, truth, value, shape):
        truth["noise"] = truth["noise"].scaled(float(value))

    def plot_signature(self, ax, plot):
        ax.loglog(plot["signal"], plot["observed_var"], "o", label="observed")
        ax.loglog(plot["signal"], plot["assumed_var"], "-", label="assumed")
        ax.loglog(plot["signal"], plot["fitted_var"], "--", label="fitted")
        ax.set_xlabel(plot["xlabel"]), ax.set_ylabel(plot["ylabel"]), ax.legend(fontsize=7)
        return True


NOISE = Noise(
    name="noise",
    description="Sensor noise (formation.PoissonGaussianNoise) stronger or weaker than the device "
    "profile: every noise standard deviation times this factor (full well / f^2, read noise / f).",
    parameter="noise_std_factor", unit="1", nominal=1.0,
    plausible_range=(0.5, 2.0), sampling="log_uniform",
    formation_switch="noise",
    signature="Zero-mean, spatially white residuals whose variance is affine in the predicted linear "
    "signal (slope gain / full well, intercept from read noise), higher at higher gain.",
)
