"""MPS files, the authors' transforms.json format and load_recording's error handling."""

from __future__ import annotations

import gzip
import json
import shutil

import numpy as np
import pandas as pd
import pytest
import torch

from egobench.data.mps import (SemiDensePoints, read_online_calibration, read_semidense_points, read_trajectory,
                               write_online_calibration, write_semidense_points)


# ---------------------------------------------------------------------------------- real MPS files
def test_real_mps_sample_parses(shared_data):
    d = shared_data / "aria_mps_sample"
    traj = read_trajectory(d / "closed_loop_trajectory.csv")
    assert len(traj) > 10000 and 11.0 < traj.duration_s < 12.0
    pts_all = read_semidense_points(d / "semidense_points.csv.gz", filter=False)
    pts = read_semidense_points(d / "semidense_points.csv.gz")
    df = pd.read_csv(d / "semidense_points.csv.gz")
    assert len(pts_all) == len(df)
    assert len(pts) == int(((df.inv_dist_std < 0.01) & (df.dist_std < 0.02)).sum())
    recs = read_online_calibration(d / "online_calibration.jsonl")
    assert len(recs) == 115
    rgb = recs[0].camera("camera-rgb")
    assert (rgb.width, rgb.height) == (1408, 1408) and rgb.readout_s == pytest.approx(0.005, abs=1e-9)
    assert rgb.time_offset_s == pytest.approx(-0.0025, abs=1e-6)
    assert rgb.params[0] == pytest.approx(609.0993041992188)
    # round trip through our writer keeps the RGB camera
    assert recs[0].to_json()["ImageSizes"][2] == [1408, 1408]


def test_semidense_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    pts = SemiDensePoints(uid=np.arange(5), points_world=rng.normal(size=(5, 3)),
                          inv_dist_std=np.array([0.001, 0.02, 0.005, 0.009, 0.0001]),
                          dist_std=np.array([0.01, 0.01, 0.03, 0.019, 0.001]))
    path = tmp_path / "semidense_points.csv.gz"
    write_semidense_points(path, pts)
    back = read_semidense_points(path, filter=False)
    np.testing.assert_allclose(back.points_world, pts.points_world, atol=1e-6)
    assert read_semidense_points(path).uid.tolist() == [0, 3, 4]
    text = gzip.open(path, "rt").read().splitlines()
    text[3] = text[3].replace(text[3].split(",")[2], "nan")
    bad = tmp_path / "bad.csv.gz"
    with gzip.open(bad, "wt") as fh:
        fh.write("\n".join(text) + "\n")
    with pytest.raises(ValueError, match=r"bad\.csv\.gz: line 4, column 'px_world'"):
        read_semidense_points(bad)
    missing = tmp_path / "missing_col.csv"
    missing.write_text("uid,px_world\n1,2\n")
    with pytest.raises(ValueError, match="missing column"):
        read_semidense_points(missing)


def test_online_calibration_errors_name_the_line(tmp_path, shared_data):
    src = shared_data / "aria_mps_sample" / "online_calibration.jsonl"
    lines = src.read_text().splitlines()[:3]
    p = tmp_path / "online_calibration.jsonl"
    p.write_text("\n".join([lines[0], lines[1][: len(lines[1]) // 2], lines[2]]) + "\n")
    with pytest.raises(ValueError, match=r"online_calibration\.jsonl: line 2: not valid JSON"):
        read_online_calibration(p)
    obj = json.loads(lines[0])
    obj["CameraCalibrations"][2]["Projection"]["Params"] = obj["CameraCalibrations"][2]["Projection"]["Params"][:10]
    p.write_text(json.dumps(obj) + "\n")
    with pytest.raises(ValueError, match=r"line 1, camera 2.*Params: expected 15"):
        read_online_calibration(p)
    recs = read_online_calibration(src)[:2]
    out = tmp_path / "rt.jsonl"
    write_online_calibration(out, recs)
    back = read_online_calibration(out)
    np.testing.assert_allclose(back[1].camera("camera-rgb").T_device_camera, recs[1].camera("camera-rgb").T_device_camera,
                               atol=1e-12)
    assert back[0].camera("camera-rgb").readout_s == pytest.approx(recs[0].camera("camera-rgb").readout_s)


# ---------------------------------------------------------------------------------- recordings
@pytest.fixture(scope="module")
def rec_dir(tmp_path_factory):
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    cfg = SimConfig.from_overrides("object", 2, {"n_frames": 6, "rectified_size": 32, "n_semidense_points": 1500})
    out = tmp_path_factory.mktemp("rec") / "object_2"
    simulate_recording(cfg, out, progress=False)
    return out


@pytest.fixture
def copy_rec(rec_dir, tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(rec_dir, dst)
    return dst


def test_load_authors_folder_directly(rec_dir):
    from egobench.data import load_recording

    rec = load_recording(rec_dir / "online")  # transforms.json folder: trajectory from ../mps/
    assert len(rec.frames) == 6 and rec.points_world.shape[1] == 3 and rec.points_world.shape[0] > 0
    img = rec.load_image(rec.frames[0])
    assert img.shape == (32, 32, 3) and 0 < float(img.mean()) < 1


def _edit_transforms(root, fn):
    p = root / "online" / "transforms.json"
    obj = json.loads(p.read_text())
    fn(obj)
    p.write_text(json.dumps(obj))


def test_missing_image_names_file_and_frame(copy_rec):
    from egobench.data import load_recording

    (copy_rec / "online" / "images" / "00003.png").unlink()
    with pytest.raises(ValueError, match=r"transforms\.json: frame 3 .*00003\.png.*missing"):
        load_recording(copy_rec, "online")
    load_recording(copy_rec, "factory")  # the other calibration is intact


def test_truncated_transforms_names_file(copy_rec):
    from egobench.data import load_recording

    p = copy_rec / "online" / "transforms.json"
    p.write_text(p.read_text()[:-200])
    with pytest.raises(ValueError, match=r"online/transforms\.json: not valid JSON"):
        load_recording(copy_rec, "online")


def test_nan_pose_names_frame(copy_rec):
    from egobench.data import load_recording

    def poison(obj):
        obj["frames"][2]["transform_matrix"][0][3] = float("nan")

    _edit_transforms(copy_rec, poison)
    with pytest.raises(ValueError, match=r"frame 2 .*transform_matrix.*NaN"):
        load_recording(copy_rec, "online")


def test_out_of_span_timestamp_names_frame(copy_rec):
    from egobench.data import load_recording

    def shift(obj):
        f = obj["frames"][4]
        for k in ("timestamp", "timestamp_read_start", "timestamp_read_end"):
            f[k] += 10**10  # 10 s later: past the trajectory's end

    _edit_transforms(copy_rec, shift)
    with pytest.raises(ValueError, match=r"frame 4 .*outside the trajectory span"):
        load_recording(copy_rec, "online")


def test_missing_field_and_bad_calibration_name(copy_rec):
    from egobench.data import load_recording

    _edit_transforms(copy_rec, lambda obj: obj["frames"][1].pop("gain"))
    with pytest.raises(ValueError, match=r"frame 1 .*missing field 'gain'"):
        load_recording(copy_rec, "online")
    with pytest.raises(ValueError, match="calibration"):
        load_recording(copy_rec, "viba")


def test_readout_displacement_matches_manual_projection(rec_dir):
    from egobench.data import load_recording
    from egobench.geometry import se3_inverse, transform_points
    from egobench.sim.figures import displacement_percentiles, readout_displacement_px

    rec = load_recording(rec_dir, "online")
    fr = rec.frames[2]
    d = readout_displacement_px(rec, fr)
    assert d.shape[0] == fr.sparse_depth.z.shape[0] and np.all(np.isfinite(d))
    # manual: the first sparse point, projected at read start and read end
    p_cam = rec.camera.unproject(torch.from_numpy(fr.sparse_depth.uv[:1])) * float(fr.sparse_depth.z[0])
    p_w = transform_points(fr.T_world_camera, p_cam)
    uv = []
    for t in (fr.read_start_ns, fr.read_end_ns):
        T = rec.trajectory.pose([t])[0] @ fr.T_device_camera
        uv.append(rec.camera.project(transform_points(se3_inverse(T), p_w))[0][0])
    assert d[0] == pytest.approx(float((uv[1] - uv[0]).norm()), rel=1e-6, abs=1e-9)
    q = displacement_percentiles(rec)
    assert q.shape == (6, 3) and np.all(q[:, 0] <= q[:, 2])
