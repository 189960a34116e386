"""The support report: a stage holding one or more prims of every kind of
``support_report.KINDS`` is reported kind by kind, with exact counts and paths (instance
proxies counted per instance); a stage of supported things only reports nothing; inspect
(text and --json) and render --json carry it."""

from __future__ import annotations

import json

from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel, UsdVol
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.usd import schema
from phrt_usd.usd.support_report import KINDS, support_lines, support_report

runner = CliRunner()


def _quad(stage: Usd.Stage, path: str, subdivided: bool = False) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    if not subdivided:
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def _preview(stage: Usd.Stage, path: str, **inputs) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    for name, value in inputs.items():
        shader.CreateInput(name, Sdf.ValueTypeNames.Float).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def _texture(stage: Usd.Stage, path: str, file: str) -> None:
    shader = UsdShade.Shader.Define(stage, path)
    shader.CreateIdAttr("UsdUVTexture")
    shader.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)


def _every_kind(tmp_path) -> str:
    """One stage with every kind; expected counts in EXPECTED."""
    # An instanced asset with a subdivided mesh: two instances count twice.
    asset = Usd.Stage.CreateNew(str(tmp_path / "rock.usda"))
    UsdGeom.Xform.Define(asset, "/Rock")
    _quad(asset, "/Rock/Shape", subdivided=True)
    asset.SetDefaultPrim(asset.GetPrimAtPath("/Rock"))
    asset.Save()

    stage = Usd.Stage.CreateNew(str(tmp_path / "every.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    for name in ("Rock_1", "Rock_2"):
        prim = UsdGeom.Xform.Define(stage, f"/World/{name}").GetPrim()
        prim.GetReferences().AddReference("./rock.usda")
        prim.SetInstanceable(True)
    _quad(stage, "/World/Cage", subdivided=True)

    mtlx = UsdShade.Material.Define(stage, "/World/Looks/Mtlx")
    std = UsdShade.Shader.Define(stage, "/World/Looks/Mtlx/Std")
    std.CreateIdAttr("ND_standard_surface_surfaceshader")
    std.CreateInput("sheen", Sdf.ValueTypeNames.Float).Set(0.5)  # not mapped: listed
    mtlx.CreateSurfaceOutput("mtlx").ConnectToSource(std.ConnectableAPI(), "out")
    studio = UsdShade.Material.Define(stage, "/World/Looks/Studio")  # a surface not read
    own = UsdShade.Shader.Define(stage, "/World/Looks/Studio/Own")
    own.CreateIdAttr("ND_studio_surface_surfaceshader")
    studio.CreateSurfaceOutput("mtlx").ConnectToSource(own.ConnectableAPI(), "out")
    ri = UsdShade.Material.Define(stage, "/World/Looks/Ri")
    pxr = UsdShade.Shader.Define(stage, "/World/Looks/Ri/Pxr")
    pxr.CreateIdAttr("PxrSurface")
    ri.CreateSurfaceOutput("ri").ConnectToSource(pxr.ConnectableAPI(), "out")

    coat = _preview(stage, "/World/Looks/Coat", clearcoat=1.0, roughness=0.0)
    mirror = _preview(stage, "/World/Looks/Mirror", roughness=0.0)
    rough = _preview(stage, "/World/Looks/Rough")  # roughness: the spec's fallback 0.5
    disp = _preview(stage, "/World/Looks/Disp", roughness=0.0)
    bump = UsdShade.Shader.Define(stage, "/World/Looks/Disp/Bump")
    bump.CreateIdAttr("UsdPreviewSurface")
    disp.CreateDisplacementOutput().ConnectToSource(bump.ConnectableAPI(), "displacement")
    _preview(stage, "/World/Looks/Leaf")  # textured occlusion and opacity, no threshold
    leaf = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Surface"))
    _texture(stage, "/World/Looks/Leaf/Maps", "leaf.png")
    maps = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Leaf/Maps"))
    for name, output in (("occlusion", "r"), ("opacity", "a")):
        leaf.CreateInput(name, Sdf.ValueTypeNames.Float).ConnectToSource(
            maps.ConnectableAPI(), output
        )

    _preview(stage, "/World/Looks/Math")  # diffuseColor from a node not read
    tint = UsdShade.Shader.Define(stage, "/World/Looks/Math/Tint")
    tint.CreateIdAttr("ND_multiply_color3")
    UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Math/Surface")).CreateInput(
        "diffuseColor", Sdf.ValueTypeNames.Color3f
    ).ConnectToSource(tint.CreateOutput("out", Sdf.ValueTypeNames.Color3f))
    # opacity from an input of the Material (a constant, not a texture): not reported.
    exposed = _preview(stage, "/World/Looks/Exposed")
    fade = exposed.CreateInput("fade", Sdf.ValueTypeNames.Float)
    fade.Set(0.5)
    UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Exposed/Surface")).CreateInput(
        "opacity", Sdf.ValueTypeNames.Float
    ).ConnectToSource(fade)

    for name, material in (("Sharp", mirror), ("Blurry", rough), ("Coated", coat)):
        mesh = _quad(stage, f"/World/{name}")
        schema.apply_reflector(mesh.GetPrim(), priority=1.0)
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)

    _texture(stage, "/World/Looks/Mirror/Udim", "wood.<UDIM>.png")
    _texture(stage, "/World/Looks/Mirror/Ptex", "wood.ptx")
    _texture(stage, "/World/Looks/Mirror/Png", "wood.png")  # readable: not reported

    skel = UsdSkel.Root.Define(stage, "/World/Char")
    UsdSkel.Skeleton.Define(stage, "/World/Char/Skel")
    body = _quad(stage, "/World/Char/Body")
    binding = UsdSkel.BindingAPI.Apply(body.GetPrim())
    binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set([0])
    binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set([1.0])
    binding.CreateSkeletonRel().SetTargets([skel.GetPath().AppendChild("Skel")])

    UsdGeom.BasisCurves.Define(stage, "/World/Hair")
    UsdGeom.NurbsCurves.Define(stage, "/World/Wire")
    UsdGeom.Points.Define(stage, "/World/Dust")
    UsdGeom.NurbsPatch.Define(stage, "/World/Patch")
    UsdGeom.TetMesh.Define(stage, "/World/Tets")
    UsdVol.Volume.Define(stage, "/World/Smoke")

    blink = UsdGeom.Xform.Define(stage, "/World/Blink")  # visibility time-sampled
    blink.CreateVisibilityAttr().Set(UsdGeom.Tokens.inherited, 1.0)
    blink.GetVisibilityAttr().Set(UsdGeom.Tokens.invisible, 2.0)
    UsdGeom.Xform.Define(stage, "/World/Still").CreateVisibilityAttr(UsdGeom.Tokens.inherited)
    crowd = UsdGeom.PointInstancer.Define(stage, "/World/Crowd")
    crowd.CreateInvisibleIdsAttr().Set([0], 1.0)
    crowd.GetInvisibleIdsAttr().Set([1], 2.0)
    UsdGeom.PointInstancer.Define(stage, "/World/Grove").CreateInvisibleIdsAttr([0])

    UsdLux.DistantLight.Define(stage, "/World/Sun")  # read as USD defines it: not reported
    UsdLux.DomeLight_1.Define(stage, "/World/Sky")  # idem
    UsdLux.SphereLight.Define(stage, "/World/Bulb")
    UsdLux.RectLight.Define(stage, "/World/Panel")
    UsdLux.PortalLight.Define(stage, "/World/Window")
    UsdLux.GeometryLight.Define(stage, "/World/Glow")
    spot = UsdLux.DiskLight.Define(stage, "/World/Spot")
    UsdLux.ShapingAPI.Apply(spot.GetPrim()).CreateShapingIesFileAttr().Set("spot.ies")
    UsdLux.LightFilter.Define(stage, "/World/Gobo")

    UsdGeom.Camera.Define(stage, "/World/Persp")  # perspective: not reported
    ortho = UsdGeom.Camera.Define(stage, "/World/Top")
    ortho.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    stage.Save()
    return str(tmp_path / "every.usda")


#: kind → the prim paths the report must list (all, in traversal order).
EXPECTED = {
    "materialx_approximated": ["/World/Looks/Mtlx"],
    "materialx_only": ["/World/Looks/Studio"],
    "other_surface_only": ["/World/Looks/Ri"],
    "subdivided_mesh": ["/World/Rock_1/Shape", "/World/Rock_2/Shape", "/World/Cage"],
    "animated_visibility": ["/World/Blink"],
    "animated_instance_mask": ["/World/Crowd"],
    "skinned_mesh": ["/World/Char/Body"],
    "basis_curves": ["/World/Hair"],
    "curves": ["/World/Wire"],
    "points": ["/World/Dust"],
    "nurbs_patch": ["/World/Patch"],
    "tet_mesh": ["/World/Tets"],
    "volume": ["/World/Smoke"],
    "texture_opacity_opaque": ["/World/Looks/Leaf/Surface"],
    "unread_shader_node": ["/World/Looks/Math/Surface"],
    # Sharp has roughness 0; Blurry takes the fallback 0.5; Coated has 0 authored.
    "rough_reflector": ["/World/Blurry"],
    "displacement": ["/World/Looks/Disp"],
    "udim_texture": ["/World/Looks/Mirror/Udim"],
    "texture_format": ["/World/Looks/Mirror/Ptex"],
    "area_light": ["/World/Bulb", "/World/Panel", "/World/Spot"],
    "unsupported_light": ["/World/Window", "/World/Glow"],
    "ies_profile": ["/World/Spot"],
    "light_filter": ["/World/Gobo"],
    "orthographic_camera": ["/World/Top"],
}


def test_every_kind_is_reported_with_counts_and_paths(tmp_path):
    assert set(EXPECTED) == {k.kind for k in KINDS}  # the test covers the whole table
    rows = support_report(Usd.Stage.Open(_every_kind(tmp_path)))
    assert [r["kind"] for r in rows] == [k.kind for k in KINDS]  # table order
    for row in rows:
        assert sorted(row["paths"]) == sorted(EXPECTED[row["kind"]]), row["kind"]
        assert row["count"] == len(EXPECTED[row["kind"]])
        assert row["treatment"] == "ignored" or row["treatment"].startswith("approximated: ")
        assert row["reason"]
    by_kind = {r["kind"]: r for r in rows}
    assert by_kind["subdivided_mesh"]["treatment"] == "approximated: cage"
    assert by_kind["materialx_only"]["treatment"] == "approximated: grey"
    lines = support_lines(rows)
    assert "1 materials MaterialX: approximated: grey (/World/Looks/Studio)" in lines
    assert (
        "1 materials MaterialX: approximated: mapped onto UsdPreviewSurface without some "
        "inputs (/World/Looks/Mtlx)" in lines
    )


def test_supported_stage_reports_nothing_and_cli_carries_it(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "plain.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.Xform.Define(stage, "/World")
    _quad(stage, "/World/Wall")
    mirror = _quad(stage, "/World/Mirror")
    schema.apply_reflector(mirror.GetPrim(), priority=1.0)
    UsdShade.MaterialBindingAPI.Apply(mirror.GetPrim()).Bind(
        _preview(stage, "/World/Looks/Mirror", roughness=0.0)
    )
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.AddTranslateOp().Set((0, 0, 5))
    UsdLux.DistantLight.Define(stage, "/World/Sun").CreateIntensityAttr(1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.Save()
    assert support_report(stage) == []
    # The cage of a subdivided mesh makes inspect and render --json say so.
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Wall")).GetSubdivisionSchemeAttr().Set(
        UsdGeom.Tokens.catmullClark
    )
    stage.Save()
    path = str(tmp_path / "plain.usda")
    inspected = runner.invoke(app, ["inspect", path, "--json"])
    assert inspected.exit_code == 0, inspected.output
    rows = json.loads(inspected.output)["support"]
    assert [(r["kind"], r["count"], r["paths"]) for r in rows] == [
        ("subdivided_mesh", 1, ["/World/Wall"])
    ]
    text = runner.invoke(app, ["inspect", path]).output
    assert "1 meshes subdivided: approximated: cage (/World/Wall)" in text
    result = phrt_usd.render(path, tmp_path / "out", frames="1", mode="raster",
                             resolution=(32, 24))  # fmt: skip
    assert [r["kind"] for r in result.summary["support"]] == ["subdivided_mesh"]


def test_probe_rough_reflector_binding_purposes():
    """The rough-reflector row follows the material the render binds: a ``full``
    binding to a mirror (roughness 0) wins over an all-purpose binding to a rough
    material, so the reflector is not listed; with render settings asking for
    ``preview`` bindings only, the all-purpose rough one is bound, and it is."""
    from pxr import UsdRender

    stage = Usd.Stage.CreateInMemory()
    mirror = _preview(stage, "/Looks/Mirror", roughness=0.0)
    rough = _preview(stage, "/Looks/Rough", roughness=0.5)
    mesh = _quad(stage, "/Floor")
    schema.apply_reflector(mesh.GetPrim(), priority=1.0)
    api = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    api.Bind(rough)
    api.Bind(mirror, materialPurpose=UsdShade.Tokens.full)
    assert "rough_reflector" not in {r["kind"] for r in support_report(stage)}
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateMaterialBindingPurposesAttr([UsdShade.Tokens.preview, ""])
    rows = {r["kind"]: r for r in support_report(stage)}
    assert rows["rough_reflector"]["paths"] == ["/Floor"]
