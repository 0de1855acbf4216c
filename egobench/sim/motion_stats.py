"""`egobench motion-stats`: simulated versus real head-motion statistics.

Angular speed is the rotation angle between consecutive trajectory samples divided by their
time step (`Trajectory.angular_speed_deg_s`), linear speed the distance between consecutive
positions over the time step. The real reference is an MPS ``closed_loop_trajectory.csv``
(the shared Aria sample: p50 27 deg/s, p99 77 deg/s); the simulated rows are the `normal`,
`fast` and `static` settings of `egobench.sim.motion` in one scene kind, pooled over seeds.

Example::

    egobench motion-stats --real ../shared/data/aria_mps_sample/closed_loop_trajectory.csv \\
        --kind indoor --seeds 0 1 2 --out results/motion_stats
"""

from __future__ import annotations

import argparse
import csv
import io
from pathlib import Path

import numpy as np

from egobench.geometry import Trajectory
from egobench.io_utils import atomic_path, write_json
from egobench.sim.motion import HeadMotionConfig, simulate_head_motion
from egobench.sim.world import make_scene

PERCENTILES: tuple[int, ...] = (25, 50, 75, 90, 99)
SETTINGS: tuple[str, ...] = ("normal", "fast", "static")


def _positions_times(trajectory) -> tuple[np.ndarray, np.ndarray]:
    p = trajectory.T_world_device[:, :3, 3].detach().cpu().numpy().astype(np.float64)
    t = trajectory.t_ns.detach().cpu().numpy().astype(np.int64)
    return p, t


def _percentiles(x: np.ndarray) -> dict[str, float]:
    if x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError("motion statistics: need a finite, non-empty speed series (at least 2 trajectory samples)")
    return {f"p{q}": float(np.percentile(x, q)) for q in PERCENTILES}


def angular_speed_percentiles(trajectory) -> dict[str, float]:
    """Percentiles p25, p50, p75, p90, p99 of the head angular speed, deg/s."""
    return _percentiles(np.asarray(trajectory.angular_speed_deg_s(), dtype=np.float64))


def linear_speed_percentiles(trajectory) -> dict[str, float]:
    """Percentiles p25, p50, p75, p90, p99 of the head (device origin) linear speed, m/s."""
    p, t = _positions_times(trajectory)
    dt_s = np.diff(t).astype(np.float64) * 1e-9
    return _percentiles(np.linalg.norm(np.diff(p, axis=0), axis=1) / dt_s)


def motion_summary(trajectories: list) -> dict:
    """Pooled statistics of several trajectories: angular (deg/s) and linear (m/s) percentiles."""
    if not trajectories:
        raise ValueError("motion_summary: expected at least one trajectory")
    ang = np.concatenate([np.asarray(tr.angular_speed_deg_s(), dtype=np.float64) for tr in trajectories])
    lin = []
    for tr in trajectories:
        p, t = _positions_times(tr)
        lin.append(np.linalg.norm(np.diff(p, axis=0), axis=1) / (np.diff(t).astype(np.float64) * 1e-9))
    duration = float(sum(tr.duration_s for tr in trajectories))
    return {"angular_speed_deg_s": _percentiles(ang), "linear_speed_m_s": _percentiles(np.concatenate(lin)),
            "duration_s": duration, "n_trajectories": len(trajectories)}


def compare(real_csv: str | Path | None, kind: str, seeds: list[int], duration_s: float,
            settings: tuple[str, ...] = SETTINGS) -> dict:
    """Rows {source: summary} for the real csv (if given) and each simulated setting."""
    rows: dict[str, dict] = {}
    if real_csv is not None:
        rows["real"] = motion_summary([Trajectory.from_mps_csv(real_csv)]) | {"source": str(real_csv)}
    for setting in settings:
        trs = []
        for seed in seeds:
            scene = make_scene(kind, seed)
            trs.append(simulate_head_motion(HeadMotionConfig(duration_s=duration_s, setting=setting), scene, seed))
        rows[setting] = motion_summary(trs) | {"source": f"simulated {setting}, scene {kind}, seeds {list(seeds)}"}
    return rows


def format_table(rows: dict[str, dict]) -> str:
    """Plain-text table: one row per source."""
    head = ["source"] + [f"ang p{q}" for q in PERCENTILES] + ["lin p50", "lin p99"]
    lines = ["  ".join(f"{h:>9}" for h in head)]
    for name, r in rows.items():
        a, l = r["angular_speed_deg_s"], r["linear_speed_m_s"]
        vals = [a[f"p{q}"] for q in PERCENTILES] + [l["p50"], l["p99"]]
        lines.append("  ".join([f"{name:>9}"] + [f"{v:9.2f}" for v in vals]))
    lines.append("(angular speed in deg/s, linear speed in m/s)")
    return "\n".join(lines)


def _csv_text(rows: dict[str, dict]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["source", "quantity", "unit"] + [f"p{q}" for q in PERCENTILES])
    for name, r in rows.items():
        w.writerow([name, "angular_speed", "deg/s"] + [f"{r['angular_speed_deg_s'][f'p{q}']:.6g}" for q in PERCENTILES])
        w.writerow([name, "linear_speed", "m/s"] + [f"{r['linear_speed_m_s'][f'p{q}']:.6g}" for q in PERCENTILES])
    return buf.getvalue()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder (motion_stats.json, motion_stats.csv)")
    parser.add_argument("--real", type=Path, default=None,
                        help="real MPS closed_loop_trajectory.csv to compare with (optional)")
    parser.add_argument("--kind", default="indoor", choices=["outdoor", "indoor", "object", "quest3"],
                        help="scene kind the simulated walks use (default indoor)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="simulation seeds (pooled)")
    parser.add_argument("--duration-s", type=float, default=20.0, help="simulated seconds per seed")


def run(args: argparse.Namespace) -> int:
    if not args.duration_s > 0:
        raise ValueError(f"--duration-s: expected a positive number of seconds, got {args.duration_s}")
    if args.real is not None and not Path(args.real).is_file():
        raise FileNotFoundError(f"--real: {args.real}: file not found")
    rows = compare(args.real, args.kind, list(args.seeds), float(args.duration_s))
    print(format_table(rows))
    out = Path(args.out)
    write_json(out / "motion_stats.json", {"schema": "egobench.motion_stats/1", "kind": args.kind, "rows": rows})
    with atomic_path(out / "motion_stats.csv") as tmp:
        tmp.write_text(_csv_text(rows))
    print(f"wrote {out / 'motion_stats.json'} and {out / 'motion_stats.csv'}")
    return 0
