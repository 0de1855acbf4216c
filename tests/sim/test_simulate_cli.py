"""`egobench simulate`: the verb, overrides, clear errors, atomic output."""

from __future__ import annotations

import json

import pytest

from egobench.cli import main


def test_simulate_verb_writes_a_loadable_recording(tmp_path, capsys):
    out = tmp_path / "quest"
    rc = main(["simulate", "--kind", "quest3", "--out", str(out), "--seed", "1", "--frames", "3",
               "--set", "rectified_size=24", "--set", "n_semidense_points=500", "--set", "jpeg=true", "--no-progress"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 3
    from egobench.data import load_recording

    rec = load_recording(out, "factory")
    assert rec.meta["device"] == "quest3" and rec.meta["sim_config"]["jpeg"] is True
    assert rec.camera.width == 24 and len(rec.frames) == 3
    # 30 fps device: frames 33.3 ms apart
    dt = rec.frames[1].read_start_ns - rec.frames[0].read_start_ns
    assert abs(dt - 1e9 / 30) <= 1


def test_bad_override_is_a_clear_error_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "bad"
    rc = main(["simulate", "--kind", "indoor", "--out", str(out), "--set", "exposure_s=-0.001"])
    assert rc == 2
    assert "SimConfig.exposure_s" in capsys.readouterr().err
    rc = main(["simulate", "--kind", "indoor", "--out", str(out), "--set", "nonsense"])
    assert rc == 2
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_failure_midway_leaves_no_half_written_output(tmp_path, monkeypatch):
    import egobench.data.transforms as transforms
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    calls = {"n": 0}
    real = transforms.write_sparse_depth

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(transforms, "write_sparse_depth", flaky)
    out = tmp_path / "rec"
    cfg = SimConfig.from_overrides("outdoor", 0, {"n_frames": 3, "rectified_size": 16, "n_semidense_points": 200})
    with pytest.raises(RuntimeError, match="disk full"):
        simulate_recording(cfg, out, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_simulation_is_deterministic(tmp_path):
    import filecmp

    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    cfg = SimConfig.from_overrides("indoor", 4, {"n_frames": 2, "rectified_size": 16, "n_semidense_points": 300})
    a, b = tmp_path / "a", tmp_path / "b"
    simulate_recording(cfg, a, progress=False)
    simulate_recording(cfg, b, progress=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) > 20
    differ = [str(f) for f in files if f.name != "recording.json" and not filecmp.cmp(a / f, b / f, shallow=False)]
    assert differ == []
