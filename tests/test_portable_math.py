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
