"""The package's layout rules: phases import only earlier phases, no import circles, no
module or class too large to read in one sitting."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "phrt_usd"
#: Phase of each subpackage in the order a frame walks them; a module may import its own
#: phase and earlier ones only. Top-level modules (cli, cluster, api) come last; the base
#: every phase uses (errors, the one atomic writer, the package root) first.
PHASES = {
    "errors": 0,
    "atomic": 0,
    "threads": 0,
    "kernels": 0,
    "model": 1,
    "usd": 2,
    "select": 3,
    "engine": 4,
    "bench": 5,
    "run": 5,
    "evaluate": 6,
}
TOP = 7
#: The package root's facade, the one exception: ``phrt_usd.render(...)`` and
#: ``phrt_usd.open(...)`` forward to the top-level API, which is imported on first use
#: (PEP 562), never when the package is.
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
        return 0  # the package root: version and plugin registration
    return PHASES.get(parts[1], TOP)


def _imports(path: Path) -> list[str]:
    """Absolute phrt_usd modules imported anywhere in the file (lazy imports included)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("phrt_usd"):
            found.append(node.module)
            found += [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("phrt_usd")]
    return found


def test_phases_import_only_earlier_phases():
    modules = _modules()
    wrong = []
    for name, path in modules.items():
        for target in _imports(path):
            if target not in modules:
                continue  # a name imported from a module, not a module
            if name == "phrt_usd" and target in ROOT_FACADE:
                continue
            if target != "phrt_usd" and _phase(target) > _phase(name):
                wrong.append(f"{name} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_no_import_circles():
    modules = _modules()
    graph = {name: {t for t in _imports(path) if t in modules and t != name and t != "phrt_usd"}
             for name, path in modules.items()}  # fmt: skip
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                raise AssertionError("import circle: " + " -> ".join([*stack, nxt]))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node)


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
