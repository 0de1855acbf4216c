"""Motion sampling: sample counts against analytic pixel motion, bracket times, R(u) index rule."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from egobench.camera.pinhole import Pinhole
from egobench.data.recording import Frame, Recording, SparseDepth
from egobench.model.motion_sampling import (
    MOTION_WINDOW_S, estimate_motion, exposure_pose_samples, frame_twist_camera, n_pose_samples,
    pixel_pose_index, pose_samples, sample_times_ns, timed_poses, timing_shifts_s, velocity_poses,
)
from egobench.model.pose_sampling import PoseSampling

F_PX = 100.0
T_C = 10_000_000_000  # centre-row time of the test frame, ns


class RotY:
    """Device rotating about its y axis at omega rad/s (angle 0 at T_C), at the origin."""

    def __init__(self, omega: float, v_x: float = 0.0) -> None:
        self.omega, self.v_x = omega, v_x

    def pose(self, t_ns) -> torch.Tensor:
        t = torch.as_tensor(t_ns).reshape(-1)
        assert not t.dtype.is_floating_point, "the Trajectory API takes integer ns"
        a = (t.to(torch.float64) - T_C) * 1e-9 * self.omega
        T = torch.eye(4, dtype=torch.float64).repeat(len(t), 1, 1)
        T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = a.cos(), a.sin(), -a.sin(), a.cos()
        T[:, 0, 3] = (t.to(torch.float64) - T_C) * 1e-9 * self.v_x
        return T

    def velocity(self, t_ns):
        from egobench.geometry import TrajectoryVelocity

        n = torch.as_tensor(t_ns).reshape(-1).shape[0]
        return TrajectoryVelocity(
            linear_world=torch.tensor([[self.v_x, 0.0, 0.0]], dtype=torch.float64).repeat(n, 1),
            angular_device=torch.tensor([[0.0, self.omega, 0.0]], dtype=torch.float64).repeat(n, 1),
        )


def make_recording(omega: float, uv: np.ndarray, z: np.ndarray, readout_s: float = 5e-3, size: int = 64,
                   v_x: float = 0.0) -> Recording:
    cam = Pinhole(fx=F_PX, fy=F_PX, cx=(size - 1) / 2, cy=(size - 1) / 2, width=size, height=size)
    exposure_s = 2e-3
    read_start = T_C - int(readout_s * 1e9 / 2) - int(exposure_s * 1e9 / 2)
    traj = RotY(omega, v_x)
    frame = Frame(
        index=0, image_path=Path("none.png"), timestamp_ns=T_C, read_start_ns=read_start,
        read_end_ns=read_start + int(readout_s * 1e9), exposure_s=exposure_s, gain=1.0,
        T_world_camera=traj.pose(torch.tensor([T_C]))[0], T_device_camera=torch.eye(4, dtype=torch.float64),
        sparse_depth=SparseDepth(uv=uv, z=z, inv_dist_std=np.zeros(len(z)), dist_std=np.zeros(len(z))),
    )
    ratio = (torch.arange(size, dtype=torch.float32) / (size - 1))[:, None].expand(size, size).contiguous()
    return Recording(
        root=Path("."), name="t", calibration="online", camera=cam, camera_model="linear", frames=[frame],
        vignette=torch.ones(size, size), mask=torch.ones(size, size, dtype=torch.bool), row_time_ratio=ratio,
        trajectory=traj, points_world=torch.zeros(1, 3),
    )


def centre_points(n: int = 20, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Points on the optical axis (u = cx, v = cy) at various depths: pure yaw moves them by f tan(angle)."""
    c = (size - 1) / 2
    return np.full((n, 2), c), np.linspace(1.0, 5.0, n)


def test_static_frame_needs_one_sample():
    uv, z = centre_points()
    rec = make_recording(0.0, uv, z)
    assert n_pose_samples(rec, rec.frames[0]) == 1
    assert n_pose_samples(rec, rec.frames[0], PoseSampling(rule="paper")) == 1


@pytest.mark.parametrize("omega", [7.0, 12.0, 40.0])
def test_code_rule_matches_analytic_count(omega):
    uv, z = centre_points()
    rec = make_recording(omega, uv, z)
    est = estimate_motion(rec, rec.frames[0])
    # A point on the axis at angle 0 sits at u = cx; at +-1 ms it is at cx -+ f tan(omega * 1 ms).
    d_2ms = 2 * F_PX * math.tan(omega * MOTION_WINDOW_S / 2)
    assert est.median_motion_px == pytest.approx(d_2ms, rel=1e-6)
    expected = int(min(max(5e-3 / MOTION_WINDOW_S * d_2ms, 1), 8))
    assert est.n_samples == expected
    assert expected > 1  # the cases are chosen to need more than one sample


def test_paper_rule_matches_analytic_count():
    omega = 1.2  # rad/s; readout 5 ms -> 6 mrad over the readout, 0.6 px
    uv, z = centre_points()
    for readout, omega in [(5e-3, 1.2), (5e-3, 3.5), (16e-3, 3.0)]:
        rec = make_recording(omega, uv, z, readout_s=readout)
        got = n_pose_samples(rec, rec.frames[0], PoseSampling(rule="paper"))
        # Brackets over [-R/2, R/2]; displacement in bracket i is f (tan a1 - tan a0); the worst is an outer one.
        expected = 8
        for n in range(1, 9):
            edges = (-readout / 2 + np.arange(n + 1) * readout / n) * omega
            worst = np.max(F_PX * np.diff(np.tan(edges)))
            if worst < 1.0:
                expected = n
                break
        assert got == expected, (readout, omega)


@pytest.mark.parametrize("step_px", [0.25, 0.5, 2.0])
def test_a_finer_step_takes_analytically_more_samples(step_px):
    """Both rules count in steps of `step_px` pixels of row shear: the code rule divides the shear by the step,
    the paper rule asks every bracket's median displacement to stay below it."""
    uv, z = centre_points()
    omega, readout = 3.0, 16e-3
    rec = make_recording(omega, uv, z, readout_s=readout)
    d_2ms = 2 * F_PX * math.tan(omega * MOTION_WINDOW_S / 2)
    code = n_pose_samples(rec, rec.frames[0], PoseSampling(64, "code", step_px))
    assert code == int(min(max(readout / MOTION_WINDOW_S * d_2ms / step_px, 1), 64))
    paper = n_pose_samples(rec, rec.frames[0], PoseSampling(64, "paper", step_px))
    worst = [np.max(F_PX * np.diff(np.tan((-readout / 2 + np.arange(n + 1) * readout / n) * omega)))
             for n in range(1, 65)]
    assert paper == next(n for n, w in enumerate(worst, 1) if w < step_px)
    released_paper = n_pose_samples(rec, rec.frames[0], PoseSampling(rule="paper"))
    assert (code > 1 and paper > 1) and (step_px >= 1 or paper > released_paper)


def test_a_runs_sample_counts_follow_its_pose_sampling():
    """`predict.sample_counts` (every render of a run) counts with the run's whole `PoseSampling`, step included."""
    from egobench.model.methods import get_method
    from egobench.model.predict import sample_counts

    uv, z = centre_points()
    rec = make_recording(3.0, uv, z, readout_s=16e-3)
    released, fine = (sample_counts(rec, rec.frames, get_method("ours"), PoseSampling(64, "code", step), 1.0)[0]
                      for step in (1.0, 0.25))
    assert released == n_pose_samples(rec, rec.frames[0], PoseSampling(64))
    assert fine == n_pose_samples(rec, rec.frames[0], PoseSampling(64, "code", 0.25)) > released


@pytest.mark.parametrize("field, value, train_field", [("step_px", 0.0, "pose_sample_step_px"),
                                                       ("max_samples", 1.5, "max_pose_samples"),
                                                       ("rule", "fast", "sample_rule")])
def test_a_sampling_setting_that_is_no_rule_is_refused_in_its_own_name(field, value, train_field):
    """One check (`sampling_problem`), named as the caller spells the field: PoseSampling or TrainConfig."""
    from egobench.train.config import TrainConfig

    with pytest.raises(ValueError, match=f"PoseSampling.{field}: expected"):
        PoseSampling(**{field: value})
    with pytest.raises(ValueError, match=f"TrainConfig.{train_field}: expected"):
        TrainConfig(**{train_field: value})


def test_pixel_scale_reduces_count():
    uv, z = centre_points()
    rec = make_recording(40.0, uv, z)
    full = estimate_motion(rec, rec.frames[0])
    half = estimate_motion(rec, rec.frames[0], pixel_scale=0.5)
    assert half.median_motion_px == pytest.approx(full.median_motion_px / 2)


def test_points_leaving_the_image_are_ignored():
    uv, z = centre_points()
    uv2 = np.concatenate([uv, [[200.0, 10.0]]])  # outside the image: never counted
    rec = make_recording(12.0, uv2, np.concatenate([z, [2.0]]))
    assert estimate_motion(rec, rec.frames[0]).n_points == len(z)


def test_missing_sparse_depth_is_a_clear_error():
    uv, z = centre_points()
    rec = make_recording(12.0, uv, z)
    rec.frames[0].sparse_depth = None
    with pytest.raises(ValueError, match="sparse depth"):
        n_pose_samples(rec, rec.frames[0])


def test_bracket_centres_and_pose_samples():
    uv, z = centre_points()
    readout = 5e-3
    rec = make_recording(12.0, uv, z, readout_s=readout)
    f = rec.frames[0]
    n = 4
    times = sample_times_ns(f, n)[0]
    R = f.read_end_ns - f.read_start_ns
    expected = T_C - R / 2 + (np.arange(n) + 0.5) * R / n
    np.testing.assert_allclose(times.numpy(), expected)
    poses, ppi = pose_samples(rec, f, n)
    assert poses.shape == (n, 4, 4) and poses.dtype == torch.float64
    ref = rec.trajectory.pose(torch.round(torch.as_tensor(expected)).long())
    torch.testing.assert_close(poses, ref)
    # Per-pixel index = round(R(u) (n - 1)) with R(u) = v / (H - 1) here.
    H = rec.camera.height
    v = np.arange(H) / (H - 1)
    np.testing.assert_array_equal(ppi[:, 0].numpy(), np.round(v * (n - 1)).astype(np.int64))
    assert ppi.dtype == torch.int64 and ppi.min() == 0 and ppi.max() == n - 1


def test_pixel_pose_index_with_nonlinear_ratio():
    r = torch.tensor([[0.0, 0.1, 0.49], [0.51, 0.9, 1.0]])
    np.testing.assert_array_equal(pixel_pose_index(r, 3).numpy(), [[0, 0, 1], [1, 2, 2]])
    assert int(pixel_pose_index(r, 1).max()) == 0


def test_exposure_samples_split_the_exposure():
    uv, z = centre_points()
    rec = make_recording(12.0, uv, z)
    f = rec.frames[0]
    t = sample_times_ns(f, 2, n_exposure_samples=4)
    assert t.shape == (4, 2)
    E = f.exposure_s * 1e9
    np.testing.assert_allclose((t[:, 0] - t[0, 0]).numpy(), np.arange(4) * E / 4)
    np.testing.assert_allclose(t.mean(0).numpy(), sample_times_ns(f, 2)[0].numpy())
    assert exposure_pose_samples(rec, f, 2, 4).shape == (4, 2, 4, 4)


def test_velocity_model_matches_constant_rotation():
    uv, z = centre_points()
    omega, v_x = 12.0, 0.5
    rec = make_recording(omega, uv, z, v_x=v_x)
    f = rec.frames[0]
    twist = frame_twist_camera(rec, f)
    torch.testing.assert_close(twist, torch.tensor([v_x, 0, 0, 0, omega, 0], dtype=torch.float64))
    dt = torch.tensor([-2e-3, 0.0, 3e-3], dtype=torch.float64)
    T = velocity_poses(f.T_world_camera, twist, dt)
    # Rotation part is exact for constant yaw; translation moves along world x at v_x.
    ref = rec.trajectory.pose(torch.round(T_C + dt * 1e9).long())
    torch.testing.assert_close(T[:, :3, :3], ref[:, :3, :3])
    torch.testing.assert_close(T[:, :3, 3], ref[:, :3, 3], atol=1e-9, rtol=0)  # world x = v_x dt at the origin


def test_a_timing_correction_moves_each_sample_to_its_corrected_time_along_the_twist():
    """Under a constant twist, the samples at the stated times moved by (offset + place x readout error) are the
    constant-velocity poses at the corrected times: the rotations exactly (exp((a + b) w) = exp(a w) exp(b w)),
    the translations to second order (the shift's step s v turns with the sample's rotation: |R(a) - I| |s v|)."""
    uv, z = centre_points()
    rec = make_recording(12.0, uv, z, v_x=0.5)
    f = rec.frames[0]
    twist = frame_twist_camera(rec, f)
    n, readout_s = 4, 0.008
    dt = (torch.arange(n, dtype=torch.float64) + 0.5) / n * readout_s - readout_s / 2  # the bracket centres
    timing = torch.tensor([1.5, -2.0], dtype=torch.float64)  # +1.5 ms offset, a readout 2 ms shorter
    shifts = timing_shifts_s(n, timing)
    torch.testing.assert_close(shifts, 1.5e-3 + ((torch.arange(n) + 0.5) / n - 0.5).double() * -2.0e-3)
    moved = timed_poses(velocity_poses(f.T_world_camera, twist, dt)[None], twist, timing)
    expected = velocity_poses(f.T_world_camera, twist, dt + shifts)
    torch.testing.assert_close(moved[0, :, :3, :3], expected[:, :3, :3], atol=1e-12, rtol=0)
    turn = (dt.abs() * twist[3:].norm() * shifts.abs() * twist[:3].norm())  # |R(a) - I| |s v| <= |a w| |s v|
    assert torch.all((moved[0, :, :3, 3] - expected[:, :3, 3]).norm(dim=-1) <= turn + 1e-12)
    assert float((moved[0, :, :3, 3] - expected[:, :3, 3]).norm(dim=-1).max()) > 0.5 * float(turn.max())
    # no correction: the poses as they were, bit for bit (exp(0) = I)
    poses = velocity_poses(f.T_world_camera, twist, dt)[None]
    assert torch.equal(timed_poses(poses, twist, torch.zeros(2, dtype=torch.float64)), poses)


def test_the_timing_correction_differentiates_as_its_finite_differences():
    uv, z = centre_points()
    rec = make_recording(12.0, uv, z, v_x=0.5)
    f = rec.frames[0]
    poses = exposure_pose_samples(rec, f, 3, 1)
    twist = frame_twist_camera(rec, f)
    timing = torch.tensor([0.7, 1.9], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: timed_poses(poses, twist, t), (timing,))


@pytest.mark.parametrize("n", [4, 8, 16, 64])
def test_the_pose_sample_staircase_renders_a_readout_about_one_nth_short(n):
    """A pixel's rendered time is its sample's bracket centre (i + 0.5) / N with i = round(R (N - 1))
    (the released code's mapping): the centres run from 0.5 / N to 1 - 0.5 / N while R(u) runs from 0
    to 1, so the least-squares slope of rendered row time on R(u) is short of 1 by a bit under 1/N
    (0.83/N at N = 4, 0.99/N at N = 64): a readout about 1/N short, which the diagnosis's readout test
    measures on a trained run's renders (results/diagnosis/README.md, null audit; `egobench diagnose --pose-samples`)."""
    r = torch.linspace(0.0, 1.0, 100001, dtype=torch.float64)[None, :]
    t_rendered = (pixel_pose_index(r, n).to(torch.float64) + 0.5) / n
    slope = float(np.polyfit(r[0].numpy(), t_rendered[0].numpy(), 1)[0])
    assert 0.8 / n < 1.0 - slope <= 1.0 / n


def test_pose_sample_cache_gives_frame_poses_bits_and_computes_once():
    """`frame_poses` with a run's `PoseSampleCache`: the uncached result bit for bit (with and without a
    pose delta, several n and exposure samples), each (frame, n, M) sampled once, the pixel index once
    per n; rendering from the cached poses leaves them as they were; the pose delta still gets a gradient."""
    from egobench.model import motion_sampling
    from egobench.model.methods import get_method
    from egobench.model.predict import PoseSampleCache, frame_poses

    uv, z = centre_points()
    rec = make_recording(12.0, uv, z)
    f, ratio = rec.frames[0], rec.row_time_ratio
    cache, calls = PoseSampleCache(), []
    real = motion_sampling.exposure_pose_samples
    for spec in (get_method("ours"), get_method("no_viba")):
        for n, m in ((3, 1), (3, 1), (1, 2), (5, 2), (3, 1)):
            delta = torch.tensor([1e-3, -2e-3, 5e-4, 1e-2, 0.0, -3e-3], requires_grad=True)
            kw = {"pose_delta": delta} if spec.pose_optimisation else {}
            want, want_ppi = frame_poses(rec, f, spec, n, ratio, n_exposure_samples=m, **kw)
            motion_sampling.exposure_pose_samples = lambda *a: calls.append(a[2:]) or real(*a)
            try:
                got, got_ppi = frame_poses(rec, f, spec, n, ratio, n_exposure_samples=m, cache=cache, **kw)
            finally:
                motion_sampling.exposure_pose_samples = real
            assert torch.equal(got, want) and (got_ppi is None) == (want_ppi is None)
            assert got_ppi is None or torch.equal(got_ppi, want_ppi)
            if spec.pose_optimisation:
                got.sum().backward()
                assert delta.grad is not None and bool(delta.grad.abs().sum() > 0)
    assert sorted(calls) == [(1, 2), (3, 1), (5, 2)] and sorted(cache.ppi) == [3, 5]
    cached = {k: v.clone() for k, v in cache.poses.items()}
    from egobench.render import render
    from egobench.render.types import Gaussians

    g = Gaussians(torch.randn(30, 3) + torch.tensor([0.0, 0.0, 4.0]), torch.randn(30, 4), torch.full((30, 3), -3.0),
                  torch.zeros(30), torch.rand(30, 3))
    poses, ppi = frame_poses(rec, f, get_method("no_viba"), 3, ratio, cache=cache)
    render(g, rec.camera, poses[0], pixel_pose_index=ppi, backend="torch")
    assert all(torch.equal(cache.poses[k], v) for k, v in cached.items())
