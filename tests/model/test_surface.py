"""The one surface rule (``model.surface``) at analytic points of a known triangle.

Thresholds follow from the arithmetic: weights 0 and 1 are exact, so corner values come
back bit for bit; elsewhere a weighted sum of three float32 products rounds at most
four times (three products, two additions, each ≤ half an ulp) on top of the weights'
own float32 rounding, so it stays within ``FLOAT32_SUM_ULPS`` ulps of the largest term.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.model import surface, surface_kernels

#: float32 ulp at 1.0.
EPS32 = float(np.finfo(np.float32).eps)
#: Worst rounding of a 3-term float32 weighted sum with rounded weights, in ulps of the
#: largest term: 3 products + 2 additions (≤ 0.5 ulp each) + 3 weights (≤ 0.5 ulp each).
FLOAT32_SUM_ULPS = 4.0

#: The triangle: world vertices, render origin, corner normals and albedo.
VERTICES = np.array([[10.0, 2.0, 0.0], [12.0, 2.0, 0.0], [10.0, 5.0, 0.0]])  # z = 0 plane
ORIGIN = np.array([10.0, 2.0, -1.0])
FRONT = np.array([0.0, 0.0, 1.0])  # e1 x e2 / |e1 x e2| for the vertex order above
CORNER_NORMALS = np.array(
    [[[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]]], dtype=np.float32
)  # unit, all on the front side
CORNER_ALBEDO = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]], np.float32)
CORNERS = np.eye(3, dtype=np.float32)  # barycentric weights of the three corners
CENTROID = np.full((1, 3), 1.0 / 3.0, dtype=np.float32)


def _table(normals=CORNER_NORMALS, albedo=CORNER_ALBEDO) -> surface.TriangleTable:
    table = surface.TriangleTable(1)
    table.fill(VERTICES, np.array([[0, 1, 2]]), ORIGIN, normals, albedo, slice(None))
    return table


def _shading_normal(table, weights, incoming) -> np.ndarray:
    """The rule end to end for points on triangle 0 at ``weights`` (m, 3) seen along
    ``incoming`` (m, 3): the compiled hit geometry (``surface_kernels.hit_geometry``,
    the rule of raster and trace alike) from Embree-style barycentrics."""
    m = len(weights)
    tri = np.zeros(m, np.int64)
    u = np.ascontiguousarray(weights[:, 1], np.float32)
    v = np.ascontiguousarray(weights[:, 2], np.float32)
    pos, ng = np.empty((m, 3)), np.empty((m, 3))
    ns = np.empty((m, 3), np.float32)
    surface_kernels.hit_geometry(
        tri, u, v, np.ascontiguousarray(incoming, np.float64), table.frame, table.corners,
        pos, ng, ns,
    )  # fmt: skip
    return ns


def test_table_frame_and_plane_describe_the_triangle():
    table = _table()
    rel = VERTICES - ORIGIN
    np.testing.assert_array_equal(table.frame[0, 0], rel[0])
    np.testing.assert_array_equal(table.frame[0, 1], rel[1] - rel[0])
    np.testing.assert_array_equal(table.frame[0, 2], rel[2] - rel[0])
    np.testing.assert_array_equal(table.frame[0, 3], FRONT)  # axis-aligned: exact
    # Point → barycentrics (the raster's direction) inverts barycentrics → point (the
    # tracer's); float64 rounding of ~1 m coordinates: 1e-15 relative, 1e-12 is safe.
    u, v = np.array([0.2], np.float32), np.array([0.7], np.float32)
    p = surface.positions(table.frame[[0]], u, v)
    plane = table.plane[0]
    np.testing.assert_allclose(p @ plane[0:3] - plane[3], u, atol=1e-12)
    np.testing.assert_allclose(p @ plane[4:7] - plane[7], v, atol=1e-12)
    np.testing.assert_allclose(p @ plane[8:11], plane[11], atol=1e-12)  # on the plane
    assert plane[12] == 6.0  # |e1 x e2| = 2 * 3


def test_degenerate_triangle_gets_the_fixed_normal():
    table = surface.TriangleTable(1)
    flat = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # collinear
    table.fill(flat, np.array([[0, 1, 2]]), np.zeros(3), CORNER_NORMALS, CORNER_ALBEDO, [0])
    np.testing.assert_array_equal(table.frame[0, 3], surface.DEGENERATE_NORMAL)
    assert np.all(np.isfinite(table.plane))


def test_corner_values_at_the_corners_and_the_mean_at_the_centroid():
    table = _table()
    corners = np.repeat(table.corners, 3, axis=0)
    values = surface.interpolate(corners, CORNERS)  # weights exactly 0 and 1
    np.testing.assert_array_equal(values[:, :3], CORNER_NORMALS[0])
    np.testing.assert_array_equal(values[:, 3:], CORNER_ALBEDO[0])
    mean = surface.interpolate(table.corners, CENTROID)[0]
    expect = table.corners[0].astype(np.float64).mean(axis=0)
    np.testing.assert_allclose(mean, expect, rtol=0, atol=FLOAT32_SUM_ULPS * EPS32)
    # Positions: the corners exactly (u, v in {0, 1}), the centroid within the float32
    # rounding of u = v = 1/3 times the edge lengths (≤ 3 m here).
    for w in CORNERS:
        p = surface.positions(table.frame, w[1:2], w[2:3])
        np.testing.assert_array_equal(p[0], (w @ VERTICES) - ORIGIN)
    third = np.array([1.0 / 3.0], np.float32)
    p = surface.positions(table.frame, third, third)[0]
    np.testing.assert_allclose(p, VERTICES.mean(axis=0) - ORIGIN, atol=3.0 * EPS32)


def test_weights_from_embree_uv():
    u = np.array([0.0, 1.0, 0.0, 0.25], np.float32)
    v = np.array([0.0, 0.0, 1.0, 0.5], np.float32)
    w = surface.weights_from_uv(u, v)
    assert w.dtype == np.float32
    np.testing.assert_array_equal(w, [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25, 0.25, 0.5]])


def test_shading_normal_faces_the_viewer_on_either_side():
    table = _table()
    # Seen from the front (ray going -z): the interpolated normal, normalised.
    down = np.array([[0.0, 0.0, -1.0]])
    n = _shading_normal(table, CENTROID, down)[0]
    mean = CORNER_NORMALS[0].astype(np.float64).mean(axis=0)
    # A unit result: float32 interpolation and normalisation, a few ulps.
    np.testing.assert_allclose(n, mean / np.linalg.norm(mean), atol=8 * EPS32)
    # Seen from behind (ray going +z, the geometric normal faces away): flipped whole.
    up = -down
    np.testing.assert_allclose(_shading_normal(table, CENTROID, up)[0], -n, atol=8 * EPS32)
    # At a corner the corner normal itself, exactly (weights 1 and 0, unit length).
    np.testing.assert_array_equal(_shading_normal(table, CORNERS[:1], down)[0], [0, 0, 1])
    np.testing.assert_array_equal(_shading_normal(table, CORNERS[:1], up)[0], [0, 0, -1])


def test_shading_normal_bent_past_the_ray_or_degenerate_becomes_geometric():
    table = _table()
    # A grazing ray along +x, slightly down, on the front: corner 1's normal (0.6, 0,
    # 0.8) faces along it (n·d > 0), so the geometric normal replaces it.
    graze = np.array([[0.99, 0.0, -0.141]])
    graze /= np.linalg.norm(graze)
    np.testing.assert_array_equal(_shading_normal(table, CORNERS[1:2], graze)[0], FRONT)
    # Opposite corner normals cancel at the midpoint: degenerate, the geometric normal
    # on the viewer's side (here the back side) instead of a NaN.
    opposed = CORNER_NORMALS.copy()
    opposed[0, 1] = -opposed[0, 0]
    half = np.array([[0.5, 0.5, 0.0]], np.float32)
    up = np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(_shading_normal(_table(opposed), half, up)[0], -FRONT)


def test_texture_wraps_with_period_one():
    rng = np.random.default_rng(3)
    tex = rng.random((4, 8, 3)).astype(np.float32)
    # 1.25 - floor(1.25) = 0.25 exactly (likewise for the other dyadic coordinates), so
    # the wrapped lookups read the same texels with the same weights: equal bit for bit.
    base = np.array([[0.25, 0.25], [0.375, 0.625]])
    shifted = base + np.array([[1.0, -1.0], [-2.0, 3.0]])
    np.testing.assert_array_equal(
        surface.sample_bilinear_wrap(tex, shifted), surface.sample_bilinear_wrap(tex, base)
    )
    np.testing.assert_array_equal(
        surface.sample_bilinear_wrap(tex, np.array([[1.25, 0.5]])),
        surface.sample_bilinear_wrap(tex, np.array([[0.25, 0.5]])),
    )
    # A texel centre reads that texel (row 0 = top, v = 0 at the bottom): u = (x + 0.5)
    # / w, v = 1 - (y + 0.5) / h, weights exactly 0 / 1.
    np.testing.assert_array_equal(
        surface.sample_bilinear_wrap(tex, np.array([[2.5 / 8, 1.0 - 1.5 / 4]]))[0], tex[1, 2]
    )


def test_texture_albedo_replaces_only_textured_materials():
    tex = np.full((2, 2, 3), 0.25, np.float32)
    tri_material = np.array([0, 1])
    corner_uv = np.zeros((2, 3, 2), np.float32)
    albedo = np.ones((2, 3), np.float32)
    out = surface.texture_albedo(
        albedo, np.array([0, 1]), CENTROID.repeat(2, 0), tri_material, corner_uv, [None, tex]
    )
    assert out is albedo
    np.testing.assert_array_equal(out, [[1, 1, 1], [0.25, 0.25, 0.25]])


def test_corners_differ_finds_changed_rows_only():
    table = _table()
    assert not table.corners_differ(CORNER_NORMALS, CORNER_ALBEDO, np.array([0])).any()
    albedo = CORNER_ALBEDO.copy()
    albedo[0, 2, 1] = 0.5
    assert table.corners_differ(CORNER_NORMALS, albedo, np.array([0])).all()
