"""Figures of a recording: a contact sheet, and the paper's rolling-shutter motion figure.

`readout_displacement_px(recording, frame)`: for the frame's sparse points (its sparse depth,
else the semi-dense points in front of the camera), the pixel distance between their
projections under the pose at read start and under the pose at read end (the device moves
during the readout; paper Fig. "camera motion artifacts").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from egobench.data.reader import load_recording
from egobench.geometry import se3_inverse, transform_points
from egobench.io_utils import atomic_path


def _frame_points_world(recording, frame) -> torch.Tensor:  # [P, 3] float64
    cam = recording.camera
    sd = frame.sparse_depth
    if sd is not None and sd.z.shape[0] > 0:
        uv = torch.as_tensor(sd.uv, dtype=torch.float64)
        rays = cam.unproject(uv)  # z = 1
        pc = rays * torch.as_tensor(sd.z, dtype=torch.float64)[:, None]
        return transform_points(frame.T_world_camera.to(torch.float64), pc)
    pts = recording.points_world.to(torch.float64)
    if pts.shape[0] == 0:
        return pts

    pc = transform_points(se3_inverse(frame.T_world_camera.to(torch.float64)), pts)
    uv, ok = cam.project(pc)
    inside = ok & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
    return pts[inside]


def readout_displacement_px(recording, frame) -> np.ndarray:  # [P]
    """Pixel displacement of the frame's sparse points between the read-start and read-end poses."""
    if isinstance(frame, int):
        frame = recording.frames[frame]
    pts = _frame_points_world(recording, frame)
    if pts.shape[0] == 0:
        return np.zeros(0)
    T_dc = frame.T_device_camera.to(torch.float64)
    T = recording.trajectory.pose([frame.read_start_ns, frame.read_end_ns]) @ T_dc  # [2, 4, 4]
    pc = transform_points(se3_inverse(T)[:, None], pts[None])  # [2, P, 3]
    uv, ok = recording.camera.project(pc)
    good = ok[0] & ok[1]
    return (uv[1] - uv[0]).norm(dim=-1)[good].numpy()


def displacement_percentiles(recording) -> np.ndarray:  # [F, 3]
    """Per frame: 25th, 50th, 75th percentile of readout_displacement_px (NaN-free: 0 if no points)."""
    out = np.zeros((len(recording.frames), 3))
    for i, fr in enumerate(recording.frames):
        d = readout_displacement_px(recording, fr)
        if d.size:
            out[i] = np.percentile(d, [25, 50, 75])
    return out


def motion_displacement_figure(recording, out_png: str | Path) -> np.ndarray:
    """Plot per-frame 25/50/75th percentile readout displacement; returns the [F, 3] numbers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    q = displacement_percentiles(recording)
    t = np.array([(f.timestamp_ns - recording.frames[0].timestamp_ns) * 1e-9 for f in recording.frames])
    fig, ax = plt.subplots(figsize=(7, 3), dpi=120)
    ax.fill_between(t, q[:, 0], q[:, 2], alpha=0.3, label="25-75th percentile")
    ax.plot(t, q[:, 1], lw=1.2, label="median")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"displacement during readout (px @ {recording.camera.width} px)")
    ax.set_title(f"{recording.name}: sparse-point motion during the {recording.frames[0].readout_s * 1e3:.2f} ms readout")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return q


def contact_sheet(recording_dir: str | Path, out_png: str | Path, n: int = 8) -> None:
    """Grid of n evenly spaced frames: online image, factory image, GT depth (when present)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = load_recording(recording_dir, "online")
    rec_f = None
    try:
        rec_f = load_recording(recording_dir, "factory")
    except (ValueError, FileNotFoundError):
        pass
    idx = np.linspace(0, len(rec.frames) - 1, min(n, len(rec.frames))).round().astype(int)
    rows = 2 + (rec.ground_truth is not None) + (rec_f is not None)
    fig, axes = plt.subplots(rows, len(idx), figsize=(1.8 * len(idx), 1.9 * rows), dpi=100, squeeze=False)
    for c, i in enumerate(idx):
        fr = rec.frames[i]
        r = 0
        axes[r, c].imshow(rec.load_image(fr).numpy())
        axes[r, c].set_title(f"#{i} {fr.exposure_s * 1e3:.2f}ms g{fr.gain:.1f}", fontsize=7)
        r += 1
        if rec_f is not None:
            axes[r, c].imshow(rec_f.load_image(rec_f.frames[i]).numpy())
            axes[r, c].set_title("factory", fontsize=7)
            r += 1
        axes[r, c].imshow(rec.row_time_ratio.numpy(), cmap="viridis") if c == 0 else axes[r, c].imshow(
            rec.vignette.numpy(), cmap="gray", vmin=0, vmax=1)
        axes[r, c].set_title("R(u)" if c == 0 else "vignette", fontsize=7)
        r += 1
        depth_file = rec.ground_truth_file("depth", fr)
        if depth_file is not None:
            d = np.load(depth_file).astype(np.float32)
            axes[r, c].imshow(d, cmap="magma")
            axes[r, c].set_title("GT depth", fontsize=7)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{rec.name} ({rec.meta.get('scene_kind', '?')}, {len(rec.frames)} frames)", fontsize=9)
    fig.tight_layout()
    with atomic_path(Path(out_png)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
