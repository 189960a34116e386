"""phrt_usd.validation: one issue line per planted problem, clean stage passes."""

import pytest
from pxr import Gf, Usd, UsdGeom, UsdRender

from phrt_usd import schema
from phrt_usd.errors import PhrtError
from phrt_usd.validation import validate_file, validate_stage


def clean_stage(path):
    """A valid stage: metadata, a quad mirror, a camera, a camera path, render settings."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/World/Mirror")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    schema.apply_reflector(mesh.GetPrim(), priority=2.0, reflectivity=0.5)
    UsdGeom.Camera.Define(stage, "/World/Cam")
    schema.define_camera_path(
        stage, "/World/Path", "/World/Cam", [(0, 1, 5), (1, 1, 5)], [(0, 0, 0), (0, 0, 0)], [1, 24]
    )
    settings = UsdRender.Settings.Define(stage, "/World/Render")
    settings.CreateResolutionAttr(Gf.Vec2i(320, 240))
    schema.apply_render_settings(settings.GetPrim(), heuristic="heu1", budget_ms=10.0)
    return stage


def errors_of(stage):
    return [i.line() for i in validate_stage(stage).errors]


def test_clean_stage_passes(tmp_path):
    report = validate_stage(clean_stage(tmp_path / "s.usda"))
    assert report.ok, [i.line() for i in report.issues]
    assert report.as_dict()["errors"] == []


@pytest.mark.parametrize(
    "plant, expected",
    [
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(-1.0),
         "ERROR /World/Mirror.phrt:priority:"),
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(float("nan")),
         "ERROR /World/Mirror.phrt:priority:"),
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.REFLECTIVITY).Set(1.5),
         "ERROR /World/Mirror.phrt:reflectivity:"),
        (lambda s: UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror")).GetPointsAttr().Set(
            [(0, 0, 0), (float("inf"), 0, 0), (1, 1, 0), (0, 1, 0)]),
         "ERROR /World/Mirror.points:"),
        (lambda s: UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror")).GetPointsAttr().Set([]),
         "ERROR /World/Mirror.points: mesh reflector has no points"),
        (lambda s: UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror")).GetFaceVertexCountsAttr().Set(
            [2, 2]),
         "ERROR /World/Mirror.faceVertexCounts:"),
        (lambda s: UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror")).GetFaceVertexCountsAttr().Set(
            [5]),
         "ERROR /World/Mirror.faceVertexIndices: has 4 entries"),
        (lambda s: UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror")).GetFaceVertexIndicesAttr().Set(
            [0, 1, 2, 7]),
         "ERROR /World/Mirror.faceVertexIndices: index 7 out of range"),
        (lambda s: s.DefinePrim("/World/Group", "Xform").AddAppliedSchema(schema.REFLECTOR_API),
         "ERROR /World/Group:"),
        (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.KEY_TIMES).Set([24.0, 1.0]),
         "ERROR /World/Path.phrt:keyTimes: not strictly increasing"),
        (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.INTERPOLATION).Set("cubic"),
         "ERROR /World/Path.phrt:interpolation:"),
        (lambda s: s.GetPrimAtPath("/World/Path").GetRelationship(schema.CAMERA).SetTargets(
            ["/World/Mirror"]),
         "ERROR /World/Path.phrt:camera: target /World/Mirror is not a UsdGeomCamera"),
        (lambda s: s.GetPrimAtPath("/World/Render").GetAttribute(schema.BOUNCE_LIMIT).Set(17),
         "ERROR /World/Render.phrt:bounceLimit:"),
        (lambda s: s.GetPrimAtPath("/World/Render").GetAttribute(schema.BUDGET_MS).Set(-1.0),
         "ERROR /World/Render.phrt:budgetMs:"),
        (lambda s: s.GetPrimAtPath("/World/Render").GetAttribute(schema.HEURISTIC).Set("best"),
         "ERROR /World/Render.phrt:heuristic:"),
        (lambda s: s.GetPrimAtPath("/World/Render").GetAttribute(schema.MODE).Set("fast"),
         "ERROR /World/Render.phrt:mode:"),
    ],
)  # fmt: skip
def test_planted_problem_gives_one_error_line(tmp_path, plant, expected):
    stage = clean_stage(tmp_path / "s.usda")
    plant(stage)
    lines = errors_of(stage)
    assert len(lines) == 1, lines
    assert lines[0].startswith(expected), lines
    assert "\n" not in lines[0]


def test_camera_path_length_mismatch_and_start_after_end(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    path = stage.GetPrimAtPath("/World/Path")
    path.GetAttribute(schema.TARGETS).Set([(0, 0, 0)])
    path.GetAttribute(schema.START_FRAME).Set(30.0)
    lines = errors_of(stage)
    assert any("different lengths (2, 1, 2)" in line for line in lines), lines
    assert any(line.startswith("ERROR /World/Path.phrt:startFrame:") for line in lines), lines


def test_zero_area_mirror_is_a_warning_only(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Mirror")).GetPointsAttr().Set([(0, 0, 0)] * 4)
    report = validate_stage(stage)
    assert report.ok
    assert [i.line() for i in report.warnings] == [
        "WARNING /World/Mirror.points: mesh reflector has zero area"
    ]


def test_usd_validator_findings_are_reported(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    stage.GetRootLayer().ClearDefaultPrim()
    lines = errors_of(stage)
    assert len(lines) == 1 and "defaultPrim" in lines[0], lines


@pytest.mark.parametrize("kind", ["missing", "directory", "garbage", "extension"])
def test_unreadable_input_is_one_line_phrt_error(tmp_path, kind):
    target = {
        "missing": tmp_path / "nope.usda",
        "directory": tmp_path,
        "garbage": tmp_path / "junk.usda",
        "extension": tmp_path / "junk.txt",
    }[kind]
    if kind in ("garbage", "extension"):
        target.write_text("this is not usd {{{")
    with pytest.raises(PhrtError) as err:
        validate_file(target)
    assert "\n" not in str(err.value) and str(target) in str(err.value)
