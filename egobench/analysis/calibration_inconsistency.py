"""The part of a calibration error that a reconstruction cannot absorb (issue 13: why w/o VIBA ties).

A constant calibration error moves a world point's image in every frame. A reconstruction absorbs
what one displaced point explains in all the frames that see it: it puts the point where the wrong
cameras agree. Only the disagreement left over blurs the model, so that residual, not the error
itself, sizes the effect VIBA removes. It grows with how differently the frames that see a point are
oriented and placed, i.e. with the field of view: a narrow view sees each point only from nearly the
same direction, and absorbs nearly all of a constant extrinsic error.

- `absorbed_residual_px`: per point, the RMS reprojection residual [P] after the least-squares 3-D
  point (damped Gauss-Newton) over the frames that see it (NaN where fewer than two do).
- `calibration_inconsistency`: the same for a recording's factory stream against where its images
  show each point when the online (VIBA) calibration is right; points are the sparse-depth points of
  every ``every``-th frame, seen by every frame whose online image contains them (occlusion ignored).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from egobench.analysis.calibration_reprojection import frame_number, from_camera, median_p90, observed_in_test_px, online_at, to_camera
from egobench.camera.pinhole import Pinhole
from egobench.model.motion_sampling import sparse_points_camera

#: Frames with fewer observations of a point than this leave its residual undefined.
MIN_VIEWS = 2


def project_world(pinhole: Pinhole, T_world_camera: Tensor, points_world: Tensor) -> tuple[Tensor, Tensor]:
    """Points [P, 3] (world) into J cameras [J, 4, 4] -> (pixels [P, J, 2], camera points [P, J, 3])."""
    R, t = T_world_camera[:, :3, :3], T_world_camera[:, :3, 3]
    Y = torch.einsum("jab,pja->pjb", R, points_world[:, None, :] - t[None])  # R^T (X - t)
    z = torch.where(Y[..., 2] > 1e-9, Y[..., 2], torch.ones_like(Y[..., 2]))
    u = torch.stack([pinhole.fx * Y[..., 0] / z + pinhole.cx, pinhole.fy * Y[..., 1] / z + pinhole.cy], dim=-1)
    return u, Y


def _jacobian(pinhole: Pinhole, Y: Tensor, R: Tensor) -> Tensor:
    """d pixel / d world point [P, J, 2, 3] at camera points Y [P, J, 3] (R: [J, 3, 3] camera -> world)."""
    x, y, z = Y.unbind(-1)
    z = torch.where(z > 1e-9, z, torch.ones_like(z))
    zero = torch.zeros_like(z)
    d_dY = torch.stack([torch.stack([pinhole.fx / z, zero, -pinhole.fx * x / z**2], -1),
                        torch.stack([zero, pinhole.fy / z, -pinhole.fy * y / z**2], -1)], -2)
    return d_dY @ R.transpose(-1, -2)[None]  # dY/dX = R^T


def absorbed_residual_px(u_obs: Tensor, valid: Tensor, pinhole: Pinhole, T_world_camera: Tensor,
                         points_world: Tensor, iterations: int = 10) -> Tensor:
    """RMS residual [P] (px) of each point's best 3-D position against its observations.

    u_obs: [P, J, 2] where frame j's image shows point p; valid: [P, J] bool; T_world_camera: [J, 4, 4]
    the cameras the reconstruction uses; points_world: [P, 3] the start. A point's depth along a ray
    that no baseline constrains is held by a small Levenberg damping."""
    X = points_world.to(torch.float64).clone()
    T = T_world_camera.to(torch.float64)
    u_obs, w = u_obs.to(torch.float64), valid.to(torch.float64)[..., None]
    eye = torch.eye(3, dtype=torch.float64)
    for _ in range(iterations):
        u, Y = project_world(pinhole, T, X)
        ok = w * (Y[..., 2:] > 1e-9)
        Jm = _jacobian(pinhole, Y, T[:, :3, :3]) * ok[..., None]
        r = (u - u_obs) * ok
        H = torch.einsum("pjai,pjak->pik", Jm, Jm)
        g = torch.einsum("pjai,pja->pi", Jm, r)
        lam = 1e-6 * H.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-12)
        X = X - torch.linalg.solve(H + lam[:, None, None] * eye, g[..., None])[..., 0]
    u, Y = project_world(pinhole, T, X)
    ok = valid & (Y[..., 2] > 1e-9)
    n = ok.sum(1)
    sq = (((u - u_obs) ** 2).sum(-1) * ok).sum(1)
    rms = torch.sqrt(sq / n.clamp_min(1))
    return torch.where(n >= MIN_VIEWS, rms, torch.full_like(rms, float("nan")))


def _world_points(recording, frames: list, every: int, max_per_frame: int) -> Tensor:
    """Sparse-depth points of every ``every``-th frame, in the world [P, 3] float64."""
    chunks = []
    for f in frames[::every]:
        if f.sparse_depth is None or len(f.sparse_depth.z) == 0:
            continue
        p_c = sparse_points_camera(recording, f)
        stride = max(1, len(p_c) // max_per_frame)
        chunks.append(from_camera(f.T_world_camera, p_c[::stride][:max_per_frame]))
    return torch.cat(chunks) if chunks else torch.zeros(0, 3, dtype=torch.float64)


def _observations(online_rec, pairs: list, cals: dict, X: Tensor) -> tuple[Tensor, Tensor]:
    """Where each factory-stream image shows each point [P, J, 2], and which frames see it [P, J]."""

    pin = online_rec.camera
    full = cals["factory"] is not None and cals["online"] is not None
    u_all, ok_all = [], []
    for f, _ in pairs:
        u_on, ok = pin.project(to_camera(f.T_world_camera, X))
        ok = ok & (u_on[:, 0] >= 0) & (u_on[:, 0] <= pin.width - 1) & (u_on[:, 1] >= 0) & (u_on[:, 1] <= pin.height - 1)
        if full:  # the raw pixel the online calibration puts X at, as the factory rectification shows it
            T_wd = f.T_world_camera.to(torch.float64) @ torch.linalg.inv(f.T_device_camera.to(torch.float64))
            u_obs, ok_obs = observed_in_test_px(to_camera(T_wd, X), online_at(cals["online"], f.timestamp_ns),
                                                cals["factory"], pin)
            ok = ok & ok_obs
        else:  # two rectified streams: they differ in extrinsics only
            u_obs = u_on
        u_all.append(u_obs)
        ok_all.append(ok)
    return torch.stack(u_all, 1), torch.stack(ok_all, 1)


def calibration_inconsistency(online_rec, factory_rec, cals: dict, pixel_scale: float = 1.0,
                              every: int = 8, max_per_frame: int = 48) -> dict:
    """Median/p90 of the factory stream's unabsorbable residual (px x pixel_scale), the median
    absolute error before absorption on the same observations, and the number of points."""

    keys = ("calib_inconsistency_px_median", "calib_inconsistency_px_p90", "calib_unabsorbed_fraction")
    if factory_rec is None:
        return {k: None for k in keys} | {"calib_inconsistency_n_points": 0}
    by_number = {frame_number(f): f for f in factory_rec.frames}
    pairs = [(f, by_number[frame_number(f)]) for f in online_rec.frames if frame_number(f) in by_number]
    X = _world_points(online_rec, [f for f, _ in pairs], every, max_per_frame)
    if len(X) == 0 or len(pairs) < MIN_VIEWS:
        return {k: None for k in keys} | {"calib_inconsistency_n_points": 0}
    u_obs, ok = _observations(online_rec, pairs, cals, X)
    T_fa = torch.stack([ff.T_world_camera.to(torch.float64) for _, ff in pairs])
    pin = online_rec.camera
    u0, _ = project_world(pin, T_fa, X)
    before = (u0 - u_obs).norm(dim=-1)[ok]
    res = absorbed_residual_px(u_obs, ok, pin, T_fa, X)
    res = res[torch.isfinite(res)].numpy() * pixel_scale
    out: dict = {"calib_inconsistency_n_points": int(res.size)}
    out["calib_inconsistency_px_median"], out["calib_inconsistency_px_p90"] = median_p90(res)
    med_before = float(np.median(before.numpy())) * pixel_scale if before.numel() else None
    out["calib_unabsorbed_fraction"] = (None if not med_before or out["calib_inconsistency_px_median"] is None
                                        else out["calib_inconsistency_px_median"] / med_before)
    return out
