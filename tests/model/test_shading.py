"""egobench.model.shading: the learnable lens shading (model extension for an absorbed vignette)."""

import math
from dataclasses import replace

import pytest
import torch

from egobench.camera.pinhole import Pinhole
from egobench.model.shading import KEY, corner_attenuation, learned_vignette, radius2, shading

CAM = Pinhole(width=9, height=7, fx=10.0, fy=10.0, cx=4.0, cy=3.0)


def test_radius2_is_zero_at_the_centre_and_one_at_the_farthest_corner():
    r2 = radius2(CAM)
    assert r2[3, 4] == 0.0 and float(r2.max()) == pytest.approx(1.0)
    assert float(r2[0, 0]) == pytest.approx(1.0) and float(r2[0, 4]) == pytest.approx(9 / 25)
    moved = radius2(CAM, (1 / 9, 0.0))  # one pixel to the right
    assert moved[3, 5] == 0.0 and float(moved[0, 0]) == pytest.approx(1.0)  # (0, 0) is now the farthest corner


def test_shading_and_its_corner_attenuation():
    a = torch.tensor([-0.2, 0.05])
    s = shading(radius2(CAM), a)
    assert float(s[3, 4]) == 1.0 and float(s[0, 0]) == pytest.approx(math.exp(-0.15))
    assert corner_attenuation(a) == pytest.approx(1 - math.exp(-0.15))
    assert corner_attenuation([0.0, 0.0]) == 0.0


def test_learned_vignette_multiplies_only_when_the_run_learned_one():
    from egobench.train import TrainConfig

    v = torch.rand(7, 9)
    cfg = TrainConfig()
    assert learned_vignette(v, CAM, {}, cfg) is v
    a = torch.tensor([-0.3, 0.0])
    out = learned_vignette(v, CAM, {KEY: a}, replace(cfg, shading_centre_dx=1 / 9))
    assert torch.allclose(out, v * torch.exp(-0.3 * radius2(CAM, (1 / 9, 0.0))))


@pytest.mark.slow
def test_a_learned_shading_recovers_a_vignette_the_trained_model_absorbs(tmp_path):
    # the same scene with and without a hidden lens shading; paired with the null, the learned extra
    # darkening at the view's corner is the hidden one (the null's value is the model's own corner bias)
    from egobench.diagnose.trained_sweep import vignette_in_view
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig
    from egobench.train import preset_config, train

    learned = {}
    for name, strength in (("vig", 0.35), ("null", 0.0)):
        simulate_recording(SimConfig.from_overrides("indoor", 5, {
            "n_frames": 32, "rectified_size": 48, "motion": "fast", "readout_s": 0.01626,
            "vignette_strength": strength}), tmp_path / name, progress=False)
        tc = replace(preset_config("cpu"), max_side=0, device="cpu", learn_shading=True).scaled_to(600)
        r = train(tmp_path / name, "ours", tc, tmp_path / f"run-{name}", progress=False)
        learned[name] = r.record["learned_shading"]["corner_attenuation"]
    truth = vignette_in_view(tmp_path / "vig", 0.35)
    assert learned["vig"] - learned["null"] == pytest.approx(truth, rel=0.3)
    assert learned["vig"] > 0.05


def test_a_run_learning_a_shading_resumes_to_the_uninterrupted_result_and_renders_with_it(tmp_path):
    from egobench.data import load_recording
    from egobench.model.predict import frame_maps, run_maps
    from egobench.sim.plane import plane_recording
    from egobench.train import TrainConfig, train
    from egobench.train.checkpoint import load_trained_run

    rec = plane_recording(tmp_path / "toy", size=32, n_frames=17, angular_speed_rad_s=1.0, n_points=800,
                          frame_interval_s=0.05)
    cfg = TrainConfig(iterations=30, max_gaussians=1000, learn_shading=True, lr_shading=0.05, checkpoint_every=10)
    train(rec, "ours", cfg, tmp_path / "a", progress=False)
    train(rec, "ours", cfg, tmp_path / "b", progress=False, stop_after=15)
    train(rec, "ours", cfg, tmp_path / "b", progress=False, resume=True)
    ea = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["extra"][KEY]
    eb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["extra"][KEY]
    assert torch.equal(ea, eb) and bool(ea.abs().sum() > 0)
    run = load_trained_run(tmp_path / "a", None, "test")
    r = rec if hasattr(rec, "frames") else load_recording(rec, "online")
    expected = frame_maps(r, run.camera).vignette * shading(radius2(run.camera), ea)
    assert torch.allclose(run_maps(r, run).vignette, expected)
