"""White balance: per-channel gains the sensor pipeline applies and a model does not."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.calibration import PlaceboRecord, frame_test
from egobench.residual.estimation import Cause, CauseResult, ResidualData, own_term, photometric_apply


class WhiteBalanceCause(Cause):
    """Per-channel gains: a constant colour cast (tested relative to green)."""

    name = "white_balance"

    def fit(self, data: ResidualData) -> CauseResult:
        fit = data.photometric()
        if not fit.testable:
            return self._untestable("too few usable photometric cells")
        f, p, q = fit.test("white_balance")
        g = fit.coefs("white_balance")
        rel = np.exp([g[0], 0.0, g[1]])
        res = CauseResult(self.name, self.kind, True, statistic=f, statistic_kind=f"F({q}, {fit.dof})", p_value=p,
                          params={"channel_gains_relative_to_green": rel.tolist(),
                                  "channel_gains": (rel * math.exp(fit.log_global)).tolist(),
                                  "global_gain": math.exp(fit.log_global), "note": "global_gain: median frame gain of the joint fit"},
                          internal={"log_gain": np.log(rel), "log_global": fit.own_global("white_balance")})
        res.effect_rms = self._effect(data, self.apply(data.p, own_term(res), data.ctx, data.frames))
        k = fit.keep
        pr = fit.partial_residual("white_balance")[k] - fit.log_global
        means = [float(np.average(pr[fit.cidx[k] == c], weights=fit.w[k][fit.cidx[k] == c])) if np.any(fit.cidx[k] == c) else 0.0
                 for c in range(3)]
        res.plot = {"channel_log_ratio": means, "xlabel": "channel", "ylabel": "log(measured / predicted) - global"}
        return res

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        log = result.internal["log_gain"] + result.internal["log_global"]
        return photometric_apply(predicted, log[None, None, None, :], ctx.gamma_assumed)

    def trained_placebos(self, result, evidence):
        """On a trained run the gains are not testable (`WhiteBalance.trained_run_untestable`); the channel
        gains' test across frames is kept for the record."""
        if not evidence.photometric_fit.testable:
            return []
        est, var = evidence.frame_estimates
        tr, tb = frame_test(est[:, 0], var[:, 0]), frame_test(est[:, 1], var[:, 1])
        p = min(1.0, 2.0 * min(tr.p_value, tb.p_value))
        return [PlaceboRecord(None, {"calibration": {"p_value_placebo": p, "render_blur_px": evidence.blur_px}},
                              untestable=True, reason=WhiteBalance.trained_run_untestable)]


class WhiteBalance(Effect):
    cause_class = WhiteBalanceCause  # the diagnosis's estimator (egobench.residual.estimation)
    trained_placebo = "photometric"
    identifiability = (
        "never on a trained run: a constant per-channel gain is absorbed exactly into the colours the "
        "model learns; only against an independent reference of the scene's colours (a twin, a chart)")
    multiplicative = True
    trained_magnitudes = (0.12,)
    in_trained_sweep = True
    on_adt = True
    trained_run_untestable = ("not identifiable from a trained run: a constant per-channel gain on every frame is "
                              "absorbed exactly into the scene colours the model learns (render = k x shading x colour)")

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"white_balance": tuple(float(x) for x in value)}

    def sweep_value(self, magnitude, rng):
        self.draw_sign(rng)  # unused: keeps the sweep's random streams
        direction = rng.normal(size=3)
        direction /= np.max(np.abs(direction))
        return tuple(float(math.exp(magnitude * d)) for d in direction)

    def trained_value(self, magnitude, rng):  # R and B gains exp(+-magnitude) in opposite directions, G = 1
        sign = self.draw_sign(rng)
        return (math.exp(sign * magnitude), 1.0, math.exp(-sign * magnitude))

    def _parameter_error(self, value, params):
        rel = np.asarray(value) / value[1]
        return float(np.max(np.abs(np.asarray(params["channel_gains_relative_to_green"]) / rel - 1)))

    def synth_photometric(self, truth, value, shape):
        truth.white_balance = np.asarray(value, dtype=np.float64)

    def smallest_testable(self, d, se, ctx):
        return {"channel_gain_relative": math.exp(d) - 1.0}

    def plot_signature(self, ax, plot):
        ax.bar(["R", "G", "B"], plot["channel_log_ratio"], color=["tab:red", "tab:green", "tab:blue"])
        ax.set_ylabel(plot["ylabel"])
        return True


WHITE_BALANCE = WhiteBalance(
    name="white_balance",
    description="Per-channel gains (R, G, B) applied by the sensor pipeline and not modelled.",
    parameter="channel_gains", unit="1", nominal=1.0,
    plausible_range=(0.8, 1.25), sampling="log_uniform", size=3,
    formation_switch="white_balance",
    signature="A constant per-channel ratio between captured and predicted linear values: a colour "
    "cast uniform over the image and all frames.",
)
