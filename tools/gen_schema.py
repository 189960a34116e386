"""Generate the codeless Phrt schema plugin (``phrt_usd/usd/plugin/``) with usd-core's own
``usdGenSchema`` (``pxr.Usd.usdGenSchema``; it needs jinja2, from the ``dev`` extra).

usdGenSchema reads ``schemas/phrt/schema.usda`` (codeless: ``skipCodeGeneration`` in its
``GLOBAL`` customData) and writes ``generatedSchema.usda`` and ``plugInfo.json``. It runs in
a fresh temporary directory with our plugInfo template (``schemas/phrt/templates/``), so
that the plugin files depend on the sources only, never on the files they replace:

* the schema library's plugin entry (``phrtUsd``, a resource plugin), whose ``Types``
  usdGenSchema fills in from the schema classes;
* the Phrt validators' python plugin entry (``phrt_usd.usd.validators``): the
  ``Validators`` metadata that any USD tool finds through ``PXR_PLUGINPATH_NAME``, and
  the module USD imports to run them. A validator's ``schemaTypes`` names the registered
  type (``PhrtUsdRenderSettingsAPI``), not its alias, or USD never calls it.

Usage::

    uv run python tools/gen_schema.py           # (re)write phrt_usd/usd/plugin/*
    uv run python tools/gen_schema.py --check   # exit 1 if the checked-in files are stale

``--out DIR`` writes (or checks) another plugin folder. Exit codes: 0 ok, 1 stale files
(``--check``), 2 usdGenSchema could not run.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SCHEMA_SOURCE = REPO / "schemas" / "phrt" / "schema.usda"
TEMPLATES = REPO / "schemas" / "phrt" / "templates"
PLUGIN_DIR = REPO / "phrt_usd" / "usd" / "plugin"
#: What usdGenSchema writes for a codeless schema library.
GENERATED_FILES = ("generatedSchema.usda", "plugInfo.json")


class GenerationFailed(Exception):
    """usdGenSchema could not run or failed; the message is one line."""


def generate(out_dir: Path) -> dict[str, str]:
    """Run usdGenSchema on the schema source into ``out_dir`` (which must be empty or new,
    so no earlier plugInfo.json is merged in); the generated files' texts by name."""
    if importlib.util.find_spec("jinja2") is None:
        raise GenerationFailed("usdGenSchema needs jinja2 (the dev group): uv sync")
    env = dict(os.environ)
    # A Phrt plugin on the plugin path (possibly a stale one) must not define the types
    # usdGenSchema is about to generate.
    env.pop("PXR_PLUGINPATH_NAME", None)
    env["TF_ENV_SETTING_ALERTS_ENABLED"] = "0"  # no banner about usdGenSchema's own setting
    cmd = [sys.executable, "-m", "pxr.Usd.usdGenSchema", "--quiet",
           "--templates", str(TEMPLATES), str(SCHEMA_SOURCE), str(out_dir)]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines() or [f"exit {proc.returncode}"]
        raise GenerationFailed(f"usdGenSchema failed: {lines[-1].strip()}")
    texts = {}
    for name in GENERATED_FILES:
        path = out_dir / name
        if not path.is_file():
            raise GenerationFailed(f"usdGenSchema wrote no {name}")
        texts[name] = path.read_text()
    return texts


def stale_files(plugin_dir: Path, texts: dict[str, str]) -> list[Path]:
    """The plugin files that differ from freshly generated ones (or are missing)."""
    return [
        plugin_dir / name
        for name, text in texts.items()
        if not (plugin_dir / name).is_file() or (plugin_dir / name).read_text() != text
    ]


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the plugin files are stale")
    parser.add_argument("--out", type=Path, default=PLUGIN_DIR, help="plugin folder")
    args = parser.parse_args(argv)
    plugin_dir = args.out.resolve()
    try:
        with tempfile.TemporaryDirectory(prefix="phrt-gen-schema-") as tmp:
            texts = generate(Path(tmp))
    except (GenerationFailed, OSError, subprocess.SubprocessError) as exc:
        print(f"gen_schema: {exc}", file=sys.stderr)
        return 2
    stale = stale_files(plugin_dir, texts)
    if args.check:
        for path in stale:
            print(f"stale: {_shown(path)} (run uv run python tools/gen_schema.py)", file=sys.stderr)
        return 1 if stale else 0
    from phrt_usd.atomic import write_text_atomic

    for path in stale:
        write_text_atomic(path, texts[path.name])
        print(f"wrote {_shown(path)}")
    if not stale:
        print(f"up to date: {_shown(plugin_dir)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
