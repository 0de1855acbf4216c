"""The compiled photometric training loss (0.8 L1 + 0.2 (1 - SSIM)) against its torch oracle (value and
gradient), finite differences, its optimum, and its bits on one and two threads."""

import numba
import numpy as np
import pytest
import torch

from egobench.host import RASTER_THREADS_ENV
from egobench.train.photometric import ROWS_PER_TASK, photometric_loss, photometric_loss_torch


def _inputs(dtype, H=23, W=31, C=3, masked=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(H, W, C, generator=g, dtype=torch.float64).to(dtype)
    gt = (0.6 * pred.double() + 0.4 * torch.rand(H, W, C, generator=g, dtype=torch.float64)).to(dtype)
    mask3 = torch.ones(H, W, 1, dtype=dtype)
    if masked:  # an invalid band and a corner, as the rectified frames' borders
        mask3[:4] = 0.0
        mask3[-6:, -5:] = 0.0
    return pred, gt, mask3, float(mask3.sum()) * C


def _value_and_grad(fn, pred, gt, mask3, n_mask, lam):
    p = pred.clone().requires_grad_(True)
    loss = fn(p, gt, mask3, n_mask, lam)
    (grad,) = torch.autograd.grad(loss, p)
    return loss.detach(), grad


@pytest.mark.parametrize("lam", [0.0, 0.2, 1.0])
@pytest.mark.parametrize("masked", [False, True])
def test_compiled_loss_matches_the_torch_oracle_in_float64(lam, masked):
    args = _inputs(torch.float64, masked=masked)
    ref_value, ref_grad = _value_and_grad(photometric_loss_torch, *args, lam)
    value, grad = _value_and_grad(photometric_loss, *args, lam)
    assert float(ref_value) > 0.05  # far from the optimum: every term carries weight
    torch.testing.assert_close(value, ref_value, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-10, atol=1e-12 * float(ref_grad.abs().max()))
    if masked:  # the invalid pixels get no gradient
        assert float(grad[:4].abs().max()) == 0.0


def test_compiled_loss_in_float32_keeps_dtype_and_value():
    args64 = _inputs(torch.float64, H=40, W=37, seed=1)
    args32 = tuple(a.float() if torch.is_tensor(a) else a for a in args64)
    ref_value, ref_grad = _value_and_grad(photometric_loss_torch, *args64, 0.2)
    value, grad = _value_and_grad(photometric_loss, *args32, 0.2)
    assert value.dtype == grad.dtype == torch.float32
    torch.testing.assert_close(value.double(), ref_value, rtol=1e-6, atol=0.0)
    torch.testing.assert_close(grad.double(), ref_grad, rtol=0.0, atol=1e-5 * float(ref_grad.abs().max()))


def test_compiled_loss_gradient_matches_finite_differences():
    pred, gt, mask3, n_mask = _inputs(torch.float64, H=13, W=14, C=2, seed=2)
    assert float((pred - gt).abs().min()) > 1e-4  # away from L1's kink
    pred.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: photometric_loss(p, gt, mask3, n_mask, 0.3), (pred,))


def test_identical_images_are_the_optimum():
    """pred == gt: L1 = 0 and SSIM = 1 everywhere, a maximum, so the loss and its gradient vanish."""
    pred, _, mask3, n_mask = _inputs(torch.float64, masked=False, seed=3)
    value, grad = _value_and_grad(photometric_loss, pred, pred.clone(), mask3, n_mask, 0.2)
    assert abs(float(value)) < 1e-12
    assert float(grad.abs().max()) < 1e-12


def test_bits_are_the_same_on_one_and_two_threads(monkeypatch):
    """Rows run in parallel in fixed tasks of ROWS_PER_TASK rows, and the sums run in row order."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba's pool has one thread")
    args = _inputs(torch.float32, H=5 * ROWS_PER_TASK + 13, W=29, seed=4)
    results = []
    for threads in ("1", "2"):
        monkeypatch.setenv(RASTER_THREADS_ENV, threads)
        results.append(_value_and_grad(photometric_loss, *args, 0.2))
    (v1, g1), (v2, g2) = results
    assert v1.item() == v2.item()
    assert torch.equal(g1.view(torch.int32), g2.view(torch.int32))


def test_bad_shapes_are_named():
    pred = torch.zeros(12, 12, 3)
    with pytest.raises(ValueError, match="same shape"):
        photometric_loss(pred, torch.zeros(12, 13, 3), torch.ones(12, 12, 1), 432.0, 0.2)
    with pytest.raises(ValueError, match=r"mask3: expected \[H, W, 1\] or \[H, W, C\]"):
        photometric_loss(pred, pred, torch.ones(12, 12), 432.0, 0.2)
    with pytest.raises(ValueError, match="at least 11x11"):
        photometric_loss(torch.zeros(10, 12, 3), torch.zeros(10, 12, 3), torch.ones(10, 12, 1), 360.0, 0.2)


def test_the_kernels_agree_with_the_oracle_on_odd_row_counts():
    """Valid-row counts that are not a multiple of ROWS_PER_TASK (the last task short) against the oracle."""
    for H in (11, 12, 11 + ROWS_PER_TASK + 3):
        args = _inputs(torch.float64, H=H, W=11, C=1, masked=False, seed=H)
        ref_value, ref_grad = _value_and_grad(photometric_loss_torch, *args, 0.5)
        value, grad = _value_and_grad(photometric_loss, *args, 0.5)
        assert np.isclose(float(value), float(ref_value), rtol=1e-12, atol=0.0)
        torch.testing.assert_close(grad, ref_grad, rtol=1e-10, atol=1e-12)
