"""Tests of the Embree tracer on small synthetic scenes built without USD."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scenes import box_between, look_at, parts_scene, quad, ray_sphere_hit, sphere

from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model import preview_surface
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, DistantLight, DomeLight, Lights, Scene

SKY = np.array([0.2, 0.4, 0.8])


# ---------------------------------------------------------------- helpers


def assert_rows(rows: np.ndarray, expected, atol: float) -> None:
    """Every row of (n, 3) ``rows`` equals ``expected`` (3,) within ``atol``."""
    np.testing.assert_allclose(rows, np.broadcast_to(expected, rows.shape), atol=atol)


# ---------------------------------------------------------------- (1) mirror physics


@pytest.mark.slow
def test_mirror_floor_reflects_sphere_where_mirrored_geometry_says():
    center, radius = np.array([0.3, 1.0, -0.5]), 0.6
    parts = [
        dict(mesh=quad(60.0), F=1.0),
        dict(mesh=sphere(radius, center, 5), albedo=(1, 0, 0), emissive=(1, 0, 0), smooth=True),
    ]
    scene = parts_scene(parts)
    tracer = Tracer(scene)
    camera = look_at((0.0, 3.0, 6.0), (0.0, 0.0, 0.0))
    gb = tracer.primary_gbuffer(camera, 160, 120)
    res = tracer.trace_reflections(gb, [0], bounce_limit=5)
    assert len(res.pixel_index) == int((gb.element_id == 0).sum())
    dirs = gb.view_dir.reshape(-1, 3)[res.pixel_index].astype(np.float64)
    mirrored = center * np.array([1.0, -1.0, 1.0])
    expected = ray_sphere_hit(camera.position, dirs, mirrored, radius)
    got = res.radiance[:, 0] > 0.5
    assert expected.sum() > 200  # the reflection covers a real patch of the image
    assert np.mean(expected == got) >= 0.99
    # Reflected sphere pixels carry its colour (emissive red + ambient), the rest the sky.
    # Red: 1 + 0.05 x (E + 1 (1 - E)) = 1.05 whatever the specular albedo E at the hit's
    # angle; green and blue: the ambient's specular part alone, 0.05 E (E of the rough
    # dielectric at most 0.3: the albedo table at roughness 1).
    seen = res.radiance[got & expected]
    np.testing.assert_allclose(seen[:, 0], 1.05, atol=1e-5)
    np.testing.assert_array_equal(seen[:, 1], seen[:, 2])
    assert np.all((seen[:, 1] > 0.0) & (seen[:, 1] <= 0.05 * 0.3))
    assert_rows(res.radiance[~got], DEFAULT_ENVIRONMENT, atol=1e-6)
    rec = res.records[0]
    assert rec.hits == {} and rec.max_reflector_bounces == 0 and rec.rays == res.rays


# ---------------------------------------------------------------- (2) parallel mirrors


@pytest.mark.parametrize("limit", [1, 3, 5])
def test_parallel_mirrors_stop_at_bounce_limit(limit):
    parts = [
        dict(mesh=quad(2000.0, (0, 0, 0), "z"), F=1.0),
        dict(mesh=quad(2000.0, (0, 0, 2.0), "z"), F=0.9),
    ]
    scene = parts_scene(parts)
    scene.geometry.triangles[2:] = scene.geometry.triangles[2:][:, ::-1]  # second faces -z
    tracer = Tracer(scene)
    camera = look_at((0.0, 0.0, 1.0), (0.05, 0.02, 0.0), focal=200.0)
    gb = tracer.primary_gbuffer(camera, 40, 30)
    assert np.all(gb.element_id == 0)
    res = tracer.trace_reflections(gb, [0], bounce_limit=limit)
    rec = res.records[0]
    assert rec.max_reflector_bounces == limit
    assert rec.mean_reflector_bounces == pytest.approx(limit)
    assert rec.rays == limit * 1200  # one reflection ray per pixel per bounce, no lights
    assert np.all(np.isfinite(res.radiance))
    # Hits alternate B, A, B, ...: every ray of every bounce hit a reflector.
    assert rec.hits.get(1, 0) == 1200 * ((limit + 1) // 2)
    assert rec.hits.get(0, 0) == 1200 * (limit // 2)


# ---------------------------------------------------------------- (3) precision


#: (scene offset from the world origin in metres, scene scale): 1e6 m away, 1 mm small.
FAR_AND_TINY = [(np.array([1e6, 0.0, -1e6]), 1.0), (np.zeros(3), 1e-3)]


@pytest.mark.parametrize(("offset", "scale"), FAR_AND_TINY)
def test_no_acne_no_leaks_far_from_origin_and_tiny(offset, scale):
    lights = Lights(
        distant=[DistantLight(np.array([0.6, 0.8, 0.0]), np.ones(3))],
        dome=DomeLight(color=SKY),
    )
    floor = quad(20.0 * scale, offset)
    lo, hi = offset + scale * np.array([-1.0, 0.0, -1.0]), offset + scale * np.array([1, 2, 1])
    cube = box_between(lo, hi)
    scene = parts_scene([dict(mesh=floor, F=0.7), dict(mesh=cube)], lights)
    tracer = Tracer(scene)
    camera = look_at(
        offset + scale * np.array([8.0, 6.0, 8.0]), offset + scale * np.array([3, 0, 3])
    )
    gb = tracer.primary_gbuffer(camera, 80, 60)
    floor_px = gb.element_id == 0
    assert floor_px.sum() > 1000
    # Reflect only the pixels whose mirror ray sees the sky (away from the box).
    pos = gb.position.reshape(-1, 3)
    far_from_box = np.max(np.abs(pos - offset)[:, [0, 2]], axis=1) > 3.5 * scale
    sky_px = floor_px.reshape(-1) & far_from_box
    gb_sky = GBuffer(
        np.where(sky_px, gb.element_id.reshape(-1), -1).reshape(gb.shape),
        gb.triangle_id,
        gb.depth,
        gb.position,
        gb.normal,
        gb.albedo,
        gb.view_dir,
    )
    res = tracer.trace_reflections(gb_sky, [0], bounce_limit=5)
    assert res.records[0].hits == {}  # no floor ray re-hit the floor (acne)
    assert_rows(res.radiance, SKY, atol=1e-6)
    # Leaks: floor points in the box's shadow right at its foot (1e-3 of its size away).
    xs = np.linspace(-0.9, 0.9, 50)
    pts = offset + scale * np.stack([-1.0 - 1e-3 * np.ones_like(xs), 0 * xs, xs], axis=1)
    vis = tracer.shadow_visibility(pts, np.tile([0.0, 1.0, 0.0], (len(xs), 1)))
    assert np.all(vis == 0.0)
    pts_lit = pts + scale * np.array([4.0, 0.0, 0.0])  # the lit side of the box
    assert np.all(tracer.shadow_visibility(pts_lit, np.tile([0.0, 1.0, 0.0], (50, 1))) == 1)


# ---------------------------------------------------------------- (4) shadows


def test_shadow_rays_under_box_and_without_lights():
    lights = Lights(distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    parts = [dict(mesh=quad(20.0)), dict(mesh=box_between((-1, 1, -1), (1, 2, 1)))]
    tracer = Tracer(parts_scene(parts, lights))
    pts = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.9, 0.0, 0.9]])
    vis = tracer.shadow_visibility(pts, np.tile([0.0, 1.0, 0.0], (3, 1)))
    np.testing.assert_array_equal(vis[:, 0], [0.0, 1.0, 0.0])
    assert tracer.rays_cast["shadow"] == 3
    dark = parts_scene(parts, Lights())
    tracer = Tracer(dark)
    assert tracer.shadow_visibility(pts, np.tile([0.0, 1.0, 0.0], (3, 1))).shape == (3, 0)
    gb = tracer.primary_gbuffer(look_at((0, 5, 8), (0, 0, 0)), 40, 30)
    tracer.trace_reflections(gb, [0], 3)
    assert tracer.rays_cast["shadow"] == 0


# ---------------------------------------------------------------- (5) refraction


def test_glass_slab_shifts_ray_as_snell_says():
    slab = box_between((-50, 0, -50), (50, 1.0, 50))
    parts = [dict(mesh=slab, opacity=0.0, ior=1.5), dict(mesh=quad(400.0, (0, -3.0, 0)))]
    tracer = Tracer(parts_scene(parts))
    tracer.record_rays = True
    camera = look_at((-1.0, 2.0, 0.0), (0.0, 1.0, 0.0))  # 45° onto the slab's top at x=0
    gb = tracer.primary_gbuffer(camera, 1, 1)
    assert gb.element_id[0, 0] == 0
    res = tracer.trace_refraction(gb, bounce_limit=5)
    # Two rays: into the slab (hits its bottom), out of it (hits the opaque floor).
    assert res.rays == 2 and np.all(np.isfinite(res.radiance))
    origin = tracer.scene.origin
    (_, o1, d1, _), (_, o2, d2, _) = tracer.last_rays
    sin_t = np.sin(np.pi / 4) / 1.5
    np.testing.assert_allclose(d1[0], [sin_t, -np.sqrt(1 - sin_t**2), 0.0], atol=1e-6)
    # Leaving the slab's bottom: parallel to the incoming ray, shifted by tan(θt).
    np.testing.assert_allclose(d2[0], [np.sqrt(0.5), -np.sqrt(0.5), 0.0], atol=1e-6)
    exit_point = o2[0].astype(np.float64) + origin
    # Tolerance: the two origin offsets (into and out of the slab) move the path by ~eps.
    eps = tracer.offset_epsilon(exit_point[None])[0]
    expected_exit = [sin_t / np.sqrt(1 - sin_t**2), 0.0, 0.0]
    np.testing.assert_allclose(exit_point, expected_exit, atol=2.0 * eps)
    assert tracer.rays_cast["refraction"] == 2
    # The floor seen through the slab, weighted by 1 - opacity = 1: the ambient times its
    # directional albedo at 45° (parts_scene's rough grey dielectric; the numpy form of
    # shade_kernels.ambient_weight).
    import shading_reference as ref

    floor = preview_surface.surface_columns(np.full((1, 3), 0.5), 0, 0, np.zeros(3), 1.0, 0,
                                            0.01, 1.5, 1, 1)  # fmt: skip
    to_eye = np.array([[-np.sqrt(0.5), np.sqrt(0.5), 0.0]])
    weight = ref.ambient_weight(floor, np.array([[0.0, 1.0, 0.0]]), to_eye)[0]
    assert_rows(res.radiance, weight * DEFAULT_ENVIRONMENT, atol=1e-6)


def test_total_internal_reflection_and_no_refraction_work_when_opaque():
    parts = [dict(mesh=quad(20.0), F=1.0), dict(mesh=sphere(0.5, (0, 1, 0)))]
    tracer = Tracer(parts_scene(parts))
    gb = tracer.primary_gbuffer(look_at((0, 3, 6), (0, 0, 0)), 40, 30)
    res = tracer.trace_refraction(gb, bounce_limit=5)
    assert res.rays == 0 and len(res.pixel_index) == 0
    tracer.trace_reflections(gb, [0, 1], 5)
    assert tracer.rays_cast["refraction"] == 0
    # Snell at grazing incidence from inside glass: beyond the critical angle, mirror.
    from phrt_usd.engine.trace.paths import refract as _refract

    d = np.array([[np.sin(1.0), np.cos(1.0), 0.0]])  # 57° > 41.8° critical, leaving
    out = _refract(d, np.array([[0.0, 1.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]), np.array([1.5]))
    np.testing.assert_allclose(out, [[np.sin(1.0), -np.cos(1.0), 0.0]], atol=1e-12)


# ---------------------------------------------------------------- (6) environment


def test_environment_up_reads_top_row():
    from phrt_usd.engine.shading import environment_radiance

    tex = np.zeros((8, 16, 3), np.float32)
    tex[:4] = (0, 0, 1)
    tex[0] = (1, 0, 0)
    lights = Lights(dome=DomeLight(color=np.ones(3), texture=tex))
    got = environment_radiance(lights, np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]))
    np.testing.assert_allclose(got, [[1, 0, 0], [0, 0, 0]], atol=1e-6)


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=True, width=64), min_size=3, max_size=3))
def test_environment_lookup_never_nan(direction):
    from phrt_usd.engine.shading import environment_radiance

    tex = np.random.default_rng(0).random((6, 12, 3)).astype(np.float32)
    rot = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # a Z-up stage's dome
    lights = Lights(dome=DomeLight(color=np.ones(3), texture=tex, world_from_light=rot))
    got = environment_radiance(lights, np.array([direction, [0.0, 0.0, 0.0]]))
    assert got.shape == (2, 3) and np.all(np.isfinite(got))
    assert np.all(got >= tex.min() - 1e-6) and np.all(got <= tex.max() + 1e-6)


# ---------------------------------------------------------------- (7) discovery


def test_offscreen_reflector_discovered_through_mirror():
    parts = [
        dict(mesh=quad(60.0), F=1.0),
        dict(mesh=sphere(1.0, (0.0, 6.0, -4.0)), F=0.5),  # above the top of the frame
    ]
    tracer = Tracer(parts_scene(parts))
    camera = look_at((0.0, 3.0, 8.0), (0.0, 0.0, 0.0))
    gb = tracer.primary_gbuffer(camera, 80, 60)
    assert not np.any(gb.element_id == 1)  # off-screen
    res = tracer.trace_reflections(gb, [0], bounce_limit=5)
    rec = res.records[0]
    assert rec.hits.get(1, 0) > 0
    assert rec.max_reflector_bounces >= 1


# ---------------------------------------------------------------- (8) primary rays


def test_primary_gbuffer_matches_direct_embree():
    lights = Lights(distant=[DistantLight(np.array([0.3, 0.9, 0.1]), np.ones(3))])
    parts = [
        dict(mesh=quad(20.0), F=0.5),
        dict(mesh=sphere(1.0, (0, 1, 0), 3), albedo=(0.2, 0.8, 0.2), smooth=True),
        dict(mesh=box_between((2, 0, -1), (3, 2, 1))),
    ]
    scene = parts_scene(parts, lights)
    tracer = Tracer(scene)
    camera = look_at((4.0, 3.0, 6.0), (0.0, 0.5, 0.0))
    gb = tracer.primary_gbuffer(camera, 64, 48)
    direct = rtcs.EmbreeScene()
    verts = (scene.geometry.vertices - scene.origin).astype(np.float32)
    TriangleMesh(direct, verts, scene.geometry.triangles.astype(np.int32))
    o, d = camera.pixel_rays(64, 48)
    prim = direct.run((o - scene.origin).astype(np.float32), d.astype(np.float32))
    expect = np.where(prim >= 0, scene.geometry.tri_element[prim], -1)
    assert np.mean(expect == gb.element_id.reshape(-1)) >= 0.999
    covered = gb.covered
    assert np.all(np.isfinite(gb.position[covered])) and np.all(np.isinf(gb.depth[~covered]))
    # Normals are unit and face the viewer; albedo is the element's.
    n = gb.normal[covered]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", n, gb.view_dir[covered]) <= 1e-6)
    assert_rows(gb.albedo[gb.element_id == 1], [0.2, 0.8, 0.2], atol=1e-6)
    # Depth is along the view direction: position = eye + view_dir * depth / cos.
    cosine = gb.view_dir[covered] @ camera.forward
    recon = camera.position + gb.view_dir[covered] * (gb.depth[covered] / cosine)[:, None]
    np.testing.assert_allclose(recon, gb.position[covered], atol=1e-4)
    # Lit scene: reflections cast shadow rays and count them per source.
    res = tracer.trace_reflections(gb, [0], 5)
    assert res.records[0].rays > res.records[0].pixels
    assert tracer.rays_cast["primary"] == 64 * 48


def test_replay_raw_uses_the_same_rays():
    parts = [dict(mesh=quad(20.0), F=1.0), dict(mesh=sphere(1.0, (0, 1, 0), 3))]
    lights = Lights(distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    tracer = Tracer(parts_scene(parts, lights))
    gb = tracer.primary_gbuffer(look_at((0, 3, 6), (0, 0, 0)), 40, 30)
    tracer.record_rays = True
    res = tracer.trace_reflections(gb, [0], 5)
    rays, seconds = tracer.replay_raw()
    assert rays == res.rays and seconds > 0


def test_grazing_shading_normals_follow_the_rasterizer_rule():
    """Where the interpolated normal faces along the view ray (strongly tilted corner
    normals seen at grazing angles), the tracer uses the geometric normal like the
    rasterizer does, instead of flipping the shading normal into the surface."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer

    floor = quad(20.0)
    scene = parts_scene([{"mesh": floor}])
    tilt = np.array([0.8, 0.6, 0.0], np.float32)  # leans towards +X, away from the camera
    scene.geometry.corner_normals[:] = tilt
    cam = look_at([-8.0, 1.0, 0.0], [0.0, 0.0, 0.0])  # looking along +X, grazing
    w, h = 96, 72
    tracer = Tracer(scene, threads=1)
    rt = tracer.primary_gbuffer(cam, w, h)
    with Rasterizer(scene, w, h) as r:
        raster = r.render(cam)
    both = (rt.triangle_id >= 0) & (rt.triangle_id == raster.triangle_id)
    assert both.sum() > 500
    view = rt.view_dir[both]
    tilted_away = np.einsum("ij,j->i", view, tilt) >= 0.0
    assert tilted_away.mean() > 0.5  # the case under test is common in this view
    np.testing.assert_allclose(rt.normal[both], raster.normal[both], atol=1e-4)
    up = np.broadcast_to([0.0, 1.0, 0.0], (int(tilted_away.sum()), 3))
    np.testing.assert_allclose(rt.normal[both][tilted_away], up, atol=1e-6)
    assert np.all(np.einsum("ij,ij->i", rt.normal[both], view) < 0.0)  # faces the eye


def test_shadow_rays_only_within_light_range_and_facing():
    """No shadow ray for a point beyond a LocalLight's range or behind its normal; such
    pairs report 0 (the light adds nothing there) and the rest are traced."""
    from phrt_usd.engine import shading
    from phrt_usd.model.scene import LocalLight

    intensity = 2.0
    light = LocalLight(np.array([0.0, 1.0, 0.0]), np.full(3, intensity))
    reach = shading.light_ranges(Lights(local=[light]))[0]
    scene = parts_scene([{"mesh": quad(1.0, center=(0.0, -50.0, 0.0))}], Lights(local=[light]))
    tracer = Tracer(scene, threads=1)
    pts = np.array([[0.5 * reach, 0.0, 0.0], [1.5 * reach, 0.0, 0.0], [0.0, 0.0, 0.0]])
    normals = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    tracer.reset_counters()
    vis = tracer.shadow_visibility(pts, normals)
    np.testing.assert_array_equal(vis[:, 0], [1.0, 0.0, 0.0])
    assert tracer.rays_cast["shadow"] == 1
    pairs = np.array([[False], [True], [True]])
    assert tracer.shadow_visibility(pts, normals, pairs=pairs)[0, 0] == 0.0  # not asked


# ---------------------------------------------------------------- (9) animated geometry


class _CountingBVH:
    """Wraps an embreex scene and counts ``run`` calls (the tracer's Embree queries)."""

    def __init__(self, bvh):
        self.bvh, self.calls = bvh, 0

    def run(self, *args):
        self.calls += 1
        return self.bvh.run(*args)


def _single_bvh_cast(scene: Scene, o32: np.ndarray, d32: np.ndarray):
    """Reference: one embreex BVH of every triangle. Returns primID (n,) and t (n,)."""
    bvh = rtcs.EmbreeScene()
    verts = (scene.geometry.vertices - scene.origin).astype(np.float32)
    TriangleMesh(bvh, verts, scene.geometry.triangles.astype(np.int32))
    out = bvh.run(o32, d32, None, "INTERSECT", 1)
    occluded = bvh.run(o32, d32, np.full(len(o32), 3.0, np.float32), "OCCLUDED") >= 0
    return out["primID"], out["tfar"], occluded


def _hit_t(tracer: Tracer, prim, u, v, o32, d32) -> np.ndarray:
    """Ray parameter of hits rebuilt from the tracer's triangle table (inf for misses)."""
    g = tracer.bvh.table.frame[np.maximum(prim, 0)]
    p = g[:, 0] + u[:, None] * g[:, 1] + v[:, None] * g[:, 2]
    t = np.einsum("ij,ij->i", p - o32, d32.astype(np.float64))
    return np.where(prim >= 0, t, np.inf)


def test_moved_animated_element_is_hit_at_its_new_place_only():
    parts = [dict(mesh=quad(20.0)), dict(mesh=box_between((-0.5, 0.5, -0.5), (0.5, 1.5, 0.5)))]
    scene = parts_scene(parts)
    scene.elements[1].animated = True
    tracer = Tracer(scene, threads=1)
    static_bvh = tracer.bvh.static
    down = np.array([[0.0, 10.0, 0.0], [4.0, 10.0, 0.0]])  # above the box, above x = 4
    dirs = np.tile([0.0, -1.0, 0.0], (2, 1))
    hits = tracer.bvh.intersect(down - scene.origin, dirs)
    np.testing.assert_array_equal(scene.geometry.tri_element[hits.tri], [1, 0])
    box_vertices = np.unique(scene.geometry.triangles[scene.geometry.tri_element == 1])
    scene.geometry.vertices[box_vertices] += (4.0, 0.0, 0.0)
    scene.geometry_changed([1])  # the owner of the scene announces the move
    tracer.update_geometry(scene)
    assert not tracer.last_build_full and tracer.bvh.static is static_bvh  # static BVH kept
    hits = tracer.bvh.intersect(down - scene.origin, dirs)
    np.testing.assert_array_equal(scene.geometry.tri_element[hits.tri], [0, 1])
    # The box top is now at y = 1.5 above x = 4; the hit point is rebuilt there.
    rel, _, _, _, _ = tracer.surfaces.at(hits.tri, hits.u, hits.v, dirs)
    np.testing.assert_allclose(rel[1] + scene.origin, [4.0, 1.5, 0.0], atol=1e-5)
    np.testing.assert_allclose(rel[0] + scene.origin, [0.0, 0.0, 0.0], atol=1e-5)
    # Shadow rays see it at the new place only.
    lights = Lights(distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    scene.lights = lights
    vis = tracer.shadow_visibility(down * (1, 0, 1), np.tile([0.0, 1.0, 0.0], (2, 1)))
    np.testing.assert_array_equal(vis[:, 0], [1.0, 0.0])
    assert tracer.bvh.boundary.extent == pytest.approx(scene.extent, rel=1e-12)
    # A static element that moves is not missed: full rebuild.
    floor_vertices = np.unique(scene.geometry.triangles[scene.geometry.tri_element == 0])
    scene.geometry.vertices[floor_vertices] += (0.0, -1.0, 0.0)
    scene.geometry_changed([0])
    tracer.update_geometry(scene)
    assert tracer.last_build_full
    hits = tracer.bvh.intersect(down[:1] - scene.origin, dirs[:1])
    rel, _, _, _, _ = tracer.surfaces.at(hits.tri, hits.u, hits.v, dirs[:1])
    np.testing.assert_allclose(rel[0] + scene.origin, [0.0, -1.0, 0.0], atol=1e-5)


def test_static_only_scene_costs_one_query_per_batch():
    lights = Lights(distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    parts = [dict(mesh=quad(20.0), F=1.0), dict(mesh=sphere(1.0, (0, 1, 0), 3))]
    tracer = Tracer(parts_scene(parts, lights), threads=1)
    assert tracer.bvh.dynamic is None
    gb = tracer.primary_gbuffer(look_at((0, 3, 6), (0, 0, 0)), 40, 30)
    counter = _CountingBVH(tracer.bvh.static)
    tracer.bvh.static = counter
    tracer.record_rays = True
    tracer.trace_reflections(gb, [0], 5)
    assert counter.calls == len(tracer.last_rays) > 0
    tracer.update_geometry(tracer.scene)  # nothing moved: nothing rebuilt
    assert tracer.bvh.static is counter and not tracer.last_build_full


@pytest.mark.parametrize("seed", range(4))
def test_two_bvhs_match_a_single_bvh_on_random_scenes(seed):
    """Random triangle soups, random elements flagged animated: the tracer's two-BVH
    answers equal one BVH of everything (ids; t within float32 tolerance), also after
    the animated elements moved (incremental update)."""
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(6):
        n = int(rng.integers(20, 200))
        centre = rng.uniform(-1.0, 1.0, 3)
        corners = centre + rng.normal(scale=0.3, size=(n, 3, 3))
        mesh = trimesh.Trimesh(
            corners.reshape(-1, 3), np.arange(3 * n).reshape(n, 3), process=False
        )
        parts.append(dict(mesh=mesh))
    scene = parts_scene(parts)
    for e in scene.elements:
        e.animated = bool(rng.random() < 0.4)
    scene.elements[int(rng.integers(6))].animated = True
    # Seed 0 also covers the split over two threads (batches >= PARALLEL_MIN_RAYS).
    tracer = Tracer(scene, threads=2 if seed == 0 else 1)
    n_rays = 10000 if seed == 0 else 4000
    o32 = rng.uniform(-2.0, 2.0, (n_rays, 3)).astype(np.float32)
    d = rng.uniform(-1.0, 1.0, (n_rays, 3)) - o32  # towards the triangles
    d32 = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    for step in range(2):
        if step:  # move the animated elements; the tracer updates incrementally
            animated = [i for i, e in enumerate(scene.elements) if e.animated]
            moving = np.isin(scene.geometry.tri_element, animated)
            ids = np.unique(scene.geometry.triangles[moving])
            scene.geometry.vertices[ids] += rng.normal(scale=0.5, size=3)
            scene.geometry_changed(animated)
            tracer.update_geometry(scene)
            assert not tracer.last_build_full
        prim, u, v = tracer.bvh.run("INTERSECT", o32, d32)
        ref_prim, ref_t, ref_occluded = _single_bvh_cast(scene, o32, d32)
        t = _hit_t(tracer, prim, u, v, o32, d32)
        assert np.mean(ref_prim >= 0) > 0.3  # the rays do hit things
        np.testing.assert_array_equal(prim >= 0, ref_prim >= 0)
        hit = ref_prim >= 0
        # t rebuilt from float32 barycentrics on ~1 m triangles: ~1e-6 m of rounding.
        np.testing.assert_allclose(t[hit], ref_t[hit], rtol=1e-5, atol=2e-5)
        # Same triangle, except where two triangles are hit at the same t (a tie, which
        # either BVH may break either way; the t check above holds for those too).
        assert np.mean(prim[hit] == ref_prim[hit]) > 0.999
        occluded = tracer.bvh.run("OCCLUDED", o32, d32, np.full(n_rays, 3.0))
        np.testing.assert_array_equal(occluded, ref_occluded)


def test_records_count_every_ray_cast_per_source():
    """Per-source bookkeeping (vectorised, evaluated once per call): the records' rays
    add up to the result's and to the rays in the recorded Embree batches; the pixels
    to the traced pixels; hits only name reflectors; repeated calls on one G-buffer
    (the reflector-pixel cache) give the same answer as a fresh tracer."""
    lights = Lights(distant=[DistantLight(np.array([0.2, 1.0, 0.1]), np.ones(3))])
    parts = [
        dict(mesh=quad(20.0), F=0.6),
        dict(mesh=sphere(1.0, (0, 1, 0), 3), F=0.8),
        dict(mesh=box_between((2, 0, -1), (3, 2, 1)), F=1.0),
        dict(mesh=box_between((-3, 0, -1), (-2, 2, 1))),
    ]
    scene = parts_scene(parts, lights)
    tracer = Tracer(scene, threads=1)
    gb = tracer.primary_gbuffer(look_at((0.0, 4.0, 7.0), (0.0, 0.5, 0.0)), 64, 48)
    tracer.record_rays = True
    res = tracer.trace_reflections(gb, [0, 1, 2], 4)
    assert sum(r.rays for r in res.records) == res.rays
    assert res.rays == sum(len(o) for _, o, _, _ in tracer.last_rays)
    assert sum(r.pixels for r in res.records) == len(res.pixel_index)
    for rec in res.records:
        assert rec.pixels == int((gb.element_id == rec.source).sum())
        assert set(rec.hits) <= {0, 1, 2}
    again = tracer.trace_reflections(gb, [1, 2], 4)
    fresh = Tracer(scene, threads=1).trace_reflections(gb, [1, 2], 4)
    np.testing.assert_array_equal(again.pixel_index, fresh.pixel_index)
    np.testing.assert_allclose(again.radiance, fresh.radiance, atol=1e-6)
    assert [r.hits for r in again.records] == [r.hits for r in fresh.records]


def test_shading_split_over_threads_matches_one_thread(monkeypatch):
    """Local shading of large batches runs in chunks on the pool: same radiance, ray
    counts and shadow visibility as on one thread (threshold lowered to force it). The
    chunks' shadow batches, cast side by side, are kept for the raw replay as one batch
    per query: the same batches as on one thread (``Bvh.merge_recorded``)."""
    import phrt_usd.engine.trace.shadow_rays as tracer_module
    from phrt_usd.model.scene import LocalLight

    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.ones(3))],
        local=[LocalLight(np.array([1.0, 3.0, 1.0]), np.full(3, 20.0))],
    )
    parts = [
        dict(mesh=quad(20.0), F=0.5),
        dict(mesh=sphere(1.0, (0, 1, 0), 3), F=0.3, smooth=True),
        dict(mesh=box_between((2, 0, -1), (3, 2, 1))),
    ]
    scene = parts_scene(parts, lights)
    camera = look_at((0.0, 4.0, 7.0), (0.0, 0.5, 0.0))
    results = []
    for threads, threshold in ((1, tracer_module.PARALLEL_MIN_SHADE_RAYS), (2, 16)):
        monkeypatch.setattr(tracer_module, "PARALLEL_MIN_SHADE_RAYS", threshold)
        tracer = Tracer(scene, threads=threads)
        gb = tracer.primary_gbuffer(camera, 48, 36)
        tracer.reset_counters()
        tracer.record_rays = True
        res = tracer.trace_reflections(gb, [0, 1], 3)
        batches = [(q, len(o), t is None) for q, o, _, t in tracer.last_rays]
        pts = gb.position[gb.covered]
        vis = tracer.shadow_visibility(pts, gb.normal[gb.covered])
        batches.append([(q, len(o)) for q, o, _, _ in tracer.last_rays])
        results.append((res, dict(tracer.rays_cast), vis, batches))
    (one, cast_one, vis_one, rec_one), (two, cast_two, vis_two, rec_two) = results
    assert rec_two == rec_one and sum(n for _, n, _ in rec_one[:-1]) == one.rays
    np.testing.assert_allclose(two.radiance, one.radiance, atol=1e-6)
    assert two.rays == one.rays and cast_two == cast_one and cast_one["shadow"] > 0
    assert [r.rays for r in two.records] == [r.rays for r in one.records]
    np.testing.assert_array_equal(vis_two, vis_one)
