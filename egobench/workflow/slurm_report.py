"""`egobench slurm-report`: the SLURM jobs of a workflow run, with each job's rule, state, memory
request and peak memory, naming the jobs that went over their memory request.

snakemake-executor-plugin-slurm writes one log per job at
``<logdir>/rule_<rule>/<wildcards>/<jobid>.log`` (``<logdir>/rule_<rule>/<jobid>.log`` without
wildcards; ``group_<name>`` for groups). Those paths tie a SLURM job id to its rule; ``sacct`` adds
the state, the requested memory (``ReqMem``) and the peak resident memory of the job's steps
(``MaxRSS``, sampled by SLURM's accounting poller). A job is over its memory when SLURM says
``OUT_OF_MEMORY``, when its log holds slurmstepd's "exceeded memory limit" kill message, or when its
peak RSS exceeds its request (possible where SLURM does not enforce memory).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

#: the plugin's default log folder, relative to the workflow's working directory
DEFAULT_LOGDIR = ".snakemake/slurm_logs"
SACCT_FIELDS = ("JobID", "State", "ExitCode", "ReqMem", "MaxRSS", "Elapsed")
#: slurmstepd's message when the accounting poller kills a step over its --mem (jobacct_gather)
KILL_MESSAGE = re.compile(r"exceeded memory limit \((\d+) > (\d+)\)")
_UNITS_MB = {"K": 1 / 1024, "M": 1.0, "G": 1024.0, "T": 1024.0**2}


@dataclass(frozen=True)
class SlurmJob:
    """One SLURM job of the run; memory in MB (None: unknown)."""

    job_id: str
    rule: str
    wildcards: str
    log: Path
    state: str = "UNKNOWN"
    exit_code: str = ""
    req_mem_mb: float | None = None
    max_rss_mb: float | None = None
    killed_rss_mb: float | None = None  # RSS in slurmstepd's kill message, if the log has one

    @property
    def peak_mb(self) -> float | None:
        values = [v for v in (self.max_rss_mb, self.killed_rss_mb) if v is not None]
        return max(values) if values else None

    @property
    def over_memory(self) -> bool:
        if self.state == "OUT_OF_MEMORY" or self.killed_rss_mb is not None:
            return True
        return self.peak_mb is not None and self.req_mem_mb is not None and self.peak_mb > self.req_mem_mb

    @property
    def failed(self) -> bool:
        return self.state not in ("COMPLETED", "PENDING", "RUNNING", "UNKNOWN")


def parse_mem_mb(text: str) -> float | None:
    """SLURM memory text -> MB: '2000M', '322384K', '1.5G', '2000Mn' (per node), '' -> None."""
    m = re.fullmatch(r"\s*([0-9.]+)([KMGT]?)[nc]?\s*", text or "")
    if not m:
        return None
    return float(m.group(1)) * _UNITS_MB[m.group(2) or "M"]


def logged_jobs(logdir: Path, since: float | None = None) -> list[tuple[str, str, str, Path]]:
    """(job id, rule, wildcards, log path) of every plugin log under ``logdir`` modified at or
    after ``since`` (unix seconds), in job-id order."""
    found = []
    for log in Path(logdir).rglob("*.log"):
        if not log.stem.isdigit() or (since is not None and log.stat().st_mtime < since):
            continue
        parts = log.relative_to(logdir).parts
        if not parts[0].startswith(("rule_", "group_")):
            continue
        rule = parts[0].split("_", 1)[1]
        wildcards = parts[1] if len(parts) == 3 else ""
        found.append((log.stem, rule, wildcards, log))
    return sorted(found, key=lambda j: int(j[0]))


def parse_sacct(text: str) -> dict[str, dict]:
    """``sacct --parsable2 --noheader --format=JobID,State,ExitCode,ReqMem,MaxRSS,Elapsed`` ->
    {job id: {state, exit_code, req_mem_mb, max_rss_mb (the largest over the job's steps)}}."""
    jobs: dict[str, dict] = {}
    for line in text.splitlines():
        fields = line.split("|")
        if len(fields) < len(SACCT_FIELDS):
            continue
        job_id, state, exit_code, req_mem, max_rss = fields[:5]
        base, _, step = job_id.partition(".")
        job = jobs.setdefault(base, {"state": "UNKNOWN", "exit_code": "", "req_mem_mb": None, "max_rss_mb": None})
        if not step:  # the allocation's own row: state and request
            job.update(state=state.split()[0] if state else "UNKNOWN", exit_code=exit_code,
                       req_mem_mb=parse_mem_mb(req_mem))
        rss = parse_mem_mb(max_rss)
        if rss is not None and (job["max_rss_mb"] is None or rss > job["max_rss_mb"]):
            job["max_rss_mb"] = rss
    return jobs


def query_sacct(job_ids: list[str]) -> str:
    """Raw sacct rows of the given jobs and their steps ('' when there are none)."""
    if not job_ids:
        return ""
    if shutil.which("sacct") is None:
        raise FileNotFoundError("sacct: not found on PATH (SLURM's accounting client is needed)")
    cmd = ["sacct", "--parsable2", "--noheader", f"--format={','.join(SACCT_FIELDS)}", "-j", ",".join(job_ids)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise ValueError(f"sacct failed ({' '.join(cmd)}): {res.stderr.strip()}")
    return res.stdout


def killed_rss_mb(log: Path) -> float | None:
    """RSS (MB) in slurmstepd's 'exceeded memory limit (used > limit)' message in a job log."""
    try:
        text = log.read_text(errors="replace")
    except FileNotFoundError:
        return None
    used = [int(m.group(1)) for m in KILL_MESSAGE.finditer(text)]
    return max(used) / 2**20 if used else None


def collect(logdir: Path, since: float | None = None, sacct_text: str | None = None) -> list[SlurmJob]:
    """The run's jobs: rule from the plugin's log paths, state and memory from sacct."""
    logged = logged_jobs(logdir, since)
    if sacct_text is None:
        sacct_text = query_sacct([j[0] for j in logged])
    acct = parse_sacct(sacct_text)
    return [SlurmJob(job_id, rule, wildcards, log, killed_rss_mb=killed_rss_mb(log), **acct.get(job_id, {}))
            for job_id, rule, wildcards, log in logged]


def _mb(value: float | None) -> str:
    return "unknown" if value is None else f"{value:.0f} MB"


def describe(job: SlurmJob) -> str:
    """One line: rule, wildcards, job, state, request and use."""
    where = f"rule {job.rule}" + (f" [{job.wildcards}]" if job.wildcards else "")
    line = f"{where}: SLURM job {job.job_id} {job.state}"
    if job.over_memory:
        line += f", over its memory request: requested {_mb(job.req_mem_mb)}, used {_mb(job.peak_mb)}"
        line += " (killed by SLURM)" if job.killed_rss_mb is not None or job.state == "OUT_OF_MEMORY" else ""
    else:
        line += f", requested {_mb(job.req_mem_mb)}, used {_mb(job.peak_mb)}"
    return f"{line}; log {job.log}"


def memory_report(jobs: list[SlurmJob]) -> str:
    """The lines of the jobs over their memory request ('' if none)."""
    return "\n".join(describe(j) for j in jobs if j.over_memory)


def report_failed_run(executor_settings, workdir: Path, since: float) -> str:
    """For a Snakefile's ``onerror``: the memory report of this run's SLURM jobs, '' when the run did
    not use the SLURM executor (no ``logdir`` setting) or nothing went over its memory."""
    if executor_settings is None or not hasattr(executor_settings, "logdir"):
        return ""
    logdir = Path(executor_settings.logdir or DEFAULT_LOGDIR)
    logdir = logdir if logdir.is_absolute() else Path(workdir) / logdir
    if not logdir.is_dir():
        return ""
    try:
        return memory_report(collect(logdir, since))
    except (ValueError, FileNotFoundError) as exc:
        return f"SLURM memory report unavailable: {exc}"


def _since(text: str | None) -> float | None:
    if not text:
        return None
    try:
        return datetime.fromisoformat(text).timestamp()
    except ValueError as exc:
        raise ValueError(f"--since: '{text}' is not an ISO date/time (e.g. 2026-01-31T12:00)") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--logdir", type=Path, default=Path(DEFAULT_LOGDIR),
                        help=f"the executor plugin's log folder (default {DEFAULT_LOGDIR}; the profile's slurm-logdir)")
    parser.add_argument("--since", help="only logs written since this ISO time (default: all)")
    parser.add_argument("--all", action="store_true", help="list every job, not only those over their memory")


def run(args: argparse.Namespace) -> int:
    if not args.logdir.is_dir():
        raise FileNotFoundError(f"--logdir {args.logdir}: no such folder (the plugin writes its job logs there)")
    jobs = collect(args.logdir, _since(args.since))
    lines = [describe(j) for j in jobs] if args.all else [describe(j) for j in jobs if j.over_memory]
    print("\n".join(lines) if lines else f"no job over its memory request among {len(jobs)} SLURM jobs")
    return 0


if __name__ == "__main__":  # pragma: no cover
    _parser = argparse.ArgumentParser(prog="egobench slurm-report", description=__doc__.splitlines()[0])
    add_arguments(_parser)
    sys.exit(run(_parser.parse_args()))
