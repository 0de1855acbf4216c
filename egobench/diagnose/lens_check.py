"""Whether a trained run can show a lens error at all, measured on the run itself (issue 72).

A run trained far from convergence leaves a radial under-fit in its residual (content displaced outward toward
the corners) that the distortion test reads as a k0 error, and nothing else on the run marks it
(results/diagnosis/README.md, "2026-12-06: what the distortion test reads on null runs"). What can be measured is
how much of a real lens error such a run keeps: warp the recording's frames as a lens with a known k0 error
shows them (`effects.distortion.lens_warp`), train the run's method again with the run's own config and seed,
and compare the distortion estimates the two runs leave, per unit of what the warp alone puts in the residual:

    retention = (k(m', p') - k(m, p)) / (k(m', p) - k(m, p))

m, p: the recording's frames and the run's renders; m': the frames warped; p': the renders of the run trained on
m'; k: the distortion cause's first-order estimate, frame-weighted over every frame. A lens error is testable on
the run when the retention reaches `LENS_RETENTION_FLOOR` (`DistortionCause.untestable_on_trained_run`).

On a trained run a lens is not tested unless the retention is measured. The check costs one more training, so it
runs when asked (`egobench diagnose --lens-check`, `diagnose_trained_run`), before any name: it injects twice the
smallest k0 error the run's report would call testable, the size that report's power claim says is named. (Checked
only after a distortion was named, with the named size injected, the writer's null runs at 64 px and 800 iterations
kept 31-83 % of it, and the check removed none of those names: results/diagnosis/README.md, "2026-12-06: a run's
retention of a lens, measured on the run".)
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from egobench.data import load_recording
from egobench.data.recording import Frame, Recording
from egobench.diagnose.core import Diagnosis, DiagnosisConfig, diagnose_residuals
from egobench.diagnose.sources import Sources, run_source
from egobench.effects.distortion import LENS_RETENTION_FLOOR, DistortionCause, lens_warp, unit_displacement
from egobench.io_utils import claim_work_dir
from egobench.residual.estimation import ResidualData
from egobench.residual.signatures import DiagnosisContext, frame_t_test
from egobench.train import train
from egobench.train.checkpoint import load_trained_run

#: The lens check injects this multiple of the run's smallest testable k0 error: the size that the diagnosis's
#: power claim says is named on the run (an effect at least twice the smallest testable).
LENS_CHECK_MULTIPLE = 2.0
#: The retention the first pass of `diagnose_trained_run` assumes, to find the run's smallest testable k0 error.
PROVISIONAL_RETENTION = 1.0
#: The warp alone must move the estimate by at least this share of the injected error (the first-order
#: estimator's own sensitivity) for a retention to be measured; below it the retention is NaN (not testable).
MIN_RESIDUAL_RESPONSE = 0.25


def warped_display(image: np.ndarray, k0_error: float, displacement: np.ndarray) -> np.ndarray:
    """An 8-bit display image [H, W, 3] in 0..1 as the lens with k0 larger by ``k0_error`` shows it, rounded
    back to 8 bits (as the camera writes it and the training's image store holds it)."""
    return np.clip(np.round(lens_warp(image, k0_error, displacement) * 255.0), 0.0, 255.0) / 255.0


@dataclass
class LensWarpedRecording(Recording):
    """A loaded recording whose frames are read through a lens with k0 larger by ``k0_error``
    (`warped_display`; ``displacement``: `unit_displacement` at the recording's size)."""

    k0_error: float = 0.0
    displacement: np.ndarray | None = None

    @classmethod
    def of(cls, recording: Recording, k0_error: float, displacement: np.ndarray) -> "LensWarpedRecording":
        return cls(**{f.name: getattr(recording, f.name) for f in fields(Recording)},
                   k0_error=float(k0_error), displacement=displacement)

    def load_image(self, frame: Frame) -> torch.Tensor:
        image = super().load_image(frame).numpy().astype(np.float64)
        return torch.from_numpy(warped_display(image, self.k0_error, self.displacement)).float()


def distortion_estimate(measured: np.ndarray, predicted: np.ndarray, ctx: DiagnosisContext, border_px: int) -> float:
    """The distortion cause's first-order k0 estimate over every frame (frame-weighted mean)."""
    data = ResidualData(measured, predicted, ctx, np.arange(len(measured)), border_px=border_px)
    est, info = DistortionCause().first_order(data)
    return float(frame_t_test(est[:, 0], info[:, 0]).mean)


def retention_of(k_run: float, k_warped: float, k_retrained: float, injected: float) -> float:
    """(k_retrained - k_run) / (k_warped - k_run); NaN when the warp alone moved the estimate by less than
    `MIN_RESIDUAL_RESPONSE` of ``injected`` or the other way."""
    response = k_warped - k_run
    if not math.isfinite(response) or response * np.sign(injected) < MIN_RESIDUAL_RESPONSE * abs(injected):
        return math.nan
    return (k_retrained - k_run) / response


def claim_warp(work_dir: Path, warp: dict) -> None:
    """Stamp WORK_DIR with the warp its run is trained on (WORK_DIR/warp.json: injected k0, run, recording), or
    raise where it holds a run of another warp (`io_utils.claim_work_dir`)."""
    claim_work_dir(work_dir, "warp.json", warp, "a lens check")


def measure_lens_retention(recording_dir: str | Path, run_dir: str | Path, src: Sources, injected_k0: float,
                           work_dir: str | Path, border_px: int, pose_samples: int | None = None,
                           progress: bool = False) -> dict:
    """Train ``run_dir``'s method with its config and seed on the recording warped by ``injected_k0`` (into
    WORK_DIR/run; a run there of the same warp, run and recording, `claim_warp`, is reused or resumed) and measure
    the run's retention of a lens error -> the record."""
    if not (math.isfinite(injected_k0) and injected_k0 != 0.0):
        raise ValueError(f"injected_k0: expected a finite nonzero k0 error, got {injected_k0!r}")
    run = load_trained_run(run_dir, None, f"lens check of {run_dir}")
    ctx = src.context
    F, H, W = src.measured.shape[:3]
    displacement = unit_displacement(ctx, H, W)
    retrained = Path(work_dir) / "run"
    claim_warp(Path(work_dir), {"injected_k0": float(injected_k0), "run": str(Path(run_dir).resolve()),
                                "recording": str(Path(recording_dir).resolve())})
    done = retrained / "train.json"
    if not (done.is_file() and json.loads(done.read_text()).get("complete")):
        recording = load_recording(recording_dir, calibration=run.spec.calibration)
        train(LensWarpedRecording.of(recording, injected_k0, displacement), run.spec.name, run.config, retrained,
              resume="auto", progress=progress)
    warped = np.stack([warped_display(m, injected_k0, displacement) for m in src.measured])
    predicted = run_source(recording_dir, retrained, max_frames=F, progress=progress,
                           pose_samples=pose_samples).predicted
    k_run = distortion_estimate(src.measured, src.predicted, ctx, border_px)
    k_warped = distortion_estimate(warped, src.predicted, ctx, border_px)
    k_retrained = distortion_estimate(warped, predicted, ctx, border_px)
    r = retention_of(k_run, k_warped, k_retrained, injected_k0)
    return {"injected_k0": float(injected_k0), "k0_run": k_run, "k0_warped": k_warped, "k0_retrained": k_retrained,
            "retention": None if math.isnan(r) else r, "floor": LENS_RETENTION_FLOOR,
            "testable": bool(math.isfinite(r) and r >= LENS_RETENTION_FLOOR), "retrained_run": str(retrained)}


def diagnose_trained_run(recording_dir: str | Path, run_dir: str | Path, src: Sources, cfg: DiagnosisConfig,
                         work_dir: str | Path, pose_samples: int | None = None, progress: bool = False) -> Diagnosis:
    """`diagnose_residuals` of a trained run's sources with a lens testable only where the run keeps one: the
    diagnosis runs once with the lens provisionally testable (`PROVISIONAL_RETENTION`) for the run's smallest
    testable k0 error s; the run's retention of a lens of `LENS_CHECK_MULTIPLE` x s (`measure_lens_retention`, in
    WORK_DIR) then decides, and where it falls below the floor the diagnosis runs again with it (the record in
    ``model_error["lens_check"]``). A run that gives no s keeps the lens untestable (unmeasurable). The lens injected
    is positive, the sign every writer run's own under-fit reads (results/diagnosis/README.md); a negative lens is
    judged by that retention too."""
    d = diagnose_residuals(src.measured, src.predicted, replace(src.context, lens_retention=PROVISIONAL_RETENTION), cfg)
    smallest = ((d.model_error or {}).get("smallest_testable") or {}).get(DistortionCause.name, {}).get("k0_error")
    if smallest is None or not (math.isfinite(smallest) and smallest != 0.0):
        d = diagnose_residuals(src.measured, src.predicted, replace(src.context, lens_retention=math.nan), cfg)
        check = {"smallest_testable_k0": None, "testable": False,
                 "reason": "the provisional diagnosis gives no smallest testable k0 error"}
    else:
        check = measure_lens_retention(recording_dir, run_dir, src, LENS_CHECK_MULTIPLE * abs(smallest), work_dir,
                                       cfg.border_px, pose_samples, progress)
        check.update(smallest_testable_k0=float(abs(smallest)), multiple=LENS_CHECK_MULTIPLE)
        if not check["testable"]:
            kept = math.nan if check["retention"] is None else check["retention"]
            d = diagnose_residuals(src.measured, src.predicted, replace(src.context, lens_retention=kept), cfg)
    if d.model_error is not None:
        d.model_error["lens_check"] = check
    return d


__all__ = ["LensWarpedRecording", "claim_warp", "diagnose_trained_run", "distortion_estimate", "measure_lens_retention",
           "retention_of", "warped_display"]
