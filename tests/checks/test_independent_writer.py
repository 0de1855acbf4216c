"""scripts/independent_writer.py: a second writer of the authors' layout, sharing no code with egobench.

Its recordings must load with egobench's reader with the stated metadata read back exactly, and a point
the writer drew at a pixel must reproject onto that pixel through the loaded trajectory, camera and row
times (the reader's conventions); the hidden effects move it by the amount truth.json states.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egobench.data import load_recording
from egobench.model.motion_sampling import camera_poses_at
from egobench.residual.signatures import distortion_profile

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "independent_writer.py"
EFFECTS = ["--vignette-corner", "0.4", "--readout-scale", "1.5", "--exposure-error", "1.25",
           "--exposure-fraction", "0.25", "--time-offset-s", "0.003"]


def _load_writer():
    spec = importlib.util.spec_from_file_location("independent_writer", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


writer = _load_writer()


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    """A tiny null recording and one with every hidden effect (32 px, 12 frames, seed 3)."""
    base = tmp_path_factory.mktemp("independent")
    out = {}
    for name, extra in (("null", []), ("effects", EFFECTS)):
        out[name] = base / name
        assert writer.main(["--out", str(out[name]), "--seed", "3", "--size", "32", "--frames", "12", *extra]) == 0
    return out


def test_the_writer_imports_nothing_from_egobench():
    tree = ast.parse(SCRIPT.read_text())
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert names <= {"__future__", "argparse", "gzip", "json", "math", "os", "shutil", "sys", "dataclasses",
                     "pathlib", "cv2", "numpy"}, names
    text = SCRIPT.read_text()
    assert "__import__" not in text and "importlib" not in text and "sys.path" not in text  # no hidden imports


def test_a_recording_loads_with_its_stated_metadata_and_truth(recordings):
    rec = load_recording(recordings["effects"])
    truth = json.loads((recordings["effects"] / "truth.json").read_text())
    assert len(rec.frames) == 12 and len(rec.test_frames) == 2 and rec.meta["dropped_frames"] == []
    assert (rec.camera.width, rec.camera.height, rec.camera.cx, rec.camera.cy) == (32, 32, 15.5, 15.5)
    altered = truth["effects"]["exposure_altered_frames"]
    assert len(altered) == 3 and truth["hidden_effects"] == ["vignette", "readout", "exposure_metadata", "time_offset"]
    for f in rec.frames:
        assert f.read_end_ns - f.read_start_ns == 8_000_000 and f.gain == 1.0
        assert f.exposure_s == truth["frames"][f.index]["exposure_recorded_s"]  # as written, bit for bit
        assert f.exposure_s == (pytest.approx(0.00125, rel=1e-12) if f.index in altered else 0.001)
        assert f.timestamp_ns == truth["frames"][f.index]["t_centre_true_ns"] - 3_000_000
        assert f.sparse_depth is not None and len(f.sparse_depth.z) > 10
    assert bool((rec.vignette == 1.0).all()) and len(rec.points_world) > 1000
    assert truth["effects"] | {"exposure_altered_frames": None} == {
        "vignette_corner": 0.4, "readout_scale": 1.5, "readout_stated_s": 0.008, "readout_true_s": 0.012,
        "exposure_error": 1.25, "exposure_fraction": 0.25, "exposure_altered_frames": None, "time_offset_s": 0.003,
        "lens_k0": 0.0}
    assert json.loads((recordings["null"] / "truth.json").read_text())["hidden_effects"] == []


def _reprojection_px(path: Path, use_truth: bool) -> np.ndarray:
    """|reprojected - drawn| (px, max of u and v) of points the writer drew at a few pixels of every 3rd frame,
    through the LOADED recording: row time timestamp - R/2 + R(u) R (with truth: + D, and R x S)."""
    rec = load_recording(path)
    truth = json.loads((path / "truth.json").read_text())
    c = writer.Config(**truth["config"])
    scene, motion, clock = writer.build_scene(c.seed), writer.head_motion(c.seed), writer.frame_clock(c)
    uv = np.array([[0, 0], [31, 0], [16, 16], [3, 29], [31, 31]], dtype=np.float64)
    offset_ns = truth["effects"]["time_offset_s"] * 1e9 if use_truth else 0.0
    scale = truth["effects"]["readout_scale"] if use_truth else 1.0
    errors = []
    for f in rec.frames[::3]:
        X, _ = writer.cast_pixels(c, scene, motion, int(clock["t_true"][f.index]), uv)
        R = (f.read_end_ns - f.read_start_ns) * scale
        ratio = rec.row_time_ratio.numpy()[uv[:, 1].astype(int), uv[:, 0].astype(int)]
        T = camera_poses_at(rec, f, f.timestamp_ns + offset_ns + (ratio - 0.5) * R).numpy()
        uv_p, ok = rec.camera.project(torch.from_numpy(np.einsum("nji,nj->ni", T[:, :3, :3], X - T[:, :3, 3])))
        assert bool(ok.all())
        errors.append(np.abs(uv_p.numpy() - uv).max(1))
        centre = camera_poses_at(rec, f, [f.timestamp_ns]).numpy()[0]
        assert np.abs(f.T_world_camera.numpy() - centre).max() < 1e-5  # transform_matrix: camera to world at timestamp
    return np.concatenate(errors)


def test_a_drawn_point_reprojects_onto_its_pixel_at_its_row_time(recordings):
    assert _reprojection_px(recordings["null"], use_truth=False).max() < 0.02
    assert _reprojection_px(recordings["effects"], use_truth=True).max() < 0.02
    assert np.median(_reprojection_px(recordings["effects"], use_truth=False)) > 0.05  # the hidden timing shows


def test_the_hidden_lens_moves_content_outward_as_a_larger_k0_does(tmp_path):
    """``--lens-k0 K``: the content the stated pinhole puts at radius r (px) shows K f sec^2(theta) theta^3 further
    out (egobench's `distortion_profile`, first order in K; at 110 deg the angle's cubic and the tangent's differ
    by a tenth), along the same azimuth; K = 0 leaves every ray; truth.json names it."""
    c = writer.Config(size=64, fov_deg=110.0, lens_k0=0.002)
    v, u = np.mgrid[0:64:7, 0:64:7].astype(np.float64)
    x, y = (u - c.centre_px) / c.focal_px, (v - c.centre_px) / c.focal_px
    tx, ty = writer.true_ray_xy(c, x, y)
    r = np.hypot(x, y) * c.focal_px
    seen_at = np.hypot(tx, ty) * c.focal_px  # where the pinhole would put the ray this pixel sees
    assert np.allclose(tx * y, ty * x, atol=1e-12)  # the same azimuth
    np.testing.assert_allclose(r - seen_at, 0.002 * distortion_profile(r, c.focal_px, None), rtol=0.03, atol=1e-6)
    assert (r - seen_at).max() > 0.15  # px at the corners
    same = writer.true_ray_xy(writer.Config(size=64), x, y)
    assert same[0] is x and same[1] is y
    writer.main(["--out", str(tmp_path / "lens"), "--seed", "2", "--size", "16", "--frames", "3", "--lens-k0", "-0.1"])
    truth = json.loads((tmp_path / "lens" / "truth.json").read_text())
    assert truth["hidden_effects"] == ["distortion"] and truth["effects"]["lens_k0"] == -0.1


def test_the_hidden_vignette_darkens_the_corners_only_in_the_images(recordings):
    def corner_over_centre(path: Path) -> float:
        stream = next(path.glob("camera-rgb-rectified-*"))
        imgs = np.stack([cv2.imread(str(p)).astype(float) for p in sorted((stream / "images").glob("*.png"))])
        lin = (imgs / 255.0) ** 2.2
        return float(lin[:, [0, 0, -1, -1], [0, -1, 0, -1]].mean() / lin[:, 14:18, 14:18].mean())

    ratio = corner_over_centre(recordings["effects"]) / corner_over_centre(recordings["null"])
    assert 0.45 < ratio < 0.8  # a 0.4 corner attenuation, on different content (other motion timing, same world)


def test_bad_arguments_are_refused_with_a_message(tmp_path, capsys):
    cases = [(["--size", "4"], "--size must be"), (["--exposure-error", "0.75"], "must be given together"),
             (["--readout-scale", "-1"], "--readout-scale must be"), (["--time-offset-s", "nan"], "--time-offset-s"),
             (["--frames", "x"], "invalid int value"),
             (["--lens-k0", "0.7"], "--lens-k0 must be"),
             (["--lens-k0", "0.3", "--fov-deg", "120"], "folds or turns back"),
             (["--lens-k0", "-0.5", "--fov-deg", "120"], "folds or turns back")]
    for extra, message in cases:
        with pytest.raises(SystemExit) as exc:
            writer.main(["--out", str(tmp_path / "r"), *extra])
        assert exc.value.code == 2 and message in capsys.readouterr().err
    (tmp_path / "r").mkdir()
    with pytest.raises(SystemExit):
        writer.main(["--out", str(tmp_path / "r")])
    assert "already exists" in capsys.readouterr().err
    assert not list(tmp_path.glob(".r.partial-*"))


def test_the_writer_is_deterministic_for_a_seed(tmp_path):
    for name in ("a", "b"):
        writer.main(["--out", str(tmp_path / name), "--seed", "5", "--size", "16", "--frames", "3"])
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) > 10
    assert all((tmp_path / "a" / p).read_bytes() == (tmp_path / "b" / p).read_bytes() for p in files)


def test_the_head_can_rotate_or_translate_alone():
    """--motion rotation keeps the device at one place, --motion translation keeps its orientation; both
    share the draws of the full motion (the same seed moves the same channels)."""
    w = writer
    t = w.T0_NS + np.arange(0, 3_000_000_000, 50_000_000)
    full, rot, trans = (w.device_poses(w.head_motion(7, kind), t) for kind in ("both", "rotation", "translation"))
    assert np.ptp(rot[:, :3, 3], axis=0).max() < 1e-12 and np.ptp(trans[:, :3, :3], axis=0).max() < 1e-12
    assert np.allclose(rot[:, :3, :3], full[:, :3, :3]) and np.allclose(trans[:, :3, 3], full[:, :3, 3])
    with pytest.raises(ValueError, match="head motion"):
        w.head_motion(7, "spin")
