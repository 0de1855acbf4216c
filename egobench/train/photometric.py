"""The training's photometric loss, (1 - l) L1 + l (1 - SSIM) over the valid pixels (docs/paper-notes.md §6).
`photometric_loss` runs a compiled CPU kernel (the value and the gradient with respect to the
prediction in one pass, in its dtype) for CPU tensors and `photometric_loss_torch`, the oracle,
elsewhere. On one thread the torch ops took 4.3 ms (forward + backward) at 128 px and 61.7 ms at
512 px (results/speed/README.md, "The photometric loss compiled").

SSIM as `egobench.metrics.ssim_map`: a separable 11-tap Gaussian (sigma 1.5), rows then columns, over
the valid region; its backward is the same separable blur transposed (columns, then rows).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from egobench.metrics import SSIM_K1, SSIM_K2, SSIM_SIGMA, SSIM_WINDOW, gaussian_taps, ssim_loss
from egobench.render.cpu_backend import set_threads

#: SSIM's stabilisers for a data range of 1
C1, C2 = SSIM_K1**2, SSIM_K2**2


def photometric_loss_torch(pred: Tensor, gt: Tensor, mask3: Tensor, n_mask: float, ssim_lambda: float) -> Tensor:
    """(1 - l) L1 + l (1 - SSIM) of ``pred`` vs ``gt`` [H, W, 3] over the valid pixels ``mask3`` [H, W, 1]
    (``n_mask``: their count x 3), in torch ops (the oracle; any device)."""
    l1 = ((pred - gt).abs() * mask3).sum() / n_mask
    ssim_term = ssim_loss((pred * mask3)[None], (gt * mask3)[None])
    return (1 - ssim_lambda) * l1 + ssim_lambda * ssim_term


#: valid SSIM rows per parallel task (a fixed split: the same bits for any thread count)
ROWS_PER_TASK = 8
#: the blur's half width: SSIM_WINDOW taps, centre included
HALF = SSIM_WINDOW // 2
if SSIM_WINDOW != 11:  # `_window` and `_tuple11` spell the taps out
    raise ImportError(f"egobench.train.photometric: the compiled blur has 11 taps, SSIM_WINDOW is {SSIM_WINDOW}")

# The row loops below run over 1-D contiguous rows with few arrays each, so that LLVM vectorizes them
# (a loop over several 2-D arrays needed more runtime alias checks than it makes). Every blur is a gather:
# out[j] = sum over the window's taps t, in order, of taps[t] src[j + t stride]; the transposed blurs
# gather with the taps reversed from zero-padded rows.


@njit(cache=True, inline="always")
def _offsets(stride):
    """The window's unsigned offsets (0, stride, ..., (SSIM_WINDOW - 1) stride)."""
    s = np.uint64(stride)
    s2, s3 = s + s, s + s + s
    s5 = s2 + s3
    return (np.uint64(0), s, s2, s3, s2 + s2, s5, s5 + s, s5 + s2, s5 + s3, s5 + s2 + s2, s5 + s5)


@njit(cache=True, inline="always")
def _window(src, j, o, w):
    """sum_t w[t] src[j + o[t]] over the SSIM_WINDOW taps, added left to right (j, o: unsigned; no
    negative-index wraparound test, so loops over j vectorize)."""
    return (w[0] * src[j] + w[1] * src[j + o[1]] + w[2] * src[j + o[2]] + w[3] * src[j + o[3]]
            + w[4] * src[j + o[4]] + w[5] * src[j + o[5]] + w[6] * src[j + o[6]] + w[7] * src[j + o[7]]
            + w[8] * src[j + o[8]] + w[9] * src[j + o[9]] + w[10] * src[j + o[10]])


@njit(cache=True, inline="always")
def _tuple11(a):
    """The SSIM_WINDOW taps as a tuple (kept in registers through a loop)."""
    return (a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10])


@njit(cache=True)
def _blur(out, src, stride, taps):
    """out[j] = sum_t taps[t] src[j + t stride] for the SSIM_WINDOW taps (1-D rows; src holds out's length
    + (SSIM_WINDOW - 1) stride)."""
    o, w = _offsets(stride), _tuple11(taps)
    for jj in range(out.shape[0]):
        j = np.uint64(jj)
        out[j] = _window(src, j, o, w)


@njit(cache=True)
def _row_sum(a):
    """Sum of a 1-D row in float64, eight interleaved partial sums (a fixed order on every machine)."""
    acc = np.zeros(8)
    n8 = a.shape[0] // 8 * 8
    for j in range(0, n8, 8):
        for k in range(8):
            acc[k] += a[j + k]
    total = 0.0
    for j in range(n8, a.shape[0]):
        total += a[j]
    for k in range(8):
        total += acc[k]
    return total


@njit(cache=True, parallel=True)
def _l1_rows(pred, gt, mask, l1_scale, grad, l1_rows):
    """Rows [H, W*C]: ``grad`` = the L1 term's gradient (``l1_scale`` sign(pred - gt) mask, torch's abs
    backward: 0 at 0) and ``l1_rows`` [H] = each row's sum of |pred - gt| mask (float64)."""
    H, WC = pred.shape
    for i in prange(H):
        p, g, m, gr = pred[i], gt[i], mask[i], grad[i]
        err = np.empty(WC, pred.dtype)
        for j in range(WC):
            d = p[j] - g[j]
            err[j] = abs(d) * m[j]
            gr[j] = l1_scale * m[j] * (1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0))
        l1_rows[i] = _row_sum(err)


@njit(cache=True)
def _masked(x, y, pred, gt, mask):
    """x, y = pred mask, gt mask (1-D rows)."""
    for j in range(x.shape[0]):
        x[j], y[j] = pred[j] * mask[j], gt[j] * mask[j]


@njit(cache=True)
def _products(xx, yy, xy, x, y):
    """x^2, y^2, x y (1-D rows)."""
    for j in range(x.shape[0]):
        xx[j], yy[j], xy[j] = x[j] * x[j], y[j] * y[j], x[j] * y[j]


@njit(cache=True, error_model="numpy")  # no ZeroDivisionError test: an early exit stops the vectorizer
def _ssim_and_partials(stats, n, consts, out, L, lo):
    """Per position of the local statistics ``stats`` (flat [5, n]: mu_x, mu_y, E[x^2], E[y^2], E[xy]):
    ds/dmu_x, ds/dE[x^2], ds/dE[xy] and SSIM into the rows of ``out`` (flat [4, L]) from column ``lo``.
    consts = (C1, C2, 2, 1) in the rows' dtype: the arithmetic stays in it, as torch's. Two flat arrays and
    unsigned indices: one alias check, so the loop vectorizes."""
    c1, c2, two, one = consts[0], consts[1], consts[2], consts[3]
    r1, r2, r3, r4 = np.uint64(n), np.uint64(2 * n), np.uint64(3 * n), np.uint64(4 * n)
    q0, q1, q2, q3 = np.uint64(lo), np.uint64(L + lo), np.uint64(2 * L + lo), np.uint64(3 * L + lo)
    for jj in range(n):
        j = np.uint64(jj)
        mx, my, e_xx, e_yy, e_xy = stats[j], stats[j + r1], stats[j + r2], stats[j + r3], stats[j + r4]
        n1, n2 = two * mx * my + c1, two * (e_xy - mx * my) + c2
        inv_d1 = one / (mx * mx + my * my + c1)
        inv_d2 = one / ((e_xx - mx * mx) + (e_yy - my * my) + c2)
        inv = inv_d1 * inv_d2
        s = n1 * n2 * inv
        out[j + q0] = two * my * (n2 - n1) * inv - s * (two * mx) * (inv_d1 - inv_d2)
        out[j + q1] = -s * inv_d2
        out[j + q2] = two * n1 * inv
        out[j + q3] = s


@njit(cache=True, inline="always")
def _band_maps(pred, gt, mask, first, n_rows, maps):
    """maps [5, >= n_rows W*C] = x, y, x^2, y^2, x y of input rows first .. first + n_rows - 1, flat."""
    WC = pred.shape[1]
    for r in range(n_rows):
        a, b = r * WC, (r + 1) * WC
        _masked(maps[0, a:b], maps[1, a:b], pred[first + r], gt[first + r], mask[first + r])
        _products(maps[2, a:b], maps[3, a:b], maps[4, a:b], maps[0, a:b], maps[1, a:b])


@njit(cache=True, parallel=True)
def _ssim_rows(pred, gt, mask, taps, C, s_rows, rows_t):
    """Per valid row i: its SSIM sum into ``s_rows[i]`` and its partials ds/d(mu_x, E[x^2], E[xy]) blurred
    back along the row (the row blur transposed) into ``rows_t`` [3, (H' + 4 HALF) W*C] (flat rows; valid
    row i at i + 2 HALF between zero rows, so that the column blur's transpose gathers)."""
    h_out, WC = s_rows.shape[0], pred.shape[1]
    out_wc = WC - 2 * HALF * C
    taps_rev = taps[::-1].copy()
    consts = np.array([C1, C2, 2.0, 1.0]).astype(pred.dtype)
    for task in prange((h_out + ROWS_PER_TASK - 1) // ROWS_PER_TASK):
        i0 = task * ROWS_PER_TASK
        n_rows = min(h_out, i0 + ROWS_PER_TASK) - i0
        maps = np.empty((5, (ROWS_PER_TASK + 2 * HALF) * WC), pred.dtype)
        _band_maps(pred, gt, mask, i0, n_rows + 2 * HALF, maps)
        cols, stats = np.empty((5, WC), pred.dtype), np.empty((5, out_wc), pred.dtype)
        L = WC + 2 * HALF * C  # rows of part: zero-padded for the transposed row blur (the 4th holds s)
        part = np.zeros((4, L), pred.dtype)
        for i in range(i0, i0 + n_rows):
            for k in range(5):
                _blur(cols[k], maps[k, (i - i0) * WC:], WC, taps)
                _blur(stats[k], cols[k], C, taps)
            _ssim_and_partials(stats.reshape(-1), out_wc, consts, part.reshape(-1), L, 2 * HALF * C)
            s_rows[i] = _row_sum(part[3, 2 * HALF * C:2 * HALF * C + out_wc])
            for k in range(3):
                _blur(rows_t[k, (i + 2 * HALF) * WC:(i + 2 * HALF + 1) * WC], part[k], C, taps_rev)


@njit(cache=True)
def _add_ssim_grad(grad, scale, g_mu, g_xx, g_xy, x, y, mask):
    """grad += scale (g_mu + 2 x g_xx + y g_xy) mask (1-D rows; x, y: the masked images)."""
    for j in range(grad.shape[0]):
        grad[j] += scale * ((g_mu[j] + (x[j] + x[j]) * g_xx[j] + y[j] * g_xy[j]) * mask[j])


@njit(cache=True, parallel=True)
def _ssim_grad(rows_t, pred, gt, mask, taps, scale, grad):
    """grad [H, W*C] += scale x (the column blur transposed of ``rows_t``, times 1, 2x, y) x mask."""
    H, WC = grad.shape
    taps_rev = taps[::-1].copy()
    for task in prange((H + ROWS_PER_TASK - 1) // ROWS_PER_TASK):
        g, xy = np.empty((3, WC), grad.dtype), np.empty((2, WC), grad.dtype)
        for r in range(task * ROWS_PER_TASK, min(H, (task + 1) * ROWS_PER_TASK)):
            for k in range(3):  # padded row r + s holds valid row r + s - 2 HALF
                _blur(g[k], rows_t[k, r * WC:], WC, taps_rev)
            _masked(xy[0], xy[1], pred[r], gt[r], mask[r])
            _add_ssim_grad(grad[r], scale, g[0], g[1], g[2], xy[0], xy[1], mask[r])


def loss_and_grad(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, C: int, n_mask: float,
                   ssim_lambda: float, taps: np.ndarray) -> tuple[float, np.ndarray]:
    """Rows [H, W*C] of pred, gt and the mask (one float dtype, the arithmetic's) -> (the loss, d loss /
    d pred [H, W*C])."""
    H, WC = pred.shape
    h_out, dtype = H - 2 * HALF, pred.dtype.type
    grad, l1_rows, s_rows = np.empty_like(pred), np.empty(H), np.empty(h_out)
    rows_t = np.empty((3, h_out + 4 * HALF, WC), pred.dtype)
    rows_t[:, :2 * HALF] = rows_t[:, h_out + 2 * HALF:] = 0.0  # the zero rows around the valid ones
    _l1_rows(pred, gt, mask, dtype((1.0 - ssim_lambda) / n_mask), grad, l1_rows)
    _ssim_rows(pred, gt, mask, taps, C, s_rows, rows_t.reshape(3, -1))
    n_ssim = h_out * (WC - 2 * HALF * C)
    _ssim_grad(rows_t.reshape(3, -1), pred, gt, mask, taps, dtype(-ssim_lambda / n_ssim), grad)
    l1 = float(np.sum(l1_rows)) / n_mask  # numpy's pairwise sums: a fixed order, any thread count
    return (1.0 - ssim_lambda) * l1 + ssim_lambda * (1.0 - float(np.sum(s_rows)) / n_ssim), grad


class _PhotometricCPU(torch.autograd.Function):
    """`photometric_loss_torch` with compiled kernels: (pred, gt, mask3, n_mask, ssim_lambda)."""

    @staticmethod
    def forward(ctx, pred, gt, mask3, n_mask, ssim_lambda):
        H, W, C = pred.shape
        rows = [t.detach().to(pred.dtype).expand(H, W, C).reshape(H, W * C).contiguous().numpy()
                for t in (pred, gt, mask3)]
        taps = gaussian_taps(SSIM_WINDOW, float(SSIM_SIGMA), pred.dtype, torch.device("cpu")).numpy()
        set_threads()
        value, grad = loss_and_grad(*rows, C, float(n_mask), float(ssim_lambda), taps)
        ctx.grad = torch.from_numpy(grad).reshape(H, W, C)
        return torch.tensor(value, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, g):
        grad = ctx.grad if float(g) == 1.0 else g * ctx.grad  # 1 x grad: the same bits, without a pass
        return grad, None, None, None, None


def photometric_loss(pred: Tensor, gt: Tensor, mask3: Tensor, n_mask: float, ssim_lambda: float) -> Tensor:
    """`photometric_loss_torch`'s value and gradient with respect to ``pred``; compiled on the CPU (float32
    and float64). pred, gt [H, W, C], mask3 [H, W, 1] (0/1) -> scalar."""
    if pred.device.type != "cpu" or pred.dtype not in (torch.float32, torch.float64):
        return photometric_loss_torch(pred, gt, mask3, n_mask, ssim_lambda)
    if pred.dim() != 3 or pred.shape != gt.shape:
        raise ValueError(f"pred, gt: expected [H, W, C] of the same shape, got {list(pred.shape)} and {list(gt.shape)}")
    if mask3.shape not in ((*pred.shape[:2], 1), pred.shape):
        raise ValueError(f"mask3: expected [H, W, 1] or [H, W, C] for pred {list(pred.shape)}, got {list(mask3.shape)}")
    if pred.shape[0] < SSIM_WINDOW or pred.shape[1] < SSIM_WINDOW:
        raise ValueError(f"pred: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW} for SSIM, "
                         f"got {pred.shape[1]}x{pred.shape[0]}")
    return _PhotometricCPU.apply(pred, gt, mask3, n_mask, ssim_lambda)
