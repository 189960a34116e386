"""What changed between frames: ``StageScene.set_time`` says which elements moved or
deformed and bumps ``Scene.versions``; the raster buffers, the BVH and the shadow maps
compare versions and update only the elements that changed, counted (not timed);
``FrameOutput.camera`` reprojects the frame's own pixels.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Gf, Usd, UsdGeom, Vt
from scenes import box, look_at, mirror_floor_stage, parts_scene, sphere

import phrt_usd
from phrt_usd.model.scene import DistantLight, ElementTriangles, Lights, LocalLight
from phrt_usd.usd.stage import read_stage

W, H = 96, 72
#: The large static scene: a grid of SPHERES x SPHERES icospheres (subdivision 3, 1280
#: triangles and 642 vertices each) and one box, the only element that moves.
SPHERES = 6
BOX_TRIANGLES, BOX_VERTICES = 12, 8  # trimesh's box


def _large_static_scene(animated_boxes: int = 1):
    """36 static spheres (46 080 triangles) on a 6 x 6 grid, then ``animated_boxes``
    boxes flagged animated (the last elements), a DistantLight and a SphereLight."""
    parts = [
        {"mesh": sphere(0.4, (1.2 * i - 3.0, 0.4, 1.2 * j - 3.0), 3)}
        for i in range(SPHERES)
        for j in range(SPHERES)
    ]
    parts += [
        {"mesh": box((0.5, 0.5, 0.5), (1.5 * k - 1.0, 1.5, 0.0))} for k in range(animated_boxes)
    ]
    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.ones(3))],
        local=[LocalLight(np.array([0.0, 4.0, 0.0]), np.full(3, 20.0))],
    )
    scene = parts_scene(parts, lights=lights)
    for e in scene.elements[len(parts) - animated_boxes :]:
        e.animated = True
    return scene


def _move(scene, element: int, offset) -> None:
    """Translate ``element``'s vertices by ``offset`` (3,) metres and announce it, as
    ``StageScene.set_time`` does."""
    geo = scene.geometry
    vertices = np.unique(geo.triangles[geo.tri_element == element])
    geo.vertices[vertices] += np.asarray(offset, dtype=np.float64)  # normals unchanged
    scene.geometry_changed([element])


@pytest.mark.slow
def test_moving_one_element_of_a_large_static_scene_updates_only_its_part():
    """One box moves among 46 080 static triangles: the rasterizer re-sends exactly its
    8 vertices and refreshes its 12 table rows, the tracer refreshes its 12 rows and
    rebuilds the animated BVH from its 12 triangles (the static BVH kept), and only the
    animated casters' shadow maps are rendered again. A second update without a change
    does nothing. Counts are exact: anything more is work on elements that did not move."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer
    from phrt_usd.engine.trace.tracer import Tracer

    scene = _large_static_scene()
    mover = len(scene.elements) - 1
    camera = look_at((0.0, 6.0, 8.0), (0.0, 0.5, 0.0))
    tracer = Tracer(scene, threads=1)
    static_bvh = tracer.bvh.static
    with Rasterizer(scene, W, H) as r:
        r.render(camera)
        r.shadow_maps()
        r.cube_maps()
        maps = r._maps
        rendered = dict(maps.maps_rendered)
        _move(scene, mover, (0.0, 0.0, 1.0))

        change = r.update_geometry(scene)
        tracer.update_geometry(scene)
        assert not change.rebuilt and change.elements.tolist() == [mover]
        assert change.vertices == BOX_VERTICES and len(change.moved_rows) == BOX_TRIANGLES
        update = tracer.bvh.last_update
        assert not update.full and update.elements.tolist() == [mover]
        assert update.table_rows == BOX_TRIANGLES and update.animated_triangles == BOX_TRIANGLES
        assert tracer.bvh.static is static_bvh
        r.shadow_maps()
        r.cube_maps()
        # One DistantLight and one SphereLight: one animated map each, no static one.
        assert maps.maps_rendered["static"] == rendered["static"]
        assert maps.maps_rendered["dynamic"] == rendered["dynamic"] + 2
        g = r.render(camera)

        # Nothing changed since: nothing is sent, refreshed or rendered.
        rendered = dict(maps.maps_rendered)
        assert r.update_geometry(scene).vertices == 0
        tracer.update_geometry(scene)
        assert tracer.bvh.last_update.table_rows == 0
        r.shadow_maps()
        r.cube_maps()
        assert maps.maps_rendered == rendered

    # The partial update gives what a fresh upload of the moved scene gives.
    with Rasterizer(scene, W, H) as fresh:
        np.testing.assert_array_equal(g.triangle_id, fresh.render(camera).triangle_id)
    o, d = camera.pixel_rays(W, H)
    hits = tracer.bvh.intersect(o - scene.origin, d)
    ref = Tracer(scene, threads=1).bvh.intersect(o - scene.origin, d)
    np.testing.assert_array_equal(hits.tri, ref.tri)


def test_two_animated_elements_far_apart_only_the_moved_one_is_refreshed():
    """Two animated boxes, the first and the last element, spheres between them in the
    vertex batch: moving one refreshes only its rows of the BVH's table (the animated
    BVH is rebuilt whole: both boxes); moving both re-sends each box's own 8 vertices,
    not the vertex range between them."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer
    from phrt_usd.engine.trace.tracer import Tracer

    parts = [{"mesh": box((0.5, 0.5, 0.5), (-3.0, 1.5, 0.0))}]
    parts += [{"mesh": sphere(0.4, (0.0, 0.4, 1.2 * k), 3)} for k in range(4)]
    parts += [{"mesh": box((0.5, 0.5, 0.5), (3.0, 1.5, 0.0))}]
    scene = parts_scene(parts)
    first, last = 0, len(parts) - 1
    scene.elements[first].animated = scene.elements[last].animated = True
    tracer = Tracer(scene, threads=1)
    with Rasterizer(scene, W, H) as r:
        _move(scene, last, (0.0, 1.0, 0.0))
        tracer.update_geometry(scene)
        update = tracer.bvh.last_update
        # The table rows of the moved box only; the animated BVH holds both boxes.
        assert update.table_rows == BOX_TRIANGLES and update.animated_triangles == 2 * BOX_TRIANGLES
        _move(scene, first, (0.0, -1.0, 0.0))
        change = r.update_geometry(scene)
        # Both boxes changed since the upload: their 16 vertices, none of the spheres'.
        assert change.elements.tolist() == [first, last] and change.vertices == 2 * BOX_VERTICES


@pytest.mark.slow
def test_a_flipped_winding_rebuilds_the_raster_buffers():
    """A changed element whose winding flipped (a transform's determinant changing
    sign) cannot be re-sent as vertices: the node is rebuilt, and the ids stay right."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer

    scene = _large_static_scene()
    mover = len(scene.elements) - 1
    camera = look_at((0.0, 6.0, 8.0), (0.0, 0.5, 0.0))
    with Rasterizer(scene, W, H) as r:
        rows = scene.geometry.tri_element == mover
        scene.geometry.triangles[rows] = scene.geometry.triangles[rows][:, [0, 2, 1]]
        scene.geometry_changed([mover])
        assert r.update_geometry(scene).rebuilt
        g = r.render(camera)
    with Rasterizer(scene, W, H) as fresh:
        np.testing.assert_array_equal(g.triangle_id, fresh.render(camera).triangle_id)


@pytest.mark.slow
def test_replaced_lights_rerender_only_the_maps_of_changed_lights():
    """New lights with the same directions and positions render nothing again; a
    DistantLight turned renders its two maps again, the SphereLight's cubes are kept."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer

    scene = _large_static_scene()
    with Rasterizer(scene, W, H) as r:
        r.shadow_maps()
        r.cube_maps()
        maps = r._maps
        rendered = dict(maps.maps_rendered)
        old = scene.lights
        scene.replace_lights(Lights(distant=list(old.distant), local=list(old.local)))
        assert scene.versions.lights == 1
        r.shadow_maps()
        r.cube_maps()
        assert maps.maps_rendered == rendered
        turned = DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))
        scene.replace_lights(Lights(distant=[turned], local=list(old.local)))
        r.shadow_maps()
        r.cube_maps()
        assert maps.maps_rendered == {k: v + 1 for k, v in rendered.items()}


def _animated_stage() -> Usd.Stage:
    """In memory, metres, Y up: /World/Still (a static quad), /World/Mover (a quad
    translated from x = 0 at time 0 to x = 10 at time 10), /World/Blob (a quad whose
    points double from time 0 to 10), and /World/Camera, translated from z = 5 at
    time 0 to z = 8 at time 5 and held there."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(10)
    quad = [(-1, 0, -1), (-1, 0, 1), (1, 0, 1), (1, 0, -1)]

    def mesh(path):
        m = UsdGeom.Mesh.Define(stage, path)
        m.CreatePointsAttr(quad)
        m.CreateFaceVertexCountsAttr([4])
        m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        return m

    mesh("/World/Still")
    mover = UsdGeom.Xform.Define(stage, "/World/Mover")
    op = mover.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0)
    op.Set(Gf.Vec3d(10, 0, 0), 10)
    mesh("/World/Mover/Quad")
    blob = mesh("/World/Blob")
    points = np.array(quad, dtype=np.float32)
    blob.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(points), 0)
    blob.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(2 * points), 10)
    camera = UsdGeom.Camera.Define(stage, "/World/Camera")
    cop = camera.AddTranslateOp()
    cop.Set(Gf.Vec3d(0, 1, 5), 0)
    cop.Set(Gf.Vec3d(0, 1, 8), 5)
    return stage


def test_set_time_says_what_moved_deformed_and_which_versions_changed():
    """A rigid transform is a move, new points a deformation; each change bumps the
    geometry version once and stamps the elements; the camera version follows the
    camera (held after time 5); the lights are never replaced by set_time."""
    ss = read_stage(_animated_stage())
    paths = [e.path for e in ss.scene.elements]
    names = ("/World/Still", "/World/Mover/Quad", "/World/Blob")
    still, mover, blob = (paths.index(p) for p in names)
    change = ss.set_time(2.0)
    assert change.moved.tolist() == [mover] and change.deformed.tolist() == [blob]
    assert change.changed.tolist() == sorted([mover, blob])
    assert (change.geometry_version, change.camera_version, change.lights_version) == (1, 1, 0)
    versions = ss.scene.versions
    assert versions.element_geometry[[still, mover, blob]].tolist() == [0, 1, 1]
    assert versions.changed_since(0).tolist() == sorted([mover, blob])
    assert versions.changed_since(1).tolist() == []
    again = ss.set_time(2.0)  # the same time: nothing
    assert not again and (again.geometry_version, again.camera_version) == (1, 1)
    ss.set_time(6.0)
    held = ss.set_time(7.0)  # the camera is held after time 5; the quads still move
    assert held.camera_version == 2 and held.geometry_version == 3


@pytest.mark.slow
def test_frame_output_carries_its_camera(tmp_path):
    """Projecting each covered pixel's world position with the frame's world-to-camera
    and projection lands on that pixel's centre, and camera-space -z is the G-buffer's
    depth: the matrices a later frame needs to reproject this one."""
    stage = mirror_floor_stage(tmp_path / "floor.usda", W, H)
    with phrt_usd.open(stage, mode="raster", resolution=(W, H)) as renderer:
        out = renderer.render(1.0)
    cam = out.camera
    assert cam.time == 1.0
    rows, cols = np.nonzero(out.gbuffer.covered)
    p = out.gbuffer.position[rows, cols]
    p_cam = p @ cam.camera_from_world[:3, :3].T + cam.camera_from_world[:3, 3]
    # Depth is stored as float32 metres (~5 m here): 1e-5 relative is float32 rounding.
    np.testing.assert_allclose(-p_cam[:, 2], out.gbuffer.depth[rows, cols], rtol=1e-5)
    clip = np.c_[p_cam, np.ones(len(p_cam))] @ cam.projection.T
    ndc = clip[:, :2] / clip[:, 3:]
    col = (ndc[:, 0] + 1.0) * 0.5 * W
    row = (1.0 - ndc[:, 1]) * 0.5 * H
    # The derived position is the pixel ray's hit, so it projects to the pixel centre up
    # to float64 rounding (1e-6 of a pixel leaves margin for the plane intersection).
    np.testing.assert_allclose(col, cols + 0.5, atol=1e-6)
    np.testing.assert_allclose(row, rows + 0.5, atol=1e-6)


def test_renderers_sharing_a_stage_each_catch_up_by_version():
    """Two renderers of one StageScene: the second, whose geometry is from the first
    time, renders the time the first one already set as a fresh renderer does (the
    SceneChange of its own set_time is empty; its versions are behind)."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer

    ss = read_stage(_animated_stage())
    camera = look_at((0.0, 12.0, 12.0), (4.0, 0.0, 0.0))
    with Rasterizer(ss.scene, W, H) as behind:
        assert ss.set_time(8.0)  # another holder moved the scene on
        assert not ss.set_time(8.0)  # nothing new for this one's own set_time
        change = behind.update_geometry(ss.scene)
        assert change.elements.tolist() == ss.scene.versions.changed_since(0).tolist()
        g = behind.render(camera)
    with Rasterizer(ss.scene, W, H) as fresh:
        np.testing.assert_array_equal(g.triangle_id, fresh.render(camera).triangle_id)


@settings(max_examples=50, deadline=None)
@given(
    n_elements=st.integers(1, 12),
    n_triangles=st.integers(0, 60),
    seed=st.integers(0, 2**31 - 1),
)
def test_element_triangles_finds_the_rows_of_changed_elements(n_elements, n_triangles, seed):
    """ElementTriangles.rows (O(their rows)) equals the pass over every triangle it
    replaces, for any element order (shuffled, empty elements, rows of no element)."""
    rng = np.random.default_rng(seed)
    tri_element = rng.integers(-1, n_elements + 1, size=n_triangles)
    changed = np.unique(rng.integers(0, n_elements, size=rng.integers(0, n_elements + 1)))
    expected = np.flatnonzero(np.isin(tri_element, changed))
    found = ElementTriangles(tri_element, n_elements).rows(changed)
    np.testing.assert_array_equal(found, expected)
    assert found.dtype == np.int64
