"""phrt_usd.usd.validation: one issue line per planted problem, clean stage passes."""

import math
import re

import pytest
from pxr import Gf, Sdf, UsdGeom, UsdRender, UsdShade
from scenes import clean_stage

from phrt_usd.errors import PhrtError
from phrt_usd.usd import schema
from phrt_usd.usd import stage as sr
from phrt_usd.usd.stage import open_usd, read_stage
from phrt_usd.usd.validation import validate_file, validate_stage


def errors_of(stage):
    return [i.line() for i in validate_stage(stage).errors]


def test_clean_stage_passes(tmp_path):
    report = validate_stage(clean_stage(tmp_path / "s.usda"))
    assert report.ok, [i.line() for i in report.issues]
    assert report.as_dict()["errors"] == []


def _mirror(s):
    return UsdGeom.Mesh(s.GetPrimAtPath("/World/Mirror"))


@pytest.mark.slow
@pytest.mark.parametrize(
    "plant, expected",
    [
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(-1.0),
         "ERROR /World/Mirror.phrt:priority: must be a finite number >= 0, got -1.0"),
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(float("nan")),
         "ERROR /World/Mirror.phrt:priority:"),
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.REFLECTIVITY).Set(
            float("inf")),
         "ERROR /World/Mirror.phrt:reflectivity: must be finite"),
        (lambda s: _mirror(s).GetPointsAttr().Set(
            [(0, 0, 0), (float("inf"), 0, 0), (1, 1, 0), (0, 1, 0)]),
         "ERROR /World/Mirror.points: non-finite point at index 1"),
        (lambda s: _mirror(s).GetPointsAttr().Set([]),
         "ERROR /World/Mirror.faceVertexIndices: index out of range [0, 0)"),
        (lambda s: _mirror(s).GetFaceVertexCountsAttr().Set([5]),
         "ERROR /World/Mirror.faceVertexIndices: 4 indices but faceVertexCounts sums to 5"),
        (lambda s: _mirror(s).GetFaceVertexIndicesAttr().Set([0, 1, 2, 7]),
         "ERROR /World/Mirror.faceVertexIndices: index out of range [0, 4)"),
        (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.KEY_TIMES).Set([24.0, 1.0]),
         "ERROR /World/Path.phrt:keyTimes: times must be finite and strictly increasing"),
        (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.INTERPOLATION).Set("cubic"),
         "ERROR /World/Path.phrt:interpolation:"),
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
    assert errors_of(stage) == [
        "ERROR /World/Path: phrt:positions has 2 points but phrt:targets has 1",
        "ERROR /World/Path: frame range [30.0, 24.0] is empty or not finite",
    ]


def test_zero_area_mirror_is_a_warning_only(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Mirror")).GetPointsAttr().Set([(0, 0, 0)] * 4)
    report = validate_stage(stage)
    assert report.ok
    assert [i.line() for i in report.warnings] == [
        "WARNING /World/Mirror.points: mesh reflector has zero area"
    ]


@pytest.mark.slow
@pytest.mark.parametrize(
    "plant, expected",
    [
        (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.REFLECTIVITY).Set(1.5),
         ["WARNING /World/Mirror.phrt:reflectivity: reflectivity F = 1.5 is outside 0..1: "
          "the renderer clamps it"]),
        (lambda s: _mirror(s).GetFaceVertexCountsAttr().Set([2, 2]),
         ["WARNING /World/Mirror.faceVertexCounts: 2 face(s) with fewer than 3 vertices "
          "(first: face 0, 2 vertices) are skipped by the renderer",
          "WARNING /World/Mirror.points: mesh reflector has zero area"]),
        (lambda s: (_mirror(s).GetFaceVertexCountsAttr().Set([]),
                    _mirror(s).GetFaceVertexIndicesAttr().Set([])),
         ["WARNING /World/Mirror.faceVertexCounts: mesh reflector has no faces"]),
        (lambda s: s.DefinePrim("/World/Group", "Xform").AddAppliedSchema(schema.REFLECTOR_API),
         ["WARNING /World/Group: PhrtReflectorAPI on a Xform: the renderer draws only Mesh, "
          "Sphere, Cube, Cylinder, Cone, Capsule, Plane, BasisCurves and ignores it"]),
        (lambda s: s.GetPrimAtPath("/World/Path").GetRelationship(schema.CAMERA).SetTargets(
            ["/World/Mirror"]),
         ["WARNING /World/Path.phrt:camera: targets /World/Mirror, not a UsdGeomCamera: "
          "the renderer ignores this path"]),
        (lambda s: schema.define_camera_path(
            s, "/World/Path2", "/World/Cam", [(0, 1, 5), (1, 1, 5)], [(0, 0, 0)] * 2, [1, 9]),
         ["WARNING /World/Path2: ignored: /World/Path already drives /World/Cam"]),
        # Render accepts unauthored key times (spread evenly) and a single control point.
        (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.KEY_TIMES).Clear(), []),
        (lambda s: [s.GetPrimAtPath("/World/Path").GetAttribute(n).Set(v) for n, v in (
            (schema.POSITIONS, [(0, 1, 5)]), (schema.TARGETS, [(0, 0, 0)]),
            (schema.KEY_TIMES, [1.0]))], []),
    ],
)  # fmt: skip
def test_what_render_accepts_is_never_an_error(tmp_path, plant, expected):
    stage = clean_stage(tmp_path / "s.usda")
    plant(stage)
    report = validate_stage(stage)
    assert report.ok, [i.line() for i in report.errors]
    assert [i.line() for i in report.warnings] == expected
    read_stage(stage)  # and the render reads it


def test_usd_validator_findings_are_reported(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    stage.GetRootLayer().ClearDefaultPrim()
    lines = errors_of(stage)
    assert len(lines) == 1 and "defaultPrim" in lines[0], lines


@pytest.mark.parametrize(
    "kind", ["missing", "directory", "garbage", "crate", "extension", "no extension"]
)
def test_unreadable_input_is_one_line_phrt_error(tmp_path, kind):
    target = {
        "missing": tmp_path / "nope.usda",
        "directory": tmp_path,
        "garbage": tmp_path / "junk.usda",
        "crate": tmp_path / "junk.usdc",
        "extension": tmp_path / "junk.txt",
        "no extension": tmp_path / "stage",
    }[kind]
    if kind not in ("missing", "directory"):
        target.write_bytes(b"#usda 1.0\n this is not usd {{{ \x00\xff")
    with pytest.raises(PhrtError) as err:
        validate_file(target)
    assert "\n" not in str(err.value) and str(target) in str(err.value)
    with pytest.raises(PhrtError) as render_err:  # the same implementation opens for render
        sr.open_stage(target)
    assert str(render_err.value) == str(err.value)


# --- validate agrees with render ------------------------------------------------------------
def _camera(s):
    return UsdGeom.Camera(s.GetPrimAtPath("/World/Cam"))


def _no_camera(s):
    s.RemovePrim("/World/Path")
    s.RemovePrim("/World/Cam")


def _free_camera_at(s, position):
    """The camera without its path, placed by its own transform."""
    s.RemovePrim("/World/Path")
    _camera(s).AddTranslateOp().Set(Gf.Vec3d(*position))


def _nan_floor(s):
    floor = UsdGeom.Mesh.Define(s, "/World/Floor")  # not a reflector: the render reads it too
    floor.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 0, math.nan)])
    floor.CreateFaceVertexCountsAttr([3])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2])


def _missing_texture(s):
    material = UsdShade.Material.Define(s, "/World/Looks/Tex")
    surface = UsdShade.Shader.Define(s, "/World/Looks/Tex/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    texture = UsdShade.Shader.Define(s, "/World/Looks/Tex/Image")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("no_such_image.png")
    rgb = texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    mirror = s.GetPrimAtPath("/World/Mirror")
    UsdShade.MaterialBindingAPI.Apply(mirror).Bind(material)


def _short_display_color(s):
    pv = UsdGeom.PrimvarsAPI(s.GetPrimAtPath("/World/Mirror")).CreatePrimvar(
        "displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex
    )
    pv.Set([(1, 0, 0), (0, 1, 0)])


def _bad_instancer(s):
    UsdGeom.Sphere.Define(s, "/World/Trees/Proto")
    pi = UsdGeom.PointInstancer.Define(s, "/World/Trees")
    pi.CreatePrototypesRel().SetTargets(["/World/Trees/Proto"])
    pi.CreatePositionsAttr([(0, 0, 0), (1, 0, 0)])
    pi.CreateProtoIndicesAttr([0, 3])


#: Every refusal path of ``read_stage``: (plant, a fragment of the render's message).
RENDER_REFUSALS = [
    (lambda s: _camera(s).GetFocalLengthAttr().Set(0.0),
     r"^/World/Cam\.focalLength: must be > 0 at time 1\.0, got 0\.0$"),
    (lambda s: _camera(s).GetHorizontalApertureAttr().Set(-2.0),
     r"^/World/Cam\.horizontalAperture: must be > 0"),
    (lambda s: _camera(s).GetClippingRangeAttr().Set(Gf.Vec2f(100.0, 1.0)),
     r"^/World/Cam\.clippingRange: need near < far, got \(100\.0, 1\.0\)$"),
    (lambda s: _camera(s).GetProjectionAttr().Set(UsdGeom.Tokens.orthographic),
     r"^/World/Cam\.projection: orthographic cameras are not supported$"),
    (lambda s: _free_camera_at(s, (math.inf, 0, 0)),
     r"^/World/Cam: non-finite camera transform"),
    (lambda s: UsdGeom.SetStageMetersPerUnit(s, 0.0),
     r"metersPerUnit must be a finite number > 0, got 0\.0$"),
    (lambda s: UsdRender.Settings(s.GetPrimAtPath("/World/Render")).CreateCameraRel().SetTargets(
        ["/World/Mirror"]), r"^/World/Render\.camera: target /World/Mirror is not a"),
    (lambda s: s.GetPrimAtPath("/World/Path").GetAttribute(schema.POSITIONS).Set(
        [(0, 1, 5), (math.nan, 1, 5)]), r"^/World/Path\.phrt:positions: non-finite"),
    (lambda s: s.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(-1.0),
     r"^/World/Mirror\.phrt:priority: must be a finite number >= 0, got -1\.0$"),
    (lambda s: _mirror(s).GetFaceVertexCountsAttr().Set([-1, 5]),
     r"^/World/Mirror\.faceVertexCounts: negative face vertex count$"),
    (_nan_floor, r"^/World/Floor\.points: non-finite point at index 2$"),
    (_short_display_color, r"^/World/Mirror\.primvars:displayColor: 2 values for vertex"),
    (_bad_instancer, r"^/World/Trees\.protoIndices: index out of range \[0, 1\)$"),
]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("plant, match", RENDER_REFUSALS)
def test_what_render_refuses_validate_reports_with_the_same_message(tmp_path, plant, match):
    stage = clean_stage(tmp_path / "s.usda")
    assert validate_stage(stage).ok
    plant(stage)
    with pytest.raises(PhrtError) as err:
        read_stage(stage)
    message = str(err.value)
    assert "\n" not in message and re.search(match, message), message
    assert f"ERROR {message}" in errors_of(stage)


def test_a_missing_texture_renders_with_a_warning_and_validate_says_error(tmp_path):
    """Issue 17: a missing texture is no refusal; the render warns (and uses the input's
    fallback), validate reports the same line as an error."""
    stage = clean_stage(tmp_path / "s.usda")
    _missing_texture(stage)
    scene = read_stage(stage)
    line = scene.texture_problems[0]
    assert re.search(r"^/World/Looks/Tex/Image\.inputs:file: texture file .* not found$", line)
    assert f"ERROR {line}" in errors_of(stage)


def test_a_stage_without_camera_renders_with_a_default_one_and_validate_warns(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    _no_camera(stage)
    scene = read_stage(stage)  # no refusal: a default camera frames the bounds
    assert scene.warnings[-1].endswith("rendering with a default camera framing the "
                                       "stage's bounds from +Z")  # fmt: skip
    report = validate_stage(stage)
    assert report.ok  # a warning, not an error
    assert [i.line() for i in report.warnings if "UsdGeomCamera" in i.line()] == [
        f"WARNING {tmp_path / 's.usda'}: stage has no UsdGeomCamera: the render uses a "
        "default camera framing the stage's bounds"
    ]
    for prim in list(stage.GetPseudoRoot().GetChildren()):  # nothing left to frame
        stage.RemovePrim(prim.GetPath())
    with pytest.raises(PhrtError, match=r"s\.usda: stage has no UsdGeomCamera and no "
                       r"geometry to frame with a default camera \(nothing to render\)$"):
        read_stage(stage)
    assert any("no geometry to frame" in line for line in errors_of(stage))


def _animate_points(stage, samples):
    attr = _mirror(stage).GetPointsAttr()
    attr.Clear()  # time samples only: no default value
    for t, pts in samples.items():
        attr.Set(pts, t)


QUAD = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
BIG_QUAD = [(0, 0, 0), (2, 0, 0), (2, 2, 0), (0, 2, 0)]


def test_reflector_with_animated_points_passes_and_renders(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    _animate_points(stage, {1.0: QUAD, 24.0: BIG_QUAD})
    report = validate_stage(stage)
    assert report.ok and report.warnings == [], [i.line() for i in report.issues]
    ss = read_stage(stage)
    assert ss.frame_range == (1.0, 24.0)
    area0 = ss.scene.elements[0].bounds_max.copy()
    assert ss.set_time(24.0)
    assert (ss.scene.elements[0].bounds_max > area0).any()


@pytest.mark.parametrize(
    "late, match",
    [
        ([(0, 0, 0), (math.inf, 0, 0), (1, 1, 0), (0, 1, 0)],
         "/World/Mirror.points: non-finite point at index 1"),
        (QUAD + [(5, 5, 5)], "/World/Mirror: topology changes at time 12.0 (not supported)"),
    ],
)  # fmt: skip
def test_problem_at_a_later_time_sample_same_message_as_render(tmp_path, late, match):
    stage = clean_stage(tmp_path / "s.usda")
    _animate_points(stage, {1.0: QUAD, 12.0: late, 24.0: QUAD})
    assert errors_of(stage) == [f"ERROR {match}"]
    ss = read_stage(stage)  # the first frame reads
    with pytest.raises(PhrtError) as err:
        ss.set_time(12.0)
    assert str(err.value) == match


def test_camera_problem_at_a_later_time_sample_same_message_as_render(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    focal = _camera(stage).GetFocalLengthAttr()
    for t, value in ((1.0, 50.0), (12.0, 0.0), (24.0, 50.0)):
        focal.Set(value, t)
    lines = errors_of(stage)
    assert lines == ["ERROR /World/Cam.focalLength: must be > 0 at time 12.0, got 0.0"]
    ss = read_stage(stage)
    with pytest.raises(PhrtError) as err:
        ss.camera(12.0)
    assert f"ERROR {err.value}" == lines[0]


def test_other_cameras_problems_are_warnings(tmp_path):
    stage = clean_stage(tmp_path / "s.usda")
    UsdGeom.Camera.Define(stage, "/World/Spare").CreateFocalLengthAttr(0.0)
    report = validate_stage(stage)
    assert report.ok
    assert [i.line() for i in report.warnings] == [
        "WARNING /World/Spare.focalLength: must be > 0 at time 0.0, got 0.0 "
        "(camera /World/Spare renders only with --camera)"
    ]
    read_stage(stage)


def test_missing_sublayer_reference_and_payload(tmp_path):
    path = tmp_path / "s.usda"
    stage = clean_stage(path)
    stage.GetRootLayer().subLayerPaths.append("./missing_sub.usda")
    for name in ("RefA", "RefB"):
        stage.DefinePrim(f"/World/{name}").GetReferences().AddReference("./missing_ref.usda")
    stage.DefinePrim("/World/Pay").GetPayloads().AddPayload("./missing_pay.usda")
    stage.GetRootLayer().Save()
    stage = open_usd(path)
    lines = errors_of(stage)
    assert sorted(lines) == sorted(
        [
            f"ERROR {path}: cannot open sublayer {tmp_path}/missing_sub.usda",
            f"ERROR /World/RefA: cannot open reference {tmp_path}/missing_ref.usda",
            f"ERROR /World/RefB: cannot open reference {tmp_path}/missing_ref.usda",
            f"ERROR /World/Pay: cannot open payload {tmp_path}/missing_pay.usda",
        ]
    )  # one line each: USD's own validators' duplicates are left out
    ss = read_stage(stage)
    assert sorted(ss.warnings) == sorted(
        [
            f"missing sublayer {tmp_path}/missing_sub.usda of {path}: not rendered "
            "(how many prims it held is unknown)",
            f"missing reference {tmp_path}/missing_ref.usda: 2 prims render without its "
            "content (/World/RefA, /World/RefB)",
            f"missing payload {tmp_path}/missing_pay.usda: 1 prim renders without its "
            "content (/World/Pay)",
            f"{path}: stage has no UsdLux lights; rendering with the default light rig "
            "(a dim dome and a headlight from the camera)",
        ]
    )
    assert all("\n" not in w for w in ss.warnings)


@pytest.mark.parametrize(
    "shader_id, flagged",
    [
        # MaterialX's standard library defines these: a USD with usdMtlx registers them,
        # and the render reads them (usd/materialx.py).
        ("ND_standard_surface_surfaceshader", False),
        ("ND_image_color3", False),
        # Defined nowhere: still USD's error.
        ("ND_no_such_node", True),
    ],
)
def test_probe_validate_flags_materialx_ids(tmp_path, shader_id, flagged):
    """usd-core has no usdMtlx: its shader registry lacks every MaterialX node, so USD's
    ShaderSdrCompliance validator called each ``ND_*`` id of a MaterialX material (the
    StandardShaderBall's, DCC exports') missing. Those MaterialX defines are not errors."""
    stage = clean_stage(tmp_path / "s.usda")
    material = UsdShade.Material.Define(stage, "/World/Looks/Mx")
    shader = UsdShade.Shader.Define(stage, "/World/Looks/Mx/Surface")
    shader.SetShaderId(shader_id)
    material.CreateSurfaceOutput("mtlx").ConnectToSource(shader.ConnectableAPI(), "out")
    missing = [line for line in errors_of(stage) if "MissingShaderIdInRegistry" in line]
    assert bool(missing) == flagged, missing
