"""Where two methods' held-out errors differ, by the captured pixel's display level: the measurement behind
the README's scene-gamma sensitivity bullet.

    python scripts/error_by_display_level.py results/default sens-no_scene_gamma-4 \
        --methods ours no_scene_gamma --seeds 0 1 2

Pools the held-out squared error of each method's runs (`egobench.evaluate.held_out_error_by_level`,
the 8-bit renders as `egobench evaluate` scores them) over the seeds, per display-level bin, and prints
a Markdown table: the share of pixels, each method's pooled PSNR in the bin, and the bin's share of the
difference in total squared error (positive: the bin moves the total the way the whole difference goes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

EDGES = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9, 1.01)


def pooled(root: Path, scene: str, method: str, seeds: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Squared error [B] and pixels [B] of `method` on `scene`, summed over `seeds`."""
    from egobench.evaluate import held_out_error_by_level

    sse, n = np.zeros(len(EDGES) - 1), np.zeros(len(EDGES) - 1)
    for seed in seeds:
        s, c = held_out_error_by_level(root / "recordings" / scene, root / "runs" / scene / method / f"seed{seed}",
                                       EDGES)
        sse, n = sse + s, n + c
    return sse, n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("suite_dir", type=Path, help="results/<suite> (recordings/ and runs/ inside)")
    ap.add_argument("scene")
    ap.add_argument("--methods", nargs=2, default=["ours", "no_scene_gamma"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    a = ap.parse_args(argv)
    (sa, n), (sb, _) = (pooled(a.suite_dir, a.scene, m, a.seeds) for m in a.methods)
    db = lambda s, c: -10 * np.log10(s / c)  # noqa: E731
    print(f"{a.scene}, seeds {a.seeds}: pooled PSNR {a.methods[0]} {db(sa.sum(), n.sum()):.2f} dB, "
          f"{a.methods[1]} {db(sb.sum(), n.sum()):.2f} dB\n")
    print(f"| display level | pixels | {a.methods[0]}, dB | {a.methods[1]}, dB | share of the SSE difference |")
    print("|---|---|---|---|---|")
    for i in np.flatnonzero(n):
        print(f"| {EDGES[i]:g}-{min(EDGES[i + 1], 1):g} | {n[i] / n.sum():.1%} | {db(sa[i], n[i]):.2f} | "
              f"{db(sb[i], n[i]):.2f} | {(sa[i] - sb[i]) / (sa.sum() - sb.sum()):+.0%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
