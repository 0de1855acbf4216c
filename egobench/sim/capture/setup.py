"""What every frame of a recording shares, built once (`build_capture_setup`), and the output helpers."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from torch import Tensor

from egobench.camera import Rectification
from egobench.camera.pinhole import Pinhole
from egobench.data.mps import CameraCalibration, SemiDensePoints
from egobench.model.formation import FormationConfig, FormationModel, PoissonGaussianNoise, radial_vignette
from egobench.sim.camera_calibration import make_calibrations
from egobench.sim.capture.raw import (
    TRAJECTORY_MARGIN_S,
    RawCamera,
    device_trajectory,
    sampled_raw_pixels,
    view_readout_rows,
)
from egobench.sim.capture.resume import stream_names
from egobench.sim.capture.semidense import make_semidense_points
from egobench.sim.config import SimConfig
from egobench.sim.devices import SEMIDENSE_NOISE, DeviceProfile, get_device
from egobench.sim.motion import HeadMotionConfig, simulate_head_motion
from egobench.sim.world import make_scene

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    from egobench.geometry import Trajectory
    from egobench.sim.camera_calibration import CalibrationSet


# ----------------------------------------------------------------------------------------
# the recording
# ----------------------------------------------------------------------------------------
@dataclass
class CaptureResult:
    """Summary of `simulate_recording` (also in recording.json)."""

    path: Path
    n_frames: int
    time_s: float
    temporal_samples: list[int] = field(default_factory=list)
    exposures_s: list[float] = field(default_factory=list)
    gains: list[float] = field(default_factory=list)
    complete: bool = True  # False: stopped by `stop_after`; `path` is then the partial folder
    resumed_from: int = 0  # frames taken over from an earlier run's partial folder


def to_uint8(display: Tensor) -> np.ndarray:
    return (display.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()


def jpeg_roundtrip(img: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def rectification_rig(cal: CameraCalibration, rect_size: int, focal_ratio: float):
    """(Rectification, pinhole) of a calibration: pinhole f = focal_ratio * W, centred, same axes."""
    W = H = int(rect_size)
    f = float(focal_ratio) * W
    pin = Pinhole(fx=f, fy=f, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
    return Rectification.build(cal.camera(), pin), pin


# ----------------------------------------------------------------------------------------
# what every frame of a recording shares (built once)
# ----------------------------------------------------------------------------------------
def calibrated_vignette(cal: CameraCalibration, dev: DeviceProfile) -> Tensor:
    """[H_raw, W_raw] the device's calibrated lens shading for `cal` (radial about its principal point)."""
    p = cal.params
    return radial_vignette((cal.height, cal.width), 1.0 - dev.vignette_corner, dev.vignette_power,
                           centre=(float(p[1]), float(p[2])))


@dataclass
class FrameClocks:
    """When each frame is read out: camera-clock read starts and the true and stated readout."""

    read_start_cam_ns: np.ndarray  # [N] int64 camera-clock read start of each frame
    true_offset_ns: int  # true camera time offset: device clock = camera clock + this
    readout_true_s: float  # true rolling-shutter readout (first to last raw row), s
    readout_stated_s: float  # readout the recording states, s

    def read_start_true_ns(self, k: int) -> int:
        """Device-clock read start of frame k under the true time offset."""
        return int(self.read_start_cam_ns[k] + self.true_offset_ns)


def _device_motion(config: SimConfig, dev: DeviceProfile, scene) -> Trajectory:
    """The device trajectory (T_world_device) over the frames plus TRAJECTORY_MARGIN_S each side."""
    duration_s = 2 * TRAJECTORY_MARGIN_S + config.n_frames / dev.fps
    look = simulate_head_motion(HeadMotionConfig(duration_s=duration_s, setting=config.motion), scene, config.seed)
    return device_trajectory(look, dev)


def _frame_clocks(config: SimConfig, dev: DeviceProfile, trajectory: Trajectory, true_cal: CameraCalibration) -> FrameClocks:
    """Frame read starts at the device's fps from the trajectory's start plus the margin (true offset undone)."""
    interval_ns = int(round(1e9 / dev.fps))
    margin_ns = int(TRAJECTORY_MARGIN_S * 1e9)
    true_offset_ns = int(round(true_cal.time_offset_s * 1e9))
    t_cam = trajectory.start_ns + margin_ns - true_offset_ns + interval_ns * np.arange(config.n_frames, dtype=np.int64)
    return FrameClocks(read_start_cam_ns=t_cam, true_offset_ns=true_offset_ns, readout_true_s=true_cal.readout_s,
                       readout_stated_s=config.stated_readout_s())


@dataclass
class PhotometricTruth:
    """The true image formation of a recording (its hidden parts are absent from the recorded metadata)."""

    gamma: float  # true response gamma
    formation: FormationModel  # ground-truth formation config with this gamma
    noise_model: PoissonGaussianNoise  # after noise_std_factor
    vignette_raw: Tensor  # [H_raw, W_raw] true lens shading: calibrated x hidden extra shading
    white_balance: Tensor  # [3] float32 true per-channel gains


def _photometric_truth(config: SimConfig, dev: DeviceProfile, true_cal: CameraCalibration,
                       raw_hw: tuple[int, int]) -> PhotometricTruth:
    """Response, noise, lens shading and white balance the raw frames are formed with."""
    gamma = config.response_gamma if config.response_gamma is not None else dev.response_gamma
    formation = FormationModel(FormationConfig.ground_truth(gamma=gamma, noise=config.noise))
    noise_model = PoissonGaussianNoise(
        full_well_e=config.full_well_e if config.full_well_e is not None else dev.noise.full_well_e,
        read_noise_e=config.read_noise_e if config.read_noise_e is not None else dev.noise.read_noise_e,
    )
    if config.noise_std_factor != 1.0:
        noise_model = noise_model.scaled(config.noise_std_factor)
    vignette_true = calibrated_vignette(true_cal, dev)
    if config.vignette_strength > 0:
        vignette_true = vignette_true * radial_vignette(raw_hw, config.vignette_strength, dev.vignette_power,
                                                        centre=(float(true_cal.params[1]), float(true_cal.params[2])))
    return PhotometricTruth(gamma=gamma, formation=formation, noise_model=noise_model, vignette_raw=vignette_true,
                            white_balance=torch.tensor(config.white_balance, dtype=torch.float32))


@dataclass
class OnlineTruthRays:
    """Per-pixel rays of the online rectified camera, along which depth and normals are cast."""

    row_time_ratio: Tensor  # [h, w] float64 read-out time of the pixel's raw source / readout (0..1)
    rays_cam: Tensor  # [h, w, 3] float64 camera-frame rays through the pixel centres, z = 1
    valid: Tensor  # [h, w] bool pixels inside the raw image


def _online_truth_rays(rect: Rectification, pin: Pinhole, readout_rows: tuple[int, int] | None) -> OnlineTruthRays:
    """The ground-truth rays of the online rig (Rectification, Pinhole)."""
    return OnlineTruthRays(row_time_ratio=rect.row_time_ratio(readout_rows).to(torch.float64),
                           rays_cam=pin.unproject(pin.pixel_grid(dtype=torch.float64)), valid=rect.valid)


def _metadata_wrong_frames(config: SimConfig) -> set[int]:
    """Frames whose recorded exposure is wrong (hidden effect `exposure_metadata_error`)."""
    rng_meta = np.random.default_rng([config.seed, 404])
    n_bad = int(round(config.exposure_metadata_fraction * config.n_frames)) if config.exposure_metadata_error else 0
    return set(rng_meta.permutation(config.n_frames)[:n_bad].tolist())


@dataclass
class SemiDenseTruth:
    """The recording's semi-dense points: as written, after the MPS filter, and their clean positions."""

    points: SemiDensePoints  # every point, as written to the MPS points file
    filtered: SemiDensePoints  # the points passing the MPS filter (noisy positions)
    clean_world: Tensor  # [M, 3] float64 noise-free world positions of the filtered points
    noisy_world: Tensor  # [M, 3] float64 recorded (noisy) world positions of the filtered points


def _semidense_truth(config: SimConfig, scene, trajectory: Trajectory, clocks: FrameClocks) -> SemiDenseTruth:
    """Surface samples seen from (up to ~64) device positions at the true frame times, with SLAM noise."""
    frame_times_true = clocks.read_start_cam_ns + clocks.true_offset_ns
    positions = trajectory.pose(torch.from_numpy(frame_times_true[:: max(1, config.n_frames // 64)]))[:, :3, 3]
    semidense, clean_points = make_semidense_points(scene, positions, config.n_semidense_points, config.seed)
    sd_filtered = semidense.filtered()
    keep_mask = ((semidense.inv_dist_std < SEMIDENSE_NOISE.max_inv_dist_std)
                 & (semidense.dist_std < SEMIDENSE_NOISE.max_dist_std))
    return SemiDenseTruth(points=semidense, filtered=sd_filtered, clean_world=torch.from_numpy(clean_points[keep_mask]),
                          noisy_world=torch.from_numpy(sd_filtered.points_world))


@dataclass
class CaptureSetup:
    """What every frame of a recording shares, built once by `build_capture_setup`."""

    config: SimConfig
    device: DeviceProfile
    compute: torch.device  # where rays are cast; formation and files stay on the CPU
    cals: CalibrationSet  # true, online, factory
    scene: object
    trajectory: Trajectory  # T_world_device(t_ns)
    clocks: FrameClocks
    raw: RawCamera  # the true raw fisheye camera
    photometric: PhotometricTruth
    rigs: dict[str, tuple[Rectification, Pinhole]]  # calibration name -> its rectified stream's rig
    truth_rays: OnlineTruthRays
    metadata_wrong_frames: set[int]  # frames whose recorded exposure is wrong (hidden)
    semidense: SemiDenseTruth
    streams: dict[str, str]  # calibration name -> stream folder name

    def calibrations(self) -> tuple[tuple[str, CameraCalibration], ...]:
        """(("online", online calibration), ("factory", factory calibration)): the recorded streams."""
        return (("online", self.cals.online), ("factory", self.cals.factory))


def build_capture_setup(config: SimConfig) -> CaptureSetup:
    """Device, calibrations, scene, trajectory, clocks, raw camera, formation, rigs, hidden frames, semi-dense points."""
    dev = get_device(config.device_name)
    compute = config.compute_torch_device()
    cals = make_calibrations(config)
    scene = make_scene(config.kind, config.seed, sun_scale=config.sun_scale, grain=config.grain,
                       variety=config.world_variety)
    trajectory = _device_motion(config, dev, scene)
    clocks = _frame_clocks(config, dev, trajectory, cals.true)
    rigs = {name: rectification_rig(cal, config.rectified_size, config.focal_ratio())
            for name, cal in (("online", cals.online), ("factory", cals.factory))}
    raw = RawCamera.build(cals.true, config.pixel_samples)
    if config.raw_roi:
        raw = raw.restricted_to(sampled_raw_pixels([rect for rect, _ in rigs.values()], raw.valid.shape),
                                meter=sampled_raw_pixels([rigs["online"][0]], raw.valid.shape))
    H_raw, W_raw = raw.valid.shape
    if config.readout_window == "view":
        raw = dataclasses.replace(raw, readout_rows=view_readout_rows(rigs["online"][0], (H_raw, W_raw)))
    photometric = _photometric_truth(config, dev, cals.true, (H_raw, W_raw))
    truth_rays = _online_truth_rays(*rigs["online"], raw.readout_rows)
    wrong = _metadata_wrong_frames(config)
    semidense = _semidense_truth(config, scene, trajectory, clocks)
    return CaptureSetup(config=config, device=dev, compute=compute, cals=cals, scene=scene, trajectory=trajectory,
                        clocks=clocks, raw=raw, photometric=photometric, rigs=rigs, truth_rays=truth_rays,
                        metadata_wrong_frames=wrong, semidense=semidense, streams=stream_names(config))
