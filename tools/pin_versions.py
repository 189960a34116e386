"""Pin the exact versions of our own set-up, tests and CI: resolve pyproject.toml's ranges
(every extra and group, Python 3.11-3.13) afresh and write each resolved package as
``name==version`` into ``[tool.uv] constraint-dependencies``.

    uv run python tools/pin_versions.py [--check]

The package's own requirements stay ranges (what a pipeline's Python can share with us);
the pins apply only in this checkout. A lock file would do the same but records the
registry's addresses, which this repository does not hold. ``--check``: exit 1 when the
pins differ from a fresh resolution (nothing written).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PYPROJECT = REPO / "pyproject.toml"
#: The block this tool owns in pyproject.toml.
BLOCK = re.compile(r"(constraint-dependencies = \[\n)(.*?)(\])", re.DOTALL)


def resolve() -> list[str]:
    """``name==version`` of every registry package a fresh resolution of the ranges
    picks, sorted by name."""
    with tempfile.TemporaryDirectory() as tmp:
        project = Path(tmp)
        text = BLOCK.sub(r"\1\3", PYPROJECT.read_text())  # resolve the ranges, unpinned
        (project / "pyproject.toml").write_text(text)
        shutil.copy(REPO / "README.md", project / "README.md")
        subprocess.run(["uv", "lock", "-q"], cwd=project, check=True)
        lock = tomllib.loads((project / "uv.lock").read_text())
    found = [p for p in lock["package"] if "registry" in p.get("source", {})]
    names = [p["name"] for p in found]
    pins = set()
    for p in found:
        pin = f"{p['name']}=={p['version']}"
        if names.count(p["name"]) > 1:  # one version per Python range: pin each to its own
            pin += "; " + " or ".join(
                f"({m})".replace('"', "'") for m in p["resolution-markers"]
            )
        pins.add(pin)
    return sorted(pins, key=str.lower)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare only; exit 1 on change")
    args = parser.parse_args()
    pins = resolve()
    text = PYPROJECT.read_text()
    block = "".join(f'    "{pin}",\n' for pin in pins)
    updated = BLOCK.sub(lambda m: m.group(1) + block + m.group(3), text)
    if args.check:
        same = updated == text
        print("pins are current" if same else "pins differ from a fresh resolution")
        return 0 if same else 1
    PYPROJECT.write_text(updated)
    print(f"pinned {len(pins)} packages in {PYPROJECT.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
