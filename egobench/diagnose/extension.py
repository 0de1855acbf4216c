"""The model extension on a user's trained run: a lens shading learned with the scene (`egobench.model.shading`),
judged against the null cases of a trained-run sweep of the same setup (issue 15, docs/diagnosis.md).

A trained model absorbs an unstated vignette, so its residual cannot show one; the extension takes it
back as a learned corner attenuation. A user's run has no nulls of its own, and a trained model darkens
its view's corners a little even when nothing is hidden (the nulls' mean, a bias of the model), so the
learned value is called only above the sweep nulls' mean + EXTENSION_SIGMAS sd, and the estimate is the
learned value minus that mean. A camera response other than the assumed one darkens the stated vignette
in the same radial way when the exposure barely varies, so the call names both.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

from egobench.diagnose.trained_sweep import EXTENSION_SIGMAS, SETUP_FIELDS, read_summary, train_once
from egobench.train.checkpoint import config_of


@dataclass(frozen=True)
class ShadingNull:
    """Learned corner attenuation of the null cases of a trained-run sweep."""

    mean: float
    sd: float
    threshold: float  # mean + EXTENSION_SIGMAS sd
    n: int
    setup: dict  # SETUP_FIELDS of the sweep
    source: str  # the sweep's summary file


def load_shading_null(path: str | Path) -> ShadingNull:
    """The null distribution from a trained-run sweep's summary (trained_sweep.json)."""
    p = Path(path)
    s, setup = read_summary(p)
    x = s.get("shading_extension")
    if not isinstance(x, dict) or not all(k in x for k in ("null_mean", "null_sd", "threshold", "n_null")):
        raise ValueError(f"{p}: field 'shading_extension': expected the nulls' learned shading (null_mean, null_sd, "
                         f"threshold, n_null) of a sweep run with the shading extension; got {x!r}")
    return ShadingNull(mean=float(x["null_mean"]), sd=float(x["null_sd"]), threshold=float(x["threshold"]),
                       n=int(x["n_null"]), setup=setup, source=str(p))


def learned_shading_of(run_dir: str | Path, recording, out_dir: str | Path, method: str,
                       progress: bool = True) -> tuple[float, str]:
    """(learned corner attenuation, run folder it comes from): the run's own when it was trained with
    ``learn_shading``; otherwise the same training config with the shading learned, trained into
    OUT/run_shading (resumable)."""
    record = _train_record(Path(run_dir))
    if record.get("learned_shading"):
        return float(record["learned_shading"]["corner_attenuation"]), str(run_dir)
    ext = Path(out_dir) / "run_shading"
    done = train_once(recording, record.get("method", method), replace(config_of(record), learn_shading=True), ext,
                      progress=progress)
    return float(done["learned_shading"]["corner_attenuation"]), str(ext)


def _train_record(run_dir: Path) -> dict:
    path = run_dir / "train.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (a run folder of `egobench train`)")
    record = json.loads(path.read_text())
    if "config" not in record:
        raise ValueError(f"{path}: field 'config': expected the training config of the run")
    return record


def run_setup(run_dir: str | Path, n_frames: int, image_size: int) -> dict:
    """The diagnosed run's SETUP_FIELDS (image size: the rendered image's larger side, px)."""
    record = _train_record(Path(run_dir))
    return {"method": record.get("method"), "size": int(image_size), "n_frames": int(n_frames),
            "iterations": int(record["config"]["iterations"])}


def judge_shading(learned: float, null: ShadingNull, setup: dict, exposure_ratio: float) -> dict:
    """The extension's call on one run: above the nulls' threshold or not, the estimate, and caveats."""
    above = bool(learned > null.threshold)
    mismatch = {k: {"run": setup.get(k), "null": null.setup.get(k)} for k in SETUP_FIELDS
                if null.setup.get(k) is not None and setup.get(k) != null.setup.get(k)}
    notes = []
    if mismatch:
        notes.append("the nulls come from another setup (" + ", ".join(
            f"{k} {v['run']} here, {v['null']} there" for k, v in mismatch.items())
            + "): a model's corner bias depends on it, so the threshold is indicative only")
    if above:
        notes.append(f"a camera response other than the assumed one would darken the stated vignette the same way "
                     f"at this run's exposure range ({exposure_ratio:.2f}x in exposure x gain)")
    return {"learned_corner_attenuation": float(learned), "null_mean": null.mean, "null_sd": null.sd,
            "threshold": null.threshold, "n_null": null.n, "sigmas": EXTENSION_SIGMAS, "above_threshold": above,
            "estimate": float(learned - null.mean) if above else None,
            "called": "vignette (or response)" if above else None,
            "setup": setup, "setup_mismatch": mismatch, "exposure_ratio": float(exposure_ratio),
            "null_source": null.source, "notes": notes}
