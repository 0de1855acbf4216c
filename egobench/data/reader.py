"""`load_recording`: a rectified stream in the authors' layout (real or simulated) -> `Recording`.

Read as the authors' training reads it (``scene/dataset_readers.py``): the transforms file
``transforms_with_sparse_depth.json`` (else ``transforms.json``), frames sorted by image path,
frames whose centre timestamp lies within 1 ms of either end of the trajectory dropped, then
every 8th frame from 0 held out (`Recording.test_frames`); the trajectory and the semi-dense
points from the folder (``closed_loop_trajectory.csv``, ``semidense_points.csv.gz``, often
symlinks) unless passed explicitly (``--trajectory``, ``--points``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from egobench.data.layout import (POINTS_FILE, TRAJECTORY_END_MARGIN_NS, TRAJECTORY_FILE, check_stream_input,
                                  find_stream, resolves_inside)
from egobench.data.mps import MAX_DIST_STD, MAX_INV_DIST_STD, read_semidense_points, read_trajectory
from egobench.data.recording import Calibration, Frame, Recording
from egobench.data.transforms import TransformsFile, read_png, read_sparse_depth, read_transforms
from egobench.io_utils import read_json


def _input_file(explicit: str | Path | None, folder: Path, name: str, what: str, option: str) -> Path:
    """The explicit file, else <folder>/<name>; FileNotFoundError names it (and a broken symlink's target)."""
    path = Path(explicit) if explicit is not None else folder / name
    if path.is_file():
        return path if explicit is not None else check_stream_input(folder, path, what)
    if path.is_symlink():
        raise FileNotFoundError(f"{path}: {what} is a symlink to {path.resolve()}, which does not exist "
                                f"(pass {option} FILE)")
    raise FileNotFoundError(f"{path}: {what} not found (pass {option} FILE)")


def _load_points(path: Path) -> torch.Tensor:
    """Filtered semi-dense points [P, 3] float32; ValueError when the MPS quality filter keeps none."""
    pts = read_semidense_points(path, filter=False)
    kept = pts.filtered()
    if len(kept) == 0:
        why = ("the file holds no points" if len(pts) == 0 else
               f"the MPS quality filter (inv_dist_std < {MAX_INV_DIST_STD} 1/m and dist_std < {MAX_DIST_STD} m) "
               f"removed all {len(pts)} points")
        raise ValueError(f"{path}: no semi-dense points to initialise the Gaussians: {why}")
    return torch.from_numpy(kept.points_world.astype(np.float32))


#: A trajectory that leaves more than this share of a recording's frames uncovered (their centre
#: time outside its span) is refused: it is cut, or it belongs to another recording.
MAX_UNCOVERED_SHARE = 0.25
#: Why a frame of the transforms file is not used (keys of ``Recording.meta["dropped"]``).
DROP_REASONS = {"trajectory_end_margin": "centre within 1 ms of the trajectory's ends (the authors' reader drops them)",
                "outside_trajectory": "centre time outside the trajectory's span"}


def _frames(tf: TransformsFile, trajectory, traj_file: Path, load_sparse_depth: bool) -> tuple[list[Frame], dict]:
    """Frames sorted by image path, those the trajectory does not cover dropped: (frames, {reason: image paths})."""
    cam0 = tf.frames[0].camera
    order = sorted(tf.frames, key=lambda f: f.image_rel)
    lo, hi = trajectory.start_ns + TRAJECTORY_END_MARGIN_NS, trajectory.end_ns - TRAJECTORY_END_MARGIN_NS
    frames: list[Frame] = []
    dropped: dict[str, list[str]] = {reason: [] for reason in DROP_REASONS}
    for fr in order:
        where = f"{tf.path}: frame {fr.position} ({fr.image_rel})"
        if fr.camera != cam0:
            raise ValueError(f"{where}: intrinsics {fr.camera} differ from frame 0's {cam0}; one rectified camera expected")
        if not lo <= fr.timestamp_ns <= hi:
            inside = trajectory.start_ns <= fr.timestamp_ns <= trajectory.end_ns
            dropped["trajectory_end_margin" if inside else "outside_trajectory"].append(fr.image_rel)
            continue
        half = (fr.read_end_ns - fr.read_start_ns) // 2
        t0, t1 = fr.timestamp_ns - half, fr.timestamp_ns + half  # the readout span the poses are sampled on
        if t0 < trajectory.start_ns or t1 > trajectory.end_ns:
            raise ValueError(f"{where}: readout [{t0}, {t1}] ns around the centre {fr.timestamp_ns} falls outside "
                             f"the trajectory span [{trajectory.start_ns}, {trajectory.end_ns}] ns of {traj_file}")
        if frames and fr.timestamp_ns <= frames[-1].timestamp_ns:
            raise ValueError(f"{where}: sorted by image path, its timestamp {fr.timestamp_ns} does not follow the "
                             f"previous frame's {frames[-1].timestamp_ns}; image names must sort in time order")
        frames.append(_frame(fr, len(frames), where, load_sparse_depth))
    uncovered = len(dropped["outside_trajectory"])
    if not frames or uncovered > MAX_UNCOVERED_SHARE * len(order):
        raise ValueError(f"{tf.path}: the trajectory {traj_file} (span [{trajectory.start_ns}, {trajectory.end_ns}] "
                         f"ns) covers {len(order) - uncovered} of the {len(order)} frames, {len(frames)} usable "
                         f"(more than {MAX_UNCOVERED_SHARE:.0%} uncovered is refused: a cut trajectory or one of "
                         "another recording); pass this recording's trajectory with --trajectory")
    return frames, dropped


def _frame(fr, index: int, where: str, load_sparse_depth: bool) -> Frame:
    """One parsed transforms entry as the `Frame` at ``index`` (its sparse depth read when asked)."""
    sparse = None
    if load_sparse_depth and fr.sparse_depth_path is not None:
        if not fr.sparse_depth_path.is_file():
            raise FileNotFoundError(f"{fr.sparse_depth_path}: sparse depth of {where} not found")
        sparse = read_sparse_depth(fr.sparse_depth_path, where=f" ({where})")
    return Frame(index=index, image_path=fr.image_path, timestamp_ns=fr.timestamp_ns, read_start_ns=fr.read_start_ns,
                 read_end_ns=fr.read_end_ns, exposure_s=fr.exposure_s, gain=fr.gain,
                 T_world_camera=torch.from_numpy(fr.transform_matrix.copy()),
                 T_device_camera=torch.from_numpy(fr.camera2device.copy()), sparse_depth=sparse)


def frame_counts(rec: Recording) -> dict:
    """The frames of the file, those used (training / held out) and those dropped by reason (for the records)."""
    dropped = rec.meta.get("dropped") or {}
    n_dropped = sum(len(v) for v in dropped.values())
    return {"in_file": len(rec.frames) + n_dropped, "used": len(rec.frames), "train": len(rec.train_frames),
            "held_out": len(rec.test_frames), "dropped": {k: list(v) for k, v in dropped.items() if v}}


def dropped_summary(rec: Recording) -> str | None:
    """One line naming how many frames of the file were dropped and why (None when none was)."""
    counts = frame_counts(rec)
    if counts["used"] == counts["in_file"]:
        return None
    parts = "; ".join(f"{len(v)}: {DROP_REASONS[k]} ({', '.join(v[:3])}{', ...' if len(v) > 3 else ''})"
                      for k, v in counts["dropped"].items())
    return f"{rec.root}: {counts['in_file'] - counts['used']} of {counts['in_file']} frames dropped: {parts}"


def say_dropped(rec: Recording, verb: str) -> None:
    """Name the frames the reader dropped on the console of ``egobench <verb>`` (the records keep them too)."""
    if line := dropped_summary(rec):
        print(f"egobench {verb}: note: {line}", file=sys.stderr)


def _camera_maps(folder: Path, tf: TransformsFile, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vignette [H, W] 0..1, mask [H, W] bool, row-time ratio [H, W] 0..1) of a stream folder."""

    def inside(path: Path, what: str) -> bool:  # present, and not a link out of the recording
        return path.is_file() and check_stream_input(folder, path, what) is not None

    def check_shape(arr: np.ndarray, name: Path) -> np.ndarray:
        if arr.shape[:2] != (H, W):
            raise ValueError(f"{name}: is {arr.shape[1]}x{arr.shape[0]}, the camera is {W}x{H}")
        return arr

    vig_path = folder / "vignette.png"
    vignette = (check_shape(read_png(vig_path, "vignette"), vig_path).astype(np.float32) / 255.0
                if inside(vig_path, "vignette") else np.ones((H, W), np.float32))
    mask_path = tf.frames[0].mask_path if tf.frames[0].mask_path is not None else folder / "mask.png"
    mask = (check_shape(read_png(mask_path, "mask"), mask_path) > 127) if inside(mask_path, "mask") else np.ones((H, W), bool)
    rtr_path, idx_path = folder / "row_time_ratio.npy", folder / "image_index.png"
    if inside(rtr_path, "row-time ratio"):
        try:
            row_time_ratio = np.load(rtr_path, allow_pickle=False).astype(np.float32)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{rtr_path}: unreadable row-time ratio array ({exc})") from exc
        check_shape(row_time_ratio, rtr_path)
        if not np.all(np.isfinite(row_time_ratio)):
            raise ValueError(f"{rtr_path}: contains NaN or infinite values")
    elif inside(idx_path, "image index"):
        row_time_ratio = check_shape(read_png(idx_path, "image index"), idx_path).astype(np.float32) / 255.0
    else:
        raise ValueError(f"{folder}: neither row_time_ratio.npy nor image_index.png present (rolling-shutter row times)")
    return vignette, mask, row_time_ratio


def load_recording(path: str | Path, calibration: Calibration = "online", *, trajectory_path: str | Path | None = None,
                   semidense_path: str | Path | None = None, load_sparse_depth: bool = True) -> Recording:
    """Read one rectified camera stream and its trajectory and points into a `Recording`.

    path: a rectified stream folder (``<label>-rectified-<focal>-h<size>[-factory-calib]``), or a
    recording / scene folder holding one (`egobench.data.layout.find_stream`). The calibration
    selects the stream by the authors' naming; one that is not there is a ValueError.
    trajectory_path / semidense_path: override the folder's closed_loop_trajectory.csv /
    semidense_points.csv.gz. Every frame is validated (missing image, bad JSON, NaN pose,
    readout outside the trajectory -> ValueError naming the file and the frame).
    """
    folder = find_stream(path, calibration)
    tf = read_transforms(folder)
    traj_file = _input_file(trajectory_path, folder, TRAJECTORY_FILE, "trajectory", "--trajectory")
    trajectory = read_trajectory(traj_file)
    frames, dropped = _frames(tf, trajectory, traj_file, load_sparse_depth)
    cam0 = tf.frames[0].camera
    vignette, mask, row_time_ratio = _camera_maps(folder, tf, cam0.height, cam0.width)
    points_file = _input_file(semidense_path, folder, POINTS_FILE, "semi-dense points file", "--points")
    points_world = _load_points(points_file)

    rec_root = folder.parent  # <vrs name>/ (simulated: the recording folder with recording.json)
    meta: dict = {"transforms": str(tf.path), "trajectory_file": str(traj_file), "points_file": str(points_file),
                  "dropped_frames": [p for paths in dropped.values() for p in paths], "dropped": dropped}
    for extra in ("recording.json", "ground_truth"):
        if (rec_root / extra).exists() and not resolves_inside(rec_root / extra, rec_root):
            raise ValueError(f"{rec_root / extra}: a symlink to {(rec_root / extra).resolve()}, outside the recording; refused")
    if (rec_root / "recording.json").is_file():
        meta.update(read_json(rec_root / "recording.json"))
    name = str(meta.get("name", rec_root.name))
    gt = rec_root / "ground_truth" if (rec_root / "ground_truth" / "truth.json").is_file() else None
    return Recording(
        root=folder, name=name, calibration=calibration, camera=cam0, camera_model="linear", frames=frames,
        vignette=torch.from_numpy(vignette), mask=torch.from_numpy(np.ascontiguousarray(mask)),
        row_time_ratio=torch.from_numpy(row_time_ratio), trajectory=trajectory, points_world=points_world,
        ground_truth=gt, meta=meta,
    )


# ----------------------------------------------------------------------------------------
# the verbs' recording options
# ----------------------------------------------------------------------------------------
def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """--trajectory and --points: every verb that takes a recording."""
    parser.add_argument("--trajectory", default=None, metavar="CSV",
                        help="MPS closed_loop_trajectory.csv (default: the one in the recording's stream folder)")
    parser.add_argument("--points", default=None, metavar="CSV_GZ",
                        help="MPS semidense_points.csv.gz (default: the one in the recording's stream folder)")


def recording_from_args(path, calibration: str, args: argparse.Namespace):
    """``path`` loaded with --trajectory/--points when either is given, else ``path`` itself (loaded later)."""
    traj, pts = getattr(args, "trajectory", None), getattr(args, "points", None)
    if traj is None and pts is None:
        return path
    return load_recording(path, calibration, trajectory_path=traj, semidense_path=pts)
