"""The null audit (issue 27): diagnose trained runs of recordings with nothing hidden and count what
the diagnosis names anyway. A suite's runs are such nulls when its recordings hide no effect (the
confirmatory suite's: stated readout = true readout, no time offset, no hidden photometric error).

    python -m egobench.diagnose.null_audit --results results/default --method ours --out DIR [--shard 1/2]

One JSON per run under OUT/rows/ (written atomically; a rerun skips the runs already there), then
OUT/null_audit.csv and OUT/null_audit.md over every row present. Shards split the runs between
processes (one torch thread each when two run side by side).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from egobench.diagnose import DiagnosisConfig, diagnose_residuals
from egobench.diagnose.sources import run_source
from egobench.effects.readout import READOUT
from egobench.io_utils import read_json, write_json


def null_runs(results: Path, method: str) -> list[tuple[str, Path, Path]]:
    """(scene, recording folder, run folder) of every trained run of ``method`` under ``results``."""
    out = []
    for train_json in sorted(results.glob(f"runs/*/{method}/seed*/train.json")):
        run = train_json.parent
        scene = run.parent.parent.name
        recording = results / "recordings" / scene
        if not recording.is_dir():
            raise FileNotFoundError(f"{recording}: the recording of run {run} is missing")
        out.append((scene, recording, run))
    if not out:
        raise FileNotFoundError(f"{results}/runs/*/{method}/seed*/train.json: no trained runs of method {method!r}")
    return out


def _readout_columns(ranking: list) -> dict:
    """The readout cause's statistics (first-order t, its placebos) from a diagnosis ranking."""
    r = {x.name: x for x in ranking}.get(READOUT.name)
    if r is None or not r.testable:
        return {}
    vel, row = r.params.get("calibration", {}), r.params.get("calibration_row_time", {})
    return {"readout_p_adjusted": r.p_adjusted, "readout_t": vel.get("first_order_t"),
            "readout_velocity_placebo_p": vel.get("p_value_placebo"),
            "readout_row_time_placebo_p": row.get("p_value_placebo"),
            "readout_relative_error": r.params.get("readout_relative_error")}


def audit_run(scene: str, recording: Path, run: Path, method: str, pose_samples: int | None = None) -> dict:
    """One null run's diagnosis, reduced to a row: verdict, named causes, the readout's statistics."""
    src = run_source(recording, run, progress=False, pose_samples=pose_samples)
    d = diagnose_residuals(src.measured, src.predicted, src.context, replace(DiagnosisConfig(), trained_run=True))
    metrics = read_json(run / "eval.json").get("metrics", {}) if (run / "eval.json").is_file() else {}
    return {"scene": scene, "method": method, "seed": run.name, "pose_samples": pose_samples or "run's own",
            "held_out_psnr_db": metrics.get("psnr"),
            "verdict": d.verdict, "named": ";".join(n.name for n in d.named), "false_alarm": bool(d.named),
            **_readout_columns(d.ranking)}


def _cell(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else ("-" if v is None else str(v))


def summarise(rows: list[dict], out: Path) -> pd.DataFrame:
    """null_audit.csv and null_audit.md: every row, and the false alarms by scene and by cause."""
    df = pd.DataFrame(rows).sort_values(["scene", "seed"]).reset_index(drop=True)
    df.to_csv(out / "null_audit.csv", index=False)
    named = df["named"].fillna("").str.split(";").explode()
    by_cause = named[named != ""].value_counts().to_dict()
    lines = [f"# Null audit: {len(df)} trained runs with nothing hidden", "",
             f"False alarms: {int(df['false_alarm'].sum())} of {len(df)} runs; named causes: {by_cause or 'none'}.", "",
             "| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    (out / "null_audit.md").write_text("\n".join(lines) + "\n")
    return df


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", required=True, help="a suite's results folder (runs/, recordings/)")
    ap.add_argument("--method", default="ours")
    ap.add_argument("--out", required=True)
    ap.add_argument("--shard", default="1/1", help="i/n: this process diagnoses every n-th run from the i-th")
    ap.add_argument("--seed", action="append", help="only the runs of these seed folders (repeatable, e.g. seed3141)")
    ap.add_argument("--scene", action="append", help="only the runs of these scenes (repeatable, e.g. outdoor_0)")
    ap.add_argument("--pose-samples", type=int, default=None,
                    help="render every moving frame with N rolling-shutter pose samples (see run_source)")
    args = ap.parse_args(argv)
    i, n = (int(x) for x in args.shard.split("/"))
    if not 1 <= i <= n:
        raise ValueError(f"--shard: expected i/n with 1 <= i <= n, got {args.shard!r}")
    out = Path(args.out)
    (out / "rows").mkdir(parents=True, exist_ok=True)
    runs = [r for r in null_runs(Path(args.results), args.method)
            if (not args.seed or r[2].name in args.seed) and (not args.scene or r[0] in args.scene)][i - 1::n]
    for scene, recording, run in tqdm(runs, desc=f"null audit {args.shard}", unit="run"):
        row_file = out / "rows" / f"{scene}_{args.method}_{run.name}.json"
        if not row_file.is_file():
            write_json(row_file, audit_run(scene, recording, run, args.method, args.pose_samples))
    summarise([json.loads(p.read_text()) for p in sorted((out / "rows").glob("*.json"))], out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
