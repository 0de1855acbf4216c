"""Figures from run records (and the runs' saved renders): PNG and PDF, matplotlib Agg.

- ``gains``: mean PSNR change of each ablation/baseline relative to ``ours``, paper vs egobench,
- ``psnr_vs_head_speed``: PSNR of each run against the recording's median head angular speed
  (from the record's ``recording_stats``; a labelled placeholder if no record carries it),
- ``qualitative``: crops of ground truth, ours, w/o VIBA, w/o motion sampling and splatfacto from
  one held-out frame (``renders/NNNNN.png`` written by `egobench.evaluate`; the ground truth is
  ``renders/NNNNN_gt.png`` if present, else the left half of evaluate's
  ``virtual_gain_3x_NNNNN_beside_input.png``, else the captured image read from the recording),
- ``motion_displacement``: `egobench.sim.figures.motion_displacement_figure` of one recording,
- ``gain3x``: the teaser's 3x-gain re-render of `ours` (``renders/virtual_gain_3x_NNNNN.png``)
  beside the captured frame and the plain render.

A figure whose input is missing is still written, as a panel stating what is missing, and
``notes.json`` lists each figure's status, so the workflow's outputs always exist.

``egobench plots --records R... --out-dir DIR [--recordings REC...] [--qualitative-scene S]``
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path
from typing import Sequence

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from egobench.data.reader import add_input_arguments, load_recording  # noqa: E402
from egobench.report import paper_numbers as pn  # noqa: E402
from egobench.report.outputs import FIGURE_FILES, FIGURES  # noqa: E402
from egobench.io_utils import atomic_path  # noqa: E402
from egobench.report.gains import gains_frame  # noqa: E402
from egobench.report.records import GROUPS, RunRecord, load_records, method_label  # noqa: E402
from egobench.sim.figures import motion_displacement_figure  # noqa: E402

OUTPUT_FILES = FIGURE_FILES  # every file `make_plots` writes (egobench.report.outputs)
#: Columns of the qualitative figure (after the ground truth), in the paper's order.
QUALITATIVE_METHODS = ("ours", "no_viba", "no_motion_sampling", "splatfacto")
RENDER_RE = re.compile(r"^(\d+)\.png$")
GAIN3X_RE = re.compile(r"^virtual_gain_3x_(\d+)\.png$")
BESIDE_RE = re.compile(r"^virtual_gain_3x_(\d+)_beside_input\.png$")


def save_figure(fig, out_dir: Path, name: str) -> list[Path]:
    """Save ``fig`` as name.png and name.pdf atomically; close it."""
    paths = []
    for ext in ("png", "pdf"):
        path = out_dir / f"{name}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=ext, dpi=150, bbox_inches="tight", metadata=_metadata(ext))
        paths.append(path)
    plt.close(fig)
    return paths


def _metadata(ext: str) -> dict:
    # Fixed metadata: identical inputs give byte-identical files (no creation date).
    return {"CreationDate": None} if ext == "pdf" else {"Software": None}


def placeholder_figure(title: str, reason: str):
    fig, ax = plt.subplots(figsize=(6, 2.5))
    ax.axis("off")
    ax.text(0.5, 0.6, title, ha="center", va="center", fontsize=13, weight="bold")
    ax.text(0.5, 0.3, f"not available: {reason}", ha="center", va="center", fontsize=9, wrap=True)
    return fig


# ---------------------------------------------------------------------------------------------


def gains_figure(records: Sequence[RunRecord]):
    """Grouped bars per table: paper's mean PSNR change (matched scenes) versus ours (95 % interval over
    seeds); a row identical to its reference by construction is labelled, not drawn as zero."""
    df = gains_frame(records)
    df = df[df["n_seeds"] > 0] if len(df) else df
    if not len(df):
        return placeholder_figure("PSNR gains", "no pair of runs (method, reference) on the same scene and seed"), \
            "placeholder: no method/reference pairs"
    groups = [g for g in GROUPS if g in set(df["group"])]
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.6), squeeze=False)
    for ax, group in zip(axes[0], groups):
        sub = df[df["group"] == group]
        x = np.arange(len(sub))
        paper = sub["paper_delta_psnr_matched"].astype(float).to_numpy()
        ours = sub["delta_psnr_mean"].astype(float).to_numpy()
        low = sub["delta_psnr_ci95_low"].astype(float).to_numpy()
        high = sub["delta_psnr_ci95_high"].astype(float).to_numpy()
        yerr = np.nan_to_num(np.stack([ours - low, high - ours]), nan=0.0)  # 95 % interval over seeds
        ax.bar(x - 0.2, np.nan_to_num(paper), 0.4, label="paper", color="#999999")
        ax.bar(x + 0.2, np.nan_to_num(ours), 0.4, yerr=yerr, capsize=3, label="egobench (95 % CI)", color="#1f77b4")
        for xi, why in zip(x, sub["identical"].fillna("")):
            if why:  # no measurement: say why instead of drawing a zero bar
                ax.text(xi + 0.2, 0.0, why.split(":")[0], rotation=90, fontsize=6, ha="center", va="bottom")
        ax.axhline(0.0, color="black", lw=0.8)
        names = [method_label(m, group) + ("" if ref == "ours" else f"\n(vs. {method_label(ref, group)})")
                 for m, ref in zip(sub["method"], sub["reference"])]
        ax.set_xticks(x, names, rotation=35, ha="right", fontsize=8)
        ax.set_title(group.replace("_", " "))
        ax.set_ylabel("PSNR change vs. reference (dB)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    return fig, f"ok: {len(df)} method/reference pairs in {len(groups)} table(s)"


def head_speed_figure(records: Sequence[RunRecord]):
    """PSNR of each run versus its recording's median head angular speed, one colour per method."""
    pts = [(r.head_speed_deg_s, r.metrics[pn.PSNR], r.method) for r in records if r.head_speed_deg_s is not None]
    if not pts:
        return placeholder_figure("PSNR versus head speed",
                                  "no record carries recording_stats head angular speed"), \
            "placeholder: no record carries a head angular speed in recording_stats"
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for m in sorted({p[2] for p in pts}):
        xs = [p[0] for p in pts if p[2] == m]
        ys = [p[1] for p in pts if p[2] == m]
        ax.scatter(xs, ys, label=method_label(m), s=18)
    ax.set_xlabel("median head angular speed (deg/s)")
    ax.set_ylabel("PSNR (dB)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    skipped = len(records) - len(pts)
    return fig, f"ok: {len(pts)} runs" + (f" ({skipped} records without head speed skipped)" if skipped else "")


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: render is missing or unreadable")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def _render_frames(run_dir: Path) -> dict[int, Path]:
    d = run_dir / "renders"
    if not d.is_dir():
        return {}
    return {int(m.group(1)): p for p in d.iterdir() if (m := RENDER_RE.match(p.name))}


def _gt_cheap(run_dir: Path, frame: int) -> np.ndarray | None:
    """Ground truth saved beside the renders (NNNNN_gt.png, or the input half of beside_input)."""
    d = run_dir / "renders"
    if (d / f"{frame:05d}_gt.png").is_file():
        return _read_rgb(d / f"{frame:05d}_gt.png")
    beside = d / f"virtual_gain_3x_{frame:05d}_beside_input.png"
    if beside.is_file():
        img = _read_rgb(beside)
        return img[:, : img.shape[1] // 2]
    return None


def ground_truth(record: RunRecord, frame: int, shape: tuple[int, ...]) -> np.ndarray:
    """The captured held-out image of ``frame`` at the render's ``shape`` [H, W, 3]."""
    gt = _gt_cheap(record.run_dir, frame)
    if gt is None:
        rec_path = record.raw.get("recording")
        if not rec_path:
            raise ValueError(f"{record.path}: field 'recording' is missing; cannot find the ground truth of frame {frame}")
        rec = load_recording(rec_path, record.raw.get("calibration") or "online", load_sparse_depth=False,
                             trajectory_path=record.raw.get("trajectory_file"), semidense_path=record.raw.get("points_file"))
        match = [f for f in rec.frames if f.index == frame]
        if not match:
            raise ValueError(f"{rec_path}: no frame {frame} (from {record.path})")
        img = rec.load_image(match[0]).numpy()
        gt = cv2.resize(img, (shape[1], shape[0]), interpolation=cv2.INTER_AREA) if img.shape != shape else img
    if gt.shape != tuple(shape):
        raise ValueError(f"{record.run_dir}/renders: ground truth of frame {frame} is {gt.shape}, renders are {shape}")
    return gt


def detail_crop(gt: np.ndarray, frac: float = 0.5) -> tuple[int, int, int, int]:
    """(row, col, height, width) of the crop (frac of the image side) with the most gradient energy."""
    h, w = gt.shape[:2]
    ch, cw = max(1, int(round(h * frac))), max(1, int(round(w * frac)))
    g = gt.mean(axis=2) if gt.ndim == 3 else gt
    energy = np.zeros((h, w), np.float64)
    energy[:, 1:] += np.diff(g, axis=1) ** 2
    energy[1:, :] += np.diff(g, axis=0) ** 2
    ii = np.pad(energy.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = ii[ch:, cw:] - ii[:-ch, cw:] - ii[ch:, :-cw] + ii[:-ch, :-cw]  # [h-ch+1, w-cw+1]
    r, c = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(r), int(c), ch, cw


def _pick_runs(records: Sequence[RunRecord], scene: str | None) -> tuple[str | None, dict[str, RunRecord]]:
    with_ours = [r for r in records if r.method == "ours" and _render_frames(r.run_dir)]
    if scene is None:
        scene = sorted(with_ours, key=lambda r: (r.scene, r.seed))[0].scene if with_ours else None
    runs: dict[str, RunRecord] = {}
    for r in sorted(records, key=lambda r: r.seed):
        if r.scene == scene and r.method in QUALITATIVE_METHODS and r.method not in runs and _render_frames(r.run_dir):
            runs[r.method] = r
    return scene, runs


def qualitative_figure(records: Sequence[RunRecord], scene: str | None = None, crop_frac: float = 0.5):
    """Crops of GT, ours, w/o VIBA, w/o motion sampling, splatfacto on one held-out frame."""
    scene, runs = _pick_runs(records, scene)
    if "ours" not in runs:
        return placeholder_figure("Qualitative comparison", f"no 'ours' renders for scene {scene!r}"), \
            f"placeholder: no ours renders (renders/NNNNN.png) for scene {scene!r}"
    frames = set(_render_frames(runs["ours"].run_dir))
    for r in runs.values():
        frames &= set(_render_frames(r.run_dir))
    if not frames:
        return placeholder_figure("Qualitative comparison", "no held-out frame rendered by every method"), \
            "placeholder: no held-out frame rendered by every method"
    # Prefer a frame whose ground truth was saved beside the renders; else read the recording.
    cheap = sorted(f for f in frames if _gt_cheap(runs["ours"].run_dir, f) is not None)
    frame = cheap[0] if cheap else min(frames)
    ours_img = _read_rgb(_render_frames(runs["ours"].run_dir)[frame])
    gt = ground_truth(runs["ours"], frame, ours_img.shape)
    r0, c0, ch, cw = detail_crop(gt, crop_frac)
    panels = [("ground truth", gt, None)]
    for m in QUALITATIVE_METHODS:
        if m in runs:
            img = _read_rgb(_render_frames(runs[m].run_dir)[frame])
            if img.shape != gt.shape:
                raise ValueError(f"{runs[m].run_dir}/renders: frame {frame} is {img.shape}, ground truth is {gt.shape}")
            # Each method is scored against the image of its own calibration stream (factory-calibrated
            # methods are evaluated on factory-rectified images), as in its eval.json.
            own_gt = gt if m == "ours" else ground_truth(runs[m], frame, img.shape)
            crop_err = float(np.mean((img[r0:r0 + ch, c0:c0 + cw] - own_gt[r0:r0 + ch, c0:c0 + cw]) ** 2))
            psnr = 10 * np.log10(1.0 / max(crop_err, 1e-12))
            panels.append((method_label(m), img, psnr))
    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.9), squeeze=False)
    for ax, (title, img, psnr) in zip(axes[0], panels):
        ax.imshow(np.clip(img[r0:r0 + ch, c0:c0 + cw], 0, 1), interpolation="nearest")
        ax.set_title(title if psnr is None else f"{title}\ncrop PSNR {psnr:.2f} dB", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{scene}, held-out frame {frame}", fontsize=9)
    fig.tight_layout()
    missing = [m for m in QUALITATIVE_METHODS if m not in runs]
    return fig, f"ok: scene {scene}, frame {frame}" + (f"; methods without renders: {', '.join(missing)}" if missing else "")


def gain3x_figure(records: Sequence[RunRecord], scene: str | None = None):
    """Captured frame, ours render, ours re-rendered with 3x virtual gain (paper teaser)."""
    scene, runs = _pick_runs(records, scene)
    ours = runs.get("ours")
    if ours is None:
        return placeholder_figure("3x gain re-render", f"no 'ours' run with renders for scene {scene!r}"), \
            "placeholder: no ours renders"
    d = ours.run_dir / "renders"
    gains = sorted((int(m.group(1)), p) for p in d.iterdir() if (m := GAIN3X_RE.match(p.name)))
    if not gains:
        return placeholder_figure("3x gain re-render", f"{d} holds no virtual_gain_3x_NNNNN.png"), \
            "placeholder: no virtual_gain_3x_NNNNN.png render"
    frame, path = gains[0]
    boosted = _read_rgb(path)
    panels = [("captured (held out)", _gt_cheap(ours.run_dir, frame)), ("ours", None), ("ours, 3x gain", boosted)]
    if (d / f"{frame:05d}.png").is_file():
        panels[1] = ("ours", _read_rgb(d / f"{frame:05d}.png"))
    panels = [(t, img) for t, img in panels if img is not None]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4), squeeze=False)
    for ax, (title, img) in zip(axes[0], panels):
        ax.imshow(img)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(f"{scene}, frame {frame}", fontsize=9)
    fig.tight_layout()
    return fig, f"ok: scene {scene}, frame {frame}"


def motion_figure(recordings: Sequence[str | Path], trajectory: str | None = None, points: str | None = None):
    """The simulator's motion-displacement figure (egobench.sim.figures) of the first recording
    (read with ``trajectory`` / ``points`` when given: the CLI's --trajectory / --points)."""
    if not recordings:
        return placeholder_figure("Motion displacement", "no recording given (--recordings)"), "placeholder: no recording"
    rec_path = Path(recordings[0])
    rec = load_recording(rec_path, "online", trajectory_path=trajectory, semidense_path=points)
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "motion.png"
        q = motion_displacement_figure(rec, png)  # [F, 3] per-frame 25/50/75th percentile, px
        img = plt.imread(png)
    fig, ax = plt.subplots(figsize=(img.shape[1] / 120, img.shape[0] / 120))
    ax.imshow(img)
    ax.axis("off")
    fig.subplots_adjust(0, 0, 1, 1)
    return fig, f"ok: recording {rec_path}, median readout displacement {float(np.median(q[:, 1])):.2f} px"


def make_plots(records: Sequence[RunRecord], out_dir: str | Path, recordings: Sequence[str | Path] = (),
               qualitative_scene: str | None = None, trajectory: str | None = None,
               points: str | None = None) -> list[Path]:
    """Write every file in OUTPUT_FILES into out_dir; return their paths (``trajectory`` / ``points``:
    read the first of ``recordings`` with these MPS files)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    notes: dict[str, str] = {}
    written: list[Path] = []
    makers = {
        "gains": lambda: gains_figure(records),
        "psnr_vs_head_speed": lambda: head_speed_figure(records),
        "qualitative": lambda: qualitative_figure(records, qualitative_scene),
        "motion_displacement": lambda: motion_figure(recordings, trajectory, points),
        "gain3x": lambda: gain3x_figure(records, qualitative_scene),
    }
    for name in FIGURES:
        fig, note = makers[name]()
        notes[name] = note
        written += save_figure(fig, out, name)
    path = out / "notes.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(notes, indent=2, sort_keys=True) + "\n")
    written.append(path)
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--records", nargs="+", required=True, metavar="EVAL_JSON",
                        help="run records (eval.json) or folders searched for eval.json")
    parser.add_argument("--out-dir", required=True, help="folder for the figures")
    parser.add_argument("--recordings", nargs="*", default=[], help="recording folders (motion-displacement figure)")
    parser.add_argument("--qualitative-scene", default=None,
                        help="scene of the qualitative and 3x-gain figures (default: first scene with ours renders)")
    add_input_arguments(parser)  # for the --recordings figure


def run(args: argparse.Namespace) -> int:
    records = load_records(args.records)
    if not records:
        raise ValueError("--records: no eval.json run records found")
    if args.qualitative_scene is not None and args.qualitative_scene not in {r.scene for r in records}:
        raise ValueError(f"--qualitative-scene: {args.qualitative_scene!r} is not a scene of the records")
    written = make_plots(records, args.out_dir, args.recordings, args.qualitative_scene,
                         trajectory=getattr(args, "trajectory", None), points=getattr(args, "points", None))
    notes = json.loads((Path(args.out_dir) / "notes.json").read_text())
    for name, note in notes.items():
        print(f"  {name}: {note}")
    print(f"egobench plots: {len(records)} records -> {len(written)} files in {args.out_dir}")
    return 0
