"""What the render reads of a stage: the traversal, visibility and purposes.

``walk_subtree`` walks a subtree with ``Usd.PrimRange`` (instance proxies included, the
default predicate: inactive, undefined, abstract and unloaded prims pruned) and yields
what the render reads, in traversal order: gprims (``meshes.RENDERED_GPRIM_TYPES``),
PointInstancers (their subtrees are not walked: prototypes render only through the
instancer) and, at the stage level, lights.

- **Visibility** is inherited strictly (an ``invisible`` prim hides everything below), so
  a subtree whose root is authored ``invisible`` is pruned before anything below is read;
  that equals ``UsdGeomImageable.ComputeVisibility`` on every prim below.
- **Purpose** follows ``UsdGeomImageable.ComputePurpose``: a prim's authored purpose wins;
  otherwise it inherits the purpose of its nearest imageable ancestor *if that one was
  authored* (or inherited from an authored one), else it is ``default``. A subtree is
  therefore never pruned by purpose: a child authored ``render`` under a ``proxy`` group
  is ``render``. A prim is read when its purpose is one of the render's
  ``includedPurposes`` (UsdRender; fallback ``default``, ``render``:
  ``DEFAULT_INCLUDED_PURPOSES``).

Visibility and purpose are evaluated once, at the time code given (the start of the
frame range): animated visibility is not supported.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from pxr import Sdf, Usd, UsdGeom, UsdLux

from phrt_usd.usd.meshes import is_subdivided, shape_kind

#: UsdRenderSettings.includedPurposes fallback: what a final render draws.
DEFAULT_INCLUDED_PURPOSES = ("default", "render")


def _purpose_info(prim: Usd.Prim) -> UsdGeom.Imageable.PurposeInfo:
    """``ComputePurposeInfo`` of ``prim`` or, for a prim that is not imageable, of its
    nearest imageable ancestor (what a child inherits); an empty info at the root."""
    while prim and not prim.IsPseudoRoot():
        if prim.IsA(UsdGeom.Imageable):
            return UsdGeom.Imageable(prim).ComputePurposeInfo()
        prim = prim.GetParent()
    return UsdGeom.Imageable.PurposeInfo()


def walk_subtree(
    root: Usd.Prim,
    code: Usd.TimeCode,
    purposes: Sequence[str] = DEFAULT_INCLUDED_PURPOSES,
    top: bool = True,
) -> Iterator[tuple[str, Usd.Prim]]:
    """(kind, prim) of what the render reads under ``root`` at ``code``, in order.

    kind: a gprim type (``meshes.SHAPE_ATTRS``), "PointInstancer" (its subtree is not
    walked) or, with ``top``, "Light" (lights inside prototypes are not read). Prims are
    read when visible and their computed purpose is in ``purposes`` (module doc).
    """
    if not root:
        return
    included = set(purposes)
    # PurposeInfo of every prim walked (for a non-imageable prim: what its children
    # inherit), keyed by path; the root's parent's from USD itself.
    info: dict[Sdf.Path, UsdGeom.Imageable.PurposeInfo] = {}
    root_parent = root.GetParent()
    root_parent_info = _purpose_info(root_parent) if root_parent else None
    it = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies()))
    for prim in it:
        if prim.IsPseudoRoot():
            continue
        path = prim.GetPath()
        parent_info = info.get(path.GetParentPath(), root_parent_info)
        if not prim.IsA(UsdGeom.Imageable):
            info[path] = parent_info if parent_info is not None else _purpose_info(prim)
            continue
        img = UsdGeom.Imageable(prim)
        if img.GetVisibilityAttr().Get(code) == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        own = img.ComputePurposeInfo(parent_info) if parent_info else img.ComputePurposeInfo()
        info[path] = own
        read = (own.purpose or UsdGeom.Tokens.default_) in included
        kind = shape_kind(prim)
        if kind is not None:
            if read:
                yield kind, prim
        elif prim.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            if read:
                yield "PointInstancer", prim
        elif top and read and prim.HasAPI(UsdLux.LightAPI):
            yield "Light", prim


def instancer_prototypes(instancer: Usd.Prim) -> list[Sdf.Path]:
    """The prototype root paths of a PointInstancer (its ``prototypes`` targets)."""
    return list(UsdGeom.PointInstancer(instancer).GetPrototypesRel().GetForwardedTargets())


def rendered_gprims(
    stage: Usd.Stage, time: float, purposes: Sequence[str] = DEFAULT_INCLUDED_PURPOSES
) -> Iterator[tuple[str, Usd.Prim]]:
    """(kind, prim) of every gprim the render reads at ``time`` (the start of the frame
    range): those of the stage and, once each, those of the PointInstancer prototypes at
    any depth of nesting."""
    code = Usd.TimeCode(float(time))
    seen: set[Sdf.Path] = set()
    queue: list[Sdf.Path] = []
    done: set[Sdf.Path] = set()
    roots = [(stage.GetPseudoRoot(), True)]
    while roots:
        root, top = roots.pop(0)
        for kind, prim in walk_subtree(root, code, purposes, top=top):
            if kind == "PointInstancer":
                queue += instancer_prototypes(prim)
            elif kind != "Light" and prim.GetPath() not in seen:
                seen.add(prim.GetPath())
                yield kind, prim
        for proto in queue:
            if proto not in done:
                done.add(proto)
                roots.append((stage.GetPrimAtPath(proto), False))
        queue = []


def subdivided_meshes(
    stage: Usd.Stage,
    time: float | None = None,
    purposes: Sequence[str] = DEFAULT_INCLUDED_PURPOSES,
) -> list[str]:
    """Prim paths of the meshes the render reads whose ``subdivisionScheme`` (authored or
    USD's fallback ``catmullClark``) is not ``none``: the render draws their control
    cage, not the limit surface. ``time``: the stage's start time code by default."""
    t = float(stage.GetStartTimeCode()) if time is None else float(time)
    return [
        str(prim.GetPath())
        for kind, prim in rendered_gprims(stage, t, purposes)
        if kind == "Mesh" and is_subdivided(prim)
    ]
