"""The per-frame render path shared by training, evaluation and diagnosis.

Given Gaussians, a recording and one of its frames: the poses the method renders the frame
with (centre row; K rolling-shutter samples gathered per pixel by the row-time image R(u); M
exposure samples averaged; or the velocity-shift model of 3DGS-on-the-move), the rasterized
scene colour, and the method's image formation (exposure*gain normaliser k, vignette,
response, scene gamma) that turns it into a predicted captured image (docs/paper-notes.md §2).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np
import torch
from torch import Tensor

import egobench.render  # `egobench.render.render`, looked up at each call (tests replace it)
from egobench.camera.pinhole import Pinhole
from egobench.data.recording import Frame, Recording
from egobench.geometry import se3_exp
from egobench.model import frame_exposure
from egobench.model import motion_sampling  # its functions looked up at each call (tests replace them)
from egobench.model.formation import FormationConfig, FormationModel, exposure_gain_normaliser
from egobench.model.methods import MethodSpec
from egobench.model.pose_sampling import PoseSampling
from egobench.model.shading import learned_vignette
from egobench.render.types import Gaussians, RenderOutput, first_image


def resize_map(x: Tensor, camera: Pinhole, kind: Literal["area", "nearest"] = "area") -> Tensor:
    """Resize an [H, W] or [H, W, C] map to the camera's size (area average, or nearest)."""
    if tuple(x.shape[:2]) == (camera.height, camera.width):
        return x
    interp = cv2.INTER_AREA if kind == "area" else cv2.INTER_NEAREST
    arr = x.detach().cpu().numpy().astype(np.float32)
    out = cv2.resize(arr, (camera.width, camera.height), interpolation=interp)
    return torch.from_numpy(out.reshape(camera.height, camera.width, *x.shape[2:]))


@dataclass
class FrameMaps:
    """The recording's per-pixel maps at a rendering camera's size."""

    mask: Tensor  # [H, W] bool valid pixels
    vignette: Tensor  # [H, W] float32
    row_time_ratio: Tensor  # [H, W] float32 R(u)
    timing_ms: Tensor | None = None  # [2] a run's learned timing correction (time offset, readout error; ms)


def frame_maps(recording: Recording, camera: Pinhole) -> FrameMaps:
    """Mask (area-resized, kept where fully valid), vignette and R(u) at ``camera``'s size."""
    return FrameMaps(mask=resize_map(recording.mask.float(), camera) > 0.999,
                     vignette=resize_map(recording.vignette.float(), camera),
                     row_time_ratio=resize_map(recording.row_time_ratio.float(), camera))


def run_maps(recording: Recording, run) -> FrameMaps:
    """`frame_maps` at a trained run's camera, its vignette times the lens shading the run learned
    (`egobench.model.shading`; unchanged for runs without one)."""
    maps = frame_maps(recording, run.camera)
    extra = run.checkpoint.get("extra") or {}
    return replace(maps, vignette=learned_vignette(maps.vignette, run.camera, extra, run.config),
                   timing_ms=learned_timing_ms(run))


def learned_timing_ms(run) -> Tensor | None:
    """The timing correction [2] (ms, float32, CPU) a trained run learned with its scene, or None."""
    timing = (run.checkpoint.get("extra") or {}).get(motion_sampling.TIMING_KEY)
    return None if timing is None else timing.detach().to(torch.float32).cpu()


def exposure_normaliser(recording: Recording) -> Tensor:
    """k [F] over all frames of the recording (exposure*gain / median), float32."""
    exposure = torch.tensor([f.exposure_s for f in recording.frames], dtype=torch.float64)
    gain = torch.tensor([f.gain for f in recording.frames], dtype=torch.float64)
    return exposure_gain_normaliser(exposure, gain).to(torch.float32)


def method_normaliser(recording: Recording, spec: MethodSpec) -> dict[int, Tensor]:
    """Frame index -> the k the method predicts that frame with (1 for methods without formation)."""
    k_all = exposure_normaliser(recording) if spec.formation else torch.ones(len(recording.frames))
    return {f.index: k_all[i] for i, f in enumerate(recording.frames)}


def run_normaliser(recording: Recording, run) -> dict[int, Tensor]:
    """`method_normaliser` of a trained run, with the exposure corrections the run learned with its scene
    (`egobench.model.frame_exposure`): each training frame's k times its own, and every other frame's (held out)
    times the median one. A scale shared by every frame is the scene's to take (the frames' scales have no zero
    of their own), so the median carries that share to the frames that learned none (frames matched by the
    checkpoint's ``extra_frames``). Unchanged for runs without one."""
    k_of = method_normaliser(recording, run.spec)
    scale = (run.checkpoint.get("extra") or {}).get(frame_exposure.KEY)
    if scale is None:
        return k_of
    where = f"{run.path}: checkpoint.pt"
    if "extra_frames" not in run.checkpoint:
        raise ValueError(f"{where}: field 'extra_frames' is missing: expected the recording's frame indices that "
                         f"the {scale.numel()} values of 'extra.{frame_exposure.KEY}' belong to")
    trained = [int(i) for i in run.checkpoint["extra_frames"]]
    if len(trained) != scale.numel():
        raise ValueError(f"{where}: field 'extra.{frame_exposure.KEY}': {scale.numel()} values for "
                         f"{len(trained)} frames in 'extra_frames'")
    missing = sorted(set(trained) - set(k_of))
    if missing:
        raise ValueError(f"{where}: field 'extra_frames': frames {missing[:5]} are not in the recording")
    scale = scale.detach().to(torch.float32).cpu()
    shared = scale.median().exp()
    learned = dict(zip(trained, scale.exp()))
    return {i: k * learned.get(i, shared) for i, k in k_of.items()}


def sample_counts(recording: Recording, frames: list[Frame], spec: MethodSpec,
                  sampling: PoseSampling, pixel_scale: float) -> list[int]:
    """Rolling-shutter sample count per frame at the rendering resolution (1 for centre methods), by
    ``sampling`` (`TrainConfig.pose_sampling`: the rule a run was trained with).

    A frame whose sparse depth is empty gets 1 sample (as the released code: it cannot see motion).
    """
    if spec.motion_sampling == "centre":
        return [1] * len(frames)
    counts = []
    for f in frames:  # per frame (not per pixel)
        if f.sparse_depth is None or len(f.sparse_depth.z) == 0:
            counts.append(1)
            continue
        counts.append(motion_sampling.n_pose_samples(recording, f, sampling, pixel_scale))
    return counts


def gaussians_from_params(params: dict) -> "Gaussians":
    """The trainer's parameter dict (means, scales, quats, opacities, colors) as `Gaussians`."""
    return Gaussians(means=params["means"], quats=params["quats"], log_scales=params["scales"],
                     opacity_logits=params["opacities"], colors=params["colors"])


def formation_model(spec: MethodSpec):
    """The trainer's image formation model for ``spec`` (its response gamma)."""
    return FormationModel(FormationConfig.paper_trainer(gamma=spec.response_gamma))


def predict_image(rgb: Tensor, spec: MethodSpec, k: Tensor | float, vignette: Tensor, formation) -> Tensor:
    """Rasterized scene colour [H, W, 3] -> predicted captured image [H, W, 3] in [0, 1]."""
    if not spec.formation:
        return rgb.clamp(0.0, 1.0)
    return formation.predict(rgb, scale_k=k, vignette=vignette, scene_gamma=spec.scene_gamma)


class PoseSampleCache:
    """One run's trainable-free part of `frame_poses` (the trainer asks for it every step): a frame's
    trajectory samples per (frame, n, M) and the pixel pose index per n, for a fixed row time ratio."""

    def __init__(self) -> None:
        self.poses: dict[tuple[int, int, int], Tensor] = {}  # (frame timestamp, n, M) -> [M, n, 4, 4] float32
        self.ppi: dict[int, Tensor] = {}  # n -> [H, W] int64
        self.twists: dict[int, Tensor] = {}  # frame timestamp -> [6] float32

    def samples(self, recording: Recording, frame: Frame, n: int, n_exposure_samples: int,
                row_time_ratio: Tensor) -> tuple[Tensor, Tensor | None]:
        key = (int(frame.timestamp_ns), n, n_exposure_samples)
        if key not in self.poses:
            self.poses[key] = motion_sampling.exposure_pose_samples(recording, frame, n, n_exposure_samples).to(torch.float32)
        if n > 1 and n not in self.ppi:
            self.ppi[n] = motion_sampling.pixel_pose_index(row_time_ratio, n)
        return self.poses[key], self.ppi.get(n) if n > 1 else None

    def twist(self, recording: Recording, frame: Frame) -> Tensor:
        """The frame's camera twist [6] float32 at its centre-row time (`motion_sampling.frame_twist_camera`)."""
        key = int(frame.timestamp_ns)
        if key not in self.twists:
            self.twists[key] = motion_sampling.frame_twist_camera(recording, frame).to(torch.float32)
        return self.twists[key]


def frame_poses(recording: Recording, frame: Frame, spec: MethodSpec, n: int, row_time_ratio: Tensor,
                pose_delta: Tensor | None = None, twist: Tensor | None = None,
                n_exposure_samples: int = 1, cache: PoseSampleCache | None = None,
                timing: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Poses to render one frame: (T_world_camera [M, K, 4, 4] float32, pixel_pose_index [H, W] | None).

    M exposure samples (averaged by the caller), K rolling-shutter samples gathered per pixel.
    ``pose_delta`` [6] (se(3), right-multiplied) and ``twist`` [6] are the per-frame trainables of
    pose-optimising / velocity-shift methods. ``timing`` [2] (ms) is a run's timing correction (time offset,
    readout error; `TrainConfig.learn_timing`): each sample moves along the frame's twist by its time shift
    (`motion_sampling.timed_poses`). ``cache`` (a run's, for its fixed ``row_time_ratio``) keeps the trajectory
    samples, pixel indices and twists between calls.
    """
    if spec.motion_sampling == "velocity_shift":
        return _velocity_shift_poses(recording, frame, n, row_time_ratio, pose_delta, twist, n_exposure_samples)
    cache = cache if cache is not None else PoseSampleCache()  # without a run's, a throwaway one: one code path
    if n == 1 and n_exposure_samples == 1:
        poses = frame.T_world_camera.to(torch.float32)[None, None]
        ppi = None
    else:
        poses, ppi = cache.samples(recording, frame, n, n_exposure_samples, row_time_ratio)
    if timing is not None:
        poses = motion_sampling.timed_poses(poses, cache.twist(recording, frame), timing)
    if pose_delta is not None:
        poses = poses.to(pose_delta.device) @ se3_exp(pose_delta.to(torch.float32))
    return poses, ppi


def _velocity_shift_poses(recording: Recording, frame: Frame, n: int, row_time_ratio: Tensor,
                          pose_delta: Tensor | None, twist: Tensor | None,
                          n_exposure_samples: int) -> tuple[Tensor, Tensor | None]:
    """3DGS-on-the-move: the centre pose moved by a constant twist over the pinhole row times."""
    H, W = row_time_ratio.shape
    T_c = frame.T_world_camera.to(torch.float32)
    if pose_delta is not None:  # a trainable on the training device: the host pose follows it
        T_c = T_c.to(pose_delta.device) @ se3_exp(pose_delta.to(torch.float32))
    if twist is None:
        twist = motion_sampling.frame_twist_camera(recording, frame).to(torch.float32)
    times = motion_sampling.sample_times_ns(frame, n, n_exposure_samples)  # [M, K]
    dt = ((times - float(frame.timestamp_ns)) * 1e-9).reshape(-1)
    poses = motion_sampling.velocity_poses(T_c, twist.to(torch.float32), dt).reshape(times.shape[0], n, 4, 4)
    ppi = motion_sampling.pixel_pose_index(motion_sampling.linear_row_time_ratio(H, W).to(row_time_ratio.device), n) if n > 1 else None
    return poses, ppi


@dataclass
class RenderSettings:
    """How a run renders: the device, its background colour and the rasterizer backend."""

    device: torch.device
    background: tuple[float, float, float]
    backend: str

    @classmethod
    def of(cls, config, device: torch.device | str | None = None) -> "RenderSettings":
        """From a `TrainConfig` (``device`` overrides ``config.device``)."""
        return cls(torch.device(device if device is not None else config.device), tuple(config.background),
                   config.backend)


def render_frame(gaussians, camera: Pinhole, poses: Tensor, ppi: Tensor | None, spec: MethodSpec,
                 settings: RenderSettings, want_normal: bool = False) -> list["RenderOutput"]:
    """Render the M exposure samples of one frame -> list of M RenderOutput (one image each)."""
    device = settings.device
    bg = torch.tensor(settings.background, dtype=torch.float32, device=device)
    outs = []
    for m in range(poses.shape[0]):  # exposure samples (1 unless the method asks for blur)
        outs.append(egobench.render.render(
            gaussians, camera, poses[m].to(device),
            pixel_pose_index=None if ppi is None else ppi.to(device),
            mode=spec.splat_mode, background=bg, backend=settings.backend,
            want_normal=want_normal or spec.splat_mode == "2dgs",
        ))
    return outs


def mean_rgb(outs: list["RenderOutput"]) -> Tensor:
    """The exposure samples' scene colour averaged -> [H, W, 3] (one sample: itself, the mean's value,
    without the stack, the mean and their autograd nodes)."""
    if len(outs) == 1:
        return first_image(outs[0].rgb)
    return torch.stack([first_image(o.rgb) for o in outs]).mean(0)


@dataclass
class FramePrediction:
    """One frame predicted: the captured image, the scene colour and the raw render outputs."""

    image: Tensor  # [H, W, 3] predicted captured image in [0, 1]
    rgb: Tensor  # [H, W, 3] scene colour (exposure samples averaged), on the CPU
    outs: list  # M RenderOutput


def predict_frame(gaussians, recording: Recording, frame: Frame, spec: MethodSpec, camera: Pinhole,
                  maps: FrameMaps, k: Tensor | float, n_samples: int, settings: RenderSettings,
                  formation) -> FramePrediction:
    """Render ``frame`` with the method's poses (``n_samples`` rolling-shutter samples and its exposure
    samples) and formation; the image formation runs on the CPU (float, as the metrics)."""
    poses, ppi = frame_poses(recording, frame, spec, n_samples, maps.row_time_ratio,
                             n_exposure_samples=spec.render_exposure_samples, timing=maps.timing_ms)
    outs = render_frame(gaussians, camera, poses, ppi, spec, settings)
    rgb = mean_rgb(outs).cpu()
    image = predict_image(rgb, spec, k, maps.vignette, formation)
    return FramePrediction(image=image, rgb=rgb, outs=outs)


@dataclass
class RunRenderer:
    """A trained run set up to render a recording's frames as it was trained to: the recording's maps at the run's
    camera (`run_maps`), its normaliser (`run_normaliser`), formation (`formation_model`) and render settings."""

    run: object  # the trained run (`egobench.train.checkpoint.TrainedRun`)
    recording: Recording
    maps: FrameMaps
    k_of: dict[int, Tensor]  # frame index -> k
    formation: FormationModel
    settings: RenderSettings

    @classmethod
    def of(cls, recording: Recording, run) -> "RunRenderer":
        """``run``'s renderer of ``recording``."""
        return cls(run, recording, run_maps(recording, run), run_normaliser(recording, run), formation_model(run.spec),
                   RenderSettings.of(run.config))

    def pose_samples(self, frames: list[Frame]) -> list[int]:
        """The frames' rolling-shutter pose samples by the run's rule (`sample_counts`), at the run's size: the
        recording's pixel motion scaled by the run's width over the recording's (1 where they match)."""
        return sample_counts(self.recording, frames, self.run.spec, self.run.config.pose_sampling,
                             self.run.camera.width / self.recording.camera.width)

    def predict(self, frame: Frame, n_samples: int, maps: FrameMaps | None = None) -> FramePrediction:
        """`predict_frame` of ``frame`` with ``n_samples`` pose samples, with ``maps`` in place of the run's own."""
        return predict_frame(self.run.gaussians, self.recording, frame, self.run.spec, self.run.camera,
                             self.maps if maps is None else maps, self.k_of[frame.index], n_samples, self.settings,
                             self.formation)
