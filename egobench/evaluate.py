"""Held-out evaluation of a trained run (docs/paper-notes.md §5): writes the run record ``eval.json``.

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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from egobench import __version__
from egobench.analysis.fidelity import transfer_function
from egobench.data import load_recording
from egobench.data.reader import add_input_arguments, frame_counts, say_dropped
from egobench.data.recording import Frame, Recording
from egobench.geometry import so3_log
from egobench.host import host_info
from egobench.io_utils import atomic_path, check_written, git_commit, holding_run_folder, read_json, write_json
from egobench.metrics import (
    depth_mse_authors, depth_si_l1, erode_mask_authors, lpips_alex, lpips_available, normal_cos_authors, normal_l1,
    psnr, ssim,
)
from egobench.model.methods import get_method
from egobench.model.predict import (
    RenderSettings, RunRenderer, frame_poses, learned_timing_ms, render_frame, resize_map,
)
from egobench.train.checkpoint import TrainedRun, check_run_complete, load_trained_run, recording_for_run
from egobench.train.normal_consistency import depth_normals

#: the record's keys of the authors' geometry metrics (`egobench.report.paper_numbers` DEPTH, NORMAL); on an
#: object capture they score the object's foreground, and the same keys with this suffix every surface in view
DEPTH_KEY, NORMAL_KEY, ALL_SURFACES_SUFFIX = "depth_mse_authors", "normal_cos_authors", "_all"

RUN_SCHEMA = "egobench.run/1"
VIRTUAL_GAIN = 3.0  # paper teaser: re-render at 3x gain


def _to_png(path: Path, image: Tensor) -> None:
    """Write an [H, W, 3] image in [0, 1] as an 8-bit PNG (atomically)."""
    arr = (image.detach().cpu().clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
    with atomic_path(path) as tmp:  # the temporary name ends in .png, so cv2 picks the codec
        check_written(path, tmp, cv2.imwrite(str(tmp), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)), "PNG")


def quantise8(image: Tensor) -> Tensor:
    """Round to the 8-bit levels a PNG stores."""
    return torch.round(image.clamp(0, 1) * 255.0) / 255.0


def _load(recording_dir, calibration: str) -> Recording:
    if isinstance(recording_dir, Recording):
        return recording_dir
    return load_recording(recording_dir, calibration=calibration)


@dataclass
class _Held(RunRenderer):
    """A trained run set up to predict the held-out frames of a recording (its maps at the run's training
    resolution)."""

    frames: list[Frame] = field(default_factory=list)  # held-out frames
    counts: list[int] = field(default_factory=list)  # rolling-shutter pose samples of each (adaptive at evaluation)


def _held_out(recording_dir, run_dir, device: str | None) -> _Held:
    run = load_trained_run(run_dir, device, f"evaluate {run_dir}")
    check_run_complete(run_dir, run.checkpoint)
    spec = run.spec
    rec = _load(recording_dir, spec.calibration)
    if rec.calibration != spec.calibration:
        raise ValueError(f"recording: method {spec.name!r} is evaluated on the {spec.calibration!r} stream, got {rec.calibration!r}")
    frames = rec.test_frames
    if not frames:
        raise ValueError(f"recording {rec.root}: no held-out frames (every 8th frame, from index 0)")
    held = _Held.of(rec, run)
    return replace(held, frames=frames, counts=held.pose_samples(frames))


def _geometry_recording(held: _Held, recording_dir, geometry_recording, notes: dict) -> Recording | None:
    """The online-calibration recording to measure depth and normals in, or None when there is no
    ground truth (or it cannot be had: a note says why)."""
    rec, first = held.recording, held.frames[0]
    if rec.ground_truth_file("depth", first) is None and rec.ground_truth_file("normal", first) is None:
        notes.setdefault("geometry", "no ground-truth depth/normal in this recording")
        return None
    if geometry_recording is not None:
        return geometry_recording
    if rec.calibration == "online":
        return rec
    if not isinstance(recording_dir, Recording):
        return _load(recording_dir, "online")
    notes["geometry"] = "skipped: pass geometry_recording (online calibration) for a factory-calibrated Recording"
    return None


def _evaluate_frame(held: _Held, f: Frame, n: int, geo_rec: Recording | None, renders_dir: Path | None,
                    ok_lpips: bool, teaser: bool, pairs: list) -> dict[str, Any]:
    """Metrics of one held-out frame (on its 8-bit render); renders and the virtual-gain teaser saved;
    (render, capture) appended to ``pairs`` for the transfer function."""
    run = held.run
    p, pred, gt = _render_pair(held, f, n)
    entry: dict[str, Any] = {"frame": f.index, "psnr": psnr(pred, gt, held.maps.mask),
                             "ssim": ssim(pred, gt, held.maps.mask), "pose_samples": int(n)}
    pairs.append((pred.cpu().numpy(), gt.cpu().numpy()))
    if ok_lpips:
        entry["lpips"] = lpips_alex(pred, gt)
    if renders_dir is not None:
        _to_png(renders_dir / f"{f.index:05d}.png", pred)
        if teaser:
            _save_virtual_gain(held, f, p.rgb, gt, renders_dir)
    if geo_rec is not None:
        entry.update(_geometry(run, geo_rec, f, n, run.camera.width / held.recording.camera.width))
    return entry


def _render_pair(held: _Held, f: Frame, n: int):
    """(prediction, its 8-bit render [H, W, 3], the captured image at the run's size) of a held-out frame."""
    p = held.predict(f, n)
    return p, quantise8(p.image), resize_map(held.recording.load_image(f), held.run.camera)


def held_out_psnr(recording_dir, run_dir, device: str | None = None) -> list[float]:
    """PSNR (dB) of each held-out frame, as `evaluate` computes it, without writing anything."""
    held = _held_out(recording_dir, run_dir, device)
    with torch.no_grad():
        return [psnr(*_render_pair(held, f, n)[1:], held.maps.mask) for f, n in zip(held.frames, held.counts)]


def held_out_renders(recording_dir, run_dir, device: str | None = None):
    """For each held-out frame of a synthetic recording: (the run's scene colour as linear radiance
    [H, W, 3] (decoded when the method keeps it gamma-compressed), its opacity [H, W], the simulator's
    clean radiance [H, W, 3] at the run's size), numpy float32; writes nothing. A recording without
    ground-truth radiance is an error."""
    held = _held_out(recording_dir, run_dir, device)
    spec = held.run.spec
    with torch.no_grad():
        for f, n in zip(held.frames, held.counts):
            path = held.recording.ground_truth_file("radiance", f)
            if path is None:
                raise FileNotFoundError(f"{recording_dir}: ground_truth/radiance/{f.index:05d}.npy missing "
                                        "(the simulator's clean radiance of a held-out frame)")
            p = held.predict(f, n)
            rgb = p.rgb.float()
            linear = held.formation.response.decode(rgb) if spec.scene_gamma else rgb
            radiance = resize_map(torch.from_numpy(np.load(path).astype(np.float32)), held.run.camera)
            yield linear.numpy(), p.outs[0].alpha[0, ..., 0].float().cpu().numpy(), radiance.numpy()


def held_out_error_by_level(recording_dir, run_dir, edges: Sequence[float],
                            device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where a run's held-out error lies: the squared error of its 8-bit renders (mean over RGB) summed
    per bin of the captured pixel's display level (mean over RGB; bins [edges[i], edges[i+1]), valid
    pixels only) over the held-out frames -> (sse [B], pixels [B]); writes nothing."""
    held = _held_out(recording_dir, run_dir, device)
    bins = torch.as_tensor(np.asarray(edges, np.float64))
    sse, count = np.zeros(len(bins) - 1), np.zeros(len(bins) - 1)
    valid = held.maps.mask.bool().cpu()
    with torch.no_grad():
        for f, n in zip(held.frames, held.counts):
            render, captured = (t.cpu().double() for t in _render_pair(held, f, n)[1:])
            err = ((render - captured) ** 2).mean(-1)[valid]
            b = torch.bucketize(captured.mean(-1)[valid], bins, right=True) - 1
            inside = (b >= 0) & (b < len(bins) - 1)
            sse += np.bincount(b[inside].numpy(), err[inside].numpy(), len(bins) - 1)
            count += np.bincount(b[inside].numpy(), minlength=len(bins) - 1)
    return sse, count


def _save_virtual_gain(held: _Held, f: Frame, rgb: Tensor, gt: Tensor, renders_dir: Path) -> None:
    """The teaser: the frame re-rendered at VIRTUAL_GAIN x its gain, alone and beside the input."""
    spec = held.run.spec
    boosted = held.formation.virtual_gain(rgb, VIRTUAL_GAIN, scale_k=held.k_of[f.index],
                                          scene_gamma=spec.scene_gamma if spec.formation else True,
                                          vignette=held.maps.vignette if spec.formation else None)
    boosted = quantise8(boosted)
    _to_png(renders_dir / f"virtual_gain_{VIRTUAL_GAIN:g}x_{f.index:05d}.png", boosted)
    _to_png(renders_dir / f"virtual_gain_{VIRTUAL_GAIN:g}x_{f.index:05d}_beside_input.png", torch.cat([gt, boosted], dim=1))


@holding_run_folder("evaluate", "run_dir", exclusive=False)
def evaluate(recording_dir, run_dir, *, scene: str | None = None, paper_scene: str | None = None,
             save_renders: bool = True, geometry_recording=None, device: str | None = None,
             scene_kind: str | None = None) -> dict:
    """Evaluate the run in ``run_dir`` on the held-out frames; writes and returns eval.json.

    ``recording_dir``: the recording folder (or a loaded `Recording` of the method's calibration).
    ``geometry_recording``: optional loaded online-calibration `Recording` for depth/normal (defaults to
    loading ``recording_dir`` with the online calibration when ground truth exists).
    ``device``: where the Gaussians are rendered (default: the run's training device, `render_device`);
    renders come back to the CPU for the image formation and the metrics (float64).
    ``scene_kind``: the table block of a real recording (simulated ones carry their kind).
    """
    held = _held_out(recording_dir, run_dir, device)
    say_dropped(held.recording, "evaluate")
    ok_lpips, lpips_reason = lpips_available(min(held.run.camera.width, held.run.camera.height))
    notes: dict[str, str] = {} if ok_lpips else {"lpips": lpips_reason}
    notes["psnr_clean"] = "not computed: PSNR against clean ground-truth radiance needs the simulator's formation"
    if held.run.spec.pose_optimisation:
        notes["test_poses"] = "held-out frames use trajectory poses (no test-time pose optimisation)"
    geo_rec = _geometry_recording(held, recording_dir, geometry_recording, notes)
    renders_dir = Path(run_dir) / "renders" if save_renders else None
    noisiest = max(held.frames, key=lambda f: (float(f.gain), -f.index))
    pairs: list = []
    with torch.no_grad():
        per_image = [_evaluate_frame(held, f, n, geo_rec, renders_dir, ok_lpips, teaser=f is noisiest, pairs=pairs)
                     for f, n in zip(held.frames, held.counts)]
    missing = sum(1 for e in per_image if e.pop("geometry_missing", False))
    if missing:
        notes["geometry"] = (f"{missing} of {len(per_image)} held-out frames have no pixel where the model is opaque "
                             "(alpha > 0.5) and the ground truth valid: their depth/normal are missing from the means")
    record = _run_record(held, per_image, notes, scene, paper_scene, scene_kind)
    record["fidelity"] = _fidelity(held, pairs)
    write_json(Path(run_dir) / "eval.json", record)
    return record


def _fidelity(held: _Held, pairs: list) -> dict:
    """The model's transfer function on the held-out frames and its resolved wavelength (egobench.analysis.fidelity)."""
    mask = held.maps.mask.cpu().numpy().astype(bool)
    return transfer_function([p for p, _ in pairs], [g for _, g in pairs], mask=mask).to_dict()


def _run_record(held: _Held, per_image: list[dict], notes: dict, scene: str | None,
                paper_scene: str | None, scene_kind: str | None) -> dict:
    """eval.json: the run's identity, training summary, mean metrics and per-image metrics."""
    run, rec, spec = held.run, held.recording, held.run.spec

    def mean_of(key: str) -> float | None:
        vals = [e[key] for e in per_image if e.get(key) is not None]
        return float(np.mean(vals)) if vals else None

    train_rec = read_json(run.path / "train.json") if (run.path / "train.json").is_file() else {}
    tr = train_rec.get("train", {})
    meta = rec.meta or {}
    return {
        "schema": RUN_SCHEMA,
        "scene": scene or meta.get("scene") or rec.name,
        "scene_kind": scene_kind or meta.get("scene_kind"),  # real recordings: from --scene-kind
        "device": meta.get("device"),
        "paper_scene": paper_scene if paper_scene is not None else meta.get("paper_scene"),
        "method": spec.name,
        "method_label": spec.label,
        "seed": int(run.config.seed),
        "calibration": spec.calibration,
        "config_hash": run.checkpoint["config_hash"],
        "git_commit": train_rec.get("git_commit") or git_commit(),
        "egobench_version": __version__,
        "recording": str(rec.root),
        "trajectory_file": meta.get("trajectory_file"),  # what the recording was read with (plots reload it)
        "points_file": meta.get("points_file"),
        "train": {
            "iterations": int(run.checkpoint["iteration"]),
            "time_s": tr.get("time_s"),
            "iters_per_s": tr.get("iters_per_s"),
            "raster_time_share": tr.get("raster_time_share"),
            "num_gaussians": int(len(run.checkpoint["params"]["means"])),
        },
        "metrics": {
            "psnr": mean_of("psnr"), "ssim": mean_of("ssim"), "lpips": mean_of("lpips"),
            DEPTH_KEY: mean_of(DEPTH_KEY), NORMAL_KEY: mean_of(NORMAL_KEY),
            DEPTH_KEY + ALL_SURFACES_SUFFIX: mean_of(DEPTH_KEY + ALL_SURFACES_SUFFIX),
            NORMAL_KEY + ALL_SURFACES_SUFFIX: mean_of(NORMAL_KEY + ALL_SURFACES_SUFFIX),
            "depth_si_l1": mean_of("depth_si_l1"), "normal_l1": mean_of("normal_l1"),
        },
        "notes": notes,
        "frames": frame_counts(rec),
        "host": {"train": train_rec.get("host"), "evaluate": host_info()},  # where each step's arithmetic ran
        "eval": {"resolution": [run.camera.width, run.camera.height], "n_test_frames": len(held.frames),
                 "pose_samples_mean": float(np.mean(held.counts))},
        "recording_stats": recording_stats(rec),
        "per_image": per_image,
    }


def recording_stats(rec: Recording, step_ns: int = 1_000_000) -> dict[str, Any]:
    """Frame count and head angular speed (deg/s, from device poses every ``step_ns`` over the
    frames' span) of a recording: Table 4's frame column and the PSNR-versus-head-speed plot."""
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


def _geometry(run: TrainedRun, geo_rec: Recording, frame: Frame, n: int, scale: float) -> dict:
    """Depth and normal errors of one held-out frame rendered through the true (online) camera and
    trajectory poses at the evaluation scale (ground truth resized by nearest neighbour): the
    authors' metrics over the ground-truth mask (`depth_mse_authors`, `normal_cos_authors`) and
    egobench's own over the pixels where the model is also opaque (`depth_si_l1`, `normal_l1`)."""
    gf = next((x for x in geo_rec.frames if x.index == frame.index), None)
    out: dict[str, Any] = {}
    if gf is None:
        return out
    cam = geo_rec.camera if abs(scale - 1) < 1e-12 else geo_rec.camera.scaled(scale)
    d_path, n_path = geo_rec.ground_truth_file("depth", gf), geo_rec.ground_truth_file("normal", gf)
    pose_spec = get_method("ours") if run.spec.models_rolling_shutter else get_method("no_motion_sampling")
    poses, ppi = frame_poses(geo_rec, gf, pose_spec, n, resize_map(geo_rec.row_time_ratio.float(), cam),
                             timing=learned_timing_ms(run))
    o = render_frame(run.gaussians, cam, poses, ppi, run.spec, RenderSettings.of(run.config),
                     want_normal=n_path is not None)[0]
    in_view = resize_map(geo_rec.mask.float(), cam, "nearest") > 0.5
    valid = in_view & (o.alpha[0, ..., 0].cpu() > 0.5)
    gt_d = None if d_path is None else resize_map(torch.from_numpy(np.load(d_path).astype(np.float32)), cam, "nearest")
    gt_n = None if n_path is None else resize_map(torch.from_numpy(np.load(n_path).astype(np.float32)), cam, "nearest")
    out.update(_authors_geometry(o, run, cam, gt_d, gt_n, in_view, _foreground(geo_rec, gf, cam)))
    if not bool(valid.any()):  # the model is transparent everywhere here: egobench's own metrics have no pixel
        return {**out, "depth_si_l1": None, "normal_l1": None, "geometry_missing": True}
    if gt_d is not None and bool((valid & (gt_d > 0)).any()):  # a view of the sky alone has no surface
        out["depth_si_l1"] = depth_si_l1(o.depth[0, ..., 0].cpu(), gt_d, valid)
    if gt_n is not None and o.normal is not None and bool((valid & (gt_n.norm(dim=-1) > 0.5)).any()):
        out["normal_l1"] = normal_l1(o.normal[0].cpu(), gt_n, valid)
    return out


def _foreground(geo_rec: Recording, frame: Frame, cam) -> Tensor | None:
    """The frame's ground-truth foreground [h, w] bool at the evaluation scale (an object capture's object
    surfaces), or None where the recording has none."""
    path = geo_rec.ground_truth_file("foreground", frame)
    if path is None:
        return None
    return resize_map(torch.from_numpy(np.load(path).astype(np.float32)), cam, "nearest") > 0.5


def _authors_geometry(o, run: TrainedRun, cam, gt_d, gt_n, in_view: Tensor, foreground: Tensor | None) -> dict:
    """The authors' depth and normal errors: on the object's foreground where the recording has one (as the
    authors score their DTC objects), and over every surface in view as ``*_all`` beside them (the only
    score where there is no foreground)."""
    out: dict[str, Any] = {}
    regions = {"": in_view if foreground is None else in_view & foreground}
    if foreground is not None:
        regions[ALL_SURFACES_SUFFIX] = in_view
    depth = None if gt_d is None else (o.depth[0, ..., 0].cpu(), gt_d, gt_d > 0)
    normal = None if gt_n is None or o.normal is None else (_authors_normal(o, run, cam), gt_n, gt_n.norm(dim=-1) > 0.5)
    for suffix, region in regions.items():  # a region the authors' erosion empties has no score in this frame
        for key, metric, maps in ((DEPTH_KEY, depth_mse_authors, depth), (NORMAL_KEY, normal_cos_authors, normal)):
            if maps is not None and _scorable(mask := region & maps[2]):
                out[key + suffix] = metric(maps[0], maps[1], mask)
    return out


def _scorable(mask: Tensor) -> bool:
    """Whether the authors' eroded ``mask`` keeps a pixel: a frame that sees no surface (an outdoor view of the
    sky alone) or none of the object has no geometry score there; the run's means are over the frames that do."""
    return bool(erode_mask_authors(mask).any())


def _authors_normal(o, run: TrainedRun, cam) -> Tensor:
    """The normal map the authors' evaluation scores: 2DGS's rasterized normals as they come (sum of
    w n, not renormalised: a pixel with alpha < 1 holds a shorter vector), 3DGS's from the rendered
    depth (unit, zero on the border: gsplat's depth_to_normal, as their vanilla_gsplat.py)."""
    if run.spec.splat_mode == "2dgs":
        return o.normal[0].cpu()
    return depth_normals(o.depth[0, ..., 0].cpu().to(torch.float64), cam)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recording", required=True, help="recording folder")
    parser.add_argument("--run", required=True, help="run folder with checkpoint.pt (eval.json written here)")
    parser.add_argument("--scene", default=None, help="scene name for the record (default: the recording's)")
    parser.add_argument("--paper-scene", default=None, help="the paper's scene this one stands for")
    parser.add_argument("--scene-kind", default=None, choices=("outdoor", "indoor", "object", "quest3"),
                        help="table block of a real recording (simulated ones carry their kind)")
    parser.add_argument("--no-renders", action="store_true", help="do not save renders")
    parser.add_argument("--device", default=None,
                        help="torch device to render on (default: the run's training device, config.device)")
    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    rec = evaluate(recording_for_run(args.run, args), args.run, scene=args.scene, paper_scene=args.paper_scene,
                   save_renders=not args.no_renders, device=args.device, scene_kind=args.scene_kind)
    m = rec["metrics"]
    print(f"evaluated {rec['method']} on {rec['scene']}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.3f} "
          f"({len(rec['per_image'])} held-out frames) -> {Path(args.run) / 'eval.json'}")
    return 0
