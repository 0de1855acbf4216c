"""The `egobench` command: one verb per workflow step.

Each verb lives in its own module, which provides ``add_arguments(parser)`` and
``run(args) -> int``; `build_parser` registers every verb as a subcommand. Verb modules keep
their heavy imports inside ``run``, so building the parser stays cheap.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: verb -> (module, one-line help)
VERBS: dict[str, tuple[str, str]] = {
    "simulate": ("egobench.sim.cli", "simulate a synthetic egocentric recording"),
    "preprocess": ("egobench.data.preprocess", "rectify a raw Aria VRS recording with its MPS output"),
    "train": ("egobench.train.cli", "train one method on one recording"),
    "evaluate": ("egobench.evaluate", "evaluate a trained run on the held-out frames"),
    "tables": ("egobench.tables", "build the paper-shaped CSV and LaTeX tables from run records"),
    "plots": ("egobench.plots", "draw the figures from run records and recordings"),
    "diagnose": ("egobench.diagnose.cli", "find what a model gets wrong about measured data"),
    "bench": ("egobench.bench", "micro-benchmarks (rasterizer, training step)"),
    "motion-stats": ("egobench.sim.motion_stats", "compare simulated and real head-motion statistics"),
    "slurm-report": ("egobench.slurm_report", "SLURM jobs of a workflow run: rule, state, memory requested and used"),
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every verb; each subparser's ``_run`` default is its module's ``run``."""
    parser = argparse.ArgumentParser(prog="egobench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, (module_name, help_text) in VERBS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(verb, help=help_text, description=help_text)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments) and run the verb; user errors (ValueError,
    FileNotFoundError) print one line and return 2."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return int(args._run(args) or 0)
    except (ValueError, FileNotFoundError) as exc:  # user errors: one clear line, no traceback
        print(f"egobench {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
