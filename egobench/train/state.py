"""The optimisation state of one run: Gaussian parameters with their Adam optimisers and learning-rate
schedule, the per-frame pose/velocity trainables, the densifier, the seeded frame order and the
counters a resume needs. `TrainState` converts to and from the checkpoint dict."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from egobench.model import frame_exposure
from egobench.model.adam import adam_step
from egobench.model.motion_sampling import TIMING_KEY, frame_twist_camera
from egobench.model.optim import GAUSSIAN_PARAMS, DensifySchedule, Densifier, make_adam
from egobench.model.shading import KEY
from egobench.train.config import TrainConfig
from egobench.train.data import TrainingData
from egobench.train.initialise import init_params

Optimisers = dict[str, torch.optim.Adam]
#: The extra trainables that hold one row per training frame and move its poses (`frame_poses`); the per-frame
#: exposure correction (`frame_exposure.KEY`) scales its normaliser instead (`frame_exposure.corrected_normaliser`).
PER_FRAME = ("pose_delta", "twist")


@dataclass
class TrainState:
    """Everything that changes while training (one run)."""

    params: dict[str, torch.nn.Parameter]  # means [N,3], scales [N,3], quats [N,4], opacities [N], colors [N,3]
    optimizers: Optimisers  # one Adam per parameter
    scheduler: torch.optim.lr_scheduler.ExponentialLR  # on the means' lr
    extra: dict[str, torch.nn.Parameter]  # per frame: pose_delta [F, 6], twist [F, 6]; per run: shading [2], timing [2]
    extra_optimizers: Optimisers
    densifier: Densifier
    frame_generator: torch.Generator  # the epoch permutations of the training frames
    order: Tensor  # [F] this epoch's frame order
    pos: int = 0  # next position in ``order``
    iteration: int = 0  # completed iterations
    last_loss: float = float("nan")
    timing: dict = field(default_factory=lambda: {"time_s": 0.0, "render_fwd_s": 0.0, "render_bwd_s": 0.0,
                                                  "iterations_timed": 0})

    def next_frame(self) -> int:
        """The next training frame's position in `TrainingData.frames` (a new permutation per epoch)."""
        if self.pos >= len(self.order):
            self.order, self.pos = torch.randperm(len(self.order), generator=self.frame_generator), 0
        fi = int(self.order[self.pos])
        self.pos += 1
        return fi

    def frame_trainables(self, fi: int) -> dict[str, Tensor]:
        """The per-frame trainables of training frame ``fi`` (``pose_delta`` [6], ``twist`` [6]) that exist."""
        return {name: value[fi] for name, value in self.extra.items() if name in PER_FRAME}

    def step_optimisers(self, it: int) -> None:
        """Adam steps of every parameter (`adam_step`), the lr schedule, then the densifier's refinement at ``it``."""
        adam_step([*self.optimizers.values(), *self.extra_optimizers.values()])
        self.scheduler.step()
        self.densifier.refine(self.params, self.optimizers, it)


def _learning_rates(config: TrainConfig, scene_scale: float) -> dict[str, float]:
    return {"means": config.lr_means_at * scene_scale, "scales": config.lr_scales, "quats": config.lr_quats,
            "opacities": config.lr_opacities, "colors": config.lr_colors, "pose_delta": config.lr_pose,
            "twist": config.lr_twist, "shading": config.lr_shading, TIMING_KEY: config.lr_timing,
            frame_exposure.KEY: config.lr_frame_exposure}


def _optimisers(params: dict, extra: dict, config: TrainConfig, scene_scale: float):
    """(Adam per Gaussian parameter, the means' exponential lr decay, Adam per per-frame trainable)."""
    lrs = _learning_rates(config, scene_scale)
    optimizers = {k: make_adam(params[k], lrs[k]) for k in GAUSSIAN_PARAMS}
    scheduler = torch.optim.lr_scheduler.ExponentialLR(
        optimizers["means"], gamma=config.lr_means_final_factor ** (1.0 / config.iterations))
    extra_optimizers = {k: make_adam(v, lrs[k]) for k, v in extra.items()}
    return optimizers, scheduler, extra_optimizers


def _densifier(config: TrainConfig, scene_scale: float) -> Densifier:
    return Densifier(DensifySchedule(
        grow_grad2d=config.grow_grad2d, grow_scale3d=config.grow_scale3d, prune_opa=config.prune_opa,
        prune_scale3d=config.prune_scale3d, refine_start_iter=config.refine_start_iter,
        refine_stop_iter=config.refine_stop_iter, refine_every=config.refine_every,
        reset_every=config.reset_every, opacity_reset=config.opacity_reset, max_gaussians=config.max_gaussians,
    ), scene_scale=scene_scale)


def _extra_trainables(data: TrainingData, config: TrainConfig, device: torch.device) -> dict[str, torch.nn.Parameter]:
    """pose_delta [F, 6] (zeros) for pose-optimising methods; twist [F, 6] (from the trajectory) for
    velocity-shift methods; shading [2] (zeros: none) with ``config.learn_shading``; timing [2] (zeros: the
    stated timing; ms) with ``config.learn_timing``; frame_exposure [F] (zeros: the records) with
    ``config.learn_frame_exposure``."""
    extra: dict[str, torch.nn.Parameter] = {}
    if config.learn_shading:
        extra[KEY] = torch.nn.Parameter(torch.zeros(2, device=device))
    if config.learn_timing:
        if data.spec.motion_sampling != "adaptive":
            raise ValueError(f"TrainConfig.learn_timing: method {data.spec.name!r} renders "
                             f"{data.spec.motion_sampling!r} poses, not the rolling-shutter samples a timing moves; "
                             "expected a method with adaptive motion sampling (e.g. 'ours')")
        extra[TIMING_KEY] = torch.nn.Parameter(torch.zeros(2, device=device))
    F = len(data.frames)
    if config.learn_frame_exposure:
        if not data.spec.formation:
            raise ValueError(f"TrainConfig.learn_frame_exposure: method {data.spec.name!r} has no exposure in its "
                             "image formation to correct; expected a method with formation (e.g. 'ours')")
        extra[frame_exposure.KEY] = torch.nn.Parameter(torch.zeros(F, device=device))
    if data.spec.pose_optimisation:
        extra["pose_delta"] = torch.nn.Parameter(torch.zeros(F, 6, device=device))
    if data.spec.motion_sampling == "velocity_shift":
        extra["twist"] = torch.nn.Parameter(
            torch.stack([frame_twist_camera(data.recording, f) for f in data.frames]).float().to(device))
    return extra


def new_state(data: TrainingData, config: TrainConfig, device: torch.device) -> TrainState:
    """A fresh run: seeds torch and the frame-order generator with ``config.seed``, initialises the
    Gaussians (`init_params`) and draws the first epoch's frame order."""
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    params = init_params(data, config, gen)
    params = {k: torch.nn.Parameter(v.detach().to(device)) for k, v in params.items()}
    extra = _extra_trainables(data, config, device)
    optimizers, scheduler, extra_optimizers = _optimisers(params, extra, config, data.scene_scale)
    return TrainState(params=params, optimizers=optimizers, scheduler=scheduler, extra=extra,
                      extra_optimizers=extra_optimizers, densifier=_densifier(config, data.scene_scale),
                      frame_generator=gen, order=torch.randperm(len(data.frames), generator=gen))


def state_dict(state: TrainState, device: torch.device) -> dict:
    """The state as plain tensors and numbers (host tensors; a CUDA run's checkpoint loads anywhere)."""
    return {
        "iteration": state.iteration,
        "params": {k: v.detach().cpu() for k, v in state.params.items()},
        "optimizers": {k: o.state_dict() for k, o in state.optimizers.items()},
        "scheduler": state.scheduler.state_dict(),
        "extra": {k: v.detach().cpu() for k, v in state.extra.items()},
        "extra_optimizers": {k: o.state_dict() for k, o in state.extra_optimizers.items()},
        "densifier": state.densifier.state_dict(),
        "rng_torch": torch.get_rng_state(), "rng_frames": state.frame_generator.get_state(),
        "rng_cuda": torch.cuda.get_rng_state(device) if device.type == "cuda" else None,
        "order": state.order, "pos": state.pos, "timing": state.timing, "last_loss": state.last_loss,
    }


def load_state(ck: dict, config: TrainConfig, scene_scale: float, device: torch.device) -> TrainState:
    """`state_dict`'s inverse: the run continues to the identical result of an uninterrupted one
    (optimiser moments, lr schedule, densifier statistics and every RNG restored)."""
    params = {k: torch.nn.Parameter(v.to(device)) for k, v in ck["params"].items()}
    extra = {k: torch.nn.Parameter(v.to(device)) for k, v in ck["extra"].items()}
    optimizers, scheduler, extra_optimizers = _optimisers(params, extra, config, scene_scale)
    for group, saved in ((optimizers, ck["optimizers"]), (extra_optimizers, ck["extra_optimizers"])):
        for k, sd in saved.items():
            group[k].load_state_dict(sd)
    scheduler.load_state_dict(ck["scheduler"])
    densifier = _densifier(config, scene_scale)
    densifier.load_state_dict(ck["densifier"])
    torch.set_rng_state(ck["rng_torch"])
    if device.type == "cuda" and ck.get("rng_cuda") is not None:  # gsplat's split draws on the GPU
        torch.cuda.set_rng_state(ck["rng_cuda"], device)
    gen = torch.Generator()
    gen.set_state(ck["rng_frames"])
    return TrainState(params=params, optimizers=optimizers, scheduler=scheduler, extra=extra,
                      extra_optimizers=extra_optimizers, densifier=densifier, frame_generator=gen,
                      order=ck["order"], pos=int(ck["pos"]), iteration=int(ck["iteration"]),
                      last_loss=float(ck.get("last_loss", float("nan"))), timing=dict(ck["timing"]))
