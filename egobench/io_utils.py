"""Writing files safely: atomic writes (an interrupted job never leaves a half-written file behind), a full
disk as one named error, and one writer per run folder."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import inspect
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

#: errno values that mean "the filesystem has no room" (a full disk, a used-up quota)
NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
#: how torch's checkpoint writer reports a short write (it raises RuntimeError, not OSError)
_TORCH_SHORT_WRITE = ("unexpected pos", "file write failed", "No space left on device")
#: the lock file of a run folder (`run_folder_lock`)
LOCK_NAME = ".egobench.lock"


class DiskFullError(OSError):
    """A write ran out of space; the message names the file, the filesystem and the space (one line)."""


class RunFolderBusy(RuntimeError):
    """Another egobench process holds the run folder (`run_folder_lock`)."""


def _mount_point(path: Path) -> Path:
    path = path.resolve()
    while not os.path.ismount(path) and path != path.parent:
        path = path.parent
    return path


def _size(n: int) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def no_space_message(path: str | os.PathLike, written: int | None = None) -> str:
    """One line: the file, its filesystem (mount point, free of total) and what the write had reached."""
    path = Path(path)
    where = path.parent if not path.is_dir() else path
    while not where.exists() and where != where.parent:
        where = where.parent
    usage = shutil.disk_usage(where)
    reached = f"; the write had reached {_size(written)} and needs more" if written else ""
    return (f"{path}: no space left on the filesystem at {_mount_point(where)} ({_size(usage.free)} free of "
            f"{_size(usage.total)}){reached}: free some space or write elsewhere")


def is_disk_full(exc: BaseException) -> bool:
    """An OSError of a full disk or quota, or torch's short-write RuntimeError."""
    if isinstance(exc, OSError):
        return exc.errno in NO_SPACE_ERRNOS
    return isinstance(exc, RuntimeError) and any(t in str(exc) for t in _TORCH_SHORT_WRITE)


#: free bytes below which a writer that reports no error of its own (OpenCV) is taken to have run out of space
NEARLY_FULL_BYTES = 64 * 1024


def check_written(path: str | os.PathLike, tmp: Path, ok: bool = True, what: str = "file") -> None:
    """After a writer that reports failure only as a flag (``cv2.imwrite``) or not at all (``cv2.VideoWriter``):
    `DiskFullError` naming ``path`` when the filesystem is (nearly) full, else ValueError when ``ok`` is false."""
    if shutil.disk_usage(tmp.parent).free < NEARLY_FULL_BYTES:
        full = DiskFullError(no_space_message(path, tmp.stat().st_size if tmp.exists() else None))
        full.errno = errno.ENOSPC
        raise full
    if not ok:
        raise ValueError(f"{path}: could not write {what}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success. A write that runs out
    of space raises `DiskFullError` naming ``path`` (the temporary file is removed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except (OSError, RuntimeError) as exc:
        if isinstance(exc, DiskFullError) or not is_disk_full(exc):
            raise
        full = DiskFullError(no_space_message(path, tmp_path.stat().st_size if tmp_path.exists() else None))
        full.errno = errno.ENOSPC
        raise full from exc
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def run_folder_lock(folder: str | os.PathLike, verb: str, *, exclusive: bool = True) -> Iterator[None]:
    """Hold ``folder``'s lock while the block runs: exclusive for a writer of the run (``train``), shared for
    those that read it and add their own files (``evaluate``, ``export``, ``render``). A second process that
    cannot take it is refused at once with `RunFolderBusy` naming the holder; the lock ends with the process
    (``flock``), so a killed job leaves none behind. A folder that cannot hold the lock file (read-only) is
    read without one when ``exclusive`` is false."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        if exclusive or exc.errno not in (errno.EACCES, errno.EROFS, errno.EPERM):
            raise
        yield
        return
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "an unnamed holder"
            raise RunFolderBusy(f"{folder}: in use by another egobench process (last taken by {holder}); one "
                                f"writer per run folder: wait for it to end, or use another folder") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"egobench {verb} (pid {os.getpid()}, since {time.strftime('%H:%M:%S')})".encode(), 0)
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> None:
    """Write JSON atomically (NaN is rejected: records must stay parseable)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=indent, allow_nan=False) + "\n")


def claim_work_dir(work_dir: str | os.PathLike, stamp_name: str, owner: dict, what: str) -> None:
    """Stamp WORK_DIR with what its run is trained for (WORK_DIR/``stamp_name``: ``owner``), or raise where it holds
    one for another, or an unstamped run: a complete run there is reused, and one trained for something else would
    give a wrong answer without a sign. ``what`` names the folder's content in the error ("a lens check")."""
    work_dir = Path(work_dir)
    stamp = work_dir / stamp_name
    if stamp.is_file():
        have = json.loads(stamp.read_text())
        if have != owner:
            raise ValueError(f"{stamp}: this folder holds {what} of {have}, not {owner}; use another --out")
    elif (work_dir / "run").exists():
        raise ValueError(f"{work_dir / 'run'}: a run without {stamp.name} (what it was trained for unknown); "
                         "use another --out")
    work_dir.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(owner) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON; a missing or truncated file raises ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON (not UTF-8 text: {exc.reason} at byte {exc.start})") from exc


def read_csv(path: str | os.PathLike, what: str, **kwargs):
    """``pandas.read_csv`` (gzip inferred from the name); a file that cannot be read or decoded
    (truncated or corrupt gzip, binary data, no columns) raises ValueError naming it and ``what``."""
    import gzip
    import zlib

    import pandas as pd

    try:
        return pd.read_csv(path, **kwargs)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, EOFError, OSError,
            gzip.BadGzipFile, zlib.error) as exc:
        raise ValueError(f"{path}: not a readable {what} ({type(exc).__name__}: {exc})") from exc


def format_value(value: Any) -> str:
    """A config value as the text of ``--set field=value`` (lists comma-joined, null -> none)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return ",".join(format_value(v) for v in value)
    return str(value)


def holding_run_folder(verb: str, arg: str, *, exclusive: bool):
    """Decorator: the function runs under `run_folder_lock` of its argument ``arg`` (a run folder)."""
    def wrap(fn):
        sig = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args, **kwargs):
            folder = sig.bind(*args, **kwargs).arguments[arg]
            with run_folder_lock(folder, verb, exclusive=exclusive):
                return fn(*args, **kwargs)
        return locked
    return wrap


def git_commit() -> str:
    """The commit of the egobench checkout this code runs from, or "unknown" (an installed copy)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"
