"""docs/architecture.md matches the tree: every module path it names exists, and every package and
module of egobench is named there (a new module without a line in the package map fails)."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DOC = (REPO / "docs" / "architecture.md").read_text()


def test_every_named_path_exists():
    named = set(re.findall(r"`(egobench/[A-Za-z0-9_/.]+)`", DOC))
    assert len(named) >= 20
    assert [n for n in sorted(named) if not (REPO / n.rstrip("/")).exists()] == []


def test_every_package_and_module_is_named():
    packages = sorted({p.parent.relative_to(REPO).as_posix() for p in (REPO / "egobench").rglob("__init__.py")} - {"egobench"})
    assert [p for p in packages if f"`{p}/`" not in DOC] == []
    # an effect's file is named by the registry (docs/effects.md), not by a line here
    from egobench.effects import EFFECTS

    effect_files = {REPO / "egobench" / "effects" / f"{name}.py" for name in EFFECTS}
    modules = [p for p in (REPO / "egobench").rglob("*.py") if p.name != "__init__.py" and p not in effect_files]
    assert [str(p.relative_to(REPO)) for p in modules if p.name not in DOC] == []


def test_the_imports_picture_is_current():
    """The "Imports" block is what scripts/layers.py reads from the code now (regenerate it with
    `python scripts/layers.py`)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("layers", REPO / "scripts" / "layers.py")
    layers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layers)
    graph = layers.imports()
    assert "train" in graph and "render" in graph["train"] and "train" not in graph["render"]
    assert layers.render_doc(DOC, graph) == DOC, "docs/architecture.md's Imports block is stale"


def test_the_tests_mirror_the_package():
    """tests/<package>/ holds the tests of egobench/<package>/, tests/test_<module>.py those of a top-level module
    egobench/<module>.py, and tests/checks/ the checks that cut across the package."""
    tests = REPO / "tests"
    packages = {p.name for p in (REPO / "egobench").iterdir() if (p / "__init__.py").is_file()}
    folders = {p.name for p in tests.iterdir() if p.is_dir() and p.name not in ("__pycache__", "fixtures")}
    assert folders - packages == {"checks"}
    modules = {p.stem for p in (REPO / "egobench").glob("*.py")}
    assert [p.name for p in tests.glob("test_*.py") if p.stem.removeprefix("test_") not in modules] == []


def test_no_module_over_800_lines_and_no_docs_page_over_400():
    """Rooms of a readable size: every module of egobench/ at most 800 lines, every page of docs/ at most 400 (the
    history of a measurement lives in its dated record under results/, not in docs/)."""
    long_modules = [(str(p.relative_to(REPO)), n) for p in (REPO / "egobench").rglob("*.py")
                    if (n := len(p.read_text().splitlines())) > 800]
    long_pages = [(p.name, n) for p in (REPO / "docs").glob("*.md") if (n := len(p.read_text().splitlines())) > 400]
    assert (long_modules, long_pages) == ([], [])
