"""Elements placed in the world many at a time: the first placement of a stage's parts.

``place_parts`` does for a list of parts what ``StageScene._place`` does for one (its
rules: row-vector transform, stage units to metres, normals through ``normal_matrix``
and normalised, the winding flipped by a negative-determinant transform), but gathers
the parts into groups of about ``PLACE_CHUNK_ROWS`` vertices and corners and transforms each
group with a few numpy calls, so 5000 small meshes cost what a few large ones do. A
part is anything with ``mesh`` (a ``LocalMesh``), ``matrix_at``, ``path``, ``element``,
``v0``, ``t0`` (its first vertex and triangle rows) and the ``matrix`` and ``flipped``
it is left with (``stage._Part``).
"""

from __future__ import annotations

import numpy as np

from phrt_usd import progress
from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import Element, Geometry
from phrt_usd.usd.values import TimeContext, normal_matrix, safe_normalize

#: Rows (vertices + triangle corners) transformed by one group's numpy calls: the
#: group's per-row matrices (72 bytes a row) stay near 5 MB, in cache, and 5000 small
#: parts make ~70 groups; a part larger than this is a group of its own, transformed by
#: its one matrix.
PLACE_CHUNK_ROWS = 1 << 16

#: Corner order of a triangle whose transform mirrors it (negative determinant).
_FLIPPED = [0, 2, 1]


def place_parts(parts, ctx: TimeContext, geometry: Geometry, elements: list[Element],
                meters_per_unit: float) -> None:  # fmt: skip
    """Place ``parts`` at ``ctx``: their world vertices (metres), triangles (winding
    included), corner normals, albedo and texture coordinates into ``geometry`` (whose
    ``tri_element`` and ``tri_material`` the caller fills) and their bounds into
    ``elements``; each part keeps its ``matrix`` and ``flipped``. Raises ``PhrtError``
    for a non-finite transform."""
    group: list = []
    size = 0
    for k, p in enumerate(parts):
        m = p.matrix_at(ctx)
        if not np.all(np.isfinite(m)):
            raise PhrtError(f"{p.path}: non-finite transform at time {ctx.time}")
        p.matrix = m
        p.flipped = bool(np.linalg.det(m[:3, :3]) < 0)
        n = len(p.mesh.points) + 3 * len(p.mesh.triangles)
        if group and size + n > PLACE_CHUNK_ROWS:
            progress.step("placing elements", k, len(parts))
            _place_group(group, geometry, elements, meters_per_unit)
            group, size = [], 0
        group.append(p)
        size += n
    if group:
        _place_group(group, geometry, elements, meters_per_unit)


def _place_group(parts, geometry: Geometry, elements: list[Element], mpu: float) -> None:
    """One group of parts whose vertex and triangle rows follow each other: one part
    alone (transformed by its matrix, its corners ``PLACE_CHUNK_ROWS`` at a time) or
    several small ones (transformed by per-row matrices)."""
    nv = np.array([len(p.mesh.points) for p in parts])
    nt = np.array([len(p.mesh.triangles) for p in parts])
    mats = np.stack([p.matrix for p in parts])  # (k, 4, 4)
    v0 = parts[0].v0
    if len(parts) == 1:
        m = mats[0]
        world = (parts[0].mesh.points @ m[:3, :3] + m[3, :3]) * mpu
        step = max(PLACE_CHUNK_ROWS // 3, 1)
        for start in range(0, int(nt[0]), step):
            _place_corners(parts, geometry, slice(start, start + step), mats, nt)
    else:
        points = np.concatenate([p.mesh.points for p in parts])
        part_of_vertex = np.repeat(np.arange(len(parts)), nv)
        world = np.einsum("ni,nij->nj", points, mats[part_of_vertex, :3, :3])
        world += mats[part_of_vertex, 3, :3]
        world *= mpu
        _place_corners(parts, geometry, slice(None), mats, nt)
    geometry.vertices[v0 : v0 + len(world)] = world
    _bounds(parts, world, nv, mats, elements, mpu)


def _place_corners(parts, geometry: Geometry, rows: slice, mats, nt: np.ndarray) -> None:
    """Triangles, corner normals, albedo and uv of a group's parts (``rows``: a slice
    of the one part's triangles, or all of several parts')."""
    g = geometry
    flipped = np.array([p.flipped for p in parts])
    if len(parts) == 1:
        mesh = parts[0].mesh
        normals = mesh.corner_normals[rows].reshape(-1, 3) @ normal_matrix(mats[0, :3, :3])
        tri_flip = np.full(len(normals) // 3, flipped[0])
    else:
        corner_normals = np.concatenate([p.mesh.corner_normals for p in parts]).reshape(-1, 3)
        nmats = np.stack([normal_matrix(m[:3, :3]) for m in mats])
        part_of_corner = np.repeat(np.arange(len(parts)), 3 * nt)
        normals = np.einsum("ni,nij->nj", corner_normals, nmats[part_of_corner])
        tri_flip = np.repeat(flipped, nt)
    first = parts[0].t0 + (rows.start or 0)
    ts = slice(first, first + len(tri_flip))
    corner_n = safe_normalize(normals).reshape(-1, 3, 3)
    offsets = np.repeat(np.array([p.v0 for p in parts]), nt)[rows, None]
    triangles = _cat([p.mesh.triangles[rows] for p in parts]) + offsets
    albedo = _cat([p.mesh.corner_albedo[rows] for p in parts])
    uv = None if g.corner_uv is None else _cat([_uv(p.mesh)[rows] for p in parts])
    if tri_flip.any():
        for a in (corner_n, triangles, albedo) + (() if uv is None else (uv,)):
            a[tri_flip] = a[tri_flip][:, _FLIPPED]
    g.corner_normals[ts] = corner_n
    g.triangles[ts] = triangles
    g.corner_albedo[ts] = albedo
    if uv is not None:
        g.corner_uv[ts] = uv


def _cat(arrays: list[np.ndarray]) -> np.ndarray:
    """The arrays one after another (a copy, which the flips may write into)."""
    return np.concatenate(arrays) if len(arrays) > 1 else arrays[0].copy()


def _uv(mesh) -> np.ndarray:
    """A mesh's corner uv (T, 3, 2), zeros when it has none."""
    if mesh.corner_uv is not None:
        return mesh.corner_uv
    return np.zeros((len(mesh.triangles), 3, 2), np.float32)


def _bounds(parts, world: np.ndarray, nv: np.ndarray, mats: np.ndarray, elements, mpu) -> None:
    """Each part's element bounds: its world vertices' box, its origin without any."""
    having = np.flatnonzero(nv)
    if len(having):
        starts = np.concatenate([[0], np.cumsum(nv)[:-1]])[having]
        lows = np.minimum.reduceat(world, starts, axis=0)
        highs = np.maximum.reduceat(world, starts, axis=0)
        for k, lo, hi in zip(having, lows, highs, strict=True):
            e = elements[parts[k].element]
            e.bounds_min, e.bounds_max = lo, hi
    for k in np.flatnonzero(nv == 0):
        e = elements[parts[k].element]
        e.bounds_min = e.bounds_max = mats[k, 3, :3] * mpu
