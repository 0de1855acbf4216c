"""Trainer image store: uint8 [F, H, W, 3] on the host, exact without resize, rounded area resize,
one frame per iteration to the device, recorded in train.json, training unchanged."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

import egobench.model.predict as P
import egobench.train.data as T
import egobench.train.initialise as I
import egobench.train.loop as L
from egobench.model.methods import get_method
from egobench.sim.plane import plane_recording
from egobench.train import TrainConfig, load_image_store, prepare_data, train

SPEC = get_method("no_motion_sampling")  # online calibration (as plane_recording), centre-row poses


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """9 frames of 32x32 (frames 0 and 8 held out: 7 training frames)."""
    return plane_recording(tmp_path_factory.mktemp("toy_store"), size=32, n_frames=9, angular_speed_rad_s=1.0,
                         n_points=600)


def test_store_is_uint8_and_exact_without_resize(toy):
    data = prepare_data(toy, SPEC, TrainConfig(max_side=0), progress=False)
    frames = toy.train_frames
    assert len(frames) == 7
    assert data.images.dtype == torch.uint8
    assert tuple(data.images.shape) == (7, 32, 32, 3) and data.images.is_contiguous()
    assert not data.images.is_pinned()  # CPU training never pins
    for i, f in enumerate(frames):
        ref = toy.load_image(f)
        assert torch.equal(data.images[i].float() / 255, ref)  # bit for bit
        assert torch.equal(T.image_to_float(data.images[i]), ref)
        # and the store holds the file's 8-bit values (independent decode)
        raw = cv2.cvtColor(cv2.imread(str(f.image_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        assert np.array_equal(data.images[i].numpy(), raw)
    # the default CPU suite trains 64 px recordings at max_side 64: no resize there either
    assert T.training_camera(toy.camera, TrainConfig(max_side=32)) is toy.camera


def test_resized_store_rounds_the_float_area_resize(toy):
    data = prepare_data(toy, SPEC, TrainConfig(max_side=20), progress=False)  # 32 -> 20: non-integer factor
    H, W = data.camera.height, data.camera.width
    assert (H, W) == (20, 20)
    assert data.images.dtype == torch.uint8 and tuple(data.images.shape) == (7, 20, 20, 3)
    max_err = 0.0
    for i, f in enumerate(toy.train_frames):
        # independent reference: cv2 area resize of the float image, straight from the file
        raw = cv2.cvtColor(cv2.imread(str(f.image_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        ref = cv2.resize(raw.astype(np.float32) / np.float32(255), (W, H), interpolation=cv2.INTER_AREA)
        got = data.images[i].numpy()
        assert np.array_equal(got, np.clip(np.rint(ref * np.float32(255)), 0, 255).astype(np.uint8))
        err = np.abs(got.astype(np.float32) / 255 - ref)
        assert err.max() <= 0.5 / 255 + 1e-6
        max_err = max(max_err, float(err.max()))
    assert max_err > 1e-4  # the resize really produced non-8-bit values that had to be rounded


def test_load_image_store_progress_bar(toy, capsys):
    frames = toy.train_frames[:2]
    load_image_store(toy, frames, toy.camera, progress=True)
    err = capsys.readouterr().err
    assert "load images" in err
    load_image_store(toy, frames, toy.camera, progress=False)
    assert capsys.readouterr().err == ""


def test_pinning_guarded_without_cuda(toy, monkeypatch):
    """A CUDA device named on a machine without CUDA must never reach pin_memory (CPU-only builds raise)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)

    def boom(*a, **k):
        raise AssertionError("pin_memory called without CUDA")

    monkeypatch.setattr(torch.Tensor, "pin_memory", boom)
    assert not T._pin_store("cuda") and not T._pin_store("cpu")
    data = prepare_data(toy, SPEC, TrainConfig(max_side=0, device="cuda"), progress=False)
    assert data.images.dtype == torch.uint8 and not data.images.is_pinned()


def _float_store_prepare(monkeypatch):
    """Patch prepare_data to the pre-uint8 path: a float32 stack of load_image (resize_map'd)."""
    orig = L.prepare_data

    def float_prepare(recording, spec, config, progress=True):
        data = orig(recording, spec, config, progress=progress)
        data.images = torch.stack([P.resize_map(recording.load_image(f), data.camera) for f in data.frames])
        return data

    monkeypatch.setattr(L, "prepare_data", float_prepare)


@pytest.mark.parametrize("method", ["ours", "no_motion_sampling"])
def test_training_identical_to_float_store(toy, tmp_path, monkeypatch, method):
    """No resize: the values fed to init and the loss are identical, so the run is bit-identical."""
    cfg = TrainConfig(iterations=12, max_side=0, max_gaussians=500, refine_start_frac=1.0, seed=3)
    res = train(toy, method, cfg, tmp_path / "u8", progress=False)
    rec = json.loads((tmp_path / "u8" / "train.json").read_text())
    store = rec["train"]["image_store"]
    assert store == {"dtype": "uint8", "shape": [7, 32, 32, 3], "mib": 7 * 32 * 32 * 3 / 2**20,
                     "pinned": False, "resized": False}

    with monkeypatch.context() as m:
        _float_store_prepare(m)
        ref = train(toy, method, cfg, tmp_path / "f32", progress=False)
    assert ref.record["train"]["image_store"]["dtype"] == "float32"  # the patch really took effect
    assert res.final_loss == ref.final_loss and np.isfinite(res.final_loss)
    p_u8 = torch.load(res.checkpoint, weights_only=True)["params"]
    p_f32 = torch.load(ref.checkpoint, weights_only=True)["params"]
    for name in p_u8:
        assert torch.equal(p_u8[name], p_f32[name]), name


def test_init_colours_read_the_store_as_float(toy):
    """init_params converts uint8 pixels to 0..1 (a missing /255 would give colours far above 1)."""
    cfg = TrainConfig(max_side=0, max_gaussians=300)
    data = prepare_data(toy, SPEC, cfg, progress=False)
    p_u8 = I.init_params(data, cfg, torch.Generator().manual_seed(0))
    data.images = torch.stack([toy.load_image(f) for f in data.frames])
    p_f32 = I.init_params(data, cfg, torch.Generator().manual_seed(0))
    assert torch.equal(p_u8["colors"], p_f32["colors"])
    colors = p_u8["colors"].detach()
    assert float(colors.max()) <= 4.0 and not torch.all(colors == 0.5)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_store_pinned_and_matches_cpu(toy, tmp_path):
    data = prepare_data(toy, SPEC, TrainConfig(max_side=0, device="cuda"), progress=False)
    assert data.images.dtype == torch.uint8 and data.images.is_pinned() and data.images.device.type == "cpu"
    cfg = TrainConfig(iterations=6, max_side=0, max_gaussians=300, refine_start_frac=1.0, device="cuda")
    res = train(toy, "no_motion_sampling", cfg, tmp_path / "cuda", progress=False)
    store = res.record["train"]["image_store"]
    assert store["pinned"] is True and store["dtype"] == "uint8" and np.isfinite(res.final_loss)


def test_store_exact_over_the_full_8bit_range():
    """Every 8-bit value 0..255 survives the store exactly (load_image's float = u8 / 255)."""
    from egobench.camera.pinhole import Pinhole

    u8 = (torch.arange(16 * 16 * 3) % 256).to(torch.uint8).reshape(16, 16, 3)
    assert set(u8.unique().tolist()) == set(range(256))

    class Stub:  # the one method load_image_store uses, decoding as Recording.load_image does
        def load_image(self, frame):
            return u8.clone().float().div_(255.0)

    cam = Pinhole(fx=14.0, fy=14.0, cx=7.5, cy=7.5, width=16, height=16)
    store = load_image_store(Stub(), [None, None], cam, progress=False)
    assert store.dtype == torch.uint8 and tuple(store.shape) == (2, 16, 16, 3)
    assert torch.equal(store[0], u8) and torch.equal(store[1], u8)
    assert torch.equal(T.image_to_float(store[1]), Stub().load_image(None))


def test_grey_init_colour_is_half_in_the_models_own_colour_space(toy):
    """init_colour="grey" (the authors' code: MPS points carry no colour) starts every Gaussian at 0.5,
    whatever the method's colour space; the geometry is the same as with image colours."""
    cfg = TrainConfig(max_side=0, max_gaussians=300)
    data = prepare_data(toy, SPEC, cfg, progress=False)
    image = I.init_params(data, cfg, torch.Generator().manual_seed(0))
    grey = I.init_params(data, TrainConfig(max_side=0, max_gaussians=300, init_colour="grey"),
                         torch.Generator().manual_seed(0))
    assert torch.equal(grey["colors"].detach(), torch.full_like(image["colors"].detach(), 0.5))
    for name in ("means", "scales", "quats", "opacities"):
        assert torch.equal(grey[name], image[name]), name
    with pytest.raises(ValueError, match="TrainConfig.init_colour: expected 'image' or 'grey', got 'gray'"):
        TrainConfig(init_colour="gray")
