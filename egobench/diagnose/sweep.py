"""The many-hidden-cases table: every effect x several magnitudes x seeds, plus null cases.

Cases come from `egobench.diagnose.synthetic` (analytic moving texture, 48 px, 16 frames), so
the table measures the statistics; a few cases through the full simulator are in the tests.
Per case: detected (verdict == the hidden effect), wrong name, parameter error, held-out gain.
Per effect: detection rate per magnitude, the smallest magnitude detected in every seed; overall:
the false-alarm rate on null cases.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from egobench.diagnose.core import NO_DISCREPANCY, DiagnosisConfig, diagnose_residuals
from egobench.diagnose.synthetic import make_case
from egobench.effects import EFFECTS
from egobench.io_utils import atomic_path, write_json

#: Relative magnitudes of the sweep, as fractions of the plausible range's lower end (below it:
#: how small an effect is still found) and points inside the range.
FRACTIONS_OF_LO = (0.125, 0.25, 0.5, 1.0)


@dataclass
class SweepConfig:
    """Settings of the hidden-case sweep."""

    seeds: int = 3  # seeds per (effect, magnitude)
    null_cases: int = 20  # cases with nothing hidden
    size: int = 48  # image width = height, px
    n_frames: int = 16  # frames per case


def magnitudes(effect: str) -> list[float]:
    """Magnitudes of the sweep for one effect, in the effect's parameter units (deviation from nominal)."""
    return EFFECTS[effect].sweep_magnitudes(FRACTIONS_OF_LO)


def hidden_value(effect: str, magnitude: float, rng: np.random.Generator):
    """A hidden value of ``magnitude`` with a random sign/direction where the effect allows one."""
    return EFFECTS[effect].sweep_value(magnitude, rng)


def parameter_error(effect: str, value, params: dict) -> float | None:
    """Absolute error of the estimate in the parameter's unit (relative for blur, noise, distortion, WB)."""
    return EFFECTS[effect].parameter_error(value, params) if effect in EFFECTS else None


#: Unit of each effect's parameter error.
ERROR_UNITS = {name: e.error_unit for name, e in EFFECTS.items()}


def run_sweep(out_dir: str | Path, config: SweepConfig | None = None, diag: DiagnosisConfig | None = None,
              effects: list[str] | None = None, progress: bool = True) -> dict:
    """Run the sweep; write sweep.csv, sweep.json and sweep.md into out_dir; return the summary."""
    cfg = config or SweepConfig()
    effects = effects or list(EFFECTS)
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"effects: unknown {unknown}; expected names from {list(EFFECTS)}")
    jobs = [(None, 0.0, s) for s in range(cfg.null_cases)]
    for e in effects:
        jobs += [(e, m, s) for m in magnitudes(e) for s in range(cfg.seeds)]
    rows = []
    iterator = tqdm(jobs, desc="diagnose sweep", unit="case") if progress else jobs
    for effect, magnitude, seed in iterator:
        rng = np.random.default_rng([seed, 31337, len(rows)])
        value = None if effect is None else hidden_value(effect, magnitude, rng)
        speed = None if effect is None else EFFECTS[effect].synth_speed_px_s
        kw = {} if speed is None else {"speed_px_s": speed}
        case = make_case(effect, value, seed=1000 + seed, size=cfg.size, n_frames=cfg.n_frames, **kw)
        t0 = time.perf_counter()
        d = diagnose_residuals(case.measured, case.predicted, case.context, diag)
        first = d.named[0] if d.named else None
        rows.append({
            "effect": effect or "none", "magnitude": magnitude, "value": str(value), "seed": seed,
            "verdict": d.verdict, "detected": effect is not None and d.verdict == effect,
            "false_alarm": effect is None and d.verdict != NO_DISCREPANCY,
            "wrong_name": effect is not None and d.verdict not in (effect, NO_DISCREPANCY),
            "param_error": parameter_error(effect, value, first.params) if (first and effect == d.verdict) else None,
            "psnr_gain_db": first.psnr_gain_db if first else 0.0,
            "nll_gain": first.nll_gain_nats_per_px if first else None,
            "runtime_s": time.perf_counter() - t0,
        })
    df = pd.DataFrame(rows)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "sweep.csv") as tmp:
        df.to_csv(tmp, index=False)
    summary = summarise(df)
    write_json(out / "sweep.json", summary)
    with atomic_path(out / "sweep.md") as tmp:
        tmp.write_text(sweep_markdown(summary))
    return summary


def summarise(df) -> dict:
    null = df[df.effect == "none"]
    out = {"schema": "egobench.diagnosis_sweep/1", "n_cases": int(len(df)),
           "false_alarm_rate": float(null.false_alarm.mean()) if len(null) else None,
           "n_null": int(len(null)), "median_runtime_s": float(df.runtime_s.median()), "effects": {}}
    for effect, g in df[df.effect != "none"].groupby("effect", sort=False):
        per_mag = []
        smallest = None
        for mag, gm in g.groupby("magnitude"):
            rate = float(gm.detected.mean())
            errs = gm.param_error.dropna()
            per_mag.append({"magnitude": float(mag), "detection_rate": rate, "wrong_name_rate": float(gm.wrong_name.mean()),
                            "median_param_error": float(errs.median()) if len(errs) else None,
                            "median_psnr_gain_db": float(gm[gm.detected].psnr_gain_db.median()) if gm.detected.any() else None})
            if rate == 1.0 and smallest is None:
                smallest = float(mag)
        out["effects"][effect] = {"magnitudes": per_mag, "smallest_magnitude_always_found": smallest,
                                  "error_unit": ERROR_UNITS[effect], "plausible_range": list(EFFECTS[effect].plausible_range)}
    return out


def sweep_markdown(s: dict) -> str:
    lines = ["# Diagnosis sweep: hidden effects on synthetic moving textures", "",
             f"{s['n_cases']} cases; false-alarm rate on {s['n_null']} null cases: {s['false_alarm_rate']:.2f}; "
             f"median runtime per diagnosis {s['median_runtime_s']:.2f} s.", "",
             "Magnitudes: deviation from nominal in the parameter's unit (log-ratio for response, noise and white balance).", "",
             "| effect | magnitude | detection rate | wrong-name rate | median param error | median PSNR gain (dB) |",
             "|---|---|---|---|---|---|"]
    for effect, e in s["effects"].items():
        for m in e["magnitudes"]:
            err = "-" if m["median_param_error"] is None else f"{m['median_param_error']:.3g} ({e['error_unit']})"
            gain = "-" if m["median_psnr_gain_db"] is None else f"{m['median_psnr_gain_db']:.2f}"
            lines.append(f"| {effect} | {m['magnitude']:.4g} | {m['detection_rate']:.2f} | {m['wrong_name_rate']:.2f} | {err} | {gain} |")
    lines += ["", "| effect | plausible range | smallest magnitude found in every seed |", "|---|---|---|"]
    for effect, e in s["effects"].items():
        lines.append(f"| {effect} | {e['plausible_range']} | {e['smallest_magnitude_always_found']} |")
    return "\n".join(lines) + "\n"
