"""`Scene`: primitives, materials and lights, cast by rays into radiance, depth and normals; fractal grain."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.sim.textures import evaluate_texture, value_noise
from egobench.sim.world.lighting import AmbientLight, Light, PointLight, SkyDome, Sun, _rgb_unit_luminance
from egobench.sim.world.primitives import (
    BIG_BOX_RADIUS_M,
    SURFACE_EPS_M,
    Box,
    Cylinder,
    Material,
    Primitive,
    Rect,
    Sphere,
    WalkRegion,
    _frame_from_axis,
    _unit,
    luminance,
)
from egobench.sim.world.raycast import (
    _TYPE_NAMES,
    RayHit,
    _box_surface_frame,
    _cylinder_surface_frame,
    _group_primitives,
    _hit_boxes,
    _hit_boxes_dense,
    _hit_cylinders,
    _hit_rects,
    _hit_spheres,
    _rect_surface_frame,
    _sphere_surface_frame,
)


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
    # world box (min xyz, max xyz) of the captured object(s) of an object capture: the ground truth's foreground
    # mask (the surfaces the authors' Table 2 geometry is scored on); None: the scene has no foreground
    foreground_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
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
    def intersect(self, origins: Tensor, directions: Tensor, t_max: Tensor | None = None,
                  backend: str = "auto") -> tuple[Tensor, Tensor]:
        """Closest hit of each ray. origins, directions (unit) [N, 3]; t_max [N] or None.

        Returns (t [N], primitive_id [N] int64); misses have t = inf and id = -1. ``backend``: "compiled"
        (`raycast_kernel`: float32 or float64 CPU rays [N, 3] without autograd, t_max [N] of their dtype), "torch"
        (the tensor tests of `raycast`, any dtype and device: the reference) or "auto" (compiled where it applies).
        They give the same bits but for torch's square root (MKL's, not correctly rounded; the kernel's is IEEE).
        """
        if backend not in ("auto", "compiled", "torch"):
            raise ValueError(f"Scene.intersect: backend must be 'auto', 'compiled' or 'torch', got {backend!r}")
        fits = _compiled_cast_applies(origins, directions, t_max)
        if backend == "compiled" and not fits:
            raise ValueError(f"Scene.intersect: the compiled backend takes float32 or float64 CPU rays [N, 3] without "
                             f"autograd and t_max [N] of their dtype, got {origins.dtype} {tuple(origins.shape)} and "
                             f"{directions.dtype} {tuple(directions.shape)} on {origins.device}")
        if backend != "torch" and fits:
            from egobench.sim.world import raycast_kernel  # loads numba: after the thread set-up (host.setup_threads)

            key = ("kernel", origins.dtype)
            if key not in self._packs:
                pack = self._pack(origins.dtype, origins.device)
                self._packs[key] = raycast_kernel.kernel_tables(pack, origins.dtype)
            return raycast_kernel.intersect_compiled(self._packs[key], origins, directions, t_max)
        return self._intersect_torch(origins, directions, t_max)

    def _intersect_torch(self, origins: Tensor, directions: Tensor, t_max: Tensor | None) -> tuple[Tensor, Tensor]:
        """`intersect` through `raycast`'s tensor tests, in chunks of `chunk_rays`."""
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


#: Fractal grain: largest feature (m) and octaves (each half the size, half the amplitude, down to 4 mm).
GRAIN_SCALE_M, GRAIN_OCTAVES = 0.5, 8


def _compiled_cast_applies(origins: Tensor, directions: Tensor, t_max: Tensor | None) -> bool:
    """May `Scene.intersect` take the compiled kernel: float32 or float64 CPU rays [N, 3] without autograd, t_max [N] of
    that dtype? (Anything else goes to the torch tests, which broadcast, raise or differentiate as torch does.)"""
    n = origins.shape[0] if origins.ndim == 2 else -1
    rays = (origins.dtype in (torch.float32, torch.float64) and origins.ndim == 2 and origins.shape[1] == 3
            and directions.shape == origins.shape
            and directions.dtype == origins.dtype and origins.device.type == "cpu" and directions.device.type == "cpu"
            and not (origins.requires_grad or directions.requires_grad))
    return rays and (t_max is None or (t_max.shape == (n,) and t_max.dtype == origins.dtype
                                       and t_max.device.type == "cpu" and not t_max.requires_grad))


def grain_factor(uv: Tensor, primitive_id: Tensor, amplitude: float, seed: int,
                 footprint_m: Tensor | None = None) -> Tensor:
    """[N] albedo multiplier 1 + amplitude * 2 g, g = sum over octaves o of w_o (value noise - 1/2),
    lattices from 0.5 m down to 4 mm, w_o = 2^(o/4) / sqrt(sum w^2). Natural images have a 1/f
    amplitude spectrum, i.e. equal power per octave (Field 1987); value noise rolls off at its own
    finest scale, and the 2^(o/4) tilt offsets that: the power per octave measured along a line is
    flat within 2x from 0.5 m to 8 mm features (tests/sim/test_sim_similarity_knobs.py). Octaves finer
    than the footprint fade to their mean, so distant surfaces do not alias. Each primitive gets
    its own offset into the field."""
    p = uv + (primitive_id.to(uv.dtype) * 17.31)[:, None]
    w = [2.0 ** (o / 4.0) for o in range(GRAIN_OCTAVES)]
    norm = math.sqrt(sum(x * x for x in w))
    g = torch.zeros(uv.shape[0], dtype=uv.dtype, device=uv.device)
    for o in range(GRAIN_OCTAVES):
        g = g + w[o] / norm * (value_noise(p, GRAIN_SCALE_M * 0.5 ** o, int(seed) + 104729 + 7919 * o, footprint_m) - 0.5)
    return 1.0 + float(amplitude) * 2.0 * g
