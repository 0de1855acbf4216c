"""The recording: `simulate_recording` and the files it writes at the end."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from tqdm import tqdm

import egobench
from egobench.data.layout import (FACTORY_CALIBRATION_FILE, MPS_SLAM, ONLINE_CALIBRATION_FILE, POINTS_FILE,
                                  TRAJECTORY_FILE, link_mps_files)
from egobench.data.mps import write_calibration_json, write_online_calibration, write_semidense_points
from egobench.data.transforms import write_camera_maps, write_transforms
from egobench.io_utils import write_json
from egobench.sim.camera_calibration import calibration_record
from egobench.sim.capture.frame import CaptureRun, frame_state, restore_run, simulate_frame
from egobench.sim.capture.resume import (
    PARTIAL_SCHEMA,
    RESUME_SUBDIR,
    drop_frames_from,
    finalise,
    frame_state_path,
    read_partial,
    frame_dirs,
    partial_dir,
    sim_config_hash,
)
from egobench.sim.capture.setup import CaptureResult, CaptureSetup, build_capture_setup, calibrated_vignette
from egobench.sim.config import SimConfig

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    from egobench.data.mps import CalibrationRecord


def simulate_recording(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
                       resume: bool | Literal["auto"] = False, stop_after: int | None = None) -> CaptureResult:
    """Simulate `config` into the recording folder `out_dir` (layout: docs/architecture.md).

    The recording is built in `partial_dir(out_dir)`; after every frame a state file (written last)
    records what later frames depend on. ``resume``: False starts afresh (an existing partial folder
    is discarded) and removes the partial folder when an exception ends the run (nothing left
    behind); "auto" (the CLI's and the workflow's choice) continues a partial folder of the same
    SimConfig and egobench version, and discards one of another config with a message on stderr;
    True continues one and raises (FileNotFoundError / ValueError) when there is none to continue.
    With resume on, the partial folder is kept when the run fails, so rerunning the command
    continues it; the result is byte-identical to an uninterrupted run (recording.json's
    simulation_time_s, summed over the runs, aside). ``stop_after``: stop once that many frames
    (in total) are done, keeping the partial folder (an interruption hook, as in
    egobench.train.train); the result then has ``complete=False`` and ``path`` = the partial folder.
    On success the partial folder replaces `out_dir` (os.replace after removing an old `out_dir`).
    """
    config.validate()
    if resume not in (True, False, "auto"):
        raise ValueError(f"simulate_recording: resume must be True, False or 'auto', got {resume!r}")
    if stop_after is not None and (isinstance(stop_after, bool) or not isinstance(stop_after, int) or stop_after < 0):
        raise ValueError(f"simulate_recording: stop_after must be None or an int >= 0, got {stop_after!r}")
    t_begin = time.perf_counter()
    out_dir = Path(out_dir)
    partial = partial_dir(out_dir)
    chash = sim_config_hash(config)

    # Resume a partial folder, or discard it and start afresh.
    states: list[dict] = []
    if partial.exists():
        why = "resume is off"
        if resume:
            states, why = read_partial(partial, chash)
        if why is not None:
            if resume is True:
                raise ValueError(f"{partial}: cannot resume: {why}")
            print(f"egobench simulate: discarding the partial recording {partial}: {why}; starting afresh",
                  file=sys.stderr)
            shutil.rmtree(partial)
    elif resume is True:
        raise FileNotFoundError(f"{partial}: no partial recording to resume from")
    resuming = partial.exists()
    if resuming:
        print(f"egobench simulate: resuming {partial} after {len(states)}/{config.n_frames} frames", file=sys.stderr)
    else:
        (partial / RESUME_SUBDIR).mkdir(parents=True)
        write_json(partial / RESUME_SUBDIR / "partial.json", {
            "schema": PARTIAL_SCHEMA, "config_hash": chash, "egobench_version": egobench.__version__,
            "sim_config": config.to_dict()})

    try:
        return _simulate_into(config, out_dir, partial, chash, states, resuming, progress, stop_after, t_begin)
    except BaseException:
        if not resume and partial.exists():
            shutil.rmtree(partial, ignore_errors=True)
        raise


# ----------------------------------------------------------------------------------------
# the recording
# ----------------------------------------------------------------------------------------
def _make_folders(config: SimConfig, partial: Path) -> None:
    """The partial folder's MPS folder and per-frame folders (raw/ only when raw frames are written)."""
    for sub in (str(MPS_SLAM),) + frame_dirs(config)[1:]:
        (partial / sub).mkdir(parents=True, exist_ok=True)
    if config.write_raw:
        (partial / "raw").mkdir(exist_ok=True)


def _frame_indices(config: SimConfig, first: int, end: int, progress: bool):
    """Frames first..end-1, with a tqdm bar counting from `first` of n_frames when `progress`."""
    iterator = range(first, end)
    if progress:
        iterator = tqdm(iterator, desc=f"simulate {config.recording_name}", unit="frame", initial=first,
                        total=config.n_frames)
    return iterator


def _write_stream_files(setup: CaptureSetup, frames_out: dict[str, list[dict]], partial: Path) -> None:
    """Each stream's camera maps (vignette, valid mask, row time ratio) and transforms.json."""
    for name, cal in setup.calibrations():
        rect, pin = setup.rigs[name]
        stream = partial / setup.streams[name]
        write_camera_maps(stream, rect.warp_vignette(calibrated_vignette(cal, setup.device)).numpy(),
                          rect.valid.numpy(), rect.row_time_ratio(setup.raw.readout_rows).numpy())
        write_transforms(stream, frames_out[name], camera_label=setup.device.label,
                         extra={"calibration": name, "readout_s": setup.clocks.readout_stated_s,
                                "pixel_centre_convention": "integer (projectaria): cx = (W - 1) / 2 is centred"})


def _write_mps_files(setup: CaptureSetup, calib_lines: list[CalibrationRecord], partial: Path) -> None:
    """Trajectory, semi-dense points, online calibration (MPS folder), factory calibration, per-stream links."""
    mps_dir = partial / MPS_SLAM
    setup.trajectory.to_mps_csv(mps_dir / TRAJECTORY_FILE)
    write_semidense_points(mps_dir / POINTS_FILE, setup.semidense.points)
    write_online_calibration(mps_dir / ONLINE_CALIBRATION_FILE, calib_lines)
    write_calibration_json(partial / FACTORY_CALIBRATION_FILE, calibration_record(setup.cals.factory))
    for name in ("online", "factory"):  # the MPS files inside each stream folder, as relative symlinks
        link_mps_files(partial / setup.streams[name], mps_dir)


def _truth_json(setup: CaptureSetup, truth_frames: list[dict]) -> dict:
    """ground_truth/truth.json: the true calibration, calibration errors, hidden effects, units, frame records."""
    config, dev, cals, clocks = setup.config, setup.device, setup.cals, setup.clocks
    noise_model = setup.photometric.noise_model
    return {
        "true_calibration": calibration_record(cals.true).to_json(),
        "calibration_errors": cals.perturbations,
        "hidden_effects": {
            "readout_scale": config.readout_scale, "readout_true_s": clocks.readout_true_s,
            "readout_stated_s": clocks.readout_stated_s,
            "time_offset_s": config.time_offset_s, "time_offset_true_s": cals.true.time_offset_s,
            "exposure_s": config.exposure_s, "vignette_strength": config.vignette_strength,
            "response_gamma": setup.photometric.gamma, "white_balance": list(config.white_balance),
            "exposure_metadata_error": config.exposure_metadata_error,
            "exposure_metadata_frames": sorted(setup.metadata_wrong_frames),
            "noise": config.noise, "full_well_e": noise_model.full_well_e, "read_noise_e": noise_model.read_noise_e,
            "noise_std_factor": config.noise_std_factor, "distortion_k0_delta": config.distortion_k0_delta,
        },
        "device": dev.name, "sensitivity": dev.sensitivity, "vignette_corner": dev.vignette_corner,
        "vignette_power": dev.vignette_power, "exposure_protocol": config.protocol,
        "gt_units": {"radiance": "clean linear irradiance (world radiance units, cd/m^2-like), exposure-averaged, "
                                 "rectified like the online stream's images (float16, clipped at 65000)",
                     "depth": "z in the online rectified camera, metres, 0 = no hit / invalid (float16)",
                     "normal": "unit normal in the online camera frame, 0 = none (float16)"},
        "frames": truth_frames,
    }


def _recording_json(setup: CaptureSetup, result: CaptureResult) -> dict:
    """recording.json: name, kind, device, motion, seed, SimConfig, sizes, fps, time and temporal-sample summary."""
    config, dev = setup.config, setup.device
    H_raw, W_raw = setup.raw.valid.shape
    return {
        "name": config.recording_name, "scene_kind": config.kind, "device": dev.name, "motion": config.motion,
        "seed": config.seed, "sim_config": config.to_dict(), "egobench_version": egobench.__version__,
        "raw_size": [W_raw, H_raw], "rectified_size": [config.rectified_size, config.rectified_size],
        "fps": dev.fps, "simulation_time_s": result.time_s,
        "temporal_samples": {"min": min(result.temporal_samples), "max": max(result.temporal_samples),
                             "mean": float(np.mean(result.temporal_samples))},
    }


def _write_recording_files(setup: CaptureSetup, run: CaptureRun, partial: Path, t_begin: float) -> None:
    """The recording-level files once every frame is done: streams, MPS, truth.json, recording.json."""
    _write_stream_files(setup, run.frames_out, partial)
    _write_mps_files(setup, run.calib_lines, partial)
    run.result.time_s = run.elapsed_before_s + time.perf_counter() - t_begin
    write_json(partial / "ground_truth" / "truth.json", _truth_json(setup, run.truth_frames))
    write_json(partial / "recording.json", _recording_json(setup, run.result))


def _simulate_into(config: SimConfig, out_dir: Path, partial: Path, chash: str, states: list[dict], resuming: bool,
                   progress: bool, stop_after: int | None, t_begin: float) -> CaptureResult:
    """The body of `simulate_recording`: frames len(states).. into `partial`, then the recording files."""
    setup = build_capture_setup(config)
    if resuming:  # frames already completed by an earlier run: their records and the state after the last one
        drop_frames_from(partial, len(states), frame_dirs(config))
    run = restore_run(setup, out_dir, states)
    _make_folders(config, partial)
    end = config.n_frames if stop_after is None else min(config.n_frames, stop_after)
    for k in _frame_indices(config, len(states), end, progress):
        simulate_frame(setup, run, k, partial)
        # the frame's state, written last: a frame without it is redone by a resumed run
        write_json(frame_state_path(partial, k), frame_state(run, k, chash, t_begin), indent=None)
    if end < config.n_frames:  # stopped by stop_after: the partial folder stays for a later run
        run.result.complete, run.result.path = False, partial
        run.result.time_s = run.elapsed_before_s + time.perf_counter() - t_begin
        return run.result
    _write_recording_files(setup, run, partial, t_begin)
    finalise(partial, out_dir)
    return run.result
