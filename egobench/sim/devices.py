"""Device profiles: every number the simulator uses for a camera, with its source.

One frozen dataclass per device (`ARIA_RGB`, `ARIA_SLAM`, `QUEST3`). Numbers come from the real
Aria online calibration shipped with the MPS sample (first line of
``aria_mps_sample/online_calibration.jsonl``, copied here as constants: nothing reads the shared
files at run time), from the paper (Lv et al. 2025) and, where neither states a value, from a
stated assumption.

Resolution scaling. The simulator renders a small raw fisheye image (e.g. 154 px instead of the
2880 px sensor). Lens parameters scale with the pixel-centre convention (f, cx, cy scale; the
distortion coefficients act on angles and do not). The rolling-shutter readout scales with
the number of rows by default (same line time): 16.26 ms at 2880 rows is only 0.72 ms at 128
rows, so rolling-shutter displacements in pixels shrink with the square of the resolution
factor. `readout_s(height, override)` lets a config keep the full-sensor 16.26 ms instead: then
the *angular* smear during readout equals the paper's and the pixel smear shrinks only with the
focal length (the recommended setting when studying motion sampling at tiny resolution).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch loads in the methods that build tensors: the workflow reads the presets at parse time
    import torch

ExposureProtocol = Literal["auto", "indoor", "fixed"]


@dataclass(frozen=True)
class AutoExposure:
    """Auto-exposure limits; AE targets `target_median` on the frame's median luminance."""

    target_median: float = 0.18  # normalised linear signal (1 = full well) for the median luminance: mid-grey 18 %
    exposure_min_s: float = 0.05e-3  # shortest exposure; Aria RGB minimum (assumption: 50 us, a typical CMOS minimum)
    exposure_max_s: float = 10e-3  # longest exposure at 10 fps (assumption: ADT indoor frames run 8.7 ms at gain 16, i.e. AE at its limit)
    gain_min: float = 1.0  # analog gain at base ISO (paper: outdoor recordings use minimum analog gain)
    gain_max: float = 16.0  # largest analog gain (ADT sample frames: gain 16 under indoor light)
    smoothing: float = 0.5  # weight of the previous frame's log exposure*gain (AE does not jump per frame; assumption)


@dataclass(frozen=True)
class NoiseProfile:
    """Per-native-pixel sensor noise (Poisson shot noise + Gaussian read noise, electrons)."""

    full_well_e: float  # electrons at saturation, gain 1
    read_noise_e: float  # read noise standard deviation, electrons


@dataclass(frozen=True)
class DeviceProfile:
    """One camera of one device. Lens params are at the native resolution `native_size`."""

    name: str  # registry key ("aria", "aria_slam", "quest3")
    label: str  # MPS camera label ("camera-rgb", "camera-slam-left")
    projection: Literal["FisheyeRadTanThinPrism"]  # lens model name as in MPS json
    lens_params: tuple[float, ...]  # [15] f, cx, cy, k0..k5, p0, p1, s0..s3 at `native_size` (pixels)
    native_size: tuple[int, int]  # (width, height) the lens params refer to
    sensor_size: tuple[int, int]  # (width, height) of the full sensor readout (readout_full_s refers to it)
    readout_full_s: float  # rolling-shutter readout for sensor_size rows (0 = global shutter)
    fps: float  # frame rate, frames per second
    T_device_camera_translation: tuple[float, float, float]  # metres
    T_device_camera_quat_wxyz: tuple[float, float, float, float]  # unit quaternion (w, x, y, z)
    time_offset_s: float  # TimeOffsetSec_Device_Camera: t_device = t_camera + offset
    response_gamma: float  # camera response: display = linear ** (1 / gamma)
    vignette_corner: float  # lens shading at the image corner relative to the centre (1 = none)
    vignette_power: float  # exponent of egobench.model.formation.radial_vignette ((1 + c r^2)^(-power/2); 4 = cos^4 law)
    noise: NoiseProfile
    sensitivity: float  # normalised signal per (cd/m^2 * s) at gain 1 (see ARIA_RGB notes)
    auto_exposure: AutoExposure = field(default_factory=AutoExposure)
    indoor_exposure_max_s: float = 2e-3  # paper's indoor protocol: exposure capped at 2 ms
    rectified_focal_ratio: float = 0.5  # pinhole focal = ratio * rectified width (paper: 1200 / 2400)
    raw_to_rectified: float = 1.2  # raw size / rectified size (paper: 2880 -> 2400)

    # ----- derived quantities -------------------------------------------------------------
    def lens_params_at(self, width: int, height: int) -> np.ndarray:  # -> [15] float64
        """Lens params scaled to a raw image of width x height (pixel-centre convention)."""
        sx, sy = width / self.native_size[0], height / self.native_size[1]
        if abs(sx - sy) > 1e-6 * max(sx, sy):
            raise ValueError(
                f"{self.name}: raw size {width}x{height} must keep the native aspect ratio "
                f"{self.native_size[0]}x{self.native_size[1]} (Fisheye624 has one focal length)"
            )
        p = np.asarray(self.lens_params, dtype=np.float64).copy()
        p[0] *= sx
        p[1] = (p[1] + 0.5) * sx - 0.5
        p[2] = (p[2] + 0.5) * sy - 0.5
        return p

    def camera(self, width: int, height: int, params: np.ndarray | None = None):
        """The Fisheye624 camera at width x height (optionally with explicit params [15])."""
        import torch

        from egobench.camera import Fisheye624

        p = self.lens_params_at(width, height) if params is None else np.asarray(params, dtype=np.float64)
        return Fisheye624(torch.as_tensor(p, dtype=torch.float64), width, height)

    def readout_s(self, height: int, override: float | None = None) -> float:
        """Readout for `height` rows: the sensor's line time x rows, or `override` seconds."""
        if override is not None:
            if not (override >= 0 and math.isfinite(override)):
                raise ValueError(f"readout_s override: expected a finite value >= 0 seconds, got {override}")
            return float(override)
        return self.readout_full_s * height / self.sensor_size[1]

    @property
    def frame_interval_s(self) -> float:
        return 1.0 / self.fps

    def T_device_camera(self) -> torch.Tensor:  # [4, 4] float64
        """Camera-to-device extrinsics from the calibration constants."""
        import torch

        from egobench.geometry import make_pose, quat_to_rotmat

        q = torch.tensor(self.T_device_camera_quat_wxyz, dtype=torch.float64)
        t = torch.tensor(self.T_device_camera_translation, dtype=torch.float64)
        return make_pose(quat_to_rotmat(q / q.norm()), t)

    def default_raw_size(self, rectified_size: int) -> tuple[int, int]:
        """Raw (width, height) for a square rectified image (paper ratio 2880 / 2400)."""
        h = int(round(rectified_size * self.raw_to_rectified))
        w = int(round(h * self.native_size[0] / self.native_size[1]))
        return w, h


# --------------------------------------------------------------------------------------
# Project Aria RGB camera.
# Lens: "camera-rgb" Projection.Params of the first line of the MPS sample's
# online_calibration.jsonl (image 1408x1408 = the 2880 sensor binned 2x with a crop).
# Extrinsics and time offset: same entry (T_Device_Camera, TimeOffsetSec_Device_Camera).
# Readout: 16.26 ms for the full 2880-row sensor (docs/paper-notes.md §2; the 1408
# sample itself reports 5 ms in its binned mode).
# Frame rate: 10 fps (paper section 5: "10 FPS JPEG-compressed 8MP images").
# Response: gamma 2.2 (paper Eq. 3 default).
# Vignette: Aria's calibrated RGB lens shading falls to roughly 40-50 % of the centre value at
#   the image corners (assumption from the shape of the vignette images shipped with Aria
#   datasets, e.g. ADT/egocentric_splats' vignette.png); we use 0.45 at the raw corner.
# Noise: Sony IMX577-class 1.55 um pixels: full well ~6000 e-, read noise ~2 e- (assumption
#   from published specifications of 1.4-1.6 um CMOS pixels). Noise is modelled per native
#   pixel and NOT reduced by the simulator's downsampling, so a simulated image has the noise
#   texture the paper's 2400 px images have.
# Sensitivity: the reflected-light exposure equation L * t = K * N^2 / S with K = 12.5, f/2.0
#   (Aria RGB aperture) and base ISO S = 100 at gain 1 (assumption) gives mid-grey (0.18 of
#   full well) at L * t = 0.5 cd s / m^2, i.e. sensitivity = 0.18 / 0.5 = 0.36 per cd s / m^2.
#   Check: 1000 cd/m^2 outdoors -> 0.5 ms (the paper: "exposure of 0.5 ms is sufficient");
#   30 cd/m^2 indoors under a 2 ms cap -> gain ~8 (within the 16 limit).
# --------------------------------------------------------------------------------------
ARIA_RGB = DeviceProfile(
    name="aria",
    label="camera-rgb",
    projection="FisheyeRadTanThinPrism",
    lens_params=(
        609.0993041992188, 714.49365234375, 705.4052124023438,
        0.4153491258621216, -0.46660879254341125, 0.0394107960164547,
        1.304983139038086, -1.7682749032974243, 0.6525987982749939,
        7.804521010257304e-05, 0.0006019965512678027,
        -0.0011151430662721395, 0.0006172532448545098, -0.00233874237164855, 0.0016606695717200637,
    ),
    native_size=(1408, 1408),
    sensor_size=(2880, 2880),
    readout_full_s=16.26e-3,
    fps=10.0,
    T_device_camera_translation=(-0.004422292398892606, -0.013187762247850052, -0.0038855180005876594),
    T_device_camera_quat_wxyz=(0.9411611597255661, 0.3335689602188102, 0.0339853373462576, 0.042336946607313145),
    time_offset_s=-0.002499999,
    response_gamma=2.2,
    vignette_corner=0.45,
    vignette_power=4.0,
    noise=NoiseProfile(full_well_e=6000.0, read_noise_e=2.0),
    sensitivity=0.36,
)

# --------------------------------------------------------------------------------------
# Project Aria SLAM camera (global shutter, 640x480, the source of the semi-dense points).
# Lens and extrinsics: "camera-slam-left" of the same calibration line (the device frame is
# this camera's frame, up to the small residual rotation below).
# Semi-dense point noise (fitted to the real sample's semidense_points.csv.gz, 99,472 points):
#   log(inv_dist_std) ~ Normal(mean=-5.78, std=1.36) (16/50/84th percentiles -7.27/-5.78/-4.55),
#   dist_std = inv_dist_std * distance^2 (first-order propagation; the sample's ratio
#   dist_std/inv_dist_std has sqrt median 3.0 m, the typical viewing distance).
# Filter (docs/paper-notes.md §3): keep inv_dist_std < 0.01 and dist_std < 0.02 (the sample keeps 44 %).
# --------------------------------------------------------------------------------------
ARIA_SLAM = DeviceProfile(
    name="aria_slam",
    label="camera-slam-left",
    projection="FisheyeRadTanThinPrism",
    lens_params=(
        242.11708068847656, 320.13153076171875, 241.91163635253906,
        -0.028203224763274193, 0.10392550379037857, -0.07162030041217804,
        0.011307119391858578, 0.0016838924493640661, -0.00046278760419227183,
        0.0014474240597337484, 0.0005256077856756747,
        -0.002205250784754753, 1.4416631529456936e-05, 7.572864706162363e-05, 0.0005642975447699428,
    ),
    native_size=(640, 480),
    sensor_size=(640, 480),
    readout_full_s=0.0,  # global shutter
    fps=30.0,  # Aria SLAM cameras run at 30 fps in the common recording profiles
    T_device_camera_translation=(0.0004100817157705536, 0.0016744963969232557, -0.0027908874334851286),
    T_device_camera_quat_wxyz=(0.9999894842054404, 0.004148791955360089, -0.0019474408062105358, -0.00016272109431038784),
    time_offset_s=0.0,
    response_gamma=1.0,
    vignette_corner=1.0,
    vignette_power=4.0,
    noise=NoiseProfile(full_well_e=10000.0, read_noise_e=3.0),  # unused by the simulator (no SLAM images)
    sensitivity=0.36,
)


@dataclass(frozen=True)
class SemiDenseNoise:
    """SLAM semi-dense point noise model and the MPS filter thresholds (see ARIA_SLAM notes)."""

    log_inv_dist_std_mean: float = -5.78  # mean of log(inv_dist_std [1/m]) in the real sample
    log_inv_dist_std_std: float = 1.36  # std of log(inv_dist_std) in the real sample
    max_inv_dist_std: float = 0.01  # filter threshold, 1/m (docs/paper-notes.md §3)
    max_dist_std: float = 0.02  # filter threshold, m


SEMIDENSE_NOISE = SemiDenseNoise()

# --------------------------------------------------------------------------------------
# Meta Quest 3 RGB passthrough camera (assumptions: Meta publishes no lens calibration).
# 1280x1280 at 30 fps (the largest mode of Meta's Passthrough Camera API); a milder fisheye
# than Aria's (f = 0.5 W, small radial terms: about 110 deg diagonal field of view); readout
# 10 ms for 1280 rows (assumption: a typical 4 MP mobile CMOS line time of ~8 us); placed 3 cm
# beside the tracking frame; no time-offset knowledge (0). Same formation assumptions as Aria.
# --------------------------------------------------------------------------------------
QUEST3 = DeviceProfile(
    name="quest3",
    label="camera-rgb",
    projection="FisheyeRadTanThinPrism",
    lens_params=(
        640.0, 639.5, 639.5,
        0.02, -0.01, 0.0, 0.0, 0.0, 0.0,
        0.0, 0.0,
        0.0, 0.0, 0.0, 0.0,
    ),
    native_size=(1280, 1280),
    sensor_size=(1280, 1280),
    readout_full_s=10e-3,
    fps=30.0,
    T_device_camera_translation=(0.03, 0.0, 0.0),
    T_device_camera_quat_wxyz=(1.0, 0.0, 0.0, 0.0),
    time_offset_s=0.0,
    response_gamma=2.2,
    vignette_corner=0.6,
    vignette_power=4.0,
    noise=NoiseProfile(full_well_e=5000.0, read_noise_e=2.5),
    sensitivity=0.36,
    auto_exposure=AutoExposure(exposure_max_s=8e-3),  # 30 fps: shorter maximum (assumption)
)

#: Devices a SimConfig may name (the RGB stream that is reconstructed).
DEVICES: dict[str, DeviceProfile] = {"aria": ARIA_RGB, "quest3": QUEST3}


def get_device(name: str) -> DeviceProfile:
    """The device profile called `name`; ValueError listing the known ones otherwise."""
    if name not in DEVICES:
        raise ValueError(f"device: unknown device {name!r}, expected one of {sorted(DEVICES)}")
    return DEVICES[name]
