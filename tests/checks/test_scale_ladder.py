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
            assert "readout_s=0.01626" in args  # Aria's readout at every size, not the simulator's row-scaled one
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
            ours = run.name.endswith("_ours")
            psnr = 25.0 + rung / 100 + (0.5 if ours else 0.0)
            spread = 0.1 if ours else 0.0  # 'ours' - ablation: +0.4 on frame 0, +0.6 on frame 8
            per_image = [{"frame": 0, "psnr": psnr - spread}, {"frame": 8, "psnr": psnr + spread}]
            (run / "eval.json").write_text(json.dumps({"metrics": {"psnr": psnr}, "per_image": per_image,
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
    # the frames' paired differences +0.4 and +0.6: mean +0.5, sem 0.1, t(0.975, 1) = 12.706
    assert "| outdoor | 64 | 500 | 321 (2000) | 26.14 | 8.0 | +0.50 [-0.77, +1.77] (+1.09) | +0.50 [-0.77, +1.77] (+" in md
    # t = 0.5 / 0.1 = 5 on 1 degree of freedom: p 0.063 each, none below 0.05 before or after Holm over the 8
    assert "Holm over the 8 deltas tested (0 identical, not tested; one-sided paired t over the held-out frames, " \
           "in the paper's direction): 0 below" in md
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
    md = (tmp_path / "ladder.md").read_text()
    assert md.count("\n") == 6 and "Holm over the 0 deltas tested" in md and not (tmp_path / "ladder.csv").exists()


def test_records_of_another_layout_are_refused(tmp_path):
    (tmp_path / "ladder.csv").write_text("kind,rung\noutdoor,128\n")
    with pytest.raises(SystemExit, match="ladder.csv: columns"):
        ladder.read_rows(tmp_path / "ladder.csv")


def test_a_delta_pairs_the_frames_and_refuses_runs_on_different_frames():
    ours = {"kind": "indoor", "rung": "128", "method": "ours", "held_out_psnr": "26.0",
            "held_out_psnr_by_frame": "0:25.0 8:27.0 16:26.0"}
    other = dict(ours, method="no_viba", held_out_psnr="25.0", held_out_psnr_by_frame="16:25.0 0:24.5 8:25.5")
    # differences +0.5, +1.5, +1.0 (frames 0, 8, 16): mean +1.0, sem 0.2887, t(0.975, 2) = 4.303
    assert ladder.delta_cell(ours, other) == "+1.00 [-0.24, +2.24]"
    # t = 1.0 / 0.2887 = 3.46 on 2 degrees of freedom: one-sided p 0.037, the only delta
    assert ladder.holm_line([ours, other]).endswith("1 below 0.05.")
    assert ladder.holm_line([ours, dict(other, held_out_psnr_by_frame="0:24.5 8:28.0 16:25.0")]).endswith("0 below 0.05.")
    assert ladder.delta_cell(ours, dict(ours, method="no_motion_sampling")) == "identical"
    with pytest.raises(SystemExit, match="different held-out frames"):
        ladder.delta_cell(ours, dict(other, held_out_psnr_by_frame="0:24.5 8:25.5"))


def test_the_trend_fits_each_frames_delta_against_log2_rung_and_reads_it_at_the_papers_size():
    def row(rung, method, frames):
        return {"kind": "indoor", "rung": str(rung), "method": method,
                "held_out_psnr_by_frame": " ".join(f"{f}:{v}" for f, v in frames.items())}

    rows = [row(256, "ours", {0: 26.0, 8: 27.0}), row(256, "no_viba", {0: 25.5, 8: 25.5}),
            row(512, "ours", {0: 27.0, 8: 28.0}), row(512, "no_viba", {0: 26.0, 8: 25.5}),
            row(1024, "ours", {0: 27.0, 8: 28.0}), row(1024, "no_viba", {0: 26.5, 8: 24.5})]
    # deltas at 256, 512, 1024 px: frame 0 +0.5, +1.0, +0.5; frame 8 +1.5, +2.5, +3.5 (x = 0, 1, 2 doublings).
    # Least squares: frame 0 slope 0, intercept 2/3; frame 8 slope +1.0, intercept +1.5 -> slopes mean +0.5, sem 0.5,
    # t(0.975, 1) = 12.706. At 2400 px, log2(2400 / 256) = 3.2288 doublings on: +0.667 and +4.729
    (line,) = ladder.trend_lines(rows)
    assert line.startswith("- indoor, ours - no_viba over 256, 512, 1024 px: per doubling +0.50 [-5.85, +6.85]; "
                           "at 2400 px +2.70 [-23.11, +28.51] (paper +1.11)")
    assert ladder.trend_lines(rows[:2]) == []  # one rung: no line
    same = [dict(r, method="no_viba") if r["method"] == "no_viba" else r for r in rows[::2]]
    same += [dict(r, method="no_viba") for r in rows[::2]]
    assert ladder.trend_lines(same) == ["- indoor, ours - no_viba over 256, 512, 1024 px: identical at every rung"]


def test_holm_leaves_identical_deltas_out_and_tests_in_the_papers_direction():
    def pair(kind, rung, a, diffs):
        frames = " ".join(f"{8 * i}:30.0" for i in range(len(diffs)))
        other = " ".join(f"{8 * i}:{30.0 - d}" for i, d in enumerate(diffs))
        return [{"kind": kind, "rung": str(rung), "method": "ours", "held_out_psnr_by_frame": frames},
                {"kind": kind, "rung": str(rung), "method": a, "held_out_psnr_by_frame": other}]

    # +1.0 over 6 frames, sd 0.14: t = 17.3 on 5 df, one-sided p 5.9e-6; against the paper's direction p = 1
    gain = [0.8, 1.2, 0.9, 1.1, 1.0, 1.0]
    rows = pair("indoor", 128, "no_viba", gain) + pair("indoor", 128, "no_motion_sampling", [0.0] * 6)
    assert ladder.holm_line(rows).startswith("Holm over the 1 deltas tested (1 identical, not tested;")
    assert ladder.holm_line(rows).endswith("1 below 0.05.")
    loss = pair("indoor", 128, "no_viba", [-d for d in gain])
    assert ladder.holm_line(loss).endswith("0 below 0.05.")  # one-sided: a loss is not a finding in the paper's direction
    # raw p 0.042 (t = 2.15 on 5 df) is below 0.05 alone, and above it times 4 after Holm
    weak = [1.0, 0.0, 2.0, 1.0, -0.5, 2.5]
    assert ladder.holm_line(pair("indoor", 128, "no_viba", weak)).endswith("1 below 0.05.")
    four = pair("indoor", 128, "no_viba", weak) + pair("indoor", 256, "no_viba", weak) + \
        pair("outdoor", 128, "no_viba", weak) + pair("outdoor", 256, "no_viba", weak)
    assert ladder.holm_line(four).endswith("0 below 0.05.")


def test_recordings_are_cast_on_the_gpu_the_ladder_trains_on(monkeypatch, tmp_path):
    seen = []
    monkeypatch.setattr(ladder, "_egobench", lambda *args, log: seen.append(args))
    ladder.recording(tmp_path / "w", tmp_path / "logs", "indoor", 64, 8, "cuda")
    ladder.recording(tmp_path / "w", tmp_path / "logs", "outdoor", 64, 8, "cpu")
    assert "compute_device=cuda" in seen[0] and not any("compute_device" in a for a in seen[1])
