"""Trainer: determinism, resume, convergence on a known scene, densification rules, guards, bad input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from egobench.model.optim import Densifier, DensifySchedule, make_adam
from egobench.sim.plane import plane_recording
from egobench.train import (
    PAPER_ITERATIONS, TrainConfig, TrainingDiverged, parse_overrides, train,
)

SMALL = dict(max_gaussians=1500, refine_every_frac=5 / 40 * 1.0)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """17 frames of a textured plane, 32x32, camera translating and yawing (2 held out... 3: 0, 8, 16)."""
    return plane_recording(tmp_path_factory.mktemp("toy"), size=32, n_frames=17, angular_speed_rad_s=1.0,
                         n_points=1200, frame_interval_s=0.05)


def _params(run_dir):
    return torch.load(run_dir / "checkpoint.pt", weights_only=True)["params"]


# ----------------------------------------------------------------------------- config
def test_schedule_scales_with_iterations():
    cfg = TrainConfig()
    assert (cfg.refine_start_iter, cfg.refine_stop_iter, cfg.refine_every, cfg.reset_every) == (500, 15_000, 100, 3_000)
    assert cfg.motion_warmup_iter == 7_500 and cfg.normal_start_iter == 7_000 and cfg.dist_start_iter == 3_000
    short = cfg.scaled_to(3_000)
    assert (short.refine_start_iter, short.refine_stop_iter, short.refine_every, short.reset_every) == (50, 1_500, 10, 300)
    assert short.motion_warmup_iter == 750 and short.iterations == 3_000
    assert cfg.hash("ours") != short.hash("ours") and cfg.hash("ours") != cfg.hash("splatfacto")


def test_means_lr_matches_the_paper_travel_on_a_short_schedule():
    """With means_travel_matched the means' lr is lr_means x 30K / iterations on a shorter schedule
    (the cpu preset), never lowered on a longer one; the Adam optimiser of the means starts there."""
    from egobench.train.state import _learning_rates

    paper = TrainConfig()
    assert paper.lr_means_at == paper.lr_means  # the paper preset keeps the paper's lr
    cpu = TrainConfig.cpu(iterations=1000)
    assert cpu.means_travel_matched and cpu.lr_means_at == pytest.approx(cpu.lr_means * 30.0)
    assert TrainConfig.cpu(iterations=60_000).lr_means_at == cpu.lr_means
    assert _learning_rates(cpu, scene_scale=2.0)["means"] == pytest.approx(cpu.lr_means * 30.0 * 2.0)
    assert cpu.hash("ours") != dataclasses.replace(cpu, means_travel_matched=False).hash("ours")


def test_a_field_added_later_keeps_the_hash_of_runs_trained_before_it():
    """`HASHED_WHEN_SET`: at its default a later field is not in the hash (the canonical JSON without it, as
    before it existed); set, it is, and every render of the run reads it through `TrainConfig.pose_sampling`."""
    import hashlib
    import json

    cfg = TrainConfig.cpu()
    later = ("pose_sample_step_px", "learn_timing", "lr_timing", "learn_frame_exposure",
             "lr_frame_exposure")  # the fields added after runs were recorded
    before = {k: v for k, v in cfg.to_dict().items() if k not in later}
    blob = json.dumps({"method": "ours", "config": before}, sort_keys=True, separators=(",", ":"))
    assert cfg.hash("ours") == hashlib.sha1(blob.encode()).hexdigest()
    assert dataclasses.replace(cfg, learn_timing=True).hash("ours") != cfg.hash("ours")
    assert dataclasses.replace(cfg, learn_frame_exposure=True).hash("ours") != cfg.hash("ours")
    fine = parse_overrides(cfg, ["pose_sample_step_px=0.25", "max_pose_samples=32"])
    assert fine.hash("ours") != dataclasses.replace(cfg, max_pose_samples=32).hash("ours")
    assert (fine.pose_sampling.step_px, fine.pose_sampling.max_samples, fine.pose_sampling.rule) == (0.25, 32, "code")
    with pytest.raises(ValueError, match="TrainConfig.pose_sample_step_px"):
        TrainConfig(pose_sample_step_px=0.0)


def test_overrides_and_errors():
    cfg = parse_overrides(TrainConfig(), ["lr_means=1e-3", "max_side=48", "opacity_reset=intended",
                                          "background=1,1,1"])
    assert cfg.lr_means == 1e-3 and cfg.max_side == 48 and cfg.opacity_reset == "intended"
    assert cfg.background == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="unknown TrainConfig field"):
        parse_overrides(TrainConfig(), ["nope=1"])
    with pytest.raises(ValueError, match="max_side=abc: expected a value of type int"):
        parse_overrides(TrainConfig(), ["max_side=abc"])
    with pytest.raises(ValueError, match="TrainConfig.iterations"):
        TrainConfig(iterations=0)


# ----------------------------------------------------------------------------- densification
def _dict_params(scales, opacities, n_extra_cols=3):
    N = len(scales)
    p = {
        "means": torch.nn.Parameter(torch.arange(N * 3, dtype=torch.float32).reshape(N, 3)),
        "scales": torch.nn.Parameter(torch.log(torch.tensor(scales, dtype=torch.float32))[:, None].repeat(1, 3)),
        "quats": torch.nn.Parameter(torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1)),
        "opacities": torch.nn.Parameter(torch.logit(torch.tensor(opacities, dtype=torch.float32))),
        "colors": torch.nn.Parameter(torch.rand(N, 3, generator=torch.Generator().manual_seed(N))),
    }
    opts = {k: make_adam(v, 0.0) for k, v in p.items()}  # lr 0: Adam state without moving the values
    for v in p.values():  # give Adam some state, which must follow the Gaussians
        v.grad = torch.ones_like(v)
    for o in opts.values():
        o.step()
        o.zero_grad()
    return p, opts


def _schedule(**kw):
    base = dict(grow_grad2d=2e-4, grow_scale3d=0.01, prune_opa=0.005, prune_scale3d=0.1, refine_start_iter=0,
                refine_stop_iter=1000, refine_every=1, reset_every=100, opacity_reset="gsplat", max_gaussians=0)
    base.update(kw)
    return DensifySchedule(**base)


def _accumulate(d, params, grads_px, width=100, height=100, step=1):
    means2d = torch.zeros(1, len(grads_px), 2, requires_grad=True)
    means2d.grad = torch.tensor(grads_px, dtype=torch.float32)[None, :, None].repeat(1, 1, 2) / math.sqrt(2)
    d.accumulate(params, step, means2d, torch.full((1, len(grads_px)), 5), width, height)


def test_densification_duplicates_splits_and_prunes_as_gsplat():
    # G0 small + high grad -> duplicate; G1 large + high grad -> split; G2 faint -> pruned; G3 kept.
    scales, opac = [0.005, 0.05, 0.02, 0.02], [0.5, 0.5, 0.001, 0.5]
    params, opts = _dict_params(scales, opac)
    d = Densifier(_schedule(), scene_scale=1.0)
    hi, lo = 1e-5, 1e-6  # px; normalised by W/2 = 50: 5e-4 > 2e-4 > 5e-5
    _accumulate(d, params, [hi, hi, lo, lo])
    torch.manual_seed(0)
    counts = d.refine(params, opts, step=1)
    assert counts == {"duplicated": 1, "split": 1, "pruned": 1, "capped": 0}
    s = torch.exp(params["scales"][:, 0]).detach()
    assert len(s) == 5
    np.testing.assert_allclose(sorted(s.tolist()), sorted([0.005, 0.005, 0.02, 0.05 / 1.6, 0.05 / 1.6]), rtol=1e-5)
    assert float(torch.sigmoid(params["opacities"].detach()).min()) > 0.005
    # The duplicate is an exact copy; split children sit within a few sigma of the parent (means[1] = [3, 4, 5]).
    m = params["means"].detach()
    small = torch.nonzero((s - 0.005).abs() < 1e-6).flatten()
    assert torch.equal(m[small[0]], m[small[1]])
    kids = torch.nonzero((s - 0.05 / 1.6).abs() < 1e-6).flatten()
    assert float((m[kids] - torch.tensor([3.0, 4.0, 5.0])).norm(dim=-1).max()) < 0.05 * 6
    # New Gaussians have zero Adam moments; the kept ones keep theirs; statistics were reset.
    st = opts["means"].state[params["means"]]["exp_avg"]
    assert st.shape == (5, 3) and float(st[0].abs().sum()) > 0 and float(st[-1].abs().sum()) == 0
    assert float(d.state["grad2d"].abs().sum()) == 0 and len(d.state["grad2d"]) == 5


@pytest.mark.parametrize("radii_dims", [2, 3])
def test_densification_statistics_are_gsplats_bit_for_bit(radii_dims):
    """The compiled statistics against gsplat's own `_update_state` (the masked gathers and index_add_):
    several views per render and several renders, radii [C, N] and [C, N, 2] (some zero)."""
    torch.manual_seed(0)
    N = 3000
    params = {k: torch.nn.Parameter(torch.randn(N, d)) for k, d in (("means", 3), ("scales", 3), ("quats", 4))}
    ours, theirs = Densifier(_schedule(), scene_scale=1.0), Densifier(_schedule(), scene_scale=1.0)
    for step, C in enumerate((6, 1, 3)):
        means2d = torch.randn(C, N, 2, requires_grad=True)
        (means2d * torch.randn(C, N, 2) * 10.0 ** torch.randint(-6, 2, (C, N, 1))).sum().backward()
        shape = (C, N) if radii_dims == 2 else (C, N, 2)
        radii = (torch.rand(shape) * 3).int()  # a third zero: not visible in that view
        ours.accumulate(params, step, means2d, radii, 128, 96)
        radii2 = radii if radii_dims == 3 else radii[..., None].expand(C, N, 2)
        info = {"width": 128, "height": 96, "n_cameras": C, "radii": radii2, "gaussian_ids": None, "means2d": means2d}
        theirs.strategy._update_state(params, theirs.state, info, packed=False)
    assert float(ours.state["count"].sum()) > N  # the views overlap: several additions per Gaussian
    assert torch.equal(ours.state["count"], theirs.state["count"])
    assert torch.equal(ours.state["grad2d"].view(torch.int32), theirs.state["grad2d"].view(torch.int32))


def test_no_refinement_outside_the_window_and_huge_pruned_after_reset():
    params, opts = _dict_params([0.02, 0.5], [0.5, 0.5])
    d = Densifier(_schedule(refine_start_iter=10, reset_every=20), scene_scale=1.0)
    _accumulate(d, params, [1e-5, 1e-6], step=5)
    assert d.refine(params, opts, step=5)["split"] == 0 and len(params["means"]) == 2  # step <= refine_start
    _accumulate(d, params, [1e-6, 1e-6], step=21)
    counts = d.refine(params, opts, step=21)
    # Statistics persist between refinements: G0's mean (5e-4 + 5e-5) / 2 > 2e-4 -> split (0.02 > 0.01);
    # step > reset_every: G1's max scale 0.5 > 0.1 * scene_scale -> pruned although its opacity is fine.
    assert counts == {"duplicated": 0, "split": 1, "pruned": 1, "capped": 0}
    np.testing.assert_allclose(torch.exp(params["scales"][:, 0]).tolist(), [0.02 / 1.6] * 2, rtol=1e-5)
    d2 = Densifier(_schedule(refine_stop_iter=3), scene_scale=1.0)
    params2, opts2 = _dict_params([0.005], [0.5])
    _accumulate(d2, params2, [1e-3], step=3)
    assert d2.state["grad2d"] is None  # no statistics from refine_stop on
    assert d2.refine(params2, opts2, step=3)["duplicated"] == 0


def test_opacity_reset_modes_and_cap():
    params, opts = _dict_params([0.02] * 4, [0.9, 0.2, 0.6, 0.05])
    d = Densifier(_schedule(reset_every=10), scene_scale=1.0)
    _accumulate(d, params, [1e-6] * 4, step=10)
    d.refine(params, opts, step=10)
    assert float(torch.sigmoid(params["opacities"].detach()).max()) == pytest.approx(0.9, rel=1e-5)  # gsplat 1.5.3: never
    d = Densifier(_schedule(reset_every=10, opacity_reset="intended"), scene_scale=1.0)
    _accumulate(d, params, [1e-6] * 4, step=10)
    d.refine(params, opts, step=10)
    assert float(torch.sigmoid(params["opacities"].detach()).max()) == pytest.approx(0.01, rel=1e-4)
    # Budget: 4 Gaussians, cap 5, all four want to grow -> only the largest-gradient one does.
    params, opts = _dict_params([0.005, 0.005, 0.05, 0.05], [0.9, 0.2, 0.6, 0.5])
    d = Densifier(_schedule(max_gaussians=5), scene_scale=1.0)
    _accumulate(d, params, [1e-5, 3e-5, 2e-5, 1.5e-5])
    assert d.refine(params, opts, step=1) == {"duplicated": 1, "split": 0, "pruned": 0, "capped": 3}
    assert len(params["means"]) == 5
    assert torch.equal(params["means"][1], params["means"][4])  # G1 (largest gradient) was duplicated


def test_growth_equals_gsplat_without_a_cap():
    """Our budgeted growth is gsplat's `_grow_gs` when the budget does not bind (random case)."""
    gen = torch.Generator().manual_seed(3)
    scales = (torch.rand(50, generator=gen) * 0.03).tolist()
    opac = (torch.rand(50, generator=gen) * 0.9 + 0.05).tolist()
    grads = (torch.rand(50, generator=gen) * 1e-5).tolist()
    results = []
    for use_gsplat in (False, True):
        params, opts = _dict_params(scales, opac)
        d = Densifier(_schedule(), scene_scale=1.0)
        _accumulate(d, params, grads)
        torch.manual_seed(7)
        if use_gsplat:
            d.strategy._grow_gs(params, opts, d.state, 1)
        else:
            d.grow(params, opts, 1)
        results.append({k: v.detach().clone() for k, v in params.items()})
    for k in results[0]:
        assert torch.equal(results[0][k], results[1][k]), k
    assert len(results[0]["means"]) > 50


# ----------------------------------------------------------------------------- training
def test_deterministic_and_resume_equals_uninterrupted(toy, tmp_path):
    cfg = TrainConfig(iterations=40, max_gaussians=1500, refine_start_frac=0.1, refine_every_frac=0.1,
                      motion_warmup_frac=0.5, checkpoint_every=10)
    a = train(toy, "ours", cfg, tmp_path / "a", progress=False)
    b = train(toy, "ours", cfg, tmp_path / "b", progress=False)
    pa, pb = _params(tmp_path / "a"), _params(tmp_path / "b")
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    assert a.num_gaussians != 1200  # densification happened, and identically
    # Interrupted at 25 (a checkpoint at 20 exists in between, then the stop writes 25), resumed to 40.
    part = train(toy, "ours", cfg, tmp_path / "c", progress=False, stop_after=25)
    assert part.iterations == 25 and not part.record["complete"]
    c = train(toy, "ours", cfg, tmp_path / "c", progress=False, resume=True)
    assert c.iterations == 40 and c.record["complete"]
    pc = _params(tmp_path / "c")
    for k in pa:
        assert torch.equal(pa[k], pc[k]), k
    other = train(toy, "ours", dataclasses.replace(cfg, seed=1), tmp_path / "d", progress=False)
    assert not torch.equal(_params(tmp_path / "d")["means"][:100], pa["means"][:100]) or other.num_gaussians != a.num_gaussians
    with pytest.raises(ValueError, match="different training config"):
        train(toy, "ours", dataclasses.replace(cfg, lr_colors=0.1), tmp_path / "c", progress=False, resume=True)
    # The workflow's resume="auto": a matching interrupted checkpoint resumes to the same result ...
    train(toy, "ours", cfg, tmp_path / "e", progress=False, stop_after=25)
    e = train(toy, "ours", cfg, tmp_path / "e", progress=False, resume="auto")
    assert e.iterations == 40 and all(torch.equal(pa[k], _params(tmp_path / "e")[k]) for k in pa)
    # ... and a stale one (another config) is replaced by a fresh run, identical to training from scratch.
    fresh_cfg = dataclasses.replace(cfg, seed=1)
    train(toy, "ours", fresh_cfg, tmp_path / "e", progress=False, resume="auto")
    pe, pd = _params(tmp_path / "e"), _params(tmp_path / "d")
    assert all(torch.equal(pe[k], pd[k]) for k in pd)


def test_fits_a_known_scene(toy, tmp_path):
    """200 iterations from noisy points: training-image PSNR rises well above the initial one."""
    from egobench.evaluate import evaluate

    cfg = TrainConfig(iterations=200, lr_colors=1e-2, max_gaussians=3000, refine_every_frac=0.1)
    res = train(toy, "no_motion_sampling", cfg, tmp_path / "fit", progress=False)
    rec0 = train(toy, "no_motion_sampling", dataclasses.replace(cfg, iterations=1), tmp_path / "init", progress=False)
    e = evaluate(toy, tmp_path / "fit", save_renders=False)
    e0 = evaluate(toy, tmp_path / "init", save_renders=False)
    assert res.final_loss < 0.05
    assert e["metrics"]["psnr"] > 24.0, e["metrics"]
    assert e["metrics"]["psnr"] > e0["metrics"]["psnr"] + 8.0
    tj = res.record
    assert tj["train"]["iters_per_s"] > 0 and 0 < tj["train"]["raster_time_share"] < 1
    assert rec0.iterations == 1


@pytest.mark.parametrize("step", ["autograd", "auto"])
def test_nan_guard_names_iteration_and_quantity(toy, tmp_path, monkeypatch, step):
    """A rendered image that turns NaN at the fourth iteration is named, on both training paths (autograd
    through `render`; the compiled step's own render)."""
    import egobench.render as R
    from egobench.train import cpu_step

    calls = {"n": 0}

    def poison(rgb):
        calls["n"] += 1
        return rgb * float("nan") if calls["n"] == 4 else rgb

    def poisoned(*args, **kwargs):
        out = real(*args, **kwargs)
        out.rgb = poison(out.rgb)
        return out

    def poisoned_compiled(*args, **kwargs):
        rendered = real_compiled(*args, **kwargs)
        rendered.comp.out_feat = poison(rendered.comp.out_feat)
        return rendered

    real, real_compiled = R.render, cpu_step.render_fwd
    monkeypatch.setattr(R, "render", poisoned)
    monkeypatch.setattr(cpu_step, "render_fwd", poisoned_compiled)
    monkeypatch.setenv(cpu_step.STEP_ENV, step)
    with pytest.raises(TrainingDiverged, match="iteration 3: rendered rgb is not finite"):
        train(toy, "no_motion_sampling", TrainConfig(iterations=10), tmp_path / "nan", progress=False)
    assert calls["n"] == 4


def test_on_the_move_corrects_a_displaced_frame(toy, tmp_path):
    """on_the_move (velocity shift, exposure samples, pose/velocity optimisation) on the factory stream,
    where one training frame's pose is displaced 15 cm along its camera x: the per-frame pose correction
    moves that frame back (its image misalignment falls from 1.73 px to under half), and the held-out
    PSNR rises well above the untrained model's."""
    from egobench.evaluate import evaluate
    from egobench.geometry import se3_exp

    shift = torch.tensor([0.15, 0, 0, 0, 0, 0], dtype=torch.float64)
    frames = [dataclasses.replace(f, T_world_camera=f.T_world_camera @ se3_exp(shift)) if f.index == 5 else f
              for f in toy.frames]
    factory = dataclasses.replace(toy, calibration="factory", frames=frames)
    cfg = TrainConfig(iterations=120, motion_warmup_frac=0.0, lr_pose=3e-3, refine_start_frac=1.0)
    train(factory, "on_the_move", cfg, tmp_path / "otm", progress=False)
    train(factory, "on_the_move", dataclasses.replace(cfg, iterations=1), tmp_path / "init", progress=False)
    ck = torch.load(tmp_path / "otm" / "checkpoint.pt", weights_only=True)
    assert ck["extra"]["twist"].shape == (len(toy.train_frames), 6)
    delta = ck["extra"]["pose_delta"][ck["extra_frames"].index(5)].double()

    def misalignment_px(T_world_camera: torch.Tensor) -> float:
        """Mean image distance, over three pixels of frame 5's true view, of the plane points
        (z = 2.5 m) they see, reprojected with T_world_camera."""
        true = next(f for f in toy.frames if f.index == 5).T_world_camera
        uv = torch.tensor([[16.0, 16.0], [4.0, 16.0], [28.0, 16.0]], dtype=torch.float64)
        rays = toy.camera.unproject(uv)
        X = (rays * (2.5 / rays[:, 2:3])) @ true[:3, :3].T + true[:3, 3]
        T_cw = torch.linalg.inv(T_world_camera)
        p, _ = toy.camera.project(X @ T_cw[:3, :3].T + T_cw[:3, 3])
        return float((p - uv).norm(dim=1).mean())

    recorded = frames[5].T_world_camera
    before = misalignment_px(recorded)
    assert before == pytest.approx(0.15 / 2.5 * toy.camera.fx, rel=1e-6)  # 1.73 px: a fronto-parallel shift
    assert misalignment_px(recorded @ se3_exp(delta)) < 0.5 * before
    e, e0 = evaluate(factory, tmp_path / "otm", save_renders=False), evaluate(factory, tmp_path / "init", save_renders=False)
    assert e["metrics"]["psnr"] > e0["metrics"]["psnr"] + 6.0, (e["metrics"], e0["metrics"])
    with pytest.raises(ValueError, match="needs the 'online' calibration"):
        train(factory, "ours", cfg, tmp_path / "x", progress=False)


def test_2dgs_normal_term_turns_surfels_onto_the_plane(tmp_path):
    """2DGS on the toy plane: with the normal-consistency term the rendered normals agree with the
    plane's (ground truth: the true scene's normal map) better than without it, and depth is right."""
    from egobench.evaluate import evaluate

    rec = plane_recording(tmp_path / "rec", size=32, n_frames=17, angular_speed_rad_s=1.0, n_points=1200,
                          frame_interval_s=0.05, with_ground_truth=True)
    cfg = TrainConfig(iterations=40, motion_warmup_frac=0.0, refine_start_frac=1.0, lr_quats=1e-2,
                      normal_start_frac=0.0, dist_start_frac=0.0)
    metrics = {}
    for lam in (0.0, 0.2):
        train(rec, "ours_2dgs", dataclasses.replace(cfg, normal_lambda=lam), tmp_path / f"n{lam}", progress=False)
        metrics[lam] = evaluate(rec, tmp_path / f"n{lam}", save_renders=False)["metrics"]
    # measured (seed 0): normal L1 0.644 without the term, 0.475 with it; depth SI-L1 ~8 mm
    assert metrics[0.2]["normal_l1"] < metrics[0.0]["normal_l1"] - 0.1, metrics
    assert metrics[0.2]["depth_si_l1"] < 0.02, metrics


# ----------------------------------------------------------------------------- bad input
def test_bad_inputs_are_named_before_training(toy, tmp_path):
    cfg = TrainConfig(iterations=2)
    no_depth = dataclasses.replace(toy, frames=[dataclasses.replace(f, sparse_depth=None) for f in toy.frames])
    with pytest.raises(ValueError, match=r"no sparse depth; method 'ours'"):
        train(no_depth, "ours", cfg, tmp_path / "a", progress=False)
    train(no_depth, "no_motion_sampling", cfg, tmp_path / "b", progress=False)  # centre-row: not needed
    bad_gain = dataclasses.replace(toy, frames=[dataclasses.replace(f, gain=float("nan")) for f in toy.frames])
    with pytest.raises(ValueError, match=r"frame 0 has gain=nan; method 'ours' models exposure and gain"):
        train(bad_gain, "ours", cfg, tmp_path / "c", progress=False)
    splat = dataclasses.replace(bad_gain, calibration="factory")
    train(splat, "splatfacto", cfg, tmp_path / "d", progress=False)  # no formation: not needed
    wrong_cam = dataclasses.replace(toy, camera=dataclasses.replace(toy.camera, width=40))
    with pytest.raises(ValueError, match="mask has shape .* the calibration says"):
        train(wrong_cam, "ours", cfg, tmp_path / "e", progress=False)
    wrong_img = dataclasses.replace(toy, camera=dataclasses.replace(toy.camera, width=40, height=40),
                                    mask=torch.ones(40, 40, dtype=torch.bool), vignette=torch.ones(40, 40),
                                    row_time_ratio=torch.zeros(40, 40))
    with pytest.raises(ValueError, match="the calibration says 40x40"):
        train(wrong_img, "ours", cfg, tmp_path / "f", progress=False)
    with pytest.raises(ValueError, match="unknown method"):
        train(toy, "nope", cfg, tmp_path / "g", progress=False)


# ----------------------------------------------------------------------------- 2DGS regularisers
def test_depth_normals_face_the_camera_like_rendered_2dgs_normals():
    """Depth normals of a tilted plane equal its analytic camera-facing normal, and the 2DGS
    normal-consistency term of a surfel lying in that plane is ~0 (a sign error made it ~2 x lambda,
    pushing surfels edge-on)."""
    from egobench.camera.pinhole import Pinhole
    from egobench.render import render
    from egobench.render.types import Gaussians
    from egobench.train.losses import twodgs_regularisers
    from egobench.train.normal_consistency import depth_normals

    cam = Pinhole(fx=20.0, fy=20.0, cx=7.5, cy=7.5, width=16, height=16)
    # plane n . p = c with a camera-facing unit normal (n . p < 0 for points in front of the camera)
    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0]), dim=0)
    c = float(n @ torch.tensor([0.0, 0.0, 2.0]))
    rays = cam.unproject(cam.pixel_grid(dtype=torch.float32))  # [H, W, 3], z = 1
    depth = c / (rays @ n)  # z-depth of the ray-plane intersection
    dn = depth_normals(depth, cam)
    assert torch.allclose(dn[1:-1, 1:-1], n.expand(14, 14, 3), atol=1e-4)

    # Rendered 2DGS normals face the camera too: a tilted surfel in that plane renders n ...
    z = -n
    x = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), z), dim=0)
    R = torch.stack([x, torch.linalg.cross(z, x), z], dim=1)
    w = torch.sqrt(1 + R.trace()) / 2
    q = torch.stack([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])

    def surfel(quat):
        g = Gaussians(means=torch.tensor([[0.0, 0.0, 2.0]]), quats=quat[None],
                      log_scales=torch.log(torch.tensor([[3.0, 3.0, 3.0]])), opacity_logits=torch.tensor([6.0]),
                      colors=torch.tensor([[0.5, 0.5, 0.5]]))
        return render(g, cam, torch.eye(4)[None], mode="2dgs", want_normal=True)

    out = surfel(q)
    assert torch.allclose(torch.nn.functional.normalize(out.normal[0, 8, 8], dim=0), n, atol=1e-4)
    # ... and a fronto-parallel surfel (constant depth: gsplat's 2DGS depth is the centre depth) has
    # zero normal-consistency loss; with opposite-facing depth normals it was 2 x lambda x alpha.
    out = surfel(torch.tensor([1.0, 0.0, 0.0, 0.0]))
    cfg = TrainConfig(iterations=10, normal_lambda=1.0, normal_start_frac=0.0, dist_lambda=0.0)
    interior = torch.zeros(16, 16, 1)
    interior[1:-1, 1:-1] = 1.0
    assert float(out.alpha[0, 1:-1, 1:-1].min()) > 0.9
    reg = twodgs_regularisers([out], cam, cfg, 5, interior)
    assert float(reg) < 1e-4


def test_gaussians_near_a_training_camera_are_counted():
    """`near_camera_count`: centres within 0.2 m (the INRIA viewers' near plane) of any training camera centre,
    counted once however many cameras they are near; the boundary is exclusive."""
    from types import SimpleNamespace

    from egobench.train.record import near_camera_count

    def frame(x):
        T = torch.eye(4, dtype=torch.float64)
        T[0, 3] = x
        return SimpleNamespace(T_world_camera=T)

    means = torch.tensor([[0.1, 0.0, 0.0], [1.05, 0.0, 0.1], [0.5, 0.0, 0.0], [0.0, 0.0, 0.2], [3.0, 0.0, 0.0]])
    rec = near_camera_count(means, [frame(0.0), frame(1.0), frame(0.05)])
    assert (rec["count"], rec["of"], rec["radius_m"]) == (2, 5, 0.2)
