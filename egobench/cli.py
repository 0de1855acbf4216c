"""The `egobench` command: one verb per workflow step.

Each verb lives in its own module, which provides ``add_arguments(parser)`` and
``run(args) -> int``. Modules are imported lazily so that ``egobench --help`` is fast and a
verb's heavy imports are paid only when it runs.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: verb -> (module, one-line help)
VERBS: dict[str, tuple[str, str]] = {
    "simulate": ("egobench.sim.cli", "simulate a synthetic egocentric recording"),
    "train": ("egobench.train", "train one method on one recording"),
    "evaluate": ("egobench.evaluate", "evaluate a trained run on the held-out frames"),
    "tables": ("egobench.tables", "build the paper-shaped CSV and LaTeX tables from run records"),
    "plots": ("egobench.plots", "draw the figures from run records and recordings"),
    "diagnose": ("egobench.diagnose", "find what a model gets wrong about measured data"),
    "bench": ("egobench.bench", "micro-benchmarks (rasterizer, training step)"),
    "motion-stats": ("egobench.sim.motion_stats", "compare simulated and real head-motion statistics"),
    "slurm-report": ("egobench.slurm_report", "SLURM jobs of a workflow run: rule, state, memory requested and used"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="egobench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, (module_name, help_text) in VERBS.items():
        p = sub.add_parser(verb, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        # Arguments are registered lazily: only the chosen verb's module is imported.
        if len(sys.argv) > 1 and sys.argv[1] == verb:
            importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    if argv is not None:
        sys.argv = ["egobench", *argv]
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:])
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except (ValueError, FileNotFoundError) as exc:  # user errors: one clear line, no traceback
        print(f"egobench {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
