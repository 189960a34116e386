"""UsdLux as the schema defines it, in raster and rt: intensity x 2^exposure x colour x
colour temperature, ``normalize``, ShapingAPI cones, DomeLight_1 and its pole axis, the
dome hidden from camera, camera exposure, ``--exposure``, the clipping warning and the
default light rig of a stage without lights.

The stage: a grey (albedo 0.5) square 4 x 4 m at z = 0 facing +Z, seen by a camera at
z = 2 looking down -Z (focal 20 over a 20 x 15 aperture: the view spans x +-1 m,
y +-0.75 m at the square, so the square fills the W x H = 32 x 24 frame). Pixel
(row, col) sees the square at x = ((col + 0.5) / 16 - 1) m, y = (1 - (row + 0.5) / 12)
x 0.75 m. Unless a test says otherwise a black dome (intensity 0) removes the ambient
term, so a pixel is the direct light alone: Lambert without 1/pi (engine/shading.py:
albedo x E x n.l) plus the white highlight 0.25 x E x (n.h)^64.
"""

from __future__ import annotations

import json

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux
from scenes import grey_square_stage, preview_shade
from shading_reference import area_light_factor, disk_light_integral, rect_light_integral
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.shading import environment_radiance
from phrt_usd.evaluate.sweep import SweepSpec, run_sweep
from phrt_usd.run.images import read_frame_exr
from phrt_usd.usd import schema
from phrt_usd.usd.blackbody import REC709_LUMINANCE, blackbody_rec709, blackbody_xyz
from phrt_usd.usd.default_lights import DOME_RADIANCE, HEADLIGHT_IRRADIANCE
from phrt_usd.usd.inspection import inspect_stage
from phrt_usd.usd.stage import read_stage

W, H = 32, 24
ALBEDO = 0.5
MODES = ("raster", "rt")
CENTRE = (12, 16)  # sees (0.03125, -0.03125, 0): 1.3 degrees off the view axis
CENTRE_POINT, EYE = np.array([0.03125, -0.03125, 0.0]), np.array([0.0, 0.0, 2.0])


def _ambient_centre(dome) -> np.ndarray:
    """The centre pixel under a uniform dome of radiance ``dome`` alone: the square's
    UsdPreviewSurface fallback material returns its directional albedo of it (albedo x
    the diffuse share plus the specular lobe's, ``shade_kernels.ambient_weight``)."""
    return preview_shade(ALBEDO, CENTRE_POINT, EYE, ambient=dome)


def _stage(half: float = 2.0, dome: bool = True) -> Usd.Stage:
    stage = grey_square_stage(ALBEDO, half)
    if dome:
        UsdLux.DomeLight.Define(stage, "/World/Black").CreateIntensityAttr(0.0)
    return stage


def _sun_centre(e: float = 1.0, tilt: float = 60.0) -> float:
    """The centre pixel lit by ``_sun`` of irradiance ``e`` alone: e x the BRDF's π f n·l
    (the square's UsdPreviewSurface fallback material), the light towards (0, -sin
    tilt, cos tilt)."""
    a = np.radians(tilt)
    towards = np.array([0.0, -np.sin(a), np.cos(a)])
    return float(preview_shade(ALBEDO, CENTRE_POINT, EYE, sources=[(towards, e)])[0])


def _sun(stage: Usd.Stage, tilt: float = 60.0, path: str = "/World/Sun") -> UsdLux.DistantLight:
    """A DistantLight tilted ``tilt`` degrees about X from shining straight down -Z:
    n.l = cos(tilt) on the square and the highlight at the centre (n.h)^64 =
    cos(tilt / 2)^64, 1e-4 at 60 degrees (negligible)."""
    sun = UsdLux.DistantLight.Define(stage, path)
    sun.AddRotateXOp().Set(tilt)
    return sun


def _render(stage: Usd.Stage, mode: str, frames=(1.0,), **options):
    """(beauty of the last frame (H, W, 3), alpha (H, W), the StageScene)."""
    scene = read_stage(stage)
    renderer = FrameRenderer(scene, RenderOptions(mode=mode, width=W, height=H, **options))
    try:
        for t in frames:
            out = renderer.render(t)
    finally:
        renderer.close()
    return out.beauty, out.alpha, scene


def _clipping(warnings: list[str]) -> list[str]:
    return [w for w in warnings if "clipped" in w]


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_unauthored_sun_is_the_fallback_50000_and_warned_once_not_white_in_silence(mode):
    stage = _stage()
    _sun(stage)  # inputs:intensity unauthored: the schema's DistantLight fallback
    beauty, _, scene = _render(stage, mode, frames=(1.0, 2.0))
    # Our convention (docs/usd-support.md "Lights"): the intensity is the irradiance of
    # a surface facing the light: 50000 x the BRDF's π f n·l at n·l = cos 60 (~12400;
    # float32 shading: 1e-5 relative).
    lit = 50000.0 * _sun_centre()
    assert beauty[CENTRE] == pytest.approx([lit] * 3, rel=1e-5)
    (line,) = _clipping(scene.warnings)  # once per run, not once per frame
    assert "/World/Sun" in line and "--exposure" in line and "fallback 50000" in line
    assert "\n" not in line
    # The suggested EV brings the median covered pixel (the centre's) to 0.5.
    suggested = float(line.rsplit("--exposure ", 1)[1])
    assert suggested == pytest.approx(np.log2(0.5 / lit), abs=0.06)  # printed to 0.1


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_light_exposure_render_exposure_and_camera_exposure_each_double(mode):
    def centre(light_exposure=0.0, camera_exposure=None, **options) -> np.ndarray:
        stage = _stage()
        sun = _sun(stage)
        sun.CreateIntensityAttr(1.0)
        sun.CreateExposureAttr(light_exposure)
        if camera_exposure is not None:
            UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam")).CreateExposureAttr(camera_exposure)
        return _render(stage, mode, **options)[0][CENTRE]

    base = centre()
    # The BRDF's π f n·l at n·l = cos 60 (~0.25; float32 shading: 1e-5 relative).
    assert base == pytest.approx([_sun_centre()] * 3, rel=1e-5)
    # Each is an exact power of two on the same float32 sums: relative 1e-6.
    np.testing.assert_allclose(centre(light_exposure=1.0), 2.0 * base, rtol=1e-6)
    np.testing.assert_allclose(centre(exposure=1.0), 2.0 * base, rtol=1e-6)
    np.testing.assert_allclose(centre(exposure=-2.0), 0.25 * base, rtol=1e-6)
    np.testing.assert_allclose(centre(camera_exposure=1.0), 2.0 * base, rtol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_color_temperature_6500_is_white_and_3000_is_reddish(mode):
    def centre(kelvin: float) -> np.ndarray:
        stage = _stage()
        sun = _sun(stage)
        sun.CreateIntensityAttr(1.0)
        sun.CreateEnableColorTemperatureAttr(True)
        sun.CreateColorTemperatureAttr(kelvin)
        return _render(stage, mode)[0][CENTRE]

    white = centre(6500.0)
    # UsdLux: "the default value of 6500 will always result in white" (luminance 1).
    np.testing.assert_allclose(white, [_sun_centre()] * 3, rtol=1e-5)
    warm = centre(3000.0)
    # A 3000 K blackbody in Rec.709: r/b ~ 6.4 (USD's own table 6.5); > 4 leaves room
    # for the colour-matching fit while excluding a neutral or cool colour.
    assert warm[0] / warm[2] > 4.0
    # The colour has luminance 1: the brightness is the 6500 K one (grey albedo).
    assert float(warm @ REC709_LUMINANCE) == pytest.approx(_sun_centre(), rel=2e-3)


def test_blackbody_chromaticity_is_on_the_planckian_locus():
    # CIE 1931 xy of the Planckian locus (Wyszecki & Stiles tables): the CMF fit of
    # Wyman et al. 2013 is within ~0.003 of them.
    locus = {2000.0: (0.5267, 0.4133), 3000.0: (0.4369, 0.4041), 6500.0: (0.3135, 0.3237),
             10000.0: (0.2807, 0.2884)}  # fmt: skip
    xyz = blackbody_xyz(np.array(list(locus)))
    xy = xyz[:, :2] / xyz.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(xy, np.array(list(locus.values())), atol=4e-3)
    rgb = blackbody_rec709(np.array([1000.0, 3000.0, 6500.0, 10000.0, np.nan, 1e9]))
    assert np.all(np.isfinite(rgb)) and np.all(rgb >= 0)
    np.testing.assert_allclose(rgb @ REC709_LUMINANCE, 1.0, rtol=1e-12)
    np.testing.assert_allclose(rgb[2], [1.0, 1.0, 1.0], rtol=1e-12)
    np.testing.assert_allclose(rgb[4], [1.0, 1.0, 1.0], rtol=1e-12)  # NaN reads 6500 K
    assert rgb[3][2] > rgb[3][0]  # 10000 K is bluish


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_normalize_keeps_an_area_light_size_independent_and_off_it_grows_with_area(mode):
    def centre(size: float, normalize: bool, kind=UsdLux.RectLight) -> float:
        stage = _stage()
        light = kind.Define(stage, "/World/Panel")
        light.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))  # 1 m above, shining down -Z
        if kind is UsdLux.RectLight:
            light.CreateWidthAttr(size)
            light.CreateHeightAttr(size)
        else:
            light.CreateRadiusAttr(size)
        light.CreateIntensityAttr(100.0)
        light.CreateNormalizeAttr(normalize)
        return float(_render(stage, mode)[0][CENTRE][0])

    for kind in (UsdLux.RectLight, UsdLux.DiskLight, UsdLux.SphereLight):
        normalized = centre(0.1, True, kind)
        # normalize: luminance / area, so the power, and the lighting, stay the same, but
        # for a Rect or Disk light's area factor (its near field, _area_factor).
        near = _area_factor(kind, 0.2) / _area_factor(kind, 0.1)
        assert centre(0.2, True, kind) == pytest.approx(normalized * near, rel=1e-6)
        small, big = centre(0.1, False, kind), centre(0.2, False, kind)
        # Off: area x 4 → 4 x the light, the sphere's πr² too (the range window,
        # shading.range_window, differs by < 1e-3 between the two).
        assert big / small == pytest.approx(4.0 * near, rel=2e-3)
        if kind is UsdLux.RectLight:
            # A 0.1 m rect of luminance 100: intensity 100 x 0.01 = 1; normalized, the
            # luminance itself, 100 (float32 sums: relative 1e-5), times its area factor.
            factor = _area_factor(kind, 0.1)
            assert small == pytest.approx(_point_lit_centre(1.0) * factor, rel=1e-5)
            assert normalized == pytest.approx(_point_lit_centre(100.0) * factor, rel=1e-5)


def _area_factor(kind, size: float) -> float:
    """The area factor (docs/usd-support.md "Lights") at the centre pixel's point of the
    test's light 1 m above the origin facing down: a rect of side ``size``, a disk of
    radius ``size`` (closed forms of their irradiance over the point light's); 1 for a
    sphere."""
    centre = np.array([0.0, 0.0, 1.0])
    if kind is UsdLux.RectLight:
        integral = rect_light_integral(CENTRE_POINT, centre, size / 2, size / 2)
        return area_light_factor(CENTRE_POINT, centre, size * size, integral)
    if kind is UsdLux.DiskLight:
        integral = disk_light_integral(CENTRE_POINT, centre, size)
        return area_light_factor(CENTRE_POINT, centre, np.pi * size * size, integral)
    return 1.0


def _point_lit_centre(intensity: float) -> float:
    """The centre pixel lit by a point of ``intensity`` 1 m above the origin, by the
    model of engine/shading.py: E x the BRDF's π f n·l (the square's UsdPreviewSurface
    fallback material), E = I / d² x the range window (1 - (d / r)^4)^2, r =
    sqrt(I / 0.02)."""
    to_light = np.array([0, 0, 1.0]) - CENTRE_POINT
    d = np.linalg.norm(to_light)
    window = (1.0 - (d / np.sqrt(intensity / 0.02)) ** 4) ** 2
    e = intensity / d**2 * window
    return float(preview_shade(ALBEDO, CENTRE_POINT, EYE, sources=[(to_light, e)])[0])


@pytest.mark.parametrize("mode", MODES)
def test_spot_cone_lights_inside_and_not_outside_with_the_schema_softness(mode):
    def render(softness: float) -> np.ndarray:
        stage = _stage()
        lamp = UsdLux.SphereLight.Define(stage, "/World/Spot")
        lamp.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))  # shines down -Z from 1 m
        lamp.CreateRadiusAttr(0.01)
        lamp.CreateNormalizeAttr(True)  # intensity 16 / 4 = 4 (usd/lights.local_intensity)
        lamp.CreateIntensityAttr(16.0)
        shaping = UsdLux.ShapingAPI.Apply(lamp.GetPrim())
        shaping.CreateShapingConeAngleAttr(30.0)
        shaping.CreateShapingConeSoftnessAttr(softness)
        return _render(stage, mode)[0]

    hard, soft = render(0.0), render(0.5)
    inside, outside, edge = CENTRE, (12, 28), (12, 22)
    # Centre: 2.5 degrees off the axis, lit: 0.5 x 4 x cos^3(2.5 deg) ~ 2 (+ highlight).
    assert hard[inside][0] > 1.9
    # Column 28 sees x = 0.78 m: 38 degrees off the axis, beyond the 30 degree cone;
    # nothing else lights it (black dome): exactly 0.
    assert hard[outside][0] == 0.0 and soft[outside][0] == 0.0
    # Column 22: x = 0.406, y = -0.031 m, 22.2 degrees off the axis. Hard cone: fully
    # lit; softness 0.5: 1 - smoothstep(15, 30, 22.2) (UsdLux ShapingAPI).
    theta = np.degrees(np.arctan(np.hypot(0.40625, 0.03125)))
    x = (theta - 15.0) / 15.0
    expected = 1.0 - x * x * (3.0 - 2.0 * x)
    assert soft[edge][0] / hard[edge][0] == pytest.approx(expected, rel=1e-4)


def test_spot_cone_raster_equals_rt():
    stage = _stage()
    lamp = UsdLux.SphereLight.Define(stage, "/World/Spot")
    lamp.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))
    lamp.CreateNormalizeAttr(True)  # intensity 8 / 4 = 2
    lamp.CreateIntensityAttr(8.0)
    shaping = UsdLux.ShapingAPI.Apply(lamp.GetPrim())
    shaping.CreateShapingConeAngleAttr(25.0)
    shaping.CreateShapingConeSoftnessAttr(0.3)
    shaping.CreateShapingFocusAttr(2.0)
    raster = _render(stage, "raster")[0]
    rt = _render(stage, "rt")[0]
    # One cone (shading.cone_falloff) for both; positions agree to float32 rounding.
    np.testing.assert_allclose(raster, rt, atol=1e-4)


def _latlong(path, top, bottom) -> str:
    """A 16 x 8 lat-long EXR: the upper half ``top``, the lower half ``bottom``."""
    image = np.zeros((8, 16, 3), np.float32)
    image[:4], image[4:] = top, bottom
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(16, 8, 3, "float"))
    out.write_image(image)
    out.close()
    return str(path)


@pytest.mark.parametrize("mode", MODES)
def test_dome_light_1_lights_a_diffuse_square(mode):
    stage = _stage(dome=False)
    dome = UsdLux.DomeLight_1.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.4, 0.6, 0.8))
    beauty, _, scene = _render(stage, mode)
    assert scene.scene.lights.dome is not None and not scene.scene.lights.default_rig
    # Only the ambient term: the surface's directional albedo x dome radiance.
    np.testing.assert_allclose(beauty[CENTRE], _ambient_centre([0.4, 0.6, 0.8]), rtol=1e-5)


@pytest.mark.parametrize("pole, up", [("scene", "Z"), ("Z", "Y"), ("Y", "Z"), ("scene", "Y")])
def test_dome_light_1_pole_axis_turns_the_map(tmp_path, pole, up):
    stage = _stage(dome=False)
    UsdGeom.SetStageUpAxis(stage, up)
    dome = UsdLux.DomeLight_1.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(_latlong(tmp_path / "sky.exr", (1, 0, 0), (0, 0, 1)))
    dome.GetPrim().GetAttribute("poleAxis").Set(pole)
    lights = read_stage(stage).scene.lights
    axis = up if pole == "scene" else pole
    zenith = np.array([[0.0, 0.0, 1.0]] if axis == "Z" else [[0.0, 1.0, 0.0]])
    # Straight up the pole: the map's top row (red); straight down: the bottom (blue).
    np.testing.assert_allclose(environment_radiance(lights, zenith)[0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(environment_radiance(lights, -zenith)[0], [0, 0, 1], atol=1e-6)


def test_unsupported_dome_format_warns_once_and_renders_untextured(tmp_path):
    stage = _stage(dome=False)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(_latlong(tmp_path / "sky.exr", (1, 0, 0), (0, 0, 1)))
    dome.CreateTextureFormatAttr("angular")
    dome.CreateColorAttr(Gf.Vec3f(0.2, 0.2, 0.2))
    beauty, _, scene = _render(stage, "raster")
    (line,) = [w for w in scene.warnings if "texture:format" in w]
    assert line.startswith("/World/Sky.inputs:texture:format: 'angular'") and "\n" not in line
    assert scene.scene.lights.dome.texture is None
    np.testing.assert_allclose(beauty[CENTRE], _ambient_centre(0.2), rtol=1e-5)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("visible", [True, False])
def test_dome_hidden_from_camera_leaves_a_black_background_and_still_lights(mode, visible):
    stage = _stage(half=0.5, dome=False)  # the square covers x, y within +-0.5 m only
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.4, 0.4, 0.4))
    if not visible:
        dome.GetPrim().CreateAttribute("visibleInPrimaryRay", Sdf.ValueTypeNames.Bool).Set(False)
    beauty, alpha, _ = _render(stage, mode)
    corner = (0, 0)  # sees x = -0.97, y = 0.72 m: beyond the square, background
    assert alpha[corner] == 0.0 and alpha[CENTRE] == 1.0
    np.testing.assert_allclose(beauty[corner], [0.4 if visible else 0.0] * 3, atol=1e-7)
    np.testing.assert_allclose(beauty[CENTRE], _ambient_centre(0.4), rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_stage_without_lights_gets_the_default_rig_with_a_notice(mode):
    stage = _stage(dome=False)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam"))
    turn = cam.AddRotateYOp()  # after the translate: turns the camera about its eye
    turn.Set(30.0, 1.0)
    turn.Set(0.0, 2.0)
    scene = read_stage(stage)
    renderer = FrameRenderer(scene, RenderOptions(mode=mode, width=W, height=H))
    turned = np.radians(30.0)
    try:
        first = renderer.render(1.0).beauty
        (notice,) = [w for w in scene.warnings if "no UsdLux lights" in w]
        assert "default light rig" in notice and "\n" not in notice
        # The headlight shines from the camera: towards it is the camera's +Z axis.
        lights = renderer.scene.lights
        assert lights.default_rig
        np.testing.assert_allclose(
            lights.distant[0].direction, [np.sin(turned), 0, np.cos(turned)], atol=1e-9
        )
        renderer.render(2.0)
        np.testing.assert_allclose(renderer.scene.lights.distant[0].direction, [0, 0, 1],
                                   atol=1e-12)  # fmt: skip
    finally:
        renderer.close()
    # Frame 1's centre pixel looks 30 degrees off the square's normal, along the
    # headlight (n.l = cos 30), plus the dome's ambient: the square's fallback material
    # under both (~0.39; an unaimed headlight, still along +Z, would give ~0.45). Bound:
    # the pixel's own 1.3 degree offset.
    towards = np.array([np.sin(turned), 0.0, np.cos(turned)])
    seen = np.array([-2.0 * np.tan(turned), 0.0, 0.0])
    expected = preview_shade(ALBEDO, seen, EYE, sources=[(towards, HEADLIGHT_IRRADIANCE)],
                             ambient=DOME_RADIANCE)  # fmt: skip
    np.testing.assert_allclose(first[CENTRE], expected, atol=4e-3)
    assert inspect_stage(stage)["default_light_rig"] is True


@pytest.mark.slow
def test_api_render_records_exposure_and_the_clipping_warning(tmp_path):
    stage = _stage()
    _sun(stage).CreateIntensityAttr(10.0)  # 0.5 x 10 x cos 60 = 2.5: clipped everywhere
    with phrt_usd.render(stage, tmp_path / "out", frames="1", mode="raster",
                         resolution=(W, H)) as result:  # fmt: skip
        (line,) = _clipping(result.summary["warnings"])
        assert "/World/Sun" in line and "--exposure -2.3" in line  # log2(0.5 / 2.5)
        assert result.summary["default_light_rig"] is False
    with phrt_usd.render(stage, frames="1", mode="raster", resolution=(W, H),
                         exposure=-2.0) as result:  # fmt: skip
        # ~2.5 / 4 < 1: no longer clipped, no warning.
        assert not _clipping(result.summary["warnings"])
        np.testing.assert_allclose(result.read_frame(1.0)["beauty"][CENTRE],
                                   10.0 * _sun_centre() / 4.0, rtol=1e-3)  # fmt: skip
        stats = json.loads((result.out / "stats.json").read_text())
        assert stats["run"]["exposure"] == -2.0


@pytest.mark.slow
def test_cli_exposure_scales_the_exr_by_2_to_the_ev_and_warns_when_clipped(tmp_path):
    stage = _stage()
    _sun(stage).CreateIntensityAttr(1.0)
    path = tmp_path / "s.usda"
    stage.GetRootLayer().Export(str(path))
    runner = CliRunner()
    values, stderr = {}, {}
    for ev in (0.0, 3.0):
        out = tmp_path / f"ev{ev}"
        done = runner.invoke(app, ["render", str(path), "--frames", "1", "--mode", "raster",
                                   "--resolution", f"{W}x{H}", "--out", str(out),
                                   "--exposure", str(ev)])  # fmt: skip
        assert done.exit_code == 0, done.output
        (exr,) = sorted(out.rglob("*.exr"))
        values[ev], stderr[ev] = read_frame_exr(exr)["beauty"][CENTRE], done.stderr
    # The EXR holds the scaled radiance: 0.25 x 2^3 = 2 (half floats: relative 1e-3).
    np.testing.assert_allclose(values[3.0], values[0.0] * 2.0**3, rtol=1e-3)
    assert not [ln for ln in stderr[0.0].splitlines() if "clipped" in ln]
    lines = [ln for ln in stderr[3.0].splitlines() if "clipped" in ln]
    # 2 in every pixel: one warning, naming the light and the option; the EV it suggests
    # brings the median to 0.5: 3 + log2(0.5 / 2) = 1.
    assert len(lines) == 1 and "/World/Sun" in lines[0] and "--exposure 1.0" in lines[0]
    assert lines[0].startswith("warning: ") and "Traceback" not in stderr[3.0]


@pytest.mark.slow
def test_sweep_exposure_scales_every_config_image(tmp_path):
    stage = _stage()
    _sun(stage).CreateIntensityAttr(1.0)  # centre 0.25 (module docstring)
    mirror = UsdGeom.Mesh.Define(stage, "/World/Mirror")  # a sweep needs a reflector
    mirror.CreatePointsAttr([(0.6, 0.4, 0.01), (0.9, 0.4, 0.01), (0.9, 0.7, 0.01),
                             (0.6, 0.7, 0.01)])  # fmt: skip
    mirror.CreateFaceVertexCountsAttr([4])
    mirror.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=0.5)
    path = tmp_path / "s.usda"
    stage.GetRootLayer().Export(str(path))
    out = tmp_path / "sweep"
    spec = SweepSpec(stages=[path], heuristics=["heu1"], budgets_rays=[0], frames="1",
                     width=W, height=H, out=out, exposure=1.0)  # fmt: skip
    assert run_sweep(spec)["exposure"] == 1.0
    previews = [p for p in sorted(out.rglob("*.png")) if p.parent.name == "1"
                and not p.stem.endswith(("flip", "temporal"))]  # fmt: skip
    assert len(previews) >= 3, previews  # heu1, and the all and rt references
    for png in previews:
        red = oiio.ImageBuf(str(png)).getpixel(CENTRE[1], CENTRE[0])[0]
        # 0.25 x 2^1 = 0.5, sRGB-encoded: code 188 (+-1 of 8-bit rounding).
        assert red * 255 == pytest.approx(188, abs=1.5), png.name


def test_validate_warns_of_the_unauthored_sun_and_an_unsupported_dome_format(tmp_path):
    """What the render warns of while rendering, validate warns of before: the fallback
    sun (it clips) and a dome format read untextured; an authored sun is no warning."""
    from phrt_usd.usd.validation import validate_stage

    stage = _stage(dome=False)
    _sun(stage)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(_latlong(tmp_path / "sky.exr", (1, 0, 0), (0, 0, 1)))
    dome.CreateTextureFormatAttr("angular")
    report = validate_stage(stage)
    lines = [i.line() for i in report.warnings]
    assert any(
        line.startswith("WARNING /World/Sun.inputs:intensity: unauthored: UsdLux's fallback 50000")
        and "--exposure" in line
        for line in lines
    ), lines
    dome_line = "WARNING /World/Sky.inputs:texture:format: 'angular'"
    assert any(line.startswith(dome_line) for line in lines), lines
    UsdLux.DistantLight(stage.GetPrimAtPath("/World/Sun")).CreateIntensityAttr(1.0)
    after = [i.line() for i in validate_stage(stage).issues]
    assert not any("/World/Sun" in line for line in after), after


@pytest.mark.parametrize("mode", MODES)
def test_probe_missing_dome_texture(tmp_path, mode):
    """A DomeLight whose texture file is missing renders as a surface texture does: one
    warning naming the attribute, and the dome's fallback, its colour untextured (the
    ambient term albedo x colour at the centre); ``phrt validate`` and ``--strict``
    call it an error, as they do a surface texture's."""
    from phrt_usd.usd.validation import validate_stage

    stage = _stage(dome=False)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(str(tmp_path / "gone.exr"))
    dome.CreateColorAttr(Gf.Vec3f(0.2, 0.4, 0.6))
    beauty, _, scene = _render(stage, mode)
    (line,) = [w for w in scene.warnings if "/World/Sky.inputs:texture:file" in w]
    assert "gone.exr" in line and "untextured, in its colour" in line and "\n" not in line
    assert scene.texture_problems and scene.scene.lights.dome.texture is None
    # rtol 1e-5: float32 shading of an exact product and the albedo table's float32
    # entries, as the other dome tests.
    np.testing.assert_allclose(beauty[CENTRE], _ambient_centre([0.2, 0.4, 0.6]), rtol=1e-5)
    errors = [i.line() for i in validate_stage(stage).errors]
    assert any("/World/Sky.inputs:texture:file" in e and "gone.exr" in e for e in errors), errors


def test_probe_missing_dome_texture_strict_is_an_error_exit_1(tmp_path):
    """``--strict``: the missing dome texture is the one error line, exit 1 (as a
    surface texture's), and no frame is rendered."""
    stage = _stage(dome=False)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(str(tmp_path / "gone.exr"))
    stage.GetRootLayer().Export(str(tmp_path / "dome.usda"))
    args = ["render", str(tmp_path / "dome.usda"), "--out", str(tmp_path / "run"),
            "--resolution", f"{W}x{H}", "--frames", "1:1"]  # fmt: skip
    result = CliRunner().invoke(app, [*args, "--strict"])
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "/World/Sky.inputs:texture:file" in lines[0], result.output
    assert "gone.exr" in lines[0] and "--strict" in lines[0]
    assert not (tmp_path / "run" / "stats.json").exists()
