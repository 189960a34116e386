"""UsdUVTexture as the UsdPreviewSurface specification reads it, end to end: texture
transforms (UsdTransform2d), wrap modes, sourceColorSpace, scale / bias, textured
emissiveColor, and MaterialX-only materials; stages and textures made here, rendered in
raster and rt, checked at pixels whose right value follows from the geometry.

The stage (``textured_stages.textured_quad_stage``): a 2 m quad at z = 0 whose ``st`` runs
0..``st_max`` along x and 0..1 along y, seen by a camera at z = 5. The test
texture ``halves.png`` is red in its left half (s < 0.5) and green in its right half.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdShade
from textured_stages import (
    define_texture,
    pixel_at,
    render_first_frame,
    textured_quad_stage,
    write_image,
)

from phrt_usd.usd.stage import read_stage
from phrt_usd.usd.support_report import support_report

RED, GREEN = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
TOKEN, FLOAT2 = Sdf.ValueTypeNames.Token, Sdf.ValueTypeNames.Float2


def _halves(path) -> None:
    """8 x 8 RGB: red columns 0-3, green columns 4-7 (8-bit 255 / 0: exact in sRGB)."""
    px = np.zeros((8, 8, 3))
    px[:, :4] = RED
    px[:, 4:] = GREEN
    write_image(path, px)


def _diffuse_texture(stage, surf, tmp_path, **inputs) -> UsdShade.Shader:
    _halves(tmp_path / "halves.png")
    tex = define_texture(stage, "/Looks/Quad/Tex", "halves.png", **inputs)
    surf.GetInput("diffuseColor").ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    return tex


def _albedo_at(stage, mode, x) -> np.ndarray:
    """The G-buffer albedo at the pixel seeing the quad's point (x, 0, 0)."""
    stage.GetRootLayer().Save()
    out, camera = render_first_frame(stage, mode)
    return out.gbuffer.albedo[pixel_at(camera, (x, 0.0, 0.0))]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_transform2d_translation_by_half_swaps_the_halves(tmp_path, mode):
    """UsdTransform2d translation (0.5, 0) with repeat wrap: st' = st + (0.5, 0), so
    the quad's left half (s = 0.25 at x = -0.5) reads s' = 0.75: green, its right half
    (s' = 1.25 → 0.25) red. Texel centres there: the albedo is exact."""
    stage, surf = textured_quad_stage(tmp_path)
    repeat = {"wrapS": (TOKEN, "repeat"), "wrapT": (TOKEN, "repeat")}
    tex = _diffuse_texture(stage, surf, tmp_path, **repeat)
    reader_out = tex.GetInput("st").GetConnectedSources()[0][0]  # the primvar reader
    xform = UsdShade.Shader.Define(stage, "/Looks/Quad/Move")
    xform.CreateIdAttr("UsdTransform2d")
    xform.CreateInput("in", FLOAT2).ConnectToSource(reader_out)
    xform.CreateInput("translation", FLOAT2).Set(Gf.Vec2f(0.5, 0.0))
    tex.GetInput("st").ConnectToSource(xform.CreateOutput("result", FLOAT2))
    np.testing.assert_allclose(_albedo_at(stage, mode, -0.5), GREEN, atol=1e-6)
    np.testing.assert_allclose(_albedo_at(stage, mode, 0.5), RED, atol=1e-6)


def test_transform2d_order_is_scale_rotate_translate():
    """The spec's order: st * scale, rotated counter-clockwise, then translated:
    (1, 0) scaled by (2, 1) is (2, 0), rotated 90° is (0, 2), moved by (0.5, 0) is
    (0.5, 2)."""
    from phrt_usd.usd.materials import transform_2d

    m = transform_2d(90.0, (2.0, 1.0), (0.5, 0.0))
    np.testing.assert_allclose(m @ [1.0, 0.0, 1.0], [0.5, 2.0], atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize(("wrap", "expected"), [("repeat", RED), ("clamp", GREEN)])
def test_wrap_clamp_and_repeat_outside_the_unit_square(tmp_path, wrap, expected):
    """st runs 0..2 along the quad: at x = 0.25, s = 1.25. Repeat reads s = 0.25 (red
    half); clamp reads the last column (green)."""
    stage, surf = textured_quad_stage(tmp_path, st_max=2.0)
    _diffuse_texture(stage, surf, tmp_path, wrapS=(TOKEN, wrap), wrapT=(TOKEN, wrap))
    np.testing.assert_allclose(_albedo_at(stage, "raster", 0.25), expected, atol=1e-6)


def _grey(path, channels: int) -> None:
    """4 x 4 8-bit texture of 128 in every channel."""
    write_image(path, np.full((4, 4, channels), 128 / 255))


#: 128 / 255 decoded: raw is the number itself; sRGB (IEC 61966-2-1) ((c + 0.055) /
#: 1.055) ** 2.4.
RAW_128 = 128 / 255
SRGB_128 = ((128 / 255 + 0.055) / 1.055) ** 2.4


@pytest.mark.slow
@pytest.mark.parametrize(
    ("space", "channels", "expected"),
    [("sRGB", 3, SRGB_128), ("raw", 3, RAW_128), ("auto", 3, SRGB_128), ("auto", 1, RAW_128)],
)
def test_source_colour_space_decodes_mid_grey(tmp_path, space, channels, expected):
    """sourceColorSpace per the UsdUVTexture spec: sRGB / raw as asked; auto: an 8-bit
    file of 3 or 4 channels is sRGB, an 8-bit grey one raw. The G-buffer albedo at a
    texel centre equals the decoded value (float32)."""
    stage, surf = textured_quad_stage(tmp_path)
    _grey(tmp_path / "grey.png", channels)
    tex = define_texture(stage, "/Looks/Quad/Tex", "grey.png", sourceColorSpace=(TOKEN, space))
    output = "rgb" if channels == 3 else "r"
    kind = Sdf.ValueTypeNames.Float3 if channels == 3 else Sdf.ValueTypeNames.Float
    surf.GetInput("diffuseColor").ConnectToSource(tex.CreateOutput(output, kind))
    np.testing.assert_allclose(_albedo_at(stage, "raster", 0.125), [expected] * 3, rtol=1e-6)


def test_scale_bias_and_missing_alpha(tmp_path):
    """scale (0.5, 0.5, 0.5, 1) and bias (0.25, 0, 0, 0) on the rgb output: red reads
    (0.75, 0, 0); ``outputs:a`` of a file without alpha reads 1 (the spec): with
    opacityThreshold 0.5 nothing is cut."""
    stage, surf = textured_quad_stage(tmp_path)
    f4 = Sdf.ValueTypeNames.Float4
    tex = _diffuse_texture(
        stage, surf, tmp_path,
        scale=(f4, Gf.Vec4f(0.5, 0.5, 0.5, 1.0)), bias=(f4, Gf.Vec4f(0.25, 0.0, 0.0, 0.0)),
    )  # fmt: skip
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
    )
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    stage.GetRootLayer().Save()
    out, camera = render_first_frame(stage, "rt")  # rt: no shadow maps to peel, a quicker test
    p = pixel_at(camera, (-0.5, 0.0, 0.0))
    assert out.gbuffer.element_id[p] == 0  # not cut
    np.testing.assert_allclose(out.gbuffer.albedo[p], (0.75, 0.0, 0.0), atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_textured_emission_adds_its_texel_to_the_pixel(tmp_path, mode):
    """emissiveColor from the halves texture: the red half emits (1, 0, 0), the green
    half (0, 1, 0); the beauty minus the same stage's without emission is exactly the
    texel (emission is added to the shaded colour, engine/shading.py)."""
    stage, surf = textured_quad_stage(tmp_path)
    stage.GetRootLayer().Save()
    plain, camera = render_first_frame(stage, mode)
    _halves(tmp_path / "halves.png")
    tex = define_texture(stage, "/Looks/Quad/Glow", "halves.png")
    surf.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    stage.GetRootLayer().Save()
    glowing, _ = render_first_frame(stage, mode)
    for x, texel in ((-0.5, RED), (0.5, GREEN)):
        p = pixel_at(camera, (x, 0.0, 0.0))
        added = glowing.beauty[p] - plain.beauty[p]
        np.testing.assert_allclose(added, texel, atol=1e-5)  # float32 sums


def _materialx(stage, ident: str, **inputs) -> None:
    """Replace /Looks/Quad's surface by a MaterialX-only one (outputs:mtlx:surface) of
    shader ``ident``."""
    mat = UsdShade.Material(stage.GetPrimAtPath("/Looks/Quad"))
    mat.GetSurfaceOutput().GetAttr().Clear()
    stage.RemovePrim("/Looks/Quad/Surface")
    shader = UsdShade.Shader.Define(stage, "/Looks/Quad/MtlxSurface")
    shader.CreateIdAttr(ident)
    for name, (kind, value) in inputs.items():
        shader.CreateInput(name, kind).Set(value)
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(
        shader.CreateOutput("out", Sdf.ValueTypeNames.Token)
    )


@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_materialx_standard_surface_renders_its_base_colour(tmp_path, mode):
    """ND_standard_surface: albedo = base * base_color = 0.5 * (0.2, 0.8, 0.4)
    (usd/materialx.py maps the whole surface); nothing is left out, so no notice and
    no support-report row."""
    stage, _ = textured_quad_stage(tmp_path)
    c3 = Sdf.ValueTypeNames.Color3f
    _materialx(
        stage, "ND_standard_surface_surfaceshader",
        base_color=(c3, Gf.Vec3f(0.2, 0.8, 0.4)), base=(Sdf.ValueTypeNames.Float, 0.5),
    )  # fmt: skip
    np.testing.assert_allclose(_albedo_at(stage, mode, 0.0), (0.1, 0.4, 0.2), atol=1e-6)
    scene = read_stage(stage)
    assert not [w for w in scene.warnings if "MaterialX" in w]
    rows = {r["kind"]: r for r in support_report(stage)}
    assert "materialx_approximated" not in rows and "materialx_only" not in rows


def test_materialx_unknown_surface_is_grey_with_a_notice(tmp_path):
    stage, _ = textured_quad_stage(tmp_path)
    _materialx(stage, "ND_my_studio_surface")
    albedo = _albedo_at(stage, "raster", 0.0)
    np.testing.assert_allclose(albedo, [0.18] * 3, atol=1e-6)  # UsdPreviewSurface grey
    scene = read_stage(stage)
    notes = [w for w in scene.warnings if "/Looks/Quad" in w and "MaterialX" in w]
    assert len(notes) == 1 and "grey" in notes[0]
    rows = {r["kind"]: r for r in support_report(stage)}
    assert rows["materialx_only"]["paths"] == ["/Looks/Quad"]
    assert "materialx_base_colour" not in rows


@pytest.mark.slow
def test_materialx_image_node_is_the_base_colour_texture(tmp_path):
    """ND_image_color3 on base_color (ND_UsdPreviewSurface's diffuseColor here): the
    halves texture, red left and green right (periodic address modes)."""
    stage, _ = textured_quad_stage(tmp_path)
    _materialx(stage, "ND_UsdPreviewSurface_surfaceshader")
    _halves(tmp_path / "halves.png")
    image = UsdShade.Shader.Define(stage, "/Looks/Quad/Image")
    image.CreateIdAttr("ND_image_color3")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("halves.png")
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Quad/MtlxSurface"))
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.CreateOutput("out", Sdf.ValueTypeNames.Color3f)
    )
    np.testing.assert_allclose(_albedo_at(stage, "raster", -0.5), RED, atol=1e-6)
    np.testing.assert_allclose(_albedo_at(stage, "raster", 0.5), GREEN, atol=1e-6)


@pytest.mark.parametrize("device", ["/dev/zero", "fifo", "directory"])
def test_probe_texture_device(tmp_path, device):
    """A texture path that is no regular file (a device, which reads without end, a
    named pipe, which blocks, or a directory) is never read: one warning naming the
    attribute, and the input's fallback (the UsdUVTexture's ``fallback``, here green);
    ``--strict`` makes it the one error line, exit 1."""
    import os

    from typer.testing import CliRunner

    from phrt_usd.cli import app

    if device == "fifo":
        device = str(tmp_path / "pipe.png")
        os.mkfifo(device)
    elif device == "directory":
        device = str(tmp_path / "folder.png")
        os.mkdir(device)
    stage, surf = textured_quad_stage(tmp_path)
    tex = define_texture(stage, "/Looks/Quad/Tex", device)
    tex.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set((0.0, 1.0, 0.0, 1.0))
    surf.GetInput("diffuseColor").ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    stage.GetRootLayer().Save()
    scene = read_stage(stage)
    (problem,) = scene.texture_problems
    assert "/Looks/Quad/Tex.inputs:file" in problem and "not a regular file" in problem
    assert f"{problem}; rendered with the input's fallback" in scene.warnings
    # The fallback green is every corner's albedo: exact, it is the authored constant.
    np.testing.assert_array_equal(scene.scene.geometry.corner_albedo[0], [GREEN] * 3)
    args = ["render", str(tmp_path / "tex.usda"), "--out", str(tmp_path / "run"), "--strict",
            "--resolution", "16x12", "--frames", "1:1"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "not a regular file" in lines[0], result.output
    assert "Traceback" not in result.output
