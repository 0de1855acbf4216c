"""Residual diagnosis: hidden-effect cases must be named, estimated and improved; a null case must not alarm."""

from __future__ import annotations

import numpy as np
import pytest

from egobench.diagnose.core import NO_DISCREPANCY, DiagnosisConfig, diagnose_residuals
from egobench.diagnose.synthetic import make_case
from egobench.effects import EFFECTS
from egobench.residual.signatures import distortion_profile, frame_t_test, holm, partial_f_test, warp, weighted_lstsq

FAST = {"speed_px_s": (250.0, 600.0)}  # "exposure 4-10 ms under fast motion"


def _param_error(effect: str, value, params: dict, affected: list[int]) -> tuple[float, float]:
    """(error, tolerance) of the estimated parameter against the hidden value."""
    if effect == "readout":
        return abs(params["readout_relative_error"] - value), 0.08  # relative readout error, absolute
    if effect == "time_offset":
        return abs(params["time_offset_error_s"] - value), 0.25e-3  # seconds
    if effect == "exposure_blur":
        return abs(params["exposure_s"] / value - 1.0), 0.25  # relative
    if effect == "vignette":
        return abs(params["corner_attenuation"] - value), 0.05  # fraction at the corner
    if effect == "response":
        return abs(params["gamma"] - value), 0.1
    if effect == "white_balance":
        true_rel = np.asarray(value) / value[1]
        return float(np.max(np.abs(np.asarray(params["channel_gains_relative_to_green"]) / true_rel - 1))), 0.05
    if effect == "exposure_metadata":
        assert sorted(params["flagged_frames"]) == sorted(f for f in affected if f % 8 != 0)
        return abs(params["median_exposure_relative_error"] - value), 0.03
    if effect == "noise":
        return abs(params["noise_std_factor"] / value - 1.0), 0.10
    if effect == "distortion":
        return abs(params["k0_error"] / value - 1.0), 0.25
    raise AssertionError(effect)


MID_RANGE = {
    "readout": 0.4, "time_offset": -3e-3, "exposure_blur": 7e-3, "vignette": 0.35, "response": 2.6,
    "white_balance": (1.15, 1.0, 0.87), "exposure_metadata": 0.2, "noise": 1.6, "distortion": 0.006,
}


@pytest.mark.parametrize("effect", list(MID_RANGE))  # issue 6's nine; a new effect brings its own test
def test_hidden_effect_mid_range_is_named_estimated_and_improved(effect):
    value = MID_RANGE[effect]
    assert EFFECTS[effect].in_range(value)
    case = make_case(effect, value, seed=3, **(FAST if effect == "exposure_blur" else {}))
    d = diagnose_residuals(case.measured, case.predicted, case.context)
    assert d.verdict == effect, [(r.name, r.p_adjusted, r.effect_rms) for r in d.ranking[:3]]
    err, tol = _param_error(effect, value, d.named[0].params, case.affected_frames)
    assert err <= tol, (d.named[0].params, value)
    if effect == "noise":
        assert d.named[0].nll_gain_nats_per_px > 0
    else:
        assert d.named[0].psnr_gain_db > 0


@pytest.mark.parametrize("effect", ["readout", "time_offset", "vignette", "response", "white_balance",
                                    "exposure_metadata"])
def test_hidden_effect_seeded_draw(effect):
    """Magnitudes drawn (seeded) from the plausible range of egobench.effects."""
    case = make_case(effect, None, seed=11)
    assert EFFECTS[effect].in_range(case.value)
    d = diagnose_residuals(case.measured, case.predicted, case.context)
    assert d.verdict == effect
    err, tol = _param_error(effect, case.value, d.named[0].params, case.affected_frames)
    assert err <= tol
    assert d.named[0].psnr_gain_db > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_null_case_has_no_false_alarm(seed):
    case = make_case(None, seed=seed)
    d = diagnose_residuals(case.measured, case.predicted, case.context)
    assert d.verdict == NO_DISCREPANCY, [(r.name, r.p_adjusted, r.effect_rms) for r in d.ranking[:3]]
    assert d.named == [] and d.psnr_gain_db == 0.0
    json_record = d.to_dict()
    assert json_record["verdict"] == NO_DISCREPANCY and len(json_record["ranking"]) == len(EFFECTS)


def test_readout_is_not_mistaken_for_time_offset_and_vice_versa():
    d = diagnose_residuals(*_mp(make_case("time_offset", 2e-3, seed=5)))
    ranks = {r.name: r for r in d.ranking}
    assert d.verdict == "time_offset" and not ranks["readout"].significant
    d = diagnose_residuals(*_mp(make_case("readout", -0.3, seed=5)))
    assert d.verdict == "readout"


def _mp(case):
    return case.measured, case.predicted, case.context


# ----------------------------------------------------------------------------- statistics
def test_frame_t_test_is_calibrated_under_the_null():
    rng = np.random.default_rng(0)
    p = np.array([frame_t_test(rng.normal(0, 1, 14), np.ones(14)).p_value for _ in range(2000)])
    assert abs(np.mean(p < 0.05) - 0.05) < 0.015
    assert frame_t_test(rng.normal(1.0, 0.1, 14), np.ones(14)).p_value < 1e-10


def test_partial_f_test_matches_an_independent_anova():
    from scipy import stats

    rng = np.random.default_rng(1)
    groups = [rng.normal(mu, 1.0, 30) for mu in (0.0, 0.3, 0.6)]
    y = np.concatenate(groups)
    X_full = np.kron(np.eye(3), np.ones((30, 1)))
    _, rss_f = weighted_lstsq(X_full, y, np.ones(90))
    _, rss_r = weighted_lstsq(np.ones((90, 1)), y, np.ones(90))
    f, p = partial_f_test(rss_f, rss_r, 2, 87)
    ref = stats.f_oneway(*groups)
    assert f == pytest.approx(ref.statistic, rel=1e-9) and p == pytest.approx(ref.pvalue, rel=1e-9)


def test_holm_adjustment():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])


@pytest.mark.parametrize("name", ["time_offset", "readout", "exposure_blur"])
def test_velocity_placebo_tables_match_the_regressors_rebuilt_with_permuted_velocities(name):
    """The tables give the slopes `first_order` gets from the regressors re-formed with frame perm[i]'s
    velocity in frame i (the placebo as it was computed before the tables), for several derangements
    and the identity; the basis describes the regressors."""
    import copy
    from dataclasses import replace

    from egobench.diagnose.estimators import CAUSES
    from egobench.residual.estimation import ResidualData
    from egobench.residual.permuted import PermutedVelocitySlopes

    case = make_case("readout", 0.3, seed=2)
    frames = np.arange(1, case.measured.shape[0], 2)  # a subset: the tables index the data's frames
    data = ResidualData(case.measured[frames], case.predicted[frames], case.context, frames).geometric()
    cause = CAUSES[name]
    tables = PermutedVelocitySlopes(cause.velocity_basis(data), data.velocity, data.p, data.r, data.usable)
    v = case.context.pixel_velocity_px_s
    rng = np.random.default_rng(0)
    for perm in [np.arange(frames.size)] + [np.roll(rng.permutation(frames.size), 1) for _ in range(4)]:
        vp = v.copy()
        vp[frames] = v[frames[perm]]
        d = copy.copy(data)
        d.ctx = replace(data.ctx, pixel_velocity_px_s=vp)
        est, info = cause.first_order(d)
        est_t, info_t = tables.slopes(perm)
        assert np.abs(est).max() > 0 and np.all(info > 0)
        np.testing.assert_allclose(est_t, est, rtol=1e-8, atol=1e-12 * np.abs(est).max())
        np.testing.assert_allclose(info_t, info, rtol=1e-8)


def test_a_velocity_basis_that_is_not_the_regressors_is_refused(monkeypatch):
    """The placebos check the tables on the true pairing: a basis with the wrong sign gives -t there."""
    from egobench.diagnose.estimators import CAUSES
    from egobench.residual.calibration import velocity_tables as _velocity_tables
    from egobench.residual.estimation import ResidualData, velocity_term_basis

    case = make_case("time_offset", 0.003, seed=2)
    data = ResidualData(case.measured, case.predicted, case.context, np.arange(case.measured.shape[0])).geometric()
    cause = CAUSES["time_offset"]
    est, info = cause.first_order(data)
    t_real = frame_t_test(est[:, 0], info[:, 0]).t
    assert _velocity_tables(cause, data, t_real, 0, False) is not None
    monkeypatch.setattr(type(cause), "velocity_basis", lambda self, d: [velocity_term_basis(d, -1.0)])
    with pytest.raises(RuntimeError, match="time_offset: velocity_basis gives t"):
        _velocity_tables(cause, data, t_real, 0, False)


def test_frame_slopes_match_a_per_frame_least_squares_reference():
    """Slopes and their information against np.linalg.lstsq frame by frame on the masked pixels with the
    design [x1, x2, 1, p - mean p] (the residual variance: RSS / n); a frame with under 20 pixels and one
    whose regressor is constant (singular design) get 0, 0."""
    from egobench.residual.estimation import frame_slopes

    rng = np.random.default_rng(3)
    F, H, W = 5, 9, 11
    p = rng.uniform(0.2, 0.9, (F, H, W, 3))
    xs = [rng.normal(0, 1, (F, H, W, 3)), rng.normal(0, 1, (F, H, W, 3))]
    y = 0.3 * xs[0] - 0.1 * xs[1] + 0.05 + 0.2 * p + rng.normal(0, 0.1, (F, H, W, 3))
    mask = rng.uniform(size=(F, H, W, 3)) < 0.7
    mask[1] = False
    mask[1, 0, :2] = True  # 6 pixels
    xs[1][3] = 2.0  # constant: collinear with the constant column
    est, info = frame_slopes(xs, p, y, mask)
    for f in (0, 2, 4):
        m = mask[f]
        pm = p[f][m]
        X = np.stack([xs[0][f][m], xs[1][f][m], np.ones(m.sum()), pm - pm.mean()], axis=1)
        coef, *_ = np.linalg.lstsq(X, y[f][m], rcond=None)
        s2 = np.sum((y[f][m] - X @ coef) ** 2) / m.sum() + 1e-12
        var = np.diag(np.linalg.inv(X.T @ X))[:2] * s2
        np.testing.assert_allclose(est[f], coef[:2], rtol=1e-9)
        np.testing.assert_allclose(info[f], 1.0 / var, rtol=1e-9)
    assert np.all(est[[1, 3]] == 0.0) and np.all(info[[1, 3]] == 0.0)


def test_warp_shifts_a_band_limited_image_by_the_displacement():
    H = W = 32
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    img = (0.5 + 0.3 * np.sin(2 * np.pi * u / 9.0) * np.cos(2 * np.pi * v / 11.0))[None, ..., None]
    disp = np.zeros((1, H, W, 2))
    disp[..., 0], disp[..., 1] = 0.37, -0.61
    out, inside = warp(img.astype(np.float32), disp)
    expected = 0.5 + 0.3 * np.sin(2 * np.pi * (u - 0.37) / 9.0) * np.cos(2 * np.pi * (v + 0.61) / 11.0)
    core = inside[0] & (u > 3) & (u < W - 4) & (v > 3) & (v < H - 4)
    assert np.max(np.abs(out[0, ..., 0] - expected)[core]) < 4e-3  # Lanczos-4 interpolation error, about 1 % of the amplitude


def test_warp_by_a_zero_displacement_is_the_remap_at_the_pixel_centres():
    """A frame with no displacement skips the remap: what it returns is bitwise what the Lanczos-4 remap
    at the pixel centres gives (the image as float32), and the frames beside it are still warped."""
    import cv2

    rng = np.random.default_rng(3)
    img = rng.normal(0.5, 0.3, (3, 12, 10, 3))
    disp = np.zeros((3, 12, 10, 2))
    disp[1] = rng.normal(0.0, 0.7, (12, 10, 2))
    disp[2, ..., 0] = -0.0  # a signed zero is no displacement either
    out, inside = warp(img, disp)
    v, u = np.meshgrid(np.arange(12, dtype=np.float32), np.arange(10, dtype=np.float32), indexing="ij")
    for f in range(3):
        su, sv = (u - disp[f, ..., 0]).astype(np.float32), (v - disp[f, ..., 1]).astype(np.float32)
        ref = cv2.remap(img[f].astype(np.float32), su, sv, interpolation=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(out[f], ref)
    np.testing.assert_array_equal(out[0], img[0].astype(np.float32))
    assert inside[0].all() and inside[2].all() and not inside[1].all()


def test_distortion_profile_matches_a_k0_perturbation_by_finite_differences():
    """A rectified pixel at angle theta shows the ray theta_t solving r(theta_t; k0 + d) = r(theta; k0)."""
    k = (0.4153, -0.4666, 0.0394, 1.305, -1.768, 0.6526)
    f = 100.0
    radius = np.array([10.0, 40.0, 80.0])
    theta = np.arctan(radius / f)

    def r(th, k0):
        kk = (k0,) + k[1:]
        return th + sum(kp * th ** (2 * i + 3) for i, kp in enumerate(kk))

    d = 1e-4
    target = r(theta, k[0])
    th_t = theta.copy()
    for _ in range(50):  # Newton on r(th_t; k0 + d) = target
        deriv = (r(th_t + 1e-7, k[0] + d) - r(th_t - 1e-7, k[0] + d)) / 2e-7
        th_t -= (r(th_t, k[0] + d) - target) / deriv
    displacement = f * (np.tan(theta) - np.tan(th_t))  # content moves outward by this (px)
    assert distortion_profile(radius, f, k) * d == pytest.approx(displacement, rel=2e-3)


def test_bad_input_names_the_argument():
    case = make_case(None, seed=0, n_frames=9)
    with pytest.raises(ValueError, match="predicted"):
        diagnose_residuals(case.measured, case.predicted[:, :-1], case.context)
    bad = case.predicted.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="predicted: contains NaN"):
        diagnose_residuals(case.measured, bad, case.context)
    with pytest.raises(ValueError, match="alpha"):
        diagnose_residuals(case.measured, case.predicted, case.context, DiagnosisConfig(alpha=2.0))
    case.context.row_time_ratio = case.context.row_time_ratio[:-1]
    with pytest.raises(ValueError, match="row_time_ratio"):
        diagnose_residuals(case.measured, case.predicted, case.context)


def test_a_new_prediction_gets_its_own_geometric_view():
    """`with_prediction` must not carry the old prediction's cached geometric view: the blur test
    'given the refined shift' fits on the shifted prediction, not on the original one."""
    from egobench.residual.estimation import ResidualData

    case = make_case(None, seed=2)
    data = ResidualData(case.measured, case.predicted, case.context, np.arange(case.measured.shape[0]))
    data.geometric()  # fills the cache for the original prediction
    other = np.clip(case.predicted * 0.9 + 0.05, 0.0, 1.0)
    view = data.with_prediction(other).geometric()
    assert not np.array_equal(view.p, data.geometric().p)
    assert np.allclose(view.m, data.geometric().m)  # the measured frames are the same


def test_held_out_frames_are_compared_with_their_neighbouring_training_views():
    """`neighbouring_training_views`: the fitting frames whose index is a held-out index +- 1 (by frame index, not
    position); every fitting frame when none is held out. A reconstruction's error varies along the trajectory by
    far more than its generalisation gap, so pooling every training frame against 1 in 8 held-out frames compares
    different parts of the walk (it put training views 0.6-4 dB below the held-out frames)."""
    from types import SimpleNamespace

    from egobench.diagnose.core import _Split, neighbouring_training_views

    def split_of(index):
        held = index % 8 == 0
        ctx = SimpleNamespace(frame_index=index, held_out=held)
        return ctx, _Split(np.flatnonzero(~held), np.flatnonzero(held), None, np.ones((2, 2), bool), np.ones((2, 2), bool))

    ctx, split = split_of(np.arange(17))
    assert neighbouring_training_views(ctx, split).tolist() == [1, 7, 9, 15]
    ctx, split = split_of(np.arange(5, 20))  # positions 0.. hold frames 5..19: held 8 and 16 at positions 3, 11
    assert ctx.frame_index[neighbouring_training_views(ctx, split)].tolist() == [7, 9, 15, 17]
    ctx, split = split_of(np.arange(1, 8))  # nothing held out
    assert neighbouring_training_views(ctx, split).tolist() == list(range(7))
