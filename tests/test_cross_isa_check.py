"""scripts/cross_isa_check.py: the parts that do not need a second machine."""

import runpy
from pathlib import Path

SCRIPT = runpy.run_path(str(Path(__file__).parents[1] / "scripts" / "cross_isa_check.py"), run_name="x")


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


def test_a_recording_is_the_same_bytes_on_the_emulated_avx2_machine(tmp_path):
    """The simulator's outputs do not follow numpy's AVX-512 code paths, its OpenBLAS kernels, torch's, MKL's,
    oneDNN's or glibc's vector variants: a small recording simulated under the script's AVX2 settings equals
    the host's byte for byte, but for recording.json's wall time (docs/reproducibility.md, stop 62). On an
    AVX2-only machine both settings are the same machine, and the test asserts nothing new."""
    import json

    for name, env in (("host", {}), ("avx2", SCRIPT["AVX2"])):
        SCRIPT["_child"](name, env, tmp_path, SCRIPT["SIM_CHILD"], str(tmp_path / name), "32", "4")
    res = SCRIPT["compare_recordings"](tmp_path / "host", tmp_path / "avx2")
    assert res["files"] > 40 and res["differing"] == ["recording.json"]
    meta = [json.loads((tmp_path / name / "recording.json").read_text()) for name in ("host", "avx2")]
    for m in meta:
        m.pop("simulation_time_s")
    assert meta[0] == meta[1]
