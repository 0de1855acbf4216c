"""The device trajectory T_world_device(t_ns): samples (~1 kHz) plus SE(3) geodesic interpolation.

Between two samples (t_i, T_i), (t_{i+1}, T_{i+1}) the pose is
``T(t) = T_i exp(a xi_i)`` with ``a = (t - t_i) / (t_{i+1} - t_i)`` and ``xi_i = log(T_i^-1 T_{i+1})``
(paper Eq. 1). The body twist is constant on a segment, so the velocity is
``angular_device = omega_i / dt_i`` and ``linear_world = R(t) rho_i / dt_i``, consistent with the
interpolation. Everything is float64; timestamps are int64 nanoseconds (device clock).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.geometry.se3 import (
    check_pose, make_pose, quat_normalize, quat_to_rotmat, rotmat_to_quat, se3_exp, se3_inverse,
    se3_log, so3_log,
)
from egobench.io_utils import atomic_path, read_csv

#: Required columns of MPS closed_loop_trajectory.csv (others are ignored on read).
MPS_POSE_COLUMNS = (
    "tracking_timestamp_us",
    "tx_world_device", "ty_world_device", "tz_world_device",
    "qx_world_device", "qy_world_device", "qz_world_device", "qw_world_device",
)
#: Columns written by Trajectory.to_mps_csv, in MPS order.
MPS_WRITE_COLUMNS = (
    "graph_uid", "tracking_timestamp_us", "utc_timestamp_ns",
    "tx_world_device", "ty_world_device", "tz_world_device",
    "qx_world_device", "qy_world_device", "qz_world_device", "qw_world_device",
    "device_linear_velocity_x_device", "device_linear_velocity_y_device", "device_linear_velocity_z_device",
    "angular_velocity_x_device", "angular_velocity_y_device", "angular_velocity_z_device",
    "gravity_x_world", "gravity_y_world", "gravity_z_world", "quality_score",
)
#: Gravity written to MPS files (world frame, z up), m/s^2.
GRAVITY_WORLD_M_S2 = (0.0, 0.0, -9.81)
#: graph_uid written by to_mps_csv (a single connected SLAM graph).
DEFAULT_GRAPH_UID = "00000000-0000-0000-0000-000000000000"


@dataclass(frozen=True)
class TrajectoryVelocity:
    """Instantaneous velocity of the device at the queried times."""

    linear_world: Tensor  # [B, 3] device origin velocity in the world frame, m/s
    angular_device: Tensor  # [B, 3] angular velocity in the device frame, rad/s


def _as_time_tensor(t_ns, name: str = "t_ns") -> Tensor:
    """int / numpy / torch timestamps -> int64 tensor [B] (a scalar becomes [1])."""
    if isinstance(t_ns, Tensor):
        t = t_ns
    else:
        arr = np.asarray(t_ns)
        if arr.dtype.kind not in "iu":
            raise ValueError(f"{name}: expected integer nanoseconds (int, int64 array or tensor), got dtype {arr.dtype}")
        t = torch.from_numpy(arr.astype(np.int64))
    if t.dtype.is_floating_point or t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name}: expected integer nanoseconds (int64), got {t.dtype}")
    return t.to(torch.int64).reshape(-1)


class Trajectory:
    """T_world_device sampled at strictly increasing int64 ``t_ns`` [M], interpolated on SE(3)."""

    def __init__(self, t_ns, T_world_device) -> None:
        t = _as_time_tensor(t_ns, "Trajectory(t_ns)")
        T = torch.as_tensor(T_world_device, dtype=torch.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"Trajectory(T_world_device): expected shape [M, 4, 4], got {tuple(T.shape)}")
        if T.shape[0] != t.shape[0]:
            raise ValueError(
                f"Trajectory: t_ns has {t.shape[0]} samples but T_world_device has {T.shape[0]}"
            )
        if t.shape[0] < 2:
            raise ValueError(f"Trajectory: need at least 2 samples, got {t.shape[0]}")
        dt = t[1:] - t[:-1]
        if bool((dt <= 0).any()):
            i = int((dt <= 0).nonzero()[0, 0])
            raise ValueError(
                f"Trajectory(t_ns): timestamps must be strictly increasing; sample {i + 1} "
                f"(t_ns={int(t[i + 1])}) follows t_ns={int(t[i])}"
            )
        check_pose(T, "Trajectory(T_world_device)")
        self.t_ns: Tensor = t.clone()  # [M] int64
        self.T_world_device: Tensor = T.clone()  # [M, 4, 4] float64
        # Segment twists xi_i = log(T_i^-1 T_{i+1}) [M-1, 6] and durations [M-1] (s).
        self._xi = se3_log(pm.matmul(se3_inverse(T[:-1]), T[1:]))
        self._dt_s = dt.to(torch.float64) * 1e-9

    # ---- basic properties ---------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def __repr__(self) -> str:
        return f"Trajectory({len(self)} samples, [{self.start_ns}, {self.end_ns}] ns, {self.duration_s:.3f} s)"

    @property
    def start_ns(self) -> int:
        return int(self.t_ns[0])

    @property
    def end_ns(self) -> int:
        return int(self.t_ns[-1])

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    # ---- queries ----------------------------------------------------------------------------
    def _locate(self, t_ns) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """-> (query [B] int64, segment index [B], alpha [B] float64, is_last_sample [B] bool)."""
        t = _as_time_tensor(t_ns)
        outside = (t < self.t_ns[0]) | (t > self.t_ns[-1])
        if bool(outside.any()):
            bad = int(t[outside][0])
            raise ValueError(
                f"Trajectory: t_ns={bad} outside the trajectory span [{self.start_ns}, {self.end_ns}] ns"
            )
        idx = torch.searchsorted(self.t_ns, t, right=True) - 1  # t_idx <= t
        is_last = idx == len(self) - 1
        seg = idx.clamp(max=len(self) - 2)
        t0 = self.t_ns[seg]
        alpha = (t - t0).to(torch.float64) / (self.t_ns[seg + 1] - t0).to(torch.float64)
        alpha = torch.where(is_last, torch.ones_like(alpha), alpha)
        return t, seg, alpha, is_last

    def pose(self, t_ns) -> Tensor:
        """T_world_device at ``t_ns`` (int, int64 array/tensor [B]) -> [B, 4, 4] float64."""
        _, seg, alpha, is_last = self._locate(t_ns)
        T = pm.matmul(self.T_world_device[seg], se3_exp(alpha[:, None] * self._xi[seg]))
        # Exact at samples: alpha = 0 gives exp(0) = I exactly; the last sample is copied.
        return torch.where(is_last[:, None, None], self.T_world_device[-1].expand_as(T), T)

    def velocity(self, t_ns) -> TrajectoryVelocity:
        """Velocity of the interpolated trajectory at ``t_ns`` [B] (right-continuous at samples)."""
        _, seg, alpha, is_last = self._locate(t_ns)
        # At a sample the segment starting there is used; the last sample uses the last segment.
        twist = self._xi[seg] / self._dt_s[seg, None]  # [B, 6] body twist per second
        T = pm.matmul(self.T_world_device[seg], se3_exp(alpha[:, None] * self._xi[seg]))
        T = torch.where(is_last[:, None, None], self.T_world_device[-1].expand_as(T), T)
        linear_world = pm.vecdot(T[:, :3, :3], twist[:, None, :3])
        return TrajectoryVelocity(linear_world=linear_world, angular_device=twist[:, 3:].clone())

    def angular_speed_deg_s(self, stride: int = 1) -> np.ndarray:
        """|log(R_i^T R_{i+stride})| / dt between samples i and i+stride -> numpy [M - stride], deg/s."""
        if int(stride) != stride or stride < 1 or stride >= len(self):
            raise ValueError(f"angular_speed_deg_s(stride): expected an integer in [1, {len(self) - 1}], got {stride}")
        R = self.T_world_device[:, :3, :3]
        dR = R[:-stride].transpose(-1, -2) @ R[stride:]
        angle = so3_log(dR).norm(dim=-1)
        dt_s = (self.t_ns[stride:] - self.t_ns[:-stride]).to(torch.float64) * 1e-9
        return np.degrees((angle / dt_s).numpy())

    # ---- derived trajectories --------------------------------------------------------------
    def slice(self, start_ns: int, end_ns: int) -> "Trajectory":
        """The trajectory on [start_ns, end_ns] (interpolated end poses added; same curve)."""
        start_ns, end_ns = int(start_ns), int(end_ns)
        if not start_ns < end_ns:
            raise ValueError(f"Trajectory.slice: expected start_ns < end_ns, got {start_ns} >= {end_ns}")
        self._locate(torch.tensor([start_ns, end_ns]))  # range check with the standard message
        inside = (self.t_ns > start_ns) & (self.t_ns < end_ns)
        t = torch.cat([torch.tensor([start_ns]), self.t_ns[inside], torch.tensor([end_ns])])
        T = torch.cat([self.pose(start_ns), self.T_world_device[inside], self.pose(end_ns)])
        return Trajectory(t, T)

    def transformed(self, T_new_world: Tensor) -> "Trajectory":
        """Re-expressed in another world frame: T_new_device = T_new_world @ T_world_device."""
        T_new_world = torch.as_tensor(T_new_world, dtype=torch.float64)
        if T_new_world.shape != (4, 4):
            raise ValueError(f"Trajectory.transformed(T_new_world): expected shape [4, 4], got {tuple(T_new_world.shape)}")
        check_pose(T_new_world, "Trajectory.transformed(T_new_world)")
        return Trajectory(self.t_ns, T_new_world @ self.T_world_device)

    # ---- MPS csv -------------------------------------------------------------------------------
    @classmethod
    def from_mps_csv(cls, path: str | os.PathLike) -> "Trajectory":
        """Read MPS closed_loop_trajectory.csv (timestamps us -> ns, quaternion xyzw -> wxyz)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: trajectory file not found")
        df = read_csv(path, "MPS trajectory CSV", usecols=lambda c: c in MPS_POSE_COLUMNS)
        missing = [c for c in MPS_POSE_COLUMNS if c not in df.columns]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; an MPS closed_loop_trajectory.csv needs {list(MPS_POSE_COLUMNS)}")
        if len(df) < 2:
            raise ValueError(f"{path}: need at least 2 trajectory rows, got {len(df)}")
        for col in MPS_POSE_COLUMNS:  # line numbers are 1-based with the header on line 1
            values = pd.to_numeric(df[col], errors="coerce")
            bad = ~np.isfinite(values.to_numpy(dtype=np.float64))
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"{path}: line {row + 2}, column {col!r}: expected a finite number, got {df[col].iloc[row]!r}"
                )
            df[col] = values
        t_us = df["tracking_timestamp_us"].to_numpy()
        if not np.all(np.equal(np.mod(t_us, 1), 0)):
            row = int(np.flatnonzero(np.mod(t_us, 1) != 0)[0])
            raise ValueError(f"{path}: line {row + 2}, column 'tracking_timestamp_us': expected an integer, got {t_us[row]!r}")
        t_ns = t_us.astype(np.int64) * 1000
        nonincr = np.flatnonzero(np.diff(t_ns) <= 0)
        if nonincr.size:
            row = int(nonincr[0]) + 1
            raise ValueError(
                f"{path}: line {row + 2}, column 'tracking_timestamp_us': time must be strictly increasing "
                f"({int(t_us[row])} follows {int(t_us[row - 1])})"
            )
        q_xyzw = df[["qx_world_device", "qy_world_device", "qz_world_device", "qw_world_device"]].to_numpy(np.float64)
        norms = np.linalg.norm(q_xyzw, axis=1)
        if (norms < 0.5).any() or (norms > 1.5).any():
            row = int(np.flatnonzero((norms < 0.5) | (norms > 1.5))[0])
            raise ValueError(
                f"{path}: line {row + 2}, columns 'qx..qw_world_device': expected a unit quaternion, norm is {norms[row]:.6g}"
            )
        q_wxyz = torch.from_numpy(q_xyzw[:, [3, 0, 1, 2]])
        t_xyz = torch.from_numpy(df[["tx_world_device", "ty_world_device", "tz_world_device"]].to_numpy(np.float64))
        T = make_pose(quat_to_rotmat(quat_normalize(q_wxyz, f"{path}: quaternions")), t_xyz)
        return cls(torch.from_numpy(t_ns), T)

    def to_mps_csv(self, path: str | os.PathLike, graph_uid: str = DEFAULT_GRAPH_UID) -> None:
        """Write the MPS closed_loop_trajectory.csv columns (atomically); t_ns must be whole microseconds."""
        rem = torch.remainder(self.t_ns, 1000)
        if bool((rem != 0).any()):
            i = int((rem != 0).nonzero()[0, 0])
            raise ValueError(
                f"Trajectory.to_mps_csv: MPS stores microseconds, but sample {i} has t_ns={int(self.t_ns[i])} "
                "(not a whole microsecond); resample the trajectory first"
            )
        vel = self.velocity(self.t_ns)
        R = self.T_world_device[:, :3, :3]
        linear_device = pm.vecdot(R.transpose(-1, -2), vel.linear_world[..., None, :])
        q = rotmat_to_quat(R).numpy()
        t = self.T_world_device[:, :3, 3].numpy()
        M = len(self)
        cols = {
            "graph_uid": [graph_uid] * M,
            "tracking_timestamp_us": (self.t_ns // 1000).numpy(),
            "utc_timestamp_ns": np.full(M, -1, dtype=np.int64),
            "tx_world_device": t[:, 0], "ty_world_device": t[:, 1], "tz_world_device": t[:, 2],
            "qx_world_device": q[:, 1], "qy_world_device": q[:, 2], "qz_world_device": q[:, 3],
            "qw_world_device": q[:, 0],
        }
        for k, axis in enumerate("xyz"):
            cols[f"device_linear_velocity_{axis}_device"] = linear_device[:, k].numpy()
        for k, axis in enumerate("xyz"):
            cols[f"angular_velocity_{axis}_device"] = vel.angular_device[:, k].numpy()
        for k, axis in enumerate("xyz"):
            cols[f"gravity_{axis}_world"] = np.full(M, GRAVITY_WORLD_M_S2[k])
        cols["quality_score"] = np.ones(M)
        df = pd.DataFrame(cols, columns=list(MPS_WRITE_COLUMNS))
        with atomic_path(path) as tmp:
            df.to_csv(tmp, index=False, float_format="%.17g")
