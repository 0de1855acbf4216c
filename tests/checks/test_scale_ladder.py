"""scripts/scale_ladder.py: the ladder's budget rule, the paper's deltas beside it, and that a call continues
the jobs an earlier one recorded (the GPU issue's resumable ladder), with the commands stubbed."""

from __future__ import annotations

import importlib.util
import json
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


def _stub(monkeypatch, calls: list):
    def egobench(*args, log):
        calls.append(args[0])
        if args[0] == "simulate":
            out = Path(args[args.index("--out") + 1])
            out.mkdir(parents=True)
            (out / "recording.json").write_text("{}")
        elif args[0] == "train":
            Path(args[args.index("--out") + 1]).mkdir(parents=True, exist_ok=True)
        elif args[0] == "evaluate":
            run = Path(args[args.index("--run") + 1])
            rung = int(run.name.split("_")[1])
            psnr = 25.0 + rung / 100 + (0.5 if run.name.endswith("_ours") else 0.0)
            (run / "eval.json").write_text(json.dumps({"metrics": {"psnr": psnr},
                                                       "fidelity": {"resolved_wavelength_px": 8.0}}))
    monkeypatch.setattr(ladder, "_egobench", egobench)


def test_a_call_records_each_job_and_the_next_continues_where_it_stopped(monkeypatch, tmp_path):
    calls: list = []
    _stub(monkeypatch, calls)
    args = ["--out", str(tmp_path / "out"), "--work", str(tmp_path / "w1"), "--top", "64", "--rungs", "32,64",
            "--device", "cpu"]
    clock = iter([0.0] + [10.0 * k for k in range(1, 100)])
    monkeypatch.setattr(ladder.time, "perf_counter", lambda: next(clock))
    assert ladder.main([*args, "--budget-s", "175"]) == 0  # 60 s must be left to start a job (a job: 30 s): 4 of 12 run
    rows = ladder.read_rows(tmp_path / "out" / "ladder.csv")
    assert [(r["kind"], r["rung"], r["method"]) for r in rows] == [
        ("outdoor", "32", "ours"), ("outdoor", "32", "no_motion_sampling"), ("outdoor", "32", "no_viba"),
        ("indoor", "32", "ours")]
    assert calls.count("simulate") == 2 and calls.count("train") == 4
    calls.clear()
    args[3] = str(tmp_path / "w2")  # a fresh machine: the work folder is gone, the records are committed
    assert ladder.main(args) == 0
    rows = ladder.read_rows(tmp_path / "out" / "ladder.csv")
    assert len(rows) == 12 and calls.count("train") == 8 and calls.count("simulate") == 2
    md = (tmp_path / "out" / "ladder.md").read_text()
    assert "| outdoor | 64 | 500 | 2000 | 26.14 | 8.0 | +0.50 (+1.09) | +0.50 (+" in md


def test_records_of_another_layout_are_refused(tmp_path):
    (tmp_path / "ladder.csv").write_text("kind,rung\noutdoor,128\n")
    with pytest.raises(SystemExit, match="ladder.csv: columns"):
        ladder.read_rows(tmp_path / "ladder.csv")
