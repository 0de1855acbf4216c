"""Lens distortion: the true Fisheye624 k0 differs from the calibration used for rectification."""

from __future__ import annotations

import copy
from dataclasses import replace as dc_replace

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.calibration import PLACEBO_CENTRE_OFFSETS, PlaceboRecord, beat_placebos
from egobench.residual.estimation import GeometricCause, ResidualData, velocity_term
from egobench.residual.signatures import distortion_profile, frame_t_test, radial_coordinates


class DistortionCause(GeometricCause):
    """Lens distortion wrong: a static radial displacement, k0 error of the rectifying calibration. theta = [dk0]."""

    name = "distortion"
    needs_velocity = False

    def _profile(self, ctx, H, W):
        radius, direction, _ = radial_coordinates(H, W, ctx.principal_point)
        g = distortion_profile(radius, ctx.focal_px, ctx.lens_radial_k)
        return g[..., None] * direction  # [H, W, 2] displacement per unit dk0

    def regressors(self, data):
        H, W = data.p.shape[1:3]
        d = self._profile(data.ctx, H, W)
        gx, gy = data.grad
        return [-(gx * d[None, :, :, 0:1] + gy * d[None, :, :, 1:2])]

    def nuisance_regressors(self, data):
        """The image motion's shift signature (the time offset's), where the frames move: a lens displaces every
        frame alike, while a radial pattern that follows each frame's motion (walking forward: the flow
        expands about a point near the principal point) is timing or the model's own error, not a lens."""
        return [] if data.velocity is None else [velocity_term(data)]

    def displacement(self, theta, ctx, frames, shape):
        d = self._profile(ctx, shape[1], shape[2])
        return [(1.0, np.broadcast_to(d[None] * theta[0], (shape[0], shape[1], shape[2], 2)))]

    def step_sizes(self, ctx):
        return np.array([1e-3])

    def describe(self, theta, ctx):
        return {"k0_error": float(theta[0])}

    def plot_data(self, data, est, info, theta):
        out = super().plot_data(data, est, info, theta)
        H, W = data.p.shape[1:3]
        radius, _, _ = radial_coordinates(H, W, data.ctx.principal_point)
        x = self.regressors(data)[0]
        rr = np.broadcast_to(radius[None, :, :, None], x.shape)
        g = np.broadcast_to(distortion_profile(radius, data.ctx.focal_px, data.ctx.lens_radial_k)[None, :, :, None], x.shape)
        m = data.usable & (g > 1e-6)
        # displacement per radial band: slope of residual on the unit-displacement regressor, times the profile
        edges = np.quantile(rr[m], np.linspace(0, 1, 9))
        band = np.clip(np.searchsorted(edges, rr[m], side="right") - 1, 0, 7)
        xm, rm = x[m], data.r[m]
        num = np.bincount(band, weights=xm * rm, minlength=8)
        den = np.bincount(band, weights=xm * xm, minlength=8)
        gm = np.bincount(band, weights=g[m], minlength=8) / np.maximum(np.bincount(band, minlength=8), 1)
        out["radius_px"] = ((edges[:-1] + edges[1:]) / 2).tolist()
        out["displacement_px"] = (num / np.maximum(den, 1e-300) * gm).tolist()
        out["fit_displacement_px"] = (theta[0] * gm).tolist()
        return out


    def trained_placebos(self, result, evidence):
        """On a trained run: the radial statistic about wrong centres (`distortion_placebo`)."""
        return [distortion_placebo(self, evidence.data)] if result.testable else []


def distortion_placebo(cause: DistortionCause, data: ResidualData) -> PlaceboRecord:
    """Lens distortion on a trained run must beat radial placebos: the same per-frame
    radial-displacement statistic about wrong centres (PLACEBO_CENTRE_OFFSETS). p_placebo = the
    larger of the rank p (1 + exceed) / 9 when a placebo is as strong, and the Student-t tail of |t| (`beat_placebos`)
    against the placebos' |t| (model error near the image border, where the model has less
    coverage, is radial about any centre and inflates them all)."""
    H, W = data.m.shape[1:3]

    def t_of(d):
        est, info = cause.first_order(d)
        return frame_t_test(est[:, 0], info[:, 0]).t

    t_real = t_of(data)
    cx, cy = data.ctx.principal_point
    t_placebo = []
    for ox, oy in PLACEBO_CENTRE_OFFSETS:
        d = copy.copy(data)
        d.ctx = dc_replace(data.ctx, principal_point=(cx + ox * W, cy + oy * H))
        t_placebo.append(t_of(d))
    p, exceed, p_tail = beat_placebos(t_real, t_placebo)
    return PlaceboRecord(p, {"calibration": {"p_value_placebo": p, "first_order_t": t_real, "placebo_centre_t": t_placebo,
                                             "placebo_exceed": exceed, "p_tail": p_tail}})


class Distortion(Effect):
    cause_class = DistortionCause  # the diagnosis's estimator (egobench.residual.estimation)
    identifiability = (
        "only when points reach the outer image in some views and the centre in others (a static radial "
        "displacement)")
    trained_magnitudes = (0.008,)
    trained_placebo = "radial_centres"

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"distortion_k0_delta": float(value)}

    def _parameter_error(self, value, params):
        return abs(params["k0_error"] / value - 1.0)

    def synth_displacement(self, value, radial_field):
        return radial_field(float(value))

    def smallest_testable(self, d, se, ctx):
        return {"k0_error": d}

    def plot_signature(self, ax, plot):
        if "radius_px" not in plot:
            return False
        ax.plot(plot["radius_px"], plot["displacement_px"], "o", label="per radial band")
        ax.plot(plot["radius_px"], plot["fit_displacement_px"], "-", label="fit")
        ax.set_xlabel("radius (px)"), ax.set_ylabel("radial displacement (px)"), ax.legend(fontsize=7)
        return True


DISTORTION = Distortion(
    name="distortion",
    description="Fisheye624 radial coefficient k0 of the true lens differs from the calibration "
    "used for rectification (absolute change of k0).",
    parameter="k0_error", unit="1", nominal=0.0,
    plausible_range=(0.002, 0.01), sampling="signed",
    signature="A static radial displacement growing with field angle (zero at the centre), identical in "
    "every frame, so edges near the image border are doubled or misplaced across views.",
)
