"""The README's results are the committed suite's: every number of its gains table and of its
held-out PSNR table, and the three counts, are recomputed from results/confirmatory_1/tables/."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[2]
TABLES = REPO / "results" / "confirmatory_1" / "tables"


def _markdown_table(header_start: str) -> list[list[str]]:
    lines = (REPO / "README.md").read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def test_the_gains_table_is_gains_csv():
    gains = pd.read_csv(TABLES / "gains.csv").set_index(["group", "method"])
    rows = _markdown_table("| table | method | vs | egobench ΔPSNR")
    assert len(rows) == len(gains)
    for table, method, ref, delta, seeds, paper, sign, p_holm, ratio, magnitude in rows:
        g = gains.loc[(table, method)]
        mean, low, high = (float(x) for x in re.findall(r"[+-]\d+\.\d+", delta))
        assert (mean, low, high) == pytest.approx(
            (g.delta_psnr_mean, g.delta_psnr_ci95_low, g.delta_psnr_ci95_high), abs=0.005), (table, method)
        assert ref == g.reference and int(seeds) == g.n_seeds
        assert float(paper) == pytest.approx(g.paper_delta_psnr_matched, abs=0.005)
        assert (sign == "yes") == bool(g.sign_and_ci) and (magnitude == "yes") == bool(g.magnitude_match)
        assert (p_holm == "<0.0001" and g.p_holm < 1e-4) or float(p_holm) == pytest.approx(g.p_holm, abs=5e-5)
        assert float(ratio) == pytest.approx(g.ratio_to_paper, abs=0.005)


def test_the_counts_sentence_is_the_counts_of_gains_csv():
    from egobench.report.gains import reproduction_counts

    c = reproduction_counts(pd.read_csv(TABLES / "gains.csv"))
    text = " ".join((REPO / "README.md").read_text().split())
    assert (f"of {c['rows']} rows, {c['sign_and_ci']} have the paper's sign with the interval excluding zero, "
            f"{c['survives_holm']} survive Holm, {c['magnitude_match']} match in magnitude") in text


def test_the_held_out_psnr_table_is_results_csv():
    results = pd.read_csv(TABLES / "results.csv")
    stats = results.groupby(["method", "scene"])["psnr"].agg(["mean", "std"])
    rows = _markdown_table("| method | outdoor_0 | indoor_0 | object_0 | quest3_0 |")
    scenes = ["outdoor_0", "indoor_0", "object_0", "quest3_0"]
    checked = 0
    for method, *cells in rows:
        for scene, cell in zip(scenes, cells):
            if cell == "–" or "±" not in cell:
                continue
            mean, sd = (float(x) for x in cell.split("±"))
            assert (mean, sd) == pytest.approx(tuple(stats.loc[(method, scene)]), abs=0.005), (method, scene)
            checked += 1
    assert checked >= 20


def test_the_readme_is_a_front_page():
    """At most ~150 lines: the two commands, what the run produces, the headline results, links."""
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    for link in ("docs/results.md", "docs/gpu-and-cluster.md", "docs/real-recordings.md", "docs/metrics.md"):
        assert link in text and (REPO / link).is_file(), link


def test_the_committed_run_is_the_protocols_confirmatory_run():
    """Every run of the committed suite was trained at one commit that contains docs/protocol.md (the
    protocol was fixed before the run), on the protocol's seeds and recordings, and nothing else."""
    import subprocess

    results = pd.read_csv(TABLES / "results.csv")
    assert results.git_commit.nunique() == 1
    commit = results.git_commit.iloc[0]
    git = ["git", "-C", str(REPO)]
    if subprocess.run(git + ["cat-file", "-e", f"{commit}^{{commit}}"], capture_output=True).returncode != 0:
        pytest.skip(f"commit {commit} is not in this clone's history (a shallow clone)")
    protocol_commit = subprocess.run(git + ["log", "--diff-filter=A", "--format=%H", "--", "docs/protocol.md"],
                                     capture_output=True, text=True, check=True).stdout.split()[-1]
    assert subprocess.run(git + ["merge-base", "--is-ancestor", protocol_commit, commit]).returncode == 0
    protocol = (REPO / "docs" / "protocol.md").read_text()
    seeds = sorted(int(s) for s in re.search(r"Training seeds: ([\d, ]+)", protocol).group(1).replace(",", " ").split())
    per_pair = results.groupby(["scene", "method"]).seed.apply(lambda s: sorted(s.astype(int)))
    assert all(v == seeds for v in per_pair), per_pair
    assert len(per_pair) == 22


def test_the_sensitivity_predictions_in_the_readme_are_prediction_csv():
    pred = pd.read_csv(REPO / "results" / "default" / "sensitivity" / "prediction.csv")
    text = " ".join((REPO / "README.md").read_text().split())
    shown = 0
    for r in pred.itertuples():
        if pd.notna(r.predicted_delta_psnr):
            assert f"{r.predicted_delta_psnr:.2f} [{r.predicted_ci95_low:.2f}, {r.predicted_ci95_high:.2f}]" in text, r.ablation
            shown += 1
    assert shown == 2
