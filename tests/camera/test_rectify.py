"""Tests for egobench.camera.rectify: analytic scenes, projectaria-tools agreement, look-up images."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from egobench.camera import Fisheye624, Rectification, default_pinhole_for
from egobench.geometry import so3_exp
from tests.helpers import ARIA_RGB_PARAMS_1408, real_rgb_calibration

F64 = torch.float64



@pytest.fixture(scope="module")
def fisheye() -> Fisheye624:
    return Fisheye624(torch.tensor(ARIA_RGB_PARAMS_1408, dtype=F64), 1408, 1408).scaled(0.25)  # 352 x 352


class Plane:
    """A textured plane: origin [3], in-plane unit axes e1, e2 [3] (camera frame, metres)."""

    def __init__(self) -> None:
        R = so3_exp(torch.tensor([0.25, -0.2, 0.1], dtype=F64))
        self.origin = torch.tensor([0.05, -0.03, 1.0], dtype=F64)
        self.e1, self.e2, self.normal = R[:, 0], R[:, 1], R[:, 2]

    def hit(self, rays: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rays [..., 3] from the camera centre -> plane coordinates [..., 2] and 3-D points."""
        s = (self.origin @ self.normal) / (rays @ self.normal)
        X = s[..., None] * rays
        d = X - self.origin
        return torch.stack([d @ self.e1, d @ self.e2], -1), X

    def point(self, ab: torch.Tensor) -> torch.Tensor:
        return self.origin + ab[..., :1] * self.e1 + ab[..., 1:] * self.e2


def render_fisheye(cam: Fisheye624, shade, supersample: int = 1) -> np.ndarray:
    """Image [H, W, C] of the plane seen by cam; shade(plane_coords [..., 2]) -> [..., C]."""
    plane = Plane()
    offs = (torch.arange(supersample, dtype=F64) + 0.5) / supersample - 0.5
    v, u = torch.meshgrid(torch.arange(cam.height, dtype=F64), torch.arange(cam.width, dtype=F64), indexing="ij")
    dv, du = torch.meshgrid(offs, offs, indexing="ij")
    pix = torch.stack([u[..., None, None] + du, v[..., None, None] + dv], -1)  # [H, W, s, s, 2]
    ab, _ = plane.hit(cam.unproject(pix))
    return shade(ab).mean(dim=(2, 3)).float().numpy()


def test_plane_coordinates_land_where_the_pinhole_projects(fisheye):
    """Rectify an image holding each pixel's plane coordinates; compare with the pinhole ray hit."""
    dst = default_pinhole_for(fisheye)
    rect = Rectification.build(fisheye, dst)
    img = render_fisheye(fisheye, lambda ab: ab)
    warped = torch.from_numpy(rect.warp(img)).double()
    ab_true, X = Plane().hit(dst.unproject(dst.pixel_grid(dtype=F64)))
    ok = rect.valid
    assert ok.float().mean() > 0.99
    # Convert the plane-coordinate error to pixels: re-project the warped plane point.
    uv_warped, _ = dst.project(Plane().point(warped))
    err_px = (uv_warped - dst.pixel_grid(dtype=F64))[ok].norm(dim=-1)
    assert float(err_px.median()) < 0.01
    assert float(err_px.max()) < 0.1
    assert torch.allclose(warped[ok], ab_true[ok], atol=1e-3)


def test_checkerboard_corners_subpixel(fisheye):
    cv2 = pytest.importorskip("cv2", reason="opencv not importable")
    square, n = 0.08, 8  # metres, squares per side (7 x 7 inner corners)

    def checker(ab):
        i, j = torch.floor(ab[..., 0] / square), torch.floor(ab[..., 1] / square)
        inside = (ab.abs() < n * square / 2).all(-1)
        white = ((i + j) % 2 == 0) | ~inside
        return white.double()[..., None]

    img = render_fisheye(fisheye, checker, supersample=3)
    dst = default_pinhole_for(fisheye)
    rect = Rectification.build(fisheye, dst)
    rectified = (rect.warp(img)[..., 0] * 255).round().astype(np.uint8)
    found, corners = cv2.findChessboardCorners(rectified, (n - 1, n - 1))
    assert found, "checkerboard not detected in the rectified image"
    corners = cv2.cornerSubPix(
        rectified, corners, (4, 4), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    ).reshape(-1, 2)
    k = torch.arange(1, n, dtype=F64) * square - n * square / 2
    grid = torch.stack(torch.meshgrid(k, k, indexing="xy"), -1).reshape(-1, 2)
    uv_true, valid = dst.project(Plane().point(grid))
    assert valid.all()
    # Match each detected corner to the nearest true one (detection order is not fixed).
    d = torch.cdist(torch.from_numpy(corners).double(), uv_true)
    err = d.min(dim=1).values
    assert len(set(d.argmin(dim=1).tolist())) == (n - 1) ** 2
    # cornerSubPix itself is good to ~0.1 px here; a half-pixel convention error would fail.
    assert float(err.mean()) < 0.15 and float(err.max()) < 0.3, err


def test_map_is_consistent_with_the_models(fisheye):
    R = so3_exp(torch.tensor([0.05, -0.1, 0.02], dtype=F64))
    dst = default_pinhole_for(fisheye, 120, 100, 60.0)
    rect = Rectification.build(fisheye, dst, R)
    assert rect.map_uv.dtype == torch.float32 and rect.map_uv.shape == (100, 120, 2)
    rays_src = fisheye.unproject(rect.map_uv.double())
    rays_dst = torch.nn.functional.normalize(dst.unproject(dst.pixel_grid(dtype=F64)), dim=-1)
    assert torch.allclose(rays_src[rect.valid], (rays_dst @ R.T)[rect.valid], atol=2e-6)  # float32 map


def test_valid_mask_inside_source_image(fisheye):
    # A very wide pinhole sees beyond the fisheye image: those pixels are invalid and zero.
    dst = default_pinhole_for(fisheye, 200, 200, 30.0)
    rect = Rectification.build(fisheye, dst)
    assert 0.1 < rect.valid.float().mean() < 0.95
    u, v = rect.map_uv[..., 0], rect.map_uv[..., 1]
    assert ((u >= 0) & (u <= fisheye.width - 1) & (v >= 0) & (v <= fisheye.height - 1))[rect.valid].all()
    out = rect.warp(torch.ones(fisheye.height, fisheye.width, 3))
    assert (out[~rect.valid] == 0).all() and torch.allclose(out[rect.valid], torch.ones(1))
    # The invalid pixels really project outside the source image.
    uv, _ = fisheye.project(dst.unproject(dst.pixel_grid(dtype=F64)))
    outside = (uv < 0).any(-1) | (uv[..., 0] > fisheye.width - 1) | (uv[..., 1] > fisheye.height - 1)
    assert torch.equal(outside, ~rect.valid)


def test_row_time_ratio_and_vignette(fisheye):
    dst = default_pinhole_for(fisheye, 160, 160, 80.0)
    rect = Rectification.build(fisheye, dst)
    ratio = rect.row_time_ratio()
    assert ratio.dtype == torch.float32 and ratio.shape == (160, 160)
    assert float(ratio.min()) >= 0 and float(ratio.max()) <= 1
    assert (ratio[~rect.valid] == 0).all()
    # Continuous (not 8-bit) and increasing down every column inside the valid region.
    both = rect.valid[1:] & rect.valid[:-1]
    assert (ratio[1:] - ratio[:-1])[both].min() > 0
    assert len(torch.unique(ratio[rect.valid])) > 1000
    # Equals the rectified source-row image.
    rows = torch.arange(fisheye.height, dtype=torch.float32)[:, None].expand(fisheye.height, fisheye.width)
    assert torch.allclose(rect.warp(rows / (fisheye.height - 1)), ratio, atol=1e-5)
    # A radial vignette is resampled bilinearly; values stay in [0, 1].
    v, u = torch.meshgrid(torch.arange(352.0), torch.arange(352.0), indexing="ij")
    vig = 1 - 0.5 * (((u - fisheye.cx) ** 2 + (v - fisheye.cy) ** 2) / 352.0**2)
    out = rect.warp_vignette(vig)
    assert out.shape == (160, 160) and float(out.max()) <= 1 and float(out[rect.valid].min()) > 0.4
    centre = rect.map_uv[80, 80]
    expected = 1 - 0.5 * (((centre[0] - fisheye.cx) ** 2 + (centre[1] - fisheye.cy) ** 2) / 352.0**2)
    assert float(out[80, 80]) == pytest.approx(float(expected), abs=1e-4)


def test_nearest_preserves_labels_and_batches(fisheye):
    dst = default_pinhole_for(fisheye, 100, 100, 50.0)
    rect = Rectification.build(fisheye, dst)
    labels = np.arange(352 * 352, dtype=np.int64).reshape(352, 352, 1) * 1_000_003  # beyond float32 precision
    out = rect.warp(labels, mode="nearest")
    assert out.dtype == np.int64 and out.shape == (100, 100, 1)
    valid = rect.valid.numpy()
    assert np.isin(out[valid], labels).all()
    iu, iv = np.rint(rect.map_uv.numpy()[..., 0]).astype(int), np.rint(rect.map_uv.numpy()[..., 1]).astype(int)
    assert (out[..., 0][valid] == labels[iv[valid], iu[valid], 0]).all()
    # Batched warp equals per-image warp.
    imgs = torch.rand(2, 352, 352, 3, generator=torch.Generator().manual_seed(0))
    batched = rect.warp(imgs)
    assert batched.shape == (2, 100, 100, 3)
    assert torch.allclose(batched[1], rect.warp(imgs[1]))


def test_bad_input(fisheye):
    rect = Rectification.build(fisheye, default_pinhole_for(fisheye, 40, 40, 20.0))
    with pytest.raises(ValueError, match="H_s, W_s = 352, 352"):
        rect.warp(np.zeros((100, 100, 3), np.float32))
    with pytest.raises(ValueError, match="mode"):
        rect.warp(np.zeros((352, 352, 3), np.float32), mode="cubic")
    with pytest.raises(ValueError, match="float image"):
        rect.warp(np.zeros((352, 352, 1), np.int32))
    with pytest.raises(ValueError, match="R_src_dst"):
        Rectification.build(fisheye, default_pinhole_for(fisheye), torch.eye(3) * 2)
    with pytest.raises(ValueError, match="Pinhole"):
        Rectification.build(fisheye, fisheye)


def test_default_pinhole_matches_paper():
    src = Fisheye624(torch.tensor(ARIA_RGB_PARAMS_1408, dtype=F64), 1408, 1408)
    big = Fisheye624(src.params, 2880, 2880)
    cam = default_pinhole_for(big)
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx) == (2400, 2400, 1200.0, 1200.0, 1199.5)


def test_matches_projectaria_distort_by_calibration():
    calibration = pytest.importorskip("projectaria_tools.core.calibration", reason="projectaria_tools not importable")
    image = pytest.importorskip("projectaria_tools.core.image", reason="projectaria_tools not importable")
    entry, size, ref_full = real_rgb_calibration()
    src = Fisheye624.from_mps_json(entry, size).scaled(0.25)
    ref_src = ref_full.rescale(np.array([src.width, src.height]), 0.25)
    v, u = np.mgrid[0 : src.height, 0 : src.width].astype(np.float32)
    img = (0.55 + 0.4 * np.sin(u / 9.0) * np.cos(v / 13.0)).astype(np.float32)  # smooth, > 0
    for dst in (default_pinhole_for(src), default_pinhole_for(src, 240, 240, 60.0)):
        ref_dst = calibration.get_linear_camera_calibration(dst.width, dst.height, dst.fx)
        assert np.allclose(ref_dst.get_principal_point(), [dst.cx, dst.cy])
        rect = Rectification.build(src, dst)
        ours = rect.warp(img)
        ref = calibration.distort_by_calibration(img, ref_dst, ref_src)
        ref_valid = ref > 0
        both = rect.valid.numpy() & ref_valid
        # Valid regions agree up to a border pixel ring.
        assert (rect.valid.numpy() != ref_valid).mean() < 0.01
        assert np.abs(ours - ref)[both].mean() < 1e-5
        assert np.abs(ours - ref)[both].max() < 1e-3
        labels = np.arange(src.width * src.height, dtype=np.float32).reshape(src.height, src.width)
        ref_nn = calibration.distort_by_calibration(labels, ref_dst, ref_src, image.InterpolationMethod.NEAREST_NEIGHBOR)
        assert (rect.warp(labels, mode="nearest") == ref_nn)[both].mean() > 0.999  # ties at .5 may round apart
