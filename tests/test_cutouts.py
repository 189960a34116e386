"""UsdPreviewSurface texture inputs and opacityThreshold cut-outs, end to end: stages made
here with textures written here (OpenImageIO), rendered in raster, hybrid and rt, checked
at pixels whose right colour follows from the geometry.

The stage (``_stage``): a wall (z = -1, 6 m square, blue) behind a quad (z = 0, 2 m
square, red, ``st`` 0..1 over it), a camera at z = 5 looking down -z, a DistantLight
travelling along (sin 30°, 0, -cos 30°): a present point of the quad at x shadows the
wall at x + tan 30° (the wall is 1 m behind it). The quad's material is a cut-out
(opacityThreshold 0.5) whose opacity is a texture's alpha: 0 in the left half (x < 0),
1 in the right half.
"""

from __future__ import annotations

import math

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd.stage import read_stage

WIDTH, HEIGHT = 96, 72
WALL = (0.1, 0.2, 0.8)
QUAD = (0.9, 0.1, 0.05)
#: The light's tilt: the shadow of the quad lands tan(30°) = 0.577 m to +x on the wall.
TILT_DEG = 30.0
SHIFT = math.tan(math.radians(TILT_DEG))


def _image(path, pixels: np.ndarray) -> None:
    """An 8-bit file of ``pixels`` (h, w, c) in [0, 1] (row 0 = top)."""
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8))
    out.write_image(np.round(np.clip(pixels, 0, 1) * 255).astype(np.uint8))
    out.close()


def _half_alpha(path) -> None:
    """8 x 8 RGBA, white, alpha 0 in the left half (columns 0-3), 1 in the right half."""
    px = np.ones((8, 8, 4))
    px[:, :4, 3] = 0.0
    _image(path, px)


def _quad(stage, path, half, z, st=True):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-half, -half, z), (half, -half, z), (half, half, z), (-half, half, z)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    if st:
        pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
        )
        pv.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    return mesh


def _material(stage, path, colour):
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return mat, surf


def _texture(stage, path, file, **inputs):
    tex = UsdShade.Shader.Define(stage, path)
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    reader = UsdShade.Shader.Define(stage, f"{path}_st")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    st_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_out)
    for name, (kind, value) in inputs.items():
        tex.CreateInput(name, kind).Set(value)
    return tex


def _stage(tmp_path, name="cutout.usda", threshold=0.5) -> Usd.Stage:
    _half_alpha(tmp_path / "half_alpha.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    wall = _quad(stage, "/Wall", 3.0, -1.0, st=False)
    quad = _quad(stage, "/Quad", 1.0, 0.0)
    wall_mat, _ = _material(stage, "/Looks/Wall", WALL)
    quad_mat, surf = _material(stage, "/Looks/Quad", QUAD)
    tex = _texture(
        stage, "/Looks/Quad/Alpha", "half_alpha.png",
        wrapS=(Sdf.ValueTypeNames.Token, "clamp"), wrapT=(Sdf.ValueTypeNames.Token, "clamp"),
    )  # fmt: skip
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
    )
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(threshold)
    UsdShade.MaterialBindingAPI.Apply(wall.GetPrim()).Bind(wall_mat)
    UsdShade.MaterialBindingAPI.Apply(quad.GetPrim()).Bind(quad_mat)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set((0.0, 0.0, 5.0))
    cam.CreateFocalLengthAttr(25.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(1.0)
    sun.CreateAngleAttr(0.0)
    # Rotating -Z (a DistantLight's direction) by -30° about +Y: (sin 30°, 0, -cos 30°).
    sun.AddRotateYOp().Set(-TILT_DEG)
    stage.GetRootLayer().Save()
    return stage


def _render(stage, mode):
    scene = read_stage(stage)
    opts = RenderOptions(mode=mode, heuristic="all", width=WIDTH, height=HEIGHT, budget_ms=None)
    renderer = FrameRenderer(scene, opts)
    try:
        out = renderer.render(scene.frame_range[0])
        return out, scene.camera(scene.frame_range[0])
    finally:
        renderer.close()


def _pixel(camera, point) -> tuple[int, int]:
    """(row, col) of the pixel whose centre sees world ``point``."""
    x, y, _ = camera.project(np.array([point], float), WIDTH, HEIGHT)[0]
    return int(y), int(x)


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    stage = _stage(tmp_path_factory.mktemp("cutout"))
    return {mode: _render(stage, mode) for mode in ("raster", "rt", "hybrid")}


@pytest.fixture(scope="module")
def without_quad(tmp_path_factory):
    """The same stage with the quad invisible: the wall as nothing shadows it."""
    stage = _stage(tmp_path_factory.mktemp("bare"))
    UsdGeom.Imageable(stage.GetPrimAtPath("/Quad")).MakeInvisible()
    return {mode: _render(stage, mode) for mode in ("raster", "rt", "hybrid")}


@pytest.mark.parametrize("mode", ["raster", "rt", "hybrid"])
def test_wall_shows_through_the_cut_half_and_the_quad_in_the_other(renders, mode):
    out, camera = renders[mode]
    g = out.gbuffer
    hole = _pixel(camera, (-0.5, 0.0, 0.0))  # on the quad's cut-out (alpha 0) half
    solid = _pixel(camera, (0.5, 0.0, 0.0))  # on its opaque half
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


@pytest.mark.parametrize("mode", ["raster", "rt", "hybrid"])
def test_the_cut_half_casts_no_shadow_and_the_present_half_does(renders, without_quad, mode):
    out, camera = renders[mode]
    bare = without_quad[mode][0].beauty
    # Wall at x = -0.2 is seen through the hole; its ray to the light crosses the quad's
    # plane at x = -0.2 - tan 30° = -0.78, inside the cut half: lit, exactly as the same
    # wall point with no quad at all (same pixel, albedo, normal, view and light).
    through = _pixel(camera, (-0.2, 0.0, -1.0))
    np.testing.assert_allclose(out.beauty[through], bare[through], rtol=1e-5)
    # Wall at x = 1.3 (beside the quad from the camera: 1.3 * 5/6 = 1.08 > 1) crosses
    # the quad's plane at 1.3 - 0.577 = 0.72, in the present half: in shadow, so only
    # the ambient term is left: well below half of the unshadowed value.
    shadowed = _pixel(camera, (1.3, 0.0, -1.0))
    assert out.beauty[shadowed][2] < 0.5 * bare[shadowed][2]


def test_raster_and_rt_agree_on_which_pixels_are_cut(renders):
    """The one cut-out rule (model/surface.py Cutouts) in raster and trace: the pixels
    showing the wall agree except on the texels' edge between the halves (bilinear
    alpha crosses 0.5 at x = 0 exactly; float32 barycentrics may differ there by one
    pixel column: at most one column of the quad's height, HEIGHT pixels)."""
    raster = renders["raster"][0].gbuffer.element_id
    rt = renders["rt"][0].gbuffer.element_id
    differ = int((raster != rt).sum())
    assert differ <= HEIGHT


def test_no_threshold_means_opaque(tmp_path):
    """opacityThreshold 0 with a textured opacity: not a cut-out and not faked
    translucency: the quad is opaque everywhere (the known limit in docs)."""
    stage = _stage(tmp_path, threshold=0.0)
    out, camera = _render(stage, "raster")
    assert out.gbuffer.element_id[_pixel(camera, (-0.5, 0.0, 0.0))] == 1
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
        stage = _stage(directory, threshold=threshold)
        _image(directory / "half_alpha.png", np.ones((8, 8, 4)))  # no holes
        scene = read_stage(stage)
        assert bool(scene.scene.materials.cutouts) == (threshold > 0)
        with Rasterizer(scene.scene, WIDTH, HEIGHT) as raster:
            ids[threshold] = raster.render(scene.camera(scene.frame_range[0])).triangle_id
    assert set(np.unique(ids[0.5])) == {-1, 0, 1, 2, 3}  # background, wall and quad
    np.testing.assert_array_equal(ids[0.5], ids[0.0])


def test_hybrid_all_matches_rt_on_the_cutout_stage(renders):
    """The hybrid-equals-rt invariant of tests/test_render.py, on cut-outs: hybrid with
    every reflector traced (none here: raster G-buffer, maps and rays for the pairs they
    cannot decide) against rt, within the same mean FLIP."""
    from test_render import HYBRID_VS_RT_FLIP

    from phrt_usd.pytest_plugin import assert_images_close

    assert_images_close(
        renders["hybrid"][0].beauty, renders["rt"][0].beauty,
        max_mean_flip=HYBRID_VS_RT_FLIP, min_psnr=None, name="cutouts",
    )  # fmt: skip


def test_animated_geometry_keeps_the_triangle_ids(tmp_path):
    """Id layers number the static triangles, then the animated ones (two draws); the
    G-buffer maps them back to the scene's triangle ids. With the wall animated (a
    time-sampled translate: its triangles drawn second) raster and rt agree on every
    pixel's triangle and the cut half still shows the wall."""
    stage = _stage(tmp_path)
    op = UsdGeom.Xformable(stage.GetPrimAtPath("/Wall")).AddTranslateOp()
    op.Set((0.0, 0.0, 0.0), 1.0)
    op.Set((0.0, 0.0, -0.5), 2.0)
    stage.SetStartTimeCode(1.0)
    stage.SetEndTimeCode(2.0)
    stage.GetRootLayer().Save()
    raster, camera = _render(stage, "raster")
    rt, _ = _render(stage, "rt")
    assert read_stage(stage).scene.elements[0].animated  # the wall is drawn second
    hole = _pixel(camera, (-0.5, 0.0, 0.0))
    assert raster.gbuffer.element_id[hole] == 0
    differ = int((raster.gbuffer.triangle_id != rt.gbuffer.triangle_id).sum())
    assert differ <= HEIGHT  # as test_raster_and_rt_agree_on_which_pixels_are_cut
