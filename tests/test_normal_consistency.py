"""The compiled 2DGS normal-consistency loss against its torch oracle (value and gradients), and
finite differences."""

import torch

from egobench.camera.pinhole import Pinhole
from egobench.train.normal_consistency import normal_consistency, normal_consistency_torch


def _inputs(dtype, H=9, W=11, seed=0):
    g = torch.Generator().manual_seed(seed)
    cam = Pinhole(fx=12.0, fy=11.0, cx=5.3, cy=4.1, width=W, height=H)
    depth = (2.0 + torch.rand(H, W, generator=g, dtype=dtype)).requires_grad_(True)
    normal = torch.randn(H, W, 3, generator=g, dtype=dtype)
    normal[2, 3] = 0.0  # a zero rendered normal: F.normalize's eps branch
    normal.requires_grad_(True)
    alpha = torch.rand(H, W, generator=g, dtype=dtype)
    mask = (torch.rand(H, W, generator=g) > 0.3).to(dtype)
    return depth, normal, alpha, mask, cam


def _value_and_grads(fn, depth, normal, alpha, mask, cam):
    loss = fn(depth, normal, alpha, mask, cam)
    g_depth, g_normal = torch.autograd.grad(loss, (depth, normal))
    return loss.detach(), g_depth, g_normal


def test_compiled_normal_consistency_matches_the_torch_oracle():
    args = _inputs(torch.float64)
    ref = _value_and_grads(normal_consistency_torch, *args)
    got = _value_and_grads(normal_consistency, *args)
    assert float(ref[0]) > 0.1  # random normals: far from consistent
    for r, g in zip(ref, got):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)
    assert float(got[1].abs().sum()) > 0 and float(got[2][2, 3].abs().sum()) > 0  # the eps branch carries a gradient


def test_compiled_normal_consistency_in_float32_keeps_dtype_and_value():
    args64 = _inputs(torch.float64, seed=1)
    args32 = tuple(a.detach().float().requires_grad_(a.requires_grad) if torch.is_tensor(a) else a for a in args64)
    ref = _value_and_grads(normal_consistency_torch, *args64)
    got = _value_and_grads(normal_consistency, *args32)
    assert got[0].dtype == got[1].dtype == got[2].dtype == torch.float32
    for r, g in zip(ref, got):
        torch.testing.assert_close(g.double(), r, rtol=1e-4, atol=1e-5)


def test_compiled_normal_consistency_gradients_match_finite_differences():
    depth, normal, alpha, mask, cam = _inputs(torch.float64, H=6, W=7, seed=2)
    with torch.no_grad():
        normal[2, 3] = torch.tensor([0.2, -0.1, -0.9], dtype=torch.float64)  # away from the kink at 0
    assert torch.autograd.gradcheck(lambda d, n: normal_consistency(d, n, alpha, mask, cam), (depth, normal))


def test_a_plane_rendered_with_its_own_normal_is_consistent():
    """Depth of a tilted plane and its camera-facing unit normal everywhere: the loss is 0 (up to
    rounding) where the depth normal exists; the border pixels count with depth normal 0."""
    cam = Pinhole(fx=20.0, fy=20.0, cx=7.5, cy=7.5, width=16, height=16)
    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64), dim=0)
    c = float(n @ torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    rays = cam.unproject(cam.pixel_grid(dtype=torch.float64))
    depth = c / (rays @ n)
    normal = n.expand(16, 16, 3).clone()
    alpha = torch.ones(16, 16, dtype=torch.float64)
    interior = torch.zeros(16, 16, dtype=torch.float64)
    interior[1:-1, 1:-1] = 1.0
    assert float(normal_consistency(depth, normal, alpha, interior, cam)) < 1e-12
    # the whole image: the 60 border pixels have err = 1
    assert abs(float(normal_consistency(depth, normal, alpha, torch.ones_like(alpha), cam)) - 60 / 256) < 1e-12
