"""Where the prediction comes from: (a) the simulator's world re-cast under the model's assumptions
("simulation vs measurement", fast and exactly controlled), or (b) a trained run's renders.

Both return a `Sources` bundle: measured [F, H, W, 3], predicted [F, H, W, 3] (display values)
and the `DiagnosisContext` (per-frame exposure and gain, R(u), valid mask, image velocity from
depth and the trajectory, assumed gamma and noise, rectifying lens coefficients).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from egobench.camera import Rectification
from egobench.data import load_recording
from egobench.data.coverage import training_view_count
from egobench.data.layout import FACTORY_CALIBRATION_FILE, MPS_SLAM, ONLINE_CALIBRATION_FILE, recording_root
from egobench.data.mps import read_calibration_json, read_online_calibration
from egobench.io_utils import read_json
from egobench.model.formation import (
    FormationConfig,
    FormationModel,
    GammaResponse,
    PoissonGaussianNoise,
    quantise,
    radial_vignette,
)
from egobench.model.predict import RunRenderer
from egobench.residual.signatures import DiagnosisContext
from egobench.sim.camera_calibration import make_calibrations
from egobench.sim.capture import RawCamera, capture_irradiance, sampled_raw_pixels, view_readout_rows
from egobench.sim.capture.setup import rectification_rig
from egobench.sim.config import SimConfig
from egobench.sim.devices import get_device
from egobench.sim.world import make_scene
from egobench.train.checkpoint import load_trained_run

#: Time step of the finite-difference image velocity, ns (1 ms).
VELOCITY_DT_NS = 1_000_000
#: Pixels whose poses `pixel_velocity` evaluates at once (~80 MB of float64 poses).
VELOCITY_CHUNK = 1 << 16


@dataclass
class Sources:
    """Measured and predicted frames of one recording plus the context of the diagnosis."""

    measured: np.ndarray  # [F, H, W, 3] display in [0, 1]
    predicted: np.ndarray  # [F, H, W, 3] display in [0, 1]
    context: DiagnosisContext
    description: str  # where the prediction comes from


def pixel_velocity(recording, frame, depth_m: np.ndarray, t_offset_s: float = 0.0,
                   chunk: int = VELOCITY_CHUNK) -> np.ndarray:
    """Image velocity [H, W, 2] px/s of the static scene at each pixel's model row time.

    depth_m [H, W]: z-depth in the rectified camera at that time (0 = unknown -> velocity 0).
    Each pixel's 3-D point is back-projected with the pose at its row time and re-projected with
    the poses 1 ms earlier and later (central difference on the 1 kHz trajectory). Every pixel has
    its own time, so the poses are evaluated ``chunk`` pixels at a time (per pixel, so the result
    does not depend on ``chunk``; at 2400 px one pass would hold ~7 GB of float64 poses).
    """
    cam = recording.camera
    H, W = depth_m.shape
    R = recording.row_time_ratio.to(torch.float64)
    readout_ns = frame.read_end_ns - frame.read_start_ns
    t_pix = (frame.read_start_ns + torch.round(R * readout_ns + frame.exposure_s * 0.5e9 + t_offset_s * 1e9)).to(torch.int64)
    traj = recording.trajectory
    lo, hi = traj.start_ns + VELOCITY_DT_NS, traj.end_ns - VELOCITY_DT_NS
    t_pix = t_pix.clamp(lo, hi).reshape(-1)
    T_dc = frame.T_device_camera.to(torch.float64)
    rays = cam.unproject(cam.pixel_grid(dtype=torch.float64)).reshape(-1, 3)
    depth = torch.from_numpy(np.asarray(depth_m, dtype=np.float64)).reshape(-1)
    v = torch.empty(H * W, 2, dtype=torch.float64)  # every block written below
    for s in range(0, H * W, chunk):
        v[s:s + chunk] = _velocity_block(traj, cam, T_dc, t_pix[s:s + chunk], rays[s:s + chunk], depth[s:s + chunk])
    v[~(depth > 0)] = 0.0
    return v.reshape(H, W, 2).numpy().astype(np.float32)


def _velocity_block(traj, cam, T_dc, t_pix, rays, depth):
    """[B, 2] px/s for B pixels: rays [B, 3] at depth [B] seen at t_pix [B] ns, central difference."""
    T0 = traj.pose(t_pix) @ T_dc
    X = (T0[:, :3, :3] @ (rays * depth[:, None])[..., None])[..., 0] + T0[:, :3, 3]
    uv = []
    for sign in (-1, 1):
        T = traj.pose(t_pix + sign * VELOCITY_DT_NS) @ T_dc
        Xc = (T[:, :3, :3].transpose(1, 2) @ (X - T[:, :3, 3])[..., None])[..., 0]
        p, _ = cam.project(Xc)
        uv.append(p)
    return (uv[1] - uv[0]) / (2 * VELOCITY_DT_NS * 1e-9)


def _context(recording, frames, velocity, gamma: float, noise, lens_k, meta) -> DiagnosisContext:
    H, W = recording.camera.height, recording.camera.width
    gain = np.array([f.gain for f in frames], dtype=np.float64)
    readout = float(np.median([(f.read_end_ns - f.read_start_ns) * 1e-9 for f in frames]))
    return DiagnosisContext(
        frame_index=np.array([f.index for f in frames]), exposure_s=np.array([f.exposure_s for f in frames]),
        gain=gain, valid=recording.mask.numpy().astype(bool).reshape(H, W),
        row_time_ratio=recording.row_time_ratio.numpy().astype(np.float64),
        principal_point=(recording.camera.cx, recording.camera.cy), focal_px=float(recording.camera.fx),
        readout_s=readout, pixel_velocity_px_s=velocity, gamma_assumed=gamma,
        noise_shot=None if noise is None else gain / noise.full_well_e,
        noise_read=None if noise is None else (gain * noise.read_noise_e / noise.full_well_e) ** 2,
        lens_radial_k=lens_k, stated_vignette=recording.vignette.numpy().astype(np.float64).reshape(H, W), meta=meta,
    )


def _select(frames, max_frames: int | None):
    if max_frames is None or len(frames) <= max_frames:
        return list(frames)
    return list(frames[:max_frames])


def recording_rectification(recording_dir: str | Path, calibration: str, device, rectified):
    """(Rectification raw -> ``rectified`` (the recording's Pinhole), raw valid [H_s, W_s] bool) of the
    calibration the recording's ``calibration`` images were rectified with, or None when the
    recording has no MPS calibration of the device's camera (then the pipeline is unknown).

    Simulated recordings rectify each stream with its own calibration (online: the first line of
    mps/slam/online_calibration.jsonl; factory: factory_calibration.json) onto the stored pinhole,
    without rotation (egobench.sim.capture.setup.rectification_rig)."""
    root = recording_root(recording_dir)
    try:
        if calibration == "factory":
            cal = read_calibration_json(root / FACTORY_CALIBRATION_FILE).camera(device.label)
        else:
            cal = read_online_calibration(root / MPS_SLAM / ONLINE_CALIBRATION_FILE)[0].camera(device.label)
    except (FileNotFoundError, ValueError):
        return None
    src = cal.camera()
    rect = Rectification.build(src, rectified)
    v, u = torch.meshgrid(torch.arange(cal.height, dtype=torch.float64), torch.arange(cal.width, dtype=torch.float64),
                          indexing="ij")
    uv = torch.stack([u, v], -1)
    if hasattr(src, "unproject_checked"):
        rays, ok = src.unproject_checked(uv)
    else:
        rays = src.unproject(uv)
        ok = torch.ones(uv.shape[:2], dtype=torch.bool)
    valid = ok & torch.isfinite(rays).all(-1)
    return rect, valid


def pipeline_noise_reference(
    predicted: np.ndarray,  # [F, H, W, 3] display prediction in the rectified camera
    rect,  # egobench.camera.Rectification raw -> rectified (the measured images' rig)
    raw_valid,  # [H_s, W_s] bool tensor: raw pixels with a valid ray
    noise,  # egobench.model.formation.PoissonGaussianNoise the model assumes
    gain: np.ndarray,  # [F] analog gains of the frames
    gamma: float,  # response gamma of the display values
    seed: int = 0,
) -> np.ndarray:  # [F, H, W, 3] one draw of the assumed noise through the pipeline, display units
    """One draw of the ASSUMED noise through the capture pipeline of a simulated recording, for a
    prediction that exists only in the rectified camera (a trained run's renders).

    The prediction is mapped back into the raw fisheye image (each raw pixel's ray projected into
    the rectified pinhole, bilinear), decoded to linear, given Poisson-Gaussian noise at the
    frame's gain, encoded and quantised to 8 bits (the raw image), rectified with the same
    bilinear rig and quantised again: reference = that - rectify(clean raw). Bilinear
    rectification of a 77 px raw image onto 64 px removes ~65 % of the high-passed noise
    variance, which an analytic per-pixel model would miss (a false "noise" alarm).
    """
    F_, H, W, _ = predicted.shape
    src, dst = rect.src, rect.dst
    Hs, Ws = src.height, src.width
    v, u = torch.meshgrid(torch.arange(Hs, dtype=torch.float64), torch.arange(Ws, dtype=torch.float64), indexing="ij")
    uv = torch.stack([u, v], -1)
    rays_src = src.unproject_checked(uv)[0] if hasattr(src, "unproject_checked") else src.unproject(uv)
    rays_dst = torch.nan_to_num(rays_src) @ rect.R_src_dst.to(torch.float64)  # rays_src = rays_dst @ R^T
    z = rays_dst[..., 2:3]
    ok = raw_valid & (z[..., 0] > 1e-6)
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    pu = dst.fx * rays_dst[..., 0:1] / zs + dst.cx
    pv = dst.fy * rays_dst[..., 1:2] / zs + dst.cy
    grid = torch.cat([pu * 2.0 / max(W - 1, 1) - 1.0, pv * 2.0 / max(H - 1, 1) - 1.0], -1)  # align_corners=True
    grid = grid[None].to(torch.float32)
    ok_f, ok_d = ok[None, ..., None].to(torch.float32), ok[None, ..., None].to(torch.float64)
    pred = torch.from_numpy(np.ascontiguousarray(predicted, dtype=np.float32)).permute(0, 3, 1, 2)

    def raw_clean(f: int) -> torch.Tensor:  # frame f of the prediction in the raw image [1, Hs, Ws, 3]
        raw = torch.nn.functional.grid_sample(pred[f:f + 1], grid, mode="bilinear", padding_mode="border",
                                              align_corners=True)
        return raw.permute(0, 2, 3, 1) * ok_f

    # Frame by frame (at paper scale one [F, Hs, Ws, 3] float64 array is ~2 GB a frame-batch copy); the
    # draws are made in the order of one batched `noise.sample`, so the reference is the same number.
    resp = GammaResponse(float(gamma))
    generator = torch.Generator().manual_seed(int(seed) * 7919 + 11)
    g = torch.from_numpy(np.asarray(gain, dtype=np.float64))[:, None, None, None]
    electrons = torch.empty((F_, Hs, Ws, 3), dtype=torch.float64)
    for f in range(F_):
        lin = resp.decode(raw_clean(f).to(torch.float64)).clamp(0.0, 1.0)
        electrons[f:f + 1] = noise.shot_electrons(lin, noise.electrons_per_unit(g[f:f + 1], lin), generator)
    noise.add_read_noise_(electrons, generator)
    out = np.empty((F_, H, W, 3), dtype=np.float64)
    for f in range(F_):
        clean = raw_clean(f)
        noisy = electrons[f:f + 1] / noise.electrons_per_unit(g[f:f + 1], electrons[f:f + 1])
        noisy = quantise(resp.encode(noisy).clamp(0, 1), 8) * ok_d
        noisy_rect = quantise(rect.warp(noisy.to(torch.float32)).clamp(0, 1), 8)
        out[f] = (noisy_rect - rect.warp(clean))[0].numpy()
    return out


def run_context(recording_dir: str | Path, rec, frames, predicted: np.ndarray, velocity: np.ndarray, gamma: float,
                calibration: str, meta: dict, seed: int = 0) -> DiagnosisContext:
    """Context of a prediction that lives only in the rectified camera (a trained run).

    The assumed noise is the device profile's; on a recording with an MPS calibration of that
    camera, the noise test is calibrated like the ground-truth path (`pipeline_noise_reference`:
    one draw of the assumed noise through 8-bit raw, the bilinear rectification and 8-bit)."""
    meta = dict(meta)
    noise, dev = None, None
    device = (rec.meta or {}).get("device")
    if device:
        try:
            dev = get_device(device)
            noise = PoissonGaussianNoise(dev.noise.full_well_e, dev.noise.read_noise_e)
        except ValueError:
            noise, dev = None, None
    ctx = _context(rec, frames, velocity, gamma, noise, None, meta)
    if noise is not None and (rec.meta or {}).get("sim_config") is not None:
        rig = recording_rectification(recording_dir, calibration, dev, rec.camera)
        if rig is not None:
            rect, raw_valid = rig
            ctx.noise_reference = pipeline_noise_reference(predicted, rect, raw_valid, noise, ctx.gain, gamma, seed)
            ctx.meta["noise_calibration"] = ("one draw of the assumed noise through 8-bit raw, rectification "
                                             f"({rect.src.width}x{rect.src.height} -> {rect.dst.width}x{rect.dst.height}) and 8-bit")
    if ctx.noise_reference is None and noise is not None:
        ctx.meta["noise_calibration"] = "analytic (capture pipeline unknown: resampling not calibrated)"
    return ctx


@dataclass
class _Recast:
    """What re-casting a simulated recording under the model's assumptions needs (one per recording)."""

    scene: object  # egobench.sim.world.Scene of the recording
    trajectory: object  # the recording's Trajectory (T_world_device)
    raw: object  # egobench.sim.capture.RawCamera of the model's camera (hidden effects removed)
    rect: object  # Rectification raw -> rectified of the measured images
    formation: object  # FormationModel of the prediction (paper trainer, gamma)
    simulator: object  # FormationModel drawing the assumed noise (ground truth, gamma)
    raw_vignette: torch.Tensor  # [H_raw, W_raw] calibrated lens shading in the raw image
    noise: object | None  # assumed PoissonGaussianNoise (None: the recording is noiseless)
    generator: torch.Generator  # draws of the assumed noise, seeded from the recording's seed
    sensitivity: float  # the device's sensitivity (formation units per lux s)
    readout_stated_s: float  # readout the recording states, s
    hidden_offset_ns: int  # hidden time offset the model does not know, ns


def _recast_setup(root: Path, info: dict, config, rec, gamma: float) -> tuple[_Recast, object]:
    """The model's re-cast of the recording at ``root`` -> (_Recast, the online CameraCalibration).

    The model's camera is the true one minus the hidden effects (VIBA-size calibration noise is
    left out: with point-sampled, aliased textures even 0.01 deg moves edge pixels by many levels).
    ValueError when the online calibration on disk is not the simulator's."""
    dev = get_device(config.device_name)
    cals = make_calibrations(config)
    cal_online = cals.online
    stated = read_online_calibration(root / MPS_SLAM / ONLINE_CALIBRATION_FILE)[0].camera(dev.label)
    if not np.allclose(stated.params, cal_online.params):
        raise ValueError(f"{root}: the online calibration on disk differs from the simulator's (was the recording edited?)")
    params = np.asarray(cals.true.params, dtype=np.float64).copy()
    params[3] -= config.distortion_k0_delta
    cal_model = replace(cals.true, params=params)
    # the measured frames' pixel-area integration (recordings from before `pixel_samples` existed: 1)
    raw = RawCamera.build(cal_model, int(info["sim_config"].get("pixel_samples", 1)))
    rect, _pin = rectification_rig(cal_online, config.rectified_size, config.focal_ratio())  # the measured images' rectification
    if config.raw_roi:
        raw = raw.restricted_to(sampled_raw_pixels([rect], raw.valid.shape))
    if config.readout_window == "view":  # the same ROI readout as the capture (the online view's rows)
        raw = replace(raw, readout_rows=view_readout_rows(rect, raw.valid.shape))
    # the calibrated lens shading in the raw image (what vignette.png is rectified from)
    raw_vignette = radial_vignette((cal_model.height, cal_model.width), 1.0 - dev.vignette_corner,
                                   dev.vignette_power, centre=(float(cal_model.params[1]), float(cal_model.params[2])))
    return _Recast(
        scene=make_scene(config.kind, config.seed, sun_scale=config.sun_scale, grain=config.grain,
                       variety=config.world_variety), trajectory=rec.trajectory, raw=raw, rect=rect,
        formation=FormationModel(FormationConfig.paper_trainer(gamma=gamma)),
        simulator=FormationModel(FormationConfig.ground_truth(gamma=gamma)), raw_vignette=raw_vignette,
        noise=PoissonGaussianNoise(dev.noise.full_well_e, dev.noise.read_noise_e) if config.noise else None,
        generator=torch.Generator().manual_seed(int(config.seed) * 7 + 3), sensitivity=dev.sensitivity,
        readout_stated_s=config.stated_readout_s(), hidden_offset_ns=int(round(config.time_offset_s * 1e9)),
    ), cal_online


def _recast_frame(rc: _Recast, frame, read_start_true_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
    """One frame re-cast with what the model assumes -> (predicted display [H, W, 3] float32,
    rectified like the captured image; one draw of the assumed noise through the same pipeline
    (8-bit raw, rectify, 8-bit) minus the prediction [H, W, 3], or None without noise)."""
    read_start_model = read_start_true_ns - rc.hidden_offset_ns
    irr = capture_irradiance(rc.scene, rc.trajectory, rc.raw, read_start_model, frame.exposure_s,
                             rc.readout_stated_s, 1)
    lin = irr * float(frame.exposure_s * frame.gain * rc.sensitivity)
    display_raw = rc.formation.predict(lin, scale_k=1.0, vignette=rc.raw_vignette, scene_gamma=False)
    display_raw = display_raw * rc.raw.valid[..., None].to(display_raw.dtype)
    pred_rect = rc.rect.warp(display_raw).to(torch.float32)
    if rc.noise is None:
        return pred_rect.numpy(), None
    noisy = rc.simulator.simulate(irr, exposure_s=frame.exposure_s, gain=frame.gain, sensitivity=rc.sensitivity,
                                  vignette=rc.raw_vignette, white_balance=(1.0, 1.0, 1.0), noise=rc.noise,
                                  generator=rc.generator)
    noisy = noisy * rc.raw.valid[..., None].to(noisy.dtype)
    noisy_rect = torch.round(rc.rect.warp(noisy).clamp(0, 1) * 255.0) / 255.0
    return pred_rect.numpy(), (noisy_rect - pred_rect).numpy()


def ground_truth_source(recording_dir: str | Path, max_frames: int | None = None, gamma: float = 2.2,
                        progress: bool = True) -> Sources:
    """Prediction = the simulator's world re-cast with the recording's own metadata and calibration.

    Each frame is re-rendered exactly as egobench.sim.capture renders it, but with what the model
    assumes: the true camera with the hidden effects removed (the stated k0 and time offset; the
    VIBA-size calibration noise is left out so that only the hidden effect differs), the stated
    readout, one instant per row at mid-exposure (no blur), the recorded exposure and
    gain, the calibrated device lens shading, gamma ``gamma``, white balance 1, no noise; the
    formation is applied in the raw image and the display image rectified with the same rig as
    the measured one (rectifying display values, as the capture does, avoids a Jensen bias). Any hidden
    effect therefore appears in measured - predicted and nothing else does.
    """
    root = recording_root(recording_dir)
    info = read_json(root / "recording.json")
    truth = read_json(root / "ground_truth" / "truth.json")
    if "sim_config" not in info:
        raise ValueError(f"{root / 'recording.json'}: field 'sim_config' missing (not a simulated recording?)")
    config = SimConfig.from_dict(info["sim_config"])
    rec = load_recording(root, calibration="online")
    frames = _select(rec.frames, max_frames)
    rc, cal_online = _recast_setup(root, info, config, rec, gamma)
    truth_frames = {int(t["index"]): t for t in truth.get("frames", [])}
    measured, predicted, velocity, noise_ref = [], [], [], []
    iterator = tqdm(frames, desc="re-cast prediction", unit="frame") if progress else frames
    for f in iterator:
        pred, ref = _recast_frame(rc, f, int(truth_frames[f.index]["read_start_true_ns"]))
        predicted.append(pred)
        if ref is not None:
            noise_ref.append(ref)
        measured.append(rec.load_image(f).numpy())
        depth_file = rec.ground_truth_file("depth", f)
        depth = np.load(depth_file).astype(np.float64) if depth_file is not None else np.zeros(rec.vignette.shape)
        velocity.append(pixel_velocity(rec, f, depth))
    lens_k = tuple(float(x) for x in cal_online.params[3:9])
    meta = {"recording": str(root), "source": "ground_truth re-cast (simulator world, model's assumptions)",
            "hidden_effects": truth.get("hidden_effects", {})}
    ctx = _context(rec, frames, np.stack(velocity), gamma, rc.noise, lens_k, meta)
    ctx.noise_reference = np.stack(noise_ref) if noise_ref else None
    return Sources(np.stack(measured), np.stack(predicted), ctx, meta["source"])


def run_renderer(recording_dir: str | Path, run, what: str, trajectory_path: str | Path | None = None,
                 semidense_path: str | Path | None = None) -> RunRenderer:
    """A loaded trained run (`load_trained_run`) set up to render its recording at full resolution: the recording
    read in the run's calibration, with ``trajectory_path`` / ``semidense_path`` as `load_recording` reads them (the
    CLI's --trajectory / --points). A ValueError naming ``what`` where the run was trained at another size."""
    cam = run.camera
    rec = load_recording(recording_dir, calibration=run.spec.calibration, trajectory_path=trajectory_path,
                         semidense_path=semidense_path)
    if (cam.width, cam.height) != (rec.camera.width, rec.camera.height):
        raise ValueError(f"{run.path}: trained at {cam.width}x{cam.height}, the recording is "
                         f"{rec.camera.width}x{rec.camera.height}; full-resolution renders are needed for {what}")
    return RunRenderer.of(rec, run)


def run_source(recording_dir: str | Path, run_dir: str | Path, max_frames: int | None = None,
               progress: bool = True, device: str | None = None, trajectory_path: str | Path | None = None,
               semidense_path: str | Path | None = None, pose_samples: int | None = None) -> Sources:
    """Prediction = a trained run's renders of every frame (its own formation model and poses),
    rendered on ``device`` (default: the run's training device; see `egobench.train.checkpoint.render_device`).
    ``trajectory_path`` / ``semidense_path``: as `load_recording`'s (the CLI's --trajectory / --points).
    ``pose_samples``: render every moving frame with this many rolling-shutter pose samples instead of
    the run's own count (at most 8 by default). The run's staircase of pose samples shortens its
    effective readout by about 1/N (`motion_sampling.pixel_pose_index`), which the readout test
    measures as a readout error; a fine staircase leaves the recording's timing alone in the residual."""
    run = load_trained_run(run_dir, device, f"diagnose run {run_dir}")
    r = run_renderer(recording_dir, run, "the diagnosis", trajectory_path, semidense_path)
    rec, spec = r.recording, run.spec
    frames = _select(rec.frames, max_frames)
    counts = r.pose_samples(frames)
    trained_counts = np.array(counts, dtype=np.int64)  # as in its training: the same rule at the same size
    if pose_samples is not None:
        if int(pose_samples) != pose_samples or pose_samples < 1:
            raise ValueError(f"pose_samples: expected a positive integer, got {pose_samples!r}")
        counts = [int(pose_samples) if n > 1 else 1 for n in counts]
    measured, predicted, velocity, coverage, views = _run_renders(r, list(zip(frames, counts)), progress)
    meta = {"recording": str(recording_dir), "run": str(run_dir), "method": spec.name,
            "source": f"renders of trained run ({spec.name})", "pose_samples": pose_samples or "the run's own"}
    ctx = run_context(recording_dir, rec, frames, predicted, velocity, float(getattr(spec, "response_gamma", 2.2)),
                      spec.calibration, meta)
    ctx.render_alpha, ctx.train_view_count, ctx.model_pose_samples = coverage, views, trained_counts
    return Sources(measured, predicted, ctx, meta["source"])


def _run_renders(r: RunRenderer, pairs: list, progress: bool) -> tuple[np.ndarray, ...]:
    """[(frame, pose samples)] rendered by ``r`` -> (measured, predicted [F, H, W, 3], image velocity [F, H, W, 2]
    of the rendered surface, render coverage (alpha) [F, H, W], training views of the surface [F, H, W])."""
    rec = r.recording
    measured, predicted, velocity, coverage, views = [], [], [], [], []
    with torch.no_grad():
        for f, n in tqdm(pairs, desc="render run", unit="frame", disable=not progress):
            p = r.predict(f, n)
            predicted.append(p.image.numpy())
            measured.append(rec.load_image(f).numpy())
            depth = p.outs[0].depth[0, ..., 0].cpu().numpy().astype(np.float64)
            alpha = p.outs[0].alpha[0, ..., 0].cpu().numpy()
            coverage.append(alpha.astype(np.float32))
            surface_depth = np.where(alpha > 0.5, depth, 0.0)  # where the model renders a surface
            velocity.append(pixel_velocity(rec, f, surface_depth))
            views.append(training_view_count(rec, f, surface_depth))
    return tuple(np.stack(x) for x in (measured, predicted, velocity, coverage, views))
