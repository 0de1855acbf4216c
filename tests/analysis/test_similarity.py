"""egobench.analysis.similarity: analytic checks of each measure, and the verb on a tiny simulated recording."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from egobench.analysis import similarity as sim_measures
from egobench.camera.pinhole import Pinhole
from egobench.data.mps import CameraCalibration
from egobench.data.recording import Frame, Recording, SparseDepth


# ----------------------------------------------------------------------------------------
# an in-memory recording yawing at a known rate, points on the image's centre column
# ----------------------------------------------------------------------------------------
def _yaw_recording(root: Path, omega_rad_s: float, readout_s: float, size: int = 32, n_frames: int = 3,
                   exposures=None, gains=None) -> Recording:
    from egobench.sim.plane import TwistTrajectory

    f = 0.9 * size
    cam = Pinhole(fx=f, fy=f, cx=(size - 1) / 2, cy=(size - 1) / 2, width=size, height=size)
    traj = TwistTrajectory(torch.eye(4, dtype=torch.float64),
                           torch.tensor([0, 0, 0, 0, omega_rad_s, 0], dtype=torch.float64), 1_000_000_000)
    v = np.arange(2.0, size - 2.0, 3.0)
    uv = np.stack([np.full_like(v, cam.cx), v], -1)
    frames = []
    for i in range(n_frames):
        ts = 1_000_000_000 + i * 50_000_000
        rs = ts - int(readout_s * 1e9 / 2)
        frames.append(Frame(
            index=i, image_path=root / "images" / f"{i:05d}.png", timestamp_ns=ts, read_start_ns=rs,
            read_end_ns=rs + int(round(readout_s * 1e9)), exposure_s=1e-3 if exposures is None else exposures[i],
            gain=1.0 if gains is None else gains[i], T_world_camera=traj.pose(torch.tensor([ts]))[0],
            T_device_camera=torch.eye(4, dtype=torch.float64),
            sparse_depth=SparseDepth(uv=uv, z=np.full(len(v), 3.0), inv_dist_std=np.full(len(v), 1e-3),
                                     dist_std=np.full(len(v), 1e-3))))
    return Recording(root=root, name="yaw", calibration="online", camera=cam, camera_model="linear", frames=frames,
                     vignette=torch.ones(size, size), mask=torch.ones(size, size, dtype=torch.bool),
                     row_time_ratio=(torch.arange(size, dtype=torch.float32) / (size - 1))[:, None].expand(size, size),
                     trajectory=traj, points_world=torch.zeros(1, 3))


def _yaw_shift_px(f: float, omega: float, before_s: float, after_s: float) -> float:
    """A point on the centre column at the centre time: bearing +w before_s at read start and -w after_s at
    read end (yaw about the camera's y axis), so it moves f (tan(w before_s) + tan(w after_s)) pixels."""
    return f * (math.tan(omega * before_s) + math.tan(omega * after_s))


def test_rs_shift_of_a_pure_yaw_is_about_f_omega_readout(tmp_path):
    omega, readout = 3.0, 0.01626
    rec = _yaw_recording(tmp_path, omega, readout)
    expected = _yaw_shift_px(rec.camera.fx, omega, readout / 2, readout / 2)
    assert expected == pytest.approx(rec.camera.fx * omega * readout, rel=1e-3)
    shifts = sim_measures.rs_shift_px(rec)
    assert shifts.size == len(rec.frames) * len(rec.frames[0].sparse_depth.z)
    np.testing.assert_allclose(shifts, expected, rtol=1e-6)
    # pixel quantities scale with the training resolution
    np.testing.assert_allclose(sim_measures.rs_shift_px(rec, pixel_scale=2.0), 2 * expected, rtol=1e-6)


def test_view_readout_span_is_the_row_time_range_of_the_valid_pixels(tmp_path):
    """A view reading rows from R = 0 to 1 spans the whole readout; one whose valid pixels read only
    R in [0.4, 0.6] (a narrow view of a tall sensor) sees a fifth of the shift between its rows."""
    import dataclasses

    rec = _yaw_recording(tmp_path, 3.0, 0.01626)
    assert sim_measures.view_readout_span(rec) == pytest.approx(1.0)
    size = rec.mask.shape[0]
    band = 0.4 + 0.2 * torch.arange(size, dtype=torch.float32)[:, None].expand(size, size) / (size - 1)
    mask = rec.mask.clone()
    mask[0] = False  # an invalid row outside the band does not count
    band[0] = 0.0
    narrow = dataclasses.replace(rec, row_time_ratio=band, mask=mask)
    assert sim_measures.view_readout_span(narrow) == pytest.approx(0.2 * (size - 2) / (size - 1), rel=1e-5)


def test_rs_shift_uses_the_true_readout_when_the_truth_has_one(tmp_path):
    omega, stated, true = 3.0, 0.01, 0.02
    rec = _yaw_recording(tmp_path, omega, stated)
    truth = {"hidden_effects": {"readout_true_s": true},
             "frames": [{"index": f.index, "read_start_true_ns": f.read_start_ns + 3_000_000} for f in rec.frames]}
    shifts = sim_measures.rs_shift_px(rec, truth)
    # true read start 3 ms after the stated one: 2 ms before the centre time, read end 18 ms after it
    np.testing.assert_allclose(shifts, _yaw_shift_px(rec.camera.fx, omega, 2e-3, 18e-3), rtol=1e-6)


def test_trajectory_rs_shift_of_a_sideways_translation_is_f_v_readout_over_depth():
    from egobench.sim.plane import TwistTrajectory

    v, depth, readout, f = 2.0, 4.0, 0.01626, 1200.0
    traj = TwistTrajectory(torch.eye(4, dtype=torch.float64), torch.tensor([v, 0, 0, 0, 0, 0], dtype=torch.float64), 0)
    traj.start_ns, traj.end_ns = 0, 1_000_000_000
    shifts = sim_measures.trajectory_rs_shift_px(traj, np.eye(4), focal_px=f, readout_s=readout, depth_m=depth)
    assert shifts.size > 0.9 * 10 * 300  # a few points leave the image
    np.testing.assert_allclose(shifts, f * v * readout / depth, rtol=1e-6)


def test_the_paper_scale_rolling_shutter_numbers_come_from_the_real_walk(shared_data):
    from egobench.data.mps import read_online_calibration
    from egobench.geometry.trajectory import Trajectory

    folder = shared_data / "aria_mps_sample"
    traj = Trajectory.from_mps_csv(folder / "closed_loop_trajectory.csv")
    T_dc = read_online_calibration(folder / "online_calibration.jsonl")[0].camera("camera-rgb").T_device_camera
    shifts = sim_measures.trajectory_rs_shift_px(traj, T_dc, depth_m=3.0)
    paper = sim_measures.paper_operating_point()
    assert float(np.percentile(shifts, 90)) == pytest.approx(paper["rs_shift_px_p90"]["value"], abs=0.05)
    assert f"gives {np.median(shifts):.1f} px" in paper["rs_shift_px_median"]["source"]


def test_motion_samples_follow_the_released_code_rule(tmp_path):
    # 2 ms window shift of a centre-column point: f (tan(w 1ms) + tan(w 1ms)); N = int(R / 2ms * shift)
    omega, readout = 10.0, 0.01626
    rec = _yaw_recording(tmp_path, omega, readout)
    shift_2ms = 2 * rec.camera.fx * math.tan(omega * 1e-3)
    for scale in (1.0, 0.5):
        out = sim_measures.motion_samples(rec, pixel_scale=scale)
        n = int(readout / 2e-3 * shift_2ms * scale)
        assert n > 1
        assert out["motion_samples_per_frame"] == [n] * len(rec.train_frames)
        assert out["motion_samples_median"] == n and out["frac_frames_multi_sample"] == 1.0
    static = sim_measures.motion_samples(_yaw_recording(tmp_path, 0.0, readout))
    assert static["frac_frames_multi_sample"] == 0.0 and static["motion_samples_median"] == 1


def test_exposure_ratio_and_scene_dynamic_range(tmp_path):
    rec = _yaw_recording(tmp_path, 0.0, 0.01, exposures=[1e-3, 2e-3, 0.5e-3], gains=[1.0, 4.0, 2.0])
    assert sim_measures.exposure_ratio(rec) == pytest.approx(8.0)
    assert sim_measures.scene_dynamic_range_stops(rec) is None  # no ground truth
    gt = tmp_path / "ground_truth" / "radiance"
    gt.mkdir(parents=True)
    for f in rec.frames:  # half the pixels at 1, half at 1024 (grey): 10 stops between p1 and p99
        rad = np.ones((32, 32, 3), np.float16)
        rad[:, 16:] = 1024.0
        np.save(gt / f"{f.index:05d}.npy", rad)
    rec.ground_truth = tmp_path / "ground_truth"
    assert sim_measures.scene_dynamic_range_stops(rec) == pytest.approx(10.0, abs=1e-6)
    rec.mask[:, 16:] = False  # the bright half invalid: no range left
    assert sim_measures.scene_dynamic_range_stops(rec) == pytest.approx(0.0, abs=1e-9)


# ----------------------------------------------------------------------------------------
# calibration reprojection
# ----------------------------------------------------------------------------------------
_DISTORTION = [0.41, -0.47, 0.04, 1.30, -1.77, 0.65, 1e-4, 6e-4, -1e-3, 6e-4, -2e-3, 1.6e-3]


def _cal(T: np.ndarray, focal: float = 33.3, distortion=None) -> CameraCalibration:
    params = np.array([focal, 38.0, 38.0] + list(np.zeros(12) if distortion is None else distortion))
    return CameraCalibration(label="camera-rgb", params=params, width=77, height=77, T_device_camera=T)


def _rot_y(angle: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return T


def _grid_points(n: int = 7, depth: float = 4.0) -> torch.Tensor:
    x = torch.linspace(-0.8, 0.8, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(x, x, indexing="xy")
    return torch.stack([gx.reshape(-1), gy.reshape(-1), torch.ones(n * n, dtype=torch.float64)], -1) * depth


def test_identical_calibrations_have_zero_reprojection_error():
    pin = Pinhole(fx=32, fy=32, cx=31.5, cy=31.5, width=64, height=64)
    T = _rot_y(0.3)
    T[:3, 3] = [0.01, -0.02, 0.003]
    cal = _cal(T, distortion=_DISTORTION)
    P = _grid_points() @ torch.as_tensor(T[:3, :3]).T + torch.as_tensor(T[:3, 3])  # in front of the camera
    err = sim_measures.calibration_reprojection_px(P, cal, cal, pin)
    assert bool(torch.isfinite(err).all())
    assert float(err.max()) < 1e-6


@pytest.mark.parametrize("fisheye", [True, False])
def test_a_rotation_offset_reprojects_to_f_tan_angle(fisheye):
    pin = Pinhole(fx=32, fy=32, cx=31.5, cy=31.5, width=64, height=64)
    angle = math.radians(2.0)
    ref, test = np.eye(4), _rot_y(angle)  # test = reference rotated by 2 deg about the camera's y axis
    if fisheye:
        ref, test = _cal(ref, distortion=_DISTORTION), _cal(test, distortion=_DISTORTION)
    on_axis = torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64)
    err = sim_measures.calibration_reprojection_px(on_axis, ref, test, pin)
    assert float(err[0]) == pytest.approx(32 * math.tan(angle), rel=1e-6)


def test_a_focal_error_reprojects_by_the_equidistant_formula():
    # equidistant fisheye (no distortion): a point at bearing theta sits at raw radius f theta; the
    # test calibration (focal f (1 + e)) reads it as theta / (1 + e)
    pin = Pinhole(fx=32, fy=32, cx=31.5, cy=31.5, width=64, height=64)
    eps, theta = 0.02, math.radians(30)
    ref, test = _cal(np.eye(4), 33.3), _cal(np.eye(4), 33.3 * (1 + eps))
    P = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=torch.float64) * 3
    err = sim_measures.calibration_reprojection_px(P, ref, test, pin)
    expected = 32 * (math.tan(theta) - math.tan(theta / (1 + eps)))
    assert float(err[0]) == pytest.approx(expected, rel=1e-6)


# ----------------------------------------------------------------------------------------
# content: spectrum and misregistration
# ----------------------------------------------------------------------------------------
def test_white_noise_spectrum_is_flat_with_most_power_above_half_nyquist():
    rng = np.random.default_rng(0)
    freq = power = None
    for _ in range(8):
        freq, p = sim_measures.power_spectrum(rng.normal(size=(128, 128)))
        power = p if power is None else power + p
    hf, slope = sim_measures.spectrum_measures(freq, power)
    assert hf == pytest.approx(1 - math.pi / 16, abs=0.02)  # the square's area outside the r = 1/4 disc
    assert abs(slope) < 0.15


def test_smooth_and_one_over_f_images():
    y, x = np.mgrid[0:64, 0:64]
    blob = np.exp(-((x - 30.0) ** 2 + (y - 34.0) ** 2) / (2 * 8.0 ** 2))
    hf, slope = sim_measures.spectrum_measures(*sim_measures.power_spectrum(blob))
    assert hf < 1e-4 and slope < -4
    # amplitude 1/f noise (power 1/f^2): the natural-image slope
    rng = np.random.default_rng(1)
    f = np.sqrt(np.fft.fftfreq(256)[:, None] ** 2 + np.fft.fftfreq(256)[None, :] ** 2)
    f[0, 0] = np.inf  # no DC
    freq = power = None
    for _ in range(4):
        img = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(256, 256))) / f))
        freq, p = sim_measures.power_spectrum(img)
        power = p if power is None else power + p
    hf, slope = sim_measures.spectrum_measures(freq, power)
    assert slope == pytest.approx(-2.0, abs=0.15)


def test_ideal_hf_fraction_is_the_mean_over_one_over_f_fields():
    n = 64
    f = np.sqrt(np.fft.fftfreq(n)[:, None] ** 2 + np.fft.fftfreq(n)[None, :] ** 2)
    f[0, 0] = np.inf
    rng = np.random.default_rng(2)
    freq = power = None
    for _ in range(400):  # the total is dominated by a few low-frequency modes: average many fields
        img = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(n, n))) / f))
        freq, p = sim_measures.power_spectrum(img)
        power = p if power is None else power + p
    hf, _ = sim_measures.spectrum_measures(freq, power)
    assert hf == pytest.approx(sim_measures.ideal_hf_fraction(n), abs=0.006)
    assert sim_measures.ideal_hf_fraction(n) > sim_measures.ideal_hf_fraction(4 * n)  # not scale invariant
    assert sim_measures.ideal_hf_fraction(2400) == pytest.approx(sim_measures.IDEAL_HF_FRACTION_2400, abs=5e-5)


def test_misregistration_psnr_of_a_ramp():
    a = 0.01
    img = np.repeat((a * np.arange(40.0))[None, :], 30, axis=0)  # horizontal ramp: MSE a^2 one way, 0 the other
    assert sim_measures.misregistration_psnr_db(img) == pytest.approx(-10 * math.log10(a * a / 2))
    mask = np.ones(img.shape, bool)
    mask[:, 20:] = False
    img_masked = img.copy()
    img_masked[:, 20:] = 1.0  # outside the mask: must not count
    assert sim_measures.misregistration_psnr_db(img_masked, mask) == pytest.approx(-10 * math.log10(a * a / 2))


# ----------------------------------------------------------------------------------------
# a tiny simulated recording: the verb end to end
# ----------------------------------------------------------------------------------------
_ZERO_ONLINE = {"online_rotation_deg": 0.0, "online_translation_mm": 0.0, "online_focal_frac": 0.0,
                "online_principal_px": 0.0, "online_time_offset_s": 0.0}
_ROTATION_ONLY_FACTORY = {"factory_rotation_deg": 2.0, "factory_translation_mm": 0.0, "factory_focal_frac": 0.0,
                          "factory_principal_px": 0.0, "factory_time_offset_s": 0.0}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A 32 px, 6-frame outdoor recording at fixed exposure, online = true calibration, factory =
    true rotated by 2 deg; and the verb's outputs on it."""
    from egobench.cli import main
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    cfg = SimConfig.from_overrides("outdoor", 0, {"n_frames": 6, "rectified_size": 32, "motion": "fast",
                                                  "readout_s": 0.01626, "exposure_s": 1e-3, "gain": 2.0,
                                                  "n_semidense_points": 3000, **_ZERO_ONLINE,
                                                  **_ROTATION_ONLY_FACTORY})
    root = tmp_path_factory.mktemp("similarity")
    simulate_recording(cfg, root / "rec", progress=False)
    out = root / "sim.json"
    assert main(["similarity", str(root / "rec"), "--out", str(out), "--csv", str(root / "sim.csv"),
                 "--table", str(root / "sim.md")]) == 0
    assert main(["similarity", str(root / "rec"), "--out", str(root / "sim64.json"), "--resolution", "64"]) == 0
    return root


def test_simulated_calibration_errors_match_the_drawn_rotation(simulated):
    from egobench.data.reader import load_recording
    from egobench.geometry import so3_exp
    from egobench.model.motion_sampling import sparse_points_camera

    res = json.loads((simulated / "sim.json").read_text())["recordings"][0]
    truth = json.loads((simulated / "rec" / "ground_truth" / "truth.json").read_text())
    err = truth["calibration_errors"]["factory"]
    R_err = so3_exp(torch.tensor(err["rotation_axis"], dtype=torch.float64) * math.radians(err["rotation_deg"]))
    rec = load_recording(simulated / "rec", "online")
    # independent expectation: same intrinsics, so only the camera rotation moves the point
    expected = []
    for f in rec.frames:
        X = sparse_points_camera(rec, f)
        u0, _ = rec.camera.project(X)
        u1, _ = rec.camera.project(X @ R_err)  # R_err^T X, row vectors
        expected.append((u0 - u1).norm(dim=-1))
    expected = torch.cat(expected).numpy()
    assert res["calib_error_method"].startswith("fisheye")
    assert res["calib_error_px_median"] == pytest.approx(float(np.median(expected)), rel=1e-4)
    assert res["calib_error_px_p90"] == pytest.approx(float(np.percentile(expected, 90)), rel=1e-4)
    assert res["calib_error_online_vs_true_px_median"] == pytest.approx(0.0, abs=1e-6)
    assert res["calib_error_factory_vs_true_px_median"] == pytest.approx(res["calib_error_px_median"], rel=1e-6)
    # a constant 2 deg rotation: most of it is absorbed, and what is left is a fraction of the error
    assert res["calib_inconsistency_n_points"] > 0
    assert 0 < res["calib_inconsistency_px_median"] < 0.8 * res["calib_error_px_median"]
    assert res["calib_unabsorbed_fraction"] == pytest.approx(
        res["calib_inconsistency_px_median"] / res["calib_error_as_trained_px_median"], rel=0.2)


def test_simulated_exposure_truth_and_resolution_scaling(simulated):
    res = json.loads((simulated / "sim.json").read_text())["recordings"][0]
    res64 = json.loads((simulated / "sim64.json").read_text())["recordings"][0]
    assert res["exposure_ratio"] == pytest.approx(1.0)  # fixed exposure and gain
    assert res["rs_shift_source"].startswith("true clocks") and res["rs_shift_n_points"] > 0
    assert res["scene_dynamic_range_stops"] > 0
    assert res["texture_hf_fraction_clean"] is not None and res["texture_spectral_slope_clean"] < 0
    for key in ("rs_shift_px_median", "rs_shift_px_p90", "calib_error_px_median", "calib_error_px_p90",
                "calib_inconsistency_px_median", "calib_inconsistency_px_p90"):
        assert res64[key] == pytest.approx(2 * res[key], rel=1e-9)  # pixel quantities: x 64 / 32
    assert res64["resolution_px"] == 64 and res64["pixel_scale"] == 2.0
    assert res64["texture_hf_fraction"] is None and "exceeds the rectified width" in res64["content_note"]


def test_without_the_simulators_extra_files_the_measures_fall_back(simulated, tmp_path):
    # a copy holding only what a real preprocessed recording has: the two streams and the MPS files
    import shutil

    copy = tmp_path / "rec"
    shutil.copytree(simulated / "rec", copy, symlinks=True)
    shutil.rmtree(copy / "ground_truth")
    (copy / "factory_calibration.json").unlink()
    (copy / "recording.json").unlink()
    res = sim_measures.measure_recording(copy)
    ref = json.loads((simulated / "sim.json").read_text())["recordings"][0]
    assert res["calib_error_method"] == "rectified streams' extrinsics only"
    assert res["calib_error_online_vs_true_px_median"] is None and res["scene_dynamic_range_stops"] is None
    assert res["texture_hf_fraction_clean"] is None and res["rs_shift_source"] == "stream's stated clocks"
    # the factory calibration differs from the (true) online one by a rotation only, and the online
    # stream's stated clocks are the true ones: extrinsics alone and stated clocks give the same numbers
    for key in ("calib_error_px_median", "calib_error_px_p90", "rs_shift_px_median", "rs_shift_px_p90",
                "calib_inconsistency_px_median", "calib_inconsistency_px_p90"):
        assert res[key] == pytest.approx(ref[key], rel=1e-4)


def test_verb_outputs_carry_every_key(simulated):
    doc = json.loads((simulated / "sim.json").read_text())
    assert doc["schema"] == sim_measures.SCHEMA
    (res,) = doc["recordings"]
    assert set(sim_measures.METRIC_KEYS) <= set(res)
    assert set(doc["paper"]) <= set(sim_measures.METRIC_KEYS)
    rows = list(csv.DictReader((simulated / "sim.csv").open()))
    assert len(rows) == 1 and float(rows[0]["rs_shift_px_median"]) == pytest.approx(res["rs_shift_px_median"])
    table = (simulated / "sim.md").read_text()
    assert table.count("\n") == 2 + len(sim_measures.HOW_MEASURED)
    assert f"| `calib_error_px_median` | 4.2 px | outdoor_0 {res['calib_error_px_median']:.3g} |" in table


def test_missing_recording_is_a_one_line_error(tmp_path, capsys):
    from egobench.cli import main

    assert main(["similarity", str(tmp_path / "nope"), "--out", str(tmp_path / "x.json")]) == 2
    assert "recording folder not found" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_display_levels_are_the_median_luminance_and_the_dark_fraction_of_valid_pixels():
    grey = np.array([0.05, 0.08, 0.3, 0.5, 0.9, 0.02])  # one row of grey pixels; the last one masked out
    img = np.repeat(grey[None, :, None], 3, axis=2)
    mask = np.array([[True] * 5 + [False]])
    out = sim_measures.display_levels([img, img], [mask, mask])
    assert out["display_level_median"] == pytest.approx(0.3) and out["dark_pixel_fraction"] == pytest.approx(0.4)
    with pytest.raises(ValueError, match="no valid pixel"):
        sim_measures.display_levels([img], [np.zeros_like(mask)])


def test_the_paper_scale_display_levels_come_from_real_aria_frames(shared_data):
    """The paper value of display_level_median / dark_pixel_fraction is what the ADT sample's real frames give."""
    pytest.importorskip("projectaria_tools")
    from egobench.diagnose.adt import read_rgb_frames

    images, _, exposure_s, gain, _ = read_rgb_frames(shared_data / "adt_sample" / "video.vrs")
    n, h, w = images.shape[:3]
    yy, xx = np.mgrid[:h, :w]
    circle = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (0.45 * w) ** 2
    out = sim_measures.display_levels(list(images.astype(np.float64) / 255), [circle] * n)
    paper = sim_measures.paper_operating_point()
    assert round(out["display_level_median"], 2) == paper["display_level_median"]["value"]
    assert round(out["dark_pixel_fraction"], 2) == paper["dark_pixel_fraction"]["value"]
    assert np.all(gain == 16.0) and np.all(exposure_s > 8e-3)  # auto-exposure at its limit, as the source says
