"""Image and geometry metrics for held-out evaluation, and the SSIM training loss.

Conventions (stated once, used everywhere):

* PSNR: 10 log10(1 / MSE), data range 1, MSE over the valid pixels (mask) and all channels,
  computed in float64. The MSE is floored at 1e-10 (PSNR at most 100 dB) so records stay finite.
* SSIM: the nerfstudio/gsplat/torchmetrics convention (Wang et al. 2004): Gaussian window
  11 x 11, sigma 1.5, population covariances, K1 = 0.01, K2 = 0.03, data range 1, the SSIM map
  averaged over the "valid" region (pixels at least 5 from the border) and over channels.
  It equals ``skimage.metrics.structural_similarity(a, b, channel_axis=-1, data_range=1.0,
  gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``. `ssim_loss` uses the same
  kernel, in torch, differentiable (the training's compiled CPU loss, `egobench.train.photometric`,
  is checked against it).
* depth_si_l1: median scaling (pred * median(gt) / median(pred) over valid pixels), then mean
  absolute error in the ground truth's unit (metres).
* normal_l1: both normals normalised to unit length, then the mean over valid pixels of the sum
  over x, y, z of |n_pred - n_gt| (MonoSDF / DTC practice; range 0..2*sqrt(3)). ``normal_cos``
  (mean 1 - cos) is given beside it.
* depth_mse_authors, normal_cos_authors: the paper's Depth and Normal columns exactly as the
  authors' evaluation computes them (facebookresearch/egocentric_splats utils/eval.py): 8-bit maps
  as their renderer writes them, the ground-truth mask eroded 5 x 5, a least-squares depth scale
  and squared error, 1 - cos for normals. Table 2 prints these beside the paper's numbers;
  depth_si_l1 and normal_l1 stay in the records and results.csv as egobench's own.
* LPIPS: AlexNet, v0.1 (egobench.perceptual), from weights `egobench setup-lpips` put in the cache;
  nothing is ever downloaded at run time.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from egobench.perceptual import available
from egobench.perceptual import lpips_alex as _lpips

#: SSIM constants (one source of truth).
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
#: PSNR is capped at this value (MSE floor 10 ** (-PSNR_MAX_DB / 10)).
PSNR_MAX_DB = 100.0


def _to_tensor(x, name: str) -> Tensor:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x)
    if isinstance(x, Tensor):
        return x
    raise ValueError(f"{name}: expected a torch.Tensor or numpy array, got {type(x).__name__}")


def _image_pair(pred, target) -> tuple[Tensor, Tensor]:
    p, t = _to_tensor(pred, "pred"), _to_tensor(target, "target")
    if p.dim() != 3 or p.shape != t.shape:
        raise ValueError(f"pred, target: expected two images [H, W, C] of the same shape, got {list(p.shape)} and {list(t.shape)}")
    return p.detach().to(torch.float64), t.detach().to(device=p.device, dtype=torch.float64)


def _mask(mask, shape: tuple[int, int], device, name: str = "mask") -> Tensor:
    if mask is None:
        return torch.ones(shape, dtype=torch.bool, device=device)
    m = _to_tensor(mask, name)
    if m.dim() == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(shape):
        raise ValueError(f"{name}: expected [H, W] = {list(shape)}, got {list(m.shape)}")
    return m.to(device=device) != 0


# ----------------------------------------------------------------------------- PSNR
def psnr(pred, target, mask=None) -> float:
    """PSNR in dB of pred [H, W, C] against target [H, W, C] over mask [H, W] (data range 1)."""
    p, t = _image_pair(pred, target)
    m = _mask(mask, tuple(p.shape[:2]), p.device)
    if not bool(m.any()):
        raise ValueError("mask: no valid pixel (PSNR undefined)")
    diff = (p - t)[m]  # [V, C]
    mse = float((diff * diff).mean())
    if not np.isfinite(mse):
        raise ValueError("pred, target: non-finite values inside the mask")
    return float(-10.0 * np.log10(max(mse, 10.0 ** (-PSNR_MAX_DB / 10.0))))


# ----------------------------------------------------------------------------- SSIM
@functools.lru_cache(maxsize=8)
def gaussian_taps(window: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Normalised Gaussian taps [window] (as scipy.ndimage with truncate so that radius = window // 2),
    cached per dtype and device: the training loss does not copy them to the GPU every iteration."""
    x = torch.arange(window, dtype=torch.float64) - (window - 1) / 2.0
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(device=device, dtype=dtype)


def ssim_map(pred: Tensor, target: Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """SSIM map over the valid region: pred, target [B, H, W, C] -> [B, H-w+1, W-w+1, C]."""
    if pred.dim() != 4 or pred.shape != target.shape:
        raise ValueError(f"pred, target: expected [B, H, W, C] of the same shape, got {list(pred.shape)} and {list(target.shape)}")
    B, H, W, C = pred.shape
    if H < window or W < window:
        raise ValueError(f"pred: images must be at least {window}x{window} for SSIM, got {W}x{H}")
    x = pred.permute(0, 3, 1, 2)  # [B, C, H, W]
    y = target.permute(0, 3, 1, 2).to(x.dtype)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    g = gaussian_taps(window, float(sigma), x.dtype, x.device)
    n = stack.shape[1]
    stack = F.conv2d(stack, g.view(1, 1, window, 1).expand(n, 1, window, 1), groups=n)
    stack = F.conv2d(stack, g.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = stack.split(C, dim=1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # data range 1
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return s.permute(0, 2, 3, 1)


def ssim(pred, target, mask=None) -> float:
    """Mean SSIM of pred [H, W, C] against target [H, W, C] (see module docstring).

    With a mask [H, W], the SSIM map is averaged over the valid-region pixels whose centre is
    masked in (the window itself may reach unmasked pixels).
    """
    p, t = _image_pair(pred, target)
    s = ssim_map(p[None], t[None])[0]  # [H', W', C]
    r = SSIM_WINDOW // 2
    m = _mask(mask, tuple(p.shape[:2]), p.device)[r : p.shape[0] - r, r : p.shape[1] - r]
    if not bool(m.any()):
        raise ValueError("mask: no valid pixel at least 5 pixels from the border (SSIM undefined)")
    value = float(s[m].mean())
    if not np.isfinite(value):
        raise ValueError("pred, target: non-finite values (SSIM undefined)")
    return value


def ssim_loss(pred: Tensor, target: Tensor) -> Tensor:
    """1 - mean SSIM of pred [B, H, W, 3] against target [B, H, W, 3]; differentiable (same kernel)."""
    return 1.0 - ssim_map(pred, target).mean()


# ----------------------------------------------------------------------------- geometry
def _geometry_mask(mask, shape, device) -> Tensor:
    return _mask(mask, shape, device)


def depth_si_l1(pred_depth, gt_depth, mask=None) -> float:
    """Scale-invariant depth L1 (metres): mean |s * pred - gt| with s = median(gt) / median(pred).

    pred_depth, gt_depth: [H, W] (or [H, W, 1]); mask [H, W]. Pixels with a non-positive or
    non-finite depth in either map are excluded.
    """
    p, g = _to_tensor(pred_depth, "pred_depth"), _to_tensor(gt_depth, "gt_depth")
    if p.dim() == 3 and p.shape[-1] == 1:
        p = p[..., 0]
    if g.dim() == 3 and g.shape[-1] == 1:
        g = g[..., 0]
    if p.dim() != 2 or p.shape != g.shape:
        raise ValueError(f"pred_depth, gt_depth: expected [H, W] of the same shape, got {list(p.shape)} and {list(g.shape)}")
    p = p.detach().to(torch.float64)
    g = g.detach().to(device=p.device, dtype=torch.float64)
    m = _geometry_mask(mask, tuple(p.shape), p.device)
    m = m & torch.isfinite(p) & torch.isfinite(g) & (p > 0) & (g > 0)
    if not bool(m.any()):
        raise ValueError("mask: no pixel with a valid (finite, positive) depth in both maps")
    pv, gv = p[m], g[m]
    scale = torch.quantile(gv, 0.5) / torch.quantile(pv, 0.5)
    return float((scale * pv - gv).abs().mean())


def _normal_pair(pred_normal, gt_normal, mask) -> tuple[Tensor, Tensor]:
    p, g = _to_tensor(pred_normal, "pred_normal"), _to_tensor(gt_normal, "gt_normal")
    if p.dim() != 3 or p.shape[-1] != 3 or p.shape != g.shape:
        raise ValueError(f"pred_normal, gt_normal: expected [H, W, 3] of the same shape, got {list(p.shape)} and {list(g.shape)}")
    p = p.detach().to(torch.float64)
    g = g.detach().to(device=p.device, dtype=torch.float64)
    pn, gn = p.norm(dim=-1), g.norm(dim=-1)
    m = _geometry_mask(mask, tuple(p.shape[:2]), p.device)
    m = m & torch.isfinite(pn) & torch.isfinite(gn) & (pn > 1e-8) & (gn > 1e-8)
    if not bool(m.any()):
        raise ValueError("mask: no pixel with a non-zero normal in both maps")
    return p[m] / pn[m][:, None], g[m] / gn[m][:, None]


def normal_l1(pred_normal, gt_normal, mask=None) -> float:
    """Mean over valid pixels of sum_xyz |n_pred - n_gt| for unit normals [H, W, 3] (MonoSDF/DTC)."""
    p, g = _normal_pair(pred_normal, gt_normal, mask)
    return float((p - g).abs().sum(dim=-1).mean())


def normal_cos(pred_normal, gt_normal, mask=None) -> float:
    """Mean over valid pixels of 1 - cos(angle) between normals [H, W, 3]."""
    p, g = _normal_pair(pred_normal, gt_normal, mask)
    return float((1.0 - (p * g).sum(dim=-1)).mean())


# ----------------------------------------------------------------------------- the authors' geometry metrics
#: facebookresearch/egocentric_splats, utils/eval.py (Table 2's Depth and Normal columns): a 5 x 5
#: erosion of the ground-truth mask, 8-bit maps as their renderer writes them.
AUTHORS_ERODE_PX = 5


def erode_mask_authors(mask) -> Tensor:
    """The authors' evaluation mask: the ground-truth mask [H, W] eroded by a 5 x 5 square (cv2.erode)."""
    m = _to_tensor(mask, "mask").detach().cpu().to(torch.float64).numpy()
    eroded = cv2.erode(m, np.ones((AUTHORS_ERODE_PX, AUTHORS_ERODE_PX), np.uint8))
    return torch.from_numpy(eroded > 0.5)


def _authors_mask(gt_mask) -> np.ndarray:
    """`erode_mask_authors` as a numpy mask; ValueError when nothing is left of it."""
    m = erode_mask_authors(gt_mask).numpy()
    if not m.any():
        raise ValueError("gt_mask: empty after the authors' 5 x 5 erosion")
    return m


def _as_png8(x: np.ndarray) -> np.ndarray:
    """What an 8-bit PNG of values in [0, 1] holds when read back /255 (``(x * 255).astype(uint8)`` truncates)."""
    return np.floor(np.clip(x, 0.0, 1.0) * 255.0) / 255.0


def _depth_png(depth: np.ndarray) -> np.ndarray:
    """A depth map as the authors' renderer stores it: min-max normalised over the image, 8-bit."""
    lo, hi = float(depth.min()), float(depth.max())
    return _as_png8((depth - lo) / (hi - lo) if hi > lo else np.zeros_like(depth))


def depth_mse_authors(pred_depth, gt_depth, gt_mask) -> float:
    """The authors' scale-invariant depth error (Table 2's Depth): both maps min-max normalised over
    the image and stored as 8 bits, the ground-truth mask eroded 5 x 5, the least-squares scale
    s = sum(gt pred) / sum(pred^2) over it (pred = 1 where it is all zero), then mean (s pred - gt)^2."""
    p = _to_tensor(pred_depth, "pred_depth").detach().cpu().to(torch.float64).numpy().squeeze()
    g = _to_tensor(gt_depth, "gt_depth").detach().cpu().to(torch.float64).numpy().squeeze()
    if p.ndim != 2 or p.shape != g.shape:
        raise ValueError(f"pred_depth, gt_depth: expected [H, W] of the same shape, got {list(p.shape)} and {list(g.shape)}")
    p, g, m = _depth_png(p), _depth_png(g), _authors_mask(gt_mask)
    if (p[m] ** 2).sum() <= 1e-6:
        p = np.ones_like(g)
    scale = (g[m] * p[m]).sum() / (p[m] ** 2).sum()
    return float(((scale * p - g) ** 2)[m].mean())


def normal_cos_authors(pred_normal, gt_normal, gt_mask) -> float:
    """The authors' normal error (Table 2's Normal): both normals stored as 8-bit (n + 1) / 2 and read
    back as (x / 255 - 0.5) * 2 (not renormalised), then the mean of 1 - n_pred . n_gt over the
    ground-truth mask eroded 5 x 5 (a pixel without a predicted normal scores about 1)."""
    p = _to_tensor(pred_normal, "pred_normal").detach().cpu().to(torch.float64).numpy()
    g = _to_tensor(gt_normal, "gt_normal").detach().cpu().to(torch.float64).numpy()
    if p.ndim != 3 or p.shape[-1] != 3 or p.shape != g.shape:
        raise ValueError(f"pred_normal, gt_normal: expected [H, W, 3] of the same shape, got {list(p.shape)} and {list(g.shape)}")
    decode = lambda n: (_as_png8((n + 1.0) / 2.0) - 0.5) * 2.0  # noqa: E731
    m = _authors_mask(gt_mask)
    return float((1.0 - (decode(p) * decode(g)).sum(-1))[m].mean())


# ----------------------------------------------------------------------------- LPIPS
def lpips_available(side_px: int | None = None) -> tuple[bool, str]:
    """(True, "") when LPIPS (AlexNet, v0.1) can run offline on images ``side_px`` a side; else
    (False, the reason)."""
    return available(side_px)


def lpips_alex(pred, target) -> float:
    """LPIPS (AlexNet, v0.1) of pred [H, W, 3] against target [H, W, 3] in [0, 1] (`egobench.perceptual`).

    Raises RuntimeError with the reason when `lpips_available()` is False (never downloads).
    """
    p, t = _image_pair(pred, target)
    return _lpips(p, t)
