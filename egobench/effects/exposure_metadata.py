"""Exposure metadata wrong on some frames: the recorded exposure is the true one times (1 + e)."""

from __future__ import annotations

import math

from egobench.effects.base import Effect

#: A frame of a trained run is flagged when both halves of it deviate beyond this many robust standard
#: deviations of the model's frame-to-frame error, and beyond FLAG_MIN_LOG. The floor is the largest
#: single-frame scale that model error alone gave on the trained sweeps' cases without a metadata error
#: (outdoor, 64 px, 800 iterations: 14 % on one frame of one null, all others <= 11 %; docs/diagnosis.md):
#: single frames of a trained model can render that much too dark or bright.
FLAG_SIGMAS, FLAG_MIN_LOG = 4.0, math.log(1.15)


class ExposureMetadata(Effect):
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
