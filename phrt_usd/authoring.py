"""``phrt author``: mark prims as reflectors without touching the user's file.

By default the opinions go to a new layer (``<stem>.phrt.usda`` next to the stage, or an
explicit path) whose root layer sublayers the original stage by a relative path and holds
``over``s with PhrtReflectorAPI and K (and F). Opening that layer gives the original stage
plus the reflector opinions. Only ``in_place=True`` edits the stage's root layer.

Every prim is checked before anything is written (exists, is a gprim); files are written
atomically (temporary file in the target directory, then ``os.replace``).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pxr import Sdf, Usd, UsdGeom

from phrt_usd import schema
from phrt_usd.errors import PhrtError
from phrt_usd.validation import open_stage

OVERLAY_SUFFIX = ".phrt.usda"


@dataclass(frozen=True)
class AuthorResult:
    """Where the opinions went and which prims got them."""

    layer: str
    prims: list[str]


def default_overlay_path(stage_path: str | Path) -> Path:
    """``dir/name.usda`` -> ``dir/name.phrt.usda``."""
    p = Path(stage_path)
    return p.with_name(p.name.split(".")[0] + OVERLAY_SUFFIX)


def _check_prims(stage: Usd.Stage, prim_paths: list[str]) -> list[Usd.Prim]:
    prims = []
    for path in prim_paths:
        if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
            raise PhrtError(f"{path}: not an absolute prim path")
        prim = stage.GetPrimAtPath(path)
        if not prim:
            raise PhrtError(f"{path}: no such prim in the stage")
        if not prim.IsA(UsdGeom.Gprim):
            raise PhrtError(
                f"{path}: is a {prim.GetTypeName() or 'typeless prim'}, not a gprim; "
                f"{schema.REFLECTOR_API} applies to gprims only"
            )
        prims.append(prim)
    return prims


def _check_values(priority: float, reflectivity: float | None) -> None:
    if not (priority >= 0.0 and priority != float("inf")):  # rejects NaN too
        raise PhrtError(f"--priority {priority}: K must be finite and >= 0")
    if reflectivity is not None and not (0.0 <= reflectivity <= 1.0):
        raise PhrtError(f"--reflectivity {reflectivity}: F must be in [0, 1]")


def _write_atomically(layer: Sdf.Layer, target: Path) -> None:
    """Export ``layer`` as text to ``target`` through a temporary file in the same directory
    (so ``os.replace`` is atomic: readers see the old file or the new one)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".usda", dir=target.parent)
    os.close(fd)
    try:
        if not layer.Export(tmp):
            raise PhrtError(f"{target}: could not write the layer")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def author_reflectors(
    stage_path: str | Path,
    prim_paths: list[str],
    priority: float,
    reflectivity: float | None = None,
    out: str | Path | None = None,
    in_place: bool = False,
) -> AuthorResult:
    """Apply PhrtReflectorAPI with K (and F) to ``prim_paths`` of the stage at
    ``stage_path``; see the module docstring for where the opinions are written."""
    if out is not None and in_place:
        raise PhrtError("--out and --in-place exclude each other")
    if not prim_paths:
        raise PhrtError("no prim paths given")
    _check_values(priority, reflectivity)
    stage_file = Path(stage_path)
    stage = open_stage(stage_file)
    _check_prims(stage, prim_paths)

    if in_place:
        # Author straight into the (already opened) root layer, then save it atomically.
        edit_layer = stage.GetRootLayer()
        edit_stage = stage
        target = Path(edit_layer.realPath)
        relative = None
    else:
        target = Path(out) if out is not None else default_overlay_path(stage_file)
        if target.resolve() == stage_file.resolve():
            raise PhrtError(f"{target}: --out is the input stage; use --in-place to edit it")
        src = stage.GetRootLayer()
        edit_layer = Sdf.Layer.CreateAnonymous(".usda")
        # Compose against the absolute identifier while authoring; the file gets the path
        # relative to its own directory, so the pair can be moved together.
        edit_layer.subLayerPaths.append(src.identifier)
        relative = Path(os.path.relpath(stage_file.resolve(), target.resolve().parent)).as_posix()
        # Keep the stage metadata visible to tools that only read the root layer.
        for key in ("upAxis", "metersPerUnit", "defaultPrim"):
            if src.pseudoRoot.HasInfo(key):
                edit_layer.pseudoRoot.SetInfo(key, src.pseudoRoot.GetInfo(key))
        edit_stage = Usd.Stage.Open(edit_layer)

    for path in prim_paths:
        schema.apply_reflector(
            edit_stage.GetPrimAtPath(path), priority=priority, reflectivity=reflectivity
        )
    if relative is not None:
        # Close the authoring stage first: while it is open, USD recomposes the anonymous
        # layer against the relative path (which only resolves next to the file) and warns.
        del edit_stage
        edit_layer.subLayerPaths[0] = relative
    _write_atomically(edit_layer, target)
    return AuthorResult(layer=str(target), prims=list(prim_paths))
