"""How many rolling-shutter pose samples a frame gets: the rule a run renders with (`motion_sampling.estimate_motion`
applies it). Without torch, so that a training config can name it where the workflow parses configs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: The released code's cap on rolling-shutter samples (`_max_rolling_shutter_sample`).
DEFAULT_MAX_SAMPLES = 8

SampleRule = Literal["code", "paper"]


@dataclass(frozen=True)
class PoseSampling:
    """The rule ("code" or "paper", `motion_sampling`), its cap and the pixels of row shear one sample covers
    (the released code: "code", 8, 1 px)."""

    max_samples: int = DEFAULT_MAX_SAMPLES
    rule: SampleRule = "code"
    step_px: float = 1.0
