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
