# Helpers shared by the workflow files: config -> targets. The logic lives in
# egobench/workflow/config.py (unit-tested); this file only adapts it to Snakemake.
from egobench.report.outputs import FIGURE_FILES, TABLE_FILES


def res(step, key):
    """A resource of one step (threads, mem_mb, gpu, runtime) from config.resources."""
    return SUITE.resources(step)[key]


def eval_records():
    return SUITE.eval_records()


def table_files():
    return [f"{R}/tables/{name}" for name in TABLE_FILES]


def figure_files():
    return [f"{R}/figures/{name}" for name in FIGURE_FILES]


def all_outputs():
    out = eval_records() + table_files() + figure_files() + SUITE.diagnosis_dirs() + SUITE.viewer_outputs()
    out.append(f"{R}/similarity/similarity.json")
    if SUITE.motion_stats:
        out.append(f"{R}/motion_stats/motion_stats.json")
    return out


def sensitivity_targets(wildcards):
    """`snakemake sensitivity`'s targets; a sweep's bad SimConfig override fails here, naming its key."""
    try:
        return SUITE.sensitivity_outputs()
    except wc.ConfigError as exc:
        raise WorkflowError(str(exc))
