"""The hidden-case sweep on TRAINED runs (issue 15): recordings simulated with one hidden effect
from `egobench.effects` (or none), trained with the CPU preset, diagnosed from the run's renders
(`--source run`, calibrated against the model's own error), tabulated.

Each case lives in OUT/cases/<case>/ (recording/, run/, diagnosis/, case.json written last), so an
interrupted or failed case is redone alone: finished cases are read back, a partial simulation or
training resumes (`resume="auto"`), and a failing case is recorded with its error and skipped.
"""

from __future__ import annotations

import json
import math
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from egobench.data import load_recording
from egobench.data.layout import MPS_SLAM, ONLINE_CALIBRATION_FILE, recording_root
from egobench.data.mps import read_online_calibration
from egobench.diagnose.core import NO_DISCREPANCY, RECONSTRUCTION_ERROR, DiagnosisConfig, diagnose_residuals
from egobench.diagnose.report import write_report
from egobench.diagnose.sources import recording_rectification, run_source
from egobench.diagnose.sweep import ERROR_UNITS, parameter_error
from egobench.effects import EFFECTS
from egobench.evaluate import held_out_psnr
from egobench.io_utils import atomic_path, write_json
from egobench.model.formation import radial_vignette
from egobench.model.shading import farthest_corner
from egobench.sim import capture
from egobench.sim.config import SimConfig, hidden_effect_overrides
from egobench.sim.devices import get_device
from egobench.train import preset_config, train

#: Hidden magnitudes (deviation from nominal, the effect's unit; white balance and response: see
#: `Effect.trained_value`) at the sizes of issue 15's targets (each effect's `trained_magnitudes`).
DEFAULT_MAGNITUDES = {name: e.trained_magnitudes for name, e in EFFECTS.items()}
#: A case's learned shading is called a vignette above the nulls' mean plus this many standard deviations.
EXTENSION_SIGMAS = 3.0
#: Setup fields of a sweep that a diagnosed run's should match (its nulls and retention depend on them).
SETUP_FIELDS = ("method", "size", "n_frames", "iterations")
#: Photometric effects (the default set of the sweep).
PHOTOMETRIC = tuple(name for name, e in EFFECTS.items() if e.in_trained_sweep)


@dataclass
class TrainedSweepConfig:
    """Settings of the trained-run sweep (defaults: the small version; see docs/diagnosis.md)."""

    null_cases: int = 6  # recordings with nothing hidden (different scene seeds)
    seeds: int = 1  # cases per (effect, magnitude)
    effects: tuple[str, ...] = PHOTOMETRIC
    kind: str = "indoor"  # scene kind (egobench.sim.world)
    motion: str = "fast"  # head motion (egobench.sim.motion): image-fixed effects need the scene to move across the image
    size: int = 40  # rectified width = height, px
    n_frames: int = 24
    iterations: int = 800  # CPU preset, schedule scaled (300: 26.6 dB median held out, 800: 31.5 dB at 40 px)
    method: str = "ours"
    magnitudes: dict = field(default_factory=lambda: dict(DEFAULT_MAGNITUDES))
    # also train each case with the learnable lens shading (egobench.model.shading) and call a vignette when the
    # learned corner attenuation exceeds the nulls' mean + EXTENSION_SIGMAS sd (trained runs absorb it)
    shading_extension: bool = True
    # further SimConfig fields of every recording (e.g. the hard cases' fixed 1 ms exposure and narrow view:
    # docs/diagnosis.md "Hard cases"); applied before the hidden effect's own overrides
    sim: dict = field(default_factory=dict)
    seed_offset: int = 0  # added to every case's simulation seed (exploratory runs on other seeds)

    def validate(self) -> "TrainedSweepConfig":
        unknown = [e for e in self.effects if e not in EFFECTS]
        if unknown:
            raise ValueError(f"TrainedSweepConfig.effects: unknown {unknown}; expected names from {list(EFFECTS)}")
        for name, lo in (("null_cases", 0), ("seeds", 1), ("size", 16), ("n_frames", 9), ("iterations", 1)):
            if int(getattr(self, name)) < lo:
                raise ValueError(f"TrainedSweepConfig.{name}: expected an integer >= {lo}, got {getattr(self, name)}")
        unknown = sorted(set(self.sim) - set(SimConfig.__dataclass_fields__))
        if unknown:
            raise ValueError(f"TrainedSweepConfig.sim: unknown SimConfig fields {unknown}")
        return self


def hidden_value(effect: str, magnitude: float, rng: np.random.Generator):
    """A hidden value of ``magnitude`` with a random sign (response: gamma = 2.2 +- magnitude; white
    balance: R and B gains exp(+-magnitude) in opposite directions, G = 1; `Effect.trained_value`)."""
    return EFFECTS[effect].trained_value(magnitude, rng)


def cases(cfg: TrainedSweepConfig) -> list[dict]:
    """Every case: {id, effect (None = null), magnitude, value, sim_seed}."""
    out = [{"id": f"null_s{s}", "effect": None, "magnitude": 0.0, "value": None, "sim_seed": cfg.seed_offset + 100 + s}
           for s in range(cfg.null_cases)]
    for k, effect in enumerate(cfg.effects):
        for mag in cfg.magnitudes.get(effect, DEFAULT_MAGNITUDES[effect]):
            for s in range(cfg.seeds):
                rng = np.random.default_rng([s, k, 1515] + ([cfg.seed_offset] if cfg.seed_offset else []))
                out.append({"id": f"{effect}_{mag:g}_s{s}", "effect": effect, "magnitude": float(mag),
                            "value": hidden_value(effect, float(mag), rng),
                            "sim_seed": cfg.seed_offset + 200 + 10 * k + s})
    return out


def _run_case(case: dict, cfg: TrainedSweepConfig, case_dir: Path, diag: DiagnosisConfig) -> dict:
    """Simulate, train and diagnose one case (each step resumes) -> the diagnosis record."""
    overrides = {"n_frames": cfg.n_frames, "rectified_size": cfg.size, "readout_s": 0.01626, "motion": cfg.motion,
                 **cfg.sim}
    if case["effect"] is not None:
        overrides.update(hidden_effect_overrides(case["effect"], case["value"]))
    rec = case_dir / "recording"
    if not (rec / "recording.json").is_file():
        capture.simulate_recording(SimConfig.from_overrides(cfg.kind, case["sim_seed"], overrides), rec,
                                   progress=False, resume="auto")
    run = case_dir / "run"
    tc = replace(preset_config("cpu"), max_side=0, device="cpu").scaled_to(cfg.iterations)
    train_once(rec, cfg.method, tc, run)
    if case["effect"] is not None and EFFECTS[case["effect"]].hidden_on_raw_sensor:  # the truth as the view sees it
        case["value_in_view"] = vignette_in_view(rec, case["value"])
    if cfg.shading_extension:  # the model extension's learned shading (set on the case)
        record = train_once(rec, cfg.method, replace(tc, learn_shading=True), case_dir / "run_shading")
        case["learned_shading"] = float(record["learned_shading"]["corner_attenuation"])
        case["extension_gain_db"] = extension_gain(rec, run, case_dir / "run_shading")["gain_db"]
    src = run_source(rec, run, progress=False)
    d = diagnose_residuals(src.measured, src.predicted, src.context, replace(diag, trained_run=True))
    return write_report(case_dir / "diagnosis", d, src.measured, src.predicted,
                        title=f"Trained-run sweep case {case['id']}", extra={"case": case})


def train_once(rec, method: str, tc, run: Path, progress: bool = False) -> dict:
    """Train ``run`` (``rec``: a recording folder or a loaded Recording) unless a complete train.json
    is there (an interrupted run resumes); its record."""
    done = run / "train.json"
    if not done.is_file() or not json.loads(done.read_text()).get("complete"):
        train(rec, method, tc, run, resume="auto", progress=progress)
    return json.loads(done.read_text())


def extension_gain(recording, base_run: str | Path, extension_run: str | Path) -> dict:
    """Held-out PSNR (dB, mean over the held-out frames, as eval.json) of the run and of its extension
    run, and the gain of the extension; nothing is written into either run (here rather than in
    `egobench.diagnose.extension`, which builds on this module: the sweep's cases and a user's run share it)."""
    base = float(np.mean(held_out_psnr(recording, base_run)))
    ext = float(np.mean(held_out_psnr(recording, extension_run)))
    return {"base_psnr_db": base, "extension_psnr_db": ext, "gain_db": ext - base}


def vignette_in_view(recording_dir: str | Path, corner_attenuation: float) -> float:
    """The attenuation, at the rectified view's corner farthest from the principal point, of a hidden
    lens shading that attenuates the RAW image's corner by ``corner_attenuation`` (the simulator's
    parameter): the diagnosis estimates the shading in the view, normalised at that corner."""
    rec = load_recording(recording_dir, "online")
    dev = get_device((rec.meta or {}).get("device") or "aria")
    rect, _ = recording_rectification(recording_dir, "online", dev, rec.camera)
    cal = read_online_calibration(recording_root(recording_dir) / MPS_SLAM / ONLINE_CALIBRATION_FILE)[0].camera(dev.label)
    raw = radial_vignette((cal.height, cal.width), corner_attenuation, dev.vignette_power,
                          centre=(float(cal.params[1]), float(cal.params[2])))
    view = rect.warp_vignette(raw.float()).numpy()
    u, v = farthest_corner(rec.camera)
    return float(1.0 - view[v, u])


def retention(effect: str | None, truth, record: dict | None) -> float | None:
    """How much of a hidden effect survives training: round 1's estimate of it (named or not) over
    the truth, both as deviations from nominal (1: all of it, 0: absorbed, < 0: the wrong sign).
    None for effects without one scalar parameter (white balance) or without an estimate."""
    if effect not in EFFECTS or record is None or not record.get("rounds"):
        return None
    key, nominal = EFFECTS[effect].estimate_key or EFFECTS[effect].parameter, EFFECTS[effect].nominal
    fit = next((r for r in record["rounds"][0] if r["name"] == effect), None)
    est = None if fit is None else fit.get("params", {}).get(key)
    if not isinstance(est, (int, float)) or not isinstance(truth, (int, float)) or truth == nominal:
        return None
    return float((est - nominal) / (truth - nominal))


def log_exposure_spread(record: dict | None) -> float | None:
    """Std of log(exposure x gain) across the fitted frames, from the response test's calibration
    (what a response error on a trained run is tested through); None where the test did not run."""
    rounds = (record or {}).get("rounds") or [[]]
    spreads = [((r.get("params") or {}).get("calibration") or {}).get("log_exposure_spread") for r in rounds[0]]
    spread = next((x for x in spreads if x is not None), None)  # only the response test records one
    return float(spread) if isinstance(spread, (int, float)) else None


def _row(case: dict, record: dict | None, error: str | None, runtime_s: float) -> dict:
    effect = case["effect"]
    verdict = record["verdict"] if record else "error"
    first = record["named"][0] if record and record["named"] else None
    later = [n["name"] for n in (record or {}).get("named", [])[1:]]
    me = (record or {}).get("model_error") or {}
    silent = verdict in (NO_DISCREPANCY, RECONSTRUCTION_ERROR)
    # named a cause the hidden one contains (time offset for a readout error), with the hidden one as its "or"
    contained = bool(first and effect is not None and verdict != effect
                     and any(a["cause"] == effect for a in first["params"].get("or", [])))
    return {
        "case": case["id"], "effect": effect or "none", "magnitude": case["magnitude"], "value": json.dumps(case["value"]),
        "verdict": verdict, "named": ";".join(n["name"] for n in (record or {}).get("named", [])),
        "detected": effect is not None and verdict == effect,
        "false_alarm": effect is None and record is not None and not silent,
        "wrong_name": effect is not None and record is not None and not silent and verdict != effect and not contained,
        "contained_name": contained,
        # causes named after a right (or contained) first one: false additions on top of the hidden effect
        "extra_names": (";".join(n for n in later if n != effect)
                        if effect is not None and (verdict == effect or contained) else ""),
        "param_error": (parameter_error(effect, case.get("value_in_view", case["value"]), first["params"])
                        if (first and effect == verdict) else None),
        "value_in_view": case.get("value_in_view"), "learned_shading": case.get("learned_shading"),
        "extension_gain_db": case.get("extension_gain_db"),
        "retention": retention(effect, case.get("value_in_view", case["value"]), record),
        "psnr_gain_db": first["psnr_gain_db"] if first else 0.0,
        "held_out_psnr_db": me.get("held_out_psnr_db"), "model_error_over_noise_db": me.get("model_error_over_noise_db"),
        "smallest_testable": json.dumps((me.get("smallest_testable") or {}).get(effect or "", {})),
        "log_exposure_spread": log_exposure_spread(record),
        "error": error or "", "runtime_s": runtime_s,
    }


def _resumed_row(done: Path, diagnosis_json: Path) -> dict:
    """A finished case's row; fields added to the table since it ran are derived from its diagnosis.json."""
    row = json.loads(done.read_text())
    if ("log_exposure_spread" not in row or "extra_names" not in row) and diagnosis_json.is_file():
        case = {"id": row["case"], "effect": None if row["effect"] == "none" else row["effect"],
                "magnitude": row["magnitude"], "value": json.loads(row["value"]),
                **{k: row[k] for k in ("value_in_view", "learned_shading", "extension_gain_db") if k in row}}
        fresh = _row(case, json.loads(diagnosis_json.read_text()), row["error"] or None, row["runtime_s"])
        row = {**fresh, **row}  # stored fields win; only the missing ones come from the record
    return row


def run_trained_sweep(out_dir: str | Path, cfg: TrainedSweepConfig | None = None, diag: DiagnosisConfig | None = None,
                      progress: bool = True) -> dict:
    """Run (or resume) every case; write trained_sweep.csv / .json / .md into out_dir; return the summary."""
    cfg = (cfg or TrainedSweepConfig()).validate()
    diag = (diag or DiagnosisConfig()).validate()
    out = Path(out_dir)
    rows = []
    for case in tqdm(cases(cfg), desc="trained sweep", unit="case", disable=not progress):
        case_dir = out / "cases" / case["id"]
        done = case_dir / "case.json"
        if done.is_file():
            rows.append(_resumed_row(done, case_dir / "diagnosis" / "diagnosis.json"))
            continue
        t0, record, error = time.perf_counter(), None, None
        try:
            record = _run_case(case, cfg, case_dir, diag)
        except (ValueError, RuntimeError, FileNotFoundError, OSError) as exc:  # recorded; the other cases go on
            error = f"{type(exc).__name__}: {exc}"
            (case_dir).mkdir(parents=True, exist_ok=True)
            (case_dir / "error.txt").write_text(traceback.format_exc())
        row = _row(case, record, error, time.perf_counter() - t0)
        rows.append(row)
        if error is None:  # a failed case is retried by the next run
            write_json(done, row)
    df = pd.DataFrame(rows)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "trained_sweep.csv") as tmp:
        df.to_csv(tmp, index=False)
    summary = summarise_trained(df, cfg)
    write_json(out / "trained_sweep.json", summary)
    with atomic_path(out / "trained_sweep.md") as tmp:
        tmp.write_text(trained_markdown(summary, df))
    return summary


def read_summary(path: str | Path) -> tuple[dict, dict]:
    """(summary, setup: SETUP_FIELDS of its config) of a sweep's trained_sweep.json; a named error if missing."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: trained-run sweep summary not found (trained_sweep.json of "
                                f"`egobench diagnose --sweep --trained`)")
    s = json.loads(p.read_text())
    config = s.get("config") or {}
    return s, {k: config.get(k) for k in SETUP_FIELDS}


def summarise_trained(df, cfg: TrainedSweepConfig) -> dict:
    ok = df[df.error.fillna("") == ""]
    null = ok[ok.effect == "none"]
    out = {"schema": "egobench.diagnosis_trained_sweep/1", "config": {**cfg.__dict__, "effects": list(cfg.effects)},
           "n_cases": int(len(df)), "n_failed": int(len(df) - len(ok)), "n_null": int(len(null)),
           "false_alarms": int(null.false_alarm.sum()),
           "false_alarm_rate": float(null.false_alarm.mean()) if len(null) else None,
           "null_verdicts": null.verdict.value_counts().to_dict(),
           "median_held_out_psnr_db": float(ok.held_out_psnr_db.median()) if len(ok) else None, "effects": []}
    for (effect, mag), g in ok[ok.effect != "none"].groupby(["effect", "magnitude"], sort=False):
        errs = g.param_error.dropna()
        out["effects"].append({
            "effect": effect, "magnitude": float(mag), "n": int(len(g)), "detection_rate": float(g.detected.mean()),
            "detected_with_positive_gain": float((g.detected & (g.psnr_gain_db > 0)).mean()),
            "wrong_name_rate": float(g.wrong_name.mean()),
            "contained_name_rate": float(g.contained_name.mean()) if "contained_name" in g else 0.0,
            "extra_name_rate": (float((g.extra_names.fillna("") != "").mean()) if "extra_names" in g else None),
            "median_log_exposure_spread": (float(g.log_exposure_spread.dropna().median()) if "log_exposure_spread" in g
                                           and g.log_exposure_spread.notna().any() else None),
            "median_retention": (float(g.retention.dropna().median())
                                 if "retention" in g and g.retention.notna().any() else None),
            "silent_rate": float(g.verdict.isin([NO_DISCREPANCY, RECONSTRUCTION_ERROR]).mean()),
            "median_param_error": float(errs.median()) if len(errs) else None, "error_unit": ERROR_UNITS[effect],
            "verdicts": g.verdict.tolist()})
    out["shading_extension"] = _extension_summary(ok)
    return out


def _extension_summary(ok) -> dict | None:
    """The learnable-shading extension as a vignette detector, calibrated on the null cases: threshold
    = nulls' mean + EXTENSION_SIGMAS sd; per effect, the fraction of cases above it and (vignette) the
    median error of learned - null mean against the truth at the view's corner."""
    if "learned_shading" not in ok or ok.learned_shading.isna().all():
        return None
    null = ok[(ok.effect == "none")].learned_shading.dropna().astype(float)
    if len(null) < 3:
        return None
    mean, sd = float(null.mean()), float(null.std(ddof=1))
    thr = mean + EXTENSION_SIGMAS * sd
    out = {"null_mean": mean, "null_sd": sd, "threshold": thr, "n_null": int(len(null)),
           "null_above": int((null > thr).sum()), "effects": []}
    nulls = ok[ok.effect == "none"]
    if "extension_gain_db" in nulls and nulls.extension_gain_db.notna().all():
        out["null_median_gain_db"] = float(nulls.extension_gain_db.astype(float).median())
    for effect, g in ok[ok.effect != "none"].groupby("effect", sort=False):
        learned = g.learned_shading.astype(float)
        e = {"effect": effect, "n": int(len(g)), "above_threshold": float((learned > thr).mean())}
        if "extension_gain_db" in g and g.extension_gain_db.notna().all():  # called, and it pays on held-out frames
            gain = g.extension_gain_db.astype(float)
            e["above_threshold_with_gain"] = float(((learned > thr) & (gain > 0)).mean())
            e["median_gain_db"] = float(gain.median())
        if EFFECTS[effect].learned_by_shading_extension and "value_in_view" in g and g.value_in_view.notna().all():
            e["median_error"] = float(np.median(np.abs(learned - mean - g.value_in_view.astype(float))))
        out["effects"].append(e)
    return out


def _extension_lines(x: dict | None) -> list[str]:
    if not x:
        return []
    out = ["", f"Vignette through the model extension (a lens shading learned with the scene, `egobench.model.shading`): "
           f"the {x['n_null']} nulls learn a corner attenuation of {x['null_mean']:.3f} +- {x['null_sd']:.3f} "
           f"(threshold {x['threshold']:.3f}, {x['null_above']} null(s) above it).", "",
           "| effect | n | above the threshold | above it with a held-out gain > 0 | median held-out gain of the "
           "extension (dB) | median error of learned - null mean (vignette) |", "|---|---|---|---|---|---|"]
    for e in x["effects"]:
        err = f"{e['median_error']:.3f}" if e.get("median_error") is not None else "-"
        paid = "-" if e.get("above_threshold_with_gain") is None else f"{e['above_threshold_with_gain']:.2f}"
        gain = "-" if e.get("median_gain_db") is None else f"{e['median_gain_db']:+.2f}"
        out.append(f"| {e['effect']} | {e['n']} | {e['above_threshold']:.2f} | {paid} | {gain} | {err} |")
    if x.get("null_median_gain_db") is not None:
        out.append(f"| none (nulls) | {x['n_null']} | {x['null_above'] / x['n_null']:.2f} | - | "
                   f"{x['null_median_gain_db']:+.2f} | - |")
    return out


def _fmt(x, digits: int = 2) -> str:
    """A table cell: '-' for a missing or non-finite number."""
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def trained_markdown(s: dict, df) -> str:
    c = s["config"]
    fa = "-" if s["false_alarm_rate"] is None else f"{s['false_alarms']}/{s['n_null']}"
    lines = ["# Diagnosis sweep on trained runs", "",
             f"{s['n_cases']} cases ({s['n_failed']} failed): {c['kind']} scenes, {c['size']} px, {c['n_frames']} frames, "
             f"'{c['method']}' trained {c['iterations']} iterations (CPU preset); diagnosed from the run's renders.", "",
             f"False alarms on null cases: {fa}; null verdicts {s['null_verdicts']}; median held-out PSNR of the runs "
             f"{s['median_held_out_psnr_db']:.2f} dB." if s["median_held_out_psnr_db"] is not None else "", "",
             "| effect | magnitude | n | detection rate | detected with gain > 0 | wrong-name rate "
             "| contained cause named (the hidden one as its 'or') | another cause named after it | silent rate "
             "| median param error | retained through training (median estimate / truth) "
             "| exposure x gain spread (median std of log) | verdicts |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in s["effects"]:
        err = "-" if e["median_param_error"] is None else f"{e['median_param_error']:.3g} ({e['error_unit']})"
        lines.append(f"| {e['effect']} | {e['magnitude']:g} | {e['n']} | {e['detection_rate']:.2f} | "
                     f"{e['detected_with_positive_gain']:.2f} | {e['wrong_name_rate']:.2f} | "
                     f"{e.get('contained_name_rate', 0.0):.2f} | {_fmt(e.get('extra_name_rate'))} | "
                     f"{e['silent_rate']:.2f} | {err} | {_fmt(e.get('median_retention'))} | "
                     f"{_fmt(e.get('median_log_exposure_spread'), 3)} | {', '.join(e['verdicts'])} |")
    lines += _extension_lines(s.get("shading_extension"))
    lines += ["", "## Cases", "", "| case | verdict | named | held-out PSNR (dB) | model error over noise (dB) | "
              "gain (dB) | smallest testable (this effect) | learned shading | exposure x gain spread | error |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in df.to_dict("records"):
        lines.append(f"| {r['case']} | {r['verdict']} | {r['named'] or '-'} | {_fmt(r['held_out_psnr_db'])} | "
                     f"{_fmt(r['model_error_over_noise_db'])} | {_fmt(r['psnr_gain_db'])} | {r['smallest_testable']} | "
                     f"{_fmt(r.get('learned_shading'))} | {_fmt(r.get('log_exposure_spread'), 3)} | "
                     f"{(r['error'] or '')[:80]} |")
    return "\n".join(lines) + "\n"
