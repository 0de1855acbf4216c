"""The initial Gaussians' scales: the 3-NN RMS distance, its log taken in float64 by numpy and rounded once."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from egobench.train.initialise import initial_log_scales


def test_initial_log_scales_are_the_log_of_the_scaled_3nn_rms_distance_on_a_lattice():
    h = 0.05  # a cubic lattice: every interior point's three nearest neighbours lie h away
    g = np.arange(5) * h
    pts = torch.tensor(np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3), dtype=torch.float32)
    out = initial_log_scales(pts, 1.5)
    assert out.dtype == torch.float32 and out.shape == (125, 3)
    interior = ((pts > 0) & (pts < 4 * h - 1e-6)).all(dim=1)
    want = np.float32(np.log(1.5 * h))
    assert torch.allclose(out[interior], torch.full((int(interior.sum()), 3), float(want)), atol=2e-7)
    assert torch.equal(out[:, 0], out[:, 1]) and torch.equal(out[:, 0], out[:, 2])


def test_initial_log_scales_are_rounded_once_from_float64():
    rng = np.random.default_rng(0)
    pts = torch.tensor(rng.normal(size=(3000, 3)), dtype=torch.float32)
    out = initial_log_scales(pts, 1.5)[:, 0].numpy()
    p = pts.numpy().astype(np.float64)
    dist, _ = cKDTree(p).query(p, k=4)
    want = np.log(1.5 * np.sqrt((dist[:, 1:] ** 2).mean(axis=1))).astype(np.float32)
    assert np.array_equal(out, want)  # numpy's float64 log rounded to float32: no torch kernel in between


def test_fewer_points_than_neighbours_get_one_centimetre():
    out = initial_log_scales(torch.zeros(2, 3), 2.0)
    assert torch.allclose(out, torch.full((2, 3), float(np.float32(np.log(0.02)))))
