"""Builds the compiled CPU rasterizer's kernels in a child process, so that every process runs the code
numba cached (docs/cpu-rasterizer.md, "Where the kernels compile").

Why: numba compiles a parallel kernel's loop body first as a library of its own and keeps it in the
compiling process; the kernel that numba caches holds another copy, optimized again. LLVM's linker
binds the first, so the process that compiles a kernel runs other machine code than every process that
loads it: other bits under fast-math contraction (measured 2026-11-28). So the first process that renders a (dtype,
mode) with the compiled backend runs ``python -m egobench.render.kernel_build`` under a file lock, which
compiles into numba's cache and leaves a marker there (`marker_path`); then it, and every later process,
loads. A kernel that still misses the cache compiles in the process, as numba does by default.

``EGOBENCH_KERNEL_BUILD=in-process`` compiles where rendered instead (the child itself uses it). With
``NUMBA_OPT=max`` in the environment numba runs its first, cheap pass at -O3 with loop vectorization too,
so the loop body's own library is optimized twice as the cached copy is: a process that compiles then runs
the cached bits at the cached speed (measured 2026-11-29; the compile takes about twice as long). That is the
way to compile in-process where no child can run.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from egobench.host import setup_threads

#: environment variable: "in-process" compiles the kernels in the rendering process (no child)
BUILD_ENV = "EGOBENCH_KERNEL_BUILD"
#: what `ensure_built` did per (dtype name, mode) in this process: "child" (built them), "marker" (found them
#: built), "in-process" (the environment says so) or "failed" (the child failed: compiled in the process)
BUILT: dict[tuple[str, str], str] = {}
#: the kernels of a set whose cache use the child checks (names; 2DGS adds "_2dgs")
KERNELS = ("project_fwd", "project_bwd", "raster_fwd", "raster_bwd")
#: the files whose text decides the kernels' machine code and signatures
_SOURCES = ("cpu/__init__.py", "cpu/args.py", "cpu/compiler.py", "cpu/projection.py", "cpu/binning.py", "cpu/composite.py",
            "cpu/surfels.py", "cpu_backend.py", "cpu_backend_2dgs.py", "kernel_build.py")


def kernel_dispatchers(mode: str) -> list:
    """The numba dispatchers of `KERNELS` for ``mode`` ("3dgs", "2dgs")."""
    if mode == "3dgs":
        from egobench.render import cpu as module
    else:
        from egobench.render.cpu import surfels as module
    suffix = "" if mode == "3dgs" else "_2dgs"
    return [getattr(module, name + suffix) for name in KERNELS]


def build_key() -> str:
    """What a build's machine code depends on, as a hash: the kernels' and their glue's source, the Python,
    numba and llvmlite versions, the CPU LLVM compiles for and numba's settings (its thread count and cache
    folder aside)."""
    import llvmlite
    import llvmlite.binding as llvm
    import numba

    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for name in _SOURCES:
        h.update(name.encode() + b"\0" + (here / name).read_bytes())
    settings = {k: v for k, v in os.environ.items()
                if k.startswith("NUMBA_") and k not in ("NUMBA_NUM_THREADS", "NUMBA_CACHE_DIR")}
    h.update(json.dumps([sys.version, numba.__version__, llvmlite.__version__, llvm.get_host_cpu_name(),
                         llvm.get_host_cpu_features().flatten(), sorted(settings.items())]).encode())
    return h.hexdigest()[:20]


def marker_path(dtype_name: str, mode: str) -> Path:
    """The marker of a finished build of ``mode``'s kernels in ``dtype_name``, in numba's cache folder of
    those kernels (deleting that folder deletes it)."""
    folder = Path(kernel_dispatchers(mode)[0].stats.cache_path)
    return folder / f"egobench-build-{mode}-{dtype_name}-{build_key()}.json"


def ensure_built(dtype: torch.dtype, mode: str) -> str:
    """Makes sure numba's cache holds ``mode``'s kernels for ``dtype`` before this process first calls them
    -> what was done (`BUILT`'s values). Cheap after the first call per (dtype, mode) in a process."""
    name = str(dtype).removeprefix("torch.")
    if (name, mode) in BUILT:
        return BUILT[(name, mode)]
    if os.environ.get(BUILD_ENV) == "in-process":
        BUILT[(name, mode)] = "in-process"
        return "in-process"
    marker = marker_path(name, mode)
    done = "marker"
    if not marker.is_file():
        with _locked(marker.with_name(f"egobench-build-{mode}-{name}.lock")):
            if not marker.is_file():  # another process may have built it while this one waited
                done = _build_in_child(name, mode)
    BUILT[(name, mode)] = done
    return done


@contextlib.contextmanager
def _locked(path: Path):
    """An exclusive lock on ``path`` (created), held for the block (none where fcntl is missing or the
    folder cannot be written: the child then reports why it failed)."""
    try:
        import fcntl

        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a")
    except (ImportError, OSError):
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _child_command(dtype_name: str, mode: str) -> list[str]:
    return [sys.executable, "-m", "egobench.render.kernel_build", "--dtype", dtype_name, "--mode", mode]


def run_child(command: list[str]) -> subprocess.CompletedProcess:
    """Runs ``command`` (`_child_command`) with this process's egobench first on the child's path: as
    PYTHONPATH, and as the working folder, since ``python -m`` puts the working folder before PYTHONPATH. A
    child started in another checkout's folder built that checkout's kernels into its own cache, so this
    process found no marker and compiled in-process (other bits, slower; measured 2026-12-06)."""
    package_root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join([package_root] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    env = dict(os.environ, PYTHONPATH=path, OMP_NUM_THREADS="1", **{BUILD_ENV: "in-process"})
    return subprocess.run(command, env=env, cwd=package_root, capture_output=True, text=True)


def _build_in_child(dtype_name: str, mode: str) -> str:
    """Runs the build in a child (`run_child`) -> "child", or "failed" after a warning with the child's error
    output (the kernels then compile in this process)."""
    print(f"egobench: compiling the CPU rasterizer's {mode} kernels for {dtype_name} in a child process "
          "(once per machine and version; about a minute)", file=sys.stderr, flush=True)
    start = time.perf_counter()
    done = run_child(_child_command(dtype_name, mode))
    if done.returncode != 0:
        print(f"egobench: the kernel build in a child failed (exit {done.returncode}); compiling in this process, "
              "whose kernels then differ from the cached ones in the last bits and run the 3DGS compositing ~4x "
              "slower (start it with NUMBA_OPT=max for the cached code, docs/cpu-rasterizer.md). "
              f"Its error output:\n{done.stderr[-2000:]}", file=sys.stderr, flush=True)
        return "failed"
    print(f"egobench: kernels built in {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    return "child"


def build_scene(dtype: torch.dtype):
    """A small seeded scene in front of a 40 x 24 camera, and two poses -> (gaussians, camera, poses [2, 4, 4])."""
    from egobench.camera.pinhole import Pinhole
    from egobench.render.types import Gaussians

    gen = torch.Generator().manual_seed(0)
    n = 48
    means = torch.cat([torch.rand(n, 2, generator=gen) * 2.0 - 1.0, torch.rand(n, 1, generator=gen) * 2.0 + 2.0], 1)
    gaussians = Gaussians(means=means, quats=torch.randn(n, 4, generator=gen),
                          log_scales=torch.rand(n, 3, generator=gen) - 3.0,
                          opacity_logits=torch.randn(n, generator=gen), colors=torch.rand(n, 3, generator=gen))
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[1, 0, 3] = 0.02
    camera = Pinhole(fx=30.0, fy=30.0, cx=19.5, cy=11.5, width=40, height=24)
    return Gaussians(**{k: v.to(dtype) for k, v in gaussians.tensors().items()}), camera, poses.to(dtype)


def render_every_kernel(dtype: torch.dtype, mode: str) -> None:
    """Renders `build_scene` under one pose and under a rolling shutter, with gradients of every input:
    every kernel of ``mode`` for ``dtype`` runs (compiled, or loaded from numba's cache)."""
    from egobench.render import render

    gaussians, camera, poses = build_scene(dtype)
    rows = (torch.arange(camera.height) >= camera.height // 2).long()[:, None]
    pixel_pose_index = rows.expand(camera.height, camera.width).contiguous()
    for T, index in ((poses[0], None), (poses, pixel_pose_index)):
        inputs = {k: v.clone().requires_grad_(True) for k, v in gaussians.tensors().items()}
        T = T.clone().requires_grad_(True)
        out = render(type(gaussians)(**inputs), camera, T, backend="cpu", mode=mode, pixel_pose_index=index,
                     want_normal=True, absgrad=True)
        maps = [out.rgb, out.alpha, out.depth, out.normal] + ([out.extras["distortion"]] if mode == "2dgs" else [])
        (sum(m.sum() for m in maps) + (out.means2d * 0.0).sum()).backward()


def main(argv: list[str] | None = None) -> int:
    """The child: compile (or load) every kernel of a set into numba's cache, then write the marker."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtype", choices=("float32", "float64"), required=True)
    parser.add_argument("--mode", choices=("3dgs", "2dgs"), required=True)
    args = parser.parse_args(argv)
    setup_threads()
    os.environ[BUILD_ENV] = "in-process"
    render_every_kernel(getattr(torch, args.dtype), args.mode)
    stats = {d.py_func.__name__: {"hits": sum(d.stats.cache_hits.values()),
                                  "misses": sum(d.stats.cache_misses.values())} for d in kernel_dispatchers(args.mode)}
    unused = [name for name, s in stats.items() if not s["hits"] + s["misses"]]
    if unused:
        print(f"kernel_build: kernels {unused} did not run for {args.mode} {args.dtype}", file=sys.stderr)
        return 1
    marker = marker_path(args.dtype, args.mode)
    for stale in marker.parent.glob(f"egobench-build-{args.mode}-{args.dtype}-*.json"):
        stale.unlink(missing_ok=True)
    partial = marker.with_name(marker.name + ".partial")
    partial.write_text(json.dumps({"kernels": stats, "built": time.strftime("%Y-%m-%dT%H:%M:%S")}))
    partial.replace(marker)
    return 0


if __name__ == "__main__":
    sys.exit(main())
