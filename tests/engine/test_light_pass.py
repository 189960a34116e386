"""The GPU lookup pass (``raster.light_pass``, ``shaders/cube_lookup.frag``) against its
numpy reference (``shadow_maps.cube_pair_visibility``) on the pairs whose answer needs
no cube texel: out of the light's range, facing away, nearer than the cube's near plane
(the shader reads no texel of its own for them) and next to ones that do."""

from __future__ import annotations

import os

import numpy as np
import pytest
from scenes import box, parts_scene, shaded_both_ways

from phrt_usd.engine import shading
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.model.scene import Lights, LocalLight

if os.environ.get("PYOPENGL_PLATFORM", "osmesa") != "osmesa":  # pragma: no cover
    pytestmark = pytest.mark.skip("these tests expect the OSMesa platform")


@pytest.mark.parametrize("offset", [np.zeros(3), np.array([1e6, -2e5, 3e6])])
def test_texel_free_pairs_match_the_numpy_reference(offset):
    """Points all around a light over a slab, at every distance from well inside the
    cube's near plane to beyond the light's range, with normals towards and away from
    it: the GPU codes equal the numpy lookup's (up to float32 rounding at the test's
    boundaries), and the texel-free pairs get exactly 1 (near plane) or 0."""
    light = LocalLight(np.array([0.0, 2.0, 0.0]) + offset, np.full(3, 2.0))
    lights = Lights(local=[light])
    parts = [
        {"mesh": box((8.0, 0.2, 8.0), (0.0, -0.1, 0.0)), "albedo": (0.5, 0.5, 0.5)},
        {"mesh": box((0.4, 0.4, 0.4), (0.5, 1.0, 0.0)), "albedo": (0.8, 0.2, 0.2)},
    ]
    scene = parts_scene(parts, offset=offset, lights=lights)
    reach = float(shading.light_ranges(lights)[0])  # 10 m
    rng = np.random.default_rng(7)
    n = 20_000
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distance = np.exp(rng.uniform(np.log(1e-6), np.log(2.0 * reach), n))
    positions = light.position + directions * distance[:, None]
    towards = np.where(rng.uniform(size=n) < 0.8, -1.0, 1.0)  # 80 % face the light
    tilt = rng.normal(scale=0.3, size=(n, 3))
    normals = towards[:, None] * directions + tilt
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    with Rasterizer(scene, 64, 48) as r:
        r.cube_lookup_on_gpu = True
        gpu = r.map_visibility(positions, normals, filtered=False)
        r.cube_lookup_on_gpu = False
        ref = r.map_visibility(positions, normals, filtered=False)
        near = r.cube_maps()[0][0].near
    assert np.mean(gpu.visibility == ref.visibility) >= 0.999
    assert np.mean(gpu.uncertain == ref.uncertain) >= 0.999
    facing = np.einsum("ij,ij->i", normals, light.position - positions) > 0.0
    out = ~facing | (distance >= reach)
    assert out.any() and np.all(gpu.visibility[out, 0] == 0.0)
    inside_near = facing & (distance < near)  # w <= |v| < near: nothing rendered there
    assert inside_near.any() and np.all(gpu.visibility[inside_near, 0] == 1.0)
    assert not gpu.uncertain[out | inside_near].any()


@pytest.mark.slow
def test_many_lights_shade_like_the_visibility_matrix():
    """20 LocalLights (two passes of the shading lookup, which walks each fragment's
    lights as bit masks) around a slab with casters, some out of reach of parts of it,
    some below it: the GPU's sums over the lit pairs plus the undecided pairs' PCF shade
    as the (n, L) visibility matrix does in numpy."""
    from scenes import look_at

    rng = np.random.default_rng(11)
    positions = rng.uniform([-4.0, -1.0, -4.0], [4.0, 3.0, 4.0], size=(20, 3))
    power = np.exp(rng.uniform(np.log(0.05), np.log(3.0), 20))  # ranges ~1.5 to 12 m
    pairs = zip(positions, power, strict=True)
    lights = Lights(local=[LocalLight(p, np.full(3, s)) for p, s in pairs])
    parts = [
        {"mesh": box((8.0, 0.2, 8.0), (0.0, -0.1, 0.0)), "albedo": (0.6, 0.6, 0.6)},
        {"mesh": box((1.0, 0.8, 1.0), (0.5, 0.4, 0.0)), "albedo": (0.8, 0.2, 0.2)},
        {"mesh": box((0.1, 1.5, 0.1), (-1.5, 0.75, 1.0)), "albedo": (0.2, 0.8, 0.2)},
    ]
    scene = parts_scene(parts, lights=lights)
    cam = look_at(np.array([0.0, 6.0, 7.0]), np.zeros(3))
    with Rasterizer(scene, 96, 72) as r:
        r.cube_lookup_on_gpu = True
        g = r.render(cam)
        cov = g.covered
        pos, nrm = g.position[cov], g.normal[cov]
        albedo, view = g.albedo[cov], g.view_dir[cov]
        vis = r.shadow_visibility(pos, nrm)
        surface = fallback_surface(albedo)  # UsdPreviewSurface's fallbacks: a highlight
        terms = r.light_terms(pos, nrm, -view, surface=surface)
    lit = vis > 0.0
    assert lit.sum(axis=1).min() < lit.sum(axis=1).max()  # points differ in their lights
    assert 0.2 < lit.mean() < 0.8
    expected, got = shaded_both_ways(pos, nrm, surface, view, lights, vis, terms)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


def test_float32_rows_are_sent_as_they_are():
    """Normals and view directions that already are the texture (float32 rows, as many
    as the texture's texels: a fully covered frame) are uploaded without packing, with
    the same results as float64 ones that are packed."""
    from phrt_usd.engine.raster import light_pass

    light = LocalLight(np.array([0.0, 2.0, 0.0]), np.full(3, 2.0))
    parts = [
        {"mesh": box((8.0, 0.2, 8.0), (0.0, -0.1, 0.0)), "albedo": (0.5, 0.5, 0.5)},
        {"mesh": box((0.4, 0.4, 0.4), (0.5, 1.0, 0.0)), "albedo": (0.8, 0.2, 0.2)},
    ]
    scene = parts_scene(parts, lights=Lights(local=[light]))
    rng = np.random.default_rng(5)
    n = 64 * 40  # whole rows of the 64-pixel-wide frame's lookup texture
    positions = np.column_stack(
        [rng.uniform(-4.0, 4.0, n), np.zeros(n), rng.uniform(-4.0, 4.0, n)]
    )
    normals = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (n, 1))
    to_eye = rng.normal(size=(n, 3)).astype(np.float32)
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    assert light_pass._texels_already(normals, None, (64, 40))
    assert not light_pass._texels_already(normals.astype(np.float64), None, (64, 40))
    assert not light_pass._texels_already(normals[:-1], None, (64, 40))
    with Rasterizer(scene, 64, 48) as r:
        r.cube_lookup_on_gpu = True
        direct = r.map_light_terms(positions, normals, to_eye)
        packed = r.map_light_terms(
            positions, normals.astype(np.float64), to_eye.astype(np.float64)
        )
    # The light is above every point: each is lit, its colour read through to_eye.
    assert np.count_nonzero(direct.lit_sums[:, :3]) > n
    np.testing.assert_array_equal(direct.lit_sums, packed.lit_sums)
    np.testing.assert_array_equal(direct.rows, packed.rows)
