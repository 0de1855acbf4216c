"""Training settings: `TrainConfig` (schedule as fractions of the paper's 30K iterations), its
presets and ``--set field=value`` overrides."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Literal

from egobench.model.pose_sampling import DEFAULT_MAX_SAMPLES, PoseSampling, SampleRule, sampling_problem

#: Length of the paper's schedule; schedule fields below are fractions of it.
PAPER_ITERATIONS = 30_000


#: TrainConfig fields added after runs were trained: `TrainConfig.hash` leaves each out at its default.
HASHED_WHEN_SET = ("pose_sample_step_px", "learn_timing", "lr_timing", "learn_frame_exposure", "lr_frame_exposure")
#: TrainConfig's field of each `PoseSampling` field
SAMPLING_FIELDS = {"max_samples": "max_pose_samples", "rule": "sample_rule", "step_px": "pose_sample_step_px"}


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. Schedule points are fractions of the paper's 30K iterations, so a short
    run scales them (`scaled_to`); absolute values are the properties ``*_iter``."""

    iterations: int = PAPER_ITERATIONS  # optimisation steps (paper: 30K)
    resolution_scale: float = 1.0  # factor applied to the rectified camera (images resized, area filter)
    max_side: int = 0  # if > 0, further downscale so that max(W, H) <= max_side (CPU budget)
    lr_means: float = 1.6e-4  # Adam lr of means, times scene_scale; decays exponentially...
    lr_means_final_factor: float = 0.01  # ...to this fraction of its initial value at the last iteration
    # True: lr_means times PAPER_ITERATIONS / iterations on a shorter schedule (`lr_means_at`), so that a
    # Gaussian can travel as far as in the paper's 30K steps (Adam moves a mean by about its lr per step)
    means_travel_matched: bool = False
    lr_scales: float = 5e-3  # Adam lr of log-scales
    lr_quats: float = 1e-3  # Adam lr of quaternions
    lr_opacities: float = 5e-2  # Adam lr of opacity logits
    lr_colors: float = 2.5e-3  # Adam lr of colours (RGB, scene-colour space)
    lr_pose: float = 1e-4  # Adam lr of per-frame pose corrections (se(3), methods with pose_optimisation)
    lr_twist: float = 1e-3  # Adam lr of per-frame velocities (velocity_shift methods)
    # Model extension (egobench.model.shading): a radial lens shading exp(a2 r^2 + a4 r^4) on top of the stated
    # vignette, learned with the scene; its centre can be moved (fractions of width / height: a placebo)
    learn_shading: bool = False
    lr_shading: float = 1e-2  # Adam lr of the shading coefficients
    shading_centre_dx: float = 0.0
    shading_centre_dy: float = 0.0
    # Model extension (egobench.model.motion_sampling.timed_poses): a time offset and a readout error (ms) learned
    # with the scene, moving every pose sample along its frame's twist by its time shift
    learn_timing: bool = False
    lr_timing: float = 1e-2  # Adam lr of the timing correction, ms
    # Model extension (egobench.model.frame_exposure): each training frame's exposure x gain corrected by a log scale
    # learned with the scene
    learn_frame_exposure: bool = False
    lr_frame_exposure: float = 1e-2  # Adam lr of the per-frame log scales
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
    max_pose_samples: int = DEFAULT_MAX_SAMPLES  # cap on rolling-shutter pose samples per frame (released code: 8)
    sample_rule: SampleRule = "code"  # how the sample count is chosen (motion_sampling)
    pose_sample_step_px: float = 1.0  # pixels of row shear one pose sample covers (released code: 1)
    normal_lambda: float = 0.05  # 2DGS normal-consistency weight...
    normal_start_frac: float = 7_000 / PAPER_ITERATIONS  # ...from this fraction (paper 7K)
    dist_lambda: float = 0.01  # 2DGS distortion weight...
    dist_start_frac: float = 3_000 / PAPER_ITERATIONS  # ...from this fraction (paper 3K)
    init_opacity: float = 0.1  # initial opacity of every Gaussian
    init_scale: float = 1.0  # initial scale = this x RMS distance to the 3 nearest points
    # initial colours: "image" (each point's colour in the first training image it projects into, the
    # method's formation inverted) or "grey" (0.5 in the model's colour space, as the authors' code, whose
    # MPS points carry no colour: linear 0.5 for w/o scene gamma, gamma-space 0.5 otherwise)
    init_colour: Literal["image", "grey"] = "image"
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
        if self.init_colour not in ("image", "grey"):
            raise ValueError(f"TrainConfig.init_colour: expected 'image' or 'grey', got {self.init_colour!r}")
        if not 0 <= self.ssim_lambda <= 1:
            raise ValueError(f"TrainConfig.ssim_lambda: expected a value in [0, 1], got {self.ssim_lambda}")
        bad = sampling_problem(**self._sampling_fields())
        if bad is not None:  # `PoseSampling`'s own check, in TrainConfig's names
            raise ValueError(f"TrainConfig.{SAMPLING_FIELDS[bad[0]]}: {bad[1]}")
        for name in ("lr_shading", "lr_timing", "lr_frame_exposure"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TrainConfig.{name}: expected > 0, got {getattr(self, name)}")
        if len(self.background) != 3:
            raise ValueError(f"TrainConfig.background: expected 3 values, got {self.background}")

    # ---- absolute schedule -----------------------------------------------------------------
    def _at(self, frac: float) -> int:
        return int(frac * self.iterations)

    @property
    def lr_means_at(self) -> float:
        """The means' initial lr (times scene_scale in the trainer): ``lr_means``, or with
        ``means_travel_matched`` on a schedule shorter than the paper's, lr_means x 30K / iterations."""
        if self.means_travel_matched and self.iterations < PAPER_ITERATIONS:
            return self.lr_means * PAPER_ITERATIONS / self.iterations
        return self.lr_means

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
        compressed schedule, growing every 2-3 iterations compounds before new Gaussians settle. The means'
        lr matched to the paper's travel (``means_travel_matched``): measured at 1000 iterations, 128 px, on
        the 64 ms outdoor sensitivity recording, 'ours' held-out PSNR 28.34 -> 30.18 dB (docs/fidelity.md)."""
        base = dict(iterations=800, max_side=64, max_gaussians=8000, refine_every_frac=1_000 / PAPER_ITERATIONS,
                    means_travel_matched=True)
        base.update(overrides)
        return cls(**base)

    @property
    def pose_sampling(self) -> PoseSampling:
        """The rolling-shutter sampling rule every render of this run uses (training, evaluation, diagnosis)."""
        return PoseSampling(**self._sampling_fields())

    def _sampling_fields(self) -> dict:
        """{`PoseSampling` field: this config's value} (`SAMPLING_FIELDS`)."""
        return {field: getattr(self, own) for field, own in SAMPLING_FIELDS.items()}

    def to_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        return d

    def hash(self, method: str) -> str:
        """sha1 of the canonical JSON of (method, config); a field added later is left out at its default
        (`HASHED_WHEN_SET`), so that runs trained before it existed keep their hash."""
        defaults = {f.name: f.default for f in fields(self) if f.name in HASHED_WHEN_SET}
        config = {k: v for k, v in self.to_dict().items() if k not in defaults or v != defaults[k]}
        blob = json.dumps({"method": method, "config": config}, sort_keys=True, separators=(",", ":"))
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



#: Starting configs of ``egobench train --preset`` (and ``diagnose --train``).
PRESETS = ("cpu", "paper")


def preset_config(name: str) -> TrainConfig:
    """The named starting config: 'cpu' (`TrainConfig.cpu`, small and fast) or 'paper' (30K, full size)."""
    if name not in PRESETS:
        raise ValueError(f"preset {name!r}: expected one of {', '.join(PRESETS)}")
    return TrainConfig.cpu() if name == "cpu" else TrainConfig()
