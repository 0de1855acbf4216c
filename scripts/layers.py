"""The picture of egobench's layers, generated from the code (docs/architecture.md, "Imports").

    python scripts/layers.py            # rewrite the block in docs/architecture.md
    python scripts/layers.py --check    # exit 1 when the block is out of date

One row per unit (a package under egobench/ or a top-level module): the units its code imports,
at module level or inside functions (read from the source with `ast`, nothing imported), and the
pairs of units that import each other. Imports by name at run time (`importlib`, the CLI's verb
registry) are not seen.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"
BEGIN, END = "<!-- layers:begin (scripts/layers.py) -->", "<!-- layers:end -->"


def unit_of(module: str) -> str | None:
    """'egobench.train.loop' -> 'train'; 'egobench.report.tables' -> 'tables'; other packages -> None."""
    parts = module.split(".")
    return parts[1] if parts[0] == "egobench" and len(parts) > 1 else None


def imports(root: Path = REPO / "egobench") -> dict[str, set[str]]:
    """unit -> the other units its source files import."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        unit = unit_of(".".join(rel.parts))
        if unit is None or unit == "__init__":
            continue
        targets = graph.setdefault(unit, set())
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
            if isinstance(node, ast.ImportFrom) and node.module == "egobench":
                names = [f"egobench.{a.name}" for a in node.names]
            targets.update(u for u in map(unit_of, names) if u and u != unit and u != "__init__")
    return {u: {d for d in deps if d in graph} for u, deps in graph.items()}  # units only (not egobench.__version__)


def circles(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Pairs of units that import each other (directly)."""
    return sorted({tuple(sorted((a, b))) for a, deps in graph.items() for b in deps if a in graph.get(b, set())})


def block(graph: dict[str, set[str]]) -> str:
    rows = [BEGIN, "", "| unit | imports (egobench units) |", "|---|---|"]
    rows += [f"| `{u}` | {', '.join(f'`{d}`' for d in sorted(deps)) or '-'} |" for u, deps in sorted(graph.items())]
    pairs = circles(graph)
    rows += ["", f"Units that import each other: {', '.join(f'`{a}` <-> `{b}`' for a, b in pairs) or 'none'}.", "", END]
    return "\n".join(rows)


def render_doc(text: str, graph: dict[str, set[str]]) -> str:
    if BEGIN not in text or END not in text:
        raise ValueError(f"{DOC}: markers {BEGIN!r} ... {END!r} not found")
    head, rest = text.split(BEGIN, 1)
    return head + block(graph) + rest.split(END, 1)[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args()
    text = DOC.read_text()
    new = render_doc(text, imports())
    if args.check:
        return 0 if new == text else 1
    DOC.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
