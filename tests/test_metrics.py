"""Tests of egobench.metrics: analytic values and scikit-image as an independent reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from egobench.metrics import (
    PSNR_MAX_DB,
    depth_si_l1,
    lpips_available,
    normal_cos,
    normal_l1,
    psnr,
    ssim,
    ssim_loss,
)

SK = dict(channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)


def _structured(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.stack([u / w, v / h, ((u // 6 + v // 6) % 2) * 0.8 + 0.1], axis=-1)
    img[10:30, 20:40] = [0.9, 0.2, 0.5]
    noisy = np.clip(img + 0.05 * rng.standard_normal(img.shape), 0, 1)
    return img, noisy


# ----------------------------------------------------------------------------- PSNR
@pytest.mark.parametrize("offset", [0.1, 0.01, 0.25])
def test_psnr_constant_offset_is_analytic(offset):
    rng = np.random.default_rng(0)
    target = rng.random((20, 30, 3)) * 0.5
    assert psnr(target + offset, target) == pytest.approx(-20 * math.log10(offset), abs=1e-9)
    assert psnr(torch.from_numpy(target - offset).float(), torch.from_numpy(target).float()) == pytest.approx(
        -20 * math.log10(offset), abs=1e-4
    )


def test_psnr_respects_mask():
    target = np.full((10, 12, 3), 0.5)
    pred = target.copy()
    pred[:, :6] += 0.2  # left half wrong by 0.2
    pred[:, 6:] += 0.05  # right half wrong by 0.05
    mask = np.zeros((10, 12), bool)
    mask[:, 6:] = True
    assert psnr(pred, target, mask) == pytest.approx(-20 * math.log10(0.05))
    assert psnr(pred, target, ~mask) == pytest.approx(-20 * math.log10(0.2))
    assert psnr(pred, target) == pytest.approx(-10 * math.log10((0.04 + 0.0025) / 2))
    assert psnr(target, target) == PSNR_MAX_DB
    with pytest.raises(ValueError, match="mask"):
        psnr(pred, target, np.zeros((10, 12), bool))
    with pytest.raises(ValueError, match="mask"):
        psnr(pred, target, np.ones((12, 10), bool))
    with pytest.raises(ValueError, match="pred, target"):
        psnr(pred, target[:5])


# ----------------------------------------------------------------------------- SSIM
def test_ssim_matches_scikit_image_random_and_structured():
    rng = np.random.default_rng(1)
    a = rng.random((40, 52, 3))
    b = np.clip(a + 0.15 * rng.standard_normal(a.shape), 0, 1)
    assert ssim(a, b) == pytest.approx(structural_similarity(a, b, **SK), abs=1e-6)
    img, noisy = _structured()
    assert ssim(noisy, img) == pytest.approx(structural_similarity(noisy, img, **SK), abs=1e-6)
    blurred = img.copy()
    blurred[1:-1] = (img[:-2] + img[1:-1] + img[2:]) / 3
    ref = structural_similarity(blurred, img, **SK)
    assert ssim(blurred, img) == pytest.approx(ref, abs=1e-6)
    # float32 torch input agrees to the brief's tolerance
    assert ssim(torch.from_numpy(blurred).float(), torch.from_numpy(img).float()) == pytest.approx(ref, abs=1e-3)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    # a different convention (uniform 7x7 window) gives a measurably different value
    assert abs(structural_similarity(noisy, img, channel_axis=-1, data_range=1.0) - ssim(noisy, img)) > 1e-3


def test_ssim_mask_averages_the_map_over_masked_centres():
    img, noisy = _structured(seed=2)
    _, full = structural_similarity(noisy, img, full=True, **SK)  # full map [H, W, 3]
    mask = np.zeros(img.shape[:2], bool)
    mask[8:30, 10:50] = True
    ref = full[mask].mean()
    assert ssim(noisy, img, mask) == pytest.approx(ref, abs=1e-6)
    assert ssim(noisy, img, np.ones(img.shape[:2], bool)) == pytest.approx(ssim(noisy, img), abs=1e-12)
    border_only = np.zeros(img.shape[:2], bool)
    border_only[:3] = True
    with pytest.raises(ValueError, match="mask"):
        ssim(noisy, img, border_only)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(noisy[:8], img[:8])


def test_ssim_loss_gradient_finite_differences():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(1, 12, 13, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(1, 12, 13, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: ssim_loss(p, target), (pred,), eps=1e-6, atol=1e-6)
    loss = ssim_loss(pred, target)
    assert float(loss.detach()) == pytest.approx(1 - ssim(pred[0].detach(), target[0]), abs=1e-12)
    batch = torch.rand(2, 16, 16, 3, generator=g)
    assert float(ssim_loss(batch, batch)) == pytest.approx(0.0, abs=1e-5)


# ----------------------------------------------------------------------------- geometry
def test_depth_si_l1_scale_invariant_and_analytic():
    rng = np.random.default_rng(3)
    gt = 0.5 + 2 * rng.random((20, 25))
    pred = gt * (1 + 0.05 * rng.standard_normal(gt.shape))
    base = depth_si_l1(pred, gt)
    assert base > 0
    for scale in (0.1, 3.7, 1000.0):
        assert depth_si_l1(pred * scale, gt) == pytest.approx(base, rel=1e-10)
    assert depth_si_l1(4.0 * gt, gt) == pytest.approx(0.0, abs=1e-12)
    # gt = 1 everywhere, pred = [1, 1, 1, 2] * 5: median scale 1/5, errors [0, 0, 0, 1]
    assert depth_si_l1(5 * np.array([[1.0, 1.0], [1.0, 2.0]]), np.ones((2, 2))) == pytest.approx(0.25)
    mask = np.array([[True, True], [True, False]])
    assert depth_si_l1(np.array([[1.0, 1.0], [1.0, 9.0]]), np.ones((2, 2)), mask) == pytest.approx(0.0)
    # invalid (zero) ground truth pixels are excluded
    gt0 = np.ones((2, 2))
    gt0[1, 1] = 0
    assert depth_si_l1(np.array([[1.0, 1.0], [1.0, 9.0]]), gt0) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="mask"):
        depth_si_l1(np.ones((2, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="pred_depth, gt_depth"):
        depth_si_l1(np.ones((2, 2)), np.ones((3, 2)))


def test_normal_l1_and_cos_analytic():
    def field(n):
        return np.broadcast_to(np.asarray(n, float), (4, 5, 3)).copy()

    x, y = field([1, 0, 0]), field([0, 1, 0])
    assert normal_l1(x, y) == pytest.approx(2.0)
    assert normal_cos(x, y) == pytest.approx(1.0)
    assert normal_l1(x, -x) == pytest.approx(2.0) and normal_cos(x, -x) == pytest.approx(2.0)
    assert normal_l1(3 * x, x) == pytest.approx(0.0)  # inputs are normalised first
    diag = field([1, 1, 0])
    assert normal_l1(x, diag) == pytest.approx(1.0)  # |1 - 0.707| + |0 - 0.707| + 0
    assert normal_cos(x, diag) == pytest.approx(1 - 1 / math.sqrt(2))
    mixed = x.copy()
    mixed[:2] = y[:2]
    mask = np.zeros((4, 5), bool)
    mask[2:] = True
    assert normal_l1(mixed, x, mask) == pytest.approx(0.0)
    assert normal_l1(mixed, x) == pytest.approx(1.0)  # half the pixels at 2
    zero = np.zeros((4, 5, 3))
    with pytest.raises(ValueError, match="mask"):
        normal_l1(zero, x)


def test_lpips_available_reports_reason():
    ok, reason = lpips_available()
    assert isinstance(ok, bool) and isinstance(reason, str)
    if not ok:
        assert reason.startswith("not available: ")


# ------------------------------------------------------------------------------------- the authors' geometry metrics
def test_authors_mask_erosion_is_5x5():
    from egobench.metrics import erode_mask_authors

    mask = np.zeros((12, 12), bool)
    mask[3:9, 3:9] = True  # a 6 x 6 block loses 2 px on each side
    eroded = erode_mask_authors(mask).numpy()
    expected = np.zeros((12, 12), bool)
    expected[5:7, 5:7] = True
    np.testing.assert_array_equal(eroded, expected)


def test_authors_depth_error_hand_computed():
    from egobench.metrics import depth_mse_authors

    gt = np.ones((9, 9))
    gt[:, 5:] = 3.0  # min-max normalised: 0 left, 1 right
    mask = np.ones((9, 9), bool)
    # a constant prediction normalises to zeros: the authors then take pred = 1, the scale is mean(gt),
    # and the error is the variance of the normalised gt over the mask (the full frame: erosion keeps it)
    frac = 36 / 81
    assert depth_mse_authors(np.full((9, 9), 2.0), gt, mask) == pytest.approx(frac * (1 - frac), abs=1e-12)
    # any affine map of the truth is scored 0 (min-max normalisation, then scale)
    assert depth_mse_authors(5.0 * gt + 1.0, gt, mask) == pytest.approx(0.0, abs=1e-15)


def test_authors_depth_error_against_a_transcription_of_their_formula():
    """utils/eval.py with the renderer's 8-bit depth PNGs, written out step by step with numpy/cv2
    (uint8 cast, float64 mask erosion, least-squares scale, masked MSE)."""
    import cv2

    from egobench.metrics import depth_mse_authors

    rng = np.random.default_rng(1)
    gt = rng.uniform(1.0, 4.0, (24, 24))
    pred = gt * 1.7 + rng.normal(0, 0.2, gt.shape)
    mask = np.zeros((24, 24), bool)
    mask[2:20, 4:23] = True

    def png(d):
        return ((d - d.min()) / (d.max() - d.min()) * 255).astype(np.uint8) / 255.0

    p, g = png(pred), png(gt)
    m = cv2.erode(mask.astype(np.float64), np.ones((5, 5), np.uint8)) > 0.5
    s = (g[m] * p[m]).sum() / (p[m] ** 2).sum()
    expected = (((s * p - g) ** 2) * m).sum() / m.sum()
    assert depth_mse_authors(pred, gt, mask) == pytest.approx(expected, rel=1e-12)


def test_authors_normal_error_hand_computed():
    from egobench.metrics import normal_cos_authors

    n = np.zeros((7, 7, 3))
    n[..., 2] = -1.0  # facing the camera: 8-bit (127, 127, 0) -> (-1/255, -1/255, -1)
    mask = np.ones((7, 7), bool)
    # identical normals score -2/255^2 (the 8-bit round trip is not renormalised), not 0
    assert normal_cos_authors(n, n, mask) == pytest.approx(-2 / 255**2, abs=1e-15)
    # no predicted normal (zeros) scores 1 - 1/255 - 2/255^2
    assert normal_cos_authors(np.zeros_like(n), n, mask) == pytest.approx(1 - 1 / 255 - 2 / 255**2, abs=1e-15)
    flipped = -n
    assert normal_cos_authors(flipped, n, mask) == pytest.approx(2.0, abs=0.01)
    with pytest.raises(ValueError, match="empty after the authors' 5 x 5 erosion"):
        normal_cos_authors(n, n, np.eye(7, dtype=bool))
