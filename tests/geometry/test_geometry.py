"""Tests for egobench.geometry: SO(3)/SE(3) maths and the Trajectory."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egobench.geometry import (
    Trajectory, check_pose, hat, make_pose, quat_multiply, quat_normalize, quat_to_rotmat,
    rotmat_to_quat, se3_exp, se3_interpolate, se3_inverse, se3_log, so3_exp, so3_log,
    transform_points,
)
from tests.helpers import SHARED_DATA

MPS_SAMPLE = SHARED_DATA / "aria_mps_sample"
F64 = torch.float64


def random_axes(n: int, gen: torch.Generator) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, dtype=F64, generator=gen), dim=-1)


def random_poses(n: int, gen: torch.Generator) -> torch.Tensor:
    omega = random_axes(n, gen) * torch.rand(n, 1, dtype=F64, generator=gen) * 3.0
    return make_pose(so3_exp(omega), torch.randn(n, 3, dtype=F64, generator=gen))


# ---------------------------------------------------------------------------------- so3 / se3
ANGLES = [0.0, 1e-12, 1e-7, 1e-4, 0.049, 0.051, 0.149, 0.151, 0.299, 0.301, 1.0, 2.5,
          math.pi - 1e-3, math.pi - 1e-7]


@pytest.mark.parametrize("angle", ANGLES)
def test_so3_exp_log_round_trip(angle):
    gen = torch.Generator().manual_seed(1)
    omega = random_axes(16, gen) * angle
    R = so3_exp(omega)
    # Independent reference: Rodrigues with the matrix exponential.
    R_ref = torch.linalg.matrix_exp(hat(omega))
    assert torch.allclose(R, R_ref, atol=1e-14, rtol=0)
    assert torch.allclose(so3_log(R), omega, atol=1e-12 if angle < 3 else 1e-6, rtol=0)


def test_so3_log_at_pi_is_a_valid_logarithm():
    gen = torch.Generator().manual_seed(2)
    omega = random_axes(32, gen) * math.pi
    R = so3_exp(omega)
    w = so3_log(R)
    assert torch.isfinite(w).all()
    assert torch.allclose(w.norm(dim=-1), torch.full((32,), math.pi, dtype=F64), atol=1e-7)
    assert torch.allclose(so3_exp(w), R, atol=1e-12)


@pytest.mark.parametrize("angle", ANGLES)
def test_se3_exp_log_round_trip(angle):
    gen = torch.Generator().manual_seed(3)
    xi = torch.cat([torch.randn(16, 3, dtype=F64, generator=gen), random_axes(16, gen) * angle], -1)
    T = se3_exp(xi)
    T_ref = torch.linalg.matrix_exp(
        torch.cat([torch.cat([hat(xi[:, 3:]), xi[:, :3, None]], -1), torch.zeros(16, 1, 4, dtype=F64)], -2)
    )
    assert torch.allclose(T, T_ref, atol=1e-13, rtol=0)
    tol = 1e-12 if angle < 3 else 1e-5
    assert torch.allclose(se3_log(T), xi, atol=tol, rtol=0)
    check_pose(T)


def test_se3_log_exp_round_trip_random_poses():
    gen = torch.Generator().manual_seed(4)
    T = random_poses(64, gen)
    assert torch.allclose(se3_exp(se3_log(T)), T, atol=1e-12)


def test_float32_is_accurate():
    gen = torch.Generator().manual_seed(5)
    for angle in [0.0, 1e-5, 0.29, 0.31, 2.0]:
        xi = torch.cat([torch.randn(8, 3, dtype=F64, generator=gen), random_axes(8, gen) * angle], -1)
        T32 = se3_exp(xi.float())
        assert torch.allclose(T32.double(), se3_exp(xi), atol=2e-6)
        assert torch.allclose(se3_log(se3_exp(xi).float()).double(), xi, atol=2e-5)


def test_quaternion_matrix_round_trip_and_product():
    gen = torch.Generator().manual_seed(6)
    q = quat_normalize(torch.randn(200, 4, dtype=F64, generator=gen))
    q = torch.where(q[:, :1] < 0, -q, q)
    R = quat_to_rotmat(q)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=F64).expand(200, 3, 3), atol=1e-14)
    assert torch.allclose(rotmat_to_quat(R), q, atol=1e-14)
    assert (rotmat_to_quat(R)[:, 0] >= 0).all()
    # Hamilton product matches matrix product.
    q2 = quat_normalize(torch.randn(200, 4, dtype=F64, generator=gen))
    assert torch.allclose(quat_to_rotmat(quat_multiply(q, q2)), R @ quat_to_rotmat(q2), atol=1e-14)
    # Known value: 90 deg about z maps x to y.
    qz = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=F64)
    assert torch.allclose(quat_to_rotmat(qz) @ torch.tensor([1.0, 0, 0], dtype=F64), torch.tensor([0, 1.0, 0], dtype=F64), atol=1e-15)
    # Rotations by ~pi (every Shepperd branch).
    for axis in torch.eye(3, dtype=F64):
        Rpi = so3_exp(axis * math.pi)
        assert torch.allclose(quat_to_rotmat(rotmat_to_quat(Rpi)), Rpi, atol=1e-14)


def test_gradcheck_se3_exp_and_so3_log():
    gen = torch.Generator().manual_seed(7)
    for angle in [0.0, 1e-3, 0.1, 1.0, 3.0]:
        xi = torch.cat([torch.randn(2, 3, dtype=F64, generator=gen), random_axes(2, gen) * angle], -1)
        torch.autograd.gradcheck(se3_exp, (xi.requires_grad_(),))
    for angle in [1e-3, 0.2, 1.5, math.pi - 1e-3]:
        omega = torch.tensor([[0.6, -0.48, 0.64]], dtype=F64) * angle  # unit axis
        R = so3_exp(omega).requires_grad_()
        torch.autograd.gradcheck(so3_log, (R,))
    # Gradients at exactly zero rotation are finite and correct (d log / d omega = I).
    w = torch.zeros(3, dtype=F64, requires_grad=True)
    J = torch.autograd.functional.jacobian(lambda x: so3_log(so3_exp(x)), w)
    assert torch.allclose(J, torch.eye(3, dtype=F64), atol=1e-12)


def test_inverse_transform_and_interpolate():
    gen = torch.Generator().manual_seed(8)
    T = random_poses(10, gen)
    eye = torch.eye(4, dtype=F64).expand(10, 4, 4)
    assert torch.allclose(T @ se3_inverse(T), eye, atol=1e-14)
    p = torch.randn(10, 5, 3, dtype=F64, generator=gen)
    ph = torch.cat([p, torch.ones(10, 5, 1, dtype=F64)], -1)
    assert torch.allclose(transform_points(T, p), (ph @ T.transpose(-1, -2))[..., :3], atol=1e-14)
    T1 = random_poses(10, gen)
    assert torch.allclose(se3_interpolate(T, T1, torch.zeros(10, dtype=F64)), T, atol=1e-14)
    assert torch.allclose(se3_interpolate(T, T1, torch.ones(10, dtype=F64)), T1, atol=1e-12)
    # Midpoint: applying the half step twice reaches T1.
    mid = se3_interpolate(T, T1, 0.5)
    assert torch.allclose(mid @ se3_inverse(T) @ mid, T1, atol=1e-12)


def test_interpolate_matches_sophus():
    sophus = pytest.importorskip("projectaria_tools.core.sophus", reason="projectaria_tools not importable")
    gen = torch.Generator().manual_seed(9)
    T0, T1 = random_poses(1, gen)[0], random_poses(1, gen)[0]
    ref = sophus.interpolate(sophus.SE3.from_matrix(T0.numpy()), sophus.SE3.from_matrix(T1.numpy()), 0.3)
    assert np.allclose(se3_interpolate(T0, T1, 0.3).numpy(), ref.to_matrix(), atol=1e-12)


def test_bad_inputs_raise_value_error():
    with pytest.raises(ValueError, match="zero-length"):
        quat_normalize(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="NaN"):
        quat_normalize(torch.tensor([1.0, float("nan"), 0, 0]))
    with pytest.raises(ValueError, match=r"\[\.\.\., 4\]"):
        quat_to_rotmat(torch.ones(3))
    with pytest.raises(ValueError, match=r"\[\.\.\., 6\]"):
        se3_exp(torch.zeros(5))
    with pytest.raises(ValueError, match=r"\[\.\.\., 4, 4\]"):
        se3_log(torch.eye(3))
    with pytest.raises(ValueError, match="my_pose.*NaN"):
        T = torch.eye(4, dtype=F64)
        T[0, 3] = float("nan")
        check_pose(T, "my_pose")
    with pytest.raises(ValueError, match="orthonormal"):
        check_pose(torch.diag(torch.tensor([2.0, 1, 1, 1], dtype=F64)))
    with pytest.raises(ValueError, match="determinant"):
        check_pose(torch.diag(torch.tensor([-1.0, 1, 1, 1], dtype=F64)))
    with pytest.raises(ValueError, match="last row"):
        T = torch.eye(4, dtype=F64)
        T[3, 0] = 1
        check_pose(T)


# ---------------------------------------------------------------------------------- Trajectory
def constant_twist_trajectory(n: int = 101, dt_ns: int = 1_000_000):
    """T(t) = T_start exp(t * twist): constant body twist (linear m/s, angular rad/s)."""
    twist = torch.tensor([0.8, -0.3, 0.5, 0.4, -1.1, 0.7], dtype=F64)  # (v_body, omega_body)
    T_start = make_pose(so3_exp(torch.tensor([0.3, 0.2, -0.1], dtype=F64)), torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    t0 = 5_000_000_000
    t_ns = t0 + dt_ns * torch.arange(n, dtype=torch.int64)
    t_s = (t_ns - t0).double() * 1e-9
    T = T_start @ se3_exp(t_s[:, None] * twist)
    return Trajectory(t_ns, T), twist, T_start, t0


def test_constant_twist_closed_form():
    traj, twist, T_start, t0 = constant_twist_trajectory()
    gen = torch.Generator().manual_seed(10)
    q_ns = traj.start_ns + (torch.rand(200, generator=gen, dtype=F64) * (traj.end_ns - traj.start_ns)).long()
    expected = T_start @ se3_exp(((q_ns - t0).double() * 1e-9)[:, None] * twist)
    assert torch.allclose(traj.pose(q_ns), expected, atol=1e-12)
    vel = traj.velocity(q_ns)
    assert torch.allclose(vel.angular_device, twist[3:].expand(200, 3), atol=1e-9)
    R = expected[:, :3, :3]
    assert torch.allclose(vel.linear_world, (R @ twist[:3])[..., :], atol=1e-9)
    # Finite difference of the interpolated positions agrees with linear_world.
    h = 1000
    mid = q_ns.clamp(traj.start_ns + h, traj.end_ns - h)
    fd = (traj.pose(mid + h)[:, :3, 3] - traj.pose(mid - h)[:, :3, 3]) / (2 * h * 1e-9)
    assert torch.allclose(fd, traj.velocity(mid).linear_world, atol=1e-6)
    assert traj.duration_s == pytest.approx(0.1)


def test_pose_exact_at_samples_and_input_types():
    gen = torch.Generator().manual_seed(11)
    T = random_poses(6, gen)
    t_ns = torch.tensor([0, 10, 25, 1_000, 1_001, 5_000_000_000], dtype=torch.int64)
    traj = Trajectory(t_ns, T)
    assert torch.equal(traj.pose(t_ns), T)
    assert torch.equal(traj.pose(np.array([25])), T[2:3])
    assert torch.equal(traj.pose(5_000_000_000), T[5:6])
    with pytest.raises(ValueError, match="integer nanoseconds"):
        traj.pose(1.5)


def test_out_of_range_message():
    traj, *_ = constant_twist_trajectory()
    with pytest.raises(ValueError, match=rf"t_ns={traj.end_ns + 1} outside the trajectory span \[{traj.start_ns}, {traj.end_ns}\] ns"):
        traj.pose(traj.end_ns + 1)
    with pytest.raises(ValueError, match="outside the trajectory span"):
        traj.velocity(torch.tensor([traj.start_ns - 1]))


def test_construction_rejects_bad_input():
    T = torch.eye(4, dtype=F64).expand(3, 4, 4).clone()
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(torch.tensor([0, 5, 5]), T)
    T_nan = T.clone()
    T_nan[1, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        Trajectory(torch.tensor([0, 1, 2]), T_nan)
    with pytest.raises(ValueError, match=r"\[M, 4, 4\]"):
        Trajectory(torch.tensor([0, 1, 2]), torch.zeros(3, 3, 3))
    with pytest.raises(ValueError, match="3 samples but"):
        Trajectory(torch.tensor([0, 1, 2]), T[:2])


def test_slice_and_transformed():
    traj, *_ = constant_twist_trajectory()
    sub = traj.slice(traj.start_ns + 2_500_000, traj.start_ns + 40_000_000)
    assert sub.start_ns == traj.start_ns + 2_500_000
    q = torch.arange(sub.start_ns, sub.end_ns + 1, 777_777)
    assert torch.allclose(sub.pose(q), traj.pose(q), atol=1e-13)
    with pytest.raises(ValueError, match="outside"):
        traj.slice(traj.start_ns - 1, traj.end_ns)
    G = make_pose(so3_exp(torch.tensor([0.0, 0.0, 1.0], dtype=F64)), torch.tensor([5.0, 0, 0], dtype=F64))
    moved = traj.transformed(G)
    assert torch.allclose(moved.pose(q), G @ traj.pose(q), atol=1e-12)
    # Angular velocity in the device frame does not depend on the world frame.
    assert torch.allclose(moved.velocity(q).angular_device, traj.velocity(q).angular_device, atol=1e-9)


def test_angular_speed():
    traj, twist, *_ = constant_twist_trajectory()
    speed = traj.angular_speed_deg_s()
    assert speed.shape == (len(traj) - 1,)
    assert np.allclose(speed, math.degrees(float(twist[3:].norm())), rtol=1e-9)
    assert np.allclose(traj.angular_speed_deg_s(stride=7), math.degrees(float(twist[3:].norm())), rtol=1e-9)


def test_mps_csv_round_trip(tmp_path):
    traj, twist, *_ = constant_twist_trajectory()
    path = tmp_path / "mps" / "closed_loop_trajectory.csv"
    traj.to_mps_csv(path)
    back = Trajectory.from_mps_csv(path)
    assert torch.equal(back.t_ns, traj.t_ns)
    assert torch.allclose(back.T_world_device, traj.T_world_device, atol=1e-14)
    import pandas as pd

    df = pd.read_csv(path)
    assert np.allclose(df[["angular_velocity_x_device", "angular_velocity_y_device", "angular_velocity_z_device"]], twist[3:].numpy(), atol=1e-9)
    assert np.allclose(df[[f"device_linear_velocity_{a}_device" for a in "xyz"]], twist[:3].numpy(), atol=1e-9)
    assert (df["gravity_z_world"] == -9.81).all() and (df["quality_score"] == 1).all()
    assert not list(path.parent.glob(".*tmp*"))  # atomic write left no temporary


def test_mps_csv_errors(tmp_path):
    traj, *_ = constant_twist_trajectory(n=5)
    good = tmp_path / "good.csv"
    traj.to_mps_csv(good)
    lines = good.read_text().splitlines()
    header = lines[0].split(",")
    # Missing column.
    p = tmp_path / "missing.csv"
    col = header.index("qw_world_device")
    p.write_text("\n".join(",".join(c for j, c in enumerate(l.split(",")) if j != col) for l in lines))
    with pytest.raises(ValueError, match=r"missing.csv.*qw_world_device"):
        Trajectory.from_mps_csv(p)
    # NaN on the 3rd data row (line 4), column tx.
    p = tmp_path / "nan.csv"
    rows = [l.split(",") for l in lines]
    rows[3][header.index("tx_world_device")] = "nan"
    p.write_text("\n".join(",".join(r) for r in rows))
    with pytest.raises(ValueError, match=r"nan.csv: line 4, column 'tx_world_device'"):
        Trajectory.from_mps_csv(p)
    # Non-increasing time on line 5.
    p = tmp_path / "time.csv"
    rows = [l.split(",") for l in lines]
    rows[4][1] = rows[3][1]
    p.write_text("\n".join(",".join(r) for r in rows))
    with pytest.raises(ValueError, match=r"time.csv: line 5, column 'tracking_timestamp_us'.*increasing"):
        Trajectory.from_mps_csv(p)
    # Extra columns are ignored.
    p = tmp_path / "extra.csv"
    p.write_text("\n".join(l + ("," + ("extra" if i == 0 else "1")) for i, l in enumerate(lines)))
    assert torch.allclose(Trajectory.from_mps_csv(p).T_world_device, traj.T_world_device, atol=1e-14)
    # Sub-microsecond timestamps cannot be written to MPS.
    bad = Trajectory(traj.t_ns + 1, traj.T_world_device)
    with pytest.raises(ValueError, match="microsecond"):
        bad.to_mps_csv(tmp_path / "x.csv")


@pytest.mark.skipif(not (MPS_SAMPLE / "closed_loop_trajectory.csv").is_file(), reason=f"real Aria MPS sample not present at {MPS_SAMPLE}")
def test_real_mps_trajectory_head_motion():
    traj = Trajectory.from_mps_csv(MPS_SAMPLE / "closed_loop_trajectory.csv")
    assert traj.duration_s == pytest.approx(11.4, abs=0.1)
    rate_hz = (len(traj) - 1) / traj.duration_s
    assert 900 < rate_hz < 1100
    speed = traj.angular_speed_deg_s()
    p50, p99 = np.percentile(speed, [50, 99])
    assert p50 == pytest.approx(27.0, abs=1.5)  # docs/paper-notes.md §4
    assert p99 == pytest.approx(77.0, abs=3.0)
    # Angular velocity of the interpolated trajectory agrees with MPS's own (device frame).
    import pandas as pd

    df = pd.read_csv(MPS_SAMPLE / "closed_loop_trajectory.csv", usecols=[f"angular_velocity_{a}_device" for a in "xyz"])
    omega_mps = torch.from_numpy(df.to_numpy()[:-1])
    omega = traj.velocity(traj.t_ns[:-1]).angular_device
    assert float((omega - omega_mps).norm(dim=-1).median()) < 0.05 * float(omega_mps.norm(dim=-1).median())
