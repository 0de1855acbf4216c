"""Sensor noise stronger or weaker than the device profile says."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.estimation import Cause, CauseResult, ResidualData, binned_means
from egobench.residual.signatures import DiagnosisContext, box3, decode, encode_slope, frame_t_test


def _factor_by_signal(signal: np.ndarray, observed: np.ndarray, expected: np.ndarray) -> list[float]:
    """Noise std factor sqrt(sum observed / sum expected) in the lower and upper half of the
    predicted signal [n] (observed, expected: [n] variances). A wrong noise scale (shot and
    read noise times f) gives the same factor in both halves; excess variance from model error
    (a trained reconstruction's residual) generally does not follow the noise model's level
    dependence (core requires the factor beyond the floor at every level)."""
    cut = float(np.median(signal))
    out = []
    for sel in (signal <= cut, signal > cut):
        den = float(np.sum(expected[sel]))
        out.append(math.sqrt(max(float(np.sum(observed[sel])) / den, 1e-4)) if den > 0 and sel.any() else 1.0)
    return out


class NoiseCause(Cause):
    """Noise model wrong: high-passed residual variance in flat regions versus the assumed model.

    Parameter: noise_std_factor f (measured variance = f^2 x assumed, both shot and read parts);
    with an assumed noiseless model, the affine fit var_linear = shot x signal + read instead.
    """

    name = "noise"
    kind = "noise"
    mean_affecting = False

    def fit(self, data: ResidualData) -> CauseResult:
        ctx = data.ctx
        gx, gy = data.grad
        gmag = np.hypot(gx, gy)
        # flat pixels whose whole 3x3 neighbourhood is usable
        full = (box3(data.usable_all.astype(np.float64)) > 0.999) & data.usable
        flat_thr = np.quantile(gmag[data.usable], 0.5) if data.usable.any() else 0.0
        m = full & (gmag <= flat_thr)
        if m.sum() < 200:
            return self._untestable("too few flat usable pixels")
        hp = (data.r - box3(data.r))[m]
        obs = hp**2 * 9.0 / 8.0  # E = pixel variance for locally constant variance
        slope2 = encode_slope(data.p_lin, ctx.gamma_assumed)[m] ** 2
        q_var = ctx.quantisation_level**2 / 12.0
        frames_px = np.broadcast_to(np.arange(data.m.shape[0])[:, None, None, None], m.shape)[m]
        signal = data.p_lin[m]
        model_lin = ctx.noise_var_linear(data.p_lin, data.frames)[m]
        res = CauseResult(self.name, self.kind, True)
        if ctx.noise_reference is not None and ctx.noise_shot is not None:
            # empirical reference: the assumed noise drawn through the same pipeline, same pixels
            ref = ctx.noise_reference[data.frames]
            ref_obs = (ref - box3(ref))[m] ** 2 * 9.0 / 8.0
            num = np.bincount(frames_px, weights=obs, minlength=data.m.shape[0])
            den = np.bincount(frames_px, weights=ref_obs, minlength=data.m.shape[0])
            cnt = np.bincount(frames_px, minlength=data.m.shape[0])
            okf = (cnt > 50) & (den > 0)
            test = frame_t_test(np.log(np.clip(num[okf] / den[okf], 1e-3, None)), cnt[okf].astype(float))
            f2 = float(np.clip(obs.sum() / max(ref_obs.sum(), 1e-300), 1e-4, None))
            transfer = float(ref_obs.sum() / max(np.sum(slope2 * model_lin + q_var), 1e-300))
            res.statistic, res.statistic_kind, res.p_value = test.t, f"t({test.df})", test.p_value
            res.params = {"noise_std_factor": math.sqrt(f2), "pipeline_variance_transfer": transfer,
                          "noise_std_factor_by_signal": _factor_by_signal(signal, obs, ref_obs)}
            res.internal = {"var_factor": f2, "transfer": transfer}
            std_now = np.sqrt(ref_obs.mean() * np.ones_like(obs))
            std_new = std_now * math.sqrt(f2)
        elif ctx.noise_shot is not None and np.any(model_lin > 0):
            expected = slope2 * model_lin + q_var
            # per-frame variance ratio (frames are the units), tested against 1 on the log scale
            num = np.bincount(frames_px, weights=obs - q_var, minlength=data.m.shape[0])
            den = np.bincount(frames_px, weights=slope2 * model_lin, minlength=data.m.shape[0])
            cnt = np.bincount(frames_px, minlength=data.m.shape[0])
            okf = (cnt > 50) & (den > 0)
            ratio = np.clip(num[okf] / den[okf], 1e-3, None)
            test = frame_t_test(np.log(ratio), cnt[okf].astype(float))
            f2 = float(np.clip(np.sum(obs - q_var) / np.sum(slope2 * model_lin), 1e-4, None))
            res.statistic, res.statistic_kind, res.p_value = test.t, f"t({test.df})", test.p_value
            res.params = {"noise_std_factor": math.sqrt(f2),
                          "noise_std_factor_by_signal": _factor_by_signal(signal, obs - q_var, slope2 * model_lin)}
            res.internal = {"var_factor": f2}
            std_now = np.sqrt(expected)
            std_new = np.sqrt(slope2 * model_lin * f2 + q_var)
        else:
            # assumed noiseless: fit var_linear = a signal + b; test the mean ratio to quantisation-only
            A = np.stack([slope2 * signal, slope2], axis=1)
            coef, *_ = np.linalg.lstsq(A, obs - q_var, rcond=None)
            coef = np.clip(coef, 0.0, None)
            num = np.bincount(frames_px, weights=obs, minlength=data.m.shape[0])
            cnt = np.bincount(frames_px, minlength=data.m.shape[0])
            okf = cnt > 50
            test = frame_t_test(np.log(np.clip(num[okf] / cnt[okf] / q_var, 1e-3, None)), cnt[okf].astype(float))
            res.statistic, res.statistic_kind, res.p_value = test.t, f"t({test.df})", test.p_value
            gain = float(np.median(ctx.gain))
            a, b = float(coef[0]), float(coef[1])
            full_well = gain / a if a > 0 else None
            res.params = {"shot_var_per_signal": a, "read_var": b, "full_well_e_at_gain_1": full_well,
                          "read_noise_e": (math.sqrt(b) * full_well / gain) if (full_well and b > 0) else 0.0,
                          "median_gain": gain}
            res.internal = {"shot": a, "read": b}
            std_now = np.sqrt(np.full_like(obs, q_var))
            std_new = np.sqrt(slope2 * (a * signal + b) + q_var)
        res.effect_rms = float(np.sqrt(np.mean((std_new - std_now) ** 2)))
        bins = binned_means(signal, obs, np.ones_like(obs), bins=10)
        bins_exp = binned_means(signal, std_now**2, np.ones_like(obs), bins=10)
        bins_new = binned_means(signal, std_new**2, np.ones_like(obs), bins=10)
        res.plot = {"signal": bins["x"], "observed_var": bins["y"], "assumed_var": bins_exp["y"],
                    "fitted_var": bins_new["y"], "xlabel": "predicted linear signal",
                    "ylabel": "residual variance (display units^2)"}
        return res

    def variance(self, predicted: np.ndarray, result: CauseResult | None, ctx: DiagnosisContext,
                 frames: np.ndarray) -> np.ndarray:
        """Per-pixel display-domain variance [f, H, W, 3] under the assumed (result None) or fitted noise."""
        lin = decode(predicted, ctx.gamma_assumed)
        slope2 = encode_slope(lin, ctx.gamma_assumed) ** 2
        q = ctx.quantisation_level**2 / 12.0
        if result is None:
            return slope2 * ctx.noise_var_linear(lin, frames) + q
        if "transfer" in result.internal:
            return (slope2 * ctx.noise_var_linear(lin, frames) + q) * result.internal["transfer"] * result.internal["var_factor"]
        if "var_factor" in result.internal:
            return slope2 * ctx.noise_var_linear(lin, frames) * result.internal["var_factor"] + q
        return slope2 * (result.internal["shot"] * np.clip(lin, 0, None) + result.internal["read"]) + q

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        return predicted  # the mean prediction is unchanged


class Noise(Effect):
    cause_class = NoiseCause  # the diagnosis's estimator (egobench.residual.estimation)
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
        truth.noise = truth.noise.scaled(float(value))

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
