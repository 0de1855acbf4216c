"""Rolling-shutter readout time: the stated readout is off by a relative error."""

from __future__ import annotations

import copy
import math
from dataclasses import replace as dc_replace

import numpy as np

from egobench.effects.base import Effect
from egobench.residual.calibration import PlaceboRecord, beat_placebos, velocity_placebo
from egobench.residual.estimation import GeometricCause, ResidualData, velocity_term, velocity_term_basis
from egobench.residual.signatures import frame_t_test


#: On a trained run the readout is testable when at least this share of the fitted frames were trained with two or
#: more rolling-shutter pose samples (`ReadoutCause.untestable_on_trained_run`).
MIN_SHUTTER_FRAME_SHARE = 0.5


def shutter_frame_share(data: ResidualData) -> float | None:
    """The share of the fitted frames a trained run rendered with two or more pose samples (its rolling shutter),
    or None where the prediction is no trained run's (`DiagnosisContext.model_pose_samples` unset)."""
    n = data.ctx.model_pose_samples
    if n is None or not len(data.frames):
        return None
    return float(np.mean(np.asarray(n)[data.frames] >= 2))


def rendered_row_time(row_time_ratio: np.ndarray, n: int) -> np.ndarray:
    """The row-time ratio a run renders each pixel at with n rolling-shutter pose samples [H, W]: sample
    round(R (n - 1)) (`motion_sampling.pixel_pose_index`) at its bracket centre (k + 0.5) / n
    (`motion_sampling.sample_times_ns`); one sample renders every row at the centre, 1/2."""
    r = np.clip(np.asarray(row_time_ratio, dtype=np.float64), 0.0, 1.0)
    return (np.round(r * (n - 1)) + 0.5) / n


def staircase_shear(data: ResidualData) -> list[np.ndarray]:
    """The row shear a trained run leaves in its residual where its staircase of pose samples departs from
    the true row times: velocity term x (R - rendered R) per frame, with the pose samples each frame was
    trained with (`DiagnosisContext.model_pose_samples`; one sample: the whole readout's shear), as a one-regressor
    list (a fixed column of the velocity placebos' tables, `GeometricCause.nuisance_basis`); empty where the
    prediction is no trained run's."""
    n = data.ctx.model_pose_samples
    if n is None or data.velocity is None:
        return []
    R = np.asarray(data.ctx.row_time_ratio, dtype=np.float64)
    gap = np.stack([R - rendered_row_time(R, int(k)) for k in np.asarray(n)[data.frames]])[..., None]
    return [velocity_term(data) * gap.astype(np.float32)]


class ReadoutCause(GeometricCause):
    """Rolling-shutter readout wrong: the time shift grows linearly with row time R(u).

    theta = [a_s, b_s]: time shift a + b (R(u) - 1/2); b is the readout error (tested), a the
    shift of the centre row (0 when the centre-row timestamp is right, b/2 when read start is).
    """

    name = "readout"
    n_params = 2
    tested_index = 1
    nests = ("time_offset",)  # a + b (R - 1/2) contains the pure shift a: see core.diagnose_residuals

    def regressors(self, data):
        x = velocity_term(data)
        return [x, x * (data.ctx.row_time_ratio - 0.5)[None, :, :, None]]

    def velocity_basis(self, data):
        return [velocity_term_basis(data), velocity_term_basis(data, (data.ctx.row_time_ratio - 0.5)[None, :, :, None])]

    def nuisance_regressors(self, data):
        """On a trained run, the shear of its own staircase of pose samples (`staircase_shear`): a run rendered
        with N samples shows a readout about 1/N short, which is the model's sampling, not the device's readout
        (egobench's confirmatory runs named it once nothing else refused it). A frame rendered with one sample
        has no readout term left beside it and drops out of the test."""
        return staircase_shear(data)

    def displacement(self, theta, ctx, frames, shape):
        dt = theta[0] + theta[1] * (ctx.row_time_ratio - 0.5)
        return [(1.0, ctx.pixel_velocity_px_s[frames].astype(np.float64) * dt[None, :, :, None])]

    def step_sizes(self, ctx):
        return np.array([2e-4, 4e-4])

    def describe(self, theta, ctx):
        rel = float(theta[1] / ctx.readout_s) if ctx.readout_s > 0 else None
        return {"readout_error_s": float(theta[1]), "readout_relative_error": rel,
                "readout_s_estimated": float(ctx.readout_s + theta[1]), "centre_row_shift_s": float(theta[0])}

    def plot_data(self, data, est, info, theta):
        out = super().plot_data(data, est, info, theta)
        # time shift per row band: regress the residual on the velocity term within bands of R(u)
        x = velocity_term(data)
        R = np.broadcast_to(data.ctx.row_time_ratio[None, :, :, None], x.shape)
        m = data.usable
        edges = np.linspace(0, 1, 9)
        band = np.clip(np.searchsorted(edges, R[m], side="right") - 1, 0, 7)
        xm, rm = x[m], data.r[m]
        num = np.bincount(band, weights=xm * rm, minlength=8)
        den = np.bincount(band, weights=xm * xm, minlength=8)
        out["row_time_ratio"] = ((edges[:-1] + edges[1:]) / 2).tolist()
        out["time_shift_s"] = (num / np.maximum(den, 1e-300)).tolist()
        out["fit_a_b"] = [float(theta[0]), float(theta[1])]
        return out


    def untestable_on_trained_run(self, data):
        """A run trained at one pose sample a frame renders no rolling shutter there (the released sampling rule
        below about a pixel of row shear): its scene absorbed part of the shear, and a readout error cannot be
        told from that. Testable when at least `MIN_SHUTTER_FRAME_SHARE` of the fitted frames were trained with
        two or more samples (results/diagnosis/README.md, 2026-12-05)."""
        share = shutter_frame_share(data)
        if share is None or share >= MIN_SHUTTER_FRAME_SHARE:
            return None
        return (f"the run renders no rolling shutter on {100 * (1 - share):.0f} % of the frames (one pose sample "
                "each: the sampling rule below one step of row shear, TrainConfig.pose_sample_step_px), so a "
                "readout error cannot be told from the shear its scene absorbed; a run trained with a sub-pixel "
                "step (--set pose_sample_step_px=0.0625) renders it")

    def trained_placebos(self, result, evidence):
        """On a trained run: the velocity placebo, and wrong row times (`row_time_placebo`)."""
        record = velocity_placebo(self, result, evidence)
        if record is None:
            return []
        return [record] + ([row_time_placebo(self, evidence.data)] if result.testable else [])


# ------------------------------------------------------------------------------------------------
# On a trained run (egobench.residual.calibration)

#: Row-time bands of the row-time placebo, and how many band orders it tries.
#: 14 scrambles since the placebos' tail became a Student-t prediction interval (`beat_placebos`): with 6,
#: a synthetic hidden readout (t 13.6, one scramble at 11.3) had p 0.019; with 14, 0.0029; with 22, 0.0010,
#: while the motion-following corner null of the same test fell from 0.059 (14) to 0.035 (22). Since each placebo
#: holds the true row times' shear (`row_time_placebo`), the same hidden readout's strongest scramble is 2.7, not
#: 11.3 (p 1e-11), and the corner null's p is 0.18 (tests/diagnose/test_diagnose_trained.py, seeds 3 and 4).
ROW_TIME_BANDS, ROW_TIME_SCRAMBLES = 8, 14


def _band_orders(n_bands: int, n_orders: int, seed: int = 2026) -> list[np.ndarray]:
    """Fixed band orders far from the true one: no band in place, |rank correlation| < 0.3."""
    rng, out, ref = np.random.default_rng(seed), [], np.arange(n_bands)
    while len(out) < n_orders:
        order = rng.permutation(n_bands)
        if np.all(order != ref) and abs(np.corrcoef(order, ref)[0, 1]) < 0.3:
            out.append(order)
    return out


def row_time_maps(R: np.ndarray, valid: np.ndarray) -> list[np.ndarray]:
    """Placebo row-time maps [H, W] in 0..1: read out along the columns (both ways), and the true rows'
    bands in scrambled orders (`_band_orders`). A readout error follows the true row time only."""
    W = R.shape[1]
    cols = np.broadcast_to(np.arange(W, dtype=np.float64)[None, :] / max(W - 1, 1), R.shape)
    lo, hi = float(R[valid].min()), float(R[valid].max())
    band = np.clip(((R - lo) / max(hi - lo, 1e-12) * ROW_TIME_BANDS).astype(int), 0, ROW_TIME_BANDS - 1)
    scrambled = [(order[band] + 0.5) / ROW_TIME_BANDS for order in _band_orders(ROW_TIME_BANDS, ROW_TIME_SCRAMBLES)]
    return [cols.copy(), 1.0 - cols, *scrambled]


def row_time_placebo(cause: GeometricCause, data: ResidualData) -> PlaceboRecord:
    """A readout error on a trained run must also beat wrong row times (in place): the same statistic
    with the row-time ratio replaced by `row_time_maps`. Model error that varies over the image (a
    poorly fitted top or border) and follows the motion correlates with any of them; a readout error
    only with the true rows. p = the larger of the rank p (1 + exceed) / (1 + n) when a placebo is as
    strong and the Student-t tail of |t| (`beat_placebos`) against the placebos' |t| (as the distortion's radial placebo).

    Each placebo's fit also holds the tested shear at the true row times as a nuisance column, so a placebo
    reads only what its wrong row times explain beyond the true ones. A scrambled map keeps part of the true
    row order (rank correlation up to 0.3), and without that column a true readout error leaks into every
    placebo in proportion to its own t: the placebos' spread then grows with the effect they are to calibrate
    (sd 1.1 beside a t of 1.1, 2.6 beside a t of 9.2 on 256 px writer runs), and no effect, however strong,
    clears their tail at the Holm level (results/diagnosis/README.md, "the row-time placebo held orthogonal
    to the true row times")."""
    j = cause.tested_index
    nuisance = cause.nuisance_regressors(data)  # the run's own shear, at its true row times

    def t_of(d, columns):
        est, info = cause.first_order(d, columns)
        return frame_t_test(est[:, j], info[:, j]).t

    data.share_derivatives()
    t_real = t_of(data, nuisance)
    held = nuisance + [cause.regressors(data)[j]]  # the true row times' shear, held in every placebo's fit
    R_true = np.asarray(data.ctx.row_time_ratio)
    t_placebo = []
    for R in row_time_maps(R_true.astype(np.float64), np.asarray(data.ctx.valid, bool)):
        d = copy.copy(data)
        d.ctx = dc_replace(data.ctx, row_time_ratio=R.astype(R_true.dtype))
        t_placebo.append(t_of(d, held))
    p, exceed, p_tail = beat_placebos(t_real, t_placebo)
    return PlaceboRecord(p, {"calibration_row_time": {
        "p_value_placebo": p, "first_order_t": t_real, "placebo_t": t_placebo, "placebo_exceed": exceed, "p_tail": p_tail,
        "placebo": "row time read along the columns, and the row bands scrambled, beside the true row times"}})



class Readout(Effect):
    cause_class = ReadoutCause  # the diagnosis's estimator (egobench.residual.estimation)
    identifiability = (
        "only with image motion during the readout: the shear grows with row time and image speed, so "
        "quasi-static frames show nothing; on a run rendered with a staircase of pose samples, only by the steps "
        "between the samples' row bands, where the run's own band-wise error also sits: a run trained in sub-pixel "
        "steps (TrainConfig.pose_sample_step_px below 1) leaves less of it")
    trained_magnitudes = (0.4,)
    error_unit = "fraction"
    trained_placebo = "velocity_permutation"
    # named from 2 ms: on exploratory runs without a readout error the learned one reached 1.12 ms, readouts 4 ms
    # long were learned as 2.86-4.37 ms (results/diagnosis/README.md, "2026-12-07: the timing learned with the scene")
    learned_timing = ("readout_error_ms", 2.0)

    def sim_overrides(self, value, affected_fraction=0.25):
        return {"readout_scale": 1.0 + float(value)}  # relative error e: true = stated (1 + e)

    def learned_estimate(self, learned_ms, stated_readout_s):
        readout_s = float(stated_readout_s) + float(learned_ms) * 1e-3
        return {"readout_s_estimated": readout_s,
                "readout_relative_error": readout_s / stated_readout_s - 1.0 if stated_readout_s > 0 else None}

    def _parameter_error(self, value, params):
        return abs(params["readout_relative_error"] - value)

    def synth_row_times(self, t_model, R, value, readout_s):
        return -0.5 * readout_s + R * readout_s * (1.0 + float(value))  # read start right, readout (1 + e) longer

    def smallest_testable(self, d, se, ctx):
        return {"readout_relative_error": d / ctx.readout_s if ctx.readout_s > 0 else math.inf}

    def plot_signature(self, ax, plot):
        if "row_time_ratio" not in plot:
            return False
        r = np.asarray(plot["row_time_ratio"])
        ax.plot(r, np.asarray(plot["time_shift_s"]) * 1e3, "o", label="per row band")
        a, b = plot["fit_a_b"]
        ax.plot(r, (a + b * (r - 0.5)) * 1e3, "-", label="fit a + b (R - 1/2)")
        ax.set_xlabel("row time ratio R(u)"), ax.set_ylabel("time shift (ms)"), ax.legend(fontsize=7)
        return True


READOUT = Readout(
    name="readout",
    description="Rolling-shutter readout: raw row r starts exposing at read_start + R(u) * readout_s. "
    "Hidden: the true readout differs from the metadata by a relative error e (true = nominal * (1 + e)).",
    parameter="readout_relative_error", unit="fraction", nominal=0.0,
    plausible_range=(0.20, 0.60), sampling="signed",
    signature="Misalignment that grows linearly with row time R(u) and with image-space velocity: "
    "edges shear along the motion, residual largest at the top and bottom rows of fast frames.",
)
