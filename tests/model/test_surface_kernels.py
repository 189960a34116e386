"""The compiled surface rule (``model.surface_kernels``) against its numpy reference.

The reference is the numpy arithmetic the kernels replaced (``model.surface``'s
``interpolate`` and ``positions``, the side rule in ``tests/surface_reference.py`` and
the G-buffer's ray-plane derivation, written out below as it stood). Both use the same
operations in the same precision; only the order of a sum's terms may differ, so:

* float64 results (positions, depths) agree to ``REL64`` relative to the scene's reach;
* float32 results (weights, normals, albedo) to ``ABS32`` absolute: a few float32 ulps
  of unit-sized values (FLOAT32_SUM_ULPS of test_surface.py, doubled for the division
  that makes a normal unit);
* ids, sides and the branch of the side rule (which normal was chosen) exactly, except
  where the reference's own decision value lies within rounding of its threshold.
"""

from __future__ import annotations

import numpy as np
import pytest
import surface_reference as reference
from hypothesis import given, settings
from hypothesis import strategies as st

from phrt_usd import kernels
from phrt_usd.model import surface, surface_kernels

#: float64 agreement, relative to the largest coordinate (order of 3-term sums).
REL64 = 1e-12
#: float32 agreement of unit-sized values: 8 ulps at 1.0.
ABS32 = 8 * float(np.finfo(np.float32).eps)
GRAZING_EPS = surface_kernels.GRAZING_EPS


def _random_table(rng, count: int, spread: float = 10.0, far: float = 0.0):
    """A TriangleTable of ``count`` random triangles (some degenerate, some with
    cancelling corner normals) around ``far`` metres from the origin."""
    vertices = rng.normal(size=(count * 3, 3)) * spread + far
    triangles = np.arange(count * 3).reshape(count, 3)
    if count > 3:
        vertices[triangles[0, 2]] = vertices[triangles[0, 1]]  # a zero-area triangle
    normals = rng.normal(size=(count, 3, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    if count > 3:
        normals[1, 1] = -normals[1, 0]  # cancel at the midpoint of an edge
        normals[2, 0] = np.nan  # a NaN corner normal
    albedo = rng.uniform(size=(count, 3, 3)).astype(np.float32)
    table = surface.TriangleTable(count)
    origin = np.full(3, far)
    table.fill(vertices, triangles, origin, normals, albedo, slice(None))
    return table, origin


def _reference_hits(table, tri, u, v, incoming):
    """The tracer's numpy hit geometry as it stood (``HitSurfaces.geometry``)."""
    g = np.take(table.frame, tri, axis=0)
    pos = surface.positions(g, u, v)
    side = reference.viewer_side(np.einsum("ij,ij->i", g[:, 3], incoming))
    ng = g[:, 3] * side[:, None]
    corners = np.take(table.corners, tri, axis=0)
    ns = surface.interpolate(corners[:, :, :3], surface.weights_from_uv(u, v))
    ns = reference.orient_shading_normals(ns, side, incoming, table, tri)
    albedo = surface.interpolate(corners[:, :, 3:], surface.weights_from_uv(u, v))
    return pos, ng, ns, albedo


def _kernel_hits(table, tri, u, v, incoming):
    m = len(tri)
    pos, ng = np.empty((m, 3)), np.empty((m, 3))
    ns, albedo = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
    surface_kernels.hit_geometry(tri, u, v, incoming, table.frame, table.corners, pos, ng, ns)
    surface_kernels.hit_albedo(tri, u, v, table.corners, albedo)
    return pos, ng, ns, albedo


def _directions(rng, m):
    d = rng.normal(size=(m, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _assert_hits_agree(table, tri, u, v, incoming, scale):
    ref = _reference_hits(table, tri, u, v, incoming)
    got = _kernel_hits(table, tri, u, v, incoming)
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=REL64 * scale)
    np.testing.assert_array_equal(got[1], ref[1])  # a sign flip of the same row
    np.testing.assert_allclose(got[3], ref[3], rtol=0, atol=ABS32)
    # The side rule's branch is decided by n·d >= 0 on a normal rounded in a different
    # order: where the reference's n·d is within rounding of 0 either branch is right.
    ns_ref = ref[2].astype(np.float64)
    decided = np.abs(np.einsum("ij,ij->i", ns_ref, incoming)) > 1e-5
    np.testing.assert_allclose(got[2][decided], ref[2][decided], rtol=0, atol=ABS32)
    assert np.all(np.isfinite(got[2]))
    np.testing.assert_allclose(np.linalg.norm(got[2], axis=1), 1.0, atol=ABS32)


def test_hit_geometry_matches_numpy_reference():
    rng = np.random.default_rng(7)
    table, _ = _random_table(rng, 64)
    m = 5000
    tri = rng.integers(0, 64, m).astype(np.int64)
    u = rng.uniform(0, 1, m).astype(np.float32)
    v = (rng.uniform(0, 1, m) * (1 - u)).astype(np.float32)
    _assert_hits_agree(table, tri, u, v, _directions(rng, m), scale=40.0)


@pytest.mark.slow
@settings(max_examples=40, deadline=None)
@given(
    far=st.sampled_from([0.0, 1e6, -3e7]),
    spread=st.sampled_from([1e-4, 1.0, 1e4]),
    seed=st.integers(0, 2**31 - 1),
)
def test_hit_geometry_extremes_stay_finite_and_agree(far, spread, seed):
    """Far from the origin, tiny and huge triangles: same results as the reference,
    finite unit shading normals (NaN corners fall back to the face normal)."""
    rng = np.random.default_rng(seed)
    table, _ = _random_table(rng, 8, spread=spread, far=far)
    m = 200
    tri = rng.integers(0, 8, m).astype(np.int64)
    u = rng.uniform(0, 1, m).astype(np.float32)
    v = (rng.uniform(0, 1, m) * (1 - u)).astype(np.float32)
    _assert_hits_agree(table, tri, u, v, _directions(rng, m), scale=10 * spread)


def _reference_derive(table, tid, d, eye, near, far, fwd):
    """The G-buffer's numpy derivation as it stood (``GBufferPass._derive``): position
    (rel), depth, weights, normal, albedo of pixels with unit rays ``d`` on ``tid``."""
    tab = np.take(table.plane, tid, axis=0)
    ng = tab[:, 8:11]
    den = np.einsum("ij,ij->i", ng, d)
    floor = GRAZING_EPS * tab[:, 12]
    den = np.where(np.abs(den) < floor, np.where(den < 0, -floor, floor), den)
    den[den == 0.0] = 1.0
    t = np.clip((tab[:, 11] - np.einsum("ij,kj->ik", ng, eye[None])[:, 0]) / den, near, far)
    p = eye + t[:, None] * d
    bv = np.einsum("ij,ij->i", p, tab[:, 0:3]) - tab[:, 3]
    bw = np.einsum("ij,ij->i", p, tab[:, 4:7]) - tab[:, 7]
    b = np.stack([np.clip(1 - bv - bw, 0, 1), np.clip(bv, 0, 1), np.clip(bw, 0, 1)], axis=1)
    b = (b / np.maximum(b.sum(axis=1), 1e-12)[:, None]).astype(np.float32)
    values = surface.interpolate(np.take(table.corners, tid, axis=0), b)
    n = reference.orient_shading_normals(values[:, :3], reference.viewer_side(den), d, table, tid)
    return p, t * (d @ fwd), b, n, values[:, 3:]


def test_derive_matches_numpy_reference():
    """Pixels of a 40 x 30 view on random triangles (ids given, as the raster's id pass
    would): every G-buffer row the kernel writes equals the reference's."""
    rng = np.random.default_rng(3)
    table, origin = _random_table(rng, 32, spread=2.0, far=5e5)
    width, height = 40, 30
    xs = np.linspace(-0.5, 0.5, width)
    ys = np.linspace(0.4, -0.4, height)
    inv_len = 1.0 / np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    eye = np.array([0.3, -0.2, 25.0])
    near, far = 0.01, 100.0
    fwd = -rot[:, 2]
    n = width * height
    ids = rng.integers(0, 33, n).astype(np.uint32)  # 0: background
    # Garbage-filled outputs: the kernel must write every row of every pixel.
    outs = [np.full(n, 7, np.int32), np.full(n, 7, np.int32), np.full(n, 7, np.float32),
            np.full((n, 3), 7.0), np.full((n, 3), 7, np.float32), np.full((n, 3), 7, np.float32),
            np.full((n, 3), 7, np.float32), np.full((n, 3), 7, np.float32)]  # fmt: skip
    none = np.zeros(0, np.int64)
    tri_element = np.arange(32, dtype=np.int64) // 4
    surface_kernels.derive(none, none, 0, n, ids, none, xs, ys, inv_len, rot, False, eye,
                           near, far, fwd, origin, table.plane, table.corners, table.frame,
                           tri_element, *outs)  # fmt: skip
    tri, elem, depth, pos, normal, albedo, view, bary = outs
    d = (ys[:, None, None] * rot[:, 1] - rot[:, 2] + xs[None, :, None] * rot[:, 0])
    d = (d * inv_len[:, :, None]).reshape(-1, 3)
    np.testing.assert_array_equal(view, d.astype(np.float32))
    cov = np.flatnonzero(ids > 0)
    bg = np.flatnonzero(ids == 0)
    np.testing.assert_array_equal(normal[bg], -view[bg])
    assert np.all(tri[bg] == -1) and np.all(elem[bg] == -1) and np.all(np.isinf(depth[bg]))
    assert not pos[bg].any() and not albedo[bg].any()
    tid = ids[cov].astype(np.int64) - 1
    np.testing.assert_array_equal(tri[cov], tid)
    np.testing.assert_array_equal(elem[cov], tri_element[tid])
    p, z, b, nrm, alb = _reference_derive(table, tid, d[cov], eye, near, far, fwd)
    np.testing.assert_allclose(pos[cov], p + origin, rtol=REL64, atol=0)
    np.testing.assert_allclose(depth[cov], z.astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(bary[cov], b, rtol=0, atol=ABS32)
    np.testing.assert_allclose(albedo[cov], alb, rtol=0, atol=ABS32)
    decided = np.abs(np.einsum("ij,ij->i", nrm.astype(np.float64), d[cov])) > 1e-5
    np.testing.assert_allclose(normal[cov][decided], nrm[decided], rtol=0, atol=ABS32)
    assert np.all(np.isfinite(normal)) and np.all(np.isfinite(pos))


def test_warm_up_compiles_every_kernel():
    """The set-up's warm-up (``python -m phrt_usd.kernels``) reaches every kernel."""
    assert "phrt_usd.model.surface_kernels" in kernels.KERNEL_MODULES
    kernels.warm_up()
    for kernel in (surface_kernels.derive, surface_kernels.hit_geometry,
                   surface_kernels.hit_albedo):  # fmt: skip
        assert kernel.signatures, kernel


@settings(max_examples=30, deadline=None)
@given(
    far=st.sampled_from([0.0, 1e6, -3e7]),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
    grazing=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
def test_derive_extremes_stay_finite(far, scale, grazing, seed):
    """A view of random triangles far from the origin, tiny or huge, seen head-on or
    at grazing angles (the camera in a triangle's plane): every written row is finite,
    depths inside the clip range, normals unit."""
    rng = np.random.default_rng(seed)
    table, origin = _random_table(rng, 8, spread=scale, far=far)
    width, height = 8, 6
    xs = np.linspace(-0.5, 0.5, width)
    ys = np.linspace(0.4, -0.4, height)
    inv_len = 1.0 / np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    # Grazing: the eye on triangle 3's plane (n·d = 0 for rays in the plane).
    eye = table.frame[3, 0] + (table.frame[3, 1] * 0.3 if grazing else table.frame[3, 3] * scale)
    near, far_clip = 1e-6 * scale, 100.0 * scale
    n = width * height
    ids = rng.integers(0, 9, n).astype(np.uint32)
    outs = [np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.float32),
            np.empty((n, 3)), np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
            np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)]  # fmt: skip
    none = np.zeros(0, np.int64)
    surface_kernels.derive(none, none, 0, n, ids, none, xs, ys, inv_len, rot, False, eye,
                           near, far_clip, -rot[:, 2], origin, table.plane, table.corners,
                           table.frame, np.zeros(8, np.int64), *outs)  # fmt: skip
    tri, _, depth, pos, normal, albedo, view, bary = outs
    cov = ids > 0
    assert np.all(np.isfinite(pos)) and np.all(np.isfinite(normal)) and np.all(np.isfinite(view))
    assert np.all(np.isfinite(depth[cov])) and np.all(np.isfinite(bary[cov]))
    # Distances along the rays lie in the clip range, up to the float64 rounding of world
    # positions this far from the world origin (a few ulps of |origin| + |eye|).
    dist = np.linalg.norm(pos[cov] - origin - eye, axis=1)
    tol = 8 * np.finfo(np.float64).eps * (np.abs(origin).max() + np.abs(eye).max() + far_clip)
    assert np.all(dist <= far_clip + tol) and np.all(dist >= near - tol)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=ABS32)
