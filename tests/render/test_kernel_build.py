"""`egobench.render.kernel_build`: the first process on a cold cache builds the kernels in one child under a
file lock, a failed child leaves no marker and says why, and the build key follows what the machine code
depends on. (The real build, end to end, is tests/render/test_render_cpu_cache.py.)"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import torch

from egobench.render import kernel_build


def _fake_builds(monkeypatch, tmp_path, script: str):
    """ensure_built with its marker in tmp_path and ``script`` (python -c, given the marker and a log file)
    as the child; -> (marker, log)."""
    marker, log = tmp_path / "egobench-build-3dgs-float32-key.json", tmp_path / "children.log"
    monkeypatch.setattr(kernel_build, "BUILT", {})
    monkeypatch.delenv(kernel_build.BUILD_ENV, raising=False)
    monkeypatch.setattr(kernel_build, "marker_path", lambda dtype, mode: marker)
    monkeypatch.setattr(kernel_build, "_child_command",
                        lambda dtype, mode: [sys.executable, "-c", script, str(marker), str(log)])
    return marker, log


CHILD = """
import sys, time
from pathlib import Path
marker, log = map(Path, sys.argv[1:])
with open(log, "a") as f:
    f.write("child\\n")
time.sleep(1.0)
marker.write_text("{}")
"""


def test_two_processes_on_a_cold_cache_build_once(monkeypatch, tmp_path):
    marker, log = _fake_builds(monkeypatch, tmp_path, CHILD)
    results = []

    def first_render():
        results.append(kernel_build.ensure_built(torch.float32, "3dgs"))
        kernel_build.BUILT.clear()  # as another process would: nothing remembered

    threads = [threading.Thread(target=first_render) for _ in range(2)]
    for t in threads:
        t.start()
        time.sleep(0.2)
    for t in threads:
        t.join()
    assert log.read_text().splitlines() == ["child"]  # the second waited for the lock, then found the marker
    assert sorted(results) == ["child", "marker"] and marker.is_file()


def test_a_warm_process_spawns_nothing(monkeypatch, tmp_path):
    marker, log = _fake_builds(monkeypatch, tmp_path, CHILD)
    marker.write_text("{}")
    assert kernel_build.ensure_built(torch.float64, "2dgs") == "marker"
    assert not log.exists()


def test_a_failed_child_leaves_no_marker_and_says_why(monkeypatch, tmp_path, capsys):
    marker, log = _fake_builds(monkeypatch, tmp_path, "import sys; sys.stderr.write('no compiler here'); sys.exit(3)")
    assert kernel_build.ensure_built(torch.float32, "3dgs") == "failed"
    err = capsys.readouterr().err
    assert "exit 3" in err and "no compiler here" in err and "compiling in this process" in err
    assert "NUMBA_OPT=max" in err  # the remedy for the in-process code's other bits and speed
    assert not marker.exists()
    assert kernel_build.ensure_built(torch.float32, "3dgs") == "failed"  # once per process: not retried


def test_in_process_builds_spawn_no_child(monkeypatch, tmp_path):
    marker, log = _fake_builds(monkeypatch, tmp_path, CHILD)
    monkeypatch.setenv(kernel_build.BUILD_ENV, "in-process")
    assert kernel_build.ensure_built(torch.float32, "2dgs") == "in-process"
    assert not log.exists() and not marker.exists()


def test_the_build_key_follows_numba_settings_but_not_its_thread_count(monkeypatch):
    monkeypatch.delenv("NUMBA_OPT", raising=False)
    base = kernel_build.build_key()
    monkeypatch.setenv("NUMBA_NUM_THREADS", "7")
    assert kernel_build.build_key() == base
    monkeypatch.setenv("NUMBA_OPT", "1")
    assert kernel_build.build_key() != base


def test_the_marker_lies_in_numba_cache_folder_of_the_kernels():
    marker = kernel_build.marker_path("float32", "2dgs")
    folder = kernel_build.kernel_dispatchers("2dgs")[2].stats.cache_path
    assert str(marker.parent) == folder and kernel_build.build_key() in marker.name
    assert marker != kernel_build.marker_path("float64", "2dgs") != kernel_build.marker_path("float32", "3dgs")


def test_an_unwritable_lock_folder_builds_without_the_lock(tmp_path):
    (tmp_path / "a-file").write_text("")
    ran = []
    with kernel_build._locked(tmp_path / "a-file" / "egobench-build-3dgs-float32.lock"):  # its folder is a file
        ran.append(True)
    assert ran == [True]


def test_the_child_imports_this_processs_egobench_from_any_working_folder(monkeypatch, tmp_path):
    """Started from a folder that holds another egobench (a second checkout), the child still runs this one:
    ``python -m`` puts the working folder first, and another checkout's child builds into its own cache."""
    other = tmp_path / "egobench"
    other.mkdir()
    (other / "__init__.py").write_text("raise ImportError('the other checkout')\n")
    monkeypatch.chdir(tmp_path)
    done = kernel_build.run_child([sys.executable, "-c", "import egobench, sys; print(egobench.__file__)"])
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(Path(kernel_build.__file__).resolve().parents[1] / "__init__.py")
