"""Many UsdGeomMeshes triangulated together: one numpy pass over all their faces.

``MeshBatch.add`` reads what one mesh holds (points, topology, the primvars the render
uses, its face materials) and checks its points and topology, raising the messages of
``meshes.mesh_problems``; ``MeshBatch.resolve`` then makes every mesh's ``LocalMesh`` in
one pass over the faces of all of them: one fan triangulation of all face counts, the
holes and ``leftHanded`` flips as masks, every primvar expanded to triangle corners by
one gather whatever each mesh's interpolation, smooth normals of all meshes by one
accumulation. The rules are those of ``phrt_usd.usd.meshes`` (its module doc), the
results the same numbers; what is batched is the numpy work, so a stage of 5000 small
meshes costs a few numpy calls instead of a few hundred thousand. Each ``LocalMesh``'s
arrays are views into the batch's arrays (readers never write into them: deformation
replaces a mesh's arrays).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom

from phrt_usd import progress
from phrt_usd.errors import PhrtError
from phrt_usd.usd import meshes
from phrt_usd.usd.materials import MaterialBank, colour_primvar, face_materials
from phrt_usd.usd.values import safe_normalize

#: Triangles resolved in one pass: the pass's temporaries (a few hundred bytes a
#: triangle) stay near 100 MB however large the stage, few enough passes that their
#: per-pass cost does not count (a 1.4 M-triangle stage: 6).
RESOLVE_CHUNK_TRIANGLES = 1 << 18

#: Interpolations by the index a corner's value is found at (``meshes._expand``).
_BY_INDEX = {"constant": 0, "uniform": 1, "vertex": 2, "varying": 2, "faceVarying": 3}


@dataclass
class _Primvar:
    """One mesh's flattened primvar values (k, c) float64 and their interpolation."""

    values: np.ndarray
    interpolation: str
    where: str


@dataclass
class _Source:
    """What one mesh contributes to the batch, as read from USD."""

    points: np.ndarray  # (n, 3) float64
    counts: np.ndarray  # (F,) int64
    indices: np.ndarray  # (sum(counts),) int64
    holes: np.ndarray  # (h,) int64 face ids (any, ids outside the faces are ignored)
    left_handed: bool
    face_material: np.ndarray  # (F,) int32 MaterialTable rows
    normals: _Primvar | None
    colour: _Primvar | None
    uv: _Primvar | None
    textured: bool  # a drawn face's material needs texture coordinates
    triangles: int  # at most this many (faces of 3 or more vertices, holes included)


class PendingMesh:
    """A mesh added to a ``MeshBatch``, its ``LocalMesh`` once the batch is resolved."""

    def __init__(self, batch: MeshBatch, slot: int) -> None:
        self.batch, self.slot = batch, slot

    def resolved(self) -> meshes.LocalMesh:
        """The mesh's ``LocalMesh`` (``MeshBatch.resolve`` must have run)."""
        return self.batch.meshes[self.slot]


class MeshBatch:
    """UsdGeomMeshes read one by one (``add``), triangulated together (``resolve``).

    meshes : the ``LocalMesh`` of each mesh added, in order, after ``resolve``."""

    def __init__(self, time: Usd.TimeCode, bank: MaterialBank) -> None:
        self.time, self.bank = time, bank
        self._sources: list[_Source] = []
        self.meshes: list[meshes.LocalMesh] = []

    def __len__(self) -> int:
        return len(self._sources)

    def add(self, prim: Usd.Prim) -> PendingMesh:
        """Read mesh ``prim`` into the batch; its ``LocalMesh`` comes with ``resolve``.
        Raises ``PhrtError`` for points or topology the render refuses
        (``meshes.mesh_problems``)."""
        time, bank = self.time, self.bank
        points = meshes._read_mesh_points(prim, time)
        counts, indices = meshes._mesh_counts_indices(prim, time)
        for problem in meshes._topology_problems(prim.GetPath(), counts, indices, len(points)):
            raise PhrtError(problem)
        mesh = UsdGeom.Mesh(prim)
        holes = mesh.GetHoleIndicesAttr().Get(time)
        holes = np.asarray(holes if holes is not None else [], dtype=np.int64)
        left = mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded
        normals = meshes.authored_normals(prim, time)
        normals = None if normals is None else _Primvar(*normals)
        face_mat, _ = face_materials(prim, len(counts), bank)
        # displayColor, or the primvar a UsdPrimvarReader of the material names.
        name = colour_primvar(bank, face_mat)
        colour = meshes._read_primvar(prim, name, time)
        if colour is not None:
            values = np.clip(np.nan_to_num(meshes.colour_values(colour[0])), 0.0, None)
            colour = _Primvar(values, colour[1], f"{prim.GetPath()}.primvars:{name}")
        uv, textured = None, False
        # The mesh's materials are in the bank now: without a textured one, no uv.
        any_textured = any(row.needs_uv for row in bank.rows)
        drawn = _drawn_materials(face_mat, counts, holes) if any_textured else []
        needs = [m for m in drawn if bank.rows[m].needs_uv]
        if needs:
            textured = True
            name = bank.rows[needs[0]].uv_primvar
            pv = meshes._read_primvar(prim, name, time)
            if pv is not None:
                values = np.nan_to_num(pv[0].reshape(len(pv[0]), -1)[:, :2])
                uv = _Primvar(values, pv[1], f"{prim.GetPath()}.primvars:{name}")
        self._sources.append(
            _Source(points, counts, indices, holes, left, face_mat, normals, colour, uv,
                    textured, int(np.maximum(counts - 2, 0).sum()))
        )  # fmt: skip
        return PendingMesh(self, len(self._sources) - 1)

    # ---- resolve --------------------------------------------------------------------

    def resolve(self) -> list[meshes.LocalMesh]:
        """The ``LocalMesh`` of every mesh added, in order (module doc), made
        ``RESOLVE_CHUNK_TRIANGLES`` triangles at a time. Raises ``PhrtError`` for a
        primvar with too few values or an unknown interpolation."""
        chunk: list[_Source] = []
        size = done = 0
        total = sum(s.triangles for s in self._sources)
        for source in self._sources:
            if chunk and size + source.triangles > RESOLVE_CHUNK_TRIANGLES:
                progress.step("triangulating", done, total)
                self.meshes += self._resolve(chunk)
                chunk, done, size = [], done + size, 0
            chunk.append(source)
            size += source.triangles
        if chunk:
            progress.step("triangulating", done, total)
            self.meshes += self._resolve(chunk)
        self._sources = []  # the LocalMeshes hold what is still needed
        return self.meshes

    def _resolve(self, sources: list[_Source]) -> list[meshes.LocalMesh]:
        """The ``LocalMesh`` of each of ``sources``, in one pass over their faces."""
        layout = _Layout(sources)
        normals = self._normals(sources, layout)
        albedo = self._albedo(sources, layout)
        uv = None
        if any(s.textured for s in sources):  # zeros where a textured mesh has no uv
            uv = np.zeros((layout.count, 3, 2), np.float32)
            gathered = layout.gather([s.uv for s in sources])
            if gathered is not None:
                uv[gathered[0]] = gathered[1]
        out = []
        for m, source in enumerate(sources):
            rows = layout.rows(m)
            out.append(
                meshes.LocalMesh(
                    points=source.points,
                    triangles=layout.local_triangles[rows],
                    corner_normals=normals[rows],
                    corner_albedo=albedo[rows],
                    tri_material=layout.tri_material[rows],
                    corner_uv=uv[rows] if source.textured else None,
                    smooth=source.normals is None,
                )
            )
        return out

    @staticmethod
    def _normals(sources: list[_Source], layout: _Layout) -> np.ndarray:
        """(T, 3, 3) float64 corner normals: the authored ones expanded and normalised,
        smooth ones (area-weighted, ``meshes.smooth_corner_normals``) for the rest."""
        smooth = np.array([s.normals is None for s in sources])
        points = sources[0].points if len(sources) == 1 else np.concatenate(
            [s.points for s in sources]
        )
        if smooth.all():  # every row: no gather, no copy
            tri = layout.local_triangles + layout.point_offset[layout.tri_mesh][:, None]
            return meshes.smooth_corner_normals(points, tri)
        out = np.empty((layout.count, 3, 3))
        rows, values = layout.gather([s.normals for s in sources])
        out[rows] = safe_normalize(values)
        if smooth.any():
            rows = layout.rows_of(smooth)
            tri = layout.local_triangles[rows] + layout.point_offset[layout.tri_mesh[rows]][:, None]
            out[rows] = meshes.smooth_corner_normals(points, tri)  # ids into all points
        return out

    def _albedo(self, sources: list[_Source], layout: _Layout) -> np.ndarray:
        """(T, 3, 3) float32 corner albedo (``meshes._albedo`` of every mesh at once)."""
        diffuse, authored = meshes.albedo_rows(self.bank)
        tri_material = layout.tri_material
        base = diffuse[tri_material]  # (T, 3)
        has_colour = np.array([s.colour is not None for s in sources])[layout.tri_mesh]
        base[(~has_colour) & (tri_material == 0)] = meshes.DEFAULT_GREY
        out = np.empty((layout.count, 3, 3), np.float32)
        out[:] = base[:, None, :]
        gathered = layout.gather([s.colour for s in sources])
        if gathered is not None:  # displayColor where the material's diffuse is not authored
            rows, colour = gathered
            take = ~authored[tri_material[rows]]
            out[rows[take]] = colour[take]
        return out


def _drawn_materials(face_mat: np.ndarray, counts: np.ndarray, holes: np.ndarray) -> list[int]:
    """The material rows of a mesh's faces that make triangles (3 or more vertices, not
    a hole), ascending."""
    drawn = counts >= 3
    if len(holes):
        drawn[holes[(holes >= 0) & (holes < len(counts))]] = False
    if len(face_mat) and face_mat[0] == face_mat[-1] and (face_mat == face_mat[0]).all():
        return [int(face_mat[0])] if drawn.any() else []  # one material: no unique
    return [int(m) for m in np.unique(face_mat[drawn])]


class _Layout:
    """The batch's triangles: one fan triangulation over all meshes' faces.

    Per triangle (T rows, grouped by mesh in order): tri_mesh, the local face, corner
    and point ids of its corners, its local triangle; per mesh: offsets and the maxima
    a primvar's value count is checked against."""

    def __init__(self, sources: list[_Source]) -> None:
        n = len(sources)
        faces = np.array([len(s.counts) for s in sources], dtype=np.int64)
        corners_n = np.array([len(s.indices) for s in sources], dtype=np.int64)
        points_n = np.array([len(s.points) for s in sources], dtype=np.int64)
        self.face_offset = np.concatenate([[0], np.cumsum(faces)[:-1]])
        self.corner_offset = np.concatenate([[0], np.cumsum(corners_n)[:-1]])
        self.point_offset = np.concatenate([[0], np.cumsum(points_n)[:-1]])
        counts = np.concatenate([s.counts for s in sources])
        indices = np.concatenate([s.indices for s in sources])
        corners, tri_face = meshes._fan_corners(counts)  # global corner and face ids
        face_mesh = np.repeat(np.arange(n), faces)
        drawn = np.ones(len(counts), dtype=bool)
        for m, s in enumerate(sources):  # holes: ids inside the mesh's faces only
            if len(s.holes):
                inside = s.holes[(s.holes >= 0) & (s.holes < len(s.counts))]
                drawn[inside + self.face_offset[m]] = False
        if not drawn.all():
            keep = drawn[tri_face]
            corners, tri_face = corners[keep], tri_face[keep]
        tri_mesh = face_mesh[tri_face]
        left = np.array([s.left_handed for s in sources])
        if left.any():
            flip = left[tri_mesh]
            corners[flip] = corners[flip][:, [0, 2, 1]]
        self.count = len(tri_face)
        self.tri_mesh = tri_mesh
        self.local_face = tri_face - self.face_offset[tri_mesh]
        self.local_corner = corners - self.corner_offset[tri_mesh][:, None]
        self.local_triangles = indices[corners]  # point ids are local already
        self.tri_material = np.concatenate([s.face_material for s in sources])[tri_face]
        self.tri_material = self.tri_material.astype(np.int32)
        per_mesh = np.bincount(tri_mesh, minlength=n)
        self.tri_offset = np.concatenate([[0], np.cumsum(per_mesh)])
        self._maxima = self._index_maxima(per_mesh)

    def rows(self, m: int) -> slice:
        """The triangle rows of mesh ``m``."""
        return slice(int(self.tri_offset[m]), int(self.tri_offset[m + 1]))

    def rows_of(self, meshes_mask: np.ndarray) -> np.ndarray:
        """Triangle rows (r,) int64 of the meshes where ``meshes_mask`` (n,) is True."""
        return np.flatnonzero(meshes_mask[self.tri_mesh])

    def _index_maxima(self, per_mesh: np.ndarray) -> np.ndarray:
        """(n, 4) per mesh: the values a primvar needs at each ``_BY_INDEX`` index
        (1 for constant; 1 + the largest drawn face, point and corner id), 0 when the
        mesh draws no triangle."""
        out = np.zeros((len(per_mesh), 4), dtype=np.int64)
        out[:, 0] = 1
        having = np.flatnonzero(per_mesh)
        if len(having):
            starts = self.tri_offset[having]
            for col, ids in ((1, self.local_face),
                             (2, self.local_triangles.max(axis=1)),
                             (3, self.local_corner.max(axis=1))):  # fmt: skip
                out[having, col] = np.maximum.reduceat(ids, starts) + 1
        return out

    def gather(self, primvars: list[_Primvar | None]) -> tuple[np.ndarray, np.ndarray] | None:
        """Each mesh's primvar at its triangles' corners: (rows (r,) int64, the triangle
        rows of the meshes that have one; values (r, 3, c) float64), or None when no
        mesh has one. Raises ``PhrtError`` for too few values or an unknown
        interpolation (``meshes._expand``'s rule)."""
        having = [m for m, pv in enumerate(primvars) if pv is not None]
        if not having:
            return None
        width = max(primvars[m].values.shape[1] for m in having)
        offsets = np.zeros(len(primvars), dtype=np.int64)
        kinds = np.zeros(len(primvars), dtype=np.int64)
        values, total = [], 0
        for m in having:
            pv = primvars[m]
            if pv.interpolation not in _BY_INDEX:
                raise PhrtError(f"{pv.where}: unknown interpolation {pv.interpolation!r}")
            kind = _BY_INDEX[pv.interpolation]
            need = int(self._maxima[m, kind])
            if len(pv.values) < need:
                raise PhrtError(
                    f"{pv.where}: {len(pv.values)} values for {pv.interpolation} "
                    f"interpolation, need {need}"
                )
            offsets[m], kinds[m] = total, kind
            v = pv.values
            if v.shape[1] < width:  # fewer components than another mesh's: zeros after
                v = np.pad(v, ((0, 0), (0, width - v.shape[1])))
            values.append(v)
            total += len(v)
        flat = np.concatenate(values) if len(values) > 1 else values[0]
        mask = np.zeros(len(primvars), dtype=bool)
        mask[having] = True
        rows = self.rows_of(mask)
        mesh = self.tri_mesh[rows]
        kind = kinds[mesh]
        index = np.empty((len(rows), 3), dtype=np.int64)
        for k, ids in enumerate((None, self.local_face, self.local_triangles, self.local_corner)):
            pick = kind == k
            if not pick.any():
                continue
            if ids is None:
                index[pick] = 0
            elif ids.ndim == 1:
                index[pick] = ids[rows[pick]][:, None]
            else:
                index[pick] = ids[rows[pick]]
        index += offsets[mesh][:, None]
        return rows, flat[index]



def read_gprim(kind: str, prim: Usd.Prim, time: Usd.TimeCode, bank: MaterialBank):
    """The ``LocalMesh`` of one gprim of type ``kind`` (``meshes.SHAPE_ATTRS``) at
    ``time``: a mesh as a batch of one, an implicit gprim tessellated."""
    if kind != "Mesh":
        return meshes.read_implicit(kind, prim, time, bank)
    batch = MeshBatch(time, bank)
    pending = batch.add(prim)
    batch.resolve()
    return pending.resolved()
