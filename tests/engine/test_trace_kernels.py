"""The compiled trace phase (``engine/trace/trace_kernels.py``) against the numpy forms it
replaced (``numpy_paths.py``): first rays, offsets, hit splitting, the bounce loop with
its gather and records, on mirrors, glass, cut-outs and lights; finite for extreme
inputs."""

from __future__ import annotations

import numpy as np
import pytest
from numpy_paths import numpy_first_rays, numpy_primary_gbuffer, numpy_trace_reflections
from scenes import box_between, look_at, parts_scene, quad, sphere
from textured_stages import mirrored_cutout_stage

from phrt_usd.engine.trace import trace_kernels
from phrt_usd.engine.trace.bounce_layout import T_SOURCES, TRI_COLUMNS, TRI_IOR, TRI_REFLECTOR
from phrt_usd.engine.trace.bvh import GLOBAL_IDS, NO_ANIMATED, RAY_OFFSET_RELATIVE
from phrt_usd.engine.trace.paths import refract
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model.scene import DistantLight, Lights, LocalLight
from phrt_usd.usd.stage import read_stage


def lit_scene(offset=(0.0, 0.0, 0.0), glass: bool = False):
    """Mirrors (F = 1 and F < 1), a diffuse box, optional glass, a distant and a local
    light; everything moved by ``offset`` metres."""
    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.ones(3))],
        local=[LocalLight(np.array([1.0, 3.0, 1.0]) + offset, np.full(3, 20.0))],
    )
    parts = [
        dict(mesh=quad(20.0, offset), F=0.6),
        dict(mesh=sphere(1.0, np.array([0, 1, 0]) + offset, 3), F=1.0, smooth=True),
        dict(mesh=box_between(np.array([2, 0, -1]) + offset, np.array([3, 2, 1]) + offset)),
        dict(
            mesh=box_between(np.array([-3, 0, -1]) + offset, np.array([-2, 2, 1]) + offset), F=0.3
        ),  # fmt: skip
    ]
    if glass:
        slab = box_between(np.array([-1, 0.2, 1.5]) + offset, np.array([1, 1.2, 2.5]) + offset)
        parts.append(dict(mesh=slab, opacity=0.3, ior=1.5, F=0.2))
    return parts_scene(parts, lights)


def _by_pixel(result):
    order = np.argsort(result.pixel_index, kind="stable")
    return result.pixel_index[order], result.radiance[order]


def assert_same_trace(new, old, atol=1e-6):
    """Same pixels, radiance, rays and records (pixel order may differ)."""
    pix_new, rad_new = _by_pixel(new)
    pix_old, rad_old = _by_pixel(old)
    np.testing.assert_array_equal(pix_new, pix_old)
    np.testing.assert_allclose(rad_new, rad_old, atol=atol, rtol=1e-5)
    assert new.rays == old.rays
    for a, b in zip(new.records, old.records, strict=True):
        assert (a.source, a.pixels, a.rays, a.hits) == (b.source, b.pixels, b.rays, b.hits)
        assert a.max_reflector_bounces == b.max_reflector_bounces
        assert a.mean_reflector_bounces == pytest.approx(b.mean_reflector_bounces)


@pytest.mark.parametrize("glass", [False, True])
@pytest.mark.parametrize("limit", [0, 1, 3, 5])
def test_bounce_loop_matches_numpy(glass, limit):
    scene = lit_scene(glass=glass)
    camera = look_at((0.0, 4.0, 7.0), (0.0, 0.5, 0.0))
    tracer = Tracer(scene, threads=1)
    gb = tracer.primary_gbuffer(camera, 64, 48)
    sources = [0, 1, 3] + ([4] if glass else [])
    tracer.reset_counters()
    new = tracer.trace_reflections(gb, sources, limit)
    new_counts = dict(tracer.rays_cast)
    tracer.reset_counters()
    old = numpy_trace_reflections(tracer, gb, sources, limit)
    assert_same_trace(new, old)
    assert new_counts == tracer.rays_cast
    if limit >= 3:
        assert any(r.hits for r in new.records)  # reflector chains were exercised
    if glass and limit >= 2:
        assert new_counts["refraction"] > 0


@pytest.mark.slow
def test_bounce_loop_through_cutouts_matches_numpy(tmp_path):
    """Reflected rays re-cast through a cut-out quad's holes (test_cutout_reflections)."""
    stage = read_stage(mirrored_cutout_stage(tmp_path))
    t = stage.frame_range[0]
    stage.set_time(t)
    scene = stage.scene
    sources = [i for i, e in enumerate(scene.elements) if e.is_reflector]
    tracer = Tracer(scene, threads=1)
    gb = tracer.primary_gbuffer(stage.camera(t), 64, 48)
    tracer.reset_counters()
    new = tracer.trace_reflections(gb, sources, 3)
    new_counts = dict(tracer.rays_cast)
    tracer.reset_counters()
    old = numpy_trace_reflections(tracer, gb, sources, 3)
    assert_same_trace(new, old)
    assert new_counts == tracer.rays_cast
    assert new_counts["reflection"] > len(new.pixel_index)  # re-casts happened


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1e6, 0.0, -1e6)])
def test_first_rays_match_numpy(offset):
    """source_rays: same pixels, snapped positions, normals, views, mirror directions and
    float32 origins as the numpy chain; far from the origin too."""
    scene = lit_scene(np.asarray(offset))
    tracer = Tracer(scene, threads=1)
    camera = look_at(np.array([0.0, 4.0, 7.0]) + offset, np.array([0.0, 0.5, 0.0]) + offset)
    gb = tracer.primary_gbuffer(camera, 48, 36)
    sources = [3, 0]
    first = tracer._source_pixels(gb, sources, None, reflect=True, surface=True)
    pix, src, origins, d, rel, ng, ns, view = numpy_first_rays(tracer, gb, sources)
    order = np.argsort(first["pix"], kind="stable")
    np.testing.assert_array_equal(first["pix"][order], pix)
    np.testing.assert_array_equal(first["src"][order], src)
    np.testing.assert_allclose(first["rel"][order], rel, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(first["ng"][order], ng)
    np.testing.assert_allclose(first["ns"][order], ns, atol=1e-7)
    np.testing.assert_allclose(first["view"][order], view, atol=1e-7)
    np.testing.assert_allclose(first["dir"][order], d, atol=1e-6)
    # The origins: off the surface by the offset, on the side the ray leaves to.
    np.testing.assert_allclose(first["org"][order], origins.astype(np.float32), rtol=1e-6)


def test_offset_origins_is_the_boundary_offset_cast():
    rng = np.random.default_rng(3)
    tracer = Tracer(lit_scene(), threads=1)
    boundary = tracer.bvh.boundary
    rel = rng.normal(size=(500, 3)) * 10.0 ** rng.integers(-3, 7, size=(500, 1))
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    dirs = rng.normal(size=(500, 3)).astype(np.float32)
    expected = boundary.offset(rel, normals, dirs).astype(np.float32)
    np.testing.assert_array_equal(boundary.offset_rays(rel, normals, dirs), expected)
    # The offset survives the cast: every origin left its surface point.
    assert np.all(np.any(boundary.offset_rays(rel, normals, dirs) != rel.astype(np.float32), 1))


def test_split_hits_matches_flatnonzero():
    rng = np.random.default_rng(5)
    prim = rng.integers(-1, 4, 300).astype(np.int32)
    u, v = rng.random(300).astype(np.float32), rng.random(300).astype(np.float32)
    out = [np.empty(300, np.int64), np.empty(300, np.int64), np.empty(300, np.float32),
           np.empty(300, np.float32), np.empty(300, np.int64)]  # fmt: skip
    h = trace_kernels.split_hits(prim, u, v, *out)
    ray = np.flatnonzero(prim >= 0)
    assert h == len(ray)
    np.testing.assert_array_equal(out[0][:h], ray)
    np.testing.assert_array_equal(out[1][:h], prim[ray])
    np.testing.assert_array_equal(out[2][:h], u[ray])
    np.testing.assert_array_equal(out[4][: 300 - h], np.flatnonzero(prim < 0))


def test_refraction_kernel_matches_snell():
    """The bounce kernel's refracted children equal ``paths.refract`` (both sides, total
    internal reflection included)."""
    rng = np.random.default_rng(7)
    m = 400
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    front = rng.normal(size=(m, 3))
    front /= np.linalg.norm(front, axis=1, keepdims=True)
    ns = (front + 0.1 * rng.normal(size=(m, 3))).astype(np.float32)
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    ior = rng.uniform(0.5, 2.5, m)
    frame = np.zeros((m, 4, 3))
    frame[:, 3] = front
    idx = np.arange(m)
    out = _bounce(idx, d.astype(np.float32), ns, frame, ior)
    expected = refract(d.astype(np.float32).astype(np.float64), ns.astype(np.float64), front, ior)
    np.testing.assert_allclose(out, expected.astype(np.float32), atol=2e-6)


def _bounce(tri, dirs, ns, frame, ior):
    """Refracted child directions (m, 3) of m glass hits (opacity 0, one material per
    triangle, shading normals ``ns`` given) by ``trace_kernels.bounce``."""
    m = len(tri)
    rays_i = np.zeros((2, 4, 2 * m), np.int64)
    rays_i[0, 0, :m] = np.arange(m)
    rays_v = np.zeros((2, 2, 2 * m, 3), np.float32)
    rays_v[0, 0, :m] = dirs
    tri_table = np.zeros((m, TRI_COLUMNS))
    tri_table[:, TRI_IOR], tri_table[:, TRI_REFLECTOR] = ior, -1.0
    gather = (
        np.zeros((5, 2 * m), np.int64), np.zeros((2, 2 * m)), np.zeros((2, 2 * m, 3)),
        np.zeros((4, 2 * m, 3), np.float32), np.zeros((2, 2 * m), np.float32),
    )  # fmt: skip
    uv = np.zeros(m, np.float32)
    n = trace_kernels.bounce(
        tri, uv, uv, *NO_ANIMATED, GLOBAL_IDS, GLOBAL_IDS, ns, rays_i, np.ones((2, 2 * m)),
        rays_v, 0, m, tri_table, frame, np.zeros((m, 3, 6), np.float32), True, False, 1e-6,
        RAY_OFFSET_RELATIVE, 1, 1,
        np.zeros(T_SOURCES + 1 + m, np.int64), *gather,
    )  # fmt: skip
    assert n == (m, m)  # every hit refracts, none reflects (F = 0)
    return rays_v[1, 0, :m]  # the children's directions


def test_kernels_finite_for_extreme_inputs():
    """Zero and huge vectors: unit rows stay finite (zero stays zero), offsets finite."""
    view = np.array([[0, 0, 0], [1e30, 0, 0], [0, 1e-30, 0], [3, 4, 0]], np.float32)
    nrm = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 1e-30], [0, 0, 1]], np.float32)
    pos = np.array([[0, 0, 0], [1e12, -1e12, 0], [1e-9, 0, 0], [5, 5, 5]], np.float64)
    frame = np.zeros((1, 4, 3))
    frame[0, 3] = (0.0, 1.0, 0.0)
    n = len(view)
    out = [np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3)),
           np.empty((n, 3), np.float32), np.empty((n, 3), np.float32),
           np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)]  # fmt: skip
    trace_kernels.source_rays(
        np.arange(n), np.array([-1, 0, -1, 0], np.int32), pos, nrm, view, np.zeros(3), frame,
        1e-6, RAY_OFFSET_RELATIVE, 0, n, *out,
    )  # fmt: skip
    for a in out[1:]:
        assert np.all(np.isfinite(a))


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1e6, 0.0, -1e6)])
def test_primary_gbuffer_matches_numpy(offset, monkeypatch):
    """The compiled pixel rays and G-buffer rows against ``pixel_rays`` + numpy scatter:
    the directions differ only by the order of the normalisation's rounding, so ids
    agree but for a few edge pixels and the rest to rounding; split over the pool (rows
    threshold lowered) the same bits as on one thread."""
    import phrt_usd.engine.trace.tracer as tracer_module  # noqa: PLC0415

    scene = lit_scene(np.asarray(offset), glass=True)
    camera = look_at(np.array([0.0, 4.0, 7.0]) + offset, np.array([0.0, 0.5, 0.0]) + offset)
    one = Tracer(scene, threads=1).primary_gbuffer(camera, 64, 48)
    ref = numpy_primary_gbuffer(Tracer(scene, threads=1), camera, 64, 48)
    same = one.element_id == ref.element_id
    assert same.mean() > 0.998 and (one.element_id >= 0).sum() > 1000
    both = same & (one.element_id >= 0)
    np.testing.assert_allclose(one.view_dir, ref.view_dir, atol=1e-7)
    np.testing.assert_allclose(one.depth[both], ref.depth[both], rtol=1e-5)
    np.testing.assert_allclose(
        one.position[both] - offset, ref.position[both] - offset, atol=1e-5
    )  # fmt: skip
    np.testing.assert_allclose(one.normal[both], ref.normal[both], atol=1e-4)
    np.testing.assert_allclose(one.albedo[both], ref.albedo[both], atol=1e-5)
    assert np.all(np.isinf(one.depth[one.element_id < 0]))
    monkeypatch.setattr(tracer_module, "PARALLEL_MIN_KERNEL_ROWS", 16)
    two = Tracer(scene, threads=2).primary_gbuffer(camera, 64, 48)
    for name in ("element_id", "depth", "position", "normal", "albedo", "view_dir"):
        np.testing.assert_array_equal(getattr(two, name), getattr(one, name))


def test_first_rays_split_over_the_pool_match_one_thread(monkeypatch):
    import phrt_usd.engine.trace.tracer as tracer_module  # noqa: PLC0415

    scene = lit_scene()
    camera = look_at((0.0, 4.0, 7.0), (0.0, 0.5, 0.0))
    one = Tracer(scene, threads=1)
    gb = one.primary_gbuffer(camera, 64, 48)
    expected = one.trace_reflections(gb, [0, 1, 3], 3)
    monkeypatch.setattr(tracer_module, "PARALLEL_MIN_KERNEL_ROWS", 16)
    got = Tracer(scene, threads=2).trace_reflections(gb, [0, 1, 3], 3)
    np.testing.assert_array_equal(got.pixel_index, expected.pixel_index)
    np.testing.assert_array_equal(got.radiance, expected.radiance)
    assert [r.rays for r in got.records] == [r.rays for r in expected.records]
