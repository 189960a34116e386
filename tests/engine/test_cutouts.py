"""UsdPreviewSurface texture inputs and opacityThreshold cut-outs, end to end: stages made
here with textures written here (OpenImageIO), rendered in raster, hybrid and rt, checked
at pixels whose right colour follows from the geometry.

The stage (``textured_stages.cutout_stage``): a blue wall behind a red quad whose
material is a cut-out (opacityThreshold 0.5), its opacity a texture's alpha: 0 in the
left half (x < 0), 1 in the right half; a DistantLight tilted 30° about +Y, so a present
point of the quad at x shadows the wall at x + tan 30°.
"""

from __future__ import annotations

import numpy as np
import pytest
from image_thresholds import HYBRID_VS_RT_FLIP
from pxr import UsdGeom
from textured_stages import (
    HEIGHT,
    QUAD,
    WALL,
    WIDTH,
    cutout_stage,
    pixel_at,
    render_first_frame,
    write_image,
)

from phrt_usd.usd.stage import read_stage


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    stage = cutout_stage(tmp_path_factory.mktemp("cutout"))
    return {mode: render_first_frame(stage, mode) for mode in ("raster", "rt", "hybrid")}


@pytest.fixture(scope="module")
def without_quad(tmp_path_factory):
    """The same stage with the quad invisible: the wall as nothing shadows it."""
    stage = cutout_stage(tmp_path_factory.mktemp("bare"))
    UsdGeom.Imageable(stage.GetPrimAtPath("/Quad")).MakeInvisible()
    return {mode: render_first_frame(stage, mode) for mode in ("raster", "rt", "hybrid")}


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt", "hybrid"])
def test_wall_shows_through_the_cut_half_and_the_quad_in_the_other(renders, mode):
    out, camera = renders[mode]
    g = out.gbuffer
    hole = pixel_at(camera, (-0.5, 0.0, 0.0))  # on the quad's cut-out (alpha 0) half
    solid = pixel_at(camera, (0.5, 0.0, 0.0))  # on its opaque half
    wall_id = 0  # elements in stage order: /Wall, then /Quad
    assert g.element_id[hole] == wall_id and g.element_id[solid] == 1
    # Albedo exactly the materials' (no texture on the colour): the wall through the
    # hole, the quad's red where it is there.
    np.testing.assert_allclose(g.albedo[hole], WALL, atol=1e-6)
    np.testing.assert_allclose(g.albedo[solid], QUAD, atol=1e-6)
    # The hole's depth is the wall's: 6 m from the camera (view depth along -z).
    assert abs(float(g.depth[hole]) - 6.0) < 1e-4
    b = out.beauty
    assert b[hole][2] > 2 * b[hole][0] and b[solid][0] > 2 * b[solid][2]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt", "hybrid"])
def test_the_cut_half_casts_no_shadow_and_the_present_half_does(renders, without_quad, mode):
    out, camera = renders[mode]
    bare = without_quad[mode][0].beauty
    # Wall at x = -0.2 is seen through the hole; its ray to the light crosses the quad's
    # plane at x = -0.2 - tan 30° = -0.78, inside the cut half: lit, exactly as the same
    # wall point with no quad at all (same pixel, albedo, normal, view and light).
    through = pixel_at(camera, (-0.2, 0.0, -1.0))
    np.testing.assert_allclose(out.beauty[through], bare[through], rtol=1e-5)
    # Wall at x = 1.3 (beside the quad from the camera: 1.3 * 5/6 = 1.08 > 1) crosses
    # the quad's plane at 1.3 - 0.577 = 0.72, in the present half: in shadow, so only
    # the ambient term is left: well below half of the unshadowed value.
    shadowed = pixel_at(camera, (1.3, 0.0, -1.0))
    assert out.beauty[shadowed][2] < 0.5 * bare[shadowed][2]


@pytest.mark.slow
def test_raster_and_rt_agree_on_which_pixels_are_cut(renders):
    """The one cut-out rule (model/surface.py Cutouts) in raster and trace: the pixels
    showing the wall agree except on the texels' edge between the halves (bilinear
    alpha crosses 0.5 at x = 0 exactly; float32 barycentrics may differ there by one
    pixel column: at most one column of the quad's height, HEIGHT pixels)."""
    raster = renders["raster"][0].gbuffer.element_id
    rt = renders["rt"][0].gbuffer.element_id
    differ = int((raster != rt).sum())
    assert differ <= HEIGHT


@pytest.mark.slow
def test_no_threshold_means_opaque(tmp_path):
    """opacityThreshold 0 with a textured opacity: not a cut-out and not faked
    translucency: the quad is opaque everywhere (the known limit in docs)."""
    stage = cutout_stage(tmp_path, threshold=0.0)
    out, camera = render_first_frame(stage, "raster")
    assert out.gbuffer.element_id[pixel_at(camera, (-0.5, 0.0, 0.0))] == 1
    scene = read_stage(stage)
    assert not scene.scene.materials.has_transmission


def test_id_layers_give_the_id_pass_ids(tmp_path):
    """shaders/peel.frag keeps flat.frag's id encoding (declared "keep in step"): a
    cut-out scene without holes (alpha 1 everywhere) draws its first layer through
    cutout_layers.IdLayers, the same scene without opacityThreshold through the id
    pass; every pixel's triangle id is the same (exact integers)."""
    from phrt_usd.engine.raster.rasterizer import Rasterizer

    ids = {}
    for threshold in (0.5, 0.0):
        directory = tmp_path / f"t{threshold}"
        directory.mkdir()
        stage = cutout_stage(directory, threshold=threshold)
        write_image(directory / "half_alpha.png", np.ones((8, 8, 4)))  # no holes
        scene = read_stage(stage)
        assert bool(scene.scene.materials.cutouts) == (threshold > 0)
        with Rasterizer(scene.scene, WIDTH, HEIGHT) as raster:
            ids[threshold] = raster.render(scene.camera(scene.frame_range[0])).triangle_id
    assert set(np.unique(ids[0.5])) == {-1, 0, 1, 2, 3}  # background, wall and quad
    np.testing.assert_array_equal(ids[0.5], ids[0.0])


@pytest.mark.slow
def test_hybrid_all_matches_rt_on_the_cutout_stage(renders):
    """The hybrid-equals-rt invariant of tests/engine/test_render.py, on cut-outs: hybrid with
    every reflector traced (none here: raster G-buffer, maps and rays for the pairs they
    cannot decide) against rt, within the same mean FLIP."""
    from phrt_usd.pytest_plugin import assert_images_close

    assert_images_close(
        renders["hybrid"][0].beauty, renders["rt"][0].beauty,
        max_mean_flip=HYBRID_VS_RT_FLIP, min_psnr=None, name="cutouts",
    )  # fmt: skip


@pytest.mark.slow
def test_animated_geometry_keeps_the_triangle_ids(tmp_path):
    """Id layers number the static triangles, then the animated ones (two draws); the
    G-buffer maps them back to the scene's triangle ids. With the wall animated (a
    time-sampled translate: its triangles drawn second) raster and rt agree on every
    pixel's triangle and the cut half still shows the wall."""
    stage = cutout_stage(tmp_path)
    op = UsdGeom.Xformable(stage.GetPrimAtPath("/Wall")).AddTranslateOp()
    op.Set((0.0, 0.0, 0.0), 1.0)
    op.Set((0.0, 0.0, -0.5), 2.0)
    stage.SetStartTimeCode(1.0)
    stage.SetEndTimeCode(2.0)
    stage.GetRootLayer().Save()
    raster, camera = render_first_frame(stage, "raster")
    rt, _ = render_first_frame(stage, "rt")
    assert read_stage(stage).scene.elements[0].animated  # the wall is drawn second
    hole = pixel_at(camera, (-0.5, 0.0, 0.0))
    assert raster.gbuffer.element_id[hole] == 0
    differ = int((raster.gbuffer.triangle_id != rt.gbuffer.triangle_id).sum())
    assert differ <= HEIGHT  # as test_raster_and_rt_agree_on_which_pixels_are_cut
