"""train.json: the self-describing record of a training run (identity, config, provenance, timings)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from egobench import __version__
from egobench.data.reader import frame_counts
from egobench.host import host_info
from egobench.io_utils import git_commit
from egobench.model import frame_exposure
from egobench.model.motion_sampling import TIMING_FIELDS, TIMING_KEY
from egobench.model.shading import KEY, corner_attenuation
from egobench.render.torch_backend import VIEWER_NEAR_PLANE
from egobench.train.config import TrainConfig
from egobench.train.data import TrainingData
from egobench.train.state import TrainState

TRAIN_SCHEMA = "egobench.train/1"


@dataclass
class TrainResult:
    """What `train` returns (and writes to train.json)."""

    run_dir: Path
    checkpoint: Path
    iterations: int  # completed iterations
    num_gaussians: int
    time_s: float  # wall time of the iterations (all resumed segments, excluding setup and checkpoints)
    iters_per_s: float
    raster_time_share: float
    final_loss: float
    record: dict = field(default_factory=dict)


#: how `raster_time_share` is timed, by the step that ran
_TIMING = {False: "render() wall time + backward from the rgb hook to the end of loss.backward(), over iteration wall time",
           True: "the compiled step's render forward + its render backward (egobench.train.cpu_render), over iteration wall time"}


def train_record(result: TrainResult, state: TrainState, data: TrainingData, config: TrainConfig,
                 method: str, backend: str, core_sharing: dict | None, compiled_step: bool = False) -> dict:
    """The train.json record of a run (``complete`` once every iteration has run). ``core_sharing``: the
    probes around this process's iterations (`egobench.core_sharing.bracket`; a resumed run: its last
    segment's; None where the kernels ran on one thread, not on the CPU, or no iteration ran).
    ``compiled_step``: the steps ran through `egobench.train.cpu_step` (else through autograd)."""
    spec, rec, cam = data.spec, data.recording, data.camera
    ns = np.asarray(data.n_samples)
    return {
        "schema": TRAIN_SCHEMA, "method": method, "method_label": spec.label, "seed": config.seed,
        "recording": str(rec.root), "scene": rec.name, "calibration": spec.calibration,
        "config": config.to_dict(), "config_hash": config.hash(method), "git_commit": git_commit(),
        "host": host_info(),
        "egobench_version": __version__, "complete": result.iterations >= config.iterations,
        "train": {
            "iterations": result.iterations, "time_s": result.time_s, "iters_per_s": result.iters_per_s,
            "raster_time_share": result.raster_time_share, "num_gaussians": result.num_gaussians,
            "render_forward_s": state.timing["render_fwd_s"], "render_backward_s": state.timing["render_bwd_s"],
            "timing_method": _TIMING[compiled_step],
            "device": config.device, "backend": backend, "step": "compiled" if compiled_step else "autograd",
            "final_loss": result.final_loss if math.isfinite(result.final_loss) else None,
            "image_store": _image_store_stats(data, config),
            "core_sharing": core_sharing,
        },
        "frames": frame_counts(rec),
        "camera": cam.to_dict(), "scene_scale": data.scene_scale,
        "motion_samples": {"mean": float(ns.mean()), "max": int(ns.max()), "min": int(ns.min()),
                           "warmup_iter": config.motion_warmup_iter, "rule": config.sample_rule,
                           "step_px": config.pose_sample_step_px},
        "densification_last": state.densifier.last_counts,
        "learned_shading": _learned_shading(state, config),
        "learned_timing": _learned_timing(state),
        "learned_frame_exposure": _learned_frame_exposure(state, data),
        "near_cameras": near_camera_count(state.params["means"], data.frames),
    }


def near_camera_count(means: Tensor, frames, radius_m: float = VIEWER_NEAR_PLANE) -> dict:
    """How many Gaussians lie within ``radius_m`` of a training camera's centre (at the frame's centre-row pose):
    what a viewer with the INRIA near plane (0.2 m) clips where egobench's renders (0.01 m) keep them. Reported,
    not pruned: pruning would change the trained models (docs/viewer.md)."""
    centres = torch.stack([f.T_world_camera[:3, 3] for f in frames]).to(torch.float64)  # [F, 3]
    m = means.detach().to("cpu", torch.float64)
    near = torch.zeros(len(m), dtype=torch.bool)
    for c in centres:  # [N] per camera: no [N, F] distance matrix
        near |= ((m - c) ** 2).sum(-1) < radius_m ** 2
    return {"radius_m": radius_m, "count": int(near.sum()), "of": int(len(m)),
            "rule": "Gaussian centres within radius_m of any training camera centre (centre-row pose)"}


def _learned_shading(state: TrainState, config: TrainConfig) -> dict | None:
    """The learned lens shading's coefficients and corner attenuation (None without learn_shading)."""
    if KEY not in state.extra:
        return None
    a = state.extra[KEY].detach().cpu().tolist()
    return {"coeffs_r2_r4": a, "corner_attenuation": corner_attenuation(a),
            "centre_offset": [config.shading_centre_dx, config.shading_centre_dy]}


def _learned_timing(state: TrainState) -> dict | None:
    """The learned timing correction (None without learn_timing): time offset and readout error, ms."""
    if TIMING_KEY not in state.extra:
        return None
    return dict(zip(TIMING_FIELDS, state.extra[TIMING_KEY].detach().cpu().tolist()))


def _learned_frame_exposure(state: TrainState, data: TrainingData) -> dict | None:
    """The learned per-frame exposure corrections (None without learn_frame_exposure): each training frame's index
    and log scale."""
    if frame_exposure.KEY not in state.extra:
        return None
    return {"frames": [int(f.index) for f in data.frames],
            "log_scale": state.extra[frame_exposure.KEY].detach().cpu().tolist()}


def _image_store_stats(data: TrainingData, config: TrainConfig) -> dict:
    images, cam, raw = data.images, data.camera, data.recording.camera
    return {
        "dtype": str(images.dtype).replace("torch.", ""), "shape": list(images.shape),
        "mib": images.numel() * images.element_size() / 2**20,
        "pinned": bool(torch.device(config.device).type == "cuda" and images.is_pinned()),
        "resized": [cam.height, cam.width] != [raw.height, raw.width],
    }
