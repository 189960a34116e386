"""The suite's own layout (tests/conftest.py): test files in phase folders, none sharing a
name (pytest imports them by their name alone: no ``__init__.py``), and no test module
importing another (what tests share lives in the helper modules of tests/ or in a
folder's conftest)."""

from __future__ import annotations

import re
from collections import Counter

from repo_paths import REPO

TESTS = REPO / "tests"
#: The folders test files live in: the package's phases, and ``top`` for what spans them.
PHASE_FOLDERS = {"model", "usd", "select", "engine", "run", "evaluate", "top"}
#: ``import test_x`` or ``from test_x import ...``, at any indentation.
IMPORT_OF_A_TEST_MODULE = re.compile(r"\s*(from|import)\s+test_\w+")


def _test_files():
    return sorted(TESTS.rglob("test_*.py"))


def test_test_files_sit_in_phase_folders_under_names_of_their_own():
    files = _test_files()
    folders = {p.parent.relative_to(TESTS).as_posix() for p in files}
    assert folders <= PHASE_FOLDERS, folders - PHASE_FOLDERS
    shared = [name for name, n in Counter(p.name for p in files).items() if n > 1]
    assert not shared
    assert not list(TESTS.rglob("__init__.py"))


def test_no_test_module_imports_another():
    found = [
        f"{path.relative_to(TESTS)}:{n}: {line.strip()}"
        for path in [*TESTS.glob("*.py"), *_test_files(), *TESTS.glob("*/conftest.py")]
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if IMPORT_OF_A_TEST_MODULE.match(line)
    ]
    assert not found
