"""Device profiles, SimConfig validation, calibrations, auto-exposure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egobench.sim.config import SimConfig, hidden_effect_overrides
from egobench.sim.devices import ARIA_RGB, ARIA_SLAM, DEVICES, QUEST3, get_device


def test_aria_constants_match_the_real_calibration(shared_data):
    from egobench.data.mps import read_online_calibration

    rec = read_online_calibration(shared_data / "aria_mps_sample" / "online_calibration.jsonl")[0]
    rgb = rec.camera("camera-rgb")
    assert (rgb.width, rgb.height) == ARIA_RGB.native_size
    np.testing.assert_allclose(rgb.params, ARIA_RGB.lens_params, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rgb.T_device_camera, ARIA_RGB.T_device_camera().numpy(), atol=1e-9)
    assert rgb.time_offset_s == pytest.approx(ARIA_RGB.time_offset_s)
    slam = rec.camera("camera-slam-left")
    np.testing.assert_allclose(slam.params, ARIA_SLAM.lens_params, atol=1e-12)


def test_lens_scaling_keeps_the_pixel_centre_convention():
    cam_native = ARIA_RGB.camera(1408, 1408)
    cam_small = ARIA_RGB.camera(154, 154)
    pts = torch.tensor([[0.1, -0.2, 1.0], [0.5, 0.3, 0.8], [0.0, 0.0, 1.0]], dtype=torch.float64)
    uv_n, _ = cam_native.project(pts)
    uv_s, _ = cam_small.project(pts)
    s = 154 / 1408
    torch.testing.assert_close(uv_s, (uv_n + 0.5) * s - 0.5, atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="aspect ratio"):
        ARIA_RGB.lens_params_at(100, 120)


def test_readout_scales_with_rows_and_can_be_overridden():
    assert ARIA_RGB.readout_s(2880) == pytest.approx(16.26e-3)
    assert ARIA_RGB.readout_s(128) == pytest.approx(16.26e-3 * 128 / 2880)  # ~0.72 ms
    assert ARIA_RGB.readout_s(128, override=16.26e-3) == pytest.approx(16.26e-3)
    assert ARIA_SLAM.readout_s(480) == 0.0
    assert QUEST3.fps == 30 and ARIA_RGB.fps == 10
    with pytest.raises(ValueError, match="device"):
        get_device("hololens")
    assert set(DEVICES) == {"aria", "quest3"}


@pytest.mark.parametrize("overrides, field", [
    ({"exposure_s": -1e-3}, "SimConfig.exposure_s"),
    ({"readout_s": 0.2}, "readout"),
    ({"readout_scale": 0.0}, "SimConfig.readout_scale"),
    ({"n_frames": 0}, "SimConfig.n_frames"),
    ({"white_balance": (1.0, -1.0, 1.0)}, "SimConfig.white_balance"),
    ({"motion": "sprint"}, "SimConfig.motion"),
    ({"device": "hololens"}, "SimConfig.device"),
    ({"exposure_s": 0.0995}, "SimConfig.exposure_s"),
    ({"response_gamma": float("nan")}, "SimConfig.response_gamma"),
])
def test_config_validation_names_the_field(overrides, field):
    cfg = SimConfig(kind="outdoor")
    for k, v in overrides.items():
        setattr(cfg, k, v)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        cfg.validate()


def test_unknown_kind_and_field_and_parsing():
    with pytest.raises(ValueError, match=r"SimConfig\.kind"):
        SimConfig(kind="mars").validate()
    with pytest.raises(ValueError, match="unknown field 'bogus'"):
        SimConfig.from_overrides("indoor", 0, {"bogus": "1"})
    with pytest.raises(ValueError, match=r"SimConfig\.n_frames"):
        SimConfig.from_overrides("indoor", 0, {"n_frames": "ten"})
    cfg = SimConfig.from_overrides("indoor", 3, {"n_frames": "7", "jpeg": "true", "white_balance": "1.1,1,0.9",
                                                 "exposure_s": "0.004", "readout_s": "none", "motion": "fast"})
    assert cfg.n_frames == 7 and cfg.jpeg is True and cfg.white_balance == (1.1, 1.0, 0.9)
    assert cfg.exposure_s == 0.004 and cfg.readout_s is None and cfg.motion == "fast" and cfg.seed == 3
    assert cfg.protocol == "indoor" and cfg.device_name == "aria"
    assert SimConfig(kind="quest3").device_name == "quest3"
    assert SimConfig.from_dict(cfg.to_dict()) == cfg


def test_every_effect_maps_to_config_fields():
    from egobench.effects import EFFECTS

    for name, effect in EFFECTS.items():
        value = effect.sample_hidden(0)
        cfg = SimConfig.from_overrides("indoor", 0, hidden_effect_overrides(name, value))
        assert cfg.validate() is cfg


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def test_calibration_perturbations_have_the_stated_magnitudes():
    from egobench.sim.camera_calibration import make_calibrations

    cfg = SimConfig(kind="outdoor", seed=5, distortion_k0_delta=0.004, time_offset_s=0.002).validate()
    cals = make_calibrations(cfg)
    t, o, f = cals.true, cals.online, cals.factory
    assert _angle_deg(t.T_device_camera[:3, :3].T @ f.T_device_camera[:3, :3]) == pytest.approx(0.2, abs=1e-6)
    assert np.linalg.norm(f.T_device_camera[:3, 3] - t.T_device_camera[:3, 3]) == pytest.approx(1e-3, rel=1e-9)
    assert abs(f.params[0] / t.params[0] - 1) == pytest.approx(0.002, rel=1e-9)
    h = cfg.raw_shape()[1]
    assert np.hypot(*(f.params[1:3] - t.params[1:3])) == pytest.approx(0.75 * h / 2880, rel=1e-9)
    assert abs(f.time_offset_s - t.time_offset_s) == pytest.approx(1e-3, rel=1e-9)
    assert _angle_deg(t.T_device_camera[:3, :3].T @ o.T_device_camera[:3, :3]) == pytest.approx(0.01, abs=1e-6)
    # hidden effects are unknown to the online calibration
    assert t.params[3] - o.params[3] == pytest.approx(0.004)
    assert t.time_offset_s - o.time_offset_s == pytest.approx(0.002, abs=3e-5)
    # seeded
    again = make_calibrations(cfg)
    np.testing.assert_array_equal(again.factory.T_device_camera, f.T_device_camera)


def test_auto_exposure_protocols():
    from egobench.sim.capture import AutoExposureState

    ae = AutoExposureState(device=ARIA_RGB, protocol="auto")
    exposure, gain = ae.step(1000.0)  # bright outdoor median: 0.18 / (0.36 * 1000) = 0.5 ms
    assert exposure == pytest.approx(0.5e-3) and gain == 1.0
    indoor = AutoExposureState(device=ARIA_RGB, protocol="indoor")
    exposure, gain = indoor.step(30.0)  # 0.18 / (0.36 * 30) = 16.7 ms*gain -> 2 ms cap, gain 8.3
    assert exposure == pytest.approx(2e-3) and gain == pytest.approx(0.18 / (0.36 * 30) / 2e-3)
    dark = AutoExposureState(device=ARIA_RGB, protocol="indoor")
    assert dark.step(0.5)[1] == 16.0  # gain saturates
    fixed = AutoExposureState(device=ARIA_RGB, protocol="fixed")
    first = fixed.step(100.0)
    assert fixed.step(10.0) == first
