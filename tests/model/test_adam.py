"""The compiled Adam step (`egobench.model.adam`) against torch's Adam and its torch-ops oracle."""

import copy
import platform
import warnings

import numpy as np
import pytest
import torch

from egobench.bench import cpu_threads
from egobench.model.adam import adam_step, adam_update_torch

DTYPES = (torch.float32, torch.float64)


def _grads(shape, dtype, steps, seed=0):
    """Gradients over eight decades, so the moments and the updates cover the exponent range."""
    gen = torch.Generator().manual_seed(seed)
    return [(torch.randn(shape, generator=gen, dtype=torch.float64)
             * 10.0 ** torch.randint(-6, 2, shape, generator=gen)).to(dtype) for _ in range(steps)]


def _adam(p0, lr=1e-3, **kw):
    p = torch.nn.Parameter(p0.clone())
    return p, torch.optim.Adam([{"params": [p], "lr": lr}], eps=1e-15, **kw)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", [1, 17, 40_003])
def test_compiled_step_is_the_oracle_bit_for_bit(dtype, n):
    """Every step (a changing learning rate, as under the scheduler) equals `adam_update_torch`."""
    p0 = torch.randn(n, dtype=dtype)
    p, opt = _adam(p0)
    ref, m, v = p0.clone(), torch.zeros(n, dtype=dtype), torch.zeros(n, dtype=dtype)
    for step, g in enumerate(_grads((n,), dtype, 12), start=1):
        lr = 1e-3 * 0.9 ** step
        opt.param_groups[0]["lr"] = lr
        p.grad = g.clone()
        adam_step([opt])
        adam_update_torch(ref, g, m, v, float(step), lr, 0.9, 0.999, 1e-15)
        state = opt.state[p]
        assert torch.equal(p.detach(), ref) and torch.equal(state["exp_avg"], m) and torch.equal(state["exp_avg_sq"], v)
        assert p.grad is None and float(state["step"]) == step


@pytest.mark.parametrize("dtype", DTYPES)
def test_compiled_step_matches_torch_adam(dtype):
    """The moments bit for bit (on x86-64, where ATen's lerp and addcmul fuse as the kernel does); the
    parameter within a 2^-20 share of its update (torch's CPU square root is not correctly rounded)."""
    p0 = torch.randn(30_011, dtype=dtype)
    a, opt_a = _adam(p0)
    b, opt_b = _adam(p0)
    for g in _grads(p0.shape, dtype, 10, seed=1):
        before = b.detach().clone()
        a.grad, b.grad = g.clone(), g.clone()
        opt_a.step()
        adam_step([opt_b])
        sa, sb = opt_a.state[a], opt_b.state[b]
        if platform.machine() in ("x86_64", "AMD64"):
            assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
        update = (b.detach() - before).abs()
        spacing = torch.from_numpy(np.spacing(b.detach().abs().numpy()))
        assert bool(((a.detach() - b.detach()).abs() <= update * 2.0**-20 + spacing).all())
        with torch.no_grad():
            a.copy_(b)  # compare each step alone
            sa["exp_avg"].copy_(sb["exp_avg"])
            sa["exp_avg_sq"].copy_(sb["exp_avg_sq"])


def test_bits_do_not_depend_on_the_thread_count():
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba's pool has one thread")
    p0 = torch.randn(100_003)
    results = []
    for threads in (1, 2):
        p, opt = _adam(p0)
        with cpu_threads(threads, 1):
            for g in _grads(p0.shape, torch.float32, 3, seed=2):
                p.grad = g
                adam_step([opt])
        results.append(p.detach())
    assert torch.equal(*results)


def test_a_non_contiguous_parameter_is_updated_in_place():
    """A transposed parameter (state of the same layout) steps as its contiguous copy does, in place."""
    base = torch.randn(50, 3)
    p_t, opt_t = _adam(base.T)  # [3, 50], strides (1, 3)
    p_c, opt_c = _adam(base.T.contiguous())
    assert not p_t.is_contiguous()
    storage = p_t.data_ptr()
    for g in _grads((3, 50), torch.float32, 4, seed=3):
        p_t.grad, p_c.grad = g.clone(), g.clone()
        adam_step([opt_t, opt_c])
    assert p_t.data_ptr() == storage and not opt_t.state[p_t]["exp_avg"].is_contiguous()
    assert torch.equal(p_t.detach(), p_c.detach())
    assert torch.equal(opt_t.state[p_t]["exp_avg_sq"], opt_c.state[p_c]["exp_avg_sq"])


def test_unsupported_options_and_missing_gradients_take_torchs_step():
    """amsgrad and weight decay are torch's own step (bit for bit); a parameter without a gradient is
    left alone, with no state created."""
    p0 = torch.randn(1000)
    for options in ({"amsgrad": True}, {"weight_decay": 0.01}):
        a, opt_a = _adam(p0, **options)
        b, opt_b = _adam(p0, **options)
        for g in _grads(p0.shape, torch.float32, 3, seed=4):
            a.grad, b.grad = g.clone(), g.clone()
            opt_a.step()
            adam_step([opt_b])
        assert torch.equal(a.detach(), b.detach())
    c, opt_c = _adam(p0)
    adam_step([opt_c])
    assert torch.equal(c.detach(), p0) and not opt_c.state[c]


def test_state_round_trips_through_torchs_state_dict():
    """The state is torch's layout: a fresh torch Adam loads it and continues as the compiled step does
    (up to the square root's rounding)."""
    p0 = torch.randn(5000)
    a, opt_a = _adam(p0)
    grads = _grads(p0.shape, torch.float32, 6, seed=5)
    for g in grads[:4]:
        a.grad = g
        adam_step([opt_a])
    b, opt_b = _adam(a.detach())
    opt_b.load_state_dict(copy.deepcopy(opt_a.state_dict()))  # as through a checkpoint file
    for g in grads[4:]:
        a.grad, b.grad = g.clone(), g.clone()
        adam_step([opt_a])
        opt_b.step()
    assert float(opt_b.state[b]["step"]) == 6.0
    torch.testing.assert_close(b.detach(), a.detach(), rtol=1e-6, atol=1e-9)


def test_hooks_run_and_the_lr_scheduler_sees_the_step():
    """An optimiser with a step hook takes torch's step (the hook runs); a compiled step counts as a step
    for torch's lr schedulers (no 'scheduler before optimizer' warning, the lr decays)."""
    p0 = torch.randn(100)
    a, opt_a = _adam(p0)
    calls = []
    opt_a.register_step_post_hook(lambda opt, args, kwargs: calls.append(1))
    a.grad = torch.ones(100)
    adam_step([opt_a])
    assert calls == [1] and a.grad is None
    b, opt_b = _adam(p0, lr=0.1)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt_b, gamma=0.5)
    b.grad = torch.ones(100)
    adam_step([opt_b])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sched.step()
    assert opt_b.param_groups[0]["lr"] == 0.05


def test_eager_adam_is_torchs_adam_with_the_same_state_dicts():
    """`make_adam`'s optimiser (EagerAdam) steps through the compiled path as torch's Adam does, bit for
    bit, and its state dicts are torch's: each loads the other's and they continue alike."""
    from egobench.model.optim import EagerAdam, make_adam

    p0 = torch.randn(3000)
    grads = _grads(p0.shape, torch.float32, 6, seed=6)
    a, opt_a = _adam(p0)
    b = torch.nn.Parameter(p0.clone())
    opt_b = make_adam(b, 1e-3)
    assert type(opt_b) is EagerAdam
    for g in grads[:3]:
        a.grad, b.grad = g.clone(), g.clone()
        adam_step([opt_a, opt_b])
    sd_a, sd_b = opt_a.state_dict(), opt_b.state_dict()
    assert sd_a["param_groups"] == sd_b["param_groups"] and sd_a["state"].keys() == sd_b["state"].keys()
    for key in ("step", "exp_avg", "exp_avg_sq"):
        assert torch.equal(sd_a["state"][0][key], sd_b["state"][0][key])
    opt_a.load_state_dict(copy.deepcopy(sd_b))  # each from the other's dict, as through a checkpoint
    opt_b.load_state_dict(copy.deepcopy(sd_a))
    for g in grads[3:]:
        a.grad, b.grad = g.clone(), g.clone()
        adam_step([opt_a, opt_b])
    assert torch.equal(a.detach(), b.detach())
    assert torch.equal(opt_a.state[a]["exp_avg_sq"], opt_b.state[b]["exp_avg_sq"])


def test_the_trainers_bookkeeping_imports_neither_dynamo_nor_sympy():
    """Optimisers, the lr schedule, their state dicts, poses and the exposure's per-image scale in a fresh
    process: none imports torch._dynamo or sympy (torch.optim's dynamo guard and torch.broadcast_shapes
    do, 1-2 s of every training and evaluation process)."""
    import subprocess
    import sys

    code = """
import sys, torch
from egobench.geometry.se3 import make_pose
from egobench.model.formation import FormationConfig, FormationModel
from egobench.model.optim import make_adam
p = torch.nn.Parameter(torch.zeros(4))
opt = make_adam(p, 0.1)
sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.9)
opt.load_state_dict(opt.state_dict())
sched.load_state_dict(sched.state_dict())
make_pose(torch.eye(3).expand(5, 3, 3), torch.zeros(3))
x = torch.full((2, 4, 6, 3), 0.5, dtype=torch.float64)
FormationModel(FormationConfig.paper_trainer()).predict(x, scale_k=torch.ones(2, dtype=torch.float64),
                                                        vignette=torch.ones(4, 6, dtype=torch.float64))
print(sorted(m for m in ("torch._dynamo", "sympy", "torch.fx.experimental.symbolic_shapes") if m in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
