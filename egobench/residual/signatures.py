"""What the diagnosis needs besides the images (`DiagnosisContext`), the image operations the
signatures are built from (gradients, flow warps, radial coordinates, block sums) and the
statistics (frame-level t-tests, partial F-tests, Holm's correction).

Conventions: images are numpy float32/float64 arrays [F, H, W, 3] of display values in [0, 1]
(after the camera response, as an 8-bit image / 255). Pixel (column i, row j) has its centre at
(u, v) = (i, j). Image velocities are px/s of the static scene's projection at each pixel.
Geometric residual model: the measured image at pixel u shows what the prediction shows at
u - d(u) ("measured(u) = predicted(u - d(u))"), so to first order
``measured - predicted = -grad(predicted) . d``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
from scipy import stats as sps

from egobench.model.formation import DEFAULT_GAMMA, GammaResponse

#: One 8-bit display level.
LEVEL = 1.0 / 255.0


@dataclass
class DiagnosisContext:
    """Per-recording facts the candidate causes need (all frames of the measured stack)."""

    frame_index: np.ndarray  # [F] int, the frames' indices in the recording (held out: index % holdout_every == 0)
    exposure_s: np.ndarray  # [F] recorded exposure durations, s
    gain: np.ndarray  # [F] recorded analog gains
    valid: np.ndarray  # [H, W] bool, valid pixels (rectification mask)
    row_time_ratio: np.ndarray  # [H, W] R(u) in 0..1: raw row / (H_raw - 1), rectified like the image
    principal_point: tuple[float, float]  # (cx, cy) pixels, the optical axis of the rectified camera
    focal_px: float  # focal length of the rectified pinhole camera, pixels
    readout_s: float = 0.0  # readout duration the model assumes (metadata), s
    pixel_velocity_px_s: np.ndarray | None = None  # [F, H, W, 2] image velocity (du/dt, dv/dt) at the model's row time, px/s; None: geometric causes untestable
    gamma_assumed: float = DEFAULT_GAMMA  # response gamma the model assumes
    noise_shot: np.ndarray | None = None  # [F] assumed linear noise variance per unit linear signal (gain / full_well); None: assumed noiseless
    noise_read: np.ndarray | None = None  # [F] assumed linear read-noise variance (linear units^2); None: assumed noiseless
    lens_radial_k: tuple[float, ...] | None = None  # Fisheye624 k0..k5 of the calibration used to rectify (distortion signature); None: pure theta^3 law
    noise_reference: np.ndarray | None = None  # [F, H, W, 3] one draw of the ASSUMED noise through the same capture pipeline (noisy prediction - prediction, display); calibrates the noise test for resampling/quantisation
    render_alpha: np.ndarray | None = None  # [F, H, W] a trained model's accumulated opacity (its coverage of each pixel); None: not a trained run
    train_view_count: np.ndarray | None = None  # [F, H, W] training frames whose image holds each pixel's rendered surface (`coverage.training_view_count`); None: not a trained run
    model_pose_samples: np.ndarray | None = None  # [F] rolling-shutter pose samples a trained model rendered each frame with in its training (its sampling rule; 1: no rolling shutter); None: not a trained run
    stated_vignette: np.ndarray | None = None  # [H, W] the lens shading the prediction applies (the recording's stated vignette, linear); None: unknown
    lens_retention: float | None = None  # share of an injected lens error a trained run keeps in its residual (`egobench.diagnose.lens_check`; NaN: not measurable); None: not measured
    holdout_every: int = 8  # every n-th frame (by index) is held out for the gain measurement
    quantisation_level: float = LEVEL  # display step of the measured images (1/255 for 8-bit)
    meta: dict = field(default_factory=dict)  # free-form provenance (recording, source of the prediction)

    def validate(self, n_frames: int, height: int, width: int) -> "DiagnosisContext":
        """Check every array against the image stack [n_frames, height, width, 3]; return self."""

        def shape(name: str, expected: tuple) -> np.ndarray:
            value = getattr(self, name)
            arr = np.asarray(value)
            if arr.shape != expected:
                raise ValueError(f"DiagnosisContext.{name}: expected shape {list(expected)}, got {list(arr.shape)}")
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                raise ValueError(f"DiagnosisContext.{name}: contains NaN or inf")
            return arr

        self.frame_index = shape("frame_index", (n_frames,)).astype(np.int64)
        self.exposure_s = shape("exposure_s", (n_frames,)).astype(np.float64)
        self.gain = shape("gain", (n_frames,)).astype(np.float64)
        self.valid = shape("valid", (height, width)).astype(bool)
        self.row_time_ratio = shape("row_time_ratio", (height, width)).astype(np.float64)
        if self.pixel_velocity_px_s is not None:
            self.pixel_velocity_px_s = shape("pixel_velocity_px_s", (n_frames, height, width, 2)).astype(np.float32)
        if self.render_alpha is not None:
            self.render_alpha = shape("render_alpha", (n_frames, height, width)).astype(np.float32)
        if self.train_view_count is not None:
            self.train_view_count = shape("train_view_count", (n_frames, height, width)).astype(np.float32)
        if self.stated_vignette is not None:
            self.stated_vignette = shape("stated_vignette", (height, width)).astype(np.float64)
        if self.model_pose_samples is not None:
            self.model_pose_samples = shape("model_pose_samples", (n_frames,)).astype(np.int64)
        if self.noise_reference is not None:
            self.noise_reference = shape("noise_reference", (n_frames, height, width, 3)).astype(np.float64)
        for name in ("noise_shot", "noise_read"):
            if getattr(self, name) is not None:
                arr = shape(name, (n_frames,)).astype(np.float64)
                if np.any(arr < 0):
                    raise ValueError(f"DiagnosisContext.{name}: variances must be >= 0")
                setattr(self, name, arr)
        if (self.noise_shot is None) != (self.noise_read is None):
            raise ValueError("DiagnosisContext.noise_shot/noise_read: give both or neither")
        if not (self.focal_px > 0 and math.isfinite(self.focal_px)):
            raise ValueError(f"DiagnosisContext.focal_px: expected a positive focal length in pixels, got {self.focal_px}")
        if not (self.gamma_assumed > 0 and math.isfinite(self.gamma_assumed)):
            raise ValueError(f"DiagnosisContext.gamma_assumed: expected a positive gamma, got {self.gamma_assumed}")
        if not (self.readout_s >= 0 and math.isfinite(self.readout_s)):
            raise ValueError(f"DiagnosisContext.readout_s: expected seconds >= 0, got {self.readout_s}")
        if self.lens_radial_k is not None and len(self.lens_radial_k) != 6:
            raise ValueError(f"DiagnosisContext.lens_radial_k: expected 6 coefficients k0..k5, got {len(self.lens_radial_k)}")
        if int(self.holdout_every) < 2:
            raise ValueError(f"DiagnosisContext.holdout_every: expected an integer >= 2, got {self.holdout_every}")
        if not self.valid.any():
            raise ValueError("DiagnosisContext.valid: no valid pixel")
        return self

    @property
    def log_exposure_gain(self) -> np.ndarray:  # [F] log of the recorded exposure x gain
        return np.log(np.maximum(np.asarray(self.exposure_s) * np.asarray(self.gain), 1e-12))

    @property
    def held_out(self) -> np.ndarray:  # [F] bool
        return (np.asarray(self.frame_index) % int(self.holdout_every)) == 0

    def noise_var_linear(self, signal_linear: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Assumed linear noise variance at ``signal_linear`` [f, ...] of frames ``frames`` [f]."""
        if self.noise_shot is None:
            return np.zeros_like(signal_linear)
        extra = (1,) * (signal_linear.ndim - 1)
        shot = self.noise_shot[frames].reshape(-1, *extra)
        read = self.noise_read[frames].reshape(-1, *extra)
        return shot * np.clip(signal_linear, 0.0, None) + read


# ----------------------------------------------------------------------------- response
def response(gamma: float) -> GammaResponse:
    """The camera response egobench's formation model uses (power law with a linear toe)."""
    return GammaResponse(float(gamma))


def decode(display: np.ndarray, gamma: float) -> np.ndarray:
    """Display [...] -> linear [...] with the formation model's gamma response."""
    return response(gamma).decode(torch.from_numpy(np.asarray(display, dtype=np.float64))).numpy()


def encode(linear: np.ndarray, gamma: float) -> np.ndarray:
    """Linear [...] -> display [...] (not clipped)."""
    return response(gamma).encode(torch.from_numpy(np.asarray(linear, dtype=np.float64))).numpy()


def encode_slope(linear: np.ndarray, gamma: float) -> np.ndarray:
    """d display / d linear at ``linear`` [...] (power-law part; the toe is below any used signal)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 1e-5, None)
    return (1.0 / gamma) * x ** (1.0 / gamma - 1.0)


# ----------------------------------------------------------------------------- image operations
def gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference image gradients of img [F, H, W, C] -> (d/du, d/dv), each [F, H, W, C] per pixel."""
    gy, gx = np.gradient(np.asarray(img, dtype=np.float64), axis=(1, 2))
    return gx, gy


def hessian(img: np.ndarray, grad: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, ...]:
    """Central-difference second derivatives (d2/du2, d2/dudv, d2/dv2) of img [F, H, W, C], each
    [F, H, W, C]; ``grad``: img's `gradients` when already computed."""
    gx, gy = gradients(img) if grad is None else grad
    gxx, gxy = gradients(gx)
    _, gyy = gradients(gy)
    return gxx, gxy, gyy


def directional_second_derivative(img: np.ndarray, velocity: np.ndarray,
                                  hess: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """v^T Hess(img) v per pixel: img [F, H, W, C], velocity [F, H, W, 2] -> [F, H, W, C] (intensity / s^2).
    ``hess``: img's `hessian` when already computed."""
    gxx, gxy, gyy = hessian(img) if hess is None else hess
    vx = velocity[..., 0:1].astype(np.float64)
    vy = velocity[..., 1:2].astype(np.float64)
    return vx * vx * gxx + 2.0 * vx * vy * gxy + vy * vy * gyy


def warp(img: np.ndarray, displacement_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample img [F, H, W, C] at u - d(u) (Lanczos-4); displacement_px [F, H, W, 2] (du, dv).

    Returns (warped [F, H, W, C] float32, inside [F, H, W] bool: the sample lies in the image).
    Works a frame at a time (float64 sample positions, cast to float32 for OpenCV): no [F, H, W] float64
    sample grids (at the paper's 2400 px, 0.8 GB for 9 frames).
    """
    F, H, W, C = img.shape
    if displacement_px.shape != (F, H, W, 2):
        raise ValueError(f"displacement_px: expected shape {[F, H, W, 2]}, got {list(displacement_px.shape)}")
    v, u = _pixel_rows_cols(H, W)

    out = np.empty((F, H, W, C), dtype=np.float32)
    inside = np.empty((F, H, W), dtype=bool)
    for f in range(F):  # one remap per frame (Lanczos-4: near band-limited, so sub-pixel shifts do not blur)
        su = u - displacement_px[f, ..., 0]
        sv = v - displacement_px[f, ..., 1]
        inside[f] = (su >= 0) & (su <= W - 1) & (sv >= 0) & (sv <= H - 1)
        frame = np.ascontiguousarray(img[f], dtype=np.float32)
        if not displacement_px[f].any():  # at the pixel centres Lanczos-4 is the identity (weights 0 and 1)
            out[f] = frame  # e.g. the exposure integral's middle instant
            continue
        out[f] = cv2.remap(frame, su.astype(np.float32), sv.astype(np.float32), interpolation=cv2.INTER_LANCZOS4,
                           borderMode=cv2.BORDER_REPLICATE).reshape(H, W, C)
    return out, inside


@functools.lru_cache(maxsize=4)
def _pixel_rows_cols(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(v, u) [H, W] float64: each pixel's row and column (read-only; shared by every `warp`)."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    v.flags.writeable = u.flags.writeable = False
    return v, u


def radial_coordinates(height: int, width: int, centre: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radius [H, W] px, unit radial direction [H, W, 2], r_norm [H, W] = radius / farthest corner)."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    du, dv = u - centre[0], v - centre[1]
    radius = np.hypot(du, dv)
    direction = np.stack([du, dv], axis=-1) / np.maximum(radius, 1e-9)[..., None]
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=np.float64)
    r_max = np.max(np.hypot(corners[:, 0] - centre[0], corners[:, 1] - centre[1]))
    return radius, direction, radius / max(r_max, 1e-9)


def distortion_profile(radius_px: np.ndarray, focal_px: float, k: tuple[float, ...] | None) -> np.ndarray:
    """Radial displacement per unit k0 error in the rectified image, px: f sec^2(theta) theta^3 / r'(theta).

    A rectified pixel at field angle theta samples the raw image where the calibration's
    Fisheye624 puts theta; if the true k0 is larger by dk0 the raw sample shows the ray
    theta - dk0 theta^3 / r'(theta), i.e. the rectified content moves outward by
    dk0 * f * sec^2(theta) * theta^3 / r'(theta) (first order in dk0).
    """
    theta = np.arctan(radius_px / focal_px)
    if k is None:
        drdtheta = np.ones_like(theta)
    else:
        powers = np.arange(1, 7)
        drdtheta = 1.0 + sum((2 * p + 1) * kp * theta ** (2 * p) for p, kp in zip(powers, k))
    return focal_px * theta**3 / np.cos(theta) ** 2 / np.maximum(drdtheta, 1e-3)


#: Knots of distance from the image border (fractions of the shorter side) of `border_pull_basis`: a trained run's
#: renders sit inward of the measured frames there, by up to half a pixel at 64 px, fading about a quarter of
#: the way in (results/diagnosis/README.md, "2026-12-06: the renders' pull sits at the image border").
BORDER_KNOTS = (0.0, 1.0 / 32.0, 1.0 / 16.0, 1.0 / 8.0, 1.0 / 4.0, 3.0 / 8.0)


def border_pull_basis(height: int, width: int, knots: tuple[float, ...] = BORDER_KNOTS) -> list[np.ndarray]:
    """Per knot but the last, a displacement field [H, W, 2] px of the measured content against the render (as
    `distortion.unit_displacement`, where a lens's points outward): along the outward normal of each border,
    1 at the knot's distance from it, falling linearly to 0 at the neighbouring knots (a hat), the four
    borders summed, so a corner moves along both. One profile shared by the four borders, piecewise linear
    between the knots and 0 from the last on, is a sum of them: a trained model's under-fit at its image border,
    not a lens."""
    v, u = _pixel_rows_cols(height, width)
    sides = ((u + 0.5, -1.0, 0.0), (width - 0.5 - u, 1.0, 0.0), (v + 0.5, 0.0, -1.0), (height - 0.5 - v, 0.0, 1.0))
    at = np.asarray(knots, dtype=np.float64) * min(height, width)
    fields = []
    for k in range(len(at) - 1):
        hat = np.eye(len(at))[k]
        field = np.zeros((height, width, 2))
        for distance, nx, ny in sides:
            weight = np.interp(distance, at, hat)
            field[..., 0] += nx * weight
            field[..., 1] += ny * weight
        fields.append(field)
    return fields


def block_sum(x: np.ndarray, block: int) -> np.ndarray:
    """Sum over non-overlapping block x block tiles: x [F, H, W, ...] -> [F, H//b, W//b, ...] (edges cropped)."""
    F, H, W = x.shape[:3]
    hb, wb = H // block, W // block
    x = x[:, : hb * block, : wb * block]
    return x.reshape(F, hb, block, wb, block, *x.shape[3:]).sum(axis=(2, 4))


def box3(x: np.ndarray) -> np.ndarray:
    """3x3 box mean over the image axes of x [F, H, W, C] (edge pixels use edge replication)."""
    pad = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    H, W = x.shape[1:3]
    out = np.zeros_like(x, dtype=np.float64)
    for dy in range(3):  # 9 shifted views (a loop over the stencil, not over pixels)
        for dx in range(3):
            out += pad[:, dy : dy + H, dx : dx + W]
    return out / 9.0


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary erosion of mask [..., H, W] by a square of half-width ``radius`` (outside = False)."""
    if radius <= 0:
        return mask.copy()
    m = mask.astype(np.float32)
    t = torch.from_numpy(m.reshape(-1, 1, *m.shape[-2:]))
    pooled = -torch.nn.functional.max_pool2d(-torch.nn.functional.pad(t, (radius,) * 4, value=0.0),
                                             2 * radius + 1, stride=1)
    return pooled.numpy().reshape(mask.shape) > 0.5


def checkerboard(height: int, width: int, parity: int) -> np.ndarray:
    """[H, W] bool: pixels with (row + column) % 2 == parity (fit on one half, score the other)."""
    v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    return ((u + v) % 2) == parity


# ----------------------------------------------------------------------------- statistics
@dataclass
class FrameTest:
    """A parameter estimated once per frame, tested across frames (frames are the units)."""

    mean: float  # precision-weighted mean of the per-frame estimates
    se: float  # its standard error from the between-frame spread
    t: float  # mean / se
    df: int  # frames - 1
    p_value: float  # two-sided (or one-sided when asked)


def frame_t_test(estimates: np.ndarray, weights: np.ndarray, one_sided: bool = False) -> FrameTest:
    """Weighted t-test of H0: mean(estimates) = 0 with the frame as the unit (robust to pixel correlation).

    estimates, weights: [F]; weights are the per-frame information (inverse variances up to a
    common factor). Frames with zero weight are ignored.
    """
    est = np.asarray(estimates, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    keep = np.isfinite(est) & np.isfinite(w) & (w > 0)
    est, w = est[keep], w[keep]
    n = int(est.size)
    if n < 3:
        return FrameTest(float(np.sum(w * est) / np.sum(w)) if n else 0.0, math.inf, 0.0, max(n - 1, 0), 1.0)
    wn = w / w.sum()
    mean = float(np.sum(wn * est))
    # Between-frame dispersion, scaled so that with equal weights it is the usual s^2 / n.
    var_mean = float(np.sum(wn**2 * (est - mean) ** 2) * n / (n - 1))
    se = math.sqrt(max(var_mean, 1e-300))
    t = mean / se
    p = float(sps.t.sf(t, n - 1)) if one_sided else float(2.0 * sps.t.sf(abs(t), n - 1))
    return FrameTest(mean, se, t, n - 1, p)


def robust_sd(x: np.ndarray) -> float:
    """Median absolute deviation from the median, scaled to a Gaussian standard deviation."""
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def weighted_lstsq(X: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least squares: X [n, k], y [n], w [n] -> (coefficients [k], weighted RSS)."""
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    res = (y - X @ coef) * sw
    return coef, float(res @ res)


def partial_f_test(rss_full: float, rss_reduced: float, q: int, dof_full: int) -> tuple[float, float]:
    """F statistic and p-value of dropping q regressors from a full model with dof_full residual d.o.f."""
    if q <= 0 or dof_full <= 0 or rss_full <= 0:
        return 0.0, 1.0
    f = max(rss_reduced - rss_full, 0.0) / q / (rss_full / dof_full)
    return float(f), float(sps.f.sf(f, q, dof_full))


def holm(p_values: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (same order as given)."""
    p = np.asarray(p_values, dtype=np.float64)
    m = p.size
    order = np.argsort(p)
    adjusted = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):  # m <= 10 candidates
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
    return adjusted.tolist()


#: Tiles per image side whose contents a placebo extension shuffles (`tile_shuffled`).
PLACEBO_TILE_GRID = 8


def tile_shuffled(delta: np.ndarray, rng: np.random.Generator, grid: int = PLACEBO_TILE_GRID) -> np.ndarray:
    """A change of the prediction delta [f, H, W, C] with the contents of its grid x grid tiles permuted within
    each frame (the rows and columns past the last whole tile stay): the same values, so the same mean and the
    same squared size, at places unrelated to where the residual lies."""
    f, H, W, C = delta.shape
    th, tw = H // grid, W // grid
    out = delta.copy()
    if th == 0 or tw == 0:
        return out
    blocks = (delta[:, :grid * th, :grid * tw].reshape(f, grid, th, grid, tw, C)
              .transpose(0, 1, 3, 2, 4, 5).reshape(f, grid * grid, th, tw, C))
    for i in range(f):  # few frames
        blocks[i] = blocks[i][rng.permutation(grid * grid)]
    out[:, :grid * th, :grid * tw] = (blocks.reshape(f, grid, grid, th, tw, C).transpose(0, 1, 3, 2, 4, 5)
                                      .reshape(f, grid * th, grid * tw, C))
    return out


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Mean over frames of PSNR (peak 1) between a, b [F, H, W, 3] on mask [F, H, W] (or [H, W])."""
    mask = np.broadcast_to(mask, a.shape[:3])
    values = []
    for f in range(a.shape[0]):  # few frames
        m = mask[f]
        if not m.any():
            continue
        mse = float(np.mean((a[f][m] - b[f][m]) ** 2))
        values.append(10.0 * math.log10(1.0 / max(mse, 1e-12)))
    if not values:
        raise ValueError("psnr: no pixel to compare (empty mask)")
    return float(np.mean(values))
