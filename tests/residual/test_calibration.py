"""Unit tests of egobench.residual.calibration: the record a placebo returns and how it merges (`PlaceboRecord`,
`OWN_P`, `merge_record`), the shared evidence (`TrainedRunEvidence`: memo, rng streams), the rank tests
(`sequential_rank_p`, `beat_placebos`), the frame permutations (`Derangements`), the photometric helpers
(`radial_terms`, `frame_test`, `render_blur`, `resolution_matched`) and the velocity placebo."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.ndimage as ndi
import scipy.stats as sps

from egobench.diagnose.estimators import CAUSES, assumed_noise_variance
from egobench.diagnose.synthetic import make_case
from egobench.residual import calibration
from egobench.residual.calibration import (BLUR_SIGMAS_PX, OWN_P, PLACEBO_MAX, PLACEBO_STOP, Cells, Derangements,
                                           PlaceboRecord, TrainedRunEvidence, beat_placebos, frame_test, merge_record,
                                           photometric_cells, radial_terms, render_blur, resolution_matched,
                                           sequential_rank_p, velocity_placebo)
from egobench.residual.estimation import CauseResult, ResidualData
from egobench.residual.signatures import decode, encode, frame_t_test

SIZE, FRAMES = 32, 9


def small_data(effect=None, value=None, seed=2, n_frames=FRAMES) -> ResidualData:
    case = make_case(effect, value, seed=seed, size=SIZE, n_frames=n_frames)
    return ResidualData(case.measured, case.predicted, case.context, np.arange(n_frames))


def blur_linear_reference(display: np.ndarray, sigma: float, gamma: float = 2.2) -> np.ndarray:
    """Gaussian blur in linear space, computed with scipy (replicated edges, 4-sigma kernel) per frame and channel."""
    lin = decode(display, gamma)
    out = np.stack([np.stack([ndi.gaussian_filter(lin[f, ..., c], sigma, mode="nearest", truncate=4.0)
                              for c in range(lin.shape[-1])], -1) for f in range(lin.shape[0])])
    return np.clip(encode(out, gamma), 0.0, 1.0)


# ============================================================================ PlaceboRecord, merge_record
def test_placebo_record_defaults_raise_nothing():
    rec = PlaceboRecord(None)
    assert (rec.p_value, rec.params, rec.untestable, rec.reason) == (None, {}, False, None)
    r = CauseResult("vignette", "photometric", True, reason="kept", p_value=0.03, params={"a": 1})
    merge_record(r, rec)
    assert (r.p_value, r.params, r.testable, r.reason) == (0.03, {"a": 1}, True, "kept")


def test_merge_record_writes_own_p_raises_p_and_keeps_key_order():
    r = CauseResult("readout", "geometric", True, p_value=0.001, params={"z_first": 1.0, "shared": "old"})
    merge_record(r, PlaceboRecord(0.05, {"calibration": {"p_value_placebo": 0.05}, "p_value_frames": OWN_P,
                                         "shared": "new"}))
    assert r.p_value == 0.05  # raised to the placebo's p
    assert r.params["p_value_frames"] == 0.001  # OWN_P: the cause's p BEFORE this merge
    assert r.params["shared"] == "new" and r.params["calibration"] == {"p_value_placebo": 0.05}
    assert list(r.params) == ["z_first", "shared", "calibration", "p_value_frames"]  # existing keys keep their place
    # a second record: OWN_P is now the p the first merge left; a smaller p lowers nothing
    merge_record(r, PlaceboRecord(0.01, {"p_value_second": OWN_P}))
    assert r.p_value == 0.05 and r.params["p_value_second"] == 0.05
    assert r.testable and r.reason == ""


def test_merge_record_own_p_is_only_the_exact_marker():
    r = CauseResult("vignette", "photometric", True, p_value=0.2)
    merge_record(r, PlaceboRecord(None, {"note": "<own p-value> (not the marker)", "number": 3}))
    assert r.params == {"note": "<own p-value> (not the marker)", "number": 3} and r.p_value == 0.2


def test_merge_record_marks_untestable_with_its_reason():
    r = CauseResult("vignette", "photometric", True, reason="before", p_value=0.01)
    merge_record(r, PlaceboRecord(None, untestable=True, reason="coverage explains it"))
    assert (r.testable, r.reason, r.p_value) == (False, "coverage explains it", 0.01)
    r2 = CauseResult("vignette", "photometric", True, reason="before")
    merge_record(r2, PlaceboRecord(0.5, reason="note only"))  # a reason without untestable changes the text only
    assert (r2.testable, r2.reason, r2.p_value) == (True, "note only", 1.0)
    r3 = CauseResult("vignette", "photometric", False, reason="untestable before")
    merge_record(r3, PlaceboRecord(0.5))  # a record never makes a cause testable again
    assert (r3.testable, r3.reason) == (False, "untestable before")


# ============================================================================ TrainedRunEvidence
def test_memo_computes_once_per_function_and_arguments():
    ev = TrainedRunEvidence(small_data(), draws=10, seed=4, noise_variance=assumed_noise_variance)
    calls = []

    def stat(evidence, k=0):
        calls.append((evidence, k))
        return {"k": k}

    def other(evidence, k=0):
        calls.append(("other", k))
        return k

    first = ev.memo(stat, 1)
    assert ev.memo(stat, 1) is first and calls == [(ev, 1)]  # computed once, with the evidence as first argument
    assert ev.memo(stat, 2) == {"k": 2} and len(calls) == 2  # other arguments: another entry
    assert ev.memo(other, 1) == 1 and len(calls) == 3  # another function, same arguments: another entry
    ev.memo(stat, 1), ev.memo(stat, 2), ev.memo(other, 1)
    assert len(calls) == 3
    ev2 = TrainedRunEvidence(ev.data, draws=10, seed=4, noise_variance=assumed_noise_variance)
    ev2.memo(stat, 1)
    assert len(calls) == 4  # the memo belongs to one evidence


def test_evidence_properties_are_computed_once(monkeypatch):
    calls = []
    real = calibration.render_blur

    def counting(data, noise_variance):
        calls.append(1)
        return real(data, noise_variance)

    monkeypatch.setattr(calibration, "render_blur", counting)
    ev = TrainedRunEvidence(small_data(), draws=10, seed=4, noise_variance=assumed_noise_variance)
    fit = ev.photometric_fit  # needs the blur
    assert ev.photometric_fit is fit and ev.blur_px in BLUR_SIGMAS_PX and len(calls) == 1
    assert ev.cells is ev.cells and ev.derangements is ev.derangements
    est, var = ev.frame_estimates
    assert est.shape == (FRAMES, 6) and var.shape == (FRAMES, 6) and ev.frame_estimates[0] is est
    assert len(calls) == 1


def test_rng_streams_are_fresh_seeded_and_distinct():
    data = small_data()
    ev = TrainedRunEvidence(data, draws=10, seed=4, noise_variance=assumed_noise_variance)
    a = ev.rng(15).random(6)
    np.testing.assert_array_equal(ev.rng(15).random(6), a)  # a fresh generator each call
    np.testing.assert_array_equal(a, np.random.default_rng([4, 15]).random(6))
    assert not np.array_equal(ev.rng(22).random(6), a)  # another stream
    other = TrainedRunEvidence(data, draws=10, seed=5, noise_variance=assumed_noise_variance)
    assert not np.array_equal(other.rng(15).random(6), a)  # another round's seed
    assert (ev.draws, ev.seed) == (10, 4)


# ============================================================================ sequential_rank_p
def test_sequential_rank_p_stops_at_the_tenth_exceedance():
    """Two-sided: every third draw is at least as extreme as |t_real| = 2 (a -2.5 counts), so the 10th exceedance comes
    at draw 30: p = 10 / 30 and no draw after it is made."""
    draws = []

    def draw(k):
        draws.append(k)
        return -2.5 if k % 3 == 2 else 0.5

    p, exceed, ts = sequential_rank_p(2.0, draw)
    assert (p, exceed, len(ts)) == (pytest.approx(10 / 30), PLACEBO_STOP, 30)
    assert draws == list(range(30)) and ts[2] == -2.5


def test_sequential_rank_p_without_the_stop_rule_is_the_rank_p_over_n_max():
    p, exceed, ts = sequential_rank_p(3.0, lambda k: 3.0 if k in (4, 17) else 1.0, n_max=99)
    assert (p, exceed, len(ts)) == (pytest.approx(3 / 100), 2, 99)  # ties count as at least as extreme
    p, exceed, ts = sequential_rank_p(5.0, lambda k: 0.0)
    assert (p, exceed, len(ts)) == (pytest.approx(1 / (1 + PLACEBO_MAX)), 0, PLACEBO_MAX)
    assert 1 / (1 + PLACEBO_MAX) == 0.001


def test_sequential_rank_p_one_sided_counts_only_the_upper_tail():
    def draw(k):
        return -4.0 if k % 2 else 1.0  # large negative placebos

    p2, e2, _ = sequential_rank_p(2.0, draw, n_max=50)
    p1, e1, ts1 = sequential_rank_p(2.0, draw, one_sided=True, n_max=50)
    assert (e2, p2) == (10, pytest.approx(10 / 20))  # two-sided: |-4| >= 2 at every odd draw
    assert (e1, p1, len(ts1)) == (0, pytest.approx(1 / 51), 50)  # one-sided: -4 < 2 never counts
    p, e, _ = sequential_rank_p(-1.0, lambda k: -0.5, one_sided=True, n_max=20)
    assert (e, p) == (10, pytest.approx(1.0))  # -0.5 >= -1: every draw exceeds, stop at the 10th


def test_sequential_rank_p_custom_stop():
    p, exceed, ts = sequential_rank_p(1.0, lambda k: 2.0 if k in (1, 6) else 0.0, stop=2, n_max=100)
    assert (p, exceed, len(ts)) == (pytest.approx(2 / 7), 2, 7)


# ============================================================================ beat_placebos
def test_beat_placebos_with_no_placebo_as_large_is_the_student_t_tail():
    p, exceed, p_tail = beat_placebos(4.0, [1.0, -2.0, 3.0])  # |t|: mean 2, sd 1
    z = (4.0 - 2.0) / (1.0 * math.sqrt(1 + 1 / 3))
    assert exceed == 0
    assert p_tail == pytest.approx(sps.t.sf(z, 2), rel=1e-12)
    assert p == p_tail  # no placebo as extreme: the rank p does not enter


def test_beat_placebos_takes_the_larger_of_rank_and_tail():
    p, exceed, p_tail = beat_placebos(-2.5, [1.0, -3.0, 2.0])  # |-3| >= 2.5
    assert exceed == 1
    assert p_tail == pytest.approx(sps.t.sf((2.5 - 2.0) / math.sqrt(4 / 3), 2))
    assert p == pytest.approx(max(2 / 4, p_tail)) and p == pytest.approx(0.5)
    p, exceed, p_tail = beat_placebos(30.0, [1.0, 1.1, 0.9, 1.05, 0.95, 1.0, 1.02, 0.98])
    assert exceed == 0 and p == p_tail < 1e-6


# ============================================================================ Derangements
def test_derangements_have_no_fixed_point_and_are_permutations():
    d = Derangements(7, seed=3)
    for k in range(40):
        perm = d[k]
        assert sorted(perm.tolist()) == list(range(7))
        assert np.all(perm != np.arange(7))


def test_derangements_are_reproducible_per_seed_and_lazy():
    a, b, c = Derangements(9, seed=11), Derangements(9, seed=11), Derangements(9, seed=12)
    late = b[5]  # drawn out of order: the same sequence
    seq_a = [a[k].tolist() for k in range(8)]
    assert late.tolist() == seq_a[5] and [b[k].tolist() for k in range(8)] == seq_a
    assert [c[k].tolist() for k in range(8)] != seq_a
    assert a[3] is a[3]  # kept, not redrawn
    assert len({tuple(p) for p in seq_a}) > 1


def test_derangements_of_two_frames_swap_them():
    d = Derangements(2, seed=0)
    assert all(d[k].tolist() == [1, 0] for k in range(3))


# ============================================================================ photometric helpers
def test_radial_terms_at_block_centres_about_an_off_centre_point():
    """r^2 of the block centre (col 4 + 1.5, row 4 + 1.5) about the centre, over the squared distance to the farthest
    image corner; r^4 = (r^2)^2."""
    H, W, centre = 24, 32, (4.0, 6.0)
    cells = Cells(frame=np.array([0, 0, 1]), row=np.array([2, 0, 5]), col=np.array([5, 1, 7]), n_cols=8)
    r2, r4 = radial_terms(cells, centre, H, W)
    r_max2 = (W - 1 - 4.0) ** 2 + (H - 1 - 6.0) ** 2  # the corner (31, 23)
    expected = np.array([(21.5 - 4) ** 2 + (9.5 - 6) ** 2, (5.5 - 4) ** 2 + (1.5 - 6) ** 2,
                         (29.5 - 4) ** 2 + (21.5 - 6) ** 2]) / r_max2
    np.testing.assert_allclose(r2, expected, rtol=1e-12)
    np.testing.assert_allclose(r4, expected**2, rtol=1e-12)
    r2c, _ = radial_terms(Cells(np.array([0]), np.array([1]), np.array([1]), 2), (5.5, 5.5), 12, 12)
    assert r2c[0] == 0.0  # the block (1, 1) is centred on (5.5, 5.5)


def test_photometric_cells_index_the_fit_cells():
    data = small_data()
    fit = data.photometric()
    cells = photometric_cells(fit)
    assert cells.n_cols == fit.cell_ok.shape[2] and cells.frame.size == fit.n_cells
    np.testing.assert_array_equal(cells.frame, fit.fidx)
    assert np.all(fit.cell_ok[cells.frame, cells.row, cells.col, fit.cidx])


def test_frame_test_drops_non_finite_and_non_positive_variances():
    est = np.array([1.0, 2.0, np.nan, 3.0, 5.0, 4.0])
    var = np.array([1.0, 1.0, 1.0, 0.0, 4.0, np.inf])
    t = frame_test(est, var)
    w = np.array([1.0, 1.0, 0.25])  # frames 0, 1, 4
    e = np.array([1.0, 2.0, 5.0])
    wn = w / w.sum()
    mean = float(wn @ e)
    se = math.sqrt(float(np.sum(wn**2 * (e - mean) ** 2)) * 3 / 2)
    assert (t.df, t.mean, t.se) == (2, pytest.approx(mean), pytest.approx(se))
    assert t.p_value == pytest.approx(2 * sps.t.sf(mean / se, 2))
    ref = frame_t_test(e, 1.0 / np.array([1.0, 1.0, 4.0]))
    assert (t.t, t.p_value) == (pytest.approx(ref.t), pytest.approx(ref.p_value))


@pytest.mark.parametrize("sigma", [0.0, 0.5, 0.8, 1.3])
def test_render_blur_finds_the_blur_of_a_noiseless_render(sigma):
    """predicted = the sharp frames blurred by sigma in linear space, no assumed noise: the sigma found is that one
    (the quantisation correction, ~1e-6 x kernel energy, is far below a 0.1 px step's error on this texture)."""
    case = make_case(None, seed=3, size=SIZE, n_frames=FRAMES)
    ctx = dataclasses.replace(case.context, noise_shot=None, noise_read=None)
    sharp = case.predicted.astype(np.float64)
    blurred = blur_linear_reference(sharp, sigma) if sigma > 0 else sharp
    data = ResidualData(sharp, blurred, ctx, np.arange(FRAMES))
    assert render_blur(data, assumed_noise_variance) == sigma


def test_resolution_matched_blurs_only_the_measurement():
    data = small_data()
    original = data.m.copy()
    assert resolution_matched(data, 0.0) is data
    _ = data.grad
    matched = resolution_matched(data, 0.8)
    np.testing.assert_allclose(matched.m, blur_linear_reference(data.m, 0.8), atol=1e-9)
    assert matched.p is data.p and matched.grad is data.grad
    np.testing.assert_array_equal(matched.usable, data.usable)
    np.testing.assert_array_equal(matched.r, matched.m - data.p)
    np.testing.assert_array_equal(data.m, original)  # the original untouched
    assert not np.allclose(matched.m, data.m)


# ============================================================================ velocity_placebo
def test_velocity_placebo_of_a_strong_time_offset_beats_every_placebo():
    """A 3 ms offset gives t ~ 40 on the true pairing; no permuted pairing comes near it, so the sequential p is its
    floor 1 / (1 + n) and every placebo is drawn. The record's own p is the frame test's (`OWN_P`)."""
    data = small_data("time_offset", 3e-3, seed=2)
    ev = TrainedRunEvidence(data, draws=49, seed=7, noise_variance=assumed_noise_variance)
    cause = CAUSES["time_offset"]
    rec = velocity_placebo(cause, None, ev, n_placebo=49)
    cal = rec.params["calibration"]
    est, info = cause.first_order(data)
    assert cal["first_order_t"] == pytest.approx(frame_t_test(est[:, 0], info[:, 0]).t)
    assert (cal["placebo_exceed"], cal["placebo_n"]) == (0, 49)
    assert rec.p_value == cal["p_value_placebo"] == pytest.approx(1 / 50)
    assert abs(cal["placebo_t_mean"]) < cal["first_order_t"] / 4
    assert rec.params["p_value_frames"] == OWN_P and not rec.untestable
    r = CauseResult("time_offset", "geometric", True, p_value=1e-9)
    merge_record(r, rec)
    assert r.p_value == pytest.approx(0.02) and r.params["p_value_frames"] == 1e-9


def test_velocity_placebo_of_a_null_stops_at_the_tenth_exceedance_reproducibly():
    data = small_data(None, seed=2)
    cause = CAUSES["time_offset"]
    recs = [velocity_placebo(cause, None, TrainedRunEvidence(data, 49, 7, assumed_noise_variance), n_placebo=49)
            for _ in range(2)]
    cal = recs[0].params["calibration"]
    assert recs[0].params == recs[1].params  # the same seed: the same derangements and statistics
    assert cal["placebo_exceed"] == PLACEBO_STOP and cal["placebo_n"] < 49  # stopped early (at draw 32 here) ...
    assert recs[0].p_value == pytest.approx(PLACEBO_STOP / cal["placebo_n"])  # ... so p = h / n
    assert recs[0].p_value > 0.05  # nothing hidden: the real pairing is not exceptional


def test_velocity_placebo_tables_and_rebuilt_regressors_agree(monkeypatch):
    """The placebo statistic from the velocity tables and from the regressors rebuilt with the permuted velocity
    fields (the path of a cause without a velocity basis) give the same record."""
    data = small_data("time_offset", 1e-3, seed=5)
    cause = CAUSES["time_offset"]
    fast = velocity_placebo(cause, None, TrainedRunEvidence(data, 30, 9, assumed_noise_variance), n_placebo=30)
    monkeypatch.setattr(type(cause), "velocity_basis", lambda self, d: None)
    slow = velocity_placebo(cause, None, TrainedRunEvidence(data, 30, 9, assumed_noise_variance), n_placebo=30)
    a, b = fast.params["calibration"], slow.params["calibration"]
    assert (a["placebo_exceed"], a["placebo_n"]) == (b["placebo_exceed"], b["placebo_n"])
    assert fast.p_value == slow.p_value
    assert a["placebo_t_mean"] == pytest.approx(b["placebo_t_mean"], rel=1e-6)
    assert a["placebo_t_sd"] == pytest.approx(b["placebo_t_sd"], rel=1e-6)


def test_velocity_placebo_needs_velocity_and_four_frames():
    data = small_data(None, seed=2)
    ctx = dataclasses.replace(data.ctx, pixel_velocity_px_s=None)
    no_v = ResidualData(data.m, data.p, ctx, data.frames)
    assert velocity_placebo(CAUSES["time_offset"], None, TrainedRunEvidence(no_v, 10, 1, assumed_noise_variance)) is None
    three = ResidualData(data.m[:3], data.p[:3], data.ctx, np.arange(3))
    assert velocity_placebo(CAUSES["time_offset"], None, TrainedRunEvidence(three, 10, 1, assumed_noise_variance)) is None
    four = ResidualData(data.m[:4], data.p[:4], data.ctx, np.arange(4))
    rec = velocity_placebo(CAUSES["time_offset"], None, TrainedRunEvidence(four, 10, 1, assumed_noise_variance),
                           n_placebo=10)
    assert rec is not None and rec.params["calibration"]["placebo_n"] <= 10
