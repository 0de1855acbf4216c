"""Aria's fisheye camera: FisheyeRadTanThinPrism ("Fisheye624"), as in projectaria-tools.

Params (15, float64): ``f, cx, cy, k0..k5, p0, p1, s0..s3`` (single focal length, pixels).
For a camera-frame point (x, y, z), with ``r = |(x, y)|`` and ``theta = atan2(r, z)``:

    th_d      = theta (1 + k0 th^2 + k1 th^4 + ... + k5 th^12)         (radial, on the angle)
    (a, b)    = th_d * (x, y) / r                                       (radially distorted)
    rr        = a^2 + b^2
    a'        = a + 2 a (p0 a + p1 b) + p0 rr + s0 rr + s1 rr^2         (tangential + thin prism)
    b'        = b + 2 b (p0 a + p1 b) + p1 rr + s2 rr + s3 rr^2
    (u, v)    = f (a', b') + (cx, cy)

Pixel centres are at integer coordinates (projectaria convention). Unprojection inverts the
tangential/thin-prism map by 2-D Newton iterations, then the radial polynomial by 1-D Newton,
in float64; a last Newton step carries the (implicit-function) gradient.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from egobench import portable_math as pm
from egobench.camera.base import check_pixels, check_points, scaled_size

#: Number of parameters of FisheyeRadTanThinPrism.
NUM_PARAMS = 15
#: projectaria-tools' model name in calibration JSON.
MPS_MODEL_NAME = "FisheyeRadTanThinPrism"
PARAM_NAMES = ("f", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")


def _solve2x2(J: Tensor, b: Tensor) -> Tensor:
    """Solve J x = b for batched 2x2 J [..., 2, 2], b [..., 2] (closed form; J near identity here)."""
    a, bb, c, d = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
    det = a * d - bb * c
    det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    return torch.stack([(d * b[..., 0] - bb * b[..., 1]) / det, (a * b[..., 1] - c * b[..., 0]) / det], -1)


class Fisheye624:
    """FisheyeRadTanThinPrism camera of ``width`` x ``height`` pixels with ``params`` [15] float64."""

    #: Newton iterations of unproject (at most; stops early when all steps are < 1e-14; convergence
    #: is checked afterwards on the residuals).
    newton_iterations: int = 20
    #: Converged when the distortion residual is below this (normalised image units).
    newton_tolerance: float = 1e-10

    def __init__(self, params, width: int, height: int) -> None:
        p = torch.as_tensor(params, dtype=torch.float64)
        if p.shape != (NUM_PARAMS,):
            raise ValueError(
                f"Fisheye624(params): expected {NUM_PARAMS} values {list(PARAM_NAMES)}, got shape {tuple(p.shape)}"
            )
        if not bool(torch.isfinite(p).all()):
            raise ValueError("Fisheye624(params): parameters contain NaN or infinite values")
        if not float(p[0]) > 0:
            raise ValueError(f"Fisheye624(params): focal length f = params[0] must be > 0, got {float(p[0])}")
        for name, value in (("width", width), ("height", height)):
            if int(value) != value or value <= 0:
                raise ValueError(f"Fisheye624.{name}: expected a positive integer, got {value}")
        self.params: Tensor = p  # [15] float64
        self.width = int(width)
        self.height = int(height)
        self.theta_max = self._monotone_theta_max()

    # ---- parameters ---------------------------------------------------------------------------
    @property
    def f(self) -> float:
        return float(self.params[0])

    @property
    def cx(self) -> float:
        return float(self.params[1])

    @property
    def cy(self) -> float:
        return float(self.params[2])

    def __repr__(self) -> str:
        return f"Fisheye624(f={self.f:.3f}, cx={self.cx:.3f}, cy={self.cy:.3f}, {self.width}x{self.height})"

    def _monotone_theta_max(self) -> float:
        """Largest angle (rad, <= pi) up to which th_d(theta) increases (the model is invertible)."""
        theta = torch.linspace(0.0, math.pi, 20001, dtype=torch.float64)
        k = self.params[3:9]
        powers = theta[:, None] ** (2 * torch.arange(1, 7, dtype=torch.float64))  # th^2 .. th^12
        deriv = 1 + (powers * k * (2 * torch.arange(1, 7, dtype=torch.float64) + 1)).sum(-1)
        bad = (deriv <= 0).nonzero()
        return float(theta[bad[0, 0] - 1]) if bad.numel() else math.pi

    @classmethod
    def from_mps_json(cls, camera_calibration: dict, image_size: Sequence[int]) -> "Fisheye624":
        """From one ``CameraCalibrations`` entry of MPS/Aria calibration JSON; image_size = (width, height)."""
        if not isinstance(camera_calibration, dict):
            raise ValueError(f"Fisheye624.from_mps_json: expected a dict (a CameraCalibrations entry), got {type(camera_calibration).__name__}")
        label = camera_calibration.get("Label", "?")
        proj = camera_calibration.get("Projection")
        if not isinstance(proj, dict) or "Params" not in proj:
            raise ValueError(f"Fisheye624.from_mps_json: camera {label!r} has no Projection.Params field")
        name = proj.get("Name", MPS_MODEL_NAME)
        if name != MPS_MODEL_NAME:
            raise ValueError(f"Fisheye624.from_mps_json: camera {label!r} has Projection.Name {name!r}, expected {MPS_MODEL_NAME!r}")
        params = proj["Params"]
        if not isinstance(params, (list, tuple)) or len(params) != NUM_PARAMS:
            raise ValueError(f"Fisheye624.from_mps_json: camera {label!r} Projection.Params must hold {NUM_PARAMS} numbers")
        if len(image_size) != 2:
            raise ValueError(f"Fisheye624.from_mps_json(image_size): expected (width, height), got {image_size!r}")
        return cls(torch.tensor([float(x) for x in params], dtype=torch.float64), int(image_size[0]), int(image_size[1]))

    def to_mps_params(self) -> list[float]:
        """The 15 parameters as MPS writes them (Projection.Params)."""
        return [float(x) for x in self.params]

    def scaled(self, factor: float) -> "Fisheye624":
        """The same lens at ``factor`` times the resolution: f, cx, cy scale (pixel-centre convention)."""
        w, h, sx, sy = scaled_size(self.width, self.height, factor, "Fisheye624")
        if abs(sx - sy) > 1e-9 * max(sx, sy):
            raise ValueError(
                f"Fisheye624.scaled(factor): factor {factor} rounds {self.width}x{self.height} to {w}x{h}, "
                "which changes the aspect ratio (a single-focal model cannot represent it)"
            )
        p = self.params.clone()
        p[0] = p[0] * sx
        p[1] = (p[1] + 0.5) * sx - 0.5
        p[2] = (p[2] + 0.5) * sy - 0.5
        return Fisheye624(p, w, h)

    # ---- model -----------------------------------------------------------------------------------
    def _params(self, device: torch.device) -> tuple[Tensor, ...]:
        p = self.params.to(device)
        return p[0], p[1:3], p[3:9], p[9:11], p[11:15]

    @staticmethod
    def _tangential_prism(ab: Tensor, pt: Tensor, s: Tensor) -> Tensor:
        """Radially distorted (a, b) [..., 2] -> with tangential and thin-prism terms [..., 2]."""
        rr = (ab * ab).sum(-1, keepdim=True)
        dot2 = 2 * (ab * pt).sum(-1, keepdim=True)
        out = ab + dot2 * ab + rr * pt
        prism = torch.stack([s[0] * rr[..., 0] + s[1] * rr[..., 0] ** 2, s[2] * rr[..., 0] + s[3] * rr[..., 0] ** 2], -1)
        return out + prism

    @staticmethod
    def _tangential_prism_jacobian(ab: Tensor, pt: Tensor, s: Tensor) -> Tensor:
        """d(_tangential_prism)/d(a, b) [..., 2, 2]."""
        a, b = ab[..., 0], ab[..., 1]
        rr = a * a + b * b
        p0, p1 = pt[0], pt[1]
        gx = 2 * (s[0] + 2 * s[1] * rr)
        gy = 2 * (s[2] + 2 * s[3] * rr)
        j00 = 1 + 6 * p0 * a + 2 * p1 * b + gx * a
        j01 = 2 * p1 * a + 2 * p0 * b + gx * b
        j10 = 2 * p0 * b + 2 * p1 * a + gy * a
        j11 = 1 + 2 * p0 * a + 6 * p1 * b + gy * b
        return torch.stack([torch.stack([j00, j01], -1), torch.stack([j10, j11], -1)], -2)

    @staticmethod
    def _radial(theta: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        """theta [...] -> (th_d, d th_d / d theta), both [...]."""
        th2 = theta * theta
        poly = torch.zeros_like(theta)
        dpoly = torch.zeros_like(theta)
        for i in range(5, -1, -1):  # Horner over the 6 coefficients (k_i th^(2i+2))
            poly = (poly + k[i]) * th2
            dpoly = dpoly * th2 + (2 * i + 3) * k[i]
        return theta * (1 + poly), 1 + dpoly * th2

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """points_cam [..., 3] -> (pixels [..., 2], valid [...]: theta within the invertible range)."""
        check_points(points_cam, "Fisheye624.project")
        f, c, k, pt, s = self._params(points_cam.device)
        P = points_cam.to(torch.float64)
        xy = P[..., :2]
        r2 = (xy * xy).sum(-1)
        nonzero = r2 > 0
        r = pm.sqrt(torch.where(nonzero, r2, torch.ones_like(r2)))
        theta = pm.atan2(r, P[..., 2])
        th_d, _ = self._radial(theta, k)
        # th_d / r -> 1 / z on the axis (where xy = 0 anyway).
        z_safe = torch.where(P[..., 2] != 0, P[..., 2], torch.ones_like(r))
        scale = torch.where(nonzero, th_d / r, 1.0 / z_safe)
        ab = scale[..., None] * xy
        uv = f * self._tangential_prism(ab, pt, s) + c
        valid = (theta < self.theta_max) & torch.isfinite(P).all(-1) & ((r2 > 0) | (P[..., 2] > 0))
        dtype = points_cam.dtype if points_cam.dtype.is_floating_point else torch.float64
        return uv.to(dtype), valid

    def unproject_checked(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """pixels [..., 2] -> (unit rays [..., 3], converged [...] bool)."""
        check_pixels(pixels, "Fisheye624.unproject")
        f, c, k, pt, s = self._params(pixels.device)
        target = (pixels.to(torch.float64) - c) / f  # [..., 2] distorted normalised coordinates
        th_max = torch.tensor(self.theta_max, dtype=torch.float64, device=pixels.device)
        with torch.no_grad():
            ab = target.detach().clone()
            for _ in range(self.newton_iterations):  # stops early once every step is negligible
                res = self._tangential_prism(ab, pt, s) - target
                step = _solve2x2(self._tangential_prism_jacobian(ab, pt, s), res)
                ab = ab - step
                if step.numel() == 0 or float(step.abs().max()) < 1e-14:
                    break
            th_d = ab.norm(dim=-1)
            theta = th_d.clamp(max=float(th_max))
            for _ in range(self.newton_iterations):
                g, dg = self._radial(theta, k)
                new_theta = (theta - (g - th_d) / dg).clamp(0.0, float(th_max))
                change = (new_theta - theta).abs()
                theta = new_theta
                if change.numel() == 0 or float(change.max()) < 1e-14:
                    break
        # One more Newton step with autograd: exact first-order (implicit) gradients.
        ab0, theta0 = ab.detach(), theta.detach()
        res = self._tangential_prism(ab0, pt, s) - target
        J = self._tangential_prism_jacobian(ab0, pt, s)
        ab = ab0 - _solve2x2(J, res)
        th_d = pm.sqrt((ab * ab).sum(-1).clamp_min(1e-300))
        g, dg = self._radial(theta0, k)
        theta = theta0 - (g - th_d) / dg
        with torch.no_grad():
            res_ab = (self._tangential_prism(ab, pt, s) - target).norm(dim=-1)
            res_th = (self._radial(theta, k)[0] - th_d).abs()
            converged = (res_ab < self.newton_tolerance) & (res_th < self.newton_tolerance) & (theta <= th_max)
            converged &= torch.isfinite(ab).all(-1) & torch.isfinite(theta)
        direction = ab / th_d[..., None]
        on_axis = (ab * ab).sum(-1) == 0
        direction = torch.where(on_axis[..., None], torch.zeros_like(direction), direction)
        rays = torch.cat([pm.sin(theta)[..., None] * direction, pm.cos(theta)[..., None]], -1)
        rays = torch.nan_to_num(rays, nan=0.0)  # a non-converged pixel is flagged, never NaN
        dtype = pixels.dtype if pixels.dtype.is_floating_point else torch.float64
        return rays.to(dtype), converged

    def unproject(self, pixels: Tensor) -> Tensor:
        """pixels [..., 2] -> unit rays [..., 3] (see unproject_checked for the convergence mask)."""
        return self.unproject_checked(pixels)[0]
