"""The compiled 2DGS normal-consistency loss against its torch oracle (value and gradients), and
finite differences."""

import numpy as np
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


def _scatter_reference(P, N, wts, rays, g):
    """The kernels' sums written the plain way (Python floats, pixels in row-major order, each pixel's
    terms scattered to its four neighbours): value, dL/d depth, dL/d normal."""
    import math

    H, W = wts.shape

    def unit(x):
        s = max(math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]), 1e-12)
        return [x[0] / s, x[1] / s, x[2] / s], s

    def unit_grad(gr, x, s):
        if s > 1e-12:
            d = x[0] * gr[0] + x[1] * gr[1] + x[2] * gr[2]
            return [(gr[c] - x[c] * d) / s for c in range(3)]
        return [gr[c] / s for c in range(3)]

    total, gP, g_normal = 0.0, np.zeros((H, W, 3)), np.zeros((H, W, 3))
    for v in range(H):
        for u in range(W):
            if not (0 < v < H - 1 and 0 < u < W - 1):
                total += wts[v, u] * (1.0 - 0.0)
                continue
            a = [P[v + 1, u, c] - P[v - 1, u, c] for c in range(3)]
            b = [P[v, u + 1, c] - P[v, u - 1, c] for c in range(3)]
            dn, sd = unit([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
            rn, sr = unit(list(N[v, u]))
            total += wts[v, u] * (1.0 - (rn[0] * dn[0] + rn[1] * dn[1] + rn[2] * dn[2]))
            w = -g * wts[v, u]
            g_normal[v, u] = unit_grad([w * dn[c] for c in range(3)], rn, sr)
            gn = unit_grad([w * rn[c] for c in range(3)], dn, sd)
            ga = [b[1] * gn[2] - b[2] * gn[1], b[2] * gn[0] - b[0] * gn[2], b[0] * gn[1] - b[1] * gn[0]]
            gb = [gn[1] * a[2] - gn[2] * a[1], gn[2] * a[0] - gn[0] * a[2], gn[0] * a[1] - gn[1] * a[0]]
            for c in range(3):
                gP[v + 1, u, c] += ga[c]
                gP[v - 1, u, c] -= ga[c]
                gP[v, u + 1, c] += gb[c]
                gP[v, u - 1, c] -= gb[c]
    g_depth = rays[..., 0] * gP[..., 0] + rays[..., 1] * gP[..., 1] + rays[..., 2] * gP[..., 2]
    return total, g_depth, g_normal


def test_compiled_kernels_are_the_row_major_scatter_bit_for_bit_on_any_thread_count():
    """The kernels run rows in parallel: the value sums the pixels' terms in pixel order, and each
    point gathers its neighbours' gradient terms in the order the serial scatter added them, so the
    bits are the scatter's at every thread count."""
    import numba

    from egobench.train.normal_consistency import _nc_backward, _nc_forward

    rng = np.random.default_rng(4)
    H, W = 9, 11
    P = rng.normal(size=(H, W, 3)) + np.array([0.0, 0.0, 3.0])
    P[4] = P[3]  # a row of zero depth normals: the eps branch
    N = rng.normal(size=(H, W, 3))
    N[2, 3] = 0.0
    wts, rays = rng.random((H, W)), rng.normal(size=(H, W, 3))
    total, g_depth, g_normal = _scatter_reference(P, N, wts, rays, 0.7)
    saved = numba.get_num_threads()
    try:
        for threads in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(threads)
            got_depth, got_normal = np.full((H, W), np.nan), np.full((H, W, 3), np.nan)
            _nc_backward(P, rays, N, wts, 0.7, got_depth, got_normal)
            assert _nc_forward(P, N, wts) == total
            assert np.array_equal(got_depth.view(np.uint64), g_depth.view(np.uint64))
            assert np.array_equal(got_normal.view(np.uint64), g_normal.view(np.uint64))
    finally:
        numba.set_num_threads(saved)


def test_kernel_inputs_are_the_torch_ops_bits_for_float32_views():
    """`_nc_inputs` (back-projected points, float64 normals and weights in one compiled pass) gives the bits
    of the torch ops it replaced, for float32 inputs read through strided views as training passes them
    (the normal a channel slice of the feature image, the mask a channel of the per-channel mask)."""
    from egobench.train.normal_consistency import NCInputs, RenderedMaps, _nc_inputs, _rays

    depth, normal, alpha, mask, cam = _inputs(torch.float32, H=13, W=17, seed=5)
    mask = mask * torch.rand(13, 17, generator=torch.Generator().manual_seed(6))  # soft: products that round
    feats = torch.randn(13, 17, 7)
    feats[..., 4:7] = normal.detach()
    normal_view, mask_view = feats[..., 4:7], mask[..., None].expand(-1, -1, 3).contiguous()[..., 0]
    assert not normal_view.is_contiguous() and not mask_view.is_contiguous()  # read strided, as in training
    rays = _rays(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    count = mask_view.sum().clamp_min(1)
    want_P = rays * depth.detach()[..., None].to(torch.float64)
    want_w = alpha.to(torch.float64) * mask_view.to(torch.float64) / count.to(torch.float64)
    P, N, wts = np.empty((13, 17, 3)), np.empty((13, 17, 3)), np.empty((13, 17))
    _nc_inputs(RenderedMaps(depth.detach().numpy(), normal_view.numpy(), alpha.numpy(), mask_view.numpy()),
               rays.numpy(), float(count), NCInputs(P, N, wts))
    assert np.array_equal(P, want_P.numpy()) and np.array_equal(wts, want_w.numpy())
    assert np.array_equal(N, normal_view.to(torch.float64).numpy())
    assert float(want_w.sum()) > 0.1  # the mean alpha over a non-empty mask: the weights are not all zero
