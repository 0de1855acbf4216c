"""Lens shading beyond the calibrated vignette: an extra radial falloff toward the corners."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.model.formation import radial_vignette
from egobench.residual.estimation import Cause, CauseResult, ResidualData, binned_means, own_term, photometric_apply
from egobench.residual.signatures import radial_coordinates


class VignetteCause(Cause):
    """Unmodelled lens shading: radial, multiplicative, the same in every frame."""

    name = "vignette"

    def fit(self, data: ResidualData) -> CauseResult:
        fit = data.photometric()
        if not fit.testable:
            return self._untestable("too few usable photometric cells")
        f, p, q = fit.test("vignette")
        a = fit.coefs("vignette")
        corner = 1.0 - math.exp(float(a[0] + a[1]))
        res = CauseResult(self.name, self.kind, True, statistic=f, statistic_kind=f"F({q}, {fit.dof})", p_value=p,
                          params={"corner_attenuation": corner, "log_shading_r2_r4": a.tolist(),
                                  "global_gain": math.exp(fit.log_global), "note": "global_gain: median frame gain of the joint fit"},
                          internal={"a": a, "log_global": fit.own_global("vignette")})
        res.effect_rms = self._effect(data, self.apply(data.p, own_term(res), data.ctx, data.frames))
        pr = fit.partial_residual("vignette")
        k = fit.keep
        rr = np.sqrt(fit.r2[k])
        res.plot = {"binned": binned_means(rr, pr[k] - fit.log_global, fit.w[k]),
                    "curve_r": np.linspace(0, 1, 21).tolist(),
                    "curve": (a[0] * np.linspace(0, 1, 21) ** 2 + a[1] * np.linspace(0, 1, 21) ** 4).tolist(),
                    "xlabel": "radius / corner radius", "ylabel": "log(measured / predicted), linear"}
        return res

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        H, W = predicted.shape[1:3]
        _, _, r = radial_coordinates(H, W, ctx.principal_point)
        a = result.internal["a"]
        log_v = a[0] * r**2 + a[1] * r**4
        return photometric_apply(predicted, result.internal["log_global"] + log_v[None, :, :, None], ctx.gamma_assumed)


def coverage_corner_deficit(render_alpha: np.ndarray, valid: np.ndarray, principal_point: tuple[float, float]) -> float:
    """1 - a trained model's opacity at the farthest corner over its opacity at the principal point:
    log of the frames' mean opacity (``render_alpha`` [F, H, W], ``valid`` [H, W] pixels) fitted with
    the vignette's own radial terms (r^2, r^4; r = 1 at the corner). A model that covers the image's
    periphery less (content there is seen in fewer views) renders it darker, which the vignette test
    reads as corners brighter than modelled: a negative corner attenuation (issue 27)."""
    H, W = valid.shape
    _, _, r = radial_coordinates(H, W, principal_point)
    mean = render_alpha.mean(axis=0)
    m = valid & (mean > 0.05)
    if m.sum() < 8:
        return 0.0
    A = np.stack([np.ones(int(m.sum())), r[m] ** 2, r[m] ** 4], axis=1)
    coef = np.linalg.lstsq(A, np.log(mean[m]), rcond=None)[0]
    return float(1.0 - math.exp(coef[1] + coef[2]))


def coverage_explains(corner_attenuation: float, deficit: float) -> bool:
    """Whether a corner shading estimate says the renders are too dark at the corners (negative) by
    no more than the model's missing opacity there can darken them (over a black background:
    measured / rendered up to 1 / (1 - deficit)): then a vignette cannot be told from it."""
    return corner_attenuation < 0.0 and deficit > 0.0 and -corner_attenuation <= deficit / (1.0 - deficit)


class Vignette(Effect):
    cause_class = VignetteCause  # the diagnosis's estimator (egobench.residual.estimation)
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
