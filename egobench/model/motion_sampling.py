"""Rolling-shutter motion sampling (paper Sec. 3, "Camera motion sampling"; docs/paper-notes.md §2).

A frame's rows expose at different times: row time t(u) = t_c - R/2 + R(u) * R, where t_c is
the frame's centre-row (mid-exposure) time `Frame.timestamp_ns`, R the readout duration and
R(u) the rectified row-time look-up image (`Recording.row_time_ratio`, 0..1). We render one
image per pose sample and gather each pixel from the sample its row time falls in.

How many samples (`n_pose_samples`), two rules:

- `PoseSampling.rule` "code" (default; the authors' released code, `scene/cameras.py`): the median over
  the frame's sparse-depth points of the pixel displacement max(|du|, |dv|) between the poses
  at t_c - 1 ms and t_c + 1 ms (a 2 ms window) is scaled to the readout:
  N = clamp(int(R / 2 ms * median_px / step_px), 1, max_samples) (the code: step_px 1). For constant
  velocity this equals the median displacement between the read-start and read-end poses, in steps.
- `PoseSampling.rule` "paper" (the paper's sentence: "half of the reprojected pixels have fewer than
  1 pixel reprojection error"): the smallest N in 1..max_samples for which, in every one of the
  N brackets, the median displacement between the bracket's start and end poses is < step_px (1 px).

Bracket centres are t_c - R/2 + (i + 0.5) R / N (i = 0..N-1), and the per-pixel sample index
is round(R(u) * (N - 1)) (as the released code; note this differs slightly from the bracket
that contains R(u), floor(R(u) * N), for N >= 3: we follow the code).

Exposure samples: the released code caps them at 1 (poses at the mid-exposure time). With
``n_exposure_samples = M > 1`` each rolling-shutter sample is split into M poses at the centres of
M equal sub-intervals of the exposure; a method averages the M gathered renders (Eq. 3).

The 3DGS-on-the-move baseline (``velocity_shift``) does not use the trajectory per pixel: it keeps a
per-frame twist (linear and angular velocity in the camera frame), assumes row time linear in
the *rectified* image row (the pinhole assumption) and extrapolates the centre pose with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from egobench.data.recording import Frame, Recording
from egobench.geometry import make_pose, so3_exp
from egobench.model.pose_sampling import PoseSampling

#: The released code measures pixel motion over this window (its `_motion_sample_max`, 2 ms).
MOTION_WINDOW_S = 2e-3
#: The name of a run's learned timing correction among its trainables (`TrainConfig.learn_timing`; [2], ms)
TIMING_KEY = "timing"
#: The learned timing's entries, in its vector's order (`timing_shifts_s`), as train.json's ``learned_timing`` names them
TIMING_FIELDS = ("time_offset_ms", "readout_error_ms")


@dataclass
class MotionEstimate:
    """Pixel motion of a frame's sparse points, as used to pick the sample count."""

    n_samples: int  # chosen number of rolling-shutter pose samples
    median_motion_px: float  # median displacement over the rule's window (code rule: 2 ms), pixels
    n_points: int  # sparse points used (in front of the camera and inside the image at both times)
    rule: str  # "code" or "paper"


def camera_poses_at(recording: Recording, frame: Frame, t_ns: Tensor | np.ndarray) -> Tensor:
    """T_world_camera [T, 4, 4] float64 at device times t_ns [T] from the trajectory."""
    t = torch.round(torch.as_tensor(np.asarray(t_ns, dtype=np.float64))).to(torch.int64).reshape(-1)  # trajectory: int ns
    T_world_device = torch.as_tensor(recording.trajectory.pose(t), dtype=torch.float64)
    if T_world_device.shape != (t.shape[0], 4, 4):
        raise ValueError(
            f"recording.trajectory.pose: expected [T, 4, 4] poses for {t.shape[0]} times, got {tuple(T_world_device.shape)}"
        )
    return T_world_device @ frame.T_device_camera.to(torch.float64)


def sparse_points_camera(recording: Recording, frame: Frame) -> Tensor:
    """The frame's sparse-depth points in its centre-row camera frame, [P, 3] float64."""
    sd = frame.sparse_depth
    if sd is None or len(sd.z) == 0:
        raise ValueError(
            f"frame {frame.index} ({frame.image_path}): no sparse depth; motion sampling needs the frame's "
            "sparse-depth points (sparse_depth/NNNNN.json)"
        )
    uv = torch.as_tensor(np.asarray(sd.uv, dtype=np.float64))
    z = torch.as_tensor(np.asarray(sd.z, dtype=np.float64))
    cam = recording.camera
    x = (uv[:, 0] - cam.cx) / cam.fx * z
    y = (uv[:, 1] - cam.cy) / cam.fy * z
    return torch.stack([x, y, z], dim=-1)


def displacements_px(recording: Recording, frame: Frame, t0_ns: Tensor, t1_ns: Tensor) -> tuple[Tensor, Tensor]:
    """Chebyshev pixel displacement of the sparse points between times t0 and t1 (each [K]).

    Returns (disp [K, P] float64, valid [K, P] bool): valid = in front and inside the image at both times.
    """
    p_c = sparse_points_camera(recording, frame)  # [P, 3] in the frame's centre camera
    K = t0_ns.shape[0]
    T_wc = camera_poses_at(recording, frame, torch.cat([t0_ns, t1_ns]))  # [2K, 4, 4]
    T_c0 = frame.T_world_camera.to(torch.float64)
    p_w = p_c @ T_c0[:3, :3].T + T_c0[:3, 3]  # [P, 3]
    R_cw = T_wc[:, :3, :3].transpose(1, 2)  # [2K, 3, 3]
    p_t = torch.einsum("kij,pj->kpi", R_cw, p_w) - torch.einsum("kij,kj->ki", R_cw, T_wc[:, :3, 3])[:, None, :]
    cam = recording.camera
    z = p_t[..., 2]
    in_front = z > 1e-6
    zs = torch.where(in_front, z, torch.ones_like(z))
    u = cam.fx * p_t[..., 0] / zs + cam.cx
    v = cam.fy * p_t[..., 1] / zs + cam.cy
    inside = in_front & (u >= -0.5) & (u <= cam.width - 0.5) & (v >= -0.5) & (v <= cam.height - 0.5)
    disp = torch.maximum((u[:K] - u[K:]).abs(), (v[:K] - v[K:]).abs())
    return disp, inside[:K] & inside[K:]


def _nan_median(disp: Tensor, valid: Tensor) -> Tensor:  # [K, P], [K, P] -> [K]
    return torch.where(valid, disp, torch.full_like(disp, float("nan"))).nanmedian(dim=1).values


def estimate_motion(recording: Recording, frame: Frame, sampling: PoseSampling = PoseSampling(),
                    pixel_scale: float = 1.0) -> MotionEstimate:
    """Pick the number of rolling-shutter pose samples for ``frame`` by ``sampling``'s rule, cap and step (see
    module docstring).

    ``pixel_scale`` converts the recording's pixels to the rendered ones (training at half
    resolution: 0.5), so that "1 pixel" means one rendered pixel, as the step does.
    `MotionEstimate.median_motion_px` stays in rendered pixels.
    """
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale: expected > 0, got {pixel_scale}")
    readout_ns = frame.read_end_ns - frame.read_start_ns
    if readout_ns < 0:
        raise ValueError(f"frame {frame.index}: read_end_ns < read_start_ns ({frame.read_end_ns} < {frame.read_start_ns})")
    count = _code_rule if sampling.rule == "code" else _paper_rule  # PoseSampling has checked its rule
    return count(recording, frame, sampling, pixel_scale, readout_ns)


def _code_rule(recording: Recording, frame: Frame, sampling: PoseSampling, pixel_scale: float,
               readout_ns: int) -> MotionEstimate:
    """The released code's count: the median motion over `MOTION_WINDOW_S` scaled to the readout, in steps."""
    t_c, half = float(frame.timestamp_ns), MOTION_WINDOW_S * 1e9 / 2
    disp, valid = displacements_px(
        recording, frame, torch.tensor([t_c - half], dtype=torch.float64), torch.tensor([t_c + half], dtype=torch.float64)
    )
    n_points = int(valid.sum())
    median = float(_nan_median(disp, valid)[0]) * pixel_scale if n_points else 0.0
    n = int(min(max(readout_ns / (MOTION_WINDOW_S * 1e9) * median / sampling.step_px, 1), sampling.max_samples))
    return MotionEstimate(n_samples=n, median_motion_px=median, n_points=n_points, rule="code")


def _paper_rule(recording: Recording, frame: Frame, sampling: PoseSampling, pixel_scale: float,
                readout_ns: int) -> MotionEstimate:
    """The paper's count: the fewest brackets whose worst median motion stays below one step (the cap when none
    does)."""
    if readout_ns == 0:
        return MotionEstimate(n_samples=1, median_motion_px=0.0, n_points=0, rule="paper")
    t_c, cap = float(frame.timestamp_ns), int(sampling.max_samples)
    # All candidate bracket edges at once: for n in 1..cap, edges t_c - R/2 + i R/n.
    starts, ends, owner = [], [], []
    for n in range(1, cap + 1):  # loop over candidate counts, not points
        edges = t_c - readout_ns / 2 + torch.arange(n + 1, dtype=torch.float64) * readout_ns / n
        starts.append(edges[:-1])
        ends.append(edges[1:])
        owner.append(torch.full((n,), n))
    disp, valid = displacements_px(recording, frame, torch.cat(starts), torch.cat(ends))
    med = _nan_median(disp, valid) * pixel_scale  # [sum n]
    med = torch.nan_to_num(med, nan=0.0)  # a bracket with no visible point cannot ask for more samples
    worst = torch.zeros(cap + 1, dtype=torch.float64).scatter_reduce(
        0, torch.cat(owner), med, reduce="amax", include_self=False
    )[1:]  # [cap] worst bracket median per candidate n
    ok = torch.nonzero(worst < sampling.step_px)
    n = int(ok[0]) + 1 if len(ok) else cap
    return MotionEstimate(n_samples=n, median_motion_px=float(worst[0]), n_points=int(valid[0].sum()), rule="paper")


def n_pose_samples(recording: Recording, frame: Frame, sampling: PoseSampling = PoseSampling(),
                   pixel_scale: float = 1.0) -> int:
    """Number of rolling-shutter pose samples for ``frame`` (1 for a static frame)."""
    return estimate_motion(recording, frame, sampling, pixel_scale).n_samples


def sample_times_ns(frame: Frame, n: int, n_exposure_samples: int = 1) -> Tensor:
    """Pose-sample times [M, N] float64 (device clock, ns): rolling-shutter bracket centres
    t_c - R/2 + (i + 0.5) R / N, each split into M exposure sub-interval centres."""
    if int(n) != n or n < 1:
        raise ValueError(f"n: expected an integer number of pose samples >= 1, got {n}")
    if int(n_exposure_samples) != n_exposure_samples or n_exposure_samples < 1:
        raise ValueError(f"n_exposure_samples: expected an integer >= 1, got {n_exposure_samples}")
    readout = float(frame.read_end_ns - frame.read_start_ns)
    t_rs = frame.timestamp_ns - readout / 2 + (torch.arange(n, dtype=torch.float64) + 0.5) * readout / n  # [N]
    exposure_ns = frame.exposure_s * 1e9
    offs = (torch.arange(n_exposure_samples, dtype=torch.float64) + 0.5) / n_exposure_samples * exposure_ns - exposure_ns / 2
    if n_exposure_samples == 1:
        offs = torch.zeros(1, dtype=torch.float64)
    return offs[:, None] + t_rs[None, :]


def pixel_pose_index(row_time_ratio: Tensor, n: int) -> Tensor:
    """Per-pixel pose-sample index [H, W] int64 = round(R(u) * (n - 1))."""
    if row_time_ratio.dim() != 2:
        raise ValueError(f"row_time_ratio: expected [H, W], got {tuple(row_time_ratio.shape)}")
    r = row_time_ratio.to(torch.float64).clamp(0.0, 1.0)
    return torch.round(r * (n - 1)).to(torch.int64)


def pose_samples(
    recording: Recording, frame: Frame, n: int, row_time_ratio: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(T_world_camera [n, 4, 4] float64 at the bracket centres, pixel_pose_index [H, W] int64).

    ``row_time_ratio`` overrides `recording.row_time_ratio` (e.g. resized to the training resolution).
    """
    times = sample_times_ns(frame, n)[0]
    rtr = recording.row_time_ratio if row_time_ratio is None else row_time_ratio
    return camera_poses_at(recording, frame, times), pixel_pose_index(rtr, n)


def exposure_pose_samples(recording: Recording, frame: Frame, n: int, n_exposure_samples: int) -> Tensor:
    """T_world_camera [M, n, 4, 4] float64: the n rolling-shutter samples at M exposure sub-interval centres."""
    times = sample_times_ns(frame, n, n_exposure_samples)
    M = times.shape[0]
    return camera_poses_at(recording, frame, times.reshape(-1)).reshape(M, n, 4, 4)


def linear_row_time_ratio(height: int, width: int) -> Tensor:
    """Row time ratio [H, W] linear in the rectified row, v / (H - 1): the pinhole assumption of
    3DGS-on-the-move (true only for an undistorted sensor)."""
    v = torch.arange(height, dtype=torch.float32) / max(height - 1, 1)
    return v[:, None].expand(height, width).contiguous()


def frame_twist_camera(recording: Recording, frame: Frame) -> Tensor:
    """Initial per-frame camera twist [6] = (linear m/s, angular rad/s), both in the camera frame,
    from the trajectory's velocity at the centre-row time (rigid device-camera lever arm applied)."""
    t = torch.tensor([int(frame.timestamp_ns)], dtype=torch.int64)
    vel = recording.trajectory.velocity(t)
    lin_world = torch.as_tensor(vel.linear_world, dtype=torch.float64).reshape(3)
    ang_device = torch.as_tensor(vel.angular_device, dtype=torch.float64).reshape(3)
    T_wd = torch.as_tensor(recording.trajectory.pose(t), dtype=torch.float64).reshape(4, 4)
    T_dc = frame.T_device_camera.to(torch.float64)
    T_wc = T_wd @ T_dc
    ang_world = T_wd[:3, :3] @ ang_device
    v_cam_world = lin_world + torch.linalg.cross(ang_world, T_wc[:3, 3] - T_wd[:3, 3])
    return torch.cat([T_wc[:3, :3].T @ v_cam_world, T_dc[:3, :3].T @ ang_device])


def velocity_poses(T_world_camera: Tensor, twist_camera: Tensor, dt_s: Tensor) -> Tensor:
    """Constant-velocity extrapolation of the centre pose (3DGS-on-the-move's motion model):
    T(t_c + dt) = T_c [exp(dt * omega^), dt * v], with (v, omega) = twist_camera in the camera frame.

    T_world_camera [4, 4], twist_camera [6], dt_s [K] -> [K, 4, 4] on twist_camera's device and dtype
    (the pose and times, built on the host from the trajectory, follow a trainable twist on the GPU);
    differentiable in both inputs.
    """
    like = dict(device=twist_camera.device, dtype=twist_camera.dtype)
    return T_world_camera[None].to(**like) @ relative_motion(twist_camera, dt_s.to(**like))


def relative_motion(twist_camera: Tensor, dt_s: Tensor) -> Tensor:
    """The camera's motion over dt_s [K] (s) at a constant twist [6] in its own frame: [exp(dt omega^), dt v]
    -> [K, 4, 4], to right-multiply a pose; differentiable in both inputs."""
    dt = dt_s[:, None]  # [K, 1]
    return make_pose(so3_exp(dt * twist_camera[None, 3:]), dt * twist_camera[None, :3])


def timing_shifts_s(n: int, timing_ms: Tensor) -> Tensor:
    """The time shifts [n] (s) of a frame's n rolling-shutter samples under a timing correction ``timing_ms``
    [2] = (time offset, readout error) in ms: the offset plus the readout error times the sample's place in the
    readout, (k + 1/2) / n - 1/2 (`sample_times_ns`' bracket centres; the centre row does not move)."""
    place = (torch.arange(n, dtype=timing_ms.dtype, device=timing_ms.device) + 0.5) / n - 0.5
    return (timing_ms[0] + place * timing_ms[1]) * 1e-3


def timed_poses(poses: Tensor, twist_camera: Tensor, timing_ms: Tensor) -> Tensor:
    """A frame's sample poses [M, K, 4, 4] moved along its constant twist [6] (camera frame) by the timing
    correction ``timing_ms`` [2] (`timing_shifts_s` of each of the K samples) -> [M, K, 4, 4], differentiable
    in ``timing_ms``: the model's poses at the times a learned time offset and readout say the rows were read."""
    like = dict(device=timing_ms.device, dtype=timing_ms.dtype)
    T_rel = relative_motion(twist_camera.to(**like), timing_shifts_s(poses.shape[-3], timing_ms))
    return poses.to(**like) @ T_rel[None]
