"""scripts/cross_isa_check.py: the parts that do not need a second machine."""

import runpy
from pathlib import Path

SCRIPT = runpy.run_path(str(Path(__file__).parents[2] / "scripts" / "cross_isa_check.py"), run_name="x")


def test_recordings_are_compared_file_by_file(tmp_path):
    """cross_isa_check's recording comparison: equal trees are identical; one changed byte and one extra
    file are both named."""
    compare = SCRIPT["compare_recordings"]
    for name in ("a", "b"):
        (tmp_path / name / "sub").mkdir(parents=True)
        (tmp_path / name / "sub" / "x.bin").write_bytes(b"\x00\x01")
        (tmp_path / name / "y.json").write_text("{}")
    assert compare(tmp_path / "a", tmp_path / "b") == {"identical": True, "files": 2, "n_differing": 0,
                                                      "differing": []}
    (tmp_path / "b" / "sub" / "x.bin").write_bytes(b"\x00\x02")
    (tmp_path / "b" / "z.txt").write_text("new")
    assert compare(tmp_path / "a", tmp_path / "b") == {"identical": False, "files": 3, "n_differing": 2,
                                                      "differing": ["sub/x.bin", "z.txt"]}


def test_a_recording_does_not_depend_on_the_blas_kernels(tmp_path):
    """The simulator computes its poses and points without numpy's OpenBLAS (`portable_math`): a small recording
    simulated with OpenBLAS forced onto its SSE3 kernels (another CPU model's summation order) equals the default
    one byte for byte, but for recording.json's wall time. Holds on every x86-64 machine: it fails only where a
    BLAS product reaches the files (numpy's ``@`` in the head motion's rotations did, and made Intel and AMD hosts
    write other trajectories). Bit identity under an emulated AVX2 CPU is machine-dependent: the script reports it."""
    import json

    SCRIPT["simulate"](tmp_path / "default", 32, 4)  # this process: OpenBLAS's own kernels for this CPU
    SCRIPT["_child"]("sse3", {"OPENBLAS_CORETYPE": "Prescott"}, tmp_path, SCRIPT["SIM_CHILD"], str(tmp_path / "sse3"),
                     "32", "4")
    res = SCRIPT["compare_recordings"](tmp_path / "default", tmp_path / "sse3")
    assert res["files"] > 40 and res["differing"] == ["recording.json"]
    meta = [json.loads((tmp_path / name / "recording.json").read_text()) for name in ("default", "sse3")]
    for m in meta:
        m.pop("simulation_time_s")
    assert meta[0] == meta[1]


def test_the_simulator_calls_no_torch_operation_that_runs_in_mkl(tmp_path):
    """torch's matrix products, inverses and determinants run in MKL, which picks its kernels by CPU vendor (AVX-512
    code on Intel, other code on AMD); the simulator's poses, rays and normals use `portable_math.matmul` / `vecdot`
    and `geometry.det3` instead. Every aten operation of a small simulation of each scene kind is recorded: none of
    them is one that reaches BLAS or LAPACK."""
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode

    from tests.helpers import small_recording

    blas = {"mm", "bmm", "addmm", "baddbmm", "addbmm", "matmul", "mv", "addmv", "dot", "vdot", "einsum", "tensordot",
            "convolution", "_convolution", "inverse"}
    seen: set[str] = set()

    class Record(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            seen.add(str(func.overloadpacket).split(".")[-1])
            return func(*args, **(kwargs or {}))

    with Record():
        for kind in ("outdoor", "indoor", "object", "quest3"):
            small_recording(tmp_path / kind, kind, 0, n_frames=3, size=16)
    assert "mul" in seen and "add" in seen  # the mode saw the arithmetic
    elementwise_linalg = {"linalg_cross", "linalg_vector_norm"}  # no BLAS or LAPACK behind these
    assert sorted(op for op in seen if op in blas or "linalg" in op and op not in elementwise_linalg) == []


def test_reference_digests_are_compared_per_recording():
    """`compare_digests`: per scene kind, identical when every file's digest agrees; a changed digest and a file on
    one side only are named. The committed reference (an AMD host's) covers the four scene kinds."""
    import json

    compare = SCRIPT["compare_digests"]
    ours = {"a": {"x.png": "1", "y.csv": "2"}, "b": {"z.json": "3"}}
    assert compare(ours, ours) == {"a": {"identical": True, "files": 2, "differing": []},
                                   "b": {"identical": True, "files": 1, "differing": []}}
    theirs = {"a": {"x.png": "1", "y.csv": "9", "w.npy": "4"}, "b": {"z.json": "3"}}
    assert compare(ours, theirs)["a"] == {"identical": False, "files": 3, "differing": ["w.npy", "y.csv"]}
    ref = json.loads((Path(__file__).parents[2] / "results" / "cross_isa" / "recording_digests.json").read_text())
    assert sorted(ref["digests"]) == sorted(SCRIPT["REFERENCE_CASES"]) and "cpu_model" in ref["host"]
