"""egobench.workflow.slurm_report: SLURM jobs of a run from the executor plugin's logs and sacct rows.

The sacct rows and the slurmstepd message are copied from a real single-node SLURM 22.05
(scripts/slurm_local.sh): job 12 was a `simulate` job killed over a 300 MB request.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from egobench import cli
from egobench.workflow import slurm_report as sr

SACCT = """\
12|FAILED|0:9|300M||00:00:04
12.batch|CANCELLED by 0|0:9||305M|00:00:04
13|COMPLETED|0:0|2000M||00:00:12
13.batch|COMPLETED|0:0||528596K|00:00:12
13.0|COMPLETED|0:0||1200K|00:00:01
14|COMPLETED|0:0|100M||00:00:09
14.batch|COMPLETED|0:0||204800K|00:00:09
"""
KILL_LOG = (
    "slurmstepd-vm: error: StepId=12.batch exceeded memory limit (319815680 > 314572800), being killed\n"
    "slurmstepd-vm: error: Exceeded job memory limit\n"
)


def _logs(root: Path) -> Path:
    logdir = root / "logs" / "slurm"
    files = {
        "rule_simulate/outdoor_0/12.log": KILL_LOG,
        "rule_train/outdoor_0_ours_0/13.log": "host: vm\n",
        "rule_tables/14.log": "",
        "group_g1/15.log": "",
        "rule_train/outdoor_0_ours_0/notes.log": "",  # not a job log: no numeric id
        "stray/16.log": "",  # not the plugin's layout
    }
    for rel, text in files.items():
        (logdir / rel).parent.mkdir(parents=True, exist_ok=True)
        (logdir / rel).write_text(text)
    return logdir


@pytest.mark.parametrize("text, mb", [("2000M", 2000.0), ("322384K", 322384 / 1024), ("1.5G", 1536.0),
                                      ("2000Mn", 2000.0), ("4Gc", 4096.0), ("7", 7.0), ("", None), ("n/a", None)])
def test_parse_mem_mb(text, mb):
    assert sr.parse_mem_mb(text) == mb


def test_parse_sacct_takes_request_from_the_job_and_peak_from_its_steps():
    jobs = sr.parse_sacct(SACCT)
    assert jobs["12"] == {"state": "FAILED", "exit_code": "0:9", "req_mem_mb": 300.0, "max_rss_mb": 305.0}
    assert jobs["13"]["req_mem_mb"] == 2000.0 and jobs["13"]["max_rss_mb"] == pytest.approx(528596 / 1024)
    assert jobs["14"]["state"] == "COMPLETED" and jobs["14"]["max_rss_mb"] == 200.0


def test_logged_jobs_reads_rule_wildcards_and_id_from_the_plugin_layout(tmp_path):
    logdir = _logs(tmp_path)
    found = sr.logged_jobs(logdir)
    assert [(j, r, w) for j, r, w, _ in found] == [
        ("12", "simulate", "outdoor_0"), ("13", "train", "outdoor_0_ours_0"), ("14", "tables", ""), ("15", "g1", "")]
    old = logdir / "rule_simulate" / "outdoor_0" / "12.log"
    os.utime(old, (1000.0, 1000.0))
    assert [j for j, *_ in sr.logged_jobs(logdir, since=2000.0)] == ["13", "14", "15"]


def test_memory_report_names_rule_request_and_use(tmp_path):
    jobs = {j.job_id: j for j in sr.collect(_logs(tmp_path), sacct_text=SACCT)}
    killed, fine, unenforced, unknown = jobs["12"], jobs["13"], jobs["14"], jobs["15"]
    assert killed.over_memory and killed.failed and killed.killed_rss_mb == pytest.approx(319815680 / 2**20)
    assert not fine.over_memory and not fine.failed
    assert unenforced.over_memory and not unenforced.failed  # 200 MB used of 100 MB, not killed
    assert not unknown.over_memory and unknown.state == "UNKNOWN"  # no sacct row
    report = sr.memory_report(list(jobs.values())).splitlines()
    assert len(report) == 2
    assert report[0].startswith("rule simulate [outdoor_0]: SLURM job 12 FAILED, over its memory request: "
                                "requested 300 MB, used 305 MB (killed by SLURM); log ")
    assert report[1].startswith("rule tables: SLURM job 14 COMPLETED, over its memory request: "
                                "requested 100 MB, used 200 MB; log ")


def test_report_failed_run_only_for_the_slurm_executor(tmp_path):
    class LocalSettings:  # the local executor's settings have no logdir
        pass

    class SlurmSettings:
        logdir = None  # the plugin's default, .snakemake/slurm_logs

    assert sr.report_failed_run(None, tmp_path, 0.0) == ""
    assert sr.report_failed_run(LocalSettings(), tmp_path, 0.0) == ""
    assert sr.report_failed_run(SlurmSettings(), tmp_path, 0.0) == ""  # no log folder: nothing ran


def test_cli_names_a_missing_logdir(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert cli.main(["slurm-report", "--logdir", str(missing)]) == 2
    assert f"--logdir {missing}: no such folder" in capsys.readouterr().err
    assert cli.main(["slurm-report", "--logdir", str(tmp_path), "--since", "yesterday"]) == 2
    assert "--since: 'yesterday' is not an ISO date/time" in capsys.readouterr().err
