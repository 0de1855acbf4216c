"""Evaluation: the run record has every field, PSNR equals metrics.psnr on the saved render, geometry."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from egobench.evaluate import RUN_SCHEMA, evaluate
from egobench.io_utils import read_json
from egobench.metrics import psnr, ssim
from egobench.predict import resize_map
from egobench.sim.plane import plane_recording
from egobench.train import TrainConfig, train


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("ev")
    rec = plane_recording(root / "rec", size=32, n_frames=17, angular_speed_rad_s=8.0, n_points=800, readout_s=16e-3,
                        frame_interval_s=0.01, with_ground_truth=True)
    cfg = TrainConfig(iterations=30, refine_start_frac=1.0, motion_warmup_frac=0.5, lr_colors=1e-2)
    train(rec, "ours", cfg, root / "run", progress=False)
    return rec, root / "run"


def test_record_fields_and_psnr_on_saved_render(trained):
    rec, run = trained
    out = evaluate(rec, run, scene="toy_0", paper_scene="bike shop")
    on_disk = read_json(run / "eval.json")
    assert on_disk == out
    for key in ("schema", "scene", "scene_kind", "device", "paper_scene", "method", "seed", "calibration",
                "config_hash", "git_commit", "egobench_version", "recording", "train", "metrics", "notes", "per_image"):
        assert key in out, key
    assert out["schema"] == RUN_SCHEMA and out["scene"] == "toy_0" and out["paper_scene"] == "bike shop"
    assert out["method"] == "ours" and out["seed"] == 0 and out["calibration"] == "online"
    # The toy head turns at a constant 8 rad/s: every percentile of its angular speed is 458.4 deg/s.
    stats = out["recording_stats"]
    assert stats["num_frames"] == 17
    assert stats["head_angular_speed_deg_s_p50"] == pytest.approx(8.0 * 180 / 3.141592653589793, rel=1e-6)
    train_json = read_json(run / "train.json")
    assert out["config_hash"] == train_json["config_hash"]
    assert set(out["train"]) == {"iterations", "time_s", "iters_per_s", "raster_time_share", "num_gaussians"}
    assert out["train"]["iterations"] == 30 and out["train"]["iters_per_s"] > 0
    assert set(out["metrics"]) == {"psnr", "ssim", "lpips", "depth_si_l1", "normal_l1"}
    assert [e["frame"] for e in out["per_image"]] == [0, 8, 16]
    if out["metrics"]["lpips"] is None:
        assert out["notes"]["lpips"].startswith("not available")
    # Motion is fast in this fixture: held-out frames use several rolling-shutter samples.
    assert max(e["pose_samples"] for e in out["per_image"]) > 1
    for e in out["per_image"]:
        img = cv2.cvtColor(cv2.imread(str(run / "renders" / f"{e['frame']:05d}.png")), cv2.COLOR_BGR2RGB)
        pred = torch.from_numpy(img).float() / 255.0
        gt = rec.load_image(next(f for f in rec.frames if f.index == e["frame"]))
        assert psnr(pred, gt, rec.mask) == pytest.approx(e["psnr"], abs=1e-9)
        assert ssim(pred, gt, rec.mask) == pytest.approx(e["ssim"], abs=1e-9)
    assert out["metrics"]["psnr"] == pytest.approx(np.mean([e["psnr"] for e in out["per_image"]]))
    teaser = list((run / "renders").glob("virtual_gain_3x_*_beside_input.png"))
    assert len(teaser) == 1 and cv2.imread(str(teaser[0])).shape == (32, 64, 3)


def test_geometry_metrics_against_ground_truth(trained):
    rec, run = trained
    out = evaluate(rec, run, save_renders=False)
    m = out["metrics"]
    assert m["depth_si_l1"] is not None and m["normal_l1"] is not None
    # A plane 2.5 m away, fitted from noisy points on it: depth errors of centimetres, not metres.
    assert m["depth_si_l1"] < 0.1
    assert 0 <= m["normal_l1"] < 3.5
    no_gt = dataclasses.replace(rec, ground_truth=None)
    out2 = evaluate(no_gt, run, save_renders=False)
    assert out2["metrics"]["depth_si_l1"] is None and "geometry" in out2["notes"]


def test_bad_run_and_recording(trained, tmp_path):
    rec, run = trained
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        evaluate(rec, tmp_path)
    (tmp_path / "checkpoint.pt").write_bytes(b"junk")
    with pytest.raises(Exception):
        evaluate(rec, tmp_path)
    factory = dataclasses.replace(rec, calibration="factory")
    with pytest.raises(ValueError, match="evaluated on the 'online' stream"):
        evaluate(factory, run)
