# egobench workflow: simulate (or preprocess a real Aria recording) -> train (scene x method x seed) -> evaluate -> tables -> plots,
# plus diagnose and (`snakemake sensitivity`) the sensitivity curves. Every rule calls one `egobench <verb>`; the science lives in the package.
#
#   snakemake --cores 2                                # the embedded default suite
#   snakemake --cores 2 --configfile config/ci.yaml    # the CI smoke suite
#   snakemake --workflow-profile profiles/slurm --configfile config/paper.yaml
import os
import re
import sys
import time

from snakemake.exceptions import WorkflowError
from snakemake.utils import min_version, validate

min_version("9.0")

sys.path.insert(0, workflow.basedir)  # egobench importable without `pip install`
from egobench.workflow import slurm_report
from egobench.workflow import config as wc


# The default suite, unless --configfile names another (then it alone is used, not merged).
if not workflow.overwrite_configfiles:

    configfile: os.path.join(workflow.basedir, "config", "config.yaml")


# Clear errors naming the key, before any job runs; then the schema's defaults are filled.
try:
    wc.check_config(config)
except wc.ConfigError as exc:
    raise WorkflowError(str(exc))
validate(config, "workflows/schemas/config.schema.yaml")

SUITE = wc.Suite(config)
R = SUITE.root
# Every rule's shell calls `egobench <verb>`: a shell function wrapping the configured command prefix.
# Not provenance (no rule's shell reads a Python global, no param): calling egobench another way never
# makes Snakemake redo finished simulations or training, and `snakemake --lint` has nothing to report.
_EGOBENCH_FUNCTION = wc.egobench_shell_function(config["egobench_command"], workflow.basedir)
_BRACES = str.maketrans({"{": "{{", "}": "}}"})  # Snakemake formats the prefix with the command
shell.prefix(f"set -euo pipefail; {_EGOBENCH_FUNCTION.translate(_BRACES)} ")
RUN_START = time.time()  # on SLURM, this run's job logs are those written since


wildcard_constraints:
    scene="|".join(re.escape(s) for s in sorted(SUITE.all_scene_names())),
    method="|".join(re.escape(m) for m in SUITE.methods()),
    seed=r"\d+",


include: "workflows/common.smk"
include: "workflows/simulate.smk"
include: "workflows/preprocess.smk"
include: "workflows/train.smk"
include: "workflows/evaluate.smk"
include: "workflows/tables.smk"
include: "workflows/plots.smk"
include: "workflows/diagnose.smk"
include: "workflows/sensitivity.smk"
include: "workflows/similarity.smk"
include: "workflows/viewer.smk"


report: "workflows/report/workflow.rst"


rule all:
    input:
        all_outputs(),
    default_target: True


onerror:
    # snakemake-executor-plugin-slurm: name the jobs that went over their memory request, with the
    # rule, the request and the peak RSS that SLURM measured (egobench slurm-report; '' otherwise)
    memory = slurm_report.report_failed_run(workflow.executor_settings, workflow.workdir_init, RUN_START)
    if memory:
        print(f"SLURM jobs over their memory request:\n{memory}", file=sys.stderr)
