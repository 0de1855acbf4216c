"""Run checkpoints: ``checkpoint.pt`` written atomically, read without executing code
(`read_checkpoint`: torch.load with weights_only=True, a checkpoint is tensors, numbers, strings and
containers, and a truncated, foreign or tampered file is a one-line ValueError naming the file),
matched against a method and config for ``--resume auto``, and loaded as a trained model for
evaluation and diagnosis (`load_trained_run`)."""

from __future__ import annotations

import pickle
import re
import struct
import sys
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from egobench.camera.pinhole import Pinhole
from egobench.data.reader import recording_from_args
from egobench.io_utils import atomic_path, read_json
from egobench.model.methods import MethodSpec, get_method
from egobench.model.predict import gaussians_from_params
from egobench.train.config import TrainConfig

CHECKPOINT_FORMAT = "egobench.checkpoint/1"


def read_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict at ``path`` (tensors on the CPU); ValueError if unreadable or not a dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError,
            AttributeError, TypeError, KeyError, IndexError, struct.error) as exc:
        raise ValueError(f"{path}: unreadable checkpoint: {_why_unreadable(path, exc)}; delete it and train again") from None
    if not isinstance(ck, dict):
        raise ValueError(f"{path}: unreadable checkpoint: expected a dict of tensors, got {type(ck).__name__}")
    return ck


def _why_unreadable(path: Path, exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused ``path``: code refused, or not a checkpoint at all."""
    text = str(exc)
    if re.search(r"\bGLOBAL\b|allowed global|Unsupported global", text):
        return "it holds objects other than tensors and plain containers (refused: loading it could run code)"
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    detail = next((ln for ln in lines if ln.startswith(("Unsupported", "invalid load key"))), lines[0] if lines else "")
    with open(path, "rb") as fh:
        head = fh.read(2)
    kind = ("a zip archive" if head == b"PK" or zipfile.is_zipfile(path) else
            "a pickle stream" if head[:1] == b"\x80" else None)
    what = f"{kind} that is truncated or corrupt" if kind else "neither a torch zip archive nor a pickle (foreign bytes)"
    return f"not a checkpoint: {what} ({type(exc).__name__}: {detail[:160]})"


def read_run_checkpoint(path: str | Path) -> dict:
    """The training checkpoint at ``path`` (read safely by `read_checkpoint`).
    FileNotFoundError if it is missing; ValueError naming the file if it cannot be read or is not an
    egobench training checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint (train the run first)")
    ck = read_checkpoint(path)
    if ck.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not an egobench checkpoint (format {ck.get('format')!r}, "
                         f"expected {CHECKPOINT_FORMAT!r})")
    return ck


def write_checkpoint(path: Path, state: dict) -> None:
    """Write ``state`` (a dict with ``format`` = CHECKPOINT_FORMAT) atomically."""
    with atomic_path(path) as tmp:
        torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)


def checkpoint_matches(path: Path, method: str, config: TrainConfig) -> bool:
    """True when ``path`` holds a resumable checkpoint of ``method`` with this exact config; an
    unreadable one or one of another run is reported on stderr (the caller starts afresh)."""
    if not path.is_file():
        return False
    try:
        ck = read_run_checkpoint(path)
    except ValueError as exc:
        print(f"egobench train: {exc}; starting afresh", file=sys.stderr)
        return False
    same = ck.get("method") == method and ck.get("config_hash") == config.hash(method)
    if not same:
        print(f"egobench train: {path}: checkpoint of another method or config; starting afresh", file=sys.stderr)
    return same


def resumable_checkpoint(path: Path, method: str, config: TrainConfig) -> dict:
    """The checkpoint to resume ``method`` with ``config`` from; a named error when it is of another run."""
    ck = read_run_checkpoint(path)
    if ck.get("method") != method:
        raise ValueError(f"{path}: checkpoint is for method {ck.get('method')!r}, not {method!r}")
    if ck.get("config_hash") != config.hash(method):
        raise ValueError(f"{path}: checkpoint was written with a different training config; resume needs the same")
    return ck


def config_of(ck: dict) -> TrainConfig:
    """The `TrainConfig` a checkpoint was trained with."""
    cfg = dict(ck["config"])  # a field added after the run was trained takes its default
    cfg["background"] = tuple(cfg["background"])
    return TrainConfig(**cfg)


@dataclass
class TrainedRun:
    """A trained run loaded for rendering (evaluation, diagnosis)."""

    path: Path  # the run folder
    checkpoint: dict
    spec: MethodSpec
    config: TrainConfig  # the training config, ``device`` set to where it renders now
    camera: Pinhole  # the training-resolution camera
    gaussians: object  # `Gaussians` on ``config.device``


def load_trained_run(run_dir: str | Path, device: str | None, where: str) -> TrainedRun:
    """The run in ``run_dir`` ready to render on ``device`` (default: its training device,
    `render_device`); ``where`` names the caller in errors."""
    run_dir = Path(run_dir)
    ck = read_run_checkpoint(run_dir / "checkpoint.pt")
    config = config_of(ck)
    dev = render_device(device, config.device, where)
    c = ck["camera"]
    camera = Pinhole(fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"], width=c["w"], height=c["h"])
    gaussians = gaussians_from_params({k: v.detach() for k, v in ck["params"].items()}).to(dev)
    return TrainedRun(path=run_dir, checkpoint=ck, spec=get_method(ck["method"]),
                      config=replace(config, device=str(dev)), camera=camera, gaussians=gaussians)


def check_run_complete(run_dir: str | Path, ck: dict) -> None:
    """A run folder is complete when its checkpoint ran every iteration of its config and its
    train.json describes that checkpoint (method, seed, config hash, iterations); otherwise a
    ValueError says what is missing or disagrees (a killed or overwritten run is never evaluated)."""
    run_dir = Path(run_dir)
    it, total = int(ck.get("iteration", -1)), int(ck.get("config", {}).get("iterations", -1))
    if it < total:
        raise ValueError(f"{run_dir}: incomplete run: checkpoint.pt stopped at iteration {it} of {total} "
                         "(training was interrupted); finish it with `egobench train ... --resume`")
    rec_path = run_dir / "train.json"
    if not rec_path.is_file():
        raise ValueError(f"{run_dir}: incomplete run: checkpoint.pt has no train.json beside it (training did "
                         "not finish writing its record); train again with `--resume auto`")
    rec = read_json(rec_path)
    theirs = {"method": rec.get("method"), "seed": rec.get("seed"), "config_hash": rec.get("config_hash"),
              "iterations": (rec.get("train") or {}).get("iterations")}
    ours = {"method": ck.get("method"), "seed": ck.get("config", {}).get("seed"),
            "config_hash": ck.get("config_hash"), "iterations": it}
    differ = [f"{k} {theirs[k]!r} (train.json) vs {ours[k]!r} (checkpoint.pt)" for k in ours if theirs[k] != ours[k]]
    if differ:
        raise ValueError(f"{run_dir}: train.json and checkpoint.pt describe different runs ({'; '.join(differ)}); "
                         "a stale record: train the run again")


def recording_for_run(run_dir: str | Path, args) -> object:
    """A verb's ``--recording`` for the run in ``run_dir``: the path as given, or, with --trajectory
    or --points, the recording loaded with them in the run's calibration."""
    if not (getattr(args, "trajectory", None) or getattr(args, "points", None)):
        return args.recording
    method = read_run_checkpoint(Path(run_dir) / "checkpoint.pt")["method"]
    return recording_from_args(args.recording, get_method(method).calibration, args)


def render_device(requested: str | None, trained_on: str, where: str) -> torch.device:
    """The torch device to render a checkpoint on: ``requested`` (``--device``) or else the run's
    training device (``config.device``). Raises a ValueError naming ``where`` when that is a CUDA
    device and this torch has no CUDA (a GPU-trained run evaluated on a CPU machine needs --device cpu)."""
    name = requested if requested else trained_on
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"{where}: device {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        origin = "requested" if requested else "the run's training device (config.device)"
        raise ValueError(f"{where}: device {name!r} is {origin}, but CUDA is not available here; "
                         "pass --device cpu (device='cpu') to render on the CPU")
    return device
