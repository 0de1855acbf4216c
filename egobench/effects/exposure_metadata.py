"""Exposure metadata wrong on some frames: the recorded exposure is the true one times (1 + e)."""

from __future__ import annotations

import math
from dataclasses import replace as dc_replace

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.calibration import OWN_P, Cells, PlaceboRecord, TrainedRunEvidence
from egobench.residual.estimation import (DISPLAY_MAX, DISPLAY_MIN, Cause, CauseResult, PhotometricFit, ResidualData,
                                          own_term, photometric_apply)
from egobench.residual.signatures import decode, psnr, robust_sd

#: A frame of a trained run is flagged when both halves of it deviate beyond this many robust standard
#: deviations of the model's frame-to-frame error, and beyond FLAG_MIN_LOG. The floor is the largest
#: single-frame scale that model error alone gave on the trained sweeps' cases without a metadata error
#: (outdoor, 64 px, 800 iterations: 14 % on one frame of one null, all others <= 11 %; results/diagnosis/README.md):
#: single frames of a trained model can render that much too dark or bright. It applies where the exposure
#: varies; at a fixed record the floor is the run's own (`fixed_record_floor`).
FLAG_SIGMAS, FLAG_MIN_LOG = 4.0, math.log(1.15)


def flag_frames_in_both_halves(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Frames [n] whose left (a) and right (b) log scales [n] BOTH deviate from the bulk of the frames,
    with the same sign, beyond FLAG_SIGMAS x the larger of the halves' disagreement and the bulk's
    robust scatter (model error moves every frame a little), and beyond FLAG_MIN_LOG -> (flags, threshold).

    The bulk comes from the shortest half of the frames' scales (`bulk_frames`). A
    metadata error on a quarter of the frames makes the frame scales bimodal (the model's colours
    absorb part of it and shift the other frames the other way); one median/MAD over all frames then
    straddles the two groups and its threshold exceeds the error (measured: 0.24 for errors of 0.13-0.20)."""
    sd_half = robust_sd((a - b) / math.sqrt(2.0))
    bulk = bulk_frames(0.5 * (a + b))
    ca, cb = a - np.median(a[bulk]), b - np.median(b[bulk])
    threshold = max(FLAG_SIGMAS * max(sd_half, robust_sd(ca[bulk]), robust_sd(cb[bulk])), FLAG_MIN_LOG)
    return (np.abs(ca) > threshold) & (np.abs(cb) > threshold) & (np.sign(ca) == np.sign(cb)), threshold


#: Frames within this many robust sds of the shortest half's centre form the bulk (one-step reweighting).
BULK_SIGMAS = 3.0


def bulk_frames(scale_log: np.ndarray) -> np.ndarray:
    """The bulk of the frames' log scales [n] -> mask [n]: within BULK_SIGMAS of the centre of the
    shortest half, its half-width / 0.6745 taken as the sd (robust to any minority group, unlike one
    median/MAD; reweighting once keeps the frames that only the minority's offset would exclude)."""
    order = np.argsort(scale_log)
    s = scale_log[order]
    h = s.size // 2 + 1
    i = int(np.argmin(s[h - 1:] - s[:s.size - h + 1]))
    centre, sd = 0.5 * (s[i] + s[i + h - 1]), 0.5 * (s[i + h - 1] - s[i]) / 0.6745
    return np.abs(scale_log - centre) <= max(BULK_SIGMAS * sd, 1e-12)


#: Frames on each side whose median a frame's scale is taken against (`view_contrast`).
VIEW_NEIGHBOURS = 3


def view_contrast(scale_log: np.ndarray, k: int = VIEW_NEIGHBOURS) -> np.ndarray:
    """Frame log scales [n], in capture order -> each frame's contrast with its k neighbours on each
    side: the smaller of (scale - median before) and (scale - median after) when both have the same
    sign, else 0 (one side alone at the ends of the walk). `metadata_flags` flags a frame only when it
    is off against the bulk of the frames AND against these.

    A metadata error is a glitch of single frames; a brightness error that the frames seeing the same
    content share (a stretch of the walk whose bright content the model under-renders, measured on an
    outdoor null: ten consecutive frames 1.4-1.7x) follows the view, not the metadata: it cancels,
    also at the stretch's first and last frames, which match the frames on one side."""
    n = scale_log.size
    out = np.zeros(n)
    for i in range(n):
        sides = [scale_log[i] - np.median(nb) for nb in (scale_log[max(0, i - k):i], scale_log[i + 1:i + 1 + k])
                 if nb.size]
        if sides and (all(c > 0 for c in sides) or all(c < 0 for c in sides)):
            out[i] = min(sides, key=abs)
    return out


def metadata_flags(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Frames [n] (capture order) whose left (a) and right (b) log scales are off against the bulk
    -> (that, that AND off against the frames' view neighbours (`view_contrast`), threshold)."""
    both, threshold = flag_frames_in_both_halves(a, b)
    local, _ = flag_frames_in_both_halves(view_contrast(a), view_contrast(b))
    return both, both & local, threshold


#: A record glitch: the image's scale jumps against the record's jump by at least this fraction of it.
GLITCH_FOLLOW = 0.5
#: The record counts as fixed when at least this share of the frames record the median exposure x gain
#: (within FIXED_RECORD_LOG): a lab capture, or the hard cases' 1 ms at gain 12.
FIXED_RECORD_SHARE, FIXED_RECORD_LOG = 0.5, 1e-3


def recorded_glitch_flags(a: np.ndarray, b: np.ndarray, recorded_log: np.ndarray) -> np.ndarray:
    """At a FIXED exposure and gain: frames [n] (capture order) whose recorded log exposure x gain [n]
    departs from the record's median while the image does not follow it. a, b: log measured / predicted of
    the frames' left and right halves. A frame is flagged when its whole scale ((a + b) / 2) jumps the other
    way against its neighbours at the fixed record (`fixed_record_contrast`) by at least the run's own floor
    (`fixed_record_floor`), the departure itself is at least that floor, and at least one half jumps the other
    way by GLITCH_FOLLOW of the departure (nearer "the image did not follow the record" than "it did"; a
    response error follows a change part-way in both halves). One half is enough: a run absorbs a wrong
    record where the content was seen only in the altered frames, so the error can show in one half alone
    (an independent writer's case: -0.19 to -0.21 in one half, -0.03 to +0.05 in the other; record x 1.25).
    A poorly fitted run's frame-to-frame error hides a 25 % error from the bulk test (hard sweep: 4 robust sds
    = 31 %); the record's own departure cannot hide. With an exposure that varies (auto-exposure), a
    record's change says nothing by itself, and neighbouring wrong records shift every contrast: no frame is
    flagged this way."""
    if not record_is_fixed(recorded_log):
        return np.zeros(np.size(recorded_log), dtype=bool)
    dx, at_fixed = record_departures(recorded_log)
    floor = fixed_record_floor(a, b, at_fixed)
    whole = fixed_record_contrast(0.5 * (a + b), at_fixed)
    shown = np.maximum(_against(fixed_record_contrast(a, at_fixed), dx), _against(fixed_record_contrast(b, at_fixed), dx))
    return (~at_fixed & (np.abs(dx) >= floor) & (whole * dx < 0) & (np.abs(whole) >= floor)
            & (shown >= GLITCH_FOLLOW * np.abs(dx)))


def _against(contrast: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """How far each frame's contrast [n] goes against the record's departure dx [n] (0 where it goes with it)."""
    return np.where(contrast * dx < 0, np.abs(contrast), 0.0)


def _neighbours_at_fixed(i: int, at_fixed: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest frames before and after frame i whose record is at the fixed value."""
    idx = np.flatnonzero(at_fixed)
    return idx[idx < i][-k:], idx[idx > i][:k]


def fixed_record_contrast(scale_log: np.ndarray, at_fixed: np.ndarray, k: int = VIEW_NEIGHBOURS) -> np.ndarray:
    """`view_contrast` against the k nearest frames on each side whose record is at the fixed value (mask
    ``at_fixed`` [n]): wrong records cluster (a quarter of the frames: runs of two to four), and a frame's
    neighbours with wrong records of their own would take its contrast away."""
    out = np.zeros(scale_log.size)
    for i in range(scale_log.size):
        sides = [scale_log[i] - np.median(scale_log[nb]) for nb in _neighbours_at_fixed(i, at_fixed, k) if nb.size]
        if sides and (all(c > 0 for c in sides) or all(c < 0 for c in sides)):
            out[i] = min(sides, key=abs)
    return out


def fixed_record_floor(a: np.ndarray, b: np.ndarray, at_fixed: np.ndarray, k: int = VIEW_NEIGHBOURS) -> float:
    """The run's own floor for a wrong record at a fixed exposure (log scale): FLAG_SIGMAS x the robust sd of
    the frame-to-frame error of the frames' whole scale ((a + b) / 2 of the halves' log scales a, b), measured
    on the frames whose record is at the fixed value as each one's deviation from the median of its k
    neighbours there on both sides. Those frames' records agree, so what moves them against their neighbours
    is the model's error (and noise), not the metadata. The whole scale, not each half's: a half's error is
    the larger (the model's error in part of a frame; an independent writer's case, robust sd 0.085 a half
    against 0.03 for the whole), and a flag reads the whole (`recorded_glitch_flags`)."""
    s = 0.5 * (np.asarray(a, float) + np.asarray(b, float))
    dev = [s[i] - np.median(s[np.concatenate(_neighbours_at_fixed(i, at_fixed, k))]) for i in np.flatnonzero(at_fixed)]
    return FLAG_SIGMAS * robust_sd(np.asarray(dev)) if len(dev) >= 4 else math.inf


def record_departures(recorded_log: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A record of log exposure x gain [n] -> (each frame's departure from the record's median [n], whether the
    frame records that median, within FIXED_RECORD_LOG [n])."""
    x = np.asarray(recorded_log, float)
    dx = x - np.median(x) if x.size else x
    return dx, np.abs(dx) <= FIXED_RECORD_LOG


def fixed_record_doubt(recorded_log: np.ndarray, shown_wrong: list[int]) -> np.ndarray:
    """Frames [n] whose record is in doubt once the positions ``shown_wrong`` are shown wrong: at a fixed record
    (`record_is_fixed`) every other departure from the fixed value, as a fixed exposure setting has no reason to
    depart; an exposure that varies, or nothing shown wrong: none. A later test reads the fixed value there, so
    no exposure change rests on a record of the kind already shown wrong."""
    dx, at_fixed = record_departures(recorded_log)
    doubt = np.zeros(dx.size, dtype=bool)
    if shown_wrong and record_is_fixed(recorded_log):
        doubt = ~at_fixed
        doubt[list(shown_wrong)] = False
    return doubt


def record_is_fixed(recorded_log: np.ndarray) -> bool:
    """Whether a record of log exposure x gain [n] is fixed: at least FIXED_RECORD_SHARE of the
    frames record its median (within FIXED_RECORD_LOG)."""
    at_fixed = record_departures(recorded_log)[1]
    return bool(at_fixed.size) and float(np.mean(at_fixed)) >= FIXED_RECORD_SHARE


def where_a_fixed_record_departs(flags: np.ndarray, a: np.ndarray, b: np.ndarray,
                                 recorded_log: np.ndarray) -> np.ndarray:
    """Flags [n] kept at a FIXED record (`record_is_fixed`): only frames whose own recorded log
    exposure x gain departs from the median by at least the run's floor (`fixed_record_floor`) while both
    halves' log scales (a, b [n], centred) go the other way. At a fixed exposure setting a frame that
    brightens while its record stays is the light (flicker) or the model's error; no image can show that
    record wrong. An exposure that varies keeps every flag."""
    if not record_is_fixed(recorded_log):
        return flags
    dx, at_fixed = record_departures(recorded_log)
    floor = fixed_record_floor(a, b, at_fixed)
    return flags & ~at_fixed & (np.abs(dx) >= floor) & (a * dx < 0) & (b * dx < 0)


def record_aware_flags(flags: np.ndarray, a: np.ndarray, b: np.ndarray, recorded_log: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split-half flags [n] (capture order; a, b centred log scales of the halves [n]) checked against
    the recorded log exposure x gain [n] (None: no record) -> (flags kept (`where_a_fixed_record_departs`),
    flags dropped because a fixed record did not change there, frames flagged by the record's own
    glitches besides the kept ones (`recorded_glitch_flags`)). The split-half test and the held-out
    rule (`held_out_flags`) both flag this way."""
    if recorded_log is None:
        none = np.zeros_like(flags)
        return flags, none, none
    rec = np.asarray(recorded_log, float)
    kept = where_a_fixed_record_departs(flags, a, b, rec)
    return kept, flags & ~kept, recorded_glitch_flags(a, b, rec) & ~kept


class ExposureMetadataCause(Cause):
    """Per-frame exposure/gain metadata error: a global per-frame scale."""

    name = "exposure_metadata"
    frame_local = True

    def corrected_context(self, ctx, params):
        """The records after this cause is named: each flagged frame's exposure times its scale over the median
        scale of the frames not flagged (`frame_scale`: measured over predicted). Without it a later round's
        response test read the wrong records as exposure changes (a spread of 0.095 at a fixed record) and
        named a response after the records on 3 of 12 fresh hard-sweep cases and 2 of 10 of the writer's
        (results/diagnosis/README.md, 2026-12-06, the corrected records). At a fixed record (`record_is_fixed`) the
        departures it did not flag are in doubt too, once some are shown wrong (a run absorbs part of a wrong record,
        so the test flags some of them: 5 of 12 on a writer's case, whose 7 others then named a response):
        `fixed_record_doubt` reads the record's fixed value there."""
        flagged = {int(f) for f in params.get("flagged_frames") or []}
        scale = {int(f): float(v) for f, v in (params.get("frame_scale") or {}).items()}
        rest = [math.log(v) for f, v in scale.items() if f not in flagged and v > 0]
        if not flagged or not rest:
            return ctx
        reference = float(np.median(rest))
        exposure = np.array(ctx.exposure_s, dtype=np.float64)
        where = {int(f): i for i, f in enumerate(np.asarray(ctx.frame_index).tolist())}
        for f in flagged:
            if f in where and scale.get(f, 0.0) > 0:
                exposure[where[f]] *= math.exp(math.log(scale[f]) - reference)
        recorded = ctx.log_exposure_gain
        doubt = fixed_record_doubt(recorded, [where[f] for f in flagged if f in where])
        exposure[doubt] = np.exp(float(np.median(recorded))) / np.asarray(ctx.gain, float)[doubt]
        return dc_replace(ctx, exposure_s=exposure)

    def fit(self, data: ResidualData) -> CauseResult:
        fit = data.photometric()
        if not fit.testable:
            return self._untestable("too few usable photometric cells")
        f, p, q = fit.test("frame")
        beta = fit.coefs("frame")
        dev = beta - fit.log_global
        spread = 1.4826 * float(np.median(np.abs(dev))) + 1e-12
        flagged = np.flatnonzero((np.abs(dev) > max(4.0 * spread, 0.03)))
        scale = np.exp(dev)
        errors = (1.0 / scale[flagged] - 1.0).tolist()  # recorded = true x (1 + e): measured / predicted = 1 / (1 + e)
        res = CauseResult(self.name, self.kind, True, statistic=f, statistic_kind=f"F({q}, {fit.dof})", p_value=p,
                          params={"frame_scale": {int(data.ctx.frame_index[fr]): float(s) for fr, s in zip(data.frames, scale)},
                                  "flagged_frames": [int(data.ctx.frame_index[data.frames[i]]) for i in flagged],
                                  "exposure_relative_error": errors,
                                  "median_exposure_relative_error": float(np.median(errors)) if errors else 0.0,
                                  "global_gain": math.exp(fit.log_global), "note": "global_gain: median frame gain of the joint fit"},
                          internal={"log_scale": dict(zip(data.frames.tolist(), dev.tolist())),
                                    "log_global": fit.own_global("frame")})
        res.effect_rms = self._effect(data, self.apply(data.p, own_term(res), data.ctx, data.frames))
        res.plot = {"frame": [int(data.ctx.frame_index[fr]) for fr in data.frames], "scale": scale.tolist(),
                    "flagged": res.params["flagged_frames"], "xlabel": "frame", "ylabel": "measured / predicted (linear)"}
        return res

    def nothing_to_name(self, result):
        if not result.params.get("flagged_frames"):
            return "no frame flagged: no record to correct, so nothing is named"
        return None

    def apply(self, predicted, result, ctx, frames, measured=None, fit_mask=None):
        """Each fitted frame's scale; a frame not fitted (held out) gets its own scale from the fit pixels,
        on a trained run only when the split-half rule would flag it too (`held_out_flags`)."""
        i = result.internal
        logs = np.zeros(len(frames))
        frames = np.asarray(frames).tolist()
        own = [fr not in i["log_scale"] for fr in frames]
        if measured is not None and any(own):
            rule = bool(i.get("held_out_rule"))  # the halves of every frame are needed only for the rule
            scales = np.array([_pixel_log_scales(measured[j], predicted[j], ctx, fit_mask, i["log_global"])
                               if rule or own[j] else (np.nan, np.nan, 0.0) for j in range(len(frames))])
            recorded = ctx.log_exposure_gain[frames]
            allowed = held_out_flags(scales[:, 0], scales[:, 1], recorded) if rule else np.ones(len(frames), bool)
        for j, fr in enumerate(frames):  # loop over frames, not pixels
            if not own[j]:
                logs[j] = i["log_scale"][fr]
            elif measured is not None and allowed[j]:
                logs[j] = scales[j, 2]
        return photometric_apply(predicted, (i["log_global"] + logs)[:, None, None, None], ctx.gamma_assumed)

    def apply_within_frames(self, predicted, result, ctx, measured, fit_mask):
        """Every frame's scale from its own fit_mask pixels, where the split-half rule flags it."""
        within = CauseResult(result.name, result.kind, result.testable, params=result.params,
                             internal={**result.internal, "log_scale": {}})
        return self.apply(predicted, within, ctx, np.arange(predicted.shape[0]), measured=measured, fit_mask=fit_mask)


    def trained_placebos(self, result, evidence):
        """On a trained run: the per-frame scales of the frames' left and right halves must agree beyond
        shuffled pairings (`exposure_split_half`); the frames it flags become the estimate (in place)."""
        if not evidence.photometric_fit.testable:
            return []
        split = _in_recording_frames(evidence.memo(metadata_split_half), evidence.data)
        if "frames_flagged_in_both_halves" in split:
            _metadata_estimate_from_split(result, split["frames_flagged_in_both_halves"])
        info = {k: v for k, v in split.items() if k != "testable"}
        calibration = {"p_value_placebo": split["p"], "render_blur_px": evidence.blur_px, **info}
        return [PlaceboRecord(split["p"], {"p_value_cells": OWN_P, "calibration": calibration})]

    def trained_standard_error(self, evidence):
        if not evidence.photometric_fit.testable:
            return None
        split = evidence.memo(metadata_split_half)
        return split["robust_sd"], split.get("n_frames", 0) - 1

def held_out_flags(left: np.ndarray, right: np.ndarray, recorded_log: np.ndarray | None = None) -> np.ndarray:
    """Which frames [n] (capture order; log scales of their left / right halves [n]; recorded log
    exposure x gain [n]) the split-half rule flags (`metadata_flags`, or `recorded_glitch_flags`): a
    held-out frame's exposure is corrected only where the test would call its metadata wrong, so that
    the held-out gain is earned by the cause, not by a free gain per frame."""
    ok = np.isfinite(left) & np.isfinite(right)
    out = np.zeros(left.size, dtype=bool)
    if ok.sum() >= 4:
        a, b = left[ok] - np.median(left[ok]), right[ok] - np.median(right[ok])
        rec = None if recorded_log is None else np.asarray(recorded_log, float)[ok]
        kept, _, glitch = record_aware_flags(metadata_flags(a, b)[1], a, b, rec)
        out[ok] = kept | glitch
    return out


def _pixel_log_scales(measured: np.ndarray, predicted: np.ndarray, ctx, fit_mask,
                      log_global: float) -> tuple[float, float, float]:
    """log(sum measured / sum predicted x global gain), linear, over one frame's [H, W, 3] usable fit
    pixels -> (left half of the columns, right half, all); a half without pixels is nan, all of them 0."""
    lin_m = decode(measured, ctx.gamma_assumed)
    lin_p = decode(predicted, ctx.gamma_assumed) * math.exp(log_global)
    m = (predicted > DISPLAY_MIN) & (predicted < DISPLAY_MAX) & (measured < 0.985)
    if fit_mask is not None:
        m &= np.broadcast_to(fit_mask[..., None], m.shape)
    m &= np.broadcast_to(ctx.valid[..., None], m.shape)
    left = np.broadcast_to((np.arange(m.shape[1]) < m.shape[1] / 2.0)[None, :, None], m.shape)

    def log_ratio(sel: np.ndarray, empty: float) -> float:
        if not sel.any():
            return empty
        return math.log(max(lin_m[sel].sum(), 1e-12) / max(lin_p[sel].sum(), 1e-12))

    return log_ratio(m & left, math.nan), log_ratio(m & ~left, math.nan), log_ratio(m, 0.0)



# ------------------------------------------------------------------------------------------------
# On a trained run (egobench.residual.calibration)

def gain_like(fit: PhotometricFit, cells: Cells, frames: np.ndarray) -> np.ndarray:
    """Is each frame's deviation [n frames] the same for its dark and bright cells, as a gain's is?
    -> bool [n]: the within-frame slope of the partial residual over the cell's log intensity is
    within FLAG_SIGMAS robust sds of the frames' median slope. A model that under-renders bright
    content (measured on an outdoor null's flagged frame: measured / predicted 1.2 in its darkest
    fifth, 0.57 in its brightest) tilts its frame; a metadata error scales every cell alike."""
    pr, x = fit.partial_residual("frame"), fit.log_p
    slope = np.full(fit.n_frames, np.nan)
    for f in range(fit.n_frames):
        sel = fit.keep & (cells.frame == f)
        if sel.sum() >= 8 and np.ptp(x[sel]) > 0:
            w = fit.w[sel]
            xc = x[sel] - np.average(x[sel], weights=w)
            slope[f] = np.sum(w * xc * pr[sel]) / max(np.sum(w * xc * xc), 1e-300)
    ok = np.isfinite(slope)
    if ok.sum() < 4:
        return np.ones(len(frames), dtype=bool)
    med, sd = np.median(slope[ok]), robust_sd(slope[ok])
    return ~(np.abs(slope[frames] - med) > FLAG_SIGMAS * sd)


def exposure_split_half(fit: PhotometricFit, cells: Cells, draws: int, rng: np.random.Generator,
                        recorded_log: np.ndarray | None = None) -> dict:
    """Agreement of per-frame log scales from the left and right halves of each frame, against
    the same agreement with the right halves' frame labels shuffled (placebo) -> empirical p.
    Frames flagged: `metadata_flags`, and `recorded_glitch_flags` with ``recorded_log`` [fitted frames]."""
    pr = fit.partial_residual("frame")
    keep = fit.keep
    left = cells.col < cells.n_cols / 2.0
    dev = np.full((2, fit.n_frames), np.nan)
    for h, side in enumerate((left, ~left)):
        for f in range(fit.n_frames):  # per-frame weighted means
            sel = keep & side & (cells.frame == f)
            if sel.sum() >= 4:
                dev[h, f] = np.average(pr[sel], weights=fit.w[sel])
    ok = np.isfinite(dev).all(axis=0)
    a, b = dev[0, ok], dev[1, ok]
    if a.size < 4:
        return {"testable": False, "p": 1.0, "corr": 0.0, "robust_sd": math.nan}
    a, b = a - np.median(a), b - np.median(b)

    def corr(x, y):
        return float(np.sum(x * y) / math.sqrt(max(np.sum(x * x) * np.sum(y * y), 1e-300)))

    observed = corr(a, b)
    placebo = np.array([corr(a, rng.permutation(b)) for _ in range(int(draws))])
    p = float((1 + np.sum(placebo >= observed)) / (1 + draws))
    off, flags, threshold = metadata_flags(a, b)
    view_shared = np.flatnonzero(ok)[off & ~flags]
    flags, unchanged, glitch = record_aware_flags(flags, a, b, None if recorded_log is None else recorded_log[ok])
    frames = np.flatnonzero(ok)[flags | glitch]
    not_gain = frames[~gain_like(fit, cells, frames)]
    frames = np.setdiff1d(frames, not_gain)
    p_corr = p
    if frames.size == 0:
        p = 1.0
    rec = None if recorded_log is None else np.asarray(recorded_log, float)[ok]
    fixed_floor = (fixed_record_floor(a, b, record_departures(rec)[1])
                   if rec is not None and record_is_fixed(rec) else None)
    return {"testable": True, "p": p, "p_placebo_corr": p_corr, "corr": observed,
            "placebo_corr_q99": float(np.quantile(placebo, 0.99)),
            "flag_threshold_log": threshold, "frames_flagged_in_both_halves": frames.tolist(),
            "frames_off_but_not_a_gain": not_gain.tolist(), "frames_off_with_their_view_neighbours": view_shared.tolist(),
            "frames_where_the_record_jumps_alone": np.flatnonzero(ok)[glitch].tolist(),
            "frames_off_at_an_unchanged_fixed_record": np.flatnonzero(ok)[unchanged].tolist(),
            "fixed_record_floor_log": fixed_floor,
            "robust_sd": (threshold if fixed_floor is None else fixed_floor) / FLAG_SIGMAS, "n_frames": int(a.size)}


def _metadata_estimate_from_split(r: CauseResult, flagged: list[int]) -> None:
    """The exposure-metadata estimate on the frames the split-half test flags (in place), so that the
    test and the estimate agree; the joint fit's own flags (one median/MAD) stay as flagged_frames_cells."""
    scale = r.params.get("frame_scale", {})
    errors = [1.0 / scale[f] - 1.0 for f in flagged if f in scale]  # recorded = true x (1 + e)
    r.params["flagged_frames_cells"] = r.params.get("flagged_frames", [])
    r.params["flagged_frames"] = [f for f in flagged if f in scale]
    r.params["exposure_relative_error"] = errors
    r.params["median_exposure_relative_error"] = float(np.median(errors)) if errors else 0.0
    r.internal["held_out_rule"] = True  # a trained run: held-out frames are corrected only where flagged
    if r.plot:
        r.plot["flagged"] = r.params["flagged_frames"]



def metadata_split_half(evidence: TrainedRunEvidence) -> dict:
    """`exposure_split_half` of a trained run (frames as positions among the fitted frames; shared with the
    response's test, which leaves the flagged frames out)."""
    data = evidence.data
    return exposure_split_half(evidence.photometric_fit, evidence.cells, evidence.draws, evidence.rng(15),
                               data.ctx.log_exposure_gain[data.frames])


#: `exposure_split_half`'s lists of frames
SPLIT_FRAME_LISTS = ("frames_flagged_in_both_halves", "frames_off_but_not_a_gain", "frames_off_with_their_view_neighbours",
                     "frames_where_the_record_jumps_alone", "frames_off_at_an_unchanged_fixed_record")


def _in_recording_frames(split: dict, data: ResidualData) -> dict:
    """``split`` with its frame lists as the recording's frame indices (positions among the fitted frames there)."""
    out = dict(split)
    if "frames_flagged_in_both_halves" in out:
        for key in SPLIT_FRAME_LISTS:
            out[key] = [int(data.ctx.frame_index[data.frames[i]]) for i in out[key]]
    return out


class ExposureMetadata(Effect):
    cause_class = ExposureMetadataCause  # the diagnosis's estimator (egobench.residual.estimation)
    trained_placebo = "photometric"
    identifiability = (
        "only when the recorded exposure x gain varies or some frames are wrong against the others; a "
        "model-error floor of 15 % on single frames applies on trained runs with an exposure that varies; at a "
        "fixed exposure x gain, only on frames whose own record departs (a frame that brightens at an unchanged "
        "record is light or model error), beyond the run's own frame-to-frame error at the fixed record")
    trained_magnitudes = (0.25,)
    in_trained_sweep = True
    on_adt = True
    error_unit = "fraction"
    estimate_key = "median_exposure_relative_error"

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"exposure_metadata_error": float(value), "exposure_metadata_fraction": float(affected_fraction)}

    def _parameter_error(self, value, params):
        return abs(params["median_exposure_relative_error"] - value)

    def synth_exposure(self, k_recorded, rng, value, metadata_fraction):
        """Frame 8 (the first held-out one after 0) and a random share of the others get (1 + e)."""
        F = len(k_recorded)
        n_aff = max(2, int(round(metadata_fraction * F)))
        pool = [f for f in range(F) if f != 8]
        affected = sorted([8] + rng.choice(pool, n_aff - 1, replace=False).tolist()) if F > 8 else sorted(
            rng.choice(F, n_aff, replace=False).tolist())
        k_recorded[affected] *= 1.0 + float(value)
        return affected

    learned_per_frame = "learned_frame_exposure"

    def judge_learned_frames(self, frames, values):
        """The log scales a run learned for its training frames with the scene (`egobench.model.frame_exposure`):
        a frame is flagged where its scale departs from the bulk of the frames' (`bulk_frames`) by more than
        FLAG_SIGMAS robust standard deviations of the bulk, the run's own frame-to-frame scatter, and by more than
        FLAG_MIN_LOG, the single-frame model error that trained runs reach (15 %). Its record's error is estimated
        as exp(-departure) - 1 (the record is the true exposure times 1 + e)."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 1 or values.size != len(frames) or values.size < 3 or not np.all(np.isfinite(values)):
            raise ValueError(f"field '{self.learned_per_frame}': expected finite log scales, one per listed frame and at least 3, "
                             f"got {values.size} for {len(frames)} frames")
        bulk = bulk_frames(values)
        centre = float(np.median(values[bulk]))
        sd = robust_sd(values[bulk] - centre)
        threshold = max(FLAG_SIGMAS * sd, FLAG_MIN_LOG)
        departure = values - centre
        flagged = np.abs(departure) > threshold
        return {"centre": centre, "bulk_sd": sd, "threshold": threshold,
                "flagged_frames": [int(f) for f, x in zip(frames, flagged) if x],
                "record_error": {str(int(f)): math.exp(-d) - 1.0 for f, d, x in zip(frames, departure, flagged) if x}}

    def learned_frames_gain(self, measured, predicted, ctx, verdict, learned, fit_mask, eval_mask):
        """The within-frame gain of the frames ``verdict`` flags, the learned route's counterpart of
        `apply_within_frames`: each flagged frame of the stack [F, H, W, 3] (rendered at its learned log scale,
        ``learned``: frame index -> log scale) is taken to the bulk's centre (its record as stated), then scaled by
        the log ratio of its own fit_mask pixels (`_pixel_log_scales`; pixels the render clipped left out) and
        scored on eval_mask -> {"gain_db": PSNR gain, mean over the stack's F frames as `signatures.psnr`'s,
        "frames": the flagged frames scored}, or None where the stack holds none of them (max_frames)."""
        position = {int(f): j for j, f in enumerate(ctx.frame_index)}
        scored = [(int(f), position[int(f)]) for f in verdict["flagged_frames"] if int(f) in position]
        if not scored:
            return None
        total = 0.0
        for f, j in scored:
            to_centre = np.full((1, 1, 1, 1), verdict["centre"] - learned[f])
            at_centre = photometric_apply(predicted[j:j + 1], to_centre, ctx.gamma_assumed)
            unclipped = fit_mask & (predicted[j] < DISPLAY_MAX).all(-1)
            own = _pixel_log_scales(measured[j], at_centre[0], ctx, unclipped, 0.0)[2]
            extended = photometric_apply(at_centre, np.full((1, 1, 1, 1), own), ctx.gamma_assumed)
            total += psnr(extended, measured[j:j + 1], eval_mask) - psnr(at_centre, measured[j:j + 1], eval_mask)
        return {"gain_db": total / predicted.shape[0], "frames": len(scored)}

    def smallest_testable(self, d, se, ctx):
        """At a fixed record the run's own floor (`fixed_record_floor`: se is a quarter of it) decides a flag;
        with an exposure that varies, the bulk test's threshold with its floor FLAG_MIN_LOG."""
        floor = FLAG_SIGMAS * se if record_is_fixed(ctx.log_exposure_gain) else max(FLAG_SIGMAS * se, FLAG_MIN_LOG)
        return {"exposure_relative_error": math.exp(floor) - 1.0}

    def plot_signature(self, ax, plot):
        ax.plot(plot["frame"], plot["scale"], "o-")
        flagged = [i for i, f in enumerate(plot["frame"]) if f in set(plot["flagged"])]
        ax.plot([plot["frame"][i] for i in flagged], [plot["scale"][i] for i in flagged], "rs", label="flagged")
        ax.set_xlabel(plot["xlabel"]), ax.set_ylabel(plot["ylabel"]), ax.legend(fontsize=7)
        return True


EXPOSURE_METADATA = ExposureMetadata(
    name="exposure_metadata",
    description="Per-frame exposure metadata wrong on a random subset of frames (the simulator chooses "
    "which): the recorded exposure_s is the true one times (1 + e).",
    parameter="exposure_relative_error", unit="fraction", nominal=0.0,
    plausible_range=(0.10, 0.30), sampling="signed",
    formation_switch="exposure_gain",
    signature="Whole-frame brightness ratio between captured and predicted images that is constant "
    "within a frame, differs between frames, and does not follow the recorded exposure * gain.",
)
