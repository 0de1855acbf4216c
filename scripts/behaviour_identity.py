"""Old code against new, on the outputs a refactor must not change: a simulated recording, a training, a trained-run
diagnosis, the synthetic hidden-case sweep and the CI suite's workflow (tables, runs, diagnosis).

    python scripts/behaviour_identity.py --old REV --new REV --out DIR

Each revision is checked out as a git worktree under DIR and run with this interpreter (PYTHONPATH = the
worktree); the outputs are compared file by file: bytes, or for JSON, CSV and checkpoints every field except
timings and the commit. Prints one line per differing file and exits 1 when any differs beyond those fields.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import torch

#: fields that record when and how fast, which commit, or the cache-sharing probe: they differ between any two runs
VOLATILE = ("time_s", "runtime", "iters_per_s", "raster_time_share", "render_forward_s", "render_backward_s",
            "git_commit", "timing", "simulation_time_s", "seconds", "core_sharing")
#: files that only record how a run went (logs, benchmarks, locks)
SKIPPED = (".log", ".tsv", ".lock")


def _run(code: Path, out: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(code)}
    py = [sys.executable, "-m", "egobench.cli"]
    steps = [
        ["simulate", "--kind", "indoor", "--out", "rec", "--seed", "11", "--frames", "24", "--set", "rectified_size=48",
         "--set", "vignette_strength=0.4", "--no-progress"],
        ["train", "--recording", "rec", "--method", "ours", "--preset", "cpu", "--iterations", "200", "--out", "run",
         "--no-progress"],
        ["diagnose", "rec", "--run", "run", "--method", "ours", "--out", "diag", "--no-progress"],
        ["diagnose", "--sweep", "--sweep-seeds", "1", "--sweep-null", "3", "--out", "sweep", "--no-progress"],
    ]
    out.mkdir(parents=True, exist_ok=True)
    for step in steps:
        subprocess.run(py + step, cwd=out, env=env, check=True, capture_output=True)
    suite = out / "suite"
    suite.mkdir(exist_ok=True)
    for name in ("Snakefile", "workflows", "config"):
        subprocess.run(["cp", "-r", str(code / name), str(suite)], check=True)
    command = f"egobench_command=env PYTHONPATH={code} {sys.executable} -m egobench.cli"
    subprocess.run(["snakemake", "--cores", "2", "--configfile", "config/ci.yaml", "--config", command], cwd=suite,
                   env=env, check=True, capture_output=True)


def _volatile(key: str) -> bool:
    return any(v in key for v in VOLATILE)


def _flat(x, prefix=""):
    if isinstance(x, dict):
        for k, v in x.items():
            yield from _flat(v, f"{prefix}/{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _flat(v, f"{prefix}[{i}]")
    else:
        yield prefix, x


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def differences(old: Path, new: Path) -> list[str]:
    """Files of ``old`` that ``new`` lacks or that differ beyond the volatile fields."""
    found = []
    for a in sorted(p for p in old.rglob("*") if p.is_file() and ".snakemake" not in p.parts):
        rel = a.relative_to(old)
        b = new / rel
        if a.suffix in SKIPPED or "logs" in rel.parts or (rel.parts[0] == "suite" and rel.parts[1] != "results"):
            continue  # run logs, and the workflow's own files copied beside its results
        if not b.is_file():
            found.append(f"{rel}: missing in new")
        elif a.suffix == ".json":
            x, y = dict(_flat(json.loads(a.read_text()))), dict(_flat(json.loads(b.read_text())))
            keys = [k for k in set(x) | set(y) if not _volatile(k) and not _same(x.get(k), y.get(k))]
            found += [f"{rel}: {k}" for k in sorted(keys)[:5]]
        elif a.suffix == ".csv":
            x, y = pd.read_csv(a), pd.read_csv(b)
            cols = [c for c in set(x.columns) | set(y.columns) if not _volatile(c)
                    and not (c in x and c in y and x[c].equals(y[c]))]
            found += [f"{rel}: column {c}" for c in sorted(cols)]
        elif a.suffix == ".pt":
            x, y = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
            if not all(torch.equal(x["params"][k], y["params"][k]) for k in x["params"]):
                found.append(f"{rel}: params")
        elif a.suffix == ".md" or a.read_bytes() != b.read_bytes():
            if a.suffix != ".md" or [ln for ln in a.read_text().splitlines() if "runtime" not in ln] != \
                    [ln for ln in b.read_text().splitlines() if "runtime" not in ln]:
                found.append(f"{rel}: bytes")
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", required=True, help="the revision before the change")
    parser.add_argument("--new", required=True, help="the revision after it")
    parser.add_argument("--out", required=True, type=Path, help="working folder (worktrees and outputs)")
    args = parser.parse_args(argv)
    repo = Path(__file__).resolve().parents[1]
    for tag, rev in (("old", args.old), ("new", args.new)):
        code = args.out / f"code_{tag}"
        if not code.exists():
            subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", str(code), rev], check=True,
                           capture_output=True)
        _run(code, args.out / tag)
    found = differences(args.out / "old", args.out / "new")
    for line in found:
        print(line)
    print(f"{len(found)} differences beyond timings and commits")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
