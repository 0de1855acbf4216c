"""Exposure metadata wrong on some frames: the recorded exposure is the true one times (1 + e)."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.estimation import (DISPLAY_MAX, DISPLAY_MIN, Cause, CauseResult, ResidualData, own_term,
                                          photometric_apply)
from egobench.residual.signatures import decode

#: A frame of a trained run is flagged when both halves of it deviate beyond this many robust standard
#: deviations of the model's frame-to-frame error, and beyond FLAG_MIN_LOG. The floor is the largest
#: single-frame scale that model error alone gave on the trained sweeps' cases without a metadata error
#: (outdoor, 64 px, 800 iterations: 14 % on one frame of one null, all others <= 11 %; docs/diagnosis.md):
#: single frames of a trained model can render that much too dark or bright.
FLAG_SIGMAS, FLAG_MIN_LOG = 4.0, math.log(1.15)


class ExposureMetadataCause(Cause):
    """Per-frame exposure/gain metadata error: a global per-frame scale."""

    name = "exposure_metadata"

    def fit(self, data: ResidualData) -> CauseResult:
        fit = data.photometric()
        if not fit.testable:
            return self._untestable("too few usable photometric cells")
        f, p, q = fit.test("frame")
        beta = fit.coefs("frame")
        dev = beta - fit.log_global
        spread = 1.4826 * float(np.median(np.abs(dev))) + 1e-12
        flagged = np.flatnonzero((np.abs(dev) > max(4.0 * spread, 0.03)))
        scale = np.exp(dev)
        errors = (1.0 / scale[flagged] - 1.0).tolist()  # recorded = true x (1 + e): measured / predicted = 1 / (1 + e)
        res = CauseResult(self.name, self.kind, True, statistic=f, statistic_kind=f"F({q}, {fit.dof})", p_value=p,
                          params={"frame_scale": {int(data.ctx.frame_index[fr]): float(s) for fr, s in zip(data.frames, scale)},
                                  "flagged_frames": [int(data.ctx.frame_index[data.frames[i]]) for i in flagged],
                                  "exposure_relative_error": errors,
                                  "median_exposure_relative_error": float(np.median(errors)) if errors else 0.0,
                                  "global_gain": math.exp(fit.log_global), "note": "global_gain: median frame gain of the joint fit"},
                          internal={"log_scale": dict(zip(data.frames.tolist(), dev.tolist())),
                                    "log_global": fit.own_global("frame")})
        res.effect_rms = self._effect(data, self.apply(data.p, own_term(res), data.ctx, data.frames))
        res.plot = {"frame": [int(data.ctx.frame_index[fr]) for fr in data.frames], "scale": scale.tolist(),
                    "flagged": res.params["flagged_frames"], "xlabel": "frame", "ylabel": "measured / predicted (linear)"}
        return res

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        i = result.internal
        logs = np.zeros(len(frames))
        for j, fr in enumerate(np.asarray(frames).tolist()):  # loop over frames, not pixels
            if fr in i["log_scale"]:
                logs[j] = i["log_scale"][fr]
            elif measured is not None:  # a frame not fitted (held out): its own scale from the fit pixels
                lin_m = decode(measured[j], ctx.gamma_assumed)
                lin_p = decode(predicted[j], ctx.gamma_assumed) * math.exp(i["log_global"])
                m = (predicted[j] > DISPLAY_MIN) & (predicted[j] < DISPLAY_MAX) & (measured[j] < 0.985)
                if fit_mask is not None:
                    m &= np.broadcast_to(fit_mask[..., None], m.shape)
                m &= np.broadcast_to(ctx.valid[..., None], m.shape)
                if m.any():
                    logs[j] = math.log(max(lin_m[m].sum(), 1e-12) / max(lin_p[m].sum(), 1e-12))
        return photometric_apply(predicted, (i["log_global"] + logs)[:, None, None, None], ctx.gamma_assumed)


class ExposureMetadata(Effect):
    cause_class = ExposureMetadataCause  # the diagnosis's estimator (egobench.residual.estimation)
    identifiability = (
        "only when the recorded exposure x gain varies or some frames are wrong against the others; a "
        "model-error floor of 15 % on single frames applies on trained runs")
    trained_magnitudes = (0.25,)
    in_trained_sweep = True
    on_adt = True
    error_unit = "fraction"
    estimate_key = "median_exposure_relative_error"

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"exposure_metadata_error": float(value), "exposure_metadata_fraction": float(affected_fraction)}

    def _parameter_error(self, value, params):
        return abs(params["median_exposure_relative_error"] - value)

    def synth_exposure(self, k_recorded, rng, value, metadata_fraction):
        """Frame 8 (the first held-out one after 0) and a random share of the others get (1 + e)."""
        F = len(k_recorded)
        n_aff = max(2, int(round(metadata_fraction * F)))
        pool = [f for f in range(F) if f != 8]
        affected = sorted([8] + rng.choice(pool, n_aff - 1, replace=False).tolist()) if F > 8 else sorted(
            rng.choice(F, n_aff, replace=False).tolist())
        k_recorded[affected] *= 1.0 + float(value)
        return affected

    def smallest_testable(self, d, se, ctx):
        return {"exposure_relative_error": math.exp(max(FLAG_SIGMAS * se, FLAG_MIN_LOG)) - 1.0}

    def plot_signature(self, ax, plot):
        ax.plot(plot["frame"], plot["scale"], "o-")
        flagged = [i for i, f in enumerate(plot["frame"]) if f in set(plot["flagged"])]
        ax.plot([plot["frame"][i] for i in flagged], [plot["scale"][i] for i in flagged], "rs", label="flagged")
        ax.set_xlabel(plot["xlabel"]), ax.set_ylabel(plot["ylabel"]), ax.legend(fontsize=7)
        return True


EXPOSURE_METADATA = ExposureMetadata(
    name="exposure_metadata",
    description="Per-frame exposure metadata wrong on a random subset of frames (the simulator chooses "
    "which): the recorded exposure_s is the true one times (1 + e).",
    parameter="exposure_relative_error", unit="fraction", nominal=0.0,
    plausible_range=(0.10, 0.30), sampling="signed",
    formation_switch="exposure_gain",
    signature="Whole-frame brightness ratio between captured and predicted images that is constant "
    "within a frame, differs between frames, and does not follow the recorded exposure * gain.",
)
