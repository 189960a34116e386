"""One BRDF in raster and trace: UsdPreviewSurface's (``model/preview_surface.py``)
shaded by the GPU light pass (GLSL, ``shaders/cube_lookup.frag``) and by the compiled
kernels at traced hits, at analytic inputs and at the pixels of a dielectric, a metal
and a clear-coated sphere."""

from __future__ import annotations

import os

import numpy as np
import pytest
import shading_reference as ref
from scenes import look_at, parts_scene, quad, sphere

from phrt_usd import kernels
from phrt_usd.engine import lighting
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.engine.trace.hit_lighting import HitLighting
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model import preview_surface as ps
from phrt_usd.model import surface
from phrt_usd.model.scene import DistantLight, DomeLight, Lights, LocalLight

if os.environ.get("PYOPENGL_PLATFORM", "osmesa") != "osmesa":  # pragma: no cover
    pytest.skip("needs the OSMesa raster", allow_module_level=True)

_SHADE = kernels.load("phrt_usd.engine.shade_kernels")

#: GPU (float32 GLSL) against compiled (float64) shading of the same lit pair: the light
#: pass's own tolerance (``tests/engine/test_light_pass.py``): a few float32 ulps of
#: each term. The GGX peak's denominator (n·h)² (a² - 1) + 1 ~ a² loses ~1.2e-7 / a²
#: of itself to float32 rounding of n·h near 1 (twice in D): below 3e-5 from roughness
#: MIN_TESTED_ROUGHNESS (a² = 0.0081) on, what the lobes of these tests have.
GPU_RTOL, GPU_ATOL = 1e-4, 1e-5
MIN_TESTED_ROUGHNESS = 0.3

#: The spheres: (name, metallic, roughness, clearcoat, clearcoatRoughness, albedo).
SPHERES = [
    ("dielectric", 0.0, 0.4, 0.0, 0.01, (0.7, 0.2, 0.1)),
    ("metal", 1.0, 0.3, 0.0, 0.01, (0.95, 0.64, 0.54)),
    ("clearcoat", 0.0, 0.6, 1.0, MIN_TESTED_ROUGHNESS, (0.1, 0.3, 0.7)),
]


def _surfaces(k: int) -> np.ndarray:
    """k surface rows spanning the inputs: both workflows, metals, clear coats, every
    roughness from MIN_TESTED_ROUGHNESS (a fixed draw)."""
    rng = np.random.default_rng(4)
    return ps.surface_columns(
        rng.uniform(0.0, 1.0, (k, 3)), rng.uniform(0.0, 1.0, k), rng.uniform(size=k) < 0.3,
        rng.uniform(0.0, 1.0, (k, 3)), rng.uniform(MIN_TESTED_ROUGHNESS, 1.0, k),
        np.where(rng.uniform(size=k) < 0.5, 1.0, 0.0), rng.uniform(MIN_TESTED_ROUGHNESS, 1.0, k),
        rng.uniform(1.1, 2.5, k), 1.0, 1.0,
    )  # fmt: skip


def test_glsl_brdf_is_the_compiled_brdf_at_analytic_inputs():
    """The light pass's GLSL BRDF and ``shade_kernels.brdf_cos`` on the same 4096 (point,
    light) pairs: random surfaces, normals, eyes and one DistantLight per call, the
    points far outside every shadow map (lit): equal within GPU_RTOL / GPU_ATOL."""
    rng = np.random.default_rng(9)
    k = 4096
    light_dir = np.array([0.3, 0.9, 0.2])
    light_dir /= np.linalg.norm(light_dir)
    lights = Lights(distant=[DistantLight(light_dir, np.array([1.0, 0.8, 0.6]))])
    scene = parts_scene([dict(mesh=quad(2.0))], lights=lights)
    normals = rng.normal(size=(k, 3))
    normals[:, 1] = np.abs(normals[:, 1])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    to_eye = rng.normal(size=(k, 3))
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    flip = np.einsum("ij,ij->i", to_eye, normals) < 0.05
    to_eye[flip] = np.abs(to_eye[flip]) * 0.0 + normals[flip]  # the eye above the surface
    positions = np.column_stack([np.full(k, 1000.0), np.arange(k) * 0.01, np.zeros(k)])
    surface = _surfaces(k)
    with Rasterizer(scene, 64, 64) as r:
        r.cube_lookup_on_gpu = True
        terms = r.map_light_terms(
            positions, normals.astype(np.float32), to_eye.astype(np.float32), surface=surface
        )
    assert not len(terms.rows)  # every pair decided (lit): all of it in the GPU's sums
    want = np.empty((k, 3))
    _SHADE.brdf_kernel(surface, normals, to_eye, np.tile(light_dir, (k, 1)),
                       ps.specular_albedo_table(), ps.MIN_ROUGHNESS, want)  # fmt: skip
    want *= [1.0, 0.8, 0.6]
    assert float(want.max()) > 1.0  # highlights among them
    np.testing.assert_allclose(terms.lit_sums[:, :3], want, rtol=GPU_RTOL, atol=GPU_ATOL)
    # And the numpy form of the model (tests/shading_reference.py) agrees with both.
    numpy_brdf = ref.brdf_cos(surface, normals, to_eye, np.tile(light_dir, (k, 1)))
    np.testing.assert_allclose(numpy_brdf * [1.0, 0.8, 0.6], want, rtol=1e-5, atol=1e-7)


def _sphere_scene():
    """Three spheres side by side (SPHERES), a DistantLight and a LocalLight that light
    them without shadowing one another, a dim dome."""
    parts = [
        dict(mesh=sphere(0.5, (x, 0.0, 0.0), subdivisions=5), albedo=albedo, smooth=True)
        for x, (_, _, _, _, _, albedo) in zip((-1.2, 0.0, 1.2), SPHERES, strict=True)
    ]
    lights = Lights(
        distant=[DistantLight(np.array([0.2, 0.6, 0.77]), np.full(3, 1.5))],
        local=[LocalLight(np.array([0.5, 1.5, 2.5]), np.full(3, 8.0))],
        dome=DomeLight(color=np.array([0.2, 0.25, 0.3])),
    )
    scene = parts_scene(parts, lights=lights)
    m = scene.materials
    m.metallic[:] = [s[1] for s in SPHERES]
    m.roughness[:] = [s[2] for s in SPHERES]
    m.clearcoat = np.array([s[3] for s in SPHERES], np.float32)
    m.clearcoat_roughness = np.array([s[4] for s in SPHERES], np.float32)
    return scene


@pytest.mark.slow
@pytest.mark.parametrize("index", range(3), ids=[s[0] for s in SPHERES])
def test_raster_and_trace_shade_a_sphere_alike(index):
    """The raster's shading of a sphere's pixels (G-buffer, GPU light pass, compiled
    ambient) and the tracer's shading of the same points as hits of rays through those
    pixels (their triangle and barycentrics, shadow rays, the compiled BRDF:
    ``hit_lighting``'s exact evaluation) agree within GPU_RTOL / GPU_ATOL at the pixels
    inside the sphere's silhouette (a pixel off it: the two see its edge at different
    sub-pixel positions); both equal the numpy BRDF there."""
    scene = _sphere_scene()
    camera = look_at(np.array([0.0, 0.4, 4.0]), np.array([0.0, 0.0, 0.0]))
    w, h = 160, 80
    tracer = Tracer(scene, threads=1)
    with Rasterizer(scene, w, h) as r:
        r.cube_lookup_on_gpu = True
        gb = r.render(camera)
        raster, _ = lighting.shade_gbuffer(gb, scene, "raster", r, None)
        cov = gb.covered
        mapped = np.zeros((h, w, 2), np.float32)
        mapped[cov] = r.shadow_visibility(gb.position[cov], gb.normal[cov])
    # The sphere's pixels whose 3 x 3 neighbourhood is all on it (no silhouette) and that
    # both lights light, by the maps and by shadow rays alike (the terminator's band,
    # where a map and a ray may disagree, is the hit-lighting rule's error:
    # docs/hit-lighting.md).
    traced_vis = np.zeros((h, w, 2), np.float32)
    traced_vis[cov] = tracer.shadow_visibility(gb.position[cov], gb.normal[cov])
    on = (gb.element_id == index) & np.all(mapped == 1.0, 2) & np.all(traced_vis == 1.0, 2)
    inner = on.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= np.roll(np.roll(on, dy, 0), dx, 1)
    rows, cols = np.nonzero(inner)
    assert len(rows) > 300
    exact = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
    exact.exact = True
    # The same points as hits: the pixel's triangle at the barycentrics of its point,
    # seen along the pixel's ray.
    tri = gb.triangle_id[rows, cols].astype(np.int64)
    geo = scene.geometry
    weights = surface.point_weights(geo.vertices, geo.triangles, tri, gb.position[rows, cols])
    u, v = weights[:, 1].copy(), weights[:, 2].copy()
    d32 = np.ascontiguousarray(gb.view_dir[rows, cols], np.float32)
    pos, ng, ns = tracer.surfaces.geometry(tri, u, v, d32)
    # A pixel's point a hair outside its triangle (its ray meets the plane past an edge,
    # the G-buffer keeps that point) is clamped onto it here: those few are left out.
    same = np.all(np.abs(pos + tracer.bvh.boundary.origin - gb.position[rows, cols]) < 1e-6, 1)
    assert same.mean() > 0.98
    rows, cols, tri, u, v, d32 = rows[same], cols[same], tri[same], u[same], v[same], d32[same]
    pos, ng, ns = pos[same], ng[same], ns[same]
    traced, _, _ = exact.shade(tri, u, v, pos, ng, ns, d32, tracer._relative_lights(),
                               np.arange(len(tri)))  # fmt: skip
    np.testing.assert_allclose(traced, raster[rows, cols], rtol=GPU_RTOL, atol=GPU_ATOL)
    # The numpy BRDF at the G-buffer's points: the same values.
    surf = lighting.gbuffer_surface(scene, tri, gb.element_id[rows, cols],
                                    gb.albedo[rows, cols], gb.position[rows, cols])  # fmt: skip
    want = ref.shade_chunk(gb.position[rows, cols], gb.normal[rows, cols], surf,
                           gb.view_dir[rows, cols], np.zeros(3), scene.lights, None)  # fmt: skip
    np.testing.assert_allclose(raster[rows, cols], want, rtol=GPU_RTOL, atol=GPU_ATOL)
    assert float(want.max()) > 0.5  # lit, highlights among them
