"""One frame: what the frames accumulate and carry over (restored on resume), and the capture, formation,
ground truth and stream files of one frame."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.camera.pinhole import Pinhole
from egobench.data.mps import CameraCalibration
from egobench.data import transforms  # write_sparse_depth looked up per call (a test makes it fail midway)
from egobench.data.transforms import frame_entry, write_png
from egobench.geometry import se3_inverse, transform_points
from egobench.sim.camera_calibration import calibration_record
from egobench.sim.capture.auto_exposure import AutoExposureState
from egobench.sim.capture.raw import (
    FLOAT16_MAX,
    as_transform,
    camera_poses,
    capture_irradiance,
    choose_temporal_samples,
    geometry_cast,
    motion_during_exposure_px,
    paired_temporal_samples,
    preview,
)
from egobench.sim.capture.resume import decode_generator, encode_generator
from egobench.sim.capture.setup import CaptureResult, CaptureSetup, jpeg_roundtrip, to_uint8
from egobench.sim.config import SimConfig

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    from egobench.camera import Rectification
    from egobench.data.mps import CalibrationRecord


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


def restore_run(setup: CaptureSetup, out_dir: Path, states: list[dict]) -> CaptureRun:
    """A fresh run, advanced past the frames earlier runs completed (`states`: their state records in order)."""
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
        decode_generator(run.noise_generator, last["noise_generator"])
        run.elapsed_before_s = float(last["elapsed_s"])
    run.result.resumed_from = len(states)
    return run


def _record_truth(run: CaptureRun, truth: dict) -> None:
    """Append a frame's truth record and its summary (temporal samples, exposure, gain) to the run."""
    run.truth_frames.append(truth)
    run.result.temporal_samples.append(truth["temporal_samples"])
    run.result.exposures_s.append(truth["exposure_true_s"])
    run.result.gains.append(truth["gain"])


def frame_state(run: CaptureRun, k: int, config_hash: str, t_begin: float) -> dict:
    """The state file of frame k: what later frames depend on (written last, after the frame's files)."""
    return {
        "frame": k, "config_hash": config_hash,
        "frames_out": {name: run.frames_out[name][-1] for name in ("online", "factory")},
        "tracking_timestamp_us": run.calib_lines[-1].tracking_timestamp_us, "truth": run.truth_frames[-1],
        "auto_exposure": {"log_eg": run.auto_exposure.log_eg,
                          "held": None if run.auto_exposure.held is None else list(run.auto_exposure.held)},
        "noise_generator": encode_generator(run.noise_generator),
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
    """Preview cast at mid-frame -> auto-exposure step (exposure, gain) and the adaptive temporal samples.

    The preview is cast on the CPU whatever `compute_device` is: the exposure and sample-count
    decisions are discontinuous in it (a 1e-6 relative change of the median luminance moved 14 % of
    a frame's pixels by up to 5 levels), so a GPU's float rounding must not reach them. It is
    PREVIEW_GRID^2 rays: no cost worth a device."""
    raw, readout_true = setup.raw, setup.clocks.readout_true_s
    t_mid = read_start_true_ns + int(round(readout_true * 0.5e9))
    lum, pts, _ = preview(setup.scene, setup.trajectory, raw, t_mid, device="cpu")
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
    raw8 = to_uint8(display)
    raw8[~setup.raw.valid.numpy()] = 0
    if config.jpeg:
        raw8 = jpeg_roundtrip(raw8, config.jpeg_quality)
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


def truth_depth_normal(setup: CaptureSetup, read_start_true_ns: int, exposure_true_s: float
                       ) -> tuple[Tensor, Tensor, Tensor | None]:
    """Online rectified camera: depth z [h, w] float64 (m, 0 = none), normals [h, w, 3] (camera frame, 0 = none),
    and where the scene has a `Scene.foreground_box`, the foreground [h, w] bool (the surface point in the box;
    else None).

    Each pixel is cast from the true pose at its own mid-exposure time (its raw source row's)."""
    rays = setup.truth_rays
    gt_valid = rays.valid
    t_pix = (read_start_true_ns
             + torch.round((rays.row_time_ratio * setup.clocks.readout_true_s + exposure_true_s / 2) * 1e9).to(torch.int64))
    Tp = camera_poses(setup.trajectory, as_transform(setup.cals.online), t_pix[gt_valid])  # [n, 4, 4]
    d_cam = rays.rays_cam[gt_valid]  # [n, 3] z = 1
    d_world = pm.vecdot(Tp[:, :3, :3], d_cam[:, None, :])
    norm = d_world.norm(dim=-1, keepdim=True)
    t_hit, n_world, is_hit = geometry_cast(setup.scene, Tp[:, :3, 3].to(torch.float32).contiguous(),
                                           (d_world / norm).to(torch.float32).contiguous(), device=setup.compute)
    z = t_hit / norm[:, 0]
    z = torch.where(is_hit & torch.isfinite(z), z, torch.zeros_like(z))
    n_cam = pm.vecdot(Tp[:, :3, :3].transpose(-1, -2), n_world[:, None, :])
    n_cam = torch.where(is_hit[:, None], n_cam, torch.zeros_like(n_cam))
    depth_map = torch.zeros(gt_valid.shape, dtype=torch.float64)
    depth_map[gt_valid] = z
    normal_map = torch.zeros(gt_valid.shape + (3,), dtype=torch.float64)
    normal_map[gt_valid] = n_cam
    return depth_map, normal_map, _foreground(setup.scene, Tp[:, :3, 3], d_world / norm, t_hit, is_hit, gt_valid)


def _foreground(scene, origins: Tensor, dirs: Tensor, t_hit: Tensor, is_hit: Tensor, valid: Tensor) -> Tensor | None:
    """[h, w] bool: the pixels whose surface point lies in the scene's foreground box (None without one)."""
    if scene.foreground_box is None:
        return None
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in scene.foreground_box)
    t = torch.where(is_hit, t_hit.to(torch.float64), torch.zeros_like(t_hit, dtype=torch.float64))
    p = origins.to(torch.float64) + t[:, None] * dirs.to(torch.float64)
    inside = is_hit & ((p >= lo) & (p <= hi)).all(dim=-1)
    out = torch.zeros(valid.shape, dtype=torch.bool)
    out[valid] = inside
    return out


def _write_ground_truth(setup: CaptureSetup, frame: RawFrame, partial: Path) -> None:
    """Frame k's ground-truth files (float16): irradiance rectified like the online image, depth, normals."""
    k = frame.index
    rect_online = setup.rigs["online"][0]
    gt_irr = rect_online.warp(frame.irradiance_raw).clamp(0, FLOAT16_MAX)
    np.save(partial / "ground_truth" / "radiance" / f"{k:05d}.npy", gt_irr.to(torch.float16).numpy())
    depth_map, normal_map, foreground = truth_depth_normal(setup, frame.read_start_true_ns,
                                                           frame.exposure.exposure_true_s)
    np.save(partial / "ground_truth" / "depth" / f"{k:05d}.npy", depth_map.to(torch.float16).numpy())
    np.save(partial / "ground_truth" / "normal" / f"{k:05d}.npy", normal_map.to(torch.float16).numpy())
    if foreground is not None:  # an object capture: the surfaces Table 2's geometry is scored on
        (partial / "ground_truth" / "foreground").mkdir(exist_ok=True)
        np.save(partial / "ground_truth" / "foreground" / f"{k:05d}.npy", foreground.numpy())


def visible_semidense(setup: CaptureSetup, t_ns: int) -> Tensor:
    """[M] bool: filtered semi-dense points not occluded from the true camera centre at `t_ns`."""
    clean = setup.semidense.clean_world
    T_mid = camera_poses(setup.trajectory, as_transform(setup.cals.true), [t_ns])[0]
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
    rect, pin = rig
    sd_filtered = setup.semidense.filtered
    pcam = transform_points(se3_inverse(T_world_camera), setup.semidense.noisy_world[visible])
    uv, okp = pin.project(pcam)
    inside = okp & (uv[:, 0] >= 0) & (uv[:, 0] <= pin.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= pin.height - 1)
    iu = uv[:, 0].round().long().clamp(0, pin.width - 1)
    iv = uv[:, 1].round().long().clamp(0, pin.height - 1)
    inside &= rect.valid[iv, iu]
    idx = visible.nonzero()[:, 0][inside]
    transforms.write_sparse_depth(path, uv[inside].numpy(), pcam[inside, 2].numpy(),
                                  sd_filtered.inv_dist_std[idx.numpy()], sd_filtered.dist_std[idx.numpy()])


def _write_stream_frame(setup: CaptureSetup, run: CaptureRun, name: str, cal: CameraCalibration, frame: RawFrame,
                        visible: Tensor, partial: Path) -> None:
    """Frame k in the stream of calibration `name`: rectified image, transforms entry, sparse depth (online: calibration line)."""
    k = frame.index
    rect, pin = setup.rigs[name]
    stream = partial / setup.streams[name]
    write_png(stream / "images" / f"{k:05d}.png", to_uint8(rect.warp(frame.image_raw_01)))
    read_start, read_end, timestamp = stream_frame_times_ns(cal, setup.clocks.read_start_cam_ns[k],
                                                            setup.clocks.readout_stated_s, frame.exposure_recorded_s)
    T_dc = as_transform(cal)
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


def simulate_frame(setup: CaptureSetup, run: CaptureRun, k: int, partial: Path) -> None:
    """Frame k: raw capture, ground truth, both streams' files, and its records in `run`."""
    frame = capture_raw_frame(setup, run, k, partial)
    _write_ground_truth(setup, frame, partial)
    # visibility of the semi-dense points from the true camera centre at mid-frame
    visible = visible_semidense(setup, frame.exposure.t_mid_ns)
    for name, cal in setup.calibrations():
        _write_stream_frame(setup, run, name, cal, frame, visible, partial)
    _record_truth(run, _truth_frame_record(setup, frame))
