"""`SimConfig`: everything one simulated recording depends on, validated before any work.

Fields fall in four groups: what is simulated (scene, device, motion, size), the capture
protocol, the *hidden effects* (physical truth that differs from what the recorded metadata
or calibration states; names follow `egobench.effects.EFFECTS`), and the calibration error
magnitudes (online = VIBA: tiny; factory: the documented perturbations of
`egobench.sim.calibration`).
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
    raw_size: int | None = None  # raw fisheye height in pixels; None = 1.2 x rectified (paper 2880 / 2400)
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
    noise: bool = True  # shot + read noise on
    full_well_e: float | None = None  # electrons at saturation; None = device
    read_noise_e: float | None = None  # read noise electrons; None = device
    noise_std_factor: float = 1.0  # every noise std times this (effects "noise": full well / f^2, read noise / f)
    distortion_k0_delta: float = 0.0  # true k0 = stated (online) k0 + delta (unmodelled distortion)
    # --- calibration error magnitudes (see egobench.sim.calibration for the sources) -------
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

    def raw_shape(self) -> tuple[int, int]:
        """(width, height) of the raw fisheye frame."""
        dev = get_device(self.device_name)
        if self.raw_size is None:
            return dev.default_raw_size(self.rectified_size)
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

        def bad(name: str, expected: str) -> None:
            raise ValueError(f"SimConfig.{name}: expected {expected}, got {getattr(self, name)!r}")

        def finite(name: str, lo: float | None = None, hi: float | None = None, strict_lo: bool = False,
                   allow_none: bool = False) -> None:
            v = getattr(self, name)
            if v is None and allow_none:
                return
            rng = f"in [{lo}, {hi}]" if hi is not None else (f"> {lo}" if strict_lo else f">= {lo}")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(name, f"a finite number {rng if lo is not None else ''}".strip())
            if lo is not None and (v < lo or (strict_lo and v <= lo)):
                bad(name, f"a number {rng}")
            if hi is not None and v > hi:
                bad(name, f"a number {rng}")

        if self.kind not in SCENE_KINDS:
            bad("kind", f"one of {list(SCENE_KINDS)}")
        if self.device is not None and self.device not in DEVICES:
            bad("device", f"one of {sorted(DEVICES)} or None")
        if self.motion not in MOTION_SETTINGS:
            bad("motion", f"one of {list(MOTION_SETTINGS)}")
        if not isinstance(self.compute_device, str) or not re.fullmatch(r"cpu|auto|cuda(:\d+)?", self.compute_device):
            bad("compute_device", "cpu, cuda, cuda:N or auto")
        if self.exposure_protocol is not None and self.exposure_protocol not in EXPOSURE_PROTOCOLS:
            bad("exposure_protocol", f"one of {list(EXPOSURE_PROTOCOLS)} or None")
        for name, lo in (("seed", 0), ("n_frames", 1), ("rectified_size", 8), ("n_semidense_points", 0),
                         ("max_temporal_samples", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                bad(name, f"an integer >= {lo}")
        if self.raw_size is not None and (isinstance(self.raw_size, bool) or not isinstance(self.raw_size, int)
                                          or self.raw_size < 8):
            bad("raw_size", "an integer >= 8 or None")
        if self.temporal_samples is not None and (not isinstance(self.temporal_samples, int)
                                                  or isinstance(self.temporal_samples, bool)
                                                  or self.temporal_samples < 1):
            bad("temporal_samples", "an integer >= 1 or None (adaptive)")
        finite("max_sample_step_px", 0, strict_lo=True)
        ps = self.pixel_samples
        if (isinstance(ps, bool) or not isinstance(ps, int) or ps < 1 or ps > 64
                or int(round(math.sqrt(ps))) ** 2 != ps):
            bad("pixel_samples", "a perfect square in [1, 64] (1 = point sampling, 4 = 2x2, 9 = 3x3, ...)")
        if not isinstance(self.jpeg_quality, int) or not 1 <= self.jpeg_quality <= 100:
            bad("jpeg_quality", "an integer in [1, 100]")
        finite("readout_s", 0, allow_none=True)
        finite("readout_scale", 0, strict_lo=True)
        finite("time_offset_s", -0.05, 0.05)
        finite("exposure_s", 0, strict_lo=True, allow_none=True)
        finite("gain", 0, strict_lo=True, allow_none=True)
        if self.gain is not None and self.exposure_s is None:
            bad("gain", "None unless exposure_s is also set")
        finite("vignette_strength", 0.0, 0.95)
        finite("response_gamma", 0, strict_lo=True, allow_none=True)
        wb = self.white_balance
        if (not isinstance(wb, (tuple, list)) or len(wb) != 3
                or not all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in wb)):
            bad("white_balance", "three positive finite channel gains (r, g, b)")
        finite("exposure_metadata_error", -0.9, 0.9)
        finite("noise_std_factor", 0, strict_lo=True)
        finite("exposure_metadata_fraction", 0.0, 1.0)
        finite("full_well_e", 0, strict_lo=True, allow_none=True)
        finite("read_noise_e", 0, allow_none=True)
        finite("distortion_k0_delta", -1.0, 1.0)
        for name in ("online_rotation_deg", "online_translation_mm", "online_focal_frac", "online_principal_px",
                     "online_time_offset_s", "factory_rotation_deg", "factory_translation_mm",
                     "factory_focal_frac", "factory_principal_px", "factory_time_offset_s"):
            finite(name, 0)
        # Physical consistency with the device.
        dev = get_device(self.device_name)
        try:
            self.raw_shape()
        except ValueError as exc:
            raise ValueError(f"SimConfig.raw_size: {exc}") from exc
        readout = self.true_readout_s()
        if readout >= dev.frame_interval_s:
            raise ValueError(
                f"SimConfig.readout_s/readout_scale: the true readout {readout * 1e3:.3f} ms must be shorter "
                f"than the frame interval {dev.frame_interval_s * 1e3:.3f} ms of {dev.name} ({dev.fps} fps)"
            )
        if self.exposure_s is not None and self.exposure_s + readout >= dev.frame_interval_s:
            raise ValueError(
                f"SimConfig.exposure_s: exposure {self.exposure_s * 1e3:.3f} ms + readout {readout * 1e3:.3f} ms "
                f"must fit in the frame interval {dev.frame_interval_s * 1e3:.3f} ms"
            )
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
    if not isinstance(value, str):
        return tuple(value) if key == "white_balance" and isinstance(value, list) else value
    default = flds[key].default if flds[key].default is not dataclasses.MISSING else None
    text = value.strip()
    try:
        if text.lower() in ("none", "null"):
            return None
        if key == "white_balance":
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


#: Effect name (egobench.effects.EFFECTS) -> how its hidden value becomes SimConfig fields.
def hidden_effect_overrides(name: str, value: Any, affected_fraction: float = 0.25) -> dict[str, Any]:
    """SimConfig overrides that hide `value` of effect `name` (e.g. from Effect.sample_hidden)."""
    table = {
        "readout": lambda v: {"readout_scale": 1.0 + float(v)},  # relative error e: true = stated (1 + e)
        "time_offset": lambda v: {"time_offset_s": float(v)},
        "exposure_blur": lambda v: {"exposure_s": float(v)},
        "vignette": lambda v: {"vignette_strength": float(v)},
        "response": lambda v: {"response_gamma": float(v)},
        "white_balance": lambda v: {"white_balance": tuple(float(x) for x in v)},
        "exposure_metadata": lambda v: {"exposure_metadata_error": float(v),
                                        "exposure_metadata_fraction": float(affected_fraction)},
        "noise": lambda v: {"noise_std_factor": float(v)},
        "distortion": lambda v: {"distortion_k0_delta": float(v)},
    }
    if name not in table:
        raise ValueError(f"hidden effect: unknown name {name!r}; expected one of {sorted(table)}")
    return table[name](value)
