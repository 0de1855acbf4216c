"""A second, independent writer of synthetic egocentric recordings in the authors' preprocessed layout.

It shares no code with egobench's simulator and imports nothing from egobench (standard library,
numpy and OpenCV only): recordings egobench did not write, to test its diagnosis on.

    python scripts/independent_writer.py --out DIR [--seed N] [--size 64] [--frames 48] [--fps 15]
        [--exposure-s 0.001] [--gain 1.0] [--readout-s 0.008] [--supersample 2] [--noise 1.0]
        [--vignette-corner F] [--readout-scale S] [--exposure-error E --exposure-fraction P]
        [--time-offset-s D] [--lens-k0 K]

The world: a 6 x 5 x 3 m box room (z up, metres) with procedural textures (seeded sums of sinusoids
plus a grid of soft lines) on its six faces and four axis-aligned boxes inside, ray-cast
analytically and shaded Lambertian by two point lights plus ambient (no shadows). A head moves on
sums of sinusoids (yaw rates up to ~200 deg/s). A rectified pinhole camera (OpenCV axes: x right,
y down, z forward; the centre of pixel (i, j) at (u, v) = (i, j), cx = (W - 1) / 2) with a rolling
shutter: row v is rendered at its mid-exposure time

    t(v) = t_centre_true + (v / (H - 1) - 1/2) * readout_true      (device clock)

i.e. the reader's R(u) = v / (H - 1) (image_index.png). Image formation: linear radiance x
exposure x gain x 1000 /s x true vignette -> clip to 0..1 -> ^(1/2.2) -> + Gaussian noise
(``--noise`` 8-bit levels) -> 8-bit PNG; each pixel averages ``--supersample``^2 rays of its row.

Files (DIR is the recording; the reader finds the stream folder under it)::

    DIR/truth.json                          seed, hidden effects, altered frames (the reader ignores it)
    DIR/mps/slam/closed_loop_trajectory.csv T_world_device at 1 kHz, whole microseconds
    DIR/mps/slam/semidense_points.csv.gz    surface points, small stated stds (pass the MPS filter)
    DIR/camera-rgb-rectified-<f>-h<H>/      images/NNNNN.png, sparse_depth/NNNNN.json, transforms.json,
        transforms_with_sparse_depth.json, vignette.png (stated: flat), mask.png, image_index.png,
        closed_loop_trajectory.csv and semidense_points.csv.gz (relative symlinks into mps/slam/)

Per frame, as the authors' extract script: timestamp_read_start = t_rec - R/2 (the first row's
mid-exposure, like Aria's capture timestamp), timestamp = t_rec (the centre row's mid-exposure),
timestamp_read_end = t_rec + R/2, with R the STATED readout and t_rec the RECORDED centre time;
transform_matrix = T_world_device(t_rec) @ camera2device (camera to world, OpenCV axes).

Hidden effects (default: none, a null recording), each written to truth.json:
  --vignette-corner F   true shading 1 - F (r / r_corner)^2 (r from (cx, cy); corners x (1 - F)); stated flat.
  --readout-scale S     true readout = stated readout x S (the centre row's time is unchanged).
  --exposure-error E, --exposure-fraction P   a seeded P share of the frames records exposure x E;
                        the images use the true exposure.
  --time-offset-s D     true centre time = recorded timestamp + D (recorded timestamps are D early).
  --lens-k0 K           the true lens bends rays radially: the pixel at field angle theta of the stated pinhole
                        sees the ray at theta - K theta^3, so the content moves outward by about
                        K f sec^2(theta) theta^3 px (a Fisheye624 k0 larger by K); the stated camera is the pinhole.
Matrix products use einsum rather than BLAS (numpy's @), whose kernels vary between CPUs.
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

ROOM = (np.zeros(3), np.array([6.0, 5.0, 3.0]))  # room bounds, metres (x, y, z; z up)
BOX_TEMPLATES = (((4.3, 0.8, 0.0), (5.3, 2.0, 0.75)), ((0.6, 3.3, 0.0), (1.2, 4.4, 1.8)),
                 ((1.0, 0.7, 0.0), (1.8, 1.4, 0.5)), ((4.6, 3.6, 1.2), (5.4, 4.4, 1.6)))
LIGHTS = ((np.array([2.0, 1.5, 2.8]), 1.6), (np.array([4.5, 3.5, 2.7]), 1.4))  # (position m, intensity)
AMBIENT = 0.25
SENSITIVITY_PER_S = 1000.0  # linear value of radiance 1 at 1 s exposure, gain 1 (1 ms -> 1.0)
GAMMA = 2.2
N_SINES = 6  # sinusoids per surface texture
T0_NS = 5_000_000_000  # device time of the first trajectory sample
MARGIN_S = 0.1  # trajectory margin before the first and after the last frame
CAMERA_LABEL = "camera-rgb"
GRAPH_UID = "00000000-0000-0000-0000-0000000000aa"  # one SLAM graph
#: rectified camera to device: pitched 4 deg down, turned 2 deg, 5 cm right and 1 cm up of the device origin
CAMERA_TILT_DEG, CAMERA_TURN_DEG, CAMERA_OFFSET_M = -4.0, 2.0, (0.05, -0.01, 0.0)


@dataclass(frozen=True)
class Config:
    """What a recording is written with (seconds, pixels; effects at their neutral values = none)."""

    seed: int = 0
    size: int = 64  # square image, pixels
    frames: int = 48
    fps: float = 15.0
    fov_deg: float = 50.0  # horizontal field of view
    exposure_s: float = 0.001
    gain: float = 1.0
    readout_s: float = 0.008  # STATED readout (first to last row)
    supersample: int = 2  # rays per pixel side
    noise: float = 1.0  # Gaussian noise sigma, 8-bit levels (display domain)
    vignette_corner: float = 0.0
    readout_scale: float = 1.0
    exposure_error: float = 1.0
    exposure_fraction: float = 0.0
    time_offset_s: float = 0.0
    lens_k0: float = 0.0
    motion: str = "both"  # the head's motion: "both", "rotation" (no translation) or "translation" (no rotation)

    @property
    def focal_px(self) -> float:
        return self.size / 2.0 / math.tan(math.radians(self.fov_deg) / 2.0)

    @property
    def centre_px(self) -> float:
        return (self.size - 1) / 2.0


def check_config(c: Config) -> None:
    """ValueError with a readable message for a configuration that cannot make a valid recording."""
    period = 1.0 / c.fps if c.fps > 0 else 0.0
    rules = [
        (0 <= c.seed < 2 ** 63, f"--seed must be a non-negative integer, got {c.seed}"),
        (8 <= c.size <= 1024, f"--size must be 8..1024 pixels, got {c.size}"),
        (2 <= c.frames <= 10000, f"--frames must be 2..10000, got {c.frames}"),
        (1.0 <= c.fps <= 120.0, f"--fps must be 1..120, got {c.fps}"),
        (10.0 <= c.fov_deg <= 120.0, f"--fov-deg must be 10..120, got {c.fov_deg}"),
        (0.0 < c.exposure_s <= period / 2,
         f"--exposure-s must be > 0 and <= half the frame period, got {c.exposure_s}"),
        (1e-3 <= c.gain <= 1e3, f"--gain must be 0.001..1000, got {c.gain}"),
        (0.0 < c.readout_s <= 0.1, f"--readout-s must be > 0 and <= 0.1 s, got {c.readout_s}"),
        (1 <= c.supersample <= 8, f"--supersample must be 1..8, got {c.supersample}"),
        (0.0 <= c.noise <= 20.0, f"--noise must be 0..20 levels, got {c.noise}"),
        (0.0 <= c.vignette_corner < 0.95, f"--vignette-corner must be in [0, 0.95), got {c.vignette_corner}"),
        (0.0 < c.readout_scale <= 4.0, f"--readout-scale must be in (0, 4], got {c.readout_scale}"),
        (c.readout_s * c.readout_scale < period - c.exposure_s,
         "the true readout (--readout-s x --readout-scale) plus the exposure must fit in a frame period"),
        (0.0 < c.exposure_error <= 10.0, f"--exposure-error must be in (0, 10], got {c.exposure_error}"),
        (0.0 <= c.exposure_fraction <= 1.0, f"--exposure-fraction must be in [0, 1], got {c.exposure_fraction}"),
        ((c.exposure_error == 1.0) == (c.exposure_fraction == 0.0),
         "--exposure-error (not 1) and --exposure-fraction (> 0) must be given together"),
        (abs(c.time_offset_s) <= 0.05, f"--time-offset-s must be within +-0.05 s, got {c.time_offset_s}"),
        (abs(c.lens_k0) <= 0.5, f"--lens-k0 must be within +-0.5, got {c.lens_k0}"),
    ]
    if all(ok for ok, _ in rules):  # the lens must map the corner's field angle one to one, in front of the camera
        corner = math.atan(math.hypot(c.centre_px, c.centre_px) / c.focal_px)
        rules.append((1.0 - 3.0 * c.lens_k0 * corner ** 2 > 0.0 and corner - c.lens_k0 * corner ** 3 < math.pi / 2,
                      f"--lens-k0 {c.lens_k0} folds or turns back the rays at the corners of a {c.fov_deg} deg view"))
    for ok, message in rules:  # every range is bounded, so NaN and infinity fail too
        if not ok:
            raise ValueError(message)


# ----------------------------------------------------------------------------------------
# small linear algebra (einsum: no BLAS)
# ----------------------------------------------------------------------------------------
def _rot(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotations [N, 3, 3] by ``angle`` [N] rad about coordinate axis 0/1/2 (right-handed)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i], R[..., i, j], R[..., j, i], R[..., j, j] = c, -s, s, c
    return R


def _mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched matrix product [..., n, m] x [..., m, k]."""
    return np.einsum("...ij,...jk->...ik", a, b)


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] -> unit quaternions [N, 4] (x, y, z, w), w >= 0 (Shepperd)."""
    tr = np.trace(R, axis1=-2, axis2=-1)
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], -1)
    pivot = np.argmax(np.concatenate([tr[:, None], diag], -1), -1)
    q = np.empty((R.shape[0], 4))
    for k in range(4):
        m = pivot == k
        r = R[m]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                             (r[:, 1, 0] - r[:, 0, 1]) / s, 0.25 * s], -1)
            continue
        i = k - 1
        j, l = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[:, i, i] - r[:, j, j] - r[:, l, l])
        v = np.empty((r.shape[0], 4))
        v[:, i], v[:, j], v[:, l] = 0.25 * s, (r[:, j, i] + r[:, i, j]) / s, (r[:, l, i] + r[:, i, l]) / s
        v[:, 3] = (r[:, l, j] - r[:, j, l]) / s
        q[m] = v
    q[q[:, 3] < 0] *= -1.0
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------
# the world: room, boxes, textures, head motion
# ----------------------------------------------------------------------------------------
def build_scene(seed: int) -> dict:
    """Boxes (jittered templates) and per-surface texture parameters; surface s: room face s < 6
    (2 axis + (1 if the far wall)), box b face 6 + 6 b + 2 axis + (1 if its max side)."""
    rng = np.random.default_rng([seed, 0])
    boxes = []
    for lo, hi in BOX_TEMPLATES:
        shift = np.append(rng.uniform(-0.1, 0.1, 2), 0.0)
        boxes.append((np.array(lo) + shift, np.array(hi) + shift))
    n = 6 + 6 * len(boxes)
    freq = rng.uniform(0.3, 3.0, (n, N_SINES))  # cycles per metre
    angle = rng.uniform(0.0, np.pi, (n, N_SINES))
    return {"boxes": boxes, "k": freq[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1),
            "phase": rng.uniform(0, 2 * np.pi, (n, N_SINES)), "amp": rng.uniform(0.3, 1.0, (n, N_SINES)),
            "c0": rng.uniform(0.05, 0.4, (n, 3)), "c1": rng.uniform(0.55, 0.95, (n, 3)),
            "grid": rng.uniform(0.35, 0.8, n), "grid_offset": rng.uniform(0, 1, (n, 2))}


def head_motion(seed: int, kind: str = "both") -> dict:
    """Seeded sinusoids of the head, per channel (amplitudes, frequencies Hz, phases rad): position
    x, y, z (m, about (3, 2.5, 1.6)), yaw (about ``yaw0``), pitch and roll (rad). ``kind`` "rotation" zeroes
    the translation's amplitudes, "translation" the rotation's (the same draws either way)."""
    motion = _head_sinusoids(seed)
    if kind == "rotation":
        motion["pos_amp"] = np.zeros_like(motion["pos_amp"])
    elif kind == "translation":
        for k in ("yaw", "pitch", "roll"):
            motion[k] = (np.zeros_like(motion[k][0]), *motion[k][1:])
    elif kind != "both":
        raise ValueError(f"head motion: expected 'both', 'rotation' or 'translation', got {kind!r}")
    return motion


def _head_sinusoids(seed: int) -> dict:
    rng = np.random.default_rng([seed, 1])

    def phases(shape):
        return rng.uniform(0, 2 * np.pi, shape)

    return {"pos_amp": np.array([[0.25, 0.06], [0.25, 0.05], [0.05, 0.02]]),
            "pos_f": np.array([[0.23, 0.9], [0.31, 0.7], [0.5, 1.7]]), "pos_ph": phases((3, 2)),
            "yaw0": rng.uniform(0, 2 * np.pi), "yaw": (np.array([0.9, 0.25]), np.array([0.35, 1.1]), phases(2)),
            "pitch": (np.array([0.25, 0.08]), np.array([0.5, 1.3]), phases(2)),
            "roll": (np.array([0.05]), np.array([0.7]), phases(1))}


def _sines(t_s: np.ndarray, amp, freq, phase) -> np.ndarray:
    return np.sum(np.asarray(amp) * np.sin(2 * np.pi * np.asarray(freq) * t_s[:, None] + np.asarray(phase)), -1)


def device_poses(motion: dict, t_ns) -> np.ndarray:
    """T_world_device [N, 4, 4] at device times t_ns [N] (ns, int or float). Device axes: x right,
    y down, z forward; yaw about world z, then pitch about device x (positive: up), roll about z."""
    t = (np.asarray(t_ns, dtype=np.float64).reshape(-1) - T0_NS) * 1e-9
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # device -> world at rest
    R = _mm(_mm(_rot(2, motion["yaw0"] + _sines(t, *motion["yaw"])), np.broadcast_to(base, (len(t), 3, 3))),
            _mm(_rot(0, _sines(t, *motion["pitch"])), _rot(2, _sines(t, *motion["roll"]))))
    pos = np.array([3.0, 2.5, 1.6]) + np.stack([_sines(t, motion["pos_amp"][i], motion["pos_f"][i],
                                                       motion["pos_ph"][i]) for i in range(3)], -1)
    T = np.zeros((len(t), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, pos, 1.0
    return T


def cast(scene: dict, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays o + t d ([N, 3], d unit) from inside the room -> (t [N] m, surface id [N], normal [N, 3])."""
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    lo, hi = ROOM
    t_ax = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    axis = np.argmin(t_ax, 1)
    rows = np.arange(len(o))
    t = t_ax[rows, axis]
    sid = 2 * axis + (d[rows, axis] > 0)
    for b, (blo, bhi) in enumerate(scene["boxes"]):
        t1, t2 = (blo - o) / d, (bhi - o) / d
        tmin = np.minimum(t1, t2)
        near, far, ax = tmin.max(1), np.maximum(t1, t2).min(1), tmin.argmax(1)
        hit = (near <= far) & (near > 1e-6) & (near < t)
        t = np.where(hit, near, t)
        sid = np.where(hit, 6 + 6 * b + 2 * ax + (d[rows, ax] < 0), sid)
    axis_of = (sid % 6) // 2
    normal = np.zeros_like(o)
    # room faces point into the room (the far wall: -1), box faces out of the box (its max side: +1)
    normal[rows, axis_of] = np.where(sid < 6, np.where(sid % 2 == 1, -1.0, 1.0), np.where(sid % 2 == 1, 1.0, -1.0))
    return t, sid, normal


def albedo(scene: dict, p: np.ndarray, sid: np.ndarray) -> np.ndarray:
    """Texture colour [N, 3] in 0..1 at surface points p [N, 3] of surfaces sid [N] (metres in-plane)."""
    axis = (sid % 6) // 2
    a = np.where(axis == 0, p[:, 1], p[:, 0])
    b = np.where(axis == 2, p[:, 1], p[:, 2])
    ab = np.stack([a, b], -1)
    arg = 2 * np.pi * np.einsum("nkc,nc->nk", scene["k"][sid], ab) + scene["phase"][sid]
    s = 0.5 + 0.5 * np.sum(scene["amp"][sid] * np.sin(arg), 1) / np.sum(scene["amp"][sid], 1)
    g = scene["grid"][sid][:, None]
    frac = (ab / g + scene["grid_offset"][sid]) % 1.0
    line = np.exp(-((np.minimum(frac, 1.0 - frac) * g / 0.025) ** 2)).max(1)[:, None]  # soft lines, 2.5 cm
    return (scene["c0"][sid] * (1 - s[:, None]) + scene["c1"][sid] * s[:, None]) * (1 - 0.55 * line)


def radiance(scene: dict, p: np.ndarray, sid: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Linear Lambertian radiance [N, 3]: albedo x (ambient + sum I cos / d^2), no shadows."""
    light = np.full(len(p), AMBIENT)
    for pos, power in LIGHTS:
        v = pos - p
        d2 = np.sum(v * v, 1)
        light += power * np.clip(np.sum(v * normal, 1), 0, None) / d2 ** 1.5
    return albedo(scene, p, sid) * light[:, None]


# ----------------------------------------------------------------------------------------
# the camera: extrinsics, frame clocks, rolling-shutter rendering
# ----------------------------------------------------------------------------------------
def camera_to_device() -> np.ndarray:
    """T_device_camera [4, 4] (rectified camera to device, OpenCV camera axes, metres)."""
    T = np.eye(4)
    tilt, turn = np.radians([CAMERA_TILT_DEG]), np.radians([CAMERA_TURN_DEG])
    T[:3, :3] = _mm(_rot(0, tilt), _rot(1, turn))[0]
    T[:3, 3] = CAMERA_OFFSET_M
    return T


def camera_poses(motion: dict, t_ns) -> np.ndarray:
    """T_world_camera [N, 4, 4] = T_world_device(t) @ T_device_camera at device times t_ns [N]."""
    return _mm(device_poses(motion, t_ns), camera_to_device())


def frame_clock(c: Config) -> dict:
    """Per-frame clocks (int64 ns, device clock) and exposures: the TRUE centre-row mid-exposure time,
    the RECORDED one (true - time offset), the recorded read start / end (stated readout), the
    true and the recorded exposure (s), and the sorted indices of the frames whose exposure is misrecorded."""
    k = np.arange(c.frames)
    t_true = T0_NS + round(MARGIN_S * 1e9) + np.round(k * 1e9 / c.fps).astype(np.int64)
    t_rec = t_true - round(c.time_offset_s * 1e9)
    readout_ns = round(c.readout_s * 1e9)
    altered: list[int] = []
    if c.exposure_fraction > 0:
        n = max(1, round(c.exposure_fraction * c.frames))
        altered = sorted(np.random.default_rng([c.seed, 3]).choice(c.frames, n, replace=False).tolist())
    exposure_rec = np.full(c.frames, c.exposure_s)
    exposure_rec[altered] = c.exposure_s * c.exposure_error
    return {"t_true": t_true, "t_rec": t_rec, "read_start": t_rec - readout_ns // 2,
            "read_end": t_rec - readout_ns // 2 + readout_ns, "exposure_true": np.full(c.frames, c.exposure_s),
            "exposure_rec": exposure_rec, "altered": altered}


def row_time_ns(c: Config, t_centre_true_ns: int, rows: np.ndarray) -> np.ndarray:
    """True mid-exposure time (float ns) of image rows: t_c + (row / (H - 1) - 1/2) x readout_true."""
    readout_true_ns = c.readout_s * c.readout_scale * 1e9
    return t_centre_true_ns + (np.asarray(rows, dtype=np.float64) / (c.size - 1) - 0.5) * readout_true_ns


def cast_pixels(c: Config, scene: dict, motion: dict, t_centre_true_ns: int, uv: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """What the rays through pixel positions uv [N, 2] (u, v; pixel centres at integers) of a frame
    see, each ray at the true time of its pixel row round(v) -> (world points [N, 3] m, radiance [N, 3])."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    rows = np.floor(uv[:, 1] + 0.5)
    T = camera_poses(motion, row_time_ns(c, t_centre_true_ns, rows))
    d_cam = np.stack([*true_ray_xy(c, (uv[:, 0] - c.centre_px) / c.focal_px, (uv[:, 1] - c.centre_px) / c.focal_px),
                      np.ones(len(uv))], -1)
    d = np.einsum("nij,nj->ni", T[:, :3, :3], d_cam / np.linalg.norm(d_cam, axis=1, keepdims=True))
    t, sid, normal = cast(scene, T[:, :3, 3], d)
    p = T[:, :3, 3] + t[:, None] * d
    return p, radiance(scene, p, sid, normal)


def true_ray_xy(c: Config, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true ray (x / z, y / z) through the stated pinhole's normalised position (x, y): its field angle
    theta taken down to theta - lens_k0 theta^3 along the same azimuth (unchanged when lens_k0 = 0)."""
    if c.lens_k0 == 0.0:
        return x, y
    r = np.hypot(x, y)
    theta = np.arctan(r)
    scale = np.tan(theta - c.lens_k0 * theta ** 3) / np.maximum(r, 1e-12)
    return x * scale, y * scale


def true_vignette(c: Config) -> np.ndarray:
    """The TRUE lens shading [H, W]: 1 - F (r / r_corner)^2, r from (cx, cy) (1 everywhere when F = 0)."""
    v, u = np.mgrid[0:c.size, 0:c.size].astype(np.float64)
    r2 = ((u - c.centre_px) ** 2 + (v - c.centre_px) ** 2) / (2.0 * c.centre_px ** 2)
    return 1.0 - c.vignette_corner * r2


def render_frame(c: Config, scene: dict, motion: dict, t_centre_true_ns: int, exposure_true_s: float,
                 vignette: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One rolling-shutter frame -> RGB uint8 [H, W, 3]: mean of supersample^2 rays per pixel x exposure
    x gain x sensitivity x true vignette, clipped, gamma 1/2.2, Gaussian noise, 8 bits."""
    H = W = c.size
    off = (np.arange(c.supersample) + 0.5) / c.supersample - 0.5
    v, u, dv, du = np.meshgrid(np.arange(H), np.arange(W), off, off, indexing="ij")
    _, L = cast_pixels(c, scene, motion, t_centre_true_ns, np.stack([u + du, v + dv], -1).reshape(-1, 2))
    L = L.reshape(H, W, c.supersample ** 2, 3).mean(2)
    lin = L * (exposure_true_s * c.gain * SENSITIVITY_PER_S) * vignette[..., None]
    display = np.clip(lin, 0.0, 1.0) ** (1.0 / GAMMA) + rng.normal(0.0, c.noise / 255.0, lin.shape)
    return np.round(np.clip(display, 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------------------
# semi-dense points and per-frame sparse depth
# ----------------------------------------------------------------------------------------
def _faces(scene: dict) -> list[tuple[int, float, np.ndarray, np.ndarray, int]]:
    """Visible rectangles (axis, plane coordinate, in-plane lo [2], hi [2], box index or -1)."""
    out = []
    for b, (lo, hi) in [(-1, ROOM)] + list(enumerate(scene["boxes"])):
        for axis in range(3):
            others = [i for i in range(3) if i != axis]
            for value in (lo[axis], hi[axis]):
                if b >= 0 and axis == 2 and value <= 1e-9:
                    continue  # a box's bottom resting on the floor
                out.append((axis, float(value), lo[others], hi[others], b))
    return out


def semidense_points(scene: dict, seed: int, n: int = 4000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """~n surface points, area-weighted, none inside a box -> (points [M, 3] m, inv_dist_std [M] 1/m,
    dist_std [M] m); the stds are small (the MPS filter keeps every point). Points are exact."""
    rng = np.random.default_rng([seed, 4])
    faces = _faces(scene)
    area = np.array([np.prod(hi - lo) for _, _, lo, hi, _ in faces])
    which = rng.choice(len(faces), n, p=area / area.sum())
    pts = np.empty((n, 3))
    for i, (axis, value, lo, hi, _) in enumerate(faces):
        m = which == i
        others = [j for j in range(3) if j != axis]
        pts[m, axis] = value
        pts[np.ix_(m, others)] = rng.uniform(lo, hi, (int(m.sum()), 2))
    keep = np.ones(n, bool)
    for b, (lo, hi) in enumerate(scene["boxes"]):
        own = np.array([faces[w][4] == b for w in which])
        keep &= own | ~np.all((pts > lo - 1e-4) & (pts < hi + 1e-4), 1)
    pts = pts[keep]
    return pts, rng.uniform(0.0005, 0.004, len(pts)), rng.uniform(0.001, 0.008, len(pts))


def sparse_depth(c: Config, scene: dict, T_world_camera: np.ndarray, pts: np.ndarray, inv_std: np.ndarray,
                 dist_std: np.ndarray) -> dict:
    """The points visible from the camera T_world_camera (not occluded, in the image) as the authors'
    sparse-depth JSON object: u, v (pixels, centres at integers), z (m along the camera axis), stds."""
    R, o = T_world_camera[:3, :3], T_world_camera[:3, 3]
    p_cam = np.einsum("ji,nj->ni", R, pts - o)
    z = p_cam[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = c.focal_px * p_cam[:, 0] / zs + c.centre_px
    v = c.focal_px * p_cam[:, 1] / zs + c.centre_px
    ok = (z > 0.05) & (u >= 0) & (u <= c.size - 1) & (v >= 0) & (v <= c.size - 1)
    vec = pts[ok] - o
    dist = np.linalg.norm(vec, axis=1)
    t_hit, _, _ = cast(scene, np.broadcast_to(o, vec.shape).copy(), vec / dist[:, None])
    idx = np.flatnonzero(ok)[t_hit >= dist - 0.01]
    return {"u": u[idx].tolist(), "v": v[idx].tolist(), "z": z[idx].tolist(),
            "inverseDistanceStd": inv_std[idx].tolist(), "distanceStd": dist_std[idx].tolist()}


# ----------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------
def stream_name(c: Config) -> str:
    """The authors' stream folder name: <label>-rectified-<int(focal)>-h<size> (online calibration)."""
    return f"{CAMERA_LABEL}-rectified-{int(c.focal_px)}-h{c.size}"


def _write_png(path: Path, image: np.ndarray) -> None:
    """8-bit PNG: RGB [H, W, 3] or grey [H, W] uint8."""
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: PNG could not be written")


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1, allow_nan=False) + "\n")


def write_trajectory(path: Path, motion: dict, start_ns: int, end_ns: int) -> None:
    """closed_loop_trajectory.csv: T_world_device at every whole millisecond of [start, end] (MPS
    columns; quaternion x, y, z, w; timestamps in microseconds; utc -1, quality 1)."""
    t_ns = np.arange(start_ns // 1_000_000, end_ns // 1_000_000 + 1, dtype=np.int64) * 1_000_000
    T = device_poses(motion, t_ns)
    q = quat_xyzw(T[:, :3, :3])
    head = ("graph_uid,tracking_timestamp_us,utc_timestamp_ns,tx_world_device,ty_world_device,tz_world_device,"
            "qx_world_device,qy_world_device,qz_world_device,qw_world_device,quality_score")
    rows = [f"{GRAPH_UID},{t // 1000},-1,{p[0]:.10f},{p[1]:.10f},{p[2]:.10f},{r[0]:.14f},{r[1]:.14f},{r[2]:.14f},"
            f"{r[3]:.14f},1.0" for t, p, r in zip(t_ns.tolist(), T[:, :3, 3].tolist(), q.tolist())]
    path.write_text(head + "\n" + "\n".join(rows) + "\n")



def write_points(path: Path, pts: np.ndarray, inv_std: np.ndarray, dist_std: np.ndarray) -> None:
    """semidense_points.csv.gz (MPS columns, gzip with mtime 0: byte-identical for a seed)."""
    lines = ["uid,graph_uid,px_world,py_world,pz_world,inv_dist_std,dist_std"]
    lines += [f"{i},{GRAPH_UID},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{a:.6f},{b:.6f}"
              for i, (p, a, b) in enumerate(zip(pts.tolist(), inv_std.tolist(), dist_std.tolist()))]
    with open(path, "wb") as raw, gzip.GzipFile(filename="", fileobj=raw, mode="wb", mtime=0) as gz:
        gz.write(("\n".join(lines) + "\n").encode())


def write_camera_maps(stream: Path, c: Config) -> None:
    """The STATED camera maps: vignette.png flat (255), mask.png all valid, image_index.png =
    round(v / (H - 1) x 255) (the row-time ratio of a pinhole sensor read top to bottom)."""
    H = c.size
    _write_png(stream / "vignette.png", np.full((H, H), 255, np.uint8))
    _write_png(stream / "mask.png", np.full((H, H), 255, np.uint8))
    ratio = np.round(np.arange(H) / (H - 1) * 255.0).astype(np.uint8)
    _write_png(stream / "image_index.png", np.ascontiguousarray(np.broadcast_to(ratio[:, None], (H, H))))


def frame_entry(c: Config, k: int, clock: dict, T_world_camera: np.ndarray) -> dict:
    """One frames[] entry of transforms_with_sparse_depth.json (the stated, recorded metadata)."""
    f = c.focal_px
    return {"fx": f, "fy": f, "cx": c.centre_px, "cy": c.centre_px, "w": c.size, "h": c.size,
            "image_path": f"images/{k:05d}.png", "mask_path": "mask.png",
            "camera2device": camera_to_device().tolist(), "transform_matrix": T_world_camera.tolist(),
            "timestamp": int(clock["t_rec"][k]), "timestamp_read_start": int(clock["read_start"][k]),
            "timestamp_read_end": int(clock["read_end"][k]),
            "exposure_duration_s": float(clock["exposure_rec"][k]), "gain": float(c.gain),
            "sparse_depth": f"sparse_depth/{k:05d}.json"}


def hidden_effects(c: Config) -> list[str]:
    """Names of the effects this configuration hides (empty: a null recording)."""
    return [name for name, on in (("vignette", c.vignette_corner > 0), ("readout", c.readout_scale != 1.0),
                                  ("exposure_metadata", c.exposure_fraction > 0), ("time_offset", c.time_offset_s != 0),
                                  ("distortion", c.lens_k0 != 0))
            if on]


def truth_record(c: Config, clock: dict) -> dict:
    """truth.json: the seed, every hidden effect and its value, the altered frames, the conventions."""
    return {
        "writer": "scripts/independent_writer.py (no code shared with egobench)", "seed": c.seed, "config": asdict(c),
        "hidden_effects": hidden_effects(c),
        "effects": {"vignette_corner": c.vignette_corner, "readout_scale": c.readout_scale,
                    "readout_stated_s": c.readout_s, "readout_true_s": c.readout_s * c.readout_scale,
                    "exposure_error": c.exposure_error, "exposure_fraction": c.exposure_fraction,
                    "exposure_altered_frames": clock["altered"], "time_offset_s": c.time_offset_s,
                    "lens_k0": c.lens_k0},
        "conventions": {
            "time_offset": "true centre-row mid-exposure time = recorded timestamp + time_offset_s",
            "lens": "the pixel at the stated pinhole's field angle theta sees the ray at theta - lens_k0 theta^3",
            "row_time": "row v is rendered at t_centre_true + (v / (H - 1) - 1/2) * readout_true_s (mid-exposure)",
            "vignette": "true shading 1 - vignette_corner * (r / r_corner)^2 from (cx, cy); vignette.png is flat",
            "exposure": "images use exposure_true_s; transforms record exposure_recorded_s",
            "frames": "frame k is images/k.png and the reader's Frame.index k (no frame is dropped)"},
        "frames": [{"index": k, "t_centre_true_ns": int(clock["t_true"][k]), "timestamp_ns": int(clock["t_rec"][k]),
                    "exposure_true_s": float(clock["exposure_true"][k]),
                    "exposure_recorded_s": float(clock["exposure_rec"][k])} for k in range(c.frames)],
    }


def _write_all(root: Path, c: Config) -> None:
    """Every file of the recording under ``root`` (a fresh folder)."""
    scene, motion, clock = build_scene(c.seed), head_motion(c.seed, c.motion), frame_clock(c)
    stream, mps = root / stream_name(c), root / "mps" / "slam"
    for d in (stream / "images", stream / "sparse_depth", mps):
        d.mkdir(parents=True)
    margin = round(MARGIN_S * 1e9)
    write_trajectory(mps / "closed_loop_trajectory.csv", motion, int(clock["t_true"][0]) - margin,
                     int(clock["t_true"][-1]) + margin)
    pts, inv_std, dist_std = semidense_points(scene, c.seed)
    write_points(mps / "semidense_points.csv.gz", pts, inv_std, dist_std)
    for name in ("closed_loop_trajectory.csv", "semidense_points.csv.gz"):
        (stream / name).symlink_to(Path("..") / "mps" / "slam" / name)
    write_camera_maps(stream, c)
    vignette, noise_rng, entries = true_vignette(c), np.random.default_rng([c.seed, 2]), []
    for k in range(c.frames):
        image = render_frame(c, scene, motion, int(clock["t_true"][k]), float(clock["exposure_true"][k]), vignette,
                             noise_rng)
        _write_png(stream / "images" / f"{k:05d}.png", image)
        T_wc = camera_poses(motion, [int(clock["t_rec"][k])])[0]  # as preprocessing: the pose at the recorded time
        _write_json(stream / "sparse_depth" / f"{k:05d}.json", sparse_depth(c, scene, T_wc, pts, inv_std, dist_std))
        entries.append(frame_entry(c, k, clock, T_wc))
    top = {"camera_model": "linear", "camera_label": CAMERA_LABEL}
    _write_json(stream / "transforms_with_sparse_depth.json", {**top, "frames": entries})
    _write_json(stream / "transforms.json", {**top, "frames": [{k: v for k, v in e.items() if k != "sparse_depth"}
                                                               for e in entries]})
    _write_json(root / "truth.json", truth_record(c, clock))


def write_recording(out: str | Path, c: Config) -> Path:
    """Write the recording of ``c`` to the new folder ``out``: built in a hidden sibling folder and
    renamed at the end (no half-written recording). ValueError for a bad config, FileExistsError if out exists."""
    check_config(c)
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise FileExistsError(f"{out}: already exists; choose a new --out folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _write_all(tmp, c)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def parse_args(argv: list[str] | None) -> tuple[Path, Config]:
    """The command line -> (out folder, checked Config); bad arguments exit 2 with a message."""
    p = argparse.ArgumentParser(prog="independent_writer.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="new recording folder (must not exist)")
    defaults = Config()
    for name, kind, helptext in (
            ("seed", int, "seed of the world, motion, noise and altered frames"), ("size", int, "image side, pixels"),
            ("frames", int, "number of frames"), ("fps", float, "frame rate, Hz"),
            ("fov-deg", float, "horizontal field of view, deg"),
            ("exposure-s", float, "true (and stated) exposure, s"), ("gain", float, "analog gain"),
            ("readout-s", float, "STATED rolling-shutter readout, s"), ("supersample", int, "rays per pixel side"),
            ("noise", float, "Gaussian noise sigma, 8-bit levels"),
            ("vignette-corner", float, "hidden: true corner shading fraction F (stated vignette flat)"),
            ("readout-scale", float, "hidden: true readout = stated x S"),
            ("exposure-error", float, "hidden: recorded exposure = true x E on --exposure-fraction of the frames"),
            ("exposure-fraction", float, "hidden: share P of frames with a misrecorded exposure"),
            ("time-offset-s", float, "hidden: true capture time = recorded timestamp + D, s"),
            ("lens-k0", float, "hidden: the pixel at field angle theta sees the ray at theta - K theta^3")):
        attr = name.replace("-", "_")
        p.add_argument(f"--{name}", type=kind, default=getattr(defaults, attr),
                       help=f"{helptext} (default {getattr(defaults, attr)})")
    p.add_argument("--motion", choices=("both", "rotation", "translation"), default=defaults.motion,
                   help="the head's motion: rotation and translation, or one of them alone (default both)")
    args = p.parse_args(argv)
    c = Config(**{k: v for k, v in vars(args).items() if k != "out"})
    try:
        check_config(c)
    except ValueError as exc:
        p.error(str(exc))
    if args.out.exists() or args.out.is_symlink():
        p.error(f"--out {args.out}: already exists; choose a new folder")
    return args.out, c


def main(argv: list[str] | None = None) -> int:
    out, c = parse_args(argv)
    write_recording(out, c)
    effects = ", ".join(hidden_effects(c)) or "none (null recording)"
    print(f"{out}: {c.frames} frames {c.size}x{c.size}, seed {c.seed}, hidden effects: {effects}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
