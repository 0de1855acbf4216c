"""The model transfer function (egobench.analysis.fidelity) against analytic cases: identity, Gaussian blur,
a one-pixel shift, unrelated content."""

from __future__ import annotations

import math

import numpy as np
import pytest

from egobench.analysis.fidelity import transfer_function


def _noise_images(n: int, size: int = 128, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.random((size, size, 3)) for _ in range(n)]


def _blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Periodic Gaussian blur by multiplication in the Fourier domain: transfer exp(-2 pi^2 s^2 f^2)."""
    fy, fx = np.fft.fftfreq(image.shape[0]), np.fft.fftfreq(image.shape[1])
    h = np.exp(-2 * math.pi ** 2 * sigma_px ** 2 * (fy[:, None] ** 2 + fx[None, :] ** 2))
    return np.stack([np.fft.ifft2(np.fft.fft2(image[..., c]) * h).real for c in range(3)], -1)


def test_identical_images_transfer_everything():
    caps = _noise_images(3)
    t = transfer_function(caps, caps)
    np.testing.assert_allclose(t.transfer, 1.0, atol=1e-12)
    assert t.resolved_wavelength_px == 2.0


@pytest.mark.parametrize("sigma_px", [1.0, 2.0])
def test_gaussian_blur_gives_its_analytic_transfer_and_mtf50(sigma_px):
    caps = _noise_images(4, seed=1)
    t = transfer_function([_blur(c, sigma_px) for c in caps], caps)
    expected = np.exp(-2 * math.pi ** 2 * sigma_px ** 2 * t.freq_cyc_px ** 2)
    np.testing.assert_allclose(t.transfer, expected, atol=0.04)
    mtf50_wavelength = 1 / (math.sqrt(math.log(2) / 2) / (math.pi * sigma_px))  # 5.34 sigma
    assert t.resolved_wavelength_px == pytest.approx(mtf50_wavelength, rel=0.05)


def test_a_one_pixel_shift_gives_the_bessel_transfer():
    """A shift of d px along x: the ring average of cos(2 pi f_x d) is J0(2 pi f d); J0 = 1/2 at
    2 pi f d = 1.5211, so the resolved wavelength is 2 pi d / 1.5211 = 4.13 px."""
    caps = _noise_images(4, seed=2)
    t = transfer_function([np.roll(c, 1, axis=1) for c in caps], caps)
    j0 = np.array([np.mean(np.cos(2 * math.pi * f * np.cos(np.linspace(0, 2 * math.pi, 4000)))) for f in t.freq_cyc_px])
    np.testing.assert_allclose(t.transfer, j0, atol=0.06)
    assert t.resolved_wavelength_px == pytest.approx(2 * math.pi / 1.5211, rel=0.06)


def test_unrelated_content_transfers_nothing_and_the_mask_is_checked():
    caps, other = _noise_images(6, seed=3), _noise_images(6, seed=4)
    t = transfer_function(other, caps, mask=np.ones((128, 128), bool))
    assert np.abs(t.transfer).max() < 0.1
    assert t.resolved_wavelength_px == pytest.approx(1 / t.freq_cyc_px[0])
    with pytest.raises(ValueError, match="mask: expected shape"):
        transfer_function(other, caps, mask=np.ones((64, 64), bool))
