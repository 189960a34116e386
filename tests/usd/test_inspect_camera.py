"""``phrt inspect`` names the camera the render uses, by the render's own rule: the
products' camera, else the render settings' camera, else the first UsdGeomCamera, else
the default camera; and the scene the render reads agrees (``StageScene.camera_path``)."""

from __future__ import annotations

from pxr import Gf, Usd, UsdGeom, UsdRender
from scenes import clean_stage, cube_stage
from typer.testing import CliRunner

from phrt_usd.cli import app
from phrt_usd.model.render_options import RenderOptions
from phrt_usd.run.render_job import RenderJob, prepare_job
from phrt_usd.usd.default_camera import DEFAULT_CAMERA_NAME
from phrt_usd.usd.inspection import render_camera
from phrt_usd.usd.stage import read_stage


def _three_cameras(tmp_path) -> Usd.Stage:
    """/A, /B, /C cameras (in that order) looking at a cube, and /Render/Settings."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "cams.usda"))
    UsdGeom.Cube.Define(stage, "/Box")
    for name in "ABC":
        UsdGeom.Camera.Define(stage, f"/{name}").AddTranslateOp().Set(Gf.Vec3d(0, 0, 10))
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(8, 8))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return stage


def _rendered_camera(stage, tmp_path) -> str:
    """The camera path the render job reads the stage with."""
    job = RenderJob(stage.GetRootLayer().realPath, tmp_path / "out", RenderOptions())
    return prepare_job(job, read_stage(stage))[1].camera_path


def test_inspect_names_the_camera_by_the_render_rule(tmp_path):
    stage = _three_cameras(tmp_path)
    stage.GetRootLayer().Save()
    assert render_camera(stage)["path"] == "/A"
    assert render_camera(stage)["source"] == "first UsdGeomCamera"
    assert _rendered_camera(stage, tmp_path) == "/A"
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    settings.CreateCameraRel().SetTargets(["/B"])
    stage.GetRootLayer().Save()
    assert render_camera(stage)["path"] == "/B" == _rendered_camera(stage, tmp_path)
    assert render_camera(stage)["source"] == "render settings /Render/Settings"
    product = UsdRender.Product.Define(stage, "/Render/Beauty")
    product.CreateProductNameAttr("beauty.exr")
    product.CreateCameraRel().SetTargets(["/C"])
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    stage.GetRootLayer().Save()
    assert render_camera(stage)["path"] == "/C" == _rendered_camera(stage, tmp_path)
    assert render_camera(stage)["source"] == "render product"


def test_inspect_names_the_default_camera_and_a_refusal(tmp_path):
    stage = Usd.Stage.Open(str(cube_stage(tmp_path / "cube.usda")))
    assert render_camera(stage)["path"] == DEFAULT_CAMERA_NAME
    stage = _three_cameras(tmp_path)
    UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings")).CreateCameraRel().SetTargets(
        ["/Box"]
    )
    camera = render_camera(stage)
    assert camera["path"] is None and "/Box is not a UsdGeomCamera" in camera["problem"]


def test_inspect_prints_the_camera_and_its_path(tmp_path):
    stage = clean_stage(tmp_path / "clean.usda")
    stage.GetRootLayer().Save()
    out = CliRunner().invoke(app, ["inspect", str(tmp_path / "clean.usda")])
    assert out.exit_code == 0
    assert "Camera: /World/Cam (first UsdGeomCamera, driven by /World/Path)" in out.stdout
