"""Tables from synthetic run records, and the paper-number transcription against paper.tex."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from egobench.report import paper_numbers as pn
from egobench.report import gains as G
from egobench.report import records as Rec
from egobench.report import tables as T
from egobench.cli import main as cli_main
from tests.helpers import write_records

PAPER_TEX = Path(__file__).resolve().parents[3] / "shared" / "paper" / "paper.tex"


def make_record(scene, kind, method, seed, psnr, ssim=0.5, paper_scene=None, **metrics):
    return {
        "schema": "egobench.run/1", "scene": scene, "scene_kind": kind, "paper_scene": paper_scene,
        "method": method, "seed": seed, "device": "aria", "calibration": "online",
        "config_hash": "x", "git_commit": "y", "egobench_version": "0.1.0", "recording": "rec",
        "train": {"iterations": 10, "time_s": 1.0, "iters_per_s": 10.0, "num_gaussians": 5},
        "metrics": {"psnr": psnr, "ssim": ssim, **{k: metrics.get(k) for k in (
            "lpips", "depth_mse_authors", "normal_cos_authors", "depth_si_l1", "normal_l1")}},
        "recording_stats": {"num_frames": 96, "head_angular_speed_deg_s_p50": 30.0 + seed},
        "notes": {}, "per_image": [],
    }




# Our synthetic suite: PSNR(method, scene, seed) = base[method] + scene offset + seed effect.
BASE = {"splatfacto": 20.0, "on_the_move": 20.5, "ours": 25.0, "no_viba": 23.0, "no_motion_sampling": 24.0,
        "no_scene_gamma": 22.5}
SEED_EFFECT = {"ours": [0.0, 1.0, 2.0], "no_viba": [0.0, 0.0, 0.0]}  # others: 0


def suite_records() -> list[dict]:
    recs = []
    for scene, kind, ps, off in (("out_a", "outdoor", "bike shop", 0.0), ("out_b", "outdoor", "garden", -2.0),
                                 ("in_a", "indoor", "library", -1.0)):
        for m, b in BASE.items():
            for seed in (0, 1, 2):
                psnr = b + off + SEED_EFFECT.get(m, [0, 0, 0])[seed]
                recs.append(make_record(scene, kind, m, seed, psnr, ssim=0.1 + b / 100, paper_scene=ps))
    for scene, off in (("obj_a", 0.0), ("obj_b", 2.0)):
        for m, b in (("ours", 28.0), ("no_viba", 27.0), ("ours_2dgs", 27.5), ("2dgs_no_motion_sampling", 26.0)):
            for seed in (0, 1):
                recs.append(make_record(scene, "object", m, seed, b + off + seed, paper_scene="DTC objects",
                                        depth_mse_authors=0.2 - b / 1000, normal_cos_authors=0.3,
                                        depth_si_l1=0.5, normal_l1=1.0))
    for m, b in (("ours", 30.0), ("no_viba", 28.0)):
        recs.append(make_record("quest", "quest3", m, 0, b, ssim=0.9, paper_scene="Quest 3", lpips=0.25))
    return recs


@pytest.fixture
def built(tmp_path):
    paths = write_records(tmp_path / "runs", suite_records())
    records = Rec.load_records([tmp_path / "runs"])
    out = tmp_path / "tables"
    T.write_tables(records, out)
    return records, out


def test_all_outputs_written_atomically(built):
    _, out = built
    assert sorted(p.name for p in out.iterdir()) == sorted(T.OUTPUT_FILES)  # no temp files left over
    results = pd.read_csv(out / "results.csv")
    assert len(results) == len(suite_records())
    assert np.isfinite(results["psnr"]).all()


def test_table1_shape_values_and_paper_block(built):
    _, out = built
    df = pd.read_csv(out / "table1_outdoor.csv")
    ours = df[df["block"] == T.OURS_BLOCK].set_index("method")
    paper = df[df["block"] == T.PAPER_BLOCK].set_index("method")
    # Rows in the paper's order (baselines, then ours and its ablations); scenes as columns in the
    # paper's column order (bike shop before garden).
    assert list(ours.index) == ["splatfacto", "on_the_move", "ours", "no_viba", "no_motion_sampling", "no_scene_gamma"]
    assert list(paper.index) == list(pn.TABLE1_OUTDOOR.methods)
    cols = [c for c in df.columns if c.endswith(" PSNR")]
    assert cols == ["out_a (bike shop) PSNR", "out_b (garden) PSNR", "mean PSNR"]
    # the mean over the scenes of each scene's seed mean (26 and 24), std over the scenes; the paper's over its
    # columns shown (bike shop and garden)
    assert ours.loc["ours", "mean PSNR"] == pytest.approx(25.0)
    assert ours.loc["ours", "mean PSNR std"] == pytest.approx(2 ** 0.5)
    assert paper.loc["ours", "mean PSNR"] == pytest.approx((29.98 + 24.00) / 2)
    # Mean and sample std over seeds: ours on out_a = 25 + {0,1,2}.
    assert ours.loc["ours", "out_a (bike shop) PSNR"] == pytest.approx(26.0)
    assert ours.loc["ours", "out_a (bike shop) PSNR std"] == pytest.approx(1.0)
    assert ours.loc["no_viba", "out_b (garden) PSNR"] == pytest.approx(21.0)
    # Paper numbers beside ours, in the matching column.
    assert paper.loc["ours", "out_b (garden) PSNR"] == pn.TABLE1_OUTDOOR.value("ours", "garden", "psnr") == 24.00
    assert paper.loc["on_the_move", "out_a (bike shop) SSIM"] == 0.806
    # Best in bold: ours is best in every PSNR column of our block, once.
    for c in cols:
        assert ours[f"{c} best"].tolist() == [m == "ours" for m in ours.index]
    tex = (out / "table1_outdoor.tex").read_text()
    assert "\\textbf{26.00}" in tex and "\\toprule" in tex and "\\bottomrule" in tex
    assert "out\\_a (bike shop)" in tex  # escaped for LaTeX
    combined = (out / "table1.tex").read_text()
    assert "in\\_a (library)" in combined and "out\\_b (garden)" in combined


def test_bold_ties_and_lower_is_better():
    block = T.Block("egobench", "t", [["a", "b", "c"]], {
        "a": [T.Cell(1.0), T.Cell(0.30)],
        "b": [T.Cell(1.001), T.Cell(0.20)],  # ties with a at 2 decimals for PSNR
        "c": [T.Cell(0.5), T.Cell(None)],
    })
    T.mark_best(block, 2, ["psnr", "depth_si_l1"], per_group=False)
    assert [block.rows[m][0].bold for m in "abc"] == [True, True, False]
    assert [block.rows[m][1].bold for m in "abc"] == [False, True, False]


def test_table2_aggregates_scenes_and_bolds_per_group(built):
    _, out = built
    df = pd.read_csv(out / "table2.csv")
    ours = df[df["block"] == T.OURS_BLOCK].set_index("method")
    col = [c for c in df.columns if c.endswith(" PSNR")][0]
    # seed 0: mean(28, 30) = 29; seed 1: 30 -> mean 29.5, std sqrt(0.5)
    assert ours.loc["ours", col] == pytest.approx(29.5)
    assert ours.loc["ours", f"{col} std"] == pytest.approx(math.sqrt(0.5))
    # 3D-GS group and 2D-GS group are bolded separately (as the paper does).
    assert bool(ours.loc["ours", f"{col} best"]) and bool(ours.loc["ours_2dgs", f"{col} best"])
    depth = [c for c in df.columns if c.endswith(" Depth")][0]
    assert bool(ours.loc["ours", f"{depth} best"])  # lower depth error is better: 0.2 - 28/1000 is lowest
    paper = df[df["block"] == T.PAPER_BLOCK].set_index("method")
    assert paper.loc["splatfacto", col] == 24.81
    t3 = pd.read_csv(out / "table3.csv").set_index(["block", "method"])
    lp = [c for c in t3.columns if c.endswith(" LPIPS")][0]
    assert t3.loc[(T.OURS_BLOCK, "ours"), lp] == pytest.approx(0.25)
    assert t3.loc[(T.PAPER_BLOCK, "no_viba"), lp] == 0.2731


def test_gains_match_hand_computation(built):
    records, out = built
    g = pd.read_csv(out / "gains.csv").set_index(["group", "method"])
    # Outdoor, no_viba - ours per seed (2 scenes): seed s: -2 - s -> [-2, -3, -4]: mean -3, std 1.
    row = g.loc[("table1_outdoor", "no_viba")]
    assert row["reference"] == "ours" and row["n_scenes"] == 2 and row["n_seeds"] == 3
    assert row["delta_psnr_mean"] == pytest.approx(-3.0)
    assert row["delta_psnr_std"] == pytest.approx(1.0)
    # splatfacto: -5 - s -> mean -6
    assert g.loc[("table1_outdoor", "splatfacto"), "delta_psnr_mean"] == pytest.approx(-6.0)
    # Paper, matched scenes (bike shop, garden) and all six scenes.
    p = pn.TABLE1_OUTDOOR
    matched = np.mean([p.value("no_viba", s, "psnr") - p.value("ours", s, "psnr") for s in ("bike shop", "garden")])
    every = np.mean([p.value("no_viba", s, "psnr") - p.value("ours", s, "psnr") for s in p.columns])
    assert row["paper_delta_psnr_matched"] == pytest.approx(matched)
    assert row["paper_delta_psnr_all"] == pytest.approx(every)
    # The 2D-GS ablation is measured against ours_2dgs: 26 - 27.5 = -1.5 on every scene and seed.
    r2 = g.loc[("table2", "2dgs_no_motion_sampling")]
    assert r2["reference"] == "ours_2dgs"
    assert r2["delta_psnr_mean"] == pytest.approx(-1.5) and r2["delta_psnr_std"] == pytest.approx(0.0)
    assert r2["paper_delta_psnr_matched"] == pytest.approx(28.75 - 29.54)
    # One seed: no std.
    assert math.isnan(g.loc[("table3", "no_viba"), "delta_psnr_std"])
    assert g.loc[("table3", "no_viba"), "delta_psnr_mean"] == pytest.approx(-2.0)


def test_table4_beside_paper(built):
    _, out = built
    t4 = pd.read_csv(out / "table4.csv").set_index("scene")
    assert t4.loc["out_a", "frames"] == 96
    assert t4.loc["out_a", "paper_frames"] == 1611
    assert t4.loc["in_a", "paper_scenario"] == "indoor, dim light, 200- lux"
    assert t4.loc["out_a", "head_speed_deg_s_p50"] == pytest.approx(30.0)


def test_no_runs_of_a_kind_still_shows_the_paper(tmp_path):
    recs = [make_record("o", "outdoor", "ours", 0, 25.0, paper_scene="bike shop")]
    records = Rec.load_records(write_records(tmp_path, recs))
    t = T.build_per_scene_table(records, "table1_indoor")
    assert t.groups == list(pn.TABLE1_INDOOR.columns)
    assert not t.blocks[0].rows and t.notes
    assert "24.59" in T.shaped_to_latex([t], t.caption, t.label)


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda r: r.update(schema="egobench.run/0"), "schema"),
        (lambda r: r.pop("method"), "method"),
        (lambda r: r.update(seed="0"), "seed"),
        (lambda r: r["metrics"].update(psnr=None), "metrics.psnr"),
        (lambda r: r["metrics"].update(ssim="high"), "metrics.ssim"),
    ],
)
def test_bad_records_name_file_and_field(tmp_path, mutate, field):
    rec = make_record("s", "outdoor", "ours", 0, 25.0)
    mutate(rec)
    (path,) = write_records(tmp_path, [rec])
    with pytest.raises(ValueError, match=re.escape(field)) as exc:
        Rec.load_records([path])
    assert str(path) in str(exc.value)


def test_nan_and_duplicates_rejected(tmp_path):
    p = tmp_path / "eval.json"
    p.write_text(json.dumps(make_record("s", "outdoor", "ours", 0, 25.0)).replace("25.0", "NaN"))
    with pytest.raises(ValueError, match="metrics.psnr"):
        Rec.load_records([p])
    dup = write_records(tmp_path / "d", [make_record("s", "outdoor", "ours", 0, 25.0)] * 2)
    with pytest.raises(ValueError, match="duplicate"):
        Rec.load_records(dup)
    with pytest.raises(FileNotFoundError, match="missing.json"):
        Rec.load_records([tmp_path / "missing.json"])


def test_cli_writes_tables(tmp_path):
    paths = write_records(tmp_path / "runs", suite_records()[:6])
    assert cli_main(["tables", "--records", *map(str, paths), "--out-dir", str(tmp_path / "t")]) == 0
    assert all((tmp_path / "t" / f).is_file() for f in T.OUTPUT_FILES)
    assert cli_main(["tables", "--records", str(tmp_path / "empty_dir_missing"), "--out-dir", str(tmp_path / "u")]) == 2


# ------------------------------------------------------------------------------------------------
# The transcription of the paper's numbers, checked against an independent parse of paper.tex.


def _tex_table(tex: str, label: str) -> str:
    end = tex.index(f"\\label{{{label}}}")
    start = tex.rindex("\\begin{tabular}", 0, end)
    return tex[start:end]


def _numeric_rows(block: str) -> list[tuple[str, list[float]]]:
    rows = []
    for line in block.replace("\n", " ").split("\\\\"):
        cells = [re.sub(r"\\textbf\{([^}]*)\}", r"\1", c).strip() for c in line.split("&")]
        cells = [re.sub(r"\\(toprule|midrule|bottomrule|cite\{[^}]*\})", "", c).strip() for c in cells]
        nums = [c for c in cells[1:] if re.fullmatch(r"-?\d+(\.\d+)?", c)]
        if len(cells) > 1 and nums and len(nums) == len(cells) - 1:
            rows.append((cells[0], [float(x) for x in nums]))
    return rows


@pytest.fixture
def paper_tex() -> str:
    if not PAPER_TEX.is_file():
        pytest.skip(f"paper source not found at {PAPER_TEX}")
    return PAPER_TEX.read_text()


def test_table1_transcription(paper_tex):
    rows = _numeric_rows(_tex_table(paper_tex, "tab:aria_scene"))
    assert len(rows) == 12
    order = list(pn.TABLE1_OUTDOOR.methods)
    for block, table in ((rows[:6], pn.TABLE1_OUTDOOR), (rows[6:], pn.TABLE1_INDOOR)):
        for (label, nums), method in zip(block, order):
            assert len(nums) == 12, label
            for j, scene in enumerate(table.columns):
                assert table.value(method, scene, "psnr") == nums[2 * j], (method, scene)
                assert table.value(method, scene, "ssim") == nums[2 * j + 1], (method, scene)
    # The column headers name the scenes in the transcribed order.
    heads = re.findall(r"\\multicolumn\{2\}\{c\}\{([^}]*)\}", _tex_table(paper_tex, "tab:aria_scene"))
    assert [h.strip().lower() for h in heads] == list(pn.TABLE1_OUTDOOR_SCENES + pn.TABLE1_INDOOR_SCENES)


def test_tables2_3_transcription(paper_tex):
    rows2 = _numeric_rows(_tex_table(paper_tex, "tab:dtc_evaluation"))
    assert len(rows2) == 7
    for (label, nums), method in zip(rows2, pn.TABLE2.methods):
        assert [pn.TABLE2.value(method, pn.DTC_COLUMN, k) for k in pn.TABLE2.metrics] == nums, label
    rows3 = _numeric_rows(_tex_table(paper_tex, "tab:quest_scene"))
    assert len(rows3) == 3
    for (label, nums), method in zip(rows3, pn.TABLE3.methods):
        assert [pn.TABLE3.value(method, pn.QUEST_COLUMN, k) for k in pn.TABLE3.metrics] == nums, label


def test_table4_transcription(paper_tex):
    block = _tex_table(paper_tex, pn.TABLE4_LABEL)
    found = {}
    for line in block.split("\\\\"):
        cells = [c.strip() for c in re.sub(r"\\(toprule|midrule|bottomrule)", "", line).split("&")]
        if len(cells) == 3 and cells[1].isdigit():
            found[cells[0].lower()] = pn.SceneStatistics(int(cells[1]), cells[2])
    assert found == dict(pn.TABLE4)


def test_record_without_kind_only_in_results(tmp_path):
    recs = [make_record("o", "outdoor", "ours", 0, 25.0, paper_scene="bike shop"),
            make_record("real", None, "ours", 0, 21.0)]
    records = Rec.load_records(write_records(tmp_path / "r", recs))
    T.write_tables(records, tmp_path / "t")
    results = pd.read_csv(tmp_path / "t" / "results.csv")
    assert sorted(results["scene_kind"]) == ["outdoor", "unknown"]
    for name in ("table1_outdoor", "table1_indoor", "table2", "table3"):
        assert "real" not in (tmp_path / "t" / f"{name}.csv").read_text()
    assert "\\texttt{tab:aria\\_scene}" in (tmp_path / "t" / "table1_outdoor.tex").read_text()


# ----------------------------------------------------------------------------- paired deltas, intervals
def test_gains_carry_a_paired_95_percent_interval_over_seeds():
    """Seed-level paired Δ of -1, -2, -3 dB: mean -2, sd 1, t(0.975, 2) = 4.302653 -> -2 -+ 2.48414."""
    recs = []
    for seed, delta in enumerate((-1.0, -2.0, -3.0)):
        recs.append(make_record("out_a", "outdoor", "ours", seed, 25.0 + seed))
        recs.append(make_record("out_a", "outdoor", "no_viba", seed, 25.0 + seed + delta))
    g = G.gains_frame([Rec.parse_record(r) for r in recs]).set_index("method").loc["no_viba"]
    half = 4.302652729911275 * 1.0 / math.sqrt(3)
    assert g["delta_psnr_mean"] == pytest.approx(-2.0) and g["delta_psnr_std"] == pytest.approx(1.0)
    assert g["delta_psnr_ci95_low"] == pytest.approx(-2.0 - half) and g["delta_psnr_ci95_high"] == pytest.approx(-2.0 + half)
    assert g["identical"] == "" and G.ci95([0.5]) == (None, None)
    assert "[-4.48, +0.48]" in T.gains_to_latex(G.gains_frame([Rec.parse_record(r) for r in recs]))


def test_a_row_identical_by_construction_is_named_not_measured():
    """Motion sampling that never switched on (one pose sample on every frame of ours) gives the ablation
    the same computation: the row says so instead of '+0.00'. Once any frame has two samples (and the
    PSNRs differ), it is a measurement again."""
    def pair(seed, samples, psnr_ablation):
        ours = make_record("out_a", "outdoor", "ours", seed, 25.0)
        ours["per_image"] = [{"frame": 0, "psnr": 25.0, "pose_samples": s} for s in samples]
        ours["eval"] = {"pose_samples_mean": float(np.mean(samples))}
        return [ours, make_record("out_a", "outdoor", "no_motion_sampling", seed, psnr_ablation)]

    same = [Rec.parse_record(r) for s in range(3) for r in pair(s, [1, 1, 1], 25.0)]
    row = G.gains_frame(same).set_index("method").loc["no_motion_sampling"]
    assert row["identical"].startswith("identical by construction") and pd.isna(row["delta_psnr_mean"])
    assert "\\emph{identical by construction}" in T.gains_to_latex(G.gains_frame(same))
    active = [Rec.parse_record(r) for s in range(3) for r in pair(s, [1, 3, 2], 24.5)]
    row = G.gains_frame(active).set_index("method").loc["no_motion_sampling"]
    assert row["identical"] == "" and row["delta_psnr_mean"] == pytest.approx(-0.5)


def test_holm_matches_a_hand_computation():
    # p = (0.01, 0.04, 0.03, None, 0.005): sorted 0.005, 0.01, 0.03, 0.04 with m = 4 ->
    # 4 x 0.005 = 0.02, 3 x 0.01 = 0.03, 2 x 0.03 = 0.06, max(0.06, 1 x 0.04) = 0.06 (step-down monotone)
    adj = G.holm([0.01, 0.04, 0.03, None, 0.005])
    assert adj[3] is None
    assert adj[4] == pytest.approx(0.02) and adj[0] == pytest.approx(0.03)
    assert adj[2] == pytest.approx(0.06) and adj[1] == pytest.approx(0.06)


def test_p_in_the_papers_direction_is_scipys_one_sided_t_test():
    from scipy.stats import ttest_1samp

    seeds = [-1.2, -0.4, -0.9, 0.1]
    assert G.p_in_direction(seeds, -0.5) == pytest.approx(ttest_1samp(seeds, 0.0, alternative="less").pvalue)
    assert G.p_in_direction(seeds, +0.5) == pytest.approx(ttest_1samp(seeds, 0.0, alternative="greater").pvalue)
    assert G.p_in_direction([-1.0], -0.5) is None and G.p_in_direction(seeds, None) is None


def test_reproduction_columns_and_counts():
    df = pd.DataFrame({
        "delta_psnr_mean": [-1.0, -0.2, -3.0, 0.5], "delta_psnr_ci95_low": [-1.5, -0.6, -3.5, 0.1],
        "delta_psnr_ci95_high": [-0.5, 0.2, -2.5, 0.9], "paper_delta_psnr_matched": [-1.2, -0.5, -1.0, -0.4],
        "p_one_sided": [0.001, 0.2, 0.0001, 0.99]})
    out = G.with_reproduction_columns(df)
    assert list(out["sign_and_ci"]) == [True, False, True, False]
    assert list(out["paper_in_ci"]) == [True, True, False, False]
    # ratio 3.0 (row 3) is outside a factor 2, and the paper's -1.0 is outside [-3.5, -2.5]
    assert list(out["magnitude_match"]) == [True, True, False, False]
    assert list(out["survives_holm"]) == [True, False, True, False]  # 4 x 0.0001, 3 x 0.001; 2 x 0.2
    assert G.reproduction_counts(out) == {"rows": 4, "sign_and_ci": 2, "survives_holm": 2, "magnitude_match": 2}


def test_lpips_is_in_every_table_with_the_papers_cells_empty_where_it_has_none(tmp_path):
    recs = suite_records()
    for i, r in enumerate(recs):
        r["metrics"]["lpips"] = 0.1 + 0.01 * (i % 3)
    write_records(tmp_path / "runs", recs)
    T.write_tables(Rec.load_records([tmp_path / "runs"]), tmp_path / "tables")
    for name in ("table1_outdoor", "table1_indoor", "table2", "table3"):
        df = pd.read_csv(tmp_path / "tables" / f"{name}.csv")
        cols = [c for c in df.columns if c.endswith(" LPIPS")]
        assert cols, name
        ours, paper = df[df["block"] == T.OURS_BLOCK], df[df["block"] == T.PAPER_BLOCK]
        assert ours[cols].notna().all().all(), name
        if name != "table3":  # only Table 3 reports LPIPS in the paper
            assert paper[cols].isna().all().all(), name
    t3 = pd.read_csv(tmp_path / "tables" / "table3.csv").set_index(["block", "method"])
    col = [c for c in t3.columns if c.endswith(" LPIPS")][0]
    assert t3.loc[(T.PAPER_BLOCK, "ours"), col] == pn.TABLE3.value("ours", pn.QUEST_COLUMN, pn.LPIPS)


def _scene_unit_records() -> list:
    """Three outdoor scenes; no_viba - ours = -1 and -2 dB on out_a's two seeds, -0.5 on out_b, -1.0 on out_c."""
    recs = []
    for scene, ps, deltas in (("out_a", "bike shop", {0: -1.0, 1: -2.0}), ("out_b", "steakhouse patio", {0: -0.5}),
                              ("out_c", "garden", {0: -1.0})):
        for seed, d in deltas.items():
            recs.append(make_record(scene, "outdoor", "ours", seed, 25.0 + seed, paper_scene=ps))
            recs.append(make_record(scene, "outdoor", "no_viba", seed, 25.0 + seed + d, paper_scene=ps))
    return [Rec.parse_record(r) for r in recs]


def test_gains_over_scenes_average_a_scenes_seeds_first():
    """Scenes as the unit: a scene's seeds averaged first (-1.5, -0.5, -1.0), then the t-interval over the three
    scenes (2 degrees of freedom); the seed spread from the scene with two seeds; the paper's per-scene range."""
    recs = _scene_unit_records()
    assert G.inference_unit(recs) == "scene"
    g = G.gains_frame(recs).set_index("method").loc["no_viba"]
    assert (g.unit, g.n_units, g.n_scenes, g.n_seeds) == ("scene", 3, 3, 2)
    assert g.delta_psnr_mean == pytest.approx(-1.0) and g.delta_psnr_std == pytest.approx(0.5)
    half = 4.302652729911275 * 0.5 / 3 ** 0.5  # t(0.975, 2)
    assert (g.delta_psnr_ci95_low, g.delta_psnr_ci95_high) == pytest.approx((-1.0 - half, -1.0 + half))
    assert g.seed_sd == pytest.approx(0.5 ** 0.5)  # sd of (-1, -2)
    assert g.p_one_sided == pytest.approx(0.037089, abs=1e-5)  # t = -3.464 with 2 df, one-sided
    # the paper: no_viba - ours on bike shop, steakhouse patio and garden = -2.30, -1.35, -1.42
    assert (g.paper_delta_psnr_min, g.paper_delta_psnr_max) == pytest.approx((-2.30, -1.35))
    assert g.paper_delta_psnr_matched == pytest.approx((-2.30 - 1.35 - 1.42) / 3)
    assert bool(g.ci_overlaps_paper_range) and g.paper_range_position == "above"
    # the same records with the seed as the unit: per seed the mean over the scenes it has
    s = G.gains_frame(recs, unit="seed").set_index("method").loc["no_viba"]
    assert s.unit == "seed" and s.n_units == 2
    assert s.delta_psnr_mean == pytest.approx(((-1.0 - 0.5 - 1.0) / 3 + -2.0) / 2)


def test_the_unit_is_named_and_chosen_from_the_design():
    recs = _scene_unit_records()
    one_scene = [r for r in recs if r.scene == "out_a"]
    assert G.inference_unit(one_scene) == "seed"  # one recording per kind: run 1's design
    with pytest.raises(ValueError, match="unit: expected one of"):
        G.inference_unit(recs, "frame")


def test_tables_2_and_3_spread_over_scenes_or_seeds(built):
    """obj_a and obj_b: ours = 28 + offset (0, 2) + seed (0, 1). Over scenes: the scene means 28.5 and 30.5;
    over seeds: the seeds' means over the scenes, 29 and 30."""
    records, _ = built
    by_scene = T.build_aggregate_table(records, "table2", "scene")
    by_seed = T.build_aggregate_table(records, "table2", "seed")
    ours_scene = by_scene.blocks[0].rows["ours"][0]
    ours_seed = by_seed.blocks[0].rows["ours"][0]
    assert (ours_scene.mean, ours_scene.std, ours_scene.n) == pytest.approx((29.5, 2 ** 0.5, 2))
    assert (ours_seed.mean, ours_seed.std, ours_seed.n) == pytest.approx((29.5, 0.5 ** 0.5, 2))
    assert "std over scenes" in by_scene.blocks[0].title and "std over seeds" in by_seed.blocks[0].title
