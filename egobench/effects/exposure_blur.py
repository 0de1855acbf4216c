"""Motion blur during a long exposure, which models rendering one instant per row miss."""

from __future__ import annotations

import math

import numpy as np

from egobench.effects.base import Effect

#: Sub-exposure instants a synthetic case averages over.
SYNTH_SUBSAMPLES = 16


class ExposureBlur(Effect):
    identifiability = (
        "only with motion during the exposure: blur length is speed x exposure, so short exposures or "
        "still frames show nothing")
    trained_magnitudes = (8e-3,)
    synth_speed_px_s = (250.0, 600.0)  # blur needs fast image motion to show at a few ms
    trained_placebo = "velocity_permutation"
    tested_given_frame_shifts = True

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"exposure_s": float(value)}

    def _parameter_error(self, value, params):
        return abs(params["exposure_s"] / value - 1.0)

    def synth_irradiance(self, image, t_true, disp_true, value):
        taus = ((np.arange(SYNTH_SUBSAMPLES) + 0.5) / SYNTH_SUBSAMPLES - 0.5) * float(value)
        return np.mean([image(t_true + tau, disp_true) for tau in taus], axis=0)

    def smallest_testable(self, d, se, ctx):
        return {"exposure_s": math.sqrt(24.0 * d)}


EXPOSURE_BLUR = ExposureBlur(
    name="exposure_blur",
    description="Motion during the exposure (Eq. 3 integral). Models render one instant per row "
    "(the released code caps exposure samples at 1). Hidden: a long exposure under fast motion.",
    parameter="exposure_s", unit="s", nominal=0.0,
    plausible_range=(4e-3, 10e-3), sampling="uniform",
    signature="Directional blur along the image-space velocity: predicted images sharper than the "
    "captured ones, residual energy at edges perpendicular to motion, scaling with exposure * speed.",
)
