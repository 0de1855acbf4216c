"""The gain a cause must earn to be named (`egobench.diagnose.gain`) and the placebo extensions behind it."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from egobench.diagnose.estimators import CAUSES
from egobench.diagnose.gain import GAIN_PLACEBOS, GainTest, gain_placebo_test, per_frame_gains, refusal
from egobench.diagnose.synthetic import make_case
from egobench.effects.distortion import unit_displacement
from egobench.effects.readout import rendered_row_time, staircase_shear
from egobench.residual.estimation import CauseResult, ResidualData, frame_slopes, velocity_term
from egobench.residual.signatures import border_pull_basis, checkerboard, tile_shuffled


def test_tile_shuffle_keeps_each_frames_values_and_moves_them():
    rng = np.random.default_rng(0)
    delta = rng.normal(size=(3, 35, 34, 3))  # 8 x 8 tiles of 4 x 4 px, and a remainder that stays
    out = tile_shuffled(delta, np.random.default_rng(1))
    for f in range(3):
        assert np.allclose(np.sort(out[f].ravel()), np.sort(delta[f].ravel()))
    assert np.array_equal(out[:, 32:], delta[:, 32:]) and np.array_equal(out[:, :, 32:], delta[:, :, 32:])
    assert not np.array_equal(out, delta)
    tile = delta[0, 4:8, 8:12]  # a tile lands whole somewhere in its own frame
    assert any(np.array_equal(out[0, 4 * i:4 * i + 4, 4 * j:4 * j + 4], tile) for i in range(8) for j in range(8))


def _stack(seed: int, f: int = 4, size: int = 32):
    rng = np.random.default_rng(seed)
    current = rng.uniform(0.2, 0.8, (f, size, size, 3))
    v, u = np.mgrid[0:size, 0:size]
    blob = np.exp(-((u - 9.0) ** 2 + (v - 22.0) ** 2) / (2 * 5.0**2))[None, :, :, None]
    return current, 0.1 * blob * np.ones((f, 1, 1, 3)), rng


def test_an_extension_that_follows_the_residual_beats_its_shuffled_placebos():
    """measured = current + a blob: extending by that blob gains far more than the blob moved around (p at its
    floor 1 / 500); extending by an unrelated blob of the same size loses, and is refused."""
    current, blob, rng = _stack(0)
    measured = np.clip(current + blob + rng.normal(0, 0.01, current.shape), 0, 1)
    mask = checkerboard(32, 32, 1)
    idx = np.arange(4)
    vignette = CAUSES["vignette"]  # the default placebo: tiles shuffled
    res = CauseResult("vignette", "photometric", True)
    good = gain_placebo_test(vignette, res, None, current, current + blob, measured, idx, mask, seed=0)
    assert good.gain_db > 1.0 and good.p_value == pytest.approx(1 / (GAIN_PLACEBOS + 1))
    assert good.placebo_n == GAIN_PLACEBOS and good.placebo_mean_db < good.gain_db
    assert refusal(good.gain_db, good, 0.01, "held-out PSNR") is None
    wrong = current + np.flip(blob, axis=(1, 2))
    bad = gain_placebo_test(vignette, res, None, current, wrong, measured, idx, mask, seed=0)
    assert bad.gain_db < 0 and "is not positive" in refusal(bad.gain_db, bad, 0.01, "held-out PSNR")
    assert per_frame_gains(current + blob, current, measured, idx, mask).mean() == pytest.approx(good.gain_db)


def test_a_small_positive_gain_that_placebos_also_earn_is_refused():
    """A change that any of its shuffles would earn as well (measured = current + a constant) is no cause."""
    current, blob, rng = _stack(1)
    measured = np.clip(current + 0.02, 0, 1)
    test = gain_placebo_test(CAUSES["vignette"], CauseResult("vignette", "photometric", True), None, current,
                             current + 0.3 * blob, measured, np.arange(4), checkerboard(32, 32, 1), seed=3)
    assert test.gain_db > 0 and test.p_value > 0.05
    assert "does not beat the gains of its" in refusal(test.gain_db, test, 0.01, "held-out PSNR")
    assert refusal(0.1, None, 0.01, "within-frame PSNR") is None  # no placebo: a positive gain suffices
    assert "FRAME_LOCAL_GAIN_FLOOR_DB" in refusal(0.04, None, 0.01, "within-frame PSNR", 0.05)  # or its floor
    assert refusal(0.1, GainTest(0.1, 0.5, 0.1, 9), 0.01, "x").startswith("x gain +0.1000 dB does not beat")


@pytest.mark.parametrize("name", ["time_offset", "exposure_blur"])
def test_a_motion_placebo_turns_each_frames_own_velocity_away_from_its_motion(name):
    """Same speeds, turned: 90-270 deg for a signed shift (time offset), 60-120 deg off the axis for a blur."""
    case = make_case(None, seed=4, n_frames=9, speed_px_s=(250.0, 600.0))
    cause = CAUSES[name]
    seen = {}

    def spy(predicted, result, ctx, frames, **_k):
        seen["v"] = ctx.pixel_velocity_px_s[frames]
        return predicted

    inst = type(cause)()  # an instance whose apply reports the field it was given
    inst.apply = spy
    frames = np.array([0, 3, 5])
    v = case.context.pixel_velocity_px_s[frames].astype(np.float64)
    for seed in range(20):
        inst.gain_placebo(case.predicted[frames], case.predicted[frames], None, case.context, frames,
                          np.random.default_rng(seed))
        vp = seen["v"].astype(np.float64)
        assert np.allclose(np.linalg.norm(vp, axis=-1), np.linalg.norm(v, axis=-1), rtol=1e-4, atol=1e-3)
        moving = np.linalg.norm(v, axis=-1) > 1.0
        cos = np.sum(vp * v, axis=-1)[moving] / (np.linalg.norm(v, axis=-1)[moving] ** 2)
        if name == "time_offset":
            assert cos.max() <= 1e-3  # opposed or orthogonal: never along the motion
        else:
            assert np.abs(cos).max() <= 0.5 + 1e-3  # at least 60 deg off the motion's axis


def test_timing_causes_are_tested_beside_the_shear_the_runs_own_staircase_leaves():
    """A trained run renders each frame with N pose samples, a staircase of row times; the residual then holds
    the shear between the true row times and that staircase (one sample: the whole readout's). The time offset
    and the readout are fitted beside it (a nuisance, never tested or applied): that shear alone gives neither a
    shift nor a readout error, whatever N, while the same fits without it take it up; a real offset or readout
    error on top of it is still found."""
    case = make_case(None, seed=5, n_frames=16, speed_px_s=(250.0, 600.0))
    R = np.ascontiguousarray(np.broadcast_to(np.linspace(0.0, 1.0, 48)[:, None] ** 1.5, (48, 48)))  # rows read unevenly
    ctx = dataclasses.replace(case.context, row_time_ratio=R)
    probe = ResidualData(case.measured, case.predicted, ctx, np.arange(16))
    x = velocity_term(probe)

    def t(cause, measured, samples, beside=True):
        data = ResidualData(measured, case.predicted, dataclasses.replace(ctx, model_pose_samples=samples), np.arange(16))
        xs = CAUSES[cause].regressors(data) + (CAUSES[cause].nuisance_regressors(data) if beside else [])
        est, info = frame_slopes(xs, data.p, data.r, data.usable)
        j = CAUSES[cause].tested_index
        keep = info[:, j] > 0
        return est[keep, j].mean() / (est[keep, j].std(ddof=1) / np.sqrt(keep.sum()))

    for n in (1, 4):
        samples = np.full(16, n)
        if n == 4:
            samples[:2] = 1  # a few one-sample frames drop out of the readout's test
        gap = np.stack([R - rendered_row_time(R, int(k)) for k in samples])[..., None]
        run_shear = np.clip(case.measured + 0.006 * x * gap, 0, 1)  # an 8 ms readout, stated right
        data = ResidualData(run_shear, case.predicted, dataclasses.replace(ctx, model_pose_samples=samples), np.arange(16))
        assert len(staircase_shear(data)) == 1
        assert abs(t("time_offset", run_shear, samples)) < 3.0 < abs(t("time_offset", run_shear, samples, beside=False))
        offset = np.clip(run_shear + 0.002 * x, 0, 1)
        assert t("time_offset", offset, samples) > 5.0
        if n == 4:
            assert abs(t("readout", run_shear, samples)) < 3.0 < abs(t("readout", run_shear, samples, beside=False))
            longer = np.clip(run_shear + 0.003 * x * (R - 0.5)[None, :, :, None], 0, 1)
            assert t("readout", longer, samples) > 5.0


def _moving(flow: np.ndarray):
    """A 16-frame synthetic case whose frames move by ``flow`` [16, 48, 48, 2] px/s -> (case, its context with
    that flow, the residual data of the case against its own prediction: its gradients and velocity term)."""
    case = make_case(None, seed=6, n_frames=16)
    ctx = dataclasses.replace(case.context, pixel_velocity_px_s=np.ascontiguousarray(flow, dtype=np.float32))
    return case, ctx, ResidualData(case.measured, case.predicted, ctx, np.arange(16))


def _frames_t(est: np.ndarray) -> float:
    return float(est.mean() / (est.std(ddof=1) / np.sqrt(len(est))))


def _lens_slopes(case, ctx, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lens's per-frame k0 slopes [16] of ``measured`` against the case's prediction: fitted alone, and beside
    its nuisance signatures (`DistortionCause.first_order`)."""
    data = ResidualData(measured, case.predicted, ctx, np.arange(16))
    lens = CAUSES["distortion"]
    alone, _ = frame_slopes(lens.regressors(data), data.p, data.r, data.usable)
    beside, _ = lens.first_order(data)
    return alone[:, 0], beside[:, 0]


def test_a_radial_flow_that_follows_the_motion_is_not_taken_for_a_lens():
    """Walking forward, a time offset moves every pixel along a flow that expands about a point near the
    principal point, which a k0 error's radial displacement resembles. Distortion is fitted beside the
    motion's shift signature: the flow's residual gives it nothing, while the radial term alone takes it up."""
    v, u = np.mgrid[0:48, 0:48].astype(np.float32)
    cx, cy = make_case(None, seed=6, n_frames=16).context.principal_point
    speed = np.linspace(0.5, 1.5, 16, dtype=np.float32)[:, None, None, None]  # each frame its own pace
    case, ctx, probe = _moving(np.stack([u - cx, v - cy], -1)[None] * 8.0 * speed)  # px/s, expanding
    measured = np.clip(case.predicted + 0.003 * velocity_term(probe), 0, 1)  # a 3 ms offset along the flow
    alone, beside = _lens_slopes(case, ctx, measured)
    assert abs(_frames_t(alone)) > 4.0 and abs(_frames_t(beside)) < 3.0, (_frames_t(alone), _frames_t(beside))


def test_a_row_time_stretch_that_follows_the_motion_is_not_taken_for_a_lens():
    """Tilting the head one way, a readout error shears the image along the rows' times: moving vertically, the
    rows read later move further, so the image stretches top to bottom as a k0 error's radial displacement partly
    does (measured: a 256 px writer run with a 50 % longer readout named a distortion first, k0 +0.078).
    Distortion is fitted beside the readout's shear too: that stretch gives it nothing, while the radial term
    alone takes it up; a real k0 error on top of it is still found."""
    pace = np.linspace(0.5, 1.5, 16, dtype=np.float32)[:, None, None]  # tilting one way, each frame its own pace
    case, ctx, probe = _moving(np.stack([np.zeros((16, 48, 48)), np.broadcast_to(400.0 * pace, (16, 48, 48))], -1))
    stretch = velocity_term(probe) * (ctx.row_time_ratio - 0.5)[None, :, :, None]
    measured = np.clip(case.predicted + 0.004 * stretch, 0, 1)  # a readout 4 ms longer than stated
    alone, beside = _lens_slopes(case, ctx, measured)
    assert abs(_frames_t(alone)) > 4.0 and abs(_frames_t(beside)) < 3.0, (_frames_t(alone), _frames_t(beside))
    gx, gy = probe.grad
    d = unit_displacement(ctx, 48, 48)
    lensed = np.clip(measured - 0.01 * (gx * d[None, ..., 0:1] + gy * d[None, ..., 1:2]), 0, 1)
    _, with_lens = _lens_slopes(case, ctx, lensed)
    assert _frames_t(with_lens) > 5.0 and with_lens.mean() == pytest.approx(0.01, rel=0.25)


def test_a_pull_at_the_image_border_is_not_taken_for_a_lens():
    """A trained run's renders sit inward of the measured frames near the image border, by up to half a pixel and
    fading a few pixels in (measured on the independent writer's nulls: at one radius twice as much beside an
    edge as towards a corner), which a lens's radial displacement takes up as a positive k0 when fitted alone.
    On a trained run the lens is fitted beside the border pull's hats (`border_pull_basis`): a smooth pull of
    another shape gives it a tenth of what it takes alone, and a real k0 error on top of it is still found; on
    a prediction that is no trained run's there is no such nuisance."""
    pace = np.linspace(0.5, 1.5, 16, dtype=np.float32)[:, None, None]
    case, ctx, probe = _moving(np.stack([np.broadcast_to(300.0 * pace, (16, 48, 48)), np.zeros((16, 48, 48))], -1))
    trained = dataclasses.replace(ctx, model_pose_samples=np.full(16, 4))
    pulled = _border_pulled(case, probe)
    gx, gy = probe.grad
    alone, beside = _lens_slopes(case, trained, pulled)
    assert _frames_t(alone) > 4.0 and abs(beside.mean()) < 0.1 * alone.mean(), (alone.mean(), beside.mean())
    _, untrained = _lens_slopes(case, ctx, pulled)
    assert untrained.mean() > 0.5 * alone.mean()
    d = unit_displacement(ctx, 48, 48)
    lensed = np.clip(pulled - 0.01 * (gx * d[None, ..., 0:1] + gy * d[None, ..., 1:2]), 0, 1)
    _, with_lens = _lens_slopes(case, trained, lensed)
    assert _frames_t(with_lens) > 5.0 and with_lens.mean() == pytest.approx(0.01, rel=0.1)


def _border_pulled(case, probe) -> np.ndarray:
    """The case's prediction with the measured content 0.5 exp(-d / 3.5) px outward of it at distance d from each
    border (an exponential, not one of the hats), first order, and seeded noise of 1 level: a trained run's pull."""
    v, u = np.mgrid[0:48, 0:48].astype(np.float64)
    outward = np.zeros((48, 48, 2))
    for distance, nx, ny in ((u + 0.5, -1, 0), (47.5 - u, 1, 0), (v + 0.5, 0, -1), (47.5 - v, 0, 1)):
        outward[..., 0] += nx * 0.5 * np.exp(-distance / 3.5)
        outward[..., 1] += ny * 0.5 * np.exp(-distance / 3.5)
    gx, gy = probe.grad
    noise = np.random.default_rng(0).normal(0.0, 0.004, case.predicted.shape)
    return np.clip(case.predicted - (gx * outward[None, ..., 0:1] + gy * outward[None, ..., 1:2]) + noise, 0, 1)


def test_a_lens_on_a_trained_run_must_beat_the_wrong_centres_with_and_without_the_border_pull():
    """`DistortionCause.trained_placebos`: two records, the lens statistic beside the border pull and beside the
    readout's signature alone, each against the same about 8 wrong centres. The pull alone passes neither; a
    k0 error of 0.01 on top passes both; one of 0.002 passes beside the pull (which removes the pull from the
    wrong centres more than from the true one) but not the radial calibration, whose wrong centres the pull
    inflates as much as the true one: it is not named (the cause's p is the larger)."""
    pace = np.linspace(0.5, 1.5, 16, dtype=np.float32)[:, None, None]
    case, ctx, probe = _moving(np.stack([np.broadcast_to(300.0 * pace, (16, 48, 48)), np.zeros((16, 48, 48))], -1))
    trained = dataclasses.replace(ctx, model_pose_samples=np.full(16, 4))
    pulled = _border_pulled(case, probe)
    gx, gy = probe.grad
    d = unit_displacement(ctx, 48, 48)
    lens = CAUSES["distortion"]

    def p_values(k0: float) -> dict:
        measured = np.clip(pulled - k0 * (gx * d[None, ..., 0:1] + gy * d[None, ..., 1:2]), 0, 1)
        data = ResidualData(measured, case.predicted, trained, np.arange(16))
        records = lens.trained_placebos(CauseResult("distortion", "geometric", True), SimpleNamespace(data=data))
        return {key: r.p_value for r in records for key in r.params}

    assert min(p_values(0.0).values()) > 0.05
    assert max(p_values(0.01).values()) < 0.01
    small = p_values(0.002)
    assert small["calibration"] < 0.01 < small["calibration_radial"], small


def test_the_border_pull_is_an_outward_normal_falling_linearly_between_knots():
    """`border_pull_basis` at 64 px (knots 0, 2, 4, 8, 16 and 24 px from each border): the pixel centre 3.5 px from
    the left edge moves by 3/4 of the hat at 4 px and 1/4 of the hat at 2 px along -x, one 3.5 px from the bottom
    edge along +y, a corner pixel along both outward normals, the centre not at all; the hats sum to 1 out to
    16 px and fall to 0 at 24 px. On a 32 x 64 image the knots are fractions of the shorter side."""
    hats = border_pull_basis(64, 64)
    assert len(hats) == 5
    assert hats[2][32, 3].tolist() == [-0.75, 0.0] and hats[1][32, 3].tolist() == [-0.25, 0.0]
    assert hats[2][60, 32].tolist() == [0.0, 0.75] and hats[0][0, 63].tolist() == [0.75, -0.75]
    assert all(h[32, 32].tolist() == [0.0, 0.0] for h in hats)
    d = np.arange(64) + 0.5
    expected = np.clip((24.0 - d[::-1]) / 8.0, 0.0, 1.0) - np.clip((24.0 - d) / 8.0, 0.0, 1.0)
    np.testing.assert_allclose(sum(h[32, :, 0] for h in hats), expected, atol=1e-12)
    wide = border_pull_basis(32, 64)  # knots at 0, 1, 2, 4, 8 and 12 px
    assert wide[3][16, 3].tolist() == [-0.75, 0.0] and wide[2][16, 3].tolist() == [-0.25, 0.0]
    assert wide[3][3, 32].tolist() == [0.0, -0.75]
    assert all(h[16, 20].tolist() == [0.0, 0.0] for h in wide)
