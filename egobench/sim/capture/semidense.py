"""Semi-dense SLAM points: scene surface samples with SLAM-like inverse-distance noise."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.data.mps import SemiDensePoints
from egobench.sim.devices import SEMIDENSE_NOISE

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    pass


# ----------------------------------------------------------------------------------------
# semi-dense points
# ----------------------------------------------------------------------------------------
def make_semidense_points(scene, positions_world: Tensor, n: int, seed: int) -> tuple[SemiDensePoints, np.ndarray]:
    """Scene surface samples + SLAM-like noise -> (points as MPS writes them, clean points [P, 3]).

    Each point gets an observer (a random device position), inv_dist_std ~ logNormal fitted to
    the real sample, a perturbed inverse distance 1/d' = 1/d + N(0, inv_dist_std) along the
    viewing ray, and dist_std = inv_dist_std * d^2 (devices.SemiDenseNoise).
    """
    rng = np.random.default_rng([seed, 303])
    if n == 0:
        z = np.zeros(0)
        return SemiDensePoints(np.zeros(0, np.int64), np.zeros((0, 3)), z, z), np.zeros((0, 3))
    res = scene.sample_surface_points(n, rng, visible_from=positions_world)
    pts = res[0] if isinstance(res, tuple) else res
    clean = np.asarray(torch.as_tensor(pts).detach().cpu().numpy(), dtype=np.float64).reshape(-1, 3)
    pos = positions_world.detach().cpu().numpy().astype(np.float64)
    obs = pos[rng.integers(0, pos.shape[0], size=clean.shape[0])]
    vec = clean - obs
    d = np.linalg.norm(vec, axis=1).clip(1e-3)
    ray = vec / d[:, None]
    noise = SEMIDENSE_NOISE
    inv_std = pm.exp(rng.normal(noise.log_inv_dist_std_mean, noise.log_inv_dist_std_std, size=d.shape))
    inv_d = 1.0 / d + rng.normal(size=d.shape) * inv_std
    inv_d = np.maximum(inv_d, 1.0 / (10.0 * d))  # never behind the observer nor at infinity
    d_noisy = 1.0 / inv_d
    noisy = obs + ray * d_noisy[:, None]
    dist_std = inv_std * d_noisy**2
    sd = SemiDensePoints(uid=np.arange(clean.shape[0], dtype=np.int64), points_world=noisy, inv_dist_std=inv_std,
                         dist_std=dist_std)
    return sd, clean
