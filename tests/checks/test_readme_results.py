"""The README's results are the committed suite's: every number of its gains table and of its
held-out PSNR table, and the three counts, are recomputed from results/confirmatory_1/tables/."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[2]
TABLES = REPO / "results" / "default" / "tables"  # run 2's
RUN1_TABLES = REPO / "results" / "confirmatory_1" / "tables"


def _markdown_table(header_start: str) -> list[list[str]]:
    lines = (REPO / "README.md").read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def _numbers(cell: str) -> list[float]:
    return [float(x) for x in re.findall(r"[+-]?\d+\.\d+", cell)]


def test_the_gains_table_is_gains_csv():
    gains = pd.read_csv(TABLES / "gains.csv").set_index(["group", "method"])
    rows = _markdown_table("| table | method | vs | egobench ΔPSNR")
    assert len(rows) == len(gains) == 18
    for table, method, ref, delta, scenes, seed_sd, paper, paper_range, sign, p_holm, ratio, magnitude in rows:
        g = gains.loc[(table, method)]
        assert g.unit == "scene"
        assert _numbers(delta) == pytest.approx(
            [g.delta_psnr_mean, g.delta_psnr_ci95_low, g.delta_psnr_ci95_high], abs=0.005), (table, method)
        assert ref == g.reference and int(scenes) == g.n_units
        assert (seed_sd == "–" and pd.isna(g.seed_sd)) or float(seed_sd) == pytest.approx(g.seed_sd, abs=0.005)
        assert float(paper) == pytest.approx(g.paper_delta_psnr_matched, abs=0.005)
        lo, hi, position = re.match(r"\[([+-]\d+\.\d+), ([+-]\d+\.\d+)\]: (\w+)", paper_range).groups()
        assert (float(lo), float(hi)) == pytest.approx((g.paper_delta_psnr_min, g.paper_delta_psnr_max), abs=0.005)
        assert position == g.paper_range_position
        assert (sign == "yes") == bool(g.sign_and_ci) and (magnitude == "yes") == bool(g.magnitude_match)
        assert (p_holm == "<0.0001" and g.p_holm < 1e-4) or float(p_holm) == pytest.approx(g.p_holm, abs=5e-5)
        assert float(ratio) == pytest.approx(g.ratio_to_paper, abs=0.005)


def test_the_counts_sentence_is_the_counts_of_gains_csv():
    from egobench.report.gains import reproduction_counts

    c = reproduction_counts(pd.read_csv(TABLES / "gains.csv"))
    text = " ".join((REPO / "README.md").read_text().split())
    assert (f"of {c['rows']} rows, {c['sign_and_ci']} have the paper's sign with the interval excluding zero, "
            f"{c['survives_holm']} survive Holm, {c['magnitude_match']} match in magnitude") in text


def test_the_per_scene_table_is_results_csv():
    """'ours' per scene: held-out PSNR (mean over the scene's seeds) and resolved wavelength, from results.csv."""
    results = pd.read_csv(TABLES / "results.csv")
    ours = results[results.method == "ours"].groupby("scene")[["psnr", "resolved_wavelength_px"]].mean()
    rows = _markdown_table("| scene | stands for | 'ours' PSNR, dB |")
    assert {r[0] for r in rows} == set(ours.index) and len(rows) == 17
    for scene, _, psnr, wavelength, *_ in rows:
        assert float(psnr) == pytest.approx(ours.loc[scene, "psnr"], abs=0.005), scene
        assert float(wavelength) == pytest.approx(ours.loc[scene, "resolved_wavelength_px"], abs=0.05), scene


def test_the_readme_is_a_front_page():
    """At most ~150 lines: the two commands, what the run produces, the headline results, links."""
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    for link in ("docs/results.md", "docs/gpu-and-cluster.md", "docs/real-recordings.md", "docs/metrics.md"):
        assert link in text and (REPO / link).is_file(), link


def _trained_after_its_protocol(results: pd.DataFrame, protocol: str) -> None:
    """Every run at one commit, and that commit has the protocol page (added in an ancestor)."""
    import subprocess

    assert results.git_commit.nunique() == 1
    commit = results.git_commit.iloc[0]
    git = ["git", "-C", str(REPO)]
    if subprocess.run(git + ["cat-file", "-e", f"{commit}^{{commit}}"], capture_output=True).returncode != 0:
        pytest.skip(f"commit {commit} is not in this clone's history (a shallow clone)")
    protocol_commit = subprocess.run(git + ["log", "--diff-filter=A", "--format=%H", "--", protocol],
                                     capture_output=True, text=True, check=True).stdout.split()[-1]
    assert subprocess.run(git + ["merge-base", "--is-ancestor", protocol_commit, commit]).returncode == 0


def test_run_1_is_its_protocols_confirmatory_run():
    """Run 1 (results/confirmatory_1/) was trained at one commit that contains docs/protocol.md (the protocol was
    fixed before the run), on the protocol's seeds and recordings, and nothing else."""
    results = pd.read_csv(RUN1_TABLES / "results.csv")
    _trained_after_its_protocol(results, "docs/protocol.md")
    protocol = (REPO / "docs" / "protocol.md").read_text()
    seeds = sorted(int(s) for s in re.search(r"Training seeds: ([\d, ]+)", protocol).group(1).replace(",", " ").split())
    per_pair = results.groupby(["scene", "method"]).seed.apply(lambda s: sorted(s.astype(int)))
    assert all(v == seeds for v in per_pair), per_pair
    assert len(per_pair) == 22


def test_run_2_is_protocol_2s_confirmatory_run():
    """Run 2 (the README's, results/default/) was trained at one commit that contains docs/protocol-2.md, on its
    seventeen recordings and its seeds: 1732 everywhere, 508 beside it on outdoor_0 and indoor_0."""
    results = pd.read_csv(TABLES / "results.csv")
    _trained_after_its_protocol(results, "docs/protocol-2.md")
    assert results.scene.nunique() == 17 and len(results) == 111
    per_pair = results.groupby(["scene", "method"]).seed.apply(lambda s: sorted(s.astype(int)))
    for (scene, _), seeds in per_pair.items():
        assert seeds == ([508, 1732] if scene in ("outdoor_0", "indoor_0") else [1732]), scene
    protocol = (REPO / "docs" / "protocol-2.md").read_text()
    for seed in (1414, 2135, 6237, 3095, 8724, 2096, 9807, 8569, 6718, 7537, 6948, 739, 3876, 6735, 6881):
        assert str(seed) in protocol


def test_the_sensitivity_predictions_in_the_readme_are_prediction_csv():
    pred = pd.read_csv(REPO / "results" / "default" / "sensitivity" / "prediction.csv")
    text = " ".join((REPO / "README.md").read_text().split())
    shown = 0
    for r in pred.itertuples():
        if pd.notna(r.predicted_delta_psnr):
            assert f"{r.predicted_delta_psnr:.2f} [{r.predicted_ci95_low:.2f}, {r.predicted_ci95_high:.2f}]" in text, r.ablation
            shown += 1
    assert shown == 2
