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

import re
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
    ``absolute`` (the authors' choice; needed when the folder is renamed into another parent)."""
    import os

    recording = stream.absolute().parent
    for name in (TRAJECTORY_FILE, POINTS_FILE):
        link, target = stream / name, (mps_dir / name).absolute()
        if not target.is_file():
            raise FileNotFoundError(f"{target}: MPS file not found (needed in {stream})")
        inside = target.is_relative_to(recording) and not absolute
        if link.is_symlink() or link.exists():
            link.unlink()
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
