"""The simulated camera's auto-exposure (exposure and gain from the preview's median luminance)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from egobench.sim.devices import DeviceProfile

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    pass


# ----------------------------------------------------------------------------------------
# auto-exposure
# ----------------------------------------------------------------------------------------
@dataclass
class AutoExposureState:
    """Running auto-exposure (log exposure*gain smoothed over frames)."""

    device: DeviceProfile
    protocol: str  # auto | indoor | fixed
    fixed_exposure_s: float | None = None
    fixed_gain: float | None = None
    log_eg: float | None = None
    held: tuple[float, float] | None = None

    def step(self, median_luminance: float) -> tuple[float, float]:
        """-> (exposure_s, gain) for a frame whose median luminance is given (cd/m^2)."""
        ae = self.device.auto_exposure
        sens = self.device.sensitivity
        # indoor: the paper's capture protocol caps exposure (2 ms); fixed (DTC-like lab captures with fixed
        # exposure and gain): the first frame's indoor-protocol values are held (assumption: the DTC
        # exposure is not published; a short exposure keeps the object sharp).
        capped = self.protocol in ("indoor", "fixed")
        exp_max = min(ae.exposure_max_s, self.device.indoor_exposure_max_s) if capped else ae.exposure_max_s
        if median_luminance > 0 and math.isfinite(median_luminance):
            target = math.log(ae.target_median / (sens * median_luminance))
        else:
            target = math.log(exp_max * ae.gain_max)
        if self.log_eg is None:
            self.log_eg = target
        else:
            self.log_eg = ae.smoothing * self.log_eg + (1.0 - ae.smoothing) * target
        eg = math.exp(self.log_eg)
        if self.fixed_exposure_s is not None:
            exposure = self.fixed_exposure_s
            gain = self.fixed_gain if self.fixed_gain is not None else min(ae.gain_max, max(ae.gain_min, eg / exposure))
            return exposure, gain
        if self.protocol == "fixed" and self.held is not None:
            return self.held
        exposure = min(exp_max, max(ae.exposure_min_s, eg / ae.gain_min))
        gain = min(ae.gain_max, max(ae.gain_min, eg / exposure))
        if self.protocol == "fixed":
            self.held = (exposure, gain)
        return exposure, gain
