"""Figures from synthetic run records and renders."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from egobench.report import plots as P
from egobench.report import records as Rec
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


def _read_png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _bar_heights_px(img: np.ndarray, rgb: tuple[int, int, int]) -> list[int]:
    """Heights (pixels) of the bars of colour rgb, left to right: runs of columns whose longest vertical
    run of that colour exceeds 30 pixels (legend patches are shorter)."""
    m = np.all(np.abs(img.astype(int) - np.array(rgb)) <= 2, axis=-1)
    longest = np.zeros(m.shape[1], int)
    for x in range(m.shape[1]):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], m[:, x].astype(int), [0]])))
        longest[x] = int(np.max(edges[1::2] - edges[::2])) if len(edges) else 0
    heights, start = [], None
    for x, tall in enumerate(np.append(longest > 30, False)):
        if tall and start is None:
            start = x
        elif not tall and start is not None:
            heights.append(int(np.median(longest[start:x])))
            start = None
    return heights


def test_all_figures_written_with_placeholders(tmp_path):
    records = Rec.load_records(_records(tmp_path, with_speed=False))
    written = P.make_plots(records, tmp_path / "fig")
    assert sorted(p.name for p in written) == sorted(P.OUTPUT_FILES)
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == sorted(P.OUTPUT_FILES)  # no temp files
    for p in written:
        if p.suffix == ".pdf":
            assert p.read_bytes().startswith(b"%PDF")
    notes = json.loads((tmp_path / "fig" / "notes.json").read_text())
    assert notes["gains"].startswith("ok")
    for name in ("psnr_vs_head_speed", "qualitative", "gain3x", "motion_displacement"):
        assert notes[name].startswith("placeholder"), name
        # a placeholder panel: black text on white, nothing else
        img = _read_png(tmp_path / "fig" / f"{name}.png").astype(int)
        ink = img.min(axis=-1) < 128
        assert 0.002 < ink.mean() < 0.1, name
        assert np.abs(img - img.mean(axis=-1, keepdims=True)).max() <= 2, name  # grey levels only
    # The gains bars: egobench (blue) = ours minus each method: splatfacto -4, w/o VIBA -2, w/o motion
    # sampling -1 dB (the records' PSNRs); paper (grey) = Table 1 outdoor, matched scene: -3.00, -2.30, -1.15.
    img = _read_png(tmp_path / "fig" / "gains.png")
    blue, grey = _bar_heights_px(img, (0x1F, 0x77, 0xB4)), _bar_heights_px(img, (0x99, 0x99, 0x99))
    assert len(blue) == 3 and len(grey) == 3, (blue, grey)
    px_per_db = blue[0] / 4.0
    assert px_per_db > 40  # the bars fill the axes
    for measured, db in zip(blue + grey, (4.0, 2.0, 1.0, 3.0, 2.3, 1.15)):
        assert measured == pytest.approx(db * px_per_db, abs=2.5), (blue, grey)


def _panels(img: np.ndarray) -> list[tuple[int, int, int, int]]:
    """(top, bottom, left, right) of the image panels of a figure: runs of columns more than 100 px
    of which are not white (titles are shorter), and in each the rows not white in most columns."""
    ink = img.min(axis=-1) < 245
    tall = np.append(ink.sum(axis=0) > 100, False)
    boxes, start = [], None
    for x, t in enumerate(tall):
        if t and start is None:
            start = x
        elif not t and start is not None:
            rows = np.flatnonzero(ink[:, start:x].mean(axis=1) > 0.5)
            boxes.append((int(rows[0]), int(rows[-1]) + 1, start, x))
            start = None
    return boxes


def test_figures_from_renders(tmp_path):
    paths = _records(tmp_path)
    gt = _add_renders(paths)
    # Held-out frame 8 of each method: the ground truth scaled by a known factor (ours: exact).
    factor = {"ours": 1.0, "no_viba": 0.8, "no_motion_sampling": 0.6, "splatfacto": 0.4}
    for p in paths:
        _png(p.parent / "renders" / "00008.png", gt * factor[json.loads(p.read_text())["method"]])
    records = Rec.load_records(paths)
    P.make_plots(records, tmp_path / "fig", qualitative_scene="out_a")
    notes = json.loads((tmp_path / "fig" / "notes.json").read_text())
    assert notes["qualitative"].startswith("ok: scene out_a, frame 8")  # frame 8 has its input saved
    assert notes["gain3x"].startswith("ok")
    assert notes["psnr_vs_head_speed"].startswith("ok: 8 runs")
    # The figure shows the same detail crop of ground truth, ours, w/o VIBA, w/o motion sampling and
    # splatfacto, left to right, at 8 bits: sample the centre of each displayed (nearest) pixel.
    def q8(x):
        return np.round(np.clip(x, 0, 1) * 255) / 255

    r0, c0, ch, cw = P.detail_crop(q8(gt), 0.5)
    img = _read_png(tmp_path / "fig" / "qualitative.png")
    panels = _panels(img)
    img = img / 255.0
    assert len(panels) == 5, panels
    for (top, bottom, left, right), f in zip(panels, (1.0, *factor.values())):
        ys = (top + (np.arange(ch) + 0.5) * (bottom - top) / ch).astype(int)
        xs = (left + (np.arange(cw) + 0.5) * (right - left) / cw).astype(int)
        expected = q8(gt * f)[r0:r0 + ch, c0:c0 + cw]
        assert np.abs(img[ys][:, xs] - expected).max() <= 1.5 / 255, (f, panels)
    # Crop PSNRs in the titles: each method against the ground truth over the crop (ours: exact -> 120 dB).
    fig, _ = P.qualitative_figure(records, "out_a")
    titles = [ax.get_title() for ax in fig.axes]
    for title, f in zip(titles[1:], factor.values()):
        err = np.mean((q8(gt * f) - q8(gt))[r0:r0 + ch, c0:c0 + cw] ** 2)
        shown = float(re.search(r"crop PSNR (-?[\d.]+) dB", title).group(1))
        assert shown == pytest.approx(10 * np.log10(1 / max(err, 1e-12)), abs=0.01), title


def test_pngs_are_deterministic(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    records = Rec.load_records(paths)
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
        P.qualitative_figure(Rec.load_records(paths), "out_a")


def test_ground_truth_without_saved_input_needs_the_recording(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    for p in tmp_path.rglob("*beside_input.png"):
        p.unlink()
    with pytest.raises(ValueError, match="field 'recording'"):
        P.qualitative_figure(Rec.load_records(paths), "out_a")


def test_cli_plots(tmp_path):
    paths = _records(tmp_path)
    _add_renders(paths)
    out = tmp_path / "fig"
    assert cli_main(["plots", "--records", str(tmp_path / "runs"), "--out-dir", str(out)]) == 0
    # the CLI writes what make_plots writes for the same records (the figures are deterministic)
    P.make_plots(Rec.load_records(paths), tmp_path / "direct")
    for name in P.OUTPUT_FILES:
        assert (out / name).read_bytes() == (tmp_path / "direct" / name).read_bytes(), name
    assert json.loads((out / "notes.json").read_text())["qualitative"].startswith("ok: scene out_a")
    assert cli_main(["plots", "--records", *map(str, paths), "--out-dir", str(out),
                     "--qualitative-scene", "nope"]) == 2
