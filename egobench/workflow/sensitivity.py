"""`config.sensitivity` -> the recordings, runs and verb arguments of `snakemake sensitivity`.

One sweep per ablation: a recording per swept value (the swept SimConfig field set to the value,
or, in ``scale`` mode, every listed field set to its base value times the multiplier), each trained
with 'ours' and the ablation for every seed through the workflow's ordinary simulate / train /
evaluate rules. A sweep recording is named ``sens-<ablation>-<value>`` (``x<multiplier>`` in scale
mode), so a changed value list keeps the recordings and runs of the values already done.

The SimConfig overrides of the sweeps are checked (`check_sims`) only when the sensitivity target
is built, so a field the simulator does not have yet fails that target, with the key named, and
never the default suite.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass
from typing import Any, Mapping

#: Similarity quantity (key of `egobench similarity`'s JSON) each ablation ignores, by default.
DEFAULT_X = {
    "no_motion_sampling": "rs_shift_px_median",
    "no_viba": "calib_inconsistency_px_median",
    "no_scene_gamma": "scene_dynamic_range_stops",
}
REFERENCE = "ours"
SCENE_PREFIX = "sens-"


@dataclass(frozen=True)
class SweepPoint:
    """One recording of one sweep."""

    scene: str  # recording / scene name, sens-<ablation>-<token>
    ablation: str  # the ablated method
    value: float  # the swept value (scale mode: the multiplier)
    sim: dict  # SimConfig overrides of this recording (suite defaults, sweep base, swept fields)


def _token(value: float) -> str:
    return f"{float(value):g}"


def sweep_points(config: Mapping) -> list[SweepPoint]:
    """Every sweep recording of ``config.sensitivity`` (empty without the block), in config order."""
    sens = config.get("sensitivity") or {}
    defaults_sim = (config.get("defaults") or {}).get("sim") or {}
    out = []
    for ablation, spec in (sens.get("ablations") or {}).items():
        base = {**defaults_sim, **(sens.get("sim") or {}), **(spec.get("sim") or {})}
        sweep = spec["sweep"]
        if "field" in sweep:
            for v in sweep["values"]:
                out.append(SweepPoint(f"{SCENE_PREFIX}{ablation}-{_token(v)}", ablation, float(v),
                                      {**base, sweep["field"]: v}))
        else:
            for m in sweep["scale"]:
                scaled = {k: float(f"{float(b) * float(m):.12g}") for k, b in sweep["fields"].items()}  # no 1.4000000000000001
                out.append(SweepPoint(f"{SCENE_PREFIX}{ablation}-x{_token(m)}", ablation, float(m),
                                      {**base, **scaled}))
    return out


def check_config(config: Mapping) -> list[str]:
    """Messages (each naming its key) for sweep settings the schema cannot express; [] if fine."""
    sens = config.get("sensitivity") or {}
    messages = []
    names = {s["name"] for s in config.get("scenes") or []}
    for ablation, spec in (sens.get("ablations") or {}).items():
        key = f"config.sensitivity.ablations.{ablation}"
        sweep = spec["sweep"]
        fields = [sweep["field"]] if "field" in sweep else list(sweep["fields"])
        for f in fields:
            if f in ("kind", "seed", "name"):
                messages.append(f"{key}.sweep: {f!r} is set by the workflow, it cannot be swept")
        if not (spec.get("x") or ablation in DEFAULT_X):
            messages.append(f"{key}.x: no default similarity quantity for {ablation!r}; name one "
                            f"(e.g. {', '.join(sorted(set(DEFAULT_X.values())))})")
        values = sweep.get("values", sweep.get("scale"))
        if len({_token(v) for v in values}) != len(values):
            messages.append(f"{key}.sweep: values {values} repeat (at 6 significant digits)")
    clash = sorted({p.scene for p in sweep_points(config)} & names)
    if clash:
        messages.append(f"config.scenes: names {clash} are reserved for config.sensitivity's recordings")
    return messages


def check_sims(config: Mapping) -> None:
    """Build every sweep recording's SimConfig; ValueError naming the key of the first bad one."""
    from egobench.sim.config import SimConfig
    from egobench.io_utils import format_value

    sens = config.get("sensitivity") or {}
    for p in sweep_points(config):
        spec = sens["ablations"][p.ablation]
        try:
            SimConfig.from_overrides(spec["kind"], int(spec.get("sim_seed", 0)),
                                     {k: format_value(v) for k, v in p.sim.items()})
        except (ValueError, TypeError) as exc:
            raise ValueError(f"config.sensitivity.ablations.{p.ablation} (recording {p.scene}, swept value "
                             f"{p.value:g}): {exc}") from exc


def scenes(config: Mapping) -> list[dict]:
    """The sweep recordings as workflow scene entries (name, kind, sim_seed, seeds, methods, ...)."""
    sens = config.get("sensitivity") or {}
    d = config.get("defaults") or {}
    out = []
    for p in sweep_points(config):
        spec = sens["ablations"][p.ablation]
        out.append({
            "name": p.scene, "kind": spec["kind"], "paper_scene": None,
            "sim_seed": int(spec.get("sim_seed", 0)),
            "seeds": list(sens.get("seeds") or d.get("seeds") or [0]),
            "methods": [REFERENCE, p.ablation],
            "iterations": int(sens.get("iterations") or d.get("iterations") or 2000),
            "sim": p.sim,
        })
    return out


def similarity_path(root: str, scene: str) -> str:
    return f"{root}/sensitivity/similarity/{scene}.json"


def output_files(root: str) -> list[str]:
    """What `egobench sensitivity` writes (the sensitivity target)."""
    from egobench.analysis.sensitivity import OUTPUT_FILES

    return [f"{root}/sensitivity/{name}" for name in OUTPUT_FILES]


def verb_args(config: Mapping) -> str:
    """`egobench sensitivity` arguments: one ``--sweep JSON`` per ablation, then --bootstrap/--seed."""
    sens = config.get("sensitivity") or {}
    parts = []
    for ablation, spec in (sens.get("ablations") or {}).items():
        paper_x = spec.get("paper_x") or {}
        sweep: dict[str, Any] = {
            "ablation": ablation, "kind": spec["kind"], "x": spec.get("x") or DEFAULT_X.get(ablation),
            "paper_x": paper_x.get("value"), "paper_x_source": paper_x.get("source", ""),
            "paper_scene": spec.get("paper_scene"),
        }
        parts.append(f"--sweep {shlex.quote(json.dumps(sweep, sort_keys=True))}")
    parts.append(f"--bootstrap {int(sens.get('bootstrap', 2000))} --seed {int(sens.get('bootstrap_seed', 0))}")
    return " ".join(parts)
