"""How many rolling-shutter pose samples a frame gets: the rule a run renders with (`motion_sampling.estimate_motion`
applies it). Without torch, so that a training config can name it where the workflow parses configs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: The released code's cap on rolling-shutter samples (`_max_rolling_shutter_sample`).
DEFAULT_MAX_SAMPLES = 8

SampleRule = Literal["code", "paper"]


def sampling_problem(max_samples, rule, step_px) -> tuple[str, str] | None:
    """The first of `PoseSampling`'s fields (max_samples, rule, step_px) that is no valid setting and what it
    should be, as (field, message); None when all are valid."""
    if rule not in ("code", "paper"):
        return "rule", f"expected 'code' or 'paper', got {rule!r}"
    if int(max_samples) != max_samples or max_samples < 1:
        return "max_samples", f"expected an integer >= 1, got {max_samples}"
    if not step_px > 0:
        return "step_px", f"expected > 0 pixels of row shear per pose sample, got {step_px}"
    return None


@dataclass(frozen=True)
class PoseSampling:
    """The rule ("code" or "paper", `motion_sampling`), its cap and the pixels of row shear one sample covers
    (the released code: "code", 8, 1 px); checked on construction (`sampling_problem`)."""

    max_samples: int = DEFAULT_MAX_SAMPLES
    rule: SampleRule = "code"
    step_px: float = 1.0

    def __post_init__(self):
        bad = sampling_problem(self.max_samples, self.rule, self.step_px)
        if bad is not None:
            raise ValueError(f"PoseSampling.{bad[0]}: {bad[1]}")
