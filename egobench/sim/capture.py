"""Capture a synthetic recording: world + head motion + device -> the recording folder.

Per frame (docs/architecture.md conventions):
1. A coarse preview cast at the centre-row time gives the frame's median luminance
   (auto-exposure: exposure and gain) and scene points for the motion estimate.
2. Raw rolling-shutter fisheye capture with the TRUE calibration: raw row r starts exposing at
   t(r) = read_start + r / (H_raw - 1) * readout and integrates S temporal samples at the
   midpoints of S equal sub-intervals of [t(r), t(r) + exposure]; every pixel also integrates
   its area over P = `pixel_samples` sub-pixel positions (k x k stratified grid); rays from
   Fisheye624.unproject of the offset pixel coordinates, posed by trajectory.pose(t) @
   T_device_camera; the mean over the ray samples is the exposure and pixel-area integral
   (clean linear irradiance). Pairing (`sample_schedule`): with S >= P each temporal sample
   takes one sub-pixel position in turn (S rounded up to a multiple of P; no extra cost), with
   S < P every temporal sample takes all P positions (S x P rays). Without area integration
   (P = 1) geometric edges alias: a 0.01 px shift moves edge pixels by several 8-bit levels,
   which breaks first-order (band-limited) residual models such as egobench.diagnose.
3. Image formation (egobench.model.formation): exposure x gain x sensitivity, lens shading (the
   device's calibrated vignette times any hidden extra shading), white balance, clipping at
   full well, Poisson-Gaussian noise, response (gamma), 8-bit; optionally JPEG.
4. Rectification to the pinhole (f = 0.5 W) with the ONLINE and with the FACTORY calibration.
5. Ground truth in the online rectified camera: clean irradiance (rectified like the image),
   depth and normals cast per rectified pixel at the pixel's true mid-exposure time.
6. Semi-dense SLAM points (scene surface samples + SLAM-like inverse-distance noise) and their
   per-frame sparse depth under each calibration.

Temporal samples S: adaptive per frame, so that the image motion between consecutive samples
is at most `max_sample_step_px` (0.15 px): S = clamp(ceil(max_motion_px / 0.15), 1, 32), where
max_motion_px is the largest displacement of preview scene points during the exposure at the
first, middle and last rows. `tests/test_capture.py` checks that doubling S changes the
noise-free display image by less than half an 8-bit level on average.

Interruption and resumption: the recording is built in a hidden partial folder beside the output
(`partial_dir`: `<parent>/.<name>.partial/`). After each frame's files, a small state file
`.resume/NNNNN.json` is written (atomically, last) holding what later frames depend on: the
auto-exposure state, the noise generator state, the frame's transforms/calibration/truth records
and the SimConfig hash. A rerun with `resume="auto"` (the CLI default) continues after the last
frame with a state file and writes a recording byte-identical to an uninterrupted run
(recording.json's simulation_time_s aside). On success the partial folder replaces the output
(os.replace after removing an old output).

Code path: `simulate_recording` -> `build_capture_setup` (once: `CaptureSetup`) and `_restore_run` (the
`CaptureRun` records and carried state, advanced past resumed frames) -> per frame `capture_raw_frame`
(steps 1-3), `_write_ground_truth` (5), `visible_semidense` and `_write_stream_frame` per calibration
(4, 6), the frame's state file -> `_write_recording_files`.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch
from torch import Tensor

from egobench.camera.pinhole import Pinhole
from egobench.camera.rectify import readout_range
from egobench.data.mps import CameraCalibration, SemiDensePoints
from egobench.sim.config import SimConfig
from egobench.sim.devices import SEMIDENSE_NOISE, DeviceProfile, get_device

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    from egobench.camera import Rectification
    from egobench.data.mps import CalibrationRecord
    from egobench.model.formation import FormationModel, PoissonGaussianNoise
    from egobench.geometry import Trajectory
    from egobench.sim.camera_calibration import CalibrationSet

#: Rays per Scene.cast call (bounds memory) on the CPU, and on a GPU (fewer, larger kernels).
CAST_CHUNK = 1 << 16
CAST_CHUNK_GPU = 1 << 18


def cast_chunk_size(device: torch.device | str) -> int:
    """Rays per Scene.cast call on ``device``."""
    return CAST_CHUNK if torch.device(device).type == "cpu" else CAST_CHUNK_GPU
#: Seconds of trajectory before the first and after the last frame.
TRAJECTORY_MARGIN_S = 0.2
#: Preview grid (per axis) for auto-exposure and the motion estimate.
PREVIEW_GRID = 24
#: float16 cannot hold more than 65504: GT radiance is clipped there.
FLOAT16_MAX = 65000.0


# ----------------------------------------------------------------------------------------
# geometry helpers
# ----------------------------------------------------------------------------------------
def device_trajectory(look_trajectory, device: DeviceProfile):
    """Re-express the motion model's head frame (camera looks along +z) as the device frame.

    The motion model moves a frame whose +z is the viewing direction. The real Aria RGB camera
    is rotated (~39 deg) against the device frame, so T_world_device = T_world_look @
    [R_device_camera^T | 0]; then T_world_device @ T_device_camera looks along the head's +z.
    """
    from egobench.geometry import Trajectory, make_pose

    R_dc = device.T_device_camera()[:3, :3]
    T_look_device = make_pose(R_dc.T, torch.zeros(3, dtype=torch.float64))
    return Trajectory(look_trajectory.t_ns, look_trajectory.T_world_device @ T_look_device)


def _as_T(cal: CameraCalibration) -> Tensor:  # [4, 4] float64
    return torch.as_tensor(cal.T_device_camera, dtype=torch.float64)


def camera_poses(trajectory, T_device_camera: Tensor, t_ns) -> Tensor:
    """T_world_camera [B, 4, 4] = trajectory.pose(t_ns) @ T_device_camera."""
    return trajectory.pose(t_ns) @ T_device_camera


def cast_chunked(scene, origins: Tensor, dirs: Tensor, want: tuple[str, ...] = ("radiance",),
                 pixel_angle_rad: float | None = None) -> dict[str, Tensor]:
    """Scene.cast in chunks (`cast_chunk_size` of the rays' device); origins/dirs [N, 3] float32
    (dirs unit). The scene works on the rays' device; outputs stay there.

    ``pixel_angle_rad`` (about 1 / focal_px) lets textures average over each pixel's footprint,
    as a real pixel integrates over its area (without it, one ray per pixel aliases)."""
    outs: dict[str, list[Tensor]] = {k: [] for k in want}
    n = origins.shape[0]
    chunk = cast_chunk_size(origins.device)
    for s in range(0, n, chunk):
        hit = scene.cast(origins[s:s + chunk], dirs[s:s + chunk], pixel_angle_rad=pixel_angle_rad)
        for k in want:
            outs[k].append(getattr(hit, k))
    if n == 0:
        return {k: torch.zeros(0) for k in want}
    return {k: torch.cat(v, 0) for k, v in outs.items()}


def geometry_cast(scene, origins: Tensor, dirs: Tensor, device: torch.device | str | None = None
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """Depth-only cast (no shading): -> (t [N] float64 (inf on miss), normal facing the ray [N, 3], hit [N]).

    Uses Scene.intersect + Scene.surface_frame when the scene has them (several times cheaper
    than Scene.cast, which also shades); otherwise Scene.cast. ``device``: cast there (e.g. a GPU)
    and return the results on the inputs' device.
    """
    if device is not None and torch.device(device) != origins.device:
        home = origins.device
        return tuple(x.to(home) for x in geometry_cast(scene, origins.to(device), dirs.to(device)))
    if not (hasattr(scene, "intersect") and hasattr(scene, "surface_frame")):
        out = cast_chunked(scene, origins, dirs, ("depth_t", "normal_world", "hit"))
        return out["depth_t"].to(torch.float64), out["normal_world"].to(torch.float64), out["hit"]
    d = dirs / dirs.norm(dim=-1, keepdim=True)
    t, pid = scene.intersect(origins, d)
    hit = pid >= 0
    normal = torch.zeros_like(origins)
    idx = hit.nonzero()[:, 0]
    if idx.numel():
        p = origins[idx] + t[idx, None] * d[idx]
        n_out = scene.surface_frame(p, pid[idx])[1]
        normal[idx] = torch.where(((n_out * d[idx]).sum(1) > 0)[:, None], -n_out, n_out)
    return t.to(torch.float64), normal.to(torch.float64), hit


@dataclass
class RawCamera:
    """Ray directions of the true raw fisheye camera (computed once per recording)."""

    calibration: CameraCalibration
    rays_cam: Tensor  # [H, W, 3] float64 unit rays in the camera frame (pixel centres)
    valid: Tensor  # [H, W] bool: unprojection converged inside the image circle
    pixel_samples: int = 1  # P sub-pixel positions per pixel (k x k jittered stratified grid, P = k^2)
    sub_rays_cam: Tensor | None = None  # [P, H, W, 3] float64 unit rays through the sub-pixel positions
    box: tuple[int, int, int, int] | None = None  # (row0, row1, col0, col1) holding every cast pixel; None = the frame
    meter_box: tuple[int, int, int, int] | None = None  # where the auto-exposure preview meters; None = ``box``
    readout_rows: tuple[int, int] | None = None  # (first, last) raw row read over the readout; None = every row

    @classmethod
    def build(cls, cal: CameraCalibration, pixel_samples: int = 1) -> "RawCamera":
        """Rays of every raw pixel centre and of its `pixel_samples` sub-pixel positions
        (Fisheye624.unproject of the offset pixel coordinates, see `subpixel_offsets`)."""
        cam = cal.camera()
        v, u = torch.meshgrid(torch.arange(cal.height, dtype=torch.float64),
                              torch.arange(cal.width, dtype=torch.float64), indexing="ij")
        uv = torch.stack([u, v], -1)  # [H, W, 2]
        rays, ok = cam.unproject_checked(uv)
        valid = ok & torch.isfinite(rays).all(-1)
        offsets = subpixel_offsets(pixel_samples, cal.height, cal.width)  # [P, H, W, 2]
        sub = None
        if offsets.shape[0] > 1:
            sub_rays, sub_ok = cam.unproject_checked(uv[None] + offsets)  # [P, H, W, 3]
            sub_ok = sub_ok & torch.isfinite(sub_rays).all(-1)
            # a sub-position outside the image circle of a valid pixel falls back to the pixel centre
            sub = torch.where(sub_ok[..., None], sub_rays, rays[None].expand_as(sub_rays))
        return cls(calibration=cal, rays_cam=rays, valid=valid, pixel_samples=int(offsets.shape[0]), sub_rays_cam=sub)

    def sample_rays(self) -> Tensor:
        """[P, H, W, 3] rays of the P sub-pixel positions (P = 1: the pixel centres)."""
        return self.rays_cam[None] if self.sub_rays_cam is None else self.sub_rays_cam

    def restricted_to(self, cast: Tensor, meter: Tensor | None = None) -> "RawCamera":
        """This camera casting only the pixels of ``cast`` [H, W] bool (the others stay black);
        ``box`` becomes their bounding box. The auto-exposure preview meters over the bounding box
        of ``meter`` [H, W] bool (default: ``cast``), so that what one stream samples (the factory
        rectification's wider footprint) does not change the exposures of another."""
        valid = self.valid & cast
        box = _bounding_box(valid, "cast")
        meter_box = box if meter is None else _bounding_box(self.valid & meter, "meter")
        return dataclasses.replace(self, valid=valid, box=box, meter_box=meter_box)


def _bounding_box(mask: Tensor, name: str) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1) of the True pixels of ``mask`` [H, W]; ValueError when there are none."""
    rows, cols = torch.nonzero(mask.any(1)).flatten(), torch.nonzero(mask.any(0)).flatten()
    if rows.numel() == 0:
        raise ValueError(f"raw camera {name}: no valid raw pixel is sampled by the rectified view")
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def sampled_raw_pixels(rects: list, raw_shape: tuple[int, int], margin_px: int = 2) -> Tensor:
    """[H, W] bool: the raw pixels the rectifications' bilinear lookups read, grown by ``margin_px``."""
    H, W = raw_shape
    need = torch.zeros(H, W, dtype=torch.bool)
    for rect in rects:
        uv = rect.map_uv[rect.valid].to(torch.float64)  # [n, 2] raw (u, v)
        u0, v0 = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        for dv in range(-margin_px, margin_px + 2):
            for du in range(-margin_px, margin_px + 2):
                need[(v0 + dv).clamp(0, H - 1), (u0 + du).clamp(0, W - 1)] = True
    return need


#: Seed of the sub-pixel jitter pattern: fixed, so that every capture of a recording (and a
#: re-cast of it, egobench.diagnose.sources) integrates each pixel over the same positions.
SUBPIXEL_JITTER_SEED = 12345


def subpixel_offsets(pixel_samples: int, height: int = 1, width: int = 1, jitter: bool = False) -> Tensor:
    """[P, H, W, 2] (du, dv) offsets from each pixel centre: a k x k stratified grid, P = k^2.

    Cell centres ((i + 0.5) / k - 0.5), optionally moved by a per-pixel uniform jitter inside its
    cell (``jitter``; off in the capture: through the diagnosis it gave worse geometric estimates
    in a 48 px comparison): edge crossings of neighbouring pixels then happen at different shifts, so the
    image changes by many small steps under a sub-pixel motion instead of a few k-aligned jumps.
    The jitter is antithetic (cell (i, j) and its mirror (k-1-i, k-1-j) move oppositely; a middle
    cell does not move), so every pixel's mean offset is exactly 0: no pixel-centre bias.
    P = 1 is the pixel centre (point sampling, the behaviour before pixel-area integration).
    """
    k = int(round(math.sqrt(pixel_samples))) if isinstance(pixel_samples, int) and pixel_samples >= 1 else 0
    if isinstance(pixel_samples, bool) or k * k != pixel_samples:
        raise ValueError(f"pixel_samples: expected a perfect square >= 1 (1, 4, 9, 16, ...), got {pixel_samples!r}")
    g = (torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5
    dv, du = torch.meshgrid(g, g, indexing="ij")
    base = torch.stack([du.reshape(-1), dv.reshape(-1)], -1)  # [P, 2]
    out = base[:, None, None, :].expand(pixel_samples, height, width, 2).clone()
    if jitter and k > 1:
        gen = torch.Generator().manual_seed(SUBPIXEL_JITTER_SEED)
        j = (torch.rand(pixel_samples, height, width, 2, generator=gen, dtype=torch.float64) - 0.5) / k
        mirror = torch.arange(pixel_samples - 1, -1, -1)  # cell (i, j) -> (k-1-i, k-1-j) in row-major order
        first = torch.arange(pixel_samples) < mirror
        j = torch.where(first[:, None, None, None], j, -j[mirror])
        j[torch.arange(pixel_samples) == mirror] = 0.0
        out = out + j
    return out


def sample_schedule(n_time: int, n_pixel: int) -> tuple[Tensor, Tensor]:
    """How S temporal samples and P sub-pixel positions combine into the ray samples of a pixel.

    -> (time index [n] into the temporal samples, sub-pixel index [n]); the pixel value is the
    plain mean over the n ray samples. S >= P: each temporal sample takes ONE sub-pixel
    position, cycling through them (the cost stays flat: one ray per temporal sample; S must
    be a multiple of P so every position has the same weight, see `paired_temporal_samples`).
    S < P: the product (S x P rays), so a short or static exposure still integrates the
    whole pixel area.
    """
    if n_time >= n_pixel:
        if n_time % n_pixel:
            raise ValueError(f"n_time: expected a multiple of n_pixel={n_pixel} when n_time >= n_pixel, got {n_time}")
        j = torch.arange(n_time)
        return j, j % n_pixel
    j = torch.arange(n_time * n_pixel)
    return j // n_pixel, j % n_pixel


def paired_temporal_samples(n_time: int, n_pixel: int) -> int:
    """S rounded up to a multiple of P when S >= P (equal weight per sub-pixel position; otherwise
    the pixel centroid would move by up to 0.5 / S px from frame to frame); S unchanged when S < P."""
    return int(math.ceil(n_time / n_pixel) * n_pixel) if n_time >= n_pixel else int(n_time)


def row_start_times_ns(read_start_ns: int, readout_s: float, height: int,
                       readout_rows: tuple[int, int] | None = None) -> Tensor:
    """t(r) = read_start + (r - a) / (b - a) * readout, [H] int64 ns (docs/architecture.md); (a, b) =
    ``readout_rows``, the first and last row read (default 0 and H - 1); rows outside are clamped."""
    a, b = readout_range(readout_rows, height)
    r = ((torch.arange(height, dtype=torch.float64) - a) / max(b - a, 1)).clamp(0.0, 1.0)
    return read_start_ns + torch.round(r * readout_s * 1e9).to(torch.int64)


def view_readout_rows(rect, raw_shape: tuple[int, int]) -> tuple[int, int]:
    """(first, last) raw row the rectification ``rect`` samples (its bilinear lookups, +2 px): the
    rows an ROI readout of that view reads (SimConfig.readout_window = "view")."""
    row0, row1, _, _ = _bounding_box(sampled_raw_pixels([rect], raw_shape), "readout window")
    return row0, row1 - 1


def capture_irradiance(scene, trajectory, raw: RawCamera, read_start_ns: int, exposure_s: float, readout_s: float,
                       n_samples: int, device: torch.device | str = "cpu") -> Tensor:
    """Clean linear irradiance of one rolling-shutter raw frame, [H, W, 3] float32.

    Every raw row integrates `n_samples` exposure samples (formation.exposure_sample_times_ns)
    and every pixel its area: ray samples pair temporal samples with the camera's
    `raw.pixel_samples` sub-pixel positions (`sample_schedule`; S is first rounded up by
    `paired_temporal_samples`). Textures are box-filtered over each ray sample's share of the
    pixel (1 / sqrt(P) of the pixel angle), so texture and edge integration together cover
    the pixel area once. Invalid raw pixels (outside the lens model) are 0. ``device``: where rays
    are built and cast (SimConfig.compute_device); the result comes back on the CPU.
    """
    from egobench.model.formation import exposure_sample_times_ns

    H, W = raw.valid.shape
    P = int(raw.pixel_samples)
    S = paired_temporal_samples(int(n_samples), P)
    t_rows = row_start_times_ns(read_start_ns, readout_s, H, raw.readout_rows)  # [H]
    t = exposure_sample_times_ns(t_rows, exposure_s, S)  # [H, S] int64
    T = camera_poses(trajectory, _as_T(raw.calibration), t.reshape(-1)).reshape(H, S, 4, 4)
    time_idx, sub_idx = sample_schedule(S, P)  # [n], [n]
    n = int(time_idx.numel())
    R = T[:, time_idx, :3, :3].to(device=device, dtype=torch.float32)  # [H, n, 3, 3]
    o = T[:, time_idx, :3, 3].to(device=device, dtype=torch.float32)  # [H, n, 3]
    rays = raw.sample_rays().to(device=device, dtype=torch.float32)  # [P, H, W, 3]
    valid = raw.valid.to(device)
    sub_idx = sub_idx.to(device)
    # radians one ray sample's share of a raw pixel subtends at the centre
    pixel_angle = 1.0 / float(raw.calibration.camera().f) / math.sqrt(P)
    out = torch.zeros(H, W, 3, dtype=torch.float32, device=device)
    row0, row1, c0, c1 = raw.box if raw.box is not None else (0, H, 0, W)
    rows_per_chunk = max(1, cast_chunk_size(device) // max(1, (c1 - c0) * n))
    for r0 in range(row0, row1, rows_per_chunk):
        r1 = min(row1, r0 + rows_per_chunk)
        vmask = valid[r0:r1, c0:c1]  # [h, w]
        if not bool(vmask.any()):
            continue
        d = torch.einsum("hnij,nhwj->hnwi", R[r0:r1], rays[sub_idx, r0:r1, c0:c1])  # [h, n, w, 3]
        orig = o[r0:r1, :, None, :].expand_as(d)
        m = vmask[:, None, :].expand(d.shape[:3])
        rad = cast_chunked(scene, orig[m].contiguous(), d[m].contiguous(),
                           pixel_angle_rad=pixel_angle)["radiance"].to(torch.float32)
        full = torch.zeros(d.shape[:3] + (3,), dtype=torch.float32, device=device)
        full[m] = rad
        out[r0:r1, c0:c1] = full.mean(dim=1)
    return out.cpu()


def preview(scene, trajectory, raw: RawCamera, t_ns: int, grid: int = PREVIEW_GRID,
            device: torch.device | str = "cpu") -> tuple[Tensor, Tensor, Tensor]:
    """Coarse cast at one time (on ``device``) -> (luminance [n], hit points world [m, 3], their raw
    pixels [m, 2]), on the CPU."""
    H, W = raw.valid.shape
    box = raw.meter_box if raw.meter_box is not None else raw.box
    r0, r1, c0, c1 = box if box is not None else (0, H, 0, W)
    iv = torch.linspace(r0, r1 - 1, grid).round().long()
    iu = torch.linspace(c0, c1 - 1, grid).round().long()
    vv, uu = torch.meshgrid(iv, iu, indexing="ij")
    ok = raw.valid[vv, uu]
    rays = raw.rays_cam[vv, uu][ok]  # [n, 3]
    T = camera_poses(trajectory, _as_T(raw.calibration), [t_ns])[0]
    d = (rays @ T[:3, :3].T).to(torch.float32)
    o = T[:3, 3].to(torch.float32).expand_as(d).contiguous()
    hit = scene.cast(o.to(device), d.to(device))
    hit = type(hit)(**{k: v.cpu() if isinstance(v, Tensor) else v for k, v in vars(hit).items()})
    lum = hit.radiance.to(torch.float32) @ torch.tensor([0.2126, 0.7152, 0.0722])
    good = hit.hit & torch.isfinite(hit.depth_t)
    pts = (o + d * hit.depth_t[:, None])[good].to(torch.float64)
    pix = torch.stack([uu[ok], vv[ok]], -1)[good]
    return lum, pts, pix


def motion_during_exposure_px(trajectory, raw: RawCamera, points_world: Tensor, read_start_ns: int,
                              exposure_s: float, readout_s: float) -> float:
    """Largest image displacement (raw px) of scene points over the exposure of the first,
    middle and last rows."""
    if points_world.shape[0] == 0 or exposure_s <= 0:
        return 0.0
    cam = raw.calibration.camera()
    H = raw.valid.shape[0]
    a, b = readout_range(raw.readout_rows, H)
    t_rows = row_start_times_ns(read_start_ns, readout_s, H, raw.readout_rows)[[a, (a + b) // 2, b]]
    t_end = t_rows + int(round(exposure_s * 1e9))
    T = camera_poses(trajectory, _as_T(raw.calibration), torch.cat([t_rows, t_end]))
    from egobench.geometry import se3_inverse, transform_points

    pc = transform_points(se3_inverse(T)[:, None], points_world[None])  # [6, P, 3]
    uv, ok = cam.project(pc)
    disp = (uv[3:] - uv[:3]).norm(dim=-1)
    good = ok[3:] & ok[:3] & torch.isfinite(disp)
    return float(disp[good].max()) if bool(good.any()) else 0.0


def choose_temporal_samples(config: SimConfig, motion_px: float) -> int:
    if config.temporal_samples is not None:
        return int(config.temporal_samples)
    return int(min(config.max_temporal_samples, max(1, math.ceil(motion_px / config.max_sample_step_px))))


# ----------------------------------------------------------------------------------------
# auto-exposure
# ----------------------------------------------------------------------------------------
@dataclass
class AutoExposureState:
    """Running auto-exposure (log exposure*gain smoothed over frames)."""

    device: DeviceProfile
    protocol: str  # auto | indoor | fixed
    fixed_exposure_s: float | None = None
    fixed_gain: float | None = None
    log_eg: float | None = None
    held: tuple[float, float] | None = None

    def step(self, median_luminance: float) -> tuple[float, float]:
        """-> (exposure_s, gain) for a frame whose median luminance is given (cd/m^2)."""
        ae = self.device.auto_exposure
        sens = self.device.sensitivity
        # indoor: the paper's capture protocol caps exposure (2 ms); fixed (DTC-like lab captures with fixed
        # exposure and gain): the first frame's indoor-protocol values are held (assumption: the DTC
        # exposure is not published; a short exposure keeps the object sharp).
        capped = self.protocol in ("indoor", "fixed")
        exp_max = min(ae.exposure_max_s, self.device.indoor_exposure_max_s) if capped else ae.exposure_max_s
        if median_luminance > 0 and math.isfinite(median_luminance):
            target = math.log(ae.target_median / (sens * median_luminance))
        else:
            target = math.log(exp_max * ae.gain_max)
        if self.log_eg is None:
            self.log_eg = target
        else:
            self.log_eg = ae.smoothing * self.log_eg + (1.0 - ae.smoothing) * target
        eg = math.exp(self.log_eg)
        if self.fixed_exposure_s is not None:
            exposure = self.fixed_exposure_s
            gain = self.fixed_gain if self.fixed_gain is not None else min(ae.gain_max, max(ae.gain_min, eg / exposure))
            return exposure, gain
        if self.protocol == "fixed" and self.held is not None:
            return self.held
        exposure = min(exp_max, max(ae.exposure_min_s, eg / ae.gain_min))
        gain = min(ae.gain_max, max(ae.gain_min, eg / exposure))
        if self.protocol == "fixed":
            self.held = (exposure, gain)
        return exposure, gain


# ----------------------------------------------------------------------------------------
# semi-dense points
# ----------------------------------------------------------------------------------------
def make_semidense_points(scene, positions_world: Tensor, n: int, seed: int) -> tuple[SemiDensePoints, np.ndarray]:
    """Scene surface samples + SLAM-like noise -> (points as MPS writes them, clean points [P, 3]).

    Each point gets an observer (a random device position), inv_dist_std ~ logNormal fitted to
    the real sample, a perturbed inverse distance 1/d' = 1/d + N(0, inv_dist_std) along the
    viewing ray, and dist_std = inv_dist_std * d^2 (devices.SemiDenseNoise).
    """
    rng = np.random.default_rng([seed, 303])
    if n == 0:
        z = np.zeros(0)
        return SemiDensePoints(np.zeros(0, np.int64), np.zeros((0, 3)), z, z), np.zeros((0, 3))
    res = scene.sample_surface_points(n, rng, visible_from=positions_world)
    pts = res[0] if isinstance(res, tuple) else res
    clean = np.asarray(torch.as_tensor(pts).detach().cpu().numpy(), dtype=np.float64).reshape(-1, 3)
    pos = positions_world.detach().cpu().numpy().astype(np.float64)
    obs = pos[rng.integers(0, pos.shape[0], size=clean.shape[0])]
    vec = clean - obs
    d = np.linalg.norm(vec, axis=1).clip(1e-3)
    ray = vec / d[:, None]
    noise = SEMIDENSE_NOISE
    inv_std = np.exp(rng.normal(noise.log_inv_dist_std_mean, noise.log_inv_dist_std_std, size=d.shape))
    inv_d = 1.0 / d + rng.normal(size=d.shape) * inv_std
    inv_d = np.maximum(inv_d, 1.0 / (10.0 * d))  # never behind the observer nor at infinity
    d_noisy = 1.0 / inv_d
    noisy = obs + ray * d_noisy[:, None]
    dist_std = inv_std * d_noisy**2
    sd = SemiDensePoints(uid=np.arange(clean.shape[0], dtype=np.int64), points_world=noisy, inv_dist_std=inv_std,
                         dist_std=dist_std)
    return sd, clean


# ----------------------------------------------------------------------------------------
# the recording
# ----------------------------------------------------------------------------------------
@dataclass
class CaptureResult:
    """Summary of `simulate_recording` (also in recording.json)."""

    path: Path
    n_frames: int
    time_s: float
    temporal_samples: list[int] = field(default_factory=list)
    exposures_s: list[float] = field(default_factory=list)
    gains: list[float] = field(default_factory=list)
    complete: bool = True  # False: stopped by `stop_after`; `path` is then the partial folder
    resumed_from: int = 0  # frames taken over from an earlier run's partial folder


def _to_uint8(display: Tensor) -> np.ndarray:
    return (display.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _rig(cal: CameraCalibration, rect_size: int, focal_ratio: float):
    """(Rectification, pinhole) of a calibration: pinhole f = focal_ratio * W, centred, same axes."""
    from egobench.camera import Rectification

    W = H = int(rect_size)
    f = float(focal_ratio) * W
    pin = Pinhole(fx=f, fy=f, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
    return Rectification.build(cal.camera(), pin), pin


# ----------------------------------------------------------------------------------------
# interruption and resumption (the partial folder)
# ----------------------------------------------------------------------------------------
#: Schema of the partial folder's manifest (`<partial>/.resume/partial.json`).
PARTIAL_SCHEMA = "egobench.sim.partial/1"
#: Folder inside the partial folder: the manifest and one state file per completed frame.
RESUME_SUBDIR = ".resume"


def stream_names(config: SimConfig) -> dict[str, str]:
    """calibration -> rectified stream folder name, by the authors' naming (egobench.data.layout)."""
    from egobench.data.layout import stream_folder_name

    dev = get_device(config.device_name)
    focal = config.focal_ratio() * config.rectified_size
    return {name: stream_folder_name(dev.label, focal, config.rectified_size, factory=name == "factory")
            for name in ("online", "factory")}


def frame_dirs(config: SimConfig) -> tuple[str, ...]:
    """Folders holding one file per frame, named NNNNN.<ext> (frames past the last state file are removed on resume)."""
    streams = tuple(f"{d}/{sub}" for d in stream_names(config).values() for sub in ("images", "sparse_depth"))
    return ("raw",) + streams + ("ground_truth/radiance", "ground_truth/depth", "ground_truth/normal")


def partial_dir(out_dir: str | Path) -> Path:
    """The hidden folder `out_dir` is built in: `<parent>/.<name>.partial` (kept when interrupted)."""
    out_dir = Path(out_dir)
    return out_dir.parent / f".{out_dir.name}.partial"


def sim_config_hash(config: SimConfig) -> str:
    """sha1 (hex) of the canonical SimConfig (`to_dict`, sorted keys) and the egobench version."""
    import egobench

    blob = json.dumps({"sim_config": config.to_dict(), "egobench_version": egobench.__version__}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()


def _frame_state_path(partial: Path, k: int) -> Path:
    return partial / RESUME_SUBDIR / f"{k:05d}.json"


def _read_partial(partial: Path, config_hash: str) -> tuple[list[dict], str | None]:
    """-> (state records of the completed frames 0..m-1 in order, None), or ([], why the partial
    folder cannot be resumed). Frame m is the first without a readable state file of this config."""
    from egobench.io_utils import read_json

    manifest = partial / RESUME_SUBDIR / "partial.json"
    try:
        meta = read_json(manifest)
    except (FileNotFoundError, ValueError) as exc:
        return [], f"no readable manifest ({exc})"
    if not isinstance(meta, dict) or meta.get("schema") != PARTIAL_SCHEMA:
        return [], f"{manifest}: field 'schema' is not {PARTIAL_SCHEMA!r}"
    if meta.get("config_hash") != config_hash:
        return [], (f"it was written for a different SimConfig or egobench version (config hash "
                    f"{str(meta.get('config_hash'))[:12]}, egobench {meta.get('egobench_version')}; "
                    f"this run: {config_hash[:12]})")
    states: list[dict] = []
    while True:
        path = _frame_state_path(partial, len(states))
        if not path.is_file():
            break
        try:
            st = read_json(path)
        except ValueError:
            break
        if not isinstance(st, dict) or st.get("frame") != len(states) or st.get("config_hash") != config_hash:
            break
        states.append(st)
    return states, None


def _drop_frames_from(partial: Path, first: int, dirs: tuple[str, ...]) -> None:
    """Remove the per-frame files and state files of frames >= `first` (half-written or stale) and
    the temporary files an interrupted atomic write left anywhere in the partial folder."""
    for sub in dirs + (RESUME_SUBDIR,):
        folder = partial / sub
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            stem = f.name.split(".", 1)[0]
            if f.is_file() and stem.isdigit() and int(stem) >= first:
                f.unlink()
    for f in partial.rglob(".*.tmp*"):
        if f.is_file():
            f.unlink()


def _encode_generator(generator: torch.Generator) -> str:
    return base64.b64encode(generator.get_state().numpy().tobytes()).decode("ascii")


def _decode_generator(generator: torch.Generator, text: str) -> None:
    generator.set_state(torch.frombuffer(bytearray(base64.b64decode(text)), dtype=torch.uint8).clone())


def _finalise(partial: Path, out_dir: Path) -> None:
    """Drop the resume state and move the finished partial folder onto `out_dir` (replacing it)."""
    state = partial / RESUME_SUBDIR
    trash = out_dir.parent / f".{out_dir.name}.partial-state.tmp"
    if trash.exists():
        shutil.rmtree(trash)
    if state.exists():
        os.replace(state, trash)  # one rename: the partial folder is never without its manifest for long
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(partial, out_dir)
    if trash.exists():
        shutil.rmtree(trash)


def simulate_recording(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
                       resume: bool | Literal["auto"] = False, stop_after: int | None = None) -> CaptureResult:
    """Simulate `config` into the recording folder `out_dir` (layout: docs/architecture.md).

    The recording is built in `partial_dir(out_dir)`; after every frame a state file (written last)
    records what later frames depend on. ``resume``: False starts afresh (an existing partial folder
    is discarded) and removes the partial folder when an exception ends the run (nothing left
    behind); "auto" (the CLI's and the workflow's choice) continues a partial folder of the same
    SimConfig and egobench version, and discards one of another config with a message on stderr;
    True continues one and raises (FileNotFoundError / ValueError) when there is none to continue.
    With resume on, the partial folder is kept when the run fails, so rerunning the command
    continues it; the result is byte-identical to an uninterrupted run (recording.json's
    simulation_time_s, summed over the runs, aside). ``stop_after``: stop once that many frames
    (in total) are done, keeping the partial folder (an interruption hook, as in
    egobench.train.train); the result then has ``complete=False`` and ``path`` = the partial folder.
    On success the partial folder replaces `out_dir` (os.replace after removing an old `out_dir`).
    """
    import egobench
    from egobench.io_utils import write_json

    config.validate()
    if resume not in (True, False, "auto"):
        raise ValueError(f"simulate_recording: resume must be True, False or 'auto', got {resume!r}")
    if stop_after is not None and (isinstance(stop_after, bool) or not isinstance(stop_after, int) or stop_after < 0):
        raise ValueError(f"simulate_recording: stop_after must be None or an int >= 0, got {stop_after!r}")
    t_begin = time.perf_counter()
    out_dir = Path(out_dir)
    partial = partial_dir(out_dir)
    chash = sim_config_hash(config)

    # Resume a partial folder, or discard it and start afresh.
    states: list[dict] = []
    if partial.exists():
        why = "resume is off"
        if resume:
            states, why = _read_partial(partial, chash)
        if why is not None:
            if resume is True:
                raise ValueError(f"{partial}: cannot resume: {why}")
            print(f"egobench simulate: discarding the partial recording {partial}: {why}; starting afresh",
                  file=sys.stderr)
            shutil.rmtree(partial)
    elif resume is True:
        raise FileNotFoundError(f"{partial}: no partial recording to resume from")
    resuming = partial.exists()
    if resuming:
        print(f"egobench simulate: resuming {partial} after {len(states)}/{config.n_frames} frames", file=sys.stderr)
    else:
        (partial / RESUME_SUBDIR).mkdir(parents=True)
        write_json(partial / RESUME_SUBDIR / "partial.json", {
            "schema": PARTIAL_SCHEMA, "config_hash": chash, "egobench_version": egobench.__version__,
            "sim_config": config.to_dict()})

    try:
        return _simulate_into(config, out_dir, partial, chash, states, resuming, progress, stop_after, t_begin)
    except BaseException:
        if not resume and partial.exists():
            shutil.rmtree(partial, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------------------
# what every frame of a recording shares (built once)
# ----------------------------------------------------------------------------------------
def calibrated_vignette(cal: CameraCalibration, dev: DeviceProfile) -> Tensor:
    """[H_raw, W_raw] the device's calibrated lens shading for `cal` (radial about its principal point)."""
    from egobench.model.formation import radial_vignette

    p = cal.params
    return radial_vignette((cal.height, cal.width), 1.0 - dev.vignette_corner, dev.vignette_power,
                           centre=(float(p[1]), float(p[2])))


@dataclass
class FrameClocks:
    """When each frame is read out: camera-clock read starts and the true and stated readout."""

    read_start_cam_ns: np.ndarray  # [N] int64 camera-clock read start of each frame
    true_offset_ns: int  # true camera time offset: device clock = camera clock + this
    readout_true_s: float  # true rolling-shutter readout (first to last raw row), s
    readout_stated_s: float  # readout the recording states, s

    def read_start_true_ns(self, k: int) -> int:
        """Device-clock read start of frame k under the true time offset."""
        return int(self.read_start_cam_ns[k] + self.true_offset_ns)


def _device_motion(config: SimConfig, dev: DeviceProfile, scene) -> Trajectory:
    """The device trajectory (T_world_device) over the frames plus TRAJECTORY_MARGIN_S each side."""
    from egobench.sim.motion import HeadMotionConfig, simulate_head_motion

    duration_s = 2 * TRAJECTORY_MARGIN_S + config.n_frames / dev.fps
    look = simulate_head_motion(HeadMotionConfig(duration_s=duration_s, setting=config.motion), scene, config.seed)
    return device_trajectory(look, dev)


def _frame_clocks(config: SimConfig, dev: DeviceProfile, trajectory: Trajectory, true_cal: CameraCalibration) -> FrameClocks:
    """Frame read starts at the device's fps from the trajectory's start plus the margin (true offset undone)."""
    interval_ns = int(round(1e9 / dev.fps))
    margin_ns = int(TRAJECTORY_MARGIN_S * 1e9)
    true_offset_ns = int(round(true_cal.time_offset_s * 1e9))
    t_cam = trajectory.start_ns + margin_ns - true_offset_ns + interval_ns * np.arange(config.n_frames, dtype=np.int64)
    return FrameClocks(read_start_cam_ns=t_cam, true_offset_ns=true_offset_ns, readout_true_s=true_cal.readout_s,
                       readout_stated_s=config.stated_readout_s())


@dataclass
class PhotometricTruth:
    """The true image formation of a recording (its hidden parts are absent from the recorded metadata)."""

    gamma: float  # true response gamma
    formation: FormationModel  # ground-truth formation config with this gamma
    noise_model: PoissonGaussianNoise  # after noise_std_factor
    vignette_raw: Tensor  # [H_raw, W_raw] true lens shading: calibrated x hidden extra shading
    white_balance: Tensor  # [3] float32 true per-channel gains


def _photometric_truth(config: SimConfig, dev: DeviceProfile, true_cal: CameraCalibration,
                       raw_hw: tuple[int, int]) -> PhotometricTruth:
    """Response, noise, lens shading and white balance the raw frames are formed with."""
    from egobench.model.formation import FormationConfig, FormationModel, PoissonGaussianNoise, radial_vignette

    gamma = config.response_gamma if config.response_gamma is not None else dev.response_gamma
    formation = FormationModel(FormationConfig.ground_truth(gamma=gamma, noise=config.noise))
    noise_model = PoissonGaussianNoise(
        full_well_e=config.full_well_e if config.full_well_e is not None else dev.noise.full_well_e,
        read_noise_e=config.read_noise_e if config.read_noise_e is not None else dev.noise.read_noise_e,
    )
    if config.noise_std_factor != 1.0:
        noise_model = noise_model.scaled(config.noise_std_factor)
    vignette_true = calibrated_vignette(true_cal, dev)
    if config.vignette_strength > 0:
        vignette_true = vignette_true * radial_vignette(raw_hw, config.vignette_strength, dev.vignette_power,
                                                        centre=(float(true_cal.params[1]), float(true_cal.params[2])))
    return PhotometricTruth(gamma=gamma, formation=formation, noise_model=noise_model, vignette_raw=vignette_true,
                            white_balance=torch.tensor(config.white_balance, dtype=torch.float32))


@dataclass
class OnlineTruthRays:
    """Per-pixel rays of the online rectified camera, along which depth and normals are cast."""

    row_time_ratio: Tensor  # [h, w] float64 read-out time of the pixel's raw source / readout (0..1)
    rays_cam: Tensor  # [h, w, 3] float64 camera-frame rays through the pixel centres, z = 1
    valid: Tensor  # [h, w] bool pixels inside the raw image


def _online_truth_rays(rect: Rectification, pin: Pinhole, readout_rows: tuple[int, int] | None) -> OnlineTruthRays:
    """The ground-truth rays of the online rig (Rectification, Pinhole)."""
    return OnlineTruthRays(row_time_ratio=rect.row_time_ratio(readout_rows).to(torch.float64),
                           rays_cam=pin.unproject(pin.pixel_grid(dtype=torch.float64)), valid=rect.valid)


def _metadata_wrong_frames(config: SimConfig) -> set[int]:
    """Frames whose recorded exposure is wrong (hidden effect `exposure_metadata_error`)."""
    rng_meta = np.random.default_rng([config.seed, 404])
    n_bad = int(round(config.exposure_metadata_fraction * config.n_frames)) if config.exposure_metadata_error else 0
    return set(rng_meta.permutation(config.n_frames)[:n_bad].tolist())


@dataclass
class SemiDenseTruth:
    """The recording's semi-dense points: as written, after the MPS filter, and their clean positions."""

    points: SemiDensePoints  # every point, as written to the MPS points file
    filtered: SemiDensePoints  # the points passing the MPS filter (noisy positions)
    clean_world: Tensor  # [M, 3] float64 noise-free world positions of the filtered points
    noisy_world: Tensor  # [M, 3] float64 recorded (noisy) world positions of the filtered points


def _semidense_truth(config: SimConfig, scene, trajectory: Trajectory, clocks: FrameClocks) -> SemiDenseTruth:
    """Surface samples seen from (up to ~64) device positions at the true frame times, with SLAM noise."""
    frame_times_true = clocks.read_start_cam_ns + clocks.true_offset_ns
    positions = trajectory.pose(torch.from_numpy(frame_times_true[:: max(1, config.n_frames // 64)]))[:, :3, 3]
    semidense, clean_points = make_semidense_points(scene, positions, config.n_semidense_points, config.seed)
    sd_filtered = semidense.filtered()
    keep_mask = ((semidense.inv_dist_std < SEMIDENSE_NOISE.max_inv_dist_std)
                 & (semidense.dist_std < SEMIDENSE_NOISE.max_dist_std))
    return SemiDenseTruth(points=semidense, filtered=sd_filtered, clean_world=torch.from_numpy(clean_points[keep_mask]),
                          noisy_world=torch.from_numpy(sd_filtered.points_world))


@dataclass
class CaptureSetup:
    """What every frame of a recording shares, built once by `build_capture_setup`."""

    config: SimConfig
    device: DeviceProfile
    compute: torch.device  # where rays are cast; formation and files stay on the CPU
    cals: CalibrationSet  # true, online, factory
    scene: object
    trajectory: Trajectory  # T_world_device(t_ns)
    clocks: FrameClocks
    raw: RawCamera  # the true raw fisheye camera
    photometric: PhotometricTruth
    rigs: dict[str, tuple[Rectification, Pinhole]]  # calibration name -> its rectified stream's rig
    truth_rays: OnlineTruthRays
    metadata_wrong_frames: set[int]  # frames whose recorded exposure is wrong (hidden)
    semidense: SemiDenseTruth
    streams: dict[str, str]  # calibration name -> stream folder name

    def calibrations(self) -> tuple[tuple[str, CameraCalibration], ...]:
        """(("online", online calibration), ("factory", factory calibration)): the recorded streams."""
        return (("online", self.cals.online), ("factory", self.cals.factory))


def build_capture_setup(config: SimConfig) -> CaptureSetup:
    """Device, calibrations, scene, trajectory, clocks, raw camera, formation, rigs, hidden frames, semi-dense points."""
    from egobench.sim.camera_calibration import make_calibrations
    from egobench.sim.world import make_scene

    dev = get_device(config.device_name)
    compute = config.compute_torch_device()
    cals = make_calibrations(config)
    scene = make_scene(config.kind, config.seed, sun_scale=config.sun_scale, grain=config.grain)
    trajectory = _device_motion(config, dev, scene)
    clocks = _frame_clocks(config, dev, trajectory, cals.true)
    rigs = {name: _rig(cal, config.rectified_size, config.focal_ratio())
            for name, cal in (("online", cals.online), ("factory", cals.factory))}
    raw = RawCamera.build(cals.true, config.pixel_samples)
    if config.raw_roi:
        raw = raw.restricted_to(sampled_raw_pixels([rect for rect, _ in rigs.values()], raw.valid.shape),
                                meter=sampled_raw_pixels([rigs["online"][0]], raw.valid.shape))
    H_raw, W_raw = raw.valid.shape
    if config.readout_window == "view":
        raw = dataclasses.replace(raw, readout_rows=view_readout_rows(rigs["online"][0], (H_raw, W_raw)))
    photometric = _photometric_truth(config, dev, cals.true, (H_raw, W_raw))
    truth_rays = _online_truth_rays(*rigs["online"], raw.readout_rows)
    wrong = _metadata_wrong_frames(config)
    semidense = _semidense_truth(config, scene, trajectory, clocks)
    return CaptureSetup(config=config, device=dev, compute=compute, cals=cals, scene=scene, trajectory=trajectory,
                        clocks=clocks, raw=raw, photometric=photometric, rigs=rigs, truth_rays=truth_rays,
                        metadata_wrong_frames=wrong, semidense=semidense, streams=stream_names(config))


# ----------------------------------------------------------------------------------------
# what the frames accumulate and carry over (restored on resume)
# ----------------------------------------------------------------------------------------
@dataclass
class CaptureRun:
    """The records the frames accumulate and the state each frame hands to the next."""

    result: CaptureResult
    auto_exposure: AutoExposureState
    noise_generator: torch.Generator
    frames_out: dict[str, list[dict]]  # calibration name -> transforms.json frame entries
    calib_lines: list[CalibrationRecord]  # the online calibration per frame (with its tracking timestamp)
    truth_frames: list[dict]  # truth.json frame records
    elapsed_before_s: float = 0.0  # simulation time of the earlier runs of a resumed recording


def _noise_generator(config: SimConfig) -> torch.Generator:
    """The noise generator at the recording's start."""
    return torch.Generator().manual_seed(int(config.seed) * 7919 + 17)


def _restore_run(setup: CaptureSetup, out_dir: Path, states: list[dict]) -> CaptureRun:
    """A fresh run, advanced past the frames earlier runs completed (`states`: their state records in order)."""
    from egobench.sim.camera_calibration import calibration_record

    config = setup.config
    run = CaptureRun(result=CaptureResult(path=out_dir, n_frames=config.n_frames, time_s=0.0),
                     auto_exposure=AutoExposureState(device=setup.device, protocol=config.protocol,
                                                     fixed_exposure_s=config.exposure_s, fixed_gain=config.gain),
                     noise_generator=_noise_generator(config), frames_out={"online": [], "factory": []},
                     calib_lines=[], truth_frames=[])
    online_record = calibration_record(setup.cals.online) if states else None
    for st in states:
        for name in ("online", "factory"):
            run.frames_out[name].append(st["frames_out"][name])
        run.calib_lines.append(dataclasses.replace(online_record, tracking_timestamp_us=st["tracking_timestamp_us"]))
        _record_truth(run, st["truth"])
    if states:
        last = states[-1]
        run.auto_exposure.log_eg = last["auto_exposure"]["log_eg"]
        held = last["auto_exposure"]["held"]
        run.auto_exposure.held = None if held is None else (float(held[0]), float(held[1]))
        _decode_generator(run.noise_generator, last["noise_generator"])
        run.elapsed_before_s = float(last["elapsed_s"])
    run.result.resumed_from = len(states)
    return run


def _record_truth(run: CaptureRun, truth: dict) -> None:
    """Append a frame's truth record and its summary (temporal samples, exposure, gain) to the run."""
    run.truth_frames.append(truth)
    run.result.temporal_samples.append(truth["temporal_samples"])
    run.result.exposures_s.append(truth["exposure_true_s"])
    run.result.gains.append(truth["gain"])


def _frame_state(run: CaptureRun, k: int, config_hash: str, t_begin: float) -> dict:
    """The state file of frame k: what later frames depend on (written last, after the frame's files)."""
    return {
        "frame": k, "config_hash": config_hash,
        "frames_out": {name: run.frames_out[name][-1] for name in ("online", "factory")},
        "tracking_timestamp_us": run.calib_lines[-1].tracking_timestamp_us, "truth": run.truth_frames[-1],
        "auto_exposure": {"log_eg": run.auto_exposure.log_eg,
                          "held": None if run.auto_exposure.held is None else list(run.auto_exposure.held)},
        "noise_generator": _encode_generator(run.noise_generator),
        "elapsed_s": run.elapsed_before_s + time.perf_counter() - t_begin,
    }


# ----------------------------------------------------------------------------------------
# one frame
# ----------------------------------------------------------------------------------------
@dataclass
class FrameExposure:
    """A frame's exposure as chosen from its preview (auto-exposure and the temporal sample count)."""

    t_mid_ns: int  # device-clock time of the middle raw row's read start (preview and visibility time)
    median_luminance: float  # median preview luminance (0 without a preview hit)
    exposure_true_s: float
    gain: float
    motion_px: float  # largest raw-pixel motion of preview points during the exposure
    temporal_samples: int  # S, paired with the raw camera's sub-pixel positions


def _expose_frame(setup: CaptureSetup, auto_exposure: AutoExposureState, read_start_true_ns: int) -> FrameExposure:
    """Preview cast at mid-frame -> auto-exposure step (exposure, gain) and the adaptive temporal samples."""
    raw, readout_true = setup.raw, setup.clocks.readout_true_s
    t_mid = read_start_true_ns + int(round(readout_true * 0.5e9))
    lum, pts, _ = preview(setup.scene, setup.trajectory, raw, t_mid, device=setup.compute)
    median_lum = float(lum.median()) if lum.numel() else 0.0
    exposure_true, gain = auto_exposure.step(median_lum)
    motion_px = motion_during_exposure_px(setup.trajectory, raw, pts, read_start_true_ns, exposure_true, readout_true)
    S = paired_temporal_samples(choose_temporal_samples(setup.config, motion_px), raw.pixel_samples)
    return FrameExposure(t_mid_ns=t_mid, median_luminance=median_lum, exposure_true_s=exposure_true, gain=gain,
                         motion_px=motion_px, temporal_samples=S)


def _form_raw_image(setup: CaptureSetup, irradiance: Tensor, exposure_s: float, gain: float,
                    generator: torch.Generator) -> np.ndarray:
    """Clean irradiance [H_raw, W_raw, 3] -> the recorded raw image [H_raw, W_raw, 3] uint8 (noise drawn from `generator`)."""
    config, photometric = setup.config, setup.photometric
    display = photometric.formation.simulate(irradiance, exposure_s=exposure_s, gain=gain,
                                             sensitivity=setup.device.sensitivity, vignette=photometric.vignette_raw,
                                             white_balance=photometric.white_balance,
                                             noise=photometric.noise_model if config.noise else None,
                                             generator=generator)
    raw8 = _to_uint8(display)
    raw8[~setup.raw.valid.numpy()] = 0
    if config.jpeg:
        raw8 = _jpeg(raw8, config.jpeg_quality)
    return raw8


@dataclass
class RawFrame:
    """One captured raw frame and how it was exposed."""

    index: int
    read_start_true_ns: int  # device-clock read start under the true time offset
    exposure: FrameExposure
    exposure_recorded_s: float  # what the metadata states (wrong on the hidden metadata-error frames)
    irradiance_raw: Tensor  # [H_raw, W_raw, 3] float32 clean linear irradiance
    image_raw_01: Tensor  # [H_raw, W_raw, 3] float32 recorded 8-bit raw image / 255


def capture_raw_frame(setup: CaptureSetup, run: CaptureRun, k: int, partial: Path) -> RawFrame:
    """Frame k's raw capture: preview and auto-exposure, rolling-shutter irradiance, formation (raw/ PNG if asked)."""
    from egobench.data.transforms import write_png

    config = setup.config
    read_start_true = setup.clocks.read_start_true_ns(k)
    exp = _expose_frame(setup, run.auto_exposure, read_start_true)
    irr = capture_irradiance(setup.scene, setup.trajectory, setup.raw, read_start_true, exp.exposure_true_s,
                             setup.clocks.readout_true_s, exp.temporal_samples, device=setup.compute)
    raw8 = _form_raw_image(setup, irr, exp.exposure_true_s, exp.gain, run.noise_generator)
    if config.write_raw:
        write_png(partial / "raw" / f"{k:05d}.png", raw8)
    raw_f = torch.from_numpy(raw8).to(torch.float32) / 255.0
    exposure_recorded = (exp.exposure_true_s * (1.0 + config.exposure_metadata_error)
                         if k in setup.metadata_wrong_frames else exp.exposure_true_s)
    return RawFrame(index=k, read_start_true_ns=read_start_true, exposure=exp, exposure_recorded_s=exposure_recorded,
                    irradiance_raw=irr, image_raw_01=raw_f)


def truth_depth_normal(setup: CaptureSetup, read_start_true_ns: int, exposure_true_s: float) -> tuple[Tensor, Tensor]:
    """Online rectified camera: depth z [h, w] float64 (m, 0 = none), normals [h, w, 3] (camera frame, 0 = none).

    Each pixel is cast from the true pose at its own mid-exposure time (its raw source row's)."""
    rays = setup.truth_rays
    gt_valid = rays.valid
    t_pix = (read_start_true_ns
             + torch.round((rays.row_time_ratio * setup.clocks.readout_true_s + exposure_true_s / 2) * 1e9).to(torch.int64))
    Tp = camera_poses(setup.trajectory, _as_T(setup.cals.online), t_pix[gt_valid])  # [n, 4, 4]
    d_cam = rays.rays_cam[gt_valid]  # [n, 3] z = 1
    d_world = torch.einsum("nij,nj->ni", Tp[:, :3, :3], d_cam)
    norm = d_world.norm(dim=-1, keepdim=True)
    t_hit, n_world, is_hit = geometry_cast(setup.scene, Tp[:, :3, 3].to(torch.float32).contiguous(),
                                           (d_world / norm).to(torch.float32).contiguous(), device=setup.compute)
    z = t_hit / norm[:, 0]
    z = torch.where(is_hit & torch.isfinite(z), z, torch.zeros_like(z))
    n_cam = torch.einsum("nji,nj->ni", Tp[:, :3, :3], n_world)
    n_cam = torch.where(is_hit[:, None], n_cam, torch.zeros_like(n_cam))
    depth_map = torch.zeros(gt_valid.shape, dtype=torch.float64)
    depth_map[gt_valid] = z
    normal_map = torch.zeros(gt_valid.shape + (3,), dtype=torch.float64)
    normal_map[gt_valid] = n_cam
    return depth_map, normal_map


def _write_ground_truth(setup: CaptureSetup, frame: RawFrame, partial: Path) -> None:
    """Frame k's ground-truth files (float16): irradiance rectified like the online image, depth, normals."""
    k = frame.index
    rect_online = setup.rigs["online"][0]
    gt_irr = rect_online.warp(frame.irradiance_raw).clamp(0, FLOAT16_MAX)
    np.save(partial / "ground_truth" / "radiance" / f"{k:05d}.npy", gt_irr.to(torch.float16).numpy())
    depth_map, normal_map = truth_depth_normal(setup, frame.read_start_true_ns, frame.exposure.exposure_true_s)
    np.save(partial / "ground_truth" / "depth" / f"{k:05d}.npy", depth_map.to(torch.float16).numpy())
    np.save(partial / "ground_truth" / "normal" / f"{k:05d}.npy", normal_map.to(torch.float16).numpy())


def visible_semidense(setup: CaptureSetup, t_ns: int) -> Tensor:
    """[M] bool: filtered semi-dense points not occluded from the true camera centre at `t_ns`."""
    from egobench.geometry import se3_inverse, transform_points

    clean = setup.semidense.clean_world
    T_mid = camera_poses(setup.trajectory, _as_T(setup.cals.true), [t_ns])[0]
    visible = torch.zeros(clean.shape[0], dtype=torch.bool)
    if clean.shape[0]:
        vec = clean - T_mid[:3, 3]
        dist = vec.norm(dim=-1)
        pc = transform_points(se3_inverse(T_mid), clean)
        front = pc[:, 2] > 0.05
        if bool(front.any()):
            t_vis, _, h_vis = geometry_cast(setup.scene,
                                            T_mid[:3, 3].to(torch.float32).expand(int(front.sum()), 3).contiguous(),
                                            (vec[front] / dist[front, None]).to(torch.float32).contiguous())
            ok = h_vis & (t_vis >= dist[front] - (0.02 + 0.01 * dist[front]))
            visible[front] = ok
    return visible


def stream_frame_times_ns(cal: CameraCalibration, read_start_cam_ns: int, readout_stated_s: float,
                          exposure_recorded_s: float) -> tuple[int, int, int]:
    """A stream's (read start, read end, mid-exposure timestamp) of a frame, device clock ns, by its calibration."""
    offset_ns = int(round(cal.time_offset_s * 1e9))
    read_start = int(read_start_cam_ns + offset_ns)
    read_end = read_start + int(round(readout_stated_s * 1e9))
    timestamp = read_start + int(round((readout_stated_s / 2 + exposure_recorded_s / 2) * 1e9))
    return read_start, read_end, timestamp


def _write_sparse_depth(setup: CaptureSetup, rig: tuple[Rectification, Pinhole], T_world_camera: Tensor, visible: Tensor, path: Path) -> None:
    """The visible filtered semi-dense points (noisy) projected into a rig's pinhole -> its sparse depth file."""
    from egobench.data.transforms import write_sparse_depth
    from egobench.geometry import se3_inverse, transform_points

    rect, pin = rig
    sd_filtered = setup.semidense.filtered
    pcam = transform_points(se3_inverse(T_world_camera), setup.semidense.noisy_world[visible])
    uv, okp = pin.project(pcam)
    inside = okp & (uv[:, 0] >= 0) & (uv[:, 0] <= pin.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= pin.height - 1)
    iu = uv[:, 0].round().long().clamp(0, pin.width - 1)
    iv = uv[:, 1].round().long().clamp(0, pin.height - 1)
    inside &= rect.valid[iv, iu]
    idx = visible.nonzero()[:, 0][inside]
    write_sparse_depth(path, uv[inside].numpy(), pcam[inside, 2].numpy(), sd_filtered.inv_dist_std[idx.numpy()],
                       sd_filtered.dist_std[idx.numpy()])


def _write_stream_frame(setup: CaptureSetup, run: CaptureRun, name: str, cal: CameraCalibration, frame: RawFrame,
                        visible: Tensor, partial: Path) -> None:
    """Frame k in the stream of calibration `name`: rectified image, transforms entry, sparse depth (online: calibration line)."""
    from egobench.data.transforms import frame_entry, write_png
    from egobench.sim.camera_calibration import calibration_record

    k = frame.index
    rect, pin = setup.rigs[name]
    stream = partial / setup.streams[name]
    write_png(stream / "images" / f"{k:05d}.png", _to_uint8(rect.warp(frame.image_raw_01)))
    read_start, read_end, timestamp = stream_frame_times_ns(cal, setup.clocks.read_start_cam_ns[k],
                                                            setup.clocks.readout_stated_s, frame.exposure_recorded_s)
    T_dc = _as_T(cal)
    T_wc = camera_poses(setup.trajectory, T_dc, [timestamp])[0]
    run.frames_out[name].append(frame_entry(k, pin, T_dc.numpy(), T_wc.numpy(), timestamp, read_start, read_end,
                                            frame.exposure_recorded_s, frame.exposure.gain))
    _write_sparse_depth(setup, (rect, pin), T_wc, visible, stream / "sparse_depth" / f"{k:05d}.json")
    if name == "online":
        run.calib_lines.append(calibration_record(cal, tracking_timestamp_us=timestamp // 1000))


def _truth_frame_record(setup: CaptureSetup, frame: RawFrame) -> dict:
    """truth.json's record of frame k: clocks, true and recorded exposure, temporal samples, motion."""
    k, exp, P = frame.index, frame.exposure, setup.raw.pixel_samples
    S = exp.temporal_samples
    return {
        "index": k, "camera_read_start_ns": int(setup.clocks.read_start_cam_ns[k]),
        "read_start_true_ns": frame.read_start_true_ns,
        "exposure_true_s": exp.exposure_true_s, "exposure_recorded_s": frame.exposure_recorded_s, "gain": exp.gain,
        "exposure_metadata_wrong": k in setup.metadata_wrong_frames, "temporal_samples": S,
        "rays_per_pixel": S * P if S < P else S,
        "motion_during_exposure_px": exp.motion_px,
        "median_luminance": exp.median_luminance,
    }


def _simulate_frame(setup: CaptureSetup, run: CaptureRun, k: int, partial: Path) -> None:
    """Frame k: raw capture, ground truth, both streams' files, and its records in `run`."""
    frame = capture_raw_frame(setup, run, k, partial)
    _write_ground_truth(setup, frame, partial)
    # visibility of the semi-dense points from the true camera centre at mid-frame
    visible = visible_semidense(setup, frame.exposure.t_mid_ns)
    for name, cal in setup.calibrations():
        _write_stream_frame(setup, run, name, cal, frame, visible, partial)
    _record_truth(run, _truth_frame_record(setup, frame))


# ----------------------------------------------------------------------------------------
# the recording
# ----------------------------------------------------------------------------------------
def _make_folders(config: SimConfig, partial: Path) -> None:
    """The partial folder's MPS folder and per-frame folders (raw/ only when raw frames are written)."""
    from egobench.data.layout import MPS_SLAM

    for sub in (str(MPS_SLAM),) + frame_dirs(config)[1:]:
        (partial / sub).mkdir(parents=True, exist_ok=True)
    if config.write_raw:
        (partial / "raw").mkdir(exist_ok=True)


def _frame_indices(config: SimConfig, first: int, end: int, progress: bool):
    """Frames first..end-1, with a tqdm bar counting from `first` of n_frames when `progress`."""
    from tqdm import tqdm

    iterator = range(first, end)
    if progress:
        iterator = tqdm(iterator, desc=f"simulate {config.recording_name}", unit="frame", initial=first,
                        total=config.n_frames)
    return iterator


def _write_stream_files(setup: CaptureSetup, frames_out: dict[str, list[dict]], partial: Path) -> None:
    """Each stream's camera maps (vignette, valid mask, row time ratio) and transforms.json."""
    from egobench.data.transforms import write_camera_maps, write_transforms

    for name, cal in setup.calibrations():
        rect, pin = setup.rigs[name]
        stream = partial / setup.streams[name]
        write_camera_maps(stream, rect.warp_vignette(calibrated_vignette(cal, setup.device)).numpy(),
                          rect.valid.numpy(), rect.row_time_ratio(setup.raw.readout_rows).numpy())
        write_transforms(stream, frames_out[name], camera_label=setup.device.label,
                         extra={"calibration": name, "readout_s": setup.clocks.readout_stated_s,
                                "pixel_centre_convention": "integer (projectaria): cx = (W - 1) / 2 is centred"})


def _write_mps_files(setup: CaptureSetup, calib_lines: list[CalibrationRecord], partial: Path) -> None:
    """Trajectory, semi-dense points, online calibration (MPS folder), factory calibration, per-stream links."""
    from egobench.data.layout import (FACTORY_CALIBRATION_FILE, MPS_SLAM, ONLINE_CALIBRATION_FILE, POINTS_FILE,
                                      TRAJECTORY_FILE, link_mps_files)
    from egobench.data.mps import write_calibration_json, write_online_calibration, write_semidense_points
    from egobench.sim.camera_calibration import calibration_record

    mps_dir = partial / MPS_SLAM
    setup.trajectory.to_mps_csv(mps_dir / TRAJECTORY_FILE)
    write_semidense_points(mps_dir / POINTS_FILE, setup.semidense.points)
    write_online_calibration(mps_dir / ONLINE_CALIBRATION_FILE, calib_lines)
    write_calibration_json(partial / FACTORY_CALIBRATION_FILE, calibration_record(setup.cals.factory))
    for name in ("online", "factory"):  # the MPS files inside each stream folder, as relative symlinks
        link_mps_files(partial / setup.streams[name], mps_dir)


def _truth_json(setup: CaptureSetup, truth_frames: list[dict]) -> dict:
    """ground_truth/truth.json: the true calibration, calibration errors, hidden effects, units, frame records."""
    from egobench.sim.camera_calibration import calibration_record

    config, dev, cals, clocks = setup.config, setup.device, setup.cals, setup.clocks
    noise_model = setup.photometric.noise_model
    return {
        "true_calibration": calibration_record(cals.true).to_json(),
        "calibration_errors": cals.perturbations,
        "hidden_effects": {
            "readout_scale": config.readout_scale, "readout_true_s": clocks.readout_true_s,
            "readout_stated_s": clocks.readout_stated_s,
            "time_offset_s": config.time_offset_s, "time_offset_true_s": cals.true.time_offset_s,
            "exposure_s": config.exposure_s, "vignette_strength": config.vignette_strength,
            "response_gamma": setup.photometric.gamma, "white_balance": list(config.white_balance),
            "exposure_metadata_error": config.exposure_metadata_error,
            "exposure_metadata_frames": sorted(setup.metadata_wrong_frames),
            "noise": config.noise, "full_well_e": noise_model.full_well_e, "read_noise_e": noise_model.read_noise_e,
            "noise_std_factor": config.noise_std_factor, "distortion_k0_delta": config.distortion_k0_delta,
        },
        "device": dev.name, "sensitivity": dev.sensitivity, "vignette_corner": dev.vignette_corner,
        "vignette_power": dev.vignette_power, "exposure_protocol": config.protocol,
        "gt_units": {"radiance": "clean linear irradiance (world radiance units, cd/m^2-like), exposure-averaged, "
                                 "rectified like the online stream's images (float16, clipped at 65000)",
                     "depth": "z in the online rectified camera, metres, 0 = no hit / invalid (float16)",
                     "normal": "unit normal in the online camera frame, 0 = none (float16)"},
        "frames": truth_frames,
    }


def _recording_json(setup: CaptureSetup, result: CaptureResult) -> dict:
    """recording.json: name, kind, device, motion, seed, SimConfig, sizes, fps, time and temporal-sample summary."""
    import egobench

    config, dev = setup.config, setup.device
    H_raw, W_raw = setup.raw.valid.shape
    return {
        "name": config.recording_name, "scene_kind": config.kind, "device": dev.name, "motion": config.motion,
        "seed": config.seed, "sim_config": config.to_dict(), "egobench_version": egobench.__version__,
        "raw_size": [W_raw, H_raw], "rectified_size": [config.rectified_size, config.rectified_size],
        "fps": dev.fps, "simulation_time_s": result.time_s,
        "temporal_samples": {"min": min(result.temporal_samples), "max": max(result.temporal_samples),
                             "mean": float(np.mean(result.temporal_samples))},
    }


def _write_recording_files(setup: CaptureSetup, run: CaptureRun, partial: Path, t_begin: float) -> None:
    """The recording-level files once every frame is done: streams, MPS, truth.json, recording.json."""
    from egobench.io_utils import write_json

    _write_stream_files(setup, run.frames_out, partial)
    _write_mps_files(setup, run.calib_lines, partial)
    run.result.time_s = run.elapsed_before_s + time.perf_counter() - t_begin
    write_json(partial / "ground_truth" / "truth.json", _truth_json(setup, run.truth_frames))
    write_json(partial / "recording.json", _recording_json(setup, run.result))


def _simulate_into(config: SimConfig, out_dir: Path, partial: Path, chash: str, states: list[dict], resuming: bool,
                   progress: bool, stop_after: int | None, t_begin: float) -> CaptureResult:
    """The body of `simulate_recording`: frames len(states).. into `partial`, then the recording files."""
    from egobench.io_utils import write_json

    setup = build_capture_setup(config)
    if resuming:  # frames already completed by an earlier run: their records and the state after the last one
        _drop_frames_from(partial, len(states), frame_dirs(config))
    run = _restore_run(setup, out_dir, states)
    _make_folders(config, partial)
    end = config.n_frames if stop_after is None else min(config.n_frames, stop_after)
    for k in _frame_indices(config, len(states), end, progress):
        _simulate_frame(setup, run, k, partial)
        # the frame's state, written last: a frame without it is redone by a resumed run
        write_json(_frame_state_path(partial, k), _frame_state(run, k, chash, t_begin), indent=None)
    if end < config.n_frames:  # stopped by stop_after: the partial folder stays for a later run
        run.result.complete, run.result.path = False, partial
        run.result.time_s = run.elapsed_before_s + time.perf_counter() - t_begin
        return run.result
    _write_recording_files(setup, run, partial, t_begin)
    _finalise(partial, out_dir)
    return run.result
