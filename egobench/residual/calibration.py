"""What the placebos of a trained run share: the evidence they are computed from, and the record they return.

On a trained run a cause must be significant against a null that holds the model's own error, not only the sensor
noise (docs/diagnosis.md, "Trained runs"). Each effect calibrates its own test (`Cause.trained_placebos`, in its file
under egobench/effects/); this module holds what those calibrations share:

* `TrainedRunEvidence`: the run's residual at the render's resolution and the fits the photometric placebos read,
  computed once and shared (the render's blur, the cell fit, the per-frame estimates, a memo for the rest);
* the photometric machinery: cells, radial terms, per-frame fits tested across frames;
* the rank tests: `sequential_rank_p` (Besag-Clifford), `beat_placebos` (a few placebos and their tail);
* the velocity placebo of every motion-driven cause (`velocity_placebo`);
* `PlaceboRecord`, what a placebo says about a cause, and `merge_record`, the one place that writes it into the
  cause's result (the cause's p-value becomes the larger of its own and the placebo's).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from dataclasses import replace as dc_replace
from typing import Any

import numpy as np
import scipy.stats as sps

from egobench.residual.estimation import BLOCK_PX, CauseResult, PhotometricFit, ResidualData, gaussian_lowpass
from egobench.residual.permuted import PermutedVelocitySlopes
from egobench.residual.signatures import decode, encode, frame_t_test, weighted_lstsq

#: Offsets of the wrong centres of the vignette placebo, as fractions of (width, height).
PLACEBO_CENTRE_OFFSETS = ((0.25, 0.0), (-0.25, 0.0), (0.0, 0.25), (0.0, -0.25),
                          (0.25, 0.25), (-0.25, 0.25), (0.25, -0.25), (-0.25, -0.25))


@dataclass
class Cells:
    """The photometric cells of a fit with their frame, block row/column and channel."""

    frame: np.ndarray  # [n] frame position within the fit
    row: np.ndarray  # [n] block row
    col: np.ndarray  # [n] block column
    n_cols: int  # block columns per frame


def photometric_cells(fit: PhotometricFit) -> Cells:
    idx = np.flatnonzero(fit.cell_ok.ravel())
    f, by, bx, _c = np.unravel_index(idx, fit.cell_ok.shape)
    return Cells(f, by, bx, fit.cell_ok.shape[2])


def radial_terms(cells: Cells, centre: tuple[float, float], height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(r^2, r^4) at the block centres about ``centre`` (px), r normalised by the farthest corner."""
    u = cells.col * BLOCK_PX + (BLOCK_PX - 1) / 2.0
    v = cells.row * BLOCK_PX + (BLOCK_PX - 1) / 2.0
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=np.float64)
    r_max = np.max(np.hypot(corners[:, 0] - centre[0], corners[:, 1] - centre[1]))
    r2 = ((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / r_max**2
    return r2, r2**2


def log_measured(fit: PhotometricFit) -> np.ndarray:
    """Cell log MEASURED linear intensity [n] (centred): the response regressor on a trained run.

    The cell-level fit regresses y = log(m / p) on log p; a model's own multiplicative error e sits in
    both (y = -e, log p = log L + e), which biases the slope by -var(e) / var(log p): a trained model
    always looks like a response error (errors in variables). Regressed on log m instead, y is
    uncorrelated with the regressor when only the model errs, and a response error k (log m = k log L)
    still gives the slope (k - 1) / k."""
    log_m = fit.y + fit.log_p  # log(sum m / n) up to the +var/2 bias correction
    return log_m - float(np.average(log_m, weights=fit.w))


def local_contrast(fit: PhotometricFit) -> np.ndarray:
    """Cell log measured intensity minus the mean over its 3 x 3-cell neighbourhood (same frame and
    channel) [n]: a nuisance on a trained run. A blurry (under-fitted) model leaks light from bright
    cells into dark neighbours, so y = log(m / p) grows with LOCAL contrast, which mimics a response
    error; with this column, the response slope is identified from intensity levels across the
    image and across frames (exposure changes), which a gamma error changes and blur does not."""
    grid = np.full(fit.cell_ok.shape, np.nan)
    grid[fit.cell_ok] = fit.y + fit.log_p
    pad = np.pad(grid, ((0, 0), (1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    hb, wb = grid.shape[1:3]
    stack = np.stack([pad[:, 1 + dy: 1 + dy + hb, 1 + dx: 1 + dx + wb] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    finite = np.isfinite(stack)
    neigh = np.where(finite, stack, 0.0).sum(axis=0) / np.maximum(finite.sum(axis=0), 1)  # centre finite where ok
    return (grid - neigh)[fit.cell_ok]


def _nuisance(fit: PhotometricFit, views: bool) -> list[np.ndarray]:
    """Cell columns a shading fit carries [n each]: local contrast, and with ``views`` on a trained
    run the log count of training views of the cell's surface (`PhotometricFit.log_views`). A model
    under-fits content few views saw (the periphery, a turn's leading edge), which darkens or
    brightens its renders there; a lens shading follows the radius at any view count."""
    return [local_contrast(fit)] + ([fit.log_views] if views and fit.log_views is not None else [])


def per_frame_photometric(fit: PhotometricFit, cells: Cells, r2: np.ndarray, r4: np.ndarray, views: bool = True
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame weighted fits of the cell log ratios on [1, R, B, r^2, r^4, log m (centred),
    nuisance columns (`_nuisance`)]
    -> (estimates [f, 6]: log R gain, log B gain, corner log shading a2 + a4, slope c' on log m, and the
    shading's slopes in r^2 at the centre, a2, and at the corner, a2 + 2 a4; variances [f, 6] from each frame's
    own residual scatter; NaN where a frame has too few cells)."""
    keep = fit.keep
    X = np.stack([np.ones(fit.n_cells), (fit.cidx == 0).astype(float), (fit.cidx == 2).astype(float),
                  r2, r4, log_measured(fit)] + _nuisance(fit, views), axis=1)
    L = np.zeros((6, X.shape[1]))
    L[0, 1] = L[1, 2] = 1.0
    L[2, 3] = L[2, 4] = 1.0
    L[3, 5] = 1.0
    L[4, 3] = 1.0
    L[5, 3], L[5, 4] = 1.0, 2.0
    est = np.full((fit.n_frames, 6), np.nan)
    var = np.full((fit.n_frames, 6), np.nan)
    for f in range(fit.n_frames):  # one small solve per frame
        sel = keep & (cells.frame == f)
        if sel.sum() < 24:
            continue
        cols = np.r_[np.arange(6), [c for c in range(6, X.shape[1]) if np.ptp(X[sel, c]) > 1e-9]]  # a flat nuisance: none
        Xf, yf, wf = X[np.ix_(sel, cols)], fit.y[sel], fit.w[sel]
        XtWX = (Xf * wf[:, None]).T @ Xf
        if np.linalg.cond(XtWX) > 1e10:
            continue
        coef, rss = weighted_lstsq(Xf, yf, wf)
        s2 = rss / max(int(sel.sum()) - len(cols), 1)  # overdispersion: the frame's own scatter
        cov = np.linalg.inv(XtWX) * s2
        est[f] = L[:, cols] @ coef
        var[f] = np.diag(L[:, cols] @ cov @ L[:, cols].T)
    return est, var


def frame_test(est: np.ndarray, var: np.ndarray):
    ok = np.isfinite(est) & np.isfinite(var) & (var > 0)
    return frame_t_test(est[ok], 1.0 / var[ok])


def radial_rss(fit: PhotometricFit, cells: Cells, r2: np.ndarray, r4: np.ndarray, views: bool = True) -> float:
    """Weighted RSS of the pooled cell fit [frame dummies, R, B, r^2, r^4, log m, nuisance] (kept cells)."""
    k = fit.keep
    frame = np.zeros((fit.n_cells, fit.n_frames))
    frame[np.arange(fit.n_cells), cells.frame] = 1.0
    X = np.concatenate([frame, np.stack([(fit.cidx == 0).astype(float), (fit.cidx == 2).astype(float), r2, r4,
                                         log_measured(fit)] + _nuisance(fit, views), axis=1)], axis=1)
    return weighted_lstsq(X[k], fit.y[k], fit.w[k])[1]


#: Gaussian sigmas (px) tried for the render's blur relative to the measured frames.
BLUR_SIGMAS_PX = tuple(round(0.1 * k, 1) for k in range(21))


def _blur_linear(display: np.ndarray, sigma: float, gamma: float) -> np.ndarray:
    """Gaussian blur of display images [f, H, W, 3] in linear space (light spreads linearly)."""
    return np.clip(encode(gaussian_lowpass(decode(display, gamma), sigma), gamma), 0.0, 1.0) if sigma > 0 else display


#: The assumed noise's per-pixel variance of a prediction: (predicted [f, H, W, 3], ctx, frames) -> [f, H, W, 3].
NoiseVariance = Callable[[np.ndarray, Any, np.ndarray], np.ndarray]


def render_blur(data: ResidualData, noise_variance: NoiseVariance) -> float:
    """The Gaussian sigma (px, from BLUR_SIGMAS_PX) that, applied to the measured frames, best
    matches the prediction (least squares on usable pixels): a trained model's renders are blurrier
    than the frames, which leaks light between neighbouring cells (a response-like signature)."""
    m = data.usable
    noise = _noise_after_blur(data, noise_variance)
    errs = [float(np.mean((_blur_linear(data.m, s, data.ctx.gamma_assumed) - data.p)[m] ** 2)) - noise(s)
            for s in BLUR_SIGMAS_PX]
    return BLUR_SIGMAS_PX[int(np.argmin(errs))]


def _noise_after_blur(data: ResidualData, noise_variance: NoiseVariance):
    """sigma -> expected noise variance left in the blurred measured frames (usable pixels): the
    blur also averages the measurement noise away, which must not count as a better match. With a
    pipeline noise reference, that reference blurred; else the analytic variance x sum of squared
    kernel weights."""
    m = data.usable
    if data.ctx.noise_reference is not None:
        ref = data.ctx.noise_reference[data.frames]
        return lambda s: float(np.mean((gaussian_lowpass(ref, s) if s > 0 else ref)[m] ** 2))
    if data.ctx.noise_shot is None:
        var = data.ctx.quantisation_level**2 / 12.0
    else:
        var = float(np.mean(noise_variance(data.p, data.ctx, data.frames)[m]))
    delta = np.zeros((1, 15, 15, 1))
    delta[0, 7, 7, 0] = 1.0
    return lambda s: var * (float(np.sum(gaussian_lowpass(delta, s) ** 2)) if s > 0 else 1.0)


def resolution_matched(data: ResidualData, sigma: float) -> ResidualData:
    """``data`` with the measured frames blurred by ``sigma`` px (linear space): measured and
    predicted at the same resolution, so photometric statistics see no leakage between cells."""
    if sigma <= 0:
        return data
    return data.with_measurement(_blur_linear(data.m, sigma, data.ctx.gamma_assumed))


#: The sequential permutation test of the motion placebos (Besag & Clifford 1991): stop at the
#: PLACEBO_STOP-th placebo statistic at least as extreme as the real one, else after PLACEBO_MAX
#: placebos. Its smallest p, 1 / (1 + PLACEBO_MAX) = 0.001, passes Holm over nine causes at alpha 0.01.
PLACEBO_STOP, PLACEBO_MAX = 10, 999


def sequential_rank_p(t_real: float, draw_t: Callable[[int], float], one_sided: bool = False,
                      stop: int = PLACEBO_STOP, n_max: int = PLACEBO_MAX) -> tuple[float, int, list[float]]:
    """Besag-Clifford p of ``t_real`` against placebo statistics draw_t(0), draw_t(1), ...: h / n when
    the h-th (= ``stop``) placebo at least as extreme comes at draw n, else (1 + exceed) / (1 + n_max).
    At least as extreme: t >= t_real (one-sided), |t| >= |t_real| (two-sided). -> (p, exceed, the
    placebo statistics drawn). A rank p assumes nothing about the placebos' distribution: a poorly
    fitted run's heavy-tailed or shifted placebo statistics cannot make it small."""
    ts: list[float] = []
    exceed = 0
    for k in range(n_max):
        t = float(draw_t(k))
        ts.append(t)
        exceed += int(t >= t_real) if one_sided else int(abs(t) >= abs(t_real))
        if exceed >= stop:
            return exceed / len(ts), exceed, ts
    return (1 + exceed) / (1 + n_max), exceed, ts


class Derangements:
    """The k-th random permutation of n frames with no frame in place, drawn lazily from one seeded
    stream (every cause sees the same sequence)."""

    def __init__(self, n: int, seed: int) -> None:
        if n < 2:
            raise ValueError(f"Derangements: {n} frame(s) have no permutation without a frame in place (need >= 2)")
        self.n, self.rng, self.perms = n, np.random.default_rng([int(seed), 1515]), []

    def __getitem__(self, k: int) -> np.ndarray:
        while len(self.perms) <= k:
            perm = self.rng.permutation(self.n)
            if np.all(perm != np.arange(self.n)):
                self.perms.append(perm)
        return self.perms[k]


def velocity_tables(cause, data: ResidualData, t_real: float, j: int, one_sided: bool):
    """The velocity placebos' moment tables (`egobench.residual.permuted`) of a cause that gives its
    regressors as velocity polynomials, else None. Checked on the true pairing: its t must be the
    cause's own (a basis that drifted from the regressors is a bug, not a placebo)."""
    basis = cause.velocity_basis(data)
    if basis is None:
        return None
    basis = basis + cause.nuisance_basis(data)
    tables = PermutedVelocitySlopes(basis, data.velocity, data.p, data.r, data.usable)
    est, info = tables.slopes(np.arange(data.frames.size))
    t_same = frame_t_test(est[:, j], info[:, j], one_sided=one_sided).t
    if not math.isclose(t_same, t_real, rel_tol=1e-6, abs_tol=1e-9):
        raise RuntimeError(f"{cause.name}: velocity_basis gives t = {t_same} on the true pairing, its regressors "
                           f"{t_real}; the basis must describe `regressors`")
    return tables


def beat_placebos(t_real: float, t_placebo: list[float]) -> tuple[float, int, float]:
    """(p, exceed, p_tail) of a statistic against a few placebo statistics: the larger of the rank p
    (1 + exceed) / (1 + n) when a placebo's |t| is as large, and the tail of |t| as a new draw from the
    placebos' |t| (a handful of placebos cannot give a small rank p alone). The tail is the Student-t
    prediction interval of n draws, (|t| - mean) / (sd sqrt(1 + 1/n)) on n - 1 degrees of freedom: the
    placebos' mean and sd are estimates (a normal tail named distortion on an outdoor response case
    at t 4.6 against 8 wrong centres at 2.1 +- 0.6: p 6e-5; this tail: 0.004). Needs at least two placebos."""
    if len(t_placebo) < 2:
        raise ValueError(f"beat_placebos: needs at least 2 placebo statistics for their spread, got {len(t_placebo)}")
    exceed = int(sum(abs(t) >= abs(t_real) for t in t_placebo))
    a = np.abs(np.asarray(t_placebo))
    n = a.size
    z = (abs(t_real) - a.mean()) / _prediction_sd(max(float(a.std(ddof=1)), 1e-12), n)
    p_tail = float(sps.t.sf(z, n - 1))
    return max((1 + exceed) / (1 + len(t_placebo)) if exceed else 0.0, p_tail), exceed, p_tail


def _prediction_sd(sd: float, n: int) -> float:
    """The scale of a new draw's Student-t prediction interval from n draws of this sd: sd sqrt(1 + 1/n)."""
    return sd * math.sqrt(1.0 + 1.0 / n)


def prediction_bound(mean: float, sd: float, n: int, level: float) -> float:
    """The value a new draw exceeds with probability ``level`` under the Student-t prediction interval of n draws
    of this mean and sd: mean + sd sqrt(1 + 1/n) t_{n-1}(1 - level), the inverse of `beat_placebos`' tail."""
    return float(mean + _prediction_sd(sd, n) * sps.t.isf(level, n - 1))


# ------------------------------------------------------------------------------------------------
# What a placebo says about a cause, and the evidence the placebos share

#: In `PlaceboRecord.params`: "the cause's own p-value before this record raises it" (kept for the record).
OWN_P = "<own p-value>"


@dataclass
class PlaceboRecord:
    """What one placebo says about one cause, merged into its `CauseResult` by `merge_record`.

    p_value: the placebo's p (the cause's p-value becomes the larger of its own and this); None: it raises nothing.
    params: entries for the cause's params, in this order; a value `OWN_P` stands for the cause's p before the merge.
    untestable: the placebo shows the run cannot test the cause (``reason`` says why).
    reason: the result's reason, when the placebo gives one."""

    p_value: float | None
    params: dict = field(default_factory=dict)
    untestable: bool = False
    reason: str | None = None


def merge_record(result: CauseResult, record: PlaceboRecord) -> None:
    """Write ``record`` into ``result`` (in place): its params, the raised p-value, and its testability."""
    for key, value in record.params.items():
        result.params[key] = result.p_value if isinstance(value, str) and value == OWN_P else value
    if record.p_value is not None:
        result.p_value = max(result.p_value, record.p_value)
    if record.untestable:
        result.testable = False
    if record.reason is not None:
        result.reason = record.reason


class TrainedRunEvidence:
    """A trained run's residual and the fits its placebos share, each computed once on first use.

    draws: placebo draws of the permutation tests; seed: the round's placebo seed (every test draws its own stream
    from it); noise_variance: the assumed noise's variance of a prediction (the variance-model effect's)."""

    def __init__(self, data: ResidualData, draws: int, seed: int, noise_variance: NoiseVariance) -> None:
        self.data, self.draws, self.seed = data, int(draws), int(seed)
        self.noise_variance = noise_variance
        self._memo: dict = {}

    def memo(self, fn: Callable, *args) -> Any:
        """fn(self, *args), computed once per (fn, args): a statistic two causes' placebos read."""
        key = (fn, args)
        if key not in self._memo:
            self._memo[key] = fn(self, *args)
        return self._memo[key]

    @property
    def blur_px(self) -> float:
        """The render's blur relative to the measured frames (`render_blur`), px."""
        return self.memo(_blur_px)

    @property
    def photometric_fit(self) -> PhotometricFit:
        """The photometric cell fit of the measured frames at the render's resolution (`resolution_matched`)."""
        return self.memo(_matched_fit)

    @property
    def cells(self) -> Cells:
        return self.memo(_cells_of)

    @property
    def frame_estimates(self) -> tuple[np.ndarray, np.ndarray]:
        """`per_frame_photometric` about the principal point without view counts: (estimates [f, 6], variances)."""
        return self.memo(_frame_estimates)

    def rng(self, stream: int) -> np.random.Generator:
        """A fresh generator of the placebo stream ``stream`` of this round."""
        return np.random.default_rng([self.seed, int(stream)])

    @property
    def derangements(self) -> Derangements:
        """The velocity placebos' frame permutations (every motion-driven cause sees the same sequence)."""
        return self.memo(_derangements_of)


def _blur_px(ev: TrainedRunEvidence) -> float:
    return render_blur(ev.data, ev.noise_variance)


def _cells_of(ev: TrainedRunEvidence) -> Cells:
    return photometric_cells(ev.photometric_fit)


def _derangements_of(ev: TrainedRunEvidence) -> Derangements:
    return Derangements(ev.data.frames.size, ev.seed)


def _matched_fit(ev: TrainedRunEvidence) -> PhotometricFit:
    return resolution_matched(ev.data, ev.blur_px).photometric()


def _frame_estimates(ev: TrainedRunEvidence) -> tuple[np.ndarray, np.ndarray]:
    H, W = ev.data.m.shape[1:3]
    r2, r4 = radial_terms(ev.cells, ev.data.ctx.principal_point, H, W)
    return per_frame_photometric(ev.photometric_fit, ev.cells, r2, r4, views=False)


def velocity_placebo(cause, result: CauseResult, evidence: TrainedRunEvidence,
                     n_placebo: int = PLACEBO_MAX) -> PlaceboRecord | None:
    """The placebo of a motion-driven cause on a trained run (None where the run has no image velocity).

    Placebo: each frame's residual regressed on the signature built with ANOTHER frame's image velocity (a random
    permutation of the frames' velocity fields), tested across frames like the real statistic. Model error not tied
    to the motion (an isotropically blurry or misplaced render) gives the same statistic under the placebos; a
    timing error only with the true motion. p = `sequential_rank_p` of the real statistic among up to
    ``n_placebo`` placebos."""
    data = evidence.data
    v = data.ctx.pixel_velocity_px_s
    if v is None or data.frames.size < 4:
        return None
    perms = evidence.derangements
    data.share_derivatives()  # every placebo below is a shallow copy with another velocity field
    j, one_sided = cause.tested_index, cause.one_sided

    def t_of(d):
        est, info = cause.first_order(d)
        return frame_t_test(est[:, j], info[:, j], one_sided=one_sided).t

    t_real = t_of(data)
    tables = velocity_tables(cause, data, t_real, j, one_sided)

    def placebo_t(k):
        if tables is not None:  # the same statistic from the velocity tables
            est, info = tables.slopes(perms[k])
            return frame_t_test(est[:, j], info[:, j], one_sided=one_sided).t
        vp = v.copy()
        vp[data.frames] = v[data.frames[perms[k]]]
        d = copy.copy(data)
        d.ctx = dc_replace(data.ctx, pixel_velocity_px_s=vp)
        return t_of(d)

    p, exceed, ts = sequential_rank_p(t_real, placebo_t, one_sided=one_sided, n_max=n_placebo)
    tp = np.asarray(ts)
    calibration = {"p_value_placebo": p, "first_order_t": t_real, "placebo_t_mean": float(tp.mean()),
                   "placebo_t_sd": float(tp.std(ddof=1)) if tp.size > 1 else 0.0,
                   "placebo_n": int(tp.size), "placebo_exceed": exceed,
                   "placebo": "velocity fields permuted across frames (sequential rank p)"}
    return PlaceboRecord(p, {"calibration": calibration, "p_value_frames": OWN_P})
