"""The light-count benchmark's stage: a floor lit by N sphere lights on a square grid,
spread so that each floor point is within reach of only a few of them, seen whole from
above (``tools/bench_lights.py``; the culled and full shading are compared on it in
``tests/engine/test_light_culling.py``).

Geometry, world metres, +Y up: a grey floor at y = 0 of side ``LIGHT_SPACING × c`` (c
= ceil(sqrt(N)) lights a row), a pillar beside every light (a shadow caster for its
maps), the lights ``LIGHT_HEIGHT`` above the floor at the cell centres, each of radiance
``LIGHT_RADIANCE`` (so of range ``sqrt(LIGHT_RADIANCE / LIGHT_CUTOFF_IRRADIANCE)``,
``shading.light_ranges``); a dim dome; a camera looking straight down from the height
that frames the floor, so every light is in view and a pixel's footprint grows with the
floor (the pixels stay the same: the lights a pixel is reached by stay about the same
whatever N).
"""

from __future__ import annotations

import math
from pathlib import Path

from pxr import Gf, Usd, UsdGeom, UsdLux, UsdRender

#: Metres between neighbouring lights (and the side of a floor cell).
LIGHT_SPACING = 8.0
#: Metres of the lights above the floor.
LIGHT_HEIGHT = 1.0
#: The sphere lights' radius, metres.
LIGHT_RADIUS = 0.1
#: Each light's radiance (``LocalLight.radiance``, intensity × π r², white): 1.28 gives a
#: range of 8 m at the shading's 0.02 cut-off, so a floor point is within reach of the
#: lights within sqrt(8² - 1²) = 7.9 m of it: 1 to 5 of the grid's (π 7.9² / 8² ≈ 3.1
#: on average), whatever N; right below a light the floor gets 1.28, 64 times the
#: cut-off (the sewer's lamps: 100 to 300 times).
LIGHT_RADIANCE = 1.28
#: The camera's focal length and film back (mm): a 73.7° × 58.7° field of view.
FOCAL_MM, APERTURE_MM = 24.0, 36.0


def lights_a_row(n_lights: int) -> int:
    """Lights on a row of the square grid holding ``n_lights``."""
    return max(1, math.ceil(math.sqrt(n_lights)))


def light_grid_stage(path: Path, n_lights: int, width: int = 320, height: int = 240) -> Path:
    """Writes the stage (see the module) with ``n_lights`` sphere lights and render
    settings of ``width`` x ``height`` to ``path``; returns it. One time code (1)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    row = lights_a_row(n_lights)
    side = LIGHT_SPACING * row
    half = side / 2.0
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    floor.CreatePointsAttr([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateDisplayColorAttr([(0.6, 0.6, 0.6)])
    area = math.pi * LIGHT_RADIUS * LIGHT_RADIUS
    for k in range(n_lights):
        x = -half + LIGHT_SPACING * (k % row + 0.5)
        z = -half + LIGHT_SPACING * (k // row + 0.5)
        light = UsdLux.SphereLight.Define(stage, f"/World/Lights/Light_{k}")
        light.CreateRadiusAttr(LIGHT_RADIUS)
        light.CreateIntensityAttr(LIGHT_RADIANCE / area)
        light.CreateColorAttr(Gf.Vec3f(1.0, 0.9 + 0.1 * (k % 2), 0.8 + 0.2 * (k % 3 == 0)))
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(x, LIGHT_HEIGHT, z))
        pillar = UsdGeom.Cube.Define(stage, f"/World/Pillars/Pillar_{k}")
        pillar.CreateSizeAttr(1.0)
        pillar.CreateDisplayColorAttr([(0.7, 0.5, 0.3)])
        ops = UsdGeom.Xformable(pillar)
        ops.AddTranslateOp().Set(Gf.Vec3d(x + 0.8, 0.75, z + 0.5))
        ops.AddScaleOp().Set(Gf.Vec3f(0.3, 1.5, 0.3))
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateIntensityAttr(0.05)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(FOCAL_MM)
    cam.CreateHorizontalApertureAttr(APERTURE_MM)
    cam.CreateVerticalApertureAttr(APERTURE_MM * height / width)
    # Straight down, the floor's shorter extent (the image's height) filling the frame.
    tan_half = (APERTURE_MM * height / width) / 2.0 / FOCAL_MM
    eye = half / tan_half
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, eye * 2.0))
    ops = UsdGeom.Xformable(cam)
    ops.AddTranslateOp().Set(Gf.Vec3d(0.0, eye, 0.0))
    ops.AddRotateXOp().Set(-90.0)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(width, height))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.GetRootLayer().Save()
    return path
