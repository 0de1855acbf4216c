"""Lens distortion: the true Fisheye624 k0 differs from the calibration used for rectification."""

from __future__ import annotations

from egobench.effects.base import Effect


class Distortion(Effect):
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
