"""`all_finite`, the trainer's divergence test: against torch.isfinite on CPU tensors of each float dtype,
with NaN and infinities placed anywhere (also past a vector's width and in non-contiguous views)."""

import pytest
import torch

from egobench.train.finite import all_finite


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
