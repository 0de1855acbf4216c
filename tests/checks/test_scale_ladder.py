"""scripts/scale_ladder.py: the ladder's budget rule, the paper's deltas beside it, and that a call continues
the jobs an earlier one recorded (the GPU issue's resumable ladder), with the commands stubbed."""

from __future__ import annotations

import importlib.util
import json
import subprocess
from pathlib import Path

import pytest

from egobench.report import paper_numbers as pn

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "scale_ladder.py"
spec = importlib.util.spec_from_file_location("scale_ladder", SCRIPT)
ladder = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ladder)


def test_the_budget_keeps_a_gaussians_travel_and_the_gaussians_per_pixel_of_128_px():
    assert ladder.budget(128) == (1000, 8000)
    assert ladder.budget(256) == (2000, 32000) and ladder.budget(1024) == (8000, 512000)


def test_the_paper_delta_is_the_mean_over_its_table1_scenes_of_the_kind():
    ours = [pn.TABLE1_INDOOR.value("ours", c, pn.PSNR) for c in pn.TABLE1_INDOOR_SCENES]
    viba = [pn.TABLE1_INDOOR.value("no_viba", c, pn.PSNR) for c in pn.TABLE1_INDOOR_SCENES]
    assert ladder.paper_delta("indoor", "no_viba") == pytest.approx((sum(ours) - sum(viba)) / 6)
    assert ladder.paper_delta("indoor", "no_viba") == pytest.approx(1.1066667, abs=1e-6)


def _stub(monkeypatch, calls: list, fail: str = ""):
    def egobench(*args, log):
        calls.append(args[0])
        if args[0] == "simulate":
            out = Path(args[args.index("--out") + 1])
            out.mkdir(parents=True)
            (out / "recording.json").write_text("{}")
        elif args[0] == "train":
            run = Path(args[args.index("--out") + 1])
            if run.name == fail:
                raise subprocess.CalledProcessError(3, "egobench train")
            run.mkdir(parents=True, exist_ok=True)
            (run / "train.json").write_text(json.dumps({"train": {"time_s": 10.0, "num_gaussians": 321,
                                                                  "device": "cpu", "backend": "cpu"}}))
        elif args[0] == "evaluate":
            run = Path(args[args.index("--run") + 1])
            rung = int(run.name.split("_")[1])
            psnr = 25.0 + rung / 100 + (0.5 if run.name.endswith("_ours") else 0.0)
            (run / "eval.json").write_text(json.dumps({"metrics": {"psnr": psnr},
                                                       "fidelity": {"resolved_wavelength_px": 8.0}}))
    monkeypatch.setattr(ladder, "_egobench", egobench)


def _jobs(out: Path) -> list[tuple]:
    return [(r["kind"], int(r["rung"]), r["method"]) for r in ladder.read_rows(out / "ladder.csv")]


def test_a_call_starts_only_the_jobs_its_budget_fits_and_the_next_continues(monkeypatch, tmp_path):
    calls: list = []
    _stub(monkeypatch, calls)
    out = tmp_path / "out"
    args = ["--out", str(out), "--top", "64", "--rungs", "32,64", "--frames", "16", "--device", "cpu"]
    clock = iter(10.0 * k for k in range(100))  # 10 s a loop
    monkeypatch.setattr(ladder.time, "perf_counter", lambda: next(clock))
    # each job trains 10 s: a 32 px job needs 10 + 60 s, a 64 px one 10 x 8 + 60 = 140 s, with 130 s left at the 7th
    assert ladder.main([*args, "--work", str(tmp_path / "w1"), "--budget-s", "200"]) == 0
    assert _jobs(out) == [(k, 32, m) for k in ladder.KINDS for m in ladder.METHODS]
    assert calls.count("simulate") == 2 and calls.count("train") == 6
    calls.clear()  # a fresh machine: the work folder is gone, the records are committed
    assert ladder.main([*args, "--work", str(tmp_path / "w2")]) == 0
    assert len(_jobs(out)) == 12 and calls.count("train") == 6 and calls.count("simulate") == 2
    row = ladder.read_rows(out / "ladder.csv")[-1]
    assert (row["train_s"], row["gaussians"], row["backend"], row["top"], row["frames"]) == ("10.0", "321", "cpu", "64", "16")
    md = (out / "ladder.md").read_text()
    assert "| outdoor | 64 | 500 | 2000 | 26.14 | 8.0 | +0.50 (+1.09) | +0.50 (+" in md
    with pytest.raises(SystemExit, match=r"not \(128, 16\)"):  # jobs on other recordings are not mixed in
        ladder.main(["--out", str(out), "--work", str(tmp_path / "w3"), "--top", "128", "--rungs", "64", "--frames", "16"])


def test_a_failed_job_is_left_out_and_the_others_run(monkeypatch, tmp_path):
    calls: list = []
    _stub(monkeypatch, calls, fail="indoor_32_no_viba")
    out = tmp_path / "out"
    assert ladder.main(["--out", str(out), "--work", str(tmp_path / "w"), "--top", "32", "--rungs", "32"]) == 1
    assert _jobs(out) == [(k, 32, m) for k in ladder.KINDS for m in ladder.METHODS][:-1]


def test_the_table_is_written_when_no_job_runs(tmp_path):
    assert ladder.main(["--out", str(tmp_path), "--work", str(tmp_path / "w"), "--budget-s", "1"]) == 0
    assert (tmp_path / "ladder.md").read_text().count("\n") == 4 and not (tmp_path / "ladder.csv").exists()


def test_records_of_another_layout_are_refused(tmp_path):
    (tmp_path / "ladder.csv").write_text("kind,rung\noutdoor,128\n")
    with pytest.raises(SystemExit, match="ladder.csv: columns"):
        ladder.read_rows(tmp_path / "ladder.csv")
