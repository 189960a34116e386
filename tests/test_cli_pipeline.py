"""The CLI as pipelines drive it: version, progress in logs, verbosity, composition
controls (session layers, variants, population masks) recorded with the run."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from scenes import mirror_gallery_stage

import phrt_usd

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
RENDER = ["--budget-rays", "600", "--resolution", "32x24"]


def _run(*args: str) -> subprocess.CompletedProcess:
    # stderr is a pipe here, never a terminal: what a render farm's log sees.
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    return mirror_gallery_stage(tmp_path_factory.mktemp("cli") / "gallery.usda", frames=4)


def test_version():
    done = _run("--version")
    assert done.returncode == 0 and done.stdout.strip() == f"phrt {phrt_usd.__version__}"


def test_progress_lines_without_a_terminal(gallery, tmp_path):
    """Default: a line at the start and at the end (with a percentage); -v: one per frame;
    -q: nothing but errors."""
    done = _run("render", str(gallery), "--out", str(tmp_path / "a"), "--frames", "1:4",
                *RENDER, "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if re.search(r"\d+/4 frames \(\d+ %\)", ln)]
    assert lines and lines[-1].endswith("4/4 frames (100 %)"), done.stderr
    verbose = _run("-v", "render", str(gallery), "--out", str(tmp_path / "b"), "--frames",
                   "1:4", *RENDER)  # fmt: skip
    assert len(re.findall(r"\d/4 frames", verbose.stderr)) == 4, verbose.stderr
    quiet = _run("-q", "render", str(gallery), "--out", str(tmp_path / "c"), "--frames",
                 "1:4", *RENDER, "--json")  # fmt: skip
    assert quiet.returncode == 0 and "frames" not in quiet.stderr, quiet.stderr
    assert json.loads(quiet.stdout)["frames"] == 4
    both = _run("-v", "-q", "render", str(gallery))
    assert both.returncode == 2 and "exclude" in both.stderr
