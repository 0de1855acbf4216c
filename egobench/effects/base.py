"""The base of every physical effect (one subclass per effect, one file each in egobench/effects/).

An `Effect` knows its parameter (name, unit), the value a model assumes by default (``nominal``),
the plausible range of the true value a model may miss (issue 6), how to draw a seeded hidden value
(``sample_hidden``), the `FormationConfig` switch that models it (when it is part of the image
formation rather than geometry/timing) and its residual signature; and, as hooks the simulator,
the synthetic cases, the sweeps and the diagnosis call instead of branching on its name: how the
simulator hides it (`sim_overrides`), the sweeps' magnitudes and hidden values, how a synthetic case
injects it (``synth_*``), its parameter error, the smallest effect a run can reveal, and its
signature plot; and its estimator, ``cause_class`` (a `Cause` of egobench.residual.estimation: how
the diagnosis tests, estimates and models it), defined in the same file. The defaults below are
"this effect does not take part"; a subclass overrides what concerns it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Literal

import numpy as np

from egobench import portable_math as pm

#: How a hidden value is drawn from ``plausible_range`` (lo, hi):
#: "uniform": U(lo, hi); "signed": +-U(lo, hi), sign a fair coin (an error of either sign);
#: "log_uniform": exp(U(log lo, log hi)) (a multiplicative factor).
Sampling = Literal["uniform", "signed", "log_uniform"]

Value = float | tuple[float, ...]

#: The order in which a trained run's placebos run, by `Effect.trained_placebo`.
TRAINED_PLACEBO_ORDER = ("photometric", "radial_centres", "velocity_permutation")


@dataclass
class PhotometricTruth:
    """The photometric truth of a synthetic case, which `Effect.synth_photometric` changes where its effect hides."""

    vignette: np.ndarray  # [H, W] the lens shading
    white_balance: np.ndarray  # [3] channel gains
    noise: Any  # the sensor noise model (egobench.model.formation.PoissonGaussianNoise)
    gamma: float  # the response's gamma


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
            values = pm.exp(rng.uniform(math.log(lo), math.log(hi), size=self.size))
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

    # ---- the simulator ------------------------------------------------------------------------
    def sim_overrides(self, value: Value, affected_fraction: float = 0.25) -> dict[str, Any]:
        """SimConfig overrides that hide ``value`` of this effect."""
        raise NotImplementedError(f"Effect {self.name}: sim_overrides")

    #: The diagnosis's estimator of this effect (an egobench.residual.estimation.Cause subclass).
    cause_class: ClassVar[type]

    # ---- the sweeps ---------------------------------------------------------------------------
    #: Sweep magnitudes are log-deviations from the nominal value (a multiplicative parameter).
    multiplicative: ClassVar[bool] = False
    #: Hidden magnitudes of the trained sweep (deviation from nominal, see `trained_value`).
    trained_magnitudes: ClassVar[tuple[float, ...]] = ()
    #: In the trained sweep's default set (the photometric effects).
    in_trained_sweep: ClassVar[bool] = False
    #: Image speeds (px/s) of the synthetic sweep's cases, when the effect needs others than the default.
    synth_speed_px_s: ClassVar[tuple[float, float] | None] = None
    #: Its hidden value is set on the raw sensor; a diagnosis of the rectified view sees it reparametrised
    #: (the trained sweep converts the truth, `vignette_in_view`).
    hidden_on_raw_sensor: ClassVar[bool] = False
    #: The model extension (a lens shading learned with the scene, egobench.model.shading) is meant to learn it.
    learned_by_shading_extension: ClassVar[bool] = False
    #: The evidence its trained-run placebos read (`Cause.trained_placebos`), which also orders them
    #: (`TRAINED_PLACEBO_ORDER`): "photometric" (the cell fit at the render's resolution), "radial_centres"
    #: (wrong centres of a static radial cause), "velocity_permutation" (motion-driven causes), or None (no placebo).
    trained_placebo: ClassVar[str | None] = None
    #: Why a trained run cannot show it (not tested there), or None.
    trained_run_untestable: ClassVar[str | None] = None
    #: A variance model (named by its held-out likelihood gain), not a mean model of the residual.
    variance_model: ClassVar[bool] = False
    #: When a recording can show it at all (said in every diagnosis report before any name).
    identifiability: ClassVar[str] = ""
    #: Tested on the Aria Digital Twin pair (real vs twin images: photometric causes only).
    on_adt: ClassVar[bool] = False
    #: Unit of `parameter_error`.
    error_unit: ClassVar[str] = "relative"
    #: Key of the diagnosis's estimate of the parameter (`retention`), when not `parameter`.
    estimate_key: ClassVar[str | None] = None
    #: Learned with the scene (`TrainConfig.learn_timing`): the key of its learned value in train.json's
    #: ``learned_timing`` (ms) and the floor from which the learned value names it (`egobench.diagnose.learned_timing`);
    #: None: not learned.
    learned_timing: ClassVar[tuple[str, float] | None] = None
    #: Learned with the scene one value per training frame (`TrainConfig.learn_frame_exposure`): the key of the values
    #: in train.json (``frames``, ``log_scale``), judged by `judge_learned_frames`; None: not learned.
    learned_per_frame: ClassVar[str | None] = None

    def sweep_magnitudes(self, fractions_of_lo: tuple[float, ...]) -> list[float]:
        """Magnitudes of the synthetic sweep (deviation from nominal, the parameter's unit; log for
        multiplicative parameters): fractions of the range's low end, its middle and its top."""
        lo, hi = self.plausible_range
        if self.multiplicative:
            nominal = self.nominal
            lo_dev = min(abs(math.log(lo / nominal)), abs(math.log(hi / nominal)))
            hi_dev = max(abs(math.log(lo / nominal)), abs(math.log(hi / nominal)))
            devs = [f * lo_dev if lo_dev > 0 else f * hi_dev for f in fractions_of_lo] + [0.5 * (lo_dev + hi_dev), hi_dev]
            return sorted(set(round(d, 6) for d in devs if d > 0))
        return [f * lo for f in fractions_of_lo] + [0.5 * (lo + hi), hi]

    @staticmethod
    def draw_sign(rng: np.random.Generator) -> float:
        """+1 or -1, a fair coin from ``rng`` (every effect's hidden value draws it, used or not)."""
        return 1.0 if rng.random() < 0.5 else -1.0

    def _signed(self, sign: float, magnitude: float) -> Value:
        return sign * magnitude if self.sampling == "signed" else magnitude

    def sweep_value(self, magnitude: float, rng: np.random.Generator) -> Value:
        """The synthetic sweep's hidden value of ``magnitude`` (a random sign where the effect has one)."""
        return self._signed(self.draw_sign(rng), magnitude)

    def trained_value(self, magnitude: float, rng: np.random.Generator) -> Value:
        """The trained sweep's hidden value of ``magnitude`` (a random sign where the effect has one)."""
        return self._signed(self.draw_sign(rng), magnitude)

    def parameter_error(self, value: Value, params: dict) -> float | None:
        """Error of a diagnosis estimate ``params`` against the hidden ``value`` (`error_unit`), or None."""
        try:
            return self._parameter_error(value, params)
        except (KeyError, TypeError, ZeroDivisionError):
            return None

    def _parameter_error(self, value: Value, params: dict) -> float | None:
        return None

    # ---- a synthetic case (egobench.diagnose.synthetic) ----------------------------------------
    def synth_exposure(self, k_recorded: np.ndarray, rng: np.random.Generator, value: Value,
                       metadata_fraction: float) -> list[int]:
        """Change the recorded exposure scales [F] in place; -> the frames whose metadata is wrong."""
        return []

    def synth_row_times(self, t_model: np.ndarray, R: np.ndarray, value: Value, readout_s: float) -> np.ndarray:
        """True row times [H, W] (s) given the model's, the row time ratio R and the stated readout."""
        return t_model.copy()

    def synth_displacement(self, value: Value, radial_field: Callable[[float], np.ndarray]) -> np.ndarray | None:
        """True static image displacement [H, W, 2] px (``radial_field(k0 change)``: a lens's radial field), or None."""
        return None

    def synth_irradiance(self, image: Callable[[np.ndarray, np.ndarray], np.ndarray], t_true: np.ndarray,
                         disp_true: np.ndarray, value: Value) -> np.ndarray:
        """The true irradiance [F, H, W, 3] from ``image(row times, displacement)``: one instant per row."""
        return image(t_true, disp_true)

    def synth_photometric(self, truth: PhotometricTruth, value: Value, shape: tuple[int, int]) -> None:
        """Change the photometric truth in place."""

    # ---- the diagnosis ------------------------------------------------------------------------
    def learned_estimate(self, learned_ms: float, stated_readout_s: float) -> dict:
        """The diagnosis's estimate of the parameter from the value learned with the scene (`learned_timing`),
        keyed as the residual diagnosis keys it; empty when the effect is not learned."""
        return {}

    def judge_learned_frames(self, frames: list[int], values: np.ndarray) -> dict:
        """The verdict on the per-frame values learned with the scene (`learned_per_frame`): a record whose
        ``flagged_frames`` (recording frame indices) name the effect where not empty."""
        raise NotImplementedError(f"effect {self.name!r} learns no per-frame values")

    def learned_frames_gain(self, measured: np.ndarray, predicted: np.ndarray, ctx, verdict: dict, learned: dict,
                            fit_mask: np.ndarray, eval_mask: np.ndarray) -> dict | None:
        """The within-frame gain of correcting the frames ``verdict`` (`judge_learned_frames`) flags, on a trained
        run's renders [F, H, W, 3] of the recording's ``measured`` frames (``learned``: frame index -> learned
        value; each frame's correction from its fit_mask pixels, scored on eval_mask) -> {"gain_db": PSNR gain, mean
        over the F frames, "frames": flagged frames scored}, or None where the stack holds none of them. An effect
        with `learned_per_frame` defines it with `judge_learned_frames`."""
        raise NotImplementedError(f"effect {self.name!r} learns no per-frame values")

    def smallest_testable(self, d: float, se: float, ctx) -> dict | None:
        """The smallest effect a run can reveal, in the parameter's unit, from the statistic's minimal
        detectable deviation ``d`` and its standard error ``se`` (None: no conversion)."""
        return None

    def plot_signature(self, ax, plot: dict) -> bool:
        """Draw this cause's signature from its ``plot`` dict; False: the generic per-frame plot."""
        return False
