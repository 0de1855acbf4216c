"""What machine a number came from: CPU model, the instruction set the compiled kernels and torch's
CPU kernels target, and the package versions.

A CPU run is bit-reproducible on one machine with one set of package versions. Across machines it
may not be (issue 31: up to 0.77 dB per run between an AVX-512 Zen 5 box and an AVX2 Zen 3 box).
What could differ: the compiled rasterizer is built for the host CPU (numba, LLVM's name for it,
e.g. ``znver5``), torch, MKL and oneDNN dispatch on the host's vector width, and so does numpy (some of
its transcendental functions give other bits under AVX-512 than under AVX2), glibc's libm picks variants
by CPU features, and pip resolves the package ranges to whatever is newest at install time.
Every run record carries `host_info()`; docs/reproducibility.md has what was measured.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

#: x86 / Arm feature flags of /proc/cpuinfo, widest vector instruction set first.
_VECTOR_FLAGS = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sse4_2", "SSE4.2"), ("sve", "SVE"),
                 ("asimd", "NEON"))


def _cpuinfo() -> str:
    info = Path("/proc/cpuinfo")
    return info.read_text(errors="replace") if info.is_file() else ""


def vector_isa(cpuinfo: str | None = None) -> str:
    """The host CPU's widest vector instruction set, from the flags of /proc/cpuinfo ("unknown" elsewhere).
    (The compiled kernels may target less: `host_info`'s kernel_target, e.g. NUMBA_CPU_NAME=znver3.)"""
    text = _cpuinfo() if cpuinfo is None else cpuinfo
    flags = set()
    for line in text.splitlines():
        if line.lower().startswith(("flags", "features")):
            flags.update(line.split(":", 1)[1].split())
    return next((name for flag, name in _VECTOR_FLAGS if flag in flags), "unknown")


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, else the platform's processor string)."""
    for line in _cpuinfo().splitlines():
        if line.lower().startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def _numpy_cpu_tables() -> tuple[list[str], dict[str, bool]]:
    """numpy's compiled dispatch targets and its runtime CPU feature table (private, moved in numpy 2)."""
    try:
        from numpy._core import _multiarray_umath as mu
    except ImportError:  # numpy < 2
        from numpy.core import _multiarray_umath as mu
    return list(mu.__cpu_dispatch__), dict(mu.__cpu_features__)


def numpy_cpu_dispatch() -> list[str]:
    """numpy's vector code paths enabled in this process (e.g. ``['X86_V3', 'X86_V4', 'AVX512_ICL']`` on an
    AVX-512 machine, ``['X86_V3']`` on an AVX2 one or with ``NPY_DISABLE_CPU_FEATURES``). numpy chooses them
    at import, whatever numba, torch or MKL were told, and its float64 exp, log and power and float32 power
    give other bits under each (results/cross_isa/README.md, 2026-11-29)."""
    targets, enabled = _numpy_cpu_tables()
    return [t for t in targets if enabled.get(t)]


def numpy_avx512_targets() -> list[str]:
    """numpy's dispatch targets that need AVX-512 (``X86_V4`` and the ``AVX512*`` ones; their names
    changed in numpy 2.3): what ``NPY_DISABLE_CPU_FEATURES`` must name to make numpy run as on an
    AVX2-only machine."""
    targets, _ = _numpy_cpu_tables()
    return [t for t in targets if t == "X86_V4" or t.startswith("AVX512")]


def host_info() -> dict[str, object]:
    """CPU model, cores, the compiled kernels' LLVM target, torch's CPU capability, numpy's vector code
    paths, package versions."""
    import torch

    try:
        import numba
        from llvmlite import binding as llvm

        kernel_target = numba.config.CPU_NAME or llvm.get_host_cpu_name()
    except ImportError:  # pragma: no cover - numba is a dependency; tolerate a broken install
        kernel_target = "unavailable"
    return {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "vector_isa": vector_isa(),
            "kernel_target": kernel_target,
            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "numpy_cpu_dispatch": numpy_cpu_dispatch(),
            "threads": {"torch": torch.get_num_threads(), "kernels": kernel_threads()},
            "allocator": dict(_ALLOCATOR) if _ALLOCATOR else None, "versions": versions()}


def kernel_threads() -> int:
    """The compiled kernels' thread count (`raster_threads`, at most numba's pool; what
    `render.cpu_backend.set_threads` sets)."""
    try:
        import numba

        return max(1, min(raster_threads(), numba.config.NUMBA_NUM_THREADS))
    except ImportError:  # pragma: no cover - numba is a dependency
        return 1


#: environment variable giving the compiled kernels their own thread count (default: torch's)
RASTER_THREADS_ENV = "EGOBENCH_RASTER_THREADS"


def cap_numba_pool(environ=None, numba_loaded: bool | None = None) -> str | None:
    """Caps numba's thread pool to the count the user (or Snakemake, which exports OMP_NUM_THREADS=
    {threads} to every job) chose: NUMBA_NUM_THREADS := EGOBENCH_RASTER_THREADS or OMP_NUM_THREADS,
    only while NUMBA_NUM_THREADS is unset and numba is not loaded yet. numba reads it once, at import;
    set after that, every later compilation fails ("Cannot set NUMBA_NUM_THREADS to a different
    value once the threads have been launched"). Run by `setup_threads` -> the value set, or None."""
    environ = os.environ if environ is None else environ
    loaded = "numba" in sys.modules if numba_loaded is None else numba_loaded
    pool = environ.get(RASTER_THREADS_ENV) or environ.get("OMP_NUM_THREADS", "")
    if loaded or "NUMBA_NUM_THREADS" in environ or not (pool.isdigit() and int(pool) > 0):
        return None
    environ["NUMBA_NUM_THREADS"] = pool
    return pool


def setup_threads() -> None:
    """The process's thread set-up, called once by each entry point before it loads numba: the CLI (`cli.main`),
    the ``python -m`` tools and the test suite (conftest). It caps numba's pool to the job's threads
    (`cap_numba_pool`); importing egobench changes nothing. The pool starts at the first kernel
    (`start_kernel_pool`)."""
    cap_numba_pool()


#: numba's threading layers in the order egobench asks for them: OpenMP first. numba's workqueue workers sleep
#: after every parallel loop, and on a 2-core VM a worker idle for a few ms took ~1 ms to wake; training calls
#: ~8 parallel kernels a step between torch operations, so its kernels barely scaled (ours_2dgs at 128 px: 26.6
#: it/s on 2 threads against 26.4 on 1). OpenMP's workers spin briefly first: 44.0-47.3 it/s, 1.58x (512 px:
#: 1.78-1.84x). With the other core busy it is ~30 % slower than workqueue. results/speed/README.md, "numba's
#: threading layer". An explicit NUMBA_THREADING_LAYER is respected; without OpenMP numba takes the next layer.
THREADING_LAYERS = ["omp", "tbb", "workqueue"]


def start_kernel_pool() -> None:
    """Starts numba's thread pool in egobench's threading layer (`THREADING_LAYERS`), once; later calls do
    nothing. Starting the OpenMP layer sets the OpenMP thread count of the process, which torch shares (one
    libgomp is loaded), so torch's own count is put back; numba gives each parallel loop its own count
    (`numba.set_num_threads`). Called where the compiled kernels set their threads
    (`render.cpu_backend.set_threads`) and by the test suite."""
    import numba
    import torch
    from numba.np.ufunc import parallel

    if parallel._is_initialized:
        return
    if "NUMBA_THREADING_LAYER" not in os.environ:
        numba.config.THREADING_LAYER_PRIORITY = list(THREADING_LAYERS)
        numba.config.THREADING_LAYER = "default"
    torch_threads = torch.get_num_threads()
    numba.get_num_threads()  # starts the pool
    if torch.get_num_threads() != torch_threads:
        torch.set_num_threads(torch_threads)


def raster_threads() -> int:
    """Threads of the compiled kernels (`render.cpu_backend.set_threads`): EGOBENCH_RASTER_THREADS
    when set, else torch's count (OMP_NUM_THREADS / torch.set_num_threads). Setting it to 2 with
    torch at 1 thread parallelises the kernels only (what `bench raster` scales; in training torch's
    threads pay, results/speed/README.md, "Torch's threads in training")."""
    import torch

    value = os.environ.get(RASTER_THREADS_ENV, "")
    if not value:
        return torch.get_num_threads()
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{RASTER_THREADS_ENV} must be a positive integer (threads of the compiled CPU "
                         f"rasterizer), got {value!r}")
    return int(value)


#: environment variables by which a user (or Snakemake, which exports OMP_NUM_THREADS={threads} to
#: every job) has chosen thread counts; with any of them set, `default_threads` changes nothing.
THREAD_ENV = ("OMP_NUM_THREADS", RASTER_THREADS_ENV, "NUMBA_NUM_THREADS")


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS reports it, else os.cpu_count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS and Windows have no affinity call
        return os.cpu_count() or 1


def default_threads(environ=None) -> dict[str, int] | None:
    """A CPU training run's threads when nobody chose them: torch's glue and the compiled kernels
    both on every usable core (sets EGOBENCH_RASTER_THREADS in ``environ``, default os.environ, and
    torch's count). Measured in training (results/speed/README.md, "Torch's threads in training"):
    torch on two threads beside the kernels is never slower than on one and gains most at larger
    images, where the glue (losses, SSIM, Adam) works on image-sized tensors; the results are bitwise
    the same. -> {"torch": n, "kernels": n}, or None where THREAD_ENV holds a choice (left as it is)."""
    import torch

    env = os.environ if environ is None else environ
    if any(env.get(name) for name in THREAD_ENV):
        return None
    n = usable_cores()
    env[RASTER_THREADS_ENV] = str(n)
    torch.set_num_threads(n)
    return {"torch": n, "kernels": n}


#: glibc malloc settings of a training process (`keep_freed_memory`): blocks below 32 MB (the most
#: glibc accepts on 64-bit) come from the heap, and up to 1 GB of freed heap stays mapped.
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 1 << 30
#: ... and of a process that works on whole image stacks (`keep_freed_memory(whole_images=True)`, the
#: diagnosis): no block is mapped on its own, and up to 2 GB (mallopt's int) of freed heap stays.
WHOLE_IMAGES_TRIM_THRESHOLD_BYTES = (1 << 31) - 1
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4  # mallopt's parameter numbers (malloc.h)
_ALLOCATOR: dict[str, int] | None = None  # what `keep_freed_memory` set in this process


def keep_freed_memory(environ=None, whole_images: bool = False) -> dict[str, int] | None:
    """Linux/glibc: keep a training step's freed buffers for the next step instead of returning them
    to the OS. A CPU step allocates its tile state, Gaussian table and image-sized tensors anew;
    with glibc's defaults many of those are mapped and unmapped every step (~2000 page faults a
    step at 128 px), 10-13 % of the step's time (results/speed/README.md, "Page faults").
    ``whole_images``: also blocks above 32 MB come from the heap (M_MMAP_MAX 0), for the diagnosis's
    [F, H, W, 3] stacks: at 1200 px its page faults were 46 % of its time (docs/diagnosis.md, "Cost at
    the paper's resolution"); the price is a larger peak RSS. Leaves malloc alone where GLIBC_TUNABLES
    sets it or there is no glibc -> the settings applied, or None."""
    global _ALLOCATOR
    env = os.environ if environ is None else environ
    if not sys.platform.startswith("linux") or "malloc" in env.get("GLIBC_TUNABLES", ""):
        return None
    import ctypes

    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl and other libcs: no glibc mallopt
        return None
    settings = {"mmap_threshold_bytes": MMAP_THRESHOLD_BYTES,
                "trim_threshold_bytes": WHOLE_IMAGES_TRIM_THRESHOLD_BYTES if whole_images else TRIM_THRESHOLD_BYTES}
    calls = [(_M_MMAP_THRESHOLD, settings["mmap_threshold_bytes"]), (_M_TRIM_THRESHOLD, settings["trim_threshold_bytes"])]
    if whole_images:
        settings["mmap_max"] = 0
        calls.append((_M_MMAP_MAX, 0))
    if not all(mallopt(param, value) for param, value in calls):
        return None
    _ALLOCATOR = settings
    return dict(_ALLOCATOR)


def versions() -> dict[str, str]:
    """The versions of the packages whose arithmetic a CPU run's numbers depend on."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("torch", "numba", "llvmlite", "numpy", "gsplat"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "absent"
    return out
