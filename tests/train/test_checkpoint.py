"""Checkpoints are read with weights_only=True; bad files give one named line, never run code."""

from __future__ import annotations

import pytest
import torch

from egobench.train.checkpoint import read_checkpoint


class _Payload:
    """Unpickling this calls open(marker, "w"): the file appears only if pickled code runs."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_checkpoint_with_code_is_refused_and_the_code_never_runs(tmp_path):
    marker = tmp_path / "code_ran"
    path = tmp_path / "checkpoint.pt"
    torch.save({"format": 1, "params": {"means": torch.zeros(2, 3)}, "evil": _Payload(marker)}, path)
    with pytest.raises(ValueError, match=r"checkpoint\.pt: unreadable checkpoint: .*refused") as info:
        read_checkpoint(path)
    assert not marker.exists()
    assert "\n" not in str(info.value)


def test_round_trip_of_plain_state(tmp_path):
    path = tmp_path / "ck.pt"
    state = {"params": {"means": torch.arange(6.0).reshape(2, 3)}, "rng": torch.get_rng_state(), "it": 7,
             "config": {"lr": 1e-3, "name": "x"}, "order": [3, 1]}
    torch.save(state, path)
    back = read_checkpoint(path)
    assert torch.equal(back["params"]["means"], state["params"]["means"]) and back["it"] == 7
    assert back["config"] == state["config"] and back["order"] == [3, 1]


@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", None])
def test_corrupt_checkpoint_is_one_named_line_in_the_cli(tmp_path, capsys, content):
    from egobench.cli import main

    run = tmp_path / "run"
    run.mkdir()
    path = run / "checkpoint.pt"
    if content is None:  # a real checkpoint cut in half (an interrupted copy)
        torch.save({"params": {"means": torch.zeros(1000, 3)}}, path)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        path.write_bytes(content)
    rc = main(["evaluate", "--recording", str(tmp_path / "rec"), "--run", str(run)])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.count("\n") == 0 and "Traceback" not in err
    assert err.startswith(f"egobench evaluate: error: {path}: unreadable checkpoint")


def test_resume_auto_starts_afresh_on_a_corrupt_checkpoint(tmp_path, capsys):
    from egobench.sim.plane import plane_recording
    from egobench.train import TrainConfig, train

    rec = plane_recording(tmp_path / "toy", size=16, n_frames=9, n_points=300)
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"garbage")
    res = train(rec, "ours", TrainConfig.cpu().scaled_to(3), out, resume="auto", progress=False)
    assert res.iterations == 3
    assert "unreadable checkpoint" in capsys.readouterr().err
    assert read_checkpoint(out / "checkpoint.pt")["iteration"] == 3
