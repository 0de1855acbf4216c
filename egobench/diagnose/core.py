"""`diagnose_residuals`: test every candidate cause, rank, name, extend the model, measure the gain.

Protocol (docs/diagnosis.md):
1. Frames whose index % holdout_every != 0 are the fitting frames; the rest are held out.
2. Round k: every cause of the library is fitted on the current residual of the fitting frames;
   raw p-values are Holm-adjusted over the testable causes. A cause is significant when its
   adjusted p < alpha AND its effect (RMS change of the display prediction) >= effect_floor
   (8-bit images hold ~10^5 pixels, so a tiny but real mismatch is always "significant"; the
   floor states what is worth modelling). Score = effect_rms x min(1, -log10(p_adj) / 10); a cause
   that contains another (readout contains time offset) outranks it when both are significant.
3. The top significant mean-affecting cause is named when its extension gains on what it was not fitted on
   (`egobench.diagnose.gain`): its estimate is applied to every frame (held-out frames: per-frame parameters
   come from their even-checkerboard pixels) and the PSNR gain is measured on the odd-checkerboard pixels of
   the held-out frames; it must be positive and, on a trained run, beat the gains of the cause's own placebo
   extensions of those frames. On a trained run, a cause with one parameter per frame (`Cause.frame_local`)
   is scored instead on the odd pixels of every frame, each frame's parameter from its own even pixels,
   against `gain.FRAME_LOCAL_GAIN_FLOOR_DB`.
4. Repeat until nothing mean-affecting is significant (at most max_causes); noise is named
   only then, because any unmodelled mean effect inflates the residual variance.
Nothing named in round 1 -> "no significant discrepancy".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from egobench.diagnose.estimators import CAUSES, variance_model_cause
from egobench.diagnose.gain import FRAME_LOCAL_GAIN_FLOOR_DB, gain_placebo_test, refusal
from egobench.diagnose.placebo import mark_untestable_on_trained_run, trained_run_records
from egobench.diagnose.power import geometric_standard_errors, smallest_testable
from egobench.effects import EFFECTS
from egobench.effects.noise import NoiseCause
from egobench.residual.calibration import merge_record
from egobench.residual.estimation import CauseResult, ResidualData
from egobench.residual.signatures import LEVEL, DiagnosisContext, box3, checkerboard, erode, holm, psnr

NO_DISCREPANCY = "no significant discrepancy"
#: Verdict of a trained run whose residual is mostly the model's own error and names no cause.
RECONSTRUCTION_ERROR = "reconstruction error dominates"


@dataclass
class DiagnosisConfig:
    """Settings of one diagnosis."""

    alpha: float = 0.01  # family-wise significance level (Holm over the library, per round)
    effect_floor: float = 0.5 * LEVEL  # smallest RMS display change (0..1) worth naming: half an 8-bit level
    noise_factor_floor: float = 0.15  # |noise_std_factor - 1| below which noise is not named (also per signal half)
    noise_nll_gain_floor: float = 0.01  # held-out Gaussian NLL gain (nats/pixel, high-passed flat pixels) noise must exceed
    max_causes: int = 3  # causes named one after another (peeling)
    causes: tuple[str, ...] = tuple(CAUSES)  # the library to test (effect names)
    border_px: int = 2  # image border excluded from fits and scores (warps sample outside there)
    # --- a trained run's renders (--source run): the null includes the model's own error (calibration.py)
    trained_run: bool = False  # calibrate statistics with placebos; gain beyond its spread; model-error verdict
    placebo_draws: int = 4999  # frame-label shuffles of the exposure placebos (smallest p: 1 / (draws + 1))
    placebo_seed: int = 0  # seeds the placebo shuffles

    def validate(self) -> "DiagnosisConfig":
        if not (0 < self.alpha < 1):
            raise ValueError(f"DiagnosisConfig.alpha: expected a level in (0, 1), got {self.alpha}")
        if not (self.effect_floor >= 0):
            raise ValueError(f"DiagnosisConfig.effect_floor: expected >= 0, got {self.effect_floor}")
        if int(self.placebo_draws) < 99:
            raise ValueError(f"DiagnosisConfig.placebo_draws: expected an integer >= 99, got {self.placebo_draws}")
        if int(self.max_causes) < 1:
            raise ValueError(f"DiagnosisConfig.max_causes: expected an integer >= 1, got {self.max_causes}")
        unknown = [c for c in self.causes if c not in CAUSES]
        if unknown:
            raise ValueError(f"DiagnosisConfig.causes: unknown {unknown}; expected names from {list(CAUSES)}")
        return self


@dataclass
class NamedCause:
    """A cause named by the diagnosis, its estimate and what modelling it gains on held-out frames."""

    name: str
    round: int  # 1-based peeling round
    p_adjusted: float
    effect_rms: float  # display units (0..1)
    params: dict
    psnr_gain_db: float  # held-out PSNR(extended) - PSNR(before this cause)
    nll_gain_nats_per_px: float | None = None  # noise only: held-out Gaussian NLL improvement


@dataclass
class Diagnosis:
    """Result of `diagnose_residuals`."""

    verdict: str  # name of the top cause, or NO_DISCREPANCY
    named: list[NamedCause]  # in the order they were peeled off
    rounds: list[list[CauseResult]]  # every cause's test in every round (round 1 = the ranking)
    baseline_psnr_db: float  # held-out PSNR of the model as given
    extended_psnr_db: float  # held-out PSNR with every named cause modelled
    held_out_frames: list[int]  # frame indices used for the gain
    runtime_s: float
    config: DiagnosisConfig
    extended_prediction: np.ndarray | None = None  # [F, H, W, 3] display (not serialised)
    unmodelled_fraction: float = 0.0  # share of photometric cells trimmed as off-model content (round 1)
    unmodelled_map: np.ndarray | None = None  # [f_fit, hb, wb] bool trimmed cells (round 1; not serialised)
    meta: dict = field(default_factory=dict)
    model_error: dict | None = None  # trained run: reconstruction error vs noise, smallest testable effects

    @property
    def psnr_gain_db(self) -> float:
        return self.extended_psnr_db - self.baseline_psnr_db

    @property
    def ranking(self) -> list[CauseResult]:
        """Round-1 results, best first (significant ones by score, then the rest by p-value)."""
        r = self.rounds[0] if self.rounds else []
        return sorted(r, key=lambda c: (not c.significant, -c.score, c.p_adjusted))

    def to_dict(self) -> dict:
        def clean(x):
            if isinstance(x, float):
                return x if math.isfinite(x) else None
            if isinstance(x, dict):
                return {str(k): clean(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [clean(v) for v in x]
            if isinstance(x, (np.floating, np.integer)):
                return clean(x.item())
            if isinstance(x, np.ndarray):
                return clean(x.tolist())
            return x

        return clean({
            "schema": "egobench.diagnosis/1",
            "verdict": self.verdict,
            "named": [n.__dict__ for n in self.named],
            "ranking": [c.to_dict() for c in self.ranking],
            "rounds": [[c.to_dict() for c in rnd] for rnd in self.rounds],
            "baseline_psnr_db": self.baseline_psnr_db,
            "extended_psnr_db": self.extended_psnr_db,
            "psnr_gain_db": self.psnr_gain_db,
            "held_out_frames": self.held_out_frames,
            "runtime_s": self.runtime_s,
            "unmodelled_fraction": self.unmodelled_fraction,
            "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.config.__dict__.items()},
            "meta": self.meta,
            **({"model_error": self.model_error} if self.model_error is not None else {}),
        })


def _check_stack(name: str, x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"{name}: expected display images of shape [F, H, W, 3], got {list(x.shape)}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: contains NaN or inf")
    return x.astype(np.float64)


def _noise_factor_beyond_floor(result: CauseResult, floor: float) -> bool:
    """|f - 1| > floor overall AND in each signal half with the same sign: a wrong noise scale
    changes the variance at every level; model error of a trained reconstruction (excess at some
    levels only) does not pass for noise."""
    f = result.params["noise_std_factor"]
    if abs(f - 1.0) <= floor:
        return False
    halves = result.params.get("noise_std_factor_by_signal")
    if not halves:
        return True
    return all((h - 1.0) * (f - 1.0) > 0 and abs(h - 1.0) > floor for h in halves)


def _noise_nll_gain(noise_cause: NoiseCause, noise: CauseResult, measured: np.ndarray, current: np.ndarray,
                    ctx: DiagnosisContext, eval_idx: np.ndarray, eval_mask: np.ndarray) -> float:
    """Held-out Gaussian NLL gain (nats/pixel) of the fitted noise over the assumed one.

    With a pipeline reference (the assumed noise drawn through rectification and quantisation)
    the variance of the high-passed residual is only known where that reference says, so the
    gain is scored on high-passed residuals, against the reference's per-frame high-passed
    variance (assumed) and f^2 times it (fitted). Otherwise per pixel, on the residual."""
    pe, me = current[eval_idx], measured[eval_idx]
    mask = np.broadcast_to(eval_mask[None, :, :, None], pe.shape)
    if ctx.noise_reference is not None and "transfer" in noise.internal:
        # scored pixels whose 3x3 high-pass window lies inside the valid region (eroding the
        # checkerboard itself would leave no pixel: every odd pixel has even neighbours)
        full = eval_mask & erode(ctx.valid, 1)
        mask = np.broadcast_to(full[None, :, :, None], pe.shape)
        ref = ctx.noise_reference[eval_idx]
        hp_r = (me - pe) - box3(me - pe)
        hp_ref = ref - box3(ref)
        var0 = np.broadcast_to(np.mean(hp_ref**2, axis=(1, 2, 3), where=mask)[:, None, None, None], pe.shape)[mask]
        var0 = np.maximum(var0, 1e-12)
        var1 = var0 * noise.internal["var_factor"]
        r2 = hp_r[mask] ** 2
    else:
        var0 = noise_cause.variance(pe, None, ctx, eval_idx)[mask]
        var1 = noise_cause.variance(pe, noise, ctx, eval_idx)[mask]
        r2 = ((me - pe)[mask]) ** 2
    nll0 = float(np.mean(0.5 * (np.log(2 * math.pi * var0) + r2 / var0)))
    nll1 = float(np.mean(0.5 * (np.log(2 * math.pi * var1) + r2 / var1)))
    return nll0 - nll1


@dataclass
class _Split:
    """Which frames and pixels fit the causes and which score them."""

    fit_idx: np.ndarray  # [f_fit] fitting frames (not held out)
    eval_idx: np.ndarray  # [f_eval] scored frames (held out; every frame when none is)
    fit_pixels: np.ndarray | None  # [H, W] bool pixels fitted on (None: all; even checkerboard when nothing is held out)
    eval_mask: np.ndarray  # [H, W] bool scored pixels: odd checkerboard inside the eroded valid region
    fit_mask: np.ndarray  # [H, W] bool even checkerboard: per-frame parameters of held-out frames come from here


def _split_frames(ctx: DiagnosisContext, cfg: DiagnosisConfig, F: int, H: int, W: int) -> _Split:
    """Fitting and scoring frames/pixels of F frames of H x W (see the module docstring, step 1)."""
    held = ctx.held_out
    fit_idx = np.flatnonzero(~held)
    eval_idx = np.flatnonzero(held)
    if fit_idx.size < 3:
        raise ValueError(f"measured: need at least 3 fitting (not held-out) frames, got {fit_idx.size} of {F}")
    fit_pixels = None
    if eval_idx.size == 0:  # nothing held out: fit on even, score on odd checkerboard pixels of every frame
        eval_idx = np.arange(F)
        fit_pixels = checkerboard(H, W, 0)
    fit_mask, eval_mask = within_frame_masks(ctx, cfg.border_px)
    return _Split(fit_idx, eval_idx, fit_pixels, eval_mask, fit_mask)


def within_frame_masks(ctx: DiagnosisContext, border_px: int) -> tuple[np.ndarray, np.ndarray]:
    """[H, W] bool pixel masks of a frame-local correction -> (fit: the even checkerboard; score: the odd
    checkerboard inside the valid region eroded by ``border_px``)."""
    H, W = ctx.valid.shape
    return checkerboard(H, W, 0), erode(ctx.valid, border_px) & checkerboard(H, W, 1)


def _adjust_and_rank(testable: list[CauseResult], cfg: DiagnosisConfig) -> None:
    """Holm-adjust the testable causes' p-values, mark the significant ones and score them (in place)."""
    for r, p_adj in zip(testable, holm([r.p_value for r in testable]) if testable else []):
        r.p_adjusted = p_adj
        r.effect_floor = cfg.effect_floor
        r.significant = p_adj < cfg.alpha and r.effect_rms >= cfg.effect_floor
        if EFFECTS[r.name].variance_model and "noise_std_factor" in r.params:
            r.significant &= _noise_factor_beyond_floor(r, cfg.noise_factor_floor)
        r.score = r.effect_rms * min(1.0, -math.log10(max(p_adj, 1e-300)) / 10.0) if r.significant else 0.0
    # Nested causes: when a cause's own extra term is significant GIVEN the cause it contains
    # (readout's row slope b given the shift a of a time offset) and both are significant, the
    # contained cause cannot explain the residual, so the general one outranks it.
    by_name = {r.name: r for r in testable}
    for r in testable:
        for inner in sorted(contained_causes(r.name)):
            o = by_name.get(inner)
            if r.significant and o is not None and o.significant and o.score >= r.score:
                r.score = o.score * (1.0 + 1e-9) + 1e-12


def _name_noise(testable: list[CauseResult], rnd: int, measured: np.ndarray, current: np.ndarray,
                ctx: DiagnosisContext, split: _Split, cfg: DiagnosisConfig) -> NamedCause | None:
    """The noise cause when it is significant AND predicts held-out residuals better (NLL gain
    above the floor); otherwise None (a significant noise that does not is marked not significant)."""
    noise = next((r for r in testable if EFFECTS[r.name].variance_model and r.significant), None)
    if noise is None:
        return None
    noise_cause: NoiseCause = CAUSES[noise.name]  # type: ignore[assignment]
    gain_nll = _noise_nll_gain(noise_cause, noise, measured, current, ctx, split.eval_idx, split.eval_mask)
    noise.params["held_out_nll_gain_nats_per_px"] = gain_nll
    if gain_nll > cfg.noise_nll_gain_floor:
        return NamedCause(noise.name, rnd, noise.p_adjusted, noise.effect_rms, noise.params, 0.0, gain_nll)
    # the fitted noise does not predict held-out residuals better: not worth modelling
    noise.significant, noise.score = False, 0.0
    noise.reason = (f"held-out NLL gain {gain_nll:.4f} nats/px <= {cfg.noise_nll_gain_floor} "
                    "(DiagnosisConfig.noise_nll_gain_floor)")
    return None


def _name_mean_cause(testable: list[CauseResult], rnd: int, measured: np.ndarray, current: np.ndarray,
                     ctx: DiagnosisContext, split: _Split, cfg: DiagnosisConfig, score
                     ) -> tuple[NamedCause, np.ndarray] | None:
    """The best significant mean-affecting cause -> (NamedCause, extended prediction), or None.

    The top candidate is named only if its extension gains on what it was not fitted on (`gain.refusal`: a
    positive gain on every path; on a trained run one that beats its placebo extensions, `gain_placebo_test`).
    When it does not, the strongest structure in the residual is the model's own error, and a weaker
    candidate fitted beside it is not trusted either (measured: a hidden time offset that the run absorbed let
    a vignette through at +0.06 dB), so the round names nothing; every candidate is marked not significant
    with the reason."""
    F = measured.shape[0]
    candidates = sorted((r for r in testable if r.significant and CAUSES[r.name].mean_affecting),
                        key=lambda r: -r.score)
    if not candidates:
        return None
    top = candidates[0]
    cause = CAUSES[top.name]
    new = cause.apply(current, top, ctx, np.arange(F), measured=measured, fit_mask=split.fit_mask)
    gain = score(new) - score(current)
    frame_local = bool(cfg.trained_run and cause.frame_local and ctx.held_out.any())
    deciding, scored_on, test = gain, "held-out PSNR", None
    if frame_local:
        within = cause.apply_within_frames(current, top, ctx, measured, split.fit_mask)
        deciding = psnr(within, measured, split.eval_mask) - psnr(current, measured, split.eval_mask)
        scored_on = "within-frame PSNR"
        top.params["held_out_gain_db"], top.params["within_frame_gain_db"] = gain, deciding
    elif cfg.trained_run and gain > 0:
        test = gain_placebo_test(cause, top, ctx, current, new, measured, split.eval_idx, split.eval_mask,
                                 int(cfg.placebo_seed) + 1000 * rnd)
        top.params.update(test.to_params())
    reason = cause.nothing_to_name(top) or refusal(deciding, test, cfg.alpha, scored_on,
                                                   FRAME_LOCAL_GAIN_FLOOR_DB if frame_local else 0.0)
    if reason is None:
        return NamedCause(top.name, rnd, top.p_adjusted, top.effect_rms, top.params, gain), new
    top.reason = reason
    top.params["held_out_gain_db"] = gain
    for r in candidates[1:]:
        r.reason = (f"not named: {top.name}, ranked above it, does not improve what it was not fitted on, so the "
                    "residual's strongest structure is the model's own error")
    for r in candidates:
        r.significant, r.score = False, 0.0
    return None


def contained_causes(name: str) -> set[str]:
    """Causes whose model is a special case of cause ``name``'s: its own `nests` and every cause that
    declares itself `nested_in` it."""
    return set(CAUSES[name].nests) | {other for other, c in CAUSES.items() if name in c.nested_in}


def _note_alternatives(cause: NamedCause, results: list[CauseResult], data: ResidualData) -> None:
    """Causes that would explain a named cause's residual on this run, in its params ("or"):
    - a more general cause that contains it (time offset in readout) when the container's extra term is not
      significant, or the container cannot be tested on this run. Measured: a readout 40 % longer than stated
      moves the centre row half the difference later than the model's timing, and a run that renders one pose
      sample a frame (its readout untestable) names that shift as a time offset (results/diagnosis/README.md,
      2026-12-05, the hard sweeps rerun);
    - a cause that mimics it where its own test cannot tell them apart (`Cause.mimicry`: a response error at a
      fixed exposure darkens the stated vignette by a power of it)."""
    alternatives = []
    by_name = {r.name: r for r in results}
    for r in results:
        if cause.name not in contained_causes(r.name) or (r.testable and r.significant):
            continue
        why = ("its extra term is not significant here" if r.testable
               else f"it cannot be tested on this run ({r.reason})")
        alternatives.append({"cause": r.name, "p_adjusted": r.p_adjusted if r.testable else None,
                             "note": f"{r.name} contains {cause.name}; {why}, so {r.name} would explain the "
                                     "same residual"})
    for name, other in CAUSES.items():
        r = by_name.get(name)
        if cause.name not in other.mimics or (r is not None and r.testable and r.significant):
            continue
        why = other.mimicry(data, cause.params)
        if why is not None:
            alternatives.append({"cause": name, "p_adjusted": None,
                                 "note": f"{why}, so {name} would explain the same residual"})
    if alternatives:
        cause.params["or"] = alternatives


def _noise_variance(pred: np.ndarray, ctx: DiagnosisContext, idx: np.ndarray) -> np.ndarray:
    """Residual variance the assumed noise alone gives [f, H, W, 3] (display units): the pipeline
    reference's squares when the context has one, else the analytic model (0 when noiseless)."""
    if ctx.noise_reference is not None:
        ref = ctx.noise_reference[idx]
        return np.broadcast_to(np.mean(ref**2, axis=(1, 2), keepdims=True), pred.shape)
    noise: NoiseCause = variance_model_cause()  # type: ignore[assignment]
    if ctx.noise_shot is None:
        return np.full(pred.shape, ctx.quantisation_level**2 / 12.0)
    return noise.variance(pred, None, ctx, idx)


def neighbouring_training_views(ctx: DiagnosisContext, split: _Split) -> np.ndarray:
    """Positions of the training (fitting) frames whose frame index is a held-out frame's +- 1; all fitting frames
    when no frame is held out or none has such a neighbour. The error of a reconstruction varies along a
    trajectory by far more than between a held-out frame and its neighbours (one 48-frame run: 15.5-33.4 dB per
    frame), so the training views that show a generalisation gap are the held-out frames' neighbours."""
    index = np.asarray(ctx.frame_index)
    held = index[split.eval_idx] if ctx.held_out.any() else np.zeros(0, dtype=index.dtype)
    near = split.fit_idx[np.isin(index[split.fit_idx], np.concatenate([held - 1, held + 1]))]
    return near if near.size else split.fit_idx


def model_error_summary(measured: np.ndarray, predicted: np.ndarray, extended: np.ndarray, ctx: DiagnosisContext,
                        split: _Split, cfg: DiagnosisConfig, se: dict, n_testable: int) -> dict:
    """How much of a trained run's held-out residual is the model's own error (not noise, not a
    named cause), in dB, and the smallest effect of each kind still testable on this run."""
    def mse(pred, idx):
        m = np.broadcast_to(split.eval_mask[None, :, :, None], pred[idx].shape)
        return float(np.mean(((pred[idx] - measured[idx]) ** 2)[m]))

    idx = split.eval_idx
    m = np.broadcast_to(split.eval_mask[None, :, :, None], predicted[idx].shape)
    noise_var = float(np.mean(_noise_variance(predicted[idx], ctx, idx)[m]))
    before, after = mse(predicted, idx), mse(extended, idx)
    near = neighbouring_training_views(ctx, split)
    excess_before, excess_after = max(before - noise_var, 1e-12), max(after - noise_var, 1e-12)

    def db(x):
        return 10.0 * math.log10(max(x, 1e-12))

    return {
        "held_out_psnr_db": -db(before), "held_out_psnr_extended_db": -db(after),
        "training_view_psnr_db": -db(mse(predicted, near)),
        "all_training_views_psnr_db": -db(mse(predicted, split.fit_idx)),
        "generalisation_gap_db": db(before) - db(mse(predicted, near)),
        "training_views_compared": "the training frames next to a held-out frame (its index +- 1): a trajectory's "
                                   "frames differ by far more than a model's generalisation gap, so the held-out "
                                   "frames are compared with their neighbours, not with every training frame",
        "noise_only_psnr_db": -db(noise_var),
        "model_error_psnr_db": -db(excess_after),  # PSNR the unexplained model error alone would give
        "model_error_over_noise_db": db(excess_after) - db(noise_var),
        "non_physical_share": float(min(1.0, excess_after / max(after, 1e-12))),
        "share_explained_by_named_causes": float(max(0.0, 1.0 - excess_after / excess_before)),
        "dominates": bool(excess_after > noise_var),
        "smallest_testable": smallest_testable(se, ctx, cfg.alpha, n_testable),
        "rule": "dominates: the held-out residual variance left after the named causes exceeds the assumed "
                "noise variance (model error > noise); non_physical_share: that excess / the residual variance",
    }


def diagnose_residuals(
    measured: np.ndarray,  # [F, H, W, 3] display values in [0, 1] (the captured frames)
    predicted: np.ndarray,  # [F, H, W, 3] the model's prediction of the same frames
    context: DiagnosisContext,
    config: DiagnosisConfig | None = None,
) -> Diagnosis:
    """Test the library of causes on the residual measured - predicted; see the module docstring."""
    t0 = time.perf_counter()
    cfg = (config or DiagnosisConfig()).validate()
    measured = _check_stack("measured", measured)
    predicted = _check_stack("predicted", predicted)
    if measured.shape != predicted.shape:
        raise ValueError(f"predicted: shape {list(predicted.shape)} differs from measured {list(measured.shape)}")
    F, H, W, _ = measured.shape
    ctx = context.validate(F, H, W)
    split = _split_frames(ctx, cfg, F, H, W)

    def score(pred: np.ndarray) -> float:
        return psnr(pred[split.eval_idx], measured[split.eval_idx], split.eval_mask)

    current = predicted.copy()
    baseline = score(current)
    round1_se: dict = {}
    named: list[NamedCause] = []
    rounds: list[list[CauseResult]] = []
    unmodelled_fraction, unmodelled_map = 0.0, None
    for rnd in range(1, int(cfg.max_causes) + 1):
        data = ResidualData(measured[split.fit_idx], current[split.fit_idx], ctx, split.fit_idx,
                            border_px=cfg.border_px, pixel_mask=split.fit_pixels)
        results = [CAUSES[name].fit(data) for name in cfg.causes if name not in {n.name for n in named}]
        pf = data.photometric_if_fitted
        if rnd == 1 and pf is not None and pf.testable:
            unmodelled_fraction = float(pf.trimmed.mean()) if pf.n_cells else 0.0
            unmodelled_map = getattr(pf, "trimmed_map", None)
        testable = [r for r in results if r.testable]
        if cfg.trained_run:
            records, se = trained_run_records(data, testable, int(cfg.placebo_draws), int(cfg.placebo_seed) + rnd)
            for result, record in records:
                merge_record(result, record)
            mark_untestable_on_trained_run(testable, data)
            testable = [r for r in testable if r.testable]  # (white balance and noise are not identifiable on a trained run)
            if rnd == 1:
                round1_se = {**se, **geometric_standard_errors(testable)}
        _adjust_and_rank(testable, cfg)
        rounds.append(results)
        picked = _name_mean_cause(testable, rnd, measured, current, ctx, split, cfg, score)
        if picked is not None:
            cause, current = picked
            _note_alternatives(cause, results, data)
            named.append(cause)
            ctx = CAUSES[cause.name].corrected_context(ctx, cause.params)  # e.g. the records it corrected
            continue
        noise = _name_noise(testable, rnd, measured, current, ctx, split, cfg)
        if noise is not None:
            named.append(noise)
        break
    model_error = None
    if cfg.trained_run:
        n_testable = sum(r.testable for r in rounds[0]) if rounds else 1
        model_error = model_error_summary(measured, predicted, current, ctx, split, cfg, round1_se, n_testable)
    verdict = named[0].name if named else NO_DISCREPANCY
    if not named and model_error is not None and model_error["dominates"]:
        verdict = RECONSTRUCTION_ERROR
    return Diagnosis(
        verdict=verdict, model_error=model_error,
        named=named, rounds=rounds, baseline_psnr_db=baseline, extended_psnr_db=score(current),
        held_out_frames=[int(ctx.frame_index[i]) for i in split.eval_idx], runtime_s=time.perf_counter() - t0,
        config=cfg, extended_prediction=current, unmodelled_fraction=unmodelled_fraction,
        unmodelled_map=unmodelled_map,
        meta={"held_out_scored_on": "odd-checkerboard pixels of held-out frames" if ctx.held_out.any() else
              "odd-checkerboard pixels of all frames (no held-out frame)",
              "frame_index": [int(i) for i in ctx.frame_index], **ctx.meta},
    )
