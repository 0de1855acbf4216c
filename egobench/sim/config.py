"""`SimConfig`: everything one simulated recording depends on, validated before any work.

Fields fall in four groups: what is simulated (scene, device, motion, size), the capture
protocol, the *hidden effects* (physical truth that differs from what the recorded metadata
or calibration states; names follow `egobench.effects.EFFECTS`), and the calibration error
magnitudes (online = VIBA: tiny; factory: the documented perturbations of
`egobench.sim.camera_calibration`).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, fields
from typing import Any, Literal

from egobench.sim.devices import DEVICES, get_device

SceneKind = Literal["outdoor", "indoor", "object", "quest3"]
SCENE_KINDS: tuple[str, ...] = ("outdoor", "indoor", "object", "quest3")
MOTION_SETTINGS: tuple[str, ...] = ("normal", "fast", "static")
EXPOSURE_PROTOCOLS: tuple[str, ...] = ("auto", "indoor", "fixed")

#: Per scene kind: (device, exposure protocol, motion). Paper: outdoor = auto-exposure with
#: minimum gain; indoor = 2 ms cap (section 5); DTC objects = fixed exposure and gain in a lab
#: (the first frame's 2 ms-capped auto-exposure, held);
#: the Quest 3 recording = an indoor room with the Quest's auto-exposure.
KIND_DEFAULTS: dict[str, tuple[str, str]] = {
    "outdoor": ("aria", "auto"),
    "indoor": ("aria", "indoor"),
    "object": ("aria", "fixed"),
    "quest3": ("quest3", "auto"),
}


@dataclass
class SimConfig:
    """One synthetic recording. `validate()` is called by `simulate_recording` first."""

    # --- what is simulated -------------------------------------------------------------
    kind: str = "outdoor"  # scene kind: outdoor | indoor | object | quest3 (egobench.sim.world.make_scene)
    seed: int = 0  # one seed drives scene, motion, noise and calibration errors
    device: str | None = None  # device profile (egobench.sim.devices.DEVICES); None = the kind's default
    motion: str = "normal"  # head motion setting: normal | fast | static (egobench.sim.motion)
    n_frames: int = 120  # frames to capture
    rectified_size: int = 128  # rectified pinhole image width = height, pixels (paper: 2400)
    rectified_focal_ratio: float | None = None  # rectified pinhole focal / width; None = the device's (Aria: 0.5, a 90 deg view as the paper's 1200 / 2400). Larger = a narrower view with more pixels per degree (docs/similarity.md)
    raw_roi: bool = False  # cast only the raw pixels the rectified streams sample (+2 px); the rest of the raw frame stays black and auto-exposure meters that region: same images, far fewer rays when the rectified view is narrow
    readout_window: str = "sensor"  # rows the rolling shutter reads over readout_s: "sensor" (every raw row, as Aria) or "view" (an ROI readout of the rows the online view samples: a narrow view then spans the readout as the paper's 90 deg view spans 78 % of it; docs/similarity.md)
    raw_size: int | None = None  # raw fisheye height in pixels; None = 1.2 x rectified x (focal ratio / the device's) (paper 2880 / 2400)
    temporal_samples: int | None = None  # exposure samples S per row; None = adaptive (see max_sample_step_px)
    max_sample_step_px: float = 0.15  # adaptive S: image motion between two temporal samples stays below this
    max_temporal_samples: int = 32  # upper bound of the adaptive S
    pixel_samples: int = 4  # sub-pixel positions each raw pixel integrates (k x k stratified grid, a perfect square; 4 = 2x2, 1 = point sampling); paired with temporal samples when S >= P (no extra cost), else S x P rays (egobench.sim.capture.sample_schedule)
    jpeg: bool = False  # JPEG-compress the raw frames like Aria's recordings
    jpeg_quality: int = 95  # JPEG quality when jpeg is on
    n_semidense_points: int = 10000  # semi-dense SLAM points sampled before the MPS filter (~45 % pass it)
    exposure_protocol: str | None = None  # auto | indoor (2 ms cap) | fixed; None = the kind's default
    readout_s: float | None = None  # stated readout in seconds; None = device line time x raw rows (see devices.py)
    write_raw: bool = False  # also write raw fisheye frames to raw/
    # --- hidden effects (truth that the recorded metadata/calibration does not state) ------
    readout_scale: float = 1.0  # true readout = stated readout x readout_scale
    time_offset_s: float = 0.0  # true camera time offset minus the offset the online calibration states, s
    exposure_s: float | None = None  # fixed true exposure (s) for every frame, overriding auto-exposure
    gain: float | None = None  # fixed analog gain with exposure_s; None = from the exposure protocol
    vignette_strength: float = 0.0  # unmodelled extra lens shading: corner attenuation fraction absent from vignette.png
    response_gamma: float | None = None  # true response gamma; None = device default (2.2), models assume 2.2
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)  # true per-channel gains (not recorded)
    exposure_metadata_error: float = 0.0  # recorded exposure = true x (1 + error) on the affected frames (signed)
    exposure_metadata_fraction: float = 0.0  # fraction of frames whose exposure metadata is wrong
    grain: float = 0.0  # fractal albedo grain on every surface, 0.5 m down to 4 mm, 1/f amplitude spectrum (egobench.sim.world.grain_factor): relative amplitude in [0, 1]
    world_variety: float = 0.0  # 0: every seed the kind's one world, jittered; up to 1: each seed another world, its layout, materials and lights redrawn (egobench.sim.world.variety)
    sun_scale: float = 1.0  # sun illuminance x this (outdoor scenes; 1 = 60 klux against a 4 klux sky): the scene's sun-to-shade dynamic range
    noise: bool = True  # shot + read noise on
    full_well_e: float | None = None  # electrons at saturation; None = device
    read_noise_e: float | None = None  # read noise electrons; None = device
    noise_std_factor: float = 1.0  # every noise std times this (effects "noise": full well / f^2, read noise / f)
    distortion_k0_delta: float = 0.0  # true k0 = stated (online) k0 + delta (unmodelled distortion)
    # --- calibration error magnitudes (see egobench.sim.camera_calibration for the sources) -------
    online_rotation_deg: float = 0.01  # VIBA extrinsic rotation error
    online_translation_mm: float = 0.1  # VIBA extrinsic translation error
    online_focal_frac: float = 1e-4  # VIBA relative focal error
    online_principal_px: float = 0.1  # VIBA principal point error at full (2880 px) resolution
    online_time_offset_s: float = 2e-5  # VIBA time offset error
    factory_rotation_deg: float = 0.2  # factory extrinsic rotation error
    factory_translation_mm: float = 1.0  # factory extrinsic translation error
    factory_focal_frac: float = 0.002  # factory relative focal error
    factory_principal_px: float = 0.75  # factory principal point error at full resolution
    factory_time_offset_s: float = 1e-3  # factory time offset error
    name: str | None = None  # recording name; None = "<kind>_<seed>"
    compute_device: str = "cpu"  # where rays are cast: cpu | cuda | cuda:N | auto (cuda when available); GPU results differ from the CPU's by float rounding

    # ------------------------------------------------------------------------------------
    @property
    def device_name(self) -> str:
        return self.device if self.device is not None else KIND_DEFAULTS.get(self.kind, ("aria", "auto"))[0]

    @property
    def protocol(self) -> str:
        if self.exposure_protocol is not None:
            return self.exposure_protocol
        return KIND_DEFAULTS.get(self.kind, ("aria", "auto"))[1]

    @property
    def recording_name(self) -> str:
        return self.name if self.name is not None else f"{self.kind}_{self.seed}"

    def focal_ratio(self) -> float:
        """Rectified pinhole focal length / rectified width (``rectified_focal_ratio`` or the device's)."""
        dev = get_device(self.device_name)
        return float(dev.rectified_focal_ratio if self.rectified_focal_ratio is None else self.rectified_focal_ratio)

    def raw_shape(self) -> tuple[int, int]:
        """(width, height) of the raw fisheye frame; by default its focal length keeps the device's
        raw-to-rectified ratio at the rectified focal length (a narrower view needs a finer raw frame)."""
        dev = get_device(self.device_name)
        if self.raw_size is None:
            zoom = self.focal_ratio() / dev.rectified_focal_ratio
            return dev.default_raw_size(int(round(self.rectified_size * zoom)))
        w = int(round(self.raw_size * dev.native_size[0] / dev.native_size[1]))
        return w, int(self.raw_size)

    def stated_readout_s(self) -> float:
        dev = get_device(self.device_name)
        return dev.readout_s(self.raw_shape()[1], self.readout_s)

    def true_readout_s(self) -> float:
        return self.stated_readout_s() * self.readout_scale

    def compute_torch_device(self) -> "torch.device":
        """The torch device rays are cast on (``compute_device``; "auto": CUDA when available)."""
        import torch

        if self.compute_device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        dev = torch.device(self.compute_device)
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"SimConfig.compute_device: {self.compute_device!r} but CUDA is not available "
                             "on this machine (use cpu or auto)")
        return dev

    def validate(self) -> "SimConfig":
        """Raise ValueError naming the first bad field and the expected form; return self."""
        _check_choices(self)
        _check_sampling(self)
        _check_effects(self)
        for name in ("online_rotation_deg", "online_translation_mm", "online_focal_frac", "online_principal_px",
                     "online_time_offset_s", "factory_rotation_deg", "factory_translation_mm",
                     "factory_focal_frac", "factory_principal_px", "factory_time_offset_s"):
            _check_number(self, name, 0)
        _check_device_timing(self)
        return self

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["white_balance"] = list(self.white_balance)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SimConfig":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"SimConfig: unknown field(s) {unknown}; known fields: {sorted(names)}")
        d = dict(d)
        if "white_balance" in d and isinstance(d["white_balance"], list):
            d["white_balance"] = tuple(d["white_balance"])
        return cls(**d)

    @classmethod
    def from_overrides(cls, kind: str, seed: int, overrides: dict[str, Any] | None = None) -> "SimConfig":
        """Defaults for `kind`, then `overrides` (field -> value; strings are parsed). Validated."""
        cfg = cls(kind=kind, seed=seed)
        for key, value in (overrides or {}).items():
            setattr(cfg, key, _parse_field(key, value))
        return cfg.validate()


def _field_types() -> dict[str, Any]:
    return {f.name: f for f in fields(SimConfig)}


def _parse_field(key: str, value: Any) -> Any:
    """Convert a `--set key=value` string to the field's type; ValueError names the field."""
    flds = _field_types()
    if key not in flds:
        raise ValueError(f"SimConfig: unknown field {key!r}; known fields: {sorted(flds)}")
    is_tuple = str(flds[key].type).startswith("tuple")  # (per-channel gains)
    if not isinstance(value, str):
        return tuple(value) if is_tuple and isinstance(value, list) else value
    default = flds[key].default if flds[key].default is not dataclasses.MISSING else None
    text = value.strip()
    try:
        if text.lower() in ("none", "null"):
            return None
        if is_tuple:
            parts = [float(x) for x in text.strip("()[] ").split(",")]
            return tuple(parts)
        type_name = str(flds[key].type)
        if isinstance(default, bool) or type_name.startswith("bool"):
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError("not a boolean")
        if type_name.startswith("int"):
            return int(text)
        if type_name.startswith("float"):
            return float(text)
        if type_name.startswith("str"):
            return text
    except ValueError as exc:
        raise ValueError(f"SimConfig.{key}: cannot parse {value!r} as {flds[key].type} ({exc})") from exc
    return text


def hidden_effect_overrides(name: str, value: Any, affected_fraction: float = 0.25) -> dict[str, Any]:
    """SimConfig overrides that hide `value` of effect `name` (e.g. from Effect.sample_hidden): the
    effect's own `sim_overrides` (egobench/effects/<name>.py)."""
    from egobench.effects import EFFECTS  # here, not at the top: the effects load torch and scipy

    if name not in EFFECTS:
        raise ValueError(f"hidden effect: unknown name {name!r}; expected one of {sorted(EFFECTS)}")
    return EFFECTS[name].sim_overrides(value, affected_fraction)


# ----------------------------------------------------------------------------- validation steps
def _bad(cfg: SimConfig, name: str, expected: str) -> None:
    """ValueError naming field ``name`` of cfg, what was expected and its value."""
    raise ValueError(f"SimConfig.{name}: expected {expected}, got {getattr(cfg, name)!r}")


def _check_number(cfg: SimConfig, name: str, lo: float | None = None, hi: float | None = None,
                  strict_lo: bool = False, allow_none: bool = False) -> None:
    """Field ``name`` is a finite number (not a bool) in [lo, hi] (> lo when strict_lo), or None when allowed."""
    v = getattr(cfg, name)
    if v is None and allow_none:
        return
    rng = f"in [{lo}, {hi}]" if hi is not None else (f"> {lo}" if strict_lo else f">= {lo}")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        _bad(cfg, name, f"a finite number {rng if lo is not None else ''}".strip())
    if lo is not None and (v < lo or (strict_lo and v <= lo)):
        _bad(cfg, name, f"a number {rng}")
    if hi is not None and v > hi:
        _bad(cfg, name, f"a number {rng}")


def _check_choices(cfg: SimConfig) -> None:
    """kind, device, motion, compute_device and exposure_protocol name known choices."""
    if cfg.kind not in SCENE_KINDS:
        _bad(cfg, "kind", f"one of {list(SCENE_KINDS)}")
    if cfg.device is not None and cfg.device not in DEVICES:
        _bad(cfg, "device", f"one of {sorted(DEVICES)} or None")
    if cfg.motion not in MOTION_SETTINGS:
        _bad(cfg, "motion", f"one of {list(MOTION_SETTINGS)}")
    if not isinstance(cfg.compute_device, str) or not re.fullmatch(r"cpu|auto|cuda(:\d+)?", cfg.compute_device):
        _bad(cfg, "compute_device", "cpu, cuda, cuda:N or auto")
    if cfg.exposure_protocol is not None and cfg.exposure_protocol not in EXPOSURE_PROTOCOLS:
        _bad(cfg, "exposure_protocol", f"one of {list(EXPOSURE_PROTOCOLS)} or None")


def _check_sampling(cfg: SimConfig) -> None:
    """Counts and sizes (seed, frames, image sizes, temporal and pixel samples, JPEG quality)."""
    for name, lo in (("seed", 0), ("n_frames", 1), ("rectified_size", 8), ("n_semidense_points", 0),
                     ("max_temporal_samples", 1)):
        v = getattr(cfg, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            _bad(cfg, name, f"an integer >= {lo}")
    if cfg.raw_size is not None and (isinstance(cfg.raw_size, bool) or not isinstance(cfg.raw_size, int)
                                     or cfg.raw_size < 8):
        _bad(cfg, "raw_size", "an integer >= 8 or None")
    if cfg.temporal_samples is not None and (not isinstance(cfg.temporal_samples, int)
                                             or isinstance(cfg.temporal_samples, bool)
                                             or cfg.temporal_samples < 1):
        _bad(cfg, "temporal_samples", "an integer >= 1 or None (adaptive)")
    _check_number(cfg, "max_sample_step_px", 0, strict_lo=True)
    _check_number(cfg, "rectified_focal_ratio", 0.1, 20.0, allow_none=True)
    if not isinstance(cfg.raw_roi, bool):
        _bad(cfg, "raw_roi", "true or false")
    if cfg.readout_window not in ("sensor", "view"):
        _bad(cfg, "readout_window", "'sensor' or 'view'")
    ps = cfg.pixel_samples
    if (isinstance(ps, bool) or not isinstance(ps, int) or ps < 1 or ps > 64
            or int(round(math.sqrt(ps))) ** 2 != ps):
        _bad(cfg, "pixel_samples", "a perfect square in [1, 64] (1 = point sampling, 4 = 2x2, 9 = 3x3, ...)")
    if not isinstance(cfg.jpeg_quality, int) or not 1 <= cfg.jpeg_quality <= 100:
        _bad(cfg, "jpeg_quality", "an integer in [1, 100]")


def _check_effects(cfg: SimConfig) -> None:
    """Readout, exposure and the hidden effects' magnitudes are in their ranges."""
    _check_number(cfg, "readout_s", 0, allow_none=True)
    _check_number(cfg, "readout_scale", 0, strict_lo=True)
    _check_number(cfg, "time_offset_s", -0.05, 0.05)
    _check_number(cfg, "exposure_s", 0, strict_lo=True, allow_none=True)
    _check_number(cfg, "gain", 0, strict_lo=True, allow_none=True)
    if cfg.gain is not None and cfg.exposure_s is None:
        _bad(cfg, "gain", "None unless exposure_s is also set")
    _check_number(cfg, "vignette_strength", 0.0, 0.95)
    _check_number(cfg, "response_gamma", 0, strict_lo=True, allow_none=True)
    wb = cfg.white_balance
    if (not isinstance(wb, (tuple, list)) or len(wb) != 3
            or not all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in wb)):
        _bad(cfg, "white_balance", "three positive finite channel gains (r, g, b)")
    _check_number(cfg, "exposure_metadata_error", -0.9, 0.9)
    _check_number(cfg, "noise_std_factor", 0, strict_lo=True)
    _check_number(cfg, "sun_scale", 0.0)
    _check_number(cfg, "grain", 0.0, 1.0)
    _check_number(cfg, "world_variety", 0.0, 1.0)
    _check_number(cfg, "exposure_metadata_fraction", 0.0, 1.0)
    _check_number(cfg, "full_well_e", 0, strict_lo=True, allow_none=True)
    _check_number(cfg, "read_noise_e", 0, allow_none=True)
    _check_number(cfg, "distortion_k0_delta", -1.0, 1.0)


def _check_device_timing(cfg: SimConfig) -> None:
    """Physical consistency with the device: the raw size, and readout (+ exposure) within a frame interval."""
    dev = get_device(cfg.device_name)
    try:
        cfg.raw_shape()
    except ValueError as exc:
        raise ValueError(f"SimConfig.raw_size: {exc}") from exc
    readout = cfg.true_readout_s()
    if readout >= dev.frame_interval_s:
        raise ValueError(
            f"SimConfig.readout_s/readout_scale: the true readout {readout * 1e3:.3f} ms must be shorter "
            f"than the frame interval {dev.frame_interval_s * 1e3:.3f} ms of {dev.name} ({dev.fps} fps)"
        )
    if cfg.exposure_s is not None and cfg.exposure_s + readout >= dev.frame_interval_s:
        raise ValueError(
            f"SimConfig.exposure_s: exposure {cfg.exposure_s * 1e3:.3f} ms + readout {readout * 1e3:.3f} ms "
            f"must fit in the frame interval {dev.frame_interval_s * 1e3:.3f} ms"
        )
