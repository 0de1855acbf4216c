"""Do CPU training results travel between machines? Train one run under emulated CPUs and compare.

    python scripts/cross_isa_check.py --out results/cross_isa [--iterations 300] [--size 64]

One recording (outdoor, seed 0) is simulated once; then 'ours' (seed 0) is trained and evaluated in
a fresh process per setting, each with its own numba cache:

- ``host``: nothing pinned (this machine's CPU: numba's LLVM host target, torch's widest kernels);
- ``avx2``: an AVX2-only x86-64 machine emulated on this one (numba compiled for ``znver3``, torch's
  AVX2 kernels, MKL and oneDNN capped at AVX2, glibc's AVX-512 variants off, numpy's AVX-512 code paths
  off and its OpenBLAS on its AVX2 (Haswell) kernels: until 2026-11-29 numpy's were left on);
- ``portable``: PORTABLE (numba ``generic``, torch ``default``, MKL CBWR, oneDNN SSE4.1);
- ``portable_avx2``: the portable settings on the emulated AVX2 machine;
- ``blas_sse3`` (recordings only): numpy's OpenBLAS on its SSE3 (``Prescott``) kernels and torch's MKL capped at
  SSE4.2: BLAS kernels of another CPU model, which a recording must not depend on.

Writes ``cross_isa.json``: per setting the host info, iterations/s (wall time of the training
iterations, one thread), held-out PSNR, and per pair the largest parameter difference and the PSNR
difference. ``--simulate-each``: the recording is also simulated again under every setting, and each is
compared file by file with the host's (``recordings``). ``--recordings-only``: only that, no training (about
a minute). ``--reference-digests FILE``: simulate the four scene kinds' reference recordings (`REFERENCE_CASES`)
and compare every file's digest with FILE, written on another machine (``--write-reference-digests FILE``
writes it; `results/cross_isa/recording_digests.json` is an Intel Xeon host's): the cross-vendor check
that needs one machine at a time. Exploratory: one seed, one scene. Bit identity under an emulated CPU is a property of the machine
this runs on (on an AMD CPU, MKL ignores some of these settings), so it is measured here and reported, not
asserted by a test (docs/reproducibility.md).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

from egobench.host import host_info, numpy_avx512_targets

#: numba's generic x86-64 target, torch's non-vectorised kernels, MKL's reproducible mode, oneDNN at SSE4.1
PORTABLE = {"NUMBA_CPU_NAME": "generic", "ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "COMPATIBLE",
            "ONEDNN_MAX_CPU_ISA": "SSE41"}
#: numpy's AVX-512 code paths (names of this numpy), switched off in the AVX2 setting
NUMPY_AVX512 = numpy_avx512_targets()
AVX2 = {"NUMBA_CPU_NAME": "znver3", "ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "ONEDNN_MAX_CPU_ISA": "AVX2", "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX512VL,-AVX512BW,-AVX512DQ,-AVX512CD",
        "OPENBLAS_CORETYPE": "Haswell",
        **({"NPY_DISABLE_CPU_FEATURES": " ".join(NUMPY_AVX512)} if NUMPY_AVX512 else {})}
#: BLAS kernels of another CPU model: numpy's OpenBLAS on SSE3 kernels, torch's MKL capped at SSE4.2
BLAS_SSE3 = {"OPENBLAS_CORETYPE": "Prescott", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"}

CHILD = r"""
import json, sys, numpy as np, torch
from dataclasses import replace
from egobench.host import host_info
from egobench.train.config import preset_config
from egobench.train.loop import train
from egobench.evaluate import evaluate
rec, out, iters = sys.argv[1], sys.argv[2], int(sys.argv[3])
torch.set_num_threads(1)
cfg = replace(preset_config("cpu").scaled_to(iters), seed=0)
res = train(rec, "ours", cfg, out, progress=False)
ev = evaluate(rec, out, save_renders=False)
ck = torch.load(out + "/checkpoint.pt", weights_only=True)
np.savez(out + "/params.npz", **{k: v.numpy() for k, v in ck["params"].items()})
print(json.dumps({"host": host_info(), "iters_per_s": res.iters_per_s, "psnr": ev["metrics"]["psnr"],
                  "n_gaussians": res.num_gaussians}))
"""


def simulate(rec: str | Path, size: int, n_frames: int = 32) -> None:
    """The recording every setting trains on: outdoor, seed 0, ``size`` px, ``n_frames`` frames."""
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    simulate_recording(SimConfig.from_overrides("outdoor", 0, {"rectified_size": size, "n_frames": n_frames}),
                       rec, progress=False)


#: `simulate` in a child: argv rec, size, n_frames
SIM_CHILD = f"""
import runpy, sys
runpy.run_path({str(Path(__file__).resolve())!r}, run_name="child")["simulate"](sys.argv[1], *map(int, sys.argv[2:]))
"""


def _child(name: str, env_extra: dict, out: Path, code: str, *argv: str) -> str:
    """Runs ``code`` in a fresh Python under setting ``name`` (one thread, its own numba cache) -> its stdout."""
    env = {k: v for k, v in os.environ.items() if k not in {**AVX2, **PORTABLE, **BLAS_SSE3}}
    env.update(env_extra, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1",
               NUMBA_CACHE_DIR=str(out / "numba_cache" / name))
    proc = subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"setting {name}: {proc.stderr[-3000:]}")
    return proc.stdout


def run_setting(name: str, env_extra: dict, rec: Path, out: Path, iterations: int) -> dict:
    stdout = _child(name, env_extra, out, CHILD, str(rec), str(out / "runs" / name), str(iterations))
    return json.loads(stdout.strip().splitlines()[-1])


#: the recordings whose file digests `--write-reference-digests` records: each scene kind, seed 0, 32 px, 4 frames
REFERENCE_CASES = ("outdoor", "indoor", "object", "quest3")


def reference_digests(out: Path) -> dict[str, dict[str, str]]:
    """Simulates `REFERENCE_CASES` under ``out`` -> {kind: {file: SHA-256}} (recording.json left out: it holds
    the wall time)."""
    from egobench.sim.capture import simulate_recording
    from egobench.sim.config import SimConfig

    res = {}
    for kind in REFERENCE_CASES:
        simulate_recording(SimConfig.from_overrides(kind, 0, {"rectified_size": 32, "n_frames": 4}), out / kind,
                           progress=False)
        res[kind] = {k: v for k, v in file_digests(out / kind).items() if k != "recording.json"}
    return res


def compare_digests(ours: dict, theirs: dict) -> dict:
    """Per kind: identical?, files compared, and the files whose digests differ or exist on one side only."""
    out = {}
    for kind in sorted(ours.keys() | theirs.keys()):
        a, b = ours.get(kind, {}), theirs.get(kind, {})
        differing = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
        out[kind] = {"identical": not differing, "files": len(a.keys() | b.keys()), "differing": differing[:20]}
    return out


def file_digests(root: Path) -> dict[str, str]:
    """Every file under root -> its SHA-256 (keys: paths relative to root)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def compare_recordings(a: Path, b: Path) -> dict:
    """Two recording folders file by file -> identical?, the file count, and the differing files."""
    da, db = file_digests(a), file_digests(b)
    differing = sorted(k for k in da.keys() | db.keys() if da.get(k) != db.get(k))
    return {"identical": not differing, "files": len(da.keys() | db.keys()), "n_differing": len(differing),
            "differing": differing[:20]}


def simulate_each(settings: dict, out: Path, size: int) -> dict:
    """The recording simulated under every setting, each compared with the host's and with the one the
    parent process simulated (a control: the same settings must give the same bytes)."""
    for name, env in settings.items():
        _child(name, env, out, SIM_CHILD, str(out / "recordings" / name), str(size))
    res = {"host (child) vs parent": compare_recordings(out / "recordings" / "host", out / "recording")}
    res.update({f"{name} vs host": compare_recordings(out / "recordings" / name, out / "recordings" / "host")
                for name in settings if name != "host"})
    return res


def compare(out: Path, a: str, b: str) -> dict:
    import numpy as np

    pa, pb = (np.load(out / "runs" / n / "params.npz") for n in (a, b))
    if any(pa[k].shape != pb[k].shape for k in pa.files):
        return {"identical": False, "max_abs_diff": None, "note": "different Gaussian counts"}
    diff = max(float(np.abs(pa[k].astype(np.float64) - pb[k]).max()) for k in pa.files)
    return {"identical": all(np.array_equal(pa[k], pb[k]) for k in pa.files), "max_abs_diff": diff}


def _reference_check(out: Path, write: str | None, against: str | None) -> int:
    """`--write-reference-digests` / `--reference-digests`: prints (and writes under ``out``) the comparison."""
    digests = reference_digests(out / "reference")
    record = {"host": host_info(), "digests": digests}
    if write:
        Path(write).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
        print(f"wrote {write}: {sum(map(len, digests.values()))} files of {len(digests)} recordings")
    if against:
        theirs = json.loads(Path(against).read_text())
        result = {"host": host_info(), "reference_host": theirs["host"],
                  "recordings": compare_digests(digests, theirs["digests"])}
        (out / "reference_comparison.json").write_text(json.dumps(result, indent=1))
        for kind, r in result["recordings"].items():
            print(kind, r)
        return 0 if all(r["identical"] for r in result["recordings"].values()) else 1
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--simulate-each", action="store_true",
                    help="also simulate the recording under every setting and compare the files with the host's")
    ap.add_argument("--recordings-only", action="store_true",
                    help="only simulate the recording under every setting and compare (no training)")
    ap.add_argument("--write-reference-digests", metavar="FILE", help="write the reference recordings' digests")
    ap.add_argument("--reference-digests", metavar="FILE",
                    help="compare the reference recordings' digests with FILE (written on another machine)")
    args = ap.parse_args()
    out = Path(args.out)
    if args.write_reference_digests or args.reference_digests:
        return _reference_check(out, args.write_reference_digests, args.reference_digests)
    rec = out / "recording"
    if not rec.exists():
        simulate(rec, args.size)
    settings = {"host": {}, "avx2": AVX2, "portable": dict(PORTABLE), "portable_avx2": {**AVX2, **PORTABLE}}
    if args.recordings_only:
        record = {"host": host_info(), "size_px": args.size,
                  "recordings": simulate_each({**settings, "blas_sse3": BLAS_SSE3}, out, args.size)}
        for k, v in record["recordings"].items():
            print(k, v)
        out.mkdir(parents=True, exist_ok=True)
        (out / "cross_isa_recordings.json").write_text(json.dumps(record, indent=1))
        return 0
    results = {name: run_setting(name, env, rec, out, args.iterations) for name, env in settings.items()}
    for name, r in results.items():
        print(f"{name}: {r['iters_per_s']:.1f} it/s, PSNR {r['psnr']:.4f} dB, {r['host']}")
    pairs = {f"{a} vs {b}": {**compare(out, a, b), "psnr_diff_db": results[a]["psnr"] - results[b]["psnr"]}
             for a, b in (("host", "avx2"), ("portable", "portable_avx2"), ("host", "portable"))}
    for k, v in pairs.items():
        print(k, v)
    record = {"settings": results, "pairs": pairs, "iterations": args.iterations, "size_px": args.size}
    if args.simulate_each:
        record["recordings"] = simulate_each(settings, out, args.size)
        for k, v in record["recordings"].items():
            print(k, v)
    (out / "cross_isa.json").write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
