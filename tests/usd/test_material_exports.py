"""The materials DCC exports write, read through USD and checked at an analytic pixel in
raster and rt: material interface inputs (a shader input connected to an input of its
Material, through NodeGraphs at any depth), a ``UsdPrimvarReader`` whose ``varname`` is
a Material input, instanced Materials, binding purposes on every gprim type and an unset
texture ``file``.

The stage (``_stage``): a gprim facing +Z at the origin, seen from (0, 0, 5) down -Z
(focal 50 mm, aperture 20 x 20 mm: the image spans +-2.1 m at z = 0, so the centre
pixel lies on the gprim's +Z face at its centre, whose normal is +Z), lit only by a
white dome of radiance 1. A UsdPreviewSurface under a uniform dome of radiance L returns
its directional albedo times L (``scenes.preview_shade``), so the centre pixel's linear
colour follows the albedo.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade
from scenes import preview_shade

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
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
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(20.0)
    cam.CreateVerticalApertureAttr(20.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateIntensityAttr(1.0)
    dome.CreateColorAttr(Gf.Vec3f(1, 1, 1))
    return stage


def _quad(stage, path: str = "/Quad") -> Usd.Prim:
    """A 2 x 2 quad at z = 0 facing +Z, with ``st`` from (0, 0) to (1, 1)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    ).Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    return mesh.GetPrim()


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
    scene = read_stage(stage)
    renderer = FrameRenderer(
        scene, RenderOptions(mode=mode, heuristic="all", width=W, height=H, budget_ms=None)
    )
    try:
        out = renderer.render(scene.frame_range[0])
        assert out.gbuffer.element_id[H // 2, W // 2] >= 0, "the centre pixel misses the gprim"
        return np.asarray(out.beauty[H // 2, W // 2], np.float64)
    finally:
        renderer.close()


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
