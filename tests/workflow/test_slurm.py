"""The cluster path: the workflow through snakemake-executor-plugin-slurm.

Profile tests dry-run through the plugin (no SLURM needed). Tests marked `slurm` submit real jobs to a
reachable SLURM with a `cpu` partition and an account `egobench` (`sudo scripts/slurm_local.sh start`)
and are skipped with the reason when there is none.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from egobench.workflow import slurm_report as sr

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile")]
LOCAL_PROFILE = ["--workflow-profile", str(REPO / "profiles" / "slurm_local")]
#: results.csv columns that are wall-clock measurements, not results
TIMING_COLUMNS = ["train_time_s", "train_iters_per_s", "train_raster_time_share"]


def run_snakemake(args: list[str], workdir: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([*SNAKEMAKE, "-d", str(workdir), *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def suite_config(tmp_path: Path, name: str, edit) -> Path:
    config = yaml.safe_load((REPO / "config" / "ci.yaml").read_text())
    config["suite"] = name
    edit(config)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def train_resources(dry_run_output: str) -> str:
    block = dry_run_output.split("rule train:", 1)[1]
    return next(line for line in block.splitlines() if line.strip().startswith("resources:"))


# ------------------------------------------------------------------------------------------------
# The profiles, through the plugin (dry runs)


def test_cluster_profile_passes_the_configs_resources(tmp_path):
    pytest.importorskip("snakemake_executor_plugin_slurm")
    res = run_snakemake(["-n", "--workflow-profile", str(REPO / "profiles" / "slurm"),
                         "--configfile", str(REPO / "config" / "paper.yaml")], tmp_path, timeout=300)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    assert "workflow specific profile" in out and "profiles/default" not in out
    # paper.yaml: train {threads: 4, mem_mb: 56000, gpu: 1, runtime: 480}; partition from the profile.
    # (With --profile, profiles/default is loaded as the workflow profile and caps these to its
    # single-machine mem_mb=8000 and gpu=0.)
    train = train_resources(out)
    for item in ("mem_mb=56000", "gpu=1", "runtime=480", "slurm_partition=gpu"):
        assert item in train, train


def test_local_profile_passes_the_configs_resources(tmp_path):
    pytest.importorskip("snakemake_executor_plugin_slurm")
    config = suite_config(tmp_path, "t", lambda c: c["resources"].update(train={"mem_mb": 1800, "runtime": 20}))
    res = run_snakemake(["-n", *LOCAL_PROFILE, "--configfile", str(config)], tmp_path, timeout=300)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    train = train_resources(out)
    for item in ("mem_mb=1800", "runtime=20", "slurm_partition=cpu", "slurm_account=egobench", "gpu=0"):
        assert item in train, train


# ------------------------------------------------------------------------------------------------
# A real SLURM


def slurm_unreachable() -> str:
    """Why no SLURM can take the jobs ('' when one can)."""
    try:
        import snakemake_executor_plugin_slurm  # noqa: F401
    except ImportError:
        return "snakemake-executor-plugin-slurm not installed (pip install -e '.[slurm]')"
    if shutil.which("sbatch") is None or shutil.which("sacct") is None:
        return "no SLURM client commands (sbatch, sacct) on PATH"
    try:
        state = subprocess.run(["sinfo", "-h", "-p", "cpu", "-o", "%T"], capture_output=True, text=True, timeout=60)
        if state.returncode != 0 or not {"idle", "mixed", "allocated"} & set(state.stdout.split()):
            return f"no SLURM partition 'cpu' with a usable node (sinfo: {(state.stdout + state.stderr).strip()!r})"
        acct = subprocess.run(["sacct", "-n", "-X", "-S", "now-1minutes"], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired as exc:
        return f"the SLURM controller did not answer {exc.cmd[0]} within {exc.timeout:.0f} s"
    if acct.returncode != 0:
        return f"SLURM accounting unavailable (sacct: {acct.stderr.strip()})"
    return ""


@pytest.fixture(scope="module")
def slurm():
    reason = slurm_unreachable()
    if reason:
        pytest.skip(f"no SLURM reachable (start one: sudo scripts/slurm_local.sh start): {reason}")


def sacct_rows(job_ids: list[str]) -> dict[str, dict[str, str]]:
    fields = ["JobID", "State", "ReqMem", "AllocCPUS", "Timelimit", "Partition", "Account"]
    out = subprocess.run(["sacct", "-X", "-P", "-n", f"--format={','.join(fields)}", "-j", ",".join(job_ids)],
                         capture_output=True, text=True, check=True).stdout
    return {row.split("|")[0]: dict(zip(fields, row.split("|"))) for row in out.splitlines()}


@pytest.mark.slurm
@pytest.mark.slow
def test_ci_suite_through_slurm_matches_a_local_run(tmp_path, slurm):
    # ci.yaml with distinct resources per rule, so that their way into sbatch can be seen
    config = suite_config(tmp_path, "ci", lambda c: c["resources"].update(
        train={"threads": 1, "mem_mb": 1800, "runtime": 20}, evaluate={"threads": 2, "mem_mb": 2500, "runtime": 30}))
    on_slurm, local = tmp_path / "slurm", tmp_path / "local"
    start = time.perf_counter()
    res = run_snakemake([*LOCAL_PROFILE, "--configfile", str(config)], on_slurm)
    print(f"ci suite through SLURM: {time.perf_counter() - start:.0f} s")
    assert res.returncode == 0, (res.stdout + res.stderr)[-4000:]
    ref = run_snakemake(["--cores", "2", "--configfile", str(config)], local)
    assert ref.returncode == 0, (ref.stdout + ref.stderr)[-4000:]

    # every job but `all` was one sbatch, logged where the profile says (logs/slurm/rule_<rule>/...)
    jobs = sr.logged_jobs(on_slurm / "logs" / "slurm")
    rules = sorted(rule for _, rule, _, _ in jobs)
    assert rules == sorted(["simulate", "train", "train", "evaluate", "evaluate", "tables", "plots", "diagnose",
                            "motion_stats"])
    submitted = re.findall(r"submitted with SLURM jobid (\d+)", res.stdout + res.stderr)
    assert sorted(submitted) == sorted(j for j, *_ in jobs)
    acct = sacct_rows([j for j, *_ in jobs])
    expected = {"train": ("1800M", "1", "00:20:00"), "evaluate": ("2500M", "2", "00:30:00"),
                "tables": ("2000M", "1", "01:00:00")}  # schema defaults: 1 thread, 2000 MB, 60 min
    for job_id, rule, _, _ in jobs:
        row = acct[job_id]
        assert row["State"] == "COMPLETED" and row["Partition"] == "cpu" and row["Account"] == "egobench", row
        if rule in expected:
            assert (row["ReqMem"], row["AllocCPUS"], row["Timelimit"]) == expected[rule], (rule, row)

    # the tables are those of the local run; results.csv differs only in its wall-clock columns
    tables = sorted(p.name for p in (local / "results" / "ci" / "tables").iterdir())
    assert tables == sorted(p.name for p in (on_slurm / "results" / "ci" / "tables").iterdir())
    for name in tables:
        a, b = (root / "results" / "ci" / "tables" / name for root in (local, on_slurm))
        if name == "results.csv":
            pd.testing.assert_frame_equal(pd.read_csv(a).drop(columns=TIMING_COLUMNS),
                                          pd.read_csv(b).drop(columns=TIMING_COLUMNS))
        else:
            assert a.read_bytes() == b.read_bytes(), name


def _wait_for(predicate, timeout_s: float, what: str):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")


@pytest.mark.slurm
@pytest.mark.slow
def test_cancelled_training_job_is_resubmitted_and_resumes(tmp_path, slurm):
    iterations = 400

    def edit(c):
        c["scenes"][0]["methods"] = ["ours"]
        c["defaults"].update(iterations=iterations, train={"checkpoint_every": 20})

    config = suite_config(tmp_path, "cancel", edit)
    run_dir = tmp_path / "results" / "cancel" / "runs" / "outdoor_0" / "ours" / "seed0"
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.Popen([*SNAKEMAKE, "-d", str(tmp_path), str(run_dir.relative_to(tmp_path) / "train.json"),
                             *LOCAL_PROFILE, "--configfile", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        # cancel the training job once it has written a checkpoint
        _wait_for(lambda: (run_dir / "checkpoint.pt").is_file(), 600, "the first checkpoint")
        first = [j for j, rule, *_ in sr.logged_jobs(tmp_path / "logs" / "slurm") if rule == "train"]
        subprocess.run(["scancel", first[0]], check=True)
        out, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-4000:]
    train_jobs = [j for j, rule, *_ in sr.logged_jobs(tmp_path / "logs" / "slurm") if rule == "train"]
    assert len(train_jobs) == 2 and train_jobs[0] == first[0], train_jobs
    acct = sacct_rows(train_jobs)
    assert acct[train_jobs[0]]["State"].startswith("CANCELLED") and acct[train_jobs[1]]["State"] == "COMPLETED"
    assert "Trying to restart job" in out
    # the resubmitted job continued from the checkpoint: its progress starts past iteration 0
    log = (tmp_path / "results" / "cancel" / "logs" / "train" / "outdoor_0" / "ours" / "seed0.log").read_text()
    first_progress = re.search(rf"(\d+)/{iterations} ", log.replace("\r", "\n"))
    assert first_progress and int(first_progress.group(1)) >= 20, log[:2000]
    record = json.loads((run_dir / "train.json").read_text())
    assert record["complete"] and record["train"]["iterations"] == iterations


@pytest.mark.slurm
def test_job_over_its_memory_request_is_reported(tmp_path, slurm):
    config = suite_config(tmp_path, "mem", lambda c: c["resources"].update(simulate={"mem_mb": 400}))
    target = "results/mem/recordings/outdoor_0"
    res = run_snakemake([target, *LOCAL_PROFILE, "--retries", "0", "--configfile", str(config)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode != 0, out[-3000:]
    line = re.compile(r"rule simulate \[outdoor_0\]: SLURM job (\d+) (\S+), over its memory request: "
                      r"requested 400 MB, used (\d+) MB")
    m = line.search(out.split("SLURM jobs over their memory request:", 1)[-1])
    assert m, out[-3000:]
    assert int(m.group(3)) > 400
    # the same from the command, and SLURM's own accounting agrees
    cli = subprocess.run([sys.executable, "-m", "egobench.cli", "slurm-report", "--logdir",
                          str(tmp_path / "logs" / "slurm")], capture_output=True, text=True, cwd=REPO)
    assert line.search(cli.stdout), cli.stdout + cli.stderr
    job = sr.parse_sacct(sr.query_sacct([m.group(1)]))[m.group(1)]
    assert job["req_mem_mb"] == 400 and job["state"] in ("FAILED", "OUT_OF_MEMORY", "CANCELLED")
