"""`load_recording`: a simulated recording or the authors' preprocessed folder -> `Recording`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from egobench.data.recording import Calibration, Frame, Recording
from egobench.data.transforms import read_png, read_sparse_depth, read_transforms


def _resolve(path: Path, calibration: str) -> tuple[Path, Path | None]:
    """-> (folder with transforms.json, simulated recording root or None)."""
    if calibration not in ("online", "factory"):
        raise ValueError(f"calibration: expected 'online' or 'factory', got {calibration!r}")
    if (path / "transforms.json").is_file():
        return path, None
    if (path / calibration / "transforms.json").is_file():
        return path / calibration, path
    if not path.exists():
        raise FileNotFoundError(f"{path}: recording folder not found")
    raise ValueError(
        f"{path}: no transforms.json here nor in {path / calibration}/ "
        f"(expected a simulated recording root or an authors'-format folder)"
    )


def load_recording(path: str | Path, calibration: Calibration = "online", *, trajectory_path: str | Path | None = None,
                   semidense_path: str | Path | None = None, load_sparse_depth: bool = True) -> Recording:
    """Read one rectified camera stream and its trajectory/points into a `Recording`.

    path: a simulated recording root (uses <path>/<calibration>/) or a folder holding
    transforms.json directly (the authors' format: the trajectory then comes from
    ../mps/closed_loop_trajectory.csv or `trajectory_path`, points from
    ../mps/semidense_points.csv.gz or `semidense_path`). Every frame is validated: missing
    image, bad JSON, NaN pose, timestamps outside the trajectory -> ValueError naming the file
    and the frame.
    """
    from egobench.data.mps import read_semidense_points, read_trajectory
    from egobench.io_utils import read_json

    path = Path(path)
    folder, sim_root = _resolve(path, calibration)
    tf = read_transforms(folder)
    mps_dir = (sim_root / "mps") if sim_root is not None else (folder.parent / "mps")
    traj_file = Path(trajectory_path) if trajectory_path is not None else mps_dir / "closed_loop_trajectory.csv"
    if not traj_file.is_file():
        raise ValueError(f"{traj_file}: trajectory not found for {tf.path} (pass trajectory_path=...)")
    trajectory = read_trajectory(traj_file)

    cam0 = tf.frames[0].camera
    order = sorted(range(len(tf.frames)), key=lambda i: tf.frames[i].timestamp_ns)
    frames: list[Frame] = []
    for index, pos in enumerate(order):
        fr = tf.frames[pos]
        where = f"{tf.path}: frame {pos} ({fr.image_path.name})"
        if fr.camera != cam0:
            raise ValueError(f"{where}: intrinsics {fr.camera} differ from frame 0's {cam0}; one rectified camera expected")
        span_end = fr.read_end_ns + int(round(fr.exposure_s * 1e9))
        if fr.read_start_ns < trajectory.start_ns or span_end > trajectory.end_ns or not (
                trajectory.start_ns <= fr.timestamp_ns <= trajectory.end_ns):
            raise ValueError(
                f"{where}: timestamps [{fr.read_start_ns}, {span_end}] ns (read start .. last row's exposure end, "
                f"centre {fr.timestamp_ns}) fall outside the trajectory span [{trajectory.start_ns}, {trajectory.end_ns}] ns "
                f"of {traj_file}"
            )
        sparse = None
        if load_sparse_depth and fr.sparse_depth_path is not None and fr.sparse_depth_path.is_file():
            sparse = read_sparse_depth(fr.sparse_depth_path, where=f" (frame {pos})")
        frames.append(Frame(
            index=index, image_path=fr.image_path, timestamp_ns=fr.timestamp_ns, read_start_ns=fr.read_start_ns,
            read_end_ns=fr.read_end_ns, exposure_s=fr.exposure_s, gain=fr.gain,
            T_world_camera=torch.from_numpy(fr.transform_matrix.copy()),
            T_device_camera=torch.from_numpy(fr.camera2device.copy()), sparse_depth=sparse,
        ))

    H, W = cam0.height, cam0.width

    def check_shape(arr: np.ndarray, name: Path) -> np.ndarray:
        if arr.shape[:2] != (H, W):
            raise ValueError(f"{name}: is {arr.shape[1]}x{arr.shape[0]}, the camera is {W}x{H}")
        return arr

    vig_path = folder / "vignette.png"
    vignette = (check_shape(read_png(vig_path, "vignette"), vig_path).astype(np.float32) / 255.0
                if vig_path.is_file() else np.ones((H, W), np.float32))
    mask_path = tf.frames[0].mask_path if tf.frames[0].mask_path is not None else folder / "mask.png"
    mask = (check_shape(read_png(mask_path, "mask"), mask_path) > 127) if mask_path.is_file() else np.ones((H, W), bool)
    rtr_path = folder / "row_time_ratio.npy"
    idx_path = folder / "image_index.png"
    if rtr_path.is_file():
        try:
            row_time_ratio = np.load(rtr_path).astype(np.float32)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{rtr_path}: unreadable row-time ratio array ({exc})") from exc
        check_shape(row_time_ratio, rtr_path)
        if not np.all(np.isfinite(row_time_ratio)):
            raise ValueError(f"{rtr_path}: contains NaN or infinite values")
    elif idx_path.is_file():
        row_time_ratio = check_shape(read_png(idx_path, "image index"), idx_path).astype(np.float32) / 255.0
    else:
        raise ValueError(f"{folder}: neither row_time_ratio.npy nor image_index.png present (rolling-shutter row times)")

    sd_file = Path(semidense_path) if semidense_path is not None else mps_dir / "semidense_points.csv.gz"
    meta: dict = {}
    if sd_file.is_file():
        pts = read_semidense_points(sd_file, filter=True)
        points_world = torch.from_numpy(pts.points_world.astype(np.float32))
    elif semidense_path is not None:
        raise ValueError(f"{sd_file}: semi-dense points file not found")
    else:
        points_world = torch.zeros((0, 3), dtype=torch.float32)
        meta["notes"] = {"points_world": f"no semi-dense points at {sd_file}"}
    if sim_root is not None and (sim_root / "recording.json").is_file():
        meta.update(read_json(sim_root / "recording.json"))
    name = str(meta.get("name", (sim_root or folder).name))
    gt = sim_root / "ground_truth" if sim_root is not None and (sim_root / "ground_truth").is_dir() else None
    return Recording(
        root=folder, name=name, calibration=calibration, camera=cam0, camera_model="linear", frames=frames,
        vignette=torch.from_numpy(vignette), mask=torch.from_numpy(np.ascontiguousarray(mask)),
        row_time_ratio=torch.from_numpy(row_time_ratio), trajectory=trajectory, points_world=points_world,
        ground_truth=gt, meta=meta,
    )
