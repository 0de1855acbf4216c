"""What a trained run's smallest testable sizes mean for the hidden effect (issue 15, docs/diagnosis.md).

The smallest testable size of each cause (`calibration.smallest_testable`) is in terms of what training
left in the residual. A trained model absorbs part of an effect into the scene (the trained sweep's
"retained through training": round 1's estimate over the truth, e.g. 0.68 for a time offset, 0.09 for a
vignette, below zero for distortion), so the hidden effect must be larger by 1 / retention to be
testable; with a retention near or below zero it is not testable on such a run at any size measured.
"""

from __future__ import annotations

from pathlib import Path

from egobench.diagnose.trained_sweep import read_summary

#: Below this median retention an effect is reported as not testable on a run of the sweep's setup.
RETENTION_FLOOR = 0.05


def load_retention(paths: list[str | Path]) -> tuple[dict[str, float], list[dict]]:
    """Median retention per effect from trained-sweep summaries (trained_sweep.json; later files win)
    -> ({effect: retention}, [{source, setup}])."""
    retention, sources = {}, []
    for path in paths:
        p = Path(path)
        s, setup = read_summary(p)
        effects = s.get("effects")
        if not isinstance(effects, list):
            raise ValueError(f"{p}: field 'effects': expected the per-effect list of a trained-sweep summary")
        found = {e["effect"]: float(e["median_retention"]) for e in effects
                 if isinstance(e, dict) and e.get("median_retention") is not None}
        if not found:
            raise ValueError(f"{p}: field 'effects[].median_retention': none given (a summary written before "
                             f"retention was measured: rerun the sweep to rewrite it)")
        retention.update(found)
        sources.append({"source": str(p), "setup": setup})
    return retention, sources


def hidden_testable(smallest: dict, retention: dict[str, float]) -> dict:
    """Smallest testable hidden effect per cause: each residual-side size over the retention, or
    not testable where the retention is below RETENTION_FLOOR. Causes without a retention are left out."""
    out = {}
    for name, sizes in smallest.items():
        r = retention.get(name)
        if r is None:
            continue
        if not r >= RETENTION_FLOOR:
            out[name] = {"testable": False, "retention": r}
        else:
            out[name] = {"testable": True, "retention": r, **{k: v / r for k, v in sizes.items()}}
    return out
