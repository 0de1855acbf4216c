"""Tests for egobench.camera models: round trips, analytic values, projectaria-tools agreement."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from egobench.camera import CameraModel, Equidistant, Fisheye624, Pinhole
from tests.helpers import ARIA_RGB_PARAMS_1408, real_rgb_calibration

F64 = torch.float64



def aria_rgb() -> Fisheye624:
    return Fisheye624(torch.tensor(ARIA_RGB_PARAMS_1408, dtype=F64), 1408, 1408)


def points_in_fov(n: int, max_theta: float, gen: torch.Generator) -> torch.Tensor:
    """Random camera-frame points [n, 3] with off-axis angle < max_theta, depths 0.2..10 m."""
    theta = torch.rand(n, dtype=F64, generator=gen) * max_theta
    phi = torch.rand(n, dtype=F64, generator=gen) * 2 * math.pi
    d = 0.2 + 9.8 * torch.rand(n, dtype=F64, generator=gen)
    return d[:, None] * torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1)


def test_protocol():
    for cam in [aria_rgb(), Equidistant(100.0, 63.5, 63.5, 128, 128), Pinhole(100.0, 100.0, 63.5, 63.5, 128, 128)]:
        assert isinstance(cam, CameraModel)


# ---------------------------------------------------------------------------------- Fisheye624
def test_fisheye_round_trips():
    cam = aria_rgb()
    gen = torch.Generator().manual_seed(0)
    P = points_in_fov(4000, math.radians(75), gen)
    uv, valid = cam.project(P)
    assert valid.all()
    rays, converged = cam.unproject_checked(uv)
    assert converged.all()
    assert torch.allclose(rays.norm(dim=-1), torch.ones(4000, dtype=F64), atol=1e-14)
    assert torch.allclose(rays, P / P.norm(dim=-1, keepdim=True), atol=1e-11)
    pix = torch.rand(4000, 2, dtype=F64, generator=gen) * 1407
    uv2, _ = cam.project(cam.unproject(pix))
    assert torch.allclose(uv2, pix, atol=1e-8)


def test_fisheye_zero_distortion_is_equidistant():
    params = torch.zeros(15, dtype=F64)
    params[:3] = torch.tensor([300.0, 319.5, 239.5])
    fish = Fisheye624(params, 640, 480)
    equi = Equidistant(300.0, 319.5, 239.5, 640, 480)
    gen = torch.Generator().manual_seed(1)
    P = points_in_fov(500, 1.4, gen)
    assert torch.allclose(fish.project(P)[0], equi.project(P)[0], atol=1e-10)
    # On the optical axis and analytic off-axis value: r = f * theta.
    uv, valid = fish.project(torch.tensor([[0.0, 0.0, 2.0], [math.tan(0.5), 0.0, 1.0]], dtype=F64))
    assert valid.all()
    assert torch.allclose(uv, torch.tensor([[319.5, 239.5], [319.5 + 300 * 0.5, 239.5]], dtype=F64), atol=1e-12)


def test_fisheye_tangential_and_prism_terms_analytic():
    # Only p0 and s0: for a point whose radially-distorted coords are (a, 0):
    # u = f (a + 2 a p0 a + p0 a^2 + s0 a^2) + cx, v = cy.
    p = torch.zeros(15, dtype=F64)
    p[:3] = torch.tensor([200.0, 100.0, 90.0])
    p[9], p[11] = 0.01, 0.02
    cam = Fisheye624(p, 201, 181)
    theta = 0.4
    uv, _ = cam.project(torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=F64))
    a = theta
    assert float(uv[0]) == pytest.approx(200 * (a + 3 * 0.01 * a * a + 0.02 * a * a) + 100, abs=1e-10)
    assert float(uv[1]) == pytest.approx(90.0, abs=1e-12)


def test_fisheye_unproject_gradient_is_implicit_inverse():
    cam = aria_rgb()
    pix = torch.tensor([[300.0, 900.0], [1000.0, 200.0]], dtype=F64, requires_grad=True)
    rays = cam.unproject(pix)
    # d(project(unproject(pix)))/d pix = I, using autograd through both.
    J = torch.autograd.functional.jacobian(lambda x: cam.project(cam.unproject(x))[0], pix.detach())
    for i in range(2):
        assert torch.allclose(J[i, :, i, :], torch.eye(2, dtype=F64), atol=1e-8)
    assert rays.requires_grad


def test_fisheye_scaled_and_json():
    cam = aria_rgb()
    small = cam.scaled(0.25)
    assert (small.width, small.height) == (352, 352)
    assert small.f == pytest.approx(cam.f * 0.25)
    assert small.cx == pytest.approx((cam.cx + 0.5) * 0.25 - 0.5)
    # Same ray lands on the same physical spot: pixel coordinates scale about the image corner.
    gen = torch.Generator().manual_seed(2)
    P = points_in_fov(100, 1.0, gen)
    assert torch.allclose(small.project(P)[0], (cam.project(P)[0] + 0.5) * 0.25 - 0.5, atol=1e-9)
    entry = {"Label": "camera-rgb", "Projection": {"Name": "FisheyeRadTanThinPrism", "Params": cam.to_mps_params()}}
    back = Fisheye624.from_mps_json(json.loads(json.dumps(entry)), (1408, 1408))
    assert torch.equal(back.params, cam.params)


def test_fisheye_validation():
    with pytest.raises(ValueError, match="15 values"):
        Fisheye624(torch.zeros(14, dtype=F64), 10, 10)
    bad = torch.tensor(ARIA_RGB_PARAMS_1408, dtype=F64)
    bad[0] = -1
    with pytest.raises(ValueError, match="f = params"):
        Fisheye624(bad, 10, 10)
    with pytest.raises(ValueError, match="width"):
        Fisheye624(torch.tensor(ARIA_RGB_PARAMS_1408), 0, 10)
    with pytest.raises(ValueError, match="Projection.Name"):
        Fisheye624.from_mps_json({"Label": "x", "Projection": {"Name": "Linear", "Params": [1.0] * 15}}, (10, 10))
    with pytest.raises(ValueError, match="shape"):
        aria_rgb().project(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="aspect"):
        Fisheye624(torch.tensor(ARIA_RGB_PARAMS_1408), 640, 480).scaled(0.333)


def test_fisheye_unproject_flags_nonconvergence():
    # A strongly folding radial polynomial: pixels beyond the fold cannot be unprojected.
    p = torch.zeros(15, dtype=F64)
    p[:3] = torch.tensor([100.0, 50.0, 50.0])
    p[3] = -0.3  # th_d = th - 0.3 th^3 peaks at th = 1.054 (th_d = 0.70)
    cam = Fisheye624(p, 101, 101)
    assert cam.theta_max == pytest.approx(math.sqrt(1 / 0.9), abs=1e-3)
    rays, conv = cam.unproject_checked(torch.tensor([[60.0, 50.0], [50.0 + 100 * 0.9, 50.0]], dtype=F64))
    assert conv.tolist() == [True, False]
    assert torch.isfinite(rays).all()
    _, valid = cam.project(torch.tensor([[math.tan(1.2), 0, 1.0], [0.1, 0, 1.0]], dtype=F64))
    assert valid.tolist() == [False, True]


@pytest.fixture(scope="module")
def aria_calibration():
    entry, size, ref = real_rgb_calibration()
    return Fisheye624.from_mps_json(entry, size), ref


def test_fisheye_matches_projectaria_tools(aria_calibration):
    cam, ref = aria_calibration
    assert (cam.width, cam.height) == tuple(ref.get_image_size())
    gen = torch.Generator().manual_seed(3)
    P = points_in_fov(300, math.radians(80), gen)
    uv, valid = cam.project(P)
    assert valid.all()
    uv_ref = np.stack([ref.project_no_checks(p).ravel() for p in P.numpy()])
    assert np.abs(uv.numpy() - uv_ref).max() < 1e-6
    pix = torch.rand(300, 2, dtype=F64, generator=gen) * (cam.width - 1)
    rays = cam.unproject(pix).numpy()
    rays_ref = np.stack([ref.unproject_no_checks(p).ravel() for p in pix.numpy()])
    rays_ref /= np.linalg.norm(rays_ref, axis=1, keepdims=True)
    # 1e-9 rad ~ 6e-7 px at f = 609.
    assert np.abs(rays - rays_ref).max() < 1e-9
    # Scaling agrees with projectaria's CameraCalibration.rescale.
    small_ref = ref.rescale(np.array([352, 352]), 0.25)
    assert np.allclose(cam.scaled(0.25).params.numpy(), small_ref.get_projection_params(), atol=1e-9)


# ---------------------------------------------------------------------------------- Equidistant
def test_equidistant_analytic_and_round_trip():
    cam = Equidistant(f=250.0, cx=255.5, cy=191.5, width=512, height=384, max_theta=math.radians(100))
    uv, valid = cam.project(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 3.0], [0.0, 1.0, -1.0]], dtype=F64))
    assert valid.tolist() == [True, True, False]
    assert torch.allclose(uv[0], torch.tensor([255.5 + 250 * math.pi / 2, 191.5], dtype=F64))
    assert torch.allclose(uv[1], torch.tensor([255.5, 191.5], dtype=F64))
    gen = torch.Generator().manual_seed(4)
    P = points_in_fov(1000, math.radians(99), gen)
    rays = cam.unproject(cam.project(P)[0])
    assert torch.allclose(rays, P / P.norm(dim=-1, keepdim=True), atol=1e-12)
    s = cam.scaled(0.5)
    assert torch.allclose(s.project(P)[0], (cam.project(P)[0] + 0.5) * 0.5 - 0.5, atol=1e-10)
    with pytest.raises(ValueError, match="Equidistant.f"):
        Equidistant(0.0, 1, 1, 2, 2)


# ---------------------------------------------------------------------------------- Pinhole
def test_pinhole_round_trip():
    cam = Pinhole(fx=200.0, fy=210.0, cx=99.5, cy=79.5, width=200, height=160)
    gen = torch.Generator().manual_seed(5)
    P = points_in_fov(500, math.radians(40), gen)
    uv, valid = cam.project(P)
    assert valid.all()
    rays = cam.unproject(uv)
    assert torch.allclose(rays[:, 2], torch.ones(500, dtype=F64))
    assert torch.allclose(rays, P / P[:, 2:], atol=1e-12)
