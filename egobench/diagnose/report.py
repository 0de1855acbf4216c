"""The diagnosis outputs: diagnosis.json (schema egobench.diagnosis/1), report.md and figures
(residual maps before/after the extension, one signature plot per candidate cause)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from egobench.diagnose.core import Diagnosis
from egobench.diagnose.learned_frames import frames_markdown
from egobench.diagnose.learned_timing import timing_markdown
from egobench.effects import EFFECTS
from egobench.io_utils import atomic_path, write_json
from egobench.residual.estimation import CauseResult

LEVELS = 255.0


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if not math.isfinite(x):
            return "-"
        return f"{x:.{digits}g}"
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_fmt(v, 3) for v in x[:6]) + (", ..." if len(x) > 6 else "") + "]"
    return str(x)


def _summary(params: dict) -> str:
    skip = {"first_order_estimate", "frame_scale", "sign", "log_shading_r2_r4", "or"}
    return "; ".join(f"{k}={_fmt(v)}" for k, v in params.items() if k not in skip)


def save_png(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)


def residual_maps(path: Path, measured: np.ndarray, predicted: np.ndarray, extended: np.ndarray | None,
                  frames: list[int], labels: list[int]) -> None:
    """Measured, predicted, residual before and after the extension, for a few frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 4 if extended is not None else 3
    fig, axes = plt.subplots(len(frames), cols, figsize=(2.6 * cols, 2.6 * len(frames)), squeeze=False)
    for row, (f, lab) in enumerate(zip(frames, labels)):
        res0 = (measured[f] - predicted[f]).mean(-1)
        panels = [(measured[f], f"measured #{lab}"), (predicted[f], "predicted"), (res0, "residual")]
        if extended is not None:
            panels.append(((measured[f] - extended[f]).mean(-1), "residual, extended"))
        for ax, (img, title) in zip(axes[row], panels):
            if img.ndim == 3:
                ax.imshow(np.clip(img, 0, 1))
            else:
                ax.imshow(img, cmap="RdBu_r", vmin=-0.08, vmax=0.08)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    save_png(fig, path)


def signature_plot(path: Path, result: CauseResult) -> None:
    """The cause's signature: what its statistic looks at, with the fitted model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = result.plot
    fig, ax = plt.subplots(figsize=(4.2, 3.0))
    title = f"{result.name}: p_adj={result.p_adjusted:.2g}, effect={result.effect_rms * LEVELS:.2f} levels"
    if not result.testable:
        ax.text(0.5, 0.5, f"not testable:\n{result.reason}", ha="center", va="center", fontsize=8)
        ax.axis("off")
    elif not EFFECTS[result.name].plot_signature(ax, p):  # time offset, blur: per-frame estimates vs image speed
        ax.plot(p.get("speed_px_s", []), p.get("per_frame", []), "o", label="per frame")
        ax.axhline(p.get("pooled", 0.0), color="k", lw=1, label="pooled")
        ax.set_xlabel("mean image speed (px/s)"), ax.set_ylabel("per-frame estimate"), ax.legend(fontsize=7)
    ax.set_title(title, fontsize=8)
    save_png(fig, path)


def lens_check_lines(check: dict | None) -> list[str]:
    """The lens check of a trained run (`egobench.diagnose.lens_check`), one line, or none."""
    if not check:
        return []
    if check.get("injected_k0") is None:
        return [f"- lens check: {check.get('reason', 'not made')}; a lens is not testable on this run"]
    kept = "not measurable" if check.get("retention") is None else f"{100 * check['retention']:.0f} %"
    size = (f" ({check['multiple']:g} x the smallest testable, {check['smallest_testable_k0']:.4f})"
            if check.get("smallest_testable_k0") is not None and check.get("multiple") else "")
    return [f"- lens check: trained again on the recording warped by a k0 error of {check['injected_k0']:+.4f}{size}, "
            f"the run keeps {kept} of it (k0 {check['k0_run']:+.4f} on the run, {check['k0_warped']:+.4f} warped, "
            f"{check['k0_retrained']:+.4f} retrained); a lens is {'testable' if check['testable'] else 'not testable'} "
            f"on this run (from {100 * check['floor']:.0f} %)"]


def model_error_markdown(me: dict, config) -> list[str]:
    """The trained-run section: how much of the residual is the model's own error, and what is testable."""
    lines = ["## Trained run: reconstruction error versus physics", "",
             f"- held-out PSNR {me['held_out_psnr_db']:.2f} dB (their neighbouring training views "
             f"{me['training_view_psnr_db']:.2f} dB, all training views {me.get('all_training_views_psnr_db', math.nan):.2f} dB); "
             f"the assumed sensor noise alone would give {me['noise_only_psnr_db']:.2f} dB",
             f"- model error left after the named causes: {me['model_error_psnr_db']:.2f} dB PSNR, "
             f"{me['model_error_over_noise_db']:+.1f} dB relative to the noise; non-physical share of the held-out "
             f"residual {100 * me['non_physical_share']:.1f} %; share of the model error explained by the named causes "
             f"{100 * me['share_explained_by_named_causes']:.1f} %",
             *lens_check_lines(me.get("lens_check")),
             f"- reconstruction error dominates: {'yes' if me['dominates'] else 'no'} ({me['rule']})",
             f"- naming rules on a trained run: placebo-calibrated p (exposure metadata: split-half frame-label "
             f"shuffles; response: per-frame scale vs permuted exposure metadata; vignette: frames as units and "
             f"wrong-centre placebos; timing: permuted velocity fields, readout also wrong row times; white balance: "
             f"not identifiable, absorbed "
             f"into the scene colours), a held-out gain positive beyond its spread over the held-out frames (one-sided "
             f"t-test at alpha; a cause with one parameter "
             f"per frame, exposure metadata: a positive gain on every frame's odd pixels, each frame's scale from its even "
             f"ones)", "",
             "| cause | smallest effect testable on this run (of what training left in the residual) "
             "| smallest hidden effect testable (over the retention of a trained sweep, `--retention`) |",
             "|---|---|---|"]
    hidden = me.get("smallest_testable_hidden", {})
    for name, v in me.get("smallest_testable", {}).items():
        h = hidden.get(name)
        cell = "-" if h is None else (f"not testable (retention {h['retention']:.2f})" if not h["testable"] else
                                      _summary({k: x for k, x in h.items() if k != "testable"}))
        lines.append(f"| {name} | {_summary(v)} | {cell} |")
    return lines + [""]


def identifiability_markdown(d: Diagnosis) -> list[str]:
    """Before any name: for every cause, whether this recording can show it (round 1's testability and
    its reason), the smallest effect it could reveal, and when a recording can show it at all
    (`Effect.identifiability`)."""
    smallest = (d.model_error or {}).get("smallest_testable", {})
    lines = ["## Identifiability on this recording (before any name)", "",
             "| cause | can this recording show it | smallest effect it could reveal | when a recording can show it |",
             "|---|---|---|---|"]
    for r in d.ranking:
        shown = "yes" if r.testable else f"no: {r.reason}"
        small = "; ".join(f"{k}={_fmt(v)}" for k, v in smallest.get(r.name, {}).items()) or "-"
        rule = EFFECTS[r.name].identifiability if r.name in EFFECTS else ""
        lines.append(f"| {r.name} | {shown} | {small} | {rule} |")
    return lines + [""]


def _testable(d: Diagnosis) -> int:
    """How many causes round 1 tested (Holm's m there)."""
    return sum(r.testable for r in d.rounds[0]) if d.rounds else 0


def markdown(d: Diagnosis, title: str) -> str:
    lines = [f"# {title}", ""]
    lines.append(f"**Verdict: {d.verdict}**" + (f" (p_adj {d.named[0].p_adjusted:.2g})" if d.named else ""))
    lines += ["", f"- held-out frames {d.held_out_frames}: PSNR {d.baseline_psnr_db:.2f} dB -> "
              f"{d.extended_psnr_db:.2f} dB (gain {d.psnr_gain_db:+.2f} dB, odd-checkerboard pixels)",
              f"- runtime {d.runtime_s:.1f} s; alpha {d.config.alpha} (Holm over the {_testable(d)} testable causes of round 1); "
              f"effect floor {d.config.effect_floor * LEVELS:.2f} levels",
              f"- photometric cells trimmed as off-model content (round 1): {100 * d.unmodelled_fraction:.1f} %", ""]
    lines += identifiability_markdown(d)
    if d.model_error is not None:
        lines += model_error_markdown(d.model_error, d.config)
    if d.named:
        lines += ["## Named causes (peeled in order)", "", "| round | cause | p_adj | effect (levels) | estimate | held-out gain |",
                  "|---|---|---|---|---|---|"]
        for n in d.named:
            gain = f"{n.psnr_gain_db:+.2f} dB" if n.nll_gain_nats_per_px is None else f"NLL {n.nll_gain_nats_per_px:+.3f} nats/px"
            lines.append(f"| {n.round} | {n.name} | {n.p_adjusted:.2g} | {n.effect_rms * LEVELS:.2f} | {_summary(n.params)} | {gain} |")
        lines.append("")
        lines += [f"- {n.name}, or {a['cause']} ({_or_p(a)}): {a['note']}" for n in d.named for a in n.params.get("or", [])]
    lines += ["## Ranking (round 1)", "", "| cause | statistic | p | p_adj (Holm) | effect (levels) | significant | estimate |",
              "|---|---|---|---|---|---|---|"]
    for r in d.ranking:
        if not r.testable:
            lines.append(f"| {r.name} | - | - | - | - | untestable: {r.reason} | - |")
            continue
        lines.append(f"| {r.name} | {r.statistic_kind}={r.statistic:.3g} | {r.p_value:.2g} | {r.p_adjusted:.2g} | "
                     f"{r.effect_rms * LEVELS:.2f} | {'yes' if r.significant else 'no'} | {_summary(r.params)} |")
    lines += ["", "Figures: `figures/residual_maps.png`, `figures/signature_<cause>.png`.", ""]
    return "\n".join(lines)


def shading_markdown(x: dict) -> str:
    """The report.md section of the model extension's call (`egobench.diagnose.extension.judge_shading`)."""
    head = (f"Learned corner attenuation {x['learned_corner_attenuation']:.3f}; the {x['n_null']} sweep nulls learn "
            f"{x['null_mean']:.3f} +- {x['null_sd']:.3f} (threshold {x['threshold']:.3f} = mean + "
            f"{x['sigmas']:.0f} sd, {x['null_source']}).")
    call = (f"Called: a lens shading beyond the stated vignette, {x['estimate']:.3f} at the view's corner "
            f"(learned - null mean)." if x["above_threshold"] else "Not called: within the nulls.")
    gain = x.get("held_out")
    if gain:
        call += (f" Held-out PSNR {gain['base_psnr_db']:.2f} dB without the learned shading, "
                 f"{gain['extension_psnr_db']:.2f} dB with it (gain {gain['gain_db']:+.2f} dB).")
    notes = "".join(f"\n- {n}" for n in x["notes"])
    return f"\n## Model extension: a learned lens shading\n\n{head}\n\n{call}\n{notes}\n"


def write_report(out_dir: str | Path, d: Diagnosis, measured: np.ndarray, predicted: np.ndarray,
                 title: str = "Residual diagnosis", extra: dict | None = None,
                 shading_extension: dict | None = None, learned_timing: dict | None = None,
                 learned_frames: dict | None = None) -> dict:
    """Write diagnosis.json, report.md and figures/ into out_dir; return the JSON record
    (``shading_extension``: the model extension's call, `egobench.diagnose.extension.judge_shading`;
    ``learned_timing``: the timing a run learned with its scene, `egobench.diagnose.learned_timing.judge_timing`;
    ``learned_frames``: its per-frame values, `egobench.diagnose.learned_frames.judge_learned_frames`)."""
    out = Path(out_dir)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    record = d.to_dict()
    if extra:
        record["extra"] = extra
    if shading_extension is not None:
        record["shading_extension"] = shading_extension
    if learned_timing is not None:
        record["learned_timing"] = learned_timing
    if learned_frames is not None:
        record["learned_frames"] = learned_frames
    write_json(out / "diagnosis.json", record)
    text = markdown(d, title)
    if shading_extension is not None:
        text += shading_markdown(shading_extension)
    if learned_timing is not None:
        text += timing_markdown(learned_timing)
    if learned_frames is not None:
        text += frames_markdown(learned_frames)
    if extra:
        text += "\n## Extra\n\n```json\n" + json.dumps(extra, indent=1, default=str)[:6000] + "\n```\n"
    with atomic_path(out / "report.md") as tmp:
        tmp.write_text(text)
    index = {int(i): k for k, i in enumerate(np.asarray(d.meta.get("frame_index", range(measured.shape[0]))))}
    held = [index[f] for f in d.held_out_frames if f in index][:3] or [0]
    residual_maps(out / "figures" / "residual_maps.png", measured, predicted, d.extended_prediction, held,
                  [d.held_out_frames[i] if i < len(d.held_out_frames) else h for i, h in enumerate(held)])
    for r in (d.rounds[0] if d.rounds else []):
        signature_plot(out / "figures" / f"signature_{r.name}.png", r)
    return record


def _or_p(alternative: dict) -> str:
    """A containing cause's p_adj as the report prints it ("untested" where it could not be tested)."""
    p = alternative.get("p_adjusted")
    return "untested" if p is None else f"p_adj {p:.2g}"
