"""Camera response: the sensor pipeline's true gamma against the assumed 2.2."""

from __future__ import annotations

import math

import numpy as np
import scipy.stats as sps

from egobench.effects.base import Effect
from egobench.effects.exposure_metadata import GLITCH_FOLLOW, metadata_split_half
from egobench.residual.calibration import OWN_P, PlaceboRecord, TrainedRunEvidence, frame_test
from egobench.residual.estimation import (Cause, CauseResult, PhotometricFit, ResidualData, binned_means, own_term,
                                          photometric_apply)
from egobench.residual.signatures import radial_coordinates


#: Smallest spread (std of log exposure x gain across frames) for the trained-run response test.
MIN_LOG_EXPOSURE_SPREAD = 0.05
#: A stated vignette whose log shading at the farthest corner lies above -this is flat (`ResponseCause.mimicry`).
FLAT_STATED_LOG_SHADING = 0.01


def stated_corner_log_shading(vignette: np.ndarray, valid: np.ndarray, centre: tuple[float, float]) -> float:
    """The stated vignette's log shading at the farthest corner, from a least-squares b2 r^2 + b4 r^4 over the valid
    pixels (r: radius over the farthest corner's, the basis of the vignette cause's corner attenuation)."""
    H, W = vignette.shape
    _, _, r = radial_coordinates(H, W, centre)
    m = valid & (vignette > 0)
    x = np.stack([r[m] ** 2, r[m] ** 4], axis=-1)
    b, *_ = np.linalg.lstsq(x, np.log(vignette[m]), rcond=None)
    return float(b[0] + b[1])


class ResponseCause(Cause):
    """Camera response wrong: log measured-linear is a power of log predicted-linear."""

    name = "response"
    mimics = ("vignette",)

    def mimicry(self, data, params):
        """At a fixed exposure a trained run's colours absorb a wrong response everywhere but where the stated
        vignette v darkens the image: there its residual is a radial log shading c log v(r), c = gamma_assumed /
        gamma - 1, which only exposure changes tell from a lens shading. Says so when the frames' exposure x gain
        spread is below the response test's (`MIN_LOG_EXPOSURE_SPREAD`) and the gamma that gives the named corner
        shading lies in the effect's plausible range (a flat stated vignette gives none)."""
        ctx = data.ctx
        spread = float(np.std(ctx.log_exposure_gain[data.frames]))
        if spread >= MIN_LOG_EXPOSURE_SPREAD or ctx.stated_vignette is None or "corner_attenuation" not in params:
            return None
        log_v = stated_corner_log_shading(ctx.stated_vignette, ctx.valid, ctx.principal_point)
        if not log_v < -FLAT_STATED_LOG_SHADING:
            return None
        c = math.log1p(-float(params["corner_attenuation"])) / log_v
        gamma = ctx.gamma_assumed / (1.0 + c) if 1.0 + c > 0.0 else math.inf
        lo, hi = RESPONSE.plausible_range
        if not lo <= gamma <= hi:
            return None
        return (f"at a fixed exposure (exposure x gain varies by {spread:.3f}, std of log) a camera response of gamma "
                f"{gamma:.2f} darkens the stated vignette (corner {math.exp(log_v):.2f}) by as much")

    def fit(self, data: ResidualData) -> CauseResult:
        fit = data.photometric()
        if not fit.testable:
            return self._untestable("too few usable photometric cells")
        f, p, q = fit.test("response")
        c = float(fit.coefs("response")[0])
        gamma_true = data.ctx.gamma_assumed / (1.0 + c) if 1.0 + c > 0.05 else float("inf")
        res = CauseResult(self.name, self.kind, True, statistic=f, statistic_kind=f"F({q}, {fit.dof})", p_value=p,
                          params={"gamma": gamma_true, "gamma_assumed": data.ctx.gamma_assumed,
                                  "log_log_slope_minus_1": c, "global_gain": math.exp(fit.log_global), "note": "global_gain: median frame gain of the joint fit"},
                          internal={"c": c, "log_p0": fit.log_p0, "log_global": fit.own_global("response")})
        if not math.isfinite(gamma_true):
            res.params["gamma"] = None
            res.reason = "log-log slope <= 0.05: not a gamma curve"
        res.effect_rms = self._effect(data, self.apply(data.p, own_term(res), data.ctx, data.frames))
        k = fit.keep
        res.plot = {"binned": binned_means(fit.log_p[k], fit.partial_residual("response")[k] - fit.log_global, fit.w[k]),
                    "slope": c, "x0": fit.log_p0,
                    "xlabel": "log predicted linear intensity", "ylabel": "log(measured / predicted), linear"}
        return res

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        i = result.internal
        log_factor = np.full((1, 1, 1, 1), i["log_global"])
        if "exposure_slope" in i:  # trained run (`response_from_exposure`): k_f^(a - 1) per frame
            log_k = ctx.log_exposure_gain[np.asarray(frames)]
            log_factor = log_factor + (i["exposure_slope"] * (log_k - i["log_k_mean"]))[:, None, None, None]
        return photometric_apply(predicted, log_factor, ctx.gamma_assumed, power=i["c"], log_p0=i["log_p0"])

    def trained_placebos(self, result, evidence):
        """On a trained run the within-image slope is absorbed by training: the response is tested by how the
        frames' scale follows the recorded exposure x gain (`response_from_exposure`), which also becomes its
        estimate and extension (this result changed in place)."""
        if not evidence.photometric_fit.testable:
            return []
        resp = evidence.memo(_response_test)
        est, var = evidence.frame_estimates
        tc = frame_test(est[:, 3], var[:, 3])
        info = {"frame_t": tc.t, "frame_df": tc.df, **{k: v for k, v in resp.items() if k != "testable"}}
        p = resp["p"] if resp["testable"] else 1.0  # within-image slope: absorbed by training
        if resp["testable"]:
            _response_from_exposure_apply(self, result, resp, evidence.data)
        calibration = {"p_value_placebo": p, "render_blur_px": evidence.blur_px, **info}
        return [PlaceboRecord(p, {"p_value_cells": OWN_P, "calibration": calibration},
                              reason=None if resp["testable"] else resp["reason"])]

    def trained_standard_error(self, evidence):
        if not evidence.photometric_fit.testable:
            return None
        resp = evidence.memo(_response_test)
        return resp.get("slope_sd_placebo", math.nan), max(evidence.photometric_fit.n_frames - 2, 2)

# ------------------------------------------------------------------------------------------------
# On a trained run (egobench.residual.calibration)


def response_from_exposure(fit: PhotometricFit, data: ResidualData, draws: int, rng: np.random.Generator,
                           exclude: list[int] | None = None) -> dict:
    """A response error on a TRAINED run: the model's colours absorb L^a (a = gamma_assumed /
    gamma_true), so what survives is a per-frame scale k_f^(a - 1) that follows the recorded
    exposure x gain k_f. Statistic: slope of the frames' log scales on log k_f; p: the larger of the
    permutation p (exposure metadata permuted across frames) and the circular-shift p
    (`exposure_shift_placebo`: exposure and model error both follow the view). ``exclude``: positions
    among the fitted frames left out (the frames the metadata test flags: their recorded exposure is
    what is in doubt, so it cannot carry a response test; at a fixed true exposure a wrong metadata
    is all the spread there is)."""
    k = data.ctx.log_exposure_gain
    use = np.ones(fit.n_frames, bool)
    use[list(exclude or [])] = False
    k_used = k[data.frames][use]
    x = k_used - float(np.mean(k_used))
    # per-frame log scale: weighted mean of the cell log ratios (no log-intensity column: in an
    # untrained prediction the response error also shows within the image, which that column
    # would take from the frames)
    keep = fit.keep
    w = np.bincount(fit.fidx[keep], weights=fit.w[keep], minlength=fit.n_frames)
    beta = (np.bincount(fit.fidx[keep], weights=(fit.w * fit.y)[keep], minlength=fit.n_frames)
            / np.maximum(w, 1e-300))[use]
    if float(np.std(x)) < MIN_LOG_EXPOSURE_SPREAD:
        where = " the frames the metadata test does not flag" if not use.all() else " frames"
        return {"testable": False, "p": 1.0, "log_exposure_spread": float(np.std(x)), "frames_left_out": int((~use).sum()),
                "reason": (f"exposure x gain varies by {float(np.std(x)):.3f} (std of log) < {MIN_LOG_EXPOSURE_SPREAD} "
                           f"across{where}: a response error is absorbed into the scene colours of a trained run")}
    b = beta - float(np.mean(beta))

    def slope(xx):
        return float(np.sum(xx * b) / np.sum(xx * xx))

    observed = slope(x)
    placebo = np.array([slope(rng.permutation(x)) for _ in range(int(draws))])
    p_perm = float((1 + np.sum(np.abs(placebo) >= abs(observed))) / (1 + draws))
    shifts = exposure_shift_placebo(x, b)
    out = {"testable": True, "p": max(p_perm, shifts["p"]), "p_permuted": p_perm, "exposure_slope": observed,
           "frames_left_out": int((~use).sum()),
           "slope_sd_placebo": max(float(placebo.std()), shifts["slope_sd"]), "slope_sd_permuted": float(placebo.std()),
           "shift_placebo": shifts, "log_k_mean": float(np.mean(k[data.frames])), "log_exposure_spread": float(np.std(x))}
    if observed < -GLITCH_FOLLOW:
        out.update(testable=False, p=1.0, reason=(
            f"the frames' scale follows the recorded exposure x gain with slope {observed:+.2f}: no camera response "
            f"does that (slope a - 1 > -{GLITCH_FOLLOW} for true gammas below {1 / (1 - GLITCH_FOLLOW):.0f}x the "
            "assumed one); a record off on some frames gives -1 (exposure metadata)"))
    elif shifts["n_lags"] < SHIFT_MIN_PLACEBOS:
        out.update(testable=False, p=1.0, reason=(
            f"exposure x gain follows the view too slowly: {shifts['n_lags']} circular shifts of it are "
            f"uncorrelated with it (< {SHIFT_MIN_PLACEBOS}), so a view-following model error cannot be told "
            "from a response error"))
    return out



#: Circular shifts of the exposure series used as placebos: at least this far from no shift (in fitted
#: frames), and correlated with the unshifted series by less than SHIFT_MAX_CORR; fewer than
#: SHIFT_MIN_PLACEBOS such shifts: the response is not testable on the run.
SHIFT_MIN_LAG, SHIFT_MAX_CORR, SHIFT_MIN_PLACEBOS = 2, 0.3, 8
#: Autocorrelation lags of Bartlett's variance inflation 1 + 2 sum_j rho_x(j) rho_b(j), which divides the
#: shifts into effectively independent placebos (Bretherton et al. 1999, J. Climate 12). Measured on independent
#: AR(1) pairs (rho 0-0.95, 42 frames, 300 draws each): false alarms 0.3-1 % at p < 0.01, 5-8 % at p < 0.05
#: (permutations: up to 30 % at p < 0.01; a normal tail of the shifts: 3-5 % and 8-15 %).
SHIFT_ACF_LAGS = 5


def exposure_shift_placebo(x: np.ndarray, b: np.ndarray) -> dict:
    """The slope of the frames' log scales ``b`` [F] on log exposure x gain ``x`` [F] (both centred,
    in time order) against the slopes on ``x`` circularly shifted (issue 27). Exposure follows the
    view, and so does a trained model's error: independent smooth series correlate far more often
    than permutations (which break the smoothness) allow. A shift keeps both series' smoothness; only
    shifts nearly uncorrelated with ``x`` are used, so a true response does not leak into them.
    -> {p: Student-t tail of |slope| over the placebos' rms slope (degrees of freedom: the shifts over
    Bartlett's inflation), slope_sd, df, n_lags, lags}."""
    F = x.size
    xx = float(np.sum(x * x))
    lags = [k for k in range(1, F) if min(k, F - k) >= SHIFT_MIN_LAG
            and abs(float(np.sum(x * np.roll(x, k)))) < SHIFT_MAX_CORR * xx]
    slopes = np.array([float(np.sum(np.roll(x, k) * b)) / xx for k in lags])
    sd = float(np.sqrt(np.mean(slopes ** 2))) if slopes.size else math.inf
    observed = float(np.sum(x * b)) / xx

    def acf(v: np.ndarray, j: int) -> float:
        return float(np.sum(v * np.roll(v, j)) / max(float(np.sum(v * v)), 1e-300))

    inflation = 1.0 + 2.0 * sum(max(acf(x, j) * acf(b, j), 0.0) for j in range(1, SHIFT_ACF_LAGS + 1))
    df = max(len(lags) / inflation, 1.0)
    p = float(2.0 * sps.t.sf(abs(observed) / sd, df)) if sd > 0.0 else float(observed == 0.0)
    return {"p": p, "slope_sd": sd, "df": df, "n_lags": len(lags), "lags": lags}


def _response_from_exposure_apply(cause: ResponseCause, r: CauseResult, resp: dict, data: ResidualData) -> None:
    """Make the response cause's estimate and extension the exposure-driven one (in place)."""
    s = resp["exposure_slope"]
    g = data.ctx.gamma_assumed
    r.params["gamma_cells"] = r.params.get("gamma")
    r.params["gamma"] = g / (1.0 + s) if 1.0 + s > 0.05 else None
    r.params["signature"] = "trained run: per-frame scale following log(exposure x gain)"
    r.internal = {"c": 0.0, "log_p0": 0.0, "log_global": 0.0, "exposure_slope": s, "log_k_mean": resp["log_k_mean"]}
    new = cause.apply(data.p, r, data.ctx, data.frames)
    m = data.usable
    r.effect_rms = float(np.sqrt(np.mean((new - data.p)[m] ** 2))) if m.any() else 0.0



def _response_test(evidence: TrainedRunEvidence) -> dict:
    """`response_from_exposure` on a trained run, leaving out the frames the exposure-metadata test flags."""
    split = evidence.memo(metadata_split_half)
    return response_from_exposure(evidence.photometric_fit, evidence.data, evidence.draws, evidence.rng(22),
                                  exclude=split.get("frames_flagged_in_both_halves"))


class Response(Effect):
    cause_class = ResponseCause  # the diagnosis's estimator (egobench.residual.estimation)
    trained_placebo = "photometric"
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
        truth.gamma = float(value)

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
