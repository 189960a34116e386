"""Materials read through USD: textures through the resolver (.usdz packages), a missing
texture as a warning with the input's fallback."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdRender, UsdShade, UsdUtils
from textured_stages import write_one_colour_png

from phrt_usd.usd.stage import read_stage

RED = (1.0, 0.0, 0.0)


def _stage(path, texture: str):
    """A quad bound to a UsdPreviewSurface whose diffuseColor is a UsdUVTexture of
    ``texture``, and a camera."""
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Quad")
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    mat = UsdShade.Material.Define(stage, "/M")
    surf = UsdShade.Shader.Define(stage, "/M/S")
    surf.CreateIdAttr("UsdPreviewSurface")
    tex = UsdShade.Shader.Define(stage, "/M/T")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
    out = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(out)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set((0, 0, 5))
    stage.GetRootLayer().Save()
    return stage


def test_texture_inside_usdz_is_read_through_the_resolver(tmp_path):
    write_one_colour_png(tmp_path / "red.png", RED)
    _stage(tmp_path / "quad.usda", "red.png")
    package = tmp_path / "quad.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(tmp_path / "quad.usda"), str(package))
    (tmp_path / "red.png").unlink()  # only the package's copy is left
    scene = read_stage(Usd.Stage.Open(str(package)))
    texture = scene.scene.materials.textures[scene.scene.geometry.tri_material[0]]
    assert texture is not None
    # The red PNG, linear: exactly (1, 0, 0) in every texel (8-bit 255 and 0 are exact).
    np.testing.assert_array_equal(texture.reshape(-1, 3), np.tile(RED, (16, 1)))
    assert not scene.texture_problems


def test_missing_texture_warns_and_uses_the_fallback(tmp_path):
    stage = _stage(tmp_path / "quad.usda", "missing.png")
    UsdShade.Shader(stage.GetPrimAtPath("/M/T")).CreateInput(
        "fallback", Sdf.ValueTypeNames.Float4
    ).Set((0.0, 0.5, 0.0, 1.0))
    scene = read_stage(stage)
    assert len(scene.texture_problems) == 1
    line = scene.texture_problems[0]
    assert "/M/T.inputs:file" in line and "missing.png" in line and "\n" not in line
    assert f"{line}; rendered with the input's fallback" in scene.warnings
    row = scene.scene.geometry.tri_material[0]
    assert scene.scene.materials.textures[row] is None
    # The UsdUVTexture's fallback (0, 0.5, 0) is the albedo every corner gets.
    np.testing.assert_allclose(scene.scene.geometry.corner_albedo[0], [[0, 0.5, 0]] * 3)


def test_full_binding_wins_over_all_purpose(tmp_path):
    """materialBindingPurposes fallback ["full", ""]: a full binding beats the
    all-purpose one; a settings prim asking for ["preview", ""] gets the preview one
    (a collection binding)."""
    stage = _stage(tmp_path / "quad.usda", "missing.png")
    colours = {"Full": (0.0, 0.0, 1.0), "Preview": (0.0, 1.0, 0.0)}
    mats = {}
    for name, colour in colours.items():
        mat = UsdShade.Material.Define(stage, f"/{name}")
        surf = UsdShade.Shader.Define(stage, f"/{name}/S")
        surf.CreateIdAttr("UsdPreviewSurface")
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(colour)
        mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
        mats[name] = mat
    quad = stage.GetPrimAtPath("/Quad")
    api = UsdShade.MaterialBindingAPI(quad)
    api.Bind(mats["Full"], materialPurpose=UsdShade.Tokens.full)
    coll = Usd.CollectionAPI.Apply(stage.GetPrimAtPath("/M"), "prev")
    coll.CreateIncludesRel().AddTarget("/Quad")
    api.Bind(coll, mats["Preview"], "prev", materialPurpose=UsdShade.Tokens.preview)
    scene = read_stage(stage)
    np.testing.assert_allclose(scene.scene.geometry.corner_albedo[0], [colours["Full"]] * 3)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateMaterialBindingPurposesAttr(["preview", ""])
    scene = read_stage(stage)
    np.testing.assert_allclose(scene.scene.geometry.corner_albedo[0], [colours["Preview"]] * 3)


def test_validate_calls_a_missing_texture_an_error(tmp_path):
    from phrt_usd.usd.rules import render_issues

    stage = _stage(tmp_path / "quad.usda", "missing.png")
    errors = [i for i in render_issues(stage) if i.severity == "error"]
    assert any("/M/T.inputs:file" in i.line() and "missing.png" in i.line() for i in errors)


def test_strict_makes_a_missing_texture_an_error_exit_1(tmp_path):
    """``phrt render --strict``: the missing texture's warning becomes the error (one
    line naming the attribute, exit 1 as a failed render, README's exit codes), before
    any frame is rendered; the API's ``strict=True`` raises the same line."""
    from typer.testing import CliRunner

    from phrt_usd import api
    from phrt_usd.cli import app
    from phrt_usd.usd.textures import TextureError

    _stage(tmp_path / "quad.usda", "missing.png")
    args = ["render", str(tmp_path / "quad.usda"), "--out", str(tmp_path / "run"), "--strict"]
    result = CliRunner().invoke(app, [*args, "--resolution", "16x12"])
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "/M/T.inputs:file" in lines[0] and "missing.png" in lines[0]
    assert "--strict" in lines[0] and "Traceback" not in result.output
    assert not (tmp_path / "run" / "stats.json").exists()
    with pytest.raises(TextureError, match="/M/T.inputs:file"):
        api.render(tmp_path / "quad.usda", tmp_path / "api-run", strict=True)
