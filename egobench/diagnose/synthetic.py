"""Hidden-effect cases on an analytic moving texture: fast, exactly controlled test data for the
statistics (the "ground-truth prediction" path of issue 6 without running the full simulator).

A band-limited log-normal colour texture T(x) is seen by a rolling-shutter camera whose image
motion is a per-frame affine velocity field v_f(u) (translation + rotation + zoom, px/s); the
image of frame f at time t is I_f(u, t) = T(u + o_f - v_f(u) t). Both the measurement and the
model's prediction are produced from the same scene with egobench.model.formation's components
(gamma response, Poisson-Gaussian noise, radial vignette, quantisation); exactly one effect
differs between them. Row times follow docs/architecture.md: t(u) = read_start + R(u) readout,
with the centre-row pose time as the origin of the model's clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from egobench.effects import EFFECTS
from egobench.effects.base import PhotometricTruth
from egobench.model.formation import GammaResponse, PoissonGaussianNoise, quantise, radial_vignette
from egobench.residual.signatures import DiagnosisContext, distortion_profile, radial_coordinates

#: Sensor of the synthetic cases (Aria-like, egobench.sim.devices.ARIA_RGB noise profile).
FULL_WELL_E, READ_NOISE_E = 6000.0, 2.0
#: Readout the model assumes (Aria full-sensor readout, docs/paper-notes.md §2), s.
READOUT_S = 16.26e-3
#: Lens shading the model knows about (present in measurement and prediction).
MODELLED_VIGNETTE = 0.3


@dataclass
class HiddenCase:
    """Measured and predicted stacks with exactly one hidden effect (or none)."""

    measured: np.ndarray  # [F, H, W, 3] display, 8-bit quantised, noisy
    predicted: np.ndarray  # [F, H, W, 3] display, the model's noiseless prediction
    context: DiagnosisContext
    effect: str | None  # hidden effect name (None: nothing hidden)
    value: object  # hidden value (effects.EFFECTS[effect].parameter)
    affected_frames: list[int]  # exposure_metadata: frames whose metadata is wrong


def _texture(rng: np.random.Generator, n_components: int = 14):
    """A band-limited random colour texture: (x [..., 2] px) -> linear irradiance [..., 3]."""
    lam = rng.uniform(7.0, 26.0, n_components)  # wavelengths, px
    ang = rng.uniform(0, 2 * math.pi, n_components)
    k = np.stack([np.cos(ang), np.sin(ang)], 1) * (2 * math.pi / lam)[:, None]  # [K, 2]
    phase = rng.uniform(0, 2 * math.pi, n_components)
    amp_shared = rng.normal(0.0, 0.42, n_components)
    amp_colour = rng.normal(0.0, 0.15, (n_components, 3))
    base = np.log(np.array([0.16, 0.2, 0.14]) * rng.uniform(0.8, 1.2, 3))

    def evaluate(x: np.ndarray) -> np.ndarray:
        s = np.sin(x @ k.T + phase)  # [..., K]
        return np.exp(base + (s * amp_shared) @ np.ones((n_components, 1)) * np.ones(3) + s @ amp_colour)

    return evaluate


def _image_motion(rng: np.random.Generator, rel: np.ndarray, F: int,
                  speed_px_s: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame affine image velocity [F, H, W, 2] px/s (translation + rotation + zoom about the
    centre; rel [H, W, 2] pixel offsets from it) and texture offsets [F, 2] px."""
    speed = rng.uniform(*speed_px_s, F)
    heading = rng.uniform(0, 2 * math.pi, F)
    trans = np.stack([np.cos(heading), np.sin(heading)], 1) * speed[:, None]
    omega = rng.uniform(-1.5, 1.5, F)
    zoom = rng.uniform(-0.5, 0.5, F)
    rot = np.stack([-rel[..., 1], rel[..., 0]], -1)
    vel = trans[:, None, None, :] + omega[:, None, None, None] * rot[None] + zoom[:, None, None, None] * rel[None]
    return vel, rng.uniform(-500, 500, (F, 2))


def _exposure_scales(rng: np.random.Generator, F: int, effect: str | None, value, metadata_fraction: float,
                     fixed: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """(true exposure x gain scale [F], analog gain [F], recorded scale [F], frames whose metadata is
    wrong): the hidden effect may change the recorded scales (`Effect.synth_exposure`)."""
    k_true = rng.uniform(0.7, 1.4, F)
    gain = rng.uniform(1.0, 4.0, F)
    if fixed:
        k_true, gain = np.ones(F), np.full(F, 2.0)
    k_recorded = k_true.copy()
    affected = [] if effect is None else EFFECTS[effect].synth_exposure(k_recorded, rng, value, metadata_fraction)
    return k_true, gain, k_recorded, affected


def _row_times(R: np.ndarray, effect: str | None, value) -> tuple[np.ndarray, np.ndarray]:
    """Row times (model [H, W], true [H, W]) in s from the frame's pose time, R [H, W] the row time ratio."""
    t_model = (R - 0.5) * READOUT_S  # centre row at the frame's pose time
    t_true = t_model.copy() if effect is None else EFFECTS[effect].synth_row_times(t_model, R, value, READOUT_S)
    return t_model, t_true


def _photometric_truth(effect: str | None, value, H: int, W: int, gamma_assumed: float):
    """(modelled vignette [H, W], true vignette [H, W], true white balance [3], true noise, true gamma)."""
    vig_model = radial_vignette((H, W), MODELLED_VIGNETTE).numpy().astype(np.float64)
    truth = PhotometricTruth(vig_model.copy(), np.ones(3), PoissonGaussianNoise(FULL_WELL_E, READ_NOISE_E), gamma_assumed)
    if effect is not None:
        EFFECTS[effect].synth_photometric(truth, value, (H, W))
    return vig_model, truth.vignette, truth.white_balance, truth.noise, truth.gamma


def make_case(
    effect: str | None,
    value=None,
    seed: int = 0,
    size: int = 48,
    n_frames: int = 16,
    speed_px_s: tuple[float, float] = (80.0, 250.0),
    gamma_assumed: float = 2.2,
    metadata_fraction: float = 0.25,
    fixed_exposure: bool = False,
) -> HiddenCase:
    """One hidden-effect case; ``value`` None draws it (seeded) from the effect's plausible range.
    ``fixed_exposure``: every frame exposed alike at one gain (a lab or a fixed-exposure capture)."""
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"effect: expected one of {list(EFFECTS)} or None, got {effect!r}")
    if size < 16 or n_frames < 9:
        raise ValueError(f"size/n_frames: expected size >= 16 and n_frames >= 9, got {size}, {n_frames}")
    rng = np.random.default_rng([int(seed), 7919])
    if effect is not None and value is None:
        value = EFFECTS[effect].sample_hidden(np.random.default_rng([int(seed), 104729]))
    H = W = int(size)
    F = int(n_frames)
    cx = cy = (W - 1) / 2.0
    focal = 0.5 * W
    tex = _texture(rng)
    v_img, u_img = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    rel = np.stack([u_img - cx, v_img - cy], -1)  # [H, W, 2]
    R = v_img / (H - 1)  # row time ratio (identity rectification)
    vel, offsets = _image_motion(rng, rel, F, speed_px_s)
    # exposure * gain normaliser the model uses (recorded), true scale, gains for noise
    k_true, gain, k_recorded, affected = _exposure_scales(rng, F, effect, value, metadata_fraction, fixed_exposure)
    t_model, t_true = _row_times(R, effect, value)
    def radial_field(k0_change: float) -> np.ndarray:  # [H, W, 2] px: the displacement of a change of k0
        radius, direction, _ = radial_coordinates(H, W, (cx, cy))
        return k0_change * distortion_profile(radius, focal, None)[..., None] * direction

    disp = None if effect is None else EFFECTS[effect].synth_displacement(value, radial_field)
    disp_true = np.zeros((H, W, 2)) if disp is None else disp

    def image(t: np.ndarray, extra_disp: np.ndarray) -> np.ndarray:  # [F, H, W, 3] linear texture
        x = (np.stack([u_img, v_img], -1) - extra_disp)[None] + offsets[:, None, None, :] - vel * t[None, :, :, None]
        return tex(x)

    irr_true = image(t_true, disp_true) if effect is None else EFFECTS[effect].synth_irradiance(image, t_true, disp_true, value)
    irr_model = image(t_model, np.zeros((H, W, 2)))
    vig_model, vig_true, wb, noise_true, gamma_true = _photometric_truth(effect, value, H, W, gamma_assumed)

    lin_true = np.clip(irr_true * k_true[:, None, None, None] * vig_true[None, :, :, None] * wb, 0.0, 1.0)
    gen = torch.Generator().manual_seed(int(seed) * 1000 + 17)
    g_t = torch.from_numpy(gain)[:, None, None, None]
    noisy = noise_true.sample(torch.from_numpy(lin_true), g_t, generator=gen)
    measured = quantise(GammaResponse(gamma_true).encode(noisy).clamp(0, 1), 8).numpy()
    lin_model = np.clip(irr_model * k_recorded[:, None, None, None] * vig_model[None, :, :, None], 0.0, 1.0)
    predicted = GammaResponse(gamma_assumed).encode(torch.from_numpy(lin_model)).clamp(0, 1).numpy()

    ctx = DiagnosisContext(
        frame_index=np.arange(F), exposure_s=np.full(F, 2e-3) * k_recorded / gain, gain=gain,
        valid=np.ones((H, W), bool), row_time_ratio=R, principal_point=(cx, cy), focal_px=focal,
        readout_s=READOUT_S, pixel_velocity_px_s=vel.astype(np.float32), gamma_assumed=gamma_assumed,
        noise_shot=gain / FULL_WELL_E, noise_read=(gain * READ_NOISE_E / FULL_WELL_E) ** 2,
        meta={"source": "synthetic texture", "hidden_effect": effect, "hidden_value": value, "seed": int(seed)},
    )
    return HiddenCase(measured.astype(np.float32), predicted.astype(np.float32), ctx, effect, value, affected)
