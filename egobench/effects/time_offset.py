"""Camera-to-device clock offset: the calibrated offset is wrong by some milliseconds."""

from __future__ import annotations

import numpy as np

from egobench.effects.base import Effect
from egobench.effects.readout import staircase_shear
from egobench.residual.calibration import velocity_placebo
from egobench.residual.estimation import GeometricCause, velocity_term, velocity_term_basis


class TimeOffsetCause(GeometricCause):
    """Camera time offset: a shift along the image motion, uniform over rows. theta = [dt_s]."""

    name = "time_offset"

    def regressors(self, data):
        return [velocity_term(data)]

    def velocity_basis(self, data):
        return [velocity_term_basis(data)]

    def nuisance_regressors(self, data):
        """On a trained run, the shear its own staircase of pose samples leaves (`readout.staircase_shear`; one
        sample: the whole readout's): a time offset tested without it took up part of that shear (two readout
        recordings of the independent writer: -0.45 ms)."""
        return staircase_shear(data)

    def displacement(self, theta, ctx, frames, shape):
        return [(1.0, ctx.pixel_velocity_px_s[frames].astype(np.float64) * theta[0])]

    def step_sizes(self, ctx):
        return np.array([2e-4])

    def describe(self, theta, ctx):
        return {"time_offset_error_s": float(theta[0]),
                "sign": "positive: the camera exposed later (device clock) than the model assumes"}


    def trained_placebos(self, result, evidence):
        """On a trained run: the velocity placebo (`egobench.residual.calibration.velocity_placebo`)."""
        record = velocity_placebo(self, result, evidence)
        return [] if record is None else [record]

class TimeOffset(Effect):
    cause_class = TimeOffsetCause  # the diagnosis's estimator (egobench.residual.estimation)
    identifiability = (
        "only with image motion: a shift along the image velocity, zero on still frames")
    trained_magnitudes = (3e-3,)
    error_unit = "s"
    trained_placebo = "velocity_permutation"
    # named from 1 ms: on exploratory runs without an offset the learned one reached 0.26 ms, 3 ms offsets were
    # learned as 2.34-3.02 ms (results/diagnosis/README.md, "2026-12-07: the timing learned with the scene")
    learned_timing = ("time_offset_ms", 1.0)

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"time_offset_s": float(value)}

    def learned_estimate(self, learned_ms, stated_readout_s):
        return {"time_offset_error_s": float(learned_ms) * 1e-3}

    def _parameter_error(self, value, params):
        return abs(params["time_offset_error_s"] - value)

    def synth_row_times(self, t_model, R, value, readout_s):
        return t_model + float(value)

    def smallest_testable(self, d, se, ctx):
        return {"time_offset_error_s": d}


TIME_OFFSET = TimeOffset(
    name="time_offset",
    description="Camera-to-device clock offset (t_device = t_camera + time_offset_s). "
    "Hidden: the calibrated offset is wrong by this many seconds.",
    parameter="time_offset_error_s", unit="s", nominal=0.0,
    plausible_range=(1e-3, 5e-3), sampling="signed",
    signature="A whole-image shift along the image-space velocity, uniform over rows, proportional to "
    "angular speed, and zero on quasi-static frames.",
)
