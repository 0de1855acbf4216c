"""The Snakemake workflow: lint, dry runs, config validation, and a real smoke run of ci.yaml."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from egobench.io_utils import read_json
from egobench.workflow import config as wc
from tests import background

REPO = Path(__file__).resolve().parents[2]
SNAKEMAKE = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile")]


def snakemake(args: list[str], workdir: Path, timeout: int = 300, python_options: tuple[str, ...] = ()
              ) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    command = [SNAKEMAKE[0], *python_options, *SNAKEMAKE[1:]]
    return subprocess.run([*command, "-d", str(workdir), *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def load(name: str) -> dict:
    return yaml.safe_load((REPO / "config" / name).read_text())


# ------------------------------------------------------------------------------------------------
# Config -> jobs (unit level)


def test_schema_enums_match_the_package():
    from egobench.model.methods import METHODS
    from egobench.sim.config import SCENE_KINDS

    schema = wc.load_schema()
    assert schema["$defs"]["method"]["enum"] == list(METHODS)
    assert schema["properties"]["scenes"]["items"]["properties"]["kind"]["enum"] == list(SCENE_KINDS)


@pytest.mark.parametrize("name", ["config.yaml", "confirmatory_1.yaml", "paper.yaml", "ci.yaml", "paper_smoke.yaml"])
def test_shipped_configs_are_valid(name):
    suite = wc.load_suite(REPO / "config" / name)
    assert suite.runs() and len(set(suite.runs())) == len(suite.runs())


T1_METHODS = {"splatfacto", "on_the_move", "ours", "no_viba", "no_motion_sampling", "no_scene_gamma"}
T2_METHODS = {"ours", "no_motion_sampling", "no_viba", "no_scene_gamma", "splatfacto", "ours_2dgs",
              "2dgs_no_motion_sampling"}
T3_METHODS = {"ours", "no_viba", "no_motion_sampling"}


def _methods_by_kind(suite) -> dict[str, set[str]]:
    by_kind: dict[str, set[str]] = {}
    for s in suite.scenes.values():
        by_kind.setdefault(s.kind, set()).update(s.methods)
    return by_kind


def test_default_suite_is_protocol_2():
    """docs/protocol-2.md's design: 6 + 6 + 3 + 2 worlds, every Table 1 row on every Table 1 scene, the paper's
    scene each stands for, one fresh training seed per scene and a second on the first outdoor and indoor one."""
    suite = wc.load_suite(REPO / "config" / "config.yaml")
    assert _methods_by_kind(suite) == {"outdoor": T1_METHODS, "indoor": T1_METHODS, "object": T2_METHODS,
                                       "quest3": T3_METHODS}
    kinds = [s.kind for s in suite.scenes.values()]
    assert (kinds.count("outdoor"), kinds.count("indoor"), kinds.count("object"), kinds.count("quest3")) == (6, 6, 3, 2)
    from egobench.report import paper_numbers as pn

    assert [s.paper_scene for s in suite.scenes.values() if s.kind == "outdoor"] == list(pn.TABLE1_OUTDOOR_SCENES)
    assert [s.paper_scene for s in suite.scenes.values() if s.kind == "indoor"] == list(pn.TABLE1_INDOOR_SCENES)
    assert all(set(s.methods) == set(suite.scenes[s.name].methods) for s in suite.scenes.values())
    for s in suite.scenes.values():
        expected = {1732, 508} if s.name in ("outdoor_0", "indoor_0") else {1732}
        assert all(set(s.seeds_of(m)) == expected for m in s.methods), s.name
    sim_seeds = [s.sim_seed for s in suite.scenes.values()]
    assert len(set(sim_seeds)) == 17 and not set(sim_seeds) & {2718, 2818, 2845, 9045}  # fresh, none of run 1's
    assert len(suite.runs()) == 12 * 6 + 3 * 7 + 2 * 3 + 2 * 6


def test_confirmatory_1_config_is_run_1():
    """config/confirmatory_1.yaml keeps run 1's design (docs/protocol.md): the same five seeds for every row."""
    suite = wc.load_suite(REPO / "config" / "confirmatory_1.yaml")
    assert _methods_by_kind(suite) == {"outdoor": T1_METHODS, "indoor": T1_METHODS, "object": T2_METHODS,
                                       "quest3": T3_METHODS}
    confirmatory = {3141, 5926, 5358, 9793, 2384}
    assert len(suite.runs()) == (6 + 6 + 7 + 3) * 5
    seeds = {(s, m): {seed for s2, m2, seed in suite.runs() if (s2, m2) == (s, m)} for s, m, _ in suite.runs()}
    assert all(v == confirmatory for v in seeds.values())
    assert {s.name: s.sim_seed for s in suite.scenes.values()} == {
        "outdoor_0": 2718, "indoor_0": 2818, "object_0": 2845, "quest3_0": 9045}


def test_paper_suite_scale():
    suite = wc.load_suite(REPO / "config" / "paper.yaml")
    from egobench.report import paper_numbers as pn

    papers = {s.paper_scene for s in suite.scenes.values() if s.kind in ("outdoor", "indoor")}
    assert papers == set(pn.TABLE1_OUTDOOR_SCENES) | set(pn.TABLE1_INDOOR_SCENES)
    for s in suite.scenes.values():
        assert s.iterations == 30000 and s.sim["rectified_size"] == 2400 and s.preset == "paper"
        if s.paper_scene in pn.TABLE4:
            assert s.sim["n_frames"] == pn.TABLE4[s.paper_scene].frames
    assert suite.resources("train")["gpu"] == 1


def test_suite_paths_and_arguments():
    config = wc.fill_defaults({
        "suite": "t",
        "defaults": {"seeds": [0, 1], "iterations": 50, "sim": {"n_frames": 16, "noise": False}},
        "scenes": [{"name": "a", "kind": "indoor", "paper_scene": "plant hallway", "methods": ["ours", "no_viba"],
                    "sim": {"n_frames": 8, "white_balance": [1.0, 0.9, 1.1]}, "train": {"lr_colors": 0.5}},
                   {"name": "b", "kind": "object", "methods": ["ours_2dgs", "ours"], "seeds": [3], "iterations": 7,
                    "preset": "paper", "method_seeds": {"ours": [3, 4]}}],
    })
    wc.check_config(config)
    s = wc.Suite(config)
    assert s.runs() == [("a", "ours", 0), ("a", "ours", 1), ("a", "no_viba", 0), ("a", "no_viba", 1),
                        ("b", "ours_2dgs", 3), ("b", "ours", 3), ("b", "ours", 4)]
    assert s.eval_records()[-1] == "results/t/runs/b/ours/seed4/eval.json"
    assert s.recording_dir("a") == "results/t/recordings/a"
    assert s.simulate_args("a") == ("--kind indoor --seed 0 --set n_frames=8 --set name=a --set noise=false "
                                    "--set white_balance=1.0,0.9,1.1")
    assert s.train_args("a") == "--preset cpu --iterations 50 --set lr_colors=0.5"
    assert s.train_args("b") == "--preset paper --iterations 7"
    assert s.evaluate_args("a") == "--scene a --paper-scene 'plant hallway'"
    assert s.evaluate_args("b") == "--scene b"
    assert s.resources("train") == {"threads": 1, "mem_mb": 2000, "gpu": 0, "runtime": 60}
    with pytest.raises(wc.ConfigError, match="'c' is not in suite"):
        s.simulate_args("c")


def test_diagnose_and_motion_stats_jobs():
    suite = wc.load_suite(REPO / "config" / "ci.yaml")
    assert suite.diagnosis_dirs() == ["results/ci/diagnosis/outdoor_0/ours"]
    assert suite.diagnose_run("outdoor_0", "ours") == ["results/ci/runs/outdoor_0/ours/seed0/train.json"]
    assert suite.diagnose_args("outdoor_0", "ours") == "--source run --run results/ci/runs/outdoor_0/ours/seed0"
    assert suite.motion_stats and suite.motion_stats_args() == "--kind indoor"
    config = load("ci.yaml")
    config["diagnose"]["source"] = "ground_truth"
    config["motion_stats"]["real_trajectory"] = __file__  # any existing file
    wc.check_config(config)
    gt = wc.Suite(wc.fill_defaults(config))
    assert gt.diagnose_run("outdoor_0", "ours") == [] and gt.diagnose_args("outdoor_0", "ours") == "--source ground_truth"
    assert gt.motion_stats_args() == f"--kind indoor --real {__file__}"
    config = load("ci.yaml")
    config["diagnose"]["lens_check"] = True  # a trained run's lens tested where the run keeps one
    wc.check_config(config)
    lens = wc.Suite(wc.fill_defaults(config))
    assert lens.diagnose_args("outdoor_0", "ours") == "--source run --run results/ci/runs/outdoor_0/ours/seed0 --lens-check"
    config["diagnose"]["lens_check"] = "yes"
    with pytest.raises(wc.ConfigError, match="lens_check"):
        wc.check_config(config)
    # the paper suite bounds the diagnosis's in-memory frames
    paper = wc.load_suite(REPO / "config" / "paper.yaml")
    assert paper.diagnose_args("bike_shop", "ours").endswith(" --max-frames 64")


def test_discovery_targets(tmp_path):
    """`snakemake discovery`: the sweep always; the ADT diagnosis only with an existing adt_dir."""
    config = load("ci.yaml")
    assert wc.Suite(wc.fill_defaults(config)).discovery_outputs() == ["results/ci/discovery/sweep"]
    adt = tmp_path / "adt"
    config["diagnose"]["adt_dir"] = str(adt)
    with pytest.raises(wc.ConfigError, match="config.diagnose.adt_dir"):
        wc.check_config(config)
    adt.mkdir()
    (adt / "video.vrs").write_bytes(b"")
    wc.check_config(config)
    suite = wc.Suite(wc.fill_defaults(config))
    assert suite.discovery_outputs() == ["results/ci/discovery/sweep", "results/ci/discovery/adt"]
    assert suite.sweep_seeds == 3


def test_trained_sweep_is_a_discovery_target_only_when_enabled():
    """config.diagnose.trained_sweep: off by default; on, `snakemake discovery` also builds the
    trained-run sweep's table with the configured arguments; an unknown effect is a config error."""
    config = load("ci.yaml")
    assert "results/ci/discovery/trained_sweep/trained_sweep.json" not in wc.Suite(wc.fill_defaults(config)).discovery_outputs()
    config["diagnose"]["trained_sweep"] = {"enabled": True, "null_cases": 10, "effects": ["vignette", "response"],
                                           "size": 32, "iterations": 200}
    wc.check_config(config)
    suite = wc.Suite(wc.fill_defaults(config))
    assert suite.discovery_outputs() == ["results/ci/discovery/sweep", "results/ci/discovery/trained_sweep/trained_sweep.json"]
    assert suite.trained_sweep_args() == ("--sweep-null 10 --sweep-seeds 1 --sweep-kind indoor --sweep-size 32 "
                                          "--sweep-frames 24 --iterations 200 --sweep-effects vignette,response")
    config["diagnose"]["trained_sweep"]["effects"] = ["vignetting"]
    with pytest.raises(wc.ConfigError, match="trained_sweep"):
        wc.check_config(config)


def test_egobench_command():
    assert wc.egobench_command("egobench --verbose") == "egobench --verbose"
    auto = wc.egobench_command("auto")
    assert auto == "egobench" or auto.endswith("-m egobench.cli")


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: c["scenes"][0].update(kind="mars"), "config.scenes[0].kind: 'mars' is not allowed"),
        (lambda c: c["scenes"][1]["methods"].append("nerf"), "config.scenes[1].methods[6]: 'nerf' is not allowed"),
        (lambda c: c.update(bogus=1), "config.bogus: unknown key 'bogus'"),
        (lambda c: c["scenes"][0].update(frames=3), "config.scenes[0].frames: unknown key 'frames'"),
        (lambda c: c["resources"]["train"].update(gpus=1), "config.resources.train.gpus: unknown key"),
        (lambda c: c["scenes"][1].update(name="outdoor_0"), "scene names must be unique; repeated: outdoor_0"),
        (lambda c: c["diagnose"].update(scenes=["nowhere"]), "config.diagnose.scenes[0]: 'nowhere'"),
        (lambda c: c["scenes"][0]["sim"].update(kind="indoor"), "config.scenes[0].sim.kind: set by the workflow"),
        (lambda c: c["scenes"][0]["sim"].update(n_frame=3), "unknown field 'n_frame'"),
        (lambda c: c["scenes"][0]["sim"].update(n_frames=0), "n_frames"),
        (lambda c: c["scenes"][0].update(train={"lr_colour": 1}), "lr_colour: unknown TrainConfig field"),
        (lambda c: c["defaults"].update(preset="gpu"), "config.defaults.preset: 'gpu' is not allowed"),
        (lambda c: c.pop("suite"), "'suite' is a required property"),
        (lambda c: c["diagnose"].update(methods=["ours_2dgs"]), "'ours_2dgs' is not run on scene 'indoor_0'"),
        (lambda c: c["scenes"][0].update(method_seeds={"ours_2dgs": [0, 1]}),
         "config.scenes[0].method_seeds: 'ours_2dgs' is not among the scene's methods (splatfacto, "),
        (lambda c: c["scenes"][0].update(method_seeds={"ours": [-1]}), "config.scenes[0].method_seeds.ours[0]: -1"),
        (lambda c: c["scenes"][0].update(paper_scene="plant halway"),
         "config.scenes[0].paper_scene: 'plant halway' (scene 'outdoor_0') is not a scene of the paper's tables; "
         "expected one of 'bike shop', 'steakhouse patio'"),
        (lambda c: c["motion_stats"].update(real_trajectory="/nonexistent/traj.csv"),
         "config.motion_stats.real_trajectory: /nonexistent/traj.csv: file not found"),
    ],
)
def test_bad_configs_name_the_key(mutate, message):
    config = load("config.yaml")
    config["scenes"][0].setdefault("sim", {})
    mutate(config)
    with pytest.raises(wc.ConfigError) as exc:
        wc.check_config(config)
    assert message in str(exc.value)


# ------------------------------------------------------------------------------------------------
# Snakemake itself


def test_lint_is_clean(tmp_path):
    """`snakemake --lint` reports nothing (rules call egobench through a shell function, not a global)."""
    res = snakemake(["--lint"], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 0 and "Congratulations, your workflow is in a good condition" in out, out
    assert not [line for line in out.splitlines() if line.lstrip().startswith("* ")], out


def test_the_shell_function_runs_the_configured_command(tmp_path):
    """The rules' `egobench` is a bash function: with the installed script it must not call itself,
    with another prefix it runs that prefix with the arguments quoted as given."""
    import subprocess

    assert wc.egobench_shell_function("egobench") == 'egobench() { command egobench "$@"; };'
    fn = wc.egobench_shell_function(f"{sys.executable} -c 'import sys; print(sys.argv[1:])'")
    out = subprocess.run(["bash", "-c", f"{fn} egobench train --set 'a b'"], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "['train', '--set', 'a b']"


@pytest.mark.parametrize("name, min_jobs", [("config.yaml", 53), ("paper.yaml", 214), ("paper_smoke.yaml", 6)])
def test_dry_run(tmp_path, name, min_jobs):
    res = snakemake(["-n", "--quiet", "rules", "--configfile", str(REPO / "config" / name)], tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    total = [line for line in (res.stdout + res.stderr).splitlines() if line.startswith("total")]
    assert total and int(total[0].split()[1]) >= min_jobs, res.stdout
    assert not (tmp_path / "results").exists()


def test_parsing_the_workflow_loads_no_torch_scipy_or_matplotlib(tmp_path):
    """Every `snakemake` call parses the Snakefile; what it imports from egobench must stay light (torch,
    scipy and matplotlib took a dry run from ~1.3 to ~4 s, and the suite makes ~20 such calls). Checked
    with Python's import log of a dry run of the default suite and of the sensitivity sweep."""
    for target in ([], ["sensitivity"]):
        res = snakemake([*target, "-n", "--quiet", "rules"], tmp_path, python_options=("-X", "importtime"))
        assert res.returncode == 0, res.stdout + res.stderr[-3000:]
        loaded = {line.rsplit("|", 1)[-1].strip() for line in res.stderr.splitlines() if line.startswith("import time:")}
        assert "egobench.workflow.config" in loaded  # the log is read right
        assert {"torch", "scipy", "matplotlib"} & loaded == set(), target


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda c: c["scenes"][1].update(kind="underwater"), "config.scenes[1].kind"),
        (lambda c: c["scenes"][12]["methods"].append("instant_ngp"), "config.scenes[12].methods[7]"),
        (lambda c: c["defaults"].update(iteratons=5), "config.defaults.iteratons"),
    ],
)
def test_bad_config_fails_before_any_job(tmp_path, edit, key):
    config = load("config.yaml")
    edit(config)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    res = snakemake(["--cores", "1", "--configfile", str(path)], tmp_path)
    assert res.returncode != 0
    assert key in res.stderr + res.stdout, res.stderr
    assert not (tmp_path / "results").exists()  # nothing ran


# ------------------------------------------------------------------------------------------------
# A real run of the smoke suite (needs every verb the rules call).


def _ci_suite() -> tuple[subprocess.CompletedProcess, Path]:
    """The CI suite run into a fresh folder (in the background, `tests.background`) -> (result, folder).
    The compiled rasterizer's kernels are compiled (or loaded) here first, in the test process, so that
    on a cold numba cache the suite's jobs load them instead of each compiling them side by side."""
    import torch

    from tests.render.test_render import pose
    from tests.render.test_render_cpu import CAM, edge_case_scene, run

    run(edge_case_scene(3, torch.float32), CAM, pose(0.1, -0.05, (0.02, 0.0, 0.0)).to(torch.float32), "cpu")
    workdir = Path(tempfile.mkdtemp(prefix="egobench_ci_suite_"))
    return snakemake(["--cores", "2", "--configfile", str(REPO / "config" / "ci.yaml")], workdir, timeout=900), workdir


BACKGROUND = {"test_ci_suite_runs_end_to_end": _ci_suite}


@pytest.mark.slow
def test_ci_suite_runs_end_to_end():
    res, tmp_path = background.start(sys.modules[__name__], "test_ci_suite_runs_end_to_end").result(timeout=1200)
    try:
        _check_ci_suite(res, tmp_path)
    finally:
        shutil.rmtree(tmp_path, ignore_errors=True)


def _check_ci_suite(res: subprocess.CompletedProcess, tmp_path: Path) -> None:
    logs = "\n".join(p.read_text()[-2000:] for p in (tmp_path / "results").rglob("*.log")) if res.returncode else ""
    assert res.returncode == 0, res.stderr[-4000:] + logs
    root = tmp_path / "results" / "ci"
    suite = wc.load_suite(REPO / "config" / "ci.yaml")
    # Every run record exists; the tables parse and hold numbers.
    results = pd.read_csv(root / "tables" / "results.csv")
    assert len(results) == len(suite.runs())
    assert np.isfinite(results["psnr"]).all()
    # Each table row is the mean PSNR of the run's saved held-out renders against the recording's
    # frames (recomputed here), and beats rendering nothing (the black background) by 3 dB.
    import cv2
    import torch

    from egobench.data import load_recording
    from egobench.metrics import psnr

    for _, row in results.iterrows():
        rec = load_recording(root / "recordings" / row["scene"], row["calibration"])
        renders = root / "runs" / row["scene"] / row["method"] / f"seed{row['seed']}" / "renders"
        scores, black = [], []
        for f in (f for f in rec.frames if f.index % 8 == 0):
            gt = rec.load_image(f)
            img = cv2.cvtColor(cv2.imread(str(renders / f"{f.index:05d}.png")), cv2.COLOR_BGR2RGB)
            scores.append(psnr(torch.from_numpy(img).float() / 255.0, gt, rec.mask))
            black.append(psnr(torch.zeros_like(gt), gt, rec.mask))
        assert row["psnr"] == pytest.approx(np.mean(scores), abs=1e-9), row["method"]
        assert row["psnr"] > np.mean(black) + 3.0, (row["method"], row["psnr"], np.mean(black))
    t1 = pd.read_csv(root / "tables" / "table1_outdoor.csv")
    ours = t1[t1["block"] == "egobench"]
    psnr_cols = [c for c in t1.columns if c.endswith(" PSNR")]
    assert len(ours) == 2 and psnr_cols and np.isfinite(ours[psnr_cols].to_numpy(float)).all()
    gains = pd.read_csv(root / "tables" / "gains.csv")
    row = gains[(gains["group"] == "table1_outdoor") & (gains["method"] == "no_motion_sampling")]
    ours_eval = read_json(root / "runs" / "outdoor_0" / "ours" / "seed0" / "eval.json")
    if all(e["pose_samples"] == 1 for e in ours_eval["per_image"]):  # motion sampling never switched on
        assert len(row) == 1 and row["identical"].iloc[0].startswith("identical by construction")
        assert pd.isna(row["delta_psnr_mean"].iloc[0])
    else:
        assert len(row) == 1 and np.isfinite(row["delta_psnr_mean"].iloc[0])
    assert all((root / "figures" / f).is_file() for f in importlib.import_module("egobench.report.plots").OUTPUT_FILES)
    assert (root / "diagnosis" / "outdoor_0" / "ours" / "diagnosis.json").is_file()
    assert (root / "motion_stats" / "motion_stats.json").is_file()
    # The viewer outputs: the PLY holds every Gaussian of the run; the video one frame per recording
    # frame (32 < max_frames 48), three panels (ours | w/o motion sampling | captured), each 48 px
    # enlarged 6x under a 20 px label bar.
    from egobench.export.ply import read_ply
    from egobench.train.checkpoint import read_run_checkpoint

    g, mode = read_ply(root / "viewer" / "outdoor_0" / "ours.ply")
    ck = read_run_checkpoint(root / "runs" / "outdoor_0" / "ours" / "seed0" / "checkpoint.pt")
    assert mode == "3dgs" and len(g) == len(ck["params"]["means"])
    video = cv2.VideoCapture(str(root / "viewer" / "outdoor_0" / "flythrough.mp4"))
    size = (int(video.get(cv2.CAP_PROP_FRAME_WIDTH)), int(video.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 32 and size == (3 * 48 * 6, 20 + 48 * 6)
    # The viewer page: one file with every frame of the recording and both runs' Gaussians.
    page = (root / "viewer" / "outdoor_0" / "view" / "index.html").read_text()
    data = json.loads(page.split('<script id="egobench-data" type="application/json">', 1)[1].split("</script>", 1)[0])
    assert len(data["frames"]) == 32 and [r["method"] for r in data["runs"]] == ["ours", "no_motion_sampling"]
    assert data["runs"][0]["n"] == len(ck["params"]["means"])
    # The similarity table measures the suite's recording at its own resolution.
    sim = read_json(root / "similarity" / "similarity.json")["recordings"]
    sim_csv = pd.read_csv(root / "similarity" / "similarity.csv")
    assert [r["name"] for r in sim] == ["outdoor_0"] and sim[0]["rectified_size_px"] == 48
    assert sim[0]["calib_error_px_median"] > 0
    assert sim_csv["calib_error_px_median"].iloc[0] == pytest.approx(sim[0]["calib_error_px_median"])
    # Rerunning resumes: nothing left to do.
    again = snakemake(["--cores", "2", "--configfile", str(REPO / "config" / "ci.yaml"), "-n"], tmp_path)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr
    # ... also when egobench is called another way (an activated venv's script vs python -m): the
    # command prefix is not provenance, so it must not make Snakemake redo simulations and training
    other = snakemake(["--cores", "2", "--configfile", str(REPO / "config" / "ci.yaml"), "-n",
                       "--config", f"egobench_command=env {sys.executable} -m egobench.cli"], tmp_path)
    assert other.returncode == 0 and "Nothing to be done" in other.stdout + other.stderr, other.stdout[-3000:]
    # The HTML report builds from the finished run.
    rep = snakemake(["--configfile", str(REPO / "config" / "ci.yaml"), "--report", str(tmp_path / "report.html")],
                    tmp_path)
    assert rep.returncode == 0, rep.stderr[-3000:]
    assert (tmp_path / "report.html").stat().st_size > 10_000
    assert "flythrough.mp4" in (tmp_path / "report.html").read_text(errors="replace")
    assert "index.html" in (tmp_path / "report.html").read_text(errors="replace")


# ------------------------------------------------------------------------------------------------
# Real scenes: preprocess before training


def _aria_config(tmp_path, **scene_extra):
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "rec.vrs").write_bytes(b"")
    (tmp_path / "mps" / "slam").mkdir(parents=True)
    config = load("ci.yaml")
    config["scenes"].append({"name": "my_room", "source": "aria", "vrs": str(tmp_path / "rec.vrs"),
                             "mps": str(tmp_path / "mps" / "slam"), "focal": 100, "size": 200,
                             "methods": ["ours", "no_viba"], **scene_extra})
    return config


def test_aria_scene_is_preprocessed(tmp_path):
    config = _aria_config(tmp_path, vignette="v.png")
    wc.check_config(config)
    suite = wc.Suite(wc.fill_defaults(config))
    assert suite.aria_scenes() == ["my_room"] and suite.simulated_scenes() == ["outdoor_0"]
    assert suite.aria_input("my_room", "vrs") == str(tmp_path / "rec.vrs")
    assert suite.preprocess_args("my_room") == "--focal 100 --size 200 --vignette v.png"
    assert suite.needs_factory_stream("my_room") and not suite.needs_factory_stream("outdoor_0")  # no_viba: factory
    assert suite.recording_dir("my_room") == "results/ci/recordings/my_room"
    assert suite.evaluate_args("my_room") == "--scene my_room"  # no kind given
    assert wc.Suite(wc.fill_defaults(_aria_config(tmp_path / "k", kind="indoor"))).evaluate_args("my_room") == \
        "--scene my_room --scene-kind indoor"
    import re

    assert re.fullmatch(suite.scene_regex(suite.aria_scenes()), "my_room")
    assert not re.fullmatch(suite.scene_regex(suite.aria_scenes()), "outdoor_0")
    assert not re.fullmatch(suite.scene_regex([]), "")


def test_aria_scene_inputs_are_checked(tmp_path):
    config = _aria_config(tmp_path)
    config["scenes"][-1]["vrs"] = str(tmp_path / "missing.vrs")
    with pytest.raises(wc.ConfigError, match=r"config\.scenes\[1\]\.vrs \(scene 'my_room'\): .*missing\.vrs: file not found"):
        wc.check_config(config)
    config = _aria_config(tmp_path / "b")
    del config["scenes"][-1]["mps"]
    with pytest.raises(wc.ConfigError, match=r"config\.scenes\[1\]: 'mps' is a required property"):
        wc.check_config(config)


def test_paper_suite_points_at_the_released_scenes_by_name(tmp_path):
    from egobench.report import paper_numbers as pn

    config = load("paper.yaml")
    names = [s["aria_scene"] for s in config["scenes"] if "aria_scene" in s]
    assert len(names) == 12 and "livingroom" in names
    assert wc.Suite(wc.fill_defaults(load("paper.yaml"))).aria_scenes() == []  # aria_root null: simulated
    for n in names:
        (tmp_path / n / "mps" / "slam").mkdir(parents=True)
        (tmp_path / n / "recording.vrs").write_bytes(b"")
    config["aria_root"] = str(tmp_path)
    wc.check_config(config)
    suite = wc.Suite(wc.fill_defaults(config))
    real = suite.aria_scenes()
    assert {suite.scenes[s].paper_scene for s in real} == set(pn.TABLE1_OUTDOOR_SCENES) | set(pn.TABLE1_INDOOR_SCENES)
    assert suite.aria_input("livingroom", "vrs") == f"{tmp_path}/livingroom/recording.vrs"
    assert suite.aria_input("livingroom", "mps") == f"{tmp_path}/livingroom/mps/slam"
    assert suite.preprocess_args("livingroom") == "--focal 1200 --size 2400"


def test_dry_run_preprocesses_a_real_scene(tmp_path):
    path = tmp_path / "aria.yaml"
    path.write_text(yaml.safe_dump(_aria_config(tmp_path)))
    res = snakemake(["-n", "--quiet", "rules", "--configfile", str(path)], tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    counts = {line.split()[0]: int(line.split()[1]) for line in out.splitlines()
              if len(line.split()) == 2 and line.split()[1].isdigit()}
    assert counts.get("preprocess") == 1 and counts.get("simulate") == 1, out


def _real_aria_scene() -> tuple[subprocess.CompletedProcess, Path] | None:
    """The real-scene workflow (ADT's frames, a test-built MPS folder) run into a fresh folder, in the
    background (`tests.background`) -> (result, folder); None without the Aria files or projectaria-tools."""
    from tests.helpers import SHARED_DATA

    if not (SHARED_DATA / "adt_sample").is_dir() or importlib.util.find_spec("projectaria_tools") is None:
        return None
    from tests.data.test_preprocess import _write_mps

    workdir = Path(tempfile.mkdtemp(prefix="egobench_real_scene_"))
    scene = workdir / "adt_scene"
    _write_mps(SHARED_DATA / "adt_sample", scene / "mps" / "slam")
    config = {"suite": "real", "defaults": {"iterations": 5, "preset": "cpu"},
              "scenes": [{"name": "adt", "source": "aria", "vrs": str(SHARED_DATA / "adt_sample" / "video.vrs"),
                          "mps": str(scene / "mps" / "slam"), "focal": 60, "size": 120, "kind": "indoor",
                          "methods": ["ours", "no_viba"]}]}
    path = workdir / "real.yaml"
    path.write_text(yaml.safe_dump(config))
    return snakemake(["--cores", "2", "--configfile", str(path), "--until", "tables"], workdir, timeout=600), workdir


BACKGROUND["test_real_aria_scene_runs_end_to_end"] = _real_aria_scene


@pytest.mark.slow
def test_real_aria_scene_runs_end_to_end(shared_data):
    """ADT's real frames with a test-built MPS folder: preprocess (online + factory) -> train -> evaluate -> tables."""
    pytest.importorskip("projectaria_tools")
    run = background.start(sys.modules[__name__], "test_real_aria_scene_runs_end_to_end").result(timeout=1200)
    assert run is not None  # the job found the files this test's fixture found
    res, tmp_path = run
    try:
        _check_real_aria_scene(res, tmp_path)
    finally:
        shutil.rmtree(tmp_path, ignore_errors=True)


def _check_real_aria_scene(res: subprocess.CompletedProcess, tmp_path: Path) -> None:
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    rec = tmp_path / "results" / "real" / "recordings" / "adt"
    streams = sorted(p.name for p in rec.iterdir() if not p.name.startswith("."))  # not .snakemake_timestamp
    assert streams == ["camera-rgb-rectified-60-h120", "camera-rgb-rectified-60-h120-factory-calib"]
    table = pd.read_csv(tmp_path / "results" / "real" / "tables" / "table1_indoor.csv")
    ours = table[(table["block"] == "egobench") & (table["method"] == "ours")]
    assert len(ours) == 1 and np.isfinite(float(ours["adt PSNR"].iloc[0]))
    ev = yaml.safe_load((tmp_path / "results/real/runs/adt/no_viba/seed0/eval.json").read_text())
    assert ev["calibration"] == "factory" and ev["recording"].endswith("-factory-calib") and ev["scene_kind"] == "indoor"
