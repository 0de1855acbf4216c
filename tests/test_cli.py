"""The `egobench` command line: every verb registered as a subcommand, no global state."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from egobench import cli
from egobench.sim.plane import plane_recording


def test_every_verb_is_registered_with_its_own_arguments():
    parser = cli.build_parser()
    args = parser.parse_args(["evaluate", "--recording", "R", "--run", "X"])
    assert (args.verb, args.recording, args.run) == ("evaluate", "R", "X")
    args = parser.parse_args(["train", "--recording", "R", "--method", "ours", "--out", "O", "--preset", "paper"])
    assert (args.verb, args.preset, args.set) == ("train", "paper", [])
    args = parser.parse_args(["diagnose", "REC", "--out", "D", "--train", "--iterations", "5"])
    assert (args.verb, args.recording, args.train, args.iterations, args.preset) == ("diagnose", "REC", True, 5, "cpu")
    subparsers = next(a for a in parser._actions if a.dest == "verb").choices
    assert set(subparsers) == set(cli.VERBS)
    for verb, (module_name, _) in cli.VERBS.items():
        assert subparsers[verb].get_default("_run").__module__ == module_name


def test_main_leaves_sys_argv_alone_and_reports_user_errors(tmp_path, capsys):
    before = list(sys.argv)
    code = cli.main(["evaluate", "--recording", str(tmp_path / "missing"), "--run", str(tmp_path)])
    assert code == 2 and sys.argv == before
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("egobench evaluate: error: ") and "checkpoint.pt" in err[0]


def test_unknown_verb_is_rejected_by_argparse(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["simulat"])
    assert exc.value.code == 2 and "invalid choice: 'simulat'" in capsys.readouterr().err


def test_diagnose_train_uses_the_train_preset_at_full_resolution(tmp_path, monkeypatch):
    """--train starts from `egobench train`'s preset (cpu: its learning schedule, not 30K iterations),
    at the recording's full resolution (diagnosis compares full-resolution renders), and --no-progress
    reaches the trainer."""
    import egobench.train as train_pkg
    from egobench.diagnose import cli as dcli
    from egobench.train import TrainConfig

    seen = {}

    def fake_train(rec, method, config, run_dir, progress=True):
        seen.update(rec=rec, method=method, config=config, progress=progress)

    monkeypatch.setattr(train_pkg, "train", fake_train)
    rec = plane_recording(tmp_path / "rec", size=16, n_frames=9, n_points=50).root
    args = cli.build_parser().parse_args(["diagnose", str(rec), "--out", str(tmp_path / "d"), "--train",
                                          "--method", "no_motion_sampling", "--iterations", "40", "--no-progress"])
    run_dir = dcli._train_for_diagnosis(args, Path(rec), tmp_path / "d")
    expected = TrainConfig.cpu(max_side=0).scaled_to(40)
    assert run_dir == tmp_path / "d" / "run" and seen["method"] == "no_motion_sampling"
    assert seen["config"] == expected and seen["progress"] is False


def test_a_verb_imports_only_its_own_module():
    """`egobench tables ...` must not pay for matplotlib (plots) or scipy.stats (diagnose): the parser
    registers only the called verb's arguments; every other verb keeps its name and help."""
    import subprocess

    code = ("import sys; from egobench import cli; p = cli.build_parser(only='tables'); "
            "print(sorted(m for m in ('egobench.report.plots', 'egobench.diagnose.core', 'egobench.report.tables') if m in sys.modules)); "
            "print(sorted(next(a for a in p._actions if a.dest == 'verb').choices) == sorted(cli.VERBS))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "['egobench.report.tables']" and out[1] == "True"
