"""The one surface rule: what a point on a triangle looks like, for raster and tracer alike.

A point on a surface is (triangle id, barycentric weights). From it come the position,
the shading normal (with the side rule below, then a tangent-space normal map:
``NormalMaps``), the albedo and the texture colour (``sample_input``: UsdUVTexture wrap
modes, UsdTransform2d, scale / bias), the emission, and whether the point is there at
all (``Cutouts``: opacityThreshold), all through this module, so the raster G-buffer
(``render.raster.gbuffer``) and the tracer's hits (``render.trace.tracer``, the ``rt``
G-buffer included) agree by construction. It follows OpenUSD hdEmbree's
``meshSamplers`` (one ``Sample(element, u, v)`` per interpolation, used by normals and
primvars alike) and pbrt-v4's ``SurfaceInteraction`` (which owns the shading-normal
rule).

Spaces and shapes: "rel" is world metres minus ``Scene.origin``, float64. T triangles,
m points. Barycentric weights are (m, 3) float32, the weights of corners 0, 1, 2 (sum 1);
Embree's (u, v) are the weights of corners 1 and 2 (``weights_from_uv``).

The shading-normal side rule: the geometric normal is turned to face the viewer
(against the incoming ray); the interpolated shading normal is flipped to that same side
of the triangle; where it then still faces along the ray (a smooth normal bent past the
silhouette) or is degenerate (shorter than ``MIN_NORMAL_LENGTH``, or NaN) the geometric
normal replaces it. The per-point loops of the rule, the G-buffer's derivation and the
tracer's hit geometry (position, side, interpolated normal and albedo) are compiled in
``model.surface_kernels``; what follows them per point (normal maps, textures,
emission, cut-outs) is here.

Plain numpy: no USD, OpenGL or Embree here.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.model.scene import ALPHA_ONE, MaterialTable, TextureInput

#: Interpolated shading normals shorter than this are degenerate and replaced by the
#: geometric normal. Corner normals are unit, so only weights that cancel opposite
#: normals get this short; 1e-6 keeps the float32 division well away from overflow.
MIN_NORMAL_LENGTH = 1e-6

#: A shadow ray's origin rises onto the smooth surface (``trace_kernels.shadow_rays``)
#: fully where its triangle's plane faces away from the light (n_g·l <= 0: lit by the
#: shading normal, shadowed by the flat neighbours), fading out until n_g·l is this cosine
#: (~6 degrees), where a flat triangle's ray clears its convex neighbours; beyond, shadows
#: that other objects cast onto a smooth mesh stay where they are. The shadow maps test
#: the point moved by the same rule (``engine/terminator.py``).
TERMINATOR_FADE = 0.1
#: A triangle is flat (no move, ``TriangleTable.smooth`` False) when each corner normal
#: is within this cosine of its face normal (either side; ~0.8 degrees): its smooth
#: surface is its plane, up to a move far below the shadow maps' bias.
FLAT_CORNER_COS = 0.9999

#: Cut-out surfaces (``Cutouts``) one ray passes through before it is stopped: the
#: raster peels one id layer per cut-out surface along a pixel's (or a shadow-map
#: texel's) ray, a full redraw each; the tracer re-casts one ray per surface from just
#: past it. Foliage cards and fences seldom stack deeper than a few along one ray; 8 keeps
#: the worst frame at 8 extra redraws. A ray stopped at the bound ends as a miss in raster
#: and trace alike (the environment; a shadow ray or map texel: no occluder).
MAX_CUTOUT_LAYERS = 8

#: Rows ``TriangleTable.fill`` computes at once: its temporaries (about 1 kB a row) stay
#: near 64 MB instead of a gigabyte on a million-triangle stage, where filling the whole
#: table in one pass took 5 s, most of it first-touching those temporaries, and in
#: chunks well under one (1.43 M triangles, this 2-core machine).
FILL_CHUNK_ROWS = 1 << 16

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
    smooth  : (T,) bool: a corner normal leaves the face normal by more than
              ``FLAT_CORNER_COS`` (either side): the triangle's smooth surface is not its
              plane (the shadow terminator's moves, ``surface_kernels.terminator_lifts``)
    """

    def __init__(self, count: int) -> None:
        self.frame = np.zeros((count, 4, 3))
        self.plane = np.zeros((count, 13))
        self.corners = np.zeros((count, 3, 6), dtype=np.float32)
        self.smooth = np.zeros(count, dtype=bool)

    def __len__(self) -> int:
        return len(self.corners)

    def fill(self, vertices, triangles, origin, corner_normals, corner_albedo, rows) -> None:
        """Recompute rows ``rows`` (index array or slice) from world vertices (V, 3)
        float64, triangles (T, 3) int, the render origin (3,) and the corner data
        (T, 3, 3) float32 (all indexed by the full triangle list), ``FILL_CHUNK_ROWS``
        rows at a time."""
        data = (vertices, triangles, origin, corner_normals, corner_albedo)
        if isinstance(rows, slice) and rows.indices(len(self))[2] == 1:
            start, stop, _ = rows.indices(len(self))
            for first in range(start, stop, FILL_CHUNK_ROWS):
                self._fill_rows(*data, slice(first, min(first + FILL_CHUNK_ROWS, stop)))
            return
        rows = np.arange(len(self))[rows] if isinstance(rows, slice) else np.asarray(rows)
        for first in range(0, len(rows), FILL_CHUNK_ROWS):
            self._fill_rows(*data, rows[first : first + FILL_CHUNK_ROWS])

    def _fill_rows(self, vertices, triangles, origin, corner_normals, corner_albedo, rows):
        """``fill`` of one chunk of rows."""
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
        normals = corner_normals[rows]
        self.corners[rows] = np.concatenate([normals, corner_albedo[rows]], axis=2)
        along = np.einsum("ikj,ij->ik", normals, unit)  # each corner normal on the face's
        squared = np.einsum("ikj,ikj->ik", normals, normals)
        self.smooth[rows] = np.any(along * along < FLAT_CORNER_COS**2 * squared, axis=1)

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


class NormalMaps:
    """UsdPreviewSurface ``normal`` textures (tangent space), the one rule of raster and
    trace: at a point the map's value m (the ``TextureInput``'s sample, scale and bias
    included; the spec expects the author's (2, 2, 2) / (-1, -1, -1) to map [0, 1] to
    [-1, 1]) bends the viewer-facing shading normal N into
    ``normalize(m_x T + m_y B + m_z N)``, T and B the triangle's d(position)/ds and
    d(position)/dt from its corner ``st`` (made orthogonal to N). Where the result would
    face away from the viewer, or the triangle's st are degenerate, N stays.

    any : some material has a normal map (nobody else needs to ask).
    """

    def __init__(self, materials: MaterialTable, tri_material: np.ndarray, corner_uv):
        self._materials = materials
        self._tri_material = np.asarray(tri_material)
        self._corner_uv = corner_uv
        rows = [m for m, inputs in enumerate(materials.texture_inputs) if "normal" in inputs]
        mapped = np.zeros(len(materials.opacity) + 1, dtype=bool)
        mapped[rows] = True
        if corner_uv is None or not rows:
            self.tri_mapped = np.zeros(len(self._tri_material), bool)
        else:
            mat = np.where(
                (self._tri_material >= 0) & (self._tri_material < len(materials.opacity)),
                self._tri_material,
                len(materials.opacity),
            )
            self.tri_mapped = mapped[mat]
        self.any = bool(self.tri_mapped.any())

    def apply(self, normals, tri, weights, incoming, table: TriangleTable) -> np.ndarray:
        """In place on ``normals`` (m, 3) float32, unit and facing the viewer (after
        the side rule, ``surface_kernels``) at points on triangles ``tri`` (m,) with weights
        (m, 3), seen along unit ``incoming`` (m, 3); returns them."""
        if not self.any or len(tri) == 0:
            return normals
        sel = np.flatnonzero(self.tri_mapped[tri])
        if len(sel) == 0:
            return normals
        t_sel = np.asarray(tri)[sel]
        n = normals[sel].astype(np.float64)
        m = input_values(
            self._materials, "normal", np.tile([0.0, 0.0, 1.0], (len(self._materials.opacity), 1)),
            t_sel, weights[sel], self._tri_material, self._corner_uv,
        ).astype(np.float64)  # fmt: skip
        frame = np.take(table.frame, t_sel, axis=0)  # v0, e1, e2, unit normal (rel)
        uv = np.asarray(self._corner_uv, np.float64)[t_sel]  # (k, 3, 2)
        d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None]
        e1, e2 = frame[:, 1], frame[:, 2]
        tangent = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv
        bitangent = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv
        out = n * m[:, 2:3]
        for axis, vec in ((0, tangent), (1, bitangent)):
            vec = vec - n * np.einsum("ij,ij->i", vec, n)[:, None]
            length = np.linalg.norm(vec, axis=1, keepdims=True)
            vec = np.where(length > 0, vec / np.where(length > 0, length, 1.0), 0.0)
            out += vec * m[:, axis : axis + 1]
        length = np.linalg.norm(out, axis=1, keepdims=True)
        bent = out / np.where(length > 0, length, 1.0)
        keep = ok & (length[:, 0] > MIN_NORMAL_LENGTH)
        keep &= np.einsum("ij,ij->i", bent, np.asarray(incoming, np.float64)[sel]) < 0.0
        normals[sel[keep]] = bent[keep].astype(np.float32)
        return normals


def texture_albedo(
    albedo, tri, weights, tri_material, corner_uv, textures, sample=None, inputs=None
):
    """Replace, in place, the rows of ``albedo`` (m, 3) float32 at points on triangles
    ``tri`` (m,) with weights (m, 3) whose material has a texture: ``textures[material]``
    sampled at the interpolated ``corner_uv`` (T, 3, 2), through the material's
    ``TextureInput`` of "diffuseColor" (``inputs``: ``MaterialTable.texture_inputs``;
    its wrap modes and transform) where it has one, else by ``sample`` (default
    ``sample_bilinear_wrap``). tri_material : (T,) material ids; textures : per material
    None or an (h, w, 3) float32 image. Returns ``albedo``."""
    sample = sample_bilinear_wrap if sample is None else sample
    mats = np.take(tri_material, tri)
    for m_id, texture in enumerate(textures):
        if texture is None:
            continue
        sel = np.flatnonzero(mats == m_id)
        if len(sel):
            uv = interpolate(corner_uv[np.take(tri, sel)], weights[sel])
            spec = inputs[m_id].get("diffuseColor") if inputs and m_id < len(inputs) else None
            if spec is not None and not spec.default_sampling:
                albedo[sel] = sample_input(spec, uv)[:, :3]
            else:
                albedo[sel] = sample(texture, uv)
    return albedo


def has_texture_input(materials: MaterialTable, name: str) -> bool:
    """Some row of ``materials`` has input ``name`` textured (``texture_inputs``)."""
    return any(name in inputs for inputs in materials.texture_inputs)


def emissive_values(materials: MaterialTable, tri, weights, tri_material, corner_uv):
    """(m, 3) float32 emissiveColor at points on triangles ``tri`` (m,) with weights
    (m, 3): the row constants, textured where the material's input is
    (``input_values``)."""
    if corner_uv is None or not has_texture_input(materials, "emissiveColor"):
        return np.take(np.asarray(materials.emissive, np.float32), np.take(tri_material, tri), 0)
    constant = np.asarray(materials.emissive, np.float32).reshape(-1, 3)
    return input_values(materials, "emissiveColor", constant, tri, weights, tri_material, corner_uv)


def emissive_at(scene, tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m, 3) float32 emissiveColor of G-buffer pixels (raster or ``rt``): triangles
    ``tri`` (m,) at world ``points`` (m, 3) of ``scene`` (a ``model.scene.Scene``); the
    weights come from the points (``point_weights``) only where some input is textured."""
    geo, materials = scene.geometry, scene.materials
    if geo.corner_uv is None or not has_texture_input(materials, "emissiveColor"):
        return np.take(
            np.asarray(materials.emissive, np.float32), np.take(geo.tri_material, tri), 0
        )
    weights = point_weights(geo.vertices, geo.triangles, tri, points)
    return emissive_values(materials, tri, weights, geo.tri_material, geo.corner_uv)


def point_weights(vertices: np.ndarray, triangles: np.ndarray, tri, points) -> np.ndarray:
    """(m, 3) float32 barycentric weights of ``points`` (m, 3) float64 (world metres,
    on or near their triangles) on triangles ``tri`` (m,), clamped onto the triangle
    and renormalised as the raster's derivation does; from world ``vertices`` (V, 3)
    and ``triangles`` (T, 3). For G-buffer pixels (raster or ``rt``) that need a
    textured input the G-buffer does not carry."""
    v = np.take(vertices, np.take(triangles, tri, axis=0), axis=0)  # (m, 3, 3)
    a = v[:, 0]
    e1 = v[:, 1] - a
    e2 = v[:, 2] - a
    p = np.asarray(points, np.float64) - a
    d00 = np.einsum("ij,ij->i", e1, e1)
    d01 = np.einsum("ij,ij->i", e1, e2)
    d11 = np.einsum("ij,ij->i", e2, e2)
    d20 = np.einsum("ij,ij->i", p, e1)
    d21 = np.einsum("ij,ij->i", p, e2)
    den = d00 * d11 - d01**2
    inv = np.where(den > 0.0, 1.0 / np.where(den > 0.0, den, 1.0), 0.0)
    return _clamped_weights((d11 * d20 - d01 * d21) * inv, (d00 * d21 - d01 * d20) * inv)


def _clamped_weights(b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """(m, 3) float32 weights (1 - b1 - b2, b1, b2) clamped to [0, 1], renormalised."""
    b0 = np.clip(1.0 - b1 - b2, 0.0, 1.0)
    b1 = np.clip(b1, 0.0, 1.0)
    b2 = np.clip(b2, 0.0, 1.0)
    w = np.stack([b0, b1, b2], axis=1)
    w /= np.maximum(b0 + b1 + b2, 1e-12)[:, None]
    return w.astype(np.float32)


def ray_plane_weights(plane: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(m, 3) float32 weights where rays from rel ``origins`` (m, 3) along ``dirs``
    (m, 3) meet the planes of their triangles (gathered ``TriangleTable.plane`` rows
    (m, 13)), clamped onto the triangle; the raster's pixel-ray rule for rays other
    than the camera's (shadow-map texels)."""
    ng = plane[:, 8:11]
    den = np.einsum("ij,ij->i", ng, dirs)
    den = np.where(den == 0.0, 1.0, den)  # parallel: never rasterized, any finite t
    t = (plane[:, 11] - np.einsum("ij,ij->i", ng, origins)) / den
    p = origins + t[:, None] * dirs
    b1 = np.einsum("ij,ij->i", p, plane[:, 0:3]) - plane[:, 3]
    b2 = np.einsum("ij,ij->i", p, plane[:, 4:7]) - plane[:, 7]
    return _clamped_weights(b1, b2)


def transformed_st(spec: TextureInput, uv: np.ndarray) -> np.ndarray:
    """(n, 2) float64 st after the ``TextureInput.transform`` (UsdTransform2d) of
    ``spec``; non-finite coordinates read as 0."""
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if spec.transform is not None:
        uv = uv @ spec.transform[:, :2].T + spec.transform[:, 2]
    return uv


def _wrap_index(i: np.ndarray, size: int, mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Texel indices ``i`` (n,) int64 mapped into [0, size) by ``mode``, and for
    ``black`` the (n,) bool mask of texels inside the image (outside reads 0)."""
    if mode == "repeat":
        return i % size, None
    if mode == "mirror":  # period 2 size: 0..size-1 then size-1..0
        j = i % (2 * size)
        return np.where(j >= size, 2 * size - 1 - j, j), None
    inside = (i >= 0) & (i < size) if mode == "black" else None
    return np.clip(i, 0, size - 1), inside


def sample_input(spec: TextureInput, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a ``TextureInput`` at st ``uv`` (n, 2) ((0, 0) = bottom-left):
    transform, wrap per axis, the output's channels, then ``scale`` and ``bias``.
    Returns (n, k) float32, k = len(spec.channels). With default sampling (repeat, no
    transform) the texel weights are those of ``sample_bilinear_wrap``."""
    texture = spec.image
    th, tw = texture.shape[:2]
    uv = transformed_st(spec, uv)
    wrap_s, wrap_t = spec.wrap
    # Repeat wraps the coordinate first (as sample_bilinear_wrap: small texel indices).
    if wrap_s == "repeat":
        uv[:, 0] -= np.floor(uv[:, 0])
    if wrap_t == "repeat":
        uv[:, 1] -= np.floor(uv[:, 1])
    # Far outside the image every mode is periodic or constant: clamp the coordinate so
    # the texel indices stay small integers (1e6 periods of mirror are still exact).
    uv = np.clip(uv, -1e6, 1e6)
    fx = uv[:, 0] * tw - 0.5
    fy = (1.0 - uv[:, 1]) * th - 0.5
    x0 = np.floor(fx)
    y0 = np.floor(fy)
    wx = (fx - x0)[:, None]
    wy = (fy - y0)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa, ina = _wrap_index(x0, tw, wrap_s)
    xb, inb = _wrap_index(x0 + 1, tw, wrap_s)
    ya, jna = _wrap_index(y0, th, wrap_t)
    yb, jnb = _wrap_index(y0 + 1, th, wrap_t)
    chans = [c for c in spec.channels]
    img = texture.reshape(th, tw, -1)

    def texel(y, x, in_x, in_y):
        out = np.empty((len(x), len(chans)), np.float32)
        for k, c in enumerate(chans):
            out[:, k] = 1.0 if c == ALPHA_ONE else img[y, x, c]
        if in_x is not None or in_y is not None:
            keep = np.ones(len(x), bool)
            keep &= True if in_x is None else in_x
            keep &= True if in_y is None else in_y
            out[~keep] = 0.0  # wrap "black": outside the image reads 0
        return out

    top = texel(ya, xa, ina, jna) * (1 - wx) + texel(ya, xb, inb, jna) * wx
    bottom = texel(yb, xa, ina, jnb) * (1 - wx) + texel(yb, xb, inb, jnb) * wx
    value = top * (1 - wy) + bottom * wy
    return (value * spec.scale + spec.bias).astype(np.float32)


def input_values(
    materials: MaterialTable, name: str, constant, tri, weights, tri_material, corner_uv
) -> np.ndarray:
    """(m, k) float32 values of UsdPreviewSurface input ``name`` at points on triangles
    ``tri`` (m,) with weights (m, 3): the material's constant ``constant`` (M, k) row,
    replaced by its ``TextureInput`` sampled at the interpolated ``corner_uv`` where the
    input is textured (first k components)."""
    mats = np.take(tri_material, tri)
    out = np.array(np.take(constant, mats, axis=0), dtype=np.float32, copy=True)
    if corner_uv is None:
        return out
    for m_id in np.unique(mats):
        spec = materials.texture_input(int(m_id), name)
        if spec is None:
            continue
        sel = np.flatnonzero(mats == m_id)
        uv = interpolate(corner_uv[np.take(tri, sel)], weights[sel])
        value = sample_input(spec, uv)
        k = out.shape[1]
        out[sel] = value[:, :k] if value.shape[1] >= k else np.repeat(value[:, :1], k, axis=1)
    return out


class Cutouts:
    """The cut-out rule (UsdPreviewSurface ``opacityThreshold``) of raster and trace
    alike: a point of a cut-out material whose opacity (constant or textured, as
    ``input_values``) is below the threshold is not there.

    tri_cutout : (T,) bool, triangles of cut-out materials; ``any`` False: the scene has
    none and nobody needs to ask.
    """

    def __init__(self, materials: MaterialTable, tri_material: np.ndarray, corner_uv):
        self._materials = materials
        self._tri_material = np.asarray(tri_material)
        self._corner_uv = corner_uv
        cut = np.zeros(len(materials.opacity) + 1, dtype=bool)
        rows = [m for m in materials.cutouts if m < len(materials.opacity)]
        cut[rows] = True
        mat = np.where(
            (self._tri_material >= 0) & (self._tri_material < len(materials.opacity)),
            self._tri_material,
            len(materials.opacity),
        )
        self.tri_cutout = cut[mat] if len(mat) else np.zeros(0, bool)
        self.any = bool(self.tri_cutout.any())
        self._threshold = np.array(
            [materials.threshold(m) for m in range(len(materials.opacity))], np.float32
        )

    def holes(self, tri: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(m,) bool: points on triangles ``tri`` (m,) with weights (m, 3) that are not
        there (opacity < the material's threshold)."""
        tri = np.asarray(tri, dtype=np.int64)
        out = np.zeros(len(tri), dtype=bool)
        if not self.any or len(tri) == 0:
            return out
        sel = np.flatnonzero(self.tri_cutout[tri])
        if len(sel):
            t = tri[sel]
            opacity = input_values(
                self._materials,
                "opacity",
                np.asarray(self._materials.opacity, np.float32)[:, None],
                t,
                weights[sel],
                self._tri_material,
                self._corner_uv,
            )[:, 0]
            thr = self._threshold[np.take(self._tri_material, t)]
            # NaN opacity (a broken texture value) counts as present: never a hole.
            out[sel] = opacity < thr
        return out


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
