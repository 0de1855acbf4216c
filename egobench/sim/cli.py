"""`egobench simulate --kind K --out DIR --seed S [--set field=value ...] [--frames N] [--no-resume]`.

The recording is built in the hidden folder `<parent>/.<name>.partial/` beside --out; rerunning
the same command after an interruption (time limit, OOM, Ctrl-C, a crash) continues after the
last completed frame (egobench.sim.capture.simulate_recording, resume="auto"); a partial folder
written for another configuration is discarded with a message on stderr.
"""

from __future__ import annotations

import argparse
import json

from egobench.sim.config import SCENE_KINDS, SimConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--kind", required=True, choices=SCENE_KINDS, help="scene kind")
    parser.add_argument("--out", required=True, help="recording folder to write (replaced atomically)")
    parser.add_argument("--seed", type=int, default=0, help="seed of scene, motion, noise and calibration errors")
    parser.add_argument("--frames", type=int, default=None, help="number of frames (SimConfig.n_frames)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a SimConfig field (repeatable), e.g. --set motion=fast --set readout_scale=1.3")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-resume", action="store_true",
                        help="start afresh: discard a partial recording of an interrupted run of the same --out "
                             "(by default it is continued), and remove the partial folder if this run fails")


def parse_overrides(items: list[str]) -> dict[str, str]:
    """["a=1", "b=x"] -> {"a": "1", "b": "x"}; ValueError on a malformed item."""
    out: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set {item!r}: expected FIELD=VALUE")
        key, value = item.split("=", 1)
        out[key.strip()] = value
    return out


def run(args: argparse.Namespace) -> int:
    from egobench.sim.capture import simulate_recording

    overrides = parse_overrides(args.overrides)
    if args.frames is not None:
        overrides["n_frames"] = str(args.frames)
    config = SimConfig.from_overrides(args.kind, args.seed, overrides)
    result = simulate_recording(config, args.out, progress=not args.no_progress,
                                resume=False if args.no_resume else "auto")
    print(json.dumps({"recording": str(result.path), "frames": result.n_frames, "time_s": round(result.time_s, 2),
                      "temporal_samples_max": max(result.temporal_samples), "resumed_from_frame": result.resumed_from}))
    return 0
