"""True, online ("VIBA") and factory calibrations of the simulated RGB camera.

The *true* calibration is the device profile (lens scaled to the raw size, extrinsics, time
offset), with the hidden effects that concern geometry/timing applied (k0 + distortion_k0_delta,
time offset + time_offset_s). The *online* calibration is what VIBA would estimate: the truth
plus tiny noise, but without knowledge of the hidden effects. The *factory* calibration is the
truth perturbed by the errors VIBA exists to remove. Each error is drawn with a fixed magnitude
(the SimConfig value) in a seeded random direction/sign, so the magnitude is exactly known.

Magnitudes and sources (SimConfig defaults):
- factory extrinsic rotation 0.2 deg. Scale: the SLAM rotational corrections of the real MPS
  sample (summary.json: p50 0.011 deg, p99 0.097 deg; "Recompute Trajectory" p99 0.125 deg) are
  what online refinement changes on well-calibrated rigs; the RGB camera sits on a flexible
  glasses frame that deforms when worn (Engel et al. 2023, "Project Aria", section on online
  calibration), so its factory extrinsic error is taken ~2x the p99 (assumption, 0.1-0.3 deg).
- factory extrinsic translation 1.0 mm: the sample's SLAM translational correction p50 1.06 mm
  (p99 6.6 mm).
- factory focal length 0.2 %: thermal and mechanical focal drift of small plastic/glass lens
  stacks (assumption within 0.1-0.3 %; at 1200 px focal this is 2.4 px at the image edge).
- factory principal point 0.75 px at full resolution (2880 px), scaled with the raw size.
- factory time offset 1 ms: the camera-to-device offset is what VIBA calibrates for the
  rolling-shutter RGB camera (paper section 3); the real sample states -2.5 ms, an error of
  0.5-2 ms is assumed for an uncalibrated unit.
- online (VIBA) errors: rotation 0.01 deg (~ the SLAM rotational correction p50), translation
  0.1 mm, focal 0.01 %, principal point 0.1 px at full resolution, time offset 20 us (assumption:
  an order of magnitude below the factory errors, VIBA's purpose).
Nothing here is tuned to reproduce the paper's numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from egobench import portable_math as pm
from egobench.data.mps import CalibrationRecord, CameraCalibration
from egobench.geometry import so3_exp
from egobench.sim.config import SimConfig
from egobench.sim.devices import ARIA_SLAM, DeviceProfile, get_device


@dataclass
class CalibrationSet:
    """The three RGB calibrations of one simulated recording (raw fisheye resolution)."""

    true: CameraCalibration  # what the simulator captures with
    online: CameraCalibration  # VIBA: truth + small noise, hidden effects unknown
    factory: CameraCalibration  # factory: truth + documented perturbations
    perturbations: dict  # the drawn errors (for truth.json)


def _random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=n)
    return v / pm.norm(v)


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    return so3_exp(torch.as_tensor(axis * angle_rad, dtype=torch.float64)).numpy()


def perturb(cal: CameraCalibration, rng: np.random.Generator, *, rotation_deg: float, translation_mm: float,
            focal_frac: float, principal_px_full: float, time_offset_s: float, full_height: int) -> tuple[CameraCalibration, dict]:
    """A copy of `cal` with errors of the given magnitudes in seeded random directions/signs.

    Rotation error is applied in the camera frame (R' = R exp(axis * angle)); the principal
    point error is `principal_px_full` at `full_height` rows, scaled to cal.height.
    """
    axis = _random_unit(rng, 3)
    R_err = _rotation(axis, math.radians(rotation_deg))
    t_dir = _random_unit(rng, 3)
    f_sign = 1.0 if rng.random() < 0.5 else -1.0
    pp_dir = _random_unit(rng, 2)
    to_sign = 1.0 if rng.random() < 0.5 else -1.0
    T = cal.T_device_camera.copy()
    T[:3, :3] = pm.matmul(T[:3, :3], R_err)
    T[:3, 3] = T[:3, 3] + t_dir * translation_mm * 1e-3
    p = np.asarray(cal.params, dtype=np.float64).copy()
    p[0] *= 1.0 + f_sign * focal_frac
    pp = pp_dir * principal_px_full * cal.height / full_height
    p[1] += pp[0]
    p[2] += pp[1]
    out = CameraCalibration(label=cal.label, params=p, width=cal.width, height=cal.height, T_device_camera=T,
                            time_offset_s=cal.time_offset_s + to_sign * time_offset_s, readout_s=cal.readout_s,
                            projection_name=cal.projection_name)
    info = {
        "rotation_axis": axis.tolist(), "rotation_deg": rotation_deg,
        "translation_m": (t_dir * translation_mm * 1e-3).tolist(),
        "focal_relative": f_sign * focal_frac, "principal_point_px": pp.tolist(),
        "time_offset_s": to_sign * time_offset_s,
    }
    return out, info


def make_calibrations(config: SimConfig) -> CalibrationSet:
    """True, online and factory RGB calibrations for `config` (seeded by config.seed)."""
    dev = get_device(config.device_name)
    w, h = config.raw_shape()
    params = dev.lens_params_at(w, h)
    true_params = params.copy()
    true_params[3] += config.distortion_k0_delta
    T_dc = dev.T_device_camera().numpy()
    stated_offset = dev.time_offset_s
    true = CameraCalibration(label=dev.label, params=true_params, width=w, height=h, T_device_camera=T_dc,
                             time_offset_s=stated_offset + config.time_offset_s, readout_s=config.true_readout_s())
    # What calibration procedures can know: the stated lens (without the hidden k0 change),
    # the stated offset and the stated readout.
    knowable = CameraCalibration(label=dev.label, params=params, width=w, height=h, T_device_camera=T_dc,
                                 time_offset_s=stated_offset, readout_s=config.stated_readout_s())
    rng_online = np.random.default_rng([config.seed, 101])
    rng_factory = np.random.default_rng([config.seed, 202])
    full_h = dev.sensor_size[1]
    online, online_info = perturb(
        knowable, rng_online, rotation_deg=config.online_rotation_deg, translation_mm=config.online_translation_mm,
        focal_frac=config.online_focal_frac, principal_px_full=config.online_principal_px,
        time_offset_s=config.online_time_offset_s, full_height=full_h)
    # Factory errors are relative to the truth (time offset included: MPS corrects it).
    factory_base = CameraCalibration(label=dev.label, params=params, width=w, height=h, T_device_camera=T_dc,
                                     time_offset_s=true.time_offset_s, readout_s=config.stated_readout_s())
    factory, factory_info = perturb(
        factory_base, rng_factory, rotation_deg=config.factory_rotation_deg,
        translation_mm=config.factory_translation_mm, focal_frac=config.factory_focal_frac,
        principal_px_full=config.factory_principal_px, time_offset_s=config.factory_time_offset_s,
        full_height=full_h)
    return CalibrationSet(true=true, online=online, factory=factory,
                          perturbations={"online": online_info, "factory": factory_info})


def slam_camera_calibration() -> CameraCalibration:
    """The SLAM-left camera entry (native 640x480) written beside the RGB camera."""
    dev: DeviceProfile = ARIA_SLAM
    return CameraCalibration(label=dev.label, params=np.asarray(dev.lens_params), width=dev.native_size[0],
                             height=dev.native_size[1], T_device_camera=dev.T_device_camera().numpy(),
                             time_offset_s=0.0, readout_s=0.0)


def calibration_record(rgb: CameraCalibration, tracking_timestamp_us: int | None = None) -> CalibrationRecord:
    """An MPS calibration object holding the SLAM-left camera and `rgb`."""
    return CalibrationRecord(tracking_timestamp_us=tracking_timestamp_us,
                             cameras=[slam_camera_calibration(), rgb], raw={})
