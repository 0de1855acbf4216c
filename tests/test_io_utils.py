"""egobench.io_utils: one writer per run folder (`run_folder_lock`) and a full disk as one named error."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from egobench import cli
from egobench.io_utils import LOCK_NAME, DiskFullError, RunFolderBusy, atomic_path, run_folder_lock
from egobench.train.checkpoint import read_checkpoint
from tests.helpers import small_recording

EGOBENCH = [sys.executable, "-m", "egobench.cli"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return small_recording(tmp_path_factory.mktemp("lock") / "indoor_0", "indoor", 0, n_frames=16)


def _hold(folder: Path, exclusive: bool) -> subprocess.Popen:
    """A child process holding ``folder``'s lock until its stdin closes; returns once it holds it."""
    code = ("import sys; from egobench.io_utils import run_folder_lock\n"
            f"with run_folder_lock({str(folder)!r}, 'holder', exclusive={exclusive}):\n"
            "    print('held', flush=True); sys.stdin.read()")
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "held"
    return child


def test_readers_share_a_run_folder_and_a_writer_is_refused_by_name(tmp_path):
    """Shared holders coexist; an exclusive one is refused naming the holder; a killed holder leaves no lock."""
    child = _hold(tmp_path, exclusive=False)
    with run_folder_lock(tmp_path, "evaluate", exclusive=False):
        pass
    with pytest.raises(RunFolderBusy, match=r"in use by another egobench process \(last taken by egobench "):
        with run_folder_lock(tmp_path, "train"):
            pass
    child.kill()
    child.wait()
    with run_folder_lock(tmp_path, "train"):  # the lock ended with the process
        code = ("from egobench.io_utils import run_folder_lock\n"
                f"with run_folder_lock({str(tmp_path)!r}, 'export', exclusive=False): pass")
        reader = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert reader.returncode != 0 and "RunFolderBusy" in reader.stderr and "(last taken by egobench train" in reader.stderr
    assert (tmp_path / LOCK_NAME).is_file()


def test_a_second_training_into_a_run_folder_is_refused_and_the_first_finishes_intact(tmp_path, recording, capsys):
    """Two `egobench train` into one --out: while the first trains, the second (another method) and an `evaluate`
    are refused with one line naming it and exit 2; the first's checkpoint and record are its own."""
    run = tmp_path / "run"
    first = subprocess.Popen([*EGOBENCH, "train", "--recording", str(recording), "--method", "ours", "--out", str(run),
                              "--iterations", "800", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    deadline = time.monotonic() + 120
    while f"pid {first.pid}" not in ((run / LOCK_NAME).read_text() if (run / LOCK_NAME).exists() else ""):
        assert first.poll() is None and time.monotonic() < deadline, first.communicate()
        time.sleep(0.02)
    codes = [cli.main(["train", "--recording", str(recording), "--method", "no_motion_sampling", "--out", str(run),
                       "--iterations", "20", "--no-progress"]),
             cli.main(["evaluate", "--recording", str(recording), "--run", str(run)])]
    assert first.poll() is None, "the first training ended before the second was tried: the test proves nothing"
    out, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert codes == [2, 2]
    refused = capsys.readouterr().err.splitlines()
    assert [line.split(":")[0] for line in refused] == ["egobench train", "egobench evaluate"]
    assert all(f"in use by another egobench process (last taken by egobench train (pid {first.pid}" in line
               for line in refused)
    ck = read_checkpoint(run / "checkpoint.pt")
    assert ck["method"] == "ours" and ck["iteration"] == 800
    assert sorted(p.name for p in run.iterdir()) == [LOCK_NAME, "checkpoint.pt", "train.json"]


def test_a_write_that_runs_out_of_space_is_one_named_error_and_leaves_nothing(tmp_path):
    """`atomic_path`: ENOSPC (and torch's short-write RuntimeError) -> DiskFullError naming the file and the
    filesystem; neither the file nor its temporary remains."""
    target = tmp_path / "sub" / "checkpoint.pt"
    for exc in (OSError(errno.ENOSPC, "No space left on device"),
                RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 967168 vs 967056")):
        with pytest.raises(DiskFullError) as info:
            with atomic_path(target) as tmp:
                tmp.write_bytes(b"x" * 1000)
                raise exc
        msg = str(info.value)
        assert info.value.errno == errno.ENOSPC
        assert msg.startswith(f"{target}: no space left on the filesystem at ")
        assert "free of" in msg and "1000 bytes" in msg and "\n" not in msg
        assert list(target.parent.iterdir()) == []
    with pytest.raises(RuntimeError, match="other"):  # other failures pass through unchanged
        with atomic_path(target):
            raise RuntimeError("other")


def test_the_cli_reports_a_full_disk_in_one_line(monkeypatch, capsys, tmp_path):
    """A writer outside `atomic_path` that hits ENOSPC: exit 2 and one line naming the file, not a traceback."""
    from egobench.report import tables

    def full(args):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "table2.csv"))

    monkeypatch.setattr(tables, "run", full)
    assert cli.main(["tables", "--records", str(tmp_path / "eval.json"), "--out-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"egobench tables: error: {tmp_path / 'table2.csv'}: no space left") and err.count("\n") == 1


def _tiny_filesystem_argv(mount: Path, inner: str) -> list[str] | None:
    """argv that runs shell ``inner`` with a 64 KiB tmpfs at ``mount`` (a private mount namespace), or None."""
    if shutil.which("unshare") is None:
        return None
    probe = subprocess.run(["unshare", "--mount", "--map-root-user", "sh", "-c",
                            f"mount -t tmpfs -o size=64k tmpfs {mount}"], capture_output=True)
    if probe.returncode != 0:
        return None
    return ["unshare", "--mount", "--map-root-user", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {mount} && {inner}"]


def test_training_into_a_full_filesystem_is_one_line_and_leaves_nothing(tmp_path, recording):
    """A real 64 KiB tmpfs: `egobench train` exits 2 with one line naming checkpoint.pt and the filesystem, and
    the run folder holds nothing but its lock file."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    inner = (f"{' '.join(EGOBENCH)} train --recording {recording} --method ours --out {mount}/run --iterations 5 "
             f"--no-progress; echo rc=$?; ls -A {mount}/run")
    argv = _tiny_filesystem_argv(mount, inner)
    if argv is None:
        pytest.skip("no private tmpfs here (unshare --mount --map-root-user not permitted)")
    proc = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": os.getcwd()})
    lines = proc.stdout.split()
    assert "rc=2" in lines, proc.stderr
    assert lines[lines.index("rc=2") + 1:] == [LOCK_NAME]
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith(f"egobench train: error: {mount}/run/checkpoint.pt: no space left "
                                               f"on the filesystem at {mount} ("), proc.stderr


def test_a_writer_without_errors_of_its_own_is_checked_against_the_free_space(tmp_path, monkeypatch):
    """`check_written` (after OpenCV's writers): a nearly full filesystem -> DiskFullError naming the file; room but
    a failed write -> ValueError; room and success -> nothing."""
    from collections import namedtuple

    from egobench import io_utils

    tmp = tmp_path / ".frame.tmp.png"
    tmp.write_bytes(b"x" * 10)
    io_utils.check_written(tmp_path / "frame.png", tmp)
    with pytest.raises(ValueError, match="frame.png: could not write PNG"):
        io_utils.check_written(tmp_path / "frame.png", tmp, ok=False, what="PNG")
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(io_utils.shutil, "disk_usage", lambda p: usage(1 << 20, (1 << 20) - 100, 100))
    with pytest.raises(DiskFullError, match=r"frame.png: no space left on the filesystem at .*\(100 bytes free of "
                                            r"1.0 MiB\); the write had reached 10 bytes"):
        io_utils.check_written(tmp_path / "frame.png", tmp, ok=False)
