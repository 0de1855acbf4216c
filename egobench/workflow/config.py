"""Workflow configuration -> job lists and verb arguments (used by the Snakefile; unit-testable).

The Snakefile stays thin: it validates the config with `check_config` (clear errors naming the
key, before any job runs), fills the schema defaults with ``snakemake.utils.validate`` and asks a
`Suite` for the paths, job lists and command-line arguments of every rule. No science here.
"""

from __future__ import annotations

import shlex
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from egobench.workflow import sensitivity as sensitivity_workflow
from egobench.io_utils import format_value

REPO_ROOT = Path(__file__).resolve().parents[2]
SCHEMA_PATH = REPO_ROOT / "workflows" / "schemas" / "config.schema.yaml"
#: SimConfig fields the workflow sets itself (from the scene entry), not through `sim:`.
WORKFLOW_SIM_FIELDS = ("kind", "seed", "name")


class ConfigError(ValueError):
    """A workflow configuration that does not match the schema or refers to unknown things."""


def load_schema(path: str | Path = SCHEMA_PATH) -> dict:
    with open(path) as f:
        return yaml.safe_load(f)


def _key_path(path) -> str:
    out = "config"
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else f".{p}"
    return out


def _schema_messages(config: Mapping, schema: Mapping) -> list[str]:
    from jsonschema import Draft202012Validator

    messages = []
    validator = Draft202012Validator(schema)
    for err in sorted(validator.iter_errors(config), key=lambda e: list(map(str, e.absolute_path))):
        where = _key_path(err.absolute_path)
        if err.validator == "additionalProperties" and isinstance(err.instance, dict):
            allowed = sorted(err.schema.get("properties", {}))
            unknown = sorted(set(err.instance) - set(allowed))
            for key in unknown:
                messages.append(f"{_key_path([*err.absolute_path, key])}: unknown key {key!r}; "
                                f"allowed keys here: {', '.join(allowed) or '(none)'}")
        elif err.validator == "enum":
            messages.append(f"{where}: {err.instance!r} is not allowed; expected one of "
                            f"{', '.join(map(str, err.validator_value))}")
        elif err.validator == "required":
            messages.append(f"{where}: {err.message}")
        else:
            messages.append(f"{where}: {err.message}")
    return messages


def check_config(config: Mapping, schema: Mapping | None = None, check_sim: bool = True) -> None:
    """Raise ConfigError listing every problem (each naming its key) or return None."""
    schema = load_schema() if schema is None else schema
    messages = _schema_messages(config, schema)
    if messages:
        raise ConfigError("invalid workflow config:\n  " + "\n  ".join(messages))
    names = [s["name"] for s in config["scenes"]]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        messages.append(f"config.scenes: scene names must be unique; repeated: {', '.join(dupes)}")
    for i, scene in enumerate(config["scenes"]):
        for src in ((config.get("defaults") or {}).get("sim") or {}, scene.get("sim") or {}):
            for key in WORKFLOW_SIM_FIELDS:
                if key in src:
                    messages.append(f"config.scenes[{i}].sim.{key}: set by the workflow from the scene entry "
                                    "(kind, sim_seed, name); remove it from sim")
    messages += _check_paper_scenes(config["scenes"]) + _check_aria_scenes(config)
    messages += sensitivity_workflow.check_config(config)
    diag = config.get("diagnose") or {}
    for i, name in enumerate(diag.get("scenes") or []):
        if name not in names:
            messages.append(f"config.diagnose.scenes[{i}]: {name!r} is not a scene of this suite "
                            f"({', '.join(names)})")
    by_name = {s["name"]: s for s in config["scenes"]}
    if diag.get("source", "run") == "run":
        for name in diag.get("scenes") or []:
            for m in diag.get("methods") or ["ours"]:
                if name in by_name and m not in by_name[name]["methods"]:
                    messages.append(f"config.diagnose.methods: {m!r} is not run on scene {name!r}; diagnose.source "
                                    "'run' needs the trained run (add it to the scene's methods or use 'ground_truth')")
    for i, scene in enumerate(config["scenes"]):
        for m in scene.get("method_seeds") or {}:
            if m not in scene["methods"]:
                messages.append(f"config.scenes[{i}].method_seeds: {m!r} is not among the scene's methods "
                                f"({', '.join(scene['methods'])})")
    adt = (config.get("diagnose") or {}).get("adt_dir")
    if adt and not (Path(adt) / "video.vrs").is_file():
        messages.append(f"config.diagnose.adt_dir: {adt}: expected a folder with video.vrs and synthetic_video.vrs")
    real = (config.get("motion_stats") or {}).get("real_trajectory")
    if real is not None and not Path(real).is_file():
        messages.append(f"config.motion_stats.real_trajectory: {real}: file not found")
    qual = (config.get("plots") or {}).get("qualitative_scene")
    if qual is not None and qual not in names:
        messages.append(f"config.plots.qualitative_scene: {qual!r} is not a scene of this suite ({', '.join(names)})")
    if not messages and check_sim:
        messages += _check_sim_overrides(config) + _check_train_overrides(config)
    if messages:
        raise ConfigError("invalid workflow config:\n  " + "\n  ".join(messages))


def _check_paper_scenes(scenes: list) -> list[str]:
    """A paper_scene must name one of the paper's table columns (case-insensitive), else its cell stays empty."""
    from egobench.report.paper_numbers import PAPER_SCENES

    messages = []
    for i, scene in enumerate(scenes):
        value = scene.get("paper_scene")
        if value is not None and value.lower() not in PAPER_SCENES:
            messages.append(f"config.scenes[{i}].paper_scene: {value!r} (scene {scene['name']!r}) is not a scene of "
                            f"the paper's tables; expected one of {', '.join(map(repr, PAPER_SCENES))} or null")
    return messages


def _method_seeds(scene: Mapping) -> dict[str, tuple[int, ...]]:
    """The scene's per-method seed overrides, method -> seeds."""
    return {m: tuple(int(x) for x in seeds) for m, seeds in (scene.get("method_seeds") or {}).items()}


def aria_inputs(scene: Mapping, aria_root: str | None) -> tuple[str, str] | None:
    """(vrs, mps folder) of a scene preprocessed from a real recording, or None for a simulated one."""
    if scene.get("source") == "aria":
        return scene["vrs"], scene["mps"]
    if aria_root and scene.get("aria_scene"):
        base = f"{aria_root.rstrip('/')}/{scene['aria_scene']}"
        return scene.get("vrs") or f"{base}/recording.vrs", scene.get("mps") or f"{base}/mps/slam"
    return None


def _check_aria_scenes(config: Mapping) -> list[str]:
    """Real scenes: the VRS file and the MPS folder exist; they have no simulator ground truth to diagnose."""
    messages = []
    root = config.get("aria_root")
    diag = config.get("diagnose") or {}
    for i, scene in enumerate(config["scenes"]):
        inputs = aria_inputs(scene, root)
        if inputs is None:
            continue
        vrs, mps = inputs
        if not Path(vrs).is_file():
            messages.append(f"config.scenes[{i}].vrs (scene {scene['name']!r}): {vrs}: file not found")
        if not Path(mps).is_dir():
            messages.append(f"config.scenes[{i}].mps (scene {scene['name']!r}): {mps}: folder not found "
                            "(expected the MPS slam folder)")
        if diag.get("source") == "ground_truth" and scene["name"] in (diag.get("scenes") or []):
            messages.append(f"config.diagnose.source: 'ground_truth' needs a simulated scene; {scene['name']!r} is "
                            "a real recording (use 'run')")
    return messages


def _check_sim_overrides(config: Mapping) -> list[str]:
    """Build each scene's SimConfig from its overrides so bad fields fail before any job runs."""
    try:
        from egobench.sim.config import SimConfig
    except ImportError:  # the simulator is optional for a dry run of the workflow
        return []
    messages = []
    defaults = (config.get("defaults") or {}).get("sim") or {}
    for i, scene in enumerate(config["scenes"]):
        if aria_inputs(scene, config.get("aria_root")) is not None:
            continue  # preprocessed, not simulated
        overrides = {k: format_value(v) for k, v in {**defaults, **(scene.get("sim") or {})}.items()}
        try:
            SimConfig.from_overrides(scene["kind"], int(scene.get("sim_seed", 0)), overrides)
        except (ValueError, TypeError) as exc:
            messages.append(f"config.scenes[{i}].sim (scene {scene['name']!r}): {exc}")
    return messages


def _check_train_overrides(config: Mapping) -> list[str]:
    """Apply each scene's train overrides to a TrainConfig so unknown fields fail before any job."""
    try:
        from egobench.train import TrainConfig, parse_overrides
    except ImportError:
        return []
    messages = []
    defaults = (config.get("defaults") or {}).get("train") or {}
    for i, scene in enumerate(config["scenes"]):
        items = [f"{k}={format_value(v)}" for k, v in {**defaults, **(scene.get("train") or {})}.items()]
        try:
            parse_overrides(TrainConfig(), items)
        except (ValueError, TypeError) as exc:
            messages.append(f"config.scenes[{i}].train (scene {scene['name']!r}): {exc}")
    return messages


def fill_defaults(config: dict, schema: Mapping | None = None) -> dict:
    """Fill the schema's defaults in place (as snakemake.utils.validate does) and return config."""
    from jsonschema import Draft202012Validator, validators

    schema = load_schema() if schema is None else schema
    validate_properties = Draft202012Validator.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, sch):
        for prop, sub in properties.items():
            if "default" in sub and isinstance(instance, dict):
                instance.setdefault(prop, sub["default"])
        yield from validate_properties(validator, properties, instance, sch)

    cls = validators.extend(Draft202012Validator, {"properties": set_defaults})
    for err in cls(schema).iter_errors(config):
        raise ConfigError(f"{_key_path(err.absolute_path)}: {err.message}")
    return config


def set_args(overrides: Mapping[str, Any]) -> str:
    """``--set k=v`` arguments, shell-quoted, in key order."""
    return " ".join(f"--set {shlex.quote(f'{k}={format_value(v)}')}" for k, v in sorted(overrides.items()))


def egobench_command(setting: str = "auto", repo_root: str | Path = REPO_ROOT) -> str:
    """The shell prefix rules use to call egobench."""
    if setting != "auto":
        return setting
    if shutil.which("egobench"):
        return "egobench"
    root = shlex.quote(str(Path(repo_root).resolve()))
    return f"env PYTHONPATH={root}${{PYTHONPATH:+:$PYTHONPATH}} {shlex.quote(sys.executable)} -m egobench.cli"


def egobench_shell_function(setting: str = "auto", repo_root: str | Path = REPO_ROOT) -> str:
    """A bash function ``egobench`` that runs `egobench_command` (the rules' shell prefix defines it)."""
    command = egobench_command(setting, repo_root)
    if command == "egobench":  # the installed script: call it, not this function again
        command = "command egobench"
    return f'egobench() {{ {command} "$@"; }};'


@dataclass(frozen=True)
class Scene:
    """One scene entry with the suite defaults applied."""

    name: str  # unique scene name
    kind: str | None  # outdoor | indoor | object | quest3 (None: a real scene without a label)
    paper_scene: str | None  # the paper's column, or None
    sim_seed: int  # seed of the simulated recording
    seeds: tuple[int, ...]  # training seeds
    methods: tuple[str, ...]  # methods run on this scene
    iterations: int  # training iterations
    preset: str  # starting train config: cpu | paper
    sim: dict  # SimConfig overrides (defaults.sim updated by the scene's sim)
    train: dict  # train-config overrides (defaults.train updated by the scene's train)
    aria: tuple[str, str] | None = None  # (vrs, mps folder) of a real scene preprocessed into the recording
    vignette: str | None = None  # real scene: raw lens shading PNG
    focal: float = 1200.0  # real scene: rectified focal, px
    size: int = 2400  # real scene: rectified side, px
    method_seeds: Mapping[str, tuple[int, ...]] = field(default_factory=dict)  # per-method seeds (override)

    def seeds_of(self, method: str) -> tuple[int, ...]:
        """Training seeds of ``method`` on this scene: its ``method_seeds`` entry, else the scene's."""
        return tuple(self.method_seeds.get(method, self.seeds))


class Suite:
    """Paths, job lists and verb arguments of one validated, default-filled config."""

    def __init__(self, config: Mapping):
        self.config = config
        self.name: str = config["suite"]
        self.root = f"{config.get('results_dir', 'results').rstrip('/')}/{self.name}"
        d = config.get("defaults") or {}
        self.scenes: dict[str, Scene] = {s["name"]: self._entry(s, d) for s in config["scenes"]}
        # `snakemake sensitivity` recordings (egobench.workflow.sensitivity): not part of `all`
        self.sensitivity_scenes: dict[str, Scene] = {s["name"]: self._entry(s, d)
                                                     for s in sensitivity_workflow.scenes(config)}
        diag = config.get("diagnose") or {}
        self.diagnose_jobs = [(s, m) for s in diag.get("scenes", []) for m in diag.get("methods", ["ours"])]
        self.diagnose_source: str = diag.get("source", "run")
        self.diagnose_max_frames: int | None = diag.get("max_frames")
        self.diagnose_lens_check: bool = bool(diag.get("lens_check", False))
        self.sweep_seeds: int = int(diag.get("sweep_seeds", 3))
        self.adt_dir: str | None = diag.get("adt_dir")
        self.trained_sweep: dict = dict(diag.get("trained_sweep") or {})
        self.qualitative_scene = (config.get("plots") or {}).get("qualitative_scene")
        self.viewer: dict = {"enabled": True, "max_frames": 48, "every": 1, "fps": 10, **(config.get("viewer") or {})}
        ms = config.get("motion_stats") or {}
        self.motion_stats = bool(ms.get("enabled", False))
        self.motion_stats_kind: str = ms.get("kind", "indoor")
        self.motion_stats_real: str | None = ms.get("real_trajectory")

    def _entry(self, s: Mapping, d: Mapping) -> Scene:
        """One scene entry with the suite defaults ``d`` applied."""
        config = self.config
        return Scene(
            name=s["name"],
            kind=s.get("kind"),
            paper_scene=s.get("paper_scene"),
            sim_seed=int(s.get("sim_seed", 0)),
            seeds=tuple(s.get("seeds") or d.get("seeds") or [0]),
            methods=tuple(s["methods"]),
            iterations=int(s.get("iterations") or d.get("iterations") or 2000),
            preset=s.get("preset") or d.get("preset") or "cpu",
            sim={**(d.get("sim") or {}), **(s.get("sim") or {})},
            train={**(d.get("train") or {}), **(s.get("train") or {})},
            aria=aria_inputs(s, config.get("aria_root")),
            vignette=s.get("vignette"),
            focal=float(s.get("focal", 1200)),
            size=int(s.get("size", 2400)),
            method_seeds=_method_seeds(s),
        )

    # ---- paths -----------------------------------------------------------------------------
    def recording_dir(self, scene: str) -> str:
        return f"{self.root}/recordings/{scene}"

    def run_dir(self, scene: str, method: str, seed: int | str) -> str:
        return f"{self.root}/runs/{scene}/{method}/seed{seed}"

    def runs(self) -> list[tuple[str, str, int]]:
        """Every (scene, method, seed) training job, in config order."""
        return [(s.name, m, seed) for s in self.scenes.values() for m in s.methods for seed in s.seeds_of(m)]

    def eval_records(self) -> list[str]:
        return [f"{self.run_dir(s, m, seed)}/eval.json" for s, m, seed in self.runs()]

    def diagnosis_dirs(self) -> list[str]:
        return [f"{self.root}/diagnosis/{s}/{m}" for s, m in self.diagnose_jobs]

    def viewer_outputs(self) -> list[str]:
        """Per scene that trains 'ours': its PLY, fly-through video and viewer page (config.viewer)."""
        if not self.viewer["enabled"]:
            return []
        return [f"{self.root}/viewer/{s}/{name}" for s, sc in self.scenes.items() if "ours" in sc.methods
                for name in ("ours.ply", "flythrough.mp4", "view/index.html")]

    def viewer_runs(self, scene: str) -> tuple[str, str | None]:
        """(the run folder of 'ours', of w/o motion sampling or None) at the scene's first seed of each."""
        sc = self._scene(scene)
        compare = "no_motion_sampling" if "no_motion_sampling" in sc.methods else None
        return (self.run_dir(scene, "ours", sc.seeds_of("ours")[0]),
                compare and self.run_dir(scene, compare, sc.seeds_of(compare)[0]))

    def render_args(self, scene: str) -> str:
        """`egobench render` options of a scene's fly-through (config.viewer)."""
        v, (_, compare) = self.viewer, self.viewer_runs(scene)
        out = f"--captured --max-frames {int(v['max_frames'])} --every {int(v['every'])} --fps {float(v['fps']):g}"
        return out + (f" --compare {compare}" if compare else "")

    def view_args(self, scene: str) -> str:
        """`egobench view` options of a scene's page: the second run to toggle to, when the scene trains it."""
        _, compare = self.viewer_runs(scene)
        return f"--compare {compare}" if compare else ""

    def methods(self) -> list[str]:
        every = [*self.scenes.values(), *self.sensitivity_scenes.values()]
        return sorted({m for s in every for m in s.methods} | {m for _, m in self.diagnose_jobs})

    def all_scene_names(self) -> list[str]:
        """The suite's scenes and the sensitivity sweep's recordings (the scene wildcard's values)."""
        return [*self.scenes, *self.sensitivity_scenes]

    # ---- `snakemake sensitivity` (egobench.workflow.sensitivity) ---------------------------
    def sensitivity_records(self) -> list[str]:
        """eval.json of every sweep run ('ours' and the ablation, every seed, every swept value)."""
        return [f"{self.run_dir(s.name, m, seed)}/eval.json"
                for s in self.sensitivity_scenes.values() for m in s.methods for seed in s.seeds]

    def sensitivity_similarity(self) -> list[str]:
        return [sensitivity_workflow.similarity_path(self.root, s) for s in self.sensitivity_scenes]

    def sensitivity_outputs(self) -> list[str]:
        """Targets of `snakemake sensitivity`; first checks every sweep's SimConfig (ConfigError)."""
        if not self.sensitivity_scenes:
            raise ConfigError("config.sensitivity: no ablations configured; `snakemake sensitivity` needs "
                              "a sensitivity block (see config/config.yaml)")
        try:
            sensitivity_workflow.check_sims(self.config)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        return sensitivity_workflow.output_files(self.root)

    def sensitivity_args(self) -> str:
        return sensitivity_workflow.verb_args(self.config)

    # ---- verb arguments --------------------------------------------------------------------
    def _scene(self, scene: str) -> Scene:
        if scene in self.sensitivity_scenes:
            return self.sensitivity_scenes[scene]
        if scene not in self.scenes:
            raise ConfigError(f"scene {scene!r} is not in suite {self.name!r} ({', '.join(self.scenes)})")
        return self.scenes[scene]

    @staticmethod
    def scene_regex(names: list[str]) -> str:
        """A wildcard constraint matching exactly these scene names (none: matches nothing)."""
        import re

        return "|".join(re.escape(n) for n in sorted(names)) or "(?!x)x"

    def simulated_scenes(self) -> list[str]:
        return [s.name for s in self.scenes.values() if s.aria is None] + list(self.sensitivity_scenes)

    def aria_scenes(self) -> list[str]:
        return [s.name for s in self.scenes.values() if s.aria is not None]

    def aria_input(self, scene: str, which: str) -> str:
        """The real scene's "vrs" file or "mps" folder."""
        s = self._scene(scene)
        if s.aria is None:
            raise ConfigError(f"scene {scene!r} is simulated, not preprocessed")
        return s.aria[0] if which == "vrs" else s.aria[1]

    def preprocess_args(self, scene: str) -> str:
        s = self._scene(scene)
        out = f"--focal {s.focal:g} --size {s.size}"
        return out + (f" --vignette {shlex.quote(s.vignette)}" if s.vignette else "")

    def needs_factory_stream(self, scene: str) -> bool:
        """True when a method of the scene trains on the factory calibration (preprocess it too)."""
        from egobench.model.methods import get_method

        return any(get_method(m).calibration == "factory" for m in self._scene(scene).methods)

    def simulate_args(self, scene: str) -> str:
        s = self._scene(scene)
        return f"--kind {s.kind} --seed {s.sim_seed} {set_args({**s.sim, 'name': s.name})}"

    def train_args(self, scene: str) -> str:
        s = self._scene(scene)
        return f"--preset {s.preset} --iterations {s.iterations} {set_args(s.train)}".strip()

    def evaluate_args(self, scene: str) -> str:
        s = self._scene(scene)
        out = f"--scene {shlex.quote(s.name)}"
        if s.paper_scene:
            out += f" --paper-scene {shlex.quote(s.paper_scene)}"
        if s.aria is not None and s.kind:  # a real recording carries no kind: its table block
            out += f" --scene-kind {s.kind}"
        return out

    def diagnose_run(self, scene: str, method: str) -> list[str]:
        """The train record the diagnosis of (scene, method) reads (first seed), or [] for ground_truth."""
        if self.diagnose_source != "run":
            return []
        return [f"{self.run_dir(scene, method, self._scene(scene).seeds[0])}/train.json"]

    def diagnose_args(self, scene: str, method: str) -> str:
        limit = "" if self.diagnose_max_frames is None else f" --max-frames {int(self.diagnose_max_frames)}"
        if self.diagnose_source != "run":
            return "--source ground_truth" + limit
        lens = " --lens-check" if self.diagnose_lens_check else ""
        return f"--source run --run {shlex.quote(self.run_dir(scene, method, self._scene(scene).seeds[0]))}" + lens + limit

    def discovery_outputs(self) -> list[str]:
        """Targets of `snakemake discovery`: the hidden-effect sweep, and the ADT diagnosis if configured."""
        out = [f"{self.root}/discovery/sweep"]
        if self.trained_sweep.get("enabled"):
            out.append(f"{self.root}/discovery/trained_sweep/trained_sweep.json")
        if self.adt_dir:
            out.append(f"{self.root}/discovery/adt")
        return out

    def trained_sweep_args(self) -> str:
        """Arguments of `egobench diagnose --sweep --trained` from config.diagnose.trained_sweep."""
        t = self.trained_sweep
        out = (f"--sweep-null {int(t.get('null_cases', 6))} --sweep-seeds {int(t.get('seeds', 1))} "
               f"--sweep-kind {t.get('kind', 'indoor')} --sweep-size {int(t.get('size', 40))} "
               f"--sweep-frames {int(t.get('n_frames', 24))} --iterations {int(t.get('iterations', 800))}")
        effects = t.get("effects")
        return out + (f" --sweep-effects {','.join(effects)}" if effects else "")

    def motion_stats_args(self) -> str:
        out = f"--kind {self.motion_stats_kind}"
        if self.motion_stats_real:
            out += f" --real {shlex.quote(self.motion_stats_real)}"
        return out

    def resources(self, step: str) -> dict[str, int]:
        """threads, mem_mb, gpu, runtime of one step (schema defaults applied)."""
        r = {"threads": 1, "mem_mb": 2000, "gpu": 0, "runtime": 60}
        r.update((self.config.get("resources") or {}).get(step) or {})
        return r


def load_suite(config_path: str | Path) -> Suite:
    """Read, check and default-fill a config file (for tests and scripts)."""
    with open(config_path) as f:
        config = yaml.safe_load(f)
    if not isinstance(config, dict):
        raise ConfigError(f"{config_path}: a workflow config is a YAML mapping")
    try:
        check_config(config)
    except ConfigError as exc:
        raise ConfigError(f"{config_path}: {exc}") from exc
    return Suite(fill_defaults(config))
