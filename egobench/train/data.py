"""Training data: a recording validated and prepared at the training resolution.

Image store: the training images stay on the host as uint8 [F, H, W, 3] (`load_image_store`; a
2400 px frame is 16.5 MiB, so paper-scale recordings fit), page-locked when training on CUDA;
each iteration copies only its own frame to the device and converts it to float / 255.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm import tqdm

from egobench.camera.pinhole import Pinhole
from egobench.data.recording import Frame, Recording
from egobench.model.methods import MethodSpec
from egobench.model.predict import FrameMaps, frame_maps, method_normaliser, resize_map, sample_counts
from egobench.train.config import TrainConfig


@dataclass
class TrainingData:
    """A recording prepared for training at the training resolution."""

    recording: Recording
    spec: MethodSpec
    camera: Pinhole  # training-resolution camera
    frames: list[Frame]  # training frames (time order)
    images: Tensor  # [F, H, W, 3] uint8 captured images (the image store, see `load_image_store`)
    maps: FrameMaps  # valid mask, vignette and R(u) at the training resolution
    k: Tensor  # [F] float32 exposure*gain normaliser of the training frames
    n_samples: list[int]  # rolling-shutter pose samples per training frame (1 for centre methods)
    scene_scale: float


def training_camera(camera: Pinhole, config: TrainConfig) -> Pinhole:
    """The rectified camera at the training resolution."""
    scale = config.resolution_scale
    if config.max_side > 0:
        scale = min(scale, config.max_side / max(camera.width, camera.height))
    return camera if abs(scale - 1.0) < 1e-12 else camera.scaled(scale)


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
    if not any(points_in_view(recording, f) for f in recording.train_frames):
        raise ValueError(f"{where}: none of the {len(recording.train_frames)} training frames sees any of the "
                         f"{len(recording.points_world)} semi-dense points (camera poses and points disagree: "
                         "a trajectory or points file of another recording?)")


def points_in_view(recording: Recording, frame: Frame) -> int:
    """How many semi-dense points project in front of the camera and inside the image at the frame's centre pose."""
    T = frame.T_world_camera.to(torch.float64)
    p_cam = (recording.points_world.to(torch.float64) - T[:3, 3]) @ T[:3, :3]
    front = p_cam[:, 2] > 1e-6
    uv, _ = recording.camera.project(p_cam[front])
    W, H = recording.camera.width, recording.camera.height
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
    return int(inside.sum())



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
    k_of = method_normaliser(recording, spec)
    counts = sample_counts(recording, frames, spec, config.pose_sampling,
                           pixel_scale=cam.width / recording.camera.width)
    return TrainingData(
        recording=recording, spec=spec, camera=cam, frames=frames, images=images, maps=frame_maps(recording, cam),
        k=torch.stack([k_of[f.index] for f in frames]), n_samples=counts,
        scene_scale=config.scene_scale if config.scene_scale > 0 else scene_scale_of(frames, recording.points_world),
    )
