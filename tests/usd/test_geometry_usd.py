"""Geometry and composition as USD defines them, checked at analytic pixels in raster and
rt: holeIndices, purposes (ComputePurpose, includedPurposes), nested PointInstancers
with masks, UsdSkel skinning and blend shapes, subdivision surfaces listed, reflectors
inside instances. Every stage is built in memory by its test; a camera at (0, 0, 10)
looks down -Z at the z = 0 plane, a white dome lights it (no shadows to reason about)."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdSkel, Vt

import phrt_usd  # noqa: F401  (registers the schema)
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd import schema
from phrt_usd.usd.stage import read_stage
from phrt_usd.usd.traversal import subdivided_meshes

W, H = 64, 48
#: Camera distance from the z = 0 plane (stage units = metres here).
EYE_Z = 10.0
MODES = ("raster", "rt")


def _stage() -> Usd.Stage:
    """Y-up, metres; camera /Cam at (0, 0, EYE_Z) looking down -Z, focal 24, apertures
    36 x 27 (the 4:3 of W x H, so every aperture fit agrees); a white dome /Sky."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(2)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, EYE_Z))
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateIntensityAttr(1.0)
    dome.CreateColorAttr(Gf.Vec3f(1, 1, 1))
    return stage


def _quad(stage, path, x0, y0, x1, y1, z=0.0, color=(0.5, 0.5, 0.5)) -> UsdGeom.Mesh:
    """A rectangle [x0, x1] x [y0, y1] at height z facing +Z (the camera)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDisplayColorAttr([color])
    return mesh


def _render(ss, mode: str, times=(1.0,)):
    """Frames of ``ss`` at ``times`` in ``mode``: [(element_id (H, W), beauty (H, W, 3))]."""
    renderer = FrameRenderer(
        ss, RenderOptions(mode=mode, heuristic="all", width=W, height=H, budget_ms=None)
    )
    try:
        frames = []
        for t in times:
            out = renderer.render(t)
            frames.append((out.gbuffer.element_id.copy(), out.beauty.copy()))
        return frames
    finally:
        renderer.close()


def _pixel(ss, point, time=1.0) -> tuple[int, int]:
    """(row, col) of the pixel a world point projects into."""
    x, y, _ = ss.camera(time).project(np.asarray([point], float), W, H)[0]
    return int(np.floor(y)), int(np.floor(x))


def _element(ss, path: str) -> int:
    return next(i for i, e in enumerate(ss.scene.elements) if e.path == path)


# ---- holeIndices -----------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_hole_faces_are_not_drawn(mode):
    stage = _stage()
    # Two unit quads side by side (faces 0: x in [-2, -1], 1: x in [1, 2]); face 0 a hole.
    mesh = UsdGeom.Mesh.Define(stage, "/World/Holed")
    mesh.CreatePointsAttr([(-2, -1, 0), (-1, -1, 0), (-1, 1, 0), (-2, 1, 0)] +
                          [(1, -1, 0), (2, -1, 0), (2, 1, 0), (1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5, 6, 7])
    mesh.CreateHoleIndicesAttr([0])
    mesh.CreateDisplayColorAttr([(0.9, 0.1, 0.1)])
    _quad(stage, "/World/Wall", -4, -3, 4, 3, z=-1.0, color=(0.1, 0.1, 0.9))
    ss = read_stage(stage)
    assert ss.scene.geometry.triangle_count == 2 + 2  # the drawn face and the wall
    ids, beauty = _render(ss, mode)[0]
    holed, wall = _element(ss, "/World/Holed"), _element(ss, "/World/Wall")
    # Through the hole the wall is seen; the other face is drawn (centres, far from edges).
    assert ids[_pixel(ss, (-1.5, 0, 0))] == wall
    assert ids[_pixel(ss, (1.5, 0, 0))] == holed
    r, g, b = beauty[_pixel(ss, (-1.5, 0, 0))]
    assert b > 3 * r  # blue wall, not the red face
    # Hole pixels: the hole's projection shrunk by 1 px (edge rasterization) is all wall.
    (r0, c0), (r1, c1) = _pixel(ss, (-2, 1, 0)), _pixel(ss, (-1, -1, 0))
    assert np.all(ids[r0 + 1 : r1, c0 + 1 : c1] == wall)


# ---- purposes ------------------------------------------------------------------------


def _purpose_stage(included=None) -> Usd.Stage:
    """A proxy group holding a child authored ``render`` (left) and one inheriting proxy
    (right), a guide quad (bottom); render settings with ``included`` purposes if given."""
    stage = _stage()
    group = UsdGeom.Xform.Define(stage, "/World/ProxyGroup")
    group.CreatePurposeAttr(UsdGeom.Tokens.proxy)
    _quad(stage, "/World/ProxyGroup/Render", -3, 0, -1, 2).CreatePurposeAttr(
        UsdGeom.Tokens.render
    )
    _quad(stage, "/World/ProxyGroup/Inherits", 1, 0, 3, 2)
    _quad(stage, "/World/Plain", -1, -3, 1, -1)
    if included is not None:
        settings = UsdRender.Settings.Define(stage, "/Render/Settings")
        settings.CreateIncludedPurposesAttr(included)
        settings.CreateCameraRel().SetTargets(["/Cam"])
    return stage


@pytest.mark.parametrize("mode", MODES)
def test_render_child_of_proxy_group_is_drawn(mode):
    ss = read_stage(_purpose_stage())
    assert ss.included_purposes == ("default", "render")  # UsdRender's fallback
    assert [e.path for e in ss.scene.elements] == ["/World/ProxyGroup/Render", "/World/Plain"]
    ids, _ = _render(ss, mode)[0]
    assert ids[_pixel(ss, (-2, 1, 0))] == _element(ss, "/World/ProxyGroup/Render")
    assert ids[_pixel(ss, (2, 1, 0))] == -1  # purpose proxy (inherited): not drawn
    assert ids[_pixel(ss, (0, -2, 0))] == _element(ss, "/World/Plain")


@pytest.mark.parametrize("mode", MODES)
def test_included_purposes_of_the_render_settings(mode):
    ss = read_stage(_purpose_stage(["default", "proxy"]))
    assert [e.path for e in ss.scene.elements] == ["/World/ProxyGroup/Inherits", "/World/Plain"]
    ids, _ = _render(ss, mode)[0]
    assert ids[_pixel(ss, (-2, 1, 0))] == -1  # render purpose not included
    assert ids[_pixel(ss, (2, 1, 0))] == _element(ss, "/World/ProxyGroup/Inherits")


def test_included_purposes_of_the_settings_prim_asked_for():
    stage = _purpose_stage(["default", "render"])
    other = UsdRender.Settings.Define(stage, "/Render/ProxyPreview")
    other.CreateIncludedPurposesAttr(["proxy"])
    assert [e.path for e in read_stage(stage).scene.elements] == [
        "/World/ProxyGroup/Render",
        "/World/Plain",
    ]
    ss = read_stage(stage, settings="/Render/ProxyPreview")  # --settings
    assert [e.path for e in ss.scene.elements] == ["/World/ProxyGroup/Inherits"]


def test_unknown_included_purpose_is_a_warning():
    ss = read_stage(_purpose_stage(["default", "rendr"]))
    assert [e.path for e in ss.scene.elements] == ["/World/Plain"]
    assert len(ss.warnings) == 1 and "'rendr' is no purpose" in ss.warnings[0]
    assert ss.warnings[0].startswith("/Render/Settings.includedPurposes:")


# ---- nested PointInstancers ------------------------------------------------------------

#: Outer instancer: its translate, instance positions, and its prototype root's own
#: translate; inner instancer's translate below that root and its instance positions.
OUTER_T = np.array([0.5, 0.0, 0.0])
OUTER_POS = np.array([(-2.0, -1.5, 0), (2.0, -1.5, 0), (-2.0, 1.5, 0), (2.0, 1.5, 0)])
GROUP_T = np.array([0.0, 0.25, 0.0])
INNER_T = np.array([0.1, 0.0, 0.0])
INNER_POS = np.array([(-0.6, -0.6, 0), (0.6, -0.6, 0), (-0.6, 0.6, 0), (0.6, 0.6, 0)])
#: Inner prototype cube colours (red, green, blue, yellow) and their dominant channel(s).
COLORS = [(0.9, 0.05, 0.05), (0.05, 0.9, 0.05), (0.05, 0.05, 0.9), (0.9, 0.9, 0.05)]


def _nested_stage(outer_invisible=(), inner_inactive=()) -> Usd.Stage:
    """A 2x2 PointInstancer /World/Outer whose one prototype /World/Outer/Protos/Group
    (translate GROUP_T) holds the 2x2 PointInstancer Inner (translate INNER_T) of four
    0.5-unit cubes of COLORS: 16 cubes, cube k of outer instance i centred at
    INNER_POS[k] + INNER_T + GROUP_T + OUTER_POS[i] + OUTER_T."""
    stage = _stage()
    outer = UsdGeom.PointInstancer.Define(stage, "/World/Outer")
    outer.AddTranslateOp().Set(Gf.Vec3d(*OUTER_T))
    group = UsdGeom.Xform.Define(stage, "/World/Outer/Protos/Group")
    group.AddTranslateOp().Set(Gf.Vec3d(*GROUP_T))
    inner = UsdGeom.PointInstancer.Define(stage, "/World/Outer/Protos/Group/Inner")
    inner.AddTranslateOp().Set(Gf.Vec3d(*INNER_T))
    cubes = []
    for k, color in enumerate(COLORS):
        cube = UsdGeom.Cube.Define(stage, f"/World/Outer/Protos/Group/Inner/Protos/C{k}")
        cube.CreateSizeAttr(0.5)
        cube.CreateDisplayColorAttr([color])
        cubes.append(cube.GetPath())
    inner.CreatePrototypesRel().SetTargets(cubes)
    inner.CreateProtoIndicesAttr([0, 1, 2, 3])
    inner.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(INNER_POS.astype(np.float32)))
    outer.CreatePrototypesRel().SetTargets([group.GetPath()])
    outer.CreateProtoIndicesAttr([0, 0, 0, 0])
    outer.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(OUTER_POS.astype(np.float32)))
    if outer_invisible:
        outer.CreateInvisibleIdsAttr(list(outer_invisible))
    for j in inner_inactive:
        inner.DeactivateId(j)
    return stage


def _cube_center(i: int, k: int) -> np.ndarray:
    return INNER_POS[k] + INNER_T + GROUP_T + OUTER_POS[i] + OUTER_T


def _dominant(rgb) -> set[int]:
    """Channels within 50 % of the brightest (COLORS have one or two such channels)."""
    return {c for c in range(3) if rgb[c] > 0.5 * max(rgb)}


def test_nested_instancer_expands_every_level():
    ss = read_stage(_nested_stage())
    els = {e.path: e for e in ss.scene.elements}
    assert len(els) == 16
    for i in range(4):
        for k in range(4):
            e = els[f"/World/Outer.instance[{i}]/Inner.instance[{k}]"]
            np.testing.assert_allclose(e.center, _cube_center(i, k), atol=1e-6)
            np.testing.assert_allclose(e.bounds_max - e.bounds_min, 0.5, atol=1e-6)


def test_nested_instancer_masks_at_both_levels():
    ss = read_stage(_nested_stage(outer_invisible=[3], inner_inactive=[0]))
    paths = {e.path for e in ss.scene.elements}
    expected = {
        f"/World/Outer.instance[{i}]/Inner.instance[{k}]" for i in range(3) for k in (1, 2, 3)
    }
    assert paths == expected


def test_nested_instancer_follows_animation_at_every_level():
    stage = _nested_stage()
    outer = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Outer"))
    moved = OUTER_POS + [0.0, 0.0, -1.0]
    outer.GetPositionsAttr().Set(Vt.Vec3fArray.FromNumpy(OUTER_POS.astype(np.float32)), 1)
    outer.GetPositionsAttr().Set(Vt.Vec3fArray.FromNumpy(moved.astype(np.float32)), 2)
    # A transform below the outer prototype root (the inner instancer's), animated.
    inner = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Outer/Protos/Group/Inner"))
    (op,) = inner.GetOrderedXformOps()
    op.Set(Gf.Vec3d(*INNER_T), 1)
    op.Set(Gf.Vec3d(*(INNER_T + [0.0, 0.5, 0.0])), 2)
    ss = read_stage(stage)
    assert all(e.animated for e in ss.scene.elements)
    ss.set_time(2.0)
    for e in ss.scene.elements:
        i, k = (int(part.split("]")[0]) for part in e.path.split("[")[1:])
        np.testing.assert_allclose(e.center, _cube_center(i, k) + [0, 0.5, -1.0], atol=1e-6)


def test_nested_instancer_pixels_raster_and_rt_agree():
    ss = read_stage(_nested_stage())
    frames = {mode: _render(ss, mode)[0] for mode in MODES}
    for i in range(4):
        for k in range(4):
            eid = _element(ss, f"/World/Outer.instance[{i}]/Inner.instance[{k}]")
            pixel = _pixel(ss, _cube_center(i, k) + [0, 0, 0.25])  # the front face centre
            for mode, (ids, beauty) in frames.items():
                assert ids[pixel] == eid, (mode, i, k)
                assert _dominant(beauty[pixel]) == _dominant(COLORS[k]), (mode, i, k)
            # Same surface read the same way in both modes (the shading model's
            # float32 boundary: 1e-3 of a unit colour).
            np.testing.assert_allclose(
                frames["raster"][1][pixel], frames["rt"][1][pixel], atol=1e-3
            )


# ---- UsdSkel ---------------------------------------------------------------------------

#: Skeleton translate; joint translation at t = 1 and t = 2; blend shape "lift" offset
#: (weight 0 at t = 1, 1 at t = 2). Box: unit cube centred at the joint's origin.
SKEL_T = np.array([-1.5, 0.0, 0.0])
JOINT_T = {1.0: np.array([0.0, 0.0, 0.0]), 2.0: np.array([2.0, 0.0, 0.0])}
LIFT = np.array([0.0, 1.0, 0.0])
LIFT_W = {1.0: 0.0, 2.0: 1.0}
BOX = np.array([(x, y, z) for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])


def _skinned_stage(with_normals: bool = False) -> Usd.Stage:
    """SkelRoot /World/Char: Skeleton Skel (translate SKEL_T, one joint "root", identity
    bind and rest) animated by Anim (JOINT_T, LIFT_W); the unit box mesh Box bound to
    the joint with vertex weights 1, a blend shape "lift", and its own translate
    (10, 0, 0) that skinning replaces by the skeleton's transform."""
    stage = _stage()
    root = UsdSkel.Root.Define(stage, "/World/Char")
    skel = UsdSkel.Skeleton.Define(stage, "/World/Char/Skel")
    skel.AddTranslateOp().Set(Gf.Vec3d(*SKEL_T))
    skel.CreateJointsAttr(["root"])
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    anim = UsdSkel.Animation.Define(stage, "/World/Char/Skel/Anim")
    anim.CreateJointsAttr(["root"])
    translations = anim.CreateTranslationsAttr()
    for t, v in JOINT_T.items():
        translations.Set(Vt.Vec3fArray([Gf.Vec3f(*v)]), t)
    anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
    anim.CreateBlendShapesAttr(["lift"])
    weights = anim.CreateBlendShapeWeightsAttr()
    for t, w in LIFT_W.items():
        weights.Set(Vt.FloatArray([w]), t)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()]
    )
    box = UsdGeom.Mesh.Define(stage, "/World/Char/Box")
    box.AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    box.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(BOX.astype(np.float32)))
    # Faces of the cube, counter-clockwise seen from outside.
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    box.CreateFaceVertexCountsAttr([4] * 6)
    box.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    box.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    box.CreateDisplayColorAttr([(0.9, 0.6, 0.1)])
    if with_normals:  # per-face normals, faceVarying
        n = [(0, 0, -1), (0, 0, 1), (0, -1, 0), (0, 1, 0), (-1, 0, 0), (1, 0, 0)]
        box.CreateNormalsAttr([v for v in n for _ in range(4)])
        box.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    binding = UsdSkel.BindingAPI.Apply(box.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set(Vt.IntArray([0] * 8))
    binding.CreateJointWeightsPrimvar(False, 1).Set(Vt.FloatArray([1.0] * 8))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    lift = UsdSkel.BlendShape.Define(stage, "/World/Char/Box/lift")
    lift.CreateOffsetsAttr(Vt.Vec3fArray([Gf.Vec3f(*LIFT)] * 8))
    binding.CreateBlendShapesAttr(["lift"])
    binding.CreateBlendShapeTargetsRel().SetTargets([lift.GetPath()])
    assert root
    return stage


def _box_center(t: float) -> np.ndarray:
    return SKEL_T + JOINT_T[t] + LIFT_W[t] * LIFT


def test_skinned_box_points_follow_joint_and_blend_shape():
    ss = read_stage(_skinned_stage(with_normals=True))
    (box,) = ss.scene.elements
    assert box.animated
    for t in (1.0, 2.0, 1.0):
        ss.set_time(t)
        np.testing.assert_allclose(box.center, _box_center(t), atol=1e-6)
        np.testing.assert_allclose(box.bounds_max - box.bounds_min, 1.0, atol=1e-6)
    # Authored normals carried by the joint (a translation: unchanged), still unit.
    n = ss.scene.geometry.corner_normals.reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert {tuple(np.round(v).astype(int)) for v in n} == {
        (0, 0, 1), (0, 0, -1), (0, 1, 0), (0, -1, 0), (1, 0, 0), (-1, 0, 0)
    }


def test_skinned_normals_turn_with_the_joint():
    stage = _skinned_stage(with_normals=True)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/World/Char/Skel/Anim"))
    half = np.sqrt(0.5)
    anim.GetRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1)]), 1)
    anim.GetRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(half, 0, 0, half)]), 2)  # 90° about Z
    ss = read_stage(stage)
    ss.set_time(2.0)
    g = ss.scene.geometry
    # The lift (0, 1, 0) is applied before skinning, so the joint turns it to (-1, 0, 0).
    center = SKEL_T + JOINT_T[2.0] + [-1.0, 0.0, 0.0]
    np.testing.assert_allclose(ss.scene.elements[0].center, center, atol=1e-6)
    # Flat faces: every corner's skinned normal is its world triangle's outward normal.
    p = g.vertices[g.triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    assert np.all(np.sum((p.mean(axis=1) - center) * face, axis=1) > 0)  # outward winding
    np.testing.assert_allclose(g.corner_normals, np.repeat(face[:, None], 3, axis=1), atol=1e-5)


def test_skinned_box_without_animation_is_static_in_skeleton_space():
    stage = _skinned_stage()
    skel = UsdSkel.BindingAPI(stage.GetPrimAtPath("/World/Char/Skel"))
    skel.GetAnimationSourceRel().ClearTargets(True)
    ss = read_stage(stage)
    (box,) = ss.scene.elements
    # Rest pose = bind pose (identity): the points as authored, placed by the skeleton
    # (the mesh's own translate (10, 0, 0) does not apply to a skinned mesh).
    assert not box.animated
    np.testing.assert_allclose(box.center, SKEL_T, atol=1e-6)


def test_skinned_instanced_references_are_skinned_per_instance():
    stage = _skinned_stage()
    layer = stage.GetRootLayer()
    Sdf.CopySpec(layer, "/World/Char", layer, "/Proto")  # the character as a class
    stage.RemovePrim("/World/Char")
    stage.GetPrimAtPath("/Proto").SetSpecifier(Sdf.SpecifierClass)
    offsets = {"/World/A/Box": np.array([0.0, 3.0, 0.0]), "/World/B/Box": np.array([5.0, 3, 0])}
    for path, offset in offsets.items():
        inst = stage.DefinePrim(path.rsplit("/", 1)[0], "SkelRoot")
        inst.GetReferences().AddInternalReference("/Proto")
        inst.SetInstanceable(True)
        UsdGeom.Xformable(inst).AddTranslateOp().Set(Gf.Vec3d(*offset))
    ss = read_stage(stage)
    assert [e.path for e in ss.scene.elements] == list(offsets)
    for t in (1.0, 2.0):
        ss.set_time(t)
        for e in ss.scene.elements:
            assert e.animated
            np.testing.assert_allclose(e.center, _box_center(t) + offsets[e.path], atol=1e-6)


@pytest.mark.parametrize("mode", MODES)
def test_skinned_box_pixels_move_with_the_joint(mode):
    ss = read_stage(_skinned_stage())
    frames = _render(ss, mode, times=(1.0, 2.0))
    for t, (ids, _) in zip((1.0, 2.0), frames, strict=True):
        corners = ss.camera(t).project(BOX + _box_center(t), W, H)
        covered = np.argwhere(ids == 0)
        # The box's pixels fill its projected bounds (corner projections) to within the
        # 1 px of edge rasterization.
        assert covered.size
        assert abs(covered[:, 1].min() - corners[:, 0].min()) <= 1.0
        assert abs(covered[:, 1].max() + 1 - corners[:, 0].max()) <= 1.0
        assert abs(covered[:, 0].min() - corners[:, 1].min()) <= 1.0
        assert abs(covered[:, 0].max() + 1 - corners[:, 1].max()) <= 1.0
        other = 2.0 if t == 1.0 else 1.0
        assert ids[_pixel(ss, (_box_center(other) + [0, 0, 0.5]), t)] == -1


# ---- subdivision surfaces ----------------------------------------------------------------


def test_subdivided_meshes_are_listed_and_drawn_as_cage():
    stage = _stage()
    fallback = _quad(stage, "/World/Fallback", -3, -1, -1, 1)
    fallback.GetSubdivisionSchemeAttr().Clear()  # USD's fallback: catmullClark
    _quad(stage, "/World/Loop", -1, -1, 1, 1).CreateSubdivisionSchemeAttr("loop")
    _quad(stage, "/World/Polygons", 1, -1, 3, 1)
    hidden = _quad(stage, "/World/Hidden", 1, 1, 3, 2)
    hidden.GetSubdivisionSchemeAttr().Clear()
    hidden.MakeInvisible()
    expected = ["/World/Fallback", "/World/Loop"]
    assert subdivided_meshes(stage) == expected
    ss = read_stage(stage)
    assert ss.subdivided_meshes == expected
    assert ss.scene.geometry.triangle_count == 3 * 2  # each quad its cage: 2 triangles


# ---- reflectors inside instances -------------------------------------------------------


@pytest.mark.parametrize("mode", ["rt", "hybrid"])
def test_reflector_on_prototype_reflects_in_every_instance(mode):
    stage = _stage()
    proto = stage.CreateClassPrim("/Proto")
    mirror = _quad(stage, "/Proto/Mirror", -1, -1, 1, 1, color=(0.2, 0.2, 0.2))
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    assert proto
    for name, x in (("Left", -2.0), ("Right", 2.0)):
        inst = UsdGeom.Xform.Define(stage, f"/World/{name}")
        inst.GetPrim().GetInherits().AddInherit("/Proto")
        inst.GetPrim().SetInstanceable(True)
        inst.AddTranslateOp().Set(Gf.Vec3d(x, 0, 0))
    # Behind the camera, facing the mirrors: what they reflect (not in direct view).
    _quad(stage, "/World/Red", -20, -20, 20, 20, z=EYE_Z + 2, color=(0.9, 0.05, 0.05))
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Red")).CreateOrientationAttr(
        UsdGeom.Tokens.leftHanded
    )  # faces -Z
    ss = read_stage(stage)
    reflectors = [e.path for e in ss.scene.elements if e.is_reflector]
    assert reflectors == ["/World/Left/Mirror", "/World/Right/Mirror"]
    ids, beauty = _render(ss, mode)[0]
    for x in (-2.0, 2.0):
        pixel = _pixel(ss, (x, 0, 0))
        r, g, b = beauty[pixel]
        assert r > 3 * g and r > 3 * b, (x, beauty[pixel])  # the red quad, reflected
    ids_raster, beauty_raster = _render(ss, "raster")[0]
    r, g, b = beauty_raster[_pixel(ss, (2.0, 0, 0))]
    assert not r > 3 * g  # raster shows the environment fallback, not the red quad

