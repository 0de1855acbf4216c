"""`egobench compare RESULTS [--reference REF]`: a regenerated suite against the committed one, row by row.

Training is chaotic: a different CPU (its BLAS kernels, its compiler target) or another package version rounds
differently, and 1,000 iterations grow that into another model of the same quality. A regenerated table
therefore differs from the committed one; the question is whether by as much as rounding does. The tolerance
is a multiple (`TRAVEL_FACTOR`) of the reference's own seed spread:

- a run's metric: ``TRAVEL_FACTOR`` x the pooled seed sd of that metric over the reference's (scene, method)
  cells (the root of the mean per-cell variance);
- a row's Δ PSNR (gains.csv): ``TRAVEL_FACTOR`` x the pooled standard error a seed redraw gives the rows' Δ
  (`row_standard_error`: seeds as the unit, the root of the mean of delta_psnr_std^2 / n_seeds; scenes as the
  unit, the pooled within-scene seed sd over sqrt(scenes)).

`TRAVEL_FACTOR` = 6 is the largest move measured between two CPU vendors in seed-spread units (an Intel Xeon
regeneration against the committed AMD Zen 5 run: 0.98 dB on one run, 0.41 dB on one row; pooled seed sd
0.166 dB, pooled row SE 0.078 dB: 5.9 and 5.3), rounded up (docs/reproducibility.md). A difference beyond it
is more than rounding: another code version, another suite configuration, or a defect. Verdicts (sign with CI,
Holm, magnitude) that change are listed too: rows near a threshold can change within tolerance.
"""

from __future__ import annotations

import argparse
import io
import math
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd

#: tolerance in units of the reference's seed spread (module docstring)
TRAVEL_FACTOR = 6.0
#: per-run metrics compared (those present in both tables)
RUN_METRICS = ("psnr", "ssim", "lpips", "depth_mse_authors", "normal_cos_authors")
RUN_KEY = ["scene", "method", "seed"]
ROW_KEY = ["group", "method"]
VERDICTS = ("sign_and_ci", "survives_holm", "magnitude_match")


def _tables_dir(path: Path) -> Path:
    return path / "tables" if (path / "tables").is_dir() else path


def _read_tables_from_dir(path: Path) -> dict[str, pd.DataFrame]:
    tables = _tables_dir(path)
    out = {}
    for name in ("results", "gains"):
        f = tables / f"{name}.csv"
        if not f.is_file():
            raise FileNotFoundError(f"{f}: not found (expected a suite's tables: results.csv and gains.csv)")
        out[name] = pd.read_csv(f)
    return out


def _read_tables_from_git(results: Path, rev: str) -> dict[str, pd.DataFrame]:
    """The tables at ``results``' place in the git repository holding it, as committed at ``rev``."""
    tables = _tables_dir(results).resolve()
    top = subprocess.run(["git", "-C", str(tables), "rev-parse", "--show-toplevel"], capture_output=True, text=True)
    if top.returncode != 0:
        raise ValueError(f"--reference git:{rev}: {tables} is not inside a git checkout; give --reference a folder")
    rel = tables.relative_to(Path(top.stdout.strip()).resolve())
    out = {}
    for name in ("results", "gains"):
        shown = subprocess.run(["git", "-C", top.stdout.strip(), "show", f"{rev}:{rel / (name + '.csv')}"],
                               capture_output=True, text=True)
        if shown.returncode != 0:
            raise ValueError(f"--reference git:{rev}: {rel / (name + '.csv')} is not committed at {rev} "
                             f"({shown.stderr.strip()}); give --reference a folder")
        out[name] = pd.read_csv(io.StringIO(shown.stdout))
    return out


def read_tables(spec: str, results: Path) -> dict[str, pd.DataFrame]:
    """A suite's results.csv and gains.csv: from a folder, or ``git:REV`` (the committed copy of ``results``)."""
    return _read_tables_from_git(results, spec[4:]) if spec.startswith("git:") else _read_tables_from_dir(Path(spec))


def _check_columns(df: pd.DataFrame, needed: list[str], what: str) -> None:
    missing = [c for c in needed if c not in df.columns]
    if missing:
        raise ValueError(f"{what}: missing column(s) {missing}")


def pooled_seed_sd(results: pd.DataFrame, metric: str) -> float:
    """The root of the mean within-(scene, method) variance of ``metric`` over seeds (cells with >= 2 seeds)."""
    var = results.groupby(["scene", "method"])[metric].var(ddof=1).dropna()
    return float(math.sqrt(var.mean())) if len(var) else float("nan")


def compare_runs(ref: pd.DataFrame, new: pd.DataFrame, factor: float = TRAVEL_FACTOR) -> pd.DataFrame:
    """Per matched run and metric: reference, regenerated, |move|, tolerance, within."""
    _check_columns(ref, RUN_KEY, "reference results.csv")
    _check_columns(new, RUN_KEY, "results.csv")
    both = ref.merge(new, on=RUN_KEY, suffixes=("_ref", "_new"))
    rows = []
    for m in (m for m in RUN_METRICS if m in ref.columns and m in new.columns):
        tol = factor * pooled_seed_sd(ref, m)
        moved = (both[f"{m}_new"] - both[f"{m}_ref"]).abs()
        keep = moved.notna()
        rows.append(pd.DataFrame({**{k: both.loc[keep, k] for k in RUN_KEY}, "metric": m,
                                  "reference": both.loc[keep, f"{m}_ref"], "regenerated": both.loc[keep, f"{m}_new"],
                                  "move": moved[keep], "tolerance": tol, "within": moved[keep] <= tol}))
    return pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()


def compare_rows(ref: pd.DataFrame, new: pd.DataFrame, factor: float = TRAVEL_FACTOR) -> pd.DataFrame:
    """Per paper row of gains.csv: Δ PSNR before and after, |move|, tolerance, within, and verdict changes."""
    need = ROW_KEY + ["delta_psnr_mean", "delta_psnr_std", "n_seeds"]
    _check_columns(ref, need, "reference gains.csv")
    _check_columns(new, ROW_KEY + ["delta_psnr_mean"], "gains.csv")
    tol = factor * row_standard_error(ref)
    both = ref.merge(new, on=ROW_KEY, suffixes=("_ref", "_new"))
    out = both[ROW_KEY].copy()
    out["reference"], out["regenerated"] = both["delta_psnr_mean_ref"], both["delta_psnr_mean_new"]
    out["move"] = (out["regenerated"] - out["reference"]).abs()
    out["tolerance"], out["within"] = tol, out["move"] <= tol
    flips = [both.apply(lambda r, v=v: f"{v} {r[v + '_ref']} -> {r[v + '_new']}"
                        if r[v + "_ref"] != r[v + "_new"] else "", axis=1)
             for v in VERDICTS if f"{v}_ref" in both and f"{v}_new" in both]
    out["verdicts_changed"] = ["; ".join(x for x in parts if x) for parts in zip(*flips)] if flips else ""
    return out


def row_standard_error(gains: pd.DataFrame) -> float:
    """The root mean square over the rows of the standard error a seed redraw gives a row's Δ. Seeds as the unit
    (run 1): the row's sd over its seeds / sqrt(seeds). Scenes as the unit (``unit`` "scene", run 2): another
    machine redraws the training noise on every scene, not the scenes, so the pooled within-scene seed sd
    (``seed_sd``) / sqrt(scenes); the sd over the scenes would allow the scene-to-scene spread."""
    if "unit" in gains and (gains["unit"] == "scene").all() and gains.get("seed_sd") is not None \
            and gains["seed_sd"].notna().any():
        se2 = float((gains["seed_sd"].dropna() ** 2).mean()) / gains["n_units"]
    else:
        units = gains["n_units"] if "n_units" in gains else gains["n_seeds"]
        se2 = (gains["delta_psnr_std"] ** 2 / units).dropna()
    return float(np.sqrt(se2.mean()))


def unmatched(ref: pd.DataFrame, new: pd.DataFrame, key: list[str]) -> tuple[int, int]:
    """(rows only in the reference, rows only in the regenerated table)."""
    a, b = set(map(tuple, ref[key].values.tolist())), set(map(tuple, new[key].values.tolist()))
    return len(a - b), len(b - a)


def report_lines(runs: pd.DataFrame, rows: pd.DataFrame, missing: dict) -> list[str]:
    """The printed comparison: a line per row, a summary per run metric, what exceeds, what is missing."""
    lines = [f"{'row':<42} {'ref Δ':>7} {'new Δ':>7} {'move':>6} {'tol':>5}  verdict"]
    for r in rows.itertuples():
        mark = "ok" if r.within else "BEYOND TOLERANCE"
        flips = f"  ({r.verdicts_changed})" if r.verdicts_changed else ""
        lines.append(f"{r.group + ' ' + r.method:<42} {r.reference:+7.2f} {r.regenerated:+7.2f} {r.move:6.2f} "
                     f"{r.tolerance:5.2f}  {mark}{flips}")
    for m, g in runs.groupby("metric", sort=False):
        lines.append(f"runs, {m}: {len(g)} matched, |move| median {g.move.median():.4g}, max {g.move.max():.4g}, "
                     f"tolerance {g.tolerance.iloc[0]:.4g}, beyond {int((~g.within).sum())}")
        for r in g[~g.within].itertuples():
            lines.append(f"  BEYOND TOLERANCE: {r.scene} {r.method} seed {r.seed}: {r.reference:.4g} -> {r.regenerated:.4g}")
    for what, (only_ref, only_new) in missing.items():
        if only_ref or only_new:
            lines.append(f"{what}: {only_ref} only in the reference, {only_new} only in the regenerated tables")
    return lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", help="a regenerated suite's folder (with tables/) or its tables folder")
    parser.add_argument("--reference", default="git:HEAD",
                        help="the tables to compare with: a folder, or git:REV for the copy of RESULTS committed at "
                             "REV (default git:HEAD)")
    parser.add_argument("--out", help="also write the per-row and per-run comparison as CSV (FILE_rows.csv, FILE_runs.csv)")


def run(args: argparse.Namespace) -> int:
    """Prints the comparison; exit 0 when every row and run is within tolerance, 1 otherwise."""
    results = Path(args.results)
    new, ref = _read_tables_from_dir(results), read_tables(args.reference, results)
    runs, rows = compare_runs(ref["results"], new["results"]), compare_rows(ref["gains"], new["gains"])
    missing = {"runs": unmatched(ref["results"], new["results"], RUN_KEY),
               "rows": unmatched(ref["gains"], new["gains"], ROW_KEY)}
    print("\n".join(report_lines(runs, rows, missing)))
    if args.out:
        rows.to_csv(f"{args.out}_rows.csv", index=False)
        runs.to_csv(f"{args.out}_runs.csv", index=False)
    beyond = int((~rows.within).sum()) + (int((~runs.within).sum()) if len(runs) else 0)
    print(f"egobench compare: {beyond} beyond tolerance ({TRAVEL_FACTOR:g} x the reference's seed spread)")
    return 0 if beyond == 0 else 1
