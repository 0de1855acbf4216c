"""The parts a synthetic world is made of: primitives, materials, the walk region, units and constants."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.sim.textures import Texture

SceneKind = Literal["outdoor", "indoor", "object", "quest3"]
SCENE_KINDS: tuple[str, ...] = ("outdoor", "indoor", "object", "quest3")
Vec3 = tuple[float, float, float]
RGB = tuple[float, float, float]

#: Rec.709 luminance weights: luminance (cd/m^2) or illuminance (lux) of a linear RGB triple.
LUMINANCE_WEIGHTS: RGB = (0.2126, 0.7152, 0.0722)
#: Default height of the eyes (device origin) above the floor, metres.
EYE_HEIGHT_M = 1.6
#: Boxes with a larger bounding radius (metres) are slab-tested against every ray instead of culled.
BIG_BOX_RADIUS_M = 2.5
#: Rays start this far from the surface they leave (shadow rays), metres.
SURFACE_EPS_M = 1e-4


def luminance(rgb: Tensor) -> Tensor:
    """Rec.709 luminance of linear RGB [..., 3] -> [...]."""
    w = torch.tensor(LUMINANCE_WEIGHTS, dtype=rgb.dtype, device=rgb.device)
    return pm.vecdot(rgb, w)


def _unit(v: Sequence[float], name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    n = pm.norm(a)
    if a.shape != (3,) or not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"{name}: expected a non-zero finite 3-vector, got {v}")
    return a / n


def rot_z(deg: float) -> np.ndarray:
    """Rotation about world z by ``deg`` degrees (3x3 float64)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is ``axis`` (unit)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= pm.norm(x)
    y = np.cross(axis, x)
    return np.stack([x, y, axis], axis=1)


# ----------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Rect:
    """A finite oriented rectangle (two-sided). Normal = axis_u x axis_v."""

    center: Vec3  # world position of the centre, metres
    axis_u: Vec3  # in-plane direction of texture u (world, normalised on packing)
    axis_v: Vec3  # in-plane direction of texture v (made orthogonal to axis_u on packing)
    half_u_m: float  # half extent along axis_u, metres
    half_v_m: float  # half extent along axis_v, metres
    material: str  # key into Scene.materials


@dataclass(frozen=True)
class Box:
    """An oriented box. ``rotation`` columns are the box axes in world coordinates."""

    center: Vec3  # world position of the centre, metres
    half_size_m: Vec3  # half extents along the box axes, metres
    material: str  # key into Scene.materials
    rotation: tuple[Vec3, Vec3, Vec3] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))  # R_world_box rows


@dataclass(frozen=True)
class Sphere:
    """A sphere."""

    center: Vec3  # world position, metres
    radius_m: float  # radius, metres
    material: str  # key into Scene.materials


@dataclass(frozen=True)
class Cylinder:
    """A capped cylinder around ``axis`` through ``center``."""

    center: Vec3  # world position of the centre (mid-height), metres
    axis: Vec3  # axis direction (world, normalised on packing)
    radius_m: float  # radius, metres
    half_height_m: float  # half the length along the axis, metres
    material: str  # key into Scene.materials


Primitive = Union[Rect, Box, Sphere, Cylinder]


def axis_rect(center: Vec3, normal: Literal["+x", "-x", "+y", "-y", "+z", "-z"], size_m: tuple[float, float],
              material: str) -> Rect:
    """Axis-aligned rectangle facing ``normal``; u is horizontal and v up on vertical faces."""
    axes = {
        "+x": ((0, 1, 0), (0, 0, 1)), "-x": ((0, -1, 0), (0, 0, 1)),
        "+y": ((-1, 0, 0), (0, 0, 1)), "-y": ((1, 0, 0), (0, 0, 1)),
        "+z": ((1, 0, 0), (0, 1, 0)), "-z": ((1, 0, 0), (0, -1, 0)),
    }
    if normal not in axes:
        raise ValueError(f"axis_rect: normal must be one of {sorted(axes)}, got {normal!r}")
    u, v = axes[normal]
    return Rect(tuple(map(float, center)), tuple(map(float, u)), tuple(map(float, v)),
                0.5 * size_m[0], 0.5 * size_m[1], material)


def yaw_box(center: Vec3, size_m: Vec3, material: str, yaw_deg: float = 0.0) -> Box:
    """Box of full size ``size_m`` rotated by ``yaw_deg`` about world z."""
    R = rot_z(yaw_deg)
    return Box(tuple(map(float, center)), tuple(0.5 * float(s) for s in size_m), material,
               tuple(tuple(float(x) for x in row) for row in R))


# ----------------------------------------------------------------------------- materials, lights
@dataclass(frozen=True)
class Material:
    """Surface appearance: Lambertian albedo texture plus optional emission."""

    albedo: Texture  # procedural albedo (linear, 0..1)
    emission_cd_m2: float = 0.0  # emitted luminance, cd/m^2 (windows, screens, lamp shades); 0 = none
    emission_rgb: RGB = (1.0, 1.0, 1.0)  # emission colour (normalised to luminance 1 on use)
    emission_texture: Texture | None = None  # pattern multiplying the emission (e.g. window panes)


@dataclass(frozen=True)
class WalkRegion:
    """Where the head may move: an axis-aligned box or a ring in x-y, at an eye height.

    ``box``: x in center +- half_size[0], y in center +- half_size[1].
    ``ring``: radius from center in [radius_min_m, radius_max_m] (orbiting an object).
    """

    kind: Literal["box", "ring"]  # region shape in the x-y plane
    center_xy: tuple[float, float]  # region centre, metres
    half_size_xy: tuple[float, float] = (1.0, 1.0)  # box half extents, metres (box only)
    radius_min_m: float = 0.0  # ring inner radius, metres (ring only)
    radius_max_m: float = 1.0  # ring outer radius, metres (ring only)
    eye_height_m: float = EYE_HEIGHT_M  # nominal head height above the floor (z), metres

    def contains(self, points: np.ndarray, margin_m: float = 0.0, height_tol_m: float = 0.5) -> np.ndarray:
        """points [..., 3] -> bool [...]: inside (x-y region grown by margin) and near eye height."""
        p = np.asarray(points, dtype=np.float64)
        dx, dy = p[..., 0] - self.center_xy[0], p[..., 1] - self.center_xy[1]
        if self.kind == "box":
            inside = (np.abs(dx) <= self.half_size_xy[0] + margin_m) & (np.abs(dy) <= self.half_size_xy[1] + margin_m)
        else:
            r = np.hypot(dx, dy)
            inside = (r >= self.radius_min_m - margin_m) & (r <= self.radius_max_m + margin_m)
        return inside & (np.abs(p[..., 2] - self.eye_height_m) <= height_tol_m)

    def sample_xy(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n uniform points of the region -> [n, 2]."""
        if self.kind == "box":
            u = rng.uniform(-1.0, 1.0, size=(n, 2)) * np.asarray(self.half_size_xy)
            return u + np.asarray(self.center_xy)
        r = np.sqrt(rng.uniform(self.radius_min_m ** 2, self.radius_max_m ** 2, size=n))
        a = rng.uniform(0, 2 * np.pi, size=n)
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1) + np.asarray(self.center_xy)

    @property
    def center_point(self) -> np.ndarray:
        """A point of the region at eye height [3] (the box centre; the ring's mid-radius at angle 0)."""
        if self.kind == "box":
            return np.array([*self.center_xy, self.eye_height_m])
        r = 0.5 * (self.radius_min_m + self.radius_max_m)
        return np.array([self.center_xy[0] + r, self.center_xy[1], self.eye_height_m])
