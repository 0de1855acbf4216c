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


def _knn_rms_distance(points: Tensor, k: int = 3) -> Tensor:
    """RMS distance of each point [N, 3] to its k nearest neighbours -> [N] (as gsplat's init)."""
    pts = points.detach().cpu().numpy().astype(np.float64)
    if len(pts) <= k:
        return torch.full((len(pts),), 0.01, dtype=torch.float32)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    d = np.sqrt((dist[:, 1:] ** 2).mean(axis=1))
    d = np.maximum(d, 1e-7)
    return torch.from_numpy(d).float()


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
    scales = torch.log(_knn_rms_distance(pts) * config.init_scale)[:, None].repeat(1, 3)
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
