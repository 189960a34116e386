"""Rasterized G-buffer (phrt_usd.engine.raster.gbuffer) against Embree primary and shadow rays.

Scenes are built here from trimesh primitives (no USD). Reference rays go through the
same pixel centres (``CameraFrame.pixel_rays``), float32 after subtracting
``Scene.origin``, as the renderer's tracer would cast them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
from embreex import mesh_construction, rtcore_scene
from repo_paths import STAGES
from scenes import box, look_at, parts_scene, shaded_both_ways, sphere

from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.model.scene import CameraFrame, DistantLight, Lights, Scene
from phrt_usd.model.surface import sample_bilinear_wrap

W, H = 320, 240
#: Required share of covered pixels whose element id matches Embree (docs/design.md §3).
ID_AGREEMENT = 0.995
#: Required share of floor pixels whose shadow-map verdict matches Embree shadow rays.
SHADOW_AGREEMENT = 0.97
#: Two hits closer than this times the scene size are one point (coincident surfaces).
COINCIDENT = 1e-6
#: The same after shadow_visibility's refine (rays at uncertain points) on the paper stages.
REFINED_SHADOW_AGREEMENT = 0.99
#: Shadow-ray origin offset along the normal, metres (scene scale ~10 m).
RAY_OFFSET = 1e-3


# ---------------------------------------------------------------- scene construction


def floor_mesh(size=20.0, y=0.0, n=10) -> trimesh.Trimesh:
    """Open, one-sided grid of 2 n^2 triangles facing +Y."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    gx, gz = np.meshgrid(xs, xs)
    v = np.stack([gx.ravel(), np.full(gx.size, y), gz.ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    f = np.concatenate(
        [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
    )
    return trimesh.Trimesh(v, f, process=False)


def showcase_parts() -> list[dict]:
    """Floor, 4 boxes, 9 smooth spheres: ~47k triangles."""
    parts = [{"mesh": floor_mesh(), "albedo": (0.6, 0.6, 0.6), "path": "/World/floor"}]
    rng = np.random.default_rng(7)
    for i in range(4):
        c = (-4.0 + 2.7 * i, 0.75, -1.5 + (i % 2))
        reflectivity = 1.0 if i % 2 == 0 else None
        parts.append({"mesh": box((1.2, 1.5, 1.2), c), "albedo": rng.random(3), "F": reflectivity})
    for i in range(9):
        c = (-4.0 + (i % 3) * 3.5, 0.6 + 0.3 * (i // 3), 1.5 - 2.5 * (i // 3))
        parts.append(
            {
                "mesh": sphere(0.6, c),
                "albedo": rng.random(3),
                "smooth": True,
                "F": 1.0 if i % 3 == 1 else None,
            }
        )
    return parts


def showcase_camera(offset: np.ndarray) -> CameraFrame:
    return look_at(np.array([0.5, 4.0, 9.0]) + offset, np.array([0.0, 0.5, -0.5]) + offset)


# ---------------------------------------------------------------- Embree reference


class EmbreeReference:
    """Primary and shadow rays against the same triangles (rel space, float32)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        rel = scene.geometry.vertices - scene.origin
        tris = rel[scene.geometry.triangles].astype(np.float32)
        self.embree = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(self.embree, tris)

    def primary(self, camera: CameraFrame) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) int32 triangle ids (-1 miss) and (H, W, 3) float64 world hit points."""
        o, d = camera.pixel_rays(W, H)
        o_rel = (o - self.scene.origin).astype(np.float32)
        res = self.embree.run(o_rel, d.astype(np.float32), output=1)
        prim = np.asarray(res["primID"], dtype=np.int32)
        tfar = np.asarray(res["tfar"], dtype=np.float64)
        hit = o + np.where(prim[:, None] >= 0, tfar[:, None], 0.0) * d
        return prim.reshape(H, W), hit.reshape(H, W, 3)

    def occluded(
        self, points: np.ndarray, normals: np.ndarray, direction: np.ndarray
    ) -> np.ndarray:
        """(n,) bool: a shadow ray from each world point towards ``direction`` hits."""
        o = points - self.scene.origin + RAY_OFFSET * normals
        d = np.broadcast_to(direction / np.linalg.norm(direction), o.shape)
        prim = self.embree.run(o.astype(np.float32), d.astype(np.float32))
        return np.asarray(prim) >= 0


# ---------------------------------------------------------------- failure images


def save_ids(path: Path, ids: np.ndarray) -> None:
    """Write an id image (H, W) int as a false-colour PNG (background black)."""
    import OpenImageIO as oiio

    h = (ids.astype(np.int64) * 2654435761) & 0xFFFFFF
    rgb = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], axis=-1).astype(np.uint8)
    rgb[ids < 0] = 0
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(ids.shape[1], ids.shape[0], 3, oiio.UINT8))
    out.write_image(rgb)
    out.close()


def check_ids(
    scene,
    g: GBuffer,
    ref_tri: np.ndarray,
    tmp_path: Path,
    name: str,
    ref_hit: np.ndarray | None = None,
    save: bool = True,
) -> float:
    """Element-id agreement over pixels covered in either image; writes PNGs on failure.

    With ``ref_hit`` (Embree's world hit points), a pixel where both found a surface at
    the same point (coincident, z-fighting surfaces authored in the stage) counts as a
    tie, not a disagreement: which of two coplanar faces wins is arbitrary in both.
    """
    ref_el = np.where(ref_tri >= 0, scene.geometry.tri_element[np.maximum(ref_tri, 0)], -1)
    union = (ref_el >= 0) | (g.element_id >= 0)
    same = ref_el == g.element_id
    if ref_hit is not None:
        both = (ref_el >= 0) & (g.element_id >= 0)
        scale = np.linalg.norm(ref_hit - g.position, axis=-1)
        dist = np.linalg.norm(ref_hit - scene.origin, axis=-1) + scene.extent
        same |= both & (scale <= COINCIDENT * dist)
    agree = float(np.mean(same[union]))
    if agree < ID_AGREEMENT and save:
        save_ids(tmp_path / f"{name}_raster.png", g.element_id)
        save_ids(tmp_path / f"{name}_embree.png", ref_el)
        save_ids(tmp_path / f"{name}_diff.png", np.where(same, -1, 1))
    return agree


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def showcase():
    scene = parts_scene(showcase_parts())
    r = Rasterizer(scene, W, H)
    yield scene, r
    r.close()


# ---------------------------------------------------------------- tests


@pytest.mark.slow
def test_showcase_is_large_enough(showcase):
    scene, _ = showcase
    assert 45_000 <= scene.geometry.triangle_count <= 60_000


@pytest.mark.slow
@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_ids_positions_normals_match_embree(offset, tmp_path):
    off = np.array([offset, 0.5 * offset, -offset])
    scene = parts_scene(showcase_parts(), offset=off)
    cam = showcase_camera(off)
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
    ref_tri, ref_hit = EmbreeReference(scene).primary(cam)

    agree = check_ids(scene, g, ref_tri, tmp_path, f"showcase_{offset:g}")
    assert agree >= ID_AGREEMENT, f"element ids agree on {agree:.4%} (files in {tmp_path})"
    assert np.mean(g.covered) > 0.5  # the camera actually sees the scene

    # Positions equal the ray hits (same triangle) within a distance-scaled tolerance.
    same = (ref_tri == g.triangle_id) & (ref_tri >= 0)
    dist = np.linalg.norm(ref_hit - cam.position, axis=-1)
    err = np.linalg.norm(g.position - ref_hit, axis=-1)
    assert np.all(err[same] <= 1e-5 * dist[same] + 1e-6), float(err[same].max())

    # Depth is the view-space z of the position.
    cov = g.covered
    view_z = (g.position[cov] - cam.position) @ cam.forward
    np.testing.assert_allclose(g.depth[cov], view_z, rtol=1e-5)

    # Normals are unit and face the camera; view_dir is unit everywhere.
    n = g.normal[cov]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
    assert np.all(np.einsum("ij,ij->i", n, g.view_dir[cov]) < 0.0)
    np.testing.assert_allclose(np.linalg.norm(g.view_dir, axis=-1), 1.0, atol=1e-5)
    _, d = cam.pixel_rays(W, H)
    np.testing.assert_allclose(g.view_dir.reshape(-1, 3), d, atol=1e-6)

    # Albedo is the element's colour (constant per part here).
    colours = scene.geometry.corner_albedo[:, 0]
    np.testing.assert_allclose(g.albedo[cov], colours[g.triangle_id[cov]], atol=1e-6)


@pytest.mark.slow
def test_background_pixels(showcase):
    scene, r = showcase
    cam = look_at([0.0, 3.0, 9.0], [0.0, 8.0, 0.0])  # looking up: mostly sky
    g = r.render(cam)
    bg = ~g.covered
    assert bg.mean() > 0.3
    assert np.all(g.triangle_id[bg] == -1) and np.all(g.element_id[bg] == -1)
    assert np.all(np.isinf(g.depth[bg]))
    assert np.all(np.isfinite(g.depth[~bg])) and np.all(g.depth[~bg] > 0)
    for arr in (g.position, g.normal, g.albedo, g.view_dir):
        assert np.all(np.isfinite(arr))
    assert g.element_id.dtype == np.int32 and g.triangle_id.dtype == np.int32
    assert g.depth.dtype == np.float32 and g.position.dtype == np.float64


def test_mirror_visible_from_behind(tmp_path):
    """A one-sided quad is rasterized from its back too (no back-face culling)."""
    quad = floor_mesh(size=4.0, n=1)  # faces +Y
    scene = parts_scene([{"mesh": quad, "albedo": (1, 0, 0), "F": 1.0}])
    cam = look_at([0.3, -3.0, 0.2], [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0))
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
    assert g.covered.mean() > 0.2
    assert np.all(g.normal[g.covered][:, 1] < -0.99)  # flipped towards the camera below


@pytest.mark.slow
def test_an_open_rasterizer_is_not_collected_until_closed():
    """pyrender's finalisers delete GL objects in whatever context is current; a rasterizer
    collected during another's render would delete that one's framebuffers."""
    import gc
    import weakref

    quad = floor_mesh(size=4.0, n=1)
    scene = parts_scene([{"mesh": quad, "albedo": (1, 0, 0), "F": 1.0}])
    cam = look_at([0.3, 3.0, 0.2], [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0))
    with Rasterizer(scene, W, H) as a:
        dropped = weakref.ref(Rasterizer(scene, W, H))
        gc.collect()
        assert dropped() is not None  # still open: kept
        assert a.render(cam).covered.mean() > 0.2
        dropped().close()
    gc.collect()
    assert dropped() is None  # closed: collected as usual


@pytest.mark.slow
def test_random_triangle_soup_ids_exact(tmp_path):
    """70k random coloured triangles (ids above 2^16 use the third byte): every id the
    rasterizer writes names a triangle that really contains the pixel's ray, and ids
    agree with Embree."""
    rng = np.random.default_rng(3)
    n = 70_000
    centres = rng.uniform(-2.0, 2.0, (n, 1, 3))
    v = (centres + rng.normal(0.0, 0.08, (n, 3, 3))).reshape(-1, 3)
    mesh = trimesh.Trimesh(v, np.arange(3 * n).reshape(n, 3), process=False)
    scene = parts_scene([{"mesh": mesh, "albedo": (0.5, 0.5, 0.5)}])
    colours = rng.random((n, 3)).astype(np.float32)
    scene.geometry.corner_albedo = np.repeat(colours[:, None, :], 3, axis=1)
    cam = look_at([0.4, 0.3, 7.0], [0.0, 0.0, 0.0])
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
    ref_tri, _ = EmbreeReference(scene).primary(cam)

    cov = g.covered
    tid = g.triangle_id[cov]
    assert tid.max() >= 2**16
    # Unclamped barycentrics of the ray / triangle-plane hit: inside up to edge rounding.
    o, d = cam.pixel_rays(W, H)
    tri = scene.geometry.vertices[scene.geometry.triangles[tid]] - scene.origin
    dr = d[cov.ravel()]
    orel = o[0] - scene.origin
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pv = np.cross(dr, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    s = orel - tri[:, 0]
    u = np.einsum("ij,ij->i", s, pv) / det
    q = np.cross(s, e1)
    vv = np.einsum("ij,ij->i", dr, q) / det
    slack = 1e-3  # barycentric units: rasterization vs. float64 at shared edges
    inside = (u >= -slack) & (vv >= -slack) & (u + vv <= 1 + slack)
    assert inside.mean() >= 0.999, f"{(~inside).sum()} pixels carry a wrong triangle id"

    union = cov | (ref_tri >= 0)
    agree = float(np.mean(g.triangle_id[union] == ref_tri[union]))
    if agree < ID_AGREEMENT:
        save_ids(tmp_path / "soup_raster.png", g.triangle_id)
        save_ids(tmp_path / "soup_embree.png", ref_tri)
    assert agree >= ID_AGREEMENT, f"triangle ids agree on {agree:.4%} (files in {tmp_path})"
    np.testing.assert_allclose(g.albedo[cov], colours[tid], atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("animated", [False, True])
def test_shadow_map_matches_shadow_rays(animated, tmp_path):
    """Floor pixels lit / shadowed as Embree shadow rays say (with the sphere flagged
    animated, its shadow comes from the animated casters' own map)."""
    light_dir = np.array([0.35, 1.0, 0.25])
    light_dir /= np.linalg.norm(light_dir)
    lights = Lights(distant=[DistantLight(direction=light_dir, radiance=np.ones(3))])
    for offset in (np.zeros(3), np.array([1e6, -2e5, 3e6])):
        parts = [
            {"mesh": floor_mesh(size=8.0), "albedo": (0.6, 0.6, 0.6), "path": "/World/floor"},
            {"mesh": box((3.5, 0.3, 2.5), (0.0, 2.0, 0.0)), "albedo": (0.8, 0.2, 0.2)},
            {"mesh": sphere(0.7, (2.5, 0.7, -1.0), 3), "albedo": (0.2, 0.8, 0.2), "smooth": True},
        ]
        scene = parts_scene(parts, offset=offset, lights=lights)
        scene.elements[2].animated = animated
        cam = look_at(np.array([0.0, 7.0, 8.0]) + offset, np.array([0.0, 0.0, 0.0]) + offset)
        with Rasterizer(scene, W, H) as r:
            g = r.render(cam)
            floor = g.element_id == 0
            vis = r.shadow_visibility(g.position[floor], g.normal[floor])
            assert vis.shape == (int(floor.sum()), 1) and vis.dtype == np.float32
            assert np.all((vis >= 0.0) & (vis <= 1.0))
            # Cached: a second query gives the same answer without re-rendering.
            static, dynamic = r.shadow_maps()[0]
            assert (dynamic is not None) == animated
            assert r.shadow_maps()[0][0] is static
        ref = EmbreeReference(scene)
        occ = ref.occluded(g.position[floor], g.normal[floor], light_dir)
        lit_map = vis[:, 0] >= 0.5
        agree = float(np.mean(lit_map == ~occ))
        assert 0.05 < occ.mean() < 0.6  # the test actually has shadow on the floor
        if agree < SHADOW_AGREEMENT:
            img = np.full((H, W), -1)
            img[floor] = lit_map.astype(int) + 2 * occ.astype(int)
            save_ids(tmp_path / "shadow_disagreement.png", img)
        print(f"offset {offset}: shadowed {occ.mean():.2%}, agreement {agree:.4%}")
        assert agree >= SHADOW_AGREEMENT, f"offset {offset}: shadow agreement {agree:.4%}"
        # Refined: uncertain points (edges) go to shadow rays; the rest stays mapped.
        with Rasterizer(scene, W, H) as r:
            r.render(cam)
            calls = []

            def refine(p, n, pairs, ref=ref, calls=calls):
                calls.append(len(p))
                return (~ref.occluded(p, n, light_dir)).astype(np.float32)[:, None]

            vis = r.shadow_visibility(g.position[floor], g.normal[floor], refine=refine)
            assert calls == [r.last_refined] and 0 < r.last_refined < 0.2 * len(occ)
        refined_agree = float(np.mean((vis[:, 0] >= 0.5) == ~occ))
        assert refined_agree >= max(agree, 0.999), f"refined agreement {refined_agree:.4%}"


@pytest.mark.slow
@pytest.mark.parametrize("animated", [False, True])
def test_update_geometry_moves_prims_and_invalidates_shadows(animated, tmp_path):
    """Moving a box re-rasterizes it and moves its shadow. Flagged animated, the box
    casts into its own small map and the static map is kept."""
    light = DistantLight(direction=np.array([0.0, 1.0, 0.0]), radiance=np.ones(3))
    parts = [
        {"mesh": floor_mesh(size=12.0), "albedo": (0.6, 0.6, 0.6)},
        {"mesh": box((1.0, 1.0, 1.0), (-2.0, 1.5, 0.0)), "albedo": (0.8, 0.2, 0.2)},
        {"mesh": box((1.0, 1.0, 1.0), (0.0, 1.5, -3.0)), "albedo": (0.2, 0.2, 0.8)},
    ]
    scene = parts_scene(parts, lights=Lights(distant=[light]))
    scene.elements[1].animated = animated
    cam = look_at([0.0, 6.0, 8.0], [0.0, 0.0, 0.0])
    below = np.array([[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, -3.0]])
    up = np.array([[0.0, 1.0, 0.0]] * 3)
    with Rasterizer(scene, W, H) as r:
        r.render(cam)
        np.testing.assert_array_equal(r.shadow_visibility(below, up)[:, 0], [0, 1, 0])
        static_before = r.shadow_maps()[0][0]
        assert (r.shadow_maps()[0][1] is not None) == animated
        box_vertices = scene.geometry.triangles[scene.geometry.tri_element == 1].ravel()
        scene.geometry.vertices[np.unique(box_vertices)] += np.array([4.0, 0.0, 0.0])
        scene.geometry_changed([1])  # the owner of the scene announces the move
        r.update_geometry(scene)
        g = r.render(cam)
        np.testing.assert_array_equal(r.shadow_visibility(below, up)[:, 0], [1, 0, 0])
        assert (r.shadow_maps()[0][0] is static_before) == animated
    ref_tri, _ = EmbreeReference(scene).primary(cam)
    agree = check_ids(scene, g, ref_tri, tmp_path, "moved")
    assert agree >= ID_AGREEMENT


def test_box_extremum_matches_a_window_reference():
    """Against the plain definition (scipy.ndimage's ``minimum_filter`` with ``mode="nearest"``):
    the extremum over the (2r+1)^2 window, the edge pixels repeated outwards."""
    from phrt_usd.engine.raster.shadow_maps import _box_extremum

    a = np.random.default_rng(1).random((37, 23)).astype(np.float32)
    a[a > 0.9] = np.inf
    for r in (1, 2):
        windows = np.lib.stride_tricks.sliding_window_view(
            np.pad(a, r, mode="edge"), (2 * r + 1, 2 * r + 1)
        )
        expect_min = windows.min(axis=(2, 3))
        np.testing.assert_array_equal(_box_extremum(a, r, np.minimum), expect_min)
        expect_max = windows.max(axis=(2, 3))
        np.testing.assert_array_equal(_box_extremum(a, r, np.maximum), expect_max)


def test_texture_lookup():
    tex = np.arange(12, dtype=np.float32).reshape(2, 2, 3)  # row 0 = top
    # Texel centres: u = 0.25 / 0.75, v = 0.75 (top row) / 0.25 (bottom row).
    uv = np.array([[0.25, 0.75], [0.75, 0.75], [0.25, 0.25], [0.75, 0.25], [1.25, -0.25]])
    out = sample_bilinear_wrap(tex, uv)
    np.testing.assert_array_equal(out[:4], tex.reshape(4, 3))
    np.testing.assert_array_equal(out[4], tex[0, 0])  # wrapped: (1.25, -0.25) ≡ (0.25, 0.75)
    assert np.all(np.isfinite(sample_bilinear_wrap(tex, np.array([[np.nan, 1e300]]))))


def test_textured_albedo_follows_uv():
    """A quad with a texture: the G-buffer albedo is the texture at the pixel's uv."""
    rng = np.random.default_rng(5)
    tex = rng.random((8, 8, 3)).astype(np.float32)
    quad = trimesh.Trimesh(
        [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False
    )
    scene = parts_scene([{"mesh": quad, "albedo": (1, 1, 1)}])
    geo = scene.geometry
    geo.corner_uv = ((geo.vertices[geo.triangles][:, :, :2] + 1.0) / 2.0).astype(np.float32)
    scene.materials.textures = [tex]
    cam = look_at([0.1, 0.2, 3.0], [0.0, 0.0, 0.0])
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
    cov = g.covered
    assert cov.mean() > 0.2
    uv = (g.position[cov][:, :2] + 1.0) / 2.0
    np.testing.assert_allclose(g.albedo[cov], sample_bilinear_wrap(tex, uv), atol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize(
    "case", ["empty", "beyond_far", "inside_box", "near0_far_inf", "tiny_far_away"]
)
def test_extreme_inputs_stay_finite(case, tmp_path):
    """No NaN/Inf (except background depth) and sane ids for degenerate set-ups."""
    parts = [{"mesh": box((2.0, 2.0, 2.0), (0.0, 0.0, 0.0)), "albedo": (0.5, 0.5, 0.5)}]
    offset = np.zeros(3)
    cam = look_at([0.0, 1.0, 6.0], [0.0, 0.0, 0.0])
    if case == "tiny_far_away":  # 1 mm box 1e6 m from the origin
        offset = np.array([1e6, 1e6, -1e6])
        parts = [{"mesh": box((1e-3,) * 3, (0.0, 0.0, 0.0)), "albedo": (0.5, 0.5, 0.5)}]
        cam = look_at(offset + [0.0, 1e-3, 4e-3], offset)
        cam.near = 1e-5
    scene = parts_scene(parts, offset=offset)
    if case == "empty":
        geo = scene.geometry
        geo.vertices = np.zeros((0, 3))
        geo.triangles = np.zeros((0, 3), np.int64)
        geo.tri_element = geo.tri_material = np.zeros(0, np.int32)
        geo.corner_normals = geo.corner_albedo = np.zeros((0, 3, 3), np.float32)
    elif case == "beyond_far":
        cam.far = 1.0  # the box is 5 m away
    elif case == "inside_box":
        cam = look_at([0.2, 0.1, 0.3], [1.0, 0.0, 0.0])
    elif case == "near0_far_inf":
        cam.near, cam.far = 0.0, np.inf
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
        vis = r.shadow_visibility(np.zeros((2, 3)), np.zeros((2, 3)))
    assert vis.shape == (2, 0)
    for arr in (g.position, g.normal, g.albedo, g.view_dir):
        assert np.all(np.isfinite(arr))
    assert np.all(np.isinf(g.depth[~g.covered])) and np.all(np.isfinite(g.depth[g.covered]))
    if case in ("empty", "beyond_far"):
        assert not g.covered.any()
    else:
        assert g.covered.mean() > (0.99 if case == "inside_box" else 0.01)
        ref_tri, _ = EmbreeReference(scene).primary(cam)
        assert check_ids(scene, g, ref_tri, tmp_path, case) >= ID_AGREEMENT


@pytest.mark.slow
def test_degenerate_camera_is_a_user_error(showcase):
    _, r = showcase
    cam = look_at([0.0, 1.0, 6.0], [0.0, 0.0, 0.0])
    cam.horizontal_aperture = 0.0
    with pytest.raises(PhrtError, match="field of view"):
        r.render(cam)


PAPER_STAGES = ["farm", "sewer"]
#: Paper stages authored without coincident (z-fighting) surfaces: their ids must agree
#: with Embree strictly, with no allowance for ties between coplanar faces.
STRICT_ID_STAGES = {"sewer"}


@pytest.mark.slow
@pytest.mark.parametrize("name", PAPER_STAGES)
def test_paper_stage_ids(name, tmp_path):
    """Element ids agree with Embree on a few frames of the paper stages."""
    path = STAGES / f"{name}.usda"
    if not path.exists():
        pytest.skip(f"{path} not there yet")
    try:
        from phrt_usd.usd.stage import open_stage
    except ImportError:
        pytest.skip("phrt_usd.usd.stage not there yet")
    stage = open_stage(str(path))
    t0, t1 = stage.frame_range
    with Rasterizer(stage.scene, W, H) as r:
        for t in np.linspace(t0, t1, 4):
            stage.set_time(float(t))
            r.update_geometry(stage.scene)  # nothing to do when no version changed
            cam = stage.camera(float(t))
            g = r.render(cam)
            assert g.covered.mean() > 0.05, f"{name} t={t}: camera sees almost nothing"
            ref_tri, ref_hit = EmbreeReference(stage.scene).primary(cam)
            strict = check_ids(stage.scene, g, ref_tri, tmp_path, name, save=False)
            agree = check_ids(stage.scene, g, ref_tri, tmp_path, f"{name}_{t:g}", ref_hit)
            print(f"{name} t={t:.1f}: ids agree {strict:.4%} strict, {agree:.4%} with ties")
            if name in STRICT_ID_STAGES:
                agree = check_ids(stage.scene, g, ref_tri, tmp_path, f"{name}_{t:g}_strict")
            assert agree >= ID_AGREEMENT, f"{name} t={t}: ids agree on {agree:.4%}"
            for k, light in enumerate(stage.scene.lights.distant):
                # Pixels facing the light: the shadow map must agree with shadow rays.
                facing = g.covered & (np.einsum("hwc,c->hw", g.normal, light.direction) > 0.05)
                vis = r.shadow_visibility(g.position[facing], g.normal[facing])[:, k]
                occ = EmbreeReference(stage.scene).occluded(
                    g.position[facing], g.normal[facing], light.direction
                )
                shadow_agree = float(np.mean((vis >= 0.5) == ~occ))
                assert shadow_agree >= SHADOW_AGREEMENT, f"{name} t={t}: {shadow_agree:.4%}"
                ref = EmbreeReference(stage.scene)

                def refine(p, n, pairs, ref=ref, lights=stage.scene.lights.distant):
                    occluded = [ref.occluded(p, n, lt.direction) for lt in lights]
                    return (~np.stack(occluded, axis=1)).astype(np.float32)

                vis = r.shadow_visibility(g.position[facing], g.normal[facing], refine)[:, k]
                refined = float(np.mean((vis >= 0.5) == ~occ))
                print(
                    f"{name} t={t:.1f} light {k}: shadows agree {shadow_agree:.4%}, "
                    f"{refined:.4%} with {r.last_refined} points refined by rays"
                )
                assert refined >= REFINED_SHADOW_AGREEMENT


if os.environ.get("PYOPENGL_PLATFORM", "osmesa") != "osmesa":  # pragma: no cover
    pytestmark = pytest.mark.skip("these tests expect the OSMesa platform")


@pytest.mark.slow
@pytest.mark.parametrize("offset", [np.zeros(3), np.array([1e6, -2e5, 3e6])])
def test_local_light_cube_shadows_match_shadow_rays(offset, tmp_path):
    """A point light over a table: the cube maps alone agree with Embree shadow rays on
    most of the floor, the GPU lookup agrees with its numpy reference, and with
    ``refine`` resolving the uncertain pairs the answer is (nearly) exact. Pairs out
    of the light's range or facing away get 0, as the tracer reports them."""
    from phrt_usd.engine import shading
    from phrt_usd.engine.trace.tracer import Tracer
    from phrt_usd.model.scene import LocalLight

    light = LocalLight(np.array([0.6, 3.5, 0.4]) + offset, np.full(3, 20.0))
    far_light = LocalLight(np.array([0.0, 1.0, -30.0]) + offset, np.full(3, 0.02))
    lights = Lights(local=[light, far_light])
    parts = [
        {"mesh": floor_mesh(size=10.0), "albedo": (0.6, 0.6, 0.6), "path": "/World/floor"},
        {"mesh": box((2.0, 0.1, 1.5), (0.0, 1.5, 0.0)), "albedo": (0.8, 0.2, 0.2)},
        {"mesh": box((0.05, 1.5, 0.05), (-1.5, 0.75, 1.0)), "albedo": (0.2, 0.8, 0.2)},
    ]
    scene = parts_scene(parts, offset=offset, lights=lights)
    cam = look_at(np.array([0.0, 7.0, 8.0]) + offset, offset)
    tracer = Tracer(scene, threads=1)
    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
        floor = g.element_id == 0
        pos, nrm = g.position[floor], g.normal[floor]
        vis = r.shadow_visibility(pos, nrm)
        assert vis.shape == (len(pos), 2) and vis.dtype == np.float32
        cube_static, cube_dynamic = r.cube_maps()[0]
        assert cube_dynamic is None and r.cube_maps()[0][0] is cube_static  # cached
        r.cube_lookup_on_gpu = False
        vis_numpy = r.shadow_visibility(pos, nrm)
        r.cube_lookup_on_gpu = True
        calls = []

        def refine(p, n, pairs):
            calls.append(int(pairs.sum()))
            return tracer.shadow_visibility(p, n, pairs=pairs)

        refined = r.shadow_visibility(pos, nrm, refine=refine)
        assert calls == [r.last_refined_pairs] and 0 < r.last_refined < 0.2 * len(pos)
    exact = tracer.shadow_visibility(pos, nrm)
    occ = exact[:, 0] < 0.5
    assert 0.05 < occ.mean() < 0.6  # the table does shadow the floor
    agree = float(np.mean((vis[:, 0] >= 0.5) == ~occ))
    if agree < SHADOW_AGREEMENT:
        img = np.full((H, W), -1)
        img[floor] = (vis[:, 0] >= 0.5).astype(int) + 2 * occ.astype(int)
        save_ids(tmp_path / "cube_disagreement.png", img)
    print(
        f"cube shadows: {occ.mean():.2%} shadowed, agreement {agree:.4%}, {r.last_refined} refined"
    )
    assert agree >= SHADOW_AGREEMENT, f"cube-map shadows agree on {agree:.4%}"
    assert np.mean(np.abs(vis - vis_numpy) < 1e-6) >= 0.999  # GPU = numpy reference
    assert float(np.mean((refined[:, 0] >= 0.5) == ~occ)) >= 0.999
    # The far, dim light reaches only 1 m: nothing on this floor is in its range.
    reach = shading.light_ranges(lights)[1]
    assert np.all(np.linalg.norm(pos - far_light.position, axis=1) > reach)
    assert np.all(vis[:, 1] == 0.0) and np.all(exact[:, 1] == 0.0)
    # Facing away from the light: 0 without any lookup answer to the contrary.
    down = np.tile([0.0, -1.0, 0.0], (len(pos), 1))
    with Rasterizer(scene, W, H) as r:
        assert np.all(r.shadow_visibility(pos, down)[:, 0] == 0.0)
    assert np.all(tracer.shadow_visibility(pos, down)[:, 0] == 0.0)


@pytest.mark.slow
@pytest.mark.parametrize("use_refine", [False, True])
@pytest.mark.parametrize("with_local", [True, False])
def test_gpu_light_terms_shade_like_the_visibility_matrix(use_refine, with_local):
    """Lights shaded in the GPU lookup pass (``light_terms`` + ``shade_local``'s
    ``lit_sums``) give the same colours as the (n, L) visibility matrix shaded in
    numpy: a DistantLight with and without LocalLights, with and without shadow-ray
    refinement."""
    from phrt_usd.engine.trace.tracer import Tracer
    from phrt_usd.model.scene import LocalLight

    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.array([0.8, 0.8, 0.7]))],
        local=[
            LocalLight(np.array([0.6, 3.5, 0.4]), np.array([20.0, 15.0, 10.0])),
            LocalLight(np.array([-2.0, 1.0, 1.5]), np.full(3, 5.0)),
        ]
        if with_local
        else [],
    )
    parts = [
        {"mesh": floor_mesh(size=10.0), "albedo": (0.6, 0.6, 0.6)},
        {"mesh": box((2.0, 0.1, 1.5), (0.0, 1.5, 0.0)), "albedo": (0.8, 0.2, 0.2)},
        {"mesh": box((0.05, 1.5, 0.05), (-1.5, 0.75, 1.0)), "albedo": (0.2, 0.8, 0.2)},
    ]
    scene = parts_scene(parts, lights=lights)
    cam = look_at(np.array([0.0, 7.0, 8.0]), np.zeros(3))
    tracer = Tracer(scene, threads=1)

    def refine(p, n, pairs):
        return tracer.shadow_visibility(p, n, pairs=pairs)

    with Rasterizer(scene, W, H) as r:
        g = r.render(cam)
        cov = g.covered
        pos, nrm = g.position[cov], g.normal[cov]
        albedo, view = g.albedo[cov], g.view_dir[cov]
        fix = refine if use_refine else None
        vis = r.shadow_visibility(pos, nrm, refine=fix)
        surface = fallback_surface(albedo)
        terms = r.light_terms(pos, nrm, -view, refine=fix, surface=surface)
    assert terms.distant_visibility.shape == (len(pos), 1)
    assert (len(terms.local_pairs.point) > 0) == with_local
    # The table's shadow edge is uncertain in the map: resolved outside the sums.
    assert np.count_nonzero(terms.distant_visibility) > 0
    expected, got = shaded_both_ways(pos, nrm, surface, view, lights, vis, terms)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


def test_local_light_animated_caster_updates_its_cube_only():
    """An animated box casts into its own cube map: moving it re-renders that one, keeps
    the static cube, and moves the shadow."""
    from phrt_usd.model.scene import LocalLight

    light = LocalLight(np.array([0.0, 4.0, 0.0]), np.full(3, 10.0))
    parts = [
        {"mesh": floor_mesh(size=12.0), "albedo": (0.6, 0.6, 0.6)},
        {"mesh": box((1.0, 1.0, 1.0), (-2.0, 1.5, 0.0)), "albedo": (0.8, 0.2, 0.2)},
    ]
    scene = parts_scene(parts, lights=Lights(local=[light]))
    scene.elements[1].animated = True
    # Straight below the box as seen from the light, before and after it moves by +4 m x.
    below = np.array([[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    up = np.tile([0.0, 1.0, 0.0], (2, 1))
    with Rasterizer(scene, W, H) as r:
        np.testing.assert_array_equal(r.shadow_visibility(below, up)[:, 0], [0, 1])
        static_before, dynamic_before = r.cube_maps()[0]
        assert static_before is not None and dynamic_before is not None
        box_vertices = scene.geometry.triangles[scene.geometry.tri_element == 1].ravel()
        scene.geometry.vertices[np.unique(box_vertices)] += np.array([4.0, 0.0, 0.0])
        scene.geometry_changed([1])  # the owner of the scene announces the move
        r.update_geometry(scene)
        np.testing.assert_array_equal(r.shadow_visibility(below, up)[:, 0], [1, 0])
        static_after, dynamic_after = r.cube_maps()[0]
        assert static_after is static_before and dynamic_after is not dynamic_before
