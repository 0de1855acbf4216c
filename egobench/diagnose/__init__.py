"""Residual diagnosis (issue 6): what a model gets wrong about measured data, named by its physical
signature, estimated, modelled, and the held-out gain measured.

API:
    diagnose_residuals(measured, predicted, context, config) -> Diagnosis   (egobench.diagnose.core)
    ground_truth_source(recording) / run_source(recording, run_dir) -> Sources  (egobench.diagnose.sources)
    write_report(out_dir, diagnosis, measured, predicted)                  (egobench.diagnose.report)
    run_sweep(out_dir) (egobench.diagnose.sweep), diagnose_adt(adt_dir, out_dir) (egobench.diagnose.adt)

CLI: ``egobench diagnose RECORDING --method M --out DIR [--run RUN_DIR | --train] [--source ...]``,
``egobench diagnose --sweep --out DIR``, ``egobench diagnose --adt ADT_DIR --out DIR``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from egobench.diagnose.core import NO_DISCREPANCY, Diagnosis, DiagnosisConfig, NamedCause, diagnose_residuals
from egobench.diagnose.signatures import DiagnosisContext

__all__ = ["NO_DISCREPANCY", "Diagnosis", "DiagnosisConfig", "DiagnosisContext", "NamedCause", "diagnose_residuals",
           "add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", nargs="?", help="recording folder (not needed with --sweep or --adt)")
    parser.add_argument("--method", default="ours", help="method whose model is diagnosed (egobench.methods)")
    parser.add_argument("--out", required=True, help="output folder: report.md, diagnosis.json, figures/")
    parser.add_argument("--run", default=None, help="trained run folder: diagnose its renders")
    parser.add_argument("--train", action="store_true", help="train --method first (into OUT/run) and diagnose it")
    parser.add_argument("--source", choices=("auto", "ground_truth", "run"), default="auto",
                        help="prediction: simulator world re-cast under the model's assumptions (ground_truth), "
                             "the run's renders (run); auto = run if --run/--train given, else ground_truth")
    parser.add_argument("--alpha", type=float, default=DiagnosisConfig.alpha, help="family-wise significance level")
    parser.add_argument("--max-causes", type=int, default=DiagnosisConfig.max_causes, help="causes peeled off at most")
    parser.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument("--sweep", action="store_true", help="run the hidden-case sweep (synthetic textures)")
    parser.add_argument("--sweep-seeds", type=int, default=3, help="seeds per effect and magnitude in --sweep")
    parser.add_argument("--sweep-null", type=int, default=20, help="null cases in --sweep")
    parser.add_argument("--adt", default=None, help="Aria Digital Twin sample folder: real (video.vrs) vs twin (synthetic_video.vrs)")
    parser.add_argument("--real-trajectory", default=None,
                        help="with --adt: a real Aria closed_loop_trajectory.csv to compare head-motion statistics with")
    parser.add_argument("--device", default=None,
                        help="torch device to render the run on (default: its training device); with --train, "
                             "also the training device (default cpu)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    from egobench.data.reader import add_input_arguments

    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = DiagnosisConfig(alpha=args.alpha, max_causes=args.max_causes).validate()
    out = Path(args.out)
    if args.sweep:
        from egobench.diagnose.sweep import SweepConfig, run_sweep

        summary = run_sweep(out, SweepConfig(seeds=args.sweep_seeds, null_cases=args.sweep_null), cfg,
                            progress=not args.no_progress)
        print(json.dumps({"out": str(out), "false_alarm_rate": summary["false_alarm_rate"], "n_cases": summary["n_cases"]}))
        return 0
    if args.adt:
        from egobench.diagnose.adt import diagnose_adt

        record = diagnose_adt(args.adt, out, config=cfg, real_trajectory=args.real_trajectory)
        print(json.dumps({"out": str(out), "verdict": record["verdict"], "named": [n["name"] for n in record["named"]]}))
        return 0
    if not args.recording:
        raise ValueError("recording: a recording folder is required (or use --sweep / --adt)")
    rec = Path(args.recording)
    if not rec.is_dir():
        raise FileNotFoundError(f"{rec}: recording folder not found")
    run_dir = Path(args.run) if args.run else None
    if args.train:
        from egobench.data.reader import recording_from_args
        from egobench.methods import get_method
        from egobench.train import TrainConfig, train

        run_dir = out / "run"
        train(recording_from_args(rec, get_method(args.method).calibration, args), args.method,
              TrainConfig(device=args.device or "cpu"), run_dir)
    source = args.source
    if source == "auto":
        source = "run" if run_dir is not None else "ground_truth"
    from egobench.diagnose.report import write_report
    from egobench.diagnose.sources import ground_truth_source, run_source

    if source == "run":
        if run_dir is None:
            raise ValueError("--run: --source run needs a trained run folder (or --train)")
        src = run_source(rec, run_dir, max_frames=args.max_frames, progress=not args.no_progress,
                         device=getattr(args, "device", None), trajectory_path=getattr(args, "trajectory", None),
                         semidense_path=getattr(args, "points", None))
    else:
        from egobench.data.layout import recording_root

        if not (recording_root(rec) / "ground_truth" / "truth.json").is_file():
            raise ValueError(f"{rec}: no ground_truth/truth.json (not simulated): pass --run RUN_DIR or --train")
        src = ground_truth_source(rec, max_frames=args.max_frames, progress=not args.no_progress)
    d = diagnose_residuals(src.measured, src.predicted, src.context, cfg)
    record = write_report(out, d, src.measured, src.predicted, title=f"Residual diagnosis of {rec.name} ({src.description})",
                          extra={"method": args.method, "source": src.description})
    print(json.dumps({"out": str(out), "verdict": record["verdict"], "psnr_gain_db": record["psnr_gain_db"]}))
    return 0
