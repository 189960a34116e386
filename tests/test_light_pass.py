"""The GPU lookup pass (``raster.light_pass``, ``shaders/cube_lookup.frag``) against its
numpy reference (``shadow_maps.cube_pair_visibility``) on the pairs whose answer needs
no cube texel: out of the light's range, facing away, nearer than the cube's near plane
(the shader reads no texel of its own for them) and next to ones that do."""

from __future__ import annotations

import os

import numpy as np
import pytest
from scenes import box, parts_scene

from phrt_usd.model.scene import Lights, LocalLight
from phrt_usd.render import shading
from phrt_usd.render.raster.rasterizer import Rasterizer

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
