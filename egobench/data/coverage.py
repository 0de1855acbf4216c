"""Held-out coverage: how much of each held-out frame some training frame saw, from the ground-truth depth.

A held-out frame tests novel-view synthesis only where the training frames saw its surfaces. In the
paper's 90 deg view at 10 fps the neighbours of every 8th frame overlap it almost entirely; in a narrow
view during a fast head turn they may not overlap it at all, and the frame then measures what a model
invents for surfaces nobody photographed, the same for every method (issue 31). This needs no training:
each sampled pixel of a held-out frame is lifted to 3D with its ground-truth depth and counted as seen
when it projects inside the valid area of a training frame whose own ground-truth depth there agrees
(the surface is not occluded in that frame).
"""

from __future__ import annotations


import numpy as np
import torch

from egobench.data.recording import Frame, Recording

#: Relative depth agreement under which a projected point counts as the surface the training frame saw.
DEPTH_TOLERANCE = 0.05
#: Pixel stride of the sampled grid in the held-out frame.
STRIDE_PX = 4


def _gt_depth(recording: Recording, frame: Frame) -> np.ndarray:
    """[H, W] float64 ground-truth z (metres, 0 = none) of a frame in the rectified online camera."""
    path = recording.ground_truth_file("depth", frame)
    if path is None:
        raise FileNotFoundError(f"{recording.ground_truth}/depth: ground-truth depth of frame {frame.index} is missing")
    depth = np.load(path, allow_pickle=False).astype(np.float64)
    if depth.shape != (recording.camera.height, recording.camera.width):
        raise ValueError(f"{path}: expected shape {(recording.camera.height, recording.camera.width)}, got {depth.shape}")
    return depth


def _lift(recording: Recording, frame: Frame, depth: np.ndarray, stride: int) -> np.ndarray:
    """World points [P, 3] of the valid pixels with depth on a ``stride`` grid of one frame."""
    cam, mask = recording.camera, recording.mask.numpy().astype(bool)
    v, u = np.mgrid[stride // 2:cam.height:stride, stride // 2:cam.width:stride]
    z = depth[v, u]
    keep = (z > 0) & mask[v, u]
    rays = cam.unproject(torch.from_numpy(np.stack([u[keep], v[keep]], axis=1).astype(np.float64))).numpy()
    Y = rays * z[keep][:, None]
    T = frame.T_world_camera.numpy()
    return Y @ T[:3, :3].T + T[:3, 3]


def _seen_in(recording: Recording, frame: Frame, depth: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """[P] bool: world points inside a frame's valid area whose ground-truth depth there agrees."""
    cam, mask = recording.camera, recording.mask.numpy().astype(bool)
    T = frame.T_world_camera.numpy()
    Y = (points_world - T[:3, 3]) @ T[:3, :3]
    pix, front = cam.project(torch.from_numpy(Y))
    uv = np.rint(pix.numpy()).astype(np.int64)  # pixel centres at integer (u, v)
    u, v, front, z = uv[:, 0], uv[:, 1], front.numpy(), Y[:, 2]
    inside = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    seen = np.zeros(len(points_world), bool)
    ui, vi = u[inside], v[inside]
    d = depth[vi, ui]
    seen[inside] = mask[vi, ui] & (d > 0) & (np.abs(d - z[inside]) <= DEPTH_TOLERANCE * z[inside])
    return seen


def heldout_coverage(recording: Recording, stride: int = STRIDE_PX) -> dict[int, float]:
    """{held-out frame index: fraction of its valid ground-truth pixels (``stride`` grid) that at least one
    training frame saw}. Needs the recording's ground truth (simulated recordings)."""
    if recording.ground_truth is None:
        raise ValueError(f"{recording.root}: held-out coverage needs ground-truth depth (a simulated recording)")
    train = [(f, _gt_depth(recording, f)) for f in recording.train_frames]
    out: dict[int, float] = {}
    for f in recording.test_frames:
        pts = _lift(recording, f, _gt_depth(recording, f), stride)
        if len(pts) == 0:
            out[f.index] = 0.0
            continue
        seen = np.zeros(len(pts), bool)
        for g, depth in train:
            seen |= _seen_in(recording, g, depth, pts)
        out[f.index] = float(seen.mean())
    return out


def training_view_count(recording: Recording, frame: Frame, depth_m: np.ndarray, max_grid: int = 96) -> np.ndarray:
    """[H, W] float32: how many of the recording's training frames hold each pixel's surface inside
    their valid image area (no occlusion test). ``depth_m`` [H, W]: the pixel's z in the rectified
    camera (a trained model's rendered depth; 0 = no surface -> 0 views). Evaluated on a grid of at
    most ``max_grid`` points a side, each point's count filling its stride x stride block.

    Content seen in few training views (a turn's leading edge, the periphery) is fitted worse; the
    count separates that under-fit from a lens shading, which follows the radius alone (issue 27)."""
    cam, mask = recording.camera, recording.mask.numpy().astype(bool)
    H, W = depth_m.shape
    stride = max(1, -(-max(H, W) // max_grid))
    v, u = np.meshgrid(_block_centres(H, stride), _block_centres(W, stride), indexing="ij")
    z = np.asarray(depth_m, dtype=np.float64)[v, u]
    keep = z > 0
    rays = cam.unproject(torch.from_numpy(np.stack([u[keep], v[keep]], axis=1).astype(np.float64))).numpy()
    T = frame.T_world_camera.numpy()
    pts = (rays * z[keep][:, None]) @ T[:3, :3].T + T[:3, 3]
    count = np.zeros(len(pts), np.float32)
    for g in recording.train_frames:
        Tg = g.T_world_camera.numpy()
        pix, front = cam.project(torch.from_numpy((pts - Tg[:3, 3]) @ Tg[:3, :3]))
        uv = np.rint(pix.numpy()).astype(np.int64)
        inside = front.numpy() & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        inside[inside] = mask[uv[inside, 1], uv[inside, 0]]
        count += inside
    grid = np.zeros(v.shape, np.float32)
    grid[keep] = count
    return np.repeat(np.repeat(grid, stride, axis=0), stride, axis=1)[:H, :W]


def _block_centres(n: int, stride: int) -> np.ndarray:
    """[ceil(n / stride)] the sampled pixel of each stride-wide block of 0..n-1: its centre, or the last
    pixel where the final block is cut short (so that the blocks cover all n pixels)."""
    return np.minimum(np.arange(-(-n // stride)) * stride + stride // 2, n - 1)


__all__ = ["heldout_coverage", "training_view_count", "DEPTH_TOLERANCE", "STRIDE_PX"]
