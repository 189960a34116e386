"""Materials read through USD, checked at an analytic pixel in raster and rt: a texture
inside a ``.usdz`` package, a missing texture's fallback, and the binding a purpose
chooses (``full`` over all-purpose; the settings' ``materialBindingPurposes``).

The stage: a 2 x 2 quad at z = 0 facing +Z, seen from (0, 0, 5) down -Z (focal 50 mm,
aperture 20 x 20 mm: the image spans +-1.05 at the quad, so the centre pixel lies on it),
lit only by a white dome of radiance 1. A UsdPreviewSurface under a uniform dome of
radiance L returns its directional albedo times L: the albedo where the specular lobe
leaves light to the diffuse one, plus the lobe's own (``_look``), so the centre pixel's
linear colour follows the albedo.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdRender, UsdShade, UsdUtils
from scenes import centre_pixel, front_view_stage, preview_shade, st_quad
from textured_stages import write_one_colour_png

W = H = 16
MODES = ("raster", "rt")
#: Largest allowed difference from the albedo at the centre pixel, per channel: the
#: dome's ambient term is exact, so this only absorbs float32 shading and 8-bit texels
#: (0 and 255 decode exactly).
TOLERANCE = 0.02
RED, GREEN_HALF, BLUE, GREEN = (1.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)


def _look(colour) -> np.ndarray:
    """(3,) the centre pixel of a material of albedo ``colour`` (its other inputs the
    fallbacks) under the white dome, seen face on from (0, 0, 5)."""
    return preview_shade(colour, (0.0, 0.0, 0.0), (0.0, 0.0, 5.0), ambient=1.0)


def _material(stage, path: str, colour=None, texture: str | None = None) -> UsdShade.Material:
    """A UsdPreviewSurface with a constant ``colour`` or a UsdUVTexture of ``texture``
    (fallback (0, 0.5, 0)) as its diffuseColor."""
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    diffuse = surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    if texture is None:
        diffuse.Set(Gf.Vec3f(*colour))
    else:
        tex = UsdShade.Shader.Define(stage, f"{path}/Texture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
        tex.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set((*GREEN_HALF, 1.0))
        diffuse.ConnectToSource(tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return mat


def _stage(path) -> Usd.Stage:
    stage = front_view_stage(path)
    st_quad(stage)
    return stage


def _bind(stage, mat, purpose=UsdShade.Tokens.allPurpose) -> None:
    api = UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Quad"))
    api.Bind(mat, materialPurpose=purpose)


def _centre(stage, mode: str) -> np.ndarray:
    """(3,) linear colour of the centre pixel of one frame in ``mode``."""
    return centre_pixel(stage, mode, W)


@pytest.mark.parametrize("mode", MODES)
def test_usdz_texture_colours_the_pixel(tmp_path, mode):
    write_one_colour_png(tmp_path / "red.png", RED)
    stage = _stage(tmp_path / "quad.usda")
    _bind(stage, _material(stage, "/M", texture="red.png"))
    stage.GetRootLayer().Save()
    package = tmp_path / "quad.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(tmp_path / "quad.usda"), str(package))
    (tmp_path / "red.png").unlink()  # only the package's copy is left
    np.testing.assert_allclose(
        _centre(Usd.Stage.Open(str(package)), mode), _look(RED), atol=TOLERANCE
    )


@pytest.mark.parametrize("mode", MODES)
def test_missing_texture_renders_its_fallback(tmp_path, mode):
    stage = _stage(tmp_path / "quad.usda")
    _bind(stage, _material(stage, "/M", texture="missing.png"))
    np.testing.assert_allclose(_centre(stage, mode), _look(GREEN_HALF), atol=TOLERANCE)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_binding_purpose_chooses_the_material(tmp_path, mode):
    stage = _stage(tmp_path / "quad.usda")
    _bind(stage, _material(stage, "/All", colour=RED))
    _bind(stage, _material(stage, "/Full", colour=BLUE), UsdShade.Tokens.full)
    _bind(stage, _material(stage, "/Preview", colour=GREEN), UsdShade.Tokens.preview)
    # materialBindingPurposes' fallback is ["full", ""]: the full binding.
    np.testing.assert_allclose(_centre(stage, mode), _look(BLUE), atol=TOLERANCE)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateMaterialBindingPurposesAttr(["preview", ""])
    np.testing.assert_allclose(_centre(stage, mode), _look(GREEN), atol=TOLERANCE)
    settings.GetMaterialBindingPurposesAttr().Set([""])
    np.testing.assert_allclose(_centre(stage, mode), _look(RED), atol=TOLERANCE)
