"""The materials DCC exports write, read through USD and checked at an analytic pixel in
raster and rt: material interface inputs (a shader input connected to an input of its
Material, through NodeGraphs at any depth), a ``UsdPrimvarReader`` whose ``varname`` is
a Material input, instanced Materials, binding purposes on every gprim type and an unset
texture ``file``.

The stage (``_stage``): a gprim facing +Z at the origin, seen from (0, 0, 5) down -Z
(focal 50 mm, aperture 20 x 20 mm: the image spans +-1 m at z = 0, so the centre
pixel lies on the gprim's +Z face at its centre, whose normal is +Z), lit only by a
white dome of radiance 1. A UsdPreviewSurface under a uniform dome of radiance L returns
its directional albedo times L (``scenes.preview_shade``), so the centre pixel's linear
colour follows the albedo.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender, UsdShade
from scenes import centre_pixel, first_frame, front_view_stage, preview_shade, st_quad

from phrt_usd.usd.stage import read_stage

W = H = 16
MODES = ("raster", "rt")
#: Largest allowed difference from the expected colour at the centre pixel, per
#: channel: the dome's ambient term is exact, so this only absorbs float32 shading and
#: the tessellated normals of curved gprims near their +Z pole (a tilt of a few degrees
#: changes the directional albedo by well under 0.01).
TOLERANCE = 0.02
RED, BLUE, GREEN = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
GREY = (0.18, 0.18, 0.18)  # UsdPreviewSurface's fallback diffuseColor


def _look(colour) -> np.ndarray:
    """(3,) the centre pixel of a material of albedo ``colour`` (its other inputs the
    fallbacks) under the white dome, seen face on from (0, 0, 5)."""
    return preview_shade(colour, (0.0, 0.0, 0.0), (0.0, 0.0, 5.0), ambient=1.0)


def _stage(tmp_path, name: str = "exports.usda") -> Usd.Stage:
    """Camera /Cam at (0, 0, 5), white dome /Sky; no geometry yet."""
    return front_view_stage(tmp_path / name)


def _quad(stage, path: str = "/Quad") -> Usd.Prim:
    """A 2 x 2 quad at z = 0 facing +Z, with ``st`` from (0, 0) to (1, 1)."""
    return st_quad(stage, path).GetPrim()


def _surface(stage, material_path: str, colour=None) -> UsdShade.Shader:
    """A Material at ``material_path`` whose surface is a UsdPreviewSurface ``Surface``
    (constant diffuseColor ``colour`` when given); the shader."""
    mat = UsdShade.Material.Define(stage, material_path)
    surf = UsdShade.Shader.Define(stage, f"{material_path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    if colour is not None:
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return surf


def _bind(prim: Usd.Prim, material_path: str, purpose=UsdShade.Tokens.allPurpose) -> None:
    mat = UsdShade.Material(prim.GetStage().GetPrimAtPath(material_path))
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat, materialPurpose=purpose)


def _centre(stage, mode: str) -> np.ndarray:
    """(3,) linear colour of the centre pixel of one frame in ``mode``."""
    return centre_pixel(stage, mode, W)


# ------------------------------------------------------------ binding purposes


def _gprim(stage, kind: str) -> Usd.Prim:
    """A gprim of type ``kind`` whose +Z face (flat, or a pole) is at the origin's side
    facing the camera: the centre pixel sees it face on."""
    if kind == "Mesh":
        return _quad(stage, "/Shape")
    prim = stage.DefinePrim("/Shape", kind)
    if kind == "Cone":
        # The base disk (local -Z) turned to face the camera: flat, normal +Z.
        UsdGeom.Xformable(prim).AddRotateXOp().Set(180.0)
    return prim


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("kind", ["Mesh", "Cube", "Sphere", "Cylinder", "Cone", "Capsule", "Plane"])
def test_binding_purposes_hold_for_every_gprim_type(tmp_path, kind, mode):
    stage = _stage(tmp_path)
    _surface(stage, "/All", RED)
    _surface(stage, "/Full", BLUE)
    _surface(stage, "/Preview", GREEN)
    prim = _gprim(stage, kind)
    _bind(prim, "/All")
    _bind(prim, "/Full", UsdShade.Tokens.full)
    _bind(prim, "/Preview", UsdShade.Tokens.preview)
    # materialBindingPurposes' fallback is ["full", ""]: the full binding.
    np.testing.assert_allclose(_centre(stage, mode), _look(BLUE), atol=TOLERANCE)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateMaterialBindingPurposesAttr(["preview", ""])
    np.testing.assert_allclose(_centre(stage, mode), _look(GREEN), atol=TOLERANCE)


# ------------------------------------------------------------ interface inputs


def _interface_material(stage, path: str, depth: int, colour) -> None:
    """Material ``path`` whose input ``base`` = ``colour`` feeds the surface's
    diffuseColor through ``depth`` nested NodeGraphs, each passing its own ``base``
    input on (the surface shader is inside the innermost one)."""
    mat = UsdShade.Material.Define(stage, path)
    source = mat.CreateInput("base", Sdf.ValueTypeNames.Color3f)
    source.Set(Gf.Vec3f(*colour))
    parent = path
    for level in range(depth):
        parent = f"{parent}/Graph{level}"
        graph = UsdShade.NodeGraph.Define(stage, parent)
        inp = graph.CreateInput("base", Sdf.ValueTypeNames.Color3f)
        inp.ConnectToSource(source)
        source = inp
    surf = UsdShade.Shader.Define(stage, f"{parent}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(source)
    out = surf.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    mat.CreateSurfaceOutput().ConnectToSource(out)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("depth", [0, 2])
def test_material_interface_inputs_at_any_depth(tmp_path, depth, mode):
    stage = _stage(tmp_path)
    _interface_material(stage, "/M", depth, RED)
    _bind(_quad(stage), "/M")
    np.testing.assert_allclose(_centre(stage, mode), _look(RED), atol=TOLERANCE)


def _reader_material(stage, path: str, reader_id: str, varname: str) -> UsdShade.Shader:
    """Material ``path`` with a UsdPrimvarReader ``reader_id`` whose ``varname`` is
    connected to the Material's input ``frame:primvarName`` = ``varname`` (the export
    Houdini and Maya write); the reader."""
    surf = _surface(stage, path)
    mat = UsdShade.Material(stage.GetPrimAtPath(path))
    name = mat.CreateInput("frame:primvarName", Sdf.ValueTypeNames.Token)
    name.Set(varname)
    reader = UsdShade.Shader.Define(stage, f"{path}/Reader")
    reader.CreateIdAttr(reader_id)
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).ConnectToSource(name)
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    return reader


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("gprim", ["Mesh", "Sphere"])
def test_probe_primvar_reader_varname_from_a_material_input(tmp_path, gprim, mode):
    stage = _stage(tmp_path)
    reader = _reader_material(stage, "/M", "UsdPrimvarReader_float3", "Cd")
    surf = UsdShade.Shader(stage.GetPrimAtPath("/M/Surface"))
    surf.GetInput("diffuseColor").ConnectToSource(reader.GetOutput("result"))
    prim = _gprim(stage, gprim)
    primvars = UsdGeom.PrimvarsAPI(prim)
    primvars.CreatePrimvar("Cd", Sdf.ValueTypeNames.Color3fArray, "constant").Set([BLUE])
    # A displayColor the material does not name is not the colour.
    primvars.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray).Set([GREEN])
    _bind(prim, "/M")
    np.testing.assert_allclose(_centre(stage, mode), _look(BLUE), atol=TOLERANCE)


@pytest.mark.parametrize("mode", MODES)
def test_texture_st_from_a_primvar_named_by_a_material_input(tmp_path, mode):
    """The UsdUVTexture's ``st`` read through a reader whose ``varname`` is the
    Material's input naming ``uv``: ``uv`` puts every corner at (5, 5), outside the
    texture, where wrap ``black`` gives black; ``st`` (not named) would give red."""
    from textured_stages import write_one_colour_png

    write_one_colour_png(tmp_path / "red.png", RED)
    stage = _stage(tmp_path)
    reader = _reader_material(stage, "/M", "UsdPrimvarReader_float2", "uv")
    tex = UsdShade.Shader.Define(stage, "/M/Texture")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("red.png")
    for axis in ("wrapS", "wrapT"):
        tex.CreateInput(axis, Sdf.ValueTypeNames.Token).Set("black")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.GetOutput("result"))
    surf = UsdShade.Shader(stage.GetPrimAtPath("/M/Surface"))
    surf.GetInput("diffuseColor").ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    quad = _quad(stage)
    UsdGeom.PrimvarsAPI(quad).CreatePrimvar(
        "uv", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    ).Set([(5, 5)] * 4)
    _bind(quad, "/M")
    np.testing.assert_allclose(_centre(stage, mode), _look((0, 0, 0)), atol=TOLERANCE)


# ------------------------------------------------------------ instanced materials


def _instanced_stage(tmp_path) -> Usd.Stage:
    """/Lib/Asset (a class): a quad bound to /Lib/Asset/Looks/Paint, a Material with
    interface input ``base`` = red through one NodeGraph; /Lib/Paint (a class): a
    Material of interface input ``base`` = grey. /Twin: the asset as a plain
    reference; /Inst: the same asset, instanceable (quad and Material are instance
    proxies). Only one of the two is active in a test (they overlap)."""
    stage = _stage(tmp_path)
    stage.CreateClassPrim("/Lib")
    _interface_material(stage, "/Lib/Asset/Looks/Paint", 1, RED)
    _bind(_quad(stage, "/Lib/Asset/Quad"), "/Lib/Asset/Looks/Paint")
    for name, instanceable in (("Twin", False), ("Inst", True)):
        prim = stage.DefinePrim(f"/{name}", "Xform")
        prim.GetReferences().AddInternalReference("/Lib/Asset")
        prim.SetInstanceable(instanceable)
    return stage


@pytest.mark.parametrize("mode", MODES)
def test_instanced_material_shades_as_its_twin(tmp_path, mode):
    stage = _instanced_stage(tmp_path)
    stage.GetPrimAtPath("/Inst").SetActive(False)
    twin = _centre(stage, mode)
    stage.GetPrimAtPath("/Inst").SetActive(True)
    stage.GetPrimAtPath("/Twin").SetActive(False)
    assert stage.GetPrimAtPath("/Inst/Quad").IsInstanceProxy()
    np.testing.assert_allclose(_centre(stage, mode), twin, atol=1e-6)
    np.testing.assert_allclose(twin, _look(RED), atol=TOLERANCE)


@pytest.mark.parametrize("mode", MODES)
def test_instanceable_material_takes_its_own_inputs(tmp_path, mode):
    """Materials that are themselves instances of one library Material (the prototype
    holds the shaders) with their own ``base`` on each instance root: each shades in
    its own colour, bound from outside and from inside an instance."""
    stage = _stage(tmp_path)
    stage.CreateClassPrim("/Lib")
    _interface_material(stage, "/Lib/Paint", 1, GREY)
    for name, colour in (("Red", RED), ("Blue", BLUE)):
        mat = stage.DefinePrim(f"/Looks/{name}", "Material")
        mat.GetReferences().AddInternalReference("/Lib/Paint")
        mat.SetInstanceable(True)
        UsdShade.Material(mat).CreateInput("base", Sdf.ValueTypeNames.Color3f).Set(
            Gf.Vec3f(*colour)
        )
    quad = _quad(stage)
    _bind(quad, "/Looks/Blue")
    np.testing.assert_allclose(_centre(stage, mode), _look(BLUE), atol=TOLERANCE)
    _bind(quad, "/Looks/Red")
    np.testing.assert_allclose(_centre(stage, mode), _look(RED), atol=TOLERANCE)


# ------------------------------------------------------------ unset texture file


def _textured(stage, file: str | None) -> None:
    """/M: diffuseColor from a UsdUVTexture of ``file`` (unset when None), no
    ``fallback`` authored; bound to a quad whose displayColor is light blue."""
    surf = _surface(stage, "/M")
    tex = UsdShade.Shader.Define(stage, "/M/Texture")
    tex.CreateIdAttr("UsdUVTexture")
    if file is not None:
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    quad = _quad(stage)
    UsdGeom.PrimvarsAPI(quad).CreatePrimvar(
        "displayColor", Sdf.ValueTypeNames.Color3fArray
    ).Set([(0.6, 0.8, 1.0)])
    _bind(quad, "/M")


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("file", [None, "missing.png"])
def test_probe_unset_texture_file_takes_the_input_fallback(tmp_path, file, mode):
    stage = _stage(tmp_path)
    _textured(stage, file)
    np.testing.assert_allclose(_centre(stage, mode), _look(GREY), atol=TOLERANCE)
    warnings = read_stage(stage).warnings
    missing = [w for w in warnings if "/M/Texture.inputs:file" in w]
    assert len(missing) == (0 if file is None else 1), warnings


@pytest.mark.parametrize("mode", MODES)
def test_instances_of_one_prototype_bound_per_instance_root(tmp_path, mode):
    """Two instances of one quad (/A at x < 0, /B at x > 0, each half the image's
    width), bound on their instance roots to red and blue: each instance proxy takes its
    root's binding (the image spans +-1 m: pixel column 2 is on /A, 13 on /B)."""
    stage = _stage(tmp_path)
    stage.CreateClassPrim("/Lib")
    _quad(stage, "/Lib/Asset/Quad")
    _surface(stage, "/Looks/Red", RED)
    _surface(stage, "/Looks/Blue", BLUE)
    for name, material, x in (("A", "/Looks/Red", -1.0), ("B", "/Looks/Blue", 1.0)):
        root = stage.DefinePrim(f"/{name}", "Xform")
        root.GetReferences().AddInternalReference("/Lib/Asset")
        root.SetInstanceable(True)
        UsdGeom.Xformable(root).AddTranslateOp().Set(Gf.Vec3d(x, 0, 0))
        UsdGeom.Xformable(root).AddScaleOp().Set(Gf.Vec3f(0.5, 0.5, 1))
        _bind(root, material)
    beauty = first_frame(stage, mode, W, H).beauty
    np.testing.assert_allclose(beauty[H // 2, 2], _look(RED), atol=TOLERANCE)
    np.testing.assert_allclose(beauty[H // 2, W - 3], _look(BLUE), atol=TOLERANCE)


@pytest.mark.parametrize("mode", MODES)
def test_texture_file_from_a_material_input(tmp_path, mode):
    """A UsdUVTexture's ``file`` connected to an asset input of its Material (how
    Houdini exposes a texture path) reads the file the Material's input names."""
    from textured_stages import write_one_colour_png

    write_one_colour_png(tmp_path / "blue.png", BLUE)
    stage = _stage(tmp_path)
    surf = _surface(stage, "/M")
    mat = UsdShade.Material(stage.GetPrimAtPath("/M"))
    path = mat.CreateInput("baseColorTexture", Sdf.ValueTypeNames.Asset)
    path.Set("blue.png")
    tex = UsdShade.Shader.Define(stage, "/M/Texture")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).ConnectToSource(path)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    _bind(_quad(stage), "/M")
    np.testing.assert_allclose(_centre(stage, mode), _look(BLUE), atol=TOLERANCE)


@pytest.mark.parametrize("mode", MODES)
def test_instanced_material_in_a_point_instancer_prototype(tmp_path, mode):
    """A PointInstancer whose prototype is an instanceable reference to an asset with
    its own Material (interface input through two NodeGraphs): the instance shades in
    the Material's input colour."""
    stage = _stage(tmp_path)
    stage.CreateClassPrim("/Lib")
    _interface_material(stage, "/Lib/Asset/Looks/Paint", 2, RED)
    _bind(_quad(stage, "/Lib/Asset/Quad"), "/Lib/Asset/Looks/Paint")
    instancer = UsdGeom.PointInstancer.Define(stage, "/Scatter")
    proto = stage.DefinePrim("/Scatter/Protos/Asset", "Xform")
    proto.GetReferences().AddInternalReference("/Lib/Asset")
    proto.SetInstanceable(True)
    instancer.CreatePrototypesRel().SetTargets([proto.GetPath()])
    instancer.CreateProtoIndicesAttr([0])
    instancer.CreatePositionsAttr([(0, 0, 0)])
    np.testing.assert_allclose(_centre(stage, mode), _look(RED), atol=TOLERANCE)


@pytest.mark.parametrize("mode", MODES)
def test_an_unread_node_is_named_and_the_input_takes_its_fallback(tmp_path, mode):
    """diffuseColor fed by a math node the render does not run: the spec's fallback
    0.18 renders, and one notice names the material, the input and the node."""
    stage = _stage(tmp_path)
    surf = _surface(stage, "/M")
    tint = UsdShade.Shader.Define(stage, "/M/Tint")
    tint.CreateIdAttr("ND_multiply_color3")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tint.CreateOutput("out", Sdf.ValueTypeNames.Color3f)
    )
    _bind(_quad(stage), "/M")
    np.testing.assert_allclose(_centre(stage, mode), _look(GREY), atol=TOLERANCE)
    notices = [w for w in read_stage(stage).warnings if w.startswith("/M:")]
    assert notices == [
        "/M: diffuseColor (ND_multiply_color3) fed by nodes the render does not run; "
        "rendered with the inputs' fallbacks"
    ]


def test_inspect_reads_an_opacity_exposed_on_the_material(tmp_path):
    """An opacity of 0.3 set on the Material's input (the shader's input connected to
    it) is translucent: inspect lists the refraction pass, as for a shader's own."""
    from phrt_usd.usd.inspection import inspect_stage

    stage = _stage(tmp_path)
    surf = _surface(stage, "/M", RED)
    fade = UsdShade.Material(stage.GetPrimAtPath("/M")).CreateInput(
        "fade", Sdf.ValueTypeNames.Float
    )
    fade.Set(0.3)
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(fade)
    _bind(_quad(stage), "/M")
    assert "refraction" in inspect_stage(stage)["passes"]
    fade.Set(1.0)
    assert "refraction" not in inspect_stage(stage)["passes"]
