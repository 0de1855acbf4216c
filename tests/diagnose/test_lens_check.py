"""The lens check (egobench.diagnose.lens_check): a run's retention of a lens error, measured by training again
on the recording warped by a known k0 error, decides whether a distortion is testable on the run."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from egobench.diagnose.lens_check import (
    LensWarpedRecording,
    distortion_estimate,
    measure_lens_retention,
    retention_of,
    warped_display,
)
from egobench.diagnose.synthetic import make_case
from egobench.effects.distortion import LENS_RETENTION_FLOOR, DistortionCause, lens_warp, unit_displacement


def _ctx(size: int = 40):
    return SimpleNamespace(principal_point=((size - 1) / 2, (size - 1) / 2 + 3.0), focal_px=0.5 * size,
                           lens_radial_k=None)


def test_the_lens_warp_samples_each_pixel_where_the_lens_moved_its_content_from():
    """On a linear image the cubic-spline warp is exact away from the mirrored edges (whose effect decays by 0.27 a
    pixel): I(x - k d(x)) = I(x) - k (a d_u + b d_v)."""
    H = W = 40
    d = unit_displacement(_ctx(W), H, W)
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    a, b, c = 0.011, -0.007, 0.5
    image = np.stack([a * u + b * v + c] * 3, axis=-1)
    k = 0.03
    out = lens_warp(image, k, d)
    src_u, src_v = u - k * d[..., 0], v - k * d[..., 1]
    inside = (src_u > 6) & (src_u < W - 7) & (src_v > 6) & (src_v < H - 7)
    expected = image[..., 0] - k * (a * d[..., 0] + b * d[..., 1])
    assert inside.sum() > 0.45 * H * W and np.abs(d[inside]).max() * k > 0.5  # the test moves pixels by > 0.5 px
    np.testing.assert_allclose(out[..., 1][inside], expected[inside], atol=2e-6)
    np.testing.assert_allclose(lens_warp(image, 0.0, d), image, atol=1e-12)


def test_a_warped_frame_reads_back_as_the_injected_k0_error():
    """The warp's sign and size are the distortion cause's: the first-order estimate moves by the injected error."""
    case = make_case(None, seed=3, size=48, n_frames=12)
    H, W = case.measured.shape[1:3]
    d = unit_displacement(case.context, H, W)
    k_run = distortion_estimate(case.measured, case.predicted, case.context, 2)
    for k in (0.05, -0.05):
        warped = np.stack([warped_display(m.astype(np.float64), k, d) for m in case.measured])
        moved = distortion_estimate(warped, case.predicted, case.context, 2) - k_run
        assert moved / k == pytest.approx(1.0, abs=0.2)
    assert np.all(warped * 255 == np.round(warped * 255))  # 8-bit, as the camera writes it


def test_the_retention_is_the_retrained_shift_over_the_warps_own():
    assert retention_of(0.01, 0.05, 0.02, 0.04) == pytest.approx(0.25)
    assert retention_of(-0.01, -0.05, -0.03, -0.04) == pytest.approx(0.5)
    assert math.isnan(retention_of(0.01, 0.015, 0.02, 0.04))  # the warp alone moved it by an eighth
    assert math.isnan(retention_of(0.01, -0.05, 0.02, 0.04))  # ... or the other way


@pytest.mark.parametrize("retention, testable", [(None, False), (LENS_RETENTION_FLOOR, True), (0.9, True),
                                                 (LENS_RETENTION_FLOOR - 0.01, False), (math.nan, False)])
def test_a_distortion_is_untestable_on_a_run_that_keeps_too_little_of_a_lens_or_was_not_measured(retention, testable):
    data = SimpleNamespace(ctx=SimpleNamespace(lens_retention=retention))
    reason = DistortionCause().untestable_on_trained_run(data)
    assert (reason is None) == testable
    if not testable:
        assert "radial under-fit" in reason and (("not measured" in reason) == (retention is None))


def test_the_lens_check_trains_the_runs_method_config_and_seed_on_the_warped_frames(tmp_path):
    """End to end on a tiny run: the retrained run has the run's method, seed and config; its images are the
    warped frames; the record's estimates are the estimator's; a second check reuses the retrained run."""
    from egobench.cli import main
    from egobench.data import load_recording
    from egobench.diagnose.sources import run_source

    rec, run = tmp_path / "rec", tmp_path / "run"
    sets = ["n_frames=16", "rectified_size=32", "readout_s=0.01626", "motion=fast"]
    assert main(["simulate", "--kind", "indoor", "--seed", "2", "--out", str(rec), "--no-progress",
                 *[x for s in sets for x in ("--set", s)]]) == 0
    assert main(["train", "--recording", str(rec), "--method", "ours", "--out", str(run), "--preset", "cpu",
                 "--iterations", "30", "--seed", "5", "--set", "max_side=0", "--no-progress"]) == 0
    src = run_source(rec, run, progress=False)
    check = measure_lens_retention(rec, run, src, 0.04, tmp_path / "check", border_px=2)
    mine, theirs = (json.loads((p / "train.json").read_text()) for p in (tmp_path / "check" / "run", run))
    keys = ("method", "seed", "config_hash")
    assert {k: mine[k] for k in keys} == {k: theirs[k] for k in keys}
    assert check["k0_run"] == distortion_estimate(src.measured, src.predicted, src.context, 2)
    d = unit_displacement(src.context, *src.measured.shape[1:3])
    warped = np.stack([warped_display(m, 0.04, d) for m in src.measured])
    assert check["k0_warped"] == distortion_estimate(warped, src.predicted, src.context, 2)
    if check["retention"] is not None:
        assert check["retention"] == pytest.approx(
            (check["k0_retrained"] - check["k0_run"]) / (check["k0_warped"] - check["k0_run"]))
    recording = load_recording(rec, calibration="online")
    lensed = LensWarpedRecording.of(recording, 0.04, d)
    frame = recording.frames[3]
    np.testing.assert_allclose(lensed.load_image(frame).numpy(), warped[3], atol=1e-6)
    stamp = (tmp_path / "check" / "run" / "train.json").stat().st_mtime_ns
    assert measure_lens_retention(rec, run, src, 0.04, tmp_path / "check", border_px=2) == check
    assert (tmp_path / "check" / "run" / "train.json").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="injected_k0"):
        measure_lens_retention(rec, run, src, 0.0, tmp_path / "check0", border_px=2)
    with pytest.raises(ValueError, match="warp.json"):  # the folder's run was trained on another lens
        measure_lens_retention(rec, run, src, 0.05, tmp_path / "check", border_px=2)


def test_a_trained_runs_lens_is_tested_only_after_its_retention_of_twice_the_smallest_testable(tmp_path):
    """`diagnose_trained_run`: the provisional diagnosis gives the run's smallest testable k0 error s; the check
    injects 2 s; the final diagnosis tests a lens exactly when the run keeps enough of it, and is the provisional
    one where it does."""
    from egobench.cli import main
    from egobench.diagnose.core import DiagnosisConfig, diagnose_residuals
    from egobench.diagnose.lens_check import LENS_CHECK_MULTIPLE, PROVISIONAL_RETENTION, diagnose_trained_run
    from egobench.diagnose.sources import run_source

    rec, run = tmp_path / "rec", tmp_path / "run"
    sets = ["n_frames=16", "rectified_size=32", "motion=fast"]
    assert main(["simulate", "--kind", "indoor", "--seed", "4", "--out", str(rec), "--no-progress",
                 *[x for s in sets for x in ("--set", s)]]) == 0
    assert main(["train", "--recording", str(rec), "--method", "ours", "--out", str(run), "--preset", "cpu",
                 "--iterations", "30", "--seed", "1", "--set", "max_side=0", "--no-progress"]) == 0
    src = run_source(rec, run, progress=False)
    cfg = DiagnosisConfig(trained_run=True)
    provisional = diagnose_residuals(src.measured, src.predicted,
                                     replace(src.context, lens_retention=PROVISIONAL_RETENTION), cfg)
    smallest = provisional.model_error["smallest_testable"]["distortion"]["k0_error"]
    d = diagnose_trained_run(rec, run, src, cfg, tmp_path / "check")
    check = d.model_error["lens_check"]
    assert check["smallest_testable_k0"] == abs(smallest)
    assert check["injected_k0"] == LENS_CHECK_MULTIPLE * abs(smallest)
    lens = next(r for r in d.rounds[0] if r.name == "distortion")
    assert lens.testable == check["testable"]
    if check["testable"]:
        assert d.verdict == provisional.verdict
    else:
        assert "of a lens error in its residual" in lens.reason
    untested = diagnose_residuals(src.measured, src.predicted, src.context, cfg)  # no retention measured
    assert not next(r for r in untested.rounds[0] if r.name == "distortion").testable


@pytest.mark.parametrize("retention, testable", [(0.8, True), (0.1, False), (None, False)])
def test_the_final_diagnosis_is_the_provisional_one_or_drops_the_lens_as_the_check_decides(monkeypatch, tmp_path,
                                                                                           retention, testable):
    """`diagnose_trained_run` with the retraining replaced by its record: a testable check returns the provisional
    diagnosis; one below the floor or unmeasurable gives the diagnosis with the lens untestable, saying why."""
    from egobench.diagnose import lens_check
    from egobench.diagnose.core import DiagnosisConfig, diagnose_residuals
    from egobench.diagnose.report import lens_check_lines

    case = make_case("distortion", 0.008, seed=3)
    src = SimpleNamespace(measured=case.measured, predicted=case.predicted, context=case.context)
    cfg = DiagnosisConfig(trained_run=True)
    provisional = diagnose_residuals(case.measured, case.predicted, replace(case.context, lens_retention=1.0), cfg)
    smallest = provisional.model_error["smallest_testable"]["distortion"]["k0_error"]
    asked = []

    def record(rec, run, src, injected, work, border_px, pose_samples, progress):
        asked.append(injected)
        return {"injected_k0": injected, "k0_run": 0.0, "k0_warped": injected, "k0_retrained": 0.0,
                "retention": retention, "floor": LENS_RETENTION_FLOOR, "testable": testable, "retrained_run": "x"}

    monkeypatch.setattr(lens_check, "measure_lens_retention", record)
    d = lens_check.diagnose_trained_run("rec", "run", src, cfg, tmp_path)
    assert asked == [lens_check.LENS_CHECK_MULTIPLE * abs(smallest)]
    lens = next(r for r in d.rounds[0] if r.name == "distortion")
    assert lens.testable == testable
    if testable:
        assert [n.name for n in d.named] == [n.name for n in provisional.named] == ["distortion"]
    else:
        assert "distortion" not in [n.name for n in d.named]
        assert ("unmeasurable share" if retention is None else "keeps 10 %") in lens.reason
    line, = lens_check_lines(d.model_error["lens_check"])
    assert f"{2 * abs(smallest):+.4f} (2 x the smallest testable, {abs(smallest):.4f})" in line
    assert ("a lens is testable" in line) == testable


def test_a_run_without_a_smallest_testable_k0_keeps_its_lens_untested(tmp_path):
    """Where the provisional diagnosis tests no lens (here: its causes leave it out) there is no size to inject:
    no retraining, and the report says why."""
    from egobench.diagnose import lens_check
    from egobench.diagnose.core import DiagnosisConfig
    from egobench.diagnose.report import lens_check_lines

    case = make_case(None, seed=3)
    src = SimpleNamespace(measured=case.measured, predicted=case.predicted, context=case.context)
    causes = tuple(c for c in DiagnosisConfig().causes if c != "distortion")
    d = lens_check.diagnose_trained_run("no-recording", "no-run", src, DiagnosisConfig(trained_run=True, causes=causes),
                                        tmp_path)
    assert d.model_error["lens_check"]["testable"] is False and not (tmp_path / "run").exists()
    assert lens_check_lines(d.model_error["lens_check"]) == [
        "- lens check: the provisional diagnosis gives no smallest testable k0 error; a lens is not testable on this run"]
