"""Rolling-shutter readout time: the stated readout is off by a relative error."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect


class Readout(Effect):
    identifiability = (
        "only with image motion during the readout: the shear grows with row time and image speed, so "
        "quasi-static frames show nothing")
    trained_magnitudes = (0.4,)
    error_unit = "fraction"
    trained_placebo = "velocity_permutation"
    trained_row_time_placebo = True

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"readout_scale": 1.0 + float(value)}  # relative error e: true = stated (1 + e)

    def _parameter_error(self, value, params):
        return abs(params["readout_relative_error"] - value)

    def synth_row_times(self, t_model, R, value, readout_s):
        return -0.5 * readout_s + R * readout_s * (1.0 + float(value))  # read start right, readout (1 + e) longer

    def smallest_testable(self, d, se, ctx):
        return {"readout_relative_error": d / ctx.readout_s if ctx.readout_s > 0 else math.inf}

    def plot_signature(self, ax, plot):
        if "row_time_ratio" not in plot:
            return False
        r = np.asarray(plot["row_time_ratio"])
        ax.plot(r, np.asarray(plot["time_shift_s"]) * 1e3, "o", label="per row band")
        a, b = plot["fit_a_b"]
        ax.plot(r, (a + b * (r - 0.5)) * 1e3, "-", label="fit a + b (R - 1/2)")
        ax.set_xlabel("row time ratio R(u)"), ax.set_ylabel("time shift (ms)"), ax.legend(fontsize=7)
        return True


READOUT = Readout(
    name="readout",
    description="Rolling-shutter readout: raw row r starts exposing at read_start + R(u) * readout_s. "
    "Hidden: the true readout differs from the metadata by a relative error e (true = nominal * (1 + e)).",
    parameter="readout_relative_error", unit="fraction", nominal=0.0,
    plausible_range=(0.20, 0.60), sampling="signed",
    signature="Misalignment that grows linearly with row time R(u) and with image-space velocity: "
    "edges shear along the motion, residual largest at the top and bottom rows of fast frames.",
)
