"""Held-out evaluation of a trained run (PAPER-NOTES §6): writes the run record ``eval.json``.

Every 8th frame is held out. Each is rendered with its own exposure*gain normaliser k and, for
methods that model rolling shutter, with adaptive motion sampling (always on at evaluation,
whatever the training warm-up); centre-row methods use the centre-row pose. Metrics against
the captured test image of the method's own calibration stream (factory-calibration methods
are evaluated on factory-rectified images, the pipeline run wholly with factory calibration as in
the paper): PSNR over the valid mask, SSIM, LPIPS (AlexNet) when available locally, and on
scenes with ground-truth geometry, depth (scale-invariant L1) and normal L1 rendered through
the *true* (online) camera and poses, since geometry does not depend on the appearance model.

Metrics are computed on the 8-bit quantised render that is saved as PNG, so recomputing them
from ``renders/NNNNN.png`` gives the same numbers. PSNR against the clean ground-truth
radiance is not computed (it needs the simulator's full formation; noted in the record).

Not modelled: test-time pose optimisation for pose-optimising baselines (3DGS-on-the-move is
evaluated at the trajectory poses with velocities from the trajectory).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from egobench import __version__
from egobench.camera.pinhole import Pinhole
from egobench.data.recording import Frame, Recording
from egobench.io_utils import read_json, write_json
from egobench.methods import MethodSpec, get_method

RUN_SCHEMA = "egobench.run/1"
VIRTUAL_GAIN = 3.0  # paper teaser: re-render at 3x gain


def _to_png(path: Path, image: Tensor) -> None:
    """Write an [H, W, 3] image in [0, 1] as an 8-bit PNG (atomically)."""
    import cv2

    from egobench.io_utils import atomic_path

    arr = (image.detach().cpu().clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
    with atomic_path(path) as tmp:  # the temporary name ends in .png, so cv2 picks the codec
        if not cv2.imwrite(str(tmp), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)):
            raise ValueError(f"{path}: could not write PNG")


def quantise8(image: Tensor) -> Tensor:
    """Round to the 8-bit levels a PNG stores."""
    return torch.round(image.clamp(0, 1) * 255.0) / 255.0


def load_checkpoint(run_dir: Path) -> dict:
    """The run's checkpoint.pt (tensors, dicts, lists, numbers and strings only: nothing in it can
    execute code). FileNotFoundError without one, ValueError naming the file when it is not an
    egobench checkpoint."""
    import pickle
    import struct

    path = Path(run_dir) / "checkpoint.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint (train the run first)")
    from egobench.train import CHECKPOINT_FORMAT

    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, EOFError, RuntimeError, struct.error) as exc:
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ValueError(f"{path}: not a readable egobench checkpoint ({why})") from exc
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not an egobench checkpoint (expected format {CHECKPOINT_FORMAT})")
    return ck


def render_device(requested: str | None, trained_on: str, where: str) -> torch.device:
    """The torch device to render a checkpoint on: ``requested`` (``--device``) or else the run's
    training device (``config.device``). Raises a ValueError naming ``where`` when that is a CUDA
    device and this torch has no CUDA (a GPU-trained run evaluated on a CPU machine needs --device cpu)."""
    name = requested if requested else trained_on
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"{where}: device {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        origin = "requested" if requested else "the run's training device (config.device)"
        raise ValueError(f"{where}: device {name!r} is {origin}, but CUDA is not available here; "
                         "pass --device cpu (device='cpu') to render on the CPU")
    return device


def _load(recording_dir, calibration: str) -> Recording:
    if isinstance(recording_dir, Recording):
        return recording_dir
    from egobench.data import load_recording

    return load_recording(recording_dir, calibration=calibration)


def _gt_file(recording: Recording, kind: str, frame: Frame) -> Path | None:
    if recording.ground_truth is None:
        return None
    p = Path(recording.ground_truth) / kind / f"{frame.index:05d}.npy"
    return p if p.is_file() else None


def evaluate(recording_dir, run_dir, *, scene: str | None = None, paper_scene: str | None = None,
             save_renders: bool = True, geometry_recording=None, device: str | None = None) -> dict:
    """Evaluate the run in ``run_dir`` on the held-out frames; writes and returns eval.json.

    ``recording_dir``: the recording folder (or a loaded `Recording` of the method's calibration).
    ``geometry_recording``: optional loaded online-calibration `Recording` for depth/normal (defaults to
    loading ``recording_dir`` with the online calibration when ground truth exists).
    ``device``: where the Gaussians are rendered (default: the run's training device, `render_device`);
    renders come back to the CPU for the image formation and the metrics (float64).
    """
    from egobench.metrics import lpips_alex, lpips_available, psnr, ssim
    from egobench.motion_sampling import pixel_pose_index  # noqa: F401  (documented dependency)
    from egobench.train import (
        TrainConfig, formation_model, frame_poses, gaussians_from_params, predict_image, resize_map,
        exposure_normaliser, render_frame, sample_counts,
    )

    run_dir = Path(run_dir)
    ck = load_checkpoint(run_dir)
    spec: MethodSpec = get_method(ck["method"])
    cfg_dict = dict(ck["config"])
    cfg_dict["background"] = tuple(cfg_dict["background"])
    config = TrainConfig(**cfg_dict)
    dev = render_device(device, config.device, f"evaluate {run_dir}")
    config = replace(config, device=str(dev))  # render_frame builds the background on config.device
    rec = _load(recording_dir, spec.calibration)
    if rec.calibration != spec.calibration:
        raise ValueError(f"recording: method {spec.name!r} is evaluated on the {spec.calibration!r} stream, got {rec.calibration!r}")
    frames = rec.test_frames
    if not frames:
        raise ValueError(f"recording {rec.root}: no held-out frames (every 8th frame, from index 0)")
    c = ck["camera"]
    cam = Pinhole(fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"], width=c["w"], height=c["h"])
    mask = resize_map(rec.mask.float(), cam) > 0.999
    vignette = resize_map(rec.vignette.float(), cam)
    rtr = resize_map(rec.row_time_ratio.float(), cam)
    k_all = exposure_normaliser(rec) if spec.formation else torch.ones(len(rec.frames))
    pos = {f.index: i for i, f in enumerate(rec.frames)}
    params = {k: v.detach() for k, v in ck["params"].items()}  # CPU (load_checkpoint maps to the CPU)
    g = gaussians_from_params(params).to(dev)  # render() runs on the device of the Gaussians
    formation = formation_model(spec)
    pixel_scale = cam.width / rec.camera.width
    # Always adaptive at evaluation for methods that model rolling shutter.
    counts = sample_counts(rec, frames, spec, config, pixel_scale)
    renders_dir = run_dir / "renders"
    ok_lpips, lpips_reason = lpips_available()
    notes: dict[str, str] = {}
    if not ok_lpips:
        notes["lpips"] = lpips_reason
    notes["psnr_clean"] = "not computed: PSNR against clean ground-truth radiance needs the simulator's formation"
    if spec.pose_optimisation:
        notes["test_poses"] = "held-out frames use trajectory poses (no test-time pose optimisation)"

    # Geometry on scenes with ground truth, through the true (online) camera.
    geo_rec = geometry_recording
    has_geo = _gt_file(rec, "depth", frames[0]) is not None or _gt_file(rec, "normal", frames[0]) is not None
    if has_geo and geo_rec is None:
        if rec.calibration == "online":
            geo_rec = rec
        elif not isinstance(recording_dir, Recording):
            geo_rec = _load(recording_dir, "online")
        else:
            notes["geometry"] = "skipped: pass geometry_recording (online calibration) for a factory-calibrated Recording"

    per_image: list[dict[str, Any]] = []
    noisiest = max(frames, key=lambda f: (float(f.gain), -f.index))
    with torch.no_grad():
        for f, n in zip(frames, counts):
            kk = k_all[pos[f.index]]
            poses, ppi = frame_poses(rec, f, spec, n, rtr, n_exposure_samples=spec.render_exposure_samples)
            outs = render_frame(g, cam, poses, ppi, spec, config)
            rgb = torch.stack([o.rgb[0] for o in outs]).mean(0).cpu()
            pred = quantise8(predict_image(rgb, spec, kk, vignette, formation))
            gt = resize_map(rec.load_image(f), cam)
            entry: dict[str, Any] = {"frame": f.index, "psnr": psnr(pred, gt, mask), "ssim": ssim(pred, gt, mask),
                                     "pose_samples": int(n)}
            if ok_lpips:
                entry["lpips"] = lpips_alex(pred, gt)
            if save_renders:
                _to_png(renders_dir / f"{f.index:05d}.png", pred)
            if f is noisiest and save_renders:
                boosted = formation.virtual_gain(rgb, VIRTUAL_GAIN, scale_k=kk,
                                                 scene_gamma=spec.scene_gamma if spec.formation else True,
                                                 vignette=vignette if spec.formation else None)
                boosted = quantise8(boosted)
                _to_png(renders_dir / f"virtual_gain_{VIRTUAL_GAIN:g}x_{f.index:05d}.png", boosted)
                _to_png(renders_dir / f"virtual_gain_{VIRTUAL_GAIN:g}x_{f.index:05d}_beside_input.png",
                        torch.cat([gt, boosted], dim=1))
            if has_geo and geo_rec is not None:
                entry.update(_geometry(g, geo_rec, f, spec, config, n, cam.width / rec.camera.width))
            per_image.append(entry)

    def mean_of(key: str) -> float | None:
        vals = [e[key] for e in per_image if e.get(key) is not None]
        return float(np.mean(vals)) if vals else None

    train_rec = read_json(run_dir / "train.json") if (run_dir / "train.json").is_file() else {}
    tr = train_rec.get("train", {})
    meta = rec.meta or {}
    record = {
        "schema": RUN_SCHEMA,
        "scene": scene or meta.get("scene") or rec.name,
        "scene_kind": meta.get("scene_kind"),
        "device": meta.get("device"),
        "paper_scene": paper_scene if paper_scene is not None else meta.get("paper_scene"),
        "method": spec.name,
        "method_label": spec.label,
        "seed": int(config.seed),
        "calibration": spec.calibration,
        "config_hash": ck["config_hash"],
        "git_commit": train_rec.get("git_commit") or _git(),
        "egobench_version": __version__,
        "recording": str(rec.root),
        "train": {
            "iterations": int(ck["iteration"]),
            "time_s": tr.get("time_s"),
            "iters_per_s": tr.get("iters_per_s"),
            "raster_time_share": tr.get("raster_time_share"),
            "num_gaussians": int(len(params["means"])),
        },
        "metrics": {
            "psnr": mean_of("psnr"), "ssim": mean_of("ssim"), "lpips": mean_of("lpips"),
            "depth_si_l1": mean_of("depth_si_l1"), "normal_l1": mean_of("normal_l1"),
        },
        "notes": notes,
        "eval": {"resolution": [cam.width, cam.height], "n_test_frames": len(frames),
                 "pose_samples_mean": float(np.mean(counts))},
        "recording_stats": recording_stats(rec),
        "per_image": per_image,
    }
    if not has_geo:
        notes.setdefault("geometry", "no ground-truth depth/normal in this recording")
    write_json(run_dir / "eval.json", record)
    return record


def recording_stats(rec: Recording, step_ns: int = 1_000_000) -> dict[str, Any]:
    """Frame count and head angular speed (deg/s, from device poses every ``step_ns`` over the
    frames' span) of a recording: Table 4's frame column and the PSNR-versus-head-speed plot."""
    from egobench.geometry import so3_log

    t0, t1 = rec.frames[0].read_start_ns, rec.frames[-1].read_end_ns
    t0 = max(t0, getattr(rec.trajectory, "start_ns", t0))  # analytic test trajectories have no span
    t1 = min(t1, getattr(rec.trajectory, "end_ns", t1))
    t = torch.arange(t0, t1 + 1, step_ns, dtype=torch.int64)
    stats: dict[str, Any] = {"num_frames": len(rec.frames), "duration_s": (t1 - t0) * 1e-9}
    if len(t) >= 2:
        R = rec.trajectory.pose(t)[:, :3, :3]
        rel = R[:-1].transpose(-1, -2) @ R[1:]
        speed = torch.rad2deg(so3_log(rel).norm(dim=-1)) / (step_ns * 1e-9)
        stats["head_angular_speed_deg_s_p50"] = float(torch.quantile(speed, 0.5))
        stats["head_angular_speed_deg_s_p99"] = float(torch.quantile(speed, 0.99))
    return stats


def _geometry(g, geo_rec: Recording, frame: Frame, spec: MethodSpec, config, n: int, scale: float) -> dict:
    """Depth SI-L1 and normal L1 of one held-out frame rendered through the true (online) camera
    and trajectory poses at the evaluation scale; ground truth resized by nearest neighbour."""
    from egobench.metrics import depth_si_l1, normal_l1
    from egobench.train import frame_poses, render_frame, resize_map

    gf = next((x for x in geo_rec.frames if x.index == frame.index), None)
    out: dict[str, Any] = {}
    if gf is None:
        return out
    cam = geo_rec.camera if abs(scale - 1) < 1e-12 else geo_rec.camera.scaled(scale)
    d_path, n_path = _gt_file(geo_rec, "depth", gf), _gt_file(geo_rec, "normal", gf)
    pose_spec = get_method("ours") if spec.models_rolling_shutter else get_method("no_motion_sampling")
    poses, ppi = frame_poses(geo_rec, gf, pose_spec, n, resize_map(geo_rec.row_time_ratio.float(), cam))
    o = render_frame(g, cam, poses, ppi, spec, config, want_normal=n_path is not None)[0]
    valid = (resize_map(geo_rec.mask.float(), cam, "nearest") > 0.5) & (o.alpha[0, ..., 0].cpu() > 0.5)
    if d_path is not None:
        gt_d = resize_map(torch.from_numpy(np.load(d_path).astype(np.float32)), cam, "nearest")
        out["depth_si_l1"] = depth_si_l1(o.depth[0, ..., 0].cpu(), gt_d, valid)
    if n_path is not None and o.normal is not None:
        gt_n = resize_map(torch.from_numpy(np.load(n_path).astype(np.float32)), cam, "nearest")
        out["normal_l1"] = normal_l1(o.normal[0].cpu(), gt_n, valid)
    return out


def _git() -> str:
    from egobench.train import _git_commit

    return _git_commit()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recording", required=True, help="recording folder")
    parser.add_argument("--run", required=True, help="run folder with checkpoint.pt (eval.json written here)")
    parser.add_argument("--scene", default=None, help="scene name for the record (default: the recording's)")
    parser.add_argument("--paper-scene", default=None, help="the paper's scene this one stands for")
    parser.add_argument("--no-renders", action="store_true", help="do not save renders")
    parser.add_argument("--device", default=None,
                        help="torch device to render on (default: the run's training device, config.device)")


def run(args: argparse.Namespace) -> int:
    rec = evaluate(args.recording, args.run, scene=args.scene, paper_scene=args.paper_scene,
                   save_renders=not args.no_renders, device=getattr(args, "device", None))
    m = rec["metrics"]
    print(f"evaluated {rec['method']} on {rec['scene']}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f} "
          f"({len(rec['per_image'])} held-out frames) -> {Path(args.run) / 'eval.json'}")
    return 0
