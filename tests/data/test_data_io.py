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
    from tests.helpers import small_recording

    return small_recording(tmp_path_factory.mktemp("rec") / "object_2", "object", 2, n_frames=6)


@pytest.fixture
def copy_rec(rec_dir, tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(rec_dir, dst)
    return dst


def _stream(root, calibration="online"):
    from egobench.data.layout import find_stream

    return find_stream(root, calibration)


def test_sim_layout_is_the_authors(rec_dir):
    from egobench.data import load_recording

    on, fa = _stream(rec_dir), _stream(rec_dir, "factory")
    assert on.name == "camera-rgb-rectified-16-h32" and fa.name == on.name + "-factory-calib"
    rec = load_recording(on)  # the stream folder itself: trajectory and points from inside it (symlinks)
    assert len(rec.frames) == 6 and rec.points_world.shape[1] == 3 and rec.points_world.shape[0] > 0
    assert rec.meta["points_file"] == str(on / "semidense_points.csv.gz")
    img = rec.load_image(rec.frames[0])
    assert img.shape == (32, 32, 3) and 0 < float(img.mean()) < 1


def _edit_transforms(root, fn):
    p = _stream(root) / "transforms_with_sparse_depth.json"
    obj = json.loads(p.read_text())
    fn(obj)
    p.write_text(json.dumps(obj))


def test_missing_image_names_file_and_frame(copy_rec):
    from egobench.data import load_recording

    (_stream(copy_rec) / "images" / "00003.png").unlink()
    with pytest.raises(ValueError, match=r"transforms_with_sparse_depth\.json: frame 3 .*00003\.png.*missing"):
        load_recording(copy_rec, "online")
    load_recording(copy_rec, "factory")  # the other calibration is intact


def test_truncated_transforms_names_file(copy_rec):
    from egobench.data import load_recording

    p = _stream(copy_rec) / "transforms_with_sparse_depth.json"
    p.write_text(p.read_text()[:-200])
    with pytest.raises(ValueError, match=r"h32/transforms_with_sparse_depth\.json: not valid JSON"):
        load_recording(copy_rec, "online")


def test_nan_pose_names_frame(copy_rec):
    from egobench.data import load_recording

    def poison(obj):
        obj["frames"][2]["transform_matrix"][0][3] = float("nan")

    _edit_transforms(copy_rec, poison)
    with pytest.raises(ValueError, match=r"frame 2 .*transform_matrix.*NaN"):
        load_recording(copy_rec, "online")


def test_out_of_span_readout_names_frame(copy_rec):
    from egobench.data import load_recording

    traj = pd.read_csv(_stream(copy_rec) / "closed_loop_trajectory.csv")
    end_ns = int(traj["tracking_timestamp_us"].iloc[-1]) * 1000

    def widen(obj):  # the last frame 2 ms before the trajectory's end, read out over 80 ms: its poses leave it
        f = obj["frames"][5]
        f["timestamp"] = end_ns - 2_000_000
        f["timestamp_read_start"], f["timestamp_read_end"] = end_ns - 42_000_000, end_ns + 38_000_000

    _edit_transforms(copy_rec, widen)
    with pytest.raises(ValueError, match=r"frame 5 .*outside the trajectory span"):
        load_recording(copy_rec, "online")


def test_missing_field_and_bad_calibration_name(copy_rec):
    from egobench.data import load_recording

    _edit_transforms(copy_rec, lambda obj: obj["frames"][1].pop("gain"))
    with pytest.raises(ValueError, match=r"frame 1 .*missing field 'gain'"):
        load_recording(copy_rec, "online")
    with pytest.raises(ValueError, match="calibration"):
        load_recording(copy_rec, "viba")


# ---------------------------------------------------------------------------------- the authors' folder as is
@pytest.fixture
def authors_scene(rec_dir, tmp_path):
    """<scene>/mps/slam/ + <scene>/recording/camera-rgb-rectified-16-h32/ as the authors' script writes them,
    with the trajectory cut 0.5 ms beyond the first and last frames' centre timestamps."""
    from tests.helpers import authors_stream_copy

    scene = tmp_path / "livingroom"
    stream = authors_stream_copy(_stream(rec_dir), scene)
    ts = [f["timestamp"] for f in json.loads((stream / "transforms.json").read_text())["frames"]]
    traj = scene / "mps" / "slam" / "closed_loop_trajectory.csv"
    df = pd.read_csv(traj)
    t_us = df["tracking_timestamp_us"].to_numpy()
    keep = (t_us * 1000 >= min(ts) - 500_000) & (t_us * 1000 <= max(ts) + 500_000)
    df[keep].to_csv(traj, index=False)
    return scene, stream


def test_authors_folder_is_read_as_it_lies(authors_scene, rec_dir):
    from egobench.data import HOLDOUT_EVERY, load_recording

    scene, stream = authors_scene
    sim = load_recording(rec_dir, "online")
    rec = load_recording(scene, "online")  # found one level down: <scene>/recording/<stream>/
    assert rec.root == stream and rec.calibration == "online"
    # frames 0 and 5 lie within 1 ms of the trajectory's ends: dropped; the rest sorted by image path
    assert [f.timestamp_ns for f in rec.frames] == [f.timestamp_ns for f in sim.frames[1:5]]
    assert sorted(rec.meta["dropped_frames"]) == sorted(
        f"images/camera-rgb_{float(sim.frames[k].timestamp_ns)}.png" for k in (0, 5))
    assert [f.index for f in rec.test_frames] == [0] and HOLDOUT_EVERY == 8
    for a, b in zip(rec.frames, sim.frames[1:5]):
        torch.testing.assert_close(a.T_world_camera, b.T_world_camera, atol=0, rtol=0)
        assert (a.read_start_ns, a.read_end_ns, a.exposure_s, a.gain) == (b.read_start_ns, b.read_end_ns, b.exposure_s, b.gain)
        np.testing.assert_array_equal(a.sparse_depth.uv, b.sparse_depth.uv)
        assert torch.equal(rec.load_image(a), sim.load_image(b))
    # image_index.png (8-bit) stands in for row_time_ratio.npy
    assert float((rec.row_time_ratio - sim.row_time_ratio).abs().max()) <= 0.5 / 255 + 1e-6
    torch.testing.assert_close(rec.points_world, sim.points_world)
    # --trajectory: the full trajectory keeps every frame
    full = load_recording(stream, "online", trajectory_path=_stream(rec_dir) / "closed_loop_trajectory.csv")
    assert len(full.frames) == 6 and full.meta["dropped_frames"] == []


def test_factory_calibration_is_found_by_the_authors_naming_or_a_named_error(authors_scene, rec_dir):
    from egobench.data import load_recording
    from tests.helpers import authors_stream_copy

    scene, stream = authors_scene
    with pytest.raises(ValueError, match=r"holds the 'online' calibration.*'factory' calibration was asked.*"
                                         r"camera-rgb-rectified-16-h32-factory-calib is not there"):
        load_recording(stream, "factory")
    with pytest.raises(ValueError, match=r"no 'factory'-calibration stream; found only camera-rgb-rectified-16-h32 \(online\)"):
        load_recording(scene, "factory")
    factory_stream = authors_stream_copy(_stream(rec_dir, "factory"), scene)
    fa = load_recording(stream, "factory", trajectory_path=_stream(rec_dir) / "closed_loop_trajectory.csv")
    on = load_recording(factory_stream, "online", trajectory_path=_stream(rec_dir) / "closed_loop_trajectory.csv")
    assert fa.root == factory_stream and fa.calibration == "factory" and on.root == stream
    sim_fa = load_recording(rec_dir, "factory")
    for a, b in zip(fa.frames, sim_fa.frames):
        torch.testing.assert_close(a.T_device_camera, b.T_device_camera, atol=0, rtol=0)
    assert not torch.equal(fa.frames[0].T_device_camera, on.frames[0].T_device_camera)


def test_missing_points_file_is_named(authors_scene):
    from egobench.data import load_recording

    scene, stream = authors_scene
    (scene / "mps" / "slam" / "semidense_points.csv.gz").unlink()  # the in-folder symlink now dangles
    with pytest.raises(FileNotFoundError, match=r"h32/semidense_points\.csv\.gz: semi-dense points file is a symlink "
                                                r"to .*mps/slam/semidense_points\.csv\.gz, which does not exist \(pass --points"):
        load_recording(stream, "online")
    with pytest.raises(FileNotFoundError, match=r"nowhere\.csv\.gz: semi-dense points file not found \(pass --points"):
        load_recording(stream, "online", semidense_path=scene / "nowhere.csv.gz")


def test_points_all_removed_by_the_quality_filter_is_named(authors_scene, tmp_path):
    from egobench.data import load_recording

    scene, stream = authors_scene
    n = 50
    noisy = SemiDensePoints(uid=np.arange(n), points_world=np.random.default_rng(0).normal(size=(n, 3)),
                            inv_dist_std=np.full(n, 0.05), dist_std=np.full(n, 0.01))
    write_semidense_points(tmp_path / "noisy.csv.gz", noisy)
    with pytest.raises(ValueError, match=r"noisy\.csv\.gz: no semi-dense points to initialise the Gaussians: the MPS "
                                         r"quality filter \(inv_dist_std < 0\.01 1/m and dist_std < 0\.02 m\) removed all 50"):
        load_recording(stream, "online", semidense_path=tmp_path / "noisy.csv.gz")


def test_missing_trajectory_is_named(authors_scene):
    from egobench.data import load_recording

    scene, stream = authors_scene
    (stream / "closed_loop_trajectory.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"h32/closed_loop_trajectory\.csv: trajectory not found \(pass --trajectory"):
        load_recording(stream, "online")


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


def test_verbs_take_trajectory_and_points(authors_scene, rec_dir, tmp_path):
    """train and evaluate read the authors' folder with explicit --trajectory / --points; diagnose and
    plots take the same options."""
    from egobench.cli import build_parser, main

    scene, stream = authors_scene
    full = _stream(rec_dir) / "closed_loop_trajectory.csv"
    pts = scene / "mps" / "slam" / "semidense_points.csv.gz"
    run = tmp_path / "run"
    assert main(["train", "--recording", str(stream), "--method", "ours", "--out", str(run), "--iterations", "2",
                 "--trajectory", str(full), "--points", str(pts), "--no-progress"]) == 0
    assert main(["evaluate", "--recording", str(stream), "--run", str(run), "--no-renders",
                 "--trajectory", str(full), "--points", str(pts)]) == 0
    ev = json.loads((run / "eval.json").read_text())
    assert ev["trajectory_file"] == str(full) and ev["points_file"] == str(pts)
    # with the full trajectory no frame is dropped: 6 frames, frame 0 (sim frame 0) held out
    from egobench.data import load_recording

    assert len(load_recording(stream, trajectory_path=full).test_frames) == 1
    assert len(ev["per_image"]) == 1
    # without --trajectory the folder's own (cut) trajectory drops the end frames: a different held-out frame
    assert load_recording(stream).test_frames[0].timestamp_ns != load_recording(stream, trajectory_path=full).test_frames[0].timestamp_ns
    import sys

    for verb, extra in (("diagnose", [str(stream), "--out", "x"]), ("plots", ["--records", "r", "--out-dir", "x"])):
        old = sys.argv
        sys.argv = ["egobench", verb]
        try:
            args = build_parser().parse_args([verb, *extra, "--trajectory", "t.csv", "--points", "p.csv.gz"])
        finally:
            sys.argv = old
        assert (args.trajectory, args.points) == ("t.csv", "p.csv.gz")
