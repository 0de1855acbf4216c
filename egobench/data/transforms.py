"""The authors' preprocessed format (facebookresearch/egocentric_splats): write and parse.

One folder per rectified camera stream (egobench.data.layout says where they lie)::

    transforms.json                    camera_model, camera_label, transform_cpf, frames[]
    transforms_with_sparse_depth.json  the same, each frame adding ``sparse_depth`` (what training reads)
    images/*.png                       rectified 8-bit RGB
    vignette.png                       rectified lens shading x 255 (8-bit)
    mask.png                           valid rectified pixels (255) / invalid (0)
    image_index.png                    round(R(u) * 255): raw row / (H_raw - 1), rectified (8-bit)
    row_time_ratio.npy                 the same R(u) as float32 [H, W] (egobench addition, full precision)
    sparse_depth/*.json                {"u": [...], "v": [...], "z": [...], "inverseDistanceStd": [...], "distanceStd": [...]}

Per frame: fx, fy, cx, cy, w, h, image_path, mask_path ("" = none), camera2device (4x4, rectified
camera to device), transform_matrix (4x4 camera-to-world, OpenCV axes, metres, at `timestamp`),
timestamp, timestamp_read_start, timestamp_read_end (device clock, ns; the authors write
capture time, capture + readout / 2 and capture + readout), exposure_duration_s, gain; the
``_with_sparse_depth`` file adds sparse_depth (a path relative to the folder).

Principal point convention: cx, cy follow projectaria-tools (centre of pixel (i, j) at (i, j),
an image centred on the axis has cx = (W - 1) / 2). gsplat's +0.5 is added inside the
rasterizer only (egobench/camera/pinhole.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from egobench.camera.pinhole import Pinhole
from egobench.data.layout import TRANSFORMS, TRANSFORMS_WITH_DEPTH, stream_file, transforms_file
from egobench.data.recording import SparseDepth
from egobench.io_utils import atomic_path, read_json, write_json

#: Plausibility bounds of the capture metadata, generous around an Aria RGB frame (exposures of
#: 0.1-40 ms, analog gains 1-16, a rolling-shutter readout of 5-33 ms).
MAX_EXPOSURE_S, MIN_GAIN, MAX_GAIN, MAX_READOUT_S = 10.0, 1e-3, 1e3, 0.1
FRAME_FIELDS = ("fx", "fy", "cx", "cy", "w", "h", "image_path", "camera2device", "transform_matrix",
                "timestamp", "timestamp_read_start", "timestamp_read_end", "exposure_duration_s", "gain")


@dataclass
class TransformsFrame:
    """One parsed frame entry of transforms.json."""

    position: int  # index in the file's frames list
    image_path: Path  # absolute
    image_rel: str  # image_path as written in the file (the authors sort frames by it)
    mask_path: Path | None
    camera: Pinhole
    camera2device: np.ndarray  # [4, 4] float64
    transform_matrix: np.ndarray  # [4, 4] float64 camera-to-world at timestamp
    timestamp_ns: int
    read_start_ns: int
    read_end_ns: int
    exposure_s: float
    gain: float
    sparse_depth_path: Path | None


@dataclass
class TransformsFile:
    """A parsed transforms.json."""

    path: Path
    camera_model: str
    camera_label: str
    frames: list[TransformsFrame]
    extra: dict  # top-level keys other than frames


# ----------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------
def frame_entry(index: int, camera: Pinhole, camera2device: np.ndarray, transform_matrix: np.ndarray,
                timestamp_ns: int, read_start_ns: int, read_end_ns: int, exposure_s: float, gain: float,
                image_ext: str = "png") -> dict:
    """One frames[] entry of transforms_with_sparse_depth.json (paths relative to the folder:
    images/NNNNN.png, sparse_depth/NNNNN.json; zero-padded, so sorting by image path is time order)."""
    return {
        "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
        "w": int(camera.width), "h": int(camera.height),
        "image_path": f"images/{index:05d}.{image_ext}", "mask_path": "mask.png",
        "camera2device": np.asarray(camera2device, dtype=np.float64).tolist(),
        "transform_matrix": np.asarray(transform_matrix, dtype=np.float64).tolist(),
        "timestamp": int(timestamp_ns), "timestamp_read_start": int(read_start_ns),
        "timestamp_read_end": int(read_end_ns),
        "exposure_duration_s": float(exposure_s), "gain": float(gain),
        "sparse_depth": f"sparse_depth/{index:05d}.json",
    }


def write_transforms(folder: str | Path, frames: list[dict], camera_label: str = "camera-rgb",
                     camera_model: str = "linear", extra: dict | None = None) -> None:
    """Write transforms_with_sparse_depth.json (frames as given) and transforms.json (without
    the per-frame ``sparse_depth``), atomically, as the authors' preprocessing leaves them."""
    obj: dict[str, Any] = {"camera_model": camera_model, "camera_label": camera_label}
    obj.update(extra or {})
    plain = [{k: v for k, v in f.items() if k != "sparse_depth"} for f in frames]
    if any("sparse_depth" in f for f in frames):
        write_json(Path(folder) / TRANSFORMS_WITH_DEPTH, {**obj, "frames": frames})
    write_json(Path(folder) / TRANSFORMS, {**obj, "frames": plain})


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an 8-bit PNG atomically (RGB [H,W,3] or grey [H,W] uint8)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"write_png({path}): expected uint8, got {image.dtype}")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise ValueError(f"{path}: PNG encoding failed")
        tmp.write_bytes(buf.tobytes())


def write_camera_maps(folder: str | Path, vignette: np.ndarray, mask: np.ndarray, row_time_ratio: np.ndarray) -> None:
    """vignette.png, mask.png, image_index.png (= round(R * 255)) and row_time_ratio.npy."""
    folder = Path(folder)
    v = np.clip(np.asarray(vignette, dtype=np.float64), 0.0, 1.0)
    r = np.clip(np.asarray(row_time_ratio, dtype=np.float32), 0.0, 1.0)
    write_png(folder / "vignette.png", np.round(v * 255.0).astype(np.uint8))
    write_png(folder / "mask.png", np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8))
    write_png(folder / "image_index.png", np.round(r * 255.0).astype(np.uint8))
    with atomic_path(folder / "row_time_ratio.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, r.astype(np.float32))


def write_sparse_depth(path: str | Path, uv: np.ndarray, z: np.ndarray, inv_dist_std: np.ndarray,
                       dist_std: np.ndarray) -> None:
    """Sparse depth JSON: u, v (rectified pixels, integer-centred), z (m), stds."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    write_json(path, {
        "u": uv[:, 0].tolist(), "v": uv[:, 1].tolist(), "z": np.asarray(z, dtype=np.float64).tolist(),
        "inverseDistanceStd": np.asarray(inv_dist_std, dtype=np.float64).tolist(),
        "distanceStd": np.asarray(dist_std, dtype=np.float64).tolist(),
    }, indent=None)


# ----------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------
def _matrix(value: Any, where: str, key: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: field {key!r} must be a 4x4 matrix of numbers") from exc
    if m.shape != (4, 4):
        raise ValueError(f"{where}: field {key!r} must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{where}: field {key!r} contains NaN or infinite values")
    R = m[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1.0) > 1e-4 or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"{where}: field {key!r} is not a rigid transform (rotation not orthonormal or last row != 0 0 0 1)")
    return m


def _number(entry: dict, key: str, where: str, integer: bool = False, positive: bool = False,
            at_most: float | None = None, at_least: float | None = None) -> float | int:
    if key not in entry:
        raise ValueError(f"{where}: missing field {key!r}")
    v = entry[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{where}: field {key!r} must be a finite number, got {v!r}")
    if integer:
        if float(v) != int(v):
            raise ValueError(f"{where}: field {key!r} must be an integer (nanoseconds / pixels), got {v!r}")
        v = int(v)
    if positive and v <= 0:
        raise ValueError(f"{where}: field {key!r} must be > 0, got {v!r}")
    if (at_most is not None and v > at_most) or (at_least is not None and v < at_least):
        low, high = at_least if at_least is not None else 0, at_most if at_most is not None else "any"
        raise ValueError(f"{where}: field {key!r} = {v!r} is implausible (expected {low} to {high})")
    return v


def read_transforms(path: str | Path, check_files: bool = True) -> TransformsFile:
    """Parse and validate a transforms file (or a stream folder's: transforms_with_sparse_depth.json,
    else transforms.json); ValueError names the file, frame and field. Paths inside are relative
    to the file's folder."""
    path = Path(path)
    if path.is_dir():
        found = transforms_file(path)
        if found is None:
            raise FileNotFoundError(f"{path}: neither {TRANSFORMS_WITH_DEPTH} nor transforms.json here")
        path = found
    folder = path.parent
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a JSON object with 'frames'")
    frames_in = obj.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise ValueError(f"{path}: field 'frames' missing or empty (expected a list of frames)")
    camera_model = str(obj.get("camera_model", "linear"))
    if camera_model not in ("linear", "pinhole", "PINHOLE"):
        raise ValueError(f"{path}: camera_model {camera_model!r} is not supported (expected 'linear' pinhole)")
    frames: list[TransformsFrame] = []
    for i, entry in enumerate(frames_in):
        where = f"{path}: frame {i}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: expected an object")
        if "image_path" in entry:
            where = f"{path}: frame {i} ({entry['image_path']})"
        for key in FRAME_FIELDS:
            if key not in entry:
                raise ValueError(f"{where}: missing field {key!r}")
        try:
            cam = Pinhole(fx=float(_number(entry, "fx", where, positive=True)),
                          fy=float(_number(entry, "fy", where, positive=True)),
                          cx=float(_number(entry, "cx", where)), cy=float(_number(entry, "cy", where)),
                          width=int(_number(entry, "w", where, integer=True, positive=True)),
                          height=int(_number(entry, "h", where, integer=True, positive=True)))
        except ValueError as exc:
            raise ValueError(f"{where}: bad intrinsics ({exc})") from exc
        image_path = stream_file(folder, entry["image_path"], where, "image_path")
        if check_files and not image_path.is_file():
            raise ValueError(f"{where}: image file {image_path} is missing")
        mask_path, sparse_depth_path = (
            None if entry.get(key) in (None, "") else stream_file(folder, entry[key], where, key)  # "" / null: none
            for key in ("mask_path", "sparse_depth"))
        t = _number(entry, "timestamp", where, integer=True)
        t0 = _number(entry, "timestamp_read_start", where, integer=True)
        t1 = _number(entry, "timestamp_read_end", where, integer=True)
        if t1 < t0:
            raise ValueError(f"{where}: timestamp_read_end {t1} precedes timestamp_read_start {t0}")
        if (t1 - t0) * 1e-9 > MAX_READOUT_S:
            raise ValueError(f"{where}: timestamp_read_end - timestamp_read_start = {(t1 - t0) * 1e-9:.4g} s is an "
                             f"implausible rolling-shutter readout (at most {MAX_READOUT_S:g} s expected)")
        frames.append(TransformsFrame(
            position=i, image_path=image_path, image_rel=str(entry["image_path"]), mask_path=mask_path, camera=cam,
            camera2device=_matrix(entry["camera2device"], where, "camera2device"),
            transform_matrix=_matrix(entry["transform_matrix"], where, "transform_matrix"),
            timestamp_ns=t, read_start_ns=t0, read_end_ns=t1,
            exposure_s=float(_number(entry, "exposure_duration_s", where, positive=True, at_most=MAX_EXPOSURE_S)),
            gain=float(_number(entry, "gain", where, positive=True, at_most=MAX_GAIN, at_least=MIN_GAIN)),
            sparse_depth_path=sparse_depth_path,
        ))
    extra = {k: v for k, v in obj.items() if k != "frames"}
    return TransformsFile(path=path, camera_model=camera_model, camera_label=str(obj.get("camera_label", "camera-rgb")),
                          frames=frames, extra=extra)


def read_sparse_depth(path: str | Path, where: str = ""):
    """Sparse depth JSON -> egobench.data.recording.SparseDepth; ValueError names the file."""
    path = Path(path)
    obj = read_json(path)
    keys = ("u", "v", "z", "inverseDistanceStd", "distanceStd")
    if not isinstance(obj, dict) or any(k not in obj for k in keys):
        raise ValueError(f"{path}{where}: expected an object with lists {list(keys)}")
    try:
        arrs = {k: np.asarray(obj[k], dtype=np.float64).reshape(-1) for k in keys}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}{where}: sparse depth lists must hold numbers") from exc
    n = arrs["u"].shape[0]
    if any(a.shape[0] != n for a in arrs.values()):
        raise ValueError(f"{path}{where}: lists {list(keys)} must have equal lengths")
    if not all(np.all(np.isfinite(a)) for a in arrs.values()):
        raise ValueError(f"{path}{where}: sparse depth contains NaN or infinite values")
    return SparseDepth(uv=np.stack([arrs["u"], arrs["v"]], -1), z=arrs["z"], inv_dist_std=arrs["inverseDistanceStd"],
                       dist_std=arrs["distanceStd"])


def read_png(path: str | Path, what: str, grey: bool = True) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: {what} image missing or unreadable")
    return img
