"""Reading USD stages into the Scene: triangulation, units, transforms, instancing,
materials, visibility, animation, lights and errors. Stages are built in memory."""

from __future__ import annotations

import math
import time as _time

import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, Vt
from scenes import camera_stage

from phrt_usd.errors import PhrtError
from phrt_usd.usd.meshes import _fan_corners, smooth_corner_normals
from phrt_usd.usd.stage import open_stage, read_stage


def quad_pentagon(stage: Usd.Stage, path: str = "/World/Mesh", left: bool = False):
    """A unit quad and a regular pentagon in the z = 0 plane, counter-clockwise from +Z."""
    ang = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    pent = np.stack([3 + np.cos(ang), np.sin(ang), np.zeros(5)], 1)
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    pts = np.concatenate([quad, pent])
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr([4, 5])
    idx = [0, 1, 2, 3] + [4, 5, 6, 7, 8]
    if left:
        idx = [0, 3, 2, 1] + [4, 8, 7, 6, 5]  # reversed winding...
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)  # ...declared left-handed
    mesh.CreateFaceVertexIndicesAttr(idx)
    return mesh


def tri_normals(geom) -> np.ndarray:
    p = geom.vertices[geom.triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ---- triangulation -------------------------------------------------------------------


@pytest.mark.parametrize("left", [False, True])
def test_quad_pentagon_triangulation_and_winding(left):
    stage = camera_stage()
    quad_pentagon(stage, left=left)
    scene = read_stage(stage).scene
    g = scene.geometry
    assert g.triangle_count == 2 + 3
    # Right-handed CCW from +Z and left-handed CW-from-+Z both face +Z after reading.
    np.testing.assert_allclose(tri_normals(g), np.tile([0, 0, 1.0], (5, 1)), atol=1e-9)
    # Smooth computed normals of a flat mesh face +Z too, and agree with the winding.
    np.testing.assert_allclose(
        g.corner_normals.reshape(-1, 3), np.tile([0, 0, 1], (15, 1)), atol=1e-6
    )
    # Triangles cover the polygons' area exactly: 1 (quad) + pentagon area.
    p = g.vertices[g.triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(1 + 2.5 * np.sin(2 * np.pi / 5), rel=1e-6)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=12), min_size=0, max_size=40))
def test_fan_triangle_count(counts):
    corners, tri_face = _fan_corners(np.array(counts, dtype=np.int64))
    assert len(corners) == sum(max(c - 2, 0) for c in counts)
    # Every triangle's corners lie inside its own face's span of the face-vertex list.
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    if len(corners):
        lo = starts[tri_face]
        hi = lo + np.array(counts)[tri_face]
        assert np.all(corners >= lo[:, None]) and np.all(corners < hi[:, None])
        assert np.all(corners[:, 0] == lo)  # fan from the first vertex


def test_meters_per_unit_scales_vertices_and_camera():
    stage = camera_stage(mpu=0.01)
    quad_pentagon(stage)
    ss = read_stage(stage)
    g = ss.scene.geometry
    assert g.vertices[:, 0].max() == pytest.approx(0.04)  # pentagon reaches x = 4 cm
    cam = ss.camera(0)
    np.testing.assert_allclose(cam.position, [0, 0, 0.1])
    assert ss.scene.meters_per_unit == 0.01
    near, far = UsdGeom.Camera(stage.GetPrimAtPath("/Cam")).GetClippingRangeAttr().Get()
    assert cam.near == pytest.approx(near * 0.01) and cam.far == pytest.approx(far * 0.01)


def test_z_up_stage_keeps_world_axes():
    stage = camera_stage(up="Z")
    xf = UsdGeom.Xform.Define(stage, "/World")
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    quad_pentagon(stage)
    ss = read_stage(stage)
    assert ss.scene.up_axis == "Z"
    np.testing.assert_allclose(ss.scene.geometry.vertices[:, 2], 5.0)
    assert ss.scene.origin[2] == pytest.approx(5.0)


# ---- instancing ----------------------------------------------------------------------


def test_reference_and_instanceable_prims_one_element_per_instance():
    stage = camera_stage()
    proto = UsdGeom.Xform.Define(stage, "/Proto")
    proto.GetPrim().SetSpecifier(Sdf.SpecifierClass)  # abstract: not rendered itself
    box = UsdGeom.Cube.Define(stage, "/Proto/Box")
    box.CreateSizeAttr(1.0)
    green, _ = preview_material(stage, "/Proto/Looks/Green", (0, 1, 0))
    UsdShade.MaterialBindingAPI.Apply(box.GetPrim()).Bind(green)
    offsets = [(0, 0, 0), (5, 0, 0), (0, 7, 0)]
    for i, off in enumerate(offsets):
        inst = UsdGeom.Xform.Define(stage, f"/World/Inst{i}")
        inst.GetPrim().GetInherits().AddInherit("/Proto")
        inst.GetPrim().SetInstanceable(True)
        inst.AddTranslateOp().Set(Gf.Vec3d(*off))
    ss = read_stage(stage)
    paths = [e.path for e in ss.scene.elements]
    assert paths == [f"/World/Inst{i}/Box" for i in range(3)]
    for e, off in zip(ss.scene.elements, offsets, strict=True):
        np.testing.assert_allclose(e.center, off, atol=1e-12)
        np.testing.assert_allclose(e.bounds_max - e.bounds_min, [1, 1, 1])
    assert ss.scene.geometry.triangle_count == 3 * 12
    # The prototype's material is one table row shared by all instances.
    assert len(ss.scene.materials.diffuse) == 2
    np.testing.assert_allclose(ss.scene.geometry.corner_albedo.reshape(-1, 3), [[0, 1, 0]] * 108)


def test_point_instancer_expansion_with_invisible_ids():
    stage = camera_stage()
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Trees")
    pi.AddTranslateOp().Set(Gf.Vec3d(0, 0, -3))
    a = UsdGeom.Cube.Define(stage, "/World/Trees/Protos/A")
    a.CreateSizeAttr(1.0)
    b = UsdGeom.Sphere.Define(stage, "/World/Trees/Protos/B")
    b.CreateRadiusAttr(0.5)
    pi.CreatePrototypesRel().SetTargets([a.GetPath(), b.GetPath()])
    pi.CreateProtoIndicesAttr([0, 1, 0, 1])
    pi.CreatePositionsAttr([(0, 0, 0), (10, 0, 0), (20, 0, 0), (30, 0, 0)])
    pi.CreateScalesAttr([(1, 1, 1), (2, 2, 2), (1, 1, 1), (1, 1, 1)])
    pi.CreateInvisibleIdsAttr([2])
    ss = read_stage(stage)
    els = {e.path: e for e in ss.scene.elements}
    assert set(els) == {f"/World/Trees.instance[{i}]" for i in (0, 1, 3)}
    np.testing.assert_allclose(els["/World/Trees.instance[1]"].center, [10, 0, -3], atol=1e-9)
    # Instance 1 is a radius-0.5 sphere scaled by 2: 2 m across (tessellation inside).
    size = els["/World/Trees.instance[1]"].bounds_max - els["/World/Trees.instance[1]"].bounds_min
    assert np.all(size <= 2.0 + 1e-9) and np.all(size > 1.9)
    np.testing.assert_allclose(els["/World/Trees.instance[0]"].bounds_min, [-0.5, -0.5, -3.5])


# ---- materials and colours -----------------------------------------------------------


def preview_material(stage, path, color):
    mat = UsdShade.Material.Define(stage, path)
    sh = UsdShade.Shader.Define(stage, f"{path}/PS")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
    sh.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.25)
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    return mat, sh


def test_geom_subset_materials_give_per_triangle_colours():
    stage = camera_stage()
    mesh = quad_pentagon(stage)
    red, _ = preview_material(stage, "/Looks/Red", (1, 0, 0))
    blue, _ = preview_material(stage, "/Looks/Blue", (0, 0, 1))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(red)
    subset = UsdShade.MaterialBindingAPI(mesh.GetPrim()).CreateMaterialBindSubset(
        "pent", Vt.IntArray([1])
    )
    UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(blue)
    scene = read_stage(stage).scene
    g = scene.geometry
    albedo = g.corner_albedo[:, 0]
    np.testing.assert_allclose(albedo[:2], [[1, 0, 0]] * 2)  # quad → red
    np.testing.assert_allclose(albedo[2:], [[0, 0, 1]] * 3)  # pentagon → blue
    assert len(scene.materials.diffuse) == 3  # none + red + blue, deduplicated
    assert len(set(g.tri_material[:2])) == 1 and g.tri_material[0] != g.tri_material[2]
    assert scene.materials.metallic[g.tri_material[0]] == pytest.approx(0.25)


@pytest.mark.parametrize("interp", ["constant", "uniform", "vertex", "faceVarying"])
def test_display_color_interpolations(interp):
    stage = camera_stage()
    mesh = quad_pentagon(stage)
    n = {"constant": 1, "uniform": 2, "vertex": 9, "faceVarying": 9}[interp]
    colors = np.linspace(0, 1, n * 3).reshape(n, 3).astype(np.float32)
    pv = mesh.CreateDisplayColorPrimvar(interp)
    pv.Set(Vt.Vec3fArray.FromNumpy(colors))
    g = read_stage(stage).scene.geometry
    alb = g.corner_albedo
    if interp == "constant":
        np.testing.assert_allclose(alb.reshape(-1, 3), np.tile(colors[0], (15, 1)))
    elif interp == "uniform":
        np.testing.assert_allclose(alb[:2].reshape(-1, 3), np.tile(colors[0], (6, 1)))
        np.testing.assert_allclose(alb[2:].reshape(-1, 3), np.tile(colors[1], (9, 1)))
    elif interp == "vertex":
        np.testing.assert_allclose(alb, colors[g.triangles], rtol=1e-6)
    else:  # face-vertex order here equals point order (indices 0..8)
        np.testing.assert_allclose(alb, colors[g.triangles], rtol=1e-6)
        # Quad fan: (0,1,2), (0,2,3); pentagon fan from corner 4.
        np.testing.assert_array_equal(g.triangles[:2], [[0, 1, 2], [0, 2, 3]])


def test_no_color_is_mid_grey():
    stage = camera_stage()
    quad_pentagon(stage)
    np.testing.assert_allclose(read_stage(stage).scene.geometry.corner_albedo, 0.5)


def test_texture_loaded_through_oiio(tmp_path):
    h, w = 4, 2
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2] = (255, 0, 0)  # top half red
    img[h // 2 :] = (0, 0, 188)  # bottom half dark blue (sRGB 188 ≈ linear 0.5)
    path = tmp_path / "tex.png"
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, 3, "uint8"))
    out.write_image(img)
    out.close()
    stage = camera_stage()
    mesh = quad_pentagon(stage)
    st_pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
    )
    st_pv.Set(Vt.Vec2fArray([(x, y) for x, y in np.random.default_rng(0).random((9, 2))]))
    mat = UsdShade.Material.Define(stage, "/Looks/Tex")
    ps = UsdShade.Shader.Define(stage, "/Looks/Tex/PS")
    ps.CreateIdAttr("UsdPreviewSurface")
    tex = UsdShade.Shader.Define(stage, "/Looks/Tex/T")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(str(path))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("auto")
    rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    ps.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
    mat.CreateSurfaceOutput().ConnectToSource(ps.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    scene = read_stage(stage).scene
    texture = scene.materials.textures[scene.geometry.tri_material[0]]
    assert texture.shape == (h, w, 3) and texture.dtype == np.float32
    np.testing.assert_allclose(texture[0, 0], [1, 0, 0], atol=1e-6)  # row 0 = top
    assert texture[-1, 0, 2] == pytest.approx(0.5029, abs=2e-3)  # sRGB → linear
    g = scene.geometry
    assert g.corner_uv is not None and g.corner_uv.shape == (5, 3, 2)
    uv = np.asarray(st_pv.Get())
    np.testing.assert_allclose(g.corner_uv, uv[g.triangles], rtol=1e-6)


# ---- visibility / purpose ------------------------------------------------------------


def test_invisible_guide_and_inactive_prims_skipped():
    stage = camera_stage()
    quad_pentagon(stage, "/World/Visible")
    hidden = UsdGeom.Xform.Define(stage, "/World/Hidden")
    hidden.MakeInvisible()
    quad_pentagon(stage, "/World/Hidden/Mesh")
    guide = UsdGeom.Xform.Define(stage, "/World/Guide")
    guide.CreatePurposeAttr(UsdGeom.Tokens.guide)
    quad_pentagon(stage, "/World/Guide/Mesh")
    quad_pentagon(stage, "/World/Proxy").CreatePurposeAttr(UsdGeom.Tokens.proxy)
    quad_pentagon(stage, "/World/Render").CreatePurposeAttr(UsdGeom.Tokens.render)
    quad_pentagon(stage, "/World/Off").GetPrim().SetActive(False)
    light = UsdLux.SphereLight.Define(stage, "/World/Hidden/Lamp")
    light.CreateIntensityAttr(10.0)
    ss = read_stage(stage)
    assert [e.path for e in ss.scene.elements] == ["/World/Visible", "/World/Render"]
    assert ss.scene.lights.local == []


# ---- animation -----------------------------------------------------------------------


def test_animated_translate_changes_only_animated_vertices():
    stage = camera_stage()
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(10)
    quad_pentagon(stage, "/World/Static")
    mover = UsdGeom.Xform.Define(stage, "/World/Mover")
    op = mover.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0)
    op.Set(Gf.Vec3d(10, 0, 0), 10)
    quad_pentagon(stage, "/World/Mover/Mesh")
    ss = read_stage(stage)
    els = ss.scene.elements
    assert [e.animated for e in els] == [False, True]
    g = ss.scene.geometry
    static_rows = slice(0, 9)
    before_static = g.vertices[static_rows].copy()
    before_moving = g.vertices[9:].copy()
    change = ss.set_time(5.0)
    # A translation: moved (rigidly), not deformed; the geometry version stamps it.
    assert change.moved.tolist() == [1] and change.deformed.tolist() == []
    assert change.geometry_version == 1 and bool(change)
    assert ss.scene.versions.element_geometry.tolist() == [0, 1]
    np.testing.assert_allclose(g.vertices[9:] - before_moving, np.tile([5, 0, 0], (9, 1)))
    np.testing.assert_array_equal(g.vertices[static_rows], before_static)
    assert els[1].bounds_min[0] == pytest.approx(5.0)
    same = ss.set_time(5.0)  # same time: nothing moved, no version bumped
    assert not same and same.changed.tolist() == [] and same.geometry_version == 1
    # Nothing animated → set_time is cheap.
    t0 = _time.perf_counter()
    for _ in range(100):
        ss.set_time(5.0)
    assert (_time.perf_counter() - t0) / 100 < 5e-3


def test_static_stage_set_time_reports_no_change():
    stage = camera_stage()
    quad_pentagon(stage)
    ss = read_stage(stage)
    change = ss.set_time(3.0)
    assert not change and (change.geometry_version, change.camera_version) == (0, 0)


def test_deforming_points_recomputed():
    stage = camera_stage()
    mesh = quad_pentagon(stage)
    pts = np.asarray(mesh.GetPointsAttr().Get())
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), 0)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts * 2), 10)
    ss = read_stage(stage)
    assert ss.scene.elements[0].animated
    change = ss.set_time(10)
    assert change.deformed.tolist() == [0] and change.moved.tolist() == []
    np.testing.assert_allclose(ss.scene.geometry.vertices, pts * 2, rtol=1e-6)


# ---- lights --------------------------------------------------------------------------


def test_lights_directions_and_radiance(tmp_path):
    stage = camera_stage()
    sun = UsdLux.DistantLight.Define(stage, "/Lights/Sun")
    sun.AddRotateXOp().Set(-90.0)  # -Z axis now points down (-Y): sun straight overhead
    sun.CreateIntensityAttr(2.0)
    sun.CreateExposureAttr(1.0)
    sun.CreateColorAttr(Gf.Vec3f(1, 0.5, 0.25))
    lamp = UsdLux.SphereLight.Define(stage, "/Lights/Lamp")
    lamp.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    lamp.CreateRadiusAttr(0.25)
    lamp.CreateIntensityAttr(5.0)
    rect = UsdLux.RectLight.Define(stage, "/Lights/Rect")
    rect.CreateWidthAttr(2.0)
    rect.CreateHeightAttr(3.0)
    rect.CreateIntensityAttr(1.0)
    env = np.full((4, 8, 3), 2.0, np.float32)
    env_path = tmp_path / "env.exr"
    out = oiio.ImageOutput.create(str(env_path))
    out.open(str(env_path), oiio.ImageSpec(8, 4, 3, "float"))
    out.write_image(env)
    out.close()
    dome = UsdLux.DomeLight.Define(stage, "/Lights/Dome")
    dome.CreateTextureFileAttr(str(env_path))
    dome.CreateIntensityAttr(0.5)
    dome.AddRotateYOp().Set(90.0)
    lights = read_stage(stage).scene.lights
    (d,) = lights.distant
    np.testing.assert_allclose(d.direction, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(d.radiance, [4, 2, 1])
    local = {round(light.radius, 6): light for light in lights.local}
    np.testing.assert_allclose(local[0.25].position, [1, 2, 3])
    # UsdLux: luminance 5 over a sphere seen face-on as π 0.25² m² (usd/lights.py).
    np.testing.assert_allclose(local[0.25].radiance, [5 * np.pi * 0.25**2] * 3)
    rect_light = local[round(0.5 * np.hypot(2, 3), 6)]
    np.testing.assert_allclose(rect_light.radiance, [6, 6, 6])  # × area 2 × 3
    assert lights.dome is not None
    np.testing.assert_allclose(lights.dome.texture, env)
    np.testing.assert_allclose(lights.dome.color, [0.5] * 3)
    np.testing.assert_allclose(lights.dome.world_from_light @ [1, 0, 0], [0, 0, -1], atol=1e-12)


# ---- reflectors and errors -----------------------------------------------------------


def test_reflector_flags_and_clamp():
    stage = camera_stage()
    m = quad_pentagon(stage, "/World/Mirror").GetPrim()
    m.AddAppliedSchema("PhrtReflectorAPI")
    m.CreateAttribute("phrt:reflectivity", Sdf.ValueTypeNames.Float).Set(3.0)
    k = quad_pentagon(stage, "/World/Prio").GetPrim()
    k.AddAppliedSchema("PhrtReflectorAPI")
    k.CreateAttribute("phrt:priority", Sdf.ValueTypeNames.Float).Set(4.0)
    quad_pentagon(stage, "/World/Plain")
    els = read_stage(stage).scene.elements
    assert [(e.is_reflector, e.priority, e.reflectivity) for e in els] == [
        (True, 1.0, 1.0),
        (True, 4.0, 1.0),
        (False, 0.0, 0.0),
    ]


@pytest.mark.parametrize("reflector", [True, False])
def test_nan_points_raise_naming_prim(reflector):
    stage = camera_stage()
    mesh = quad_pentagon(stage, "/World/Bad")
    if reflector:
        mesh.GetPrim().AddAppliedSchema("PhrtReflectorAPI")
    pts = np.array(mesh.GetPointsAttr().Get())
    pts[3, 1] = np.nan
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts))
    with pytest.raises(PhrtError, match=r"/World/Bad\.points") as info:
        read_stage(stage)
    assert "\n" not in str(info.value)


def test_out_of_range_index_raises():
    stage = camera_stage()
    mesh = quad_pentagon(stage, "/World/Bad")
    mesh.GetFaceVertexIndicesAttr().Set([0, 1, 2, 99, 4, 5, 6, 7, 8])
    with pytest.raises(PhrtError, match=r"/World/Bad\.faceVertexIndices"):
        read_stage(stage)


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("nope.usda", None, "no such file"),
        ("dir.usda", "dir", "is a directory, not a USD file"),
        ("stage", "#usda 1.0\n", "no USD file extension (.usda/.usdc/.usd/.usdz)"),
        ("stage.txt", "#usda 1.0\n", "not a USD file (extension '.txt', expected "
         ".usda/.usdc/.usd/.usdz)"),
        ("bad.usda", '#usda 1.0\n def Xform "A" {{{ \n', "cannot open as USD ("),
        ("bad.usdc", b"\x00\xffgarbage", "cannot open as USD (File too small"),
        ("bad.usd", b"PXR-USDC garbage \x00" * 20, "cannot open as USD ("),
        ("bad.usdz", b"PK\x03\x04 garbage", "cannot open as USD ("),
    ],
)  # fmt: skip
def test_unusable_stage_file_is_one_line_error(tmp_path, name, content, problem):
    path = tmp_path / name
    if content == "dir":
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    with pytest.raises(PhrtError) as err:
        open_stage(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {problem}"), message
    assert "\n" not in message and "Traceback" not in message


def test_missing_reference_is_a_warning_not_a_refusal(tmp_path):
    stage = camera_stage()
    quad_pentagon(stage)
    UsdLux.DistantLight.Define(stage, "/World/Sun")  # lit: no default-rig notice
    assert read_stage(stage).warnings == []
    stage.DefinePrim("/World/Prop").GetReferences().AddReference(str(tmp_path / "gone.usda"))
    ss = read_stage(stage)
    assert ss.warnings == [
        f"missing reference {tmp_path}/gone.usda: 1 prim renders without its content (/World/Prop)"
    ]
    assert ss.scene.geometry.triangle_count == 5  # the rest renders


def test_no_camera(tmp_path):
    stage = Usd.Stage.CreateInMemory()
    with pytest.raises(PhrtError, match="no UsdGeomCamera and no geometry to frame"):
        read_stage(stage)  # nothing to frame with a default camera either
    UsdGeom.Cube.Define(stage, "/Box")
    scene = read_stage(stage)  # tests/usd/test_cameras_usd.py checks the default camera
    assert scene.camera_path == "<default camera>"
    assert "no UsdGeomCamera; rendering with a default camera" in scene.warnings[-1]
    with pytest.raises(PhrtError, match="/Nope"):
        read_stage(camera_stage(), camera="/Nope")


def test_camera_choice_render_settings_over_first_camera(tmp_path):
    stage = camera_stage()
    UsdGeom.Camera.Define(stage, "/Other")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets(["/Other"])
    assert read_stage(stage).camera_path == "/Other"
    assert read_stage(stage, camera="/Cam").camera_path == "/Cam"
    path = tmp_path / "s.usda"
    stage.GetRootLayer().Export(str(path))
    assert open_stage(path).camera_path == "/Other"


def test_implicit_gprims_are_closed_and_outward():
    stage = camera_stage()
    for i, kind in enumerate(["Sphere", "Cube", "Cylinder", "Cone", "Capsule"]):
        prim = stage.DefinePrim(f"/World/{kind}", kind)
        UsdGeom.Xformable(prim).AddTranslateOp().Set(Gf.Vec3d(3 * i, 0, 0))
        if kind != "Sphere" and kind != "Cube":
            prim.GetAttribute("axis").Set("X")
    scene = read_stage(stage).scene
    g = scene.geometry
    n = tri_normals_safe(g)
    for e_id, e in enumerate(scene.elements):
        sel = g.tri_element == e_id
        p = g.vertices[g.triangles[sel]]
        centroid = p.mean(axis=1) - e.center
        nn = n[sel]
        ok = np.linalg.norm(nn, axis=1) > 0
        # Outward: geometric normals point away from the centre.
        assert np.all(np.einsum("ij,ij->i", nn[ok], centroid[ok]) > 0), e.path
        # Shading normals agree with the winding.
        cn = g.corner_normals[sel].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", cn[ok], nn[ok]) > 0), e.path
        # Closed surface: signed volume matches the analytic shape within tessellation.
        vol = (
            np.einsum(
                "ij,ij->i", p[:, 0] - e.center, np.cross(p[:, 1] - e.center, p[:, 2] - e.center)
            ).sum()
            / 6
        )
        expected = {
            "Sphere": 4 / 3 * np.pi,
            "Cube": 8.0,
            "Cylinder": 2 * np.pi,
            "Cone": 2 * np.pi / 3,
            "Capsule": np.pi * 0.25 * 1 + 4 / 3 * np.pi * 0.125,
        }[e.path.rsplit("/", 1)[1]]
        assert vol == pytest.approx(expected, rel=0.03), e.path
    # Axis X: the cylinder's long side runs along X.
    cyl = scene.elements[2]
    np.testing.assert_allclose(cyl.bounds_max - cyl.bounds_min, [2, 2, 2], atol=1e-9)
    cone = scene.elements[3]
    assert cone.bounds_max[0] - cone.bounds_min[0] == pytest.approx(2.0)


def tri_normals_safe(geom) -> np.ndarray:
    p = geom.vertices[geom.triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 1e-12, n / np.where(length > 0, length, 1), 0)


def test_smooth_normals_area_weighted():
    # A "roof": two faces meeting at the ridge; ridge vertex normal is the area-weighted
    # average — the bigger face pulls harder.
    pts = np.array([[0, 0, 0], [0, 0, 1], [1, 1, 0], [-3, 3, 0.0]])
    tris = np.array([[0, 2, 1], [0, 1, 3]])
    cn = smooth_corner_normals(pts, tris)
    np.testing.assert_allclose(np.linalg.norm(cn, axis=2), 1.0)
    a = np.cross(pts[2] - pts[0], pts[1] - pts[0])
    b = np.cross(pts[1] - pts[0], pts[3] - pts[0])
    expect = (a + b) / np.linalg.norm(a + b)
    np.testing.assert_allclose(cn[0, 0], expect, atol=1e-12)


def test_negative_scale_keeps_front_face_consistent():
    stage = camera_stage()
    xf = UsdGeom.Xform.Define(stage, "/World")
    xf.AddScaleOp().Set(Gf.Vec3f(-1, 1, 1))
    quad_pentagon(stage)
    g = read_stage(stage).scene.geometry
    geo = tri_normals(g)
    np.testing.assert_allclose((g.corner_normals.mean(axis=1) * geo).sum(axis=1), 1.0, atol=1e-6)


@pytest.mark.slow
def test_read_speed_many_prims():
    stage = camera_stage()
    for i in range(300):
        s = UsdGeom.Sphere.Define(stage, f"/World/S{i}")
        s.AddTranslateOp().Set(Gf.Vec3d(i, 0, 0))
    t0 = _time.perf_counter()
    ss = read_stage(stage)
    elapsed = _time.perf_counter() - t0
    assert len(ss.scene.elements) == 300
    assert elapsed < 2.0


def test_deforming_instances_and_animated_normals():
    """Instances of one deforming prototype each follow it; authored normals animate."""
    stage = camera_stage()
    proto = UsdGeom.Xform.Define(stage, "/Proto")
    proto.GetPrim().SetSpecifier(Sdf.SpecifierClass)
    mesh = quad_pentagon(stage, "/Proto/Mesh")
    pts = np.array(mesh.GetPointsAttr().Get())
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), 0)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts + [0, 0, 1]), 10)
    normals = mesh.CreateNormalsAttr()
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.constant)
    normals.Set([(0, 0, 1)], 0)
    normals.Set([(0, 1, 0)], 10)
    for i in range(2):
        inst = UsdGeom.Xform.Define(stage, f"/World/I{i}")
        inst.GetPrim().GetInherits().AddInherit("/Proto")
        inst.GetPrim().SetInstanceable(True)
        inst.AddTranslateOp().Set(Gf.Vec3d(10 * i, 0, 0))
    ss = read_stage(stage)
    assert all(e.animated for e in ss.scene.elements)
    assert ss.set_time(10).deformed.tolist() == [0, 1]  # points and normals changed
    g = ss.scene.geometry
    np.testing.assert_allclose(g.vertices[:, 2], 1.0, rtol=1e-6)  # both instances moved
    np.testing.assert_allclose(g.corner_normals.reshape(-1, 3), [[0, 1, 0]] * 30, atol=1e-6)


@pytest.mark.parametrize(
    "axis, size, normal",
    [("X", [0, 4, 2], [1, 0, 0]), ("Y", [2, 0, 4], [0, 1, 0]), ("Z", [2, 4, 0], [0, 0, 1])],
)
def test_plane_axes(axis, size, normal):
    """UsdGeomPlane: width along z/x/x and length along y/z/y for axis X/Y/Z."""
    stage = camera_stage()
    plane = UsdGeom.Plane.Define(stage, "/World/Plane")
    plane.CreateAxisAttr(axis)
    plane.CreateWidthAttr(2.0)
    plane.CreateLengthAttr(4.0)
    scene = read_stage(stage).scene
    e = scene.elements[0]
    np.testing.assert_allclose(e.bounds_max - e.bounds_min, size)
    np.testing.assert_allclose(tri_normals(scene.geometry), [normal] * 2, atol=1e-12)
    np.testing.assert_allclose(scene.geometry.corner_normals.reshape(-1, 3), [normal] * 6)


#: A text layer that does not parse: line 5, column 21 holds the second number of a
#: scalar value ("1 2"), where the parser expects the end of the prim.
_UNPARSABLE = '#usda 1.0\n\ndef Xform "World"\n{\n    double radius = 1 2\n}\n'


def test_probe_parse_error_names_file_line_column(tmp_path):
    """USD's own parse error reaches the message: the parser's ``file:line:column:
    what``, in one line, not only "cannot open as USD"; text that is not UTF-8 (USD's
    message then cannot be decoded) is located by its first bad byte."""
    from phrt_usd.usd.stage import open_usd

    bad = tmp_path / "bad.usda"
    bad.write_text(_UNPARSABLE)
    with pytest.raises(PhrtError) as err:
        open_usd(bad)
    message = str(err.value)
    assert message.startswith(f"{bad}: cannot open as USD ({bad}:5:"), message
    assert "Expected" in message and "\n" not in message
    damaged = tmp_path / "damaged.usda"
    damaged.write_bytes(b'#usda 1.0\ndef Xform "\xff\xfe" {{{\n')
    with pytest.raises(PhrtError, match=rf"\({damaged}:2:12: bytes that are not UTF-8"):
        open_usd(damaged)


def test_probe_parse_error_of_a_referenced_layer_is_in_the_warning(tmp_path):
    """A reference or sublayer that does not parse: the render goes on without it, its
    warning carries the parser's ``file:line:column``."""
    (tmp_path / "bad.usda").write_text(_UNPARSABLE)
    stage = camera_stage()
    UsdGeom.Cube.Define(stage, "/World/Box")
    UsdLux.DistantLight.Define(stage, "/World/Sun")
    stage.DefinePrim("/World/Prop").GetReferences().AddReference(str(tmp_path / "bad.usda"))
    stage.GetRootLayer().subLayerPaths.append(str(tmp_path / "bad.usda"))
    warnings = read_stage(stage).warnings
    located = [w for w in warnings if f"{tmp_path}/bad.usda:5:" in w]
    assert len(located) == 2, warnings  # the reference's and the sublayer's


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
def test_stage_file_that_is_no_regular_file_is_refused_unread(tmp_path, special):
    """A device or a named pipe with a USD extension (here a link to one) is refused
    before USD reads it (a device reads without end, a pipe blocks)."""
    import os

    from phrt_usd.usd.stage import open_usd

    target = special
    if special == "fifo":
        target = str(tmp_path / "pipe")
        os.mkfifo(target)
    link = tmp_path / "stage.usda"
    link.symlink_to(target)
    with pytest.raises(PhrtError, match=rf"^{link}: not a regular file"):
        open_usd(link)


@pytest.mark.parametrize(
    "value, accepted",
    [(Vt.Float(0.25), 0.25), (2, 2.0), (math.inf, None), (math.nan, None), (-1.0, None),
     (0.0, None), (1e-300, 1e-300)],
)  # fmt: skip
def test_probe_float_meters_per_unit(value, accepted):
    """metersPerUnit read tolerantly: a float or an int is its number (0.25 is exact in
    float32); a value that is not finite or not > 0 refuses the stage as unusable input
    (exit 2 in the CLI), one line naming the layer metadata."""
    from phrt_usd.errors import UnreadableInput
    from phrt_usd.usd.stage import meters_per_unit

    stage = camera_stage()
    UsdGeom.Cube.Define(stage, "/World/Box")
    stage.GetRootLayer().pseudoRoot.SetInfo("metersPerUnit", value)
    mpu, problems = meters_per_unit(stage)
    if accepted is not None:
        assert mpu == accepted and problems == []
        assert read_stage(stage).meters_per_unit == accepted
        return
    (problem,) = problems
    where = stage.GetRootLayer().identifier
    assert problem.startswith(f"{where}: layer metadata metersPerUnit must be a finite number")
    with pytest.raises(UnreadableInput) as err:
        read_stage(stage)
    assert str(err.value) == problem and "\n" not in problem


def test_probe_bad_camera_and_settings_are_bad_options():
    """--camera and --settings naming nothing are bad options (exit 2), listing what
    there is."""
    from phrt_usd.errors import BadOption

    stage = camera_stage()
    UsdGeom.Cube.Define(stage, "/World/Box")
    UsdRender.Settings.Define(stage, "/Render/Main")
    with pytest.raises(BadOption, match=r"^--camera /Nope: no UsdGeomCamera .*\(cameras: /Cam\)"):
        read_stage(stage, camera="/Nope")
    with pytest.raises(BadOption, match=r"^--camera Nope: no UsdGeomCamera of this name"):
        read_stage(stage, camera="Nope")
    with pytest.raises(
        BadOption, match=r"^--settings /Nope: no RenderSettings .*\(RenderSettings prims: "
        r"/Render/Main\)"
    ):
        read_stage(stage, settings="/Nope")
    with pytest.raises(BadOption, match=r"^--settings Render: no RenderSettings"):
        read_stage(stage, settings="Render")


def test_probe_unknown_variant_names_set_prim_and_variants(tmp_path):
    """A --variant name USD cannot even hold (``a.b``) is an unknown variant like any
    other: the prim, the set and the variants it has, not "cannot open as USD"."""
    from phrt_usd.errors import BadOption
    from phrt_usd.usd.stage import open_usd
    from phrt_usd.usd.stage_controls import StageControls

    stage = Usd.Stage.CreateNew(str(tmp_path / "v.usda"))
    holder = stage.DefinePrim("/World")
    look = holder.GetVariantSets().AddVariantSet("look")
    for name in ("red", "blue"):
        look.AddVariant(name)
    stage.GetRootLayer().Save()
    for variant in ("/World:look=a.b", "/World:look=gr een", "/World:look=green"):
        controls = StageControls.from_options((), [variant])
        with pytest.raises(BadOption) as err:
            open_usd(tmp_path / "v.usda", controls)
        name = variant.rpartition("=")[2]
        assert str(err.value) == (
            f"--variant {variant}: /World has no variant {name!r} in its variant set 'look' "
            "(it has: blue, red)"
        )
    with pytest.raises(BadOption, match=r"/World has no variant set 'lo\.ok' \(it has: look\)"):
        open_usd(tmp_path / "v.usda", StageControls.from_options((), ["/World:lo.ok=red"]))


def test_probe_session_layer_directory(tmp_path):
    """A directory given as --session-layer is said to be one, not "no such file"."""
    from phrt_usd.errors import BadOption
    from phrt_usd.usd.stage_controls import StageControls

    with pytest.raises(BadOption, match=rf"^--session-layer {tmp_path}: is a directory"):
        StageControls.from_options([tmp_path])
    with pytest.raises(BadOption, match=r"no such file"):
        StageControls.from_options([tmp_path / "gone.usda"])
    (tmp_path / "bad.usda").write_text(_UNPARSABLE)
    with pytest.raises(BadOption, match=rf"cannot open \({tmp_path}/bad.usda:5:"):
        StageControls.from_options([tmp_path / "bad.usda"])
