"""The gains table (``gains.csv``): each ablation's and baseline's held-out PSNR change against its reference,
ours beside the paper's, with its interval, the one-sided test in the paper's direction, Holm's correction over
the rows and the three counts a reproduction reports (docs/protocol.md, docs/protocol-2.md)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import pandas as pd

from egobench.report import paper_numbers as pn
from egobench.report.records import GAIN_REFERENCE, GROUPS, RunRecord

def ci95(values: Sequence[float]) -> tuple[float | None, float | None]:
    """Two-sided 95 % t-interval of the mean of ``values`` (seed-level paired differences); (None,
    None) below two values."""
    n = len(values)
    if n < 2:
        return None, None
    from scipy.stats import t

    mean, sem = float(np.mean(values)), float(np.std(values, ddof=1)) / math.sqrt(n)
    half = float(t.ppf(0.975, n - 1)) * sem
    return mean - half, mean + half


def identical_by_construction(method: str, pairs: Sequence[tuple[RunRecord, RunRecord]]) -> str:
    """Why ``method`` cannot differ from its reference on these runs ('' when it can): a motion-sampling
    ablation whose reference rendered every frame with one pose sample, at training and evaluation, is
    the same computation. Detected from the records, never assumed: every paired PSNR must be equal too."""
    if not pairs or any(a.metrics[pn.PSNR] != b.metrics[pn.PSNR] for a, b in pairs):
        return ""
    if "no_motion_sampling" in method:
        one_sample = all((b.raw.get("eval") or {}).get("pose_samples_mean") == 1.0
                         and all(e.get("pose_samples", 1) == 1 for e in b.raw.get("per_image", [])) for _, b in pairs)
        if one_sample:
            return ("identical by construction: every held-out frame of the reference has one rolling-shutter "
                    "pose sample (motion sampling never switches on at this motion and resolution)")
    return "identical results: every paired PSNR is equal (this ablation changes nothing on these runs)"


def _paired(recs: Sequence[RunRecord], method: str, ref: str) -> list[tuple[RunRecord, RunRecord]]:
    """(method run, reference run) on the same scene and seed (the same recording)."""
    ref_by = {(r.scene, r.seed): r for r in recs if r.method == ref}
    return sorted(((r, ref_by[(r.scene, r.seed)]) for r in recs if r.method == method and (r.scene, r.seed) in ref_by),
                  key=lambda p: (p[0].scene, p[0].seed))


#: The unit of inference a gains table is computed over (`inference_unit`).
UNITS = ("auto", "seed", "scene")


def inference_unit(records: Sequence[RunRecord], unit: str = "auto") -> str:
    """"seed" or "scene". "auto": "scene" when every scene kind with runs has at least two scenes (the paper's
    design and run 2's: recordings are the unit), else "seed" (run 1's: one recording per kind, training seeds
    the unit)."""
    if unit not in UNITS:
        raise ValueError(f"unit: expected one of {', '.join(UNITS)}, got {unit!r}")
    if unit != "auto":
        return unit
    scenes: dict[str, set[str]] = {}
    for r in records:
        scenes.setdefault(r.scene_kind, set()).add(r.scene)
    return "scene" if scenes and all(len(v) >= 2 for v in scenes.values()) else "seed"


def _deltas_by(pairs: Sequence[tuple[RunRecord, RunRecord]], key) -> dict:
    """key(run) -> the paired PSNR differences of the runs with that key."""
    out: dict = {}
    for a, b in pairs:
        out.setdefault(key(a), []).append(a.metrics[pn.PSNR] - b.metrics[pn.PSNR])
    return out


def unit_means(pairs: Sequence[tuple[RunRecord, RunRecord]], unit: str) -> list[float]:
    """The paired differences averaged within each unit, in the units' order. "scene": a scene's seeds first
    (the paper's per-scene Δ); "seed": for each seed the mean over the scenes."""
    by = _deltas_by(pairs, (lambda r: r.scene) if unit == "scene" else (lambda r: r.seed))
    return [float(np.mean(v)) for _, v in sorted(by.items())]


def seed_spread(pairs: Sequence[tuple[RunRecord, RunRecord]]) -> float | None:
    """The training seeds' spread of a row's Δ on one recording: the pooled within-scene sample sd over the
    scenes that have two or more seeds (None where none has)."""
    by_scene = _deltas_by(pairs, lambda r: r.scene)
    groups = [np.asarray(v) for v in by_scene.values() if len(v) >= 2]
    if not groups:
        return None
    dof = sum(len(g) - 1 for g in groups)
    return float(math.sqrt(sum(((g - g.mean()) ** 2).sum() for g in groups) / dof))


def _mean_sd(values: Sequence[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    return float(np.mean(values)), (float(np.std(values, ddof=1)) if len(values) > 1 else None)


def gains_frame(records: Sequence[RunRecord], unit: str = "auto") -> pd.DataFrame:
    """Mean PSNR change of each method relative to its reference, ours versus the paper's.

    Only methods run on scenes of the table's kind are listed. Ours: the paired difference
    PSNR(method) - PSNR(reference) on the same scene and seed (the same recording), averaged within each
    unit of inference (`inference_unit`, `unit_means`), then the mean, sample std and 95 % t-interval over
    the units, and the one-sided t-test in the paper's direction; ``seed_sd`` is the training seeds' spread
    on one recording (`seed_spread`). A method that cannot differ from its reference on these runs
    (`identical_by_construction`) carries the reason instead of a Δ. Paper: the mean difference over the
    paper columns our scenes stand for (``paper_matched``), its smallest and largest per-scene difference
    there, and the mean over all of the paper table's columns (``paper_all``).
    """
    unit = inference_unit(records, unit)
    rows = []
    for group, (kind, paper) in GROUPS.items():
        recs = [r for r in records if r.scene_kind == kind]
        run_methods = {r.method for r in recs}
        methods = [m for m in paper.methods if m in run_methods] + sorted(run_methods - set(paper.methods))
        for m in methods:
            ref = GAIN_REFERENCE.get(m, "ours")
            if m != ref and m != "ours":
                rows.append(_gain_row(group, kind, paper, recs, m, ref, unit))
    return with_reproduction_columns(pd.DataFrame(rows))


def _gain_row(group: str, kind: str, paper: pn.PaperTable, recs: Sequence[RunRecord], m: str, ref: str,
              unit: str) -> dict:
    pairs = _paired(recs, m, ref)
    means = unit_means(pairs, unit)
    mean, sd = _mean_sd(means)
    low, high = ci95(means)
    identical = identical_by_construction(m, pairs)
    cols = _matched_columns(recs, kind, paper)
    per_scene = paper_deltas(paper, m, ref, cols)
    matched = _paper_delta(paper, m, ref, cols)
    return {
        "group": group, "method": m, "reference": ref, "unit": unit, "n_units": len(means),
        "n_scenes": len({a.scene for a, _ in pairs}), "n_seeds": len({a.seed for a, _ in pairs}),
        "delta_psnr_mean": None if identical else mean,
        "delta_psnr_std": None if identical else sd,
        "delta_psnr_ci95_low": None if identical else low,
        "delta_psnr_ci95_high": None if identical else high,
        "seed_sd": None if identical else seed_spread(pairs),
        "identical": identical,
        "paper_delta_psnr_matched": matched,
        "paper_delta_psnr_min": round(min(per_scene), 6) if per_scene else None,
        "paper_delta_psnr_max": round(max(per_scene), 6) if per_scene else None,
        "paper_delta_psnr_all": _paper_delta(paper, m, ref, paper.columns),
        "p_one_sided": None if identical else p_in_direction(means, matched),
    }


def p_in_direction(seed_means: Sequence[float], paper_delta: float | None) -> float | None:
    """One-sided paired t-test p over the units' mean differences (seeds or scenes), against 'no difference',
    in the paper's direction (None below two units or without a paper Δ)."""
    n = len(seed_means)
    if n < 2 or paper_delta is None or paper_delta == 0:
        return None
    from scipy.stats import t

    sd = float(np.std(seed_means, ddof=1))
    if sd == 0:
        return 0.0 if np.sign(np.mean(seed_means)) == np.sign(paper_delta) else 1.0
    tstat = float(np.mean(seed_means)) / (sd / math.sqrt(n)) * float(np.sign(paper_delta))
    return float(t.sf(tstat, n - 1))


def holm(p_values: Sequence[float | None]) -> list[float | None]:
    """Holm's step-down adjusted p-values (None stays None and does not count towards m)."""
    idx = [i for i, p in enumerate(p_values) if p is not None and not pd.isna(p)]
    order = sorted(idx, key=lambda i: p_values[i])
    out: list[float | None] = [None] * len(p_values)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(order) - rank) * float(p_values[i])))
        out[i] = running
    return out


#: The three counts a reproduction reports (docs: README "Results"), from `gains_frame`'s columns.
COUNT_COLUMNS = {"sign_and_ci": "the paper's sign with the 95 % interval excluding zero",
                 "survives_holm": "one-sided paired t-test in the paper's direction, Holm-adjusted p < 0.05 over all rows",
                 "magnitude_match": "the paper's Δ inside our interval, or our Δ within a factor 2 of it"}


def with_reproduction_columns(df: pd.DataFrame, alpha: float = 0.05) -> pd.DataFrame:
    """Per row: Holm-adjusted p, whether the sign (with its interval), the Holm test and the magnitude
    reproduce, our Δ over the paper's (matched scenes), whether our interval overlaps the paper's per-scene
    range and where our mean falls against it."""
    if df.empty:
        return df
    df = df.copy()
    df["p_holm"] = holm(list(df["p_one_sided"]))
    paper, low, high, ours = (df[c].astype(float) for c in ("paper_delta_psnr_matched", "delta_psnr_ci95_low",
                                                            "delta_psnr_ci95_high", "delta_psnr_mean"))
    df["ratio_to_paper"] = ours / paper
    df["paper_in_ci"] = (low <= paper) & (paper <= high)
    df["sign_and_ci"] = ((paper < 0) & (high < 0)) | ((paper > 0) & (low > 0))
    df["survives_holm"] = df["p_holm"].astype(float) < alpha
    df["magnitude_match"] = df["paper_in_ci"] | ((df["ratio_to_paper"] >= 0.5) & (df["ratio_to_paper"] <= 2.0))
    lo_p, hi_p = (df[c].astype(float) if c in df else paper for c in ("paper_delta_psnr_min", "paper_delta_psnr_max"))
    df["ci_overlaps_paper_range"] = (low <= hi_p) & (high >= lo_p)
    df["paper_range_position"] = [_position(x, a, b) for x, a, b in zip(ours, lo_p, hi_p)]
    return df


def _position(value: float, lo: float, hi: float) -> str | None:
    """Where our mean Δ falls against the paper's per-scene range: 'below', 'inside' or 'above'."""
    if any(pd.isna(v) for v in (value, lo, hi)):
        return None
    return "below" if value < lo else "above" if value > hi else "inside"


def reproduction_counts(gains: pd.DataFrame) -> dict[str, int]:
    """The three counts over the rows of ``gains`` (and the number of rows)."""
    return {"rows": int(len(gains)),
            **{c: int(gains[c].fillna(False).astype(bool).sum()) if c in gains else 0 for c in COUNT_COLUMNS}}


def _matched_columns(recs: Sequence[RunRecord], kind: str, paper: pn.PaperTable) -> list[str]:
    """The paper columns our scenes stand for (object and Quest 3: all of the table's)."""
    if kind in ("object", "quest3") and recs:
        return list(paper.columns)
    return sorted({(r.paper_scene or "").lower() for r in recs} & set(paper.columns))


def paper_deltas(paper: pn.PaperTable, method: str, ref: str, cols) -> list[float]:
    """The paper's per-scene PSNR differences over ``cols`` (scenes where it reports both rows)."""
    return [paper.value(method, c, pn.PSNR) - paper.value(ref, c, pn.PSNR) for c in cols
            if paper.value(method, c, pn.PSNR) is not None and paper.value(ref, c, pn.PSNR) is not None]


def _paper_delta(paper: pn.PaperTable, method: str, ref: str, cols) -> float | None:
    d = paper_deltas(paper, method, ref, cols)
    return round(float(np.mean(d)), 6) if d else None


def counts_line(gains: pd.DataFrame) -> str:
    """'of N rows: a with the paper's sign ..., b survive Holm, c match in magnitude'."""
    c = reproduction_counts(gains)
    return (f"of {c['rows']} rows: {c['sign_and_ci']} with the paper's sign and the 95 % interval excluding zero, "
            f"{c['survives_holm']} survive Holm (one-sided, alpha 0.05), {c['magnitude_match']} with the paper's "
            "delta inside the interval or within a factor 2")

