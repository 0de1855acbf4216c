"""The training loop (paper Sec. 3-4, docs/paper-notes.md §2 and §6).

Each iteration picks a training frame (seeded permutation per epoch), renders it under the
method's pose model (centre-row pose; adaptive rolling-shutter pose samples after the warm-up;
or the velocity-shift model of the 3DGS-on-the-move baseline; `egobench.model.predict`), applies the
method's image formation, takes the loss 0.8 L1 + 0.2 (1 - SSIM) on valid-mask pixels, steps
Adam per parameter group and gsplat 1.5.3's densification (`egobench.model.optim`). Deterministic on
the CPU for a seed; resumable from a checkpoint to the identical result.

Timing method (``raster_time_share`` in train.json): wall time inside `render()` (forward) plus
the rasterizer's share of the backward pass, measured from the moment autograd reaches the
render output (a tensor hook on ``rgb``) to the end of ``loss.backward()``; everything upstream
of the rasterizer in the graph (pose exponentials, parameter activations) is tiny and is counted
as raster time. Divided by the total wall time of the iterations. Where the compiled training step
(`egobench.train.cpu_step`, the autograd path's bits, much less glue) runs a step, the share is that
step's render forward plus its render backward (train.json's ``train.step`` says which ran).
"""

from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor
from tqdm import tqdm

from egobench.core_sharing import bracketing
from egobench.data import load_recording
from egobench.data.reader import say_dropped
from egobench.data.recording import Recording
from egobench.host import kernel_threads
from egobench.io_utils import holding_run_folder, write_json
from egobench.model.frame_exposure import corrected_normaliser
from egobench.model.methods import MethodSpec, get_method
from egobench.model.motion_sampling import TIMING_KEY
from egobench.model.optim import GAUSSIAN_PARAMS
from egobench.model.predict import (
    PoseSampleCache, RenderSettings, formation_model, frame_poses, gaussians_from_params, mean_rgb, predict_image,
    render_frame,
)
from egobench.model.shading import KEY, radius2_of, shading
from egobench.render import resolve_backend
from egobench.render.finite import all_finite
from egobench.train import cpu_step
from egobench.train.checkpoint import checkpoint_matches, resumable_checkpoint, write_checkpoint
from egobench.train.config import TrainConfig
from egobench.train.data import TrainingData, image_to_float, prepare_data
from egobench.train.losses import twodgs_regularisers
from egobench.train.photometric import photometric_loss
from egobench.train.record import TrainResult, train_record
from egobench.train.state import TrainState, load_state, new_state, state_dict


class TrainingDiverged(RuntimeError):
    """Raised when a loss or parameter becomes non-finite, or refinement prunes every Gaussian
    (names the iteration and quantity)."""


@dataclass
class StepContext:
    """What every iteration reads: the prepared data and its per-pixel maps on the training device."""

    data: TrainingData
    config: TrainConfig
    settings: RenderSettings
    formation: object  # the method's `FormationModel`
    mask3: Tensor  # [H, W, 3] float valid pixels, one per channel (the photometric loss reads it without a copy)
    n_mask: float  # valid pixels x 3
    vignette: Tensor  # [H, W]
    k: Tensor  # [F] exposure*gain normaliser of the training frames
    row_time_ratio: Tensor  # [H, W] R(u): pixel-pose indices are built on the device
    shading_r2: Tensor | None = None  # [H, W] normalised r^2 of the learnable shading (learn_shading), else None
    pose_samples: PoseSampleCache = field(default_factory=PoseSampleCache)  # the frames' trajectory samples
    compiled_inputs: cpu_step.RunInputs | None = None  # what `cpu_step.frame_step` reads every step, or None

    @property
    def compiled(self) -> bool:
        """Each step is `cpu_step.frame_step` (else autograd through `render`)."""
        return self.compiled_inputs is not None


def step_context(data: TrainingData, config: TrainConfig, device: torch.device, step: str = "auto",
                 dtype: torch.dtype = torch.float32) -> StepContext:
    """Move the maps to the device; a valid mask that is empty at the training resolution is a named error.
    ``step``: "auto" takes the compiled step (`cpu_step`) where it applies, "autograd" never does; ``dtype``:
    the Gaussian parameters' (what the compiled step's run inputs are held in)."""
    mask = data.maps.mask.to(device)[..., None].float()
    n_mask = float(mask.sum()) * 3
    mask3 = mask.expand(-1, -1, 3).contiguous()
    if n_mask == 0:
        raise ValueError(f"recording {data.recording.root}: the valid-pixel mask is empty at the training resolution")
    formation = formation_model(data.spec)
    compiled = step == "auto" and cpu_step.unsupported_reason(
        data.spec, resolve_backend(config.backend, device), formation, config) is None
    inputs = (cpu_step.run_inputs(mask3, n_mask, config, data.camera, data.spec.splat_mode == "2dgs", dtype)
              if compiled else None)
    return StepContext(data=data, config=config, settings=RenderSettings.of(config, device),
                       formation=formation, mask3=mask3, n_mask=n_mask,
                       vignette=data.maps.vignette.to(device), k=data.k.to(device),
                       row_time_ratio=data.maps.row_time_ratio.to(device),
                       shading_r2=_shading_r2(data, config, device), compiled_inputs=inputs)


def _shading_r2(data: TrainingData, config: TrainConfig, device: torch.device) -> Tensor | None:
    return radius2_of(data.camera, config).to(device) if config.learn_shading else None


def _check_finite(it: int, named: list[tuple[str, Tensor]]) -> None:
    """Raise TrainingDiverged naming the first non-finite tensor of ``named``. One host sync for
    all of them (a CUDA run does not stall on each tensor); the per-tensor search runs only on failure."""
    named = [(n, t.detach()) for n, t in named if t is not None]
    if all_finite([t for _, t in named]):
        return
    for name, value in named:
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise TrainingDiverged(f"training diverged at iteration {it}: {name} is not finite "
                                   f"({bad} non-finite values); lower the learning rates or check the input")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _poses(state: TrainState, ctx: StepContext, it: int, fi: int) -> tuple[Tensor, Tensor | None]:
    """Training frame ``fi``'s poses [M, K, 4, 4] and pixel pose index at iteration ``it``."""
    data, spec = ctx.data, ctx.data.spec
    warm = it >= ctx.config.motion_warmup_iter
    return frame_poses(data.recording, data.frames[fi], spec, data.n_samples[fi] if warm else 1,
                       ctx.row_time_ratio, **state.frame_trainables(fi),
                       n_exposure_samples=spec.render_exposure_samples if warm else 1, cache=ctx.pose_samples,
                       timing=state.extra.get(TIMING_KEY))


def _forward(state: TrainState, ctx: StepContext, it: int, fi: int) -> tuple[Tensor, list, float]:
    """Render training frame ``fi`` and return (loss, render outputs, forward render seconds)."""
    data, config, spec = ctx.data, ctx.config, ctx.data.spec
    poses, ppi = _poses(state, ctx, it, fi)
    g = gaussians_from_params(state.params)
    _sync(ctx.settings.device)
    t0 = time.perf_counter()
    outs = render_frame(g, data.camera, poses, ppi, spec, ctx.settings)
    _sync(ctx.settings.device)
    t_fwd = time.perf_counter() - t0
    for o in outs:
        if o.means2d is not None and o.means2d.requires_grad:
            o.means2d.retain_grad()
    rgb = mean_rgb(outs)  # [H, W, 3] exposure samples averaged
    pred = predict_image(rgb, spec, corrected_normaliser(ctx.k[fi], state.extra, fi), _vignette(state, ctx), ctx.formation)
    gt = image_to_float(data.images[fi].to(ctx.settings.device, non_blocking=True))  # [H, W, 3] 0..1
    loss = photometric_loss(pred, gt, ctx.mask3, ctx.n_mask, config.ssim_lambda)
    if spec.splat_mode == "2dgs":
        loss = loss + twodgs_regularisers(outs, data.camera, config, it, ctx.mask3)
    _check_finite(it, [("rendered rgb", rgb), ("loss", loss)])
    return loss, outs, t_fwd


def _vignette(state: TrainState, ctx: StepContext) -> Tensor:
    """The stated vignette, times the learnable shading when the run learns one."""
    if ctx.shading_r2 is None:
        return ctx.vignette
    return ctx.vignette * shading(ctx.shading_r2, state.extra[KEY])


def _backward(loss: Tensor, outs: list, device: torch.device) -> float:
    """loss.backward(); returns the rasterizer's share of it in seconds (from the rgb hook to the end)."""
    hook_t: list[float] = []
    rgb_leaf = outs[-1].rgb
    if rgb_leaf.requires_grad:
        rgb_leaf.register_hook(lambda grad: hook_t.append(time.perf_counter()) or None)
    loss.backward()
    _sync(device)
    return (time.perf_counter() - min(hook_t)) if hook_t else 0.0


def _autograd_step(state: TrainState, ctx: StepContext, it: int, fi: int) -> tuple[Tensor, list, float, float]:
    """Loss and gradients through `render` and torch's autograd -> (loss, densification carriers (means2d
    with .grad, radii), forward and backward render seconds)."""
    loss, outs, t_fwd = _forward(state, ctx, it, fi)
    t_bwd = _backward(loss, outs, ctx.settings.device)
    carriers = [(o.means2d, o.radii) for o in outs
                if o.means2d is not None and o.means2d.grad is not None and o.radii is not None]
    return loss, carriers, t_fwd, t_bwd


def _compiled_step(state: TrainState, ctx: StepContext, it: int, fi: int) -> tuple[Tensor, list, float, float]:
    """`_autograd_step`'s results from `cpu_step.frame_step` (no autograd graph)."""
    poses, ppi = _poses(state, ctx, it, fi)
    data = ctx.data
    target = cpu_step.frame_target(image_to_float(data.images[fi]), ctx.k[fi], _vignette(state, ctx),
                                   state.params["means"].dtype)
    out = cpu_step.frame_step(gaussians_from_params(state.params), data.camera, poses[0], ppi, data.spec,
                              ctx.formation, ctx.compiled_inputs, target, it)
    _check_finite(it, [("rendered rgb", out.rgb), ("loss", out.loss)])
    return out.loss, out.carriers, out.render_fwd_s, out.render_bwd_s


def train_step(state: TrainState, ctx: StepContext, it: int) -> None:
    """One iteration: forward, backward, densification statistics, optimiser steps, refinement."""
    t0 = time.perf_counter()
    loss, carriers, t_fwd, t_bwd = (_compiled_step if ctx.compiled else _autograd_step)(state, ctx, it,
                                                                                         state.next_frame())
    cam = ctx.data.camera
    for means2d, radii in carriers:
        state.densifier.accumulate(state.params, it, means2d, radii, cam.width, cam.height)
    _check_finite(it, [(f"gradient of {name}", state.params[name].grad) for name in GAUSSIAN_PARAMS])
    state.step_optimisers(it)
    if len(state.params["means"]) == 0:
        raise TrainingDiverged(f"training collapsed at iteration {it}: refinement pruned every Gaussian "
                               f"(scene scale {ctx.data.scene_scale:.3g} m); check the poses and points, or train longer "
                               "than the refinement schedule's first steps")
    _check_finite(it, [(name, state.params[name]) for name in GAUSSIAN_PARAMS] + list(state.extra.items()))
    state.last_loss = float(loss.detach())
    state.iteration = it + 1
    for key, value in (("time_s", time.perf_counter() - t0), ("render_fwd_s", t_fwd), ("render_bwd_s", t_bwd),
                       ("iterations_timed", 1)):
        state.timing[key] += value


def _recording_for(recording_dir, spec: MethodSpec) -> Recording:
    """A folder loaded with the method's calibration, or a loaded `Recording` checked against it."""
    if isinstance(recording_dir, Recording):
        if recording_dir.calibration != spec.calibration:
            raise ValueError(
                f"recording: method {spec.name!r} needs the {spec.calibration!r} calibration, got a recording "
                f"loaded with {recording_dir.calibration!r}"
            )
        return recording_dir
    return load_recording(recording_dir, calibration=spec.calibration)


def _checkpoint_state(state: TrainState, method: str, config: TrainConfig, data: TrainingData,
                      device: torch.device) -> dict:
    """The checkpoint dict: the state plus what identifies the run."""
    return {"method": method, "config": config.to_dict(), "config_hash": config.hash(method),
            **state_dict(state, device), "extra_frames": [f.index for f in data.frames],
            "camera": data.camera.to_dict(), "scene_scale": data.scene_scale,
            "recording": str(data.recording.root), "n_samples": data.n_samples}


def _warn_backend(device: torch.device, config: TrainConfig) -> str:
    """Resolve (maybe build) the rasterizer backend before timing starts; warn on a slow CUDA fallback."""
    backend = resolve_backend(config.backend, device)
    if device.type == "cuda" and backend == "torch" and config.backend == "auto":
        print("egobench train: warning: gsplat's CUDA extension cannot be loaded (needs nvcc to build once); "
              "training with the pure-torch rasterizer, which is many times slower", file=sys.stderr)
    return backend


@holding_run_folder("train", "out_dir", exclusive=True)
def train(recording_dir, method: str, config: TrainConfig, out_dir, *, resume: bool | Literal["auto"] = False,
          stop_after: int | None = None, progress: bool = True) -> TrainResult:
    """Train ``method`` on a recording (a folder, or a loaded `Recording` of the method's calibration).

    Writes ``out_dir/checkpoint.pt`` (atomic; every ``checkpoint_every`` and at the end) and
    ``out_dir/train.json``. ``resume`` continues from the checkpoint to the identical result of an
    uninterrupted run; ``resume="auto"`` (the workflow's choice) resumes a checkpoint of the same
    method and config and otherwise starts afresh (a stale checkpoint is replaced). ``stop_after``
    ends after that many total iterations (as an interruption would: checkpoint written, no train.json).
    """
    spec = get_method(method)
    ckpt_path = Path(out_dir) / "checkpoint.pt"
    data = prepare_data(_recording_for(recording_dir, spec), spec, config, progress=progress)
    say_dropped(data.recording, "train")
    device = torch.device(config.device)
    state = new_state(data, config, device)
    backend = _warn_backend(device, config)
    ctx = step_context(data, config, device, cpu_step.requested_step())
    if resume == "auto":
        resume = checkpoint_matches(ckpt_path, method, config)
    if resume:
        state = load_state(resumable_checkpoint(ckpt_path, method, config), config, data.scene_scale, device)
    _drop_stale_records(Path(out_dir))
    start_it = state.iteration
    end_it = config.iterations if stop_after is None else min(config.iterations, int(stop_after))
    bar = tqdm(range(start_it, end_it), desc=f"train {method}", disable=not progress, file=sys.stderr,
               initial=start_it, total=config.iterations, mininterval=2.0)
    with _probing_cores(backend, end_it > start_it) as sharing:  # the last probe after the final checkpoint
        for it in bar:
            train_step(state, ctx, it)
            if progress and it % 50 == 0:
                bar.set_postfix(loss=f"{state.last_loss:.4f}", n=len(state.params["means"]))
            if config.checkpoint_every > 0 and (it + 1) % config.checkpoint_every == 0 and it + 1 < end_it:
                write_checkpoint(ckpt_path, _checkpoint_state(state, method, config, data, device))
        bar.close()
        state.iteration = max(end_it, start_it)
        write_checkpoint(ckpt_path, _checkpoint_state(state, method, config, data, device))
    return _result(state, data, config, method, Path(out_dir), backend, sharing or None, ctx.compiled)


def _probing_cores(backend: str, iterating: bool):
    """Around this process's iterations (``iterating``: there are some): `core_sharing.bracketing` where the
    compiled CPU kernels run on two or more threads (whether those share a cache then decides their speed);
    otherwise nothing is probed. Yields the dict that holds the record once the block has run (empty when
    nothing was probed)."""
    if backend != "cpu" or not iterating:
        return contextlib.nullcontext({})
    return bracketing(kernel_threads() > 1)


def _drop_stale_records(out_dir: Path) -> None:
    """Remove the records of an earlier run in ``out_dir`` (train.json, eval.json) before this one
    writes its first checkpoint: a run killed midway then has no record that could pass for its own."""
    for name in ("train.json", "eval.json"):
        (out_dir / name).unlink(missing_ok=True)


def _result(state: TrainState, data: TrainingData, config: TrainConfig, method: str, out_dir: Path,
            backend: str, core_sharing: dict | None, compiled_step: bool) -> TrainResult:
    """The run's result; train.json is written only for a finished run (the workflow's output).
    ``core_sharing``: `_probing_cores`' record of this process's iterations (None: not probed)."""
    ts, its = state.timing["time_s"], state.timing["iterations_timed"]
    result = TrainResult(
        run_dir=out_dir, checkpoint=out_dir / "checkpoint.pt", iterations=state.iteration,
        num_gaussians=int(len(state.params["means"])), time_s=ts, iters_per_s=its / ts if ts > 0 else 0.0,
        raster_time_share=(state.timing["render_fwd_s"] + state.timing["render_bwd_s"]) / ts if ts > 0 else 0.0,
        final_loss=state.last_loss,
    )
    result.record = train_record(result, state, data, config, method, backend, core_sharing, compiled_step)
    if result.record["complete"]:
        write_json(out_dir / "train.json", result.record)
    return result
