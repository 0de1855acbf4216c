"""World variety: one scene kind, many worlds (the layout, the content and the lighting follow the seed).

At ``amount`` 0 a scene kind's worlds differ only by small layout jitter and texture seeds (what every
recording of the confirmatory run 1 used). Above 0 the builder's layout jitter is widened
(`layout_spread`) and `vary_content_and_light` redraws, from a stream of its own, every material's colours
and feature size and every light's strength (and the sun's position in the sky): a recording then stands for
another place of the same kind, as the paper's six outdoor and six indoor scenes do (docs/protocol.md,
protocol 2).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from egobench.sim.world.lighting import AmbientLight, PointLight, SkyDome, Sun
from egobench.sim.world.primitives import Material
from egobench.sim.world.scene import Scene

#: the layout jitter of a builder at ``amount`` 1 is this many times its amount-0 jitter
MAX_LAYOUT_SPREAD = 4.0
#: at ``amount`` 1: colour gains per channel exp(N(0, COLOUR_LOG_SD)), feature sizes x exp(U(-SCALE_LOG, +)),
#: light strengths x exp(U(-LIGHT_LOG, +)), the sun anywhere in azimuth and SUN_ELEVATION_DEG high
COLOUR_LOG_SD, SCALE_LOG, LIGHT_LOG = 0.3, 0.4, 0.5
SUN_ELEVATION_DEG = (25.0, 65.0)
#: colours stay albedos a real surface has
ALBEDO_RANGE = (0.02, 0.95)


def check_amount(amount: float) -> float:
    if isinstance(amount, bool) or not isinstance(amount, (int, float)) or not 0.0 <= amount <= 1.0:
        raise ValueError(f"world variety: expected a number in [0, 1], got {amount!r}")
    return float(amount)


def layout_spread(amount: float) -> float:
    """The factor on a builder's layout jitter: 1 at amount 0, `MAX_LAYOUT_SPREAD` at 1."""
    return 1.0 + (MAX_LAYOUT_SPREAD - 1.0) * check_amount(amount)


def _vary_material(mat: Material, rng: np.random.Generator, amount: float) -> Material:
    tex = mat.albedo
    gain = np.exp(rng.normal(0.0, COLOUR_LOG_SD * amount, 3))
    colors = tuple(tuple(float(np.clip(c * g, *ALBEDO_RANGE)) for c, g in zip(col, gain)) for col in tex.colors)
    scale = tex.scale_m * math.exp(rng.uniform(-SCALE_LOG, SCALE_LOG) * amount)
    return replace(mat, albedo=replace(tex, colors=colors, scale_m=scale))


def _vary_light(light, rng: np.random.Generator, amount: float):
    factor = math.exp(rng.uniform(-LIGHT_LOG, LIGHT_LOG) * amount)
    if isinstance(light, Sun):
        old = np.asarray(light.direction_to_sun, dtype=float)
        az0, el0 = math.atan2(old[1], old[0]), math.asin(float(np.clip(old[2], -1.0, 1.0)))
        az = az0 + amount * rng.uniform(-math.pi, math.pi)
        el = el0 + amount * (math.radians(rng.uniform(*SUN_ELEVATION_DEG)) - el0)
        direction = (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))
        return replace(light, direction_to_sun=direction, illuminance_lux=light.illuminance_lux * factor)
    if isinstance(light, SkyDome):
        return replace(light, horizontal_illuminance_lux=light.horizontal_illuminance_lux * factor)
    if isinstance(light, AmbientLight):
        return replace(light, illuminance_lux=light.illuminance_lux * factor)
    if isinstance(light, PointLight):
        return replace(light, intensity_cd=light.intensity_cd * factor)
    raise TypeError(f"world variety: no rule for a light of type {type(light).__name__}")


def vary_content_and_light(scene: Scene, rng: np.random.Generator, amount: float) -> Scene:
    """``scene`` with every material's colours and feature size, and every light, redrawn by ``amount`` in
    [0, 1] from ``rng`` (in the materials' and the lights' order: the same seed, the same world)."""
    amount = check_amount(amount)
    if amount == 0.0:
        return scene
    materials = {name: _vary_material(mat, rng, amount) for name, mat in scene.materials.items()}
    lights = [_vary_light(light, rng, amount) for light in scene.lights]
    return replace(scene, materials=materials, lights=lights)
