"""The compiled closest-hit kernel against the torch tests it repeats: the same bits for every ray.

torch's ``sqrt`` on the CPU calls MKL's vector math (``vmsSqrt``, ``vmdSqrt``), which is not correctly rounded
(on an AMD EPYC Zen 4, 17 % of a million float32 values and 1.2 % of float64 ones differ from IEEE sqrt) and may
differ between CPU vendors; the kernel's sqrt is IEEE's. The reference here is therefore the torch path with
torch's sqrt replaced by IEEE sqrt (numpy's), which makes the comparison hold on every x86-64 machine.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egobench.sim.textures import Texture
from egobench.sim.world import Box, Cylinder, Material, Rect, Scene, Sphere, WalkRegion, make_scene
from egobench.sim.world.raycast_kernel import K_SLAB_FILL, K_SLAB_TINY, kernel_constants


@pytest.fixture
def ieee_sqrt(monkeypatch):
    """torch.sqrt correctly rounded (numpy's), for the torch reference path."""
    torch_sqrt = torch.sqrt

    def sqrt(x, *args, **kwargs):
        if x.device.type != "cpu" or x.requires_grad or args or kwargs:
            return torch_sqrt(x, *args, **kwargs)
        return torch.from_numpy(np.sqrt(x.numpy()))

    monkeypatch.setattr(torch, "sqrt", sqrt)


def _rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins at head height in the walk region and anywhere in the scene's box (inside furniture and
    bounding spheres too); random directions, an eighth of them along the axes (parallel to faces and caps)."""
    rng = np.random.default_rng(seed)
    o = np.concatenate([scene.walk_region.sample_xy(rng, n), rng.uniform(0.3, 2.5, (n, 1))], 1)
    lo, hi = np.maximum(scene.scene_bounds[0], (-8, -8, -1)), np.minimum(scene.scene_bounds[1], (8, 8, 4))
    o[n // 2:] = rng.uniform(lo, hi, (n - n // 2, 3))
    d = rng.normal(size=(n, 3))
    axis = rng.integers(0, 3, n // 8)
    d[: n // 8] = np.eye(3)[axis] * rng.choice([-1.0, 1.0], (n // 8, 1))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _assert_same_bits(scene: Scene, o: np.ndarray, d: np.ndarray, dtype: torch.dtype, t_max=None) -> int:
    O, D = torch.tensor(o, dtype=dtype), torch.tensor(d, dtype=dtype)
    tm = None if t_max is None else torch.tensor(t_max, dtype=dtype)
    t_ref, id_ref = scene.intersect(O, D, tm, backend="torch")
    t, ids = scene.intersect(O, D, tm, backend="compiled")
    assert t.dtype == dtype and ids.dtype == torch.int64
    np.testing.assert_array_equal(ids.numpy(), id_ref.numpy())
    np.testing.assert_array_equal(t.numpy().view(np.uint8), t_ref.numpy().view(np.uint8))  # bits, signs of 0 too
    return int((ids >= 0).sum())


@pytest.mark.parametrize("kind", ["outdoor", "indoor", "object", "quest3"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_hits_equal_the_torch_path_bit_for_bit(kind, dtype, ieee_sqrt):
    for seed, variety in ((3, 0.0), (17, 1.0)):
        scene = make_scene(kind, seed, grain=0.6, variety=variety)
        o, d = _rays(scene, 6000, seed)
        hits = _assert_same_bits(scene, o, d, dtype)
        assert hits > 3000  # the rays do meet the scene
        t_max = np.random.default_rng(seed).uniform(0.05, 6.0, len(o))  # shadow rays: occluders before t_max
        _assert_same_bits(scene, o, d, dtype, t_max)


def _doubled_scene() -> Scene:
    """Every kind twice at one place (ties between equal t) and enough small boxes for grouped culling."""
    flat = {"flat": Material(Texture("checker", ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)), 0.1, grain=0.0))}
    prims = []
    for _ in range(2):
        prims += [Rect((0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), 4.0, 4.0, "flat"),
                  Box((6.0, 0.0, 1.0), (3.0, 3.0, 1.0), "flat"),  # a big box: the dense slab test
                  Sphere((0.0, 3.0, 1.0), 0.5, "flat"),
                  Cylinder((0.0, -3.0, 1.0), (0, 0, 1), 0.4, 0.8, "flat")]
    prims += [Box((-3.0 + 0.5 * i, 1.5, 0.3), (0.2, 0.2, 0.3), "flat") for i in range(10)]
    prims += [Box((-3.0 + 0.5 * i, 1.5, 0.3), (0.2, 0.2, 0.3), "flat") for i in range(3)]  # doubles
    prims += [Cylinder((-3.0 + 0.6 * i, -1.5, 0.5), (0, 0, 1), 0.2, 0.5, "flat") for i in range(10)]
    prims += [Box((2.0, 2.0 + i, 0.5), (0.5, 0.25, 0.5), "flat") for i in range(2)]  # faces on a 0.25 m grid
    return Scene("custom", prims, flat, [], WalkRegion("box", (0.0, 0.0), (5.0, 5.0)), np.zeros((1, 3)),
                 ((-6.0, -6.0, -1.0), (10.0, 6.0, 3.0)))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ties_between_equal_primitives_break_as_the_torch_path_breaks_them(dtype, ieee_sqrt):
    scene = _doubled_scene()
    o, d = _rays(scene, 8000, 5)
    _assert_same_bits(scene, o, d, dtype)
    # origins on a 0.25 m grid, along the axes: rays that start on faces and graze edges exactly
    g = np.stack(np.meshgrid(np.arange(1.0, 3.01, 0.25), np.arange(1.0, 3.51, 0.25), np.arange(0.0, 1.01, 0.25),
                             indexing="ij"), -1).reshape(-1, 3)
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    _assert_same_bits(scene, np.repeat(g, 6, 0), np.tile(axes, (len(g), 1)), dtype)
    t, ids = scene.intersect(torch.tensor(o, dtype=dtype), torch.tensor(d, dtype=dtype), backend="compiled")
    hit_kinds = {type(scene.primitives[i]).__name__ for i in ids.unique().tolist() if i >= 0}
    assert hit_kinds == {"Rect", "Box", "Sphere", "Cylinder"}
    # doubled rects: the first of the kind wins (torch's min); doubled small boxes: the larger id (_reduce_pairs)
    assert 4 not in ids.tolist() and 0 in ids.tolist()
    small_first, small_double = 8, 8 + 10
    assert small_first not in ids.tolist() and small_double in ids.tolist()


def test_empty_rays_and_bad_backends():
    scene = make_scene("object", 0)
    t, ids = scene.intersect(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64),
                             backend="compiled")
    assert t.shape == (0,) and ids.shape == (0,)
    o = torch.zeros(2, 3, dtype=torch.float16)
    with pytest.raises(ValueError, match="compiled backend takes float32 or float64 CPU rays"):
        scene.intersect(o, o, backend="compiled")
    with pytest.raises(ValueError, match="backend must be"):
        scene.intersect(o.double(), o.double(), backend="numba")


def test_constants_are_in_the_rays_dtype():
    """A float64 constant would turn float32 arithmetic into float64 (other bits than torch's float32)."""
    for dtype in (np.float32, np.float64):
        k = kernel_constants(dtype)
        assert all(type(v) is dtype for v in k)
    f32, f64 = kernel_constants(np.float32), kernel_constants(np.float64)
    assert f32[K_SLAB_TINY] == f32[K_SLAB_FILL] == np.float32(1e-20) and f64[K_SLAB_TINY] == 1e-30
    assert f64[K_SLAB_FILL] == float(np.float32(1e-30)) != 1e-30  # torch.where of two Python scalars is float32


def test_degenerate_rays_equal_the_torch_path(ieee_sqrt):
    """Zero directions from inside boxes and unit rays far away: the slab's replaced components decide t."""
    scene = _doubled_scene()
    o = np.array([[-3.0, 1.5, 0.3], [6.0, 0.0, 1.0], [0.1, 0.2, 1.3], [2e14, 0.0, 0.5], [-3.0, -2e14, 0.3]])
    d = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for dtype in (torch.float64, torch.float32):
        _assert_same_bits(scene, o, d, dtype)


def _outcome(scene: Scene, o, d, t_max, backend: str):
    """(t, ids) as lists, or the type of the error raised."""
    try:
        t, ids = scene.intersect(o, d, t_max, backend=backend)
    except (RuntimeError, IndexError, ValueError) as err:
        return type(err)
    return t.tolist(), ids.tolist()


def test_other_shapes_and_dtypes_take_the_torch_path():
    """t_max of another dtype or a broadcast shape, mismatched directions, autograd: "auto" does what torch does."""
    scene = _doubled_scene()
    o, d = (torch.tensor(a, dtype=torch.float32) for a in _rays(scene, 64, 2))
    t_max64 = torch.full((64,), 1.00000001, dtype=torch.float64)
    for t_max, d_ in ((t_max64, d), (torch.tensor([2.0], dtype=torch.float32), d), (None, d[:1])):
        assert _outcome(scene, o, d_, t_max, "auto") == _outcome(scene, o, d_, t_max, "torch")
        with pytest.raises(ValueError, match="compiled backend takes"):
            scene.intersect(o, d_, t_max, backend="compiled")
    og = o.double().requires_grad_()
    t, _ = scene.intersect(og, d.double())
    assert t.grad_fn is not None
