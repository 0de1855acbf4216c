"""Camera response: the sensor pipeline's true gamma against the assumed 2.2."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.estimation import Cause, CauseResult, ResidualData, binned_means, own_term, photometric_apply


class ResponseCause(Cause):
    """Camera response wrong: log measured-linear is a power of log predicted-linear."""

    name = "response"

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
        if "exposure_slope" in i:  # trained run (egobench.diagnose.placebo): k_f^(a - 1) per frame
            log_k = ctx.log_exposure_gain[np.asarray(frames)]
            log_factor = log_factor + (i["exposure_slope"] * (log_k - i["log_k_mean"]))[:, None, None, None]
        return photometric_apply(predicted, log_factor, ctx.gamma_assumed, power=i["c"], log_p0=i["log_p0"])


class Response(Effect):
    cause_class = ResponseCause  # the diagnosis's estimator (egobench.residual.estimation)
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
