"""The BRDF's UsdPreviewSurface inputs textured as the others are (``usd/materials.py``,
``model/preview_surface.py``): a 2 x 1 texture feeding ``metallic`` (its red channel) and
``occlusion`` (its green one) of a quad under a white dome, seen face on, in raster and
rt: each half of the quad shows what its texel's inputs say."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdShade
from scenes import front_view_stage, st_quad

from phrt_usd.engine import shading
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.model import preview_surface as ps
from phrt_usd.usd.stage import read_stage

ALBEDO = (0.8, 0.4, 0.2)
#: The two texels (raw, 8-bit): (metallic, occlusion, unused).
TEXELS = np.array([[[0, 255, 0], [255, 128, 0]]], np.uint8)
#: Float32 shading of the same rows (the texel values are exact in 8 bits).
TOLERANCE = 1e-5


def _stage(tmp_path) -> Usd.Stage:
    """A 2 x 2 quad at z = 0 facing +Z (st 0..1 across it), the texture's left texel on
    its left half, seen from (0, 0, 5); a white dome of radiance 1, no other light."""
    png = tmp_path / "inputs.png"
    out = oiio.ImageOutput.create(str(png))
    out.open(str(png), oiio.ImageSpec(2, 1, 3, oiio.UINT8))
    out.write_image(TEXELS)
    out.close()
    stage = front_view_stage(tmp_path / "quad.usda")
    mesh = st_quad(stage)
    mat = UsdShade.Material.Define(stage, "/M")
    surf = UsdShade.Shader.Define(stage, "/M/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*ALBEDO))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.3)
    tex = UsdShade.Shader.Define(stage, "/M/Inputs")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("inputs.png")
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    for axis in ("wrapS", "wrapT"):
        tex.CreateInput(axis, Sdf.ValueTypeNames.Token).Set("clamp")
    for name, channel in (("metallic", "r"), ("occlusion", "g")):
        surf.CreateInput(name, Sdf.ValueTypeNames.Float).ConnectToSource(
            tex.CreateOutput(channel, Sdf.ValueTypeNames.Float)
        )
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    stage.GetRootLayer().Save()
    return stage


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_textured_metallic_and_occlusion_shade_per_texel(tmp_path, mode):
    """Left half: metallic 0, occlusion 1 (a dielectric: its albedo plus ~4 % white);
    right half: metallic 1, occlusion 128/255 (a metal: its albedo, darkened by the
    occlusion). A pixel near the middle of a half equals the ambient weight
    (``shading.surface_weights``) of the surface row of the texels' bilinear blend at
    its point, seen from its own view."""
    scene = read_stage(_stage(tmp_path))
    renderer = FrameRenderer(scene, RenderOptions(mode=mode, width=16, height=16))
    try:
        out = renderer.render(scene.frame_range[0])
    finally:
        renderer.close()
    gb = out.gbuffer
    for col in (4, 11):
        at = (8, col)
        assert gb.element_id[at] == 0
        # The bilinear blend of the two texels at the pixel's s (clamped at the edges).
        s = (gb.position[at][0] + 1.0) / 2.0
        w = float(np.clip(s * 2.0 - 0.5, 0.0, 1.0))
        metallic, occlusion = w, (1.0 - w) + w * 128 / 255
        row = ps.surface_columns(np.array([ALBEDO]), metallic, 0, np.zeros(3), 0.3, 0.0,
                                 0.01, 1.5, occlusion, 1.0)  # fmt: skip
        ambient, _ = shading.surface_weights(row, gb.normal[at][None], -gb.view_dir[at][None])
        np.testing.assert_allclose(out.beauty[at], ambient[0], atol=TOLERANCE, err_msg=str(at))
    left, right = out.beauty[8, 4], out.beauty[8, 11]
    assert left[2] > 0.2 and right[2] < 0.15  # the metal has no white specular floor


def test_brdf_constants_are_read_into_the_material_table(tmp_path):
    """Every constant input the BRDF reads lands in its MaterialTable row (clamped to
    its range): the specular workflow, its colour, ior, clear coat and its roughness,
    occlusion."""
    stage = _stage(tmp_path)
    surf = UsdShade.Shader(stage.GetPrimAtPath("/M/Surface"))
    values = {"useSpecularWorkflow": (Sdf.ValueTypeNames.Int, 1),
              "ior": (Sdf.ValueTypeNames.Float, 2.0),
              "clearcoat": (Sdf.ValueTypeNames.Float, 0.7),
              "clearcoatRoughness": (Sdf.ValueTypeNames.Float, 1.5),
              "specularColor": (Sdf.ValueTypeNames.Color3f, Gf.Vec3f(0.1, 0.2, 0.3))}  # fmt: skip
    for name, (kind, value) in values.items():
        surf.CreateInput(name, kind).Set(value)
    m = read_stage(stage).scene.materials
    row = 1  # row 0: no material
    assert m.use_specular_workflow[row] == 1.0 and m.ior[row] == 2.0
    assert m.clearcoat[row] == pytest.approx(0.7) and m.clearcoat_roughness[row] == 1.0
    np.testing.assert_allclose(m.specular_color[row], [0.1, 0.2, 0.3], rtol=1e-6)
    assert "metallic" in m.texture_inputs[row] and "occlusion" in m.texture_inputs[row]
