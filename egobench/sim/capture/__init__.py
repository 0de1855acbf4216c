"""Capture a synthetic recording: world + head motion + device -> the recording folder.

Per frame (docs/architecture.md conventions):
1. A coarse preview cast at the centre-row time gives the frame's median luminance
   (auto-exposure: exposure and gain) and scene points for the motion estimate.
2. Raw rolling-shutter fisheye capture with the TRUE calibration: raw row r starts exposing at
   t(r) = read_start + r / (H_raw - 1) * readout and integrates S temporal samples at the
   midpoints of S equal sub-intervals of [t(r), t(r) + exposure]; every pixel also integrates
   its area over P = `pixel_samples` sub-pixel positions (k x k stratified grid); rays from
   Fisheye624.unproject of the offset pixel coordinates, posed by trajectory.pose(t) @
   T_device_camera; the mean over the ray samples is the exposure and pixel-area integral
   (clean linear irradiance). Pairing (`sample_schedule`): with S >= P each temporal sample
   takes one sub-pixel position in turn (S rounded up to a multiple of P; no extra cost), with
   S < P every temporal sample takes all P positions (S x P rays). Without area integration
   (P = 1) geometric edges alias: a 0.01 px shift moves edge pixels by several 8-bit levels,
   which breaks first-order (band-limited) residual models such as egobench.diagnose.
3. Image formation (egobench.model.formation): exposure x gain x sensitivity, lens shading (the
   device's calibrated vignette times any hidden extra shading), white balance, clipping at
   full well, Poisson-Gaussian noise, response (gamma), 8-bit; optionally JPEG.
4. Rectification to the pinhole (f = 0.5 W) with the ONLINE and with the FACTORY calibration.
5. Ground truth in the online rectified camera: clean irradiance (rectified like the image),
   depth and normals cast per rectified pixel at the pixel's true mid-exposure time.
6. Semi-dense SLAM points (scene surface samples + SLAM-like inverse-distance noise) and their
   per-frame sparse depth under each calibration.

Temporal samples S: adaptive per frame, so that the image motion between consecutive samples
is at most `max_sample_step_px` (0.15 px): S = clamp(ceil(max_motion_px / 0.15), 1, 32), where
max_motion_px is the largest displacement of preview scene points during the exposure at the
first, middle and last rows. `tests/sim/test_capture.py` checks that doubling S changes the
noise-free display image by less than half an 8-bit level on average.

Interruption and resumption: the recording is built in a hidden partial folder beside the output
(`partial_dir`: `<parent>/.<name>.partial/`). After each frame's files, a small state file
`.resume/NNNNN.json` is written (atomically, last) holding what later frames depend on: the
auto-exposure state, the noise generator state, the frame's transforms/calibration/truth records
and the SimConfig hash. A rerun with `resume="auto"` (the CLI default) continues after the last
frame with a state file and writes a recording byte-identical to an uninterrupted run
(recording.json's simulation_time_s aside). On success the partial folder replaces the output
(os.replace after removing an old output).

Modules (one section each of the former capture.py): `raw` (the raw rolling-shutter capture and its
sample schedules), `auto_exposure`, `semidense` (SLAM points), `setup` (what every frame shares),
`frame` (one frame and the state it carries over), `resume` (the partial folder), `recording`
(`simulate_recording` and the files written at the end).

Code path: `simulate_recording` -> `build_capture_setup` (once: `CaptureSetup`) and `restore_run` (the
`CaptureRun` records and carried state, advanced past resumed frames) -> per frame `capture_raw_frame`
(steps 1-3), `_write_ground_truth` (5), `visible_semidense` and `_write_stream_frame` per calibration
(4, 6), the frame's state file -> `_write_recording_files`.
"""

from egobench.sim.capture.auto_exposure import AutoExposureState
from egobench.sim.capture.raw import (
    RawCamera,
    camera_poses,
    capture_irradiance,
    cast_chunked,
    choose_temporal_samples,
    device_trajectory,
    geometry_cast,
    motion_during_exposure_px,
    preview,
    row_start_times_ns,
    sampled_raw_pixels,
    subpixel_offsets,
    view_readout_rows,
)
from egobench.sim.capture.recording import simulate_recording
from egobench.sim.capture.resume import partial_dir, sim_config_hash, stream_names
from egobench.sim.capture.setup import CaptureResult, CaptureSetup, build_capture_setup

__all__ = [
    "AutoExposureState", "CaptureResult", "CaptureSetup", "RawCamera", "build_capture_setup", "camera_poses",
    "capture_irradiance", "cast_chunked", "choose_temporal_samples", "device_trajectory", "geometry_cast",
    "motion_during_exposure_px", "partial_dir", "preview", "row_start_times_ns", "sampled_raw_pixels",
    "sim_config_hash", "simulate_recording", "stream_names", "subpixel_offsets", "view_readout_rows",
]
