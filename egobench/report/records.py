"""Run records (``eval.json``, schema ``egobench.run/1``): reading and validating them, the combined results
(``results.csv``), and the names every report shares (the metrics a record carries, which paper table a scene kind
is compared with, the paper's row label of a method)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import pandas as pd

from egobench.io_utils import read_json
from egobench.model.methods import get_method
from egobench.report import paper_numbers as pn

RUN_SCHEMA = "egobench.run/1"
#: Metrics a record may carry (None = not measured).
METRICS = (pn.PSNR, pn.SSIM, pn.LPIPS, pn.DEPTH, pn.NORMAL, pn.OWN_DEPTH, pn.OWN_NORMAL, pn.DEPTH_ALL, pn.NORMAL_ALL)
#: Reference method of each compared method in the gains table (default: ``ours``).
GAIN_REFERENCE = {"2dgs_no_motion_sampling": "ours_2dgs"}
#: Table of each group in egobench.model.methods' row labels ("aria", "dtc", "quest3").
LABEL_TABLE = {"table1_outdoor": "aria", "table1_indoor": "aria", "table2": "dtc", "table3": "quest3"}
#: Table groups: name -> (scene kind, paper table): the one place that says which paper table a
#: simulated scene kind is compared with.
GROUPS = {
    "table1_outdoor": ("outdoor", pn.TABLE1_OUTDOOR),
    "table1_indoor": ("indoor", pn.TABLE1_INDOOR),
    "table2": ("object", pn.TABLE2),
    "table3": ("quest3", pn.TABLE3),
}
#: Keys of ``recording_stats`` read for Table 4 and the head-speed plot.
NUM_FRAMES_KEY = "num_frames"
HEAD_SPEED_KEY = "head_angular_speed_deg_s_p50"  # median head angular speed of the recording, deg/s


def method_label(method: str, group: str | None = None) -> str:
    """The paper's row label of a method (egobench/model/methods.py), or its key if unregistered."""
    try:
        spec = get_method(method)
    except (ImportError, ValueError):
        return method
    return spec.label_for(LABEL_TABLE[group]) if group in LABEL_TABLE else spec.label



@dataclass(frozen=True)
class RunRecord:
    """The fields of one run record that tables and plots use."""

    path: Path  # where the record was read from (for error messages and locating renders only)
    scene: str  # our scene name, e.g. "outdoor_0"
    scene_kind: str  # outdoor | indoor | object | quest3 ("unknown" when the record has none)
    paper_scene: str | None  # the paper's scene column this scene stands for
    method: str  # method key (egobench/model/methods.py)
    seed: int
    metrics: dict[str, float | None]  # METRICS: psnr, ssim, lpips, the authors' depth/normal, egobench's own
    train: dict[str, Any] = field(default_factory=dict)  # iterations, time_s, iters_per_s, ...
    recording_stats: dict[str, Any] = field(default_factory=dict)  # num_frames, head speed, ...
    raw: dict[str, Any] = field(default_factory=dict, repr=False)  # the whole record

    @property
    def run_dir(self) -> Path:
        return self.path.parent

    @property
    def head_speed_deg_s(self) -> float | None:
        """Median head angular speed of the recording (deg/s), if the record carries it."""
        value = self.recording_stats.get(HEAD_SPEED_KEY)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        return None


def _require(rec: dict, key: str, kind: type | tuple, path: Path) -> Any:
    if key not in rec:
        raise ValueError(f"{path}: run record lacks field {key!r} (schema {RUN_SCHEMA})")
    value = rec[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ValueError(f"{path}: field {key!r} is {value!r}; expected {getattr(kind, '__name__', kind)}")
    return value


def parse_record(rec: dict, path: str | Path = "<record>") -> RunRecord:
    """Validate one record (a parsed eval.json) and return its table fields."""
    path = Path(path)
    if not isinstance(rec, dict):
        raise ValueError(f"{path}: a run record is a JSON object, got {type(rec).__name__}")
    schema = rec.get("schema")
    if schema != RUN_SCHEMA:
        raise ValueError(f"{path}: field 'schema' is {schema!r}; expected {RUN_SCHEMA!r}")
    scene = _require(rec, "scene", str, path)
    scene_kind = rec.get("scene_kind") or "unknown"  # real recordings may have none: in results.csv only
    if not isinstance(scene_kind, str):
        raise ValueError(f"{path}: field 'scene_kind' is {scene_kind!r}; expected a string or null")
    method = _require(rec, "method", str, path)
    seed = _require(rec, "seed", int, path)
    paper_scene = rec.get("paper_scene")
    if paper_scene is not None and not isinstance(paper_scene, str):
        raise ValueError(f"{path}: field 'paper_scene' is {paper_scene!r}; expected a string or null")
    metrics_in = _require(rec, "metrics", dict, path)
    metrics: dict[str, float | None] = {}
    for key in METRICS:
        value = metrics_in.get(key)
        if value is None:
            metrics[key] = None
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{path}: field 'metrics.{key}' is {value!r}; expected a finite number or null")
        metrics[key] = float(value)
    if metrics[pn.PSNR] is None:
        raise ValueError(f"{path}: field 'metrics.psnr' is null; every run record must carry a PSNR")
    train = rec.get("train") or {}
    stats = rec.get("recording_stats") or {}
    if not isinstance(train, dict) or not isinstance(stats, dict):
        raise ValueError(f"{path}: fields 'train' and 'recording_stats' must be JSON objects")
    return RunRecord(path, scene, scene_kind, paper_scene, method, seed, metrics, train, stats, rec)


def find_record_files(paths: Iterable[str | Path]) -> list[Path]:
    """Expand folders to the eval.json files below them (sorted); files are kept as given."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(p.rglob("eval.json")))
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"{p}: run record (eval.json) or folder not found")
    return out


def load_records(paths: Iterable[str | Path]) -> list[RunRecord]:
    """Read and validate run records; duplicates of (scene, method, seed) are an error."""
    records = [parse_record(read_json(p), p) for p in find_record_files(paths)]
    seen: dict[tuple[str, str, int], Path] = {}
    for r in records:
        key = (r.scene, r.method, r.seed)
        if key in seen:
            raise ValueError(f"{r.path}: duplicate run record for scene {r.scene!r}, method {r.method!r}, "
                             f"seed {r.seed} (also in {seen[key]})")
        seen[key] = r.path
    return records


def records_frame(records: Sequence[RunRecord]) -> pd.DataFrame:
    """The combined results: one row per record."""
    rows = []
    for r in records:
        row: dict[str, Any] = {
            "scene": r.scene,
            "scene_kind": r.scene_kind,
            "paper_scene": r.paper_scene,
            "device": r.raw.get("device"),
            "method": r.method,
            "seed": r.seed,
            "calibration": r.raw.get("calibration"),
        }
        row.update({k: r.metrics[k] for k in METRICS})
        for k in ("iterations", "time_s", "iters_per_s", "raster_time_share", "num_gaussians"):
            row[f"train_{k}"] = r.train.get(k)
        row["num_frames"] = r.recording_stats.get(NUM_FRAMES_KEY)
        # the model's resolved wavelength on the held-out frames (egobench.analysis.fidelity); older records lack it
        row["resolved_wavelength_px"] = (r.raw.get("fidelity") or {}).get("resolved_wavelength_px")
        row["head_speed_deg_s_p50"] = r.head_speed_deg_s
        host = ((r.raw.get("host") or {}).get("train") or {})  # where the training arithmetic ran
        row.update({f"train_{k}": host.get(k) for k in ("cpu_model", "kernel_target", "torch_cpu_capability")})
        row["train_versions"] = " ".join(f"{k}={v}" for k, v in (host.get("versions") or {}).items()) or None
        row["config_hash"] = r.raw.get("config_hash")
        row["git_commit"] = r.raw.get("git_commit")
        row["record"] = str(r.path)
        rows.append(row)
    columns = list(rows[0]) if rows else ["scene", "scene_kind", "paper_scene", "method", "seed", *METRICS]
    return pd.DataFrame(rows, columns=columns)

