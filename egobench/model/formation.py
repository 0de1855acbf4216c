"""Physical image formation (paper Eqs. 3-5; docs/paper-notes.md §2).

One model serves two users:

* the simulator (``FormationModel.simulate``): every effect on, producing the ground-truth
  captured image from clean linear irradiance;
* the trainer (``FormationModel.predict``): the subset of effects a method models, applied to
  the rasterized scene colour as the authors' code does
  (``image = encode(decode(x) * k * V)``, clamped to [0, 1]). The paper's response is a pure
  gamma 2.2 (`GammaResponse`); the released code actually uses an sRGB-shaped curve with
  exponent 2.2 (`AuthorsSRGB22Response`, ``response="authors_srgb22"``), offered for fidelity.

Units. "Normalised linear signal" is irradiance after exposure, gain and sensitivity, scaled so
that 1.0 is the full well (the clipping level) of the sensor at the frame's gain. "Display"
values are after the camera response, in [0, 1] (what an 8-bit image holds divided by 255).

Every component is a small function or class with its parameters validated; all of them are
vectorised torch, differentiable where the trainer needs it, and keep the input's dtype and
device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal, Protocol, Sequence, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from egobench.model.gamma_exposure import compiled_exposure_applies, gamma_expose

ResponseKind = Literal["gamma", "linear", "srgb", "authors_srgb22"]

#: Default camera response exponent (paper: "gamma value 2.2 as our default setting").
DEFAULT_GAMMA = 2.2
#: Linear input below which the gamma curve is replaced by a straight line through 0 (keeps
#: the gradient finite at 0). At gamma 2.2 the toe ends at display value 0.0053 (1.4 8-bit levels).
GAMMA_TOE_LINEAR = 1e-5


# ----------------------------------------------------------------------------- responses
@runtime_checkable
class Response(Protocol):
    """Camera response phi: linear signal -> display value, and its inverse."""

    def encode(self, linear: Tensor) -> Tensor:  # [...] -> [...]
        ...

    def decode(self, display: Tensor) -> Tensor:  # [...] -> [...]
        ...


@dataclass(frozen=True)
class LinearResponse:
    """phi(x) = x (a raw, linear camera)."""

    def encode(self, linear: Tensor) -> Tensor:
        return linear

    def decode(self, display: Tensor) -> Tensor:
        return display


@dataclass(frozen=True)
class GammaResponse:
    """phi(x) = x ** (1 / gamma) with a linear toe below ``toe_linear``.

    For x >= toe_linear the curve is the exact power law; below it (and for negative inputs,
    which noise can produce) it is the straight line through 0 and (toe, toe ** (1/gamma)),
    so encode/decode are continuous, exact inverses of each other everywhere, and have finite
    gradients at 0.
    """

    gamma: float = DEFAULT_GAMMA  # exponent of the display->linear curve (2.2: sRGB-like displays)
    toe_linear: float = GAMMA_TOE_LINEAR  # linear value where the power law hands over to the line

    def __post_init__(self) -> None:
        if not (isinstance(self.gamma, (int, float)) and math.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"GammaResponse.gamma: expected a finite number > 0, got {self.gamma!r}")
        if not (0 < self.toe_linear < 1):
            raise ValueError(f"GammaResponse.toe_linear: expected a value in (0, 1), got {self.toe_linear!r}")

    @property
    def _toe_display(self) -> float:
        return self.toe_linear ** (1.0 / self.gamma)

    def encode(self, linear: Tensor) -> Tensor:
        x0 = self.toe_linear
        slope = self._toe_display / x0
        power = linear.clamp_min(x0).pow(1.0 / self.gamma)  # clamp keeps the unused branch's gradient finite
        return torch.where(linear >= x0, power, linear * slope)

    def decode(self, display: Tensor) -> Tensor:
        y0 = self._toe_display
        slope = y0 / self.toe_linear
        power = display.clamp_min(y0).pow(self.gamma)
        return torch.where(display >= y0, power, display / slope)


@dataclass(frozen=True)
class SRGBResponse:
    """The sRGB transfer curve (IEC 61966-2-1), linear below 0.0031308."""

    def encode(self, linear: Tensor) -> Tensor:
        power = 1.055 * linear.clamp_min(0.0031308).pow(1.0 / 2.4) - 0.055
        return torch.where(linear > 0.0031308, power, 12.92 * linear)

    def decode(self, display: Tensor) -> Tensor:
        power = ((display.clamp_min(0.04045) + 0.055) / 1.055).pow(2.4)
        return torch.where(display > 0.04045, power, display / 12.92)


@dataclass(frozen=True)
class AuthorsSRGB22Response:
    """The curve of the authors' released code (scene/cameras.py, ``expose_image_gamma``).

    sRGB constants with exponent 2.2 instead of 2.4: decode(y) = y / 12.92 for y < 0.04045,
    else ((y + 0.055) / 1.055) ** 2.2; encode is the matching pair of branches. With exponent
    2.2 the two branches do not meet (decode jumps from 0.00313 to 0.00506 at y = 0.04045), so
    the curve is not a proper response: the code picks the branch from the *input* scene colour
    and keeps it after scaling (`expose`). Only the trainer path (`predict`, scene gamma) uses it.
    """

    gamma: float = DEFAULT_GAMMA  # exponent replacing sRGB's 2.4
    threshold: float = 0.04045  # display value where the code switches branch

    def decode(self, display: Tensor) -> Tensor:
        power = ((display.clamp_min(self.threshold) + 0.055) / 1.055).pow(self.gamma)
        return torch.where(display < self.threshold, display / 12.92, power)

    def encode(self, linear: Tensor) -> Tensor:
        """Branch by the linear value (threshold 0.04045 / 12.92); see `expose` for the code's rule."""
        lin_threshold = self.threshold / 12.92
        power = 1.055 * linear.clamp_min(lin_threshold).pow(1.0 / self.gamma) - 0.055
        return torch.where(linear < lin_threshold, 12.92 * linear, power)

    def expose(self, scene_colour: Tensor, scale: Tensor) -> Tensor:
        """The code's ``expose_image_gamma`` before clamping: decode, multiply by ``scale``, encode,
        each pixel staying on the branch its input colour selected."""
        power = 1.055 * (((scene_colour.clamp_min(self.threshold) + 0.055) / 1.055).pow(self.gamma) * scale).clamp_min(
            1e-12  # keeps the gradient finite where scale is 0 (outside the image circle)
        ).pow(1.0 / self.gamma) - 0.055
        return torch.where(scene_colour < self.threshold, scene_colour * scale, power)


def make_response(kind: ResponseKind, gamma: float = DEFAULT_GAMMA) -> Response:
    """The response named ``kind`` ("gamma" and "authors_srgb22" use ``gamma``)."""
    if kind == "gamma":
        return GammaResponse(gamma=gamma)
    if kind == "linear":
        return LinearResponse()
    if kind == "srgb":
        return SRGBResponse()
    if kind == "authors_srgb22":
        if not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma: expected a finite number > 0, got {gamma!r}")
        return AuthorsSRGB22Response(gamma=gamma)
    raise ValueError(f"response: expected one of 'gamma', 'linear', 'srgb', 'authors_srgb22', got {kind!r}")


# ----------------------------------------------------------------------------- helpers
def _as_tensor(value: float | Tensor, like: Tensor) -> Tensor:
    if isinstance(value, Tensor):
        return value.to(dtype=like.dtype, device=like.device)
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def _check_values(value: float | Tensor, name: str, *, positive: bool) -> None:
    t = torch.as_tensor(value, dtype=torch.float64) if not isinstance(value, Tensor) else value.detach()
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: expected finite values, got {value!r}")
    if positive and not bool((t > 0).all()):
        raise ValueError(f"{name}: expected values > 0, got {value!r}")
    if not positive and not bool((t >= 0).all()):
        raise ValueError(f"{name}: expected values >= 0, got {value!r}")


def _per_image(value: float | Tensor, image: Tensor, name: str, *, positive: bool) -> Tensor:
    """Scalar or per-image value (shape broadcastable to image.shape[:-3]) -> [..., 1, 1, 1]."""
    _check_values(value, name, positive=positive)
    t = _as_tensor(value, image)
    leading = tuple(image.shape[:-3])
    if t.dim() > 0:
        try:
            ok = np.broadcast_shapes(tuple(t.shape), leading) == leading  # (not torch's: it imports sympy)
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"{name}: expected a scalar or one value per image (shape broadcastable to {list(leading)}), "
                f"got shape {list(t.shape)}"
            )
    return t.reshape(*t.shape, 1, 1, 1)


def _check_image(image: Tensor, name: str) -> None:
    if not isinstance(image, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor [..., H, W, 3], got {type(image).__name__}")
    if image.dim() < 3 or image.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape [..., H, W, 3], got {list(image.shape)}")


def _check_map(vignette: Tensor, image: Tensor, name: str = "vignette") -> Tensor:
    if not isinstance(vignette, Tensor) or vignette.dim() != 2 or tuple(vignette.shape) != tuple(image.shape[-3:-1]):
        shape = list(vignette.shape) if isinstance(vignette, Tensor) else type(vignette).__name__
        raise ValueError(f"{name}: expected a tensor [H, W] = {list(image.shape[-3:-1])}, got {shape}")
    return vignette.to(dtype=image.dtype, device=image.device)[..., None]  # [H, W, 1]


def _check_wb(white_balance: Tensor | Sequence[float], image: Tensor) -> Tensor:
    wb = _as_tensor(torch.as_tensor(white_balance), image)
    if wb.shape[-1:] != (3,):
        raise ValueError(f"white_balance: expected per-channel gains [3] (or [..., 3] per image), got {list(wb.shape)}")
    _check_values(wb, "white_balance", positive=True)
    if wb.dim() > 1:  # per image: [..., 3] -> [..., 1, 1, 3]
        wb = wb.reshape(*wb.shape[:-1], 1, 1, 3)
    return wb


# ----------------------------------------------------------------------------- exposure
def integrate_exposure(samples: Tensor) -> Tensor:
    """Discrete exposure integral of Eq. 3: the mean over S temporal samples.

    samples: [S, ...] renders at the times of `exposure_sample_times_ns` -> [...].
    The mean (not the sum) because exposure_s is carried by the gain normalisation.
    """
    if not isinstance(samples, Tensor) or samples.dim() < 1 or samples.shape[0] < 1:
        raise ValueError(f"samples: expected a tensor [S, ...] with S >= 1, got {getattr(samples, 'shape', samples)!r}")
    return samples.mean(dim=0)


def exposure_sample_times_ns(row_start_ns: Tensor, exposure_s: float | Tensor, n_samples: int) -> Tensor:
    """Times of ``n_samples`` exposure samples for rows starting at ``row_start_ns``.

    row_start_ns: [...] time t(row) a row starts exposing (device clock, ns);
    exposure_s: scalar or broadcastable to [...], seconds.
    Returns [..., S]: midpoints of S equal sub-intervals of [t(row), t(row) + exposure_s],
    t(row) + (i + 0.5) / S * exposure. Integer input gives int64 ns (rounded), float input float.
    """
    if not isinstance(n_samples, int) or isinstance(n_samples, bool) or n_samples < 1:
        raise ValueError(f"n_samples: expected an integer >= 1, got {n_samples!r}")
    row_start_ns = torch.as_tensor(row_start_ns)
    _check_values(exposure_s, "exposure_s", positive=False)
    work = torch.float64
    exposure_ns = torch.as_tensor(exposure_s, dtype=work, device=row_start_ns.device) * 1e9
    frac = (torch.arange(n_samples, dtype=work, device=row_start_ns.device) + 0.5) / n_samples  # [S]
    offsets = exposure_ns[..., None] * frac  # [..., S]
    if row_start_ns.dtype.is_floating_point:
        return (row_start_ns[..., None].to(work) + offsets).to(row_start_ns.dtype)
    return row_start_ns.to(torch.int64)[..., None] + torch.round(offsets).to(torch.int64)


def exposure_gain_normaliser(exposure_s: Tensor, gain: Tensor) -> Tensor:
    """Per-frame normaliser k = exposure*gain / median(exposure*gain) (the authors' code).

    exposure_s: [F] seconds, gain: [F] analog gain -> k [F] (median(k) = 1; the median of an
    even count is the mean of the two middle values, as numpy's).
    """
    exposure_s = torch.as_tensor(exposure_s)
    gain = torch.as_tensor(gain)
    if exposure_s.dim() != 1 or gain.shape != exposure_s.shape or exposure_s.numel() == 0:
        raise ValueError(
            f"exposure_s, gain: expected two 1-D tensors [F] of the same non-zero length, "
            f"got {list(exposure_s.shape)} and {list(gain.shape)}"
        )
    _check_values(exposure_s, "exposure_s", positive=True)
    _check_values(gain, "gain", positive=True)
    dtype = exposure_s.dtype if exposure_s.dtype.is_floating_point else torch.float64
    product = exposure_s.to(dtype) * gain.to(dtype)
    return product / torch.quantile(product.to(torch.float64), 0.5).to(dtype)


def sensor_scale(exposure_s: float | Tensor, gain: float | Tensor, sensitivity: float | Tensor) -> Tensor:
    """Irradiance -> normalised linear signal factor: exposure_s * gain * sensitivity.

    ``sensitivity`` (1 / (irradiance unit * s)) is the device's conversion so that
    irradiance * exposure_s * gain * sensitivity = 1.0 at full well (clipping).
    """
    _check_values(exposure_s, "exposure_s", positive=False)
    _check_values(gain, "gain", positive=True)
    _check_values(sensitivity, "sensitivity", positive=True)
    return torch.as_tensor(exposure_s) * torch.as_tensor(gain) * torch.as_tensor(sensitivity)


# ----------------------------------------------------------------------------- vignette, WB
def radial_vignette(
    camera_or_shape: "object | tuple[int, int]",
    strength: float,
    power: float = 4.0,
    centre: tuple[float, float] | None = None,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Radial lens shading V [H, W] in (0, 1], 1 at ``centre``.

    V(r) = (1 + (c r)^2) ** (-power / 2), r = distance to ``centre`` divided by the distance to
    the farthest image corner (pixel centres at integers). power = 4 is the cos^4 law of a
    pinhole (cos theta = 1 / sqrt(1 + (r/f)^2)); c is set so that the farthest corner is
    attenuated by ``strength``: V(1) = 1 - strength (strength 0.3 -> corner at 70 %).

    camera_or_shape: a camera with width/height (centre defaults to its cx, cy) or (H, W)
    (centre defaults to ((W-1)/2, (H-1)/2)). centre is (u, v) in pixels.
    """
    if isinstance(camera_or_shape, tuple):
        if len(camera_or_shape) != 2 or not all(isinstance(n, int) and n > 0 for n in camera_or_shape):
            raise ValueError(f"camera_or_shape: expected (H, W) positive integers or a camera, got {camera_or_shape!r}")
        height, width = camera_or_shape
        default_centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    elif hasattr(camera_or_shape, "width") and hasattr(camera_or_shape, "height"):
        height, width = int(camera_or_shape.height), int(camera_or_shape.width)
        default_centre = (float(getattr(camera_or_shape, "cx", (width - 1) / 2.0)),
                          float(getattr(camera_or_shape, "cy", (height - 1) / 2.0)))
    else:
        raise ValueError(f"camera_or_shape: expected (H, W) or a camera with width/height, got {camera_or_shape!r}")
    if not (0.0 <= strength < 1.0):
        raise ValueError(f"strength: expected the corner attenuation in [0, 1), got {strength!r}")
    if not (power > 0 and math.isfinite(power)):
        raise ValueError(f"power: expected a finite number > 0, got {power!r}")
    cu, cv = default_centre if centre is None else centre
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64, device=device),
        torch.arange(width, dtype=torch.float64, device=device),
        indexing="ij",
    )
    radius = torch.sqrt((u - cu) ** 2 + (v - cv) ** 2)
    corners = torch.tensor([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=torch.float64)
    r_max = torch.sqrt((corners[:, 0] - cu) ** 2 + (corners[:, 1] - cv) ** 2).max().item()
    r = radius / max(r_max, 1e-12)
    c2 = (1.0 - strength) ** (-2.0 / power) - 1.0
    return ((1.0 + c2 * r**2) ** (-power / 2.0)).to(dtype)


def apply_white_balance(linear: Tensor, white_balance: Tensor | Sequence[float]) -> Tensor:
    """Per-channel gains: linear [..., H, W, 3] * white_balance [3] (or [..., 3] per image)."""
    _check_image(linear, "linear")
    return linear * _check_wb(white_balance, linear)


# ----------------------------------------------------------------------------- noise, quantisation
@dataclass(frozen=True)
class PoissonGaussianNoise:
    """Shot + read noise in normalised linear units (signal 1 = full well at gain 1).

    For a clean signal x >= 0 at analog gain g the noisy signal is
        y = g / full_well_e * (Poisson(x * full_well_e / g) + N(0, read_noise_e^2)),
    so E[y] = x and Var[y] = (g / full_well_e) * x + (g * read_noise_e / full_well_e)^2.
    (x * full_well_e / g electrons are collected; the gain amplifies them and the read noise.)
    Negative x (impossible physically) are treated as 0 for the Poisson part.
    """

    full_well_e: float  # electrons at which the pixel saturates (gain 1)
    read_noise_e: float  # standard deviation of the read noise, electrons

    def __post_init__(self) -> None:
        if not (math.isfinite(self.full_well_e) and self.full_well_e > 0):
            raise ValueError(f"PoissonGaussianNoise.full_well_e: expected a finite number > 0, got {self.full_well_e!r}")
        if not (math.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise ValueError(f"PoissonGaussianNoise.read_noise_e: expected a finite number >= 0, got {self.read_noise_e!r}")

    def _gain(self, gain: float | Tensor, signal: Tensor) -> Tensor:
        _check_values(gain, "gain", positive=True)
        g = _as_tensor(gain, signal)
        try:
            np.broadcast_shapes(tuple(g.shape), tuple(signal.shape))
        except ValueError as exc:
            raise ValueError(f"gain: shape {list(g.shape)} does not broadcast to signal {list(signal.shape)}") from exc
        return g

    def sample(self, signal: Tensor, gain: float | Tensor, generator: torch.Generator | None = None) -> Tensor:
        """A noisy draw of ``signal`` [...] (normalised linear) at analog ``gain`` (scalar or broadcastable)."""
        scale = self.electrons_per_unit(gain, signal)
        electrons = self.add_read_noise_(self.shot_electrons(signal, scale, generator), generator)
        return electrons / scale

    def electrons_per_unit(self, gain: float | Tensor, signal: Tensor) -> Tensor:
        """full_well_e / gain: electrons collected per unit of normalised ``signal`` at ``gain``."""
        return self.full_well_e / self._gain(gain, signal)

    def shot_electrons(self, signal: Tensor, scale: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Poisson(signal x scale) [...], the collected electrons (``scale``: `electrons_per_unit`). The
        draws are consumed element by element in order, so drawing a batch in slices (frames) and then
        `add_read_noise_` over all of it gives the same numbers as `sample` on the whole batch."""
        return torch.poisson((signal.clamp_min(0.0) * scale).expand_as(signal).contiguous(), generator=generator)

    def add_read_noise_(self, electrons: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """electrons += N(0, read_noise_e^2), in place (one temporary of its size) -> electrons."""
        if self.read_noise_e > 0:
            draw = torch.randn(electrons.shape, generator=generator, dtype=electrons.dtype, device=electrons.device)
            electrons.add_(draw.mul_(self.read_noise_e))
        return electrons

    def variance(self, signal: Tensor, gain: float | Tensor) -> Tensor:
        """Var[y] = (gain / full_well_e) * signal + (gain * read_noise_e / full_well_e)^2."""
        g = self._gain(gain, signal)
        return g / self.full_well_e * signal.clamp_min(0.0) + (g * self.read_noise_e / self.full_well_e) ** 2

    def scaled(self, std_factor: float) -> "PoissonGaussianNoise":
        """The same sensor with every noise standard deviation multiplied by ``std_factor``."""
        if not (std_factor > 0 and math.isfinite(std_factor)):
            raise ValueError(f"std_factor: expected a finite number > 0, got {std_factor!r}")
        return PoissonGaussianNoise(self.full_well_e / std_factor**2, self.read_noise_e / std_factor)


def quantise(display: Tensor, bits: int = 8) -> Tensor:
    """Round display values to the 2**bits - 1 levels of an integer image (clamped to [0, 1])."""
    if not isinstance(bits, int) or isinstance(bits, bool) or not (1 <= bits <= 16):
        raise ValueError(f"bits: expected an integer in 1..16, got {bits!r}")
    levels = float(2**bits - 1)
    return torch.round(display.clamp(0.0, 1.0) * levels) / levels


# ----------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class FormationConfig:
    """Which effects the formation model applies (the simulator turns all on)."""

    # camera response phi: "gamma" (x^(1/gamma), the paper), "linear", "srgb", or "authors_srgb22"
    # (the released code's sRGB-shaped curve with exponent 2.2; trainer path with scene gamma only)
    response: ResponseKind = "gamma"
    gamma: float = DEFAULT_GAMMA  # exponent of the gamma response (used when response == "gamma")
    exposure_gain: bool = True  # scale by exposure*gain*sensitivity (simulate) / per-frame normaliser k (predict)
    vignette: bool = True  # multiply by the lens-shading map V(u) (a map must then be given)
    white_balance: bool = True  # multiply by per-channel gains (a [3] vector must then be given)
    noise: bool = True  # Poisson-Gaussian sensor noise (simulate only; a PoissonGaussianNoise must be given)
    quantise_bits: int | None = 8  # round to an integer image of this depth (simulate only); None = off
    clamp: bool = True  # clip the linear signal at full well (1) and the display image to [0, 1]

    def __post_init__(self) -> None:
        make_response(self.response, self.gamma)  # validates response and gamma
        if self.quantise_bits is not None:
            quantise(torch.zeros(1), self.quantise_bits)  # validates bits
        for name in ("exposure_gain", "vignette", "white_balance", "noise", "clamp"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"FormationConfig.{name}: expected a bool, got {getattr(self, name)!r}")

    @classmethod
    def ground_truth(cls, **overrides) -> "FormationConfig":
        """Every effect on (the simulator)."""
        return replace(cls(), **overrides)

    @classmethod
    def paper_trainer(cls, **overrides) -> "FormationConfig":
        """What the authors' trainer models: gamma 2.2, exposure*gain normaliser, vignette, clamp."""
        return replace(cls(white_balance=False, noise=False, quantise_bits=None), **overrides)

    @classmethod
    def off(cls, response: ResponseKind = "linear", **overrides) -> "FormationConfig":
        """Every switchable effect off (only the response remains)."""
        return replace(
            cls(response=response, exposure_gain=False, vignette=False, white_balance=False, noise=False,
                quantise_bits=None, clamp=False),
            **overrides,
        )


class FormationModel:
    """Applies a `FormationConfig`'s effects, for the simulator and for the trainer."""

    def __init__(self, config: FormationConfig | None = None) -> None:
        self.config = config if config is not None else FormationConfig()
        if not isinstance(self.config, FormationConfig):
            raise ValueError(f"config: expected a FormationConfig, got {type(config).__name__}")
        self.response: Response = make_response(self.config.response, self.config.gamma)

    def simulate(
        self,
        irradiance_linear: Tensor,  # [..., H, W, 3] clean scene irradiance (linear)
        *,
        exposure_s: float | Tensor,  # scalar or per image [...], seconds
        gain: float | Tensor,  # analog gain, scalar or per image [...]
        sensitivity: float | Tensor = 1.0,  # irradiance*s -> normalised signal (1 = full well)
        vignette: Tensor | None = None,  # [H, W] lens shading
        white_balance: Tensor | Sequence[float] | None = None,  # [3] (or [..., 3]) channel gains
        noise: PoissonGaussianNoise | None = None,
        generator: torch.Generator | None = None,  # for the noise draw (determinism)
    ) -> Tensor:  # [..., H, W, 3] display image (in [0, 1] when config.clamp)
        """Ground-truth capture: scale, vignette, WB, clip at full well, noise, response, quantise.

        An effect switched on in the config needs its argument (ValueError otherwise); an effect
        switched off ignores it. Noise follows `PoissonGaussianNoise` at ``gain``.
        """
        cfg = self.config
        if cfg.response == "authors_srgb22":
            raise ValueError("config.response: 'authors_srgb22' is not a monotone response; simulate with 'gamma' or 'srgb'")
        _check_image(irradiance_linear, "irradiance_linear")
        x = irradiance_linear
        per_image_gain = _per_image(gain, x, "gain", positive=True)
        if cfg.exposure_gain:
            x = x * (
                _per_image(exposure_s, x, "exposure_s", positive=False)
                * per_image_gain
                * _per_image(sensitivity, x, "sensitivity", positive=True)
            )
        x = x * self._shading(x, vignette, white_balance)
        if cfg.clamp:
            x = x.clamp(0.0, 1.0)  # full well
        if cfg.noise:
            if noise is None:
                raise ValueError("noise: config.noise is on, so a PoissonGaussianNoise is required")
            x = noise.sample(x, per_image_gain, generator)
        y = self.response.encode(x)
        if cfg.clamp:
            y = y.clamp(0.0, 1.0)
        if cfg.quantise_bits is not None:
            y = quantise(y, cfg.quantise_bits)
        return y

    def _shading(self, image: Tensor, vignette, white_balance) -> Tensor:
        """Product of the switched-on multiplicative factors (vignette [H, W], white balance [3]),
        broadcastable against ``image`` [..., H, W, 3]; 1 when both are off."""
        cfg = self.config
        factor = torch.ones((), dtype=image.dtype, device=image.device)
        if cfg.vignette:
            if vignette is None:
                raise ValueError("vignette: config.vignette is on, so a [H, W] lens-shading map is required")
            factor = factor * _check_map(vignette, image)
        if cfg.white_balance:
            if white_balance is None:
                raise ValueError("white_balance: config.white_balance is on, so per-channel gains [3] are required")
            factor = factor * _check_wb(white_balance, image)
        return factor

    def predict(
        self,
        scene_colour: Tensor,  # [..., H, W, 3] rasterized colour (gamma-compressed if scene_gamma)
        *,
        scale_k: float | Tensor = 1.0,  # per-frame normaliser k (exposure_gain_normaliser), scalar or [...]
        vignette: Tensor | None = None,  # [H, W] lens shading
        scene_gamma: bool = True,  # True: scene colour holds phi^-1(irradiance); False: linear radiance
        white_balance: Tensor | Sequence[float] | None = None,  # [3] (or [..., 3]) when config.white_balance
    ) -> Tensor:  # [..., H, W, 3] predicted display image
        """Trainer path (authors' code): image = encode(decode(x) * k * V), RGB clamped to [0, 1].

        With scene_gamma=False the colour is linear: image = encode(x * k * V). Noise and
        quantisation are never applied here. Differentiable (zero gradient where clamped). With
        `GammaResponse` on the CPU this is `gamma_exposure.gamma_expose` (these torch ops its oracle).
        """
        cfg = self.config
        _check_image(scene_colour, "scene_colour")
        scale = torch.ones((), dtype=scene_colour.dtype, device=scene_colour.device)
        if cfg.exposure_gain:
            scale = scale * _per_image(scale_k, scene_colour, "scale_k", positive=True)
        scale = scale * self._shading(scene_colour, vignette, white_balance)
        if isinstance(self.response, GammaResponse):
            if compiled_exposure_applies(scene_colour, scale):  # one compiled pass on the CPU
                return gamma_expose(scene_colour, scale, self.response.gamma, self.response.toe_linear,
                                    decode=scene_gamma, clamp=cfg.clamp)
        image = self._expose(scene_colour, scale, scene_gamma)
        return image.clamp(0.0, 1.0) if cfg.clamp else image

    def _expose(self, scene_colour: Tensor, scale: Tensor, scene_gamma: bool) -> Tensor:
        """encode(decode(x) * scale) (scene gamma) or encode(x * scale) (linear scene colour)."""
        if isinstance(self.response, AuthorsSRGB22Response):
            if not scene_gamma:
                raise ValueError(
                    "scene_gamma: the 'authors_srgb22' response is defined for gamma-space scene colour only; "
                    "use response='gamma' for the no-scene-gamma ablation"
                )
            return self.response.expose(scene_colour, scale)
        lin = self.response.decode(scene_colour) if scene_gamma else scene_colour
        return self.response.encode(lin * scale)

    def virtual_gain(
        self,
        scene_colour: Tensor,  # [..., H, W, 3]
        factor: float,  # virtual gain multiplier (paper teaser: 3)
        *,
        scale_k: float | Tensor = 1.0,
        scene_gamma: bool = True,
        vignette: Tensor | None = None,  # None: render through an ideal (shading-free) lens
    ) -> Tensor:  # [..., H, W, 3]
        """Re-render at ``factor`` x gain: encode(decode(x) * k * factor [* V]), clamped to [0, 1].

        The exposure/gain and vignette switches of the config do not apply here (k and V as given).
        """
        _check_values(factor, "factor", positive=True)
        _check_image(scene_colour, "scene_colour")
        scale = _per_image(scale_k, scene_colour, "scale_k", positive=True) * float(factor)
        if vignette is not None:
            scale = scale * _check_map(vignette, scene_colour)
        return self._expose(scene_colour, scale, scene_gamma).clamp(0.0, 1.0)
