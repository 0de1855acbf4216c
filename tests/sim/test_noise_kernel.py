"""The compiled value noise against the torch version it repeats: the same bits, every point."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egobench.sim import textures
from egobench.sim.world import make_scene


def _both(monkeypatch, fn):
    """(compiled, torch) results of fn()."""
    compiled = fn()
    with monkeypatch.context() as m:
        m.setattr(textures, "_compiled_noise_applies", lambda uv, e: False)
        reference = fn()
    return compiled, reference


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    np.testing.assert_array_equal(a.numpy().view(np.uint8), b.numpy().view(np.uint8))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_value_noise_equals_the_torch_version_bit_for_bit(dtype, monkeypatch):
    rng = np.random.default_rng(7)
    uv = torch.tensor(np.concatenate([rng.uniform(-40, 40, (20000, 2)), rng.uniform(-1e4, 1e4, (2000, 2)),
                                      np.round(rng.uniform(-5, 5, (500, 2)), 1)]), dtype=dtype)  # lattice points too
    e = torch.tensor(rng.uniform(0, 0.2, len(uv)), dtype=dtype)
    for scale, seed in ((0.013, 3), (0.37, 104729), (2.5, 7919 * 4)):
        _same_bits(*_both(monkeypatch, lambda: textures.value_noise(uv, scale, seed)))
        _same_bits(*_both(monkeypatch, lambda: textures.value_noise(uv, scale, seed, e)))
    a = textures.value_noise(uv, 0.37, 3)
    assert 0.0 <= float(a.min()) and float(a.max()) <= 1.0 and float(a.std()) > 0.1  # it is noise


def test_textures_and_grain_of_a_scene_equal_the_torch_version(monkeypatch):
    """Every texture kind of the four scene kinds (fbm and grain octaves, footprints) through `albedo_at`."""
    rng = np.random.default_rng(1)
    for kind in ("outdoor", "indoor", "object", "quest3"):
        scene = make_scene(kind, 5, grain=0.6, variety=1.0)
        pid = torch.tensor(rng.integers(0, len(scene.primitives), 4000))
        uv = torch.tensor(rng.uniform(-3, 3, (4000, 2)), dtype=torch.float32)
        foot = torch.tensor(rng.uniform(0, 0.05, 4000), dtype=torch.float32)
        _same_bits(*_both(monkeypatch, lambda: scene.albedo_at(uv, pid, foot)))


def test_autograd_and_mixed_dtypes_take_the_torch_version():
    uv = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    assert not textures._compiled_noise_applies(uv, None)
    assert not textures._compiled_noise_applies(uv.detach(), torch.zeros(3, dtype=torch.float32))
    assert textures._compiled_noise_applies(uv.detach(), torch.zeros(3, dtype=torch.float64))
    assert not textures._compiled_noise_applies(torch.zeros(3, 1, dtype=torch.float64), None)  # not points [N, 2]
    assert not textures._compiled_noise_applies(uv.detach(), torch.zeros(2, dtype=torch.float64))
    textures.value_noise(uv, 0.5, 1).sum().backward()  # the torch version: differentiable
    assert uv.grad is not None
