"""Motion vectors (``engine/motion.py``, ``FrameOutput.motion``) at pixels whose motion is
known analytically: a camera translating sideways over a wall, a still camera, a camera
turning in place (background included), elements moving rigidly in front of a still
camera; the first frame and a frame rendered out of order.

The stages: a camera at (0, 0, D) looking down -Z (focal 24, horizontal aperture 36, so
a pixel of a W-wide image spans tan(half fov) / (W / 2): FOCAL_PX = W * 24 / 36 pixels per
unit of x / depth), a wall at z = 0 facing it, and an optional mover (a quad facing the
camera) nearer. Convention under test: pixels, this frame's position minus the previous
frame's, +x right, +y down.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from phrt_usd.engine.motion import VertexMotion  # noqa: E402
from phrt_usd.engine.renderer import FrameRenderer  # noqa: E402
from phrt_usd.model.render_options import RenderOptions  # noqa: E402
from phrt_usd.usd.stage import open_stage  # noqa: E402

W, H = 64, 48
FOCAL_PX = W * 24.0 / 36.0  # pixels per unit of (camera x / depth)
D = 5.0  # the camera's distance to the wall (m)
#: The motion vectors are float64 projections of float64 G-buffer positions, stored as
#: float32: at values up to ~W pixels float32 keeps ~1e-5 px, so 1e-3 px is exact.
EXACT_PX = 1e-3


def _quad_xy(stage, path: str, half: float, z: float, color) -> UsdGeom.Mesh:
    """A square of side 2 ``half`` in the plane z = ``z``, facing +Z (towards the camera)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-half, -half, z), (half, -half, z), (half, half, z), (-half, half, z)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateDisplayColorAttr([color])
    return mesh


def _stage(path: Path, *, camera_x=(0.0, 0.0), camera_yaw=None, wall=True, wall_half=20.0,
           mover=None) -> Path:  # fmt: skip
    """Frames 1..len(camera_x): the camera at (camera_x[f], 0, D) (or turned by
    camera_yaw[f] degrees about +Y at (0, 0, D)), a wall of side 2 ``wall_half`` m at
    z = 0 unless not ``wall`` (then the view is the dome), ``mover``: a dict of a 0.5 m
    quad at z = mover["z"] with per-frame ``translate`` (x, y, z) and optional ``rotate``
    (degrees about Z)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.3, 0.5, 0.9))
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.0)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * H / W)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    frames = len(camera_yaw) if camera_yaw is not None else len(camera_x)
    move = UsdGeom.Xformable(cam).AddTranslateOp()
    if camera_yaw is not None:
        turn = UsdGeom.Xformable(cam).AddRotateYOp()
        for f, yaw in enumerate(camera_yaw):
            move.Set(Gf.Vec3d(0.0, 0.0, D), f + 1)
            turn.Set(float(yaw), f + 1)
    else:
        for f, x in enumerate(camera_x):
            move.Set(Gf.Vec3d(x, 0.0, D), f + 1)
    if wall:
        _quad_xy(stage, "/World/Wall", wall_half, 0.0, (0.6, 0.6, 0.6))
    if mover is not None:
        quad = _quad_xy(stage, "/World/Mover", 0.5, 0.0, (0.9, 0.1, 0.1))
        xf = UsdGeom.Xformable(quad)
        shift = xf.AddTranslateOp()
        spin = xf.AddRotateZOp() if "rotate" in mover else None
        for f, offset in enumerate(mover["translate"]):
            shift.Set(Gf.Vec3d(offset[0], offset[1], mover["z"] + offset[2]), f + 1)
            if spin is not None:
                spin.Set(float(mover["rotate"][f]), f + 1)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    stage.GetRootLayer().Save()
    return path


def _render(path: Path, times, plan=None, mode="raster"):
    """FrameOutputs of ``times`` rendered in order by one renderer planned on ``plan``
    (default: ``times``)."""
    scene = open_stage(path)
    renderer = FrameRenderer(scene, RenderOptions(mode=mode, width=W, height=H))
    try:
        renderer.plan(list(plan if plan is not None else times))
        return [renderer.render(t) for t in times], scene
    finally:
        renderer.close()


@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_camera_translating_sideways_over_a_wall(tmp_path, mode):
    """The camera moves 0.3 m right between frames 1 and 2 at 5 m from the wall: every
    pixel of the wall moves 0.3 / 5 x FOCAL_PX = 2.56 pixels left, none up or down; the
    first frame has no previous one: zero motion. The same from the raster G-buffer and
    from primary rays (``rt``)."""
    path = _stage(tmp_path / "pan.usda", camera_x=(0.0, 0.3))
    (first, second), _ = _render(path, [1.0, 2.0], mode=mode)
    assert second.gbuffer.covered.all()  # the wall fills the view
    assert np.array_equal(first.motion, np.zeros((H, W, 2), np.float32))
    want = -0.3 / D * FOCAL_PX
    assert np.abs(second.motion[..., 0] - want).max() < EXACT_PX
    assert np.abs(second.motion[..., 1]).max() < EXACT_PX


@pytest.mark.slow
def test_still_camera_over_a_still_scene_is_zero(tmp_path):
    """Camera and a 4 m wall do not move (the dome around it): the motion is 0 at every
    pixel, covered or background (the same projection both ways: float64 round-off)."""
    path = _stage(tmp_path / "still.usda", camera_x=(0.0, 0.0), wall_half=2.0)
    (_, second), _ = _render(path, [1.0, 2.0])
    covered = second.gbuffer.covered
    assert second.motion_field.has_previous and covered.any() and not covered.all()
    assert np.abs(second.motion).max() < EXACT_PX


@pytest.mark.parametrize("wall", [True, False])
def test_camera_turning_in_place_moves_every_pixel_alike_at_any_depth(tmp_path, wall):
    """A pure turn by 4 degrees about +Y: a pixel's direction (x, y, -1) in this camera
    was ((x cos t - sin t), y, ...) / (x sin t + cos t) in the previous one, whatever its
    depth; the background (no wall: the dome) moves by the same formula (points at
    infinity)."""
    theta = math.radians(4.0)
    path = _stage(tmp_path / "turn.usda", camera_yaw=(0.0, 4.0), wall=wall)
    (_, second), _ = _render(path, [1.0, 2.0])
    assert second.gbuffer.covered.all() == wall and (wall or not second.gbuffer.covered.any())
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = (cols - W / 2) / FOCAL_PX, (H / 2 - rows) / FOCAL_PX
    scale = x * math.sin(theta) + math.cos(theta)
    then_x, then_y = (x * math.cos(theta) - math.sin(theta)) / scale, y / scale
    want = np.stack([cols - (W / 2 + FOCAL_PX * then_x), rows - (H / 2 - FOCAL_PX * then_y)], -1)
    assert np.abs(second.motion - want).max() < EXACT_PX
    assert np.abs(want[..., 0]).min() > 2.0  # the turn moves every pixel a few pixels


@pytest.mark.slow
def test_element_moving_rigidly_moves_its_pixels_by_the_projected_displacement(tmp_path):
    """Still camera, still wall; a quad 2 m nearer (depth 3 m) moves by (0.2, 0.1, 0) m:
    its pixels move by (0.2, -0.1) / 3 x FOCAL_PX pixels (y up in the world is up the
    image, rows down), the wall's by 0."""
    mover = {"z": 2.0, "translate": [(0.0, 0.0, 0.0), (0.2, 0.1, 0.0)]}
    path = _stage(tmp_path / "mover.usda", camera_x=(0.0, 0.0), mover=mover)
    (_, second), scene = _render(path, [1.0, 2.0])
    ids = second.gbuffer.element_id
    mover_id = next(i for i, e in enumerate(scene.scene.elements) if e.path == "/World/Mover")
    on_mover = ids == mover_id
    assert on_mover.sum() > 100  # the quad covers about 11 x 11 pixels
    depth = D - 2.0
    want = np.array([0.2 / depth * FOCAL_PX, -0.1 / depth * FOCAL_PX])
    assert np.abs(second.motion[on_mover] - want).max() < EXACT_PX
    assert np.abs(second.motion[~on_mover]).max() < EXACT_PX


def test_element_turning_and_moving_with_a_moving_camera(tmp_path):
    """The quad turns 20 degrees about its axis and moves while the camera moves too:
    each mover pixel's previous position is its point taken back through the quad's two
    transforms (the rigid motion, computed here from the authored values) and projected
    with the previous camera (``CameraFrame.project``)."""
    mover = {"z": 2.0, "translate": [(0.1, 0.0, 0.0), (0.25, -0.05, 0.3)], "rotate": [0.0, 20.0]}
    path = _stage(tmp_path / "turning.usda", camera_x=(0.0, 0.15), mover=mover)
    (_, second), scene = _render(path, [1.0, 2.0])
    mover_id = next(i for i, e in enumerate(scene.scene.elements) if e.path == "/World/Mover")
    on_mover = second.gbuffer.element_id == mover_id
    points = second.gbuffer.position[on_mover]

    def placed(offset, degrees, p):  # rotate about Z, then translate (USD op order)
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return p @ rot.T + np.array([offset[0], offset[1], 2.0 + offset[2]])

    c, s = math.cos(math.radians(20.0)), math.sin(math.radians(20.0))
    rot_now = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = (points - np.array([0.25, -0.05, 2.3])) @ rot_now  # inverse of rotate + translate
    before = placed((0.1, 0.0, 0.0), 0.0, local)
    then = scene.camera(1.0).project(before, W, H)[:, :2]
    rows, cols = np.nonzero(on_mover)
    want = np.stack([cols + 0.5, rows + 0.5], 1) - then
    assert on_mover.sum() > 100
    assert np.abs(second.motion[on_mover] - want).max() < EXACT_PX


@pytest.mark.slow
def test_a_frame_rendered_out_of_order_gets_the_motion_of_its_planned_predecessor(tmp_path):
    """Frame 3 of the plan 1, 2, 3 rendered alone (as after a resume) has the motion of
    frame 3 rendered after 1 and 2: the renderer evaluates the stage at frame 2 for the
    mover's previous vertices."""
    mover = {"z": 2.0, "translate": [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.3, 0.1, 0.0)]}
    path = _stage(tmp_path / "order.usda", camera_x=(0.0, 0.1, 0.15), mover=mover)
    in_order, _ = _render(path, [1.0, 2.0, 3.0])
    alone, _ = _render(path, [3.0], plan=[1.0, 2.0, 3.0])
    assert np.abs(in_order[2].motion).max() > 1.0
    # Both are the same float64 computation on the same G-buffer.
    assert np.abs(alone[0].motion - in_order[2].motion).max() < 1e-5


def test_previous_points_keep_barycentric_coordinates_of_a_deformed_triangle():
    """A triangle whose corners move apart (not rigidly): a point at barycentrics (0.2,
    0.3, 0.5) now was at the same barycentrics of the previous corners; a point on a
    triangle that did not move stays."""
    now = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    before = np.array([[1.0, 1.0, 1.0], [2.0, 1.5, 1.0], [0.5, 2.0, 2.0]])
    vm = VertexMotion(
        tri_rows=np.array([7]), tri_vertices=np.array([[10, 11, 12]]),
        vertex_ids=np.array([10, 11, 12]), previous=before, current=now,
    )  # fmt: skip
    bary = np.array([0.2, 0.3, 0.5])
    points = np.array([bary @ now, [5.0, 5.0, 5.0]])
    moved = vm.previous_points(np.array([7, 3]), points)
    assert np.allclose(moved[0], bary @ before, atol=1e-12)
    assert np.array_equal(moved[1], points[1])
