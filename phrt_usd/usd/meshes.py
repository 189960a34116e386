"""Geometry: gprims as triangles in their own space, primvars, PointInstancer elements.

Every ``Mesh``, ``Sphere``, ``Cube``, ``Cylinder``, ``Cone``, ``Capsule``, ``Plane`` and
``BasisCurves`` (tubes, ``phrt_usd.usd.curves``) becomes one ``LocalMesh``: its
triangles prepared once in its local space (stage units;
fan triangulation, ``leftHanded`` flipped, normals, colours and texture coordinates
expanded to triangle corners; the rules are here, a stage's meshes are read all
together by ``phrt_usd.usd.mesh_batch``). ``phrt_usd.usd.instancers`` makes the elements
of PointInstancers from these, ``phrt_usd.usd.skinning`` deforms skinned ones;
``phrt_usd.usd.stage`` places them in the world and re-reads the shapes that deform
(``local_shape_fn``).

Decisions where USD leaves room:

- Normals: authored ``primvars:normals`` (preferred) or ``normals`` in any interpolation;
  otherwise smooth, area-weighted vertex normals — what Hydra / usdview draw for a mesh
  without normals, whatever its ``subdivisionScheme``. Implicit gprims get their exact
  analytic normals (flat on planar faces, smooth on curved ones).
- Albedo per corner: the bound material's ``diffuseColor`` when authored (a texture's
  mean colour when it is textured), else ``primvars:displayColor`` (linear by USD
  convention, any interpolation), else the UsdPreviewSurface default 0.18 when a material
  is bound, else mid grey 0.5.
- Faces listed in ``holeIndices`` are not triangulated (raster and trace read the same
  triangles, so neither draws them); indices outside the faces are ignored, as Hydra
  does. Smooth normals are computed from the faces that are drawn.
- Subdivision surfaces (``subdivisionScheme`` other than ``none``, USD's fallback being
  ``catmullClark``) are drawn as their control cage; ``is_subdivided`` says which
  (``phrt_usd.usd.traversal.subdivided_meshes`` lists them for a report).
- Faces with fewer than 3 vertices are skipped (they have no area). Non-finite points,
  face counts that do not add up, and out-of-range indices raise ``PhrtError``
  (``mesh_problems`` / ``mesh_problems_in_range`` return those messages for
  ``phrt validate``).

Limits: no subdivision (the cage is rendered), no other curves, points or volumes, no primvar
inheritance from ancestors, implicit gprims take only a constant displayColor and no
texture coordinates. Topology (point, face, hole and instance counts) must not change
over time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Usd, UsdGeom

from phrt_usd.errors import PhrtError
from phrt_usd.usd.curves import tube_corner_colours, tube_geometry
from phrt_usd.usd.materials import MaterialBank, bound_material, colour_primvar
from phrt_usd.usd.values import (
    MIN_NORMAL_LENGTH,
    attr_value,
    first_per_location,
    safe_normalize,
    varies,
)

#: Albedo of a gprim with neither a material nor ``primvars:displayColor``.
DEFAULT_GREY = 0.5


#: Tessellation of implicit gprims: segments around the axis, rings pole to pole.
IMPLICIT_SEGMENTS = 32
IMPLICIT_RINGS = 16


#: Attributes whose animation changes a gprim's local shape.
SHAPE_ATTRS = {
    "Mesh": ("points", "normals", "primvars:normals"),
    "Sphere": ("radius",),
    "Cube": ("size",),
    "Cylinder": ("radius", "height"),
    "Cone": ("radius", "height"),
    "Capsule": ("radius", "height"),
    "Plane": ("width", "length"),
    "BasisCurves": ("points", "widths"),  # drawn as tubes (usd/curves.py)
}


#: Prim types the render reads as geometry (other gprims, e.g. NURBS curves, points,
#: are not drawn).
RENDERED_GPRIM_TYPES = tuple(SHAPE_ATTRS)


def shape_kind(prim: Usd.Prim) -> str | None:
    """The prim's type when the render reads it as geometry (``SHAPE_ATTRS``), else None."""
    t = prim.GetTypeName()
    return t if t in SHAPE_ATTRS else None


# ---- primvars: values expanded to triangle corners ----------------------------------


def _fan_corners(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons without a per-face loop.

    counts : (F,) int vertex count of each face (faces with < 3 vertices are skipped).
    Returns corner ids (T, 3) int64 into the flat face-vertex list and the face of each
    triangle (T,) int64, T = sum(max(count - 2, 0)).
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else counts
    ntri = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts), dtype=np.int64), ntri)
    first = np.concatenate([[0], np.cumsum(ntri)[:-1]]) if len(counts) else ntri
    k = np.arange(len(tri_face), dtype=np.int64) - np.repeat(first, ntri)
    base = starts[tri_face]
    corners = np.stack([base, base + k + 1, base + k + 2], axis=1)
    return corners, tri_face


def _expand(
    values: np.ndarray,
    interpolation: str,
    corners: np.ndarray,
    tri_face: np.ndarray,
    triangles: np.ndarray,
    where: str,
) -> np.ndarray:
    """Expand primvar values (k, c) of any interpolation to triangle corners (T, 3, c).

    corners : (T, 3) face-vertex ids; tri_face : (T,) face ids; triangles : (T, 3) point
    ids. Raises ``PhrtError`` naming ``where`` when there are too few values.
    """
    values = np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    if interpolation == "constant":
        need, idx = 1, None
    elif interpolation == "uniform":
        idx = tri_face
        need = int(idx.max()) + 1 if len(idx) else 0
        if len(values):
            idx = np.repeat(idx[:, None], 3, axis=1)
    elif interpolation in ("vertex", "varying"):
        idx = triangles
        need = int(idx.max()) + 1 if idx.size else 0
    elif interpolation == "faceVarying":
        idx = corners
        need = int(idx.max()) + 1 if idx.size else 0
    else:
        raise PhrtError(f"{where}: unknown interpolation {interpolation!r}")
    if len(values) < need:
        raise PhrtError(
            f"{where}: {len(values)} values for {interpolation} interpolation, need {need}"
        )
    if idx is None:
        return np.broadcast_to(values[0], (len(triangles), 3, values.shape[1])).copy()
    return values[idx]


def _read_primvar(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> tuple[np.ndarray, str] | None:
    """Flattened values and interpolation of an authored primvar, or None."""
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    if not pv or not pv.HasAuthoredValue():
        return None
    value = pv.ComputeFlattened(time)
    if value is None or len(value) == 0:
        return None
    return np.asarray(value, dtype=np.float64), str(pv.GetInterpolation())


# ---- meshes ---------------------------------------------------------------------------


@dataclass
class LocalMesh:
    """Triangles of one gprim in its own space (stage units).

    points         : (n, 3) float64
    triangles      : (T, 3) int64 into points, counter-clockwise = front
    corner_normals : (T, 3, 3) float64 unit normals (authored, analytic, or smooth)
    corner_albedo  : (T, 3, 3) float32 linear RGB
    tri_material   : (T,) int32 MaterialTable rows
    corner_uv      : (T, 3, 2) float32, or None when the gprim has no texture
    """

    points: np.ndarray
    triangles: np.ndarray
    corner_normals: np.ndarray
    corner_albedo: np.ndarray
    tri_material: np.ndarray
    corner_uv: np.ndarray | None = None
    smooth: bool = False  # normals are smooth_corner_normals(points): redo on deformation


#: Triangles whose corner positions are gathered at once by ``smooth_corner_normals``:
#: its temporaries stay a few MB whatever the mesh's size.
SMOOTH_CHUNK_TRIANGLES = 1 << 16


def smooth_corner_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals, gathered to corners: (T, 3, 3) float64."""
    face = np.empty((len(triangles), 3))  # e1 x e2, length = 2 * area
    for start in range(0, len(triangles), SMOOTH_CHUNK_TRIANGLES):
        rows = slice(start, start + SMOOTH_CHUNK_TRIANGLES)
        p = points[triangles[rows]]
        face[rows] = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    acc = np.zeros_like(points)
    for c in range(3):
        for axis in range(3):
            acc[:, axis] += np.bincount(triangles[:, c], face[:, axis], minlength=len(points))
    corner = safe_normalize(acc)[triangles]
    # Vertices whose incident faces cancel (or have zero area) take their face normal.
    bad = (np.linalg.norm(acc, axis=1) <= MIN_NORMAL_LENGTH)[triangles]
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=1))
        face_n = safe_normalize(face[rows])[:, None, :]
        corner[rows] = np.where(bad[rows][..., None], face_n, corner[rows])
    return corner


def _points_problems(points: np.ndarray, where: str) -> list[str]:
    """Render refusal of a point array (n, 3): non-finite values."""
    if np.isfinite(points).all():  # one reduction for the usual case
        return []
    finite = np.all(np.isfinite(points), axis=1)
    return [f"{where}: non-finite point at index {int(np.argmax(~finite))}"]


def _check_points(points: np.ndarray, where: str) -> None:
    for problem in _points_problems(points, where):
        raise PhrtError(problem)


def _mesh_counts_indices(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[np.ndarray, np.ndarray]:
    """faceVertexCounts and faceVertexIndices at ``time`` as int64 arrays."""
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    return counts, indices


def _topology_problems(path, counts: np.ndarray, indices: np.ndarray, n_points: int) -> list[str]:
    """Render refusals of a mesh topology: negative counts, counts that do not add up to
    the indices, indices outside the points."""
    problems = []
    if np.any(counts < 0):
        problems.append(f"{path}.faceVertexCounts: negative face vertex count")
    if int(counts.sum()) != len(indices):
        problems.append(
            f"{path}.faceVertexIndices: {len(indices)} indices but faceVertexCounts "
            f"sums to {int(counts.sum())}"
        )
    if len(indices) and (indices.min() < 0 or indices.max() >= n_points):
        problems.append(
            f"{path}.faceVertexIndices: index out of range [0, {n_points}) "
            f"(min {indices.min()}, max {indices.max()})"
        )
    return problems


def mesh_problems(prim: Usd.Prim, time: float) -> list[str]:
    """Every reason the render refuses this UsdGeomMesh's points and topology at ``time``
    (the first is the message it raises), ``[]`` when it reads. Faces with fewer than
    3 vertices are not a refusal (they are skipped)."""
    code = Usd.TimeCode(float(time))
    points = _mesh_points_at(prim, code)
    counts, indices = _mesh_counts_indices(prim, code)
    path = prim.GetPath()
    return _points_problems(points, f"{path}.points") + _topology_problems(
        path, counts, indices, len(points)
    )


def mesh_problems_in_range(prim: Usd.Prim, frames: tuple[float, float]) -> list[str]:
    """``mesh_problems`` wherever the render reads this mesh over the frame range: at its
    start and, when the shape is animated (points or normals may vary, as the render
    decides), at every time sample inside the range of points and topology, with the
    refusal of a point count that changes. One message per location, the earliest."""
    start, end = frames
    problems = mesh_problems(prim, start)
    if problems or not varies(prim, SHAPE_ATTRS["Mesh"]):
        return problems
    n_points = len(_mesh_points_at(prim, Usd.TimeCode(start)))
    interval = Gf.Interval(start, end)
    times: set[float] = set()
    for name in (*SHAPE_ATTRS["Mesh"], "faceVertexCounts", "faceVertexIndices"):
        attr = prim.GetAttribute(name)
        if attr:
            times.update(attr.GetTimeSamplesInInterval(interval))
    later = []
    for t in sorted(times - {start}):
        found = mesh_problems(prim, t)
        if not found and len(_mesh_points_at(prim, Usd.TimeCode(t))) != n_points:
            found = [f"{prim.GetPath()}: topology changes at time {t} (not supported)"]
        later += found
    return problems + first_per_location(later)


def _mesh_topology(prim: Usd.Prim, time: Usd.TimeCode, n_points: int):
    """Validated fan triangulation of a UsdGeomMesh, without its ``holeIndices`` faces.

    Returns corners (T, 3) face-vertex ids, tri_face (T,), triangles (T, 3) point ids,
    all int64, with ``leftHanded`` winding already flipped.
    """
    mesh = UsdGeom.Mesh(prim)
    counts, indices = _mesh_counts_indices(prim, time)
    for problem in _topology_problems(prim.GetPath(), counts, indices, n_points):
        raise PhrtError(problem)
    corners, tri_face = _fan_corners(counts)
    holes = mesh.GetHoleIndicesAttr().Get(time)
    if holes is not None and len(holes) and len(tri_face):
        drawn = ~np.isin(tri_face, np.asarray(holes, dtype=np.int64))
        corners, tri_face = corners[drawn], tri_face[drawn]
    if mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        corners = corners[:, [0, 2, 1]]
    return corners, tri_face, indices[corners]


def _mesh_points_at(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    """(n, 3) float64 points at ``time`` (unchecked; empty when unauthored)."""
    pts = UsdGeom.Mesh(prim).GetPointsAttr().Get(time)
    return np.asarray(pts if pts is not None else [], dtype=np.float64).reshape(-1, 3)


def _read_mesh_points(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    points = _mesh_points_at(prim, time)
    _check_points(points, f"{prim.GetPath()}.points")
    return points


def authored_normals(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[np.ndarray, str, str] | None:
    """A mesh's authored normals: (values (k, 3) float64, NaN read as 0, interpolation,
    where) of ``primvars:normals`` (preferred) or ``normals``; None when neither is
    authored (smooth normals are computed)."""
    path = prim.GetPath()
    pv = _read_primvar(prim, "normals", time)
    if pv is not None:
        values, interp = pv
        where = f"{path}.primvars:normals"
    else:
        mesh = UsdGeom.Mesh(prim)
        attr = mesh.GetNormalsAttr()
        if not attr.HasAuthoredValue():
            return None
        raw = attr.Get(time)
        if raw is None or len(raw) == 0:
            return None
        values = np.asarray(raw, dtype=np.float64)
        interp = str(mesh.GetNormalsInterpolation())
        where = f"{path}.normals"
    return np.nan_to_num(values.reshape(-1, 3)), interp, where  # bad normals shade, not crash


def _mesh_normals(prim, time, corners, tri_face, triangles) -> np.ndarray | None:
    """Authored normals expanded to corners (T, 3, 3), or None (compute smooth)."""
    normals = authored_normals(prim, time)
    if normals is None:
        return None
    values, interp, where = normals
    return safe_normalize(_expand(values, interp, corners, tri_face, triangles, where))


def colour_values(values: np.ndarray) -> np.ndarray:
    """(n, 3) colours of a colour primvar's values: RGB of colour3 or colour4 values, a
    float's grey."""
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return np.zeros((0, 3))
    values = values.reshape(len(values), -1) if values.ndim else values.reshape(1, 1)
    return values[:, :3] if values.shape[1] >= 3 else np.repeat(values[:, :1], 3, axis=1)


def albedo_rows(bank: MaterialBank) -> tuple[np.ndarray, np.ndarray]:
    """Per MaterialTable row: its diffuse (M, 3) and whether it is authored (M,) bool."""
    rows = bank.rows
    diffuse = np.array([r.diffuse for r in rows])
    return diffuse, np.array([r.diffuse_authored for r in rows], dtype=bool)


def _albedo(tri_material: np.ndarray, display: np.ndarray | None, bank: MaterialBank) -> np.ndarray:
    """Corner albedo (T, 3, 3) float32: material diffuse, else displayColor, else grey."""
    diffuse, authored = albedo_rows(bank)
    diffuse, authored = diffuse[tri_material], authored[tri_material]  # (T, 3), (T,)
    if display is None:
        no_material = tri_material == 0
        diffuse[no_material] = DEFAULT_GREY
        out = np.repeat(diffuse[:, None, :], 3, axis=1)
    else:
        out = np.where(authored[:, None, None], diffuse[:, None, :], display)
    return out.astype(np.float32)


# ---- implicit gprims (built along +Z, then rotated onto their axis) ------------------


def _grid_surface(profile_r: np.ndarray, profile_z: np.ndarray, normal_rz: np.ndarray):
    """Surface of revolution around +Z from a profile curve (ring k at radius r[k], z[k]).

    normal_rz : (k, 2) profile normals (radial, z). Returns points (n, 3), triangles
    (T, 3) and per-point normals (n, 3), counter-clockwise seen from outside.
    """
    seg = IMPLICIT_SEGMENTS
    phi = np.linspace(0.0, 2.0 * np.pi, seg, endpoint=False)
    c, s = np.cos(phi), np.sin(phi)
    pts = np.stack(
        [np.outer(profile_r, c), np.outer(profile_r, s), np.repeat(profile_z[:, None], seg, 1)],
        axis=-1,
    ).reshape(-1, 3)
    nrm = np.stack(
        [
            np.outer(normal_rz[:, 0], c),
            np.outer(normal_rz[:, 0], s),
            np.repeat(normal_rz[:, 1:2], seg, 1),
        ],
        axis=-1,
    ).reshape(-1, 3)
    k = len(profile_r)
    ring = np.arange(k - 1)[:, None] * seg
    j = np.arange(seg)[None, :]
    a = (ring + j).ravel()
    b = (ring + (j + 1) % seg).ravel()
    a2, b2 = a + seg, b + seg
    tris = np.concatenate([np.stack([a, b, b2], 1), np.stack([a, b2, a2], 1)])
    return pts, tris, safe_normalize(nrm)


def _disk(radius: float, z: float, up: bool):
    """A flat disk at height z facing +Z (up) or -Z: points, triangles, normals."""
    seg = IMPLICIT_SEGMENTS
    phi = np.linspace(0.0, 2.0 * np.pi, seg, endpoint=False)
    pts = np.concatenate(
        [
            [[0.0, 0.0, z]],
            np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(seg, z)], 1),
        ]
    )
    j = np.arange(seg)
    tris = np.stack([np.zeros(seg, np.int64), 1 + j, 1 + (j + 1) % seg], 1)
    if not up:
        tris = tris[:, [0, 2, 1]]
    nrm = np.tile([0.0, 0.0, 1.0 if up else -1.0], (seg + 1, 1))
    return pts, tris, nrm


def _merge(parts):
    pts, tris, nrms, off = [], [], [], 0
    for p, t, n in parts:
        pts.append(p)
        tris.append(t + off)
        nrms.append(n)
        off += len(p)
    return np.concatenate(pts), np.concatenate(tris), np.concatenate(nrms)


def _sphere_profile(radius: float, z0: float, lat0: float, lat1: float, rings: int):
    lat = np.linspace(lat0, lat1, rings + 1)
    r = radius * np.cos(lat)
    z = z0 + radius * np.sin(lat)
    return r, z, np.stack([np.cos(lat), np.sin(lat)], 1)


def _implicit_z(kind: str, prim: Usd.Prim, time: Usd.TimeCode):
    """Tessellate an implicit gprim along +Z: points (n, 3), triangles, point normals."""
    g = lambda name, d: float(attr_value(prim, name, time, d))  # noqa: E731
    if kind == "Sphere":
        r, z, n = _sphere_profile(g("radius", 1.0), 0.0, -np.pi / 2, np.pi / 2, IMPLICIT_RINGS)
        return _grid_surface(r, z, n)
    if kind == "Cube":
        h = 0.5 * g("size", 2.0)
        faces = []
        for axis in range(3):
            for sign in (1.0, -1.0):
                u, v = (axis + 1) % 3, (axis + 2) % 3
                quad = np.zeros((4, 3))
                quad[:, axis] = sign * h
                quad[:, u] = [-h, h, h, -h]
                quad[:, v] = [-h, -h, h, h]
                tri = np.array([[0, 1, 2], [0, 2, 3]])
                if sign < 0:
                    tri = tri[:, [0, 2, 1]]
                nrm = np.zeros((4, 3))
                nrm[:, axis] = sign
                faces.append((quad, tri, nrm))
        return _merge(faces)
    if kind == "Cylinder":
        r, hh = g("radius", 1.0), 0.5 * g("height", 2.0)
        side = _grid_surface(np.array([r, r]), np.array([-hh, hh]), np.array([[1, 0], [1, 0.0]]))
        return _merge([side, _disk(r, hh, True), _disk(r, -hh, False)])
    if kind == "Cone":
        r, h = g("radius", 1.0), g("height", 2.0)
        slope = np.array([h, r]) / max(np.hypot(h, r), MIN_NORMAL_LENGTH)
        # Apex ring of radius 0 (duplicated per segment) keeps per-segment normals.
        side = _grid_surface(np.array([r, 0.0]), np.array([-h / 2, h / 2]), np.stack([slope] * 2))
        return _merge([side, _disk(r, -h / 2, False)])
    if kind == "Capsule":
        r, hh = g("radius", 0.5), 0.5 * g("height", 1.0)
        half = IMPLICIT_RINGS // 2
        lo = _sphere_profile(r, -hh, -np.pi / 2, 0.0, half)
        hi = _sphere_profile(r, hh, 0.0, np.pi / 2, half)
        prof = [np.concatenate([a, b]) for a, b in zip(lo, hi, strict=True)]
        return _grid_surface(*prof)
    raise AssertionError(kind)


#: UsdGeomPlane: (width axis, length axis) for each value of ``axis`` (the normal).
_PLANE_AXES = {"X": (2, 1), "Y": (0, 2), "Z": (0, 1)}


def _plane(prim: Usd.Prim, time: Usd.TimeCode):
    """A UsdGeomPlane as two triangles facing +axis: points, triangles, point normals.

    Single-sided (front = +axis); ``doubleSided`` is left to the renderer's culling.
    """
    axis = str(attr_value(prim, "axis", time, "Z"))
    u, v = _PLANE_AXES.get(axis, _PLANE_AXES["Z"])
    n = 3 - u - v
    half_w = 0.5 * float(attr_value(prim, "width", time, 2.0))
    half_l = 0.5 * float(attr_value(prim, "length", time, 2.0))
    pts = np.zeros((4, 3))
    pts[:, u] = [-half_w, half_w, half_w, -half_w]
    pts[:, v] = [-half_l, -half_l, half_l, half_l]
    normal = np.eye(3)[n]
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    if np.dot(np.cross(pts[1] - pts[0], pts[2] - pts[0]), normal) < 0:
        tris = tris[:, [0, 2, 1]]  # (u, v, n) is a left-handed frame for axis X
    return pts, tris, np.tile(normal, (4, 1))


#: Cyclic permutations (proper rotations, det +1) taking the +Z-built shape onto axis X
#: or Y: ``new = old[:, perm]`` moves the old Z column to the new axis.
_AXIS_PERMUTATION = {"Z": [0, 1, 2], "X": [2, 0, 1], "Y": [1, 2, 0]}


def _implicit_geometry(kind: str, prim: Usd.Prim, time: Usd.TimeCode):
    """Points (n, 3), triangles (T, 3), corner normals (T, 3, 3) in prim space."""
    if kind == "BasisCurves":
        return tube_geometry(prim, time)
    if kind == "Plane":
        pts, tris, nrm = _plane(prim, time)
    else:
        pts, tris, nrm = _implicit_z(kind, prim, time)
        axis = str(attr_value(prim, "axis", time, "Z")) if kind not in ("Sphere", "Cube") else "Z"
        perm = _AXIS_PERMUTATION.get(axis, [0, 1, 2])
        pts, nrm = pts[:, perm], nrm[:, perm]
    _check_points(pts, f"{prim.GetPath()} (size attributes)")
    return pts, tris.astype(np.int64), nrm[tris]


def read_implicit(kind: str, prim: Usd.Prim, time: Usd.TimeCode, bank: MaterialBank) -> LocalMesh:
    """The ``LocalMesh`` of an implicit gprim (any ``SHAPE_ATTRS`` type but ``Mesh``;
    meshes are read, many at once, by ``phrt_usd.usd.mesh_batch``)."""
    pts, tris, normals = _implicit_geometry(kind, prim, time)
    # Bound for the render's binding purposes, as meshes are (``materials.face_materials``).
    mat = bank.index(bound_material(prim, bank.purposes))
    tri_material = np.full(len(tris), mat, dtype=np.int32)
    display = None
    name = colour_primvar(bank, tri_material[:1])
    pv = _read_primvar(prim, name, time)
    if pv is not None and len(pv[0]) and kind == "BasisCurves":  # along each curve
        values = np.clip(np.nan_to_num(colour_values(pv[0])), 0.0, None)
        where = f"{prim.GetPath()}.primvars:{name}"
        display = tube_corner_colours(prim, time, values, pv[1], where)
    elif pv is not None and len(pv[0]):
        color = np.clip(np.nan_to_num(colour_values(pv[0])[0]), 0.0, None)
        display = np.broadcast_to(color, (len(tris), 3, 3))
    albedo = _albedo(tri_material, display, bank)
    uv = np.zeros((len(tris), 3, 2), np.float32) if bank.rows[mat].needs_uv else None
    return LocalMesh(pts, tris, normals, albedo, tri_material, uv)


# ---- deformation and dispatch -----------------------------------------------------


#: Deformation reader: time → (local points (n, 3), corner normals (T, 3, 3) or None
#: when the normals are analytic or smooth).
ShapeAt = Callable[[Usd.TimeCode], tuple[np.ndarray, np.ndarray | None]]


def local_shape_fn(kind: str, prim: Usd.Prim) -> ShapeAt:
    """Reader of a deforming gprim's points (and authored normals) at a time."""
    if kind == "BasisCurves":  # a tube's normals follow its curve
        return lambda code: (lambda g: (g[0], g[2]))(_implicit_geometry(kind, prim, code))
    if kind != "Mesh":
        return lambda code: (_implicit_geometry(kind, prim, code)[0], None)

    def mesh_at(code: Usd.TimeCode):
        return _read_mesh_points(prim, code), mesh_normals_at(prim, code)[1]

    return mesh_at


def mesh_normals_at(prim: Usd.Prim, code: Usd.TimeCode) -> tuple[np.ndarray, np.ndarray | None]:
    """A UsdGeomMesh's drawn triangles (T, 3) int64 point ids and its authored normals
    expanded to their corners (T, 3, 3) float64 in mesh space, or None (smooth) at
    ``code``."""
    points = _read_mesh_points(prim, code)
    corners, tri_face, triangles = _mesh_topology(prim, code, len(points))
    return triangles, _mesh_normals(prim, code, corners, tri_face, triangles)


def is_subdivided(prim: Usd.Prim) -> bool:
    """True for a UsdGeomMesh whose ``subdivisionScheme`` (authored, else USD's fallback
    ``catmullClark``) is not ``none``: a subdivision surface, drawn as its cage."""
    if not prim.IsA(UsdGeom.Mesh):
        return False
    return UsdGeom.Mesh(prim).GetSubdivisionSchemeAttr().Get() != UsdGeom.Tokens.none


def mesh_area(
    points: np.ndarray,
    counts: np.ndarray,
    indices: np.ndarray,
    holes: np.ndarray | None = None,
) -> float:
    """Total area of a polygon mesh, fan-triangulated as the render does (faces of fewer
    than 3 vertices and the ``holeIndices`` faces skipped), in stage units squared.

    points : (p, 3) float64; counts : (f,) int64 >= 0; indices : (sum(counts),) int64 in
    range (the render's topology rules hold); holes : (h,) int face indices left out
    (``holeIndices``; indices outside the faces are ignored, as the render does).
    """
    corners, tri_face = _fan_corners(counts)
    if holes is not None and len(holes) and len(tri_face):
        corners = corners[~np.isin(tri_face, np.asarray(holes, dtype=np.int64))]
    if len(corners) == 0:
        return 0.0
    a, b, c = (points[indices[corners[:, k]]] for k in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
