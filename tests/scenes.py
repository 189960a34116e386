"""Small USD stages authored for tests (fast to render, with known geometry)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux, UsdRender

import phrt_usd  # noqa: F401  (registers the schema before any stage opens)
from phrt_usd.usd import schema

SPHERE_CENTER = np.array([0.0, 1.0, 0.0])
SPHERE_RADIUS = 0.5
EYE = np.array([0.0, 2.0, 5.0])
TARGET = np.array([0.0, 0.2, 0.0])


def _look_at_matrix(eye: np.ndarray, target: np.ndarray) -> Gf.Matrix4d:
    """World-from-camera for a USD camera (looks down -Z, +Y up) at eye, facing target."""
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = r, u, -f, eye  # USD: row vectors
    return Gf.Matrix4d(m.tolist())


def _quad(stage: Usd.Stage, path: str, half: float, color) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateDisplayColorAttr([color])
    return mesh


def _common(stage: Usd.Stage, width: int, height: int) -> UsdGeom.Camera:
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-60, 30, 0))
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.3, 0.5, 0.9))
    dome.CreateIntensityAttr(0.5)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * height / width)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(width, height))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    schema.apply_render_settings(settings.GetPrim(), budget_ms=1000.0)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return cam


def mirror_floor_stage(path: Path, width: int = 160, height: int = 120) -> Path:
    """A 10 m mirror floor at y = 0 (F = 1), a red sphere above it, a fixed camera."""
    stage = Usd.Stage.CreateNew(str(path))
    cam = _common(stage, width, height)
    UsdGeom.Xformable(cam).AddTransformOp().Set(_look_at_matrix(EYE, TARGET))
    floor = _quad(stage, "/World/Floor", 5.0, (0.2, 0.2, 0.2))
    schema.apply_reflector(floor.GetPrim(), priority=1.0, reflectivity=1.0)
    sphere = UsdGeom.Sphere.Define(stage, "/World/Ball")
    sphere.CreateRadiusAttr(SPHERE_RADIUS)
    sphere.CreateDisplayColorAttr([(0.9, 0.05, 0.05)])
    UsdGeom.Xformable(sphere).AddTranslateOp().Set(Gf.Vec3d(*SPHERE_CENTER))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.GetRootLayer().Save()
    return path


def mirror_gallery_stage(path: Path, frames: int = 40, width: int = 64, height: int = 48) -> Path:
    """Five mirror panels of different priorities around a floor, and a camera path that
    sweeps past them over ``frames`` frames (for render-job and heuristic tests)."""
    stage = Usd.Stage.CreateNew(str(path))
    cam = _common(stage, width, height)
    _quad(stage, "/World/Ground", 20.0, (0.4, 0.6, 0.3))
    for i in range(5):
        x = -8.0 + 4.0 * i
        panel = _quad(stage, f"/World/Mirror{i}", 1.0, (0.5, 0.5, 0.5))
        xf = UsdGeom.Xformable(panel)
        xf.AddTranslateOp().Set(Gf.Vec3d(x, 1.0, -3.0 + (i % 2)))
        xf.AddRotateXOp().Set(80.0)
        schema.apply_reflector(panel.GetPrim(), priority=1.0 + i, reflectivity=0.8)
        ball = UsdGeom.Sphere.Define(stage, f"/World/Ball{i}")
        ball.CreateRadiusAttr(0.4)
        ball.CreateDisplayColorAttr([(0.2 * i, 0.3, 1.0 - 0.2 * i)])
        UsdGeom.Xformable(ball).AddTranslateOp().Set(Gf.Vec3d(x + 1.0, 0.4, 0.0))
    keys = np.array([1.0, 1.0 + 0.5 * (frames - 1), frames])
    positions = [(-10.0, 1.6, 6.0), (0.0, 1.8, 5.0), (10.0, 1.6, 6.0)]
    targets = [(-6.0, 1.0, -3.0), (0.0, 1.0, -3.0), (6.0, 1.0, -3.0)]
    schema.define_camera_path(
        stage, "/World/CameraPath", cam.GetPath(), positions, targets, keys, 1.0, float(frames)
    )
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    stage.GetRootLayer().Save()
    return path


def mirrored_sphere_pixels(camera, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels whose ray, mirrored in the plane y = 0, hits the sphere.

    A ray reflected by the floor hits the sphere exactly where the straight ray from the
    eye hits the sphere mirrored through the floor (centre (x, -y, z)), provided the ray
    reaches the floor first, which holds for every hit of the mirrored sphere (it lies
    below the plane)."""
    origins, dirs = camera.pixel_rays(width, height)
    c = SPHERE_CENTER * np.array([1.0, -1.0, 1.0])
    oc = origins - c
    b = np.sum(oc * dirs, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - SPHERE_RADIUS**2)
    return ((disc > 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0)).reshape(height, width)
