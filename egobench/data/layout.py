"""Where a recording's files lie: the authors' preprocessed layout (one format for real and simulated data).

As facebookresearch/egocentric_splats writes it (``scripts/extract_aria_vrs.py``) and reads it
(``scene/dataset_readers.py``)::

    <scene>/recording.vrs                      raw Aria recording (input of `egobench preprocess`)
    <scene>/mps/slam/                          MPS output: closed_loop_trajectory.csv, semidense_points.csv.gz,
                                               semidense_observations.csv.gz, online_calibration.jsonl, summary.json
    <scene>/<vrs name>/<label>-rectified-<focal>-h<size>/                 online (VIBA) calibration
    <scene>/<vrs name>/<label>-rectified-<focal>-h<size>-factory-calib/   factory calibration ("w/o VIBA")

A rectified stream folder holds ``images/``, ``transforms.json``, ``transforms_with_sparse_depth.json``
(per-frame ``sparse_depth``: a path to ``sparse_depth/<label>_<timestamp>.json``), ``vignette.png``,
``mask.png``, ``image_index.png`` and, inside the folder (symlinks), ``closed_loop_trajectory.csv``
and ``semidense_points.csv.gz``. egobench's simulated recordings use the same layout, plus
``recording.json``, ``ground_truth/`` and ``factory_calibration.json`` at the recording level
and ``row_time_ratio.npy`` (full-precision ``image_index.png``) in each stream folder.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

TRANSFORMS = "transforms.json"
TRANSFORMS_WITH_DEPTH = "transforms_with_sparse_depth.json"
TRAJECTORY_FILE = "closed_loop_trajectory.csv"
POINTS_FILE = "semidense_points.csv.gz"
OBSERVATIONS_FILE = "semidense_observations.csv.gz"
ONLINE_CALIBRATION_FILE = "online_calibration.jsonl"
FACTORY_SUFFIX = "-factory-calib"
#: egobench's simulated recordings: the factory calibration (a real one lies in the VRS), at the recording level.
FACTORY_CALIBRATION_FILE = "factory_calibration.json"
MPS_SLAM = Path("mps") / "slam"
#: Frames whose centre timestamp lies within this of either end of the trajectory are dropped (authors' reader).
TRAJECTORY_END_MARGIN_NS = 1_000_000
_STREAM_NAME = re.compile(r"^(?P<label>.+)-rectified-(?P<focal>\d+)-h(?P<size>\d+)(?P<factory>-factory-calib)?$")


def stream_folder_name(camera_label: str, focal_px: float, size_px: int, factory: bool = False) -> str:
    """``<label>-rectified-<int(focal)>-h<size>[-factory-calib]`` (the authors' naming)."""
    return f"{camera_label}-rectified-{int(focal_px)}-h{int(size_px)}" + (FACTORY_SUFFIX if factory else "")


def transforms_file(folder: Path) -> Path | None:
    """The transforms file training reads: ``transforms_with_sparse_depth.json``, else ``transforms.json``."""
    for name in (TRANSFORMS_WITH_DEPTH, TRANSFORMS):
        if (folder / name).is_file():
            return folder / name
    return None


def is_stream(folder: Path) -> bool:
    return folder.is_dir() and transforms_file(folder) is not None


def stream_calibration(folder: Path) -> str:
    """'factory' when the folder name carries the authors' ``-factory-calib`` suffix, else 'online'."""
    return "factory" if folder.name.endswith(FACTORY_SUFFIX) else "online"


def variant_path(folder: Path, calibration: str) -> Path:
    """The sibling stream folder of the other calibration, by the authors' naming."""
    base = folder.name[: -len(FACTORY_SUFFIX)] if folder.name.endswith(FACTORY_SUFFIX) else folder.name
    return folder.parent / (base + (FACTORY_SUFFIX if calibration == "factory" else ""))


def recording_root(path: str | Path) -> Path:
    """The recording folder of ``path``: the parent of a stream folder, else ``path`` itself."""
    path = Path(path)
    return path.parent if is_stream(path) else path


def link_mps_files(stream: Path, mps_dir: Path, absolute: bool = False) -> None:
    """Put closed_loop_trajectory.csv and semidense_points.csv.gz inside a stream folder as symlinks
    to the MPS files: relative when the MPS folder lies inside the recording (it can move) unless
    ``absolute`` (the authors' choice; needed when the folder is renamed into another parent). An
    MPS folder that is not ``mps/slam/`` of the capture (`check_stream_input`'s rule) is copied."""
    recording = stream.absolute().parent
    for name in (TRAJECTORY_FILE, POINTS_FILE):
        link, target = stream / name, (mps_dir / name).absolute()
        if not target.is_file():
            raise FileNotFoundError(f"{target}: MPS file not found (needed in {stream})")
        inside = target.is_relative_to(recording) and not absolute
        if link.is_symlink() or link.exists():
            link.unlink()
        if not any(resolves_inside(target, base) for base in _mps_dirs(stream)):
            shutil.copyfile(target, link)
            continue
        link.symlink_to(os.path.relpath(target, stream.absolute()) if inside else target)


def _streams_under(root: Path) -> list[Path]:
    """Rectified stream folders directly under ``root``, else one level deeper (``<scene>/<vrs name>/``)."""
    found = sorted(d for d in root.iterdir() if _STREAM_NAME.match(d.name) and is_stream(d))
    if not found:
        for sub in sorted(d for d in root.iterdir() if d.is_dir()):
            found += sorted(d for d in sub.iterdir() if _STREAM_NAME.match(d.name) and is_stream(d))
    return found


def find_stream(path: str | Path, calibration: str) -> Path:
    """The rectified stream folder of ``calibration`` for ``path`` (a stream folder, a recording or a scene folder).

    A stream folder of the other calibration leads to its sibling by the authors' naming; asking
    for a calibration that is not there is a ValueError naming the folder that was expected.
    """
    if calibration not in ("online", "factory"):
        raise ValueError(f"calibration: expected 'online' or 'factory', got {calibration!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: recording folder not found")
    if is_stream(path):
        if stream_calibration(path) == calibration:
            return path
        other = variant_path(path, calibration)
        if is_stream(other):
            return other
        flag = "with" if calibration == "factory" else "without"
        raise ValueError(
            f"{path}: holds the {stream_calibration(path)!r} calibration (the authors' naming: a "
            f"'{FACTORY_SUFFIX}' suffix marks the factory one); the {calibration!r} calibration was asked, "
            f"but {other} is not there (run `egobench preprocess` {flag} --factory-calibration)"
        )
    if not path.is_dir():
        raise ValueError(f"{path}: expected a recording folder, got a file")
    streams = _streams_under(path)
    match = [s for s in streams if stream_calibration(s) == calibration]
    if len(match) == 1:
        return match[0]
    if len(match) > 1:
        raise ValueError(f"{path}: several {calibration!r} streams ({', '.join(s.name for s in match)}); "
                         "pass the stream folder itself")
    if streams:
        raise ValueError(f"{path}: no {calibration!r}-calibration stream; found only "
                         f"{', '.join(f'{s.name} ({stream_calibration(s)})' for s in streams)}")
    if (path / "online" / TRANSFORMS).is_file():
        raise ValueError(f"{path}: an old egobench layout (online/, factory/); simulate it again with this version")
    raise ValueError(
        f"{path}: no rectified stream folder (<camera label>-rectified-<focal>-h<size>[{FACTORY_SUFFIX}] "
        f"holding {TRANSFORMS_WITH_DEPTH} or {TRANSFORMS}) here or one level below"
    )


# ----------------------------------------------------------------------------------------
# what a recording may make egobench read
# ----------------------------------------------------------------------------------------
#: The rule (docs/robustness.md): a recording names files only inside itself. Paths in its JSON
#: (image_path, mask_path, sparse_depth) are relative, without '..', and resolve (symlinks
#: followed) inside the stream folder; the stream folder's closed_loop_trajectory.csv and
#: semidense_points.csv.gz are files in it or symlinks into ``mps/slam/`` of the same capture
#: (the stream folder's parent or grandparent, as the authors' preprocessing links them).
#: Files passed explicitly (--trajectory, --points) are the user's choice and are not confined.


def resolves_inside(path: Path, base: Path) -> bool:
    """Whether ``path`` (symlinks followed) lies inside ``base``."""
    return path.resolve().is_relative_to(base.resolve())


def _mps_dirs(stream: Path) -> list[Path]:
    """Where a stream folder's MPS links may point: ``mps/slam/`` of its parent or grandparent."""
    real = stream.resolve()
    return [real.parent / MPS_SLAM, real.parent.parent / MPS_SLAM]


def stream_file(folder: Path, value: object, where: str, key: str) -> Path:
    """``folder / value`` for a path a recording's JSON names; ValueError unless ``value`` is a
    relative path that stays inside ``folder`` (no absolute path, no '..', no symlink leading out)."""
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"{where}: field {key!r} must be a non-empty relative path (a string), got {value!r}")
    rel = Path(value)
    if any(len(part.encode("utf-8", "surrogatepass")) > 255 for part in rel.parts):
        raise ValueError(f"{where}: field {key!r} = {value[:40]!r}... is not a file name (a part over 255 bytes)")
    if rel.is_absolute() or ".." in rel.parts or "\x00" in value:
        raise ValueError(f"{where}: field {key!r} = {value!r} is refused: a recording may only name files inside "
                         f"its stream folder {folder} (a relative path without '..')")
    path = folder / rel
    if not resolves_inside(path, folder):
        raise ValueError(f"{where}: field {key!r} = {value!r} is a symlink leading to {path.resolve()}, outside the "
                         f"stream folder {folder}; refused (a recording may only name files inside itself)")
    return path


def check_stream_input(stream: Path, path: Path, what: str) -> Path:
    """``path`` (a file the stream folder holds: a camera map or an MPS file) if it resolves inside
    the stream folder or, for the MPS files, into ``mps/slam/`` of the capture; else ValueError."""
    allowed = [stream] + (_mps_dirs(stream) if path.name in (TRAJECTORY_FILE, POINTS_FILE, OBSERVATIONS_FILE) else [])
    if not any(resolves_inside(path, base) for base in allowed):
        raise ValueError(f"{path}: {what} resolves to {path.resolve()}, outside the recording; refused (a stream "
                         f"folder's files must lie in it, and its MPS links point into mps/slam/ of the same "
                         f"capture: {', '.join(str(b) for b in allowed[1:]) or 'none'})")
    return path
