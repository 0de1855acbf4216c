"""How a candidate cause is tested in a residual: the shared estimation machinery.

Each effect's own estimator (`Cause` subclass) lives in its file under egobench/effects/; this
module holds what they share. A cause tests its physical signature in the residual between
measured and predicted images (`fit` -> `CauseResult`: statistic, p-value, effect size, parameter
estimate, plot data) and extends the prediction with its estimated parameter (`apply`).

Photometric causes (vignette, response, white balance, exposure metadata) share one weighted
regression of block-level log ratios log(sum measured_linear / sum predicted_linear) on
frame dummies, channel dummies, a radial polynomial and log intensity (`PhotometricFit`); each is
the partial F-test of its own regressors (type-III), so they are tested jointly and do not
masquerade as each other. Blocks (4 x 4 px) are the units, which absorbs pixel-scale correlation.

Geometric causes (readout, time offset, exposure blur, distortion; `GeometricCause`) regress the
pixel residual on their first-order signature (-grad(prediction) . displacement) frame by frame
and test the per-frame slopes across frames (frames are the units: robust to spatially
correlated model error). Their parameters are then refined by Gauss-Newton on the warped
prediction, which is also how `apply` re-renders the prediction under the corrected model
(a Lanczos-4 warp of the predicted image by the corrected displacement field, `signatures.warp`).

Noise compares the high-passed residual variance in flat regions with the assumed
Poisson-Gaussian model; it does not change the mean prediction (its gain is a held-out
log-likelihood gain, not PSNR).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from dataclasses import replace as dc_replace

import cv2
import numpy as np

from egobench.residual.signatures import (LEVEL, DiagnosisContext, block_sum, decode, encode, encode_slope, erode,
                                          frame_t_test, gradients, hessian, partial_f_test, radial_coordinates, robust_sd,
                                          tile_shuffled, warp, weighted_lstsq)

#: Display range used for fits: darker pixels are dominated by noise/quantisation in log
#: space, brighter ones may be clipped.
DISPLAY_MIN, DISPLAY_MAX = 0.04, 0.95
#: Block size (pixels) of the photometric regression cells.
BLOCK_PX = 4
#: Gaussian sigma (pixels) of the low-pass applied to measured and predicted images before the
#: geometric fits (ResidualData.geometric); 0 = none. Measured through the simulator (48 px,
#: pixel_samples=4): 0.8 px improved a time-offset estimate (2.77 vs 2.56 ms of 3) but attenuated
#: the readout row slope (0.25 vs 0.35 of 0.4), so it is off.
GEOMETRIC_PREFILTER_PX = 0.0


def gaussian_lowpass(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass over the image axes of x [F, H, W, C] (edge replication)."""
    F, H, W, C = x.shape
    out = np.empty_like(x, dtype=np.float64)
    for f in range(F):  # one separable filter per frame
        out[f] = cv2.GaussianBlur(np.ascontiguousarray(x[f], dtype=np.float64), (0, 0), sigmaX=sigma, sigmaY=sigma,
                                  borderType=cv2.BORDER_REPLICATE).reshape(H, W, C)
    return out


@dataclass
class CauseResult:
    """One candidate cause tested on one residual."""

    name: str  # effect name (egobench.effects.EFFECTS key)
    kind: str  # "photometric" | "geometric" | "noise"
    testable: bool  # False when the context lacks what the signature needs (reason says what)
    reason: str = ""  # why untestable, or notes on the estimate
    statistic: float = 0.0  # value of the test statistic
    statistic_kind: str = ""  # e.g. "F(2, 4000)", "t(13)"
    p_value: float = 1.0  # raw p-value
    p_adjusted: float = 1.0  # Holm-adjusted over the library (filled by the engine)
    effect_rms: float = 0.0  # RMS change of the display prediction (0..1 units) when the cause is applied; noise: RMS std change
    effect_floor: float = 0.0  # practical-significance floor on effect_rms
    params: dict = field(default_factory=dict)  # estimated parameter(s), JSON-ready, named with units
    significant: bool = False  # p_adjusted < alpha and effect_rms >= effect_floor
    score: float = 0.0  # ranking key: effect size x saturating significance
    plot: dict = field(default_factory=dict)  # signature plot data (lists), see report.py
    internal: dict = field(default_factory=dict)  # arrays needed by apply (not serialised)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("internal", "plot")}


class ResidualData:
    """Measured and predicted stacks of some frames, with the derived quantities the causes share."""

    def __init__(self, measured: np.ndarray, predicted: np.ndarray, ctx: DiagnosisContext, frames: np.ndarray,
                 border_px: int = 2, pixel_mask: np.ndarray | None = None) -> None:
        self.ctx = ctx
        self.frames = np.asarray(frames, dtype=np.int64)  # [f] positions in the context arrays
        self.m = np.asarray(measured, dtype=np.float64)  # [f, H, W, 3]
        self.p = np.asarray(predicted, dtype=np.float64)  # [f, H, W, 3]
        self.r = self.m - self.p
        g = ctx.gamma_assumed
        self.m_lin = decode(self.m, g)
        self.p_lin = decode(self.p, g)
        H, W = self.m.shape[1:3]
        self.valid = erode(ctx.valid, border_px)  # [H, W]
        self.usable_all = ((self.p > DISPLAY_MIN) & (self.p < DISPLAY_MAX) & (self.m < 0.985) & (self.m > 0.005)
                           & self.valid[None, :, :, None])  # ignoring pixel_mask (noise neighbourhoods)
        self.pixel_fraction = 1.0 if pixel_mask is None else float(np.mean(pixel_mask))
        if pixel_mask is not None:  # statistics on these pixels only (e.g. even checkerboard; odd ones score the gain)
            self.valid = self.valid & pixel_mask
        in_range = (self.p > DISPLAY_MIN) & (self.p < DISPLAY_MAX) & (self.m < 0.985) & (self.m > 0.005)
        self.usable = in_range & self.valid[None, :, :, None]  # [f, H, W, 3]
        self._grad = None
        self._hess = None
        self._photometric = None
        self._geometric = None

    def with_prediction(self, predicted: np.ndarray, inside: np.ndarray | None = None) -> "ResidualData":
        """The same measured frames against another prediction [f, H, W, 3]; pixels outside
        ``inside`` [f, H, W] (e.g. warped from beyond the border) are not usable."""
        out = copy.copy(self)
        out.p = np.asarray(predicted, dtype=np.float64)
        out.r = out.m - out.p
        out.p_lin = decode(out.p, self.ctx.gamma_assumed)
        in_range = (out.p > DISPLAY_MIN) & (out.p < DISPLAY_MAX)
        out.usable = self.usable & in_range & (True if inside is None else inside[..., None])
        out.usable_all = self.usable_all & in_range
        out._grad = None
        out._hess = None
        out._photometric = None
        out._geometric = None  # a cached view of the old prediction would be stale
        return out

    def with_measurement(self, measured: np.ndarray) -> "ResidualData":
        """The same prediction against other measured frames [f, H, W, 3] (a blurred copy of these: the
        trained-run calibration's resolution match). The usable pixels stay those of these frames, and the
        prediction's derivatives are shared."""
        out = copy.copy(self)
        out.m = measured
        out.m_lin = decode(out.m, self.ctx.gamma_assumed)
        out.r = out.m - out.p
        out._photometric = out._geometric = None
        return out

    @property
    def photometric_if_fitted(self) -> "PhotometricFit | None":
        """The photometric fit when a cause has already made it, else None (nothing is fitted here)."""
        return self._photometric

    def geometric(self) -> "ResidualData":
        """The view the geometric causes fit on: measured and predicted low-passed by a Gaussian of
        GEOMETRIC_PREFILTER_PX (display values; usable pixels need their whole footprint usable).

        Ray-cast images (egobench.sim) are not band-limited even with pixel-area integration:
        a sub-pixel shift moves edge pixels in steps; the low-pass turns those steps into the
        smooth first-order response the signatures assume (gradients of the filtered image are
        not noisy, so the slopes are not attenuated). A shift commutes with the filter, so the
        parameters keep their meaning."""
        if self._geometric is None:
            sigma = GEOMETRIC_PREFILTER_PX
            if sigma <= 0:
                self._geometric = self
            else:
                out = self.with_prediction(gaussian_lowpass(self.p, sigma))
                out.m = gaussian_lowpass(self.m, sigma)
                out.r = out.m - out.p
                rad = int(math.ceil(2 * sigma))
                ok = erode(self.usable_all.all(axis=-1), rad)  # [f, H, W]
                out.usable = out.usable & ok[..., None] & self.valid[None, :, :, None]
                out._geometric = out
                self._geometric = out
        return self._geometric

    @property
    def grad(self) -> tuple[np.ndarray, np.ndarray]:
        if self._grad is None:
            self._grad = gradients(self.p)
        return self._grad

    @property
    def hess(self) -> tuple[np.ndarray, ...]:
        """The prediction's second derivatives (`signatures.hessian`), cached."""
        if self._hess is None:
            self._hess = hessian(self.p, self.grad)
        return self._hess

    def share_derivatives(self) -> "ResidualData":
        """Compute and cache the prediction's derivatives, so shallow copies (the placebos' contexts) reuse them."""
        _ = self.grad, self.hess
        return self

    @property
    def velocity(self) -> np.ndarray | None:  # [f, H, W, 2]
        v = self.ctx.pixel_velocity_px_s
        return None if v is None else v[self.frames].astype(np.float64)

    def photometric(self) -> "PhotometricFit":
        if self._photometric is None:
            self._photometric = PhotometricFit(self)
        return self._photometric


# ============================================================================ photometric
class PhotometricFit:
    """Weighted regression of block log ratios (see module docstring). Cells with robust |z| > 5 are trimmed."""

    def __init__(self, data: ResidualData, block: int = BLOCK_PX) -> None:
        ctx = data.ctx
        f_count = data.m.shape[0]
        H, W = data.m.shape[1:3]
        mask = data.usable.astype(np.float64)  # [f, H, W, 3]
        n = block_sum(mask, block)  # [f, hb, wb, 3]
        sm = block_sum(data.m_lin * mask, block)
        sp = block_sum(data.p_lin * mask, block)
        var_lin = ctx.noise_var_linear(data.p_lin, data.frames) + (LEVEL / encode_slope(data.p_lin, ctx.gamma_assumed)) ** 2 / 12.0
        sv = block_sum(var_lin * mask, block)
        _, _, r_norm = radial_coordinates(H, W, ctx.principal_point)
        r2 = block_sum(np.broadcast_to((r_norm**2)[None, :, :, None], mask.shape) * mask, block)
        r4 = block_sum(np.broadcast_to((r_norm**4)[None, :, :, None], mask.shape) * mask, block)
        ok = (n >= 0.75 * block * block * data.pixel_fraction) & (sp > 0) & (sm > 0)
        var_y = sv / np.maximum(sp, 1e-12) ** 2 + 1e-8
        y = np.log(np.maximum(sm, 1e-12) / np.maximum(sp, 1e-12)) + 0.5 * var_y  # second-order bias correction
        log_p = np.log(np.maximum(sp, 1e-12) / np.maximum(n, 1))
        fidx = np.broadcast_to(np.arange(f_count)[:, None, None, None], ok.shape)
        cidx = np.broadcast_to(np.arange(3)[None, None, None, :], ok.shape)
        self.cell_ok = ok  # [f, hb, wb, 3]
        sel = ok.ravel()
        self.n_cells = int(sel.sum())
        self.y = y.ravel()[sel]
        self.w = 1.0 / var_y.ravel()[sel]
        self.fidx = fidx.ravel()[sel]
        self.cidx = cidx.ravel()[sel]
        self.r2 = (r2 / np.maximum(n, 1)).ravel()[sel]
        self.r4 = (r4 / np.maximum(n, 1)).ravel()[sel]
        self.log_p = log_p.ravel()[sel]
        self.log_views = None  # [n] cell mean log(1 + training views of its surface), centred; trained runs only
        if ctx.train_view_count is not None:
            lv = np.broadcast_to(np.log1p(ctx.train_view_count[data.frames])[..., None], mask.shape)
            lv = (block_sum(lv * mask, block) / np.maximum(n, 1)).ravel()[sel]
            if self.n_cells and np.ptp(lv) > 1e-9:  # counts that do not vary explain nothing: no column
                self.log_views = lv - float(np.average(lv, weights=self.w))
        self.log_p0 = float(np.average(self.log_p, weights=self.w)) if self.n_cells else 0.0
        self.n_frames = f_count
        self.trimmed = np.zeros(self.n_cells, dtype=bool)
        self.testable = self.n_cells > f_count + 8
        if not self.testable:
            return
        self._fit()
        # Trim cells far off the model (unmodelled content such as a person absent from a simulation).
        res = (self.y - self.X @ self.coef) * np.sqrt(self.w)
        scale = robust_sd(res) + 1e-12
        self.trimmed = np.abs(res) > 5.0 * scale
        if self.trimmed.any() and (~self.trimmed).sum() > f_count + 8:
            self._fit()
        trimmed_map = np.zeros(ok.size, dtype=bool)
        trimmed_map[np.flatnonzero(sel)[self.trimmed]] = True
        self.trimmed_map = trimmed_map.reshape(ok.shape).any(axis=-1)  # [f, hb, wb]

    # column blocks of the design matrix
    def _design(self) -> dict[str, np.ndarray]:
        frame = np.zeros((self.n_cells, self.n_frames))
        frame[np.arange(self.n_cells), self.fidx] = 1.0
        wb = np.stack([(self.cidx == 0).astype(float), (self.cidx == 2).astype(float)], axis=1)
        vig = np.stack([self.r2, self.r4], axis=1)
        resp = (self.log_p - self.log_p0)[:, None]
        return {"frame": frame, "white_balance": wb, "vignette": vig, "response": resp}

    def _fit(self) -> None:
        keep = ~self.trimmed
        blocks = self._design()
        self.blocks = blocks
        self.X = np.concatenate(list(blocks.values()), axis=1)
        self.names = list(blocks)
        self.slices = {}
        start = 0
        for name, b in blocks.items():
            self.slices[name] = slice(start, start + b.shape[1])
            start += b.shape[1]
        self.coef, self.rss = weighted_lstsq(self.X[keep], self.y[keep], self.w[keep])
        self.dof = int(keep.sum()) - self.X.shape[1]
        self.keep = keep

    def test(self, block: str) -> tuple[float, float, int]:
        """Partial F-test of one regressor block -> (F, p, q)."""
        keep = self.keep
        cols = [b for name, b in self.blocks.items() if name != block]
        if block == "frame":  # H0: one common scale for every frame (an intercept)
            cols = [np.ones((self.n_cells, 1))] + cols
            q = self.n_frames - 1
        else:
            q = self.blocks[block].shape[1]
        Xr = np.concatenate(cols, axis=1)
        _, rss_r = weighted_lstsq(Xr[keep], self.y[keep], self.w[keep])
        f, p = partial_f_test(self.rss, rss_r, q, self.dof)
        return f, p, q

    def coefs(self, block: str) -> np.ndarray:
        return self.coef[self.slices[block]]

    @property
    def log_global(self) -> float:
        """Median per-frame log scale: an overall gain (a nuisance every photometric extension carries)."""
        return float(np.median(self.coefs("frame")))

    def own_global(self, block: str) -> float:
        """Log gain that best accompanies this block alone (weighted mean of y minus its term, kept cells)."""
        term = self.blocks[block] @ self.coefs(block)
        if block == "frame":
            term = term - self.log_global
        k = self.keep
        return float(np.average((self.y - term)[k], weights=self.w[k]))

    def partial_residual(self, block: str) -> np.ndarray:
        """y minus every other block's contribution (cells) -> [n_cells]."""
        return self.y - self.X @ self.coef + self.blocks[block] @ self.coefs(block)


def photometric_apply(predicted: np.ndarray, log_factor: np.ndarray, gamma: float, power: float = 0.0,
                       log_p0: float = 0.0) -> np.ndarray:
    """Display [f, H, W, 3] -> display with linear * exp(log_factor + power * (log linear - log_p0)), clipped."""
    lin = decode(predicted, gamma)
    log_lin = np.log(np.clip(lin, 1e-6, None))
    out = lin * np.exp(log_factor + power * (log_lin - log_p0))
    return np.clip(encode(out, gamma), 0.0, 1.0)


def own_term(result: "CauseResult") -> "CauseResult":
    """The result without the shared global gain, so that effect_rms measures the cause's own term."""
    internal = dict(result.internal)
    internal["log_global"] = 0.0
    return CauseResult(result.name, result.kind, result.testable, internal=internal)


class Cause:
    """Base class of a candidate cause."""

    name = ""
    kind = "photometric"
    mean_affecting = True
    nests: tuple[str, ...] = ()  # causes whose model is a special case of this one's (ranking rule in core)
    nested_in: tuple[str, ...] = ()  # the converse, declared by the special case (a new effect's own file)
    mimics: tuple[str, ...] = ()  # causes whose residual this one leaves where its own test cannot tell (`mimicry`)
    #: One parameter per frame (exposure metadata): it cannot generalise across frames, so a trained
    #: run scores its gain on every frame's own held-out pixels (`apply_within_frames`, core).
    frame_local = False

    def fit(self, data: ResidualData) -> CauseResult:  # pragma: no cover - interface
        raise NotImplementedError

    def apply(self, predicted: np.ndarray, result: CauseResult, ctx: DiagnosisContext, frames: np.ndarray,
              measured: np.ndarray | None = None, fit_mask: np.ndarray | None = None) -> np.ndarray:
        """Extend the prediction predicted [f, H, W, 3] (frames: positions in ctx) with the estimate."""
        raise NotImplementedError  # pragma: no cover

    def apply_within_frames(self, predicted: np.ndarray, result: CauseResult, ctx: DiagnosisContext,
                            measured: np.ndarray, fit_mask: np.ndarray) -> np.ndarray:
        """A frame_local cause: extend every frame of ctx [F, H, W, 3] with parameters estimated
        from that frame's own fit_mask [H, W] pixels only (fitted frames' joint-fit values unused)."""
        raise NotImplementedError  # pragma: no cover

    def gain_placebo(self, predicted: np.ndarray, extended: np.ndarray, result: CauseResult, ctx: DiagnosisContext,
                     frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A placebo of the extension ``extended`` [f, H, W, 3] of ``predicted`` (frames: positions in ctx): the
        same change with its tiles shuffled within each frame (`signatures.tile_shuffled`). Its gain is what a
        change of this size and make-up earns where it does not follow the residual (`egobench.diagnose.gain`)."""
        return np.clip(predicted + tile_shuffled(extended - predicted, rng), 0.0, 1.0)

    def nothing_to_name(self, result: CauseResult) -> str | None:
        """Why a significant ``result`` changes nothing worth a name (None: it may be named if it gains;
        `egobench.diagnose.gain`). Exposure metadata that flags no frame corrects no record."""
        return None

    def corrected_context(self, ctx: DiagnosisContext, params: dict) -> DiagnosisContext:
        """The context the rounds after this cause, named with ``params``, read (default: unchanged): a cause that
        says a recorded quantity is wrong corrects it there, as the prediction peeled carries its correction."""
        return ctx

    def mimicry(self, data: ResidualData, params: dict) -> str | None:
        """Why, on this run, this cause would leave the residual that a cause of `mimics`, named with ``params``,
        explains, while its own test cannot tell the two apart (None: it would not). The diagnosis carries it as
        the named cause's "or" (`core._note_alternatives`)."""
        return None

    def untestable_on_trained_run(self, data: ResidualData) -> str | None:
        """Why a trained run cannot show this cause in ``data`` (None: it can). Checked after the placebos,
        beside `Effect.trained_run_untestable` (`diagnose.placebo.mark_untestable_on_trained_run`)."""
        return None

    def trained_placebos(self, result: CauseResult, evidence) -> list:
        """The placebos this cause must beat on a trained run, as records the diagnosis merges in order
        (`egobench.residual.calibration`: ``evidence`` is its `TrainedRunEvidence`); none by default."""
        return []

    def trained_standard_error(self, evidence) -> tuple[float, int] | None:
        """(se, df) between frames of the parameter the trained-run calibration tests (the smallest testable
        effect), or None (a geometric cause's comes with its fit)."""
        return None

    def _untestable(self, reason: str) -> CauseResult:
        return CauseResult(self.name, self.kind, testable=False, reason=reason)

    @staticmethod
    def _effect(data: ResidualData, new_pred: np.ndarray, extra_mask: np.ndarray | None = None) -> float:
        m = data.usable if extra_mask is None else data.usable & extra_mask
        if not m.any():
            return 0.0
        return float(np.sqrt(np.mean((new_pred - data.p)[m] ** 2)))


def binned_means(x: np.ndarray, y: np.ndarray, w: np.ndarray, bins: int = 12) -> dict:
    """Weighted means of y in quantile bins of x (for signature plots)."""
    if x.size == 0:
        return {"x": [], "y": []}
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    sw = np.bincount(idx, weights=w, minlength=len(edges) - 1)
    xm = np.bincount(idx, weights=w * x, minlength=len(edges) - 1) / np.maximum(sw, 1e-300)
    ym = np.bincount(idx, weights=w * y, minlength=len(edges) - 1) / np.maximum(sw, 1e-300)
    keep = sw > 0
    return {"x": xm[keep].tolist(), "y": ym[keep].tolist()}


# ============================================================================ geometric
class WarpSource:
    """A prediction [f, H, W, 3] (display values) as `warp` samples it, float32: the display values for
    one instant, the decoded linear irradiance for an exposure integral; each made once, on first use."""

    def __init__(self, predicted: np.ndarray, gamma: float):
        self._predicted, self._gamma = predicted, float(gamma)
        self._display: np.ndarray | None = None
        self._linear: np.ndarray | None = None

    def display(self) -> np.ndarray:
        if self._display is None:
            self._display = np.ascontiguousarray(self._predicted, dtype=np.float32)
        return self._display

    def linear(self) -> np.ndarray:
        if self._linear is None:
            self._linear = decode(self._predicted, self._gamma).astype(np.float32)
        return self._linear


class GeometricCause(Cause):
    """Shared machinery: per-frame first-order slopes, frame-level test, Gauss-Newton refinement."""

    kind = "geometric"
    needs_velocity = True
    #: The signature depends on the motion's axis only, not its sign (a blur along v is one along -v).
    axial = False
    #: Turns of the velocity field for the gain placebos (degrees, drawn uniformly; an axial cause also turned
    #: by a further 180 at random): a signed shift is opposed or orthogonal to its motion from 90 to 270, an
    #: axial one at least 60 from its axis from 60 to 120.
    placebo_turns_deg = (90.0, 270.0)
    n_params = 1
    one_sided = False

    def displacement(self, theta: np.ndarray, ctx: DiagnosisContext, frames: np.ndarray, shape) -> list[tuple[float, np.ndarray]]:
        """[(weight, displacement [f, H, W, 2])]: the prediction is the weighted sum of warps."""
        raise NotImplementedError  # pragma: no cover

    def regressors(self, data: ResidualData) -> list[np.ndarray]:
        """First-order signature regressors, each [f, H, W, 3] (residual ~ sum theta_k x_k)."""
        raise NotImplementedError  # pragma: no cover

    def velocity_basis(self, data: ResidualData) -> list | None:
        """The regressors as polynomials in the pixel velocity, [[(map [f, H, W, 3], power of vx, power
        of vy), ...] per regressor] (`egobench.residual.permuted`), for the velocity placebos' tables;
        None where they are not built from the velocity that way."""
        return None

    def warp_prediction(self, predicted, theta, ctx, frames, source: WarpSource | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
        """(predicted [f, H, W, 3] moved by theta's displacement, float64; inside [f, H, W]).
        ``source``: predicted's `WarpSource` when several calls warp the same stack (`refine`)."""
        parts = self.displacement(np.asarray(theta, dtype=np.float64), ctx, frames, predicted.shape)
        src = WarpSource(predicted, ctx.gamma_assumed) if source is None else source
        if len(parts) == 1:
            out, inside = warp(src.display(), parts[0][1])
            return out.astype(np.float64), inside
        # several instants (exposure integral): average irradiance, i.e. in linear space
        lin = src.linear()
        inside = np.ones(predicted.shape[:3], dtype=bool)
        acc = np.zeros(lin.shape, dtype=np.float64)
        for weight, disp in parts:
            w_img, ins = warp(lin, disp)
            acc += weight * w_img
            inside &= ins
        return encode(np.clip(acc, 0.0, None), ctx.gamma_assumed), inside

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        out, _ = self.warp_prediction(predicted, result.internal["theta"], ctx, frames)
        return np.clip(out, 0.0, 1.0)

    def gain_placebo(self, predicted, extended, result, ctx, frames, rng):
        """A motion-driven cause: the same estimate applied along each frame's own image velocity turned by a
        random angle away from its motion (`placebo_turns_deg`): a field of the frame's own magnitudes and
        make-up that does not follow its motion. Model error tied to edges but not to the frame's motion
        direction earns such a placebo the same gain; a timing error only the true motion. (Another frame's
        field is no placebo: neighbouring frames move alike.)"""
        v = ctx.pixel_velocity_px_s
        if not self.needs_velocity or v is None:
            return super().gain_placebo(predicted, extended, result, ctx, frames, rng)
        frames = np.asarray(frames)
        lo, hi = self.placebo_turns_deg
        angle = np.deg2rad(rng.uniform(lo, hi, frames.size) + 180.0 * rng.integers(0, 2, frames.size) * self.axial)
        c, s = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
        vf = v[frames].astype(np.float64)
        vp = v.copy()
        vp[frames, ..., 0] = c * vf[..., 0] - s * vf[..., 1]
        vp[frames, ..., 1] = s * vf[..., 0] + c * vf[..., 1]
        return self.apply(predicted, result, dc_replace(ctx, pixel_velocity_px_s=vp), frames)

    def fit(self, data: ResidualData) -> CauseResult:
        if self.needs_velocity and data.velocity is None:
            return self._untestable("no per-pixel image velocity in the context")
        raw_data, data = data, data.geometric()  # statistics on the pre-filtered stacks; effect on the images
        est, info = self.first_order(data)
        j = self.tested_index
        test = frame_t_test(est[:, j], info[:, j], one_sided=self.one_sided)
        theta0 = self.initial_theta(est, info)
        theta = self.refine(data, theta0)
        res = CauseResult(self.name, self.kind, True, statistic=test.t, statistic_kind=f"t({test.df})",
                          p_value=test.p_value, internal={"theta": theta, "theta_first_order": theta0,
                                                          "frame_se": test.se, "frame_df": test.df})
        new_pred, inside = self.warp_prediction(raw_data.p, theta, data.ctx, data.frames)
        res.effect_rms = self._effect(raw_data, np.clip(new_pred, 0, 1), inside[..., None])
        res.params = self.describe(theta, data.ctx)
        res.params["first_order_estimate"] = self.describe(theta0, data.ctx)
        res.plot = self.plot_data(data, est, info, theta)
        return res

    def first_order(self, data: ResidualData, nuisance: list[np.ndarray] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame least-squares slopes of the residual on the signature regressors and the nuisance ones after
        them (default: `nuisance_regressors` of ``data``; a placebo passes the true data's) -> (est [f, k],
        info [f, k]; the cause's own in the first n_params columns)."""
        nuisance = self.nuisance_regressors(data) if nuisance is None else nuisance
        return frame_slopes(self.regressors(data) + nuisance, data.p, data.r, data.usable)

    def nuisance_regressors(self, data: ResidualData) -> list[np.ndarray]:
        """Signatures fitted beside the cause's own and never tested or applied: structure this run leaves in the
        residual that the cause's signature would otherwise take up (none by default)."""
        return []

    def nuisance_basis(self, data: ResidualData) -> list:
        """`nuisance_regressors` in the velocity placebos' tables (`velocity_basis`): fixed columns, since the
        structure a run leaves follows the frame's true motion, not a placebo's."""
        return [[(x, 0, 0)] for x in self.nuisance_regressors(data)]

    tested_index = 0

    def initial_theta(self, est: np.ndarray, info: np.ndarray) -> np.ndarray:
        """The pooled first-order estimate of the cause's own parameters (the first n_params columns of
        `first_order`; the nuisance columns after them are not the cause's)."""
        est, info = est[:, :self.n_params], info[:, :self.n_params]
        w = info / np.maximum(info.sum(axis=0, keepdims=True), 1e-300)
        return np.sum(w * est, axis=0)

    def step_sizes(self, ctx: DiagnosisContext) -> np.ndarray:
        raise NotImplementedError  # pragma: no cover

    def refine(self, data: ResidualData, theta: np.ndarray, iterations: int = 3) -> np.ndarray:
        """Gauss-Newton on the warped prediction (numeric Jacobian), pooled over the frames."""
        theta = np.asarray(theta, dtype=np.float64).copy()
        eps = self.step_sizes(data.ctx)
        src = WarpSource(data.p, data.ctx.gamma_assumed)
        for _ in range(iterations):
            base, inside = self.warp_prediction(data.p, theta, data.ctx, data.frames, src)
            cols = []
            for i in range(len(theta)):
                d = np.zeros_like(theta)
                d[i] = eps[i]
                plus, ins_p = self.warp_prediction(data.p, theta + d, data.ctx, data.frames, src)
                minus, ins_m = self.warp_prediction(data.p, theta - d, data.ctx, data.frames, src)
                inside &= ins_p & ins_m
                cols.append((plus - minus) / (2 * eps[i]))
            m = data.usable & inside[..., None]
            if m.sum() < 20:
                break
            J = np.stack([c[m] for c in cols], axis=1)
            r = (data.m - base)[m]
            JtJ = J.T @ J
            if np.linalg.cond(JtJ) > 1e12:
                break
            delta = np.linalg.solve(JtJ, J.T @ r)
            theta = self.constrain(theta + delta)
            if np.all(np.abs(delta) < 0.01 * eps):
                break
        return theta

    def constrain(self, theta: np.ndarray) -> np.ndarray:
        return theta

    def describe(self, theta: np.ndarray, ctx: DiagnosisContext) -> dict:
        raise NotImplementedError  # pragma: no cover

    def plot_data(self, data, est, info, theta) -> dict:
        speed = np.linalg.norm(data.velocity, axis=-1).mean(axis=(1, 2)) if data.velocity is not None else np.zeros(len(est))
        return {"frame": [int(data.ctx.frame_index[f]) for f in data.frames], "speed_px_s": speed.tolist(),
                "per_frame": est[:, self.tested_index].tolist(), "pooled": float(theta[self.tested_index])}


def masked_moments(u: list[np.ndarray], m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame sums of the columns u (each [F, P]) over the pixels m [F, P] (0/1) -> (lin [F, c] =
    sum m u_a, S [F, c, c] = sum m u_a u_b). No [F, P] temporary per column: allocating those (page
    faults on fresh 1-3 MB buffers) was most of `frame_slopes`' cost."""
    F, c = m.shape[0], len(u)
    lin = np.stack([np.einsum("fp,fp->f", m, col) for col in u], axis=1)
    S = np.empty((F, c, c))
    for a in range(c):
        for b in range(a, c):
            S[:, a, b] = S[:, b, a] = np.einsum("fp,fp,fp->f", m, u[a], u[b])
    return lin, S


def normal_equations_from_moments(lin: np.ndarray, S: np.ndarray, n: np.ndarray, k: int
                                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw moments of the columns [x_1..x_k, p, y] (lin [F, k+2], S [F, k+2, k+2], n [F] pixels) ->
    the normal equations of y on the design [x_1..x_k, 1, p - mean p]: (XtX [F, k+2, k+2], Xty [F, k+2],
    yty [F]). The prediction is centred here, from its sums."""
    F = n.shape[0]
    pm = lin[:, k] / np.maximum(n, 1.0)  # the frame's mean prediction
    XtX = np.empty((F, k + 2, k + 2))
    XtX[:, :k, :k] = S[:, :k, :k]
    XtX[:, :k, k] = XtX[:, k, :k] = lin[:, :k]
    XtX[:, :k, k + 1] = XtX[:, k + 1, :k] = S[:, :k, k] - pm[:, None] * lin[:, :k]
    XtX[:, k, k] = n
    XtX[:, k, k + 1] = XtX[:, k + 1, k] = lin[:, k] - pm * n
    XtX[:, k + 1, k + 1] = S[:, k, k] - pm * lin[:, k]
    Xty = np.concatenate([S[:, :k, k + 1], lin[:, k + 1:], (S[:, k, k + 1] - pm * lin[:, k + 1])[:, None]], axis=1)
    return XtX, Xty, S[:, k + 1, k + 1]


def slopes_from_normal_equations(XtX: np.ndarray, Xty: np.ndarray, yty: np.ndarray, n: np.ndarray, k: int
                                 ) -> tuple[np.ndarray, np.ndarray]:
    """`frame_slopes`' solve: (est [F, k], info [F, k]) of the first k columns; the residual sum of
    squares as y'y - coef'X'y; a frame with under 20 pixels or a singular design gets 0, 0."""
    F = n.shape[0]
    est, info = np.zeros((F, k)), np.zeros((F, k))
    ok = n >= 20
    ok[ok] = np.linalg.cond(XtX[ok]) <= 1e12
    if not ok.any():
        return est, info
    coef = np.linalg.solve(XtX[ok], Xty[ok][..., None])[..., 0]  # [g, k + 2]
    rss = np.maximum(yty[ok] - np.einsum("gk,gk->g", coef, Xty[ok]), 0.0)
    resid_var = rss / n[ok] + 1e-12
    cov_diag = np.diagonal(np.linalg.inv(XtX[ok]), axis1=1, axis2=2)[:, :k] * resid_var[:, None]
    est[ok] = coef[:, :k]
    info[ok] = 1.0 / np.maximum(cov_diag, 1e-300)
    return est, info


def frame_slopes(xs: list[np.ndarray], predicted: np.ndarray, residual: np.ndarray,
                 mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's least-squares fit of residual [f, H, W, 3] on the regressors xs (each [f, H, W, 3])
    and two nuisance columns, a constant and the prediction minus its mean (they partial out a global
    and a multiplicative intensity mismatch, e.g. shading, which correlates with curvature), over the
    frame's ``mask`` pixels -> (est [f, k], info [f, k] = 1 / var of each slope). All frames at once
    through their normal equations; a frame with under 20 pixels or a singular design gets 0, 0."""
    F, k = residual.shape[0], len(xs)
    m = mask.reshape(F, -1).astype(np.float64)
    n = m.sum(axis=1)
    lin, S = masked_moments([*(x.reshape(F, -1) for x in xs), predicted.reshape(F, -1), residual.reshape(F, -1)], m)
    return slopes_from_normal_equations(*normal_equations_from_moments(lin, S, n, k), n, k)


def velocity_term(data: ResidualData) -> np.ndarray:
    """-grad(prediction) . velocity: [f, H, W, 3] (residual per second of time shift)."""
    gx, gy = data.grad
    v = data.velocity
    return -(gx * v[..., 0:1] + gy * v[..., 1:2])


def velocity_term_basis(data: ResidualData, weight: np.ndarray | float = 1.0) -> list[tuple[np.ndarray, int, int]]:
    """`velocity_term` x weight (broadcast to [f, H, W, 3]) as a velocity polynomial: -gx w vx - gy w vy."""
    gx, gy = data.grad
    return [(-gx * weight, 1, 0), (-gy * weight, 0, 1)]
