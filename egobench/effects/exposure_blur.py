"""Motion blur during a long exposure, which models rendering one instant per row miss."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from egobench.effects.base import Effect
from egobench.effects.readout import ReadoutCause
from egobench.effects.time_offset import TimeOffsetCause
from egobench.residual.calibration import PlaceboRecord, velocity_placebo
from egobench.residual.estimation import CauseResult, GeometricCause, ResidualData
from egobench.residual.signatures import directional_second_derivative, warp

#: Sub-exposure instants a synthetic case averages over.
SYNTH_SUBSAMPLES = 16


class ExposureBlurCause(GeometricCause):
    """Motion blur over the exposure: average of the prediction along the motion. theta = [T_s]."""

    name = "exposure_blur"
    one_sided = True
    axial, placebo_turns_deg = True, (60.0, 120.0)  # a blur along v is one along -v
    n_sub = 9  # sub-samples over the exposure when re-rendering by warps

    def regressors(self, data):
        # residual ~ (T^2 / 24) v^T H v for a box exposure centred on the model time
        return [directional_second_derivative(data.p, data.velocity, data.hess)]

    def velocity_basis(self, data):
        gxx, gxy, gyy = data.hess  # v^T H v = gxx vx^2 + 2 gxy vx vy + gyy vy^2
        return [[(gxx, 2, 0), (2.0 * gxy, 1, 1), (gyy, 0, 2)]]

    def initial_theta(self, est, info):
        beta = super().initial_theta(est, info)[0]
        return np.array([math.sqrt(24.0 * beta) if beta > 0 else 1e-3])

    def displacement(self, theta, ctx, frames, shape):
        v = ctx.pixel_velocity_px_s[frames].astype(np.float64)
        taus = (np.arange(self.n_sub) + 0.5) / self.n_sub - 0.5
        return _Instants(1.0 / self.n_sub, v, [tau * theta[0] for tau in taus])

    def step_sizes(self, ctx):
        return np.array([5e-4])

    def constrain(self, theta):
        return np.abs(theta)

    def describe(self, theta, ctx):
        return {"exposure_s": float(abs(theta[0])), "recorded_exposure_s_median": float(np.median(ctx.exposure_s))}

    def fit_unconditioned(self, data: ResidualData) -> CauseResult:
        """The blur fit on the residual as it is, without removing the best row-dependent shift first
        (`blur_given_frame_shifts` supplies its own shift)."""
        return super().fit(data)

    def fit(self, data):
        """Tested GIVEN the best row-dependent time shift (the readout model a + b (R - 1/2), which
        contains a time offset): the second-order term of a shift d, (1/2) d^T H d, has exactly
        the blur signature (a 3 ms offset looks like a 10 ms exposure), so the prediction is first
        warped by the refined shift and blur is fitted and sized on what remains."""
        if data.velocity is None:
            return self._untestable("no per-pixel image velocity in the context")
        shift = ReadoutCause()
        est, info = shift.first_order(data)
        theta_shift = shift.refine(data, shift.initial_theta(est, info))
        p_shift, inside = shift.warp_prediction(data.p, theta_shift, data.ctx, data.frames)
        res = super().fit(data.with_prediction(np.clip(p_shift, 0.0, 1.0), inside))
        if res.testable:
            beta = res.internal["theta_first_order"][0]
            res.params["first_order_estimate"] = {"exposure_s": float(beta)}
            res.params["conditioned_on_shift_s"] = {"centre": float(theta_shift[0]), "row_slope": float(theta_shift[1])}
        return res


    def trained_placebos(self, result, evidence):
        """On a trained run: the velocity placebo, and the blur given a shift in every frame (`blur_given_frame_shifts`)."""
        record = velocity_placebo(self, result, evidence)
        if record is None:
            return []
        given = blur_given_frame_shifts(self, evidence.data) if result.testable else None
        return [record] + ([given] if given is not None else [])

class _Instants(Sequence):
    """The exposure's sub-instants as (weight, displacement [f, H, W, 2] = velocity x time) pairs, each
    displacement made when it is read: all n_sub at once were the diagnosis's largest block at its peak
    memory (docs/diagnosis.md, "Cost at the paper's resolution")."""

    def __init__(self, weight: float, velocity_px_s: np.ndarray, times_s: list):
        self._weight, self._velocity, self._times = weight, velocity_px_s, times_s

    def __len__(self) -> int:
        return len(self._times)

    def __getitem__(self, i):
        if not 0 <= i < len(self._times):  # (also ends the iteration Sequence derives from this)
            raise IndexError(i)
        return self._weight, self._velocity * self._times[i]



def blur_given_frame_shifts(cause: ExposureBlurCause, data: ResidualData) -> PlaceboRecord | None:
    """Exposure blur on a trained run, tested GIVEN a separate shift along the motion in every frame
    (in place: p-value = the larger of both). A trained model's per-frame pose/timing errors are
    shifts along each frame's motion with varying sign; their second-order term (1/2) d^T H d is
    positive whatever the sign, exactly the blur signature, which one global shift cannot remove."""
    if data.velocity is None:
        return None
    est, _ = TimeOffsetCause().first_order(data)  # per-frame time shift dt_f [f, 1], s
    shifted, inside = warp(data.p, data.velocity * est[:, 0][:, None, None, None])
    shifted_data = data.with_prediction(np.clip(shifted, 0.0, 1.0), inside)
    given = cause.fit_unconditioned(shifted_data)
    if not given.testable:
        return None
    return PlaceboRecord(given.p_value, {"p_value_given_frame_shifts": given.p_value,
                                         "exposure_s_given_frame_shifts": given.params.get("exposure_s")})


class ExposureBlur(Effect):
    cause_class = ExposureBlurCause  # the diagnosis's estimator (egobench.residual.estimation)
    identifiability = (
        "only with motion during the exposure: blur length is speed x exposure, so short exposures or "
        "still frames show nothing")
    trained_magnitudes = (8e-3,)
    synth_speed_px_s = (250.0, 600.0)  # blur needs fast image motion to show at a few ms
    trained_placebo = "velocity_permutation"

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
