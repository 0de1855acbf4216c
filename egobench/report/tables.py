"""Paper-shaped tables from run records (``eval.json``, schema ``egobench.run/1``).

Everything here is computed from the records' contents, never from their paths. Outputs (CSV and
booktabs LaTeX, written atomically):

- ``results.csv``: one row per record (the combined results),
- ``table1_outdoor``, ``table1_indoor`` (+ ``table1.tex`` holding both blocks), ``table2``,
  ``table3``: methods as rows, scenes as columns, best in bold, the paper's numbers in an adjacent
  block (same columns, matched through the record's ``paper_scene``),
- ``table4``: dataset statistics, ours beside the paper's,
- ``gains``: mean PSNR change of each ablation/baseline relative to its reference (``ours``;
  ``ours_2dgs`` for the 2D-GS ablation), ours (mean and interval over seeds or scenes) versus the paper's
  (`egobench.report.gains`).

The records are read by `egobench.report.records`.

``egobench tables --records R1.json R2.json ... --out-dir DIR [--unit auto|seed|scene]``
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from egobench.io_utils import atomic_path
from egobench.report import paper_numbers as pn
from egobench.report.gains import UNITS, counts_line, gains_frame, inference_unit
from egobench.report.outputs import TABLE_FILES
from egobench.report.records import GROUPS, NUM_FRAMES_KEY, RunRecord, load_records, method_label, records_frame

OUTPUT_FILES = TABLE_FILES  # every file `write_tables` produces (egobench.report.outputs)
OURS_BLOCK = "egobench"
PAPER_BLOCK = "paper"


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
    if len(scene_cols) > 1 and scene_cols[0][0]:  # several scenes: their mean, as the paper's last column
        groups.append(MEAN_COLUMN)
        _add_scene_means(ours_rows, paper_rows, recs, paper, [ps for _, ps in scene_cols], metrics)
        notes.append(f"{MEAN_COLUMN}: egobench, the mean over the scenes of each scene's mean over its seeds "
                     "(std over the scenes); the paper, the mean over the columns shown")
    return _assemble(group, paper, groups, metrics, ours_rows, paper_rows, notes, per_group=False)


#: the column of Table 1 that holds the mean over its scenes
MEAN_COLUMN = "mean"


def _add_scene_means(ours_rows: dict, paper_rows: dict, recs: Sequence[RunRecord], paper: pn.PaperTable,
                     paper_scenes: list[str | None], metrics: list[str]) -> None:
    """Append the mean-over-scenes cells to every row: ours over the scenes' seed means, the paper's over
    ``paper_scenes``."""
    for m in ours_rows:
        mine = [r for r in recs if r.method == m]
        ours_rows[m].extend(_stats(list(per_scene_mean(mine, k).values())) for k in metrics)
    for m in paper_rows:
        for k in metrics:
            vals = [paper.value(m, ps, k) for ps in paper_scenes if ps]
            vals = [v for v in vals if v is not None]
            paper_rows[m].append(Cell(float(np.mean(vals)), None, len(vals)) if vals else Cell())


def build_aggregate_table(records: Sequence[RunRecord], group: str, unit: str = "seed") -> ShapedTable:
    """Tables 2 and 3: one column (mean over our scenes of that kind) beside the paper's. ``unit`` "seed":
    std over the seeds of the mean over scenes; "scene": std over the scenes of each scene's seed mean."""
    kind, paper = GROUPS[group]
    recs = [r for r in records if r.scene_kind == kind]
    metrics = table_metrics(paper) + _all_surface_metrics(group, recs)
    scenes = sorted({r.scene for r in recs})
    spread = "std over seeds of the scene mean" if unit == "seed" else "std over scenes of each scene's seed mean"
    notes = [f"egobench: mean over {len(scenes)} scene(s) of kind {kind!r}: {', '.join(scenes) or 'none'}; {spread}"]
    per_unit = _per_seed_scene_mean if unit == "seed" else per_scene_mean
    ours_rows = {m: [_stats(list(per_unit([r for r in recs if r.method == m], k).values())) for k in metrics]
                 for m in sorted({r.method for r in recs})}
    paper_rows = {m: [Cell(paper.value(m, paper.columns[0], k), None, 1) for k in metrics] for m in paper.methods}
    label = f"{kind} ({len(scenes)} scene{'s' if len(scenes) != 1 else ''}) / {paper.columns[0]}"
    return _assemble(group, paper, [label], metrics, ours_rows, paper_rows, notes, per_group=group == "table2",
                     spread=unit)


def _all_surface_metrics(group: str, recs: Sequence[RunRecord]) -> list[str]:
    """Table 2's geometry over every surface in view, beside the foreground's, where the records have it."""
    if group != "table2":
        return []
    return [k for k in (pn.DEPTH_ALL, pn.NORMAL_ALL) if any(r.metrics.get(k) is not None for r in recs)]


def _means_by(recs: Sequence[RunRecord], metric: str, key) -> dict:
    """key(record) -> the mean of the metric over the records with that key (records without a value skipped)."""
    out: dict = {}
    for k in sorted({key(r) for r in recs}):
        vals = [r.metrics[metric] for r in recs if key(r) == k and r.metrics[metric] is not None]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def _per_seed_scene_mean(recs: Sequence[RunRecord], metric: str) -> dict[int, float]:
    """seed -> mean over scenes of the metric (scenes without a value are skipped)."""
    return _means_by(recs, metric, lambda r: r.seed)


def per_scene_mean(recs: Sequence[RunRecord], metric: str) -> dict[str, float]:
    """scene -> mean over its seeds of the metric (seeds without a value are skipped)."""
    return _means_by(recs, metric, lambda r: r.scene)


def _assemble(group, paper, groups, metrics, ours_rows, paper_rows, notes, per_group, spread="seed") -> ShapedTable:
    title = f"egobench (this run; mean $\\pm$ std over {spread}s)"
    ours = Block(OURS_BLOCK, title, _row_groups(paper, ours_rows), ours_rows)
    ours.row_groups = [[m for m in g if m in ours_rows] for g in ours.row_groups]
    ours.row_groups = [g for g in ours.row_groups if g]
    theirs = Block(PAPER_BLOCK, f"paper (Lv et al. 2025, \\texttt{{{latex_escape(paper.label)}}})", [list(g) for g in paper.row_groups], paper_rows)
    metric_per_col = [m for _ in groups for m in metrics]
    for b in (ours, theirs):
        mark_best(b, len(metric_per_col), metric_per_col, per_group)
    return ShapedTable(group, paper.caption, f"tab:egobench_{group}", groups, metrics, [ours, theirs], notes)



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
    units = _units_header(df)
    lines = _latex_head(
        "Mean PSNR change (dB) relative to the reference method on the same recordings: egobench (mean "
        f"over {units}, 95\\,\\% interval over {units}) versus the paper (same scenes / all of the table's scenes).",
        "llcccc",
    ) + [
        f"table & method (vs.\\ reference) & {units} & egobench $\\Delta$PSNR & paper (matched) & paper (all) \\\\",
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
            f"{latex_escape(r['group'])} & {method} (vs.\\ {ref}) & {int(r.get('n_units', r['n_seeds']))} & "
            f"{_gain_cell(r)} & "
            f"{_num(r['paper_delta_psnr_matched'], 2, True)} & {_num(r['paper_delta_psnr_all'], 2, True)} \\\\"
        )
    lines += ["\\bottomrule", "\\end{tabular}", "\\par\\footnotesize " + latex_escape("O" + counts_line(df)[1:]) + ".",
              "\\label{tab:egobench_gains}", "\\end{table}", ""]
    return "\n".join(lines)


def _units_header(df: pd.DataFrame) -> str:
    """The gains table's count column: the unit of inference (seeds or scenes)."""
    unit = df["unit"].iloc[0] if "unit" in df and len(df) else "seed"
    return f"{unit}s"


def _gain_cell(r: pd.Series) -> str:
    """Our Δ with its interval over the units, or the reason it is not a measurement."""
    if isinstance(r.get("identical"), str) and r["identical"]:
        return "\\emph{" + latex_escape(r["identical"].split(":")[0]) + "}"
    ours = _num(r["delta_psnr_mean"], 2, True)
    low, high = r.get("delta_psnr_ci95_low"), r.get("delta_psnr_ci95_high")
    if low is not None and not pd.isna(low):
        ours += f"\\,{{\\scriptsize[{low:+.2f}, {high:+.2f}]}}"
    else:
        ours += f"\\,{{\\scriptsize(1 {r.get('unit', 'seed')})}}"
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


def build_tables(records: Sequence[RunRecord], unit: str = "auto") -> dict[str, ShapedTable]:
    """The four paper-shaped tables (Table 1 as two blocks); ``unit`` as `gains.inference_unit`."""
    unit = inference_unit(records, unit)
    return {
        "table1_outdoor": build_per_scene_table(records, "table1_outdoor"),
        "table1_indoor": build_per_scene_table(records, "table1_indoor"),
        "table2": build_aggregate_table(records, "table2", unit),
        "table3": build_aggregate_table(records, "table3", unit),
    }


def write_tables(records: Sequence[RunRecord], out_dir: str | Path, unit: str = "auto") -> list[Path]:
    """Write every file in OUTPUT_FILES into out_dir (atomically); return their paths. ``unit``: the unit of
    inference of the gains and of Tables 2 and 3 (`gains.inference_unit`)."""
    out = Path(out_dir)
    written = [_write_csv(out / "results.csv", records_frame(records))]
    tables = build_tables(records, unit)
    for name, t in tables.items():
        written.append(_write_csv(out / f"{name}.csv", shaped_to_frame(t)))
        written.append(_write_text(out / f"{name}.tex", shaped_to_latex([t], t.caption, t.label)))
    written.append(_write_text(out / "table1.tex", shaped_to_latex(
        [tables["table1_outdoor"], tables["table1_indoor"]],
        "Aria scene dataset (Table 1): egobench beside the paper", "tab:egobench_table1")))
    t4 = table4_frame(records)
    written += [_write_csv(out / "table4.csv", t4), _write_text(out / "table4.tex", table4_to_latex(t4))]
    g = gains_frame(records, unit)
    written += [_write_csv(out / "gains.csv", g), _write_text(out / "gains.tex", gains_to_latex(g))]
    return written


# --------------------------------------------------------------------------------------------
# CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--records", nargs="+", required=True, metavar="EVAL_JSON",
                        help="run records (eval.json) or folders searched for eval.json")
    parser.add_argument("--out-dir", required=True, help="folder for the CSV and LaTeX tables")
    parser.add_argument("--unit", choices=UNITS, default="auto",
                        help="unit of inference of the gains and Tables 2-3: training seeds on one recording per "
                             "kind, or scenes (auto: scenes when every kind has two or more)")


def run(args: argparse.Namespace) -> int:
    records = load_records(args.records)
    if not records:
        raise ValueError("--records: no eval.json run records found")
    written = write_tables(records, args.out_dir, args.unit)
    print(f"egobench tables: {len(records)} records -> {len(written)} files in {args.out_dir}")
    print(f"egobench tables: {counts_line(pd.read_csv(Path(args.out_dir) / 'gains.csv'))}")
    return 0
