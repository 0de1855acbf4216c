"""`egobench train --recording REC --method M --out RUN [--preset cpu|paper] [--set field=value ...]`."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from egobench.data.reader import add_input_arguments
from egobench.train.config import PRESETS, TrainConfig, parse_overrides, preset_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recording", required=True,
                        help="recording: a rectified stream folder (<label>-rectified-<focal>-h<size>) or the folder holding it")
    parser.add_argument("--method", required=True, help="method name (egobench.model.methods)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--out", required=True, help="run folder (checkpoint.pt, train.json)")
    parser.add_argument("--iterations", type=int, default=None, help="iterations (schedule scaled to it)")
    parser.add_argument("--preset", choices=PRESETS, default="cpu",
                        help="starting config: 'cpu' (small, ~1 min) or 'paper' (30K, full resolution)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override a TrainConfig field")
    parser.add_argument("--resume", nargs="?", const="yes", choices=("yes", "auto"), default=None,
                        help="continue from RUN_DIR/checkpoint.pt; 'auto': only if it matches this method and "
                             "config, else start afresh (what the workflow passes)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    add_input_arguments(parser)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The preset, then ``--set`` overrides, the seed, and ``--iterations`` (schedule scaled)."""
    config = parse_overrides(preset_config(args.preset), args.set)
    config = replace(config, seed=int(args.seed))
    if args.iterations is not None:
        config = config.scaled_to(args.iterations)
    return config


def run(args: argparse.Namespace) -> int:
    from egobench.data.reader import recording_from_args
    from egobench.model.methods import get_method
    from egobench.train.loop import TrainingDiverged, train

    config = config_from_args(args)
    if not str(config.device).startswith("cuda"):
        from egobench.host import default_threads, keep_freed_memory

        default_threads()  # torch and the kernels on every core; unless OMP_NUM_THREADS & co. say otherwise
        keep_freed_memory()  # reuse each step's freed buffers (Snakemake's jobs too)
    try:
        resume = {None: False, "yes": True, "auto": "auto"}[args.resume]
        recording = recording_from_args(args.recording, get_method(args.method).calibration, args)
        res = train(recording, args.method, config, args.out, resume=resume, progress=not args.no_progress)
    except TrainingDiverged as exc:
        print(f"egobench train: error: {exc}", file=sys.stderr)
        return 3
    sharing, cores = res.record["train"]["core_sharing"], ""
    if sharing:  # probed: numba is there
        from egobench.core_sharing import describe

        cores = describe(sharing)
    print(f"trained {args.method}: {res.iterations} iterations, {res.num_gaussians} Gaussians, "
          f"{res.iters_per_s:.1f} it/s, raster share {res.raster_time_share:.2f}{cores} -> {res.checkpoint}")
    return 0
