"""scripts/independent_sweep.py: the tally of the diagnosis on the independent writer's recordings (what counts as
named, wrong, geometric, flagged), from a case's truth.json and diagnosis.json."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from egobench.diagnose.learned_frames import judge_learned_frames

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "independent_sweep.py"


def _load():
    spec = importlib.util.spec_from_file_location("independent_sweep", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


sweep = _load()


def _case(tmp_path: Path, name: str, altered: list[int], named: list[dict]) -> Path:
    case = tmp_path / name
    (case / "rec").mkdir(parents=True)
    (case / "diag").mkdir()
    (case / "rec" / "truth.json").write_text(json.dumps({"effects": {"exposure_altered_frames": altered}}))
    (case / "diag" / "diagnosis.json").write_text(json.dumps({"named": named, "psnr_gain_db": 0.1}))
    return case


def test_a_case_row_counts_names_flags_and_estimates(tmp_path):
    records = _case(tmp_path, "records", [3, 9, 17, 30], [
        {"name": "exposure_metadata", "params": {"flagged_frames": [3, 9, 12]}},
        {"name": "readout", "params": {"readout_s_estimated": 0.0125}},
        {"name": "time_offset", "params": {"time_offset_error_s": 0.0021}}])
    row = sweep.case_row("exposure_metadata", 401, records, {})
    assert row["expected_named"] and not row["wrong_first"] and row["geometric_named"]
    assert (row["flagged_altered"], row["flagged_wrong"]) == (2, 1)
    assert row["readout_s_estimated"] == 0.0125 and row["time_offset_s"] == 0.0021
    null = sweep.case_row("null", 101, _case(tmp_path, "null", [], [{"name": "readout", "params": {}}]), {})
    assert null["wrong_first"] and null["geometric_named"] and not null["expected_named"]
    quiet = sweep.case_row("null", 102, _case(tmp_path, "quiet", [], []), {})
    assert not quiet["named"] and not quiet["wrong_first"]
    # a time offset named with the (untestable) readout as its "or" on a readout case: contained, not wrong
    offset = [{"name": "time_offset", "params": {"or": [{"cause": "readout", "p_adjusted": None, "note": ""}]}}]
    contained = sweep.case_row("readout", 301, _case(tmp_path, "contained", [], offset), {})
    assert contained["contained_first"] and not contained["wrong_first"]
    elsewhere = sweep.case_row("time_offset", 501, _case(tmp_path, "offset", [], offset), {})
    assert not elsewhere["contained_first"] and not elsewhere["wrong_first"] and elsewhere["expected_named"]


def test_the_summary_applies_the_issues_criteria():
    rows = [
        {"effect": "readout", "named": "readout", "expected_named": True, "wrong_first": False,
         "geometric_named": True, "readout_s_estimated": 0.0149},  # within 25 % of the true 12 ms
        {"effect": "readout", "named": "readout", "expected_named": True, "wrong_first": False,
         "geometric_named": True, "readout_s_estimated": 0.0151},  # 25.8 % off
        {"effect": "readout", "named": "", "expected_named": False, "wrong_first": False,
         "geometric_named": False, "readout_s_estimated": None},
        {"effect": "exposure_metadata", "named": "exposure_metadata", "expected_named": True, "wrong_first": False,
         "geometric_named": False, "altered_frames": "1 2 3 4", "flagged_altered": 2, "flagged_wrong": 2},
        {"effect": "exposure_metadata", "named": "exposure_metadata", "expected_named": True, "wrong_first": False,
         "geometric_named": False, "altered_frames": "1 2 3 4", "flagged_altered": 2, "flagged_wrong": 3},
    ]
    s = sweep.summary(rows)
    assert s["readout"] == {"cases": 3, "nothing_named": 1, "expected_named": 2, "wrong_first_name": 0,
                            "contained_first_name": 0, "geometric_named": 2, "estimate_within_25pct": 1, "at_least_twice_testable": 0,
                            "named_where_at_least_twice_testable": 0}
    assert s["exposure_metadata"]["half_altered_flagged_and_at_most_2_wrong"] == 1
    assert set(s) == {"readout", "exposure_metadata"}


@pytest.mark.parametrize("effect", sorted(sweep.CASES))
def test_every_effect_has_its_seeds_and_flags(effect):
    flags, expected, seeds = sweep.CASES[effect]
    assert len(seeds) == (20 if effect == "null" else 10)
    assert (expected is None) == (effect == "null") and (flags(0) == []) == (effect == "null")
    # a later seed set is the next block of as many seeds, disjoint from the first
    again = sweep.seeds_of(effect, 2)
    assert len(again) == len(seeds) and again.start == seeds.stop and sweep.seeds_of(effect, 1) == seeds


def test_the_power_tally_counts_cases_whose_hidden_size_is_at_least_twice_the_runs_smallest_testable():
    d = {"model_error": {"smallest_testable": {"time_offset": {"time_offset_error_s": 0.001}}}}
    assert sweep.smallest_testable_of("time_offset", d) == {"smallest_testable": 0.001, "at_least_twice_testable": True}
    d["model_error"]["smallest_testable"]["time_offset"]["time_offset_error_s"] = 0.002
    assert sweep.smallest_testable_of("time_offset", d)["at_least_twice_testable"] is False
    assert sweep.smallest_testable_of("readout", d) == {"smallest_testable": None, "at_least_twice_testable": False}
    assert sweep.smallest_testable_of("null", d) == {}
    rows = [{"effect": "time_offset", "named": n, "expected_named": bool(n), "wrong_first": False,
             "geometric_named": bool(n), "at_least_twice_testable": t} for n, t in
            (("time_offset", True), ("", True), ("", False))]
    s = sweep.summary(rows)["time_offset"]
    assert s["at_least_twice_testable"] == 2 and s["named_where_at_least_twice_testable"] == 1


def test_a_case_is_written_and_trained_at_the_size_asked(tmp_path, monkeypatch):
    """--size S: the writer writes S x S images and the training's max_side is S (the issue's 64 by default);
    --iterations N: the training's iterations (the issue's 800)."""
    commands = []

    def run(cmd, log, in_process=False):
        commands.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True)
        name = {"train": "train.json", "diagnose": "diagnosis.json"}.get(cmd[3], "truth.json")
        (out / name).write_text(json.dumps({"effects": {"exposure_altered_frames": []}, "named": []}))
        return 0.0

    monkeypatch.setattr(sweep, "_run", run)
    for size, iterations in ((sweep.ISSUE_SIZE, sweep.ISSUE_ITERATIONS), (128, 3000)):
        commands.clear()
        sweep.run_case(tmp_path / str(size), "readout", 1101, seed_set=81, size=size, iterations=iterations)
        write, train, _ = commands
        assert write[write.index("--size") + 1] == str(size) and "--readout-scale" in write
        assert train[train.index("--set") + 1] == f"max_side={size}"
        assert train[train.index("--iterations") + 1] == str(iterations)
    commands.clear()
    sweep.run_case(tmp_path / "fine", "readout", 1101, seed_set=81, size=256,
                   train_set=("pose_sample_step_px=0.25", "max_pose_samples=32"))
    train = commands[1]
    sets = [train[i + 1] for i, a in enumerate(train) if a == "--set"]
    assert sets == ["max_side=256", "pose_sample_step_px=0.25", "max_pose_samples=32"]


def test_an_egobench_stage_run_in_process_logs_fails_and_restores_the_threads_as_a_process_would(tmp_path, monkeypatch):
    """`_run(..., in_process=True)`: the egobench command runs here (no subprocess), on one torch and one kernel
    thread while it runs; its output goes to its log, a failure raises naming the log, argparse's exit is the status,
    and the process's torch threads and environment are as before, also after an exception."""
    import os

    import torch

    from egobench import host
    from egobench.diagnose import cli as diagnose_cli

    def no_subprocess(*args, **kwargs):
        raise AssertionError("an in-process stage started a process")

    monkeypatch.setattr(sweep.subprocess, "run", no_subprocess)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.delenv("EGOBENCH_RASTER_THREADS", raising=False)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    seen = {}

    def stub(args):
        seen.update(torch=torch.get_num_threads(), kernels=host.kernel_threads(), omp=os.environ["OMP_NUM_THREADS"])
        print("the stub ran")
        raise ValueError("the stub's error")

    monkeypatch.setattr(diagnose_cli, "run", stub)
    try:
        log = tmp_path / "diagnose.log"
        with pytest.raises(RuntimeError, match="diagnose.log"):
            sweep._run([*sweep.EGOBENCH, "diagnose", "rec", "--out", str(tmp_path / "d")], log, in_process=True)
        assert seen == {"torch": 1, "kernels": 1, "omp": "1"}
        assert "the stub ran" in log.read_text() and "egobench diagnose: error: the stub's error" in log.read_text()
        assert torch.get_num_threads() == 2 and os.environ["OMP_NUM_THREADS"] == "3"
        assert "EGOBENCH_RASTER_THREADS" not in os.environ
        with open(tmp_path / "help.log", "w") as fh:
            assert sweep._run_here(["tables", "--help"], fh) == 0
        with open(tmp_path / "bad.log", "w") as fh:
            assert sweep._run_here(["tables", "--no-such-flag"], fh) == 2
        assert "usage: egobench tables" in (tmp_path / "help.log").read_text()
    finally:
        torch.set_num_threads(threads)


def test_a_sweep_folder_keeps_the_conditions_of_its_cases(tmp_path):
    """A folder's cases are reused stage by stage, so a sweep at another size or iteration count into it stops."""
    sweep.claim_conditions(tmp_path, 128, 800)
    sweep.claim_conditions(tmp_path, 128, 800)  # the same conditions: resumes
    with pytest.raises(SystemExit, match="128"):
        sweep.claim_conditions(tmp_path, 256, 800)
    old = tmp_path / "old"
    (old / "cases").mkdir(parents=True)  # cases written before the stamp: the issue's conditions
    sweep.claim_conditions(old, sweep.ISSUE_SIZE, sweep.ISSUE_ITERATIONS)
    older = tmp_path / "older"
    (older / "cases").mkdir(parents=True)
    with pytest.raises(SystemExit, match="3000"):
        sweep.claim_conditions(older, 64, 3000)
    with pytest.raises(SystemExit, match="pose_sample_step_px"):  # the same size, another training
        sweep.claim_conditions(tmp_path, 128, 800, ("pose_sample_step_px=0.25",))
    with pytest.raises(SystemExit):  # a field the sweep sets itself is no training override
        sweep.main(["--out", str(tmp_path / "fixed"), "--train-set", "max_side=32"])
    assert not (tmp_path / "fixed").exists()


def test_a_sweep_run_one_effect_at_a_time_keeps_the_earlier_cases_rows(tmp_path):
    """cases.csv after `--only B` still holds the cases an earlier `--only A` into the same folder tallied (re-read
    from their folders, their stage times kept); a case this invocation ran, or one without a diagnosis, is not
    taken from the old table."""
    import csv

    cases = tmp_path / "cases"
    _case(cases, "readout_301", [], [{"name": "readout", "params": {"readout_s_estimated": 0.0115}}])
    _case(cases, "readout_302", [], [])
    (cases / "readout_303" / "rec").mkdir(parents=True)  # written, never diagnosed
    with open(tmp_path / "cases.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["effect", "seed", "named", "write_s", "train_s", "diagnose_s"])
        w.writeheader()
        w.writerows([{"effect": "readout", "seed": 301, "named": "stale", "write_s": "27.5", "train_s": "12.0",
                      "diagnose_s": "150.0"},
                     {"effect": "readout", "seed": 302, "named": "", "write_s": "", "train_s": "", "diagnose_s": ""},
                     {"effect": "readout", "seed": 303, "named": "", "write_s": "1", "train_s": "", "diagnose_s": ""}])
    rows = sweep.earlier_rows(tmp_path, {("readout", 302), ("null", 101)})
    assert [(r["effect"], r["seed"]) for r in rows] == [("readout", 301)]
    assert rows[0]["named"] == "readout" and rows[0]["readout_s_estimated"] == 0.0115  # from its folder, not the table
    assert (rows[0]["write_s"], rows[0]["train_s"], rows[0]["diagnose_s"]) == (27.5, 12.0, 150.0)
    assert sweep.earlier_rows(tmp_path / "fresh", set()) == []


def test_a_case_row_reads_the_lens_check_and_the_summary_counts_the_runs_a_lens_is_testable_on(tmp_path):
    case = _case(tmp_path, "lens", [], [])
    d = json.loads((case / "diag" / "diagnosis.json").read_text())
    d["model_error"] = {"lens_check": {"injected_k0": 0.09, "retention": 0.31, "testable": True}}
    (case / "diag" / "diagnosis.json").write_text(json.dumps(d))
    row = sweep.case_row("null", 101, case, {})
    assert (row["lens_injected_k0"], row["lens_retention"], row["lens_testable"]) == (0.09, 0.31, True)
    assert "lens_testable" not in sweep.case_row("null", 102, _case(tmp_path, "unchecked", [], []), {})
    rows = [dict(row), dict(row, lens_testable=False), dict(row, lens_testable=True)]  # as case_row makes them
    assert sweep.summary(rows)["null"]["lens_testable"] == 2


def test_the_round1_tests_table_reads_the_readout_and_both_lens_calibrations(tmp_path):
    case = _case(tmp_path, "readout_1181", [], [{"name": "readout", "params": {}}])
    d = json.loads((case / "diag" / "diagnosis.json").read_text())
    d["rounds"] = [[
        {"name": "readout", "statistic": 4.1, "p_adjusted": 0.004, "reason": "", "params": {"readout_s_estimated": 0.0103}},
        {"name": "distortion", "statistic": 2.5, "p_adjusted": 0.2, "significant": False, "testable": True, "reason": "",
         "params": {"k0_error": 0.03, "calibration": {"placebo_centre_t": [1.0, 2.0, 3.0]},
                    "calibration_radial": {"first_order_t": 5.9, "p_value_placebo": 0.001}}}]]
    d["model_error"] = {"lens_check": {"injected_k0": 0.12, "retention": None, "testable": False}}
    (case / "diag" / "diagnosis.json").write_text(json.dumps(d))
    row = sweep.round1_tests_row(case)
    assert (row["case"], row["named"], row["readout_t"], row["readout_s_estimated"]) == ("readout_1181", "readout", 4.1, 0.0103)
    assert (row["distortion_placebo_t_mean"], row["distortion_radial_t"], row["distortion_radial_p"]) == (2.0, 5.9, 0.001)
    assert (row["lens_injected_k0"], row["lens_retention"], row["lens_testable"]) == (0.12, None, False)
    assert sweep.round1_tests_row(tmp_path / "not_diagnosed") is None
    sweep.write_csv(tmp_path / "t.csv", [row, {"case": "x", "extra": 1}])
    assert (tmp_path / "t.csv").read_text().splitlines()[0].endswith(",extra")


def test_a_learned_timings_names_come_first_with_its_estimates(tmp_path):
    """A run trained with learn_timing: the diagnosis's learned_timing names (`judge_timing`) lead the case's names
    and give the timing estimates; a photometric name of the residual follows."""
    from egobench.diagnose.learned_timing import judge_timing

    from tests.diagnose.test_learned_timing import EVIDENCE

    case = _case(tmp_path, "timed", [], [{"name": "vignette", "params": {}}])
    d = json.loads((case / "diag" / "diagnosis.json").read_text())
    d["learned_timing"] = judge_timing({"time_offset_ms": 0.2, "readout_error_ms": 3.4}, 0.008, EVIDENCE)
    (case / "diag" / "diagnosis.json").write_text(json.dumps(d))
    row = sweep.case_row("readout", 301, case, {})
    assert row["named"] == "readout vignette" and row["first"] == "readout" and row["expected_named"]
    assert row["readout_s_estimated"] == 0.0114 and row["timing_named"] == "readout"
    assert (row["learned_time_offset_ms"], row["learned_readout_error_ms"]) == (0.2, 3.4)
    assert (row["learned_time_offset_t"], row["learned_readout_t"]) == pytest.approx((1.0, 6.8))
    plain = sweep.case_row("readout", 302, _case(tmp_path, "plain", [], []), {})
    assert "learned_readout_error_ms" not in plain and not plain["named"]


def test_a_timing_named_on_a_null_with_nothing_from_the_residual_is_a_wrong_first_name(tmp_path):
    from egobench.diagnose.learned_timing import judge_timing

    from tests.diagnose.test_learned_timing import EVIDENCE

    case = _case(tmp_path, "timed_null", [], [])
    d = json.loads((case / "diag" / "diagnosis.json").read_text())
    d["learned_timing"] = judge_timing({"time_offset_ms": 1.5, "readout_error_ms": 0.1}, 0.008, EVIDENCE)
    (case / "diag" / "diagnosis.json").write_text(json.dumps(d))
    row = sweep.case_row("null", 101, case, {})
    assert row["first"] == "time_offset" and row["wrong_first"] and not row["contained_first"]


def test_the_per_frame_exposures_names_follow_the_timings_and_give_the_flagged_frames(tmp_path):
    """A run trained with learn_frame_exposure: the names of its learned frames come after the learned timing's and
    before the residual's, and their flagged frames are the case's (the residual's own flags are not counted)."""
    case = _case(tmp_path, "frames", [3, 9, 17, 30], [
        {"name": "exposure_metadata", "params": {"flagged_frames": [5, 6, 7]}}, {"name": "vignette", "params": {}}])
    d = json.loads((case / "diag" / "diagnosis.json").read_text())
    values = [0.0] * 30 + [0.0]
    for f in (3, 9, 17):
        values[f] = -0.25
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "train.json").write_text(json.dumps({"learned_frame_exposure": {
        "frames": list(range(len(values))), "log_scale": values}}))
    d["learned_frames"] = judge_learned_frames(tmp_path / "run")
    (case / "diag" / "diagnosis.json").write_text(json.dumps(d))
    row = sweep.case_row("exposure_metadata", 401, case, {})
    assert row["named"] == "exposure_metadata vignette" and row["frames_named"] == "exposure_metadata"
    assert (row["flagged_altered"], row["flagged_wrong"]) == (3, 0) and not row["wrong_first"]
