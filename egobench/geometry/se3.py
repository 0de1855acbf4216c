"""Batched, differentiable SO(3)/SE(3) maths in torch.

Conventions: quaternions are (w, x, y, z); a pose ``T_a_b`` is a [..., 4, 4] matrix mapping
b-coordinates to a-coordinates; a twist ``xi = (rho, omega)`` has the translational part first,
``se3_exp(xi) = [[exp(omega^), V(omega) rho], [0, 1]]`` (Sophus / Barfoot convention).
Small-angle series are used below a dtype-dependent threshold so that values and gradients are
finite at (and accurate near) zero rotation; ``so3_log`` goes through a Shepperd quaternion so
it is stable up to a rotation of pi.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from egobench import portable_math as pm

__all__ = [
    "quat_normalize", "quat_to_rotmat", "rotmat_to_quat", "quat_multiply", "quat_conjugate",
    "hat", "so3_exp", "so3_log", "se3_exp", "se3_log", "se3_inverse", "make_pose",
    "transform_points", "se3_interpolate", "check_pose",
]


def _small_threshold(dtype: torch.dtype) -> float:
    """Squared angle below which the series expansions are used."""
    return 0.05**2 if dtype == torch.float64 else 0.3**2


def _check_last(x: Tensor, size: int, name: str, what: str) -> None:
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape {what}, got {type(x).__name__}")
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(f"{name}: expected shape {what}, got {tuple(x.shape)}")


def _quat_norm(q: Tensor) -> Tensor:
    """|q| [..., 1] of quaternions [..., 4]: squares added in index order, a correctly rounded square root on the CPU
    (`portable_math.sqrt`: the same bits on every x86-64 machine)."""
    return pm.sqrt(pm.vecdot(q, q))[..., None]


def quat_normalize(q: Tensor, name: str = "quats") -> Tensor:
    """q [..., 4] (w, x, y, z) -> unit quaternions; ValueError on zero or non-finite entries."""
    _check_last(q, 4, name, "[..., 4] (w, x, y, z)")
    if not bool(torch.isfinite(q).all()):
        raise ValueError(f"{name}: quaternions contain NaN or infinite values")
    norm = _quat_norm(q)
    if bool((norm < 1e-12).any()):
        raise ValueError(f"{name}: zero-length quaternion cannot be normalised")
    return q / norm


def quat_conjugate(q: Tensor) -> Tensor:
    """q [..., 4] -> conjugate [..., 4] (the inverse for unit quaternions)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product q1 * q2, both [..., 4] (w, x, y, z), broadcast."""
    _check_last(q1, 4, "q1", "[..., 4]")
    _check_last(q2, 4, "q2", "[..., 4]")
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quat_to_rotmat(q: Tensor) -> Tensor:
    """q [..., 4] (w, x, y, z), normalised here -> R [..., 3, 3]."""
    w, x, y, z = quat_normalize(q, "quat_to_rotmat(q)").unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(*q.shape[:-1], 3, 3)


def _check_rotmat(R: Tensor, name: str) -> None:
    if not isinstance(R, Tensor) or R.ndim < 2 or R.shape[-2:] != (3, 3):
        shape = tuple(R.shape) if isinstance(R, Tensor) else type(R).__name__
        raise ValueError(f"{name}: expected rotation matrices of shape [..., 3, 3], got {shape}")
    if not bool(torch.isfinite(R).all()):
        raise ValueError(f"{name}: rotation matrices contain NaN or infinite values")


def rotmat_to_quat(R: Tensor) -> Tensor:
    """R [..., 3, 3] -> unit quaternion [..., 4] (w, x, y, z) with w >= 0 (Shepperd's method)."""
    _check_rotmat(R, "rotmat_to_quat(R)")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tiny = torch.finfo(R.dtype).tiny
    # Four candidate forms; each is well conditioned when its pivot is the largest.
    s0 = 2.0 * pm.sqrt((1.0 + m00 + m11 + m22).clamp_min(tiny))  # s = 4w
    s1 = 2.0 * pm.sqrt((1.0 + m00 - m11 - m22).clamp_min(tiny))  # s = 4x
    s2 = 2.0 * pm.sqrt((1.0 - m00 + m11 - m22).clamp_min(tiny))  # s = 4y
    s3 = 2.0 * pm.sqrt((1.0 - m00 - m11 + m22).clamp_min(tiny))  # s = 4z
    q0 = torch.stack([0.25 * s0, (m21 - m12) / s0, (m02 - m20) / s0, (m10 - m01) / s0], -1)
    q1 = torch.stack([(m21 - m12) / s1, 0.25 * s1, (m01 + m10) / s1, (m02 + m20) / s1], -1)
    q2 = torch.stack([(m02 - m20) / s2, (m01 + m10) / s2, 0.25 * s2, (m12 + m21) / s2], -1)
    q3 = torch.stack([(m10 - m01) / s3, (m02 + m20) / s3, (m12 + m21) / s3, 0.25 * s3], -1)
    pivots = torch.stack([m00 + m11 + m22, m00, m11, m22], -1)
    choice = pivots.argmax(-1)
    cands = torch.stack([q0, q1, q2, q3], -2)  # [..., 4 candidates, 4]
    q = torch.gather(cands, -2, choice[..., None, None].expand(*choice.shape, 1, 4)).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q / _quat_norm(q)


def hat(omega: Tensor) -> Tensor:
    """omega [..., 3] -> skew-symmetric [..., 3, 3] with hat(a) b = a x b."""
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*omega.shape[:-1], 3, 3)


def _so3_coeffs(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 (all [...]) from t^2."""
    small = theta2 < _small_threshold(theta2.dtype)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)  # safe value for the direct branch
    t = pm.sqrt(t2)
    s, c = pm.sin(t), pm.cos(t)
    A_direct, B_direct, C_direct = s / t, (1 - c) / t2, (t - s) / (t2 * t)
    x = theta2
    A_series = 1 - x / 6 * (1 - x / 20 * (1 - x / 42 * (1 - x / 72)))
    B_series = 0.5 * (1 - x / 12 * (1 - x / 30 * (1 - x / 56 * (1 - x / 90))))
    C_series = (1 - x / 20 * (1 - x / 42 * (1 - x / 72 * (1 - x / 110)))) / 6
    return (
        torch.where(small, A_series, A_direct),
        torch.where(small, B_series, B_direct),
        torch.where(small, C_series, C_direct),
    )


def so3_exp(omega: Tensor) -> Tensor:
    """Rotation vector omega [..., 3] (radians) -> R [..., 3, 3] (Rodrigues)."""
    _check_last(omega, 3, "so3_exp(omega)", "[..., 3]")
    theta2 = pm.vecdot(omega, omega)
    A, B, _ = _so3_coeffs(theta2)
    K = hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + A[..., None, None] * K + B[..., None, None] * pm.matmul(K, K)


def so3_log(R: Tensor) -> Tensor:
    """R [..., 3, 3] -> rotation vector [..., 3] with norm in [0, pi] (via the quaternion)."""
    q = rotmat_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = pm.vecdot(v, v)
    small = n2 < (1e-6 if q.dtype == torch.float64 else 1e-4)
    n = pm.sqrt(torch.where(small, torch.ones_like(n2), n2))
    direct = 2.0 * pm.atan2(n, w) / n
    ws = torch.where(small, w, torch.ones_like(w))  # w ~ 1 where small
    x2 = n2 / (ws * ws)
    series = 2.0 / ws * (1 - x2 / 3 + x2 * x2 / 5)  # 2 atan(n / w) / n
    return torch.where(small, series, direct)[..., None] * v


def _check_pose_shape(T: Tensor, name: str) -> None:
    if not isinstance(T, Tensor) or T.ndim < 2 or T.shape[-2:] != (4, 4):
        shape = tuple(T.shape) if isinstance(T, Tensor) else type(T).__name__
        raise ValueError(f"{name}: expected poses of shape [..., 4, 4], got {shape}")


def se3_exp(xi: Tensor) -> Tensor:
    """Twist xi [..., 6] = (rho, omega) -> T [..., 4, 4] = [[exp(omega^), V rho], [0, 1]]."""
    _check_last(xi, 6, "se3_exp(xi)", "[..., 6] (rho, omega)")
    rho, omega = xi[..., :3], xi[..., 3:]
    theta2 = pm.vecdot(omega, omega)
    A, B, C = _so3_coeffs(theta2)
    K = hat(omega)
    K2 = pm.matmul(K, K)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(K)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    V = eye + B[..., None, None] * K + C[..., None, None] * K2
    t = pm.vecdot(V, rho[..., None, :])
    return make_pose(R, t)


def se3_log(T: Tensor) -> Tensor:
    """T [..., 4, 4] -> twist [..., 6] = (rho, omega), |omega| in [0, pi]."""
    _check_pose_shape(T, "se3_log(T)")
    R, t = T[..., :3, :3], T[..., :3, 3]
    omega = so3_log(R)
    theta2 = pm.vecdot(omega, omega)
    # D = (1 - A / (2B)) / theta^2 cancels badly for small angles: series below 0.15 rad (float64).
    small = theta2 < (0.15**2 if theta2.dtype == torch.float64 else _small_threshold(theta2.dtype))
    A, B, _ = _so3_coeffs(theta2)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    D_direct = (1 - A / (2 * B)) / t2
    x = theta2
    x2 = x * x
    D_series = 1 / 12 + x / 720 + x2 / 30240 + x2 * x / 1209600 + x2 * x2 / 47900160
    D = torch.where(small, D_series, D_direct)
    K = hat(omega)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(K)
    V_inv = eye - 0.5 * K + D[..., None, None] * pm.matmul(K, K)
    rho = pm.vecdot(V_inv, t[..., None, :])
    return torch.cat([rho, omega], -1)


def det3(M: Tensor) -> Tensor:
    """Determinants of [..., 3, 3] matrices by cofactors (elementwise; ``torch.linalg.det`` runs an LU in MKL)."""
    return (M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
            - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
            + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0]))


def make_pose(R: Tensor, t: Tensor) -> Tensor:
    """R [..., 3, 3], t [..., 3] -> T [..., 4, 4] (broadcast over the batch dims)."""
    _check_rotmat(R, "make_pose(R)")
    _check_last(t, 3, "make_pose(t)", "[..., 3]")
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])  # (torch's first call imports sympy: 0.4 s)
    top = torch.cat([R.expand(*batch, 3, 3), t.expand(*batch, 3)[..., None]], -1)
    bottom = torch.zeros(*batch, 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def se3_inverse(T: Tensor) -> Tensor:
    """T [..., 4, 4] -> T^-1 [..., 4, 4] (closed form)."""
    _check_pose_shape(T, "se3_inverse(T)")
    Rt = T[..., :3, :3].transpose(-1, -2)
    return make_pose(Rt, -pm.vecdot(Rt, T[..., None, :3, 3]))


def transform_points(T: Tensor, p: Tensor) -> Tensor:
    """T [..., 4, 4] applied to points p [..., N, 3] -> [..., N, 3]."""
    _check_pose_shape(T, "transform_points(T)")
    _check_last(p, 3, "transform_points(p)", "[..., N, 3]")
    return pm.matmul(p, T[..., :3, :3].transpose(-1, -2)) + T[..., None, :3, 3]


def se3_interpolate(T0: Tensor, T1: Tensor, alpha: Tensor | float) -> Tensor:
    """Geodesic interpolation T0 exp(alpha log(T0^-1 T1)); T0, T1 [..., 4, 4], alpha [...]."""
    _check_pose_shape(T0, "se3_interpolate(T0)")
    _check_pose_shape(T1, "se3_interpolate(T1)")
    alpha = torch.as_tensor(alpha, dtype=T0.dtype, device=T0.device)
    xi = se3_log(se3_inverse(T0) @ T1)
    return T0 @ se3_exp(alpha[..., None] * xi)


def check_pose(T: Tensor, name: str = "pose", atol: float | None = None) -> Tensor:
    """Return T unchanged or raise ValueError: shape [..., 4, 4], finite, orthonormal R, det +1.

    ``atol`` bounds max |R^T R - I| and the last-row error (default 1e-6 for float64, 1e-4 else).
    """
    _check_pose_shape(T, name)
    if not bool(torch.isfinite(T).all()):
        bad = (~torch.isfinite(T)).flatten(-2).any(-1).nonzero()
        raise ValueError(f"{name}: pose contains NaN or infinite values (first at batch index {bad[0].tolist()})")
    if atol is None:
        atol = 1e-6 if T.dtype == torch.float64 else 1e-4
    R = T[..., :3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    ortho_err = (pm.matmul(R.transpose(-1, -2), R) - eye).abs().amax(dim=(-1, -2))
    if bool((ortho_err > atol).any()):
        raise ValueError(
            f"{name}: rotation part is not orthonormal (max |R^T R - I| = {float(ortho_err.max()):.3g} > {atol:g})"
        )
    if bool((det3(R) <= 0).any()):
        raise ValueError(f"{name}: rotation part has negative determinant (a reflection, not a rotation)")
    last = T[..., 3, :] - T.new_tensor([0.0, 0.0, 0.0, 1.0])
    if bool((last.abs() > atol).any()):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    return T
