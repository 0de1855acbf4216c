"""One object per physical effect: the list the simulator hides, the trainer ablates and the
diagnosis looks for (DESIGN.md, "One idea that keeps the three users of physics in step").

Each `Effect` knows its parameter (name, unit), the value a model assumes by default
(``nominal``), the plausible range of the true value a model may miss (issue 6), how to draw a
seeded hidden value (``sample_hidden``), the `FormationConfig` switch that models it (when it
is part of the image formation rather than geometry/timing), and its residual signature.
Estimators live with the diagnosis (``egobench/diagnose``), keyed by these names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

#: How a hidden value is drawn from ``plausible_range`` (lo, hi):
#: "uniform": U(lo, hi); "signed": +-U(lo, hi), sign a fair coin (an error of either sign);
#: "log_uniform": exp(U(log lo, log hi)) (a multiplicative factor).
Sampling = Literal["uniform", "signed", "log_uniform"]

Value = float | tuple[float, ...]


@dataclass(frozen=True)
class Effect:
    """A physical effect, its parameter and where a model that ignores it goes wrong."""

    name: str  # registry key (also the SimConfig hidden-effect name and the diagnosis key)
    description: str  # what the effect is physically, and how the simulator applies the hidden value
    parameter: str  # name of the hidden parameter
    unit: str  # its unit ("s", "1" for dimensionless, "fraction" for a relative error)
    nominal: float  # what a model assumes by default (per channel when size > 1)
    plausible_range: tuple[float, float]  # (lo, hi) of the hidden value (of its magnitude for "signed")
    sampling: Sampling  # how sample_hidden draws from plausible_range
    signature: str  # one sentence: the physical signature in the residuals a diagnosis looks for
    size: int = 1  # number of values (3 for per-channel gains)
    formation_switch: str | None = None  # FormationConfig field that models it; None: geometry/timing

    def __post_init__(self) -> None:
        lo, hi = self.plausible_range
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"Effect {self.name}: plausible_range must be finite (lo, hi) with lo <= hi, got {self.plausible_range}")
        if self.sampling == "log_uniform" and lo <= 0:
            raise ValueError(f"Effect {self.name}: log_uniform sampling needs lo > 0, got {self.plausible_range}")
        if self.sampling not in ("uniform", "signed", "log_uniform"):
            raise ValueError(f"Effect {self.name}: sampling must be uniform|signed|log_uniform, got {self.sampling!r}")
        if self.size < 1:
            raise ValueError(f"Effect {self.name}: size must be >= 1, got {self.size}")

    def sample_hidden(self, rng: np.random.Generator | int) -> Value:
        """A seeded draw of the hidden true value (a float, or a tuple of ``size`` floats).

        rng: a numpy Generator (advanced by the draw) or an integer seed.
        """
        if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
            rng = np.random.default_rng(int(rng))
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng: expected a numpy.random.Generator or an integer seed, got {type(rng).__name__}")
        lo, hi = self.plausible_range
        if self.sampling == "uniform":
            values = rng.uniform(lo, hi, size=self.size)
        elif self.sampling == "log_uniform":
            values = np.exp(rng.uniform(math.log(lo), math.log(hi), size=self.size))
        else:  # signed
            magnitude = rng.uniform(lo, hi, size=self.size)
            values = np.where(rng.random(size=self.size) < 0.5, -magnitude, magnitude)
        values = [float(v) for v in values]
        return values[0] if self.size == 1 else tuple(values)

    def in_range(self, value: Value) -> bool:
        """Whether ``value`` is a possible hidden value (magnitude in range for "signed")."""
        values = (value,) if self.size == 1 and not isinstance(value, (tuple, list)) else tuple(value)
        if len(values) != self.size:
            return False
        lo, hi = self.plausible_range
        mags = [abs(v) if self.sampling == "signed" else v for v in values]
        return all(lo <= m <= hi for m in mags)

    def to_dict(self) -> dict:
        """JSON-ready description (for truth.json and reports)."""
        return {
            "name": self.name, "description": self.description, "parameter": self.parameter, "unit": self.unit,
            "nominal": self.nominal, "plausible_range": list(self.plausible_range), "sampling": self.sampling,
            "size": self.size, "formation_switch": self.formation_switch, "signature": self.signature,
        }


_EFFECTS = [
    Effect(
        name="readout",
        description="Rolling-shutter readout: raw row r starts exposing at read_start + R(u) * readout_s. "
        "Hidden: the true readout differs from the metadata by a relative error e (true = nominal * (1 + e)).",
        parameter="readout_relative_error", unit="fraction", nominal=0.0,
        plausible_range=(0.20, 0.60), sampling="signed",
        signature="Misalignment that grows linearly with row time R(u) and with image-space velocity: "
        "edges shear along the motion, residual largest at the top and bottom rows of fast frames.",
    ),
    Effect(
        name="time_offset",
        description="Camera-to-device clock offset (t_device = t_camera + time_offset_s). "
        "Hidden: the calibrated offset is wrong by this many seconds.",
        parameter="time_offset_error_s", unit="s", nominal=0.0,
        plausible_range=(1e-3, 5e-3), sampling="signed",
        signature="A whole-image shift along the image-space velocity, uniform over rows, proportional to "
        "angular speed, and zero on quasi-static frames.",
    ),
    Effect(
        name="exposure_blur",
        description="Motion during the exposure (Eq. 3 integral). Models render one instant per row "
        "(the released code caps exposure samples at 1). Hidden: a long exposure under fast motion.",
        parameter="exposure_s", unit="s", nominal=0.0,
        plausible_range=(4e-3, 10e-3), sampling="uniform",
        signature="Directional blur along the image-space velocity: predicted images sharper than the "
        "captured ones, residual energy at edges perpendicular to motion, scaling with exposure * speed.",
    ),
    Effect(
        name="vignette",
        description="Lens shading not contained in the calibrated vignette image: an extra radial "
        "falloff (formation.radial_vignette, cos^4-like) attenuating the corners by this fraction.",
        parameter="corner_attenuation", unit="fraction", nominal=0.0,
        plausible_range=(0.20, 0.50), sampling="uniform",
        formation_switch="vignette",
        signature="A smooth, radially symmetric, multiplicative darkening of the captured image relative to "
        "the prediction, identical in every frame and view-independent, growing towards the corners.",
    ),
    Effect(
        name="response",
        description="Camera response phi: the true gamma of the sensor pipeline versus the assumed 2.2.",
        parameter="gamma", unit="1", nominal=2.2,
        plausible_range=(1.6, 2.8), sampling="uniform",
        formation_switch="response",
        signature="A monotone, intensity-dependent bias: a curved (not straight) scatter of captured versus "
        "predicted values, mid-tones off while black and white agree, and exposure changes not "
        "explained by a single scale.",
    ),
    Effect(
        name="white_balance",
        description="Per-channel gains (R, G, B) applied by the sensor pipeline and not modelled.",
        parameter="channel_gains", unit="1", nominal=1.0,
        plausible_range=(0.8, 1.25), sampling="log_uniform", size=3,
        formation_switch="white_balance",
        signature="A constant per-channel ratio between captured and predicted linear values: a colour "
        "cast uniform over the image and all frames.",
    ),
    Effect(
        name="exposure_metadata",
        description="Per-frame exposure metadata wrong on a random subset of frames (the simulator chooses "
        "which): the recorded exposure_s is the true one times (1 + e).",
        parameter="exposure_relative_error", unit="fraction", nominal=0.0,
        plausible_range=(0.10, 0.30), sampling="signed",
        formation_switch="exposure_gain",
        signature="Whole-frame brightness ratio between captured and predicted images that is constant "
        "within a frame, differs between frames, and does not follow the recorded exposure * gain.",
    ),
    Effect(
        name="noise",
        description="Sensor noise (formation.PoissonGaussianNoise) stronger or weaker than the device "
        "profile: every noise standard deviation times this factor (full well / f^2, read noise / f).",
        parameter="noise_std_factor", unit="1", nominal=1.0,
        plausible_range=(0.5, 2.0), sampling="log_uniform",
        formation_switch="noise",
        signature="Zero-mean, spatially white residuals whose variance is affine in the predicted linear "
        "signal (slope gain / full well, intercept from read noise), higher at higher gain.",
    ),
    Effect(
        name="distortion",
        description="Fisheye624 radial coefficient k0 of the true lens differs from the calibration "
        "used for rectification (absolute change of k0).",
        parameter="k0_error", unit="1", nominal=0.0,
        plausible_range=(0.002, 0.01), sampling="signed",
        signature="A static radial displacement growing with field angle (zero at the centre), identical in "
        "every frame, so edges near the image border are doubled or misplaced across views.",
    ),
]

#: The registry, keyed by effect name (order: geometry/timing first, then photometric).
EFFECTS: dict[str, Effect] = {effect.name: effect for effect in _EFFECTS}


def get_effect(name: str) -> Effect:
    """The effect called ``name``; ValueError listing the known names otherwise."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise ValueError(f"effect: unknown name {name!r}; expected one of {sorted(EFFECTS)}") from None


def sample_hidden_effects(names: list[str], seed: int) -> dict[str, Value]:
    """Seeded hidden values for several effects, each drawn from its own stream (order-independent)."""
    out: dict[str, Value] = {}
    for name in names:
        effect = get_effect(name)
        index = list(EFFECTS).index(name)
        out[name] = effect.sample_hidden(np.random.default_rng([int(seed), index]))
    return out
