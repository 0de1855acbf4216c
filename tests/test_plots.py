"""Figures from synthetic run records and renders."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from egobench import plots as P
from egobench import tables as T
from egobench.cli import main as cli_main
from tests.helpers import write_records


def make_record(scene, kind, method, seed, psnr, paper_scene=None):
    return {
        "schema": "egobench.run/1", "scene": scene, "scene_kind": kind, "paper_scene": paper_scene,
        "method": method, "seed": seed, "metrics": {"psnr": psnr, "ssim": 0.5},
        "recording_stats": {"num_frames": 96, "head_angular_speed_deg_s_p50": 30.0 + seed},
    }




def _png(path: Path, rgb01: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((np.clip(rgb01, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))


def _records(tmp_path: Path, with_speed: bool = True) -> list[Path]:
    recs = []
    for m, psnr in (("ours", 25.0), ("no_viba", 23.0), ("no_motion_sampling", 24.0), ("splatfacto", 21.0)):
        for seed in (0, 1):
            r = make_record("out_a", "outdoor", m, seed, psnr + seed, paper_scene="bike shop")
            if not with_speed:
                r["recording_stats"] = {}
            recs.append(r)
    return write_records(tmp_path / "runs", recs)


def _add_renders(paths: list[Path], size: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    gt = rng.random((size, size, 3)).astype(np.float32)
    for p in paths:
        rec = json.loads(p.read_text())
        noise = {"ours": 0.02, "no_viba": 0.1, "no_motion_sampling": 0.05, "splatfacto": 0.2}[rec["method"]]
        d = p.parent / "renders"
        _png(d / "00000.png", gt + noise * rng.standard_normal(gt.shape))
        _png(d / "00008.png", gt)
        _png(d / "virtual_gain_3x_00008.png", gt * 3)  # as egobench.evaluate writes them
        _png(d / "virtual_gain_3x_00008_beside_input.png", np.concatenate([gt, gt * 3], axis=1))
    return gt


def test_all_figures_written_with_placeholders(tmp_path):
    records = T.load_records(_records(tmp_path, with_speed=False))
    written = P.make_plots(records, tmp_path / "fig")
    assert sorted(p.name for p in written) == sorted(P.OUTPUT_FILES)
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == sorted(P.OUTPUT_FILES)  # no temp files
    for p in written:
        if p.suffix == ".png":
            img = cv2.imread(str(p))
            assert img is not None and img.shape[0] > 50 and img.shape[1] > 50
        if p.suffix == ".pdf":
            assert p.read_bytes().startswith(b"%PDF")
    notes = json.loads((tmp_path / "fig" / "notes.json").read_text())
    assert notes["gains"].startswith("ok")
    for name in ("psnr_vs_head_speed", "qualitative", "gain3x", "motion_displacement"):
        assert notes[name].startswith("placeholder"), name


def test_figures_from_renders(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    records = T.load_records(paths)
    P.make_plots(records, tmp_path / "fig", qualitative_scene="out_a")
    notes = json.loads((tmp_path / "fig" / "notes.json").read_text())
    assert notes["qualitative"].startswith("ok: scene out_a, frame 8")  # frame 8 has its input saved
    assert notes["gain3x"].startswith("ok")
    assert notes["psnr_vs_head_speed"].startswith("ok: 8 runs")


def test_pngs_are_deterministic(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    records = T.load_records(paths)
    P.make_plots(records, tmp_path / "a")
    P.make_plots(records, tmp_path / "b")
    for name in ("gains.png", "qualitative.png", "gains.pdf"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


def test_detail_crop_matches_brute_force():
    rng = np.random.default_rng(1)
    img = np.zeros((20, 24, 3), np.float32)
    img[12:19, 2:9] = rng.random((7, 7, 3))  # the only texture: bottom-left
    r, c, h, w = P.detail_crop(img, frac=0.4)
    assert (h, w) == (8, 10)
    g = img.mean(axis=2).astype(np.float64)
    e = np.zeros_like(g)
    e[:, 1:] += np.diff(g, axis=1) ** 2
    e[1:, :] += np.diff(g, axis=0) ** 2
    sums = np.array([[e[i:i + h, j:j + w].sum() for j in range(24 - w + 1)] for i in range(20 - h + 1)])
    assert sums[r, c] == pytest.approx(sums.max())
    assert 4 <= r <= 12 and c <= 8


def test_mismatched_render_size_is_an_error(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    bad = next(p for p in paths if json.loads(p.read_text())["method"] == "no_viba")
    _png(bad.parent / "renders" / "00008.png", np.zeros((16, 16, 3)))
    with pytest.raises(ValueError, match="frame 8"):
        P.qualitative_figure(T.load_records(paths), "out_a")


def test_ground_truth_without_saved_input_needs_the_recording(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    for p in tmp_path.rglob("*beside_input.png"):
        p.unlink()
    with pytest.raises(ValueError, match="field 'recording'"):
        P.qualitative_figure(T.load_records(paths), "out_a")


def test_cli_plots(tmp_path):
    paths = _records(tmp_path)
    out = tmp_path / "fig"
    assert cli_main(["plots", "--records", str(tmp_path / "runs"), "--out-dir", str(out)]) == 0
    assert all((out / f).is_file() for f in P.OUTPUT_FILES)
    assert cli_main(["plots", "--records", *map(str, paths), "--out-dir", str(out),
                     "--qualitative-scene", "nope"]) == 2
