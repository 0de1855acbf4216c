"""Lens shading beyond the calibrated vignette: an extra radial falloff toward the corners."""

from __future__ import annotations

import math

import numpy as np
import scipy.stats as sps

from egobench.effects.base import Effect
from egobench.model.formation import radial_vignette
from egobench.residual.calibration import (OWN_P, PLACEBO_CENTRE_OFFSETS, Cells, PlaceboRecord, TrainedRunEvidence,
                                           frame_test, per_frame_photometric, radial_rss, radial_terms)
from egobench.residual.estimation import (Cause, CauseResult, PhotometricFit, ResidualData, binned_means, own_term,
                                          photometric_apply)
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

    def trained_placebos(self, result, evidence):
        """On a trained run: the corner shading tested across frames and against wrong centres
        (`vignette_calibration`), then the model's coverage rule (`coverage_rule`) and the lens's profile
        (`profile_rule`)."""
        if not evidence.photometric_fit.testable:
            return []
        p, info, t, slopes = evidence.memo(_calibration_on)
        record = PlaceboRecord(p, {"p_value_cells": OWN_P,
                                   "calibration": {"p_value_placebo": p, "render_blur_px": evidence.blur_px, **info}})
        coverage_rule(record, result, evidence.data, t)
        profile_rule(record, *slopes)
        return [record]

    def trained_standard_error(self, evidence):
        if not evidence.photometric_fit.testable:
            return None
        t = evidence.memo(_calibration_on)[2]
        return t.se, t.df


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


def coverage_explains(corner_attenuation: float, deficit: float, log_se: float = 0.0, df: int = 0) -> bool:
    """Whether a corner shading estimate says the renders are too dark at the corners (negative) by
    no more than the model's missing opacity there can darken them (over a black background:
    measured / rendered up to 1 / (1 - deficit)), within the estimate's own uncertainty: its log corner
    shading, log(1 - corner_attenuation), does not exceed -log(1 - deficit) by more than the one-sided 95 %
    Student-t quantile on ``df`` degrees of freedom times ``log_se`` (its standard error across frames;
    0: the bound alone). An estimate at the bound is as likely from the coverage as from a lens (measured:
    a hard-sweep null at -0.046 against a deficit's -0.044, named; results/diagnosis/README.md, 2026-12-06)."""
    if not (corner_attenuation < 0.0 and deficit > 0.0):
        return False
    margin = float(sps.t.ppf(0.95, df)) * log_se if log_se > 0 and df > 0 else 0.0
    return math.log1p(-corner_attenuation) <= -math.log1p(-deficit) + margin



# ------------------------------------------------------------------------------------------------
# On a trained run (egobench.residual.calibration)

def vignette_placebo(fit: PhotometricFit, cells: Cells, ctx, height: int, width: int, views: bool = True,
                     frame_estimates: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Corner shading about the principal point: its per-frame estimates tested across frames, and
    the radial fit about the principal point against radial fits about wrong centres (placebos: a
    shading of the lens is centred on the principal point; structured model error is not).
    ``views``: the fits carry the training-view counts where the run has them (`_nuisance`).
    "p": the larger of the frame test's p and, where a wrong centre fits as well, the placebo p.
    ``frame_estimates``: `per_frame_photometric` of these terms, when the caller has them."""
    cx, cy = ctx.principal_point
    r2, r4 = radial_terms(cells, (cx, cy), height, width)
    est, var = per_frame_photometric(fit, cells, r2, r4, views) if frame_estimates is None else frame_estimates
    true = frame_test(est[:, 2], var[:, 2])
    slopes = (frame_test(est[:, 4], var[:, 4]), frame_test(est[:, 5], var[:, 5]))
    rss_true = radial_rss(fit, cells, r2, r4, views)
    rss_placebo = [radial_rss(fit, cells, *radial_terms(cells, (cx + ox * width, cy + oy * height), height, width), views)
                   for ox, oy in PLACEBO_CENTRE_OFFSETS]
    exceed = int(sum(r <= rss_true for r in rss_placebo))
    placebo_p = (1 + exceed) / (1 + len(rss_placebo))
    return {"frame_test": true, "slope_tests": slopes, "rss_true": rss_true, "rss_placebo": rss_placebo,
            "placebo_exceed": exceed, "placebo_p": placebo_p, "p": max(true.p_value, placebo_p if exceed else 0.0),
            "est": est, "var": var}


def vignette_calibration(fit: PhotometricFit, cells: Cells, ctx, height: int, width: int, without: dict):
    """The vignette's calibrated p on a trained run -> (p, info, the frame test behind p, the frame tests of the
    same fit's slopes at the centre and at the corner, `profile_rule`'s); ``without``:
    `vignette_placebo` of the same fit without the counts (computed once by the caller). With
    training-view counts that vary (`PhotometricFit.log_views`), the shading must pass
    `vignette_placebo` both with and without them as a nuisance (p: the larger):
    a radial residual that the counts explain is model under-fit (issue 27: the hard indoor null_s5,
    p 6e-5 without them, 0.007 with), and the extra column, partly collinear with the radius, must
    not make a null's shading significant either (seen once: the hard quest3 null_s0, 0.33 -> 6e-5)."""
    specs = [True, False] if fit.log_views is not None else [False]
    runs = {False: without}
    if fit.log_views is not None:
        runs[True] = vignette_placebo(fit, cells, ctx, height, width, views=True)
    worst = max(specs, key=lambda v: runs[v]["p"])
    t = runs[worst]["frame_test"]
    info = {"frame_t": t.t, "frame_df": t.df, "frame_p": t.p_value,
            "placebo_centre_rss_ratio": [r / runs[worst]["rss_true"] for r in runs[worst]["rss_placebo"]],
            "placebo_exceed": runs[worst]["placebo_exceed"],
            "slope_centre_t": runs[worst]["slope_tests"][0].t, "slope_corner_t": runs[worst]["slope_tests"][1].t}
    if fit.log_views is not None:
        info["p_with_view_counts"], info["p_without_view_counts"] = runs[True]["p"], runs[False]["p"]
    return runs[worst]["p"], info, t, runs[worst]["slope_tests"]



def _calibration_on(evidence: TrainedRunEvidence):
    """`vignette_calibration` of a trained run's evidence -> (p, info, frame test, slope tests)."""
    data, fit, cells = evidence.data, evidence.photometric_fit, evidence.cells
    H, W = data.m.shape[1:3]
    without = vignette_placebo(fit, cells, data.ctx, H, W, views=False, frame_estimates=evidence.frame_estimates)
    return vignette_calibration(fit, cells, data.ctx, H, W, without=without)


def coverage_rule(record: PlaceboRecord, r: CauseResult, data: ResidualData, shading_test=None) -> None:
    """On a trained run, a vignette estimate that says the renders are too dark at the corners, by no
    more than the model's own coverage falls off there within the estimate's uncertainty (`coverage_explains`;
    ``shading_test``: the corner shading's test across frames, whose se and df it reads; None: the bound
    alone), is not testable (``record`` changed in place; the deficit is recorded in its calibration either way)."""
    alpha = data.ctx.render_alpha
    if alpha is None:
        return
    deficit = coverage_corner_deficit(alpha[data.frames], data.ctx.valid, data.ctx.principal_point)
    record.params["calibration"]["coverage_corner_deficit"] = deficit
    corner = float(r.params["corner_attenuation"])
    se, df = (0.0, 0) if shading_test is None else (float(shading_test.se), int(shading_test.df))
    if coverage_explains(corner, deficit, se, df):
        record.untestable, record.reason = True, (
            f"the model's coverage falls off toward the corners (render opacity {100 * deficit:.1f} % lower there "
            f"than at the centre), which darkens its renders there as much as the shading estimate "
            f"({corner:+.3f}) says, within its uncertainty: a vignette cannot be told from it")


def profile_rule(record: PlaceboRecord, centre, corner) -> None:
    """On a trained run, a radial shading that changes direction is not testable as a vignette (``record``
    changed in place). A lens's shading error is monotone in the radius: a lens darker than stated darkens the
    image from the centre to the corner, one lighter than stated brightens it. Log shading a2 r^2 + a4 r^4 has
    the slope a2 in r^2 at the centre and a2 + 2 a4 at the corner; ``centre`` and ``corner`` are their
    `FrameTest`s across frames. Where both differ from zero with opposite signs, each beyond its one-sided 95 %
    Student-t quantile (an intersection-union test at 5 %), the shading is what training left, of a lens it
    absorbed or of its own error, which cannot be told apart (measured: results/diagnosis/README.md,
    2026-12-06, the shading's profile)."""
    if record.untestable or not all(x.se > 0 and x.df > 0 for x in (centre, corner)):
        return
    q = [float(sps.t.ppf(0.95, x.df)) for x in (centre, corner)]
    if (centre.t > q[0] and corner.t < -q[1]) or (centre.t < -q[0] and corner.t > q[1]):
        record.untestable, record.reason = True, (
            f"the residual shading changes direction between the centre and the corner (slope in r^2 "
            f"{centre.mean:+.3f} at the centre, t {centre.t:.1f}; {corner.mean:+.3f} at the corner, t {corner.t:.1f}): "
            "a lens's shading error is monotone in the radius, so this is what training left, of a lens or of its "
            "own error, and the two cannot be told apart")


class Vignette(Effect):
    cause_class = VignetteCause  # the diagnosis's estimator (egobench.residual.estimation)
    trained_placebo = "photometric"
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
        truth.vignette = truth.vignette * radial_vignette(shape, float(value), power=4.0).numpy()

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
