"""Paper-shaped tables from run records (``eval.json``, schema ``egobench.run/1``).

Everything here is computed from the records' contents, never from their paths. Outputs (CSV and
booktabs LaTeX, written atomically):

- ``results.csv``: one row per record (the combined results),
- ``table1_outdoor``, ``table1_indoor`` (+ ``table1.tex`` holding both blocks), ``table2``,
  ``table3``: methods as rows, scenes as columns, best in bold, the paper's numbers in an adjacent
  block (same columns, matched through the record's ``paper_scene``),
- ``table4``: dataset statistics, ours beside the paper's,
- ``gains``: mean PSNR change of each ablation/baseline relative to its reference (``ours``;
  ``ours_2dgs`` for the 2D-GS ablation), ours (mean and std over seeds) versus the paper's.

``egobench tables --records R1.json R2.json ... --out-dir DIR``
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from egobench.report import paper_numbers as pn
from egobench.report.outputs import TABLE_FILES
from egobench.io_utils import atomic_path, read_json
from egobench.model.methods import get_method

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
OUTPUT_FILES = TABLE_FILES  # every file `write_tables` produces (egobench.report.outputs)
OURS_BLOCK = "egobench"
PAPER_BLOCK = "paper"


def method_label(method: str, group: str | None = None) -> str:
    """The paper's row label of a method (egobench/model/methods.py), or its key if unregistered."""
    try:
        spec = get_method(method)
    except (ImportError, ValueError):
        return method
    return spec.label_for(LABEL_TABLE[group]) if group in LABEL_TABLE else spec.label


# --------------------------------------------------------------------------------------------
# Records


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


# --------------------------------------------------------------------------------------------
# Paper-shaped tables


@dataclass
class Cell:
    """One table entry: mean over seeds, its sample std (None for one seed) and the seed count."""

    mean: float | None = None
    std: float | None = None
    n: int = 0
    bold: bool = False


@dataclass
class Block:
    """A set of rows: ours or the paper's. rows[method] = one Cell per table column."""

    name: str  # OURS_BLOCK or PAPER_BLOCK
    title: str  # shown as a row spanning the table
    row_groups: list[list[str]]  # method keys, groups separated by a rule
    rows: dict[str, list[Cell]]


@dataclass
class ShapedTable:
    """A table shaped like one of the paper's: column groups (scenes) x metrics, blocks of rows."""

    name: str  # file stem, e.g. "table1_outdoor"
    caption: str
    label: str  # LaTeX label of the table we write
    groups: list[str]  # column group headers (scenes)
    metrics: list[str]  # metrics per group
    blocks: list[Block]
    notes: list[str] = field(default_factory=list)

    @property
    def columns(self) -> list[tuple[str, str]]:
        return [(g, m) for g in self.groups for m in self.metrics]


def _stats(values: Sequence[float]) -> Cell:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not vals:
        return Cell()
    arr = np.asarray(vals, dtype=np.float64)
    return Cell(float(arr.mean()), float(arr.std(ddof=1)) if arr.size > 1 else None, int(arr.size))


def _round(value: float, metric: str) -> float:
    return round(value, pn.METRIC_DECIMALS[metric])


def mark_best(block: Block, n_columns: int, metrics_per_column: Sequence[str], per_group: bool) -> None:
    """Bold the best entry of each column (ties at printed precision are all bold)."""
    groups = block.row_groups if per_group else [[m for g in block.row_groups for m in g]]
    for rows in groups:
        for j in range(n_columns):
            metric = metrics_per_column[j]
            cells = [block.rows[m][j] for m in rows if m in block.rows and block.rows[m][j].mean is not None]
            if len(cells) < 2:
                continue
            vals = [_round(c.mean, metric) for c in cells]
            best = max(vals) if pn.HIGHER_IS_BETTER[metric] else min(vals)
            for c, v in zip(cells, vals):
                c.bold = v == best


def _row_groups(paper: pn.PaperTable, present: Iterable[str]) -> list[list[str]]:
    groups = [list(g) for g in paper.row_groups]
    extra = sorted(set(present) - set(paper.methods))
    if extra:
        groups.append(extra)
    return groups


def _scene_columns(records: Sequence[RunRecord], paper: pn.PaperTable) -> list[tuple[str, str | None]]:
    """(our scene, paper scene) pairs in the paper's column order, then unmatched scenes by name."""
    scenes: dict[str, str | None] = {}
    for r in records:
        scenes.setdefault(r.scene, r.paper_scene)
    order = {c: i for i, c in enumerate(paper.columns)}

    def key(item):
        ps = (item[1] or "").lower()
        return (order.get(ps, len(order)), item[0])

    return sorted(scenes.items(), key=key)


def _scene_label(scene: str, paper_scene: str | None) -> str:
    return f"{scene} ({paper_scene})" if paper_scene else scene


def table_metrics(paper: pn.PaperTable) -> list[str]:
    """The paper table's metrics, plus LPIPS where the paper does not report it (the field's third
    metric; the paper's cells there stay empty)."""
    return list(paper.metrics) + ([] if pn.LPIPS in paper.metrics else [pn.LPIPS])


def build_per_scene_table(records: Sequence[RunRecord], group: str) -> ShapedTable:
    """Table 1 block (outdoor or indoor): scenes as columns, PSNR/SSIM, methods as rows."""
    kind, paper = GROUPS[group]
    recs = [r for r in records if r.scene_kind == kind]
    metrics = table_metrics(paper)
    notes = []
    scene_cols = _scene_columns(recs, paper)
    if not scene_cols:  # no runs: show the paper's columns alone
        notes.append(f"no egobench runs of scene kind {kind!r}")
        scene_cols = [("", c) for c in paper.columns]
    groups = [_scene_label(s, ps) if s else ps for s, ps in scene_cols]
    methods = sorted({r.method for r in recs})
    ours_rows: dict[str, list[Cell]] = {}
    for m in methods:
        cells = []
        for s, _ in scene_cols:
            sel = [r for r in recs if r.method == m and r.scene == s]
            cells.extend(_stats([r.metrics[k] for r in sel]) for k in metrics)
        ours_rows[m] = cells
    paper_rows: dict[str, list[Cell]] = {}
    for m in paper.methods:
        cells = []
        for _, ps in scene_cols:
            for k in metrics:
                v = paper.value(m, ps, k) if ps else None
                cells.append(Cell(v, None, 1 if v is not None else 0))
        paper_rows[m] = cells
    unmatched = sorted({s for s, ps in scene_cols if s and (not ps or ps.lower() not in paper.columns)})
    if unmatched:
        notes.append("no paper column for: " + ", ".join(unmatched))
    return _assemble(group, paper, groups, metrics, ours_rows, paper_rows, notes, per_group=False)


def build_aggregate_table(records: Sequence[RunRecord], group: str) -> ShapedTable:
    """Tables 2 and 3: one column (mean over our scenes of that kind) beside the paper's."""
    kind, paper = GROUPS[group]
    recs = [r for r in records if r.scene_kind == kind]
    metrics = table_metrics(paper)
    scenes = sorted({r.scene for r in recs})
    notes = [f"egobench: mean over {len(scenes)} scene(s) of kind {kind!r}: {', '.join(scenes) or 'none'}; "
             "std over seeds of the scene mean"]
    ours_rows: dict[str, list[Cell]] = {}
    for m in sorted({r.method for r in recs}):
        cells = []
        for k in metrics:
            per_seed = _per_seed_scene_mean([r for r in recs if r.method == m], k)
            cells.append(_stats(list(per_seed.values())))
        ours_rows[m] = cells
    paper_rows = {m: [Cell(paper.value(m, paper.columns[0], k), None, 1) for k in metrics] for m in paper.methods}
    label = f"{kind} ({len(scenes)} scene{'s' if len(scenes) != 1 else ''}) / {paper.columns[0]}"
    return _assemble(group, paper, [label], metrics, ours_rows, paper_rows, notes, per_group=group == "table2")


def _per_seed_scene_mean(recs: Sequence[RunRecord], metric: str) -> dict[int, float]:
    """seed -> mean over scenes of the metric (scenes without a value are skipped)."""
    out: dict[int, float] = {}
    for seed in sorted({r.seed for r in recs}):
        vals = [r.metrics[metric] for r in recs if r.seed == seed and r.metrics[metric] is not None]
        if vals:
            out[seed] = float(np.mean(vals))
    return out


def _assemble(group, paper, groups, metrics, ours_rows, paper_rows, notes, per_group) -> ShapedTable:
    ours = Block(OURS_BLOCK, "egobench (this run; mean $\\pm$ std over seeds)", _row_groups(paper, ours_rows), ours_rows)
    ours.row_groups = [[m for m in g if m in ours_rows] for g in ours.row_groups]
    ours.row_groups = [g for g in ours.row_groups if g]
    theirs = Block(PAPER_BLOCK, f"paper (Lv et al. 2025, \\texttt{{{latex_escape(paper.label)}}})", [list(g) for g in paper.row_groups], paper_rows)
    metric_per_col = [m for _ in groups for m in metrics]
    for b in (ours, theirs):
        mark_best(b, len(metric_per_col), metric_per_col, per_group)
    return ShapedTable(group, paper.caption, f"tab:egobench_{group}", groups, metrics, [ours, theirs], notes)


# --------------------------------------------------------------------------------------------
# Gains and Table 4


def ci95(values: Sequence[float]) -> tuple[float | None, float | None]:
    """Two-sided 95 % t-interval of the mean of ``values`` (seed-level paired differences); (None,
    None) below two values."""
    n = len(values)
    if n < 2:
        return None, None
    from scipy.stats import t

    mean, sem = float(np.mean(values)), float(np.std(values, ddof=1)) / math.sqrt(n)
    half = float(t.ppf(0.975, n - 1)) * sem
    return mean - half, mean + half


def identical_by_construction(method: str, pairs: Sequence[tuple[RunRecord, RunRecord]]) -> str:
    """Why ``method`` cannot differ from its reference on these runs ('' when it can): a motion-sampling
    ablation whose reference rendered every frame with one pose sample, at training and evaluation, is
    the same computation. Detected from the records, never assumed: every paired PSNR must be equal too."""
    if not pairs or any(a.metrics[pn.PSNR] != b.metrics[pn.PSNR] for a, b in pairs):
        return ""
    if "no_motion_sampling" in method:
        one_sample = all((b.raw.get("eval") or {}).get("pose_samples_mean") == 1.0
                         and all(e.get("pose_samples", 1) == 1 for e in b.raw.get("per_image", [])) for _, b in pairs)
        if one_sample:
            return ("identical by construction: every held-out frame of the reference has one rolling-shutter "
                    "pose sample (motion sampling never switches on at this motion and resolution)")
    return "identical results: every paired PSNR is equal (this ablation changes nothing on these runs)"


def _paired(recs: Sequence[RunRecord], method: str, ref: str) -> list[tuple[RunRecord, RunRecord]]:
    """(method run, reference run) on the same scene and seed (the same recording)."""
    ref_by = {(r.scene, r.seed): r for r in recs if r.method == ref}
    return sorted(((r, ref_by[(r.scene, r.seed)]) for r in recs if r.method == method and (r.scene, r.seed) in ref_by),
                  key=lambda p: (p[0].scene, p[0].seed))


def gains_frame(records: Sequence[RunRecord]) -> pd.DataFrame:
    """Mean PSNR change of each method relative to its reference, ours versus the paper's.

    Only methods run on scenes of the table's kind are listed. Ours: the paired difference
    PSNR(method) - PSNR(reference) on the same scene and seed (the same recording); for every seed
    the mean over scenes, then the mean, sample std and 95 % t-interval over seeds. A method that
    cannot differ from its reference on these runs (`identical_by_construction`) carries the reason
    instead of a Δ. Paper: the mean difference over the paper columns our scenes stand for
    (``paper_matched``) and over all of the paper table's columns (``paper_all``).
    """
    rows = []
    for group, (kind, paper) in GROUPS.items():
        recs = [r for r in records if r.scene_kind == kind]
        run_methods = {r.method for r in recs}
        methods = [m for m in paper.methods if m in run_methods] + sorted(run_methods - set(paper.methods))
        for m in methods:
            ref = GAIN_REFERENCE.get(m, "ours")
            if m == ref or m == "ours":
                continue
            pairs = _paired(recs, m, ref)
            per_seed: dict[int, list[float]] = {}
            for a, b in pairs:
                per_seed.setdefault(a.seed, []).append(a.metrics[pn.PSNR] - b.metrics[pn.PSNR])
            seed_means = [float(np.mean(v)) for _, v in sorted(per_seed.items())]
            cell = _stats(seed_means)
            low, high = ci95(seed_means)
            identical = identical_by_construction(m, pairs)
            rows.append({
                "group": group, "method": m, "reference": ref, "n_scenes": len({a.scene for a, _ in pairs}),
                "n_seeds": cell.n,
                "delta_psnr_mean": None if identical else cell.mean,
                "delta_psnr_std": None if identical else cell.std,
                "delta_psnr_ci95_low": None if identical else low,
                "delta_psnr_ci95_high": None if identical else high,
                "identical": identical,
                "paper_delta_psnr_matched": (matched := _paper_delta(paper, m, ref, _matched_columns(recs, kind, paper))),
                "paper_delta_psnr_all": _paper_delta(paper, m, ref, paper.columns),
                "p_one_sided": None if identical else p_in_direction(seed_means, matched),
            })
    return with_reproduction_columns(pd.DataFrame(rows))


def p_in_direction(seed_means: Sequence[float], paper_delta: float | None) -> float | None:
    """One-sided paired t-test p over the seeds, against 'no difference', in the paper's direction
    (None below two seeds or without a paper Δ)."""
    n = len(seed_means)
    if n < 2 or paper_delta is None or paper_delta == 0:
        return None
    from scipy.stats import t

    sd = float(np.std(seed_means, ddof=1))
    if sd == 0:
        return 0.0 if np.sign(np.mean(seed_means)) == np.sign(paper_delta) else 1.0
    tstat = float(np.mean(seed_means)) / (sd / math.sqrt(n)) * float(np.sign(paper_delta))
    return float(t.sf(tstat, n - 1))


def holm(p_values: Sequence[float | None]) -> list[float | None]:
    """Holm's step-down adjusted p-values (None stays None and does not count towards m)."""
    idx = [i for i, p in enumerate(p_values) if p is not None and not pd.isna(p)]
    order = sorted(idx, key=lambda i: p_values[i])
    out: list[float | None] = [None] * len(p_values)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(order) - rank) * float(p_values[i])))
        out[i] = running
    return out


#: The three counts a reproduction reports (docs: README "Results"), from `gains_frame`'s columns.
COUNT_COLUMNS = {"sign_and_ci": "the paper's sign with the 95 % interval excluding zero",
                 "survives_holm": "one-sided paired t-test in the paper's direction, Holm-adjusted p < 0.05 over all rows",
                 "magnitude_match": "the paper's Δ inside our interval, or our Δ within a factor 2 of it"}


def with_reproduction_columns(df: pd.DataFrame, alpha: float = 0.05) -> pd.DataFrame:
    """Per row: Holm-adjusted p, whether the sign (with its interval), the Holm test and the magnitude
    reproduce, and our Δ over the paper's (matched scenes)."""
    if df.empty:
        return df
    df = df.copy()
    df["p_holm"] = holm(list(df["p_one_sided"]))
    paper, low, high, ours = (df[c].astype(float) for c in ("paper_delta_psnr_matched", "delta_psnr_ci95_low",
                                                            "delta_psnr_ci95_high", "delta_psnr_mean"))
    df["ratio_to_paper"] = ours / paper
    df["paper_in_ci"] = (low <= paper) & (paper <= high)
    df["sign_and_ci"] = ((paper < 0) & (high < 0)) | ((paper > 0) & (low > 0))
    df["survives_holm"] = df["p_holm"].astype(float) < alpha
    df["magnitude_match"] = df["paper_in_ci"] | ((df["ratio_to_paper"] >= 0.5) & (df["ratio_to_paper"] <= 2.0))
    return df


def reproduction_counts(gains: pd.DataFrame) -> dict[str, int]:
    """The three counts over the rows of ``gains`` (and the number of rows)."""
    return {"rows": int(len(gains)),
            **{c: int(gains[c].fillna(False).astype(bool).sum()) if c in gains else 0 for c in COUNT_COLUMNS}}


def _matched_columns(recs: Sequence[RunRecord], kind: str, paper: pn.PaperTable) -> list[str]:
    """The paper columns our scenes stand for (object and Quest 3: all of the table's)."""
    if kind in ("object", "quest3") and recs:
        return list(paper.columns)
    return sorted({(r.paper_scene or "").lower() for r in recs} & set(paper.columns))


def _paper_delta(paper: pn.PaperTable, method: str, ref: str, cols) -> float | None:
    d = [paper.value(method, c, pn.PSNR) - paper.value(ref, c, pn.PSNR) for c in cols
         if paper.value(method, c, pn.PSNR) is not None and paper.value(ref, c, pn.PSNR) is not None]
    return round(float(np.mean(d)), 6) if d else None


def table4_frame(records: Sequence[RunRecord]) -> pd.DataFrame:
    """Dataset statistics: our scenes (frames, kind, head speed) beside the paper's Table 4."""
    rows = []
    for scene in sorted({r.scene for r in records}):
        rs = [r for r in records if r.scene == scene]
        r0 = rs[0]
        frames = next((r.recording_stats.get(NUM_FRAMES_KEY) for r in rs if r.recording_stats.get(NUM_FRAMES_KEY)), None)
        speed = next((r.head_speed_deg_s for r in rs if r.head_speed_deg_s is not None), None)
        paper = pn.TABLE4.get((r0.paper_scene or "").lower())
        rows.append({
            "scene": scene,
            "scene_kind": r0.scene_kind,
            "paper_scene": r0.paper_scene,
            "frames": frames,
            "head_speed_deg_s_p50": speed,
            "paper_frames": paper.frames if paper else None,
            "paper_scenario": paper.scenario if paper else None,
        })
    return pd.DataFrame(rows, columns=["scene", "scene_kind", "paper_scene", "frames", "head_speed_deg_s_p50",
                                       "paper_frames", "paper_scenario"])


# --------------------------------------------------------------------------------------------
# Rendering: CSV and LaTeX


def shaped_to_frame(table: ShapedTable) -> pd.DataFrame:
    """CSV form: one row per (block, method); columns '<scene> <METRIC>' and '<scene> <METRIC> std'."""
    rows = []
    for block in table.blocks:
        for m in (m for g in block.row_groups for m in g):
            if m not in block.rows:
                continue
            row: dict[str, Any] = {"block": block.name, "method": m, "label": method_label(m, table.name)}
            for (g, k), cell in zip(table.columns, block.rows[m]):
                name = f"{g} {pn.METRIC_LABELS[k]}"
                row[name] = cell.mean
                row[f"{name} std"] = cell.std
                row[f"{name} best"] = cell.bold
            rows.append(row)
    return pd.DataFrame(rows)


def latex_escape(text: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"), ("$", r"\$")):
        text = text.replace(a, b)
    return text


def _fmt(cell: Cell, metric: str) -> str:
    if cell.mean is None:
        return "--"
    d = pn.METRIC_DECIMALS[metric]
    s = f"{cell.mean:.{d}f}"
    if cell.bold:
        s = f"\\textbf{{{s}}}"
    if cell.std is not None:
        s += f"\\,{{\\scriptsize$\\pm${cell.std:.{d}f}}}"
    return s


def _latex_head(caption: str, colspec: str, env: str = "table") -> list[str]:
    """Opening lines of a generated booktabs table (caption already LaTeX)."""
    return [
        "% generated by egobench tables: do not edit",
        f"\\begin{{{env}}}[t]",
        "\\centering",
        "\\small",
        f"\\caption{{{caption}}}",
        f"\\begin{{tabular}}{{{colspec}}}",
        "\\toprule",
    ]


def shaped_to_latex(tables: Sequence[ShapedTable], caption: str, label: str) -> str:
    """One booktabs table holding one or more shaped tables stacked (as Table 1 stacks two)."""
    n_cols = max(len(t.columns) for t in tables)
    lines = _latex_head(latex_escape(caption), "l" + "c" * n_cols, env="table*")
    for i, t in enumerate(tables):
        if i:
            lines.append("\\midrule\\midrule")
        k = len(t.metrics)
        head = " & ".join(f"\\multicolumn{{{k}}}{{c}}{{{latex_escape(g)}}}" for g in t.groups)
        lines.append(f"\\textbf{{{latex_escape(t.caption)}}} & {head} \\\\")
        lines.append(" & " + " & ".join(pn.METRIC_LABELS[m] for _, m in t.columns) + " \\\\")
        for block in t.blocks:
            lines.append("\\midrule")
            lines.append(f"\\multicolumn{{{n_cols + 1}}}{{l}}{{\\textit{{{block.title}}}}} \\\\")
            for gi, g in enumerate(block.row_groups):
                if gi:
                    lines.append("\\midrule")
                for m in g:
                    if m not in block.rows:
                        continue
                    cells = " & ".join(_fmt(c, k) for c, (_, k) in zip(block.rows[m], t.columns))
                    lines.append(f"{latex_escape(method_label(m, t.name))} & {cells} \\\\")
        for note in t.notes:
            lines.append(f"\\multicolumn{{{n_cols + 1}}}{{l}}{{\\scriptsize {latex_escape(note)}}} \\\\")
    lines += ["\\bottomrule", "\\end{tabular}", f"\\label{{{label}}}", "\\end{table*}", ""]
    return "\n".join(lines)


def _num(value: Any, decimals: int, signed: bool = False) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "--"
    return f"{value:+.{decimals}f}" if signed else f"{value:.{decimals}f}"


def gains_to_latex(df: pd.DataFrame) -> str:
    lines = _latex_head(
        "Mean PSNR change (dB) relative to the reference method on the same recordings: egobench (mean "
        "over seeds, 95\\,\\% interval over seeds) versus the paper (same scenes / all of the table's scenes).",
        "llcccc",
    ) + [
        "table & method (vs.\\ reference) & seeds & egobench $\\Delta$PSNR & paper (matched) & paper (all) \\\\",
        "\\midrule",
    ]
    prev = None
    for _, r in df.iterrows():
        if prev is not None and r["group"] != prev:
            lines.append("\\midrule")
        prev = r["group"]
        method = latex_escape(method_label(r["method"], r["group"]))
        ref = latex_escape(method_label(r["reference"], r["group"]))
        lines.append(
            f"{latex_escape(r['group'])} & {method} (vs.\\ {ref}) & {int(r['n_seeds'])} & {_gain_cell(r)} & "
            f"{_num(r['paper_delta_psnr_matched'], 2, True)} & {_num(r['paper_delta_psnr_all'], 2, True)} \\\\"
        )
    lines += ["\\bottomrule", "\\end{tabular}", "\\par\\footnotesize " + latex_escape("O" + counts_line(df)[1:]) + ".",
              "\\label{tab:egobench_gains}", "\\end{table}", ""]
    return "\n".join(lines)


def _gain_cell(r: pd.Series) -> str:
    """Our Δ with its seed interval, or the reason it is not a measurement."""
    if isinstance(r.get("identical"), str) and r["identical"]:
        return "\\emph{" + latex_escape(r["identical"].split(":")[0]) + "}"
    ours = _num(r["delta_psnr_mean"], 2, True)
    low, high = r.get("delta_psnr_ci95_low"), r.get("delta_psnr_ci95_high")
    if low is not None and not pd.isna(low):
        ours += f"\\,{{\\scriptsize[{low:+.2f}, {high:+.2f}]}}"
    else:
        ours += "\\,{\\scriptsize(1 seed)}"
    return ours


def table4_to_latex(df: pd.DataFrame) -> str:
    lines = _latex_head(
        "Dataset statistics: egobench recordings beside the paper's Aria scenes (Table 4).", "lllrrrl",
    ) + [
        "scene & kind & paper scene & \\#frames & head speed p50 (deg/s) & paper \\#frames & paper scenario \\\\",
        "\\midrule",
    ]
    for _, r in df.iterrows():
        frames = "--" if r["frames"] is None or pd.isna(r["frames"]) else str(int(r["frames"]))
        pframes = "--" if r["paper_frames"] is None or pd.isna(r["paper_frames"]) else str(int(r["paper_frames"]))
        lines.append(" & ".join([
            latex_escape(str(r["scene"])), latex_escape(str(r["scene_kind"])),
            latex_escape(str(r["paper_scene"] or "--")), frames, _num(r["head_speed_deg_s_p50"], 1),
            pframes, latex_escape(str(r["paper_scenario"] or "--")),
        ]) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}", "\\label{tab:egobench_dataset}", "\\end{table}", ""]
    return "\n".join(lines)


def _write_text(path: Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def _write_csv(path: Path, df: pd.DataFrame) -> Path:
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)
    return path


def build_tables(records: Sequence[RunRecord]) -> dict[str, ShapedTable]:
    """The four paper-shaped tables (Table 1 as two blocks)."""
    return {
        "table1_outdoor": build_per_scene_table(records, "table1_outdoor"),
        "table1_indoor": build_per_scene_table(records, "table1_indoor"),
        "table2": build_aggregate_table(records, "table2"),
        "table3": build_aggregate_table(records, "table3"),
    }


def write_tables(records: Sequence[RunRecord], out_dir: str | Path) -> list[Path]:
    """Write every file in OUTPUT_FILES into out_dir (atomically); return their paths."""
    out = Path(out_dir)
    written = [_write_csv(out / "results.csv", records_frame(records))]
    tables = build_tables(records)
    for name, t in tables.items():
        written.append(_write_csv(out / f"{name}.csv", shaped_to_frame(t)))
        written.append(_write_text(out / f"{name}.tex", shaped_to_latex([t], t.caption, t.label)))
    written.append(_write_text(out / "table1.tex", shaped_to_latex(
        [tables["table1_outdoor"], tables["table1_indoor"]],
        "Aria scene dataset (Table 1): egobench beside the paper", "tab:egobench_table1")))
    t4 = table4_frame(records)
    written += [_write_csv(out / "table4.csv", t4), _write_text(out / "table4.tex", table4_to_latex(t4))]
    g = gains_frame(records)
    written += [_write_csv(out / "gains.csv", g), _write_text(out / "gains.tex", gains_to_latex(g))]
    return written


def counts_line(gains: pd.DataFrame) -> str:
    """'of N rows: a with the paper's sign ..., b survive Holm, c match in magnitude'."""
    c = reproduction_counts(gains)
    return (f"of {c['rows']} rows: {c['sign_and_ci']} with the paper's sign and the 95 % interval excluding zero, "
            f"{c['survives_holm']} survive Holm (one-sided, alpha 0.05), {c['magnitude_match']} with the paper's "
            "delta inside the interval or within a factor 2")


# --------------------------------------------------------------------------------------------
# CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--records", nargs="+", required=True, metavar="EVAL_JSON",
                        help="run records (eval.json) or folders searched for eval.json")
    parser.add_argument("--out-dir", required=True, help="folder for the CSV and LaTeX tables")


def run(args: argparse.Namespace) -> int:
    records = load_records(args.records)
    if not records:
        raise ValueError("--records: no eval.json run records found")
    written = write_tables(records, args.out_dir)
    print(f"egobench tables: {len(records)} records -> {len(written)} files in {args.out_dir}")
    print(f"egobench tables: {counts_line(pd.read_csv(Path(args.out_dir) / 'gains.csv'))}")
    return 0
