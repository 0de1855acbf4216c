"""Imports at the top: a module's dependencies are read in its first lines.

An import inside a function is allowed only at a named boundary: a library that is loaded late on purpose
(`LAZY_LIBRARIES`), a module whose importers must stay light (`LIGHT_MODULES`), or a CLI verb's `run`
(the command line imports only the module of the verb it runs). The checks parse the source (`ast`), so a
planted example of each kind shows they can fail.
"""

from __future__ import annotations

import ast
from pathlib import Path

from egobench.cli import VERBS

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "egobench"

#: library -> why it is imported where it is used
LAZY_LIBRARIES = {
    "matplotlib": "figures only; its import and backend choice cost ~0.5 s",
    "numba": "the compiled kernels: the kernel thread count must be set before numba loads (host.setup_threads)",
    "llvmlite": "numba's compiler, read for the kernel build key and the host record",
    "projectaria_tools": "an optional dependency (pip install --no-deps), for VRS files only",
    "gsplat": "CUDA only",
    "playwright": "the browser test's driver, optional",
}
#: module (path under the repository) -> why what it imports inside functions stays there
LIGHT_MODULES = {
    "egobench/cli.py": "the command line parses arguments before a verb's imports",
    "egobench/host.py": "imported by the command line before any verb: no torch at import, numba after the thread set-up",
    "egobench/io_utils.py": "imported by the Snakefile's parse (through workflow/): no pandas at import",
    "egobench/workflow/config.py": "the Snakefile's parse imports neither torch nor pandas",
    "egobench/workflow/sensitivity.py": "the Snakefile's parse imports neither torch nor pandas",
    "egobench/analysis/sensitivity.py": "imported by the Snakefile's parse (its output names): no torch, scipy or "
                                        "matplotlib at import",
    "egobench/report/tables.py": "imported by the Snakefile's parse (through analysis/sensitivity.py): no scipy at import",
    "egobench/report/gains.py": "imported by the Snakefile's parse (through analysis/sensitivity.py): no scipy at import",
    "egobench/sim/config.py": "imported by the Snakefile's parse (the scene kinds): no torch at import",
    "egobench/sim/devices.py": "imported by the Snakefile's parse (through sim/config.py): no torch at import",
    "egobench/render/__init__.py": "the backend is chosen per call: the CPU kernels load numba, gsplat needs CUDA",
    "egobench/render/kernel_build.py": "builds the numba kernels in a child process",
    "egobench/sim/textures.py": "the compiled value noise (noise_kernel) loads numba at the first lookup, after the "
                                "thread set-up",
    "egobench/sim/world/scene.py": "the compiled ray caster (raycast_kernel) loads numba at the first cast, after the "
                                   "thread set-up",
}
#: functions that are entry points of a CLI verb
VERB_FUNCTIONS = {"run", "main"}
#: the most function-local imports of egobench's own modules, all at the boundaries above
MAX_OWN_LOCAL = 40


def _verb_paths() -> set[str]:
    paths = set()
    for module, _help in VERBS.values():
        rel = Path(*module.split("."))
        paths.add(str(rel / "__init__.py") if (REPO / rel).is_dir() else f"{rel}.py")
    return paths


def _local_imports(source: str, rel: str):
    """(function, module, own?) for every import inside a function of ``source``."""
    tree = ast.parse(source, rel)
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom):
                names = [("." * node.level) + (node.module or "")]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                yield fn.name, name, name.startswith((".", "egobench"))


def violations(source: str, rel: str, verb_paths: set[str]) -> list[str]:
    """The function-local imports of ``source`` (at ``rel``) that sit at no named boundary."""
    found = []
    for function, module, _own in _local_imports(source, rel):
        if module.split(".")[0] in LAZY_LIBRARIES or rel in LIGHT_MODULES:
            continue
        if rel in verb_paths and function in VERB_FUNCTIONS:
            continue
        found.append(f"{rel}: {function}: {module}")
    return found


def _sources():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield str(path.relative_to(REPO)), path.read_text()


def test_function_local_imports_sit_at_named_boundaries():
    verb_paths = _verb_paths()
    found = [v for rel, source in _sources() for v in violations(source, rel, verb_paths)]
    assert found == [], f"{len(found)} function-local imports outside a named boundary:\n" + "\n".join(found)


def test_few_own_modules_are_imported_inside_functions():
    own = [f"{rel}: {fn}: {m}" for rel, source in _sources() for fn, m, is_own in _local_imports(source, rel)
           if is_own]
    assert len(own) <= MAX_OWN_LOCAL, "\n".join(own)


def test_the_rule_catches_a_planted_example_of_each():
    verb_paths = {"egobench/some_verb.py"}
    planted = "def f():\n    from egobench.model import formation\n    import cv2\n"
    assert len(violations(planted, "egobench/some_module.py", verb_paths)) == 2
    assert violations("def f():\n    import matplotlib.pyplot as plt\n", "egobench/a.py", verb_paths) == []
    assert violations("def f():\n    import torch\n", "egobench/host.py", verb_paths) == []
    verb = "def run(args):\n    from egobench.train import loop\n"
    assert violations(verb, "egobench/some_verb.py", verb_paths) == []
    assert len(violations(verb, "egobench/not_a_verb.py", verb_paths)) == 1
    nested = "class A:\n    def g(self):\n        def h():\n            from . import x\n        return h\n"
    assert len(violations(nested, "egobench/a.py", verb_paths)) >= 1
    assert all(lib in LAZY_LIBRARIES for lib in ("numba", "matplotlib", "gsplat", "projectaria_tools"))
