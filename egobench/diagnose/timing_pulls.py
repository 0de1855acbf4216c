"""What each training frame says about the timing a run learned with its scene: the frame's pull on it and its
curvature, with the scene held as trained; from them, the learned value's standard error on this run.

Frame i's squared error E_i(tau) = |I_i(tau) - M_i|^2 over the recording's mask, near the learned timing tau [2]
(time offset, readout error; ms): its gradient g_i = J_i^T r_i and Gauss-Newton curvature H_i = J_i^T J_i, with
J_i = dI_i / dtau by central differences of STEP_MS. The learned value's variance is the sandwich
H^-1 S H^-1 (H = sum of H_i), S the scatter of the pulls summed over blocks of consecutive frames: frames that see
the same content pull alike, so frames are not independent draws, and the blocks are (`block_length`, Newey and
West's rule of thumb for the lag window). The block sums' own scatter is the run's frame-to-frame model error;
the test that uses it (`learned_timing.judge_timing`) has blocks - 1 degrees of freedom. The error is the squared
one, a Gauss-Newton stand-in for the L1 + SSIM loss the run was trained with, so the sandwich describes that
stand-in's estimate near the learned value, not the training's own.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from egobench.data.recording import Frame, Recording
from egobench.diagnose.sources import run_renderer
from egobench.model.predict import learned_timing_ms
from egobench.train.checkpoint import load_trained_run

#: the timing's central difference step (ms): the render is smooth in the poses at this scale, and the step moves
#: a row by well under a pixel at the walks' speeds
STEP_MS = 0.25


def block_length(n: int) -> int:
    """Frames per block for ``n`` frames in capture order: floor(4 (n / 100)^(2/9)), at least 1 (Newey and West's
    rule of thumb for the lag window; 3 for the 42 training frames of a 48-frame recording)."""
    return max(1, int(4.0 * (n / 100.0) ** (2.0 / 9.0)))


def sandwich_standard_error(pulls: np.ndarray, curvature: np.ndarray) -> tuple[np.ndarray, int]:
    """Per-frame pulls [n, p] (capture order) and curvatures [n, p, p] -> (the standard error [p] of the value
    that minimises the frames' summed error, its degrees of freedom): the sandwich with the pulls summed over
    blocks of `block_length` consecutive frames, centred, and scaled by blocks / (blocks - 1)."""
    pulls, curvature = np.asarray(pulls, dtype=np.float64), np.asarray(curvature, dtype=np.float64)
    n = pulls.shape[0]
    b = block_length(n)
    blocks = np.array([pulls[i:i + b].sum(0) for i in range(0, n, b)])
    if blocks.shape[0] < 3:
        raise ValueError(f"the learned timing's standard error needs at least 3 blocks of {b} frames; got {n} frames")
    centred = blocks - blocks.mean(0)
    try:
        inverse = np.linalg.inv(curvature.sum(0))
    except np.linalg.LinAlgError:
        raise ValueError("the frames' summed curvature in the timing is singular (a camera that barely moves, or "
                         "frames rendered with one pose sample): no standard error") from None
    k = blocks.shape[0]
    variance = inverse @ (centred.T @ centred) @ inverse * k / (k - 1)
    return np.sqrt(np.diag(variance)), k - 1


def frame_pulls(t: TimedRun, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A run that learned a timing, on its recording's training frames in capture order -> (pulls [F, 2],
    curvatures [F, 2, 2]) at the learned timing (module doc)."""
    steps = [torch.tensor([STEP_MS, 0.0]), torch.tensor([0.0, STEP_MS])]
    pulls, curvature = [], []
    with torch.no_grad():
        for f, n in tqdm(t.frames(t.rec.train_frames), desc="timing pulls", unit="frame", disable=not progress):
            r = t.image(f, n, t.timing) - t.measured(f)
            J = torch.stack([(t.image(f, n, t.timing + s) - t.image(f, n, t.timing - s)) / (2.0 * STEP_MS)
                             for s in steps], 1)
            pulls.append((J.T @ r).numpy())
            curvature.append((J.T @ J).numpy())
    return np.array(pulls), np.array(curvature)


def held_out_timing_gain(t: TimedRun, progress: bool = False) -> dict:
    """The learned timing's held-out gain: the run's held-out frames rendered with it and without it (the stated
    timing), the scene as trained with it, each frame with the pose samples of the run's own rule (those the timing
    was learned at) -> {"gain_db": mean over the frames of the PSNR gain over the recording's mask, "frames": how
    many}. Reported beside the learned timing, not deciding (`learned_timing`)."""
    gains = []
    with torch.no_grad():
        for f, n in tqdm(t.frames(t.rec.test_frames), desc="timing held out", unit="frame", disable=not progress):
            m = t.measured(f)
            with_it, without = (((t.image(f, n, timing) - m) ** 2).mean().item() for timing in (t.timing, None))
            gains.append(10.0 * np.log10(max(without, 1e-20) / max(with_it, 1e-20)))
    if not gains:
        raise ValueError(f"{t.recording_dir}: no held-out frames: the learned timing's held-out gain needs some")
    return {"gain_db": float(np.mean(gains)), "frames": len(gains)}


class TimedRun:
    """A run that learned a timing, on its recording, rendered at any timing over the recording's mask, on
    ``device`` (None: the run's training device), the recording read with ``trajectory_path`` / ``semidense_path``
    as `load_recording` reads them (the diagnosis's --device, --trajectory, --points); loaded once for
    `frame_pulls` and `held_out_timing_gain`."""

    def __init__(self, recording_dir: str | Path, run_dir: str | Path, device: str | None = None,
                 trajectory_path: str | Path | None = None, semidense_path: str | Path | None = None):
        what = "the learned timing's standard error and held-out gain"
        run = load_trained_run(run_dir, device, f"{what}, run {run_dir}")
        self.timing = learned_timing_ms(run)
        if self.timing is None:
            raise ValueError(f"{Path(run_dir) / 'checkpoint.pt'}: field 'extra.timing': the run learned no timing "
                             "(train it with learn_timing)")
        self.recording_dir = recording_dir
        self.renderer = run_renderer(recording_dir, run, what, trajectory_path, semidense_path)

    @property
    def rec(self) -> Recording:
        """The run's recording."""
        return self.renderer.recording

    def frames(self, frames: list) -> list:
        """[(frame, its pose samples as in training)]."""
        return list(zip(frames, self.renderer.pose_samples(frames)))

    def image(self, f: Frame, n: int, timing: torch.Tensor | None) -> torch.Tensor:
        """Frame f rendered with n pose samples at ``timing`` (None: the stated one), masked, flat, float64."""
        maps = self.renderer.maps
        p = self.renderer.predict(f, n, replace(maps, timing_ms=timing))
        return p.image[maps.mask].reshape(-1).to(torch.float64)

    def measured(self, f: Frame) -> torch.Tensor:
        """Frame f's captured image, masked, flat, float64."""
        return self.rec.load_image(f)[self.renderer.maps.mask].reshape(-1).to(torch.float64)


__all__ = ["STEP_MS", "TimedRun", "block_length", "frame_pulls", "held_out_timing_gain", "sandwich_standard_error"]
