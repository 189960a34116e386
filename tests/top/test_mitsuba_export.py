"""Mitsuba export (peer benchmark only): geometry, materials, camera and light scaling.

Skipped when the optional ``bench`` extra (mitsuba) is not installed.
"""

from __future__ import annotations

import numpy as np
import pytest
from scenes import preview_shade

from phrt_usd.model.scene import (
    CameraFrame,
    DistantLight,
    DomeLight,
    Element,
    Geometry,
    Lights,
    MaterialTable,
    Scene,
)

mi = pytest.importorskip("mitsuba", reason="mitsuba is optional (the bench extra)")

from phrt_usd.bench import mitsuba_export  # noqa: E402  (after the skip)

#: Scene far from the world origin: the export must subtract it like our renderer does.
ORIGIN = np.array([1000.0, 0.0, -2000.0])


@pytest.fixture(autouse=True)
def _scalar_variant():
    mi.set_variant("scalar_rgb")


def _quad(center, half, axis_u, axis_v):
    """Two CCW triangles of a square (4 vertices, 2 triangles), world metres."""
    c = np.asarray(center, float)
    u, v = np.asarray(axis_u, float) * half, np.asarray(axis_v, float) * half
    verts = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def make_scene(quads, albedo, reflectivity, lights) -> Scene:
    """Quads facing +Z (in the z = const plane), element k = quad k."""
    verts, tris, tri_elem, elements = [], [], [], []
    for k, (center, half) in enumerate(quads):
        v, t = _quad(np.asarray(center) + ORIGIN, half, [1, 0, 0], [0, 1, 0])
        tris.append(t + 4 * k)
        verts.append(v)
        tri_elem += [k, k]
        elements.append(
            Element(
                f"/Quad{k}",
                reflectivity[k] > 0,
                1.0 if reflectivity[k] > 0 else 0.0,
                reflectivity[k],
                v.min(0),
                v.max(0),
            )
        )
    vertices = np.concatenate(verts)
    triangles = np.concatenate(tris)
    n = len(triangles)
    normals = np.broadcast_to(np.float32([0, 0, 1]), (n, 3, 3)).copy()
    corner_albedo = np.repeat(np.float32(albedo)[np.array(tri_elem)][:, None, :], 3, axis=1)
    geometry = Geometry(
        vertices,
        triangles,
        np.array(tri_elem, np.int32),
        np.zeros(n, np.int32),
        normals,
        corner_albedo,
    )
    materials = MaterialTable(
        diffuse=np.ones((1, 3), np.float32),
        metallic=np.zeros(1, np.float32),
        roughness=np.full(1, 0.5, np.float32),  # UsdPreviewSurface's fallback
        opacity=np.ones(1, np.float32),
        ior=np.full(1, 1.5, np.float32),
        emissive=np.zeros((1, 3), np.float32),
    )
    return Scene(elements, geometry, materials, lights, ORIGIN.copy())


def camera_at(eye, world_from_camera_rot=None) -> CameraFrame:
    m = np.eye(4)
    if world_from_camera_rot is not None:
        m[:3, :3] = world_from_camera_rot
    m[:3, 3] = np.asarray(eye, float) + ORIGIN
    return CameraFrame(m, focal_length=18.0, horizontal_aperture=36.0, near=0.01, far=100.0)


def _render(scene: Scene, camera: CameraFrame, w=16, h=12, spp=64) -> np.ndarray:
    mi_scene = mitsuba_export.load_scene(scene, camera, w, h)
    return np.asarray(mi.render(mi_scene, spp=spp, seed=1), dtype=np.float64)


def test_triangles_grouped_by_reflectivity_and_mirror_is_a_conductor():
    scene = make_scene(
        [((0, 0, 0), 1.0), ((3, 0, 0), 1.0), ((-3, 0, 0), 1.0)],
        albedo=[[0.5, 0.5, 0.5], [0.2, 0.3, 0.4], [0.9, 0.1, 0.1]],
        reflectivity=[0.0, 1.0, 0.5],
        lights=Lights(dome=DomeLight(np.array([0.2, 0.2, 0.2]))),
    )
    groups = mitsuba_export.mesh_groups(scene)
    # The non-reflector follows its material (None), the reflectors their authored F.
    assert [g.reflectivity for g in groups] == [None, 0.5, 1.0]
    assert sum(g.triangle_count for g in groups) == scene.geometry.triangle_count
    # Positions are render-relative: the world origin offset is gone.
    assert np.abs(np.concatenate([g.positions for g in groups])).max() < 10.0

    mi_scene = mitsuba_export.load_scene(scene, camera_at([0, 0, 5]), 32, 24)
    shapes = mi_scene.shapes()
    assert sum(s.face_count() for s in shapes) == scene.geometry.triangle_count
    # load_dict names each shape by its dict key, mesh_<k> for mesh_groups()[k].
    by_key = {s.id(): str(s.bsdf()) for s in shapes}
    bsdfs = {g.reflectivity: by_key[f"mesh_{k}"] for k, g in enumerate(groups)}
    assert "SmoothConductor" in bsdfs[1.0] and "BlendBSDF" not in bsdfs[1.0]
    assert "BlendBSDF" in bsdfs[0.5] and "SmoothConductor" in bsdfs[0.5]
    # The material's lobes summed: the GGX dielectric lobe and the diffuse one.
    assert "RoughConductor" in bsdfs[None] and "SmoothDiffuse" in bsdfs[None]
    assert "SmoothConductor" not in bsdfs[None]
    for text in bsdfs.values():
        assert "TwoSided" in text


def test_camera_to_world_maps_eye_and_pixel_directions():
    # A camera turned 30° about +Y, so handedness errors cannot cancel out.
    a = np.radians(30.0)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    eye = np.array([1.0, 2.0, 7.0])
    camera = camera_at(eye, rot)
    scene = make_scene(
        [((0, 0, 0), 1.0)], [[0.5, 0.5, 0.5]], [0.0], Lights(dome=DomeLight(np.ones(3)))
    )
    w, h = 40, 30
    to_world = mitsuba_export.sensor_to_world(camera, scene.origin)
    np.testing.assert_allclose(to_world @ [0, 0, 0, 1], [*eye, 1], atol=1e-12)

    sensor = mitsuba_export.load_scene(scene, camera, w, h).sensors()[0]
    origins, dirs = camera.pixel_rays(w, h)
    for row, col in [(0, 0), (15, 20), (29, 39), (3, 31)]:
        film = mi.Point2f((col + 0.5) / w, (row + 0.5) / h)
        ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
        # Mitsuba starts camera rays on the near plane (near = 0.01 m).
        assert np.linalg.norm(np.array(ray.o) - eye) < 2.0 * camera.near
        np.testing.assert_allclose(np.array(ray.d), dirs[row * w + col], atol=1e-5)


def _ours(camera: CameraFrame, w: int, h: int, albedo, sources=(), ambient=0.0) -> np.ndarray:
    """(3,) our shading's mean over the pixels of ``camera`` (looking at the z = 0 plane
    of the fallback material of ``albedo``): the numpy model of the BRDF per pixel."""
    origins, dirs = camera.pixel_rays(w, h)
    eye = origins[0] - ORIGIN
    points = eye + dirs * (-eye[2] / dirs[:, 2])[:, None]
    return np.mean([preview_shade(albedo, p, eye, sources=sources, ambient=ambient)
                    for p in points], axis=0)  # fmt: skip


def test_mirror_reflects_environment_and_material_matches_our_light_scale():
    """Constant dome c: a perfect mirror facing the camera shows c; a quad of the
    fallback material of albedo a shows our ambient term (its directional albedo x c).
    A unit DistantLight straight on it with a black dome shows our BRDF's π f n·l (no
    1/π: ``LAMBERT_SCALE``). Within 5 %: the export's lobes are ours face on, and
    brighter by a few % at the frame's corners (n·v 0.6; the module docstring). (0 < F < 1
    is left out: Mitsuba's own blendbsdf of a diffuse and a delta lobe is not F-linear in
    its path integrator, see the module docstring.)"""
    dome = np.array([0.3, 0.5, 0.7])
    albedo = np.array([0.8, 0.4, 0.2])
    camera = camera_at([0, 0, 3])
    w, h = 16, 12
    scene = make_scene([((0, 0, 0), 10.0)], [albedo], [1.0], Lights(dome=DomeLight(dome)))
    np.testing.assert_allclose(_render(scene, camera).reshape(-1, 3).mean(0), dome, rtol=0.05)
    scene = make_scene([((0, 0, 0), 10.0)], [albedo], [0.0], Lights(dome=DomeLight(dome)))
    expected = _ours(camera, w, h, albedo, ambient=dome)
    np.testing.assert_allclose(_render(scene, camera).reshape(-1, 3).mean(0), expected, rtol=0.05)

    sun = DistantLight(np.array([0.0, 0.0, 1.0]), np.array([1.0, 1.0, 1.0]))
    scene = make_scene(
        [((0, 0, 0), 10.0)], [albedo], [0.0], Lights(distant=[sun], dome=DomeLight(np.zeros(3)))
    )
    # Two emitters: next-event estimation picks one at random, hence the many samples.
    image = _render(scene, camera, spp=256)
    expected = _ours(camera, w, h, albedo, sources=[((0.0, 0.0, 1.0), 1.0)])
    np.testing.assert_allclose(image.reshape(-1, 3).mean(0), expected, rtol=0.05)


def test_missing_variant_or_bad_resolution_is_a_user_error():
    from phrt_usd.errors import PhrtError

    scene = make_scene([((0, 0, 0), 1.0)], [[0.5, 0.5, 0.5]], [0.0], Lights())
    with pytest.raises(PhrtError, match="resolution"):
        mitsuba_export.scene_dict(scene, camera_at([0, 0, 5]), 0, 10)
