"""The package's layout rules: phases import only earlier phases, no import circles, no
module or class too large to read in one sitting."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from repo_paths import PACKAGE

ROOT = "phrt_usd"
#: Phase of each subpackage in the order a frame walks them; a module may import its own
#: phase and earlier ones only. Top-level modules (cli, cluster, api) come last; the base
#: every phase uses (the package's version and OpenGL default, errors, the value checks,
#: the one atomic writer, threads, kernels) first.
PHASES = {
    "base": 0,
    "errors": 0,
    "checks": 0,
    "atomic": 0,
    "threads": 0,
    "kernels": 0,
    "progress": 0,
    "small_pages": 0,
    "model": 1,
    "usd": 2,
    "select": 3,
    "engine": 4,
    "bench": 5,
    "run": 5,
    "evaluate": 6,
}
TOP = 7
#: The package root is a facade on top: ``phrt_usd.render(...)`` and ``phrt_usd.open(...)``
#: forward to the top-level API. Its one import of the API, on first use (PEP 562), never
#: when the package is, is the one edge left out of the graph; a module below the top
#: that imports the root itself (not one of its modules) imports back up into it.
ROOT_FACADE = ("phrt_usd.api",)
#: Reading limits (lines): a module a stranger reads in one go, a class one role wide.
MAX_MODULE_LINES = 800
MAX_CLASS_LINES = 450
#: Modules of the plain-data phase never touch USD, OpenGL or Embree.
MODEL_FORBIDDEN = ("pxr", "OpenGL", "pyrender", "embreex")


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _phase(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1:
        return TOP  # the package root: the API's facade (ROOT_FACADE)
    return PHASES.get(parts[1], TOP)


def _imports(path: Path, modules: dict[str, Path]) -> list[str]:
    """The phrt_usd modules the file imports anywhere (lazy imports included): ``from M
    import a`` imports the module ``M.a`` when there is one, else a name of ``M``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith(ROOT):
            names = [f"{node.module}.{a.name}" for a in node.names]
            found += [n for n in names if n in modules]
            if any(n not in modules for n in names):
                found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith(ROOT)]
    return [name for name in found if name in modules]


def _graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports, but for the root's facade edge."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        targets = set(_imports(path, modules)) - {name}
        if name == ROOT:
            targets -= set(ROOT_FACADE)
        graph[name] = targets
    return graph


def up_arrows() -> list[str]:
    """Imports from a module into a later phase than its own (the root included)."""
    return [f"{name} imports {target}" for name, targets in sorted(_graph().items())
            for target in sorted(targets) if _phase(target) > _phase(name)]  # fmt: skip


@pytest.mark.slow
def test_phases_import_only_earlier_phases():
    wrong = up_arrows()
    assert not wrong, "\n".join(wrong)


@pytest.mark.slow
def test_no_import_circles():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                raise AssertionError("import circle: " + " -> ".join([*stack, nxt]))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node)


@pytest.mark.slow
def test_probe_imports_back_up_into_the_root():
    """The package root is a facade on top of every phase: the version and the OpenGL
    default every phase reads are in phrt_usd.base (phase 0), so no module below the top
    imports the root itself. Threshold 0: one such import is a way round the phases."""
    into_root = [arrow for arrow in up_arrows() if arrow.endswith(f" imports {ROOT}")]
    assert into_root == []
    base = _modules()["phrt_usd.base"]
    assert _imports(base, _modules()) == []  # the base imports nothing of the package


def test_model_is_plain_data():
    for name, path in _modules().items():
        if name.startswith("phrt_usd.model"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                bad = [n for n in names if n.split(".")[0] in MODEL_FORBIDDEN]
                assert not bad, f"{name} imports {bad}"


@pytest.mark.slow
def test_modules_and_classes_fit_in_one_reading():
    big = []
    for name, path in _modules().items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            big.append(f"{name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_CLASS_LINES:
                    big.append(f"{name}.{node.name}: {lines} lines")
    assert not big, "\n".join(big)
