"""The simulator knobs of the similarity-designed suite: narrow rectified view, raw ROI casting,
fractal grain and sun scale (docs/similarity.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egobench.sim.config import SimConfig


def _sim(tmp_path, name: str, **overrides):
    from egobench.sim.capture import simulate_recording

    base = {"n_frames": 3, "rectified_size": 32, "rectified_focal_ratio": 2.0, "exposure_s": 0.002, "gain": 2.0,
            "n_semidense_points": 500, "motion": "fast", "name": name}
    cfg = SimConfig.from_overrides("indoor", 4, {**base, **overrides})
    out = tmp_path / name
    simulate_recording(cfg, out, progress=False)
    return out, cfg


def test_raw_roi_gives_the_same_images_with_a_fraction_of_the_rays(tmp_path):
    """With a fixed exposure, fixed temporal samples and no noise (the Poisson draws and the
    preview-chosen sample count are the only things the ROI changes) the rectified frames of both
    streams are byte-identical with and without the ROI, while the ROI casts under a quarter of
    the raw pixels."""
    from egobench.sim.capture import build_capture_setup
    from egobench.data.transforms import read_png

    same = {"noise": False, "temporal_samples": 4}
    full, cfg = _sim(tmp_path, "full", raw_roi=False, **same)
    roi, cfg_roi = _sim(tmp_path, "roi", raw_roi=True, **same)
    streams = sorted(p.name for p in full.glob("camera-*"))
    assert streams == ["camera-rgb-rectified-64-h32", "camera-rgb-rectified-64-h32-factory-calib"]
    for s in streams:
        for k in range(3):
            a = read_png(full / s / "images" / f"{k:05d}.png", "image", grey=False)
            b = read_png(roi / s / "images" / f"{k:05d}.png", "image", grey=False)
            assert np.array_equal(a, b), (s, k)
    n_full = int(build_capture_setup(cfg).raw.valid.sum())
    setup = build_capture_setup(cfg_roi)
    assert int(setup.raw.valid.sum()) < 0.25 * n_full
    r0, r1, c0, c1 = setup.raw.box
    assert setup.raw.valid[:r0].sum() == 0 and setup.raw.valid[r1:].sum() == 0
    assert setup.raw.valid[:, :c0].sum() == 0 and setup.raw.valid[:, c1:].sum() == 0


def test_focal_ratio_sets_the_pinhole_and_scales_the_raw_frame():
    from egobench.sim.devices import get_device

    dev = get_device("aria")
    wide = SimConfig.from_overrides("indoor", 0, {"rectified_size": 64})
    narrow = SimConfig.from_overrides("indoor", 0, {"rectified_size": 64, "rectified_focal_ratio": 2.0})
    assert wide.focal_ratio() == dev.rectified_focal_ratio
    assert narrow.focal_ratio() == 2.0
    # the raw frame keeps the device's raw-to-rectified focal ratio: 4x the focal, 4x the rows
    assert narrow.raw_shape() == dev.default_raw_size(256)
    with pytest.raises(ValueError, match="rectified_focal_ratio"):
        SimConfig.from_overrides("indoor", 0, {"rectified_focal_ratio": 0.0})


def _band_powers(signal: np.ndarray, spacing_m: float, bands: list[float]) -> list[float]:
    """Power of ``signal`` in each octave [f, 2 f) (cycles per metre)."""
    spec = np.abs(np.fft.rfft(signal - signal.mean())) ** 2
    freq = np.fft.rfftfreq(signal.size, spacing_m)
    return [float(spec[(freq >= f) & (freq < 2 * f)].sum()) for f in bands]


def test_grain_has_equal_power_per_octave_and_fades_with_the_footprint():
    """1/f amplitude spectrum: equal power per octave (within 2x) from 0.5 m to 8 mm features;
    a footprint wider than the largest feature leaves the albedo untouched."""
    from egobench.sim.world import grain_factor

    n, dx = 1 << 16, 0.0005  # a 32.8 m line sampled every 0.5 mm
    x = torch.arange(n, dtype=torch.float64) * dx
    uv = torch.stack([x, torch.full_like(x, 0.123)], -1)
    pid = torch.zeros(n, dtype=torch.int64)
    g = grain_factor(uv, pid, 0.5, seed=3).numpy()
    assert abs(g.mean() - 1.0) < 0.05  # the 0.5 m octave has only ~65 lattice cells on this line
    powers = _band_powers(g, dx, [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])  # 0.5 m ... 8 mm features
    assert max(powers) / min(powers) < 2.5, powers
    # a 1/f^2 amplitude (fbm with halving amplitude) would drop 4x per octave: 256x over these bands
    blurred = grain_factor(uv, pid, 0.5, seed=3, footprint_m=torch.full((n,), 2.0, dtype=torch.float64))
    assert torch.allclose(blurred, torch.ones_like(blurred), atol=1e-12)
    assert not np.allclose(g, grain_factor(uv, pid, 0.5, seed=4).numpy())


def test_sun_scale_scales_only_the_sun():
    from egobench.sim.world import make_scene

    p = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)  # open ground in the walk region
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    E = [float(make_scene("outdoor", 0, sun_scale=s).irradiance(p, up).sum()) for s in (0.0, 1.0, 2.0)]
    assert E[1] - E[0] > 5 * E[0]  # sunlit: the sun is most of the light (60 klux at 50 deg vs 4 klux sky)
    assert math.isclose(E[2] - E[1], E[1] - E[0], rel_tol=1e-9)
    indoor = [make_scene("indoor", 0, sun_scale=s).irradiance(p + torch.tensor([[0, 0, 1.0]]), up) for s in (0.5, 2)]
    assert torch.equal(indoor[0], indoor[1])


def test_auto_exposure_meters_over_the_online_view_only():
    """With the raw ROI, a larger factory-calibration error widens the cast region (the factory
    stream samples more raw pixels) but must not move where the auto-exposure meters: the metering
    box is the online (true) view's, identical for the default factory errors and large ones."""
    from egobench.sim.capture import build_capture_setup

    base = {"n_frames": 3, "rectified_size": 32, "rectified_focal_ratio": 2.0, "raw_roi": True}
    big = {"factory_focal_frac": 0.1, "factory_principal_px": 300.0}  # a moved, wider factory footprint
    small_setup = build_capture_setup(SimConfig.from_overrides("indoor", 4, base))
    big_setup = build_capture_setup(SimConfig.from_overrides("indoor", 4, {**base, **big}))
    assert big_setup.raw.box != small_setup.raw.box  # the factory stream's footprint grew
    assert big_setup.raw.meter_box == small_setup.raw.meter_box
    r0, r1, c0, c1 = small_setup.raw.meter_box
    R0, R1, C0, C1 = small_setup.raw.box
    assert R0 <= r0 < r1 <= R1 and C0 <= c0 < c1 <= C1


def test_a_view_readout_window_spans_the_readout_over_the_view():
    """readout_window = "view": the rolling shutter reads only the rows the online view samples, so
    the written row-time ratio runs from ~0 to ~1 across the view (the paper's 90 deg view: 0.11-0.89)
    instead of a narrow band around 0.5, and the raw rows' start times run from read start at the
    window's first row to read start + readout at its last."""
    from egobench.sim.capture import build_capture_setup, row_start_times_ns

    base = {"n_frames": 3, "rectified_size": 32, "rectified_focal_ratio": 2.0, "raw_roi": True}
    sensor = build_capture_setup(SimConfig.from_overrides("indoor", 4, base))
    view = build_capture_setup(SimConfig.from_overrides("indoor", 4, {**base, "readout_window": "view"}))
    r_sensor = sensor.rigs["online"][0].row_time_ratio(sensor.raw.readout_rows)[sensor.rigs["online"][0].valid]
    r_view = view.rigs["online"][0].row_time_ratio(view.raw.readout_rows)[view.rigs["online"][0].valid]
    assert sensor.raw.readout_rows is None and float(r_sensor.max() - r_sensor.min()) < 0.4
    assert float(r_view.min()) < 0.1 and float(r_view.max()) > 0.9  # the window keeps a 2 px margin
    np.testing.assert_allclose(view.truth_rays.row_time_ratio[view.truth_rays.valid].numpy(), r_view.numpy(), atol=1e-6)
    a, b = view.raw.readout_rows
    t = row_start_times_ns(1_000_000, 0.05, view.raw.valid.shape[0], (a, b))
    assert int(t[a]) == 1_000_000 and int(t[b]) == 1_000_000 + 50_000_000
    assert int(t[0]) == 1_000_000 and int(t[-1]) == 1_000_000 + 50_000_000  # rows outside are clamped
    assert int(t[(a + b) // 2]) == pytest.approx(1_000_000 + 25_000_000, abs=50_000_000 / (b - a))
    with pytest.raises(ValueError, match="readout_window"):
        SimConfig.from_overrides("indoor", 4, {**base, "readout_window": "rows"})
