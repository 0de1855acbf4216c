"""Sensitivity curves (`egobench sensitivity`, `snakemake sensitivity`): fit, paired intervals, outputs, dry run."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from egobench.analysis import sensitivity as sens
from egobench.workflow import sensitivity as sw
from egobench.workflow import config as wc
from egobench.cli import main
from egobench.report.gains import ci95
from egobench.report.records import load_records

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------------
# Fixtures: run records and similarity files of a small synthetic sweep


def write_record(root: Path, scene: str, method: str, seed: int, psnr: float) -> Path:
    path = root / "runs" / scene / method / f"seed{seed}" / "eval.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"schema": "egobench.run/1", "scene": scene, "scene_kind": "outdoor", "method": method,
                                "seed": seed, "metrics": {"psnr": psnr}}))
    return path


def synthetic_sweep(root: Path, x0=2.0, p=1.5, xs=(0.5, 1.0, 2.0, 4.0), seeds=(0, 1, 2), noise=0.05):
    """A sweep of no_viba whose true Δ(x) is `delta_model(x, x0, p)`; 'ours' varies by ±1.5 dB over
    seeds (shared by the paired ablation run), the pair's own noise is `noise` dB."""
    rng = np.random.default_rng(7)
    sims, truth = [], {}
    for i, x in enumerate(xs):
        scene = f"sens-no_viba-x{i}"
        d_true = float(sens.delta_model(np.array([x]), x0, p)[0])
        for s in seeds:
            ours = 30.0 + 1.5 * math.sin(3.0 * s + i)
            d = d_true + float(rng.normal(0.0, noise))
            truth[(scene, s)] = d
            write_record(root, scene, "ours", s, ours)
            write_record(root, scene, "no_viba", s, ours + d)
        sim = root / "similarity" / f"{scene}.json"
        sim.parent.mkdir(parents=True, exist_ok=True)
        sim.write_text(json.dumps({"calib_error_px_median": x, "rs_shift_px_median": 0.1}))
        sims.append(sim)
    return sims, truth


SWEEP = sens.Sweep("no_viba", "outdoor", "calib_error_px_median", 4.2, "test", "bike shop")


# ------------------------------------------------------------------------------------------------
# The model and its fit


def test_fit_recovers_a_known_curve():
    x = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0])
    x0, p = sens.fit_curve(x, sens.delta_model(x, 3.0, 1.3))
    assert x0 == pytest.approx(3.0, rel=1e-5) and p == pytest.approx(1.3, rel=1e-5)
    # the model: Δ(x0) = -10 log10(2), Δ(0) = 0, large x linear in log x with slope -10 p per decade
    assert sens.delta_model(np.array([3.0]), 3.0, 1.3)[0] == pytest.approx(-10 * math.log10(2))
    assert sens.delta_model(np.array([0.0]), 3.0, 1.3)[0] == 0.0
    big = sens.delta_model(np.array([3e3, 3e4]), 3.0, 1.3)
    assert big[1] - big[0] == pytest.approx(-13.0, abs=1e-3)


def test_prediction_interval_covers_the_truth_and_shrinks_with_seed_noise():
    xs = [0.5, 1.0, 2.0, 4.0]
    rng = np.random.default_rng(3)
    truth = float(sens.delta_model(np.array([6.0]), 2.0, 1.5)[0])
    widths = []
    for noise in (0.3, 0.03):
        points = [(x, sens.delta_model(np.array([x]), 2.0, 1.5)[0] + rng.normal(0, noise, 3)) for x in xs]
        out = sens.predict(points, 6.0, n_boot=300, seed=0)
        assert out["predicted_ci95_low"] <= truth <= out["predicted_ci95_high"]
        assert out["predicted_ci95_low"] <= out["predicted_delta_psnr"] <= out["predicted_ci95_high"]
        widths.append(out["predicted_ci95_high"] - out["predicted_ci95_low"])
        assert sens.predict(points, 6.0, n_boot=300, seed=0) == out  # seeded: deterministic
    assert widths[1] < widths[0] / 4


def test_seed_free_points_give_a_zero_width_interval():
    xs = [0.5, 1.0, 2.0, 4.0]
    points = [(x, np.repeat(sens.delta_model(np.array([x]), 2.0, 1.5)[0], 3)) for x in xs]
    out = sens.predict(points, 3.0, n_boot=50)
    assert out["predicted_ci95_high"] - out["predicted_ci95_low"] == pytest.approx(0.0, abs=1e-6)
    assert out["predicted_delta_psnr"] == pytest.approx(sens.delta_model(np.array([3.0]), 2.0, 1.5)[0], abs=1e-6)


# ------------------------------------------------------------------------------------------------
# Paired deltas and their intervals


def test_curve_points_are_paired_by_seed_with_tables_ci95(tmp_path):
    sims, truth = synthetic_sweep(tmp_path)
    write_record(tmp_path, "sens-no_viba-x0", "ours", 9, 10.0)  # an unpaired 'ours' run is ignored
    records = load_records([tmp_path / "runs"])
    curve = sens.curve_frame(records, sens.load_similarity(sims), [SWEEP])
    assert list(curve["x_value"]) == [0.5, 1.0, 2.0, 4.0]
    for _, row in curve.iterrows():
        deltas = [truth[(row["scene"], s)] for s in (0, 1, 2)]
        low, high = ci95(deltas)
        assert row["n_seeds"] == 3
        assert row["delta_psnr_mean"] == pytest.approx(np.mean(deltas), abs=1e-9)
        assert (row["delta_psnr_ci95_low"], row["delta_psnr_ci95_high"]) == pytest.approx((low, high), abs=1e-9)
        # pairing removes the ±1.5 dB seed-to-seed spread of 'ours'
        assert row["delta_psnr_ci95_high"] - row["delta_psnr_ci95_low"] < 0.8
        assert row["identical"] == ""


def test_an_ablation_run_without_its_ours_pair_is_an_error(tmp_path):
    write_record(tmp_path, "s", "no_viba", 0, 20.0)
    write_record(tmp_path, "s", "ours", 1, 21.0)
    with pytest.raises(ValueError, match=r"no 'ours' run of scene 's', seed 0"):
        sens.paired_deltas(load_records([tmp_path]), "no_viba")


# ------------------------------------------------------------------------------------------------
# Similarity files


def test_similarity_schema_flat_and_paper_block(tmp_path):
    flat = tmp_path / "a.json"
    flat.write_text(json.dumps({"rs_shift_px_median": 0.4}))
    full = tmp_path / "b.json"
    full.write_text(json.dumps({"schema": "egobench.similarity/1", "recordings": [{"rs_shift_px_median": 1.5}],
                                "paper": {"rs_shift_px_median": {"value": 13.4, "source": "issue 13"}}}))
    sims = sens.load_similarity([flat, full])
    assert sens.x_value(sims, "a", "rs_shift_px_median") == 0.4
    assert sens.x_value(sims, "b", "rs_shift_px_median") == 1.5
    sweep = sens.Sweep("no_motion_sampling", "outdoor", "rs_shift_px_median")
    filled = sens.with_paper_x(sweep, sims, ["a", "b"])
    assert filled.paper_x == 13.4 and "issue 13" in filled.paper_x_source
    with pytest.raises(ValueError, match=r"a\.json: field 'calib_error_px_median' is None"):
        sens.x_value(sims, "a", "calib_error_px_median")
    two = tmp_path / "c.json"
    two.write_text(json.dumps({"recordings": [{}, {}]}))
    with pytest.raises(ValueError, match=r"c\.json: field 'recordings' must list exactly one"):
        sens.load_similarity([two])
    with pytest.raises(FileNotFoundError, match="no z.json"):
        sens.x_value(sims, "z", "rs_shift_px_median")


# ------------------------------------------------------------------------------------------------
# Outputs, read back


def test_outputs_read_back(tmp_path):
    sims, truth = synthetic_sweep(tmp_path, x0=2.0, p=1.5, noise=0.02)
    out = tmp_path / "out"
    rc = main(["sensitivity", "--records", str(tmp_path / "runs"), "--similarity", *map(str, sims),
               "--sweep", json.dumps({"ablation": "no_viba", "kind": "outdoor", "x": "calib_error_px_median",
                                      "paper_x": 6.0, "paper_x_source": "test point", "paper_scene": "bike shop"}),
               "--out-dir", str(out), "--bootstrap", "200"])
    assert rc == 0
    curve = pd.read_csv(out / "sensitivity.csv")
    assert list(curve.columns) == sens.CURVE_COLUMNS
    assert curve["delta_psnr_mean"].tolist() == pytest.approx(
        [np.mean([truth[(f"sens-no_viba-x{i}", s)] for s in (0, 1, 2)]) for i in range(4)], abs=1e-9)
    pred = pd.read_csv(out / "prediction.csv").iloc[0]
    assert pred["paper_delta_psnr"] == pytest.approx(27.68 - 29.98)  # Table 1, bike shop
    assert pred["paper_x"] == 6.0 and pred["paper_x_source"] == "test point"
    assert bool(pred["extrapolation"]) and "extrapolation" in pred["note"]  # 6 > the measured 4
    assert (pred["x_min"], pred["x_max"]) == (0.5, 4.0)
    assert pred["fit_x0"] == pytest.approx(2.0, rel=0.1) and pred["fit_p"] == pytest.approx(1.5, rel=0.1)
    assert pred["predicted_delta_psnr"] == pytest.approx(
        float(sens.delta_model(np.array([6.0]), pred["fit_x0"], pred["fit_p"])[0]), abs=1e-6)
    truth6 = float(sens.delta_model(np.array([6.0]), 2.0, 1.5)[0])
    assert pred["predicted_ci95_low"] <= truth6 <= pred["predicted_ci95_high"]
    import matplotlib.image

    png = matplotlib.image.imread(out / "sensitivity.png")
    assert png.shape[0] > 100 and png[..., :3].std() > 0.05  # a drawn figure, not a blank canvas


def test_figure_marks_the_operating_point_and_the_prediction(tmp_path):
    sims, _ = synthetic_sweep(tmp_path)
    records = load_records([tmp_path / "runs"])
    similarity = sens.load_similarity(sims)
    sweep = sens.Sweep("no_viba", "outdoor", "calib_error_px_median", 3.0, "test", None)
    curve = sens.curve_frame(records, similarity, [sweep])
    pred = sens.prediction_frame(records, curve, [sweep], similarity, n_boot=100)
    assert not bool(pred.iloc[0]["extrapolation"])  # 3.0 lies inside 0.5..4
    assert "mean of 6 scenes" in pred.iloc[0]["paper_delta_source"]
    fig = sens.sensitivity_figure(curve, pred)
    ax = fig.axes[0]
    vlines = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
    assert len(vlines) == 1 and list(vlines[0].get_xdata()) == [3.0, 3.0]
    xy = {(round(float(x), 6), round(float(y), 6)) for ln in ax.lines for x, y in zip(ln.get_xdata(), ln.get_ydata())}
    assert (3.0, round(float(pred.iloc[0]["predicted_delta_psnr"]), 6)) in xy
    means = curve["delta_psnr_mean"].round(6).tolist()
    assert all((x, m) in xy for x, m in zip(curve["x_value"], means))


def test_one_measured_x_is_not_fitted(tmp_path):
    sims, _ = synthetic_sweep(tmp_path, xs=(1.0, 1.0))
    records = load_records([tmp_path / "runs"])
    similarity = sens.load_similarity(sims)
    curve = sens.curve_frame(records, similarity, [SWEEP])
    pred = sens.prediction_frame(records, curve, [SWEEP], similarity, n_boot=50).iloc[0]
    assert pred["predicted_delta_psnr"] is None and "1 distinct measured x" in pred["note"]


def test_an_ablation_that_gains_gets_no_prediction(tmp_path):
    """A curve that rises above zero with confidence is no loss curve: the fit (Δ <= 0) would predict
    ~0 with a zero-width interval, so no prediction is given and the note names the point."""
    sims, _ = synthetic_sweep(tmp_path, xs=(0.5, 1.0, 2.0, 4.0))
    gain = tmp_path / "runs" / "sens-no_viba-x3" / "no_viba"
    for seed in (0, 1, 2):  # the largest x: the ablation 1.5 dB better than 'ours' on every seed
        ours = json.loads((tmp_path / "runs" / "sens-no_viba-x3" / "ours" / f"seed{seed}" / "eval.json").read_text())
        write_record(tmp_path, "sens-no_viba-x3", "no_viba", seed, ours["metrics"]["psnr"] + 1.5 + 0.01 * seed)
    records = load_records([tmp_path / "runs"])
    similarity = sens.load_similarity(sims)
    curve = sens.curve_frame(records, similarity, [SWEEP])
    pred = sens.prediction_frame(records, curve, [SWEEP], similarity, n_boot=50).iloc[0]
    assert gain.is_dir() and pred["predicted_delta_psnr"] is None and pred["predicted_ci95_low"] is None
    assert pred["note"].startswith("no prediction: the ablation gains with 95 % confidence at x = 4 (+1.51 [")
    fig = sens.sensitivity_figure(curve, sens.prediction_frame(records, curve, [SWEEP], similarity, n_boot=50))
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert not any(lb.startswith("fit") or lb.startswith("predicted") for lb in labels)
    assert any(t.get_text() == "no prediction: the ablation gains" for t in fig.axes[0].texts)
    # the same sweep without the gain is predicted
    sims, _ = synthetic_sweep(tmp_path / "b", xs=(0.5, 1.0, 2.0, 4.0))
    records = load_records([tmp_path / "b" / "runs"])
    curve = sens.curve_frame(records, sens.load_similarity(sims), [SWEEP])
    assert sens.prediction_frame(records, curve, [SWEEP], sens.load_similarity(sims), n_boot=50).iloc[0][
        "predicted_delta_psnr"] < 0


def test_bad_sweep_argument_is_one_line_error(tmp_path, capsys):
    rc = main(["sensitivity", "--records", str(tmp_path), "--similarity", "x.json", "--sweep",
               '{"ablation": "no_viba", "kind": "underwater", "x": "k"}', "--out-dir", str(tmp_path)])
    assert rc == 2 and "field 'kind' is 'underwater'" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Workflow: config -> sweep recordings, and the dry run


def sens_config() -> dict:
    config = yaml.safe_load((REPO / "config" / "ci.yaml").read_text())
    config["sensitivity"] = {"seeds": [0, 1], "iterations": 20, "ablations": {
        "no_motion_sampling": {"kind": "outdoor", "sim": {"motion": "fast"},
                               "sweep": {"field": "readout_s", "values": [0.004, 0.016]}},
        "no_viba": {"kind": "outdoor", "paper_x": {"value": 4.2, "source": "s"},
                    "sweep": {"fields": {"factory_rotation_deg": 0.2, "factory_principal_px": 0.75}, "scale": [1, 4]}},
    }}
    return config


def test_sweep_recordings_and_their_overrides():
    config = sens_config()
    points = sw.sweep_points(config)
    assert [p.scene for p in points] == ["sens-no_motion_sampling-0.004", "sens-no_motion_sampling-0.016",
                                        "sens-no_viba-x1", "sens-no_viba-x4"]
    assert points[1].sim == {"rectified_size": 48, "n_frames": 32, "motion": "fast", "readout_s": 0.016}
    assert points[3].sim["factory_rotation_deg"] == pytest.approx(0.8)
    assert points[3].sim["factory_principal_px"] == pytest.approx(3.0)
    wc.check_config(config)
    suite = wc.Suite(wc.fill_defaults(config))
    assert len(suite.runs()) == 2  # the suite's own runs are untouched
    assert len(suite.sensitivity_records()) == 4 * 2 * 2
    assert "--set readout_s=0.016" in suite.simulate_args("sens-no_motion_sampling-0.016")
    assert suite.train_args("sens-no_viba-x4") == "--preset cpu --iterations 20"
    args = suite.sensitivity_args()
    assert '"paper_x": 4.2' in args and '"x": "calib_inconsistency_px_median"' in args and '"paper_x": null' in args


@pytest.mark.parametrize("edit, key", [
    (lambda c: c["sensitivity"]["ablations"].update(instant_ngp={"kind": "outdoor",
                                                                 "sweep": {"field": "a", "values": [1, 2]}}),
     "config.sensitivity.ablations"),
    (lambda c: c["sensitivity"]["ablations"]["no_viba"]["sweep"].update(field="seed"),
     "config.sensitivity.ablations.no_viba.sweep"),
    (lambda c: c["sensitivity"]["ablations"]["no_motion_sampling"]["sweep"].update(field="seed"),
     "config.sensitivity.ablations.no_motion_sampling.sweep: 'seed'"),
])
def test_bad_sensitivity_config_names_the_key(edit, key):
    config = sens_config()
    edit(config)
    with pytest.raises(wc.ConfigError, match=key.replace(".", r"\.").replace("[", r"\[")):
        wc.check_config(config)


def snakemake(args: list[str], workdir: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir), *args],
                          capture_output=True, text=True, timeout=300, env=env)


def job_counts(output: str) -> dict[str, int]:
    """rule -> job count from the (last) "Job stats:" table of a dry run."""
    block = output.rsplit("Job stats:", 1)[1].split("Reasons:", 1)[0]
    rows = [line.split() for line in block.splitlines()]
    return {r[0]: int(r[1]) for r in rows if len(r) == 2 and r[1].isdigit()}


def test_dry_run_lists_the_sweep_jobs(tmp_path):
    path = tmp_path / "sens.yaml"
    path.write_text(yaml.safe_dump(sens_config()))
    res = snakemake(["sensitivity", "-n", "--quiet", "rules", "--configfile", str(path)], tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert job_counts(res.stdout + res.stderr) == {
        "simulate": 4, "sensitivity_similarity": 4, "train": 16, "evaluate": 16, "sensitivity_curves": 1,
        "sensitivity": 1, "total": 42}
    # `all` does not include the sweep, and a sweep field the simulator lacks fails only the sensitivity target
    config = sens_config()
    config["sensitivity"]["ablations"]["no_viba"]["sweep"]["fields"]["not_a_sim_field"] = 1.0
    path.write_text(yaml.safe_dump(config))
    res = snakemake(["-n", "--quiet", "rules", "--configfile", str(path)], tmp_path)
    assert res.returncode == 0 and "sensitivity" not in job_counts(res.stdout + res.stderr), res.stdout + res.stderr
    res = snakemake(["sensitivity", "-n", "--configfile", str(path)], tmp_path)
    assert res.returncode != 0
    assert "config.sensitivity.ablations.no_viba (recording sens-no_viba-x1" in res.stderr + res.stdout
    assert "unknown field 'not_a_sim_field'" in res.stderr + res.stdout
    assert not (tmp_path / "results").exists()


def test_misregistration_exponent_of_a_sinusoid():
    """A sinusoid of f cycles/px shifted by δ: mean square difference 1 − cos(2π f δ) (its amplitude 1),
    so the local exponent → 2 for small shifts and falls as the shift nears half a period."""
    f = 4 / 64
    image = np.tile(np.sin(2 * np.pi * f * np.arange(64)), (40, 1))
    shifts = [0.01, 0.02, 1.0, 2.0, 8.0]
    mse, p = sens.misregistration_exponents(image, shifts)
    assert mse == pytest.approx([1 - math.cos(2 * math.pi * f * d) for d in shifts], rel=1e-9)
    assert p[0] == pytest.approx(2.0, abs=1e-3) and p[-1] < 1.5
    assert sens.p_bounds("rs_shift_px_median") == (0.5, 2.0) and sens.p_bounds("scene_dynamic_range_stops") == (0.5, 4.0)


def test_schema_ablation_names_are_methods():
    from egobench.model.methods import METHODS

    schema = wc.load_schema()["properties"]["sensitivity"]["properties"]["ablations"]
    assert set(schema["propertyNames"]["enum"]) == set(METHODS) - {"ours"}
    assert set(sw.DEFAULT_X) <= set(schema["propertyNames"]["enum"])
    x_enum = schema["additionalProperties"]["properties"]["x"]["enum"]
    assert set(sw.DEFAULT_X.values()) <= set(x_enum) and set(sens.PIXEL_QUANTITIES) <= set(x_enum)


def test_scaled_sweep_values_carry_no_float_noise():
    config = {"sensitivity": {"ablations": {"no_viba": {
        "kind": "outdoor", "sweep": {"fields": {"factory_rotation_deg": 0.2, "factory_principal_px": 0.1},
                                     "scale": [3, 7]}}}}}
    points = sw.sweep_points(config)
    assert 0.2 * 7 != 1.4 and points[1].sim["factory_rotation_deg"] == 1.4  # as the simulate args print it
    assert points[0].sim["factory_principal_px"] == 0.3 and 0.1 * 3 != 0.3
