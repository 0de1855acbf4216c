"""Rolling-shutter readout time: the stated readout is off by a relative error."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.estimation import GeometricCause, velocity_term, velocity_term_basis


class ReadoutCause(GeometricCause):
    """Rolling-shutter readout wrong: the time shift grows linearly with row time R(u).

    theta = [a_s, b_s]: time shift a + b (R(u) - 1/2); b is the readout error (tested), a the
    shift of the centre row (0 when the centre-row timestamp is right, b/2 when read start is).
    """

    name = "readout"
    n_params = 2
    tested_index = 1
    nests = ("time_offset",)  # a + b (R - 1/2) contains the pure shift a: see core.diagnose_residuals

    def regressors(self, data):
        x = velocity_term(data)
        return [x, x * (data.ctx.row_time_ratio - 0.5)[None, :, :, None]]

    def velocity_basis(self, data):
        return [velocity_term_basis(data), velocity_term_basis(data, (data.ctx.row_time_ratio - 0.5)[None, :, :, None])]

    def displacement(self, theta, ctx, frames, shape):
        dt = theta[0] + theta[1] * (ctx.row_time_ratio - 0.5)
        return [(1.0, ctx.pixel_velocity_px_s[frames].astype(np.float64) * dt[None, :, :, None])]

    def step_sizes(self, ctx):
        return np.array([2e-4, 4e-4])

    def describe(self, theta, ctx):
        rel = float(theta[1] / ctx.readout_s) if ctx.readout_s > 0 else None
        return {"readout_error_s": float(theta[1]), "readout_relative_error": rel,
                "readout_s_estimated": float(ctx.readout_s + theta[1]), "centre_row_shift_s": float(theta[0])}

    def plot_data(self, data, est, info, theta):
        out = super().plot_data(data, est, info, theta)
        # time shift per row band: regress the residual on the velocity term within bands of R(u)
        x = velocity_term(data)
        R = np.broadcast_to(data.ctx.row_time_ratio[None, :, :, None], x.shape)
        m = data.usable
        edges = np.linspace(0, 1, 9)
        band = np.clip(np.searchsorted(edges, R[m], side="right") - 1, 0, 7)
        xm, rm = x[m], data.r[m]
        num = np.bincount(band, weights=xm * rm, minlength=8)
        den = np.bincount(band, weights=xm * xm, minlength=8)
        out["row_time_ratio"] = ((edges[:-1] + edges[1:]) / 2).tolist()
        out["time_shift_s"] = (num / np.maximum(den, 1e-300)).tolist()
        out["fit_a_b"] = [float(theta[0]), float(theta[1])]
        return out


class Readout(Effect):
    cause_class = ReadoutCause  # the diagnosis's estimator (egobench.residual.estimation)
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
