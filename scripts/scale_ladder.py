"""The scale ladder: how the laptop suite's findings move as the regime approaches the paper's.

    python scripts/scale_ladder.py --out OUT --work WORK [--top 512] [--rungs 128,256,512]
        [--frames 48] [--device cuda] [--budget-s 480] [--dry-run]

One outdoor and one indoor recording are simulated at TOP px (seed 0, Aria's 16.26 ms readout: `READOUT_S`; into
WORK; once a machine), and 'ours', w/o motion sampling and w/o VIBA are trained on each at every rung
(`--set max_side=RUNG`, seed 0) and evaluated on the held-out frames. The budget of a rung is fixed by this rule,
written before any run: the cpu preset's schedule with `ITERATIONS_AT_128` x (rung / 128) iterations and
`GAUSSIANS_AT_128` x (rung / 128)^2 Gaussians at most (a Gaussian's travel and the Gaussians per pixel as at 128
px). Jobs run rung by rung, smallest first.

OUT keeps only the small records: OUT/ladder.csv (one row per finished job: held-out PSNR, resolved wavelength,
the budget, the recordings' size and frames, the training time and Gaussians as `egobench train` recorded them,
the device and backend, and the held-out PSNR frame by frame), OUT/ladder.md (per kind and rung: 'ours', each
ablation's delta with its 95 % t-interval over the held-out frames, paired by frame, and the resolved wavelength,
beside the paper's mean delta over its Table 1 scenes of that kind; how many deltas survive Holm in the paper's
direction; each delta's line against log2(rung), frame by frame, read at the paper's 2400 px) and OUT/logs/
(each command's output; a failed job's is kept there and the ladder goes on). A job in OUT/ladder.csv is not run again: commit
OUT after a call and the next call (a fresh machine, WORK lost) continues the ladder. A job starts only where
its estimated time (`estimate_s`) fits in what is left of the budget.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from egobench.report import paper_numbers as pn
from egobench.report.gains import ci95, holm, p_in_direction, paper_deltas

KINDS = ("outdoor", "indoor")
METHODS = ("ours", "no_motion_sampling", "no_viba")
ABLATIONS = METHODS[1:]
#: the recordings' rolling-shutter readout, s: Aria's full sensor (egobench.sim.devices), kept at every size so that
#: the smear during readout is the paper's in angle and grows in pixels with the rung (the simulator's default,
#: one line time, shortens the readout with the rows: 3.47 ms at 512 px, where no frame asked for a second pose
#: sample; results/ladder/README.md, 2026-12-07)
READOUT_S = 16.26e-3
ITERATIONS_AT_128 = 1000
GAUSSIANS_AT_128 = 8000
#: the paper's image size, px: where `trend_lines` reads each delta's line
PAPER_SIDE = 2400
#: the smallest time a job is given before any has been timed, s
MIN_JOB_S = 60
FIELDS = ("kind", "rung", "method", "top", "frames", "iterations", "max_gaussians", "held_out_psnr",
          "held_out_psnr_by_frame", "resolved_wavelength_px", "train_s", "gaussians", "device", "backend")
PAPER_TABLE = {"outdoor": pn.TABLE1_OUTDOOR, "indoor": pn.TABLE1_INDOOR}


def budget(rung: int) -> tuple[int, int]:
    """(iterations, Gaussian cap) of a rung: the rule of the module docstring."""
    scale = rung / 128
    return max(1, round(ITERATIONS_AT_128 * scale)), max(1, round(GAUSSIANS_AT_128 * scale * scale))


def paper_delta(kind: str, ablation: str) -> float:
    """The paper's mean PSNR delta ('ours' - ablation) over its Table 1 scenes of ``kind``."""
    d = paper_deltas(PAPER_TABLE[kind], "ours", ablation, PAPER_TABLE[kind].columns)
    return sum(d) / len(d)


def read_rows(path: Path, top: int | None = None, frames: int | None = None) -> list[dict]:
    """The recorded jobs of ``path``; refused where its columns or its recordings' size and frames differ."""
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if rows and set(rows[0]) != set(FIELDS):
        raise SystemExit(f"{path}: columns {sorted(rows[0])}, expected {sorted(FIELDS)}; use another --out")
    other = {(r["top"], r["frames"]) for r in rows} - {(str(top), str(frames))}
    if top is not None and other:
        raise SystemExit(f"{path}: jobs on recordings of {sorted(other)} (top px, frames), not ({top}, {frames}); "
                         "use another --out")
    return rows


def write_rows(path: Path, rows: list[dict]) -> None:
    partial = path.with_name(path.name + ".partial")
    with open(partial, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    partial.replace(path)


def _egobench(*args: str, log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        subprocess.run([sys.executable, "-m", "egobench.cli", *args], stdout=fh, stderr=subprocess.STDOUT, check=True)


def recording(work: Path, logs: Path, kind: str, top: int, frames: int, device: str = "cpu") -> Path:
    """The kind's recording at TOP px (simulated once into WORK, its rays cast on ``device`` where that is a GPU;
    the simulator resumes an interrupted one)."""
    rec = work / f"{kind}_{top}"
    if not (rec / "recording.json").is_file():
        cast_on = ["--set", f"compute_device={device}"] if device.startswith("cuda") else []
        _egobench("simulate", "--kind", kind, "--seed", "0", "--out", str(rec), "--frames", str(frames),
                  "--set", f"rectified_size={top}", "--set", f"readout_s={READOUT_S}", *cast_on, "--no-progress",
                  log=logs / f"simulate_{kind}.log")
    return rec


def run_job(work: Path, logs: Path, rec: Path, job: tuple[str, int, str], top: int, frames: int, device: str) -> dict:
    """Train and evaluate one job (kind, rung, method) -> its ladder row."""
    kind, rung, method = job
    iterations, gaussians = budget(rung)
    run = work / "runs" / f"{kind}_{rung}_{method}"
    log = logs / f"{kind}_{rung}_{method}.log"
    _egobench("train", "--recording", str(rec), "--method", method, "--seed", "0", "--out", str(run), "--preset", "cpu",
              "--iterations", str(iterations), "--set", f"max_side={rung}", "--set", f"max_gaussians={gaussians}",
              "--set", f"device={device}", "--resume", "auto", "--no-progress", log=log)
    _egobench("evaluate", "--recording", str(rec), "--run", str(run), "--no-renders", log=log)
    record = json.loads((run / "eval.json").read_text())
    trained = json.loads((run / "train.json").read_text())["train"]
    return {"kind": kind, "rung": rung, "method": method, "top": top, "frames": frames, "iterations": iterations,
            "max_gaussians": gaussians, "held_out_psnr": record["metrics"][pn.PSNR],
            "held_out_psnr_by_frame": " ".join(f"{e['frame']}:{e[pn.PSNR]!r}" for e in record["per_image"]),
            "resolved_wavelength_px": (record.get("fidelity") or {}).get("resolved_wavelength_px"),
            "train_s": round(float(trained["time_s"]), 1), "gaussians": trained.get("num_gaussians"),
            "device": trained.get("device", device), "backend": trained.get("backend", "")}


def estimate_s(rows: list[dict], rung: int) -> float:
    """A job's expected time, s: the slowest recorded job at the largest rung timed so far, times (rung / its
    rung)^3 (iterations grow as the rung, pixels as its square), plus `MIN_JOB_S` for start, recording and
    evaluation; `MIN_JOB_S` before any job has been timed."""
    timed = [r for r in rows if r.get("train_s") not in (None, "")]
    if not timed:
        return MIN_JOB_S
    base = max(int(r["rung"]) for r in timed)
    slowest = max(float(r["train_s"]) for r in timed if int(r["rung"]) == base)
    return slowest * (rung / base) ** 3 + MIN_JOB_S


def jobs(rows: list[dict]) -> dict[tuple[str, int, str], dict]:
    """The rows by job: (kind, rung, method) -> row."""
    return {(r["kind"], int(r["rung"]), r["method"]): r for r in rows}


def with_interval(values) -> str:
    """The values' mean, dB, and its 95 % t-interval where there are two or more (`report.gains.ci95`)."""
    lo, hi = ci95(values)
    return f"{float(np.mean(values)):+.2f}" + ("" if lo is None else f" [{lo:+.2f}, {hi:+.2f}]")


def by_frame(row: dict) -> dict[int, float]:
    """A row's held-out PSNR per frame index (its `held_out_psnr_by_frame`: "frame:psnr" pairs)."""
    pairs = [item.split(":") for item in row["held_out_psnr_by_frame"].split()]
    if not pairs:
        raise SystemExit(f"ladder.csv: {row['kind']} {row['rung']} px {row['method']}: no held-out frame's PSNR "
                         "(held_out_psnr_by_frame is empty)")
    return {int(f): float(v) for f, v in pairs}


def frame_diffs(ours: dict, other: dict) -> list[float]:
    """'ours' minus the ablation, held-out PSNR dB, frame by frame (refused where their frames differ)."""
    a, b = by_frame(ours), by_frame(other)
    if set(a) != set(b):
        raise SystemExit(f"ladder.csv: {ours['kind']} {ours['rung']} px: 'ours' and {other['method']} were evaluated "
                         f"on different held-out frames ({sorted(a)} against {sorted(b)})")
    return [a[f] - b[f] for f in sorted(a)]


def delta_cell(ours: dict, other: dict) -> str:
    """'ours' minus the ablation, dB, with its 95 % t-interval over the held-out frames (paired by frame)."""
    diffs = frame_diffs(ours, other)
    if not any(diffs):
        return "identical"  # every held-out frame's PSNR equal: the ablation changed nothing (e.g. one pose sample)
    return with_interval(diffs)


def holm_line(rows: list[dict]) -> str:
    """How many deltas are in the paper's direction after Holm over those tested (one-sided paired t over the
    held-out frames); an identical delta is not tested, as `report.gains` leaves identical rows out."""
    by = jobs(rows)
    diffs = [(frame_diffs(ours, by[(k, g, a)]), paper_delta(k, a))
             for (k, g, m), ours in by.items() if m == "ours" for a in ABLATIONS if (k, g, a) in by]
    p = [p_in_direction(d, paper) if any(d) else None for d, paper in diffs]
    adjusted = [q for q in holm(p) if q is not None]
    return (f"Holm over the {len(adjusted)} deltas tested ({len(p) - len(adjusted)} identical, not tested; one-sided "
            f"paired t over the held-out frames, in the paper's direction): {sum(q < 0.05 for q in adjusted)} below 0.05.")


def trend_lines(rows: list[dict]) -> list[str]:
    """Per kind and ablation over two or more rungs: the delta's least-squares line against log2(rung), frame by
    frame; its slope per doubling and its value at `PAPER_SIDE`, each the mean over the frames with its 95 %
    t-interval (an extrapolation from this ladder's rungs, not a measurement)."""
    by = jobs(rows)
    out = []
    for kind in KINDS:
        for a in ABLATIONS:
            rungs = sorted(g for k, g, m in by if k == kind and m == "ours" and (kind, g, a) in by)
            if len(rungs) < 2:
                continue
            x = np.log2(np.asarray(rungs, dtype=float) / rungs[0])
            frames = {tuple(sorted(by_frame(by[(kind, g, "ours")]))) for g in rungs}
            if len(frames) > 1:
                raise SystemExit(f"ladder.csv: {kind}: the rungs were evaluated on different held-out frames ({sorted(frames)})")
            d = np.array([frame_diffs(by[(kind, g, "ours")], by[(kind, g, a)]) for g in rungs])  # [rungs, frames]
            if not d.any():
                out.append(f"- {kind}, ours - {a} over {', '.join(map(str, rungs))} px: identical at every rung")
                continue
            slope, intercept = np.polyfit(x, d, 1)  # one line per frame
            at_paper = intercept + slope * math.log2(PAPER_SIDE / rungs[0])
            cells = [f"per doubling {with_interval(slope)}", f"at {PAPER_SIDE} px {with_interval(at_paper)}"]
            out.append(f"- {kind}, ours - {a} over {', '.join(map(str, rungs))} px: {'; '.join(cells)} "
                       f"(paper {paper_delta(kind, a):+.2f})")
    return out


def table(rows: list[dict]) -> str:
    """OUT/ladder.md: per kind and rung, 'ours', each ablation's delta and the resolved wavelength, beside the
    paper's mean delta."""
    by = jobs(rows)
    head = ["kind", "rung px", "iterations", "'ours' Gaussians (cap)", "'ours' PSNR", "resolved wavelength px",
            *[f"ours - {a} (paper)" for a in ABLATIONS]]
    out = ["delta: 'ours' minus the ablation, held-out PSNR dB, one seed, with its 95 % t-interval over the held-out "
           "frames (paired by frame: the views' spread, not the seeds'), 'identical' where every frame's PSNR is equal; "
           "in parentheses the paper's mean over its Table 1 scenes of the kind. Gaussians: those 'ours' ended with, "
           "and in parentheses the rung's cap.", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for kind, rung in sorted({(k, g) for k, g, _ in by}, key=lambda x: (KINDS.index(x[0]), x[1])):
        ours = by.get((kind, rung, "ours"))
        if ours is None:
            continue
        cells = [kind, rung, ours["iterations"], f"{ours['gaussians']} ({ours['max_gaussians']})",
                 f"{float(ours['held_out_psnr']):.2f}",
                 f"{float(ours['resolved_wavelength_px']):.1f}" if ours["resolved_wavelength_px"] not in (None, "") else "-"]
        for a in ABLATIONS:
            other = by.get((kind, rung, a))
            delta = "-" if other is None else delta_cell(ours, other)
            cells.append(f"{delta} ({paper_delta(kind, a):+.2f})")
        out.append("| " + " | ".join(str(c) for c in cells) + " |")
    trend = trend_lines(rows)
    if trend:
        trend = ["", "The delta against log2(rung), fitted frame by frame (an extrapolation to the paper's size, "
                     "not a measurement):", *trend]
    return "\n".join([*out, "", holm_line(rows), *trend]) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="the small records (commit it)")
    ap.add_argument("--work", required=True, type=Path, help="recordings and runs (not kept)")
    ap.add_argument("--top", type=int, default=512, help="the recordings' size, px")
    ap.add_argument("--rungs", default="128,256,512", help="training sizes, px, comma-separated, at most --top")
    ap.add_argument("--frames", type=int, default=48, help="frames of each recording")
    ap.add_argument("--device", default="cuda", help="torch device of training and evaluation")
    ap.add_argument("--budget-s", type=float, default=None, help="start no job that would end after this many s")
    ap.add_argument("--dry-run", action="store_true", help="list the jobs left and their budgets, run nothing")
    args = ap.parse_args(argv)
    rungs = sorted({int(r) for r in args.rungs.split(",") if r.strip()})
    if not rungs or rungs[0] < 8 or rungs[-1] > args.top:
        ap.error(f"--rungs: expected sizes from 8 to --top ({args.top}) px, got {args.rungs!r}")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = read_rows(args.out / "ladder.csv", args.top, args.frames)
    done = set(jobs(rows))
    todo = [(k, g, m) for g in rungs for k in KINDS for m in METHODS if (k, g, m) not in done]
    if args.dry_run:
        for k, g, m in todo:
            print(k, g, m, "iterations %d, at most %d Gaussians" % budget(g))
        return 0
    (args.out / "ladder.md").write_text(table(rows))
    began, logs, failed = time.perf_counter(), args.out / "logs", []
    for n, job in enumerate(todo):
        left = None if args.budget_s is None else args.budget_s - (time.perf_counter() - began)
        if left is not None and estimate_s(rows, job[1]) > left:
            print(f"left for the next call: {len(todo) - n} jobs ({left:.0f} s left, this one needs about "
                  f"{estimate_s(rows, job[1]):.0f} s)", flush=True)
            break
        try:
            rec = recording(args.work, logs, job[0], args.top, args.frames, args.device)
            rows.append(run_job(args.work, logs, rec, job, args.top, args.frames, args.device))
        except subprocess.CalledProcessError as err:
            failed.append(job)
            print(f"failed: {job}: exit {err.returncode}; see {logs}", flush=True)
            continue
        write_rows(args.out / "ladder.csv", rows)
        (args.out / "ladder.md").write_text(table(rows))
        print(json.dumps(rows[-1]), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
