"""How fine a detail a trained model reproduces: its transfer function against the captured images.

A pixel-scale effect (a rolling-shutter shift of a few pixels, a calibration error of one pixel) can
only cost a model PSNR if the model renders detail at that scale. This module measures the scale:
per radial frequency band f (cycles/px) of the held-out images' luminance,

    T(f) = sum Re(P(k) G*(k)) / sum |G(k)|^2        (sums over the band's frequencies and the frames)

with P the render's and G the captured image's Fourier transform (masked mean removed, Hann window).
T is the model's modulation transfer function measured in the captured image's own content: 1 where
the render reproduces the capture's detail in amplitude and phase, exp(-2 pi^2 sigma^2 f^2) for a
render blurred by a Gaussian of sigma px, cos(2 pi f d) along a shift of d px, 0 for detail the render
lacks or places at random. Sensor noise in the capture counts as detail no model reproduces, so T falls
at frequencies where noise dominates whatever the model.

The **resolved wavelength** is 1 / f50, f50 the lowest frequency where T falls below one half (the
"MTF50" of imaging, in px): a model misregistered by much less than it hardly loses PSNR to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Luminance weights (Rec. 709) applied to the encoded RGB values.
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: Radial bands between 0 and the Nyquist frequency (0.5 cycles/px).
N_BANDS = 16


@dataclass
class Transfer:
    """A model's transfer function against captured images."""

    freq_cyc_px: np.ndarray  # [B] band centres, cycles per pixel
    transfer: np.ndarray  # [B] T(f), see the module docstring
    resolved_wavelength_px: float  # 1 / f50; 2.0 (Nyquist) if T never falls below 0.5
    n_frames: int

    def to_dict(self) -> dict:
        return {"freq_cyc_px": [round(float(f), 4) for f in self.freq_cyc_px],
                "transfer": [round(float(t), 4) for t in self.transfer],
                "resolved_wavelength_px": float(self.resolved_wavelength_px), "n_frames": self.n_frames}


def _luma(image: np.ndarray, name: str) -> np.ndarray:
    """[H, W] or [H, W, 3] -> [H, W] float64."""
    a = np.asarray(image, dtype=np.float64)
    if a.ndim == 3 and a.shape[-1] == 3:
        return a @ LUMA
    if a.ndim == 2:
        return a
    raise ValueError(f"{name}: expected an [H, W] or [H, W, 3] image, got shape {a.shape}")


def _spectrum(image: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """FFT of the image with its weighted mean removed, times the weight (mask x Hann window)."""
    mean = float((image * weight).sum() / max(weight.sum(), 1e-12))
    return np.fft.fft2((image - mean) * weight)


def _band_index(shape: tuple[int, int], n_bands: int) -> np.ndarray:
    """[H, W] radial band of each FFT frequency (n_bands: beyond Nyquist, and the DC term)."""
    fy, fx = np.fft.fftfreq(shape[0]), np.fft.fftfreq(shape[1])
    fr = np.hypot(fy[:, None], fx[None, :])
    band = np.floor(fr / 0.5 * n_bands).astype(np.int64)
    band[0, 0] = n_bands  # the mean is removed; the DC term carries no detail
    return np.minimum(band, n_bands)


def transfer_function(renders: list, captures: list, mask: np.ndarray | None = None,
                      n_bands: int = N_BANDS) -> Transfer:
    """T(f) of renders against captures (lists of [H, W] or [H, W, 3] images of one size, in [0, 1]);
    ``mask`` [H, W] bool: pixels to use (the valid-pixel mask)."""
    if len(renders) != len(captures) or not renders:
        raise ValueError(f"transfer_function: expected as many renders as captures (>= 1), got "
                         f"{len(renders)} and {len(captures)}")
    shape = _luma(captures[0], "captures[0]").shape
    weight = np.outer(np.hanning(shape[0]), np.hanning(shape[1]))
    if mask is not None:
        if np.shape(mask) != shape:
            raise ValueError(f"mask: expected shape {shape}, got {np.shape(mask)}")
        weight = weight * np.asarray(mask, dtype=np.float64)
    band = _band_index(shape, n_bands).ravel()
    cross, power = np.zeros(n_bands + 1), np.zeros(n_bands + 1)
    for i, (r, c) in enumerate(zip(renders, captures)):
        p, g = _luma(r, f"renders[{i}]"), _luma(c, f"captures[{i}]")
        if p.shape != shape or g.shape != shape:
            raise ValueError(f"frame {i}: expected render and capture of shape {shape}, got {p.shape} and {g.shape}")
        P, G = _spectrum(p, weight).ravel(), _spectrum(g, weight).ravel()
        cross += np.bincount(band, weights=(P * G.conj()).real, minlength=n_bands + 1)
        power += np.bincount(band, weights=np.abs(G) ** 2, minlength=n_bands + 1)
    t = cross[:n_bands] / np.maximum(power[:n_bands], 1e-300)
    freq = (np.arange(n_bands) + 0.5) / n_bands * 0.5
    return Transfer(freq_cyc_px=freq, transfer=t, resolved_wavelength_px=_wavelength_at_half(freq, t),
                    n_frames=len(renders))


def _wavelength_at_half(freq: np.ndarray, t: np.ndarray) -> float:
    """1 / f where T first falls below 0.5 (linear between band centres); 2 px if it never does,
    1 / freq[0] if it starts below."""
    below = np.nonzero(t < 0.5)[0]
    if len(below) == 0:
        return 2.0
    i = int(below[0])
    if i == 0:
        return float(1.0 / freq[0])
    f = freq[i - 1] + (t[i - 1] - 0.5) / (t[i - 1] - t[i]) * (freq[i] - freq[i - 1])
    return float(1.0 / f)
