"""The one surface rule: what a point on a triangle looks like, for raster and tracer alike.

A point on a surface is (triangle id, barycentric weights). From it come the position,
the shading normal (with the side rule below), the albedo and the texture colour, all
through this module, so the raster G-buffer (``render.raster.gbuffer``) and the tracer's
hits (``render.trace.tracer``, the ``rt`` G-buffer included) agree by construction. It
follows OpenUSD hdEmbree's ``meshSamplers`` (one ``Sample(element, u, v)`` per
interpolation, used by normals and primvars alike) and pbrt-v4's ``SurfaceInteraction``
(which owns the shading-normal rule).

Spaces and shapes: "rel" is world metres minus ``Scene.origin``, float64. T triangles,
m points. Barycentric weights are (m, 3) float32, the weights of corners 0, 1, 2 (sum 1);
Embree's (u, v) are the weights of corners 1 and 2 (``weights_from_uv``).

The shading-normal side rule (``orient_shading_normals``): the geometric normal is
turned to face the viewer (against the incoming ray); the interpolated shading normal is
flipped to that same side of the triangle; where it then still faces along the ray (a
smooth normal bent past the silhouette) or is degenerate (shorter than
``MIN_NORMAL_LENGTH``, or NaN) the geometric normal replaces it.

Plain numpy: no USD, OpenGL or Embree here.
"""

from __future__ import annotations

import numpy as np

#: Interpolated shading normals shorter than this are degenerate and replaced by the
#: geometric normal. Corner normals are unit, so only weights that cancel opposite
#: normals get this short; 1e-6 keeps the float32 division well away from overflow.
MIN_NORMAL_LENGTH = 1e-6

#: Unit normal of a degenerate (zero-area) triangle in ``TriangleTable.frame``. Neither
#: the rasterizer nor Embree ever reports a hit on one; any finite unit vector does.
DEGENERATE_NORMAL = (0.0, 1.0, 0.0)


class TriangleTable:
    """Per-triangle tables of one geometry, packed so that one gather per table fetches
    all a point needs. Two views of each triangle's plane serve the two directions of
    the lookup; both are built from the same rel edges.

    frame   : (T, 4, 3) float64 rel: v0, e1 = v1 - v0, e2 = v2 - v0 and the unit
              front-face normal (e1 x e2 normalised, ``DEGENERATE_NORMAL`` at zero area).
              Barycentrics → point (``positions``): the tracer's hits.
    plane   : (T, 13) float64 rel. Columns: g1 (3), c1, g2 (3), c2, n_g (3), h, |n_g|.
              n_g = e1 x e2 (unnormalised), h = n_g·v0. For a point p on the plane the
              weights of corners 1 and 2 are p·g1 - c1 and p·g2 - c2 (g1, g2: the dual
              basis of e1, e2 within the plane). Point → barycentrics: the rasterizer's
              pixel rays.
    corners : (T, 3, 6) float32: per corner its shading normal, then its albedo
              (``Geometry.corner_normals`` / ``corner_albedo``), so one weighted sum
              over the corners (``interpolate``) gives both.
    """

    def __init__(self, count: int) -> None:
        self.frame = np.zeros((count, 4, 3))
        self.plane = np.zeros((count, 13))
        self.corners = np.zeros((count, 3, 6), dtype=np.float32)

    def __len__(self) -> int:
        return len(self.corners)

    def fill(self, vertices, triangles, origin, corner_normals, corner_albedo, rows) -> None:
        """Recompute rows ``rows`` (index array or slice) from world vertices (V, 3)
        float64, triangles (T, 3) int, the render origin (3,) and the corner data
        (T, 3, 3) float32 (all indexed by the full triangle list)."""
        tri = vertices[triangles[rows]] - origin  # (n, 3, 3) rel
        if len(tri) == 0:
            return
        a = tri[:, 0]
        e1 = tri[:, 1] - a
        e2 = tri[:, 2] - a
        ng = np.cross(e1, e2)
        length = np.linalg.norm(ng, axis=1)
        d00 = np.einsum("ij,ij->i", e1, e1)
        d01 = np.einsum("ij,ij->i", e1, e2)
        d11 = np.einsum("ij,ij->i", e2, e2)
        den = d00 * d11 - d01**2
        # Degenerate (zero-area) triangles are never hit; guard the divisions anyway.
        inv = np.where(den > 0.0, 1.0 / np.where(den > 0.0, den, 1.0), 0.0)[:, None]
        g1 = (d11[:, None] * e1 - d01[:, None] * e2) * inv
        g2 = (d00[:, None] * e2 - d01[:, None] * e1) * inv
        self.plane[rows] = np.concatenate(
            [
                g1,
                np.einsum("ij,ij->i", a, g1)[:, None],
                g2,
                np.einsum("ij,ij->i", a, g2)[:, None],
                ng,
                np.einsum("ij,ij->i", a, ng)[:, None],
                length[:, None],
            ],
            axis=1,
        )
        ok = length[:, None] > 0
        unit = np.where(ok, ng / np.where(ok, length[:, None], 1.0), DEGENERATE_NORMAL)
        self.frame[rows] = np.stack([a, e1, e2, unit], axis=1)
        self.corners[rows] = np.concatenate([corner_normals[rows], corner_albedo[rows]], axis=2)

    def corners_differ(self, corner_normals, corner_albedo, rows: np.ndarray) -> np.ndarray:
        """(k,) bool: rows ``rows`` (k,) whose corner normals or albedo differ from the
        table (exact float32 comparison); the change test for shading data."""
        fresh = np.concatenate([corner_normals[rows], corner_albedo[rows]], axis=2)
        return np.any(fresh != self.corners[rows], axis=(1, 2))


def weights_from_uv(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(m, 3) float32 weights (1 - u - v, u, v) from Embree's barycentrics u, v (m,)."""
    w = np.empty((len(u), 3), np.float32)
    w[:, 1] = u
    w[:, 2] = v
    w[:, 0] = 1.0 - w[:, 1] - w[:, 2]
    return w


def interpolate(corners: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The one interpolation of corner attributes: (m, k) = Σ_j weights[:, j] corners[:, j]
    for corners (m, 3, k) and weights (m, 3) (float32 in, float32 out)."""
    return np.einsum("ij,ijk->ik", weights, corners)


def positions(frame: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(m, 3) float64 rel points v0 + u e1 + v e2 of gathered ``TriangleTable.frame``
    rows (m, 4, 3) at barycentrics u, v (m,)."""
    return frame[:, 0] + u[:, None] * frame[:, 1] + v[:, None] * frame[:, 2]


def viewer_side(facing: np.ndarray) -> np.ndarray:
    """(m,) float64: -1 where the viewer sees a triangle's back face, else +1, from
    ``facing`` (m,) = front-face normal · incoming ray direction as the caller's hit
    computed it (> 0: the ray runs along the normal, so the back face is seen)."""
    return np.where(facing > 0.0, -1.0, 1.0)


def orient_shading_normals(normals, side, incoming, table: TriangleTable, tri) -> np.ndarray:
    """The side rule (module docstring), in place on ``normals`` (m, 3) float32, the
    interpolated corner normals of triangles ``tri`` (m,): returns them unit and facing
    the viewer. side : (m,) ``viewer_side``; incoming : (m, 3) unit ray directions."""
    normals *= side.astype(np.float32)[:, None]
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    # ``~(length >= ...)`` also catches a NaN interpolated normal.
    bad = ~(length >= MIN_NORMAL_LENGTH) | (np.einsum("ij,ij->i", normals, incoming) >= 0.0)
    normals /= np.maximum(length, MIN_NORMAL_LENGTH)[:, None]
    if bad.any():
        rows = np.flatnonzero(bad)
        front = np.take(table.frame, np.take(tri, rows), axis=0)[:, 3]
        normals[rows] = front * side[rows][:, None]
    return normals


def texture_albedo(albedo, tri, weights, tri_material, corner_uv, textures, sample=None):
    """Replace, in place, the rows of ``albedo`` (m, 3) float32 at points on triangles
    ``tri`` (m,) with weights (m, 3) whose material has a texture: ``sample`` (default
    ``sample_bilinear_wrap``) of ``textures[material]`` at the interpolated
    ``corner_uv`` (T, 3, 2). tri_material : (T,) material ids; textures : per material
    None or an (h, w, 3) float32 image. Returns ``albedo``."""
    sample = sample_bilinear_wrap if sample is None else sample
    mats = np.take(tri_material, tri)
    for m_id, texture in enumerate(textures):
        if texture is None:
            continue
        sel = np.flatnonzero(mats == m_id)
        if len(sel):
            uv = interpolate(corner_uv[np.take(tri, sel)], weights[sel])
            albedo[sel] = sample(texture, uv)
    return albedo


def sample_bilinear_wrap(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup with wrap-around.

    texture : (h, w, 3) float32 linear RGB, row 0 = top of the image
    uv      : (n, 2) texture coordinates, (0, 0) = bottom-left (USD ``st``), period 1;
              non-finite coordinates read as 0
    Returns (n, 3) float32.
    """
    th, tw = texture.shape[:2]
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    uv = uv - np.floor(uv)  # wrap first: keeps the integer texel indices small
    fx = uv[:, 0] * tw - 0.5
    fy = (1.0 - uv[:, 1]) * th - 0.5
    x0 = np.floor(fx)
    y0 = np.floor(fy)
    wx = (fx - x0)[:, None]
    wy = (fy - y0)[:, None]
    x0 = x0.astype(np.int64) % tw
    y0 = y0.astype(np.int64) % th
    x1 = (x0 + 1) % tw
    y1 = (y0 + 1) % th
    top = texture[y0, x0] * (1 - wx) + texture[y0, x1] * wx
    bottom = texture[y1, x0] * (1 - wx) + texture[y1, x1] * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)
