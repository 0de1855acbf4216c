"""Sensitivity curves: an ablation's ΔPSNR against the size of the effect it ignores.

Input: the run records (``eval.json``) of the sweep (``snakemake sensitivity``: one recording per
swept value, 'ours' and the ablation trained with several seeds on each) and, per recording, the
JSON of ``egobench similarity`` (file name ``<scene>.json``; schema ``egobench.similarity/1``: one entry
in ``recordings`` with keys such as ``rs_shift_px_median``, ``calib_error_px_median``,
``scene_dynamic_range_stops``, and the paper's values in ``paper``; a flat dict of the keys works too).

Per recording (one point of a curve): Δ = PSNR(ablation) − PSNR(ours) paired by training seed on
that recording, the mean over seeds and its 95 % t-interval (`egobench.report.tables.ci95`), at x = the
recording's measured effect size.

Model of a curve (the prediction at the paper's operating point x*)::

    Δ(x) = −10 · log10(1 + (x / x0)^p),        x0 > 0,  0.5 ≤ p ≤ p_max

Reason: ignoring an effect adds an error image of mean square M(x) to the reconstruction error
MSE0 that 'ours' leaves, so Δ = −10 log10(1 + M(x) / MSE0), and M grows as a power of the effect
size. The power was measured (`misregistration_exponents`, ``scripts/misregistration_exponent.py``)
on a real Aria RGB frame (Aria Digital Twin sample, ``video.vrs``, area-downsampled to 64, 176 and
704 px): the mean square of the frame minus itself shifted by δ px grows as δ^p with p = 1.97-1.99
between 1/8 and 1/4 px at every size, then 1.7-1.9 between 0.5 and 1 px, 0.9-1.8 between 1 and 2 px
and 0.6-1.1 between 4 and 8 px (the image decorrelates). So for the pixel quantities (rolling-shutter shift, calibration
error) p_max = 2; elsewhere (dynamic range in stops, where a loss may switch on past the 8 stops an
8-bit image holds) p_max = 4. The model is 0 at x = 0, a power law for small effects and linear in
log x for large ones, so it covers the 'saturating' and 'linear in log' shapes with two parameters.
Caveat from the same measurement: a sweep that stays sub-pixel fits p ≈ 2, and carried to an
operating point of several pixels it overstates the loss (the true exponent there is ≈ 1): such a
prediction is an extrapolation (flagged) and a bound on the magnitude, not an estimate.

It is fitted by least squares to the points' seed means; the interval of the prediction is the
2.5-97.5 % range of a parametric bootstrap over seeds: every point's mean redrawn from its own seed
spread, mean + sem · t(n−1) (the spread behind its `ci95` interval; a plain resampling of 3 seeds
would understate it), refitted; seeded, so deterministic. An operating point outside the measured x
range is flagged as an extrapolation. The model cannot return Δ > 0: an ablation that helps fits as
Δ ≡ 0, so where any point's interval lies above zero there is no prediction (the note gives the points).

``egobench sensitivity --records EVAL... --similarity SIM_JSON... --sweep JSON... --out-dir DIR``
writes ``sensitivity.csv`` (one row per point), ``prediction.csv`` (one row per ablation) and the
figure ``sensitivity.png`` / ``.pdf`` (one panel per ablation).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from egobench.report import paper_numbers as pn
from egobench.io_utils import atomic_path, read_json
from egobench.report.gains import ci95, identical_by_construction
from egobench.report.records import GROUPS, RunRecord, load_records, method_label

OUTPUT_FILES = ("sensitivity.csv", "prediction.csv", "sensitivity.png", "sensitivity.pdf")
REFERENCE = "ours"
#: Bounds of the model's exponent p: (min, max for pixel quantities, max otherwise); see the module doc.
P_MIN, P_MAX_PX, P_MAX = 0.5, 2.0, 4.0
#: x quantities in pixels (a misregistration: its mean-square error grows at most as x^2).
PIXEL_QUANTITIES = ("rs_shift_px_median", "calib_error_px_median", "calib_inconsistency_px_median")
CURVE_COLUMNS = ["ablation", "x_quantity", "x_value", "scene", "n_seeds", "delta_psnr_mean",
                 "delta_psnr_ci95_low", "delta_psnr_ci95_high", "identical"]
PREDICTION_COLUMNS = ["ablation", "x_quantity", "paper_x", "paper_x_source", "predicted_delta_psnr",
                      "predicted_ci95_low", "predicted_ci95_high", "paper_delta_psnr", "paper_delta_source",
                      "x_min", "x_max", "extrapolation", "fit_x0", "fit_p", "fit_rms_db", "n_points", "note"]


@dataclass(frozen=True)
class Sweep:
    """One ablation's curve: what is on the x-axis and where the paper sits."""

    ablation: str  # method key of the ablation
    kind: str  # scene kind (outdoor | indoor | object | quest3): which paper table holds its Δ
    x: str  # key of the similarity JSON on the x-axis
    paper_x: float | None = None  # the paper's operating point on the x-axis
    paper_x_source: str = ""  # where that number comes from
    paper_scene: str | None = None  # the paper column whose Δ is tabled (None: the table's mean)


def parse_sweep(text: str) -> Sweep:
    """A ``--sweep`` JSON object (ablation, kind, x, paper_x, paper_x_source, paper_scene)."""
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--sweep: {text!r} is not JSON ({exc})") from exc
    if not isinstance(obj, dict):
        raise ValueError(f"--sweep: {text!r}: expected a JSON object")
    for key in ("ablation", "kind", "x"):
        if not isinstance(obj.get(key), str) or not obj[key]:
            raise ValueError(f"--sweep {text!r}: field {key!r} must be a non-empty string")
    if obj["kind"] not in {k for k, _ in GROUPS.values()}:
        raise ValueError(f"--sweep {text!r}: field 'kind' is {obj['kind']!r}; expected one of "
                         f"{sorted({k for k, _ in GROUPS.values()})}")
    paper_x = obj.get("paper_x")
    if paper_x is not None and (isinstance(paper_x, bool) or not isinstance(paper_x, (int, float))
                                or not math.isfinite(paper_x) or paper_x < 0):
        raise ValueError(f"--sweep {text!r}: field 'paper_x' is {paper_x!r}; expected a number >= 0 or null")
    return Sweep(obj["ablation"], obj["kind"], obj["x"], None if paper_x is None else float(paper_x),
                 str(obj.get("paper_x_source") or ""), obj.get("paper_scene"))


def similarity_measures(obj: object, path: Path) -> tuple[dict, dict]:
    """(measures, paper operating points) of one `egobench similarity` file: its schema
    (``{"schema": "egobench.similarity/1", "recordings": [one measure dict], "paper": {key: {"value",
    "source", ...}}}``) or a flat measure dict (no paper block)."""
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: a similarity file is a JSON object, got {type(obj).__name__}")
    if "recordings" not in obj:
        return obj, {}
    recs = obj["recordings"]
    if not isinstance(recs, list) or len(recs) != 1 or not isinstance(recs[0], dict):
        got = f"{len(recs)} entries" if isinstance(recs, list) else type(recs).__name__
        raise ValueError(f"{path}: field 'recordings' must list exactly one recording's measures "
                         f"(one file per recording), got {got}")
    paper = obj.get("paper") or {}
    if not isinstance(paper, dict):
        raise ValueError(f"{path}: field 'paper' is {type(paper).__name__}; expected an object")
    return recs[0], paper


def load_similarity(paths: Sequence[str | Path]) -> dict[str, tuple[Path, dict, dict]]:
    """scene (the file's stem) -> (path, measures, paper operating points) of `egobench similarity` files."""
    out: dict[str, tuple[Path, dict, dict]] = {}
    for p in map(Path, paths):
        measures, paper = similarity_measures(read_json(p), p)
        if p.stem in out:
            raise ValueError(f"{p}: a second similarity file for scene {p.stem!r} (also {out[p.stem][0]})")
        out[p.stem] = (p, measures, paper)
    return out


def x_value(similarity: Mapping[str, tuple], scene: str, key: str) -> float:
    """The measured effect size ``key`` of one recording; errors name the file and the key."""
    if scene not in similarity:
        raise FileNotFoundError(f"--similarity: no {scene}.json for recording {scene!r} "
                                f"(have: {', '.join(sorted(similarity)) or 'none'})")
    path, obj, _ = similarity[scene]
    value = obj.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{path}: field {key!r} is {value!r}; expected a finite number >= 0 "
                         f"(keys present: {', '.join(sorted(obj))})")
    return float(value)


def with_paper_x(sw: Sweep, similarity: Mapping[str, tuple], scenes: Sequence[str]) -> Sweep:
    """``sw`` with the paper's operating point from the similarity files' paper block where the sweep
    gives none (the first of ``scenes`` that carries a number for ``sw.x``)."""
    if sw.paper_x is not None:
        return sw
    for scene in scenes:
        entry = similarity.get(scene, (None, {}, {}))[2].get(sw.x)
        value = entry.get("value") if isinstance(entry, dict) else None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            src = f"egobench similarity: {entry.get('source', '')}".strip()
            return Sweep(sw.ablation, sw.kind, sw.x, float(value), src, sw.paper_scene)
    return sw


def paired_deltas(records: Sequence[RunRecord], ablation: str) -> dict[str, dict[int, float]]:
    """scene -> seed -> PSNR(ablation) − PSNR(ours) on that recording and seed."""
    ours = {(r.scene, r.seed): r for r in records if r.method == REFERENCE}
    out: dict[str, dict[int, float]] = {}
    for r in records:
        if r.method != ablation:
            continue
        ref = ours.get((r.scene, r.seed))
        if ref is None:
            raise ValueError(f"{r.path}: no '{REFERENCE}' run of scene {r.scene!r}, seed {r.seed} to pair with")
        out.setdefault(r.scene, {})[r.seed] = r.metrics[pn.PSNR] - ref.metrics[pn.PSNR]
    return out


def curve_frame(records: Sequence[RunRecord], similarity: Mapping, sweeps: Sequence[Sweep]) -> pd.DataFrame:
    """One row per (ablation, recording): x, seed count, mean Δ and its 95 % interval over seeds."""
    rows = []
    by_key = {(r.scene, r.method, r.seed): r for r in records}
    for sw in sweeps:
        deltas = paired_deltas(records, sw.ablation)
        if not deltas:
            raise ValueError(f"--records: no run of {sw.ablation!r} paired with '{REFERENCE}'")
        for scene, by_seed in deltas.items():
            seeds = sorted(by_seed)
            values = [by_seed[s] for s in seeds]
            low, high = ci95(values)
            pairs = [(by_key[(scene, sw.ablation, s)], by_key[(scene, REFERENCE, s)]) for s in seeds]
            rows.append({"ablation": sw.ablation, "x_quantity": sw.x, "x_value": x_value(similarity, scene, sw.x),
                         "scene": scene, "n_seeds": len(values), "delta_psnr_mean": float(np.mean(values)),
                         "delta_psnr_ci95_low": low, "delta_psnr_ci95_high": high,
                         "identical": identical_by_construction(sw.ablation, pairs)})
    df = pd.DataFrame(rows, columns=CURVE_COLUMNS)
    return df.sort_values(["ablation", "x_value", "scene"], kind="stable").reset_index(drop=True)


# --------------------------------------------------------------------------------------------
# The model and its fit


def delta_model(x: np.ndarray, x0: float, p: float) -> np.ndarray:
    """Δ(x) = −10 log10(1 + (x/x0)^p), dB; x (N,) >= 0."""
    return -10.0 * np.log10(1.0 + (np.asarray(x, float) / x0) ** p)


def p_bounds(x_quantity: str) -> tuple[float, float]:
    """The exponent's range for an x quantity (module doc: 2 at most for a misregistration in px)."""
    return (P_MIN, P_MAX_PX if x_quantity in PIXEL_QUANTITIES else P_MAX)


def fit_curve(x: np.ndarray, delta: np.ndarray, start: tuple[float, float] | None = None,
              bounds: tuple[float, float] = (P_MIN, P_MAX)) -> tuple[float, float]:
    """Least-squares (x0, p) of `delta_model` to points x (N,), Δ (N,) dB, p within ``bounds``; a
    coarse grid picks the start."""
    from scipy.optimize import least_squares

    x, delta = np.asarray(x, float), np.asarray(delta, float)
    scale = float(np.max(x[x > 0])) if np.any(x > 0) else 1.0
    lo, hi = math.log(scale * 1e-4), math.log(scale * 1e4)

    def resid(theta):
        return delta_model(x, math.exp(theta[0]), theta[1]) - delta

    if start is None:
        grid = [(lx, p) for lx in np.linspace(lo, hi, 33) for p in np.linspace(*bounds, 8)]
        theta0 = min(grid, key=lambda t: float(np.sum(resid(t) ** 2)))
    else:
        theta0 = (min(max(math.log(start[0]), lo), hi), min(max(start[1], bounds[0]), bounds[1]))
    sol = least_squares(resid, theta0, bounds=([lo, bounds[0]], [hi, bounds[1]]), x_scale=[1.0, 0.5])
    return math.exp(float(sol.x[0])), float(sol.x[1])


def predict(points: Sequence[tuple[float, np.ndarray]], x_star: float, n_boot: int = 2000,
            seed: int = 0, bounds: tuple[float, float] = (P_MIN, P_MAX)) -> dict:
    """Fit the point means (x, mean of its seed Δs) and predict Δ(x_star), with the 95 % range of a
    parametric bootstrap: each point's mean redrawn as mean + sem · t(n−1) (the spread `ci95` uses),
    refitted. A point with one seed is held fixed (no interval)."""
    from scipy.stats import t as student_t

    xs = np.array([x for x, _ in points], float)
    means = np.array([float(np.mean(d)) for _, d in points])
    sems = np.array([float(np.std(d, ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else 0.0 for _, d in points])
    dofs = np.array([max(len(d) - 1, 1) for _, d in points])
    x0, p = fit_curve(xs, means, bounds=bounds)
    rms = float(np.sqrt(np.mean((delta_model(xs, x0, p) - means) ** 2)))
    rng = np.random.default_rng(seed)
    draws = means + sems * student_t.rvs(dofs, size=(n_boot, len(points)), random_state=rng)
    boot = np.array([delta_model(np.array([x_star]), *fit_curve(xs, d, start=(x0, p), bounds=bounds))[0]
                     for d in draws])
    low, high = np.percentile(boot, [2.5, 97.5])
    return {"predicted_delta_psnr": float(delta_model(np.array([x_star]), x0, p)[0]),
            "predicted_ci95_low": float(low), "predicted_ci95_high": float(high),
            "fit_x0": x0, "fit_p": p, "fit_rms_db": rms}


def misregistration_exponents(image: np.ndarray, shifts_px: Sequence[float],
                              margin: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Mean square of ``image`` (H, W) minus itself shifted by δ px along x (Fourier shift, a
    ``margin`` px border left out), for each δ of ``shifts_px`` (increasing), and the local exponent
    d log MSE / d log δ between consecutive shifts: the measurement behind the model's p bound."""
    a = np.asarray(image, float)
    kx = np.fft.fftfreq(a.shape[1])[None, :]
    spectrum = np.fft.fft2(a)
    mse = np.array([np.mean((np.real(np.fft.ifft2(spectrum * np.exp(-2j * np.pi * kx * d))) - a)
                            [margin:-margin, margin:-margin] ** 2) for d in shifts_px])
    return mse, np.diff(np.log(mse)) / np.diff(np.log(np.asarray(shifts_px, float)))


def paper_delta(sw: Sweep) -> tuple[float | None, str]:
    """The paper's PSNR(ablation) − PSNR(ours) on ``sw.paper_scene`` (else the mean over the table of
    ``sw.kind``) and a description of which."""
    paper = next(t for k, t in GROUPS.values() if k == sw.kind)
    cols = [sw.paper_scene.lower()] if sw.paper_scene else list(paper.columns)
    d = [paper.value(sw.ablation, c, pn.PSNR) - paper.value(REFERENCE, c, pn.PSNR) for c in cols
         if paper.value(sw.ablation, c, pn.PSNR) is not None and paper.value(REFERENCE, c, pn.PSNR) is not None]
    where = f"{paper.label}, {sw.paper_scene}" if sw.paper_scene else f"{paper.label}, mean of {len(d)} scenes"
    return (round(float(np.mean(d)), 6), where) if d else (None, f"{paper.label}: no {sw.ablation} row")


def significant_gains(points: pd.DataFrame) -> pd.DataFrame:
    """The curve points whose 95 % interval lies above zero: the ablation gains there, which the loss
    model (Δ <= 0) cannot describe."""
    return points[points["delta_psnr_ci95_low"] > 0]


def prediction_row(curve: pd.DataFrame, seed_deltas: Mapping[str, Mapping[int, float]], sw: Sweep,
                   n_boot: int, seed: int) -> dict:
    """One ablation's prediction at the paper's operating point, beside the paper's Δ."""
    pts = curve[curve["ablation"] == sw.ablation]
    xs = pts["x_value"].to_numpy(float)
    paper_d, paper_src = paper_delta(sw)
    row = {"ablation": sw.ablation, "x_quantity": sw.x, "paper_x": sw.paper_x, "paper_x_source": sw.paper_x_source,
           "predicted_delta_psnr": None, "predicted_ci95_low": None, "predicted_ci95_high": None,
           "paper_delta_psnr": paper_d, "paper_delta_source": paper_src,
           "x_min": float(xs.min()), "x_max": float(xs.max()), "extrapolation": None,
           "fit_x0": None, "fit_p": None, "fit_rms_db": None, "n_points": len(pts), "note": ""}
    if len(np.unique(xs)) < 2:
        row["note"] = f"not fitted: {len(np.unique(xs))} distinct measured x value(s); a curve needs 2 or more"
        return row
    points = [(float(x), np.array([seed_deltas[s][k] for k in sorted(seed_deltas[s])]))
              for x, s in zip(xs, pts["scene"])]
    if sw.paper_x is None:
        row["note"] = "no paper operating point given (config.sensitivity.ablations.<name>.paper_x)"
        return row
    row.update(predict(points, sw.paper_x, n_boot, seed, p_bounds(sw.x)))
    gains = significant_gains(pts)
    if len(gains):  # the model cannot return a gain: its fit is no estimate of this curve
        row.update(predicted_delta_psnr=None, predicted_ci95_low=None, predicted_ci95_high=None)
        row["note"] = ("no prediction: the ablation gains with 95 % confidence at " + ", ".join(
            f"x = {g.x_value:.3g} ({g.delta_psnr_mean:+.2f} [{g.delta_psnr_ci95_low:+.2f}, "
            f"{g.delta_psnr_ci95_high:+.2f}] dB)" for g in gains.itertuples())
            + ", which a loss model (Δ <= 0) cannot describe")
        return row
    outside = not (row["x_min"] <= sw.paper_x <= row["x_max"])
    row["extrapolation"] = outside
    notes = []
    if outside:
        notes.append(f"extrapolation: the paper's x = {sw.paper_x:g} lies outside the measured "
                     f"{row['x_min']:g}..{row['x_max']:g}; the prediction rests on the model's shape")
    if all(len(d) < 2 for _, d in points):
        notes.append("one seed per point: the interval carries no seed spread")
    row["note"] = "; ".join(notes)
    return row


def prediction_frame(records: Sequence[RunRecord], curve: pd.DataFrame, sweeps: Sequence[Sweep],
                     similarity: Mapping | None = None, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """One row per ablation: predicted Δ at the paper's operating point (bootstrap interval), the paper's Δ.
    A sweep without ``paper_x`` takes it from the similarity files' paper block (`with_paper_x`)."""
    similarity = similarity or {}
    rows = []
    for sw in sweeps:
        deltas = paired_deltas(records, sw.ablation)
        sw = with_paper_x(sw, similarity, sorted(deltas))
        rows.append(prediction_row(curve, deltas, sw, n_boot, seed))
    return pd.DataFrame(rows, columns=PREDICTION_COLUMNS)


# --------------------------------------------------------------------------------------------
# Figure and outputs


def _axis_label(key: str) -> str:
    return {"rs_shift_px_median": "rolling-shutter shift during readout, median (px)",
            "calib_error_px_median": "calibration reprojection error, median (px)",
            "calib_inconsistency_px_median": "calibration error a reconstruction cannot absorb, median (px)",
            "scene_dynamic_range_stops": "scene dynamic range (stops)"}.get(key, key)


def sensitivity_figure(curve: pd.DataFrame, pred: pd.DataFrame):
    """One panel per ablation: points with their 95 % interval, the fitted model, the paper's operating
    point (dashed line), the prediction there (diamond, bootstrap interval) and the paper's Δ (star);
    a logarithmic x-axis when the values span more than 10x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(pred), 1)
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 3.6), squeeze=False)
    for ax, (_, pr) in zip(axes[0], pred.iterrows()):
        pts = curve[curve["ablation"] == pr["ablation"]]
        y = pts["delta_psnr_mean"].to_numpy(float)
        lo = pts["delta_psnr_ci95_low"].to_numpy(float)
        hi = pts["delta_psnr_ci95_high"].to_numpy(float)
        err = np.where(np.isfinite(lo), np.vstack([y - lo, hi - y]), 0.0)
        ax.errorbar(pts["x_value"], y, yerr=err, fmt="o", color="C0", capsize=3, label="egobench (95 % CI)")
        span = [*pts["x_value"].astype(float), *([float(pr["paper_x"])] if pd.notna(pr["paper_x"]) else [])]
        log_x = min(span) > 0 and max(span) > 10 * min(span)  # points bunched far below the operating point
        if log_x:  # plain numbers at the major ticks, no labels at the minor ones (they collide)
            from matplotlib.ticker import NullFormatter, ScalarFormatter

            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())
            ax.xaxis.set_minor_formatter(NullFormatter())
        if len(significant_gains(pts)):  # a gain the loss model cannot describe: its (flat) fit is not drawn
            ax.text(0.02, 0.03, "no prediction: the ablation gains", transform=ax.transAxes, fontsize=7)
        elif pd.notna(pr["fit_x0"]):
            xx = (np.geomspace(min(span) / 1.2, max(span) * 1.2, 200) if log_x
                  else np.linspace(0.0, max(span) * 1.08, 200))
            ax.plot(xx, delta_model(xx, pr["fit_x0"], pr["fit_p"]), color="C0", lw=1,
                    label=f"fit: x0={pr['fit_x0']:.3g}, p={pr['fit_p']:.2f}")
        if pd.notna(pr["paper_x"]):
            ax.axvline(pr["paper_x"], color="0.4", ls="--", lw=1, label="paper operating point")
            if pd.notna(pr["predicted_delta_psnr"]):
                d = pr["predicted_delta_psnr"]
                ax.errorbar([pr["paper_x"]], [d], yerr=[[d - pr["predicted_ci95_low"]], [pr["predicted_ci95_high"] - d]],
                            fmt="D", color="C3", capsize=3,
                            label="predicted" + (" (extrapolated)" if pr["extrapolation"] else ""))
            if pd.notna(pr["paper_delta_psnr"]):
                ax.plot([pr["paper_x"]], [pr["paper_delta_psnr"]], "*", color="k", ms=10, label="paper Δ")
        ax.axhline(0.0, color="0.8", lw=0.8)
        ax.set_title(method_label(pr["ablation"]))
        ax.set_xlabel(_axis_label(pr["x_quantity"]))
        ax.set_ylabel("ΔPSNR vs ours (dB)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def write_outputs(records: Sequence[RunRecord], similarity: Mapping, sweeps: Sequence[Sweep], out_dir: str | Path,
                  n_boot: int = 2000, seed: int = 0) -> list[Path]:
    """Write every file of OUTPUT_FILES into ``out_dir`` (atomically)."""
    from egobench.report.plots import save_figure

    out = Path(out_dir)
    curve = curve_frame(records, similarity, sweeps)
    pred = prediction_frame(records, curve, sweeps, similarity, n_boot, seed)
    written = []
    for name, df in (("sensitivity.csv", curve), ("prediction.csv", pred)):
        with atomic_path(out / name) as tmp:
            df.to_csv(tmp, index=False)
        written.append(out / name)
    return written + save_figure(sensitivity_figure(curve, pred), out, "sensitivity")


# --------------------------------------------------------------------------------------------
# CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--records", nargs="+", required=True, metavar="EVAL_JSON",
                        help="run records (eval.json) of the sweep, or folders searched for eval.json")
    parser.add_argument("--similarity", nargs="+", required=True, metavar="SIM_JSON",
                        help="`egobench similarity` output of each recording, named <scene>.json")
    parser.add_argument("--sweep", action="append", required=True, metavar="JSON",
                        help='one per ablation: {"ablation": "no_viba", "kind": "outdoor", "x": '
                             '"calib_error_px_median", "paper_x": 4.0, "paper_x_source": "...", "paper_scene": null}')
    parser.add_argument("--out-dir", required=True, help="folder for sensitivity.csv, prediction.csv and the figure")
    parser.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples over seeds (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")


def run(args: argparse.Namespace) -> int:
    if args.bootstrap < 1:
        raise ValueError(f"--bootstrap: {args.bootstrap}; expected a positive count")
    sweeps = [parse_sweep(s) for s in args.sweep]
    records = load_records(args.records)
    if not records:
        raise ValueError("--records: no eval.json run records found")
    written = write_outputs(records, load_similarity(args.similarity), sweeps, args.out_dir, args.bootstrap, args.seed)
    print(f"egobench sensitivity: {len(records)} records, {len(sweeps)} sweeps -> {len(written)} files in {args.out_dir}")
    return 0
