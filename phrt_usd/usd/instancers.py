"""PointInstancers: one element per (instance, prototype gprim), nested at any depth.

``expand_instancer`` passes every visible instance × gprim of a PointInstancer to the
scene's ``add``, in instance order. A prototype may hold PointInstancers itself: they are
expanded in turn, for every instance of the outer one, so that a gprim of an inner
prototype is placed by

    world = rel(gprim → inner proto root) @ inner_instance[j]
            @ rel(inner instancer → outer proto root) @ outer_instance[i] @ world(outer)

(USD's row-vector convention, ``p' = p @ M``, stage units). ``inner_instance[j]`` and
``outer_instance[i]`` are ``ComputeInstanceTransformsAtTime`` with the prototype root's
own transform included (``IncludeProtoXform``), so ``rel`` is the identity for the
prototype root itself and the transform below it otherwise, evaluated at every time.
Instances masked by ``invisibleIds``, ``inactiveIds`` or ``ComputeMaskAtTime`` are
skipped at every level (the mask is read at the first time only).

Element paths name the chain: ``/Outer.instance[i]``, then ``/rel/path`` below the
prototype root, then ``.instance[j]`` for an inner instancer's instances
(``/Outer.instance[1]/Inner.instance[3]/Cube``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from phrt_usd.errors import PhrtError
from phrt_usd.usd.mesh_batch import PendingMesh
from phrt_usd.usd.meshes import LocalMesh
from phrt_usd.usd.values import AnimationProbe, TimeContext, varies

#: PointInstancer attributes whose animation moves its instances.
INSTANCE_ATTRS = (
    "positions",
    "orientations",
    "orientationsf",
    "scales",
    "protoIndices",
    "velocities",
    "angularVelocities",
)

#: A gprim's local mesh: its LocalMesh, or a PendingMesh of the scene's MeshBatch.
Mesh = LocalMesh | PendingMesh

#: Receiver of one element: (gprim, element path, kind, its mesh, matrix_at(ctx) →
#: (4, 4) row-vector prototype gprim → world in stage units, transform may vary).
AddElement = Callable[[Usd.Prim, str, str, Mesh, Callable[[TimeContext], np.ndarray], bool], None]

#: Reader of a gprim's mesh: (kind, prim) → its mesh (read once per prim here).
ReadMesh = Callable[[str, Usd.Prim], Mesh]

#: (kind, prim) the render reads under a prototype root: gprims and "PointInstancer".
GprimsUnder = Callable[[Usd.Prim], Iterable[tuple[str, Usd.Prim]]]

#: A placement: ctx → (4, 4) row-vector matrix, stage units.
MatrixAt = Callable[[TimeContext], np.ndarray]


@dataclass
class _Entry:
    """One thing under a prototype root: a gprim (with its mesh) or an inner instancer."""

    kind: str
    prim: Usd.Prim
    suffix: str  # path below the prototype root, "." for the root itself
    is_root: bool
    mesh: Mesh | None  # None for an inner PointInstancer


@dataclass
class _Plan:
    """What one PointInstancer expands to (the same for every outer instance)."""

    proto_idx: np.ndarray  # (n,) int64
    visible: np.ndarray  # (n,) bool: the mask (invisibleIds, inactiveIds)
    entries: list[list[_Entry]]  # per prototype
    roots: list[Usd.Prim]  # per prototype


class _Expander:
    """Expands PointInstancers, nested ones for every outer instance; plans and meshes of
    a prim are read once however many outer instances reach it."""

    def __init__(self, ctx, probe, read_mesh, gprims_under, add):
        self.ctx, self.probe, self.read_mesh = ctx, probe, read_mesh
        self.gprims_under, self.add = gprims_under, add
        self._plans: dict[Sdf.Path, _Plan] = {}
        self._meshes: dict[Sdf.Path, Mesh] = {}

    def plan(self, prim: Usd.Prim) -> _Plan:
        path = prim.GetPath()
        if path not in self._plans:
            self._plans[path] = self._read_plan(prim)
        return self._plans[path]

    def _read_plan(self, prim: Usd.Prim) -> _Plan:
        ctx = self.ctx
        pi = UsdGeom.PointInstancer(prim)
        where = str(prim.GetPath())
        protos = pi.GetPrototypesRel().GetForwardedTargets()
        proto_idx = np.asarray(pi.GetProtoIndicesAttr().Get(ctx.code) or [], dtype=np.int64)
        if len(proto_idx) and (proto_idx.min() < 0 or proto_idx.max() >= len(protos)):
            raise PhrtError(f"{where}.protoIndices: index out of range [0, {len(protos)})")
        xforms = ctx.instance_xforms(prim)
        if len(xforms) != len(proto_idx):
            raise PhrtError(f"{where}: instance transforms do not match protoIndices")
        if not np.all(np.isfinite(xforms)):
            raise PhrtError(f"{where}: non-finite instance transform (positions/scales)")
        mask = pi.ComputeMaskAtTime(ctx.code)  # inactive and invisible ids → False
        visible = np.ones(len(proto_idx), bool) if not mask else np.asarray(mask, bool)
        entries, roots = [], []
        for proto_path in protos:
            root = prim.GetStage().GetPrimAtPath(proto_path)
            found = []
            for kind, g in self.gprims_under(root):
                suffix = str(g.GetPath().MakeRelativePath(root.GetPath()))
                mesh = None
                if kind != "PointInstancer":
                    if g.GetPath() not in self._meshes:
                        self._meshes[g.GetPath()] = self.read_mesh(kind, g)
                    mesh = self._meshes[g.GetPath()]
                found.append(_Entry(kind, g, suffix, g == root, mesh))
            entries.append(found)
            roots.append(root)
        return _Plan(proto_idx, visible, entries, roots)

    def expand(
        self,
        prim: Usd.Prim,
        label: str,
        to_world: MatrixAt,
        animated: bool,
        chain: tuple[Sdf.Path, ...],
    ) -> None:
        """Add the elements of instancer ``prim`` (element path prefix ``label``), its
        instancer space placed in the world by ``to_world``."""
        where = str(prim.GetPath())
        if prim.GetPath() in chain:
            raise PhrtError(f"{where}: PointInstancer is inside its own prototype")
        chain = (*chain, prim.GetPath())
        plan = self.plan(prim)
        probe = self.probe
        animated = animated or probe.xform_varies(prim) or varies(prim, INSTANCE_ATTRS)
        for i in np.flatnonzero(plan.visible):
            proto = int(plan.proto_idx[i])
            entries, root = plan.entries[proto], plan.roots[proto]

            def inst_at(c, i=int(i)):
                inst = c.instance_xforms(prim)
                if i >= len(inst):
                    raise PhrtError(
                        f"{where}: instance count changed at time {c.time} (not supported)"
                    )
                return inst[i]

            for e in entries:
                path = f"{label}.instance[{i}]"
                if len(entries) > 1 or e.suffix != ".":
                    path += f"/{e.suffix}" if e.suffix != "." else ""

                def matrix_at(c, e=e, root=root, inst_at=inst_at):
                    # The root's own xform is in the instance transform (IncludeProtoXform).
                    rel = np.eye(4) if e.is_root else _relative(c, e.prim, root)
                    return rel @ inst_at(c) @ to_world(c)

                moving = animated or probe.xform_varies(e.prim)
                if e.kind == "PointInstancer":
                    self.expand(e.prim, path, matrix_at, moving, chain)
                else:
                    self.add(e.prim, path, e.kind, e.mesh, matrix_at, moving)


def _relative(ctx: TimeContext, prim: Usd.Prim, root: Usd.Prim) -> np.ndarray:
    """(4, 4) row-vector transform of ``prim``'s space into its prototype root's."""
    return np.array(ctx.cache.ComputeRelativeTransform(prim, root)[0])


def expand_instancer(
    prim: Usd.Prim,
    ctx: TimeContext,
    probe: AnimationProbe,
    read_mesh: ReadMesh,
    gprims_under: GprimsUnder,
    add: AddElement,
) -> None:
    """One element per (instance, prototype gprim) of a PointInstancer and, recursively,
    of the PointInstancers inside its prototypes, passed to ``add`` in instance order
    (module doc); masked instances are skipped.

    gprims_under(root) : (kind, prim) the render reads under a prototype root, gprims
    and nested "PointInstancer"s; read_mesh(kind, gprim) : its mesh, asked once a gprim.
    """
    expander = _Expander(ctx, probe, read_mesh, gprims_under, add)
    expander.expand(prim, str(prim.GetPath()), lambda c: c.world(prim), False, ())
