"""The scene kinds behind a registry: `make_scene(kind, seed)` builds one (one module per kind)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from egobench.sim.world.lighting import Sun
from egobench.sim.world.primitives import SCENE_KINDS, SceneKind
from egobench.sim.world.scene import Scene
from egobench.sim.world.scenes import dtc_object, indoor, outdoor, quest3
from egobench.sim.world.variety import layout_spread, vary_content_and_light

#: scene kind -> its builder ``(rng, seed, spread) -> Scene`` (``spread``: the factor on its layout jitter) (one module per kind; a new kind is a module and a line here)
BUILDERS = {"outdoor": outdoor.build, "indoor": indoor.build, "object": dtc_object.build, "quest3": quest3.build}


def make_scene(kind: SceneKind, seed: int = 0, sun_scale: float = 1.0, grain: float = 0.0,
               variety: float = 0.0) -> Scene:
    """Build a scene of ``kind`` (outdoor, indoor, object, quest3); the layout jitter,
    colours and texture patterns follow ``seed`` deterministically. ``sun_scale`` multiplies
    the illuminance of every `Sun` (the sun-to-shade dynamic range; scenes without a sun ignore it);
    ``grain`` adds a fractal albedo grain of that amplitude to every surface (`grain_factor`); ``variety`` in
    [0, 1] makes each seed another world of the kind (`egobench.sim.world.variety`; 0: the same world,
    jittered, whatever the seed)."""
    if not (math.isfinite(grain) and 0.0 <= grain <= 1.0):
        raise ValueError(f"make_scene: grain must be a number in [0, 1], got {grain!r}")
    if kind not in BUILDERS:
        raise ValueError(f"make_scene: kind must be one of {list(SCENE_KINDS)}, got {kind!r}")
    if int(seed) != seed:
        raise ValueError(f"make_scene: seed must be an integer, got {seed!r}")
    if not (math.isfinite(sun_scale) and sun_scale >= 0):
        raise ValueError(f"make_scene: sun_scale must be a finite number >= 0, got {sun_scale!r}")
    rng = np.random.default_rng([int(seed), SCENE_KINDS.index(kind)])
    scene = BUILDERS[kind](rng, int(seed), layout_spread(variety))
    scene = vary_content_and_light(scene, np.random.default_rng([int(seed), SCENE_KINDS.index(kind), 1]), variety)
    scene.grain = float(grain)
    if sun_scale != 1.0:
        scene.lights = [replace(l, illuminance_lux=l.illuminance_lux * sun_scale) if isinstance(l, Sun) else l
                        for l in scene.lights]
    return scene
