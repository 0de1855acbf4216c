"""A textured plane of Gaussians seen by a translating, yawing pinhole camera: a tiny recording
rendered by our own rasterizer (no image-formation effects). The training benchmark's scene
(`egobench bench train`) and the tests' toy recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.data.recording import Frame, Recording, SparseDepth
from egobench.geometry import TrajectoryVelocity, se3_exp
from egobench.render import render
from egobench.render.types import Gaussians


class TwistTrajectory:
    """Analytic trajectory T_world_device(t) = T0 exp((t - t0) xi) with the `Trajectory` query API."""

    def __init__(self, T0: Tensor, xi_per_s: Tensor, t0_ns: int) -> None:
        self.T0, self.xi, self.t0_ns = T0.to(torch.float64), xi_per_s.to(torch.float64), int(t0_ns)

    def pose(self, t_ns) -> Tensor:
        t = torch.as_tensor(t_ns).reshape(-1).to(torch.float64)
        dt = (t - self.t0_ns) * 1e-9
        return self.T0[None] @ se3_exp(dt[:, None] * self.xi[None])

    def velocity(self, t_ns):
        T = self.pose(t_ns)
        lin = (T[:, :3, :3] @ self.xi[:3, None])[..., 0]
        return TrajectoryVelocity(linear_world=lin, angular_device=self.xi[3:].expand(T.shape[0], 3).clone())


def _plane_gaussians():
    """The ground-truth scene: a 30 x 30 grid of coloured Gaussians on the plane z = 2.5 m
    (x in +-3 m, y in +-2 m), each 0.6 grid steps wide, nearly opaque."""
    side = 30
    xs, ys = torch.linspace(-3.0, 3.0, side), torch.linspace(-2.0, 2.0, side)
    gx, gy = torch.meshgrid(xs, ys, indexing="xy")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((side * side,), 2.5)], -1)
    N = len(means)
    cols = 0.5 + 0.4 * torch.stack([torch.sin(3 * means[:, 0]), torch.cos(4 * means[:, 1]),
                                    torch.sin(2 * (means[:, 0] + means[:, 1]))], -1)
    sx, sy = float(xs[1] - xs[0]), float(ys[1] - ys[0])
    return Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).repeat(N, 1),
                     log_scales=torch.log(torch.tensor([sx * 0.6, sy * 0.6, 0.01])).repeat(N, 1),
                     opacity_logits=torch.full((N,), 3.0), colors=cols)


def _sparse_depth(means_world: Tensor, T_world_camera: Tensor, cam: Pinhole):
    """The Gaussian centres [N, 3] seen in the image as sparse depth (u, v, z; tiny std)."""
    T_cw = torch.linalg.inv(T_world_camera)
    pc = (means_world.double() @ T_cw[:3, :3].T + T_cw[:3, 3])
    uv, valid = cam.project(pc)
    ok = valid & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
    n = int(ok.sum())
    return SparseDepth(uv=uv[ok].numpy(), z=pc[ok, 2].numpy(), inv_dist_std=np.full(n, 1e-3), dist_std=np.full(n, 1e-3))


def _write_frame(root: Path, i: int, truth, cam: Pinhole, T_wc: Tensor, with_ground_truth: bool) -> Path:
    """Render frame ``i`` at its centre-row pose; write images/NNNNN.png (and ground-truth depth/normal)."""
    with torch.no_grad():
        out = render(truth, cam, T_wc[None].float(), pixel_pose_index=None, mode="3dgs",
                     background=torch.zeros(3), backend="auto", want_normal=with_ground_truth)
    if with_ground_truth:
        for kind, arr in (("depth", out.depth[0, ..., 0]), ("normal", out.normal[0])):
            (root / "ground_truth" / kind).mkdir(parents=True, exist_ok=True)
            np.save(root / "ground_truth" / kind / f"{i:05d}.npy", arr.numpy().astype(np.float16))
    img = (out.rgb[0].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    path = root / "images" / f"{i:05d}.png"
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return path


def plane_recording(root: Path, size: int = 32, n_frames: int = 9, angular_speed_rad_s: float = 0.0,
                    readout_s: float = 5e-3, seed: int = 0, n_points: int = 2000,
                    frame_interval_s: float = 0.05, with_ground_truth: bool = False) -> Recording:
    """A tiny synthetic recording for tests and benchmarks (images rendered by our rasterizer).

    Scene: a textured plane of Gaussians 2.5 m in front of a camera that translates 2 m along x (and
    rotates about y at ``angular_speed_rad_s``); images are the centre-row renders (no formation
    effects: exposure 1 ms, gain 1 for every frame, flat vignette), sparse depth from the points.
    ``with_ground_truth`` also writes ground_truth/depth and ground_truth/normal (.npy, float16).
    """
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(seed)
    cam = Pinhole(fx=size * 0.9, fy=size * 0.9, cx=(size - 1) / 2, cy=(size - 1) / 2, width=size, height=size)
    truth = _plane_gaussians()
    t0 = 1_000_000_000
    dt_ns = int(round(frame_interval_s * 1e9))
    # The camera translates 2 m along x over the frames (gsplat's scene scale ~ 1.1 m) and yaws at
    # angular_speed_rad_s; the middle frame sits at x = 0 looking down +z.
    duration_s = max(n_frames - 1, 1) * dt_ns * 1e-9
    xi = torch.tensor([2.0 / duration_s, 0.0, 0.0, 0.0, angular_speed_rad_s, 0.0], dtype=torch.float64)
    traj = TwistTrajectory(torch.eye(4, dtype=torch.float64), xi, t0 + (n_frames // 2) * dt_ns)
    exposure_s = 1e-3
    frames = []
    for i in range(n_frames):
        ts = t0 + i * dt_ns
        T_wc = traj.pose(torch.tensor([ts]))[0]
        path = _write_frame(root, i, truth, cam, T_wc, with_ground_truth)
        read_start = ts - int(readout_s * 1e9 / 2) - int(exposure_s * 1e9 / 2)
        frames.append(Frame(index=i, image_path=path, timestamp_ns=ts, read_start_ns=read_start,
                            read_end_ns=read_start + int(readout_s * 1e9), exposure_s=exposure_s, gain=1.0,
                            T_world_camera=T_wc, T_device_camera=torch.eye(4, dtype=torch.float64),
                            sparse_depth=_sparse_depth(truth.means, T_wc, cam)))
    # Initial points: n_points random points on the plane (SLAM-like: positions only, slightly noisy).
    u = torch.rand(n_points, 2, generator=gen)
    pts = torch.stack([-3 + 6 * u[:, 0], -2 + 4 * u[:, 1], 2.5 + 0.01 * torch.randn(n_points, generator=gen)], -1)
    v = torch.arange(size, dtype=torch.float32) / (size - 1)
    return Recording(
        root=root, name="toy", calibration="online", camera=cam, camera_model="linear", frames=frames,
        vignette=torch.ones(size, size), mask=torch.ones(size, size, dtype=torch.bool),
        row_time_ratio=v[:, None].expand(size, size).contiguous(), trajectory=traj,
        points_world=pts.float(), meta={"scene_kind": "toy", "device": "toy"},
        ground_truth=(root / "ground_truth") if with_ground_truth else None,
    )
