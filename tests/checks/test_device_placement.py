"""Device placement without a GPU: trainer-path functions run on a *fake accelerator* and every
output must stay on it; a tensor made on the CPU and combined with a device tensor must raise.

How: ``torch._subclasses.fake_tensor.FakeTensorMode`` (no data, shapes and devices only) checks in
Python that the operands of every op share a device (``FakeTensorDeviceMismatchError``), as CUDA
kernels do. The fake device is ``meta``, not ``cuda``: on a CPU-only torch build a fake *CUDA*
tensor can be created, but every Python indexing (``x[..., None]``, ``x[idx]``) and several ops
go through a C++ CUDA device guard and fail with "PyTorch is not linked with support for cuda
devices", so only index-free code could run. ``meta`` has a device guard on every build; a
``ShapeEnv`` lets boolean-mask indexing / ``nonzero`` produce symbolic sizes.

Limits (why some paths are not here): code that reads tensor *values* on the host
(``bool(t.any())``, ``int(t.sum())``, ``len(torch.where(m)[0])``, ``.item()``) cannot run on data-less
tensors: `render` (finite-value checks), `metrics.psnr/ssim` (float results), `Densifier.grow`/
`_prune_gs` and gsplat's duplicate/split/remove (host counts). FakeTensorMode also does not flag
a CPU convolution weight or a CPU tensor indexed by a device index (CUDA does), so those stay
unchecked here. The value validation of formation (`_check_values`) and geometry (`_check_rotmat`)
is data-dependent and is switched off in these tests only (fixture `no_value_checks`).
"""

from __future__ import annotations

import json
from contextlib import contextmanager

import pytest
import torch

from torch._subclasses.fake_tensor import FakeTensorMode

try:  # torch >= 2.12 names the error
    from torch._subclasses.fake_tensor import FakeTensorDeviceMismatchError
except ImportError:  # torch 2.11 (the GPU image's) raises a RuntimeError naming the two devices
    FakeTensorDeviceMismatchError = RuntimeError
#: both messages name the fake device first: "... devices, meta and cpu!" (2.12+), "... devices meta, cpu" (2.11)
MISMATCH = r"meta(,| and) cpu"
from torch.fx.experimental.symbolic_shapes import ShapeEnv

FAKE = torch.device("meta")  # the stand-in accelerator (see module docstring)


@pytest.fixture(autouse=True)
def _clear_ssim_taps_cache():
    """`metrics.gaussian_taps` caches taps per device; fake tensors must not outlive their mode."""
    from egobench.metrics import gaussian_taps

    gaussian_taps.cache_clear()
    yield
    gaussian_taps.cache_clear()


@contextmanager
def fake_accelerator():
    """Inside: factory calls with ``device=FAKE`` give data-less tensors on the fake device; real
    CPU tensors made before (module constants, frames) enter as CPU tensors."""
    with FakeTensorMode(allow_non_fake_inputs=True, shape_env=ShapeEnv()) as mode:
        yield mode


def dev(*shape, dtype=torch.float32, requires_grad: bool = False) -> torch.Tensor:
    """A tensor [*shape] on the fake device (call inside `fake_accelerator`)."""
    t = torch.rand(shape, dtype=dtype, device=FAKE) if dtype.is_floating_point else \
        torch.zeros(shape, dtype=dtype, device=FAKE)
    return t.requires_grad_(requires_grad) if requires_grad else t


@pytest.fixture
def no_value_checks(monkeypatch):
    """Switch off the data-dependent *value* validation (finite, positive: `bool(t.all())` needs data)
    of formation and geometry; shapes are still checked by the ops themselves."""
    import egobench.model.formation as fm
    import egobench.geometry.se3 as se3

    monkeypatch.setattr(fm, "_check_values", lambda *a, **k: None)
    monkeypatch.setattr(se3, "_check_rotmat", lambda R, name: None)


def assert_on_fake(*tensors: torch.Tensor) -> None:
    for t in tensors:
        assert isinstance(t, torch.Tensor) and t.device == FAKE, f"expected a tensor on {FAKE}, got {t.device}"


# ----------------------------------------------------------------------------- the check itself
_CPU_CONSTANT = torch.ones(3)  # a module constant made on the CPU, as a forgotten .to(device) leaves it


def _wrong_new_tensor(x: torch.Tensor) -> torch.Tensor:  # the bug class: a tensor made without device=
    return x + torch.ones(x.shape)


def _right_new_tensor(x: torch.Tensor) -> torch.Tensor:
    return x + torch.ones(x.shape, device=x.device)


def _wrong_constant(x: torch.Tensor) -> torch.Tensor:
    return x @ torch.eye(3, dtype=torch.float64) + _CPU_CONSTANT


def test_harness_catches_a_cpu_tensor_meeting_a_device_tensor():
    with fake_accelerator():
        x = dev(4, 3)
        assert_on_fake(_right_new_tensor(x))
        with pytest.raises(FakeTensorDeviceMismatchError, match=MISMATCH):
            _wrong_new_tensor(x)
        with pytest.raises(FakeTensorDeviceMismatchError, match=MISMATCH):
            _wrong_constant(x.double())
        # the same functions on real CPU tensors are fine: only a device mix-up is flagged
    assert _wrong_new_tensor(torch.zeros(4, 3)).device.type == "cpu"
    with fake_accelerator():
        s = torch.tensor(2.0)  # 0-dim CPU scalars may meet device tensors (CUDA allows it too)
        assert_on_fake(dev(4, 3) * s)


# ----------------------------------------------------------------------------- formation (training loss path)
def test_formation_predict_and_virtual_gain_stay_on_the_device(no_value_checks):
    import egobench.model.formation as fm

    model = fm.FormationModel(fm.FormationConfig.paper_trainer())
    with fake_accelerator():
        x = dev(6, 5, 3, requires_grad=True)
        k = dev()  # k[fi]: a 0-dim tensor on the device, as in the training loop
        for vignette in (dev(6, 5), torch.ones(6, 5)):  # a CPU vignette is moved (documented behaviour)
            out = model.predict(x, scale_k=k, vignette=vignette, scene_gamma=True)
            assert_on_fake(out)
            assert tuple(out.shape) == (6, 5, 3)
        lin = model.predict(x, scale_k=1.5, vignette=dev(6, 5), scene_gamma=False)
        lin.sum().backward()
        assert_on_fake(lin, x.grad)
        assert_on_fake(model.virtual_gain(x, 3.0, scale_k=k, vignette=dev(6, 5)))


# ----------------------------------------------------------------------------- SSIM loss
def test_ssim_loss_and_its_gradient_stay_on_the_device():
    from egobench.metrics import ssim_loss, ssim_map

    with fake_accelerator():
        pred = dev(1, 16, 12, 3, requires_grad=True)
        gt = dev(1, 16, 12, 3)
        loss = ssim_loss(pred, gt)
        loss.backward()
        assert_on_fake(loss, pred.grad, ssim_map(pred.detach().double(), gt.double()))
        assert tuple(ssim_map(pred.detach(), gt).shape) == (1, 6, 2, 3)


# ----------------------------------------------------------------------------- poses
def _frame():
    from egobench.data.recording import Frame

    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    return Frame(index=0, image_path=None, timestamp_ns=1_000_000_000, read_start_ns=999_990_000,
                 read_end_ns=1_000_006_000, exposure_s=2e-3, gain=1.0, T_world_camera=T,
                 T_device_camera=torch.eye(4, dtype=torch.float64))


def test_velocity_poses_follow_a_trainable_twist_on_the_device(no_value_checks):
    """3DGS-on-the-move: host pose and times, twist trained on the GPU (was a device mix-up)."""
    from egobench.model.motion_sampling import pixel_pose_index, sample_times_ns, velocity_poses

    frame = _frame()
    with fake_accelerator():
        twist = dev(6, requires_grad=True)
        dt = (sample_times_ns(frame, 4, 2) - float(frame.timestamp_ns)).reshape(-1) * 1e-9  # host, float64
        poses = velocity_poses(frame.T_world_camera.float(), twist, dt)
        poses.sum().backward()
        assert_on_fake(poses, twist.grad, pixel_pose_index(dev(8, 6), 4))
        assert tuple(poses.shape) == (8, 4, 4) and poses.dtype == torch.float32


def test_frame_poses_velocity_shift_with_device_twist(no_value_checks):
    from egobench.model.methods import get_method
    from egobench.model.predict import frame_poses

    frame = _frame()
    with fake_accelerator():
        poses, ppi = frame_poses(None, frame, get_method("on_the_move"), 3, torch.zeros(8, 6),
                                 twist=dev(6), n_exposure_samples=2)
        assert_on_fake(poses)
        assert tuple(poses.shape) == (2, 3, 4, 4) and ppi.device.type == "cpu"  # render_frame moves ppi


def test_frame_poses_velocity_shift_with_device_pose_delta(no_value_checks):
    from egobench.model.methods import get_method
    from egobench.model.predict import frame_poses

    frame = _frame()
    with fake_accelerator():
        poses, _ = frame_poses(None, frame, get_method("on_the_move"), 3, torch.zeros(8, 6),
                               pose_delta=dev(6), twist=dev(6), n_exposure_samples=2)
        assert_on_fake(poses)


def test_depth_normals_of_the_2dgs_regulariser_stay_on_the_device():
    from egobench.camera.pinhole import Pinhole
    from egobench.train.normal_consistency import depth_normals

    cam = Pinhole(fx=10.0, fy=10.0, cx=3.5, cy=2.5, width=8, height=6)
    with fake_accelerator():
        n = depth_normals(dev(6, 8), cam)
        assert_on_fake(n)
        assert tuple(n.shape) == (6, 8, 3)


# ----------------------------------------------------------------------------- densification statistics
def _params(n: int) -> dict:
    return {name: torch.nn.Parameter(dev(*shape)) for name, shape in
            (("means", (n, 3)), ("scales", (n, 3)), ("quats", (n, 4)), ("opacities", (n,)), ("colors", (n, 3)))}


def _densifier():
    from egobench.model.optim import Densifier, DensifySchedule

    return Densifier(DensifySchedule(grow_grad2d=2e-4, grow_scale3d=0.01, prune_opa=0.005, prune_scale3d=0.1,
                                     refine_start_iter=0, refine_stop_iter=100, refine_every=10, reset_every=50,
                                     opacity_reset="gsplat", max_gaussians=0), scene_scale=1.0)


def test_densifier_statistics_live_on_the_device_and_checkpoint_on_the_cpu():
    n = 7
    d = _densifier()
    with fake_accelerator():
        params = _params(n)
        means2d = dev(2, n, 2, requires_grad=True)  # two pose samples (rolling shutter)
        means2d.grad = dev(2, n, 2)
        radii = dev(2, n, dtype=torch.int32)
        d.accumulate(params, 1, means2d, radii, 8, 6)
        assert_on_fake(d.state["grad2d"], d.state["count"])
        saved = d.state_dict()
        assert saved["grad2d"].device.type == "cpu" and saved["count"].device.type == "cpu"  # portable checkpoint
        # resume: a CPU state (torch.load(map_location="cpu")) meets parameters on the device
        d2 = _densifier()
        d2.load_state_dict({"grad2d": torch.zeros(n), "count": torch.zeros(n), "scene_scale": 1.0})
        d2.accumulate(params, 2, means2d, radii, 8, 6)
        assert_on_fake(d2.state["grad2d"], d2.state["count"])
        d3 = _densifier()
        d3.load_state_dict({"grad2d": torch.zeros(n), "count": torch.zeros(n), "scene_scale": 1.0})
        d3.refine(params, {}, 5)  # not a refinement step: only the state moves
        assert_on_fake(d3.state["grad2d"], d3.state["count"])


# ----------------------------------------------------------------------------- evaluation device
def _toy_run(tmp_path, device: str):
    from egobench.sim.plane import plane_recording
    from egobench.train import TrainConfig

    rec = plane_recording(tmp_path / "rec", size=16, n_frames=9, n_points=50)
    n = 20
    gen = torch.Generator().manual_seed(0)
    params = {"means": torch.rand(n, 3, generator=gen) + torch.tensor([0.0, 0.0, 2.0]), "scales": torch.full((n, 3), -3.0),
              "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), "opacities": torch.zeros(n),
              "colors": torch.rand(n, 3, generator=gen)}
    config = TrainConfig(iterations=1, device=device)
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"format": "egobench.checkpoint/1", "method": "ours", "iteration": 1, "config": config.to_dict(),
                "config_hash": config.hash("ours"), "params": params, "camera": rec.camera.to_dict()},
               run / "checkpoint.pt")
    (run / "train.json").write_text(json.dumps({"method": "ours", "seed": config.seed, "config_hash": config.hash("ours"),
                                                "train": {"iterations": 1}}))  # the record of a finished run
    return rec, run


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU-only message")
def test_evaluate_of_a_gpu_run_on_a_cpu_machine_names_the_fix(tmp_path):
    from egobench.evaluate import evaluate
    from egobench.train.checkpoint import render_device

    rec, run = _toy_run(tmp_path, "cuda")
    with pytest.raises(ValueError, match=r"training device.*CUDA is not available.*--device cpu"):
        evaluate(rec, run, save_renders=False)
    with pytest.raises(ValueError, match="requested"):
        render_device("cuda:0", "cpu", "here")
    out = evaluate(rec, run, save_renders=False, device="cpu")
    assert len(out["per_image"]) == 2 and out["metrics"]["psnr"] > 0


def test_evaluate_renders_on_the_requested_device(tmp_path, monkeypatch):
    """The Gaussians are rendered where asked (before: always on the CPU, whatever config.device)."""
    import egobench.model.predict as predict_mod
    from egobench.evaluate import evaluate
    from egobench.render.types import RenderOutput

    rec, run = _toy_run(tmp_path, "cpu")
    seen = []

    def fake_render_frame(g, camera, poses, ppi, spec, settings, want_normal=False):
        seen.append((g.means.device, g.colors.device, settings.device))
        H, W = camera.height, camera.width
        return [RenderOutput(rgb=torch.full((1, H, W, 3), 0.5), alpha=torch.ones(1, H, W, 1),
                             depth=torch.ones(1, H, W, 1))]

    monkeypatch.setattr(predict_mod, "render_frame", fake_render_frame)
    out = evaluate(rec, run, save_renders=False, device="meta")
    assert seen and all(d == (FAKE, FAKE, FAKE) for d in seen)
    assert out["train"]["num_gaussians"] == 20
