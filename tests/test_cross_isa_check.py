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
