"""egobench preprocess on real Aria frames (ADT sample video.vrs) with an MPS folder built by the test.

The MPS folder: the ADT ground-truth trajectory written as closed_loop_trajectory.csv (MPS columns);
semi-dense points and their SLAM-camera observations from the ground-truth SLAM depth maps
(depth_images.vrs, unprojected with the device's SLAM calibrations); an online calibration = the
factory one with the focal 1 % longer (so the two variants differ by a known amount).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

pytest.importorskip("projectaria_tools")

SIZE, FOCAL = 160, 80.0  # small rectified images keep the test fast
MPS_TRAJ_COLUMNS = ["graph_uid", "tracking_timestamp_us", "utc_timestamp_ns", "tx_world_device", "ty_world_device",
                    "tz_world_device", "qx_world_device", "qy_world_device", "qz_world_device", "qw_world_device",
                    "device_linear_velocity_x_device", "device_linear_velocity_y_device",
                    "device_linear_velocity_z_device", "angular_velocity_x_device", "angular_velocity_y_device",
                    "angular_velocity_z_device", "gravity_x_world", "gravity_y_world", "gravity_z_world", "quality_score"]


def _provider(path):
    from projectaria_tools.core import data_provider

    return data_provider.create_vrs_data_provider(str(path))


def _write_mps(adt, mps):
    """closed_loop_trajectory.csv, semidense_points.csv.gz, semidense_observations.csv.gz, online_calibration.jsonl."""
    import dataclasses

    from egobench.data.mps import (CalibrationRecord, SemiDensePoints, read_trajectory, write_online_calibration,
                                   write_semidense_points)
    from egobench.data.preprocess import _factory_calibration

    mps.mkdir(parents=True)
    gt = pd.read_csv(adt / "aria_trajectory.csv")
    gt[MPS_TRAJ_COLUMNS].to_csv(mps / "closed_loop_trajectory.csv", index=False)
    traj = read_trajectory(mps / "closed_loop_trajectory.csv")
    video, depth = _provider(adt / "video.vrs"), _provider(adt / "depth_images.vrs")
    dev = video.get_device_calibration()
    pts, obs, uid = [], [], 0
    for label, stream in (("camera-slam-left", "345-2"), ("camera-slam-right", "345-3")):
        from projectaria_tools.core.stream_id import StreamId

        sid = StreamId(stream)
        cal = _factory_calibration(video, label)
        serial = dev.get_camera_calib(label).get_serial_number()
        slam_sid = video.get_stream_id_from_label(label)
        for k in range(depth.get_num_data(sid)):
            d_img, d_rec = depth.get_image_data_by_index(sid, k)
            d_mm = d_img.to_numpy_array().astype(np.float64)
            t_slam = video.get_image_data_by_index(slam_sid, k)[1].capture_timestamp_ns
            v, u = np.mgrid[10:cal.height - 10:24, 10:cal.width - 10:24]
            u, v = u.reshape(-1), v.reshape(-1)
            d = d_mm[v, u] / 1000.0
            ok = d > 0.1
            rays = cal.camera().unproject(torch.from_numpy(np.stack([u[ok], v[ok]], -1).astype(np.float64))).numpy()
            p_cam = rays / rays[:, 2:3] * d[ok, None]
            T = traj.pose([int(d_rec.capture_timestamp_ns)])[0].numpy() @ cal.T_device_camera
            p_w = p_cam @ T[:3, :3].T + T[:3, 3]
            for (x, y), p in zip(np.stack([u[ok], v[ok]], -1), p_w):
                pts.append((uid, *p))
                obs.append((uid, t_slam // 1000, serial, float(x), float(y)))
                uid += 1
    arr = np.array(pts)
    write_semidense_points(mps / "semidense_points.csv.gz", SemiDensePoints(
        arr[:, 0].astype(np.int64), arr[:, 1:4], np.full(len(arr), 1e-3), np.full(len(arr), 5e-3)))
    pd.DataFrame(obs, columns=["uid", "frame_tracking_timestamp_us", "camera_serial", "u", "v"]).to_csv(
        mps / "semidense_observations.csv.gz", index=False)
    rgb = _factory_calibration(video, "camera-rgb")
    online = dataclasses.replace(rgb, params=rgb.params * np.r_[1.01, np.ones(14)])
    rgb_sid = video.get_stream_id_from_label("camera-rgb")
    times = [video.get_image_data_by_index(rgb_sid, i)[1].capture_timestamp_ns for i in range(3)]
    write_online_calibration(mps / "online_calibration.jsonl",
                             [CalibrationRecord(t // 1000 + 2500, [online]) for t in times])
    return len(arr)


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    from tests.conftest import SHARED_DATA

    adt = SHARED_DATA / "adt_sample"
    if not (adt / "video.vrs").is_file():
        pytest.skip(f"ADT sample not found at {adt}")
    from egobench.data.preprocess import PreprocessOptions, preprocess

    root = tmp_path_factory.mktemp("aria")
    mps = root / "scene" / "mps" / "slam"
    n_points = _write_mps(adt, mps)
    out = root / "scene" / "recording"
    online = preprocess(adt / "video.vrs", mps, out, PreprocessOptions(focal_px=FOCAL, size_px=SIZE), progress=False)
    factory = preprocess(adt / "video.vrs", mps, out, PreprocessOptions(focal_px=FOCAL, size_px=SIZE, factory=True),
                         progress=False)
    return adt, mps, out, online, factory, n_points


def test_layout_times_and_exposure_match_the_vrs(processed):
    adt, mps, out, online, factory, _ = processed
    assert online.name == "camera-rgb-rectified-80-h160" and factory.name == online.name + "-factory-calib"
    for rel in ("transforms.json", "transforms_with_sparse_depth.json", "vignette.png", "mask.png",
                "image_index.png", "closed_loop_trajectory.csv", "semidense_points.csv.gz"):
        assert (online / rel).exists(), rel
    assert (online / "closed_loop_trajectory.csv").resolve() == (mps / "closed_loop_trajectory.csv").resolve()
    frames = json.loads((online / "transforms_with_sparse_depth.json").read_text())["frames"]
    video = _provider(adt / "video.vrs")
    sid = video.get_stream_id_from_label("camera-rgb")
    records = [video.get_image_data_by_index(sid, i)[1] for i in range(video.get_num_data(sid))]
    # frame 0's read start lies 0.1 ms before the ground-truth trajectory starts: skipped, as the authors do
    assert [f["timestamp_read_start"] for f in frames] == [r.capture_timestamp_ns for r in records[1:]]
    for f, r in zip(frames, records[1:]):
        assert f["timestamp"] == r.capture_timestamp_ns + 2_500_000  # 1408 rows: 5 ms readout
        assert f["timestamp_read_end"] == r.capture_timestamp_ns + 5_000_000
        assert f["exposure_duration_s"] == pytest.approx(r.exposure_duration) and f["gain"] == pytest.approx(r.gain)
        assert f["image_path"] == f"images/camera-rgb_{f['timestamp']}.png"


def test_rectification_agrees_with_projectaria(processed):
    import cv2
    from projectaria_tools.core import calibration
    from projectaria_tools.core.sophus import SE3

    from egobench.data.preprocess import _factory_calibration

    adt, _, _, _, factory, _ = processed
    video = _provider(adt / "video.vrs")
    sid = video.get_stream_id_from_label("camera-rgb")
    raw = video.get_image_data_by_index(sid, 1)[0].to_numpy_array()
    src = video.get_device_calibration().get_camera_calib("camera-rgb")
    dst = calibration.get_linear_camera_calibration(SIZE, SIZE, FOCAL, "camera-rgb", src.get_transform_device_camera())
    theirs = calibration.distort_by_calibration(raw, dst, src).astype(np.float64)
    frame = json.loads((factory / "transforms.json").read_text())["frames"][0]
    ours = cv2.cvtColor(cv2.imread(str(factory / frame["image_path"])), cv2.COLOR_BGR2RGB).astype(np.float64)
    valid = cv2.erode((cv2.imread(str(factory / "mask.png"), 0) > 127).astype(np.uint8), np.ones((5, 5))) > 0
    diff = np.abs(ours - theirs)[valid]
    assert valid.mean() > 0.5
    assert diff.max() <= 1, diff.max()  # within one 8-bit level (rounding; measured mean 0.49)
    # the rectified pinhole follows projectaria's linear model: same intrinsics
    assert (frame["fx"], frame["cx"], frame["cy"]) == (FOCAL, (SIZE - 1) / 2, (SIZE - 1) / 2)
    assert dst.get_principal_point().tolist() == [frame["cx"], frame["cy"]]
    # transform_matrix = T_world_device(timestamp) @ T_device_camera (the factory calibration)
    from egobench.data.mps import read_trajectory

    traj = read_trajectory(processed[1] / "closed_loop_trajectory.csv")
    T = traj.pose([frame["timestamp"]])[0].numpy() @ _factory_calibration(video, "camera-rgb").T_device_camera
    np.testing.assert_allclose(np.array(frame["transform_matrix"]), T, atol=1e-12)
    assert SE3  # imported to build projectaria calibrations elsewhere


def test_row_ratios_grow_with_the_raw_row(processed):
    from projectaria_tools.core import calibration

    adt, _, _, online, _, _ = processed
    rtr = np.load(online / "row_time_ratio.npy")
    mask = np.load(online / "row_time_ratio.npy") > 0
    col = rtr[:, SIZE // 2][mask[:, SIZE // 2]]
    assert col.size > SIZE // 2 and np.all(np.diff(col) > 0)
    # at a rectified pixel the ratio is the raw row it samples / (H_raw - 1), by projectaria's own models
    video = _provider(adt / "video.vrs")
    src = video.get_device_calibration().get_camera_calib("camera-rgb")
    p = src.get_projection_params().copy()
    p[0] *= 1.01  # the online calibration of this test
    online_cal = calibration.CameraCalibration("camera-rgb", calibration.CameraModelType.FISHEYE624, p,
                                               src.get_transform_device_camera(), 1408, 1408, None, 90.0, "")
    dst = calibration.get_linear_camera_calibration(SIZE, SIZE, FOCAL)
    for u, v in ((80, 20), (30, 100), (140, 150), (80, 80)):
        raw_uv = online_cal.project(dst.unproject(np.array([u, v], dtype=np.float64)))
        assert rtr[v, u] == pytest.approx(raw_uv[1] / 1407, abs=2e-4)
    idx = np.asarray(__import__("cv2").imread(str(online / "image_index.png"), 0), dtype=np.float64) / 255
    assert np.abs(idx - rtr).max() <= 0.5 / 255 + 1e-6


def test_sparse_depth_comes_from_the_slam_observations(processed):
    adt, mps, _, online, _, n_points = processed
    frames = json.loads((online / "transforms_with_sparse_depth.json").read_text())["frames"]
    pts = pd.read_csv(mps / "semidense_points.csv.gz")
    world = pts[["px_world", "py_world", "pz_world"]].to_numpy()
    for f in frames:
        sd = json.loads((online / f["sparse_depth"]).read_text())
        assert len(sd["u"]) > 20
        T_cw = np.linalg.inv(np.array(f["transform_matrix"]))
        p = world @ T_cw[:3, :3].T + T_cw[:3, 3]
        u = FOCAL * p[:, 0] / p[:, 2] + f["cx"]
        # every listed (u, z) is the projection of some semi-dense point
        for uu, zz in zip(sd["u"][:10], sd["z"][:10]):
            assert np.min(np.abs(u - uu) + np.abs(p[:, 2] - zz)) < 1e-6
    assert n_points > 100


def test_the_folder_loads_and_trains(processed, tmp_path):
    from egobench.data import load_recording
    from egobench.train import TrainConfig, train

    adt, _, out, online, factory, _ = processed
    rec = load_recording(out, "online")
    assert rec.root == online and len(rec.frames) == 2 and len(rec.train_frames) == 1
    assert rec.frames[0].sparse_depth is not None and rec.points_world.shape[0] > 100
    fa = load_recording(online, "factory")  # the factory variant by the authors' naming
    assert fa.root == factory
    # the 1 % longer online focal moves off-axis content: the two variants' images differ
    assert float((rec.load_image(rec.frames[1]) - fa.load_image(fa.frames[1])).abs().mean()) > 1e-3
    res = train(rec, "ours", TrainConfig.cpu().scaled_to(3), tmp_path / "run", progress=False)
    assert res.iterations == 3 and res.num_gaussians > 0


def test_missing_projectaria_is_a_clear_error(monkeypatch):
    import sys

    from egobench.data import preprocess

    monkeypatch.setitem(sys.modules, "projectaria_tools.core", None)
    with pytest.raises(ValueError, match=r"needs projectaria-tools .*pip install projectaria-tools==2\.3\.0"):
        preprocess._projectaria()


def test_missing_mps_file_is_named(processed, tmp_path):
    from egobench.data.preprocess import PreprocessOptions, preprocess

    adt, mps, _, _, _, _ = processed
    empty = tmp_path / "slam"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match=r"slam/closed_loop_trajectory\.csv: trajectory file not found"):
        preprocess(adt / "video.vrs", empty, tmp_path / "out", PreprocessOptions(focal_px=FOCAL, size_px=SIZE))


def test_interrupted_preprocess_resumes_to_the_same_folder(processed, tmp_path, monkeypatch):
    from egobench.data import preprocess as pp

    adt, mps, _, online, _, _ = processed
    out = tmp_path / "recording"
    real, calls = pp._process_frame, []

    def interrupted(i, *args, **kwargs):
        calls.append(i)
        if len(calls) == 3:  # frame 2, after frames 0 (skipped: outside the trajectory) and 1
            raise KeyboardInterrupt
        return real(i, *args, **kwargs)

    monkeypatch.setattr(pp, "_process_frame", interrupted)
    opts = pp.PreprocessOptions(focal_px=FOCAL, size_px=SIZE)
    with pytest.raises(KeyboardInterrupt):
        pp.preprocess(adt / "video.vrs", mps, out, opts, progress=False)
    assert not (out / online.name).exists()
    calls.clear()
    final = pp.preprocess(adt / "video.vrs", mps, out, opts, progress=False)
    assert calls == [2]  # frames 0 and 1 were finished by the first run
    assert not list(tmp_path.glob(".*partial"))
    for rel in ("transforms_with_sparse_depth.json", "image_index.png", "vignette.png"):
        assert (final / rel).read_bytes() == (online / rel).read_bytes(), rel
    for f in json.loads((final / "transforms.json").read_text())["frames"]:
        assert (final / f["image_path"]).read_bytes() == (online / f["image_path"]).read_bytes()
