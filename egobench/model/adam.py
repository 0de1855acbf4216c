"""Adam steps of `torch.optim.Adam` optimisers, one compiled pass per parameter on the CPU.

`adam_step` updates the optimiser's own state (``step``, ``exp_avg``, ``exp_avg_sq``), so checkpoints and
gsplat's densification ops see torch's layout. The update is torch's single-tensor Adam operation for
operation, fused-multiply-adds where ATen's kernels use them (lerp, addcmul), with one difference: the
square root is IEEE's, correctly rounded, where torch's CPU sqrt is off by one unit in the last place
in a few elements per million (exp_avg and exp_avg_sq stay bit for bit; see tests/model/test_adam.py).
On one thread torch's steps took ~0.8 ms of a 128 px training step (20 000 Gaussians, seven
optimisers); the compiled pass runs in parallel and the bits do not depend on the thread count.
Other devices and dtypes, and options this pass does not implement, take torch's own step.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from egobench.model.optim import EagerAdam, _fma
from egobench.render.cpu_backend import contiguous_numpy, set_threads


@njit(cache=True, parallel=True)
def _adam_update(param, grad, exp_avg, exp_avg_sq, coef):
    """In place, 1-D arrays of one dtype; coef = (w1, beta2, c2, bc2_sqrt, eps, neg_step_size):
    exp_avg.lerp_(grad, w1); exp_avg_sq.mul_(beta2).addcmul_(grad, grad, c2);
    param.addcdiv_(exp_avg, sqrt(exp_avg_sq) / bc2_sqrt + eps, neg_step_size)."""
    w1, beta2, c2, bc2_sqrt, eps, neg_step_size = coef[0], coef[1], coef[2], coef[3], coef[4], coef[5]
    for i in prange(param.shape[0]):
        g = grad[i]
        m = _fma(w1, g - exp_avg[i], exp_avg[i])  # ATen's lerp for a weight below 0.5
        v = _fma(c2 * g, g, exp_avg_sq[i] * beta2)
        exp_avg[i] = m
        exp_avg_sq[i] = v
        param[i] = param[i] + neg_step_size * m / (np.sqrt(v) / bc2_sqrt + eps)


def adam_update_torch(param: Tensor, grad: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, step: float, lr: float,
                      beta1: float, beta2: float, eps: float) -> None:
    """`_adam_update`'s step ``step`` (1, 2, ...) in torch ops with the IEEE square root (the oracle; CPU)."""
    exp_avg.lerp_(grad, 1 - beta1)
    exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
    root = torch.from_numpy(np.sqrt(exp_avg_sq.numpy()))
    param.addcdiv_(exp_avg, (root / (1 - beta2**step) ** 0.5).add_(eps), value=-(lr / (1 - beta1**step)))


def _compiled(opt: torch.optim.Optimizer) -> bool:
    """Can `_adam_update` step this optimiser (plain Adam of CPU float32/float64 tensors, every
    parameter with a dense gradient of its dtype, a plain-float learning rate, no step hooks)?"""
    if type(opt) not in (torch.optim.Adam, EagerAdam):
        return False
    if opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks:
        return False  # (hooks: torch's step runs them)
    for group in opt.param_groups:
        if (group["amsgrad"] or group["maximize"] or group["weight_decay"] or group.get("capturable")
                or group.get("differentiable") or group.get("fused") or not isinstance(group["lr"], float)):
            return False
        for p in group["params"]:
            g = p.grad
            if p.device.type != "cpu" or p.dtype not in (torch.float32, torch.float64) or (
                    g is not None and (g.is_sparse or g.dtype != p.dtype or g.device != p.device)):
                return False
    return True


def _state(opt: torch.optim.Adam, p: Tensor) -> dict:
    """The parameter's Adam state, created as torch creates it at the first step."""
    state = opt.state[p]
    if not state:
        state["step"] = torch.tensor(0.0, dtype=torch.float64 if torch.get_default_dtype() == torch.float64
                                     else torch.float32)
        state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    return state


def _step_parameter(opt: torch.optim.Adam, group: dict, p: Tensor) -> None:
    state = _state(opt, p)
    counter = state["step"].numpy()
    counter += 1  # in place, in the counter's dtype (as torch's ``step_t += 1``)
    step = float(counter)
    beta1, beta2 = group["betas"]
    coef = np.array([1 - beta1, beta2, 1 - beta2, (1 - beta2**step) ** 0.5, group["eps"],
                     -(group["lr"] / (1 - beta1**step))], dtype=np.float32 if p.dtype == torch.float32 else np.float64)
    targets = [t.detach() for t in (p, state["exp_avg"], state["exp_avg_sq"])]
    arrays = [contiguous_numpy(t).reshape(-1) for t in targets]  # copies only where a tensor is not contiguous
    _adam_update(arrays[0], contiguous_numpy(p.grad).reshape(-1), arrays[1], arrays[2], coef)
    for target, flat in zip(targets, arrays):
        if not target.is_contiguous():
            target.copy_(torch.from_numpy(flat).view(target.shape))


@torch.no_grad()
def adam_step(optimizers: Iterable[torch.optim.Optimizer]) -> None:
    """One step of each optimiser (``optimizer.step()``), then its gradients set to None."""
    set_threads()
    for opt in optimizers:
        if not _compiled(opt):
            opt.step()
            opt.zero_grad(set_to_none=True)
            continue
        for group in opt.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    _step_parameter(opt, group, p)
                    p.grad = None
        opt._opt_called = True  # what torch's lr schedulers read to know that the optimiser stepped
