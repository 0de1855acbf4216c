"""simulate_recording can be interrupted and resumed: the resumed recording is byte-identical to
an uninterrupted one; stale partial folders are discarded; half-written frames are redone."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from egobench.sim.config import SimConfig

N_FRAMES = 6
#: Tiny recordings (as in tests/sim/test_capture.py, smaller): "auto" exercises the smoothed auto-exposure,
#: raw frames, JPEG and exposure-metadata errors; "fixed" (object kind) the held exposure of the fixed protocol.
CONFIGS = {
    "auto": ("outdoor", 1, {"n_frames": N_FRAMES, "rectified_size": 24, "motion": "fast", "n_semidense_points": 500,
                            "write_raw": True, "jpeg": True, "exposure_metadata_error": 0.2,
                            "exposure_metadata_fraction": 0.5}),
    "fixed": ("object", 2, {"n_frames": N_FRAMES, "rectified_size": 24, "n_semidense_points": 500}),
}
#: Fields that are wall-clock timings (differ between any two runs); everything else must match bytewise.
TIMING_FIELDS = {"recording.json": ("simulation_time_s",)}


def _config(name: str, **extra) -> SimConfig:
    kind, seed, overrides = CONFIGS[name]
    return SimConfig.from_overrides(kind, seed, {**overrides, **extra})


def _on() -> str:
    """The online stream folder of the "fixed" config (the authors' naming)."""
    from egobench.sim.capture import stream_names

    return stream_names(_config("fixed"))["online"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Uninterrupted recordings, one per config: name -> folder."""
    from egobench.sim.capture import simulate_recording

    root = tmp_path_factory.mktemp("reference")
    out = {}
    for name in CONFIGS:
        out[name] = root / name
        simulate_recording(_config(name), out[name], progress=False)
    return out


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def assert_same_recording(a: Path, b: Path) -> None:
    """Same file set; every file bytewise equal, except timing fields (TIMING_FIELDS) removed first."""
    fa, fb = _files(a), _files(b)
    assert fa == fb, f"file sets differ: only in {a}: {sorted(set(fa) - set(fb))}, only in {b}: {sorted(set(fb) - set(fa))}"
    assert len(fa) > 20
    differ = []
    for rel in fa:
        ba, bb = (a / rel).read_bytes(), (b / rel).read_bytes()
        if str(rel) in TIMING_FIELDS:
            ja, jb = json.loads(ba), json.loads(bb)
            for key in TIMING_FIELDS[str(rel)]:
                assert isinstance(ja.pop(key), float) and isinstance(jb.pop(key), float)
            if ja != jb:
                differ.append(str(rel))
        elif ba != bb:
            differ.append(str(rel))
    assert differ == [], f"files differ between {a} and {b}: {differ}"


@pytest.mark.parametrize("name", list(CONFIGS))
def test_interrupted_twice_then_resumed_is_byte_identical(reference, tmp_path, name, capsys):
    from egobench.sim.capture import partial_dir, simulate_recording

    cfg = _config(name)
    out = tmp_path / "rec"
    part = partial_dir(out)
    assert part == tmp_path / ".rec.partial"
    r1 = simulate_recording(cfg, out, progress=False, stop_after=2)
    assert not r1.complete and r1.path == part and not out.exists()
    assert sorted(p.name for p in (part / ".resume").iterdir()) == ["00000.json", "00001.json", "partial.json"]
    assert len(r1.temporal_samples) == 2
    r2 = simulate_recording(cfg, out, progress=False, resume=True, stop_after=4)
    assert not r2.complete and r2.resumed_from == 2 and len(r2.temporal_samples) == 4
    for st in (part / ".resume").glob("0*.json"):
        assert st.stat().st_size < 16_000, "per-frame state should stay small"
    r3 = simulate_recording(cfg, out, progress=False, resume="auto")
    assert r3.complete and r3.path == out and r3.resumed_from == 4
    assert "resuming" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"], "partial or temporary folders left behind"
    assert_same_recording(reference[name], out)
    # the result summary covers every frame, also those of the earlier runs
    truth = json.loads((out / "ground_truth/truth.json").read_text())
    assert r3.temporal_samples == [f["temporal_samples"] for f in truth["frames"]]
    assert r3.gains == [f["gain"] for f in truth["frames"]]
    assert json.loads((out / "recording.json").read_text())["simulation_time_s"] >= r2.time_s


def test_the_resumed_run_uses_the_saved_noise_state(reference, tmp_path):
    """Negative control: replacing the saved generator state by the initial one changes the resumed
    images (so the byte-identity above is due to the restored state, not to luck)."""
    import torch

    from egobench.sim.capture import partial_dir, simulate_recording
    from egobench.sim.capture.resume import encode_generator

    cfg = _config("fixed")
    out = tmp_path / "rec"
    simulate_recording(cfg, out, progress=False, stop_after=3)
    st_path = partial_dir(out) / ".resume" / "00002.json"
    st = json.loads(st_path.read_text())
    st["noise_generator"] = encode_generator(torch.Generator().manual_seed(int(cfg.seed) * 7919 + 17))
    st_path.write_text(json.dumps(st))
    simulate_recording(cfg, out, progress=False, resume=True)
    same = [(out / f"{_on()}/images/{k:05d}.png").read_bytes() == (reference["fixed"] / f"{_on()}/images/{k:05d}.png").read_bytes()
            for k in range(N_FRAMES)]
    assert same == [True, True, True, False, False, False]


def test_half_written_frame_is_redone(reference, tmp_path):
    """An interruption inside frame 3 (KeyboardInterrupt after some of its files) keeps the partial
    folder under resume="auto"; frame 3's files (here also corrupted), a stray later frame and
    leftover temporary files are replaced/removed by the resumed run."""
    import egobench.data.transforms as transforms
    from egobench.sim.capture import partial_dir, simulate_recording

    cfg = _config("fixed")
    out = tmp_path / "rec"
    part = partial_dir(out)
    real = transforms.write_sparse_depth
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2 * 3 + 2:  # frame 3, factory calibration: online files of frame 3 already written
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    transforms.write_sparse_depth = interrupted
    try:
        with pytest.raises(KeyboardInterrupt):
            simulate_recording(cfg, out, progress=False, resume="auto")
    finally:
        transforms.write_sparse_depth = real
    assert not out.exists() and part.is_dir()
    assert (part / _on() / "images/00003.png").is_file() and (part / _on() / "sparse_depth/00003.json").is_file()
    assert not (part / ".resume/00003.json").exists()
    # make the half-written frame visibly wrong, and add debris an interruption could leave
    (part / _on() / "images/00003.png").write_bytes(b"\x89PNG truncated")
    (part / _on() / "sparse_depth/00003.json").write_text('{"u": [1.0, 2')
    np.save(part / "ground_truth/depth/00003.npy", np.zeros((2, 2), np.float16))
    np.save(part / "ground_truth/depth/00009.npy", np.zeros((2, 2), np.float16))  # beyond n_frames
    (part / _on() / "images/.00004.png.x1y2.tmp.png").write_bytes(b"partial")
    (part / ".resume/.00003.json.abcd.tmp.json").write_text("{")
    result = simulate_recording(cfg, out, progress=False, resume="auto")
    assert result.resumed_from == 3 and result.complete
    assert_same_recording(reference["fixed"], out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def test_stale_partial_of_another_config_is_discarded(reference, tmp_path, capsys):
    from egobench.sim.capture import partial_dir, simulate_recording

    out = tmp_path / "rec"
    part = partial_dir(out)
    other = _config("fixed", noise_std_factor=2.0)
    simulate_recording(other, out, progress=False, stop_after=2)
    cfg = _config("fixed")
    # strict resume refuses (and keeps the partial folder); auto discards it and starts afresh
    with pytest.raises(ValueError, match="different SimConfig"):
        simulate_recording(cfg, out, progress=False, resume=True)
    assert (part / ".resume/00001.json").is_file()
    capsys.readouterr()
    result = simulate_recording(cfg, out, progress=False, resume="auto")
    err = capsys.readouterr().err
    assert "discarding the partial recording" in err and "different SimConfig" in err
    assert result.resumed_from == 0
    assert_same_recording(reference["fixed"], out)
    # no partial folder: strict resume is an error, auto starts afresh
    with pytest.raises(FileNotFoundError, match="no partial recording"):
        simulate_recording(cfg, tmp_path / "other", progress=False, resume=True)
    # a partial folder without a manifest (interrupted before it was written) is discarded too
    (tmp_path / ".bare.partial" / _on()).mkdir(parents=True)
    r = simulate_recording(cfg, tmp_path / "bare", progress=False, resume="auto", stop_after=1)
    assert r.resumed_from == 0 and "no readable manifest" in capsys.readouterr().err


def test_resume_off_discards_the_partial_and_cleans_up_on_failure(tmp_path, capsys):
    import egobench.data.transforms as transforms
    from egobench.sim.capture import partial_dir, simulate_recording

    cfg = _config("fixed")
    out = tmp_path / "rec"
    simulate_recording(cfg, out, progress=False, stop_after=2)
    real = transforms.write_sparse_depth

    def failing(*args, **kwargs):
        raise RuntimeError("disk full (simulated)")

    transforms.write_sparse_depth = failing
    try:
        with pytest.raises(RuntimeError, match="disk full"):
            simulate_recording(cfg, out, progress=False)  # resume=False: starts afresh, leaves nothing
    finally:
        transforms.write_sparse_depth = real
    assert "resume is off" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [] and not partial_dir(out).exists()


def test_config_hash_and_argument_checks(monkeypatch, tmp_path):
    import egobench
    from egobench.sim.capture import sim_config_hash, simulate_recording

    h = sim_config_hash(_config("fixed"))
    assert h == sim_config_hash(_config("fixed")) and len(h) == 40
    assert h != sim_config_hash(_config("fixed", n_frames=N_FRAMES + 1))
    monkeypatch.setattr(egobench, "__version__", "999.0")
    assert h != sim_config_hash(_config("fixed"))
    with pytest.raises(ValueError, match="resume"):
        simulate_recording(_config("fixed"), tmp_path / "x", resume="yes")
    with pytest.raises(ValueError, match="stop_after"):
        simulate_recording(_config("fixed"), tmp_path / "x", stop_after=-1)
    assert list(tmp_path.iterdir()) == []


def test_cli_resumes_by_default_and_no_resume_starts_afresh(tmp_path, capsys):
    from egobench.cli import main
    from egobench.sim.capture import simulate_recording

    args = ["simulate", "--kind", "quest3", "--out", str(tmp_path / "q"), "--seed", "1", "--frames", "3",
            "--set", "rectified_size=16", "--set", "n_semidense_points=300", "--no-progress"]
    cfg = SimConfig.from_overrides("quest3", 1, {"n_frames": "3", "rectified_size": "16", "n_semidense_points": "300"})
    simulate_recording(cfg, tmp_path / "q", progress=False, stop_after=2)
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["resumed_from_frame"] == 2 and summary["frames"] == 3
    simulate_recording(cfg, tmp_path / "q2", progress=False, stop_after=2)
    assert main(args[:4] + [str(tmp_path / "q2")] + args[5:] + ["--no-resume"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["resumed_from_frame"] == 0
    assert_same_recording(tmp_path / "q", tmp_path / "q2")  # resumed by the CLI == fresh
    assert sorted(p.name for p in tmp_path.iterdir()) == ["q", "q2"]
