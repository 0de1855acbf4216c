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
Write a module ``scenes/<kind>.py`` whose ``build(rng, seed) -> Scene`` lists primitives (each naming a material), a
``materials`` dict of `Material` (a `Texture` albedo, optional emission in cd/m^2), lights, a
`WalkRegion` (where the head may move: a box or a ring in x-y, at an eye height), look targets
(points of interest, [K, 3]) and the scene bounds; register it in ``scenes.BUILDERS``. Keep the walk
region clear of furniture (the motion model does not do collision avoidance), keep textures at feature
sizes of a few mm or more, and check the illuminance with ``Scene.cast(...)
.illuminance_lux`` from the walk region.
"""

from __future__ import annotations

from egobench.sim.world.lighting import AmbientLight, Light, PointLight, SkyDome, Sun
from egobench.sim.world.primitives import (
    EYE_HEIGHT_M,
    LUMINANCE_WEIGHTS,
    RGB,
    SCENE_KINDS,
    Box,
    Cylinder,
    Material,
    Primitive,
    Rect,
    SceneKind,
    Sphere,
    Vec3,
    WalkRegion,
    axis_rect,
    luminance,
    rot_z,
    yaw_box,
)
from egobench.sim.world.raycast import RayHit
from egobench.sim.world.scene import Scene, grain_factor
from egobench.sim.world.scenes import BUILDERS, make_scene

__all__ = [
    "AmbientLight", "BUILDERS", "Box", "Cylinder", "EYE_HEIGHT_M", "LUMINANCE_WEIGHTS", "Light", "Material",
    "PointLight", "Primitive", "RGB", "RayHit", "Rect", "SCENE_KINDS", "Scene", "SceneKind", "SkyDome", "Sphere",
    "Sun", "Vec3", "WalkRegion", "axis_rect", "grain_factor", "luminance", "make_scene", "rot_z", "yaw_box",
]
