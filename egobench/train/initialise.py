"""Initial Gaussians from the semi-dense SLAM points (docs/paper-notes.md §6, as gsplat's init)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from egobench.model.formation import GammaResponse
from egobench.model.methods import MethodSpec
from egobench.train.config import TrainConfig
from egobench.train.data import TrainingData, image_to_float


def _knn_rms_distance(points: Tensor, k: int = 3) -> np.ndarray:
    """RMS distance of each point [N, 3] to its k nearest neighbours -> [N] float64 (as gsplat's init)."""
    pts = points.detach().cpu().numpy().astype(np.float64)
    if len(pts) <= k:
        return np.full(len(pts), 0.01)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    d = np.sqrt((dist[:, 1:] ** 2).mean(axis=1))
    return np.maximum(d, 1e-7)


def initial_log_scales(points: Tensor, init_scale: float) -> Tensor:
    """[N, 3] float32: log(init_scale x the 3-NN RMS distance), the same on all three axes. The log is numpy's
    in float64, rounded once to float32: torch's CPU log on a tensor that its thread pool splits returned a
    first half up to 4e-5 off in a few processes in twenty on an Intel Xeon (results/ladder/README.md,
    2026-12-07), which made one seed train two different runs."""
    log_d = np.log(_knn_rms_distance(points) * float(init_scale)).astype(np.float32)
    return torch.from_numpy(np.repeat(log_d[:, None], 3, axis=1))


def scene_colour_from_image(pixel: Tensor, k: Tensor, vignette: Tensor, spec: MethodSpec) -> Tensor:
    """Invert the method's formation for initial colours: pixel [P, 3] display -> scene colour."""
    if not spec.formation:
        return pixel
    resp = GammaResponse(spec.response_gamma)
    lin = resp.decode(pixel) / (k[:, None] * vignette[:, None]).clamp_min(1e-3)
    return resp.encode(lin).clamp(0, 1) if spec.scene_gamma else lin.clamp(0, 4)


def init_params(data: TrainingData, config: TrainConfig, generator: torch.Generator) -> dict[str, torch.nn.Parameter]:
    """Gaussians from the semi-dense points: opacity init_opacity, scale from 3-NN distance,
    random quaternions (gsplat), colour from the first training image each point projects into
    (inside the valid mask), else grey 0.5 (``init_colour="grey"``: 0.5 everywhere, as the authors' code)."""
    pts = data.recording.points_world.to(torch.float32)
    if config.max_gaussians > 0 and len(pts) > config.max_gaussians:
        keep = torch.randperm(len(pts), generator=generator)[: config.max_gaussians].sort().values
        pts = pts[keep]
    N = len(pts)
    scales = initial_log_scales(pts, config.init_scale)
    quats = torch.rand((N, 4), generator=generator)
    opacities = torch.logit(torch.full((N,), float(config.init_opacity)))
    colors = _initial_colours(data, pts) if config.init_colour == "image" else torch.full((N, 3), 0.5)
    return {
        "means": torch.nn.Parameter(pts.clone()),
        "scales": torch.nn.Parameter(scales),
        "quats": torch.nn.Parameter(quats),
        "opacities": torch.nn.Parameter(opacities),
        "colors": torch.nn.Parameter(colors),
    }


def _initial_colours(data: TrainingData, pts: Tensor) -> Tensor:
    """Scene colour [N, 3] of each point [N, 3] from the first of a few training images it projects
    into inside the valid mask (the method's formation inverted), else grey 0.5."""
    N = len(pts)
    colors = torch.full((N, 3), 0.5)
    assigned = torch.zeros(N, dtype=torch.bool)
    cam = data.camera
    step = max(1, len(data.frames) // 16)
    for i in range(0, len(data.frames), step):  # a few frames, vectorised over points
        f = data.frames[i]
        T_cw = torch.linalg.inv(f.T_world_camera.to(torch.float64)).to(torch.float32)
        pc = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv, valid = cam.project(pc)
        ui, vi = torch.round(uv[:, 0]).long(), torch.round(uv[:, 1]).long()
        inside = valid & (ui >= 0) & (ui < cam.width) & (vi >= 0) & (vi < cam.height) & ~assigned
        ui, vi = ui.clamp(0, cam.width - 1), vi.clamp(0, cam.height - 1)
        inside &= data.maps.mask[vi, ui]
        if inside.any():
            px = image_to_float(data.images[i][vi[inside], ui[inside]])
            kk = data.k[i].expand(int(inside.sum()))
            colors[inside] = scene_colour_from_image(px, kk, data.maps.vignette[vi[inside], ui[inside]], data.spec).float()
            assigned |= inside
        if bool(assigned.all()):
            break
    return colors
