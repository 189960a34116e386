"""UsdSkel: skinned meshes deformed per frame by USD's own skinning.

A Mesh bound to a Skeleton (``UsdSkelBindingAPI`` under a ``SkelRoot``) is read through
``UsdSkel.Cache``: the root's ``ComputeSkelBindings`` give each skinned mesh its
``UsdSkelSkinningQuery`` and its skeleton's ``UsdSkelSkeletonQuery``. At a time code its
points are

1. the mesh's authored points at that time,
2. plus its blend shapes (``UsdSkelBlendShapeQuery``: the animation's weights remapped to
   the mesh's ``skel:blendShapes`` order, in-betweens included) when it has any,
3. skinned by ``SkinningQuery.ComputeSkinnedPoints`` with the skeleton's
   ``ComputeSkinningTransforms`` (linear blend or dual-quaternion, as
   ``skel:skinningMethod`` says; rigid bindings too).

The result is in **skeleton space**: the mesh's own transform is replaced by the
skeleton's local-to-world (as UsdSkel specifies and ``UsdSkelBakeSkinning`` does), so
``Skinned.matrix_at`` is the skeleton prim's world transform. Authored normals are
carried by the same joint influences (linear blend of each joint's normal matrix,
``normals_lbs``); a mesh without authored normals gets its smooth normals recomputed
from the skinned points (``LocalMesh.smooth``).

A skinned mesh is an animated element when the skeleton's animation, its blend-shape
weights, the mesh's points or the skeleton's transform may vary in time; ``set_time``
then re-skins it. Skinned meshes inside instanced references (instance proxies) are skinned
per instance. Limits: skinned meshes inside PointInstancer prototypes are not skinned
(drawn as authored), nor are meshes with blend shapes but no joint influences; the
skinning of authored normals is linear blend even for a
dual-quaternion binding.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

from phrt_usd.errors import PhrtError
from phrt_usd.usd.meshes import mesh_normals_at
from phrt_usd.usd.values import (
    AnimationProbe,
    TimeContext,
    normal_matrix,
    safe_normalize,
    varies,
)

#: Shape reader of a skinned mesh: time → (skeleton-space points (n, 3) float64,
#: corner normals (T, 3, 3) or None when the normals are smooth).
SkinnedShapeAt = Callable[[Usd.TimeCode], tuple[np.ndarray, np.ndarray | None]]


@dataclass
class Skinned:
    """How one skinned mesh deforms: its queries and its skeleton."""

    prim: Usd.Prim
    skel_query: UsdSkel.SkeletonQuery
    skinning_query: UsdSkel.SkinningQuery
    skeleton: Usd.Prim
    blend_shapes: UsdSkel.BlendShapeQuery | None

    def matrix_at(self, ctx: TimeContext) -> np.ndarray:
        """(4, 4) row-vector skeleton space → world, stage units."""
        return ctx.world(self.skeleton)

    def animated(self, probe: AnimationProbe) -> bool:
        """True when the skinned points or their placement may vary in time."""
        anim = self.skel_query.GetAnimQuery()
        moving = bool(anim) and (
            anim.JointTransformsMightBeTimeVarying()
            or (self.blend_shapes is not None and anim.BlendShapeWeightsMightBeTimeVarying())
        )
        return (
            moving
            or varies(self.prim, ("points", "normals", "primvars:normals"))
            or probe.xform_varies(self.skeleton)
        )

    def _skinning_xforms(self, code: Usd.TimeCode, where: str):
        xforms = self.skel_query.ComputeSkinningTransforms(code)
        if xforms is None:
            raise PhrtError(f"{where}: cannot compute skinning transforms at time {code}")
        return xforms

    def points_at(self, code: Usd.TimeCode) -> np.ndarray:
        """(n, 3) float64 skeleton-space points at ``code`` (blend shapes, then skinning)."""
        where = f"{self.prim.GetPath()} (skeleton {self.skeleton.GetPath()})"
        points = UsdGeom.Mesh(self.prim).GetPointsAttr().Get(code)
        points = Vt.Vec3fArray(points if points is not None else [])
        if self.blend_shapes is not None:
            self._apply_blend_shapes(points, code, where)
        xforms = self._skinning_xforms(code, where)
        if not self.skinning_query.ComputeSkinnedPoints(xforms, points, code):
            raise PhrtError(
                f"{where}: UsdSkel skinning failed at time {code} "
                "(joint influences do not match the points or joints)"
            )
        out = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(out)):
            raise PhrtError(f"{where}: non-finite skinned point at time {code}")
        return out

    def _apply_blend_shapes(self, points: Vt.Vec3fArray, code: Usd.TimeCode, where: str):
        anim = self.skel_query.GetAnimQuery()
        mapper = self.skinning_query.GetBlendShapeMapper()
        if not anim or mapper is None or mapper.IsNull():
            return
        weights = mapper.Remap(anim.ComputeBlendShapeWeights(code))
        bq = self.blend_shapes
        sub_weights, shape_idx, sub_idx = bq.ComputeSubShapeWeights(weights)
        ok = bq.ComputeDeformedPoints(
            sub_weights,
            shape_idx,
            sub_idx,
            bq.ComputeBlendShapePointIndices(),
            bq.ComputeSubShapePointOffsets(),
            points,
        )
        if not ok:
            raise PhrtError(f"{where}: blend shapes do not match the points at time {code}")

    def normals_lbs(self, code: Usd.TimeCode, triangles: np.ndarray, normals: np.ndarray):
        """Corner normals (T, 3, 3) carried to skeleton space by the joint influences.

        triangles : (T, 3) point ids; normals : (T, 3, 3) mesh-space corner normals.
        Each point's normal matrix is the weighted sum of the normal matrices of
        geomBindTransform @ skinning transform of its joints (linear blend).
        """
        where = str(self.prim.GetPath())
        q = self.skinning_query
        xforms = [np.array(m) for m in self._skinning_xforms(code, where)]
        bind = np.array(q.GetGeomBindTransform(code))[:3, :3]
        mapper = q.GetJointMapper()
        if mapper is not None and not mapper.IsNull() and not mapper.IsIdentity():
            # Skeleton-order transforms to the mesh's skel:joints order.
            order = list(self.skel_query.GetJointOrder())
            xforms = [xforms[order.index(j)] for j in q.GetJointOrder()]
        joint_n = np.stack([normal_matrix(bind @ m[:3, :3]) for m in xforms])  # (J, 3, 3)
        indices, weights = q.ComputeJointInfluences(code)
        k = q.GetNumInfluencesPerComponent()
        idx = np.clip(np.asarray(indices, np.int64).reshape(-1, k), 0, len(joint_n) - 1)
        w = np.asarray(weights, np.float64).reshape(-1, k)
        per = np.einsum("pk,pkij->pij", w, joint_n[idx])  # (P, 3, 3), P = 1 when rigid
        corner = per[0] if len(per) == 1 else per[triangles]  # (3, 3) or (T, 3, 3, 3)
        if corner.ndim == 2:
            out = normals @ corner
        else:
            out = np.einsum("tci,tcij->tcj", normals, corner)
        return safe_normalize(out)

    def shape_fn(self, smooth: bool) -> SkinnedShapeAt:
        """The deformation reader of this mesh (``smooth``: normals are recomputed)."""

        def shape_at(code: Usd.TimeCode):
            points = self.points_at(code)
            if smooth:
                return points, None
            triangles, normals = mesh_normals_at(self.prim, code)
            return points, None if normals is None else self.normals_lbs(code, triangles, normals)

        return shape_at


class SkinningReader:
    """USD's ``UsdSkel.Cache`` over the stage's SkelRoots, populated per root on demand
    (a stage without UsdSkel costs one ``HasAPI`` per mesh)."""

    def __init__(self):
        self._cache = UsdSkel.Cache()
        self._roots: set[Sdf.Path] = set()
        self._targets: dict[Sdf.Path, Skinned] = {}

    def skinned(self, prim: Usd.Prim, kind: str) -> Skinned | None:
        """The skinning of a gprim when it is a Mesh bound to a skeleton, else None."""
        if kind != "Mesh" or not prim.HasAPI(UsdSkel.BindingAPI):
            return None
        root = UsdSkel.Root.Find(prim)
        if not root:
            return None
        if root.GetPath() not in self._roots:
            self._roots.add(root.GetPath())
            self._populate(root)
        return self._targets.get(prim.GetPath())

    def _populate(self, root: UsdSkel.Root) -> None:
        # Instance proxies included: a skinned character may be an instanced reference.
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        self._cache.Populate(root, predicate)
        for binding in self._cache.ComputeSkelBindings(root, predicate):
            skel = binding.GetSkeleton()
            skel_query = self._cache.GetSkelQuery(skel)
            if not skel_query:
                continue
            for query in binding.GetSkinningTargets():
                prim = query.GetPrim()
                if not prim.IsA(UsdGeom.Mesh) or not query.HasJointInfluences():
                    continue
                shapes = None
                if query.HasBlendShapes():
                    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
                self._targets[prim.GetPath()] = Skinned(
                    prim, skel_query, query, skel.GetPrim(), shapes
                )
