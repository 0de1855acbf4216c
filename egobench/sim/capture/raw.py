"""Raw rolling-shutter capture: device trajectory, camera poses, chunked ray casting, the raw camera, sub-
pixel and temporal sample schedules, the exposure integral of a frame, its preview and the motion
estimate."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.camera.rectify import readout_range
from egobench.data.mps import CameraCalibration
from egobench.geometry import Trajectory, make_pose, se3_inverse, transform_points
from egobench.model.formation import exposure_sample_times_ns
from egobench.sim.config import SimConfig
from egobench.sim.devices import DeviceProfile
from egobench.sim.world import luminance

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    pass


#: Rays per Scene.cast call (bounds memory) on the CPU, and on a GPU. One Scene.cast is ~16k torch
#: ops (profiled on the CPU), so on a GPU a call costs tens of ms of launches whatever its size: at
#: 2^18 rays a paper-resolution frame (2880^2 raw x up to 32 samples) took 26-54 s on an H200, about
#: what ~1000 calls' launch overhead predicts. 2^22 rays peak at ~1-1.6 GB (250-385 B/ray, CPU RSS).
CAST_CHUNK = 1 << 16
CAST_CHUNK_GPU = 1 << 22


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
    R_dc = device.T_device_camera()[:3, :3]
    T_look_device = make_pose(R_dc.T, torch.zeros(3, dtype=torch.float64))
    return Trajectory(look_trajectory.t_ns, pm.matmul(look_trajectory.T_world_device, T_look_device))


def as_transform(cal: CameraCalibration) -> Tensor:  # [4, 4] float64
    return torch.as_tensor(cal.T_device_camera, dtype=torch.float64)


def camera_poses(trajectory, T_device_camera: Tensor, t_ns) -> Tensor:
    """T_world_camera [B, 4, 4] = trajectory.pose(t_ns) @ T_device_camera."""
    return pm.matmul(trajectory.pose(t_ns), T_device_camera)


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
    H, W = raw.valid.shape
    P = int(raw.pixel_samples)
    S = paired_temporal_samples(int(n_samples), P)
    t_rows = row_start_times_ns(read_start_ns, readout_s, H, raw.readout_rows)  # [H]
    t = exposure_sample_times_ns(t_rows, exposure_s, S)  # [H, S] int64
    T = camera_poses(trajectory, as_transform(raw.calibration), t.reshape(-1)).reshape(H, S, 4, 4)
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
        d = pm.vecdot(R[r0:r1, :, None], rays[sub_idx, r0:r1, c0:c1].permute(1, 0, 2, 3)[..., None, :])  # [h, n, w, 3]
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
    T = camera_poses(trajectory, as_transform(raw.calibration), [t_ns])[0]
    d = pm.matmul(rays, T[:3, :3].T).to(torch.float32)
    o = T[:3, 3].to(torch.float32).expand_as(d).contiguous()
    hit = scene.cast(o.to(device), d.to(device))
    hit = type(hit)(**{k: v.cpu() if isinstance(v, Tensor) else v for k, v in vars(hit).items()})
    lum = luminance(hit.radiance.to(torch.float32))
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
    T = camera_poses(trajectory, as_transform(raw.calibration), torch.cat([t_rows, t_end]))
    pc = transform_points(se3_inverse(T)[:, None], points_world[None])  # [6, P, 3]
    uv, ok = cam.project(pc)
    disp = (uv[3:] - uv[:3]).norm(dim=-1)
    good = ok[3:] & ok[:3] & torch.isfinite(disp)
    return float(disp[good].max()) if bool(good.any()) else 0.0


def choose_temporal_samples(config: SimConfig, motion_px: float) -> int:
    if config.temporal_samples is not None:
        return int(config.temporal_samples)
    return int(min(config.max_temporal_samples, max(1, math.ceil(motion_px / config.max_sample_step_px))))
