"""Camera evaluation: PhrtCameraPath interpolation, look-at, time-sampled xform cameras."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Gf, Usd, UsdGeom
from scenes import camera_path_stage

from phrt_usd.errors import PhrtError
from phrt_usd.usd.camera_path import interpolate, look_at
from phrt_usd.usd.stage import read_stage

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)


def assert_rotation(m):
    r = m[:3, :3]
    assert np.all(np.isfinite(m))
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0)


POS = [(0, 0, 0), (10, 0, 0), (10, 0, 10), (0, 5, 10)]
TGT = [(0, 0, -5), (10, 0, -5), (20, 0, 10), (0, 5, 20)]
KEYS = [0.0, 10.0, 15.0, 40.0]


@pytest.mark.parametrize("interp", ["linear", "catmullRom"])
def test_exact_at_key_times_and_clamped(interp):
    ss = read_stage(camera_path_stage(POS, TGT, KEYS, interp, startFrame=0.0, endFrame=40.0))
    assert ss.frame_range == (0.0, 40.0)
    assert ss.path_driver is not None
    for p, t, k in zip(POS, TGT, KEYS, strict=True):
        cam = ss.camera(k)
        np.testing.assert_allclose(cam.position, p, atol=1e-12)
        d = np.subtract(t, p)
        np.testing.assert_allclose(cam.forward, d / np.linalg.norm(d), atol=1e-12)
        assert_rotation(cam.world_from_camera)
    np.testing.assert_allclose(ss.camera(-100).position, POS[0])  # clamped before
    np.testing.assert_allclose(ss.camera(1e9).position, POS[-1])  # clamped after
    assert ss.camera(0).focal_length == pytest.approx(35.0)


def test_linear_midpoint_and_catmull_rom_smooth():
    pts = np.array(POS, float)
    keys = np.array(KEYS)
    np.testing.assert_allclose(interpolate(pts, keys, 5.0, "linear"), [5, 0, 0])
    # Catmull-Rom is C1: the velocity is continuous across key 10.
    eps = 1e-6
    v_left = (
        interpolate(pts, keys, 10 - eps, "catmullRom")
        - interpolate(pts, keys, 10 - 2 * eps, "catmullRom")
    ) / eps
    v_right = (
        interpolate(pts, keys, 10 + 2 * eps, "catmullRom")
        - interpolate(pts, keys, 10 + eps, "catmullRom")
    ) / eps
    np.testing.assert_allclose(v_left, v_right, rtol=1e-3, atol=1e-3)
    # Collinear points: the spline stays on the line, and moves forward only.
    line = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3.0]])
    s = interpolate(line, np.arange(4.0), np.linspace(0, 3, 31), "catmullRom")
    np.testing.assert_allclose(s - s[:, :1], 0.0, atol=1e-12)
    assert np.all(np.diff(s[:, 0]) > 0)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(
    st.lists(vec3, min_size=1, max_size=6),
    st.lists(st.floats(min_value=0.01, max_value=100), min_size=6, max_size=6),
)
def test_catmull_rom_passes_through_control_points(points, gaps):
    pts = np.array(points)
    keys = np.concatenate([[0.0], np.cumsum(gaps[: len(pts) - 1])])
    out = interpolate(pts, keys, keys, "catmullRom")
    np.testing.assert_allclose(out, pts, atol=1e-6 * (1 + np.abs(pts).max()))
    mid = interpolate(pts, keys, np.linspace(-1, keys[-1] + 1, 17), "catmullRom")
    assert np.all(np.isfinite(mid))


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@given(vec3, vec3, st.sampled_from([(0, 1, 0), (0, 0, 1)]))
def test_look_at_never_nan(pos, tgt, up):
    m = look_at(pos, tgt, np.array(up, float))
    assert_rotation(m)
    d = tgt - pos
    if np.linalg.norm(d) > 1e-6:
        np.testing.assert_allclose(-m[:3, 2], d / np.linalg.norm(d), atol=1e-6)


@pytest.mark.parametrize("up", ["Y", "Z"])
def test_degenerate_views(up):
    upv = np.array([0, 1.0, 0]) if up == "Y" else np.array([0, 0, 1.0])
    same = [(1, 2, 3), (1, 2, 3)]
    straight_up = [tuple(np.array([1, 2, 3]) + 5 * upv), tuple(np.array([1, 2, 3]) - 5 * upv)]
    ss = read_stage(camera_path_stage([(1, 2, 3), (1, 2, 3)], same + [], [0.0, 1.0], up=up))
    assert_rotation(ss.camera(0.5).world_from_camera)
    ss = read_stage(camera_path_stage([(1, 2, 3), (1, 2, 3)], straight_up, [0.0, 1.0], up=up))
    m0, m1 = ss.camera(0).world_from_camera, ss.camera(1).world_from_camera
    assert_rotation(m0)
    assert_rotation(m1)
    np.testing.assert_allclose(-m0[:3, 2], upv, atol=1e-12)  # looking straight up
    np.testing.assert_allclose(-m1[:3, 2], -upv, atol=1e-12)  # and straight down
    # Ordinary views keep the stage up axis as camera up (no roll).
    ss = read_stage(
        camera_path_stage([(0, 0, 0)], [tuple(np.cross(upv, [1, 0, 0]) + [1, 0, 0])], None, up=up)
    )
    cam_up = ss.camera(0).world_from_camera[:3, 1]
    assert np.dot(cam_up, upv) > 0.5
    assert abs(np.dot(ss.camera(0).world_from_camera[:3, 0], upv)) < 1e-12


def test_path_in_stage_units_scaled_to_metres():
    ss = read_stage(camera_path_stage(POS, TGT, KEYS, mpu=0.01))
    np.testing.assert_allclose(ss.camera(10).position, [0.1, 0, 0])


def test_key_times_default_and_frame_range_from_keys():
    ss = read_stage(camera_path_stage(POS, TGT, None, startFrame=1.0, endFrame=31.0))
    np.testing.assert_allclose(ss.path_driver.key_times, [1, 11, 21, 31])
    np.testing.assert_allclose(ss.camera(11).position, POS[1])
    ss = read_stage(camera_path_stage(POS, TGT, KEYS))
    assert ss.frame_range == (0.0, 40.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"keys": [0.0, 5.0, 5.0, 9.0]}, "strictly increasing"),
        ({"keys": [0.0, 1.0]}, "2 times for 4"),
        ({"interp": "bezier"}, "phrt:interpolation"),
        ({"targets": TGT[:2]}, "phrt:targets"),
    ],
)
def test_invalid_paths_raise(kwargs, match):
    args = {"positions": POS, "targets": TGT, "keys": KEYS, "interp": "linear"} | kwargs
    with pytest.raises(PhrtError, match=match):
        read_stage(camera_path_stage(**args))


def test_time_sampled_xform_camera_without_path():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.5)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(25)
    rig = UsdGeom.Xform.Define(stage, "/Rig")
    cam = UsdGeom.Camera.Define(stage, "/Rig/Cam")
    rig.AddScaleOp().Set(Gf.Vec3f(3, 3, 3))  # scale must not leak into the rotation
    tr = cam.AddTranslateOp()
    tr.Set(Gf.Vec3d(0, 0, 0), 1)
    tr.Set(Gf.Vec3d(4, 0, 0), 25)
    rot = cam.AddRotateYOp()
    rot.Set(0.0, 1)
    rot.Set(90.0, 25)
    cam.GetFocalLengthAttr().Set(20.0, 1)
    cam.GetFocalLengthAttr().Set(80.0, 25)
    ss = read_stage(stage)
    assert ss.path_driver is None
    assert ss.frame_range == (1.0, 25.0)
    c0, c1 = ss.camera(1), ss.camera(25)
    np.testing.assert_allclose(c0.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(c1.forward, [-1, 0, 0], atol=1e-12)  # rotateY 90: -Z → -X
    np.testing.assert_allclose(c1.position, [4 * 3 * 0.5, 0, 0])  # stage units × scale × mpu
    np.testing.assert_allclose(ss.camera(13).position, [3, 0, 0])
    assert (c0.focal_length, c1.focal_length) == (20.0, 80.0)
    for c in (c0, c1, ss.camera(7.3)):
        assert_rotation(c.world_from_camera)


def test_path_for_other_camera_is_ignored():
    stage = camera_path_stage(POS, TGT, KEYS)
    other = UsdGeom.Camera.Define(stage, "/Other")
    other.AddTranslateOp().Set(Gf.Vec3d(7, 8, 9))
    ss = read_stage(stage, camera="/Other")
    assert ss.path_driver is None
    np.testing.assert_allclose(ss.camera(0).position, [7, 8, 9])


def test_bad_camera_attributes_raise():
    stage = camera_path_stage(POS, TGT, KEYS)
    UsdGeom.Camera(stage.GetPrimAtPath("/Cam")).GetFocalLengthAttr().Set(0.0)
    with pytest.raises(PhrtError, match="focalLength"):
        read_stage(stage).camera(0)


def test_catmull_rom_matches_uniform_spline_for_even_keys():
    """Even key spacing: the classic uniform Catmull-Rom with duplicated end points."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(6, 3))
    keys = 2.0 + 5.0 * np.arange(6)
    t = np.linspace(keys[0], keys[-1], 101)
    seg = np.clip(((t - keys[0]) // 5).astype(int), 0, 4)
    s = ((t - keys[seg]) / 5.0)[:, None]
    p0, p1 = pts[np.maximum(seg - 1, 0)], pts[seg]
    p2, p3 = pts[seg + 1], pts[np.minimum(seg + 2, 5)]
    ref = 0.5 * (
        2 * p1
        + (p2 - p0) * s
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s**2
        + (-p0 + 3 * p1 - 3 * p2 + p3) * s**3
    )
    np.testing.assert_allclose(interpolate(pts, keys, t, "catmullRom"), ref, atol=1e-12)
