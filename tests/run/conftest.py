"""Fixtures of the run phase's tests (run directories, images, products, resume)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import OpenImageIO as oiio
import pytest
from pxr import Sdf


def _open_finished_files(out: Path) -> int:
    """Open every finished file in a run directory; returns how many were checked."""
    n = 0
    for path in list(out.rglob("*")):
        if path.name.startswith(".") or not path.is_file():
            continue  # temp files of an atomic write in progress
        try:
            if path.suffix in (".exr", ".png"):
                buf = oiio.ImageBuf(str(path))
                assert not buf.has_error and buf.spec().width > 0, path
            elif path.suffix == ".json":
                json.loads(path.read_text())
            elif path.suffix == ".usda":
                assert Sdf.Layer.OpenAsAnonymous(str(path)) is not None, path
        except FileNotFoundError:
            continue  # replaced between listing and opening
        n += 1
    return n


@pytest.fixture
def check_readable() -> Callable[[Path], int]:
    """``check_readable(out)``: opens every finished file under a run directory (images,
    JSON, layers; hidden temp files skipped) and returns how many it checked; a file under
    its final name that does not read fails the test."""
    return _open_finished_files
