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


def test_default_threads_put_torch_on_one_and_the_kernels_on_every_core_unless_chosen(monkeypatch):
    """With no thread variable set, a CPU training run's torch runs one thread and the compiled kernels
    every usable core (what the thread scaling measured to gain); any of OMP_NUM_THREADS,
    EGOBENCH_RASTER_THREADS, NUMBA_NUM_THREADS (Snakemake exports the first) leaves both alone."""
    import torch

    from egobench.host import default_threads, host_info, usable_cores
    from egobench.host import raster_threads

    before = torch.get_num_threads()
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(n))
    calls: list[int] = []
    assert default_threads({"OMP_NUM_THREADS": "3"}) is None and calls == []
    env = {"PATH": "/bin"}
    assert default_threads(env) == {"torch": 1, "kernels": usable_cores()} and calls == [1]
    assert env == {"PATH": "/bin", "EGOBENCH_RASTER_THREADS": str(usable_cores())}
    monkeypatch.undo()
    assert torch.get_num_threads() == before
    monkeypatch.setenv("EGOBENCH_RASTER_THREADS", "1")
    assert raster_threads() == 1 and host_info()["threads"] == {"torch": before, "kernels": 1}


def test_the_benchmarks_scale_the_kernels_with_torch_on_one_thread(monkeypatch):
    """`bench.kernel_threads(n)`: torch at one thread and the kernels at n inside, both restored after;
    more threads than numba's pool is an error naming the variable that sizes it."""
    import numba
    import pytest
    import torch

    from egobench.bench import kernel_threads
    from egobench.host import RASTER_THREADS_ENV, raster_threads

    monkeypatch.setenv(RASTER_THREADS_ENV, "1")
    monkeypatch.delenv(RASTER_THREADS_ENV)
    before = torch.get_num_threads()
    with kernel_threads(1):
        assert torch.get_num_threads() == 1 and raster_threads() == 1
    assert torch.get_num_threads() == before and RASTER_THREADS_ENV not in __import__("os").environ
    with pytest.raises(ValueError, match="NUMBA_NUM_THREADS"), kernel_threads(numba.config.NUMBA_NUM_THREADS + 1):
        pass


def test_egobench_train_runs_torch_on_one_thread_and_the_kernels_on_every_core(tmp_path, monkeypatch):
    """`egobench train` on the CPU applies `default_threads` where no thread variable is set, and its
    run record says so; with OMP_NUM_THREADS set (as the test session and Snakemake jobs set it) it
    leaves torch's count and the kernels' alone."""
    import json

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
    threads = json.loads((tmp_path / "default" / "train.json").read_text())["host"]["threads"]
    assert threads == {"torch": 1, "kernels": min(usable_cores(), numba.config.NUMBA_NUM_THREADS)}
