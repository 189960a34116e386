"""Lights cost by where they reach: the compiled shading walks, per block of points,
only the LocalLights whose range reaches the block (``shade_kernels.block_lights``),
and the GPU light pass, per tile of points, only those reaching the tile
(``light_pass.LOOKUP_TILE``, ``shade_kernels.tile_lights``). Both leave out only lights
that add exactly 0 (``shading.range_window`` is 0 at and beyond the range): the image is
the full evaluation's, checked here on a floor lit by a grid of 64 sphere lights (the
bench stage's layout, ``phrt_usd.bench.light_grid``) and at analytic points."""

from __future__ import annotations

import numpy as np
import pytest
from scenes import box, look_at, parts_scene, preview_shade, shaded_both_ways
from shading_reference import shade_chunk

from phrt_usd.bench import light_grid
from phrt_usd.engine import shade_kernels, shading
from phrt_usd.engine.raster import light_pass, map_lighting
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.model.scene import Lights, LocalLight

#: Lights on the grid of the tests' stage (8 x 8, as the bench's largest).
GRID_LIGHTS = 64


def _grid_lights(n: int = GRID_LIGHTS) -> tuple[Lights, float]:
    """``n`` LocalLights laid out as ``light_grid_stage``'s (radiance LIGHT_RADIANCE,
    LIGHT_HEIGHT above the floor y = 0, LIGHT_SPACING apart, slightly tinted), and the
    half side of their floor."""
    row = light_grid.lights_a_row(n)
    half = light_grid.LIGHT_SPACING * row / 2.0
    lights = []
    for k in range(n):
        x = -half + light_grid.LIGHT_SPACING * (k % row + 0.5)
        z = -half + light_grid.LIGHT_SPACING * (k // row + 0.5)
        tint = np.array([1.0, 0.9 + 0.1 * (k % 2), 0.8 + 0.2 * (k % 3 == 0)])
        lights.append(LocalLight(np.array([x, light_grid.LIGHT_HEIGHT, z]),
                                 light_grid.LIGHT_RADIANCE * tint))  # fmt: skip
    return Lights(local=lights), half


def _floor_points(half: float, side: int) -> tuple[np.ndarray, ...]:
    """``side`` x ``side`` points of the floor y = 0 in row order (as a G-buffer seen from
    above has them), slightly tilted normals, views from 20 m above, a glossy surface."""
    rng = np.random.default_rng(7)
    u = np.linspace(-half, half, side)
    x, z = np.meshgrid(u, u)
    pos = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    nrm = np.array([0.0, 1.0, 0.0]) + rng.normal(0.0, 0.1, (len(pos), 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = pos - np.array([0.0, 20.0, 0.0])
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    surface = fallback_surface(rng.uniform(0.2, 0.9, (len(pos), 3)))
    return pos, nrm.astype(np.float32), surface, view.astype(np.float32)


def test_culled_kernel_is_the_full_evaluation_on_a_grid_of_lights():
    """The compiled shading of a floor under 64 lights, points in row order (blocks of
    neighbours: each walks a few lights), equals bit for bit the same points shaded
    shuffled (each block's box spans the floor: every light walked, the unculled
    evaluation), and the numpy model of every (point, light) pair within float32
    rounding."""
    lights, half = _grid_lights()
    pos, nrm, surface, view = _floor_points(half, 200)
    culled = shading.shade_local(pos, nrm, surface, view, np.zeros(3), lights, None)
    order = np.random.default_rng(1).permutation(len(pos))
    every = np.empty_like(culled)
    every[order] = shading.shade_local(
        pos[order], nrm[order], surface[order], view[order], np.zeros(3), lights, None
    )
    # Same lights, same order, same float64 sums per point: the same bits.
    np.testing.assert_array_equal(culled, every)
    reference = shade_chunk(pos, nrm, surface, view, np.zeros(3), lights, None)
    # float32 model (numpy) against float64 sums (kernel): a few float32 ulps.
    np.testing.assert_allclose(culled, reference, rtol=2e-5, atol=1e-7)
    # The blocks in row order do cull: a block of 32 neighbours reaches a few lights.
    table = shading.light_table(lights)
    reached, box_scratch = np.empty(GRID_LIGHTS, np.int64), np.empty((2, 3))
    counts = [
        shade_kernels.block_lights(pos, i, min(i + 32, len(pos)), table.l_position,
                                   table.l_range, box_scratch, reached)
        for i in range(0, len(pos), 32)
    ]  # fmt: skip
    assert np.mean(counts) < 8  # of 64: ~3-5 reach a 2.6 m strip of the floor


def test_a_point_under_one_light_is_shaded_as_the_model_says():
    """Directly below a grid light, 1 m down: only that light reaches the point (its
    neighbours are sqrt(8² + 1²) m away, beyond their 8 m range), whose E is radiance x
    window / d²; a point just beyond every light's range gets the ambient alone."""
    lights, half = _grid_lights()
    light = lights.local[27]
    r = float(shading.light_ranges(lights)[27])
    below = light.position - np.array([0.0, light_grid.LIGHT_HEIGHT, 0.0])
    # Just beyond the range of the light, straight down (and of every other).
    beyond = light.position - np.array([0.0, r + 1e-6, 0.0])
    eye = below + np.array([0.3, 5.0, 0.2])
    pos = np.array([below, beyond])
    nrm = np.array([[0.0, 1.0, 0.0]] * 2, np.float32)
    view = (pos - eye) / np.linalg.norm(pos - eye, axis=1, keepdims=True)
    got = shading.shade_local(pos, nrm, np.full((2, 3), 0.5), view, np.zeros(3), lights, None)
    ambient = shading.ambient_radiance(lights)
    d = light_grid.LIGHT_HEIGHT
    e = light.radiance * float(shading.range_window(np.array([d]), r)[0]) / d**2
    want = preview_shade(0.5, below, eye, (0.0, 1.0, 0.0), [((0.0, 1.0, 0.0), e)], ambient)
    np.testing.assert_allclose(got[0], want, rtol=1e-5)  # float32 output of the model
    want_beyond = preview_shade(0.5, beyond, eye, (0.0, 1.0, 0.0), [], ambient)
    np.testing.assert_allclose(got[1], want_beyond, rtol=1e-5)


def _grid_scene():
    """The floor under 64 grid lights with a pillar beside each (shadows to decide)."""
    lights, half = _grid_lights()
    parts = [{"mesh": box((2 * half, 0.2, 2 * half), (0.0, -0.1, 0.0)),
              "albedo": (0.6, 0.6, 0.6)}]  # fmt: skip
    for li in lights.local:
        centre = li.position + np.array([0.8, 0.75 - light_grid.LIGHT_HEIGHT, 0.5])
        parts.append({"mesh": box((0.3, 1.5, 0.3), centre), "albedo": (0.7, 0.5, 0.3)})
    return parts_scene(parts, lights=lights), half


@pytest.mark.slow
def test_tiled_light_pass_is_the_full_evaluation(monkeypatch):
    """The GPU pass with each tile's lights equals the pass with every light in every
    tile (one tile: four passes of 16) within float32 rounding, and the (n, L)
    visibility matrix shaded in numpy within the GPU's own tolerance."""
    scene, half = _grid_scene()
    cam = look_at(np.array([0.0, 1.8 * half, 0.01]), np.zeros(3), focal=24.0)  # the floor
    with Rasterizer(scene, 320, 240) as r:
        r.cube_lookup_on_gpu = True
        g = r.render(cam)
        cov = g.covered
        pos, nrm, view = g.position[cov], g.normal[cov], g.view_dir[cov]
        surface = fallback_surface(g.albedo[cov])
        vis = r.shadow_visibility(pos, nrm)
        slots = []
        lookup = light_pass.LightPass.lookup

        def spy(self, *args, **kwargs):
            result = lookup(self, *args, **kwargs)
            slots.append(result[2].slots)
            return result

        monkeypatch.setattr(map_lighting.LightPass, "lookup", spy)
        tiled = r.light_terms(pos, nrm, -view, surface=surface)
        # One tile holding every point: every light walked everywhere.
        monkeypatch.setattr(light_pass, "LOOKUP_TILE", 1 << 30)
        monkeypatch.setattr(light_pass, "LOOKUP_TILE_JUMP", np.inf)
        whole = r.light_terms(pos, nrm, -view, surface=surface)
    # Tiled: each tile holds the few lights reaching it, one pass of 16 slots for all;
    # whole: every light in the one tile, four passes.
    assert slots[0].shape[1] <= light_pass.LOOKUP_LIGHTS_PER_PASS
    assert np.mean((slots[0] >= 0).sum(axis=1)) < 8
    assert slots[1].shape == (1, GRID_LIGHTS)
    lights = scene.lights
    culled = shading.shade_local(pos, nrm, surface, view, np.zeros(3), lights,
                                 tiled.distant_visibility, local_pairs=tiled.local_pairs,
                                 lit_sums=tiled.lit_sums)  # fmt: skip
    full = shading.shade_local(pos, nrm, surface, view, np.zeros(3), lights,
                               whole.distant_visibility, local_pairs=whole.local_pairs,
                               lit_sums=whole.lit_sums)  # fmt: skip
    assert float(full.max()) > 0.05 and tiled.local_pairs is not None
    # The same lit pairs summed in other groupings (one pass against four, float32):
    # a few ulps of the brightest pixel.
    np.testing.assert_allclose(culled, full, rtol=1e-5, atol=1e-6 * float(full.max()))
    # Against the (n, L) visibility matrix in numpy: the GPU's BRDF in float32
    # (tests/engine/test_light_pass.py's tolerance).
    expected, _ = shaded_both_ways(pos, nrm, surface, view, lights, vis, whole)
    np.testing.assert_allclose(culled, expected, rtol=1e-4, atol=1e-5)
