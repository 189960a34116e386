"""MaterialX surfaces mapped onto UsdPreviewSurface (``usd/materialx.py``): a ``.mtlx``
document referenced by a prim (which usd-core cannot compose), a MaterialX Shader
authored in USD, a missing document; rendered in raster and rt.

The stage (``_ball_stage``): ``scenes.front_view_stage`` (camera at (0, 0, 5) looking
down -z, a white dome of radiance 1) with a sphere of radius 0.8 at the origin and a
DistantLight from the upper right, so that the image holds the diffuse, the specular
highlight and the Fresnel rim of the sphere's material. A MaterialX surface and the
UsdPreviewSurface the mapping's table says it is (module doc of ``usd/materialx.py``)
give the same material row, hence the same image: compared pixel for pixel.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade
from scenes import first_frame, front_view_stage, st_quad
from textured_stages import write_image

from phrt_usd.usd import materialx
from phrt_usd.usd.stage import read_stage
from phrt_usd.usd.support_report import support_report

MODES = ("raster", "rt")
SIZE = 24
#: Largest difference between the images of a MaterialX surface and of its
#: UsdPreviewSurface: the two give the same material row (the same float32 inputs), so
#: only float rounding of the row's construction can differ.
SAME_IMAGE = 1e-5
GOLD = (0.910751, 0.793992, 0.405919)
PLASTIC = (0.209884, 0.562091, 0.766)


def _ball_stage(path):
    stage = front_view_stage(path)
    UsdGeom.Sphere.Define(stage, "/Ball").CreateRadiusAttr(0.8)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(2.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-30.0, 30.0, 0.0))
    return stage


def _bind(stage, path: str) -> None:
    api = UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Ball"))
    api.GetDirectBindingRel().SetTargets([Sdf.Path(path)])


def _preview(stage, path: str, **inputs) -> None:
    """A UsdPreviewSurface Material at ``path`` with ``inputs`` (name -> value)."""
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    for name, value in inputs.items():
        kind = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
        surf.CreateInput(name, kind).Set(Gf.Vec3f(*value) if isinstance(value, tuple) else value)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")


def _document(path, surface: str, name: str, **inputs) -> None:
    """A ``.mtlx`` document of one ``surfacematerial`` ``name`` over a ``surface`` node
    (standard_surface / open_pbr_surface) with ``inputs``."""
    lines = []
    for key, value in inputs.items():
        kind = "color3" if isinstance(value, tuple) else "float"
        text = ", ".join(map(str, value)) if isinstance(value, tuple) else str(value)
        lines.append(f'<input name="{key}" type="{kind}" value="{text}"/>')
    path.write_text(
        '<?xml version="1.0"?>\n<materialx version="1.39">\n'
        f'  <{surface} name="surface" type="surfaceshader">\n    '
        + "\n    ".join(lines)
        + f"\n  </{surface}>\n"
        f'  <surfacematerial name="{name}" type="material">\n'
        '    <input name="surfaceshader" type="surfaceshader" nodename="surface"/>\n'
        "  </surfacematerial>\n</materialx>\n"
    )


def _reference(stage, prim: str, document: str) -> None:
    """``prim`` references ``document``'s materials as the StandardShaderBall does
    (``@doc.mtlx@</MaterialX/Materials>``)."""
    scope = UsdGeom.Scope.Define(stage, prim).GetPrim()
    scope.GetReferences().AddReference(document, Sdf.Path("/MaterialX/Materials"))


def _image(stage, mode: str) -> np.ndarray:
    stage.GetRootLayer().Save()
    out = first_frame(stage, mode, SIZE)
    return np.asarray(out.beauty, np.float64)


def _pair(tmp_path, material_x, preview_inputs: dict, mode: str):
    """(image with the MaterialX material, image with the UsdPreviewSurface), of two
    stages that differ only in the material bound to the ball."""
    mx_stage = _ball_stage(tmp_path / "mx.usda")
    material_x(mx_stage)
    pv_stage = _ball_stage(tmp_path / "pv.usda")
    _preview(pv_stage, "/Looks/Preview", **preview_inputs)
    _bind(pv_stage, "/Looks/Preview")
    return mx_stage, _image(mx_stage, mode), _image(pv_stage, mode)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_gold_standard_surface_document_renders_as_its_preview_surface(tmp_path, mode):
    """A standard_surface gold metal in a referenced ``.mtlx``: the same image as the
    UsdPreviewSurface metal of its base colour and roughness, and no warning (the
    reference USD could not compose is read, nothing is left out)."""
    _document(tmp_path / "gold.mtlx", "standard_surface", "gold",
              base=1.0, base_color=GOLD, metalness=1.0, specular_roughness=0.3)  # fmt: skip

    def gold(stage):
        _reference(stage, "/Looks/Mtlx", "gold.mtlx")
        _bind(stage, "/Looks/Mtlx/gold")

    stage, got, want = _pair(
        tmp_path, gold, {"diffuseColor": GOLD, "metallic": 1.0, "roughness": 0.3}, mode
    )
    np.testing.assert_allclose(got, want, atol=SAME_IMAGE)
    centre = got[SIZE // 2, SIZE // 2]
    assert centre[0] > 1.5 * centre[2]  # gold, not the grey of no material
    assert read_stage(stage).warnings == []


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_open_pbr_plastic_document_renders_as_its_preview_surface(tmp_path, mode):
    """An open_pbr_surface plastic with half the specular weight and a coat: the
    specular workflow with specularColor = 0.5 R²(1.5) = 0.02 (the weight scales F0),
    clearcoat 0.5 of roughness 0.1; the same image, no warning."""
    _document(tmp_path / "plastic.mtlx", "open_pbr_surface", "plastic",
              base_color=PLASTIC, specular_roughness=0.15, specular_weight=0.5,
              coat_weight=0.5, coat_roughness=0.1, coat_ior=1.5)  # fmt: skip

    def plastic(stage):
        _reference(stage, "/Looks/Mtlx", "plastic.mtlx")
        _bind(stage, "/Looks/Mtlx/plastic")

    preview = {"diffuseColor": PLASTIC, "roughness": 0.15, "useSpecularWorkflow": 1.0,
               "specularColor": (0.02, 0.02, 0.02), "clearcoat": 0.5,
               "clearcoatRoughness": 0.1}  # fmt: skip
    stage, got, want = _pair(tmp_path, plastic, preview, mode)
    np.testing.assert_allclose(got, want, atol=SAME_IMAGE)
    assert read_stage(stage).warnings == []


def _inline(stage, path: str, ident: str, **inputs) -> UsdShade.Shader:
    """A Material at ``path`` whose ``mtlx`` surface is a Shader ``ident`` with
    ``inputs`` authored in USD."""
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr(ident)
    for name, value in inputs.items():
        kind = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
        shader.CreateInput(name, kind).Set(Gf.Vec3f(*value) if isinstance(value, tuple) else value)
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(shader.ConnectableAPI(), "out")
    return shader


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_inline_standard_surface_shader_renders_as_its_preview_surface(tmp_path, mode):
    """ND_standard_surface_surfaceshader authored in USD (no ``.mtlx`` file), its base
    colour connected to an input of the Material (an export's interface): the same
    image as the UsdPreviewSurface gold."""

    def gold(stage):
        shader = _inline(stage, "/Looks/Gold", "ND_standard_surface_surfaceshader",
                         metalness=1.0, specular_roughness=0.3)  # fmt: skip
        mat = UsdShade.Material(stage.GetPrimAtPath("/Looks/Gold"))
        face = mat.CreateInput("face", Sdf.ValueTypeNames.Color3f)
        face.Set(Gf.Vec3f(*GOLD))
        shader.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).ConnectToSource(face)
        _bind(stage, "/Looks/Gold")

    # standard_surface's default base weight is 1: diffuseColor is the gold itself.
    stage, got, want = _pair(
        tmp_path, gold, {"diffuseColor": GOLD, "metallic": 1.0, "roughness": 0.3}, mode
    )
    np.testing.assert_allclose(got, want, atol=SAME_IMAGE)
    assert read_stage(stage).warnings == []


def test_missing_document_keeps_one_notice(tmp_path):
    """A reference to a ``.mtlx`` that is not there: one warning naming it, the ball
    drawn with no material (row 0, UsdPreviewSurface's grey)."""
    stage = _ball_stage(tmp_path / "missing.usda")
    _reference(stage, "/Looks/Mtlx", "absent.mtlx")
    _bind(stage, "/Looks/Mtlx/gold")
    stage.GetRootLayer().Save()
    scene = read_stage(stage)
    named = [w for w in scene.warnings if "absent.mtlx" in w]
    assert len(named) == 1 and named[0].startswith("missing reference")
    assert len(scene.scene.materials.opacity) == 1  # only row 0: nothing bound


def test_material_prim_referencing_its_document_material(tmp_path):
    """A Material prim that itself references a document's material
    (``@gold.mtlx@</MaterialX/Materials/gold>``): the same row as the binding through
    a referencing scope, no warning."""
    _document(tmp_path / "gold.mtlx", "standard_surface", "gold",
              base_color=GOLD, metalness=1.0, specular_roughness=0.3)  # fmt: skip
    stage = _ball_stage(tmp_path / "direct.usda")
    mat = UsdShade.Material.Define(stage, "/Looks/Gold").GetPrim()
    mat.GetReferences().AddReference("gold.mtlx", Sdf.Path("/MaterialX/Materials/gold"))
    _bind(stage, "/Looks/Gold")
    stage.GetRootLayer().Save()
    scene = read_stage(stage)
    assert scene.warnings == []
    materials = scene.scene.materials
    np.testing.assert_allclose(materials.diffuse[1], GOLD, atol=1e-7)
    assert materials.metallic[1] == 1.0 and abs(materials.roughness[1] - 0.3) < 1e-7
    assert materials.glossy[1]  # its roughness blurs its reflections, as a preview's


def test_material_the_document_lacks_is_named(tmp_path):
    """A binding under a readable document's arc to a material the document does not
    define: grey (row 1 at UsdPreviewSurface's 0.18) and one notice naming it."""
    _document(tmp_path / "gold.mtlx", "standard_surface", "gold", metalness=1.0)
    stage = _ball_stage(tmp_path / "lacks.usda")
    _reference(stage, "/Looks/Mtlx", "gold.mtlx")
    _bind(stage, "/Looks/Mtlx/silver")
    stage.GetRootLayer().Save()
    scene = read_stage(stage)
    assert scene.warnings == [
        "/Looks/Mtlx/silver: no MaterialX material silver in the .mtlx documents "
        "referenced there; rendered grey"
    ]
    np.testing.assert_allclose(scene.scene.materials.diffuse[1], [0.18] * 3, atol=1e-7)


def test_dropped_inputs_are_named_once(tmp_path):
    """A document surface authoring what the mapping leaves out (sheen, a metal's edge
    tint, a coat IOR other than the base's): one notice naming each, and the support
    report's row for the same surface authored in USD."""
    _document(tmp_path / "odd.mtlx", "standard_surface", "odd", metalness=1.0,
              specular_color=(1.0, 0.5, 0.5), sheen=0.5, coat=1.0, coat_IOR=2.0)  # fmt: skip
    stage = _ball_stage(tmp_path / "odd.usda")
    _reference(stage, "/Looks/Mtlx", "odd.mtlx")
    _bind(stage, "/Looks/Mtlx/odd")
    _inline(stage, "/Looks/Inline", "ND_standard_surface_surfaceshader", sheen=0.5)
    stage.GetRootLayer().Save()
    (notice,) = read_stage(stage).warnings
    assert notice.startswith("/Looks/Mtlx/odd (odd.mtlx): MaterialX standard_surface")
    for name in ("sheen", "specular_color", "coat_IOR"):
        assert name in notice
    rows = {r["kind"]: r for r in support_report(stage)}
    assert rows["materialx_approximated"]["paths"] == ["/Looks/Inline"]


def test_mapping_table():
    """``map_surface`` at a few points of its table (module doc of usd/materialx.py)."""
    std = materialx.node_defaults("ND_standard_surface_surfaceshader")
    glass = materialx.map_surface("standard_surface", {"transmission": 1.0}, std)
    assert float(glass.constants["opacity"]) == 0.0  # full transmission: the glass
    assert glass.dropped == []
    # Its colour is the transmission colour (white by default), not the base weight's.
    np.testing.assert_allclose(glass.constants["diffuseColor"], (1.0, 1.0, 1.0))
    tinted = materialx.map_surface(
        "standard_surface", {"transmission": 0.5,
                             "transmission_color": np.array([0.0, 1.0, 0.0])}, std,
    )  # fmt: skip
    # 0.5 * 0.8 * 1 (base, base_color's default 0.8) + 0.5 * (0, 1, 0)
    np.testing.assert_allclose(tinted.constants["diffuseColor"], (0.4, 0.9, 0.4))
    assert float(tinted.constants["opacity"]) == 0.5
    assert any(d.startswith("transmission_color") for d in tinted.dropped)
    mixed = materialx.map_surface(
        "standard_surface", {"base": 0.5, "subsurface": 0.5,
                             "subsurface_color": np.array([1.0, 0.0, 0.0])}, std,
    )  # fmt: skip
    # 0.5 * 0.8 (base_color's default) * 0.5 + 0.5 * (1, 0, 0)
    np.testing.assert_allclose(mixed.constants["diffuseColor"], (0.7, 0.2, 0.2))
    assert any(d.startswith("subsurface") for d in mixed.dropped)
    opb = materialx.node_defaults("ND_open_pbr_surface_surfaceshader")
    glow = materialx.map_surface(
        "open_pbr_surface", {"emission_luminance": 3.0,
                             "emission_color": np.array([0.0, 1.0, 0.0])}, opb,
    )  # fmt: skip
    np.testing.assert_allclose(glow.constants["emissiveColor"], (0.0, 3.0, 0.0))


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_document_image_is_the_base_colour_texture(tmp_path, mode):
    """A ``tiledimage`` on base_color in the document (base 0.5): the quad's left half
    reads the texture's red, its right half green, times 0.5; the file resolved beside
    the document (which sits in its own folder)."""
    (tmp_path / "looks").mkdir()
    px = np.zeros((8, 8, 3))
    px[:, :4] = (1.0, 0.0, 0.0)
    px[:, 4:] = (0.0, 1.0, 0.0)
    write_image(tmp_path / "looks" / "halves.png", px)
    (tmp_path / "looks" / "quad.mtlx").write_text(
        '<?xml version="1.0"?>\n<materialx version="1.39">\n'
        '  <tiledimage name="tex" type="color3">\n'
        '    <input name="file" type="filename" value="halves.png" colorspace="srgb_texture"/>\n'
        "  </tiledimage>\n"
        '  <standard_surface name="surface" type="surfaceshader">\n'
        '    <input name="base" type="float" value="0.5"/>\n'
        '    <input name="base_color" type="color3" nodename="tex"/>\n'
        "  </standard_surface>\n"
        '  <surfacematerial name="quad" type="material">\n'
        '    <input name="surfaceshader" type="surfaceshader" nodename="surface"/>\n'
        "  </surfacematerial>\n</materialx>\n"
    )
    stage = front_view_stage(tmp_path / "quad.usda")
    st_quad(stage)
    _reference(stage, "/Looks/Mtlx", "looks/quad.mtlx")
    api = UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Quad"))
    api.GetDirectBindingRel().SetTargets([Sdf.Path("/Looks/Mtlx/quad")])
    stage.GetRootLayer().Save()
    out = first_frame(stage, mode, SIZE)
    row = SIZE // 2
    # Texel centres of the 8-texel halves: sRGB 255 and 0 decode exactly.
    np.testing.assert_allclose(out.gbuffer.albedo[row, SIZE // 4], (0.5, 0.0, 0.0), atol=1e-6)
    np.testing.assert_allclose(out.gbuffer.albedo[row, 3 * SIZE // 4], (0.0, 0.5, 0.0),
                               atol=1e-6)  # fmt: skip
