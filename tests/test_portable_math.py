"""egobench.portable_math: glibc's elementary functions element by element (bits that do not follow numpy's
vector code paths)."""

import math

import numpy as np
import pytest

from egobench import portable_math as pm


def test_each_value_is_pythons_math_and_the_shape_broadcasts():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 5)) * 3
    y, p = rng.normal(size=(1, 5)), np.abs(x) + 1e-3
    e, lg, a = pm.exp(x), pm.log(p), pm.arctan2(y, x)
    assert e.shape == lg.shape == a.shape == (4, 5) and e.dtype == np.float64
    for i, j in np.ndindex(4, 5):
        assert e[i, j] == math.exp(x[i, j]) and lg[i, j] == math.log(p[i, j])
        assert a[i, j] == math.atan2(y[0, j], x[i, j])
    # the same functions as numpy's, to its accuracy (a few units in the last place at most)
    np.testing.assert_allclose(e, np.exp(x), rtol=4e-16)
    np.testing.assert_allclose(lg, np.log(p), rtol=4e-16, atol=1e-300)
    np.testing.assert_allclose(a, np.arctan2(y, x), rtol=4e-16)
    assert pm.exp(0.5).shape == () and float(pm.exp(0.5)) == math.exp(0.5)
    assert pm.exp([]).shape == (0,)


def test_log_of_a_non_positive_value_is_refused():
    with pytest.raises(ValueError, match="math domain error"):
        pm.log([1.0, 0.0])


def test_convolve_valid_is_numpys_valid_convolution_summed_in_a_fixed_order():
    rng = np.random.default_rng(5)
    x, k = rng.normal(size=301), rng.normal(size=17)
    out = pm.convolve_valid(x, k)
    np.testing.assert_allclose(out, np.convolve(x, k, mode="valid"), rtol=0, atol=1e-13)
    # taps added one after another: exactly this loop, whatever the machine
    ref = np.zeros(285)
    for m in range(17):
        ref += k[16 - m] * x[m:m + 285]
    assert np.array_equal(out, ref)
    assert np.array_equal(pm.convolve_valid([1.0, 2.0, 3.0], [1.0]), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="1 <= K <= N"):
        pm.convolve_valid(np.ones(3), np.ones(4))


def test_matmul_dot_and_norm_agree_with_numpy_and_sum_in_index_order():
    """matmul/dot/norm equal numpy's BLAS results to rounding; on integers (exact in float64) bit for bit; matmul
    adds its K products in index order (checked where another order rounds differently); bad shapes are named."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 3, 4)), rng.normal(size=(5, 4, 2))
    np.testing.assert_allclose(pm.matmul(a, b), a @ b, rtol=1e-13, atol=1e-15)
    ia, ib = rng.integers(-9, 9, (3, 4)).astype(float), rng.integers(-9, 9, (4, 3)).astype(float)
    assert np.array_equal(pm.matmul(ia, ib), ia @ ib)
    # (1e16 + 1) - 1e16: left to right 1e16 + 1 rounds to 1e16, so the sum is 0 (a pairwise or reversed order gives 1)
    row, col = np.array([[1e16, 1.0, -1e16]]), np.ones((3, 1))
    assert pm.matmul(row, col)[0, 0] == 0.0
    v, w = rng.normal(size=7), rng.normal(size=7)
    assert pm.dot(v, w) == pytest.approx(float(v @ w), rel=1e-13)
    assert pm.dot([1e16, 1.0, -1e16], [1.0, 1.0, 1.0]) == 1.0  # exact sum (fsum), whatever the order
    assert pm.norm([3.0, 4.0, 12.0]) == 13.0 and pm.norm(v) == pytest.approx(float(np.linalg.norm(v)), rel=1e-14)
    with pytest.raises(ValueError, match="matmul"):
        pm.matmul(a, a)
    with pytest.raises(ValueError, match="dot"):
        pm.dot(v, w[:3])


def test_tensor_functions_are_correctly_rounded_or_glibcs_on_float64_cpu_tensors():
    """torch's CPU sqrt is MKL's vector math (about 1 % of float64 roots off IEEE's, other ones on Intel than on
    AMD): on 10^5 values it would differ from Python's correctly rounded `math.sqrt` somewhere."""
    import torch

    rng = np.random.default_rng(5)
    x = torch.from_numpy(rng.random(100_000) * 7)
    y = torch.from_numpy(rng.normal(size=100_000))
    root, s, c, a = pm.sqrt(x), pm.sin(y), pm.cos(y), pm.atan2(y, x - 3.5)
    assert root.dtype == s.dtype == a.dtype == torch.float64
    assert root.tolist() == [math.sqrt(v) for v in x.tolist()]
    assert a.tolist() == [math.atan2(p, q) for p, q in zip(y.tolist(), (x - 3.5).tolist())]
    assert s.tolist() == np.sin(y.numpy()).tolist() and c.tolist() == np.cos(y.numpy()).tolist()
    np.testing.assert_allclose(s.numpy(), [math.sin(v) for v in y.tolist()], rtol=0, atol=2e-16)
    # float32 and broadcast operands
    assert pm.sqrt(x.float()).dtype == torch.float32
    assert pm.atan2(y[:3, None], x[None, :2]).shape == (3, 2)


def test_tensor_functions_differentiate_as_torchs():
    import torch

    x = torch.tensor([0.3, 1.7, 4.0], dtype=torch.float64, requires_grad=True)
    y = torch.tensor([-0.4, 0.9, 2.2], dtype=torch.float64, requires_grad=True)
    for f in (pm.sqrt, pm.sin, pm.cos):
        assert torch.autograd.gradcheck(f, (x,))
    assert torch.autograd.gradcheck(pm.atan2, (y, x))
