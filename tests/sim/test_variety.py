"""World variety (egobench.sim.world.variety): at 0 a seed gives the kind's one world, as before; at 1 each
seed another world (layout, materials, lights), the same one for the same seed. An object capture's ground
truth carries the object's foreground."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egobench.sim.capture.frame import _foreground
from egobench.sim.capture.recording import simulate_recording
from egobench.sim.config import SimConfig
from egobench.sim.world import Sun, make_scene
from egobench.sim.world.variety import ALBEDO_RANGE, MAX_LAYOUT_SPREAD, layout_spread

KINDS = ("outdoor", "indoor", "object", "quest3")


def _colours(scene) -> dict:
    return {name: m.albedo.colors for name, m in scene.materials.items()}


@pytest.mark.parametrize("kind", KINDS)
def test_no_variety_is_the_kinds_one_world(kind):
    a, b = make_scene(kind, 11), make_scene(kind, 11, variety=0.0)
    assert _colours(a) == _colours(b) and a.lights == b.lights and repr(a.primitives) == repr(b.primitives)


@pytest.mark.parametrize("kind", KINDS)
def test_each_seed_another_world_the_same_for_the_same_seed(kind):
    a, b, c = (make_scene(kind, s, variety=1.0) for s in (11, 11, 12))
    assert _colours(a) == _colours(b) and a.lights == b.lights and repr(a.primitives) == repr(b.primitives)
    assert _colours(a) != _colours(c) and a.lights != c.lights and repr(a.primitives) != repr(c.primitives)
    plain = make_scene(kind, 11)
    assert _colours(a) != _colours(plain)
    for colours in _colours(a).values():  # albedos a real surface has
        assert all(ALBEDO_RANGE[0] <= x <= ALBEDO_RANGE[1] for col in colours for x in col)


def test_the_sun_moves_over_the_sky_and_stays_above_the_horizon():
    elevations, azimuths = [], []
    for seed in range(40):
        sun = next(light for light in make_scene("outdoor", seed, variety=1.0).lights if isinstance(light, Sun))
        d = np.asarray(sun.direction_to_sun)
        assert np.linalg.norm(d) == pytest.approx(1.0)
        elevations.append(math.degrees(math.asin(d[2])))
        azimuths.append(math.degrees(math.atan2(d[1], d[0])) % 360)
    assert 25.0 - 1e-9 <= min(elevations) and max(elevations) <= 65.0 + 1e-9
    assert max(elevations) - min(elevations) > 25.0
    assert np.histogram(azimuths, bins=4, range=(0, 360))[0].min() >= 4  # every quarter of the sky


def test_layout_spread_and_bad_amounts():
    assert layout_spread(0.0) == 1.0 and layout_spread(1.0) == MAX_LAYOUT_SPREAD
    for bad in (-0.1, 1.5, True, "1"):
        with pytest.raises(ValueError, match="world variety"):
            make_scene("indoor", 0, variety=bad)


def test_foreground_is_the_surface_points_in_the_box():
    """Rays from the origin along +x hit at t: points in the object's box are foreground, misses never."""
    class Box:
        foreground_box = ((1.0, -1.0, -1.0), (2.0, 1.0, 1.0))

    t = torch.tensor([0.5, 1.5, 1.5, 2.5, 1.99])
    hit = torch.tensor([True, True, False, True, True])
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(5, 3)
    valid = torch.tensor([[True, True, True], [False, True, True]])
    fg = _foreground(Box(), torch.zeros(5, 3), dirs, t, hit, valid)
    assert fg.tolist() == [[False, True, False], [False, False, True]]
    Box.foreground_box = None
    assert _foreground(Box(), torch.zeros(5, 3), dirs, t, hit, valid) is None


def test_an_object_capture_writes_its_foreground(tmp_path):
    """Every frame of an object capture has a foreground: some of the view, all of it on a surface nearer than
    the room (the orbit keeps the objects about 1.1-1.4 m away)."""
    config = SimConfig(kind="object", seed=3, n_frames=4, rectified_size=48, rectified_focal_ratio=3.0,
                       raw_roi=True, world_variety=1.0)
    simulate_recording(config, tmp_path / "object", progress=False)
    gt = tmp_path / "object" / "ground_truth"
    files = sorted((gt / "foreground").glob("*.npy"))
    assert len(files) == 4
    for f in files:
        fg, depth = np.load(f), np.load(gt / "depth" / f.name).astype(np.float64)
        assert fg.dtype == bool and fg.shape == depth.shape and 0.01 < fg.mean() < 0.9
        assert (depth[fg] > 0.5).all() and (depth[fg] < 2.0).all()
        assert depth[~fg & (depth > 0)].max() > 2.0  # the room behind is background
