"""`egobench preprocess`: a raw Aria VRS recording + its MPS folder -> a rectified stream folder.

Writes the authors' layout (egobench.data.layout; facebookresearch/egocentric_splats,
``scripts/extract_aria_vrs.py``) that `load_recording` and training read:
``<out>/<label>-rectified-<focal>-h<size>[-factory-calib]/`` with the rectified images, both
transforms files, per-frame sparse depth, vignette.png, mask.png, image_index.png (and egobench's
full-precision row_time_ratio.npy) and symlinks to the MPS trajectory and points.

Per frame, as the authors' script: capture timestamp t_c and exposure/gain from the VRS record;
readout R by the raw image height (2880 rows: 16.26 ms, 1408: 5 ms, 480 (SLAM): 0);
timestamp_read_start = t_c, timestamp = t_c + R/2, timestamp_read_end = t_c + R (the authors'
convention; frames whose read start, centre or end lie outside the trajectory are skipped); the
calibration is the online (VIBA) one nearest in time, or the VRS factory calibration with
``factory=True``; transform_matrix = T_world_device(timestamp) @ T_device_camera. The rectified
pinhole (f = focal, size x size, cx = cy = (size - 1) / 2, same axes as the fisheye camera) is
resampled with egobench's own Fisheye624 and rectifier (egobench.camera), the same as the
simulator's. Sparse depth: the semi-dense points observed by the SLAM cameras in their frames
nearest to the RGB centre time (semidense_observations.csv.gz), projected into the rectified
camera. projectaria-tools (VRS reading) is imported only here, lazily.

Resumable: frames are written into ``<out parent>/.<out name>.<stream>.partial/`` beside the
output (a frame's record last; a workflow that clears ``<out>`` before a rerun keeps it) and a
rerun reuses finished frames; the folder is renamed onto ``<out>/<stream>/`` at the end.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from egobench.camera import Rectification
from egobench.camera.pinhole import Pinhole
from egobench.data.layout import (MPS_SLAM, OBSERVATIONS_FILE, ONLINE_CALIBRATION_FILE, POINTS_FILE, TRAJECTORY_FILE,
                                  link_mps_files, stream_folder_name)
from egobench.data.mps import (CalibrationRecord, CameraCalibration, read_online_calibration, read_semidense_points,
                               read_trajectory)
from egobench.data.transforms import write_camera_maps, write_png, write_transforms
from egobench.io_utils import read_csv, read_json, write_json

#: Rolling-shutter readout by raw image height (the authors' values; Aria Gen 1).
READOUT_NS_BY_HEIGHT = {2880: 16_260_000, 1408: 5_000_000, 480: 0}
#: Largest gap between an RGB frame's centre time and the SLAM frame whose observations give its sparse depth.
SLAM_FRAME_TOLERANCE_NS = 50_000_000
SLAM_LABELS = ("camera-slam-left", "camera-slam-right")


def _projectaria():
    try:
        from projectaria_tools.core import data_provider
    except ImportError as exc:
        raise ValueError("egobench preprocess needs projectaria-tools to read VRS files "
                         f"(pip install projectaria-tools==2.3.0): {exc}") from None
    return data_provider


@dataclass
class MpsInputs:
    """What preprocessing reads from the MPS folder."""

    folder: Path
    trajectory: object  # egobench.geometry.Trajectory of T_world_device
    points_uid: np.ndarray  # [P] int64, all points (the quality filter applies at training)
    points_world: np.ndarray  # [P, 3] float64
    inv_dist_std: np.ndarray  # [P]
    dist_std: np.ndarray  # [P]
    observations: object | None  # pandas DataFrame uid, frame_tracking_timestamp_us, camera_serial (or None)
    online: list[CalibrationRecord] | None  # online_calibration.jsonl lines (None when not needed)


def read_mps_folder(mps_dir: str | Path, need_online: bool) -> MpsInputs:
    """Read an MPS slam folder; FileNotFoundError names each missing file."""
    mps_dir = Path(mps_dir)
    if not mps_dir.is_dir():
        raise FileNotFoundError(f"{mps_dir}: MPS folder not found (expected the MPS output's slam/ folder with "
                                f"{TRAJECTORY_FILE}, {POINTS_FILE}, {OBSERVATIONS_FILE}, {ONLINE_CALIBRATION_FILE})")
    traj = read_trajectory(mps_dir / TRAJECTORY_FILE)
    pts = read_semidense_points(mps_dir / POINTS_FILE, filter=False)
    obs = None
    obs_path = mps_dir / OBSERVATIONS_FILE
    if obs_path.is_file():
        obs = read_csv(obs_path, "MPS semi-dense observations CSV")
        missing = [c for c in ("uid", "frame_tracking_timestamp_us", "camera_serial") if c not in obs.columns]
        if missing:
            raise ValueError(f"{obs_path}: missing column(s) {missing}")
    else:
        print(f"egobench preprocess: warning: {obs_path} not found: frames get no sparse depth "
              "(motion sampling then assumes a moving camera)", file=sys.stderr)
    online = read_online_calibration(mps_dir / ONLINE_CALIBRATION_FILE) if need_online else None
    return MpsInputs(mps_dir, traj, pts.uid, pts.points_world, pts.inv_dist_std, pts.dist_std, obs, online)


def _factory_calibration(provider, label: str) -> CameraCalibration:
    cal = provider.get_device_calibration().get_camera_calib(label)
    if cal is None:
        raise ValueError(f"VRS device calibration has no camera {label!r}")
    w, h = (int(x) for x in cal.get_image_size())
    return CameraCalibration(label=label, params=np.asarray(cal.get_projection_params(), dtype=np.float64), width=w,
                             height=h, T_device_camera=np.asarray(cal.get_transform_device_camera().to_matrix()))


def _online_for(records: list[CalibrationRecord], t_ns: int, label: str) -> CameraCalibration:
    """The online calibration of ``label`` nearest in time to ``t_ns``."""
    times = np.array([r.tracking_timestamp_us if r.tracking_timestamp_us is not None else -1 for r in records],
                     dtype=np.int64) * 1000
    return records[int(np.argmin(np.abs(times - t_ns)))].camera(label)


def rectified_pinhole(focal_px: float, size_px: int):
    return Pinhole(fx=float(focal_px), fy=float(focal_px), cx=(size_px - 1) / 2, cy=(size_px - 1) / 2,
                   width=int(size_px), height=int(size_px))


def read_vignette(path: str | Path | None, height: int, width: int) -> tuple[np.ndarray, str | None]:
    """Raw-sensor lens shading [H, W] in 0..1 from a PNG (8 or 16 bit; colour -> mean), or flat + a warning."""
    if path is None:
        return np.ones((height, width), np.float32), (
            "no --vignette: a flat lens shading is written; the real fall-off (Aria RGB corners are several "
            "times darker than the centre) is then learnt into the scene's colours and the exposure model "
            "cannot separate it (pass the device's vignette PNG, e.g. the authors' data/vignette_imx577_16bit.png)")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: vignette image missing or unreadable")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    v = img.astype(np.float32) / scale
    if v.ndim == 3:
        v = v[..., :3].mean(-1)
    if v.shape != (height, width):
        if v.shape == (2880, 2880) and height == width == 1408:  # the authors: crop 32 px, then downsample
            v = cv2.resize(v[32:-32, 32:-32], (width, height), interpolation=cv2.INTER_AREA)
        else:
            raise ValueError(f"{path}: vignette is {v.shape[1]}x{v.shape[0]}, the raw images are {width}x{height}")
    return np.clip(v, 0.0, 1.0), None


class SparseDepthIndex:
    """Semi-dense points observed by the SLAM cameras, looked up by time (uids per SLAM frame)."""

    def __init__(self, mps: MpsInputs, slam_serials: list[str]):
        self.mps = mps
        self.row_of_uid = {int(u): i for i, u in enumerate(mps.points_uid.tolist())}
        self.frames: list[tuple[np.ndarray, list[np.ndarray]]] = []  # per SLAM camera: (times ns, uids per time)
        obs = mps.observations
        if obs is None:
            return
        for serial in slam_serials:
            sub = obs[obs["camera_serial"].astype(str) == str(serial)]
            if sub.empty:
                continue
            groups = sub.groupby("frame_tracking_timestamp_us")["uid"]
            times = np.array(list(groups.groups.keys()), dtype=np.int64) * 1000
            uids = [g.to_numpy(dtype=np.int64) for _, g in groups]
            self.frames.append((times, uids))

    def visible_uids(self, t_ns: int) -> np.ndarray:
        """uids observed in each SLAM camera's frame nearest to ``t_ns`` (within SLAM_FRAME_TOLERANCE_NS)."""
        out = []
        for times, uids in self.frames:
            k = int(np.argmin(np.abs(times - t_ns)))
            if abs(int(times[k]) - t_ns) <= SLAM_FRAME_TOLERANCE_NS:
                out.append(uids[k])
        return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)

    def sparse_depth(self, t_ns: int, T_world_camera: np.ndarray, pinhole, valid: np.ndarray) -> dict:
        """{u, v, z, inverseDistanceStd, distanceStd} of the visible points in the rectified camera."""
        rows = np.array([self.row_of_uid[u] for u in self.visible_uids(t_ns).tolist() if u in self.row_of_uid],
                        dtype=np.int64)
        T_cw = np.linalg.inv(T_world_camera)
        p = self.mps.points_world[rows] @ T_cw[:3, :3].T + T_cw[:3, 3]  # [n, 3] camera frame
        z = p[:, 2]
        front = z > 1e-6
        u = pinhole.fx * p[:, 0] / np.where(front, z, 1.0) + pinhole.cx
        v = pinhole.fy * p[:, 1] / np.where(front, z, 1.0) + pinhole.cy
        keep = front & (u >= 0) & (u <= pinhole.width - 1) & (v >= 0) & (v <= pinhole.height - 1)
        iu = np.clip(np.round(u), 0, pinhole.width - 1).astype(np.int64)
        iv = np.clip(np.round(v), 0, pinhole.height - 1).astype(np.int64)
        keep &= valid[iv, iu]
        r = rows[keep]
        return {"u": u[keep].tolist(), "v": v[keep].tolist(), "z": z[keep].tolist(),
                "inverseDistanceStd": self.mps.inv_dist_std[r].tolist(), "distanceStd": self.mps.dist_std[r].tolist()}


@dataclass
class PreprocessOptions:
    """What `preprocess` makes (the CLI's options)."""

    focal_px: float = 1200.0  # rectified pinhole focal (paper: 1200)
    size_px: int = 2400  # rectified image side (paper: 2400)
    factory: bool = False  # factory calibration (the "w/o VIBA" rows) instead of the online one
    vignette: str | None = None  # raw-sensor lens shading PNG
    camera_label: str = "camera-rgb"
    max_frames: int | None = None  # only the first N frames of the VRS (tests, quick looks)

    def fingerprint(self, vrs: Path, mps_dir: Path) -> dict:
        return {"vrs": str(Path(vrs).resolve()), "mps": str(Path(mps_dir).resolve()), "focal_px": self.focal_px,
                "size_px": self.size_px, "factory": self.factory, "vignette": self.vignette,
                "camera_label": self.camera_label, "max_frames": self.max_frames}


def _frame_times(capture_ns: int, height: int, where: str) -> tuple[int, int, int]:
    """(read start, centre, read end) ns of a raw frame (the authors' convention)."""
    if height not in READOUT_NS_BY_HEIGHT:
        raise ValueError(f"{where}: raw image height {height} is not an Aria Gen 1 mode "
                         f"({sorted(READOUT_NS_BY_HEIGHT)}); its readout time is unknown")
    readout = READOUT_NS_BY_HEIGHT[height]
    return capture_ns, capture_ns + readout // 2, capture_ns + readout


class _Rig:
    """Rectifications raw -> pinhole, cached by calibration (online calibrations change over time)."""

    def __init__(self, pinhole):
        self.pinhole, self.key, self.rect = pinhole, None, None

    def get(self, cal: CameraCalibration):
        key = (tuple(np.round(cal.params, 12).tolist()), cal.width, cal.height)
        if key != self.key:
            self.key, self.rect = key, Rectification.build(cal.camera(), self.pinhole)
        return self.rect


def _process_frame(i: int, provider, stream_id, mps: MpsInputs, cal_of, rig: _Rig, depth: SparseDepthIndex,
                   label: str, partial: Path) -> dict:
    """Rectify frame ``i``, write its image and sparse depth; its transforms entry (or {"skipped": why})."""
    image_data, record = provider.get_image_data_by_index(stream_id, i)
    raw = image_data.to_numpy_array()
    where = f"VRS {label} frame {i}"
    t0, tc, t1 = _frame_times(int(record.capture_timestamp_ns), raw.shape[0], where)
    traj = mps.trajectory
    if t0 < traj.start_ns or t1 > traj.end_ns:
        return {"skipped": f"readout [{t0}, {t1}] ns outside the trajectory [{traj.start_ns}, {traj.end_ns}] ns"}
    cal = cal_of(tc)
    if (cal.width, cal.height) != (raw.shape[1], raw.shape[0]):
        raise ValueError(f"{where}: the calibration is for {cal.width}x{cal.height} images, the frame is "
                         f"{raw.shape[1]}x{raw.shape[0]}")
    rect = rig.get(cal)
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=-1)
    img = rect.warp(torch.from_numpy(raw[..., :3].astype(np.float32)))
    name = f"{label}_{tc}"
    write_png(partial / "images" / f"{name}.png", img.round().clamp(0, 255).to(torch.uint8).numpy())
    T_wc = traj.pose([tc])[0].numpy() @ cal.T_device_camera
    pin = rig.pinhole
    write_json(partial / "sparse_depth" / f"{name}.json", depth.sparse_depth(tc, T_wc, pin, rect.valid.numpy()),
               indent=None)
    return {
        "fx": pin.fx, "fy": pin.fy, "cx": pin.cx, "cy": pin.cy, "w": pin.width, "h": pin.height,
        "image_width_raw": int(raw.shape[1]), "image_height_raw": int(raw.shape[0]),
        "image_path": f"images/{name}.png", "image_modality": "rgb", "mask_path": "",
        "camera2device": cal.T_device_camera.tolist(), "transform_matrix": T_wc.tolist(),
        "timestamp": tc, "timestamp_read_start": t0, "timestamp_read_end": t1,
        "exposure_duration_s": float(record.exposure_duration), "gain": float(record.gain),
        "sparse_depth": f"sparse_depth/{name}.json",
    }


def _open_partial(partial: Path, fingerprint: dict) -> None:
    """Keep a partial folder of the same inputs and options (resume); discard one of others."""
    manifest = partial / ".frames" / "options.json"
    if partial.exists():
        try:
            same = read_json(manifest) == fingerprint
        except (FileNotFoundError, ValueError):
            same = False
        if not same:
            print(f"egobench preprocess: {partial}: written for other inputs or options; starting afresh", file=sys.stderr)
            shutil.rmtree(partial)
    for sub in ("images", "sparse_depth", ".frames"):
        (partial / sub).mkdir(parents=True, exist_ok=True)
    if not manifest.is_file():
        write_json(manifest, fingerprint)


def preprocess(vrs: str | Path, mps_dir: str | Path, out: str | Path, options: PreprocessOptions | None = None,
               progress: bool = True) -> Path:
    """Rectify the VRS's RGB stream with the MPS trajectory, calibration and points; -> the stream folder."""
    o = options or PreprocessOptions()
    vrs, mps_dir, out = Path(vrs), Path(mps_dir), Path(out)
    if not vrs.is_file():
        raise FileNotFoundError(f"{vrs}: VRS file not found")
    if o.focal_px <= 0 or o.size_px <= 1:
        raise ValueError(f"--focal {o.focal_px} / --size {o.size_px}: expected a positive focal and a size > 1")
    data_provider = _projectaria()
    mps = read_mps_folder(mps_dir, need_online=not o.factory)
    provider = data_provider.create_vrs_data_provider(str(vrs))
    if provider is None:
        raise ValueError(f"{vrs}: not a readable VRS file")
    stream_id = provider.get_stream_id_from_label(o.camera_label)
    if stream_id is None:
        raise ValueError(f"{vrs}: no {o.camera_label!r} image stream")
    factory_cal = _factory_calibration(provider, o.camera_label)
    cal_of = (lambda t: factory_cal) if o.factory else (lambda t: _online_for(mps.online, t, o.camera_label))
    device_cal = provider.get_device_calibration()
    serials = [device_cal.get_camera_calib(s).get_serial_number() for s in SLAM_LABELS if device_cal.get_camera_calib(s)]
    depth = SparseDepthIndex(mps, serials)
    vignette_raw, warning = read_vignette(o.vignette, factory_cal.height, factory_cal.width)
    if warning:
        print(f"egobench preprocess: warning: {warning}", file=sys.stderr)

    name = stream_folder_name(o.camera_label, o.focal_px, o.size_px, factory=o.factory)
    final, partial = out / name, out.absolute().parent / f".{out.name}.{name}.partial"
    _open_partial(partial, o.fingerprint(vrs, mps_dir))
    rig = _Rig(rectified_pinhole(o.focal_px, o.size_px))
    n = provider.get_num_data(stream_id) if o.max_frames is None else min(o.max_frames, provider.get_num_data(stream_id))
    entries = []
    for i in tqdm(range(n), desc=f"preprocess {vrs.name}", unit="frame", disable=not progress):
        rec_path = partial / ".frames" / f"{i:06d}.json"
        if rec_path.is_file():  # finished by an earlier run
            entry = read_json(rec_path)
        else:
            entry = _process_frame(i, provider, stream_id, mps, cal_of, rig, depth, o.camera_label, partial)
            write_json(rec_path, entry, indent=None)  # last: a frame without it is redone
        entries.append(entry)
    frames = [e for e in entries if "skipped" not in e]
    if not frames:
        raise ValueError(f"{vrs}: none of {n} frames lies inside the trajectory of {mps_dir / TRAJECTORY_FILE}")
    first = cal_of(frames[0]["timestamp"])
    rect = rig.get(first)
    write_camera_maps(partial, rect.warp_vignette(vignette_raw).numpy(), rect.valid.numpy(), rect.row_time_ratio().numpy())
    cpf = device_cal.get_transform_cpf_sensor(o.camera_label)
    write_transforms(partial, frames, camera_label=o.camera_label, camera_model="linear", extra={
        "transform_cpf": None if cpf is None else np.asarray(cpf.to_matrix()).tolist(),
        "calibration": "factory" if o.factory else "online"})
    link_mps_files(partial, mps_dir, absolute=True)
    shutil.rmtree(partial / ".frames")
    if final.exists():
        shutil.rmtree(final)
    out.mkdir(parents=True, exist_ok=True)
    partial.rename(final)
    skipped = len(entries) - len(frames)
    print(f"egobench preprocess: {len(frames)} frames -> {final}" + (f" ({skipped} outside the trajectory skipped)"
                                                                     if skipped else ""), file=sys.stderr)
    return final


# ----------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("vrs", help="the Aria recording (.vrs)")
    parser.add_argument("--mps", required=True,
                        help=f"MPS slam folder ({TRAJECTORY_FILE}, {POINTS_FILE}, {OBSERVATIONS_FILE}, "
                             f"{ONLINE_CALIBRATION_FILE}); usually <scene>/{MPS_SLAM}")
    parser.add_argument("--out", required=True,
                        help="recording folder the stream folder <label>-rectified-<focal>-h<size>[-factory-calib]/ "
                             "is written into (the authors': <scene>/<vrs name>/)")
    parser.add_argument("--focal", type=float, default=1200.0, help="rectified pinhole focal, px (paper: 1200)")
    parser.add_argument("--size", type=int, default=2400, help="rectified image side, px (paper: 2400)")
    parser.add_argument("--factory-calibration", action="store_true",
                        help="rectify with the VRS factory calibration (the 'w/o VIBA' rows) instead of the online one")
    parser.add_argument("--vignette", default=None, help="raw-sensor lens shading PNG (8 or 16 bit)")
    parser.add_argument("--camera", default="camera-rgb", help="camera stream label")
    parser.add_argument("--max-frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")


def run(args: argparse.Namespace) -> int:
    opts = PreprocessOptions(focal_px=args.focal, size_px=args.size, factory=args.factory_calibration,
                             vignette=args.vignette, camera_label=args.camera, max_frames=args.max_frames)
    folder = preprocess(args.vrs, args.mps, args.out, opts, progress=not args.no_progress)
    print(json.dumps({"stream": str(folder)}))
    return 0
