"""Exact ray casting against the primitives: the dense and culled intersection tests, surface frames."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm


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
