"""Optimiser and densification helpers for the trainer (gsplat 1.5.3 semantics).

Densification uses gsplat's own pure-torch `DefaultStrategy` methods and `strategy.ops`
(duplicate / split / remove / reset_opa) on a dict of parameters named as gsplat names them
(``means, scales, quats, opacities, colors``; scales are log, opacities logits): the rules are
therefore exactly gsplat 1.5.3's:

- statistics: for every rendered view, the image-plane gradient of ``means2d`` (pixels) is scaled
  by (W/2 * n_views, H/2 * n_views); its norm is accumulated per Gaussian visible in that view
  (radius > 0), with a visibility count;
- every ``refine_every`` steps in (refine_start, refine_stop): Gaussians whose mean accumulated
  gradient exceeds ``grow_grad2d`` are duplicated when max(scale) <= grow_scale3d * scene_scale,
  else split in two (samples from the Gaussian, scales / 1.6); then Gaussians with opacity <
  ``prune_opa`` are removed, and (after the first ``reset_every`` steps) those with max(scale) >
  prune_scale3d * scene_scale; the statistics are zeroed;
- opacity reset: gsplat 1.5.3 writes ``step % reset_every == 0 & step > 0``, which Python parses as
  the chained comparison ``(step % reset_every == 0) and (0 > 0)``: it never fires, so gsplat
  1.5.3 (and the authors' runs on it) never reset opacities. ``opacity_reset="gsplat"`` keeps
  that; ``"intended"`` clamps opacities to 2 * prune_opa every ``reset_every`` steps (3DGS paper).

Added here (not in gsplat): a ``max_gaussians`` budget (CPU). Growth is gsplat's `_grow_gs`
verbatim while N + growth fits; when it would not, only the candidates with the largest mean
gradient grow (each duplicate or split adds one Gaussian), so the cap never destroys existing
Gaussians. An initial point cloud larger than the cap is subsampled by the trainer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from numba import njit, prange
from numba.extending import intrinsic
from torch import Tensor

from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import duplicate, reset_opa, split

from egobench.host import start_kernel_pool

GAUSSIAN_PARAMS = ("means", "scales", "quats", "opacities", "colors")


@dataclass
class DensifySchedule:
    """Densification settings in absolute iterations (see `TrainConfig` for the fractions)."""

    grow_grad2d: float  # mean screen-space gradient above which a Gaussian grows
    grow_scale3d: float  # duplicate if max scale <= this * scene_scale, else split
    prune_opa: float  # prune opacity threshold
    prune_scale3d: float  # prune if max scale > this * scene_scale (after the first reset_every)
    refine_start_iter: int  # refine only for step > this
    refine_stop_iter: int  # no statistics or refinement from this step on
    refine_every: int  # refine when step % refine_every == 0
    reset_every: int  # opacity-reset period (see opacity_reset)
    opacity_reset: Literal["gsplat", "intended"]  # gsplat 1.5.3 behaviour (never) or the 3DGS rule
    max_gaussians: int  # 0 = no cap


class Densifier:
    """gsplat 1.5.3 DefaultStrategy on our parameter dict, plus a Gaussian-count cap."""

    def __init__(self, schedule: DensifySchedule, scene_scale: float) -> None:
        self.schedule = schedule
        self.strategy = DefaultStrategy(
            prune_opa=schedule.prune_opa,
            grow_grad2d=schedule.grow_grad2d,
            grow_scale3d=schedule.grow_scale3d,
            prune_scale3d=schedule.prune_scale3d,
            refine_start_iter=schedule.refine_start_iter,
            refine_stop_iter=schedule.refine_stop_iter,
            reset_every=schedule.reset_every,
            refine_every=schedule.refine_every,
        )
        self.state = self.strategy.initialize_state(scene_scale=scene_scale)
        self.last_counts = {"duplicated": 0, "split": 0, "pruned": 0, "capped": 0}

    def accumulate(self, params: dict, step: int, means2d: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one render's statistics: means2d [C, N, 2] (with .grad), radii [C, N] (or [C, N, 2]) pixels."""
        if step >= self.schedule.refine_stop_iter:
            return
        self._follow(params)
        if means2d.grad is None:
            raise ValueError("means2d: no gradient; the renderer must return means2d with retain_grad()")
        s = self.strategy
        if means2d.device.type == "cpu" and not s.absgrad and s.refine_scale2d_stop_iter == 0:
            self._update_state_cpu(params, means2d, radii, width, height)
            return
        radii2 = radii if radii.dim() == 3 else radii[..., None].expand(*radii.shape, 2)  # gsplat wants [C, N, 2]
        info = {
            "width": width, "height": height, "n_cameras": means2d.shape[0],
            "radii": radii2, "gaussian_ids": None, "means2d": means2d,
        }
        s._update_state(params, self.state, info, packed=False)

    def _update_state_cpu(self, params: dict, means2d: Tensor, radii: Tensor, width: int, height: int) -> None:
        """gsplat's `_update_state` (packed=False, no absgrad, no 2D-scale statistics), bit for bit, in one
        compiled pass instead of its scaled copy, norms, masked gathers and index_add_ (~1.9 ms of a 128 px
        step). means2d [C, N, 2] with .grad, radii [C, N] or [C, N, 2] pixels."""
        n_gaussian = len(params["means"])
        for key in ("grad2d", "count"):
            if self.state[key] is None:
                self.state[key] = torch.zeros(n_gaussian)
        grads = means2d.grad.detach().contiguous().numpy()  # [C, N, 2] pixels
        n_cameras = means2d.shape[0]
        scale = np.array([width / 2.0 * n_cameras, height / 2.0 * n_cameras],
                         dtype=grads.dtype)  # torch's float32 op casts the Python scalar so
        radii3 = radii if radii.dim() == 3 else radii[..., None]  # [C, N, R]
        start_kernel_pool()
        _add_visible(grads, scale, radii3.contiguous().numpy(), self.state["grad2d"].numpy(),
                     self.state["count"].numpy())

    @torch.no_grad()
    def refine(self, params: dict, optimizers: dict, step: int) -> dict:
        """Grow, prune, cap and (maybe) reset at ``step`` as gsplat's step_post_backward does."""
        s, sch = self.strategy, self.schedule
        counts = {"duplicated": 0, "split": 0, "pruned": 0, "capped": 0}
        if step >= sch.refine_stop_iter:
            self.last_counts = counts
            return counts
        self._follow(params)
        if self.state["grad2d"] is not None and step > s.refine_start_iter and step % s.refine_every == 0 \
                and step % s.reset_every >= s.pause_refine_after_reset:
            counts["duplicated"], counts["split"], counts["capped"] = self.grow(params, optimizers, step)
            counts["pruned"] = s._prune_gs(params, optimizers, self.state, step)
            self.state["grad2d"].zero_()
            self.state["count"].zero_()
        if sch.opacity_reset == "intended" and step > 0 and step % sch.reset_every == 0:
            reset_opa(params=params, optimizers=optimizers, state=self.state, value=sch.prune_opa * 2.0)
        self.last_counts = counts
        return counts

    @torch.no_grad()
    def grow(self, params: dict, optimizers: dict, step: int) -> tuple[int, int, int]:
        """gsplat 1.5.3 `_grow_gs` with the Gaussian budget -> (duplicated, split, candidates left out)."""
        s, state = self.strategy, self.state
        grads = state["grad2d"] / state["count"].clamp_min(1)
        is_grad_high = grads > s.grow_grad2d
        is_small = torch.exp(params["scales"]).max(dim=-1).values <= s.grow_scale3d * state["scene_scale"]
        left_out = 0
        cap = self.schedule.max_gaussians
        if cap > 0:
            room = max(cap - int(params["means"].shape[0]), 0)
            n_cand = int(is_grad_high.sum())
            if n_cand > room:
                score = torch.where(is_grad_high, grads, torch.full_like(grads, -1.0))
                keep = torch.argsort(score, descending=True, stable=True)[:room]
                limited = torch.zeros_like(is_grad_high)
                limited[keep] = True
                is_grad_high = limited
                left_out = n_cand - room
        is_dupli = is_grad_high & is_small
        is_split = is_grad_high & ~is_small
        n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
        if n_dupli > 0:
            duplicate(params=params, optimizers=optimizers, state=state, mask=is_dupli)
        is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        if n_split > 0:
            split(params=params, optimizers=optimizers, state=state, mask=is_split, revised_opacity=s.revised_opacity)
        return n_dupli, n_split, left_out

    def _follow(self, params: dict) -> None:
        """Move the running statistics (grad2d, count [N]) to the device of ``params["means"]``: a
        state loaded from a checkpoint (CPU tensors, `state_dict`) follows the parameters."""
        device = params["means"].device
        for k, v in self.state.items():
            if isinstance(v, Tensor) and v.device != device:
                self.state[k] = v.to(device)

    def state_dict(self) -> dict:
        """Copies of the running state with tensors on the CPU (a checkpoint written on CUDA loads anywhere)."""
        return {k: (v.detach().to("cpu", copy=True) if isinstance(v, Tensor) else v) for k, v in self.state.items()}

    def load_state_dict(self, state: dict) -> None:
        """Restore `state_dict`; tensors move to the parameters' device at the next accumulate/refine."""
        self.state = {k: (v.clone() if isinstance(v, Tensor) else v) for k, v in state.items()}


def _undecorated(method):
    """A torch.optim.Optimizer method without its ``torch._disable_dynamo`` wrapper (the method itself where
    a torch has none)."""
    return getattr(method, "__wrapped__", method)


class EagerAdam(torch.optim.Adam):
    """torch's Adam (the same state, state dicts and steps) whose bookkeeping methods skip the
    ``torch._disable_dynamo`` wrapper. That wrapper's first call imports torch._dynamo, and with it sympy
    and torch.fx: 1.1 s of every training process on a Zen 4 VM, for a guard that only matters under
    torch.compile, which the trainer does not use."""

    add_param_group = _undecorated(torch.optim.Optimizer.add_param_group)
    state_dict = _undecorated(torch.optim.Optimizer.state_dict)
    load_state_dict = _undecorated(torch.optim.Optimizer.load_state_dict)


def make_adam(param: torch.nn.Parameter, lr: float) -> torch.optim.Adam:
    """One Adam per parameter (gsplat: eps 1e-15, batch size 1)."""
    return EagerAdam([{"params": [param], "lr": lr}], eps=1e-15)


@intrinsic
def _fma(typingctx, a, b, c):
    """a b + c rounded once (LLVM's fma; torch's float32 2-norm is sqrt(fma(y, y, x x)))."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return a(a, b, c), codegen


@njit(cache=True, inline="always")
def _visible(radii, c, n):
    """radii [C, N, R] (pixels; R = 1 or 2): Gaussian n drawn in view c (every radius > 0)."""
    for r in range(radii.shape[2]):
        if radii[c, n, r] <= 0:
            return False
    return True


@njit(cache=True, parallel=True)
def _add_visible(grads, scale, radii, grad2d, count):
    """grads [C, N, 2], scale [2], radii [C, N, R]. Per Gaussian n, over the views c in order where it is
    visible: grad2d[n] += |grads[c, n] * scale| and count[n] += 1 (float32; torch's norm and, for each n,
    the additions of gsplat's index_add_ in its order)."""
    one = np.float32(1.0)
    for n in prange(grads.shape[1]):
        g, k = grad2d[n], count[n]
        for c in range(grads.shape[0]):
            if _visible(radii, c, n):
                x, y = grads[c, n, 0] * scale[0], grads[c, n, 1] * scale[1]
                g += math.sqrt(_fma(y, y, x * x))
                k += one
        grad2d[n], count[n] = g, k
