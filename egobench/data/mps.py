"""Aria MPS files: closed-loop trajectory, semi-dense points, online calibration (read + write).

Schemas (docs/paper-notes.md §4):
- ``closed_loop_trajectory.csv``: read/written by `egobench.geometry.Trajectory`.
- ``semidense_points.csv.gz``: uid, graph_uid, px_world, py_world, pz_world, inv_dist_std, dist_std.
- ``online_calibration.jsonl``: one JSON object per line: tracking_timestamp_us,
  CameraCalibrations[] (Label, Projection {Name, Params[15]}, T_Device_Camera {Translation,
  UnitQuaternion [w, [x, y, z]]}, TimeOffsetSec_Device_Camera), ImuCalibrations[], ImageSizes
  [[w, h]] (aligned with CameraCalibrations), ReadoutTimesSec [[camera index, seconds]].

projectaria-tools' readers return empty lists on a bad file; these raise ValueError naming the
file and the line.
"""

from __future__ import annotations

import gzip
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from egobench.camera import Fisheye624
from egobench.geometry import Trajectory, quat_to_rotmat, rotmat_to_quat
from egobench.io_utils import atomic_path, read_csv, read_json, write_json

SEMIDENSE_COLUMNS = ("uid", "graph_uid", "px_world", "py_world", "pz_world", "inv_dist_std", "dist_std")
#: MPS semi-dense filter (docs/paper-notes.md §3): keep inv_dist_std < 0.01 1/m and dist_std < 0.02 m.
MAX_INV_DIST_STD = 0.01
MAX_DIST_STD = 0.02
GRAPH_UID = "00000000-0000-0000-0000-000000000000"  # graph uid written into synthetic files


# ----------------------------------------------------------------------------------------
# Trajectory
# ----------------------------------------------------------------------------------------
def read_trajectory(path: str | Path):
    """closed_loop_trajectory.csv -> `egobench.geometry.Trajectory` (T_world_device, 1 kHz)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    return Trajectory.from_mps_csv(path)


def write_trajectory(trajectory, path: str | Path) -> None:
    """Write a Trajectory as MPS closed_loop_trajectory.csv (atomically)."""
    trajectory.to_mps_csv(Path(path))


# ----------------------------------------------------------------------------------------
# Semi-dense points
# ----------------------------------------------------------------------------------------
@dataclass
class SemiDensePoints:
    """Semi-dense SLAM points in the world frame."""

    uid: np.ndarray  # [P] int64 point ids
    points_world: np.ndarray  # [P, 3] float64 metres
    inv_dist_std: np.ndarray  # [P] 1/m
    dist_std: np.ndarray  # [P] m

    def __len__(self) -> int:
        return int(self.uid.shape[0])

    def filtered(self, max_inv_dist_std: float = MAX_INV_DIST_STD, max_dist_std: float = MAX_DIST_STD) -> "SemiDensePoints":
        """The points passing the MPS quality filter (strict inequalities)."""
        keep = (self.inv_dist_std < max_inv_dist_std) & (self.dist_std < max_dist_std)
        return SemiDensePoints(self.uid[keep], self.points_world[keep], self.inv_dist_std[keep], self.dist_std[keep])


def read_semidense_points(path: str | Path, filter: bool = True, max_inv_dist_std: float = MAX_INV_DIST_STD,
                          max_dist_std: float = MAX_DIST_STD) -> SemiDensePoints:
    """Read semidense_points.csv(.gz); ValueError names the file, line and column of bad rows."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: semi-dense points file not found")
    df = read_csv(path, "semi-dense points CSV")
    missing = [c for c in SEMIDENSE_COLUMNS if c != "graph_uid" and c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; expected columns {list(SEMIDENSE_COLUMNS)}")
    num_cols = ["uid", "px_world", "py_world", "pz_world", "inv_dist_std", "dist_std"]
    values = df[num_cols].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ValueError(
            f"{path}: line {row + 2}, column {num_cols[col]!r}: expected a finite number, "
            f"got {df[num_cols[col]].iloc[row]!r}"
        )
    pts = SemiDensePoints(
        uid=values[:, 0].astype(np.int64), points_world=values[:, 1:4].copy(),
        inv_dist_std=values[:, 4].copy(), dist_std=values[:, 5].copy(),
    )
    return pts.filtered(max_inv_dist_std, max_dist_std) if filter else pts


def write_semidense_points(path: str | Path, points: SemiDensePoints, graph_uid: str = GRAPH_UID) -> None:
    """Write semidense_points.csv.gz (gzip, MPS columns, atomically)."""
    path = Path(path)
    buf = io.StringIO()
    buf.write(",".join(SEMIDENSE_COLUMNS) + "\n")
    p = points.points_world
    for arr, name in ((p, "points_world"), (points.inv_dist_std, "inv_dist_std"), (points.dist_std, "dist_std")):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"write_semidense_points: {name} contains NaN/inf")
    lines = [
        f"{int(u)},{graph_uid},{x:.6f},{y:.6f},{z:.6f},{a:.6f},{b:.6f}"
        for u, (x, y, z), a, b in zip(points.uid.tolist(), p.tolist(), points.inv_dist_std.tolist(),
                                      points.dist_std.tolist())
    ]
    buf.write("\n".join(lines) + ("\n" if lines else ""))
    with atomic_path(path) as tmp:
        # mtime=0 and no file name in the header: identical inputs give byte-identical files
        with open(tmp, "wb") as raw, gzip.GzipFile(filename="", fileobj=raw, mode="wb", compresslevel=6, mtime=0) as gz:
            gz.write(buf.getvalue().encode())


# ----------------------------------------------------------------------------------------
# Calibration
# ----------------------------------------------------------------------------------------
@dataclass
class CameraCalibration:
    """One camera of an MPS calibration (Fisheye624 = FisheyeRadTanThinPrism)."""

    label: str  # "camera-rgb", "camera-slam-left", ...
    params: np.ndarray  # [15] f, cx, cy, k0..k5, p0, p1, s0..s3 (pixels at width x height)
    width: int
    height: int
    T_device_camera: np.ndarray  # [4, 4] float64 camera-to-device
    time_offset_s: float = 0.0  # TimeOffsetSec_Device_Camera: t_device = t_camera + offset
    readout_s: float = 0.0  # rolling-shutter readout (0 = global shutter / not stated)
    projection_name: str = "FisheyeRadTanThinPrism"

    def camera(self):
        """The `egobench.camera.Fisheye624` model of this calibration."""
        return Fisheye624(torch.as_tensor(np.asarray(self.params, dtype=np.float64)), self.width, self.height)

    def to_mps_entry(self) -> dict:
        """The CameraCalibrations[] JSON entry."""
        q = rotmat_to_quat(torch.as_tensor(self.T_device_camera[:3, :3], dtype=torch.float64)).tolist()
        entry = {
            "Calibrated": True,
            "Projection": {"Params": [float(x) for x in self.params], "Description": "see FisheyeRadTanThinPrism.h",
                           "Name": self.projection_name},
            "T_Device_Camera": {"Translation": [float(x) for x in self.T_device_camera[:3, 3]],
                                "UnitQuaternion": [float(q[0]), [float(q[1]), float(q[2]), float(q[3])]]},
            "SerialNumber": "",
            "Label": self.label,
        }
        if self.time_offset_s != 0.0 or self.label == "camera-rgb":
            entry["TimeOffsetSec_Device_Camera"] = float(self.time_offset_s)
        return entry

    @classmethod
    def from_mps_entry(cls, entry: dict, image_size: tuple[int, int], readout_s: float = 0.0,
                       where: str = "calibration") -> "CameraCalibration":
        """Parse one CameraCalibrations[] entry; ValueError names `where` and the field."""
        try:
            label = str(entry["Label"])
            proj = entry["Projection"]
            params = np.asarray(proj["Params"], dtype=np.float64)
            name = str(proj.get("Name", "FisheyeRadTanThinPrism"))
            tdc = entry["T_Device_Camera"]
            trans = np.asarray(tdc["Translation"], dtype=np.float64)
            uq = tdc["UnitQuaternion"]
            quat = np.asarray([uq[0], *uq[1]], dtype=np.float64)
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise ValueError(
                f"{where}: camera entry lacks or mangles a field ({exc!r}); expected Label, Projection.Params[15], "
                f"T_Device_Camera.Translation[3], T_Device_Camera.UnitQuaternion [w, [x, y, z]]"
            ) from exc
        if params.shape != (15,) and name == "FisheyeRadTanThinPrism":
            raise ValueError(f"{where}: camera {label!r} Projection.Params: expected 15 numbers, got {params.shape[0]}")
        if not (np.all(np.isfinite(params)) and np.all(np.isfinite(trans)) and np.all(np.isfinite(quat))
                and trans.shape == (3,) and quat.shape == (4,)):
            raise ValueError(f"{where}: camera {label!r}: non-finite or misshaped Params/Translation/UnitQuaternion")
        qn = np.linalg.norm(quat)
        if not 0.9 < qn < 1.1:
            raise ValueError(f"{where}: camera {label!r} T_Device_Camera.UnitQuaternion has norm {qn}, expected 1")
        T = np.eye(4)
        T[:3, :3] = quat_to_rotmat(torch.as_tensor(quat / qn)).numpy()
        T[:3, 3] = trans
        offset = float(entry.get("TimeOffsetSec_Device_Camera", 0.0))
        if not math.isfinite(offset):
            raise ValueError(f"{where}: camera {label!r} TimeOffsetSec_Device_Camera is not finite")
        w, h = int(image_size[0]), int(image_size[1])
        return cls(label=label, params=params, width=w, height=h, T_device_camera=T, time_offset_s=offset,
                   readout_s=float(readout_s), projection_name=name)


@dataclass
class CalibrationRecord:
    """One line of online_calibration.jsonl (or the factory calibration file)."""

    tracking_timestamp_us: int | None
    cameras: list[CameraCalibration]
    raw: dict = field(default_factory=dict, repr=False)  # the parsed JSON (IMU calibrations etc. kept as is)

    def camera(self, label: str = "camera-rgb") -> CameraCalibration:
        for cam in self.cameras:
            if cam.label == label:
                return cam
        raise ValueError(f"calibration has no camera labelled {label!r} (has {[c.label for c in self.cameras]})")

    def to_json(self) -> dict:
        sizes = [[c.width, c.height] for c in self.cameras]
        readouts = [[i, float(c.readout_s)] for i, c in enumerate(self.cameras) if c.readout_s > 0]
        out = {k: v for k, v in self.raw.items()
               if k not in ("CameraCalibrations", "ImageSizes", "ReadoutTimesSec", "tracking_timestamp_us")}
        out.setdefault("utc_timestamp_ns", -1)
        if self.tracking_timestamp_us is not None:
            out["tracking_timestamp_us"] = int(self.tracking_timestamp_us)
        out["ReadoutTimesSec"] = readouts
        out.setdefault("ImuCalibrations", [])
        out["ImageSizes"] = sizes
        out["CameraCalibrations"] = [c.to_mps_entry() for c in self.cameras]
        return out


def parse_calibration_record(obj: dict, where: str) -> CalibrationRecord:
    """Parse one MPS calibration JSON object (a jsonl line or the factory file)."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    cams = obj.get("CameraCalibrations")
    sizes = obj.get("ImageSizes")
    if not isinstance(cams, list) or not cams:
        raise ValueError(f"{where}: field 'CameraCalibrations' missing or empty (expected a list of cameras)")
    if not isinstance(sizes, list) or len(sizes) != len(cams):
        raise ValueError(
            f"{where}: field 'ImageSizes' must list one [width, height] per camera "
            f"({len(cams)} cameras, got {sizes!r:.80})"
        )
    readouts: dict[int, float] = {}
    for item in obj.get("ReadoutTimesSec", []) or []:
        try:
            readouts[int(item[0])] = float(item[1])
        except (TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"{where}: field 'ReadoutTimesSec' expected [[camera index, seconds]], got {item!r}") from exc
    cameras = [
        CameraCalibration.from_mps_entry(c, tuple(sizes[i]), readouts.get(i, 0.0), where=f"{where}, camera {i}")
        for i, c in enumerate(cams)
    ]
    ts = obj.get("tracking_timestamp_us")
    return CalibrationRecord(tracking_timestamp_us=None if ts is None else int(ts), cameras=cameras, raw=obj)


def read_online_calibration(path: str | Path) -> list[CalibrationRecord]:
    """online_calibration.jsonl -> one record per line; ValueError names file and line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: online calibration file not found")
    records = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: line {lineno}: not valid JSON ({exc.msg} at column {exc.colno})") from exc
        records.append(parse_calibration_record(obj, where=f"{path}: line {lineno}"))
    if not records:
        raise ValueError(f"{path}: no calibration lines (expected one JSON object per line)")
    return records


def write_online_calibration(path: str | Path, records: list[CalibrationRecord]) -> None:
    """Write online_calibration.jsonl (one compact JSON object per line, atomically)."""
    with atomic_path(path) as tmp:
        tmp.write_text("".join(json.dumps(r.to_json(), allow_nan=False) + "\n" for r in records))


def read_calibration_json(path: str | Path) -> CalibrationRecord:
    """A single calibration object (our factory_calibration.json)."""
    return parse_calibration_record(read_json(path), where=str(path))


def write_calibration_json(path: str | Path, record: CalibrationRecord) -> None:
    write_json(path, record.to_json())
