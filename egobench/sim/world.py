"""Analytic synthetic worlds (not Gaussians): exact ray casting, HDR lighting, procedural detail.

Units and frames
----------------
- World frame: metres, right-handed, **z up** (gravity along -z, as in Aria MPS worlds). The
  floor/ground is z = 0; eye height is about 1.6 m.
- Radiance is photometric **luminance in cd/m^2** per linear RGB channel (light colours are
  normalised to Rec.709 luminance 1, so the luminance of an RGB value is
  0.2126 R + 0.7152 G + 0.0722 B).
- Irradiance is **illuminance in lux** per channel. A Lambertian surface of albedo rho under
  illuminance E has luminance ``L = rho * E / pi`` (cd/m^2 = lux / sr). This is the radiance
  <-> lux mapping used everywhere: ``radiance = albedo * irradiance / pi + emission``.
- Light sources: `Sun` (directional, illuminance at normal incidence, lux; always casts
  shadows), `SkyDome` (uniform sky of horizontal illuminance E_sky: a surface with normal n
  receives ``E_sky (1 + n_z) / 2`` plus ground bounce ``rho_g E_ground (1 - n_z) / 2``; rays
  that miss everything see the sky luminance ~E_sky / pi), `AmbientLight` (uniform
  illuminance from all directions: the inter-reflections of a room), `PointLight` (intensity in
  candela, ``E = I max(n.l, 0) / r^2``, optional shadows). Emissive surfaces (windows, screens)
  carry a luminance in cd/m^2.
- Typical levels (checked by tests): outdoor: sun 60 klux at 50 deg elevation, sky 4 klux, so
  the ground is 1 + 60000 sin(50 deg) / 4000 = 12.5x brighter in sun than in shade, sunlit
  surfaces 10^3-10^4 cd/m^2 and the median scene illuminance >= 3000 lux; indoor and quest3
  rooms 150-300 lux (surfaces 10-100 cd/m^2) with windows (1000 cd/m^2) 10-50x brighter than the
  room; the object lab ~300 lux, nearly uniform.

Primitives and ray casting
--------------------------
`Rect` (finite oriented rectangle, two-sided), `Box` (oriented), `Sphere`, `Cylinder` (capped).
`Scene.cast` works in ray chunks (``chunk_rays``) to bound memory, in the dtype of the rays
(float32 for images, float64 for exact tests). Rectangles, spheres and big boxes are tested
densely ([rays, primitives] tensors); small boxes and cylinders go through two-level
bounding-sphere culling (k-means groups of ~4, then members) and exact tests on the surviving
(ray, primitive) pairs only. Returned normals face the incoming ray. ``depth_t`` is the distance
along the *unit* direction. Pass ``pixel_angle_rad`` (~1 / focal_px) so that textures are
box-filtered over the pixel footprint (no moire on distant detail).
Rays that hit nothing see the sky (outdoor) and get ``depth_t = inf``, ``normal = 0``,
``primitive_id = -1``, ``hit = False``; indoor scenes are closed rooms, so every ray hits.

Adding a scene kind
-------------------
Write ``_build_<kind>(rng) -> Scene`` that lists primitives (each naming a material), a
``materials`` dict of `Material` (a `Texture` albedo, optional emission in cd/m^2), lights, a
`WalkRegion` (where the head may move: a box or a ring in x-y, at an eye height), look targets
(points of interest, [K, 3]) and the scene bounds; register it in ``_BUILDERS``. Keep the walk
region clear of furniture (the motion model does not do collision avoidance), keep textures
at feature sizes of a few mm or more, and check the illuminance with ``Scene.cast(...)
.illuminance_lux`` from the walk region.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.sim.textures import Texture, evaluate_texture

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


# ----------------------------------------------------------------------------- walk region
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


# ----------------------------------------------------------------------------- results
@dataclass
class RayHit:
    """What each ray sees (all tensors share the rays' dtype; N rays)."""

    radiance: Tensor  # [N, 3] linear luminance per channel, cd/m^2 (sky for misses)
    depth_t: Tensor  # [N] distance along the unit ray to the hit, metres (inf for misses)
    normal_world: Tensor  # [N, 3] unit normal facing the ray (0 for misses)
    hit: Tensor  # [N] bool
    primitive_id: Tensor  # [N] int64 index into Scene.primitives (-1 for misses)
    albedo: Tensor  # [N, 3] surface albedo (0 for misses)
    illuminance_lux: Tensor  # [N] illuminance on the hit surface, lux (0 for misses)


_TYPE_NAMES = ("rect", "box", "sphere", "cylinder")


# ----------------------------------------------------------------------------- surface frames
# Each takes a packed primitive table q (Scene._pack), the points' indices j [n] into it and the
# points p [n, 3] on those primitives, and returns (uv [n, 2] texture coordinates in metres,
# outward normal [n, 3], tangent_u [n, 3], tangent_v [n, 3]) in world coordinates.
def _rect_surface_frame(q: dict, j: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rectangles: uv along the rectangle's U and V axes from its centre."""
    rel = p - q["C"][j]
    uv = torch.stack([(rel * q["U"][j]).sum(1), (rel * q["V"][j]).sum(1)], 1)
    return uv, q["N"][j], q["U"][j], q["V"][j]


def _sphere_surface_frame(q: dict, j: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Spheres: uv = (longitude, latitude) x radius; tangent_u points east."""
    rel = p - q["C"][j]
    r = q["r"][j]
    n_ = rel / rel.norm(dim=1, keepdim=True).clamp_min(1e-12)  # exact unit length despite rounding
    lon = torch.atan2(n_[:, 1], n_[:, 0])
    lat = torch.asin(torch.clamp(n_[:, 2], -1.0, 1.0))
    uv = torch.stack([lon * r, lat * r], 1)
    east = torch.stack([-torch.sin(lon), torch.cos(lon), torch.zeros_like(lon)], 1)
    return uv, n_, east, torch.cross(n_, east, dim=1)


def _box_surface_frame(q: dict, j: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Oriented boxes: the face is the local axis where |p_local| / half-size is largest; uv in
    that face's plane, offset per face so that faces do not share texture."""
    R = q["R"][j]  # [n, 3, 3] columns = local axes
    loc = pm.vecdot(R.transpose(-1, -2), (p - q["C"][j])[:, None, :])
    h = q["H"][j]
    k = torch.argmax(torch.abs(loc) / h, dim=1)  # face axis
    sign = torch.sign(torch.gather(loc, 1, k[:, None]))[:, 0]
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    # (u, v) axes per face axis: x-face (y, z), y-face (x, z), z-face (x, y)
    ua = torch.tensor([1, 0, 0], device=p.device)[k]
    va = torch.tensor([2, 2, 1], device=p.device)[k]
    ar = torch.arange(len(k), device=p.device)
    uv = torch.stack([loc[ar, ua] + 3.7 * k.to(p.dtype) + 1.3 * (sign + 1), loc[ar, va]], 1)
    return uv, R[ar, :, k] * sign[:, None], R[ar, :, ua], R[ar, :, va]


def _cylinder_surface_frame(q: dict, j: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Capped cylinders: side uv = (angle x radius, height); caps uv = local (x, y), offset per cap."""
    R = q["R"][j]  # [n, 3, 3] columns = local axes
    loc = pm.vecdot(R.transpose(-1, -2), (p - q["C"][j])[:, None, :])
    r, hh = q["r"][j], q["h"][j]
    rho = torch.sqrt(loc[:, 0] ** 2 + loc[:, 1] ** 2)
    cap = (torch.abs(loc[:, 2]) - hh) > (rho - r)  # closer to a cap plane than to the side
    sgn = torch.sign(loc[:, 2])
    sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)
    ang = torch.atan2(loc[:, 1], loc[:, 0])
    side_n = torch.stack([torch.cos(ang), torch.sin(ang), torch.zeros_like(ang)], 1)
    cap_n = torch.stack([torch.zeros_like(ang), torch.zeros_like(ang), sgn], 1)
    n_loc = torch.where(cap[:, None], cap_n, side_n)
    uv_side = torch.stack([ang * r, loc[:, 2]], 1)
    uv_cap = torch.stack([loc[:, 0] + 5.0 * (sgn + 1), loc[:, 1]], 1)
    t_side = torch.stack([-torch.sin(ang), torch.cos(ang), torch.zeros_like(ang)], 1)
    t_cap = torch.zeros_like(t_side)
    t_cap[:, 0] = 1.0
    tu_loc = torch.where(cap[:, None], t_cap, t_side)
    tv_loc = torch.cross(n_loc, tu_loc, dim=1)
    return (torch.where(cap[:, None], uv_cap, uv_side), pm.vecdot(R, n_loc[:, None, :]),
            pm.vecdot(R, tu_loc[:, None, :]), pm.vecdot(R, tv_loc[:, None, :]))


@dataclass(eq=False)
class Scene:
    """An analytic world: primitives, materials, lights, and where a head may walk and look."""

    kind: str  # scene kind name (outdoor, indoor, object, quest3 or custom)
    primitives: list[Primitive]  # the geometry; primitive_id indexes this list
    materials: dict[str, Material]  # material name -> Material
    lights: list[Light]  # light sources (see module docstring)
    walk_region: WalkRegion  # where the head may move
    look_targets: np.ndarray  # [K, 3] points of interest (world, metres)
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]]  # (min xyz, max xyz), metres
    seed: int = 0  # the seed the scene was built from
    chunk_rays: int = 32768  # rays per internal chunk (bounds memory: ~chunk x primitives x 8 floats)
    grain: float = 0.0  # amplitude of a fractal albedo grain on every surface (see `grain_factor`); 0 = none
    _packs: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if not self.primitives:
            raise ValueError("Scene.primitives: expected at least one primitive")
        for i, p in enumerate(self.primitives):
            if not isinstance(p, (Rect, Box, Sphere, Cylinder)):
                raise ValueError(f"Scene.primitives[{i}]: expected Rect, Box, Sphere or Cylinder, got {type(p).__name__}")
            if p.material not in self.materials:
                raise ValueError(f"Scene.primitives[{i}].material: {p.material!r} is not in Scene.materials "
                                 f"({sorted(self.materials)})")
        self.look_targets = np.asarray(self.look_targets, dtype=np.float64).reshape(-1, 3)
        self._material_names = sorted(self.materials)
        self._material_index = np.array([self._material_names.index(p.material) for p in self.primitives])
        self._type_of = np.array([_TYPE_NAMES.index(type(p).__name__.lower()) for p in self.primitives])
        self._index_in_type = np.zeros(len(self.primitives), dtype=np.int64)
        for t in range(4):
            sel = np.nonzero(self._type_of == t)[0]
            self._index_in_type[sel] = np.arange(len(sel))

    # ------------------------------------------------------------------ packing
    def _pack(self, dtype: torch.dtype, device: torch.device) -> dict:
        key = (dtype, str(device))
        if key in self._packs:
            return self._packs[key]

        def T(a) -> Tensor:
            return torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=device)

        pk: dict = {}
        ids = {t: np.nonzero(self._type_of == t)[0] for t in range(4)}
        rects = [self.primitives[i] for i in ids[0]]
        if rects:
            U = np.stack([_unit(r.axis_u, "Rect.axis_u") for r in rects])
            V0 = np.stack([np.asarray(r.axis_v, dtype=np.float64) for r in rects])
            V = V0 - (V0 * U).sum(1, keepdims=True) * U
            V /= np.linalg.norm(V, axis=1, keepdims=True)
            N = np.cross(U, V)
            C = np.stack([np.asarray(r.center, dtype=np.float64) for r in rects])
            H = np.array([[r.half_u_m, r.half_v_m] for r in rects], dtype=np.float64)
            if not np.all(H > 0):
                raise ValueError("Rect.half_u_m/half_v_m: expected positive half extents in metres")
            pk["rect"] = dict(C=T(C), U=T(U), V=T(V), N=T(N), H=T(H), cU=T((C * U).sum(1)), cV=T((C * V).sum(1)),
                              cN=T((C * N).sum(1)), ids=torch.as_tensor(ids[0], device=device))
        # Boxes whose bounding sphere is large (facades, walls) are poorly culled by spheres: they
        # go through a dense slab test against every ray; the others through grouped culling.
        box_ids = ids[1]
        if len(box_ids):  # all boxes in primitive order, for surface attributes
            boxes = [self.primitives[i] for i in box_ids]
            pk["box_all"] = dict(C=T([b.center for b in boxes]), R=T([b.rotation for b in boxes]),
                                 H=T([b.half_size_m for b in boxes]))
        box_r = np.array([pm.norm(self.primitives[i].half_size_m) for i in box_ids])
        big = box_r > BIG_BOX_RADIUS_M
        parts = (("box_big", 1, box_ids[big]), ("box", 1, box_ids[~big]), ("cylinder", 3, ids[3]))
        for tname, t, sel_ids in parts:
            prims = [self.primitives[i] for i in sel_ids]
            if not prims:
                continue
            if t == 1:
                R = np.stack([np.asarray(b.rotation, dtype=np.float64) for b in prims])
                Hs = np.stack([np.asarray(b.half_size_m, dtype=np.float64) for b in prims])
                if not np.all(Hs > 0):
                    raise ValueError("Box.half_size_m: expected positive half extents in metres")
                extra = dict(H=T(Hs))
            else:
                R = np.stack([_frame_from_axis(_unit(c.axis, "Cylinder.axis")) for c in prims])
                rad = np.array([c.radius_m for c in prims], dtype=np.float64)
                hh = np.array([c.half_height_m for c in prims], dtype=np.float64)
                if not (np.all(rad > 0) and np.all(hh > 0)):
                    raise ValueError("Cylinder.radius_m/half_height_m: expected positive lengths in metres")
                extra = dict(r=T(rad), h=T(hh))
            err = np.abs(np.einsum("pji,pjk->pik", R, R) - np.eye(3)).max()
            if err > 1e-6:
                raise ValueError(f"Box.rotation: expected an orthonormal 3x3 rotation, max |R^T R - I| = {err:.2e}")
            C = np.stack([np.asarray(p.center, dtype=np.float64) for p in prims])
            bound_r = np.linalg.norm(Hs, axis=1) if t == 1 else np.hypot(rad, hh)
            bound_r = bound_r * (1 + 1e-6) + 1e-9
            P = len(prims)
            pk[tname] = dict(C=T(C), R=T(R), c2r2_bound=T((C * C).sum(1) - bound_r ** 2), r_bound=T(bound_r),
                             ids=torch.as_tensor(sel_ids, device=device),
                             # dense form: o @ Rflat -> [n, P*3] = R^T o per primitive
                             Rflat=T(R.transpose(1, 0, 2).reshape(3, P * 3)), cR=T(np.einsum("pj,pjk->pk", C, R)),
                             **extra)
            if tname != "box_big" and len(prims) > 8:  # two-level culling pays off beyond a few primitives
                gc, gr, members = _group_primitives(C, bound_r)
                pk[tname].update(G_C=T(gc), G_r=T(gr), G_c2r2=T((gc * gc).sum(1) - gr ** 2),
                                 G_members=torch.as_tensor(members, device=device))
        spheres = [self.primitives[i] for i in ids[2]]
        if spheres:
            C = np.stack([np.asarray(s.center, dtype=np.float64) for s in spheres])
            rad = np.array([s.radius_m for s in spheres], dtype=np.float64)
            if not np.all(rad > 0):
                raise ValueError("Sphere.radius_m: expected a positive radius in metres")
            pk["sphere"] = dict(C=T(C), r=T(rad), c2r2=T((C * C).sum(1) - rad ** 2), ids=torch.as_tensor(ids[2], device=device))
        self._packs[key] = pk
        return pk

    # ------------------------------------------------------------------ intersection
    def intersect(self, origins: Tensor, directions: Tensor, t_max: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Closest hit of each ray. origins, directions (unit) [N, 3]; t_max [N] or None.

        Returns (t [N], primitive_id [N] int64); misses have t = inf and id = -1.
        """
        n = origins.shape[0]
        t_out = torch.full((n,), math.inf, dtype=origins.dtype, device=origins.device)
        id_out = torch.full((n,), -1, dtype=torch.int64, device=origins.device)
        pk = self._pack(origins.dtype, origins.device)
        for s in range(0, n, self.chunk_rays):
            e = min(n, s + self.chunk_rays)
            o, d = origins[s:e], directions[s:e]
            best_t = torch.full((e - s,), math.inf, dtype=o.dtype, device=o.device)
            best_id = torch.full((e - s,), -1, dtype=torch.int64, device=o.device)
            if t_max is not None:  # shadow rays: only occluders closer than t_max matter
                best_t = t_max[s:e].clone()
            # cheap dense kinds first, so that the culled kinds see a short best_t
            for name, fn in (("rect", _hit_rects), ("box_big", _hit_boxes_dense), ("sphere", _hit_spheres),
                             ("box", _hit_boxes), ("cylinder", _hit_cylinders)):
                if name in pk:
                    best_t, best_id = fn(pk[name], o, d, best_t, best_id)
            if t_max is not None:
                best_t = torch.where(best_id < 0, torch.full_like(best_t, math.inf), best_t)
            t_out[s:e] = best_t
            id_out[s:e] = best_id
        return t_out, id_out

    # ------------------------------------------------------------------ surface attributes
    def surface_frame(self, points: Tensor, primitive_id: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Attributes of surface points. points [N, 3] on primitives primitive_id [N] (all >= 0).

        Returns (uv [N, 2] texture coordinates in metres, outward normal [N, 3],
        tangent_u [N, 3], tangent_v [N, 3]) in world coordinates.
        """
        pk = self._pack(points.dtype, points.device)
        N = points.shape[0]
        uv = points.new_zeros((N, 2))
        nrm = points.new_zeros((N, 3))
        tu = points.new_zeros((N, 3))
        tv = points.new_zeros((N, 3))
        pid_np = primitive_id.cpu().numpy()
        types = self._type_of[pid_np]
        local_idx = torch.as_tensor(self._index_in_type[pid_np], device=points.device)
        frame_of_type = ((_rect_surface_frame, "rect"), (_box_surface_frame, "box_all"),
                         (_sphere_surface_frame, "sphere"), (_cylinder_surface_frame, "cylinder"))
        for t, (frame_fn, pack_name) in enumerate(frame_of_type):  # t indexes _TYPE_NAMES
            sel_np = np.nonzero(types == t)[0]
            if len(sel_np) == 0:
                continue
            sel = torch.as_tensor(sel_np, device=points.device)
            uv[sel], nrm[sel], tu[sel], tv[sel] = frame_fn(pk[pack_name], local_idx[sel], points[sel])
        # decorrelate primitives sharing a material: shift texture coordinates per primitive
        shift = (primitive_id % 37).to(points.dtype)
        uv = uv + torch.stack([2.9 * shift, 1.7 * shift], 1)
        return uv, nrm, tu, tv

    def albedo_at(self, uv: Tensor, primitive_id: Tensor, footprint_m: Tensor | None = None) -> Tensor:
        """Albedo [N, 3] at texture coordinates uv [N, 2] of primitives primitive_id [N] (>= 0),
        box-filtered over footprint_m [N] (metres on the surface) when given."""
        out = uv.new_zeros((uv.shape[0], 3))
        mats = self._material_index[primitive_id.cpu().numpy()]
        for m in np.unique(mats):
            sel = torch.as_tensor(np.nonzero(mats == m)[0], device=uv.device)
            fp = None if footprint_m is None else footprint_m[sel]
            out[sel] = evaluate_texture(self.materials[self._material_names[m]].albedo, uv[sel], fp)
        if self.grain > 0:
            out = (out * grain_factor(uv, primitive_id, self.grain, self.seed, footprint_m)[:, None]).clamp(0.0, 1.0)
        return out

    def emission_at(self, uv: Tensor, primitive_id: Tensor, footprint_m: Tensor | None = None) -> Tensor:
        """Emitted luminance [N, 3] cd/m^2 at uv [N, 2] of primitives primitive_id [N] (>= 0)."""
        out = uv.new_zeros((uv.shape[0], 3))
        mats = self._material_index[primitive_id.cpu().numpy()]
        for m in np.unique(mats):
            mat = self.materials[self._material_names[m]]
            if mat.emission_cd_m2 <= 0:
                continue
            sel = torch.as_tensor(np.nonzero(mats == m)[0], device=uv.device)
            rgb = torch.as_tensor(_rgb_unit_luminance(mat.emission_rgb), dtype=uv.dtype, device=uv.device)
            e = mat.emission_cd_m2 * rgb.expand(len(sel), 3)
            if mat.emission_texture is not None:
                e = e * evaluate_texture(mat.emission_texture, uv[sel], None if footprint_m is None else footprint_m[sel])
            out[sel] = e
        return out

    # ------------------------------------------------------------------ lighting
    def irradiance(self, points: Tensor, normals: Tensor) -> Tensor:
        """Illuminance per channel (lux) [N, 3] at surface points [N, 3] with normals [N, 3].

        ``normals`` must face the side that is lit (the side the viewer is on).
        """
        E = points.new_zeros((points.shape[0], 3))
        dt, dev = points.dtype, points.device
        for light in self.lights:
            if isinstance(light, AmbientLight):
                E = E + light.illuminance_lux * torch.as_tensor(_rgb_unit_luminance(light.rgb), dtype=dt, device=dev)
            elif isinstance(light, SkyDome):
                nz = normals[:, 2:3]
                sky = torch.as_tensor(0.5 * (_rgb_unit_luminance(light.zenith_rgb) + _rgb_unit_luminance(light.horizon_rgb)),
                                      dtype=dt, device=dev)
                E_ground = light.horizontal_illuminance_lux + sum(
                    l.illuminance_lux * max(0.0, _unit(l.direction_to_sun, "Sun.direction_to_sun")[2])
                    for l in self.lights if isinstance(l, Sun))
                E = E + light.horizontal_illuminance_lux * 0.5 * (1 + nz) * sky
                E = E + light.ground_albedo * E_ground * 0.5 * (1 - nz) * torch.ones(3, dtype=dt, device=dev)
            elif isinstance(light, Sun):
                ldir = torch.as_tensor(_unit(light.direction_to_sun, "Sun.direction_to_sun"), dtype=dt, device=dev)
                cos = torch.clamp(pm.vecdot(normals, ldir), min=0.0)
                lit = cos > 0
                vis = torch.zeros_like(cos)
                if bool(lit.any()):
                    idx = torch.nonzero(lit)[:, 0]
                    o = points[idx] + normals[idx] * self._eps(dt)
                    t, _ = self.intersect(o, ldir.expand(len(idx), 3).contiguous())
                    vis[idx] = torch.isinf(t).to(dt)
                E = E + (light.illuminance_lux * cos * vis)[:, None] * torch.as_tensor(
                    _rgb_unit_luminance(light.rgb), dtype=dt, device=dev)
            elif isinstance(light, PointLight):
                lp = torch.as_tensor(np.asarray(light.position, dtype=np.float64), dtype=dt, device=dev)
                to_l = lp - points
                r2 = (to_l * to_l).sum(1).clamp_min(1e-6)
                r = torch.sqrt(r2)
                ldir = to_l / r[:, None]
                cos = torch.clamp((normals * ldir).sum(1), min=0.0)
                vis = torch.ones_like(cos)
                if light.cast_shadows:
                    idx = torch.nonzero(cos > 0)[:, 0]
                    o = points[idx] + normals[idx] * self._eps(dt)
                    t, _ = self.intersect(o, ldir[idx].contiguous(), t_max=r[idx] - 2 * self._eps(dt))
                    vis[idx] = torch.isinf(t).to(dt)
                E = E + (light.intensity_cd * cos * vis / r2)[:, None] * torch.as_tensor(
                    _rgb_unit_luminance(light.rgb), dtype=dt, device=dev)
        return E

    def sky_radiance(self, directions: Tensor) -> Tensor:
        """Luminance per channel (cd/m^2) [N, 3] seen by rays that hit nothing; 0 without a sky."""
        out = directions.new_zeros((directions.shape[0], 3))
        for light in self.lights:
            if isinstance(light, SkyDome):
                dt, dev = directions.dtype, directions.device
                z = directions[:, 2:3]
                zen = torch.as_tensor(_rgb_unit_luminance(light.zenith_rgb), dtype=dt, device=dev)
                hor = torch.as_tensor(_rgb_unit_luminance(light.horizon_rgb), dtype=dt, device=dev)
                w = torch.sqrt(torch.clamp(z, 0.0, 1.0))
                sky = (hor + (zen - hor) * w) * (light.horizontal_illuminance_lux / math.pi)
                E_ground = light.horizontal_illuminance_lux + sum(
                    l.illuminance_lux * max(0.0, _unit(l.direction_to_sun, "Sun.direction_to_sun")[2])
                    for l in self.lights if isinstance(l, Sun))
                ground = torch.full_like(sky, light.ground_albedo * E_ground / math.pi)
                out = out + torch.where(z >= 0, sky, ground)
        return out

    def _eps(self, dtype: torch.dtype) -> float:
        return 1e-3 if dtype == torch.float32 else SURFACE_EPS_M

    # ------------------------------------------------------------------ the public cast
    def cast(self, origins: Tensor, directions: Tensor, pixel_angle_rad: float | Tensor | None = None) -> RayHit:
        """Cast rays: origins [N, 3], directions [N, 3] (normalised here) -> RayHit (N rays).

        ``pixel_angle_rad`` (scalar or [N]): the angle one pixel subtends (about 1 / focal_px);
        textures are then box-filtered over the pixel's footprint on the surface,
        ``pixel_angle * depth / max(|cos incidence|, 0.1)``, so distant detail averages
        instead of aliasing. None: no footprint filtering (only each texture's edge_m).
        """
        if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
            raise ValueError(f"Scene.cast: origins and directions must both have shape [N, 3], got "
                             f"{tuple(origins.shape)} and {tuple(directions.shape)}")
        if not (torch.is_floating_point(origins) and origins.dtype == directions.dtype):
            raise ValueError(f"Scene.cast: origins and directions must share a floating dtype, got "
                             f"{origins.dtype} and {directions.dtype}")
        norm = torch.linalg.norm(directions, dim=1)
        if not bool(torch.isfinite(origins).all()) or not bool((torch.isfinite(norm) & (norm > 1e-12)).all()):
            raise ValueError("Scene.cast: origins must be finite and directions finite and non-zero")
        d = directions / norm[:, None]
        t, pid = self.intersect(origins, d)
        hit = pid >= 0
        N = origins.shape[0]
        normal = origins.new_zeros((N, 3))
        albedo = origins.new_zeros((N, 3))
        E = origins.new_zeros((N, 3))
        radiance = self.sky_radiance(d) * (~hit)[:, None].to(d.dtype)
        idx = torch.nonzero(hit)[:, 0]
        if len(idx):
            p = origins[idx] + t[idx, None] * d[idx]
            uv, n_out, _, _ = self.surface_frame(p, pid[idx])
            facing = torch.where(((n_out * d[idx]).sum(1) > 0)[:, None], -n_out, n_out)
            footprint = None
            if pixel_angle_rad is not None:
                pa = torch.as_tensor(pixel_angle_rad, dtype=d.dtype, device=d.device).expand(N)[idx]
                if not bool((torch.isfinite(pa) & (pa >= 0)).all()):
                    raise ValueError("Scene.cast: pixel_angle_rad must be finite and >= 0 (radians)")
                cos_inc = torch.abs((facing * d[idx]).sum(1)).clamp_min(0.1)
                footprint = pa * t[idx] / cos_inc
            a = self.albedo_at(uv, pid[idx], footprint)
            e_lux = self.irradiance(p, facing)
            normal[idx] = facing
            albedo[idx] = a
            E[idx] = e_lux
            radiance[idx] = a * e_lux / math.pi + self.emission_at(uv, pid[idx], footprint)
        return RayHit(radiance=radiance, depth_t=t, normal_world=normal, hit=hit, primitive_id=pid,
                      albedo=albedo, illuminance_lux=luminance(E))

    # ------------------------------------------------------------------ semi-dense points
    def primitive_areas(self) -> np.ndarray:
        """Surface area of each primitive, m^2 [P]."""
        out = []
        for p in self.primitives:
            if isinstance(p, Rect):
                out.append(4 * p.half_u_m * p.half_v_m)
            elif isinstance(p, Box):
                a, b, c = p.half_size_m
                out.append(8 * (a * b + b * c + a * c))
            elif isinstance(p, Sphere):
                out.append(4 * math.pi * p.radius_m ** 2)
            else:
                out.append(2 * math.pi * p.radius_m * 2 * p.half_height_m + 2 * math.pi * p.radius_m ** 2)
        return np.asarray(out, dtype=np.float64)

    def _sample_on_primitives(self, rng: np.random.Generator, pids: np.ndarray) -> np.ndarray:
        """Uniform points on the surfaces of primitives pids [M] -> [M, 3] (float64)."""
        out = np.zeros((len(pids), 3))
        for i_type in range(4):
            sel = np.nonzero(self._type_of[pids] == i_type)[0]
            if len(sel) == 0:
                continue
            prims = [self.primitives[k] for k in pids[sel]]
            m = len(sel)
            if i_type == 0:
                C = np.array([p.center for p in prims]); U = np.array([_unit(p.axis_u, "Rect.axis_u") for p in prims])
                V0 = np.array([p.axis_v for p in prims], dtype=np.float64)
                V = V0 - (V0 * U).sum(1, keepdims=True) * U
                V /= np.linalg.norm(V, axis=1, keepdims=True)
                a = rng.uniform(-1, 1, (m, 2)) * np.array([[p.half_u_m, p.half_v_m] for p in prims])
                out[sel] = C + a[:, :1] * U + a[:, 1:] * V
            elif i_type == 2:
                v = rng.normal(size=(m, 3))
                v /= np.linalg.norm(v, axis=1, keepdims=True)
                out[sel] = np.array([p.center for p in prims]) + v * np.array([p.radius_m for p in prims])[:, None]
            elif i_type == 1:
                H = np.array([p.half_size_m for p in prims], dtype=np.float64)
                R = np.array([p.rotation for p in prims], dtype=np.float64)
                face_area = np.stack([H[:, 1] * H[:, 2], H[:, 0] * H[:, 2], H[:, 0] * H[:, 1]], 1)
                cum = np.cumsum(face_area, 1) / face_area.sum(1, keepdims=True)
                k = (rng.uniform(size=(m, 1)) > cum).sum(1)
                loc = rng.uniform(-1, 1, (m, 3)) * H
                sign = np.where(rng.uniform(size=m) < 0.5, -1.0, 1.0)
                loc[np.arange(m), k] = sign * H[np.arange(m), k]
                out[sel] = np.array([p.center for p in prims]) + np.einsum("mij,mj->mi", R, loc)
            else:
                r = np.array([p.radius_m for p in prims]); h = np.array([p.half_height_m for p in prims])
                R = np.stack([_frame_from_axis(_unit(p.axis, "Cylinder.axis")) for p in prims])
                side = rng.uniform(size=m) < (2 * r * h * 2) / (2 * r * h * 2 + 2 * r ** 2)
                ang = rng.uniform(0, 2 * np.pi, m)
                rad = np.where(side, r, r * np.sqrt(rng.uniform(size=m)))
                z = np.where(side, rng.uniform(-1, 1, m) * h, np.where(rng.uniform(size=m) < 0.5, -h, h))
                loc = np.stack([rad * np.cos(ang), rad * np.sin(ang), z], 1)
                out[sel] = np.array([p.center for p in prims]) + np.einsum("mij,mj->mi", R, loc)
        return out

    def sample_surface_points(self, n: int, rng: np.random.Generator | int,
                              visible_from: np.ndarray | Tensor | None = None,
                              gradient_floor: float = 0.05, oversample: int = 8) -> tuple[Tensor, Tensor]:
        """Surface points like a semi-dense tracker finds them: on textured/edge regions.

        Candidates are drawn uniformly by area, then ``n`` are kept with probability
        proportional to ``|grad albedo luminance| (per metre) + gradient_floor * median``,
        without replacement. With ``visible_from`` (positions [P, 3]) a candidate is kept only
        if the straight line from a random one of those positions reaches it unoccluded.
        Returns (points_world [n, 3] float64, normals_world [n, 3] float64, outward or,
        for rectangles, facing the viewpoint).
        """
        if int(n) != n or n <= 0:
            raise ValueError(f"sample_surface_points: n must be a positive integer, got {n}")
        rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
        views = None
        if visible_from is not None:
            views = np.asarray(visible_from.cpu().numpy() if isinstance(visible_from, Tensor) else visible_from,
                               dtype=np.float64).reshape(-1, 3)
            if len(views) == 0 or not np.isfinite(views).all():
                raise ValueError("sample_surface_points: visible_from must be finite positions [P, 3] with P >= 1")
        areas = self.primitive_areas()
        prob = areas / areas.sum()
        pts_all, nrm_all, w_all = [], [], []
        have = 0
        for _round in range(8):
            m = max(1024, oversample * n)
            pids = rng.choice(len(self.primitives), size=m, p=prob)
            pts = self._sample_on_primitives(rng, pids)
            pid_t = torch.as_tensor(pids)
            P = torch.as_tensor(pts)
            uv, nrm, _, _ = self.surface_frame(P, pid_t)
            keep = np.ones(m, dtype=bool)
            if views is not None:
                vsel = views[rng.integers(0, len(views), size=m)]
                to_p = pts - vsel
                dist = np.linalg.norm(to_p, axis=1)
                ok = dist > 1e-3
                d = to_p / np.maximum(dist, 1e-9)[:, None]
                t, _ = self.intersect(torch.as_tensor(vsel), torch.as_tensor(d))
                keep = ok & (t.numpy() >= dist - 2e-3)
                facing = (nrm.numpy() * d).sum(1) > 0  # outward normal points away from the viewer
                is_rect = self._type_of[pids] == 0
                nrm_np = nrm.numpy()
                nrm_np[is_rect & facing] *= -1.0  # rectangles: flip to the viewer's side
                keep &= ~facing | is_rect
                nrm = torch.as_tensor(nrm_np)
            if not keep.any():
                continue
            k = np.nonzero(keep)[0]
            h = 2e-3  # finite-difference step in texture space, metres
            uvk, pk_ = uv[k], pid_t[k]
            y0 = luminance(self.albedo_at(uvk, pk_))
            gu = (luminance(self.albedo_at(uvk + torch.tensor([h, 0.0], dtype=uvk.dtype), pk_)) - y0) / h
            gv = (luminance(self.albedo_at(uvk + torch.tensor([0.0, h], dtype=uvk.dtype), pk_)) - y0) / h
            pts_all.append(pts[k]); nrm_all.append(nrm.numpy()[k]); w_all.append(torch.sqrt(gu ** 2 + gv ** 2).numpy())
            have += len(k)
            if have >= 2 * n:
                break
        if have < n:
            raise ValueError(f"sample_surface_points: only {have} visible surface points found for n={n}; "
                             f"check visible_from (positions inside the scene?)")
        pts = np.concatenate(pts_all); nrm = np.concatenate(nrm_all); g = np.concatenate(w_all)
        w = g + gradient_floor * max(float(np.median(g)), 1e-3)
        # weighted sampling without replacement (Efraimidis-Spirakis keys)
        keys = pm.log(rng.uniform(size=len(w)).clip(1e-300)) / w
        chosen = np.argsort(-keys)[:n]
        return torch.as_tensor(pts[chosen]), torch.as_tensor(nrm[chosen])


# --------------------------------------------------------------------------- intersection kernels
def _hit_rects(q: dict, o: Tensor, d: Tensor, best_t: Tensor, best_id: Tensor) -> tuple[Tensor, Tensor]:
    """Closest rectangle per ray: (t [n], index in the rect list [n])."""
    dn = pm.matmul(d, q["N"].T)  # [n, P]
    on = pm.matmul(o, q["N"].T)
    eps = 1e-12
    safe = torch.where(torch.abs(dn) > eps, dn, torch.full_like(dn, eps))
    t = (q["cN"] - on) / safe
    pu = pm.matmul(o, q["U"].T) - q["cU"] + t * pm.matmul(d, q["U"].T)
    pv = pm.matmul(o, q["V"].T) - q["cV"] + t * pm.matmul(d, q["V"].T)
    ok = (torch.abs(dn) > eps) & (t > 0) & (torch.abs(pu) <= q["H"][:, 0]) & (torch.abs(pv) <= q["H"][:, 1])
    t = torch.where(ok, t, torch.full_like(t, math.inf))
    tmin, j = t.min(dim=1)
    better = tmin < best_t
    return torch.where(better, tmin, best_t), torch.where(better, q["ids"][j], best_id)


def _sphere_mask(C: Tensor, c2r2: Tensor, r: Tensor, o: Tensor, d: Tensor, best_t: Tensor) -> Tensor:
    """[n, P] may ray i enter bounding sphere j (centres C [P, 3]) before best_t[i]?

    Conservative and sqrt-free: the line meets the sphere, the sphere is not behind the
    origin (centre ahead, or origin inside), and the entry distance, which is at least
    d.(c - o) - r, is below the best hit so far.
    """
    b = (d * o).sum(1, keepdim=True) - pm.matmul(d, C.T)  # d.(o - c)
    c = (o * o).sum(1, keepdim=True) - 2 * pm.matmul(o, C.T) + c2r2  # |o - c|^2 - r^2
    return (b * b >= c) & ((b < 0) | (c < 0)) & (-b - r < best_t[:, None])


def _bounding_sphere_candidates(q: dict, o: Tensor, d: Tensor, best_t: Tensor) -> tuple[Tensor, Tensor]:
    """(ray, primitive) pairs that survive bounding-sphere culling (two levels: groups, then members)."""
    if "G_C" not in q:
        pairs = torch.nonzero(_sphere_mask(q["C"], q["c2r2_bound"], q["r_bound"], o, d, best_t))
        return pairs[:, 0], pairs[:, 1]
    gp = torch.nonzero(_sphere_mask(q["G_C"], q["G_c2r2"], q["G_r"], o, d, best_t))
    mem = torch.index_select(q["G_members"], 0, gp[:, 1])  # [K1, M] primitive indices, -1 padded
    valid = mem >= 0
    ray = gp[:, 0:1].expand_as(mem)[valid]
    prim = mem[valid]
    oc = torch.index_select(o, 0, ray) - torch.index_select(q["C"], 0, prim)
    dr = torch.index_select(d, 0, ray)
    b = _dot3(dr, oc)
    rb = torch.index_select(q["r_bound"], 0, prim)
    c = _dot3(oc, oc) - rb * rb
    keep = (b * b >= c) & ((b < 0) | (c < 0)) & (-b - rb < torch.index_select(best_t, 0, ray))
    return ray[keep], prim[keep]


def _dot3(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot product of [K, 3] tensors (faster than (a * b).sum(1) for tiny rows)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _group_primitives(C: np.ndarray, r: np.ndarray, per_group: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deterministic k-means of bounding spheres (centres C [P, 3], radii r [P]) into groups.

    Returns (group centres [G, 3], group radii [G], members [G, M] padded with -1).
    """
    P = len(C)
    G = max(1, int(math.ceil(P / per_group)))
    centres = [C[0]]
    for _ in range(1, G):  # farthest-point initialisation
        dist = np.min(np.linalg.norm(C[:, None] - np.asarray(centres)[None], axis=2), axis=1)
        centres.append(C[int(np.argmax(dist))])
    cen = np.asarray(centres)
    for _ in range(20):
        lab = np.argmin(np.linalg.norm(C[:, None] - cen[None], axis=2), axis=1)
        cen = np.stack([C[lab == g].mean(0) if np.any(lab == g) else cen[g] for g in range(G)])
    lab = np.argmin(np.linalg.norm(C[:, None] - cen[None], axis=2), axis=1)
    groups = [np.nonzero(lab == g)[0] for g in range(G) if np.any(lab == g)]
    M = max(len(m) for m in groups)
    members = np.full((len(groups), M), -1, dtype=np.int64)
    gc = np.zeros((len(groups), 3))
    gr = np.zeros(len(groups))
    for g, m in enumerate(groups):
        members[g, : len(m)] = m
        gc[g] = C[m].mean(0)
        gr[g] = np.max(np.linalg.norm(C[m] - gc[g], axis=1) + r[m]) * (1 + 1e-6) + 1e-9
    return gc, gr, members


def _reduce_pairs(best_t: Tensor, best_id: Tensor, ray: Tensor, t: Tensor, ids: Tensor) -> tuple[Tensor, Tensor]:
    """Fold per-pair hits (ray [K], t [K], global primitive ids [K]) into the per-ray best."""
    if ray.numel() == 0:
        return best_t, best_id
    new_t = best_t.scatter_reduce(0, ray, t, reduce="amin")
    new_at_ray = torch.index_select(new_t, 0, ray)
    won = (t == new_at_ray) & (t < torch.index_select(best_t, 0, ray))
    # deterministic tie-break: the largest primitive id among equal distances
    cand = torch.where(won, ids, torch.full_like(ids, -1))
    new_id = torch.full_like(best_id, -1).scatter_reduce(0, ray, cand, reduce="amax")
    improved = new_t < best_t
    return new_t, torch.where(improved, new_id, best_id)


def _local_pairs(q: dict, o: Tensor, d: Tensor, ray: Tensor, prim: Tensor) -> tuple[Tensor, Tensor]:
    """Ray origin and direction in the frames of the paired primitives: R^T (o - c), R^T d, [K, 3]."""
    R = torch.index_select(q["R"], 0, prim)  # [K, 3, 3] columns = local axes in world
    oc = torch.index_select(o, 0, ray) - torch.index_select(q["C"], 0, prim)
    dr = torch.index_select(d, 0, ray)
    ol = torch.stack([_dot3(R[:, :, k], oc) for k in range(3)], 1)
    dl = torch.stack([_dot3(R[:, :, k], dr) for k in range(3)], 1)
    return ol, dl


def _hit_boxes(q: dict, o: Tensor, d: Tensor, best_t: Tensor, best_id: Tensor) -> tuple[Tensor, Tensor]:
    """Boxes after bounding-sphere culling: slab tests on the surviving (ray, box) pairs."""
    ray, prim = _bounding_sphere_candidates(q, o, d, best_t)
    ol, dl = _local_pairs(q, o, d, ray, prim)
    t = _slab(ol, dl, torch.index_select(q["H"], 0, prim))
    return _reduce_pairs(best_t, best_id, ray, t, torch.index_select(q["ids"], 0, prim))


def _slab(ol: Tensor, dl: Tensor, H: Tensor) -> Tensor:
    """Slab test in box frames: ol, dl [..., 3] local origin/direction, H [..., 3] half sizes -> t [...]."""
    tiny = 1e-30 if ol.dtype == torch.float64 else 1e-20
    dl = torch.where(torch.abs(dl) < tiny, torch.where(dl < 0, -tiny, tiny), dl)
    inv = 1.0 / dl
    t1 = (-H - ol) * inv
    t2 = (H - ol) * inv
    tn = torch.minimum(t1, t2).amax(dim=-1)
    tf = torch.maximum(t1, t2).amin(dim=-1)
    t = torch.where(tn > 0, tn, tf)  # a ray starting inside a box hits its far wall
    return torch.where((tf >= tn) & (t > 0), t, torch.full_like(t, math.inf))


def _hit_boxes_dense(q: dict, o: Tensor, d: Tensor, best_t: Tensor, best_id: Tensor) -> tuple[Tensor, Tensor]:
    """Every ray against every (big) box: [n, P] slab tests."""
    n, P = o.shape[0], q["C"].shape[0]
    ol = pm.matmul(o, q["Rflat"]).view(n, P, 3) - q["cR"]
    dl = pm.matmul(d, q["Rflat"]).view(n, P, 3)
    tmin, j = _slab(ol, dl, q["H"]).min(dim=1)
    better = tmin < best_t
    return torch.where(better, tmin, best_t), torch.where(better, q["ids"][j], best_id)


def _hit_spheres(q: dict, o: Tensor, d: Tensor, best_t: Tensor, best_id: Tensor) -> tuple[Tensor, Tensor]:
    b = (d * o).sum(1, keepdim=True) - pm.matmul(d, q["C"].T)  # d.(o - c)  [n, P]
    c = (o * o).sum(1, keepdim=True) - 2 * pm.matmul(o, q["C"].T) + q["c2r2"]  # |o - c|^2 - r^2
    disc = b * b - c
    ok = disc >= 0
    sq = torch.sqrt(torch.clamp(disc, min=0.0))
    t0, t1 = -b - sq, -b + sq
    t = torch.where(t0 > 0, t0, t1)
    t = torch.where(ok & (t > 0), t, torch.full_like(t, math.inf))
    tmin, j = t.min(dim=1)
    better = tmin < best_t
    return torch.where(better, tmin, best_t), torch.where(better, q["ids"][j], best_id)


def _hit_cylinders(q: dict, o: Tensor, d: Tensor, best_t: Tensor, best_id: Tensor) -> tuple[Tensor, Tensor]:
    ray, prim = _bounding_sphere_candidates(q, o, d, best_t)
    ol, dl = _local_pairs(q, o, d, ray, prim)
    r, h = torch.index_select(q["r"], 0, prim), torch.index_select(q["h"], 0, prim)
    inf = torch.full_like(ol[:, 0], math.inf)
    a = dl[:, 0] ** 2 + dl[:, 1] ** 2
    b = ol[:, 0] * dl[:, 0] + ol[:, 1] * dl[:, 1]
    c = ol[:, 0] ** 2 + ol[:, 1] ** 2 - r * r
    disc = b * b - a * c
    good = (disc >= 0) & (a > 1e-18)
    sq = torch.sqrt(torch.clamp(disc, min=0.0))
    a_safe = torch.where(a > 1e-18, a, torch.ones_like(a))
    best = inf
    for ts in ((-b - sq) / a_safe, (-b + sq) / a_safe):
        z = ol[:, 2] + ts * dl[:, 2]
        ok = good & (ts > 0) & (torch.abs(z) <= h)
        best = torch.minimum(best, torch.where(ok, ts, inf))
    dz = dl[:, 2]
    dz_safe = torch.where(torch.abs(dz) > 1e-18, dz, torch.full_like(dz, 1e-18))
    for sgn in (-1.0, 1.0):
        tc = (sgn * h - ol[:, 2]) / dz_safe
        x = ol[:, 0] + tc * dl[:, 0]
        y = ol[:, 1] + tc * dl[:, 1]
        ok = (torch.abs(dz) > 1e-18) & (tc > 0) & (x * x + y * y <= r * r)
        best = torch.minimum(best, torch.where(ok, tc, inf))
    return _reduce_pairs(best_t, best_id, ray, best, torch.index_select(q["ids"], 0, prim))


# =========================================================================== scene kinds
def _jit(rng: np.random.Generator, scale: float) -> float:
    return float(rng.uniform(-scale, scale))


def _palette(rng: np.random.Generator, n: int, lo: float = 0.08, hi: float = 0.75) -> tuple[RGB, ...]:
    return tuple(tuple(float(x) for x in rng.uniform(lo, hi, 3)) for _ in range(n))


def _build_outdoor(rng: np.random.Generator, seed: int) -> Scene:
    """A sunlit street corner / patio: brick and plaster facades, shop signs, poles, tables, awning."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731 - texture seeds
    M = {
        "pavement": Material(Texture("tiles", ((0.32, 0.30, 0.28), (0.12, 0.12, 0.12), (0.45, 0.42, 0.38)), 0.4, s(0))),
        "asphalt": Material(Texture("noise", ((0.10, 0.10, 0.10), (0.22, 0.21, 0.20)), 0.08, s(1))),
        "bricks": Material(Texture("bricks", ((0.45, 0.20, 0.12), (0.55, 0.52, 0.48), (0.30, 0.13, 0.09)), 0.24, s(2))),
        "plaster": Material(Texture("noise", ((0.62, 0.58, 0.50), (0.48, 0.44, 0.38)), 0.3, s(3))),
        "shopfront": Material(Texture("grid", ((0.05, 0.06, 0.07), (0.50, 0.50, 0.50)), 0.6, s(4))),
        "sign1": Material(Texture("text", ((0.80, 0.78, 0.70), (0.05, 0.05, 0.08)), 0.12, s(5))),
        "sign2": Material(Texture("text", ((0.08, 0.20, 0.45), (0.85, 0.85, 0.85)), 0.09, s(6))),
        "menu": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.8, 0.75, 0.6), (0.7, 0.3, 0.2), (0.85, 0.8, 0.7)), 0.035, s(7))),
        "metal": Material(Texture("noise", ((0.18, 0.18, 0.19), (0.35, 0.35, 0.36)), 0.05, s(8))),
        "wood": Material(Texture("planks", ((0.42, 0.26, 0.14), (0.10, 0.06, 0.04), (0.55, 0.36, 0.20)), 0.09, s(9))),
        "awning": Material(Texture("checker", ((0.65, 0.08, 0.06), (0.80, 0.78, 0.72)), 0.5, s(10), edge_m=0.004)),
        "planter": Material(Texture("noise", ((0.08, 0.22, 0.05), (0.25, 0.40, 0.10)), 0.04, s(11))),
        "stone": Material(Texture("noise", ((0.50, 0.50, 0.48), (0.30, 0.30, 0.29)), 0.06, s(12))),
    }
    P: list[Primitive] = []
    P.append(axis_rect((0, 0, 0), "+z", (60.0, 60.0), "pavement"))
    P.append(axis_rect((0, -9.0, 0.002), "+z", (60.0, 6.0), "asphalt"))
    # north facade (bricks) with a shop front and signs; west facade (plaster); a south-west building
    P.append(yaw_box((0, 7.5, 5.0), (24.0, 1.0, 10.0), "bricks"))
    P.append(axis_rect((_jit(rng, 1.0) - 2.0, 6.99, 1.5), "-y", (5.0, 2.6), "shopfront"))
    P.append(axis_rect((-2.0, 6.96, 3.4), "-y", (4.0, 0.7), "sign1"))
    P.append(axis_rect((4.5 + _jit(rng, 0.5), 6.98, 2.6), "-y", (2.2, 1.4), "menu"))
    P.append(yaw_box((-9.5, 0.0, 4.0), (1.0, 16.0, 8.0), "plaster"))
    P.append(axis_rect((-8.99, -1.0 + _jit(rng, 0.5), 2.8), "+x", (3.0, 0.6), "sign2"))
    P.append(axis_rect((-8.99, 2.5, 1.4), "+x", (1.2, 1.6), "menu"))
    P.append(yaw_box((-3.0, -12.5, 6.0), (14.0, 1.0, 12.0), "bricks"))
    # awning over the shop front (casts a shadow band)
    P.append(Rect((-2.0, 5.9, 3.0), (1.0, 0.0, 0.0), (0.0, 0.8, 0.6), 3.0, 1.1, "awning"))
    # poles with signs
    for k, (x, y) in enumerate([(3.5, -3.2), (-5.5, 3.8), (6.5, 3.0)]):
        x, y = x + _jit(rng, 0.3), y + _jit(rng, 0.3)
        P.append(Cylinder((x, y, 1.5), (0, 0, 1), 0.045, 1.5, "metal"))
        P.append(Rect((x, y, 2.55 + 0.1 * k), (1.0, 0.3 * (k - 1), 0.0), (0, 0, 1), 0.45, 0.3, "sign1" if k % 2 else "sign2"))
    # bistro tables with chairs, and planters
    for (x, y) in [(2.0, 4.0), (-1.5, 4.3), (5.0, 5.2), (-6.0, -4.0)]:
        x, y = x + _jit(rng, 0.3), y + _jit(rng, 0.3)
        P.append(Cylinder((x, y, 0.74), (0, 0, 1), 0.4, 0.02, "wood"))
        P.append(Cylinder((x, y, 0.37), (0, 0, 1), 0.04, 0.36, "metal"))
        P.append(yaw_box((x + 0.65, y, 0.45), (0.42, 0.42, 0.06), "wood", yaw_deg=_jit(rng, 30)))
        P.append(yaw_box((x - 0.65, y, 0.45), (0.42, 0.42, 0.06), "wood", yaw_deg=_jit(rng, 30)))
    for (x, y) in [(-7.5, -2.5), (-7.5, 1.0), (7.0, -2.0)]:
        P.append(yaw_box((x, y, 0.35), (0.9, 0.9, 0.7), "stone"))
        P.append(Sphere((x, y, 0.9), 0.45, "planter"))
    for x in (-3.0, -1.0, 1.0, 3.0):
        P.append(Sphere((x, -5.5, 0.35), 0.25, "stone"))
    # sun from the south-west, 50 deg elevation: facades and the awning cast long shadows
    az, el = math.radians(225.0 + _jit(rng, 10.0)), math.radians(50.0)
    lights: list[Light] = [
        Sun((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)), 60000.0),
        SkyDome(4000.0, ground_albedo=0.25),
    ]
    targets = np.array([[-2.0, 6.9, 3.4], [4.5, 6.9, 2.6], [-8.9, -1.0, 2.8], [2.0, 4.0, 0.8], [-6.0, -4.0, 0.8],
                        [3.5, -3.2, 2.5], [-7.5, -2.5, 0.9]])
    return Scene("outdoor", P, M, lights, WalkRegion("box", (0.0, 0.0), (4.0, 2.0)), targets,
                 ((-30.0, -30.0, 0.0), (30.0, 30.0, 12.0)), seed)


def _room_shell(P: list[Primitive], size: tuple[float, float, float], floor: str, wall: str, ceiling: str) -> None:
    """Floor, ceiling and four walls of a closed room centred on (0, 0), facing inwards."""
    sx, sy, sz = size
    P.append(axis_rect((0, 0, 0), "+z", (sx, sy), floor))
    P.append(axis_rect((0, 0, sz), "-z", (sx, sy), ceiling))
    P.append(axis_rect((-sx / 2, 0, sz / 2), "+x", (sy, sz), wall))
    P.append(axis_rect((sx / 2, 0, sz / 2), "-x", (sy, sz), wall))
    P.append(axis_rect((0, -sy / 2, sz / 2), "+y", (sx, sz), wall))
    P.append(axis_rect((0, sy / 2, sz / 2), "-y", (sx, sz), wall))


def _bookshelf(P: list[Primitive], x: float, y: float, yaw_deg: float, width: float, material_frame: str,
               material_books: str, height: float = 2.0, depth: float = 0.32) -> None:
    """A shelf unit: a frame box with a row of books (textured box front) per shelf."""
    R = rot_z(yaw_deg)
    fwd = R[:, 1]  # the shelf faces +y of its frame
    P.append(Box((x, y, height / 2), (width / 2, 0.02, height / 2), material_frame, tuple(map(tuple, R))))  # back
    for k in range(5):
        z = 0.05 + k * 0.4
        c = np.array([x, y, z]) + fwd * depth / 2
        P.append(Box(tuple(c), (width / 2, depth / 2, 0.015), material_frame, tuple(map(tuple, R))))
        if k < 4:
            bc = np.array([x, y, z + 0.16]) + fwd * (depth / 2 - 0.02)
            P.append(Box(tuple(bc), (width / 2 - 0.02, depth / 2 - 0.04, 0.145), material_books, tuple(map(tuple, R))))


def _build_indoor(rng: np.random.Generator, seed: int) -> Scene:
    """A library-like room: shelves of books, posters, a table, a bright window, ~150-300 lux."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    covers = _palette(rng, 6, 0.08, 0.7)
    M = {
        "floor": Material(Texture("planks", ((0.40, 0.27, 0.16), (0.12, 0.08, 0.05), (0.52, 0.36, 0.22)), 0.14, s(0))),
        "wall": Material(Texture("noise", ((0.70, 0.68, 0.62), (0.60, 0.58, 0.52)), 0.2, s(1))),
        "ceiling": Material(Texture("grid", ((0.75, 0.75, 0.73), (0.45, 0.45, 0.45)), 0.6, s(2))),
        "shelf": Material(Texture("planks", ((0.35, 0.22, 0.12), (0.15, 0.09, 0.05), (0.45, 0.30, 0.18)), 0.1, s(3))),
        "books": Material(Texture("books", ((0.05, 0.04, 0.03), (0.85, 0.80, 0.65), *covers), 0.035, s(4))),
        "poster1": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.04, 0.04, 0.04), (0.85, 0.8, 0.7), (0.2, 0.4, 0.7), (0.8, 0.6, 0.2)), 0.03, s(5))),
        "poster2": Material(Texture("text", ((0.85, 0.84, 0.80), (0.05, 0.05, 0.05)), 0.025, s(6))),
        "board": Material(Texture("grid", ((0.80, 0.80, 0.78), (0.15, 0.25, 0.45)), 0.05, s(7))),
        "table": Material(Texture("planks", ((0.50, 0.35, 0.20), (0.20, 0.12, 0.06), (0.60, 0.45, 0.28)), 0.12, s(8))),
        "rug": Material(Texture("checker", ((0.45, 0.12, 0.10), (0.70, 0.62, 0.45)), 0.25, s(9))),
        "metal": Material(Texture("noise", ((0.25, 0.25, 0.26), (0.40, 0.40, 0.41)), 0.05, s(10))),
        "window": Material(Texture("plain", ((0.6, 0.6, 0.6),), 1.0, s(11)), emission_cd_m2=1000.0,
                           emission_rgb=(0.9, 1.0, 1.15),
                           emission_texture=Texture("window", ((0.95, 0.95, 0.95), (0.03, 0.03, 0.03)), 0.45, s(12))),
        "lamp": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(13)), emission_cd_m2=2500.0, emission_rgb=(1.0, 0.95, 0.85)),
    }
    size = (9.0, 7.0, 2.9)
    P: list[Primitive] = []
    _room_shell(P, size, "floor", "wall", "ceiling")
    # shelves along the north and west walls
    for k in range(3):
        _bookshelf(P, -3.0 + 2.2 * k + _jit(rng, 0.1), 3.48, 180.0, 2.0, "shelf", "books")
    _bookshelf(P, -4.48, -1.2 + _jit(rng, 0.2), -90.0, 2.4, "shelf", "books")
    # posters and a notice board on the south wall; a window on the east wall
    P.append(axis_rect((-2.5, -3.49, 1.6), "+y", (0.8, 1.1), "poster1"))
    P.append(axis_rect((-1.2 + _jit(rng, 0.2), -3.49, 1.5), "+y", (0.7, 0.9), "poster2"))
    P.append(axis_rect((1.5, -3.49, 1.5), "+y", (1.8, 1.0), "board"))
    P.append(axis_rect((4.49, 0.3 + _jit(rng, 0.3), 1.55), "-x", (2.0, 1.4), "window"))
    # a reading table, chairs, a rug, ceiling lamps
    P.append(axis_rect((0.3, 0.2, 0.004), "+z", (3.0, 2.0), "rug"))
    P.append(yaw_box((2.6, -1.9, 0.74), (1.6, 0.8, 0.04), "table", yaw_deg=_jit(rng, 10)))
    for dx in (-0.7, 0.7):
        P.append(Cylinder((2.6 + dx, -1.9, 0.36), (0, 0, 1), 0.03, 0.36, "metal"))
        P.append(yaw_box((2.6 + dx, -1.2, 0.45), (0.45, 0.45, 0.05), "shelf", yaw_deg=_jit(rng, 20)))
    lamp_xy = [(-2.0, 0.0), (1.5, 0.0), (1.5, -2.0)]
    for (x, y) in lamp_xy:
        P.append(Cylinder((x, y, 2.86), (0, 0, 1), 0.25, 0.03, "lamp"))
    lights: list[Light] = [AmbientLight(110.0, (1.0, 0.98, 0.95))]
    lights += [PointLight((x, y, 2.8), 600.0, cast_shadows=False) for (x, y) in lamp_xy]
    lights.append(PointLight((3.6, 0.3, 1.8), 500.0, rgb=(0.9, 1.0, 1.15)))  # light from the window
    targets = np.array([[-3.0, 3.3, 1.2], [-0.8, 3.3, 1.0], [1.4, 3.3, 1.4], [-4.3, -1.2, 1.2], [-2.5, -3.4, 1.6],
                        [1.5, -3.4, 1.5], [4.4, 0.3, 1.5], [2.6, -1.9, 0.8]])
    return Scene("indoor", P, M, lights, WalkRegion("box", (0.0, 0.9), (3.2, 1.5)), targets,
                 ((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2])), seed)


def _build_object(rng: np.random.Generator, seed: int) -> Scene:
    """A DTC-like object capture: a mug, a printed box and a ball on a table in an evenly lit lab."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    M = {
        "floor": Material(Texture("tiles", ((0.45, 0.45, 0.44), (0.20, 0.20, 0.20), (0.55, 0.55, 0.53)), 0.6, s(0))),
        "wall": Material(Texture("noise", ((0.62, 0.62, 0.60), (0.52, 0.52, 0.50)), 0.25, s(1))),
        "ceiling": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(2))),
        # A plain grey felt mat, as DTC's captures put objects on a plain backdrop. A 4 cm black-and-white
        # checkerboard here (2-3 px cells at 128 px, half of every view) made the scene near white noise
        # (spectral slope -0.26, one-pixel-shift PSNR 21.4 dB) and capped every model near 20 dB (issue 31).
        "mat": Material(Texture("plain", ((0.55, 0.55, 0.53),), 1.0, s(3))),
        "table": Material(Texture("noise", ((0.30, 0.30, 0.32), (0.40, 0.40, 0.42)), 0.05, s(4))),
        "mug": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.1), (0.80, 0.75, 0.65), (0.15, 0.35, 0.6), (0.7, 0.2, 0.15)), 0.012, s(5), edge_m=0.0007)),
        "package": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.9, 0.9, 0.85), (0.7, 0.15, 0.1), (0.9, 0.7, 0.1), (0.1, 0.3, 0.6)), 0.01, s(6), edge_m=0.0007)),
        "ball": Material(Texture("checker", ((0.85, 0.6, 0.1), (0.1, 0.2, 0.5)), 0.03, s(7), edge_m=0.0007)),
        "poster": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.85, 0.8, 0.7), (0.3, 0.5, 0.3)), 0.04, s(8))),
        "lamp": Material(Texture("plain", ((0.8, 0.8, 0.8),), 1.0, s(9)), emission_cd_m2=3000.0),
    }
    size = (6.0, 6.0, 3.0)
    P: list[Primitive] = []
    _room_shell(P, size, "floor", "wall", "ceiling")
    P.append(axis_rect((0.0, 2.99, 1.5), "-y", (1.5, 1.0), "poster"))
    P.append(axis_rect((-2.99, 0.0, 1.5), "+x", (1.5, 1.0), "poster"))
    table_top = 0.75
    P.append(yaw_box((0, 0, table_top - 0.02), (1.0, 0.8, 0.04), "table"))
    for dx in (-0.45, 0.45):
        for dy in (-0.35, 0.35):
            P.append(Cylinder((dx, dy, (table_top - 0.04) / 2), (0, 0, 1), 0.025, (table_top - 0.04) / 2, "table"))
    P.append(axis_rect((0, 0, table_top + 0.0005), "+z", (0.6, 0.45), "mat"))
    mx, my = 0.08 + _jit(rng, 0.02), 0.02 + _jit(rng, 0.02)
    P.append(Cylinder((mx, my, table_top + 0.05), (0, 0, 1), 0.042, 0.05, "mug"))
    P.append(yaw_box((mx + 0.055, my, table_top + 0.05), (0.018, 0.012, 0.06), "mug"))  # handle
    P.append(yaw_box((-0.12, 0.05, table_top + 0.09), (0.09, 0.05, 0.18), "package", yaw_deg=20 + _jit(rng, 15)))
    P.append(Sphere((0.03, -0.12, table_top + 0.045), 0.045, "ball"))
    lamp_xy = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)]
    for (x, y) in lamp_xy:
        P.append(axis_rect((x, y, 2.99), "-z", (0.6, 0.6), "lamp"))
    lights: list[Light] = [AmbientLight(250.0)]
    lights += [PointLight((x, y, 2.9), 300.0, rgb=(1.0, 1.0, 1.0)) for (x, y) in lamp_xy]
    targets = np.array([[0.0, 0.0, table_top + 0.06]])
    return Scene("object", P, M, lights, WalkRegion("ring", (0.0, 0.0), radius_min_m=1.1, radius_max_m=1.4,
                                                    eye_height_m=1.5), targets,
                 ((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0)), seed)


def _build_quest3(rng: np.random.Generator, seed: int) -> Scene:
    """A living room (Quest 3 captures): sofa, coffee table, TV, rug, bookshelf, window, lamps."""
    s = lambda k: int(rng.integers(0, 2 ** 31 - 1)) + k  # noqa: E731
    covers = _palette(rng, 5, 0.1, 0.7)
    M = {
        "floor": Material(Texture("planks", ((0.55, 0.40, 0.25), (0.15, 0.10, 0.06), (0.62, 0.48, 0.30)), 0.18, s(0))),
        "wall": Material(Texture("noise", ((0.72, 0.70, 0.64), (0.64, 0.62, 0.56)), 0.3, s(1))),
        "ceiling": Material(Texture("plain", ((0.8, 0.8, 0.78),), 1.0, s(2))),
        "fabric": Material(Texture("noise", ((0.20, 0.28, 0.38), (0.30, 0.38, 0.48)), 0.01, s(3))),
        "cushion": Material(Texture("checker", ((0.70, 0.60, 0.30), (0.25, 0.20, 0.15)), 0.08, s(4))),
        "wood": Material(Texture("planks", ((0.45, 0.30, 0.18), (0.15, 0.10, 0.06), (0.55, 0.38, 0.22)), 0.1, s(5))),
        "rug": Material(Texture("grid", ((0.60, 0.55, 0.45), (0.30, 0.10, 0.08)), 0.15, s(6))),
        "tv": Material(Texture("noise", ((0.03, 0.03, 0.03), (0.06, 0.06, 0.06)), 0.05, s(7))),
        "screen": Material(Texture("plain", ((0.02, 0.02, 0.02),), 1.0, s(8)), emission_cd_m2=120.0,
                           emission_texture=Texture("poster", ((0.5, 0.5, 0.5), (0.95, 0.95, 0.95), (0.3, 0.5, 0.8), (0.8, 0.4, 0.2)), 0.05, s(9))),
        "books": Material(Texture("books", ((0.05, 0.04, 0.03), (0.85, 0.80, 0.65), *covers), 0.04, s(10))),
        "art": Material(Texture("poster", ((0.1, 0.1, 0.1), (0.05, 0.05, 0.05), (0.8, 0.7, 0.5), (0.2, 0.5, 0.4)), 0.04, s(11))),
        "magazine": Material(Texture("text", ((0.9, 0.88, 0.85), (0.05, 0.05, 0.05)), 0.012, s(12), edge_m=0.0008)),
        "window": Material(Texture("plain", ((0.6, 0.6, 0.6),), 1.0, s(13)), emission_cd_m2=1000.0, emission_rgb=(0.9, 1.0, 1.15),
                           emission_texture=Texture("window", ((0.95, 0.95, 0.95), (0.05, 0.05, 0.05)), 0.5, s(14))),
        "shade": Material(Texture("noise", ((0.9, 0.85, 0.7), (0.8, 0.75, 0.6)), 0.05, s(15)), emission_cd_m2=600.0,
                          emission_rgb=(1.0, 0.9, 0.75)),
        "metal": Material(Texture("noise", ((0.2, 0.2, 0.2), (0.35, 0.35, 0.35)), 0.05, s(16))),
    }
    size = (7.0, 5.5, 2.6)
    P: list[Primitive] = []
    _room_shell(P, size, "floor", "wall", "ceiling")
    # sofa against the south wall, coffee table and rug in front, TV on the north wall
    P.append(yaw_box((0.0, -2.3, 0.22), (2.2, 0.9, 0.44), "fabric"))
    P.append(yaw_box((0.0, -2.65, 0.65), (2.2, 0.2, 0.5), "fabric"))
    for dx in (-0.6, 0.6):
        P.append(yaw_box((dx + _jit(rng, 0.1), -2.35, 0.52), (0.5, 0.5, 0.16), "cushion", yaw_deg=_jit(rng, 8)))
    P.append(axis_rect((0.0, -0.9, 0.004), "+z", (2.6, 1.8), "rug"))
    P.append(yaw_box((0.0, -1.0, 0.42), (1.1, 0.6, 0.04), "wood"))
    P.append(yaw_box((0.0, -1.0, 0.2), (1.0, 0.5, 0.02), "wood"))
    P.append(yaw_box((0.15, -1.0, 0.445), (0.28, 0.21, 0.01), "magazine", yaw_deg=15 + _jit(rng, 10)))
    P.append(yaw_box((0.0, 2.7, 1.3), (1.4, 0.06, 0.8), "tv"))
    P.append(axis_rect((0.0, 2.665, 1.3), "-y", (1.3, 0.72), "screen"))
    P.append(yaw_box((0.0, 2.5, 0.3), (2.0, 0.45, 0.6), "wood"))
    _bookshelf(P, -3.48, 1.0, -90.0, 1.6, "wood", "books", height=1.8)
    P.append(axis_rect((3.49, 0.0, 1.45), "-x", (1.8, 1.3), "window"))
    P.append(axis_rect((-3.49, -1.6, 1.5), "+x", (1.0, 0.7), "art"))
    # floor lamp
    P.append(Cylinder((2.8, -2.2, 0.8), (0, 0, 1), 0.02, 0.8, "metal"))
    P.append(Cylinder((2.8, -2.2, 1.7), (0, 0, 1), 0.2, 0.14, "shade"))
    lights: list[Light] = [AmbientLight(110.0), PointLight((2.8, -2.2, 1.7), 150.0, rgb=(1.0, 0.9, 0.75)),
                           PointLight((0.0, 0.0, 2.5), 450.0), PointLight((3.0, 0.0, 1.6), 300.0, rgb=(0.9, 1.0, 1.15))]
    targets = np.array([[0.0, 2.66, 1.3], [0.0, -1.0, 0.45], [0.0, -2.3, 0.6], [-3.3, 1.0, 1.0], [3.45, 0.0, 1.45],
                        [-3.45, -1.6, 1.5]])
    return Scene("quest3", P, M, lights, WalkRegion("box", (0.2, 0.9), (1.8, 0.9)), targets,
                 ((-size[0] / 2, -size[1] / 2, 0.0), (size[0] / 2, size[1] / 2, size[2])), seed)


_BUILDERS = {"outdoor": _build_outdoor, "indoor": _build_indoor, "object": _build_object, "quest3": _build_quest3}


#: Fractal grain: largest feature (m) and octaves (each half the size, half the amplitude, down to 4 mm).
GRAIN_SCALE_M, GRAIN_OCTAVES = 0.5, 8


def grain_factor(uv: Tensor, primitive_id: Tensor, amplitude: float, seed: int,
                 footprint_m: Tensor | None = None) -> Tensor:
    """[N] albedo multiplier 1 + amplitude * 2 g, g = sum over octaves o of w_o (value noise - 1/2),
    lattices from 0.5 m down to 4 mm, w_o = 2^(o/4) / sqrt(sum w^2). Natural images have a 1/f
    amplitude spectrum, i.e. equal power per octave (Field 1987); value noise rolls off at its own
    finest scale, and the 2^(o/4) tilt offsets that: the power per octave measured along a line is
    flat within 2x from 0.5 m to 8 mm features (tests/test_sim_similarity_knobs.py). Octaves finer
    than the footprint fade to their mean, so distant surfaces do not alias. Each primitive gets
    its own offset into the field."""
    from egobench.sim.textures import value_noise

    p = uv + (primitive_id.to(uv.dtype) * 17.31)[:, None]
    w = [2.0 ** (o / 4.0) for o in range(GRAIN_OCTAVES)]
    norm = math.sqrt(sum(x * x for x in w))
    g = torch.zeros(uv.shape[0], dtype=uv.dtype, device=uv.device)
    for o in range(GRAIN_OCTAVES):
        g = g + w[o] / norm * (value_noise(p, GRAIN_SCALE_M * 0.5 ** o, int(seed) + 104729 + 7919 * o, footprint_m) - 0.5)
    return 1.0 + float(amplitude) * 2.0 * g


def make_scene(kind: SceneKind, seed: int = 0, sun_scale: float = 1.0, grain: float = 0.0) -> Scene:
    """Build a scene of ``kind`` (outdoor, indoor, object, quest3); the layout jitter,
    colours and texture patterns follow ``seed`` deterministically. ``sun_scale`` multiplies
    the illuminance of every `Sun` (the sun-to-shade dynamic range; scenes without a sun ignore it);
    ``grain`` adds a fractal albedo grain of that amplitude to every surface (`grain_factor`)."""
    if not (math.isfinite(grain) and 0.0 <= grain <= 1.0):
        raise ValueError(f"make_scene: grain must be a number in [0, 1], got {grain!r}")
    if kind not in _BUILDERS:
        raise ValueError(f"make_scene: kind must be one of {list(SCENE_KINDS)}, got {kind!r}")
    if int(seed) != seed:
        raise ValueError(f"make_scene: seed must be an integer, got {seed!r}")
    if not (math.isfinite(sun_scale) and sun_scale >= 0):
        raise ValueError(f"make_scene: sun_scale must be a finite number >= 0, got {sun_scale!r}")
    rng = np.random.default_rng([int(seed), SCENE_KINDS.index(kind)])
    scene = _BUILDERS[kind](rng, int(seed))
    scene.grain = float(grain)
    if sun_scale != 1.0:
        scene.lights = [replace(l, illuminance_lux=l.illuminance_lux * sun_scale) if isinstance(l, Sun) else l
                        for l in scene.lights]
    return scene
