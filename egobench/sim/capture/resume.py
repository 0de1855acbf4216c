"""Interruption and resumption: the partial folder, the per-frame state files, the config hash."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import torch

import egobench
from egobench.data.layout import stream_folder_name
from egobench.io_utils import read_json
from egobench.sim.config import SimConfig
from egobench.sim.devices import get_device

if TYPE_CHECKING:  # annotations only (these modules are imported lazily)
    pass


# ----------------------------------------------------------------------------------------
# interruption and resumption (the partial folder)
# ----------------------------------------------------------------------------------------
#: Schema of the partial folder's manifest (`<partial>/.resume/partial.json`).
PARTIAL_SCHEMA = "egobench.sim.partial/1"
#: Folder inside the partial folder: the manifest and one state file per completed frame.
RESUME_SUBDIR = ".resume"


def stream_names(config: SimConfig) -> dict[str, str]:
    """calibration -> rectified stream folder name, by the authors' naming (egobench.data.layout)."""
    dev = get_device(config.device_name)
    focal = config.focal_ratio() * config.rectified_size
    return {name: stream_folder_name(dev.label, focal, config.rectified_size, factory=name == "factory")
            for name in ("online", "factory")}


def frame_dirs(config: SimConfig) -> tuple[str, ...]:
    """Folders holding one file per frame, named NNNNN.<ext> (frames past the last state file are removed on resume)."""
    streams = tuple(f"{d}/{sub}" for d in stream_names(config).values() for sub in ("images", "sparse_depth"))
    return ("raw",) + streams + ("ground_truth/radiance", "ground_truth/depth", "ground_truth/normal")


def partial_dir(out_dir: str | Path) -> Path:
    """The hidden folder `out_dir` is built in: `<parent>/.<name>.partial` (kept when interrupted)."""
    out_dir = Path(out_dir)
    return out_dir.parent / f".{out_dir.name}.partial"


def sim_config_hash(config: SimConfig) -> str:
    """sha1 (hex) of the canonical SimConfig (`to_dict`, sorted keys) and the egobench version."""
    blob = json.dumps({"sim_config": config.to_dict(), "egobench_version": egobench.__version__}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()


def frame_state_path(partial: Path, k: int) -> Path:
    return partial / RESUME_SUBDIR / f"{k:05d}.json"


def read_partial(partial: Path, config_hash: str) -> tuple[list[dict], str | None]:
    """-> (state records of the completed frames 0..m-1 in order, None), or ([], why the partial
    folder cannot be resumed). Frame m is the first without a readable state file of this config."""
    manifest = partial / RESUME_SUBDIR / "partial.json"
    try:
        meta = read_json(manifest)
    except (FileNotFoundError, ValueError) as exc:
        return [], f"no readable manifest ({exc})"
    if not isinstance(meta, dict) or meta.get("schema") != PARTIAL_SCHEMA:
        return [], f"{manifest}: field 'schema' is not {PARTIAL_SCHEMA!r}"
    if meta.get("config_hash") != config_hash:
        return [], (f"it was written for a different SimConfig or egobench version (config hash "
                    f"{str(meta.get('config_hash'))[:12]}, egobench {meta.get('egobench_version')}; "
                    f"this run: {config_hash[:12]})")
    states: list[dict] = []
    while True:
        path = frame_state_path(partial, len(states))
        if not path.is_file():
            break
        try:
            st = read_json(path)
        except ValueError:
            break
        if not isinstance(st, dict) or st.get("frame") != len(states) or st.get("config_hash") != config_hash:
            break
        states.append(st)
    return states, None


def drop_frames_from(partial: Path, first: int, dirs: tuple[str, ...]) -> None:
    """Remove the per-frame files and state files of frames >= `first` (half-written or stale) and
    the temporary files an interrupted atomic write left anywhere in the partial folder."""
    for sub in dirs + (RESUME_SUBDIR,):
        folder = partial / sub
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            stem = f.name.split(".", 1)[0]
            if f.is_file() and stem.isdigit() and int(stem) >= first:
                f.unlink()
    for f in partial.rglob(".*.tmp*"):
        if f.is_file():
            f.unlink()


def encode_generator(generator: torch.Generator) -> str:
    return base64.b64encode(generator.get_state().numpy().tobytes()).decode("ascii")


def decode_generator(generator: torch.Generator, text: str) -> None:
    generator.set_state(torch.frombuffer(bytearray(base64.b64decode(text)), dtype=torch.uint8).clone())


def finalise(partial: Path, out_dir: Path) -> None:
    """Drop the resume state and move the finished partial folder onto `out_dir` (replacing it)."""
    state = partial / RESUME_SUBDIR
    trash = out_dir.parent / f".{out_dir.name}.partial-state.tmp"
    if trash.exists():
        shutil.rmtree(trash)
    if state.exists():
        os.replace(state, trash)  # one rename: the partial folder is never without its manifest for long
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(partial, out_dir)
    if trash.exists():
        shutil.rmtree(trash)
