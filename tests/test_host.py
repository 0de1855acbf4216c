"""Where a number came from (egobench.host)."""

from __future__ import annotations


def test_host_info_names_the_cpu_and_versions():
    from egobench.host import host_info

    h = host_info()
    assert h["cpu_model"] and h["cpu_model"] != "unknown"
    assert set(h["versions"]) == {"torch", "numba", "llvmlite", "numpy", "gsplat"}
    assert h["versions"]["torch"].split("+")[0] == __import__("torch").__version__.split("+")[0]


def test_the_kernel_target_is_the_one_numba_compiles_for():
    """NUMBA_CPU_NAME (numba's target override) is what the record says; without it, LLVM's host CPU."""
    import os
    import subprocess
    import sys

    from llvmlite import binding as llvm

    code = "from egobench.host import host_info; print(host_info()['kernel_target'])"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CPU_NAME"}
    run = lambda extra: subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True,  # noqa: E731
                                       text=True, check=True).stdout.strip()
    assert run({"NUMBA_CPU_NAME": "znver3"}) == "znver3"
    assert run({}) == llvm.get_host_cpu_name()


def test_the_vector_isa_is_the_widest_the_cpu_flags_name():
    """The bench's host record names the widest vector instruction set among the CPU's flags."""
    from egobench.host import host_info, vector_isa

    assert vector_isa("processor: 0\nflags\t\t: fpu sse4_2 avx avx2 fma avx512f avx512bw\n") == "AVX-512"
    assert vector_isa("flags\t\t: fpu sse4_2 avx avx2 fma\n") == "AVX2"
    assert vector_isa("Features\t: fp asimd evtstrm\n") == "NEON"
    assert vector_isa("model name: something\n") == "unknown"
    assert host_info()["vector_isa"] == vector_isa()


def test_default_threads_put_torch_and_the_kernels_on_every_core_unless_chosen(monkeypatch):
    """With no thread variable set, a CPU training run's torch and compiled kernels run on every
    usable core (what the training thread scaling measured to gain); any of OMP_NUM_THREADS,
    EGOBENCH_RASTER_THREADS, NUMBA_NUM_THREADS (Snakemake exports the first) leaves both alone."""
    import torch

    from egobench.host import default_threads, host_info, usable_cores
    from egobench.host import raster_threads

    before = torch.get_num_threads()
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(n))
    calls: list[int] = []
    assert default_threads({"OMP_NUM_THREADS": "3"}) is None and calls == []
    env = {"PATH": "/bin"}
    assert default_threads(env) == {"torch": usable_cores(), "kernels": usable_cores()} and calls == [usable_cores()]
    assert env == {"PATH": "/bin", "EGOBENCH_RASTER_THREADS": str(usable_cores())}
    monkeypatch.undo()
    assert torch.get_num_threads() == before
    monkeypatch.setenv("EGOBENCH_RASTER_THREADS", "1")
    assert raster_threads() == 1 and host_info()["threads"] == {"torch": before, "kernels": 1}


def test_the_benchmarks_set_the_kernels_and_torch_threads_and_restore_them(monkeypatch):
    """`bench.cpu_threads(n, torch_n)`: the kernels at n and torch at torch_n (default n) inside, both
    restored after; more threads than numba's pool is an error naming the variable that sizes it."""
    import numba
    import pytest
    import torch

    from egobench.bench import cpu_threads
    from egobench.host import RASTER_THREADS_ENV, raster_threads

    monkeypatch.setenv(RASTER_THREADS_ENV, "1")
    monkeypatch.delenv(RASTER_THREADS_ENV)
    before = torch.get_num_threads()
    with cpu_threads(1, torch_n=2):
        assert torch.get_num_threads() == 2 and raster_threads() == 1
    torch.set_num_threads(3)
    try:
        with cpu_threads(1):  # torch follows the kernels' count
            assert torch.get_num_threads() == 1 and raster_threads() == 1
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
    assert RASTER_THREADS_ENV not in __import__("os").environ
    with pytest.raises(ValueError, match="NUMBA_NUM_THREADS"), cpu_threads(numba.config.NUMBA_NUM_THREADS + 1):
        pass


def test_egobench_train_runs_torch_and_the_kernels_on_every_core(tmp_path, monkeypatch):
    """`egobench train` on the CPU applies `default_threads` where no thread variable is set, and its
    run record says so; with OMP_NUM_THREADS set (as the test suite and Snakemake jobs set it) it
    leaves torch's count and the kernels' alone."""
    import json
    import os
    import sys

    import numba
    import torch

    from egobench.cli import main
    from egobench.host import usable_cores
    from tests.helpers import small_recording

    rec = small_recording(tmp_path / "rec", "indoor", 2, n_frames=9, size=24)
    before = torch.get_num_threads()
    args = ["train", "--recording", str(rec), "--method", "no_motion_sampling", "--iterations", "2", "--no-progress"]
    assert main(args + ["--out", str(tmp_path / "chosen")]) == 0  # conftest: OMP_NUM_THREADS=1
    threads = json.loads((tmp_path / "chosen" / "train.json").read_text())["host"]["threads"]
    assert threads == {"torch": before, "kernels": before}
    for name in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "EGOBENCH_RASTER_THREADS"):
        monkeypatch.setenv(name, "1")  # recorded first, so that undo also removes what train sets
        monkeypatch.delenv(name)
    try:
        assert main(args + ["--out", str(tmp_path / "default")]) == 0
    finally:
        torch.set_num_threads(before)
    record = json.loads((tmp_path / "default" / "train.json").read_text())["host"]
    assert record["threads"] == {"torch": usable_cores(), "kernels": min(usable_cores(), numba.config.NUMBA_NUM_THREADS)}
    if sys.platform.startswith("linux") and "malloc" not in os.environ.get("GLIBC_TUNABLES", ""):
        assert record["allocator"] == {"mmap_threshold_bytes": 32 << 20, "trim_threshold_bytes": 1 << 30}


def test_a_training_run_is_bitwise_the_same_with_torch_on_one_and_on_two_threads(tmp_path, monkeypatch):
    """`default_threads` puts torch's glue on every core: that must not change a bit of the trained
    parameters or of Adam's state.
    128 px images, so the glue's image-sized tensors (49k values) are above torch's parallel grain."""
    import torch

    from egobench.host import RASTER_THREADS_ENV
    from egobench.sim.plane import plane_recording
    from egobench.train import TrainConfig, train

    monkeypatch.setenv(RASTER_THREADS_ENV, "1")
    rec = plane_recording(tmp_path / "rec", size=128, n_frames=9, angular_speed_rad_s=6.0, frame_interval_s=0.01,
                          n_points=2000)
    before, states = torch.get_num_threads(), []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            cfg = TrainConfig(iterations=12, max_side=128, device="cpu", motion_warmup_frac=0.0, refine_start_frac=1.0)
            train(rec, "ours", cfg, tmp_path / f"t{n}", progress=False)
            states.append(torch.load(tmp_path / f"t{n}" / "checkpoint.pt", weights_only=True))
    finally:
        torch.set_num_threads(before)
    one, two = states
    assert one["params"].keys() == two["params"].keys() and len(one["params"]) == 5
    for name, value in one["params"].items():
        assert torch.equal(value, two["params"][name]), name
        moments = one["optimizers"][name]["state"][0]["exp_avg"]
        assert moments.abs().max() > 0 and torch.equal(moments, two["optimizers"][name]["state"][0]["exp_avg"]), name
    # the logged loss is a mean over pixels that torch sums in a thread-dependent order: its last bit
    # may differ (measured: 0.23276394605636597 against ...93115520477), the parameters may not


def test_keep_freed_memory_sets_glibc_malloc_unless_tunables_chose_and_the_record_says_so(monkeypatch):
    """`keep_freed_memory` (egobench train on the CPU) raises glibc's mmap and trim thresholds so a
    step's freed buffers are reused, not unmapped and faulted in again; GLIBC_TUNABLES that set malloc
    are the user's choice (mallopt is not called); elsewhere than Linux it does nothing. With
    ``whole_images`` (the diagnosis) no block is mapped on its own."""
    import ctypes
    import sys

    import pytest

    from egobench import host

    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append((param, value))
            return 1

    host.host_info()  # loads numba and llvmlite, which open their libraries through ctypes.CDLL, before it is faked
    monkeypatch.setattr(ctypes, "CDLL", lambda name: FakeLibc())
    monkeypatch.setattr(host, "_ALLOCATOR", None)
    assert host.keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"}) is None and calls == []
    if not sys.platform.startswith("linux"):
        pytest.skip("mallopt is glibc's (Linux)")
    want = {"mmap_threshold_bytes": 32 << 20, "trim_threshold_bytes": 1 << 30}
    assert host.keep_freed_memory({}) == want
    assert calls == [(-3, 32 << 20), (-1, 1 << 30)]  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD of malloc.h
    assert host.host_info()["allocator"] == want
    calls.clear()  # the diagnosis: no block mapped on its own (M_MMAP_MAX 0), mallopt's largest trim threshold
    images = {"mmap_threshold_bytes": 32 << 20, "trim_threshold_bytes": (1 << 31) - 1, "mmap_max": 0}
    assert host.keep_freed_memory({}, whole_images=True) == images == host.host_info()["allocator"]
    assert calls == [(-3, 32 << 20), (-1, (1 << 31) - 1), (-4, 0)]
    monkeypatch.setattr(sys, "platform", "darwin")
    monkeypatch.setattr(host, "_ALLOCATOR", None)
    assert host.keep_freed_memory({}) is None and len(calls) == 3 and host.host_info()["allocator"] is None


def test_numba_pool_is_capped_only_before_numba_loads():
    """`cap_numba_pool`: NUMBA_NUM_THREADS from EGOBENCH_RASTER_THREADS, else OMP_NUM_THREADS, only when
    it is unset and numba is not loaded (set later, numba refuses every compilation)."""
    from egobench.host import cap_numba_pool

    env = {"OMP_NUM_THREADS": "1"}
    assert cap_numba_pool(env, numba_loaded=False) == "1" and env["NUMBA_NUM_THREADS"] == "1"
    env = {"OMP_NUM_THREADS": "1", "EGOBENCH_RASTER_THREADS": "3"}
    assert cap_numba_pool(env, numba_loaded=False) == "3" and env["NUMBA_NUM_THREADS"] == "3"
    for env in ({"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "4"}, {"OMP_NUM_THREADS": "x"}, {}):
        before = dict(env)
        assert cap_numba_pool(env, numba_loaded=False) is None and env == before
    env = {"OMP_NUM_THREADS": "1"}
    assert cap_numba_pool(env, numba_loaded=True) is None and env == {"OMP_NUM_THREADS": "1"}


def test_kernels_compile_whichever_module_loads_numba_first():
    """With OMP_NUM_THREADS=1 (as Snakemake's jobs) and no NUMBA_NUM_THREADS: numba loaded before the entry
    point's `setup_threads` (pool left alone) or by the 2DGS kernels and the host record after it (pool capped
    to 1), a later compilation works. Setting NUMBA_NUM_THREADS after numba loaded made every
    compilation fail (a cold cache, or a new dtype, in a Snakemake job)."""
    import os
    import subprocess
    import sys

    compile_one = "import numba; print(numba.njit(lambda x: x + 1)(1), numba.config.NUMBA_NUM_THREADS)"
    setup = "from egobench.host import setup_threads\nsetup_threads()\n"
    orders = {"numba first": "import numba\n" + setup + "from egobench.render import cpu\n",
              "2dgs first": (setup + "from egobench.host import host_info\nhost_info()\n"
                             "from egobench.render.cpu import surfels\n")}
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_NUM_THREADS", "EGOBENCH_RASTER_THREADS")}
    env["OMP_NUM_THREADS"] = "1"
    out = {name: subprocess.run([sys.executable, "-c", pre + compile_one], env=env, capture_output=True, text=True,
                                check=True).stdout.split() for name, pre in orders.items()}
    assert out["numba first"][0] == "2" and out["2dgs first"] == ["2", "1"]


def test_numpy_vector_paths_are_recorded_and_the_avx2_emulation_turns_numpys_avx512_off():
    """numpy dispatches its own vector code by the CPU (its float64 exp/log/power give other bits under
    AVX-512): the record names the paths enabled, and NPY_DISABLE_CPU_FEATURES with
    `numpy_avx512_targets` (what scripts/cross_isa_check.py's AVX2 setting sets) leaves exactly the others."""
    import json
    import os
    import runpy
    import subprocess
    import sys
    from pathlib import Path

    from egobench.host import _numpy_cpu_tables, host_info, numpy_avx512_targets, numpy_cpu_dispatch

    compiled, _ = _numpy_cpu_tables()
    assert host_info()["numpy_cpu_dispatch"] == numpy_cpu_dispatch()
    assert set(numpy_avx512_targets()) <= set(compiled)
    code = "import json; from egobench.host import numpy_cpu_dispatch as d; print(json.dumps(d()))"
    env = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}
    run = lambda extra: json.loads(subprocess.run([sys.executable, "-c", code], env={**env, **extra},  # noqa: E731
                                                  capture_output=True, text=True, check=True).stdout)
    enabled = run({})
    assert set(enabled) <= set(compiled)
    avx2 = runpy.run_path(str(Path(__file__).parents[1] / "scripts" / "cross_isa_check.py"), run_name="x")["AVX2"]
    off = run({"NPY_DISABLE_CPU_FEATURES": avx2["NPY_DISABLE_CPU_FEATURES"]}) if numpy_avx512_targets() else enabled
    assert off == [t for t in enabled if t not in numpy_avx512_targets()]



def test_importing_egobench_and_its_kernels_sets_no_thread_state():
    """No side effects at import: in a fresh process with OMP_NUM_THREADS=1, importing egobench, the CLI and the
    CPU kernels leaves NUMBA_NUM_THREADS unset, numba's pool unstarted and torch's thread count as it was; the
    entry point's `setup_threads` then caps the pool, and `start_kernel_pool` starts it keeping torch's count."""
    import json
    import os
    import subprocess
    import sys

    code = """
import json, os, torch
torch.set_num_threads(1)
import egobench, egobench.cli
from egobench.render import cpu
from egobench.render.cpu import surfels
from numba.np.ufunc import parallel
after_import = {"numba_env": os.environ.get("NUMBA_NUM_THREADS"), "pool": parallel._is_initialized,
                "torch": torch.get_num_threads()}
from egobench.host import start_kernel_pool
start_kernel_pool()
start_kernel_pool()
print(json.dumps({"import": after_import, "started": parallel._is_initialized, "torch": torch.get_num_threads()}))
"""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_NUM_THREADS", "EGOBENCH_RASTER_THREADS")}
    env["OMP_NUM_THREADS"] = "1"
    out = json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                    check=True).stdout.splitlines()[-1])
    assert out == {"import": {"numba_env": None, "pool": False, "torch": 1}, "started": True, "torch": 1}
