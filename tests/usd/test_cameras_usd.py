"""Cameras as GfCamera and UsdRender define them: both apertures, aperture offsets, the
settings' aspectRatioConformPolicy and pixelAspectRatio (``CameraFrame.image_window``),
camera choice by name, and the default camera of a stage without any.

The stage: a unit square (z = 0, centred on the origin, facing +Z) seen by a camera at
z = 1.25 looking down -Z, focal length 20 mm over a square 20 x 20 mm aperture: the
aperture window is tan = +-0.5 and the square spans tan = +-0.4 of it. Rendered at
64 x 48 (4:3), every edge falls between pixel centres (at 4.8, 12.8, ... pixels), so the
covered rows and columns follow exactly from the window and raster and rt must agree
pixel for pixel.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from image_thresholds import HYBRID_VS_RT_FLIP
from pxr import Gf, Usd, UsdGeom, UsdRender
from scenes import mirror_floor_stage

from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.model.scene import CameraFrame
from phrt_usd.pytest_plugin import assert_images_close
from phrt_usd.usd.default_camera import FOCAL_LENGTH, VERTICAL_APERTURE
from phrt_usd.usd.stage import choose_camera, read_stage

W, H = 64, 48
FOCAL = 20.0
APERTURE = 20.0  # square: tan(half field of view) = 0.5 both ways
DISTANCE = 1.25  # the unit square's half side 0.5 is tan 0.4 at this distance


def _square_stage(
    policy: str | None = None, offsets=(0.0, 0.0), pixel_aspect: float | None = None
) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    quad = UsdGeom.Mesh.Define(stage, "/World/Square")
    quad.CreatePointsAttr([(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)])
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(APERTURE)
    cam.CreateVerticalApertureAttr(APERTURE)
    cam.CreateHorizontalApertureOffsetAttr(offsets[0])
    cam.CreateVerticalApertureOffsetAttr(offsets[1])
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 10.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, DISTANCE))
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(W, H))
    if policy is not None:
        settings.CreateAspectRatioConformPolicyAttr(policy)
    if pixel_aspect is not None:
        settings.CreatePixelAspectRatioAttr(pixel_aspect)
    return stage


def _covered(stage: Usd.Stage) -> tuple[list[int], list[int]]:
    """(rows, cols) the square covers, after checking raster and rt ids are identical."""
    scene = read_stage(stage)
    camera = scene.camera(scene.frame_range[0])
    with Rasterizer(scene.scene, W, H) as r:
        raster = r.render(camera).element_id
    rt = Tracer(scene.scene, threads=1).primary_gbuffer(camera, W, H).element_id
    # Every edge is >= 0.2 px from a pixel centre: raster and primary rays agree exactly.
    np.testing.assert_array_equal(raster, rt)
    rows = np.flatnonzero((raster >= 0).any(axis=1)).tolist()
    cols = np.flatnonzero((raster >= 0).any(axis=0)).tolist()
    return rows, cols


def _span(a: int, b: int) -> list[int]:
    return list(range(a, b + 1))


# Covered rows / cols from the window's half sizes (hx, hy) and centre (cx, cy): the
# square's edges at tan +-0.4 land on pixel ((+-0.4 - cx) / hx + 1) * W / 2 (columns),
# (1 - (+-0.4 - cy) / hy) * H / 2 (rows); a pixel is covered when its centre is inside:
# edges at pixel coordinates a < b cover ceil(a - 0.5) .. floor(b - 0.5).
CONFORM_CASES = {
    # hx = 0.5 * 64/48, hy = 0.5: the whole square in view (rows 4.8..43.2).
    "expandAperture": (_span(5, 42), _span(13, 50)),
    # hx = 0.5, hy = 0.5 * 48/64 = 0.375 < 0.4: top and bottom cropped away.
    "cropAperture": (_span(0, 47), _span(6, 57)),
    "adjustApertureWidth": (_span(5, 42), _span(13, 50)),  # keeps hy = 0.5
    "adjustApertureHeight": (_span(0, 47), _span(6, 57)),  # keeps hx = 0.5
    # hx = hy = 0.5: the square aperture on a 4:3 image, pixels stretched.
    "adjustPixelAspectRatio": (_span(5, 42), _span(6, 57)),
}


@pytest.mark.slow
@pytest.mark.parametrize("policy", list(CONFORM_CASES))
def test_conform_policy_decides_what_of_a_square_aperture_a_4_3_image_shows(policy):
    assert _covered(_square_stage(policy)) == CONFORM_CASES[policy]


def test_unauthored_policy_is_expand_aperture():
    assert _covered(_square_stage()) == CONFORM_CASES["expandAperture"]


def test_aperture_offsets_shift_the_image_by_the_analytic_pixels():
    # cx = 2.5 / 20 = 0.125 of hx = 2/3: the image moves 0.125 / (4/3) * 64 = 6 px left;
    # cy = 1.25 / 20 = 0.0625 of hy = 0.5: it moves 0.0625 / 1 * 48 = 3 px down.
    rows, cols = _covered(_square_stage(offsets=(2.5, 1.25)))
    assert (rows, cols) == (_span(8, 45), _span(7, 44))


def test_pixel_aspect_ratio_widens_the_image_under_expand():
    # Image aspect 64 * 2 / 48 = 8/3: hy = 0.5, hx = 0.5 * 8/3 = 4/3; edges at columns
    # (+-0.3 + 1) * 32 = 22.4 and 41.6.
    assert _covered(_square_stage(pixel_aspect=2.0)) == (_span(5, 42), _span(22, 41))


def test_window_equals_gf_camera_frustum_when_aspects_match():
    # With the image aspect of the aperture no policy changes the window: it must be
    # GfCamera's frustum window (offsets included) for every policy.
    gf = Gf.Camera()
    gf.focalLength, gf.horizontalAperture, gf.verticalAperture = 35.0, 36.0, 24.0
    gf.horizontalApertureOffset, gf.verticalApertureOffset = 3.0, -1.5
    window = gf.frustum.window
    expected = (window.min[0], window.max[0], window.min[1], window.max[1])
    for policy in CONFORM_CASES:
        cam = CameraFrame(np.eye(4), 35.0, 36.0, 0.1, 10.0, 24.0, 3.0, -1.5, policy)
        np.testing.assert_allclose(cam.image_window(360, 240), expected, rtol=1e-12)


def test_bad_settings_values_are_one_line_errors():
    with pytest.raises(PhrtError, match=r"^/Render/Settings\.pixelAspectRatio: must be"):
        read_stage(_square_stage(pixel_aspect=0.0))
    with pytest.raises(PhrtError, match=r"^/Render/Settings\.aspectRatioConformPolicy: 'fit'"):
        read_stage(_square_stage("fit"))


def test_data_window_names_its_pixels():
    stage = _square_stage()
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    settings.CreateDataWindowNDCAttr(Gf.Vec4f(0.25, 0.5, 1.0, 1.0))
    scene = read_stage(stage)
    cam = scene.camera(0.0)
    # Columns whose centres are in [0.25, 1] * 64, rows (down) in [0, 0.5] * 48.
    assert cam.data_window_pixels(W, H) == (16, 0, 64, 24)
    # Applied to the written images (tests/run/test_camera_outputs.py): no warning.
    assert not any("dataWindowNDC" in w for w in scene.warnings)


def test_camera_by_name_or_path():
    stage = _square_stage()
    UsdGeom.Camera.Define(stage, "/World/Rig/Side")
    assert str(choose_camera(stage, "Side").GetPath()) == "/World/Rig/Side"
    assert str(choose_camera(stage, "/World/Cam").GetPath()) == "/World/Cam"
    UsdGeom.Camera.Define(stage, "/World/Other/Side")
    with pytest.raises(BadOption, match=r"^--camera Side: 2 cameras have this name "
                       r"\(/World/Rig/Side, /World/Other/Side\)$"):  # fmt: skip
        choose_camera(stage, "Side")
    have = r"\(cameras: /World/Cam, /World/Rig/Side, /World/Other/Side\)$"
    with pytest.raises(PhrtError, match=r"^--camera Top: no UsdGeomCamera of this name " + have):
        choose_camera(stage, "Top")


@pytest.mark.slow
def test_cli_refuses_an_ambiguous_camera_name_in_one_line(tmp_path):
    stage = _square_stage()
    UsdGeom.Camera.Define(stage, "/A/Cam")
    path = tmp_path / "s.usda"
    stage.GetRootLayer().Export(str(path))
    cli = [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render", str(path)]
    done = subprocess.run(
        [*cli, "--camera", "Cam", "--out", str(tmp_path / "out"), "--frames", "1"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr  # a bad option
    assert "Traceback" not in done.stderr
    assert "--camera Cam: 2 cameras have this name (/World/Cam, /A/Cam)" in done.stderr
    assert done.stderr.count("\n") == 1, done.stderr


def _box_stage(up: str, lo, hi) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    cube = UsdGeom.Cube.Define(stage, "/Box")
    cube.CreateSizeAttr(1.0)
    lo, hi = np.array(lo, float), np.array(hi, float)
    xf = UsdGeom.Xformable(cube)
    xf.AddTranslateOp().Set(Gf.Vec3d(*(0.5 * (lo + hi))))
    xf.AddScaleOp().Set(Gf.Vec3f(*(hi - lo)))
    return stage


@pytest.mark.parametrize("up", ["Y", "Z"])
def test_default_camera_frames_the_bounds_along_the_up_axis(up):
    lo, hi = (1.0, 2.0, -3.0), (3.0, 6.0, 1.0)  # a 2 x 4 x 4 box centred on (2, 4, -1)
    scene = read_stage(_box_stage(up, lo, hi))
    cam = scene.camera(0.0)
    assert scene.camera_path == "<default camera>"
    assert "no UsdGeomCamera; rendering with a default camera" in scene.warnings[-1]
    centre, radius = np.array([2.0, 4.0, -1.0]), 3.0  # half the diagonal sqrt(36)
    # usdrecord's convention: from +Z looking down -Z (Y up), from -Y looking down +Y
    # with +Z up in the image (Z up); distance: the sphere tangent to the vertical
    # (smaller) half field of view atan(15.2908 / 2 / 50).
    distance = radius / np.sin(np.arctan(0.5 * VERTICAL_APERTURE / FOCAL_LENGTH))
    back = np.array([0.0, 0.0, 1.0]) if up == "Y" else np.array([0.0, -1.0, 0.0])
    np.testing.assert_allclose(cam.position, centre + distance * back, rtol=1e-12)
    np.testing.assert_allclose(cam.forward, -back, atol=1e-15)
    image_up = cam.world_from_camera[:3, 1]
    np.testing.assert_allclose(image_up, [0, 1, 0] if up == "Y" else [0, 0, 1], atol=1e-15)
    # The centre projects to the image centre; every corner of the bounds into the image.
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])  # fmt: skip
    px = cam.project(np.vstack([centre, corners]), W, H)
    np.testing.assert_allclose(px[0, :2], [W / 2, H / 2], atol=1e-9)
    assert np.all((px[1:, 0] > 0) & (px[1:, 0] < W) & (px[1:, 1] > 0) & (px[1:, 1] < H))
    assert np.all(px[1:, 2] >= cam.near) and np.all(px[1:, 2] <= cam.far)
    # Rendered: the box is seen, and nowhere touches the image border.
    with Rasterizer(scene.scene, W, H) as r:
        ids = r.render(cam).element_id
    rt = Tracer(scene.scene, threads=1).primary_gbuffer(cam, W, H).element_id
    assert np.mean(ids == rt) >= 0.995  # the hybrid-all == rt id agreement
    assert (ids >= 0).sum() > 0.05 * W * H
    border = np.concatenate([ids[0], ids[-1], ids[:, 0], ids[:, -1]])
    assert np.all(border == -1)


@pytest.mark.parametrize("authored", ["X", "banana"])
def test_an_up_axis_usd_does_not_define_is_read_as_y_with_one_warning(authored):
    """UsdGeom defines upAxis Y and Z only; USD returns any authored token. The stage is
    read as USD's fallback (Y): the default camera looks down -Z, and a warning says so."""
    stage = _box_stage("Y", (-1, -1, -1), (1, 1, 1))
    stage.SetMetadata("upAxis", authored)
    scene = read_stage(stage)
    assert scene.up_axis == "Y"
    [warning] = [w for w in scene.warnings if "upAxis" in w]
    assert f"upAxis {authored!r} is not Y or Z; read as Y" in warning and "\n" not in warning
    np.testing.assert_allclose(scene.camera(0.0).forward, [0, 0, -1], atol=1e-15)


#: Share of pixels whose element ids must agree between hybrid with every reflector
#: traced and rt (the renderer's invariant, docs/design.md; the mean FLIP allowed is
#: image_thresholds.HYBRID_VS_RT_FLIP).
ID_AGREEMENT = 0.995


def test_hybrid_all_equals_rt_with_offsets_and_a_conformed_square_aperture(tmp_path):
    stage = Usd.Stage.Open(str(mirror_floor_stage(tmp_path / "mirror.usda", W, H)))
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    cam.GetVerticalApertureAttr().Set(36.0)  # square: expandAperture widens it at 4:3
    cam.CreateHorizontalApertureOffsetAttr(3.0)
    cam.CreateVerticalApertureOffsetAttr(-2.0)
    scene = read_stage(stage)
    outs = {}
    for mode in ("hybrid", "rt"):
        options = RenderOptions(mode=mode, heuristic="all", width=W, height=H, budget_ms=None)
        renderer = FrameRenderer(scene, options)
        try:
            outs[mode] = renderer.render(1.0)
        finally:
            renderer.close()
    hybrid, rt = outs["hybrid"], outs["rt"]
    assert np.mean(hybrid.gbuffer.element_id == rt.gbuffer.element_id) >= ID_AGREEMENT
    assert hybrid.traced_mask.any()  # the mirror is in view and traced
    assert_images_close(hybrid.beauty, rt.beauty, max_mean_flip=HYBRID_VS_RT_FLIP, min_psnr=None)


@pytest.mark.parametrize(
    ("clipping", "visible"),
    # The square lies at view depth DISTANCE = 1.25 m: inside (0.1, 10) and (1.2, 1.3),
    # in front of near in (1.3, 10) and beyond far in (0.1, 1.2).
    [((0.1, 10.0), True), ((1.2, 1.3), True), ((1.3, 10.0), False), ((0.1, 1.2), False)],
)
def test_clipping_range_clips_raster_and_primary_rays_alike(clipping, visible):
    stage = _square_stage()
    UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam")).GetClippingRangeAttr().Set(
        Gf.Vec2f(*clipping)
    )
    rows, cols = _covered(stage)  # raster ids == rt ids is checked inside
    assert bool(rows) == visible and bool(cols) == visible


def test_a_product_authors_the_image_window_over_its_settings():
    """A RenderProduct is a UsdRenderSettingsBase: its authored conform policy overrides
    the settings' (here the unauthored expandAperture); products that disagree are
    refused in one line, as for resolution and camera."""
    stage = _square_stage()
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    beauty = UsdRender.Product.Define(stage, "/Render/Beauty")
    beauty.CreateAspectRatioConformPolicyAttr("cropAperture")
    settings.CreateProductsRel().SetTargets([beauty.GetPath()])
    assert _covered(stage) == CONFORM_CASES["cropAperture"]
    other = UsdRender.Product.Define(stage, "/Render/Other")
    other.CreateAspectRatioConformPolicyAttr("adjustPixelAspectRatio")
    settings.GetProductsRel().AddTarget(other.GetPath())
    match = r"^products differ in aspectRatioConformPolicy \(/Render/Beauty"
    with pytest.raises(PhrtError, match=match):
        read_stage(stage)
