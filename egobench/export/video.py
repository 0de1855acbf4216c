"""`egobench render RUN --recording REC --video OUT.mp4`: a fly-through along the recording's trajectory.

Every frame (or every ``--every``-th) of the recording is rendered as the run predicts it (the
method's rolling-shutter poses and exposure samples, and its image formation at the frame's own
exposure and gain, `egobench.model.predict.predict_frame`), at the run's training resolution. Panels
side by side: this run, optionally a second run (``--compare``, e.g. w/o motion sampling, each
run with its own calibration stream of the recording) and the captured frames (``--captured``).
Encoded with OpenCV's MPEG-4 writer (opencv-python-headless, nothing downloaded).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from egobench.data import load_recording
from egobench.data.reader import add_input_arguments
from egobench.io_utils import atomic_path, check_written, holding_run_folder
from egobench.model.predict import RunRenderer, resize_map
from egobench.train.checkpoint import check_run_complete, load_trained_run, recording_for_run

#: Panels are enlarged (nearest neighbour) to at least this height, with a label bar above.
MIN_PANEL_PX, LABEL_PX = 256, 20


@dataclass
class _Panel:
    """What one panel shows: a run set up to predict frames, or the captured images."""

    label: str
    run: RunRenderer | None  # None: the captured images
    recording: object


def _run_panel(run_dir, recording_dir, device: str | None):
    run = load_trained_run(run_dir, device, f"render {run_dir}")
    check_run_complete(run_dir, run.checkpoint)
    rec = recording_dir if not isinstance(recording_dir, (str, Path)) else load_recording(recording_dir, run.spec.calibration)
    if rec.calibration != run.spec.calibration:
        raise ValueError(f"render {run_dir}: method {run.spec.name!r} renders the {run.spec.calibration!r} stream, "
                         f"the recording was loaded with {rec.calibration!r} (pass the recording folder instead)")
    return _Panel(label=run.spec.label, run=RunRenderer.of(rec, run), recording=rec)


def _predict(panel: _Panel, timestamp_ns: int) -> np.ndarray:
    """[H, W, 3] uint8: the panel's image of the frame at ``timestamp_ns``."""
    held = panel.run
    frame = next((f for f in panel.recording.frames if f.timestamp_ns == timestamp_ns), None)
    if frame is None:
        raise ValueError(f"{panel.recording.root}: no frame at {timestamp_ns} ns (the runs' recordings differ)")
    if held is None:
        cam = panel.recording.camera if panel.label != "captured" else panel.camera
        img = resize_map(panel.recording.load_image(frame), cam)
    else:
        img = held.predict(frame, held.pose_samples([frame])[0]).image
    return (img.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()


def _labelled(img: np.ndarray, label: str, scale: int) -> np.ndarray:
    """A panel enlarged ``scale`` x (nearest), with its label in a bar above (RGB uint8)."""
    big = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    bar = np.zeros((LABEL_PX, big.shape[1], 3), np.uint8)
    cv2.putText(bar, label, (4, LABEL_PX - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([bar, big], axis=0)


@holding_run_folder("render", "run_dir", exclusive=False)
def render_video(run_dir, recording_dir, out: str | Path, *, compare=None, captured: bool = False, every: int = 1,
                 max_frames: int | None = None, fps: float = 10.0, device: str | None = None,
                 progress: bool = True) -> dict:
    """Render the recording's frames (every ``every``-th, at most ``max_frames``) as panels side by
    side into ``out`` (MPEG-4); returns frames, size and panels written."""
    if Path(out).suffix.lower() != ".mp4":
        raise ValueError(f"render: --video {out}: expected a .mp4 file (MPEG-4)")
    if every < 1 or (max_frames is not None and max_frames < 1) or not fps > 0:
        raise ValueError(f"render: every ({every}) and max_frames ({max_frames}) must be >= 1 and fps ({fps}) > 0")
    panels = [_run_panel(run_dir, recording_dir, device)]
    if compare is not None:
        panels.append(_run_panel(compare, recording_dir, device))
    if captured:
        cap = _Panel(label="captured", run=None, recording=panels[0].recording)
        cap.camera = panels[0].run.run.camera
        panels.append(cap)
    frames = panels[0].recording.frames[::every][:max_frames]
    H = panels[0].run.run.camera.height
    scale = max(1, math.ceil(MIN_PANEL_PX / H))
    size = None
    with atomic_path(out) as tmp:  # .<name>.XXXX.tmp.mp4: the container follows the suffix
        writer = None
        for f in tqdm(frames, desc=f"render {Path(out).name}", disable=not progress, file=sys.stderr, mininterval=2.0):
            row = np.concatenate([_labelled(_predict(p, f.timestamp_ns), p.label, scale) for p in panels], axis=1)
            row = np.pad(row, ((0, row.shape[0] % 2), (0, row.shape[1] % 2), (0, 0)))  # even sizes for MPEG-4
            if writer is None:
                size = (row.shape[1], row.shape[0])
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size)
                if not writer.isOpened():
                    raise ValueError(f"{out}: OpenCV cannot open an MPEG-4 (mp4v) writer here")
            writer.write(cv2.cvtColor(row, cv2.COLOR_RGB2BGR))
        writer.release()
        check_written(out, tmp, what="video")  # OpenCV's writer reports no error: a full disk truncates silently
    return {"path": str(out), "frames": len(frames), "width": size[0], "height": size[1], "fps": fps,
            "panels": [p.label for p in panels]}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder with checkpoint.pt and train.json (a finished run)")
    parser.add_argument("--recording", required=True, help="the recording the run was trained on")
    parser.add_argument("--video", required=True, metavar="OUT.mp4", help="the video to write")
    parser.add_argument("--compare", default=None, metavar="RUN2", help="a second run shown beside the first")
    parser.add_argument("--captured", action="store_true", help="add the captured frames as a panel")
    parser.add_argument("--every", type=int, default=1, help="render every N-th frame (default: all)")
    parser.add_argument("--max-frames", type=int, default=None, help="at most this many frames")
    parser.add_argument("--fps", type=float, default=10.0, help="frames per second of the video")
    parser.add_argument("--device", default=None, help="torch device (default: the run's training device)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    out = render_video(args.run, recording_for_run(args.run, args), args.video, compare=args.compare, captured=args.captured,
                       every=args.every, max_frames=args.max_frames, fps=args.fps, device=args.device,
                       progress=not args.no_progress)
    print(f"rendered {out['frames']} frames ({' | '.join(out['panels'])}), {out['width']}x{out['height']} px -> {out['path']}")
    return 0
