"""Light sources of a synthetic world (sun, sky dome, ambient, point lights), in lux and candela."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np

from egobench import portable_math as pm
from egobench.sim.world.primitives import LUMINANCE_WEIGHTS, RGB, Vec3


@dataclass(frozen=True)
class Sun:
    """Directional light with cast shadows."""

    direction_to_sun: Vec3  # unit vector from the scene towards the sun (world)
    illuminance_lux: float  # illuminance on a surface facing the sun, lux (clear day: 30K-100K)
    rgb: RGB = (1.0, 0.97, 0.92)  # colour (normalised to luminance 1)


@dataclass(frozen=True)
class SkyDome:
    """Uniform sky above the horizon plus a ground bounce below it (outdoor ambient light)."""

    horizontal_illuminance_lux: float  # sky illuminance on an unshadowed horizontal surface, lux
    zenith_rgb: RGB = (0.55, 0.75, 1.25)  # sky colour overhead (normalised to luminance 1)
    horizon_rgb: RGB = (0.95, 1.0, 1.05)  # sky colour at the horizon (normalised to luminance 1)
    ground_albedo: float = 0.25  # albedo of the ground seen below the horizon (bounce light)


@dataclass(frozen=True)
class AmbientLight:
    """Uniform illuminance from every direction (inter-reflections of a room)."""

    illuminance_lux: float  # lux on any surface, whatever its orientation
    rgb: RGB = (1.0, 1.0, 1.0)  # colour (normalised to luminance 1)


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light: E = I cos(theta) / r^2."""

    position: Vec3  # world position, metres
    intensity_cd: float  # luminous intensity, candela
    rgb: RGB = (1.0, 0.95, 0.85)  # colour (normalised to luminance 1)
    cast_shadows: bool = False  # trace a shadow ray (costs one extra cast per light)


Light = Union[Sun, SkyDome, AmbientLight, PointLight]


def _rgb_unit_luminance(rgb: RGB) -> np.ndarray:
    a = np.asarray(rgb, dtype=np.float64)
    if a.shape != (3,) or not (y := pm.dot(a, LUMINANCE_WEIGHTS)) > 0:
        raise ValueError(f"light colour: expected an RGB triple with positive luminance, got {rgb}")
    return a / y
