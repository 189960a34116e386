"""Small stages made with textures written beside them (OpenImageIO), for the texture,
cut-out and normal-map tests, and their one-frame renders.

``cutout_stage``: a wall (z = -1, 6 m square, blue) behind a quad (z = 0, 2 m square,
red, ``st`` 0..1 over it), a camera at z = 5 looking down -z, a DistantLight travelling
along (sin 30°, 0, -cos 30°): a present point of the quad at x shadows the wall at
x + tan 30° (the wall is 1 m behind it). The quad's material is a cut-out
(opacityThreshold 0.5) whose opacity is a texture's alpha: 0 in the left half (x < 0),
1 in the right half.

``textured_quad_stage``: a 2 m quad at z = 0 whose ``st`` runs 0..``st_max`` along x and
0..1 along y, seen by the same camera, nothing connected to its UsdPreviewSurface yet.

``mirrored_cutout_stage``: a mirror (PhrtReflectorAPI, F = 1) at z = -1 seen by the
camera, reflecting the cut-out quad (z = 6) and the wall (z = 7) placed behind it.
"""

from __future__ import annotations

import math

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd import schema
from phrt_usd.usd.stage import read_stage

WIDTH, HEIGHT = 96, 72
WALL = (0.1, 0.2, 0.8)
QUAD = (0.9, 0.1, 0.05)
#: The light's tilt: the shadow of the quad lands tan(30°) = 0.577 m to +x on the wall.
TILT_DEG = 30.0
SHIFT = math.tan(math.radians(TILT_DEG))


def write_image(path, pixels: np.ndarray) -> None:
    """An 8-bit file of ``pixels`` (h, w, c) in [0, 1] (row 0 = top)."""
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8))
    out.write_image(np.round(np.clip(pixels, 0, 1) * 255).astype(np.uint8))
    out.close()


def write_half_alpha(path) -> None:
    """8 x 8 RGBA, white, alpha 0 in the left half (columns 0-3), 1 in the right half."""
    px = np.ones((8, 8, 4))
    px[:, :4, 3] = 0.0
    write_image(path, px)


def define_quad(stage, path, half, z, st=True):
    """A square mesh of half side ``half`` at depth ``z`` facing +z, ``st`` 0..1 over it."""
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


def define_material(stage, path, colour):
    """A rough UsdPreviewSurface of ``colour``; returns the material and its shader."""
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return mat, surf


def define_texture(stage, path, file, **inputs):
    """A UsdUVTexture of ``file`` reading primvar ``st``; ``inputs``: name → (type, value)."""
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


def cutout_stage(tmp_path, name="cutout.usda", threshold=0.5) -> Usd.Stage:
    """The cut-out stage (module doc) written into ``tmp_path``."""
    write_half_alpha(tmp_path / "half_alpha.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    wall = define_quad(stage, "/Wall", 3.0, -1.0, st=False)
    quad = define_quad(stage, "/Quad", 1.0, 0.0)
    wall_mat, _ = define_material(stage, "/Looks/Wall", WALL)
    quad_mat, surf = define_material(stage, "/Looks/Quad", QUAD)
    tex = define_texture(
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


def render_first_frame(stage, mode):
    """The stage's first frame in ``mode`` at WIDTH x HEIGHT, every reflector traced;
    returns the frame and its camera."""
    scene = read_stage(stage)
    opts = RenderOptions(mode=mode, heuristic="all", width=WIDTH, height=HEIGHT, budget_ms=None)
    renderer = FrameRenderer(scene, opts)
    try:
        out = renderer.render(scene.frame_range[0])
        return out, scene.camera(scene.frame_range[0])
    finally:
        renderer.close()


def pixel_at(camera, point) -> tuple[int, int]:
    """(row, col) of the pixel whose centre sees world ``point``."""
    x, y, _ = camera.project(np.array([point], float), WIDTH, HEIGHT)[0]
    return int(y), int(x)


def textured_quad_stage(tmp_path, st_max=1.0, name="tex.usda") -> tuple[Usd.Stage, UsdShade.Shader]:
    """The quad, its material /Looks/Quad and camera; returns the stage and the
    UsdPreviewSurface (nothing connected yet)."""
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mesh = UsdGeom.Mesh.Define(stage, "/Quad")
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    ).Set([(0, 0), (st_max, 0), (st_max, 1), (0, 1)])
    mat, surf = define_material(stage, "/Looks/Quad", (0.5, 0.5, 0.5))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set((0.0, 0.0, 5.0))
    cam.CreateFocalLengthAttr(25.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    UsdLux.DistantLight.Define(stage, "/Sun").CreateIntensityAttr(1.0)
    return stage, surf


def mirrored_cutout_stage(tmp_path) -> Usd.Stage:
    """The mirror reflecting the cut-out quad and the wall (module doc)."""
    write_half_alpha(tmp_path / "half_alpha.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / "mirror.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mirror = define_quad(stage, "/Mirror", 3.0, -1.0, st=False)
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    # The quad and wall face +z as in test_cutouts; their back faces look at the mirror.
    wall = define_quad(stage, "/Wall", 3.0, 7.0, st=False)
    quad = define_quad(stage, "/Quad", 1.0, 6.0)
    wall_mat, _ = define_material(stage, "/Looks/Wall", WALL)
    quad_mat, surf = define_material(stage, "/Looks/Quad", QUAD)
    tex = define_texture(stage, "/Looks/Quad/Alpha", "half_alpha.png")
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
    )
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    UsdShade.MaterialBindingAPI.Apply(wall.GetPrim()).Bind(wall_mat)
    UsdShade.MaterialBindingAPI.Apply(quad.GetPrim()).Bind(quad_mat)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set((0.0, 0.0, 5.0))
    cam.CreateFocalLengthAttr(25.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(1.0)
    sun.AddRotateYOp().Set(180.0)  # -Z turned to +Z: light travelling towards the wall
    stage.GetRootLayer().Save()
    return stage


def write_one_colour_png(path, rgb):
    """A 4 x 4 8-bit PNG of one colour (sRGB 255 = linear 1, 0 = 0: exact)."""
    img = np.zeros((4, 4, 3), np.uint8)
    img[:] = np.array(rgb) * 255
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(4, 4, 3, oiio.UINT8))
    out.write_image(img)
    out.close()
