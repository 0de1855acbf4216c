"""The one trainer: every method of `egobench.methods` is a set of switches read here.

Loop (paper Sec. 3-4, PAPER-NOTES §2 and §7): pick a training frame (seeded permutation per
epoch), render it under its pose model (centre-row pose; adaptive rolling-shutter pose samples
after the warm-up; or the velocity-shift model of the 3DGS-on-the-move baseline), apply the
method's image formation (exposure*gain normaliser k, vignette, response, scene gamma), loss
0.8 L1 + 0.2 (1 - SSIM) on valid-mask pixels, Adam per parameter group, gsplat 1.5.3
densification (`egobench.optim`). Deterministic on CPU for a seed; resumable from a checkpoint
to the identical result.

Timing method (``raster_time_share`` in train.json): wall time inside `render()` (forward) plus
the rasterizer's share of the backward pass, measured from the moment autograd reaches the
render output (a tensor hook on ``rgb``) to the end of ``loss.backward()``; everything upstream
of the rasterizer in the graph (pose exponentials, parameter activations) is tiny and is counted
as raster time. Divided by the total wall time of the iterations.

Image store: the training images stay on the host as uint8 [F, H, W, 3] (`load_image_store`; a
2400 px frame is 16.5 MiB, so paper-scale recordings fit), page-locked when training on CUDA;
each iteration copies only its own frame to the device and converts it to float / 255.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from egobench import __version__
from egobench.camera.pinhole import Pinhole
from egobench.checkpoint import read_checkpoint
from egobench.data.recording import Frame, Recording
from egobench.io_utils import atomic_path, write_json
from egobench.methods import MethodSpec, get_method
from egobench.optim import GAUSSIAN_PARAMS, DensifySchedule, Densifier, make_adam

#: Length of the paper's schedule; schedule fields below are fractions of it.
PAPER_ITERATIONS = 30_000
CHECKPOINT_FORMAT = "egobench.checkpoint/1"


class TrainingDiverged(RuntimeError):
    """Raised when a loss or parameter becomes non-finite (names the iteration and quantity)."""


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. Schedule points are fractions of the paper's 30K iterations, so a short
    run scales them (`scaled_to`); absolute values are the properties ``*_iter``."""

    iterations: int = PAPER_ITERATIONS  # optimisation steps (paper: 30K)
    resolution_scale: float = 1.0  # factor applied to the rectified camera (images resized, area filter)
    max_side: int = 0  # if > 0, further downscale so that max(W, H) <= max_side (CPU budget)
    lr_means: float = 1.6e-4  # Adam lr of means, times scene_scale; decays exponentially...
    lr_means_final_factor: float = 0.01  # ...to this fraction of its initial value at the last iteration
    lr_scales: float = 5e-3  # Adam lr of log-scales
    lr_quats: float = 1e-3  # Adam lr of quaternions
    lr_opacities: float = 5e-2  # Adam lr of opacity logits
    lr_colors: float = 2.5e-3  # Adam lr of colours (RGB, scene-colour space)
    lr_pose: float = 1e-4  # Adam lr of per-frame pose corrections (se(3), methods with pose_optimisation)
    lr_twist: float = 1e-3  # Adam lr of per-frame velocities (velocity_shift methods)
    grow_grad2d: float = 2e-4  # densify when the mean normalised screen gradient exceeds this
    grow_scale3d: float = 0.01  # duplicate below / split above this max-scale (x scene_scale)
    prune_opa: float = 0.005  # prune below this opacity
    prune_scale3d: float = 0.1  # prune above this max-scale (x scene_scale), after the first reset period
    refine_start_frac: float = 500 / PAPER_ITERATIONS  # refinement starts after this fraction (paper 500)
    refine_stop_frac: float = 15_000 / PAPER_ITERATIONS  # and stops here (paper 15K)
    refine_every_frac: float = 100 / PAPER_ITERATIONS  # period (paper 100)
    reset_every_frac: float = 3_000 / PAPER_ITERATIONS  # opacity-reset period (paper 3000)
    opacity_reset: Literal["gsplat", "intended"] = "gsplat"  # "gsplat": never (gsplat 1.5.3 bug, authors' runs)
    ssim_lambda: float = 0.2  # loss = (1 - l) L1 + l (1 - SSIM)
    motion_warmup_frac: float = 7_500 / PAPER_ITERATIONS  # motion sampling on after this (paper 7.5K; code 10K)
    max_pose_samples: int = 8  # cap on rolling-shutter pose samples per frame (released code: 8)
    sample_rule: Literal["code", "paper"] = "code"  # how the sample count is chosen (motion_sampling)
    normal_lambda: float = 0.05  # 2DGS normal-consistency weight...
    normal_start_frac: float = 7_000 / PAPER_ITERATIONS  # ...from this fraction (paper 7K)
    dist_lambda: float = 0.01  # 2DGS distortion weight...
    dist_start_frac: float = 3_000 / PAPER_ITERATIONS  # ...from this fraction (paper 3K)
    init_opacity: float = 0.1  # initial opacity of every Gaussian
    init_scale: float = 1.0  # initial scale = this x RMS distance to the 3 nearest points
    scene_scale: float = 0.0  # > 0: override gsplat's scene scale (1.1 x camera-centre extent), metres
    max_gaussians: int = 0  # cap on the Gaussian count (initial subsample and after growth); 0 = none
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # background colour (scene-colour space)
    seed: int = 0  # torch seed and frame-order generator seed
    device: str = "cpu"  # torch device
    backend: str = "auto"  # rasterizer backend passed to egobench.render.render
    checkpoint_every: int = 0  # write checkpoint.pt every N iterations (0 = only at the end)

    def __post_init__(self) -> None:
        if int(self.iterations) != self.iterations or self.iterations < 1:
            raise ValueError(f"TrainConfig.iterations: expected an integer >= 1, got {self.iterations}")
        if not self.resolution_scale > 0:
            raise ValueError(f"TrainConfig.resolution_scale: expected > 0, got {self.resolution_scale}")
        if self.opacity_reset not in ("gsplat", "intended"):
            raise ValueError(f"TrainConfig.opacity_reset: expected 'gsplat' or 'intended', got {self.opacity_reset!r}")
        if self.sample_rule not in ("code", "paper"):
            raise ValueError(f"TrainConfig.sample_rule: expected 'code' or 'paper', got {self.sample_rule!r}")
        if not 0 <= self.ssim_lambda <= 1:
            raise ValueError(f"TrainConfig.ssim_lambda: expected a value in [0, 1], got {self.ssim_lambda}")
        if int(self.max_pose_samples) != self.max_pose_samples or self.max_pose_samples < 1:
            raise ValueError(f"TrainConfig.max_pose_samples: expected an integer >= 1, got {self.max_pose_samples}")
        if len(self.background) != 3:
            raise ValueError(f"TrainConfig.background: expected 3 values, got {self.background}")

    # ---- absolute schedule -----------------------------------------------------------------
    def _at(self, frac: float) -> int:
        return int(frac * self.iterations)

    @property
    def refine_start_iter(self) -> int:
        return self._at(self.refine_start_frac)

    @property
    def refine_stop_iter(self) -> int:
        return self._at(self.refine_stop_frac)

    @property
    def refine_every(self) -> int:
        return max(1, self._at(self.refine_every_frac))

    @property
    def reset_every(self) -> int:
        return max(1, self._at(self.reset_every_frac))

    @property
    def motion_warmup_iter(self) -> int:
        return self._at(self.motion_warmup_frac)

    @property
    def normal_start_iter(self) -> int:
        return self._at(self.normal_start_frac)

    @property
    def dist_start_iter(self) -> int:
        return self._at(self.dist_start_frac)

    def scaled_to(self, iterations: int) -> "TrainConfig":
        """The same schedule compressed/stretched to ``iterations`` steps."""
        return replace(self, iterations=int(iterations))

    @classmethod
    def cpu(cls, **overrides) -> "TrainConfig":
        """CPU preset for the default workflow (~1 minute per train+eval on one core at 64 px,
        ~12 it/s measured). Refinement every 1/30 of the run instead of 1/300 (paper): with a
        compressed schedule, growing every 2-3 iterations compounds before new Gaussians settle."""
        base = dict(iterations=800, max_side=64, max_gaussians=8000, refine_every_frac=1_000 / PAPER_ITERATIONS)
        base.update(overrides)
        return cls(**base)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        return d

    def hash(self, method: str) -> str:
        """sha1 of the canonical JSON of (method, config)."""
        blob = json.dumps({"method": method, "config": self.to_dict()}, sort_keys=True, separators=(",", ":"))
        return hashlib.sha1(blob.encode()).hexdigest()


def parse_overrides(config: TrainConfig, items: list[str]) -> TrainConfig:
    """Apply ``field=value`` strings (``--set``) to a config, converting to the field's type."""
    types = {f.name: f.type for f in fields(TrainConfig)}
    current = config.to_dict()
    changes: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set {item!r}: expected field=value")
        key, value = item.split("=", 1)
        key = key.strip()
        if key not in types:
            raise ValueError(f"--set {key}: unknown TrainConfig field; expected one of {', '.join(types)}")
        old = current[key]
        try:
            if isinstance(old, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                new: Any = value.lower() in ("true", "1")
            elif isinstance(old, int):
                new = int(value)
            elif isinstance(old, float):
                new = float(value)
            elif isinstance(old, list):
                new = tuple(float(v) for v in value.split(","))
            else:
                new = value
        except ValueError:
            raise ValueError(f"--set {key}={value}: expected a value of type {type(old).__name__}") from None
        changes[key] = new
    return replace(config, **changes)


@dataclass
class TrainResult:
    """What `train` returns (and writes to train.json)."""

    run_dir: Path
    checkpoint: Path
    iterations: int  # completed iterations
    num_gaussians: int
    time_s: float  # wall time of the iterations (all sessions, excluding setup and checkpoints)
    iters_per_s: float
    raster_time_share: float
    final_loss: float
    record: dict = field(default_factory=dict)


# ============================================================================= data
@dataclass
class TrainingData:
    """A recording prepared for training at the training resolution."""

    recording: Recording
    spec: MethodSpec
    camera: Pinhole  # training-resolution camera
    frames: list[Frame]  # training frames (time order)
    images: Tensor  # [F, H, W, 3] uint8 captured images (the image store, see `load_image_store`)
    mask: Tensor  # [H, W] bool valid pixels
    vignette: Tensor  # [H, W] float32
    row_time_ratio: Tensor  # [H, W] float32 R(u)
    k: Tensor  # [F] float32 exposure*gain normaliser of the training frames
    n_samples: list[int]  # rolling-shutter pose samples per training frame (1 for centre methods)
    scene_scale: float


def training_camera(camera: Pinhole, config: TrainConfig) -> Pinhole:
    """The rectified camera at the training resolution."""
    scale = config.resolution_scale
    if config.max_side > 0:
        scale = min(scale, config.max_side / max(camera.width, camera.height))
    return camera if abs(scale - 1.0) < 1e-12 else camera.scaled(scale)


def resize_map(x: Tensor, camera: Pinhole, kind: Literal["area", "nearest"] = "area") -> Tensor:
    """Resize an [H, W] or [H, W, C] map to the camera's size (area average, or nearest)."""
    import cv2

    if tuple(x.shape[:2]) == (camera.height, camera.width):
        return x
    interp = cv2.INTER_AREA if kind == "area" else cv2.INTER_NEAREST
    arr = x.detach().cpu().numpy().astype(np.float32)
    out = cv2.resize(arr, (camera.width, camera.height), interpolation=interp)
    return torch.from_numpy(out.reshape(camera.height, camera.width, *x.shape[2:]))


def _pin_store(device: torch.device | str) -> bool:
    """Whether a host image store for ``device`` should be page-locked: only for a CUDA device with
    CUDA available, so CPU-only torch builds never pin."""
    return torch.device(device).type == "cuda" and torch.cuda.is_available()


def load_image_store(recording: Recording, frames: list[Frame], camera: Pinhole, *, pin_memory: bool = False,
                     progress: bool = True) -> Tensor:
    """The frames' captured images at the camera's size as one uint8 tensor [F, H, W, 3].

    Filled frame by frame into a preallocated tensor: peak memory is the store plus one decoded
    frame (a 2400 px frame is 16.5 MiB as uint8 vs 66 MiB as float32). When the recording is
    already at the training size the store is exact: ``store[i].float() / 255`` equals
    ``recording.load_image(frames[i])`` bit for bit (8-bit PNG/JPEG). When the training size is
    smaller, each frame is area-resized in float (cv2 INTER_AREA, as `resize_map`) and rounded
    to uint8, i.e. within 0.5/255 of the float resize (as 3DGS / nerfstudio store downscaled
    image pyramids on disk). ``pin_memory`` allocates page-locked host memory (for non-blocking
    host-to-GPU copies of one frame per iteration). ``progress``: tqdm bar "load images" on stderr.
    """
    from tqdm import tqdm

    H, W = camera.height, camera.width
    shape = (len(frames), H, W, 3)
    try:
        store = torch.empty(shape, dtype=torch.uint8, pin_memory=pin_memory)
    except RuntimeError as exc:  # page-locking this much host memory can fail; pageable still works
        print(f"egobench train: could not pin a {math.prod(shape) / 2**20:.0f} MiB image store ({exc}); "
              "using pageable memory (slower host-to-GPU copies)", file=sys.stderr)
        store = torch.empty(shape, dtype=torch.uint8)
    for i, f in enumerate(tqdm(frames, desc="load images", disable=not progress, file=sys.stderr,
                               mininterval=2.0)):
        img = recording.load_image(f)  # float32 [H0, W0, 3], = u8 / 255
        if tuple(img.shape[:2]) != (H, W):
            img = resize_map(img, camera)
        # x * 255 recovers the decoded 8-bit value exactly (error < 1e-4 << 0.5); resized values round.
        store[i].copy_(torch.round(img * 255.0).clamp_(0.0, 255.0))
    return store


def image_to_float(pixels: Tensor) -> Tensor:
    """Image-store pixels (uint8, any shape) -> float32 in 0..1 (u8 / 255, as `Recording.load_image`).
    A float tensor is taken to be 0..1 already and returned as float32."""
    if pixels.dtype == torch.uint8:
        return pixels.float() / 255.0
    return pixels.float()


def exposure_normaliser(recording: Recording) -> Tensor:
    """k [F] over all frames of the recording (exposure*gain / median), float32."""
    from egobench.formation import exposure_gain_normaliser

    exposure = torch.tensor([f.exposure_s for f in recording.frames], dtype=torch.float64)
    gain = torch.tensor([f.gain for f in recording.frames], dtype=torch.float64)
    return exposure_gain_normaliser(exposure, gain).to(torch.float32)


def validate_recording(recording: Recording, spec: MethodSpec, frames: list[Frame] | None = None) -> None:
    """Clear errors, before any work, for inputs a method cannot use (see module docs)."""
    where = f"recording {recording.root}"
    if len(recording.train_frames) == 0:
        raise ValueError(f"{where}: no training frames (frames: {len(recording.frames)}; every 8th is held out)")
    H, W = recording.camera.height, recording.camera.width
    for name in ("mask", "vignette", "row_time_ratio"):
        value = getattr(recording, name)
        if value is None or tuple(value.shape[:2]) != (H, W):
            shape = None if value is None else tuple(value.shape)
            raise ValueError(f"{where}: {name} has shape {shape}, the calibration says [H, W] = [{H}, {W}]")
    if recording.points_world is None or len(recording.points_world) == 0:
        raise ValueError(f"{where}: no semi-dense points (points_world); they are needed to initialise the Gaussians")
    frames = recording.frames if frames is None else frames
    if spec.formation:
        for f in frames:
            for name in ("exposure_s", "gain"):
                v = getattr(f, name)
                if v is None or not math.isfinite(float(v)) or float(v) <= 0:
                    raise ValueError(
                        f"{where}: frame {f.index} has {name}={v}; method {spec.name!r} models exposure and gain "
                        "and needs positive exposure_duration_s and gain for every frame"
                    )
    if spec.motion_sampling != "centre":
        missing = [f.index for f in frames if f.sparse_depth is None]
        if missing:
            raise ValueError(
                f"{where}: frames {missing[:5]}{'...' if len(missing) > 5 else ''} have no sparse depth; method "
                f"{spec.name!r} picks its rolling-shutter pose samples from sparse-depth points "
                "(sparse_depth/NNNNN.json); use a centre-row method or provide them"
            )
        for f in frames:
            if f.read_end_ns < f.read_start_ns:
                raise ValueError(f"{where}: frame {f.index} has read_end_ns < read_start_ns")
    # The image size must match the calibration (load_image raises a clear ValueError otherwise).
    recording.load_image(frames[0])


def sample_counts(data_rec: Recording, frames: list[Frame], spec: MethodSpec, config: TrainConfig,
                  pixel_scale: float) -> list[int]:
    """Rolling-shutter sample count per frame at the training resolution (1 for centre methods).

    A frame whose sparse depth is empty gets 1 sample (as the released code: it cannot see motion).
    """
    from egobench.motion_sampling import estimate_motion

    if spec.motion_sampling == "centre":
        return [1] * len(frames)
    counts = []
    for f in frames:  # per frame (not per pixel)
        if f.sparse_depth is None or len(f.sparse_depth.z) == 0:
            counts.append(1)
            continue
        est = estimate_motion(data_rec, f, max_samples=config.max_pose_samples, rule=config.sample_rule,
                              pixel_scale=pixel_scale)
        counts.append(est.n_samples)
    return counts


def scene_scale_of(frames: list[Frame], points_world: Tensor) -> float:
    """gsplat's scene scale: 1.1 x max distance of camera centres from their mean. A capture
    with (almost) no translation falls back to the median distance of the points from it."""
    centres = torch.stack([f.T_world_camera[:3, 3].to(torch.float64) for f in frames])
    mean = centres.mean(0)
    scale = float((centres - mean).norm(dim=-1).max()) * 1.1
    if scale < 1e-3:
        scale = float((points_world.to(torch.float64) - mean).norm(dim=-1).median())
    return max(scale, 1e-3)


def prepare_data(recording: Recording, spec: MethodSpec, config: TrainConfig, progress: bool = True) -> TrainingData:
    """Validate, load the training images into a uint8 store at the training resolution
    (`load_image_store`: exact when no resize is needed, else area-resized and rounded to uint8;
    page-locked when training on CUDA), resize the maps, compute k and sample counts."""
    validate_recording(recording, spec)
    cam = training_camera(recording.camera, config)
    frames = recording.train_frames
    images = load_image_store(recording, frames, cam, pin_memory=_pin_store(config.device), progress=progress)
    mask = resize_map(recording.mask.float(), cam) > 0.999
    vignette = resize_map(recording.vignette.float(), cam)
    rtr = resize_map(recording.row_time_ratio.float(), cam)
    k_all = exposure_normaliser(recording) if spec.formation else torch.ones(len(recording.frames))
    pos = {f.index: i for i, f in enumerate(recording.frames)}
    k = torch.stack([k_all[pos[f.index]] for f in frames])
    pixel_scale = cam.width / recording.camera.width
    counts = sample_counts(recording, frames, spec, config, pixel_scale)
    return TrainingData(
        recording=recording, spec=spec, camera=cam, frames=frames, images=images, mask=mask,
        vignette=vignette, row_time_ratio=rtr, k=k, n_samples=counts,
        scene_scale=config.scene_scale if config.scene_scale > 0 else scene_scale_of(frames, recording.points_world),
    )


# ============================================================================= model
def _knn_rms_distance(points: Tensor, k: int = 3) -> Tensor:
    """RMS distance of each point [N, 3] to its k nearest neighbours -> [N] (as gsplat's init)."""
    from scipy.spatial import cKDTree

    pts = points.detach().cpu().numpy().astype(np.float64)
    if len(pts) <= k:
        return torch.full((len(pts),), 0.01, dtype=torch.float32)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    d = np.sqrt((dist[:, 1:] ** 2).mean(axis=1))
    d = np.maximum(d, 1e-7)
    return torch.from_numpy(d).float()


def scene_colour_from_image(pixel: Tensor, k: Tensor, vignette: Tensor, spec: MethodSpec) -> Tensor:
    """Invert the method's formation for initial colours: pixel [P, 3] display -> scene colour."""
    if not spec.formation:
        return pixel
    from egobench.formation import GammaResponse

    resp = GammaResponse(spec.response_gamma)
    lin = resp.decode(pixel) / (k[:, None] * vignette[:, None]).clamp_min(1e-3)
    return resp.encode(lin).clamp(0, 1) if spec.scene_gamma else lin.clamp(0, 4)


def init_params(data: TrainingData, config: TrainConfig, generator: torch.Generator) -> dict[str, torch.nn.Parameter]:
    """Gaussians from the semi-dense points: opacity init_opacity, scale from 3-NN distance,
    random quaternions (gsplat), colour from the first training image each point projects into
    (inside the valid mask), else grey 0.5."""
    pts = data.recording.points_world.to(torch.float32)
    if config.max_gaussians > 0 and len(pts) > config.max_gaussians:
        keep = torch.randperm(len(pts), generator=generator)[: config.max_gaussians].sort().values
        pts = pts[keep]
    N = len(pts)
    scales = torch.log(_knn_rms_distance(pts) * config.init_scale)[:, None].repeat(1, 3)
    quats = torch.rand((N, 4), generator=generator)
    opacities = torch.logit(torch.full((N,), float(config.init_opacity)))
    colors = torch.full((N, 3), 0.5)
    assigned = torch.zeros(N, dtype=torch.bool)
    cam = data.camera
    step = max(1, len(data.frames) // 16)
    for i in range(0, len(data.frames), step):  # a few frames, vectorised over points
        f = data.frames[i]
        T_cw = torch.linalg.inv(f.T_world_camera.to(torch.float64)).to(torch.float32)
        pc = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv, valid = cam.project(pc)
        ui, vi = torch.round(uv[:, 0]).long(), torch.round(uv[:, 1]).long()
        inside = valid & (ui >= 0) & (ui < cam.width) & (vi >= 0) & (vi < cam.height) & ~assigned
        ui, vi = ui.clamp(0, cam.width - 1), vi.clamp(0, cam.height - 1)
        inside &= data.mask[vi, ui]
        if inside.any():
            px = image_to_float(data.images[i][vi[inside], ui[inside]])
            kk = data.k[i].expand(int(inside.sum()))
            colors[inside] = scene_colour_from_image(px, kk, data.vignette[vi[inside], ui[inside]], data.spec).float()
            assigned |= inside
        if bool(assigned.all()):
            break
    return {
        "means": torch.nn.Parameter(pts.clone()),
        "scales": torch.nn.Parameter(scales),
        "quats": torch.nn.Parameter(quats),
        "opacities": torch.nn.Parameter(opacities),
        "colors": torch.nn.Parameter(colors),
    }


def gaussians_from_params(params: dict) -> "Any":
    from egobench.render.types import Gaussians

    return Gaussians(means=params["means"], quats=params["quats"], log_scales=params["scales"],
                     opacity_logits=params["opacities"], colors=params["colors"])


def formation_model(spec: MethodSpec):
    from egobench.formation import FormationConfig, FormationModel

    return FormationModel(FormationConfig.paper_trainer(gamma=spec.response_gamma))


def predict_image(rgb: Tensor, spec: MethodSpec, k: Tensor | float, vignette: Tensor, formation) -> Tensor:
    """Rasterized scene colour [H, W, 3] -> predicted captured image [H, W, 3] in [0, 1]."""
    if not spec.formation:
        return rgb.clamp(0.0, 1.0)
    return formation.predict(rgb, scale_k=k, vignette=vignette, scene_gamma=spec.scene_gamma)


# ============================================================================= poses
def frame_poses(data_rec: Recording, frame: Frame, spec: MethodSpec, n: int, row_time_ratio: Tensor,
                pose_delta: Tensor | None = None, twist: Tensor | None = None,
                n_exposure_samples: int = 1) -> tuple[Tensor, Tensor | None]:
    """Poses to render one frame: (T_world_camera [M, K, 4, 4] float32, pixel_pose_index [H, W] | None).

    M exposure samples (averaged by the caller), K rolling-shutter samples gathered per pixel.
    ``pose_delta`` [6] (se(3), right-multiplied) and ``twist`` [6] are the per-frame trainables of
    pose-optimising / velocity-shift methods.
    """
    from egobench.geometry import se3_exp
    from egobench.motion_sampling import (
        exposure_pose_samples, linear_row_time_ratio, pixel_pose_index, sample_times_ns, velocity_poses,
    )

    H, W = row_time_ratio.shape
    if spec.motion_sampling == "velocity_shift":
        T_c = frame.T_world_camera.to(torch.float32)
        if pose_delta is not None:  # a trainable on the training device: the host pose follows it
            T_c = T_c.to(pose_delta.device) @ se3_exp(pose_delta.to(torch.float32))
        if twist is None:
            from egobench.motion_sampling import frame_twist_camera
            twist = frame_twist_camera(data_rec, frame).to(torch.float32)
        times = sample_times_ns(frame, n, n_exposure_samples)  # [M, K]
        dt = ((times - float(frame.timestamp_ns)) * 1e-9).reshape(-1)
        poses = velocity_poses(T_c, twist.to(torch.float32), dt).reshape(times.shape[0], n, 4, 4)
        ppi = pixel_pose_index(linear_row_time_ratio(H, W).to(row_time_ratio.device), n) if n > 1 else None
        return poses, ppi
    if n == 1 and n_exposure_samples == 1:
        poses = frame.T_world_camera.to(torch.float32)[None, None]
        ppi = None
    else:
        poses = exposure_pose_samples(data_rec, frame, n, n_exposure_samples).to(torch.float32)
        ppi = pixel_pose_index(row_time_ratio, n) if n > 1 else None
    if pose_delta is not None:
        poses = poses.to(pose_delta.device) @ se3_exp(pose_delta.to(torch.float32))
    return poses, ppi


def render_frame(gaussians, camera: Pinhole, poses: Tensor, ppi: Tensor | None, spec: MethodSpec,
                 config: TrainConfig, want_normal: bool = False) -> list:
    """Render the M exposure samples of one frame -> list of M RenderOutput (one image each)."""
    from egobench.render import render

    device = torch.device(config.device)
    bg = torch.tensor(config.background, dtype=torch.float32, device=device)
    outs = []
    for m in range(poses.shape[0]):  # exposure samples (1 unless the method asks for blur)
        outs.append(render(
            gaussians, camera, poses[m].to(device),
            pixel_pose_index=None if ppi is None else ppi.to(device),
            mode=spec.splat_mode, background=bg, backend=config.backend,
            want_normal=want_normal or spec.splat_mode == "2dgs",
        ))
    return outs


def _depth_normals(depth: Tensor, camera: Pinhole) -> Tensor:
    """Normals from a depth map [H, W] by central differences of the back-projected points -> [H, W, 3],
    facing the camera (negative z for a surface seen from the front) like the rendered normals
    (gsplat's ``depth_to_normal``: cross(d/drow, d/dcolumn)); zero on the border rows/columns."""
    grid = camera.pixel_grid(dtype=depth.dtype, device=depth.device)
    pts = camera.unproject(grid) * depth[..., None]  # [H, W, 3]
    d_col = torch.zeros_like(pts)
    d_row = torch.zeros_like(pts)
    d_col[:, 1:-1] = pts[:, 2:] - pts[:, :-2]  # along +u (camera +x)
    d_row[1:-1] = pts[2:] - pts[:-2]  # along +v (camera +y)
    n = torch.linalg.cross(d_row, d_col, dim=-1)  # y x x = -z: towards the camera
    return torch.nn.functional.normalize(n, dim=-1)


# ============================================================================= train
def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _check_finite(it: int, named: list[tuple[str, Tensor]]) -> None:
    """Raise TrainingDiverged naming the first non-finite tensor of ``named``. One host sync for
    all of them (a CUDA run does not stall on each tensor); the per-tensor search runs only on failure."""
    named = [(n, t.detach()) for n, t in named if t is not None]
    if not named or bool(torch.stack([torch.isfinite(t).all() for _, t in named]).all()):
        return
    for name, value in named:
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise TrainingDiverged(f"training diverged at iteration {it}: {name} is not finite "
                                   f"({bad} non-finite values); lower the learning rates or check the input")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _load_recording(recording_dir, spec: MethodSpec) -> Recording:
    if isinstance(recording_dir, Recording):
        if recording_dir.calibration != spec.calibration:
            raise ValueError(
                f"recording: method {spec.name!r} needs the {spec.calibration!r} calibration, got a recording "
                f"loaded with {recording_dir.calibration!r}"
            )
        return recording_dir
    from egobench.data import load_recording

    return load_recording(recording_dir, calibration=spec.calibration)


def train(recording_dir, method: str, config: TrainConfig, out_dir, *, resume: bool | Literal["auto"] = False,
          stop_after: int | None = None, progress: bool = True) -> TrainResult:
    """Train ``method`` on a recording (a folder, or a loaded `Recording` of the method's calibration).

    Writes ``out_dir/checkpoint.pt`` (atomic; every ``checkpoint_every`` and at the end) and
    ``out_dir/train.json``. ``resume`` continues from the checkpoint to the identical result of an
    uninterrupted run; ``resume="auto"`` (the workflow's choice) resumes a checkpoint of the same
    method and config and otherwise starts afresh (a stale checkpoint is replaced). ``stop_after`` ends after that many total iterations (as an interruption would:
    checkpoint written, no train.json).
    """
    from tqdm import tqdm

    spec = get_method(method)
    out_dir = Path(out_dir)
    ckpt_path = out_dir / "checkpoint.pt"
    rec = _load_recording(recording_dir, spec)
    data = prepare_data(rec, spec, config, progress=progress)
    device = torch.device(config.device)
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    formation = formation_model(spec)
    cam = data.camera
    F = len(data.frames)

    params = init_params(data, config, gen)
    params = {k: torch.nn.Parameter(v.detach().to(device)) for k, v in params.items()}
    lrs = {"means": config.lr_means * data.scene_scale, "scales": config.lr_scales, "quats": config.lr_quats,
           "opacities": config.lr_opacities, "colors": config.lr_colors}
    optimizers = {k: make_adam(params[k], lrs[k]) for k in GAUSSIAN_PARAMS}
    sched = torch.optim.lr_scheduler.ExponentialLR(
        optimizers["means"], gamma=config.lr_means_final_factor ** (1.0 / config.iterations))
    extra: dict[str, torch.nn.Parameter] = {}
    if spec.pose_optimisation:
        extra["pose_delta"] = torch.nn.Parameter(torch.zeros(F, 6, device=device))
    if spec.motion_sampling == "velocity_shift":
        from egobench.motion_sampling import frame_twist_camera

        extra["twist"] = torch.nn.Parameter(
            torch.stack([frame_twist_camera(rec, f) for f in data.frames]).float().to(device))
    extra_opt = {k: make_adam(v, config.lr_pose if k == "pose_delta" else config.lr_twist) for k, v in extra.items()}
    densifier = Densifier(DensifySchedule(
        grow_grad2d=config.grow_grad2d, grow_scale3d=config.grow_scale3d, prune_opa=config.prune_opa,
        prune_scale3d=config.prune_scale3d, refine_start_iter=config.refine_start_iter,
        refine_stop_iter=config.refine_stop_iter, refine_every=config.refine_every,
        reset_every=config.reset_every, opacity_reset=config.opacity_reset, max_gaussians=config.max_gaussians,
    ), scene_scale=data.scene_scale)

    # host store [F, H, W, 3] uint8 (page-locked by prepare_data on CUDA; not re-pinned here: pinning
    # copies, and a paper-scale store is tens of GiB); one frame per iteration goes to the device
    images = data.images
    mask3 = data.mask.to(device)[..., None].float()
    n_mask = float(mask3.sum()) * 3
    if n_mask == 0:
        raise ValueError(f"recording {rec.root}: the valid-pixel mask is empty at the training resolution")
    vignette = data.vignette.to(device)
    k = data.k.to(device)
    row_time_ratio = data.row_time_ratio.to(device)  # [H, W]: pixel-pose indices are built on the device
    from egobench.render import resolve_backend

    backend_used = resolve_backend(config.backend, device)  # loads (maybe builds) gsplat before timing starts
    if device.type == "cuda" and backend_used == "torch" and config.backend == "auto":
        print("egobench train: warning: gsplat's CUDA extension cannot be loaded (needs nvcc to build once); "
              "training with the pure-torch rasterizer, which is many times slower", file=sys.stderr)
    timing = {"time_s": 0.0, "render_fwd_s": 0.0, "render_bwd_s": 0.0, "iterations_timed": 0}
    order = torch.randperm(F, generator=gen)
    pos = 0
    start_it = 0
    last_loss = float("nan")

    if resume == "auto":
        resume = _checkpoint_matches(ckpt_path, method, config)
    if resume:
        if not ckpt_path.is_file():
            raise FileNotFoundError(f"{ckpt_path}: no checkpoint to resume from")
        ck = read_checkpoint(ckpt_path)  # weights_only; RNG states stay host tensors
        if ck.get("format") != CHECKPOINT_FORMAT or ck.get("method") != method:
            raise ValueError(f"{ckpt_path}: checkpoint is for method {ck.get('method')!r} (format {ck.get('format')}), not {method!r}")
        if ck["config_hash"] != config.hash(method):
            raise ValueError(f"{ckpt_path}: checkpoint was written with a different training config; resume needs the same")
        params = {k_: torch.nn.Parameter(v.to(device)) for k_, v in ck["params"].items()}
        optimizers = {k_: make_adam(params[k_], lrs[k_]) for k_ in GAUSSIAN_PARAMS}
        for k_, sd in ck["optimizers"].items():
            optimizers[k_].load_state_dict(sd)
        sched = torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=config.lr_means_final_factor ** (1.0 / config.iterations))
        sched.load_state_dict(ck["scheduler"])
        extra = {k_: torch.nn.Parameter(v.to(device)) for k_, v in ck["extra"].items()}
        extra_opt = {k_: make_adam(v, config.lr_pose if k_ == "pose_delta" else config.lr_twist) for k_, v in extra.items()}
        for k_, sd in ck["extra_optimizers"].items():
            extra_opt[k_].load_state_dict(sd)
        densifier.load_state_dict(ck["densifier"])
        torch.set_rng_state(ck["rng_torch"])
        if device.type == "cuda" and ck.get("rng_cuda") is not None:  # gsplat's split draws on the GPU
            torch.cuda.set_rng_state(ck["rng_cuda"], device)
        gen.set_state(ck["rng_frames"])
        order, pos, start_it = ck["order"], int(ck["pos"]), int(ck["iteration"])
        timing = dict(ck["timing"])
        last_loss = float(ck.get("last_loss", float("nan")))

    def save_checkpoint(iteration: int) -> None:
        state = {
            "format": CHECKPOINT_FORMAT, "method": method, "iteration": iteration,
            "config": config.to_dict(), "config_hash": config.hash(method),
            "params": {k_: v.detach().cpu() for k_, v in params.items()},
            "optimizers": {k_: o.state_dict() for k_, o in optimizers.items()},
            "scheduler": sched.state_dict(),
            "extra": {k_: v.detach().cpu() for k_, v in extra.items()},
            "extra_optimizers": {k_: o.state_dict() for k_, o in extra_opt.items()},
            "extra_frames": [f.index for f in data.frames],
            "densifier": densifier.state_dict(),
            "rng_torch": torch.get_rng_state(), "rng_frames": gen.get_state(),
            "rng_cuda": torch.cuda.get_rng_state(device) if device.type == "cuda" else None, "order": order, "pos": pos,
            "timing": timing, "last_loss": last_loss,
            "camera": cam.to_dict(), "scene_scale": data.scene_scale, "recording": str(rec.root),
            "n_samples": data.n_samples,
        }
        with atomic_path(ckpt_path) as tmp:
            torch.save(state, tmp)

    end_it = config.iterations if stop_after is None else min(config.iterations, int(stop_after))
    bar = tqdm(range(start_it, end_it), desc=f"train {method}", disable=not progress, file=sys.stderr,
               initial=start_it, total=config.iterations, mininterval=2.0)
    counts_used: list[int] = []
    for it in bar:
        t0 = time.perf_counter()
        if pos >= F:
            order, pos = torch.randperm(F, generator=gen), 0
        fi = int(order[pos])
        pos += 1
        frame = data.frames[fi]
        n = data.n_samples[fi] if it >= config.motion_warmup_iter else 1
        n_exp = spec.render_exposure_samples if it >= config.motion_warmup_iter else 1
        poses, ppi = frame_poses(rec, frame, spec, n, row_time_ratio,
                                 pose_delta=extra["pose_delta"][fi] if "pose_delta" in extra else None,
                                 twist=extra["twist"][fi] if "twist" in extra else None,
                                 n_exposure_samples=n_exp)
        counts_used.append(poses.shape[0] * poses.shape[1])
        g = gaussians_from_params(params)
        _sync(device)
        tr0 = time.perf_counter()
        outs = render_frame(g, cam, poses, ppi, spec, config)
        _sync(device)
        t_fwd = time.perf_counter() - tr0
        for o in outs:
            if o.means2d is not None and o.means2d.requires_grad:
                o.means2d.retain_grad()
        rgb = torch.stack([o.rgb[0] for o in outs]).mean(0)  # [H, W, 3] exposure samples averaged
        pred = predict_image(rgb, spec, k[fi], vignette, formation)
        gt = image_to_float(images[fi].to(device, non_blocking=True))  # [H, W, 3] 0..1
        l1 = ((pred - gt).abs() * mask3).sum() / n_mask
        from egobench.metrics import ssim_loss

        ssim_term = ssim_loss((pred * mask3)[None], (gt * mask3)[None])
        loss = (1 - config.ssim_lambda) * l1 + config.ssim_lambda * ssim_term
        if spec.splat_mode == "2dgs":
            loss = loss + _twodgs_regularisers(outs, cam, config, it, mask3)
        _check_finite(it, [("rendered rgb", rgb), ("loss", loss)])
        hook_t: list[float] = []
        rgb_leaf = outs[-1].rgb
        if rgb_leaf.requires_grad:
            rgb_leaf.register_hook(lambda grad: hook_t.append(time.perf_counter()) or None)
        loss.backward()
        _sync(device)
        t_bwd_end = time.perf_counter()
        t_bwd = (t_bwd_end - min(hook_t)) if hook_t else 0.0
        for o in outs:
            if o.means2d is not None and o.means2d.grad is not None and o.radii is not None:
                densifier.accumulate(params, it, o.means2d, o.radii, cam.width, cam.height)
        _check_finite(it, [(f"gradient of {name}", params[name].grad) for name in GAUSSIAN_PARAMS])
        for o in optimizers.values():
            o.step()
            o.zero_grad(set_to_none=True)
        for o in extra_opt.values():
            o.step()
            o.zero_grad(set_to_none=True)
        sched.step()
        densifier.refine(params, optimizers, it)
        _check_finite(it, [(name, params[name]) for name in GAUSSIAN_PARAMS] + list(extra.items()))
        last_loss = float(loss.detach())
        timing["time_s"] += time.perf_counter() - t0
        timing["render_fwd_s"] += t_fwd
        timing["render_bwd_s"] += t_bwd
        timing["iterations_timed"] += 1
        if progress and it % 50 == 0:
            bar.set_postfix(loss=f"{last_loss:.4f}", n=len(params["means"]))
        done = it + 1
        if config.checkpoint_every > 0 and done % config.checkpoint_every == 0 and done < end_it:
            save_checkpoint(done)
    bar.close()
    done = max(end_it, start_it)
    save_checkpoint(done)

    ts = timing["time_s"]
    its = timing["iterations_timed"]
    share = (timing["render_fwd_s"] + timing["render_bwd_s"]) / ts if ts > 0 else 0.0
    result = TrainResult(
        run_dir=out_dir, checkpoint=ckpt_path, iterations=done, num_gaussians=int(len(params["means"])),
        time_s=ts, iters_per_s=its / ts if ts > 0 else 0.0, raster_time_share=share, final_loss=last_loss,
    )
    ns = np.asarray(data.n_samples)
    record = {
        "schema": "egobench.train/1", "method": method, "method_label": spec.label, "seed": config.seed,
        "recording": str(rec.root), "scene": rec.name, "calibration": spec.calibration,
        "config": config.to_dict(), "config_hash": config.hash(method), "git_commit": _git_commit(),
        "egobench_version": __version__, "complete": done >= config.iterations,
        "train": {
            "iterations": done, "time_s": ts, "iters_per_s": result.iters_per_s,
            "raster_time_share": share, "num_gaussians": result.num_gaussians,
            "render_forward_s": timing["render_fwd_s"], "render_backward_s": timing["render_bwd_s"],
            "timing_method": "render() wall time + backward from the rgb hook to the end of loss.backward(), over iteration wall time",
            "device": config.device, "backend": backend_used, "final_loss": last_loss if math.isfinite(last_loss) else None,
            "image_store": {
                "dtype": str(images.dtype).replace("torch.", ""), "shape": list(images.shape),
                "mib": images.numel() * images.element_size() / 2**20,
                "pinned": bool(device.type == "cuda" and images.is_pinned()),
                "resized": [cam.height, cam.width] != [rec.camera.height, rec.camera.width],
            },
        },
        "camera": cam.to_dict(), "scene_scale": data.scene_scale,
        "motion_samples": {"mean": float(ns.mean()), "max": int(ns.max()), "min": int(ns.min()),
                           "warmup_iter": config.motion_warmup_iter, "rule": config.sample_rule},
        "densification_last": densifier.last_counts,
    }
    if record["complete"]:  # train.json marks a finished run (the workflow's output); an interrupted one has none
        write_json(out_dir / "train.json", record)
    result.record = record
    return result


def _twodgs_regularisers(outs: list, cam: Pinhole, config: TrainConfig, it: int, mask3: Tensor) -> Tensor:
    """2DGS losses: normal consistency (rendered normal vs depth normal) and distortion."""
    o = outs[0]
    zero = o.rgb.new_zeros(())
    total = zero
    if config.normal_lambda > 0 and it >= config.normal_start_iter and o.normal is not None:
        depth_n = _depth_normals(o.depth[0, ..., 0], cam)
        rend_n = torch.nn.functional.normalize(o.normal[0], dim=-1)
        err = (1 - (rend_n * depth_n).sum(-1)) * o.alpha[0, ..., 0].detach()
        total = total + config.normal_lambda * (err * mask3[..., 0]).sum() / mask3[..., 0].sum().clamp_min(1)
    if config.dist_lambda > 0 and it >= config.dist_start_iter and o.extras and "distortion" in o.extras:
        total = total + config.dist_lambda * o.extras["distortion"].mean()
    return total


# ============================================================================= CLI
def _checkpoint_matches(ckpt_path: Path, method: str, config: TrainConfig) -> bool:
    """True when ``ckpt_path`` holds a resumable checkpoint of ``method`` with this exact config."""
    if not ckpt_path.is_file():
        return False
    try:
        ck = read_checkpoint(ckpt_path)
    except ValueError as exc:  # a truncated or foreign file: start afresh, say so
        print(f"egobench train: {ckpt_path}: unreadable checkpoint ({exc}); starting afresh", file=sys.stderr)
        return False
    same = (ck.get("format") == CHECKPOINT_FORMAT and ck.get("method") == method
            and ck.get("config_hash") == config.hash(method))
    if not same:
        print(f"egobench train: {ckpt_path}: checkpoint of another method or config; starting afresh", file=sys.stderr)
    return same


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recording", required=True,
                        help="recording: a rectified stream folder (<label>-rectified-<focal>-h<size>) or the folder holding it")
    parser.add_argument("--method", required=True, help="method name (egobench.methods)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--out", required=True, help="run folder (checkpoint.pt, train.json)")
    parser.add_argument("--iterations", type=int, default=None, help="iterations (schedule scaled to it)")
    parser.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                        help="starting config: 'cpu' (small, ~1 min) or 'paper' (30K, full resolution)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override a TrainConfig field")
    parser.add_argument("--resume", nargs="?", const="yes", choices=("yes", "auto"), default=None,
                        help="continue from RUN_DIR/checkpoint.pt; 'auto': only if it matches this method and "
                             "config, else start afresh (what the workflow passes)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    from egobench.data.reader import add_input_arguments

    add_input_arguments(parser)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    config = TrainConfig.cpu() if args.preset == "cpu" else TrainConfig()
    config = parse_overrides(config, args.set)
    config = replace(config, seed=int(args.seed))
    if args.iterations is not None:
        config = config.scaled_to(args.iterations)
    return config


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    try:
        resume = {None: False, "yes": True, "auto": "auto"}[args.resume]
        from egobench.data.reader import recording_from_args

        recording = recording_from_args(args.recording, get_method(args.method).calibration, args)
        res = train(recording, args.method, config, args.out, resume=resume,
                    progress=not getattr(args, "no_progress", False))
    except TrainingDiverged as exc:
        print(f"egobench train: error: {exc}", file=sys.stderr)
        return 3
    print(f"trained {args.method}: {res.iterations} iterations, {res.num_gaussians} Gaussians, "
          f"{res.iters_per_s:.1f} it/s, raster share {res.raster_time_share:.2f} -> {res.checkpoint}")
    return 0


# ============================================================================= toy data
class _TwistTrajectory:
    """Analytic trajectory T_world_device(t) = T0 exp((t - t0) xi) with the `Trajectory` query API."""

    def __init__(self, T0: Tensor, xi_per_s: Tensor, t0_ns: int) -> None:
        self.T0, self.xi, self.t0_ns = T0.to(torch.float64), xi_per_s.to(torch.float64), int(t0_ns)

    def pose(self, t_ns) -> Tensor:
        from egobench.geometry import se3_exp

        t = torch.as_tensor(t_ns).reshape(-1).to(torch.float64)
        dt = (t - self.t0_ns) * 1e-9
        return self.T0[None] @ se3_exp(dt[:, None] * self.xi[None])

    def velocity(self, t_ns):
        from egobench.geometry import TrajectoryVelocity

        T = self.pose(t_ns)
        lin = (T[:, :3, :3] @ self.xi[:3, None])[..., 0]
        return TrajectoryVelocity(linear_world=lin, angular_device=self.xi[3:].expand(T.shape[0], 3).clone())


def toy_recording(root: Path, size: int = 32, n_frames: int = 9, angular_speed_rad_s: float = 0.0,
                  readout_s: float = 5e-3, seed: int = 0, n_points: int = 2000,
                  frame_interval_s: float = 0.05, with_ground_truth: bool = False) -> Recording:
    """A tiny synthetic recording for tests and benchmarks (images rendered by our rasterizer).

    Scene: a textured plane of Gaussians 2.5 m in front of a camera that translates 2 m along x (and
    rotates about y at ``angular_speed_rad_s``); images are the centre-row renders (no formation
    effects: exposure 1 ms, gain 1 for every frame, flat vignette), sparse depth from the points.
    ``with_ground_truth`` also writes ground_truth/depth and ground_truth/normal (.npy, float16).
    """
    import cv2

    from egobench.data.recording import SparseDepth
    from egobench.render import render
    from egobench.render.types import Gaussians

    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(seed)
    cam = Pinhole(fx=size * 0.9, fy=size * 0.9, cx=(size - 1) / 2, cy=(size - 1) / 2, width=size, height=size)
    # Ground-truth scene: a grid of coloured Gaussians on the plane z = 2.5 (x in +-3 m, y in +-2 m).
    side = 30
    xs, ys = torch.linspace(-3.0, 3.0, side), torch.linspace(-2.0, 2.0, side)
    gx, gy = torch.meshgrid(xs, ys, indexing="xy")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((side * side,), 2.5)], -1)
    N = len(means)
    cols = 0.5 + 0.4 * torch.stack([torch.sin(3 * means[:, 0]), torch.cos(4 * means[:, 1]),
                                    torch.sin(2 * (means[:, 0] + means[:, 1]))], -1)
    sx, sy = float(xs[1] - xs[0]), float(ys[1] - ys[0])
    truth = Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).repeat(N, 1),
                      log_scales=torch.log(torch.tensor([sx * 0.6, sy * 0.6, 0.01])).repeat(N, 1),
                      opacity_logits=torch.full((N,), 3.0), colors=cols)
    t0 = 1_000_000_000
    dt_ns = int(round(frame_interval_s * 1e9))
    # The camera translates 2 m along x over the frames (gsplat's scene scale ~ 1.1 m) and yaws at
    # angular_speed_rad_s; the middle frame sits at x = 0 looking down +z.
    duration_s = max(n_frames - 1, 1) * dt_ns * 1e-9
    xi = torch.tensor([2.0 / duration_s, 0.0, 0.0, 0.0, angular_speed_rad_s, 0.0], dtype=torch.float64)
    traj = _TwistTrajectory(torch.eye(4, dtype=torch.float64), xi, t0 + (n_frames // 2) * dt_ns)
    exposure_s = 1e-3
    frames = []
    for i in range(n_frames):
        ts = t0 + i * dt_ns
        T_wc = traj.pose(torch.tensor([ts]))[0]
        with torch.no_grad():
            out = render(truth, cam, T_wc[None].float(), pixel_pose_index=None, mode="3dgs",
                         background=torch.zeros(3), backend="auto", want_normal=with_ground_truth)
        if with_ground_truth:
            for kind, arr in (("depth", out.depth[0, ..., 0]), ("normal", out.normal[0])):
                (root / "ground_truth" / kind).mkdir(parents=True, exist_ok=True)
                np.save(root / "ground_truth" / kind / f"{i:05d}.npy", arr.numpy().astype(np.float16))
        img = (out.rgb[0].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        path = root / "images" / f"{i:05d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        T_cw = torch.linalg.inv(T_wc)
        pc = (means.double() @ T_cw[:3, :3].T + T_cw[:3, 3])
        uv, valid = cam.project(pc)
        ok = valid & (uv[:, 0] >= 0) & (uv[:, 0] <= size - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= size - 1)
        sd = SparseDepth(uv=uv[ok].numpy(), z=pc[ok, 2].numpy(), inv_dist_std=np.full(int(ok.sum()), 1e-3),
                         dist_std=np.full(int(ok.sum()), 1e-3))
        read_start = ts - int(readout_s * 1e9 / 2) - int(exposure_s * 1e9 / 2)
        frames.append(Frame(index=i, image_path=path, timestamp_ns=ts, read_start_ns=read_start,
                            read_end_ns=read_start + int(readout_s * 1e9), exposure_s=exposure_s, gain=1.0,
                            T_world_camera=T_wc, T_device_camera=torch.eye(4, dtype=torch.float64), sparse_depth=sd))
    # Initial points: n_points random points on the plane (SLAM-like: positions only, slightly noisy).
    u = torch.rand(n_points, 2, generator=gen)
    pts = torch.stack([-3 + 6 * u[:, 0], -2 + 4 * u[:, 1], 2.5 + 0.01 * torch.randn(n_points, generator=gen)], -1)
    v = torch.arange(size, dtype=torch.float32) / (size - 1)
    return Recording(
        root=root, name="toy", calibration="online", camera=cam, camera_model="linear", frames=frames,
        vignette=torch.ones(size, size), mask=torch.ones(size, size, dtype=torch.bool),
        row_time_ratio=v[:, None].expand(size, size).contiguous(), trajectory=traj,
        points_world=pts.float(), meta={"scene_kind": "toy", "device": "toy"},
        ground_truth=(root / "ground_truth") if with_ground_truth else None,
    )
