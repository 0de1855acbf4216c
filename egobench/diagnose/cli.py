"""`egobench diagnose`: what a model gets wrong about a recording (see `egobench.diagnose`)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import yaml

import egobench.train  # called as egobench.train.train: a replacement there (tests) is the one run
from egobench.analysis.similarity import exposure_gain_ratio
from egobench.data.layout import recording_root
from egobench.data.reader import add_input_arguments, recording_from_args
from egobench.diagnose.absorption import hidden_testable, load_retention
from egobench.diagnose.core import DiagnosisConfig, diagnose_residuals
from egobench.diagnose.extension import judge_shading, learned_shading_of, load_shading_null, run_setup
from egobench.diagnose.learned_frames import judge_learned_frames
from egobench.diagnose.learned_timing import judge_timing, learned_timing_of, timing_evidence, timing_of_run
from egobench.diagnose.lens_check import diagnose_trained_run
from egobench.diagnose.report import write_report
from egobench.diagnose.sources import ground_truth_source, run_source
from egobench.diagnose.timing_pulls import TimedRun, held_out_timing_gain
from egobench.diagnose.trained_sweep import PHOTOMETRIC, TrainedSweepConfig, extension_gain, run_trained_sweep
from egobench.model.methods import get_method


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", nargs="?", help="recording folder (not needed with --sweep or --adt)")
    parser.add_argument("--method", default="ours", help="method whose model is diagnosed (egobench.model.methods)")
    parser.add_argument("--out", required=True, help="output folder: report.md, diagnosis.json, figures/")
    parser.add_argument("--run", default=None, help="trained run folder: diagnose its renders")
    parser.add_argument("--train", action="store_true", help="train --method first (into OUT/run) and diagnose it")
    parser.add_argument("--source", choices=("auto", "ground_truth", "run"), default="auto",
                        help="prediction: simulator world re-cast under the model's assumptions (ground_truth), "
                             "the run's renders (run); auto = run if --run/--train given, else ground_truth")
    parser.add_argument("--alpha", type=float, default=DiagnosisConfig.alpha, help="family-wise significance level")
    parser.add_argument("--max-causes", type=int, default=DiagnosisConfig.max_causes, help="causes peeled off at most")
    parser.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument("--pose-samples", type=int, default=None,
                        help="with --run: render every moving frame with N rolling-shutter pose samples instead of "
                             "the run's own (its staircase shortens the effective readout by ~1/N; docs/diagnosis.md)")
    parser.add_argument("--sweep", action="store_true", help="run the hidden-case sweep (synthetic textures)")
    parser.add_argument("--sweep-seeds", type=int, default=3, help="seeds per effect and magnitude in --sweep")
    parser.add_argument("--sweep-null", type=int, default=20, help="null cases in --sweep")
    parser.add_argument("--trained", action="store_true",
                        help="with --sweep: the trained-run sweep (simulate hidden effects, train --method with the "
                             "CPU preset, diagnose the run's renders; resumable per case in OUT/cases/)")
    parser.add_argument("--sweep-effects", default=None,
                        help="with --sweep --trained: comma-separated effects (default: the photometric ones)")
    parser.add_argument("--sweep-size", type=int, default=40, help="with --sweep --trained: image size, px")
    parser.add_argument("--sweep-frames", type=int, default=24, help="with --sweep --trained: frames per recording")
    parser.add_argument("--sweep-kind", default="indoor", help="with --sweep --trained: scene kind")
    parser.add_argument("--sweep-motion", default="fast",
                        help="with --sweep --trained: head motion (normal | fast | static)")
    parser.add_argument("--sweep-sim", action="append", default=[], metavar="FIELD=VALUE",
                        help="with --sweep --trained: a further SimConfig field of every recording, e.g. "
                             "exposure_s=0.001 (repeatable; docs/diagnosis.md 'Hard cases')")
    parser.add_argument("--sweep-seed-offset", type=int, default=0,
                        help="with --sweep --trained: added to every simulation seed (exploration on other seeds)")
    parser.add_argument("--adt", default=None, help="Aria Digital Twin sample folder: real (video.vrs) vs twin (synthetic_video.vrs)")
    parser.add_argument("--real-trajectory", default=None,
                        help="with --adt: a real Aria closed_loop_trajectory.csv to compare head-motion statistics with")
    parser.add_argument("--device", default=None,
                        help="torch device to render the run on (default: its training device); with --train, "
                             "also the training device (default cpu)")
    parser.add_argument("--preset", choices=("cpu", "paper"), default="cpu",
                        help="with --train: the starting config, as `egobench train --preset` (at the recording's "
                             "full resolution: diagnosis compares full-resolution renders)")
    parser.add_argument("--iterations", type=int, default=None, help="with --train: iterations (schedule scaled)")
    parser.add_argument("--shading-null", default=None, metavar="TRAINED_SWEEP_JSON",
                        help="with a run: the model extension (a lens shading learned with the scene; the run's own "
                             "when trained with learn_shading, else trained into OUT/run_shading with the run's "
                             "config), called against the null cases of this trained-run sweep summary")
    parser.add_argument("--retention", action="append", default=None, metavar="TRAINED_SWEEP_JSON",
                        help="with a run: scale the smallest testable sizes by how much of each effect training "
                             "retained in this trained-run sweep summary (repeatable; later files win)")
    parser.add_argument("--learn-timing", action="store_true",
                        help="with a run that did not learn its timing (`egobench train --set learn_timing=true`): "
                             "train the run's method once more with its config, seed and the timing into "
                             "OUT/learn_timing, and judge the time offset and readout error it learns "
                             "(egobench.diagnose.learned_timing)")
    parser.add_argument("--lens-check", action="store_true",
                        help="on a trained run, measure the run's retention of a lens of twice the smallest k0 "
                             "error its report calls testable (the method trained once more, on the recording "
                             "warped by it, into OUT/lens_check) and test a lens only from a retention of 25 %%; "
                             "without it a trained run's lens is not tested (egobench.diagnose.lens_check)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from egobench.host import keep_freed_memory

    keep_freed_memory(whole_images=True)  # reuse the freed image stacks (docs/diagnosis.md, "Cost at ...")
    cfg = DiagnosisConfig(alpha=args.alpha, max_causes=args.max_causes).validate()
    out = Path(args.out)
    if args.sweep and args.trained:
        return _trained_sweep(args, cfg, out)
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
    return _diagnose_recording(args, cfg, out)


def _trained_sweep(args: argparse.Namespace, cfg: DiagnosisConfig, out: Path) -> int:
    """--sweep --trained: the hidden-case sweep on trained runs (egobench.diagnose.trained_sweep)."""
    effects = tuple(e.strip() for e in args.sweep_effects.split(",") if e.strip()) if args.sweep_effects else PHOTOMETRIC
    sc = TrainedSweepConfig(null_cases=args.sweep_null, seeds=args.sweep_seeds, effects=effects, kind=args.sweep_kind,
                            size=args.sweep_size, n_frames=args.sweep_frames, method=args.method,
                            motion=args.sweep_motion, sim=sim_overrides(args.sweep_sim),
                            seed_offset=args.sweep_seed_offset,
                            iterations=args.iterations if args.iterations is not None else TrainedSweepConfig.iterations)
    s = run_trained_sweep(out, sc, cfg, progress=not args.no_progress)
    print(json.dumps({"out": str(out), "false_alarms": s["false_alarms"], "n_null": s["n_null"], "n_cases": s["n_cases"],
                      "n_failed": s["n_failed"]}))
    return 0


def sim_overrides(pairs: list[str]) -> dict:
    """FIELD=VALUE strings of --sweep-sim -> {field: value} (values read as YAML scalars: 0.001, true, null)."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--sweep-sim: expected FIELD=VALUE (a SimConfig field), got {pair!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


def _train_for_diagnosis(args: argparse.Namespace, rec: Path, out: Path) -> Path:
    """--train: train --method with the --preset rules of `egobench train`, at full resolution, into OUT/run."""
    config = replace(egobench.train.preset_config(args.preset), max_side=0, device=args.device or "cpu")
    if args.iterations is not None:
        config = config.scaled_to(args.iterations)
    run_dir = out / "run"
    recording = recording_from_args(rec, get_method(args.method).calibration, args)
    egobench.train.train(recording, args.method, config, run_dir, progress=not args.no_progress)
    return run_dir


def _diagnose_recording(args: argparse.Namespace, cfg: DiagnosisConfig, out: Path) -> int:
    """Diagnose one recording against the simulator's world (ground_truth) or a trained run's renders."""
    if not args.recording:
        raise ValueError("recording: a recording folder is required (or use --sweep / --adt)")
    rec = Path(args.recording)
    if not rec.is_dir():
        raise FileNotFoundError(f"{rec}: recording folder not found")
    run_dir = _train_for_diagnosis(args, rec, out) if args.train else (Path(args.run) if args.run else None)
    source = args.source if args.source != "auto" else ("run" if run_dir is not None else "ground_truth")
    if args.learn_timing and source != "run":
        raise ValueError("--learn-timing: the timing is learned with a trained run's scene; pass --run RUN_DIR or --train")
    if source == "run":
        if run_dir is None:
            raise ValueError("--run: --source run needs a trained run folder (or --train)")
        src = run_source(rec, run_dir, max_frames=args.max_frames, progress=not args.no_progress, device=args.device,
                         pose_samples=args.pose_samples,
                         trajectory_path=args.trajectory, semidense_path=args.points)
    else:
        if not (recording_root(rec) / "ground_truth" / "truth.json").is_file():
            raise ValueError(f"{rec}: no ground_truth/truth.json (not simulated): pass --run RUN_DIR or --train")
        src = ground_truth_source(rec, max_frames=args.max_frames, progress=not args.no_progress)
    if source == "run":  # the null includes the trained model's own error (egobench.diagnose.placebo, `Cause.trained_placebos`)
        cfg = replace(cfg, trained_run=True)
    extension = _shading_extension(args, rec, run_dir, src, out) if args.shading_null else None
    if source == "run" and args.lens_check:  # a lens tested only where the run keeps one
        d = diagnose_trained_run(rec, run_dir, src, cfg, out / "lens_check", pose_samples=args.pose_samples,
                                 progress=not args.no_progress)
    else:
        d = diagnose_residuals(src.measured, src.predicted, src.context, cfg)
    if args.retention:
        _add_hidden_testable(d, args.retention)
    extra = {"method": args.method, "source": src.description}
    timing = _learned_timing(args, rec, run_dir, out, src) if source == "run" else None
    frames = judge_learned_frames(run_dir, src, cfg.border_px) if source == "run" else None
    record = write_report(out, d, src.measured, src.predicted, title=f"Residual diagnosis of {rec.name} ({src.description})",
                          extra=extra, shading_extension=extension, learned_timing=timing, learned_frames=frames)
    summary = {"out": str(out), "verdict": record["verdict"], "psnr_gain_db": record["psnr_gain_db"]}
    if timing is not None:
        summary["learned_timing_named"] = timing["named"]
    if frames is not None:
        summary["learned_frames_named"] = frames["named"]
    if extension is not None:
        summary["shading_extension"] = extension["called"]
        if extension["held_out"]:
            summary["shading_extension_gain_db"] = extension["held_out"]["gain_db"]
    print(json.dumps(summary))
    return 0


def _learned_timing(args: argparse.Namespace, rec: Path, run_dir: Path, out: Path, src) -> dict | None:
    """The timing the run learned with its scene, judged (None where it learned none and --learn-timing is off;
    with it, the run's method trained once more with the timing, into OUT/learn_timing)."""
    if args.learn_timing:
        learned, learned_in = timing_of_run(rec, run_dir, out / "learn_timing", progress=not args.no_progress)
    else:
        learned, learned_in = learned_timing_of(run_dir), run_dir
    if learned is None:
        return None
    try:  # the run loaded once for both reports beside the floors; a run they cannot be made on is still judged
        timed = TimedRun(rec, learned_in, device=args.device, trajectory_path=args.trajectory,
                         semidense_path=args.points)
    except ValueError as e:
        evidence, reports = None, {"tests_unavailable": str(e), "held_out_unavailable": str(e)}
    else:
        evidence, reports = _timing_reports(timed, progress=not args.no_progress)
    return {**judge_timing(learned, src.context.readout_s, evidence), "learned_in": str(learned_in), **reports}


def _timing_reports(timed: TimedRun, progress: bool) -> tuple[dict | None, dict]:
    """The learned timing's standard errors on its run and its held-out gain, reported beside its floors, never
    deciding (egobench.diagnose.learned_timing) -> (the evidence, or None where it cannot be computed; the record's
    "held_out", with "tests_unavailable" / "held_out_unavailable" saying why where one cannot be)."""
    reports = {}
    try:
        evidence = timing_evidence(timed, progress=progress)
    except ValueError as e:
        evidence, reports["tests_unavailable"] = None, str(e)
    try:
        reports["held_out"] = held_out_timing_gain(timed, progress=progress)
    except (ValueError, OSError) as e:
        reports["held_out_unavailable"] = str(e)
    return evidence, reports


def _add_hidden_testable(d, paths: list[str]) -> None:
    """--retention: the smallest testable hidden effects (egobench.diagnose.absorption) into model_error."""
    if d.model_error is None:
        raise ValueError("--retention: needs a trained run's diagnosis (--run RUN_DIR or --train)")
    retention, sources = load_retention(paths)
    d.model_error["smallest_testable_hidden"] = hidden_testable(d.model_error.get("smallest_testable", {}), retention)
    d.model_error["retention_sources"] = sources


def _shading_extension(args: argparse.Namespace, rec: Path, run_dir: Path | None, src, out: Path) -> dict:
    """--shading-null: the learned lens shading of the run (or of its extension run) against the sweep's nulls."""
    if run_dir is None:
        raise ValueError("--shading-null: the model extension needs a trained run (--run RUN_DIR or --train)")
    null = load_shading_null(args.shading_null)
    recording = recording_from_args(rec, get_method(args.method).calibration, args)
    learned, learned_in = learned_shading_of(run_dir, recording, out, args.method, progress=not args.no_progress)
    n, h, w = src.measured.shape[:3]
    setup = run_setup(run_dir, n_frames=n, image_size=max(h, w))
    ratio = exposure_gain_ratio(src.context.exposure_s, src.context.gain, where=f"{rec}: exposure metadata")
    judged = {**judge_shading(learned, null, setup, ratio), "learned_in": learned_in, "held_out": None}
    if Path(learned_in) != Path(run_dir):  # an extension run beside the user's: what the extension gains
        judged["held_out"] = extension_gain(recording, run_dir, learned_in)
    return judged
