"""Constants and small helpers shared by several test modules."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import SHARED_DATA

__all__ = ["SHARED_DATA", "ARIA_RGB_PARAMS_1408", "real_rgb_calibration", "write_records"]

#: A real Aria RGB online calibration (1408 x 1408; the first line of the MPS sample's
#: online_calibration.jsonl), so the analytic tests run without the data folder.
ARIA_RGB_PARAMS_1408 = [
    609.0993041992188, 714.49365234375, 705.4052124023438, 0.4153491258621216, -0.46660879254341125,
    0.0394107960164547, 1.304983139038086, -1.7682749032974243, 0.6525987982749939,
    7.804521010257304e-05, 0.0006019965512678027, -0.0011151430662721395, 0.0006172532448545098,
    -0.00233874237164855, 0.0016606695717200637,
]


def small_recording(out: Path, kind: str, seed: int, n_frames: int, size: int = 32) -> Path:
    """Simulate a small recording (``size`` px, ``n_frames`` frames, 1500 semi-dense points) into ``out``."""
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    cfg = SimConfig.from_overrides(kind, seed, {"n_frames": n_frames, "rectified_size": size, "n_semidense_points": 1500})
    simulate_recording(cfg, out, progress=False)
    return out


def write_records(root: Path, recs: list[dict]) -> list[Path]:
    """Write run records as root/runNNN/eval.json; the paths deliberately do not carry the identity
    (tables and plots must read it from the records)."""
    paths = []
    for i, r in enumerate(recs):
        p = root / f"run{i:03d}" / "eval.json"
        p.parent.mkdir(parents=True)
        p.write_text(json.dumps(r))
        paths.append(p)
    return paths


def real_rgb_calibration():
    """(MPS camera-rgb entry, image size, projectaria CameraCalibration) of the first line of the real
    online_calibration.jsonl; skips the test when projectaria-tools or the file is absent."""
    import math

    import numpy as np
    import pytest

    calibration = pytest.importorskip("projectaria_tools.core.calibration", reason="projectaria_tools not importable")
    sophus = pytest.importorskip("projectaria_tools.core.sophus", reason="projectaria_tools not importable")
    path = SHARED_DATA / "aria_mps_sample" / "online_calibration.jsonl"
    if not path.is_file():
        pytest.skip(f"real Aria calibration not present at {path}")
    with path.open() as fh:
        line = json.loads(fh.readline())
    (idx,) = [i for i, c in enumerate(line["CameraCalibrations"]) if c["Label"] == "camera-rgb"]
    entry, size = line["CameraCalibrations"][idx], line["ImageSizes"][idx]
    ref = calibration.CameraCalibration(
        "camera-rgb", calibration.CameraModelType.FISHEYE624, np.array(entry["Projection"]["Params"]),
        sophus.SE3(), size[0], size[1], None, math.pi, "",
    )
    return entry, size, ref


def authors_stream_copy(stream: Path, scene: Path, vrs_name: str = "recording") -> Path:
    """Rewrite a simulated stream folder exactly as the authors' preprocessing leaves one.

    <scene>/mps/slam/ holds the MPS files; <scene>/<vrs_name>/<stream name>/ holds images named
    <label>_<timestamp>.png (timestamps as the float the authors' script writes), frames listed in
    another order than time, the authors' per-frame keys (image_modality, image_width_raw,
    mask_path "", sparse_depth -> sparse_depth/<label>_<timestamp>.json), no row_time_ratio.npy and
    absolute symlinks to the MPS files. Returns the new stream folder.
    """
    import os
    import shutil

    src = json.loads((stream / "transforms_with_sparse_depth.json").read_text())
    mps = scene / "mps" / "slam"
    mps.mkdir(parents=True, exist_ok=True)
    for name in ("closed_loop_trajectory.csv", "semidense_points.csv.gz"):
        if not (mps / name).exists():
            shutil.copyfile(stream / name, mps / name)
    dst = scene / vrs_name / stream.name
    (dst / "images").mkdir(parents=True)
    (dst / "sparse_depth").mkdir()
    for name in ("vignette.png", "mask.png", "image_index.png"):
        shutil.copyfile(stream / name, dst / name)
    label = src["camera_label"]
    frames = []
    for f in src["frames"]:
        ts = float(f["timestamp"])
        img, depth = f"images/{label}_{ts}.png", f"sparse_depth/{label}_{ts}.json"
        shutil.copyfile(stream / f["image_path"], dst / img)
        shutil.copyfile(stream / f["sparse_depth"], dst / depth)
        frames.append({
            "fx": f["fx"], "fy": f["fy"], "cx": f["cx"], "cy": f["cy"], "w": f["w"], "h": f["h"],
            "image_width_raw": 2 * f["w"], "image_height_raw": 2 * f["h"], "image_path": img,
            "image_modality": "rgb", "mask_path": "", "camera2device": f["camera2device"],
            "transform_matrix": f["transform_matrix"], "timestamp": ts,
            "timestamp_read_start": f["timestamp_read_start"], "timestamp_read_end": float(f["timestamp_read_end"]),
            "exposure_duration_s": f["exposure_duration_s"], "gain": f["gain"], "sparse_depth": depth,
        })
    frames = frames[1::2] + frames[0::2]  # not in time order: the reader sorts by image path
    top = {"camera_model": "linear", "camera_label": label, "transform_cpf": [[1.0, 0, 0, 0], [0, 1.0, 0, 0],
                                                                              [0, 0, 1.0, 0], [0, 0, 0, 1.0]]}
    (dst / "transforms.json").write_text(json.dumps({**top, "frames": [
        {k: v for k, v in f.items() if k != "sparse_depth"} for f in frames]}, indent=4))
    (dst / "transforms_with_sparse_depth.json").write_text(json.dumps({**top, "frames": frames}, indent=4))
    for name in ("closed_loop_trajectory.csv", "semidense_points.csv.gz"):
        os.symlink((mps / name).absolute(), dst / name)
    return dst
