"""The compiled CPU training step (`egobench.train.cpu_step`, `cpu_render`) against the autograd path it
replaces: the same kernels in the same order, so the loss and every gradient are the same bits, 3DGS and
2DGS with its regularisers; the whole run the same parameters; the torch rasterizer's autograd (the oracle)
to float rounding."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from egobench.sim.plane import plane_recording
from egobench.train import TrainConfig, cpu_step, loop, train
from egobench.train.data import prepare_data
from egobench.train.state import new_state

CFG = TrainConfig(iterations=30, max_side=48, motion_warmup_frac=0.0, refine_start_frac=0.2, refine_every_frac=0.2,
                  max_gaussians=2000)


@pytest.fixture(scope="module")
def plane(tmp_path_factory):
    """A textured plane, 48 px, the camera turning fast enough that 'ours' renders several pose samples."""
    return plane_recording(tmp_path_factory.mktemp("plane"), size=48, n_frames=9, angular_speed_rad_s=6.0,
                           n_points=1500, frame_interval_s=0.01)


def _data(rec, method: str, config: TrainConfig):
    """The prepared training data of ``method`` (the recording under the method's calibration)."""
    spec = loop.get_method(method)
    return prepare_data(dataclasses.replace(rec, calibration=spec.calibration), spec, config, progress=False)


def _one_step(rec, method: str, config: TrainConfig, step: str, it: int = 0):
    """(loss, {parameter: gradient}, the densification carrier's gradient, compiled?, the most pose samples)
    of a first step taken as iteration ``it`` (2DGS's regularisers follow the iteration)."""
    data = _data(rec, method, config)
    state = new_state(data, config, torch.device("cpu"))
    ctx = loop.step_context(data, config, torch.device("cpu"), step)
    take = loop._compiled_step if ctx.compiled else loop._autograd_step
    loss, carriers, _, _ = take(state, ctx, it, state.next_frame())
    return (float(loss.detach()), {k: v.grad.clone() for k, v in state.params.items()},
            carriers[0][0].grad.clone(), ctx.compiled, max(data.n_samples))


@pytest.mark.parametrize("method, it", [("ours", 0), ("no_scene_gamma", 0), ("no_motion_sampling", 0),
                                        ("splatfacto", 0), ("ours_2dgs", 0), ("ours_2dgs", 5), ("ours_2dgs", 25),
                                        ("2dgs_no_motion_sampling", 25)])
def test_a_step_is_the_autograd_paths_bits(plane, method, it):
    """Loss, every Gaussian parameter's gradient and the densification carrier's gradient: identical. 2DGS at
    iteration 0 (no regulariser), 5 (the distortion from `dist_start_iter` 3) and 25 (the normal consistency
    too, from 7)."""
    loss_a, grads_a, m2_a, compiled_a, _ = _one_step(plane, method, CFG, "autograd", it)
    loss_c, grads_c, m2_c, compiled_c, samples = _one_step(plane, method, CFG, "auto", it)
    assert not compiled_a and compiled_c
    if method in ("ours", "no_scene_gamma", "ours_2dgs"):
        assert samples > 1  # the rolling-shutter path is the one compared
    assert loss_c == loss_a
    for name, g in grads_a.items():
        assert torch.equal(grads_c[name], g), name
        assert g.abs().max() > 0, name  # a gradient that flows
    assert torch.equal(m2_c.contiguous(), m2_a.contiguous())


def test_a_background_colour_reaches_the_gradients(plane):
    """With a grey background the transmittance's gradient joins the backward: equal to float rounding
    (numpy's product and sum against autograd's), and not equal to the black background's gradients."""
    grey = dataclasses.replace(CFG, background=(0.5, 0.5, 0.5))
    loss_a, grads_a, _, _, _ = _one_step(plane, "ours", grey, "autograd")
    loss_c, grads_c, _, _, _ = _one_step(plane, "ours", grey, "auto")
    _, grads_black, _, _, _ = _one_step(plane, "ours", CFG, "auto")
    assert loss_c == pytest.approx(loss_a, rel=1e-6)
    for name, g in grads_a.items():
        torch.testing.assert_close(grads_c[name], g, rtol=1e-5, atol=1e-7 * float(g.abs().max()))
    assert not torch.allclose(grads_c["opacities"], grads_black["opacities"])


@pytest.mark.parametrize("method, it", [("ours", 0)])
def test_a_step_agrees_with_the_torch_rasterizer(plane, method, it):
    """Against the oracle, the torch rasterizer under autograd, in float64: the loss to 1e-9 and the gradients
    to 1e-7 relative (float32 drift of one ulp per op would be ~1e-7 per op); the absolute floor is 1e-9 of the
    largest gradient (the quaternions' gradient is zero on this plane of round Gaussians, up to rounding).
    3DGS only: a 2DGS image depends on the tile size (gsplat's surfel culling; 0.03 apart at 4 and 16 px on
    tests/render's surfel scene) and the two backends' defaults differ (4, 16); the render tests compare
    them at one tile size, and the 2DGS step is the cpu backend's bits (above)."""
    cfg = dataclasses.replace(CFG, backend="torch")
    data = _data(plane, method, CFG)
    out = {}
    for name, config in (("torch", cfg), ("compiled", CFG)):
        state = new_state(data, config, torch.device("cpu"))
        for p in state.params.values():
            p.data = p.data.double()
        ctx = loop.step_context(data, config, torch.device("cpu"), dtype=torch.float64)
        take = loop._compiled_step if ctx.compiled else loop._autograd_step
        loss, _, _, _ = take(state, ctx, it, state.next_frame())
        out[name] = (float(loss.detach()), {k: v.grad for k, v in state.params.items()}, ctx.compiled)
    assert out["compiled"][2] and not out["torch"][2]
    assert out["compiled"][0] == pytest.approx(out["torch"][0], rel=1e-9)
    scale = max(float(g.abs().max()) for g in out["torch"][1].values())
    for name, g in out["torch"][1].items():
        assert out["compiled"][1][name].dtype == torch.float64
        torch.testing.assert_close(out["compiled"][1][name], g, rtol=1e-7, atol=1e-9 * scale)


@pytest.mark.parametrize("method", ["ours", "ours_2dgs"])
def test_a_run_is_the_autograd_runs_parameters(plane, tmp_path, monkeypatch, method):
    """30 iterations with densification (and 2DGS's regularisers from their iterations): the compiled run's
    parameters are the autograd run's, bit for bit, and a second compiled run repeats them; train.json says
    which step ran."""
    runs = {}
    for name, step in (("autograd", "autograd"), ("compiled", "auto"), ("again", "auto")):
        monkeypatch.setenv(cpu_step.STEP_ENV, step)
        result = train(plane, method, CFG, tmp_path / name, progress=False)
        assert result.record["train"]["step"] == ("autograd" if step == "autograd" else "compiled")
        runs[name] = torch.load(tmp_path / name / "checkpoint.pt", weights_only=True)["params"]
    assert len(runs["compiled"]["means"]) != 1500  # densification changed the count
    for key, value in runs["autograd"].items():
        assert torch.equal(runs["compiled"][key], value), key
        assert torch.equal(runs["again"][key], value), key


@pytest.mark.parametrize("method, config, reason", [
    ("on_the_move", CFG, "poses"),
    ("ours", dataclasses.replace(CFG, learn_shading=True), "lens shading"),
    ("ours", dataclasses.replace(CFG, learn_timing=True), "timing"),
    ("ours", dataclasses.replace(CFG, backend="torch"), "backend"),
])
def test_what_the_compiled_step_leaves_to_autograd(plane, method, config, reason):
    spec = loop.get_method(method)
    data = _data(plane, method, config)
    ctx = loop.step_context(data, config, torch.device("cpu"))
    assert not ctx.compiled
    why = cpu_step.unsupported_reason(spec, loop.resolve_backend(config.backend, "cpu"), ctx.formation, config)
    assert reason in why


def test_a_bad_step_choice_is_named(monkeypatch):
    monkeypatch.setenv(cpu_step.STEP_ENV, "fused")
    with pytest.raises(ValueError, match="EGOBENCH_TRAIN_STEP='fused'"):
        cpu_step.requested_step()


def test_a_timing_is_learned_only_where_the_method_renders_rolling_shutter_samples(plane):
    """The learned timing moves the pose samples: a velocity-shift or centre-pose method has none it could move, so
    it would record a timing that never got a gradient."""
    config = dataclasses.replace(CFG, learn_timing=True)
    for method in ("on_the_move", "no_motion_sampling"):
        with pytest.raises(ValueError, match="TrainConfig.learn_timing: method"):
            new_state(_data(plane, method, config), config, torch.device("cpu"))
    assert "timing" in new_state(_data(plane, "ours", config), config, torch.device("cpu")).extra
