"""`all_finite`, the trainer's divergence test: against torch.isfinite on CPU tensors of each float dtype,
with NaN and infinities placed anywhere (also past a vector's width and in non-contiguous views);
`has_zero_row` and `render`'s check of its Gaussians, compiled and through torch."""

import pytest
import torch

from egobench.render import _gaussians_valid, render
from egobench.render.finite import all_finite, has_zero_row
from egobench.render.types import Gaussians


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_all_finite_finds_every_non_finite_value(dtype):
    g = torch.Generator().manual_seed(0)
    for n in (1, 15, 16, 17, 257, 4099):
        for bad in (float("nan"), float("inf"), float("-inf")):
            for pos in (0, n // 2, n - 1):
                t = torch.randn(n, generator=g, dtype=dtype) * 1e30
                assert all_finite([t]) is True
                t[pos] = bad
                assert all_finite([torch.ones(3, dtype=dtype), t]) is False


def test_all_finite_on_views_empty_and_other_dtypes():
    big = torch.full((8, 6), torch.finfo(torch.float32).max)  # finite, and its float64 sum too
    assert all_finite([big, torch.empty(0), torch.arange(5)]) is True
    view = torch.zeros(8, 6)[:, ::2]  # non-contiguous
    view[3, 1] = float("nan")
    assert all_finite([view]) is False
    assert all_finite([torch.tensor([1.0, float("inf")], dtype=torch.bfloat16)]) is False  # the torch path
    assert all_finite([torch.tensor([1.0, 2.0], dtype=torch.float16)]) is True


def _torch_zero_row(t):
    return bool(((t * t).sum(-1) == 0).any())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_has_zero_row_is_the_squared_norm_test(dtype):
    """A zero row anywhere, a row whose squares underflow in the dtype, none; the compiled pass (float32,
    float64) and the torch path (float16) against the torch expression."""
    g = torch.Generator().manual_seed(1)
    tiny = {torch.float32: 1e-30, torch.float64: 1e-200, torch.float16: 1e-4}[dtype]
    for n in (1, 5, 33):
        for pos in (0, n // 2, n - 1):
            q = torch.randn(n, 4, generator=g).to(dtype)
            assert has_zero_row(q) is False
            q[pos] = 0.0
            assert has_zero_row(q) is True
            q[pos] = torch.tensor([tiny, -tiny, tiny, 0.0], dtype=dtype)
            assert has_zero_row(q) is _torch_zero_row(q) is True
            q[pos, 0] = 1e-3 if dtype == torch.float16 else 1e-15  # its square is representable
            assert has_zero_row(q) is _torch_zero_row(q) is False
    assert has_zero_row(torch.empty(0, 4)) is False
    assert has_zero_row(torch.zeros(6, 4)[:, ::2]) is True  # non-contiguous


def _gaussians(dtype, n=40):
    g = torch.Generator().manual_seed(2)
    return {"means": torch.randn(n, 3, generator=g).to(dtype) + torch.tensor([0.0, 0.0, 4.0], dtype=dtype),
            "quats": torch.randn(n, 4, generator=g).to(dtype), "log_scales": torch.full((n, 3), -3.0, dtype=dtype),
            "opacity_logits": torch.zeros(n, dtype=dtype), "colors": torch.rand(n, 3, generator=g).to(dtype)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_render_check_finds_each_bad_tensor(dtype):
    """`_gaussians_valid`, compiled (float32) and through torch (float16): NaN or inf in any tensor, or a
    zero quaternion, is invalid; a valid set is valid."""
    assert _gaussians_valid(Gaussians(**_gaussians(dtype))) is True
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        for bad in (float("nan"), float("inf")):
            tensors = _gaussians(dtype)
            tensors[name].view(-1)[7] = bad
            assert _gaussians_valid(Gaussians(**tensors)) is False, (name, bad)
    tensors = _gaussians(dtype)
    tensors["quats"][-1] = 0.0
    assert _gaussians_valid(Gaussians(**tensors)) is False


def test_render_names_a_zero_quaternion():
    """(The check runs before any backend; the torch backend renders the valid case without compiling.)"""
    from egobench.camera.pinhole import Pinhole

    cam = Pinhole(fx=40.0, fy=40.0, cx=16.0, cy=12.0, width=32, height=24)
    tensors = _gaussians(torch.float32)
    assert render(Gaussians(**tensors), cam, torch.eye(4), backend="torch").rgb.shape == (1, 24, 32, 3)
    tensors["quats"][3] = 0.0
    with pytest.raises(ValueError, match="quats must be non-zero quaternions"):
        render(Gaussians(**tensors), cam, torch.eye(4), backend="torch")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_render_check_and_zero_rows_on_cuda():
    """The torch path with its one host sync: the same answers as on the CPU."""
    assert _gaussians_valid(Gaussians(**{k: v.cuda() for k, v in _gaussians(torch.float32).items()})) is True
    for name, bad in (("colors", float("nan")), ("means", float("inf"))):
        tensors = {k: v.cuda() for k, v in _gaussians(torch.float32).items()}
        tensors[name].view(-1)[3] = bad
        assert _gaussians_valid(Gaussians(**tensors)) is False
    q = torch.randn(9, 4, device="cuda")
    assert has_zero_row(q) is False
    q[8] = 0.0
    assert has_zero_row(q) is True and _gaussians_valid(Gaussians(**{**{k: v.cuda() for k, v in _gaussians(
        torch.float32, n=9).items()}, "quats": q})) is False


def test_render_names_a_bad_pose():
    """A pose with NaN or inf, or a last row other than [0, 0, 0, 1] (beyond torch.allclose's tolerance), is
    named; a last row within it renders (the check runs before any backend)."""
    from egobench.camera.pinhole import Pinhole

    cam = Pinhole(fx=40.0, fy=40.0, cx=16.0, cy=12.0, width=32, height=24)
    g = Gaussians(**_gaussians(torch.float32))
    for bad in (float("nan"), float("inf")):
        T = torch.eye(4).repeat(2, 1, 1)
        T[1, 0, 3] = bad
        with pytest.raises(ValueError, match="T_world_camera must be finite"):
            render(g, cam, T, backend="torch")
    T = torch.eye(4)
    T[3, 2] = 1e-4
    with pytest.raises(ValueError, match=r"last row \[0, 0, 0, 1\]"):
        render(g, cam, T, backend="torch")
    T[3, 2] = 5e-7  # within atol 1e-6
    assert render(g, cam, T, backend="torch").rgb.shape == (1, 24, 32, 3)
