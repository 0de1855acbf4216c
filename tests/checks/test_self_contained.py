"""The project speaks of itself only: no names of work periods, no files it does not contain."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SELF = "tests/checks/test_self_contained.py"  # holds the planted examples
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".sh", ".smk", ".txt", ".cfg", ".json", ".tex", ".html"}
#: a numbered work period: the word for one, a space and a digit
WORK_PERIOD = re.compile(r"\bstops? \d", re.IGNORECASE)
#: the other work-period word, allowed only as pytest's own API
PERIOD_WORD = "ses" + "sion"  # spelled in parts: this file plants examples of what it forbids
PERIOD_NAME = re.compile(PERIOD_WORD, re.IGNORECASE)
PYTEST_API = re.compile(rf'scope="{PERIOD_WORD}"|request\.{PERIOD_WORD}|\b{PERIOD_WORD}\.items\b|def warm_up\({PERIOD_WORD}\b')
#: files outside the repository that a clone does not have; the real sample data (an environment variable with a
#: documented default, ../shared/data) is the one exception
OUTSIDE = re.compile(r"PAPER-NOTES|DESIGN\.md|\.\./shared/(?!data\b)")
#: a scratch folder of the machine a measurement ran on (a record names its command, not its scratch files)
SCRATCH = re.compile(r"(?<![\w.])/work/")


def _text_files() -> list[Path]:
    listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "--cached", "--others", "--exclude-standard"],
                            capture_output=True, text=True, check=True).stdout.split()
    return [REPO / p for p in listed if (Path(p).suffix in TEXT_SUFFIXES or Path(p).name == "Snakefile")
            and (REPO / p).is_file() and p != SELF]


def _hits(pattern: re.Pattern, allowed: re.Pattern | None = None, under: tuple[str, ...] = ()) -> list[str]:
    found = []
    for path in _text_files():
        rel = str(path.relative_to(REPO))
        if under and not rel.startswith(under):
            continue
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if pattern.search(allowed.sub("", line) if allowed else line):
                found.append(f"{rel}:{n}: {line.strip()[:100]}")
    return found


def test_no_work_period_is_named_anywhere():
    """No numbered work periods and no named ones: a reader outside the project's history cannot place them.
    Dates and commits can be placed."""
    assert _hits(WORK_PERIOD) == []
    assert _hits(PERIOD_NAME, PYTEST_API) == []


def test_the_package_docs_and_tests_cite_only_files_in_the_repository():
    assert _hits(OUTSIDE, under=("egobench/", "docs/", "tests/", "README.md", "scripts/")) == []


def test_no_text_names_a_scratch_folder_of_the_machine_it_ran_on():
    assert _hits(SCRATCH) == []


def test_the_guards_catch_a_planted_example_of_each():
    stop = "st" + "op"
    assert WORK_PERIOD.search(f"measured in {stop} 62") and WORK_PERIOD.search(f"after {stop}s 45-49")
    assert not WORK_PERIOD.search("scene_dynamic_range_stops 3.48") and not WORK_PERIOD.search("stop at 1e-4")
    assert PERIOD_NAME.search(PYTEST_API.sub("", f"the fourth GPU {PERIOD_WORD}")) is not None
    assert PERIOD_NAME.search(PYTEST_API.sub("", f'@pytest.fixture(scope="{PERIOD_WORD}")')) is None
    assert OUTSIDE.search("see PAPER-NOTES section 2") and OUTSIDE.search("open ../shared/DESIGN.md")
    assert not OUTSIDE.search("expected at ../shared/data/ (EGOBENCH_SHARED_DATA)")
    assert SCRATCH.search("Command: `/wor" + "k/explore/vig_views.py`") and not SCRATCH.search("a network/work/ path")
