"""``phrt author``: mark prims as reflectors without touching the user's files.

By default the opinions go to a new layer (``<stem>.phrt.usda`` next to the stage, or an
explicit ``out`` path) that sublayers the original stage's root layer by a relative path
and holds ``over``s with PhrtReflectorAPI and K (and F). Opening that layer gives the
original stage plus the reflector opinions. Only ``in_place=True`` edits the stage's root
layer.

What this module guarantees:

* Nothing is written unless every prim checks out (exists, is a gprim) and K / F are in
  range; errors are one-line ``PhrtError``s naming the prim or the file.
* An overlay composes exactly like the stage alone: it carries *all* layer metadata of
  the stage's root layer (``UsdUtils.CopyLayerMetadata``: timeCodesPerSecond,
  framesPerSecond, start/end time code, renderSettingsPrimPath, customLayerData, upAxis,
  metersPerUnit, defaultPrim, ...), so the sublayer is not retimed and the stage's time
  range and render settings survive.
* An overlay never overwrites an existing file unless ``force=True``, and never (not
  even with ``force``) the input stage or any layer the stage uses: its layer stack,
  referenced and payload layers, and what those layers use in turn (compared by real
  path, symlinks resolved).
* ``in_place=True`` keeps the file's format: a text layer stays text, a crate stays
  crate (a ``.usd`` file keeps whichever of the two it is). A ``.usdz`` package is never
  edited in place (refused, the file untouched); write an overlay instead.
* A prim inside an instance (an instance proxy) cannot carry opinions: USD ignores any
  opinion below an instanceable prim. Authoring one is refused in one line naming the
  instance root, unless ``on_prototype=True``: then the opinions go where they compose
  into *every* instance of that prototype, without de-instancing anything and without
  editing the referenced asset: a ``class`` prim ``/PhrtPrototypes/<Name>`` in the
  written layer holds an ``over`` at the proxy's path below its instance root (with
  PhrtReflectorAPI, K, F), and every instance root of the prototype gets a prepended
  ``inherits`` arc to it. Inherits are part of an instance's composition key and
  identical on all of them, so the instances still share one prototype, and inherits are
  stronger than the references/payloads that bring the asset in (LIVRPS), so K and F
  win over the asset's own. Nested instancing (an instance inside a prototype) is
  refused: the inner instance root is itself a proxy and cannot take the arc.
* Every file goes through ``phrt_usd.atomic.atomic_path`` (temp file beside the target, then a
  rename; an existing file's mode is kept, a new file follows the umask), and the written
  layer is reopened and checked before it replaces the target. On any failure the
  target keeps its previous content.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pxr import Ar, Pcp, Sdf, Tf, Usd, UsdGeom, UsdUtils

from phrt_usd.atomic import WriteFailed, atomic_path
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.usd import schema
from phrt_usd.usd.stage import open_usd

OVERLAY_SUFFIX = ".phrt.usda"

#: Root ``class`` prim holding the per-prototype reflector opinions (``on_prototype``).
PROTOTYPE_OPINIONS_ROOT = Sdf.Path("/PhrtPrototypes")

#: Sdf file formats phrt writes layers in (``usd`` is text or crate, see ``_usd_flavour``).
WRITABLE_FORMATS = ("usda", "usdc", "usd")

#: First bytes of each flavour of layer file.
_MAGIC = {"usdc": b"PXR-USDC", "usda": b"#usda"}


@dataclass(frozen=True)
class AuthorResult:
    """Where the opinions went and which prims got them."""

    layer: str
    prims: list[str]


def default_overlay_path(stage_path: str | Path) -> Path:
    """``dir/name.usda`` -> ``dir/name.phrt.usda``."""
    p = Path(stage_path)
    return p.with_name(p.name.split(".")[0] + OVERLAY_SUFFIX)


def instance_root(prim: Usd.Prim) -> Usd.Prim:
    """The outermost instance root above an instance proxy (the prim that can carry
    opinions and arcs); ``prim`` itself when it is not a proxy."""
    root = prim
    while root.IsInstanceProxy():
        root = root.GetParent()
    return root


def _proxy_refusal(prim: Usd.Prim) -> str:
    root = instance_root(prim)
    source = _prototype_source(root)
    return (
        f"{prim.GetPath()}: is inside the instance {root.GetPath()} (an instance proxy "
        f"cannot carry opinions); author on the prototype with --on-prototype (every "
        f"instance of it gets the reflector), or on its source{source}, or de-instance "
        f"{root.GetPath()} (instanceable = false)"
    )


def _prototype_source(root: Usd.Prim) -> str:
    """`` <asset>@<prim>`` of the first reference or payload that brings the instance's
    content in, or "" when it has none (e.g. an internal inherit)."""
    for node in root.GetPrimIndex().rootNode.children:
        if node.arcType in (Pcp.ArcTypeReference, Pcp.ArcTypePayload):
            layer = node.layerStack.identifier.rootLayer
            return f" {layer.identifier}@{node.path}"
    return ""


def _check_prims(
    stage: Usd.Stage, prim_paths: list[str], on_prototype: bool = False
) -> list[Usd.Prim]:
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
        if prim.IsInstanceProxy():
            if not on_prototype:
                raise PhrtError(_proxy_refusal(prim))
            root = instance_root(prim)
            inner = prim.GetParent()
            while inner != root:
                if inner.IsInstance():
                    raise PhrtError(
                        f"{path}: is inside the instance {inner.GetPath()}, itself inside "
                        f"the instance {root.GetPath()} (nested instancing); author on the "
                        f"inner prototype's source or de-instance {root.GetPath()}"
                    )
                inner = inner.GetParent()
        prims.append(prim)
    return prims


def _check_values(priority: float, reflectivity: float | None) -> None:
    if not (priority >= 0.0 and priority != float("inf")):  # rejects NaN too
        raise BadOption(f"--priority {priority}: K must be finite and >= 0")
    if reflectivity is not None and not (0.0 <= reflectivity <= 1.0):
        raise BadOption(f"--reflectivity {reflectivity}: F must be in [0, 1]")


# --- which files a stage uses ----------------------------------------------------------


def _real(path: str) -> str:
    """The real file behind a layer path (the package itself for ``a.usdz[b.usda]``)."""
    if Ar.IsPackageRelativePath(path):
        path = Ar.SplitPackageRelativePathOuter(path)[0]
    return os.path.realpath(path)


def _used_files(stage: Usd.Stage) -> set[str]:
    """Real paths of every file the stage's layers use: the stage's layer stack, all
    layers it composes (references, payloads), and, transitively, every sublayer,
    reference and payload any of those layers names, loaded or not (unselected variants,
    unloaded payloads included)."""
    files: set[str] = set()
    seen: set[str] = set()
    todo = list(stage.GetUsedLayers())
    while todo:
        layer = todo.pop()
        if layer.identifier in seen:
            continue
        seen.add(layer.identifier)
        if layer.realPath:
            files.add(_real(layer.realPath))
        for asset in layer.GetCompositionAssetDependencies():
            path = layer.ComputeAbsolutePath(asset)
            if not path:
                continue
            files.add(_real(path))
            if os.path.isfile(_real(path)):
                try:
                    dependency = Sdf.Layer.FindOrOpen(path)
                except Tf.ErrorException:
                    dependency = None
                if dependency is not None:
                    todo.append(dependency)
    return files


# --- formats -----------------------------------------------------------------------------


def _usd_flavour(path: Path) -> str:
    """``usdc`` when the ``.usd`` file at ``path`` is a crate, else ``usda``."""
    return "usdc" if Sdf.FileFormat.FindById("usdc").CanRead(str(path)) else "usda"


def _check_written(
    final: Path, flavour: str | None, prim_paths: list[str]
) -> Callable[[Path], None]:
    """A check for ``atomic_path``: the temp file is of the expected flavour (``usda`` /
    ``usdc``; None: either), reopens as a layer, and holds K for every prim."""

    def check(tmp: Path) -> None:
        if flavour is not None:
            with open(tmp, "rb") as f:
                head = f.read(len(_MAGIC[flavour]))
            if head != _MAGIC[flavour]:
                raise WriteFailed(f"{final}: the written file is not a {flavour} layer")
        try:
            layer = Sdf.Layer.OpenAsAnonymous(str(tmp))
        except Tf.ErrorException:
            layer = None
        if layer is None:
            raise WriteFailed(f"{final}: the written file does not open as a USD layer")
        for path in prim_paths:
            attr = layer.GetAttributeAtPath(Sdf.Path(path).AppendProperty(schema.PRIORITY))
            if attr is None or not attr.HasDefaultValue():
                raise WriteFailed(f"{final}: the written layer lost the opinions on {path}")

    return check


def _write(
    layer: Sdf.Layer, final: Path, flavour: str | None, args: dict, prim_paths: list[str]
) -> None:
    with atomic_path(final, check=_check_written(final, flavour, prim_paths)) as tmp:
        if not layer.Export(str(tmp), args=args):
            raise WriteFailed(f"{final}: USD could not write the layer")


# --- authoring ---------------------------------------------------------------------------


def author_reflectors(
    stage_path: str | Path,
    prim_paths: list[str],
    priority: float,
    reflectivity: float | None = None,
    out: str | Path | None = None,
    in_place: bool = False,
    force: bool = False,
    on_prototype: bool = False,
) -> AuthorResult:
    """Apply PhrtReflectorAPI with K (and F) to ``prim_paths`` of the stage at
    ``stage_path``; see the module docstring for where the opinions are written and what
    is guaranteed. ``force`` lets an overlay replace an existing file that the stage does
    not use (it has no effect with ``in_place``). ``on_prototype``: a prim inside an
    instance is authored on its prototype, through a class every instance inherits
    (module docstring); without it such a prim is refused."""
    if out is not None and in_place:
        raise BadOption("--out and --in-place exclude each other")
    if not prim_paths:
        raise BadOption("no prim paths given")
    _check_values(priority, reflectivity)
    stage_file = Path(stage_path)
    stage = open_usd(stage_file)
    _check_prims(stage, prim_paths, on_prototype)
    if in_place:
        target = _author_in_place(stage, stage_file, prim_paths, priority, reflectivity)
    else:
        target = Path(out) if out is not None else default_overlay_path(stage_file)
        _author_overlay(stage, stage_file, target, prim_paths, priority, reflectivity, force)
    return AuthorResult(layer=str(target), prims=list(prim_paths))


def _author_in_place(
    stage: Usd.Stage,
    stage_file: Path,
    prim_paths: list[str],
    priority: float,
    reflectivity: float | None,
) -> Path:
    """Author into the stage's root layer and write it back in its own format."""
    root = stage.GetRootLayer()
    file_format = root.GetFileFormat()
    if file_format.IsPackage() or file_format.formatId == "usdz":
        raise PhrtError(
            f"{stage_file}: a .usdz package cannot be edited in place; "
            f"write an overlay instead (drop --in-place, or use --out PATH)"
        )
    if file_format.formatId not in WRITABLE_FORMATS:
        raise PhrtError(
            f"{stage_file}: cannot edit a '{file_format.formatId}' layer in place; "
            f"write an overlay instead (drop --in-place, or use --out PATH)"
        )
    # The real file (a symlinked stage keeps its link; the file it points to is edited).
    target = Path(os.path.realpath(root.realPath))
    if file_format.formatId == "usd":
        flavour = _usd_flavour(target)
        args = {"format": flavour}
    else:
        flavour, args = file_format.formatId, {}
    try:
        plain, proxies = _split_proxies(stage, prim_paths)
        for path in plain:
            schema.apply_reflector(
                stage.GetPrimAtPath(path), priority=priority, reflectivity=reflectivity
            )
        written = plain + _author_on_prototypes(root, proxies, priority, reflectivity)
        _write(root, target, flavour, args, written)
    finally:
        # The registry's layer now matches the file again (or, after a failure, drops
        # the opinions that never reached it).
        root.Reload(force=True)
    return target


def _check_parent(target: Path) -> None:
    """``BadOption`` when the overlay's directory cannot be made: the nearest part of
    its path that exists is not a directory."""
    parent = Path(os.path.abspath(target)).parent
    while not os.path.lexists(parent) and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise BadOption(f"--out {target}: {parent} is not a directory")


def _author_overlay(
    stage: Usd.Stage,
    stage_file: Path,
    target: Path,
    prim_paths: list[str],
    priority: float,
    reflectivity: float | None,
    force: bool,
) -> None:
    """Write a new layer over the stage's root layer holding the opinions."""
    ext = target.suffix.lstrip(".")
    file_format = Sdf.FileFormat.FindByExtension(ext) if ext else None
    if file_format is None or file_format.formatId not in WRITABLE_FORMATS:
        raise BadOption(f"--out {target}: write the overlay as .usda, .usdc or .usd")
    src = stage.GetRootLayer()
    real_target = os.path.realpath(target)
    if real_target == _real(src.realPath) or real_target == os.path.realpath(stage_file):
        raise PhrtError(f"{target}: is the input stage; use --in-place to edit it")
    if real_target in _used_files(stage):
        raise PhrtError(
            f"{target}: is a layer the stage uses (sublayer, reference or payload); "
            f"refusing to overwrite it, even with --force"
        )
    if target.is_dir():
        raise PhrtError(f"{target}: is a directory")
    _check_parent(target)
    if os.path.lexists(target) and not force:
        raise PhrtError(f"{target}: already exists; pass --force to overwrite it")

    edit_layer = Sdf.Layer.CreateAnonymous(f".{ext}")
    # Every piece of the root layer's metadata: an overlay without timeCodesPerSecond
    # would retime the stage (24 against the sublayer's own), lose its time range, ...
    UsdUtils.CopyLayerMetadata(src, edit_layer, skipSublayers=True, bakeUnauthoredFallbacks=False)
    # Compose against the absolute identifier while authoring; the file gets the path
    # relative to its own directory, so the pair can be moved together.
    edit_layer.subLayerPaths.append(src.identifier)
    relative = Path(os.path.relpath(stage_file.resolve(), target.resolve().parent)).as_posix()
    edit_stage = Usd.Stage.Open(edit_layer)
    plain, proxies = _split_proxies(edit_stage, prim_paths)
    for path in plain:
        schema.apply_reflector(
            edit_stage.GetPrimAtPath(path), priority=priority, reflectivity=reflectivity
        )
    written = plain + _author_on_prototypes(edit_layer, proxies, priority, reflectivity)
    # Close the authoring stage first: while it is open, USD recomposes the anonymous
    # layer against the relative path (which only resolves next to the file) and warns.
    del edit_stage
    edit_layer.subLayerPaths[0] = relative
    flavour = file_format.formatId if file_format.formatId in _MAGIC else None
    _write(edit_layer, target, flavour, {}, written)


# --- on the prototype ---------------------------------------------------------------------


def _split_proxies(stage: Usd.Stage, prim_paths: list[str]) -> tuple[list[str], list[Usd.Prim]]:
    """(paths of prims that take opinions, instance-proxy prims), in the given order."""
    plain, proxies = [], []
    for path in prim_paths:
        prim = stage.GetPrimAtPath(path)
        (proxies.append(prim) if prim.IsInstanceProxy() else plain.append(path))
    return plain, proxies


def _class_name(taken: set[str], root: Usd.Prim) -> str:
    """A child name of PROTOTYPE_OPINIONS_ROOT for the prototype of instance ``root``."""
    name, n = root.GetName(), 1
    while name in taken:
        n += 1
        name = f"{root.GetName()}_{n}"
    taken.add(name)
    return name


def _existing_class(layer: Sdf.Layer, root: Usd.Prim) -> Sdf.Path | None:
    """The PROTOTYPE_OPINIONS_ROOT class instance ``root`` already inherits in ``layer``."""
    spec = layer.GetPrimAtPath(root.GetPath())
    if spec is None:
        return None
    for target in spec.inheritPathList.GetAddedOrExplicitItems():
        if target.HasPrefix(PROTOTYPE_OPINIONS_ROOT) and target != PROTOTYPE_OPINIONS_ROOT:
            return target
    return None


def _author_on_prototypes(
    layer: Sdf.Layer, proxies: list[Usd.Prim], priority: float, reflectivity: float | None
) -> list[str]:
    """Author the reflector opinions of instance-proxy gprims into ``layer`` on a class
    per prototype, inherited by every instance of it (module docstring). Returns the
    paths of the specs holding K (what the written layer is checked for)."""
    if not proxies:
        return []
    top = layer.GetPrimAtPath(PROTOTYPE_OPINIONS_ROOT) or Sdf.CreatePrimInLayer(
        layer, PROTOTYPE_OPINIONS_ROOT
    )
    top.specifier = Sdf.SpecifierClass
    taken = {child.name for child in top.nameChildren}
    classes: dict[Sdf.Path, Sdf.Path] = {}  # prototype path -> class path
    written: list[str] = []
    with Sdf.ChangeBlock():
        for prim in proxies:
            root = instance_root(prim)
            prototype = root.GetPrototype()
            if prototype.GetPath() not in classes:
                instances = sorted(prototype.GetInstances(), key=lambda p: p.GetPath())
                found = [c for i in instances if (c := _existing_class(layer, i))]
                cls = found[0] if found else PROTOTYPE_OPINIONS_ROOT.AppendChild(
                    _class_name(taken, instances[0])
                )
                spec = layer.GetPrimAtPath(cls) or Sdf.CreatePrimInLayer(layer, cls)
                spec.specifier = Sdf.SpecifierClass
                for instance in instances:
                    ispec = layer.GetPrimAtPath(instance.GetPath()) or Sdf.CreatePrimInLayer(
                        layer, instance.GetPath()
                    )
                    if cls not in ispec.inheritPathList.GetAddedOrExplicitItems():
                        ispec.inheritPathList.Prepend(cls)
                classes[prototype.GetPath()] = cls
            where = classes[prototype.GetPath()].AppendPath(
                prim.GetPath().MakeRelativePath(root.GetPath())
            )
            spec = layer.GetPrimAtPath(where) or Sdf.CreatePrimInLayer(layer, where)
            apis = spec.GetInfo("apiSchemas")
            if schema.REFLECTOR_API not in apis.GetAddedOrExplicitItems():
                apis.prependedItems = [schema.REFLECTOR_API, *apis.prependedItems]
                spec.SetInfo("apiSchemas", apis)
            values = [(schema.PRIORITY, priority), (schema.REFLECTIVITY, reflectivity)]
            for name, value in values:
                if value is None:
                    continue
                attr = spec.attributes.get(name) or Sdf.AttributeSpec(
                    spec, name, Sdf.ValueTypeNames.Float
                )
                attr.default = float(value)
            written.append(str(where))
    return written
