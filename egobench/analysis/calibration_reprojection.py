"""Calibration geometry shared by `egobench.analysis.similarity` and `egobench.analysis.calibration_inconsistency`: frame
changes of points, where a rectified image shows a point under another calibration, the online
calibration nearest a time, the simulator's frame numbers, and a robust median/p90 summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from egobench.data.recording import Frame


def median_p90(values: np.ndarray) -> tuple[float | None, float | None]:
    """(median, 90th percentile) of the finite values; (None, None) when there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None, None
    return float(np.median(v)), float(np.percentile(v, 90))


def frame_number(frame: Frame) -> int:
    """The simulator's frame number k of a frame (its image name NNNNN.png), else its index."""
    stem = Path(frame.image_path).stem
    return int(stem) if stem.isdigit() else int(frame.index)


def to_camera(T_a_camera: Tensor | np.ndarray, points_a: Tensor) -> Tensor:
    """Points [P, 3] in frame a -> the camera frame, given T_a_camera (camera -> a)."""
    T = torch.as_tensor(np.asarray(T_a_camera), dtype=torch.float64)
    return (points_a - T[:3, 3]) @ T[:3, :3]  # R^T (p - t), row vectors


def from_camera(T_a_camera: Tensor, points_camera: Tensor) -> Tensor:
    """Points [P, 3] in the camera frame -> frame a."""
    T = T_a_camera.to(torch.float64)
    return points_camera @ T[:3, :3].T + T[:3, 3]


def observed_in_test_px(points_reference_device: Tensor, reference, test, pinhole) -> tuple[Tensor, Tensor]:
    """Where ``test``'s rectified image shows device points [P, 3] that ``reference`` images right:
    (pixels [P, 2] of ``pinhole``, valid [P]). Fisheye `CameraCalibration`s: the raw pixel
    r = F_ref(X_ref) rectified by test, pinhole(F_test^-1(r)); 4x4 T_device_camera's (rectified
    streams, extrinsics only): pinhole(X_ref)."""
    P = torch.as_tensor(points_reference_device, dtype=torch.float64)
    if not hasattr(reference, "camera"):
        return pinhole.project(to_camera(reference, P))
    raw, ok = reference.camera().project(to_camera(reference.T_device_camera, P))
    ok = ok & (raw[:, 0] >= 0) & (raw[:, 0] <= reference.width - 1) & (raw[:, 1] >= 0) & (raw[:, 1] <= reference.height - 1)
    ray, conv = test.camera().unproject_checked(raw)
    u_obs, ok_obs = pinhole.project(ray)
    return u_obs, ok & conv & ok_obs


def online_at(online: list, t_ns: int):
    """The online calibration record nearest in time to ``t_ns``."""
    i = int(np.argmin([abs(ts * 1000 - t_ns) for ts, _ in online]))
    return online[i][1]
