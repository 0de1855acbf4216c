"""Unit tests of egobench.residual.estimation: the data the causes share (`ResidualData`), the photometric cell
regression (`PhotometricFit`), the geometric first-order fit (`GeometricCause`), and the small helpers
(`CauseResult`, `own_term`, `photometric_apply`, `gaussian_lowpass`, `binned_means`).

The cases are small analytic ones (`egobench.diagnose.synthetic.make_case`, 32 px, 9 frames) or hand-made arrays."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.ndimage as ndi
import scipy.stats as sps

from egobench.diagnose.estimators import CAUSES
from egobench.diagnose.synthetic import make_case
from egobench.residual.estimation import (BLOCK_PX, DISPLAY_MAX, DISPLAY_MIN, CauseResult, PhotometricFit, ResidualData,
                                          binned_means, gaussian_lowpass, own_term, photometric_apply)
from egobench.residual.signatures import LEVEL, checkerboard, decode, encode, encode_slope, radial_coordinates

SIZE, FRAMES = 32, 9


def small_case(effect=None, value=None, seed=3):
    return make_case(effect, value, seed=seed, size=SIZE, n_frames=FRAMES)


def data_of(case, ctx=None, **kw) -> ResidualData:
    F = case.measured.shape[0]
    return ResidualData(case.measured, case.predicted, case.context if ctx is None else ctx, np.arange(F), **kw)


def noiseless_ctx(case):
    """The case's context with no assumed sensor noise (the cell weights then come from quantisation only)."""
    return dataclasses.replace(case.context, noise_shot=None, noise_read=None)


def with_linear_factor(predicted: np.ndarray, log_factor: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """Display images whose linear intensity is predicted's times exp(log_factor) (no noise, no quantisation)."""
    return encode(decode(predicted.astype(np.float64), gamma) * np.exp(log_factor), gamma)


# ============================================================================ CauseResult, own_term
def test_cause_result_defaults_and_to_dict_leaves_out_internal_and_plot():
    r = CauseResult("vignette", "photometric", True)
    assert (r.p_value, r.p_adjusted, r.effect_rms, r.significant, r.params) == (1.0, 1.0, 0.0, False, {})
    r.params["corner_attenuation"] = 0.2
    r.internal["a"] = np.array([1.0, 2.0])
    r.plot["binned"] = {"x": [1.0]}
    d = r.to_dict()
    assert "internal" not in d and "plot" not in d
    expected = {f.name for f in dataclasses.fields(CauseResult)} - {"internal", "plot"}
    assert set(d) == expected
    assert d["params"] == {"corner_attenuation": 0.2} and d["name"] == "vignette" and d["testable"] is True


def test_own_term_zeroes_the_global_gain_and_leaves_the_original_untouched():
    a = np.array([-0.2, 0.05])
    r = CauseResult("vignette", "photometric", True, reason="x", statistic=9.0, p_value=1e-4, effect_rms=0.3,
                    params={"k": 1}, internal={"a": a, "log_global": 0.7})
    o = own_term(r)
    assert o.internal["log_global"] == 0.0 and o.internal["a"] is a
    assert r.internal["log_global"] == 0.7  # a copy of the dict, not the result's own
    assert (o.name, o.kind, o.testable) == ("vignette", "photometric", True)
    assert (o.p_value, o.statistic, o.effect_rms, o.params, o.reason) == (1.0, 0.0, 0.0, {}, "")


# ============================================================================ photometric_apply
def test_photometric_apply_scales_linear_intensity_and_clips():
    rng = np.random.default_rng(0)
    pred = rng.uniform(0.05, 0.95, (2, 5, 6, 3))
    lin = decode(pred, 2.2)
    same = photometric_apply(pred, np.zeros((1, 1, 1, 1)), 2.2)
    np.testing.assert_allclose(same, pred, atol=1e-12)  # exp(0): an exact round trip through the response
    out = photometric_apply(pred, np.full((1, 1, 1, 1), math.log(1.5)), 2.2)
    bright = 1.5 * lin >= 1.0
    assert bright.any() and (~bright).any()
    np.testing.assert_allclose(decode(out, 2.2)[~bright], 1.5 * lin[~bright], rtol=1e-10)
    assert np.all(out[bright] == 1.0)  # clipped at white
    # a per-pixel factor broadcasts over frames and channels
    field = np.linspace(-0.3, 0.0, 6)[None, None, :, None] * np.ones((1, 5, 1, 1))
    np.testing.assert_allclose(decode(photometric_apply(pred, field, 2.2), 2.2), lin * np.exp(field), rtol=1e-10)


def test_photometric_apply_power_term_leaves_the_reference_intensity_fixed():
    """linear -> linear * exp(power (log linear - log_p0)): linear^(1 + power) / p0^power, identity at linear = p0."""
    lin = np.array([0.05, 0.1, 0.2, 0.4, 0.7]).reshape(1, 1, 5, 1) * np.ones((1, 1, 1, 3))
    pred = encode(lin, 2.2)
    out = decode(photometric_apply(pred, np.zeros((1, 1, 1, 1)), 2.2, power=0.1, log_p0=math.log(0.2)), 2.2)
    np.testing.assert_allclose(out, lin ** 1.1 / 0.2 ** 0.1, rtol=1e-9)
    np.testing.assert_allclose(out[0, 0, 2], 0.2, rtol=1e-9)
    assert np.all(out[0, 0, :2] < lin[0, 0, :2]) and np.all(out[0, 0, 3:] > lin[0, 0, 3:])


# ============================================================================ gaussian_lowpass
@pytest.mark.parametrize("sigma", [1.0, 1.5])
def test_gaussian_lowpass_matches_scipy_with_edge_replication(sigma):
    """An independent reference: scipy's Gaussian (mode nearest = replicated edge; truncate 4 sigma is OpenCV's
    kernel radius for float images at these sigmas) per frame and channel."""
    rng = np.random.default_rng(1)
    x = rng.uniform(size=(2, 13, 17, 3)).astype(np.float32)
    out = gaussian_lowpass(x, sigma)
    assert out.dtype == np.float64 and out.shape == x.shape
    ref = np.stack([np.stack([ndi.gaussian_filter(x[f, ..., c].astype(np.float64), sigma, mode="nearest", truncate=4.0)
                              for c in range(3)], -1) for f in range(2)])
    np.testing.assert_allclose(out, ref, atol=1e-6)  # float32 input: OpenCV filters it at float64 after the cast


def test_gaussian_lowpass_does_not_mix_frames_or_channels_and_keeps_constants():
    x = np.zeros((3, 11, 11, 3))
    x[1, 5, 5, 2] = 1.0
    out = gaussian_lowpass(x, 1.0)
    assert out[1, ..., 2].sum() == pytest.approx(1.0, abs=1e-12)  # the kernel is normalised, the delta inside
    assert np.all(out[[0, 2]] == 0.0) and np.all(out[1, ..., :2] == 0.0)
    np.testing.assert_allclose(gaussian_lowpass(np.full((1, 7, 9, 3), 0.37), 1.5), 0.37, atol=1e-12)


# ============================================================================ binned_means
def test_binned_means_are_weighted_means_in_quantile_bins():
    x = np.arange(12, dtype=float)  # 3 bins: edges 0, 11/3, 22/3, 11 -> {0..3}, {4..7}, {8..11} (the maximum joins the last)
    y = np.arange(12, dtype=float) ** 2
    w = np.array([1, 1, 1, 1, 2, 0, 0, 2, 1, 3, 0, 0], dtype=float)
    out = binned_means(x, y, w, bins=3)
    xs = [np.average(x[s], weights=w[s]) for s in (slice(0, 4), slice(4, 8), slice(8, 12))]
    ys = [np.average(y[s], weights=w[s]) for s in (slice(0, 4), slice(4, 8), slice(8, 12))]
    assert out["x"] == pytest.approx(xs) and out["y"] == pytest.approx(ys)
    assert out["x"] == pytest.approx([1.5, 5.5, 8.75])


def test_binned_means_drop_empty_bins_and_handle_no_data():
    assert binned_means(np.array([]), np.array([]), np.array([])) == {"x": [], "y": []}
    x = np.array([0.0, 1.0, 2.0, 3.0])
    out = binned_means(x, 10 * x, np.array([1.0, 1.0, 0.0, 0.0]), bins=2)  # the upper bin has no weight
    assert out == {"x": [0.5], "y": [5.0]}
    same = binned_means(np.full(5, 2.0), np.arange(5.0), np.ones(5), bins=4)  # one distinct x: one bin
    assert same["x"] == pytest.approx([2.0]) and same["y"] == pytest.approx([2.0])


# ============================================================================ ResidualData
def test_residual_data_usable_pixels_follow_the_display_range_and_the_border():
    case = small_case()
    m, p = case.measured.astype(np.float64).copy(), case.predicted.astype(np.float64).copy()
    p[0, 10, 10, 0] = 0.5 * (DISPLAY_MAX + 1.0)  # prediction too bright
    p[0, 10, 11, 1] = 0.5 * DISPLAY_MIN  # prediction too dark
    m[0, 11, 11, 2] = 0.99  # measured clipped
    p[0, 11, 11, 2] = 0.5
    data = ResidualData(m, p, case.context, np.arange(FRAMES))
    np.testing.assert_array_equal(data.r, m - p)
    np.testing.assert_allclose(data.m_lin, decode(m, 2.2))
    assert not data.usable[0, 10, 10, 0] and not data.usable[0, 10, 11, 1] and not data.usable[0, 11, 11, 2]
    assert not data.usable[:, :2].any() and not data.usable[:, :, -2:].any()  # border_px = 2 eroded away
    inner = (p > DISPLAY_MIN) & (p < DISPLAY_MAX) & (m > 0.005) & (m < 0.985)
    np.testing.assert_array_equal(data.usable[:, 2:-2, 2:-2], inner[:, 2:-2, 2:-2])
    wide = ResidualData(m, p, case.context, np.arange(FRAMES), border_px=0)
    np.testing.assert_array_equal(wide.usable, inner)


def test_residual_data_pixel_mask_restricts_the_statistics_not_usable_all():
    case = small_case()
    even = checkerboard(SIZE, SIZE, 0)
    data = data_of(case, pixel_mask=even)
    full = data_of(case)
    assert data.pixel_fraction == 0.5
    assert not data.usable[:, ~even].any()
    np.testing.assert_array_equal(data.usable[:, even], full.usable[:, even])
    np.testing.assert_array_equal(data.usable_all, full.usable)  # the whole neighbourhood stays visible


def test_with_prediction_replaces_the_prediction_and_drops_the_caches():
    case = small_case()
    data = data_of(case)
    fit = data.photometric()
    assert data.photometric_if_fitted is fit and data.photometric() is fit  # fitted once, then cached
    _ = data.grad
    other = np.clip(case.predicted * 1.1, 0.0, 1.0).astype(np.float64)
    inside = np.ones(other.shape[:3], dtype=bool)
    inside[:, 10:12] = False
    new = data.with_prediction(other, inside)
    np.testing.assert_array_equal(new.p, other)
    np.testing.assert_array_equal(new.r, data.m - other)
    np.testing.assert_allclose(new.p_lin, decode(other, 2.2))
    in_range = (other > DISPLAY_MIN) & (other < DISPLAY_MAX)
    np.testing.assert_array_equal(new.usable, data.usable & in_range & inside[..., None])
    np.testing.assert_array_equal(new.usable_all, data.usable_all & in_range)
    assert new.photometric_if_fitted is None and new._grad is None
    assert data.photometric_if_fitted is fit  # the original keeps its own fit and prediction
    np.testing.assert_array_equal(data.p, case.predicted.astype(np.float64))
    assert new.photometric() is not fit


def test_with_measurement_keeps_usable_pixels_and_shares_derivatives():
    case = small_case()
    data = data_of(case)
    data.photometric()
    grad = data.grad
    other = np.clip(case.measured * 1.3, 0.0, 1.0).astype(np.float64)  # brighter: some pixels now clip
    new = data.with_measurement(other)
    assert new.m is other and new.p is data.p
    np.testing.assert_array_equal(new.r, other - data.p)
    np.testing.assert_allclose(new.m_lin, decode(other, 2.2))
    np.testing.assert_array_equal(new.usable, data.usable)  # "the usable pixels stay those of these frames"
    assert new.grad is grad  # not recomputed for the same prediction
    assert new.photometric_if_fitted is None
    assert not np.allclose(new.photometric().y[:10], data.photometric().y[:10])


# ============================================================================ PhotometricFit
def test_photometric_fit_recovers_known_frame_and_channel_gains():
    """measured = predicted x exp(frame gain + channel gain) in linear units, no noise: every cell's log ratio is
    that factor exactly (up to the +var/2 bias correction, ~1e-5 here), so the frame and white-balance coefficients
    are the hidden gains and the vignette and response coefficients vanish."""
    case = small_case()
    gains = np.linspace(-0.1, 0.1, FRAMES)
    wb = np.array([0.05, 0.0, -0.04])
    m = with_linear_factor(case.predicted, gains[:, None, None, None] + wb)
    fit = ResidualData(m, case.predicted, noiseless_ctx(case), np.arange(FRAMES)).photometric()
    assert fit.testable and fit.n_cells > 500
    np.testing.assert_allclose(fit.coefs("frame"), gains, atol=2e-4)
    np.testing.assert_allclose(fit.coefs("white_balance"), [0.05, -0.04], atol=2e-4)
    np.testing.assert_allclose(fit.coefs("vignette"), 0.0, atol=2e-3)
    assert abs(fit.coefs("response")[0]) < 2e-4
    assert fit.log_global == pytest.approx(np.median(gains), abs=2e-4)


@pytest.mark.parametrize("seed", [0, 3])
def test_photometric_fit_recovers_a_hidden_vignette(seed):
    """A hidden log shading a2 r^2 + a4 r^4 (r = 1 at the farthest corner). The cells average r^2 uniformly but the
    log ratio of SUMS weights each pixel by its intensity, so a 4 x 4 cell's y differs from its radial term by the
    shading's spread in the cell times the texture's weight variation (residual sd ~0.003 here): the fitted curve
    matches the hidden one within 0.015 where cells exist (r <= 0.85 after the 2 px border) and r^2, r^4 separately
    are only loosely identified, so the test is on the curve, not on the two coefficients."""
    case = small_case(seed=seed)
    _, _, r = radial_coordinates(SIZE, SIZE, case.context.principal_point)
    a2, a4 = -0.3, 0.1
    m = with_linear_factor(case.predicted, (a2 * r**2 + a4 * r**4)[None, :, :, None] + np.zeros((FRAMES, 1, 1, 3)))
    fit = ResidualData(m, case.predicted, noiseless_ctx(case), np.arange(FRAMES)).photometric()
    a = fit.coefs("vignette")
    rr = np.linspace(0.0, math.sqrt(fit.r2.max()), 30)
    np.testing.assert_allclose(a[0] * rr**2 + a[1] * rr**4 - (a2 * rr**2 + a4 * rr**4), 0.0, atol=0.015)
    assert 1.0 - math.exp(a.sum()) == pytest.approx(1.0 - math.exp(a2 + a4), abs=0.03)  # corner, extrapolated
    np.testing.assert_allclose(fit.coefs("frame"), 0.0, atol=0.01)
    f, p, q = fit.test("vignette")
    assert q == 2 and p < 1e-10


def test_photometric_fit_is_the_weighted_least_squares_and_partial_f_test_by_hand():
    """An independent reference on a noisy hidden-vignette case: the normal equations (X'WX) b = X'Wy on the kept
    cells, the residual d.o.f., and each block's partial F against the fit without it (the frame block's reduced model
    keeps one intercept)."""
    case = small_case("vignette", 0.35, seed=1)
    fit = data_of(case).photometric()
    k = fit.keep
    X, y, w = fit.X[k], fit.y[k], fit.w[k]
    assert X.shape[1] == FRAMES + 2 + 2 + 1 and fit.names == ["frame", "white_balance", "vignette", "response"]
    coef = np.linalg.solve(X.T @ (w[:, None] * X), X.T @ (w * y))
    np.testing.assert_allclose(fit.coef, coef, rtol=1e-7, atol=1e-10)
    rss = float(np.sum(w * (y - X @ coef) ** 2))
    assert fit.rss == pytest.approx(rss, rel=1e-8)
    assert fit.dof == int(k.sum()) - X.shape[1]
    for block, q in (("vignette", 2), ("response", 1), ("white_balance", 2), ("frame", FRAMES - 1)):
        cols = [c for c in range(X.shape[1]) if not (fit.slices[block].start <= c < fit.slices[block].stop)]
        Xr = X[:, cols] if block != "frame" else np.concatenate([np.ones((X.shape[0], 1)), X[:, cols]], axis=1)
        br = np.linalg.lstsq(Xr * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)[0]
        rss_r = float(np.sum(w * (y - Xr @ br) ** 2))
        F_ref = (rss_r - rss) / q / (rss / fit.dof)
        F, p, q_out = fit.test(block)
        assert q_out == q
        assert F == pytest.approx(F_ref, rel=1e-6)
        assert p == pytest.approx(sps.f.sf(F_ref, q, fit.dof), rel=1e-6, abs=1e-300)
    assert fit.test("vignette")[1] < 1e-6  # the hidden shading is found
    assert fit.coefs("vignette").sum() < 0  # darker corners


def test_photometric_fit_cells_are_block_sums_of_the_pixels():
    """A few cells recomputed from the pixels: frame, block and channel from the cell index, y = log(sum m / sum p)
    + var/2 over the usable pixels of the 4 x 4 block, w = 1 / var (assumed noise plus quantisation)."""
    case = small_case("vignette", 0.35, seed=1)
    data = data_of(case)
    fit = data.photometric()
    cells = np.flatnonzero(fit.cell_ok.ravel())
    var_lin = (case.context.noise_var_linear(data.p_lin, data.frames)
               + (LEVEL / encode_slope(data.p_lin, 2.2)) ** 2 / 12.0)
    for k in (0, fit.n_cells // 3, fit.n_cells - 1):
        f, by, bx, c = np.unravel_index(cells[k], fit.cell_ok.shape)
        blk = (f, slice(by * BLOCK_PX, (by + 1) * BLOCK_PX), slice(bx * BLOCK_PX, (bx + 1) * BLOCK_PX), c)
        use = data.usable[blk]
        sm, sp = data.m_lin[blk][use].sum(), data.p_lin[blk][use].sum()
        var_y = var_lin[blk][use].sum() / sp**2 + 1e-8
        assert use.sum() >= 0.75 * BLOCK_PX**2
        assert (fit.fidx[k], fit.cidx[k]) == (f, c)
        assert fit.y[k] == pytest.approx(math.log(sm / sp) + 0.5 * var_y, rel=1e-9, abs=1e-12)
        assert fit.w[k] == pytest.approx(1.0 / var_y, rel=1e-9)


def test_photometric_fit_trims_a_patch_the_model_does_not_explain():
    """A 1.6 x brighter 8 x 8 patch in one frame of a noisy null case (content absent from the prediction): its four
    blocks are trimmed (robust |z| > 5), nothing in the other frames is, and the frame gains stay those of the clean
    fit (untrimmed, the patch would lift frame 4's gain by ~0.05: a tenth of log 1.6 over ~36 blocks)."""
    case = small_case(None, seed=3)
    clean = data_of(case).photometric()
    assert not clean.trimmed.any()
    m = case.measured.astype(np.float64).copy()
    m[4, 8:16, 16:24] = with_linear_factor(m[4, 8:16, 16:24], np.log(1.6))
    fit = ResidualData(m, case.predicted, case.context, np.arange(FRAMES)).photometric()
    assert fit.trimmed_map.shape == (FRAMES, SIZE // BLOCK_PX, SIZE // BLOCK_PX)
    assert fit.trimmed_map[4, 2:4, 4:6].all()
    assert set(np.argwhere(fit.trimmed_map)[:, 0]) == {4}
    assert (~fit.keep).sum() == fit.trimmed.sum() > 0
    np.testing.assert_allclose(fit.coefs("frame"), clean.coefs("frame"), atol=5e-3)


def test_photometric_fit_with_too_few_cells_is_not_testable():
    case = small_case()
    p = np.full(case.predicted.shape, 0.99)  # above DISPLAY_MAX: nothing usable ...
    p[0, 4:8, 4:8] = case.predicted[0, 4:8, 4:8]  # ... but one block of one frame (3 cells <= frames + 8)
    fit = ResidualData(case.measured, p, case.context, np.arange(FRAMES)).photometric()
    assert not fit.testable and fit.n_cells <= FRAMES + 8
    assert not hasattr(fit, "coef")


# ============================================================================ GeometricCause (time offset)
@pytest.mark.parametrize("dt", [3e-3, -3e-3])
@pytest.mark.parametrize("seed", [2, 5])
def test_first_order_time_offset_estimate_has_the_sign_and_size_of_the_hidden_offset(dt, seed):
    """The measurement is the scene dt later: residual ~ -grad(prediction) . v dt, the regressor's slope is dt. The
    per-frame slopes all have dt's sign; their information-weighted mean is within 20 % of dt (first-order truncation
    of a ~0.5 px shift plus 8-bit noise: 1-9 % seen on these cases)."""
    case = small_case("time_offset", dt, seed=seed)
    cause = CAUSES["time_offset"]
    est, info = cause.first_order(data_of(case))
    assert est.shape == (FRAMES, 1) and np.all(info > 0)
    assert np.all(np.sign(est[:, 0]) == np.sign(dt))
    theta0 = cause.initial_theta(est, info)
    assert theta0.shape == (1,)
    assert theta0[0] == pytest.approx(dt, rel=0.2)


def test_first_order_time_offset_of_a_null_case_is_near_zero():
    case = small_case(None, seed=2)
    cause = CAUSES["time_offset"]
    est, info = cause.first_order(data_of(case))
    assert abs(cause.initial_theta(est, info)[0]) < 1e-4  # 0.1 ms: 30 x below the 3 ms offsets above


def test_initial_theta_is_the_information_weighted_mean_per_parameter():
    est = np.array([[1.0, 10.0], [3.0, 20.0]])
    info = np.array([[1.0, 1.0], [3.0, 1.0]])
    np.testing.assert_allclose(CAUSES["readout"].initial_theta(est, info), [2.5, 15.0])


def test_geometric_fit_tests_across_frames_and_refines_the_estimate():
    case = small_case("time_offset", 3e-3, seed=2)
    res = CAUSES["time_offset"].fit(data_of(case))
    assert res.testable and res.kind == "geometric"
    assert res.statistic_kind == f"t({FRAMES - 1})" and res.internal["frame_df"] == FRAMES - 1
    assert res.p_value < 1e-6 and res.statistic > 0
    assert res.params["time_offset_error_s"] == pytest.approx(3e-3, rel=0.1)
    assert res.params["first_order_estimate"]["time_offset_error_s"] == res.internal["theta_first_order"][0]
    assert res.effect_rms > 0


def test_geometric_fit_without_image_velocity_is_not_testable():
    case = small_case("time_offset", 3e-3, seed=2)
    ctx = dataclasses.replace(case.context, pixel_velocity_px_s=None)
    res = CAUSES["time_offset"].fit(data_of(case, ctx))
    assert (res.name, res.kind, res.testable, res.p_value) == ("time_offset", "geometric", False, 1.0)
