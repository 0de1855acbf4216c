"""The gain of modelling an absorbed effect, measured against the simulator's truth (issue 27 item 5).

A trained model absorbs an unstated vignette (and, at a near-constant exposure, a response error) into
its scene colours, so its held-out PSNR cannot show what modelling the effect gains: the renders
match the images either way. On a synthetic recording the simulator knows the scene's clean linear
radiance in every held-out view (ground_truth/radiance). A model's scene colour, decoded to linear,
should be that radiance up to one global scale; the error left after the best scale says how right
the reconstructed scene is, independently of how the images were formed. The gain of an extension
is how much it lowers that error.

    python -m egobench.diagnose.truth --sweep OUT   # every case of a trained-run sweep with run_shading/

writes OUT/truth_gain.csv and OUT/truth_gain.md (per effect: the median radiance error without and
with the learned shading, and the gain), beside the sweep's own table.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.stats as sps
import torch

from egobench.evaluate import held_out_renders
from egobench.io_utils import atomic_path

#: Pixels used: the model's opacity at least this (uncovered pixels have no scene colour to judge).
MIN_ALPHA = 0.5


def log_radiance_error(scene_linear: np.ndarray, truth: np.ndarray, weight: np.ndarray) -> float:
    """RMS over the weighted pixels of log(model / truth) after the best global log scale (the weighted
    mean), as a relative error: exp(rms) - 1. ``scene_linear``, ``truth`` [N, 3] > 0; ``weight`` [N]."""
    w = np.repeat(weight[:, None], 3, axis=1).ravel()
    d = (np.log(scene_linear) - np.log(truth)).ravel()
    if not (w > 0).any():
        raise ValueError("log_radiance_error: no pixel with a positive weight")
    d = d - np.sum(w * d) / np.sum(w)
    return float(math.expm1(math.sqrt(np.sum(w * d * d) / np.sum(w))))


def held_out_radiance_error(recording_dir, run_dir) -> float:
    """The run's scene colour against the simulator's clean radiance over the held-out frames
    (`log_radiance_error` over pixels with opacity >= MIN_ALPHA and positive radiance)."""
    model, truth, weight = [], [], []
    for lin, alpha, radiance in held_out_renders(recording_dir, run_dir):
        ok = (alpha >= MIN_ALPHA) & (radiance.min(-1) > 0) & (lin.min(-1) > 0)
        model.append(lin[ok])
        truth.append(radiance[ok])
        weight.append(alpha[ok])
    if not sum(len(w) for w in weight):
        raise ValueError(f"{run_dir}: no held-out pixel with opacity >= {MIN_ALPHA} and a positive radiance")
    return log_radiance_error(np.concatenate(model).astype(np.float64), np.concatenate(truth).astype(np.float64),
                              np.concatenate(weight).astype(np.float64))


def extension_truth_gain(recording_dir, base_run, extension_run) -> dict:
    """Radiance error of the run and of its extension run, and the gain (base - extension: > 0 when
    the extension's scene is nearer the truth)."""
    base = held_out_radiance_error(recording_dir, base_run)
    ext = held_out_radiance_error(recording_dir, extension_run)
    return {"base_radiance_error": base, "extension_radiance_error": ext, "radiance_error_reduction": base - ext}


def sweep_truth_gains(sweep_dir: str | Path) -> list[dict]:
    """One row per case of a trained-run sweep folder that has recording/, run/ and run_shading/ (and
    its case.json): the case's held-out PSNR gain of the extension beside its truth gain."""
    rows = []
    for case_dir in sorted((Path(sweep_dir) / "cases").iterdir()):
        done = case_dir / "case.json"
        if not (done.is_file() and (case_dir / "run_shading" / "train.json").is_file()):
            continue
        row = json.loads(done.read_text())
        truth = extension_truth_gain(case_dir / "recording", case_dir / "run", case_dir / "run_shading")
        rows.append({"case": row["case"], "effect": row["effect"], "value": row["value"],
                     "held_out_psnr_db": row.get("held_out_psnr_db"), "extension_gain_db": row.get("extension_gain_db"),
                     **truth})
    return rows


def truth_markdown(df) -> str:
    """Per effect: cases, median held-out PSNR gain of the extension, median radiance errors, the median
    reduction, and the reduction against the nulls' (one-sided Mann-Whitney p: larger than on nulls)."""
    null = df[df.effect == "none"].radiance_error_reduction.to_numpy()
    lines = ["| effect | n | extension: held-out PSNR gain (median dB) | radiance error without | with | "
             "reduction (median) | nearer the truth | reduction above the nulls' (Mann-Whitney p) |",
             "|---|---|---|---|---|---|---|---|"]
    for effect, g in df.groupby("effect", sort=False):
        red = g.radiance_error_reduction.to_numpy()
        p = (f"{sps.mannwhitneyu(red, null, alternative='greater').pvalue:.3f}"
             if effect != "none" and len(null) and len(red) else "-")
        lines.append(f"| {effect} | {len(g)} | {g.extension_gain_db.median():+.3f} | "
                     f"{100 * g.base_radiance_error.median():.1f} % | {100 * g.extension_radiance_error.median():.1f} % | "
                     f"{100 * np.median(red):+.2f} pts | {int((red > 0).sum())} / {len(g)} | {p} |")
    return ("# Gain of the learned shading against the simulator's truth\n\nRadiance error: exp(RMS log(model scene "
            "colour / clean radiance)) - 1 over the held-out frames' covered pixels, after the best global scale "
            "(`egobench.diagnose.truth`); reduction: without - with, in percentage points.\n\n" + "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sweep", required=True, help="a trained-run sweep folder (its cases/ with run_shading/)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = sweep_truth_gains(args.sweep)
    if not rows:
        raise ValueError(f"{args.sweep}: no finished case with run/ and run_shading/ under cases/")
    df = pd.DataFrame(rows)
    out = Path(args.sweep)
    with atomic_path(out / "truth_gain.csv") as tmp:
        df.to_csv(tmp, index=False)
    with atomic_path(out / "truth_gain.md") as tmp:
        tmp.write_text(truth_markdown(df))
    print(truth_markdown(df))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
