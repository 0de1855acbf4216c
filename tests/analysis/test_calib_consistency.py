"""egobench.analysis.calibration_inconsistency: the part of a calibration error a reconstruction cannot absorb."""

import math

import numpy as np
import pytest
import torch

from egobench.analysis.calibration_inconsistency import absorbed_residual_px, project_world
from egobench.camera.pinhole import Pinhole
from egobench.geometry import so3_exp

PIN = Pinhole(width=128, height=128, fx=384.0, fy=384.0, cx=63.5, cy=63.5)


def _pose(rotvec, centre) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = so3_exp(torch.tensor(rotvec, dtype=torch.float64))
    T[:3, 3] = torch.tensor(centre, dtype=torch.float64)
    return T


def _rig(n: int, seed: int) -> torch.Tensor:
    """n cameras on a 1 m arc looking at points ~5 m ahead (z forward), small random orientations."""
    rng = np.random.default_rng(seed)
    return torch.stack([_pose(rng.normal(scale=0.03, size=3), [x, rng.normal(scale=0.05), 0.0])
                        for x in np.linspace(-0.5, 0.5, n)])


def _points(n: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.as_tensor(np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(4, 6, n)])


def test_two_cameras_rotated_apart_leave_f_tan_angle():
    # same centre, the wrong cameras yawed by +-a: the best point sits on the axis, each view misses by f tan a
    a = math.radians(0.3)
    X = torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64)
    T_true = torch.stack([_pose([0, 0, 0], [0, 0, 0])] * 2)
    u_obs, _ = project_world(PIN, T_true, X)
    T_wrong = torch.stack([_pose([0, a, 0], [0, 0, 0]), _pose([0, -a, 0], [0, 0, 0])])
    res = absorbed_residual_px(u_obs, torch.ones(1, 2, dtype=torch.bool), PIN, T_wrong, X)
    assert res.item() == pytest.approx(PIN.fx * math.tan(a), rel=1e-4)


def test_an_error_shared_by_the_whole_world_is_absorbed():
    # the wrong cameras are the true ones moved by one rigid transform: the moved points explain every view
    T_true, X = _rig(8, 0), _points(40, 1)
    u_obs, _ = project_world(PIN, T_true, X)
    G = _pose([0.004, -0.003, 0.002], [0.01, -0.02, 0.005])
    T_wrong = G @ T_true
    before = (project_world(PIN, T_wrong, X)[0] - u_obs).norm(dim=-1)
    res = absorbed_residual_px(u_obs, torch.ones(40, 8, dtype=torch.bool), PIN, T_wrong, X)
    assert before.median() > 3.0
    assert res.max() < 1e-6


def test_the_residual_matches_an_independent_least_squares():
    from scipy.optimize import least_squares

    T_true, X = _rig(6, 2), _points(12, 3)
    u_obs, _ = project_world(PIN, T_true, X)
    rng = np.random.default_rng(4)
    T_wrong = torch.stack([T @ _pose(rng.normal(scale=0.004, size=3), rng.normal(scale=0.003, size=3)) for T in T_true])
    valid = torch.as_tensor(rng.random((12, 6)) > 0.2)
    valid[:, :2] = True
    res = absorbed_residual_px(u_obs, valid, PIN, T_wrong, X)
    for p in range(12):
        js = valid[p].nonzero()[:, 0]

        def f(x, p=p, js=js):
            u, _ = project_world(PIN, T_wrong[js], torch.as_tensor(x)[None])
            return (u[0] - u_obs[p, js]).reshape(-1).numpy()

        sol = least_squares(f, X[p].numpy(), xtol=1e-14, ftol=1e-14, gtol=1e-14)
        expected = math.sqrt(2 * sol.cost * 2 / (2 * len(js)))  # cost = sum(r^2) / 2; RMS over views of |r|
        assert res[p].item() == pytest.approx(expected, rel=1e-5, abs=1e-9)


def test_a_point_seen_once_has_no_residual():
    T, X = _rig(3, 5), _points(2, 6)
    u_obs, _ = project_world(PIN, T, X)
    valid = torch.tensor([[True, False, False], [True, True, False]])
    res = absorbed_residual_px(u_obs, valid, PIN, T, X)
    assert math.isnan(res[0].item()) and res[1].item() < 1e-9
