"""UsdLux in any units: every light type renders the same image for a stage authored in
centimetres (``metersPerUnit`` 0.01, every length x 100) and the same stage in metres,
in raster and rt, at the intensity of the one unit rule (``usd/lights.local_intensity``);
a non-normalized SphereLight no longer brightens 10^4 times when the same file is read
in centimetres; the clipping warning names the camera's exposure when it is the cause.

The stage (in metres; x ``1 / mpu`` in stage units): a grey (albedo 0.5) square 4 x 4 m
at z = 0 facing +Z, a camera at z = 2 m looking down -Z (focal 20 over a 20 x 15
aperture: the square fills the 32 x 24 frame), a black dome (no ambient term) and one
light 1 m above the origin. The centre pixel (row 12, col 16) sees (0.03125, -0.03125, 0)
m. A point light of intensity I there gives, by the model of engine/shading.py, E x the
BRDF's π f n.l (UsdPreviewSurface's fallback material: the square has no material) with
E = I / d² x the range window (``_point_lit_centre``); a Rect or Disk light's pair is
that times its area factor (``_area_factor``).
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux
from scenes import grey_square_stage, preview_shade
from shading_reference import (
    area_light_factor,
    brdf_cos,
    disk_light_integral,
    rect_light_integral,
)

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.shading import LIGHT_CUTOFF_IRRADIANCE
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.usd.default_lights import DOME_RADIANCE, HEADLIGHT_IRRADIANCE
from phrt_usd.usd.stage import read_stage

W, H = 32, 24
ALBEDO = 0.5
CENTRE = (12, 16)
CENTRE_POINT = np.array([0.03125, -0.03125, 0.0])  # metres
EYE = np.array([0.0, 0.0, 2.0])
LUMINANCE = 10.0  # inputs:intensity of every light below (nits, UsdLux)
CENTIMETRES = 0.01
MODES = ("raster", "rt")

#: The lights of the centimetre/metre pairs: (UsdLux type, sizes in metres, normalize,
#: treatAsPoint) and the intensity (cd) the unit rule gives them: luminance x the area
#: seen face-on in m² (sphere πr², rect w·h, disk πr², cylinder side-on 2rℓ) or, with
#: normalize, x face-on / surface (1/4, 1, 1, 1/π); treatAsPoint: the normalized
#: sphere's 1/4.
LIGHTS = {
    "sphere": (UsdLux.SphereLight, {"radius": 0.1}, False, False, LUMINANCE * np.pi * 0.01),
    "sphere_normalized": (UsdLux.SphereLight, {"radius": 0.1}, True, False, LUMINANCE / 4),
    "sphere_point": (UsdLux.SphereLight, {"radius": 0.1}, False, True, LUMINANCE / 4),
    "rect": (UsdLux.RectLight, {"width": 0.2, "height": 0.3}, False, False, LUMINANCE * 0.06),
    "rect_normalized": (UsdLux.RectLight, {"width": 0.2, "height": 0.3}, True, False, LUMINANCE),
    "disk": (UsdLux.DiskLight, {"radius": 0.1}, False, False, LUMINANCE * np.pi * 0.01),
    "disk_normalized": (UsdLux.DiskLight, {"radius": 0.1}, True, False, LUMINANCE),
    "cylinder": (
        UsdLux.CylinderLight, {"radius": 0.05, "length": 0.3}, False, False, LUMINANCE * 0.03
    ),
    "cylinder_normalized": (
        UsdLux.CylinderLight, {"radius": 0.05, "length": 0.3}, True, False, LUMINANCE / np.pi
    ),
}  # fmt: skip


def _stage(mpu: float, dome: float = 0.0) -> Usd.Stage:
    """The module's stage with ``mpu`` metres per unit (every length / ``mpu``) and a
    dome of constant radiance ``dome`` (0: black)."""
    stage = grey_square_stage(ALBEDO, 2.0, EYE, meters_per_unit=mpu)
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(dome)
    return stage


def _local_light(stage: Usd.Stage, mpu: float, name: str) -> None:
    """LIGHTS[``name``] 1 m above the origin, its sizes in stage units."""
    kind, sizes, normalize, point = LIGHTS[name][:4]
    light = kind.Define(stage, "/World/Light")
    light.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1.0 / mpu))
    light.CreateIntensityAttr(LUMINANCE)
    light.CreateNormalizeAttr(normalize)
    for attr, metres in sizes.items():
        light.GetPrim().GetAttribute(f"inputs:{attr}").Set(metres / mpu)
    if point:
        light.GetPrim().CreateAttribute("treatAsPoint", Sdf.ValueTypeNames.Bool).Set(True)


def _render(stage: Usd.Stage, mode: str):
    """(beauty (H, W, 3) of frame 1, the StageScene)."""
    scene = read_stage(stage)
    renderer = FrameRenderer(scene, RenderOptions(mode=mode, width=W, height=H))
    try:
        return renderer.render(1.0).beauty, scene
    finally:
        renderer.close()


def _point_lit_centre(intensity: float) -> float:
    """The centre pixel lit by a point of ``intensity`` 1 m above the origin (module
    doc): the range window (1 - (d / r)^4)^2 with r = sqrt(I / LIGHT_CUTOFF_IRRADIANCE)."""
    to_light, to_eye = np.array([0, 0, 1.0]) - CENTRE_POINT, EYE - CENTRE_POINT
    d = np.linalg.norm(to_light)
    window = (1.0 - (d / np.sqrt(intensity / LIGHT_CUTOFF_IRRADIANCE)) ** 4) ** 2
    e = intensity / d**2 * window
    surface = fallback_surface(np.full((1, 3), ALBEDO))
    up = np.array([[0.0, 0.0, 1.0]])
    brdf = brdf_cos(surface, up, (to_eye / np.linalg.norm(to_eye))[None], (to_light / d)[None])
    return float(e * brdf[0, 0])


#: The pair's images agree to float32 rounding: the centimetre stage's points and
#: sizes, times 0.01 in float64, are the metre stage's to 1e-16 relative, and both go
#: through the same float32 shading and rasterization (depth, interpolated positions:
#: ~1e-7 relative). 1e-5 relative bounds that with margin; a unit slip (x100 in a
#: distance, x10^4 in an area) fails it by orders of magnitude.
PAIR_RTOL = 1e-5
#: The centre pixel against the rule's point light (times a Rect or Disk light's area
#: factor, in closed form): float32 sums (1e-6) and the range window, computed the same
#: way (docs/usd-support.md "Lights"); a disk's 24-gon of its area, 1 m from a 0.1 m
#: disk, is within 1e-6 of its irradiance.
ANALYTIC_RTOL = 1e-4


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name", list(LIGHTS))
def test_local_light_centimetres_and_metres_render_the_same(name, mode):
    images = {}
    for mpu in (CENTIMETRES, 1.0):
        stage = _stage(mpu)
        _local_light(stage, mpu, name)
        images[mpu], scene = _render(stage, mode)
        (light,) = scene.scene.lights.local
        np.testing.assert_allclose(light.radiance, [LIGHTS[name][4]] * 3, rtol=1e-6)
        if name == "sphere_point":  # a point: no shadow-ray offset
            assert light.radius == 0.0
    np.testing.assert_allclose(images[CENTIMETRES], images[1.0], rtol=PAIR_RTOL, atol=1e-9)
    expected = _point_lit_centre(LIGHTS[name][4]) * _area_factor(name)
    assert images[1.0][CENTRE][0] == pytest.approx(expected, rel=ANALYTIC_RTOL)


def _area_factor(name: str) -> float:
    """1, or for a Rect or Disk light its area factor at the centre pixel's point (the
    closed forms of its irradiance over the point light's: docs/usd-support.md "Lights")."""
    kind, sizes = LIGHTS[name][:2]
    centre = np.array([0.0, 0.0, 1.0])
    if kind is UsdLux.RectLight:
        a, b = 0.5 * sizes["width"], 0.5 * sizes["height"]
        integral = rect_light_integral(CENTRE_POINT, centre, a, b)
        return area_light_factor(CENTRE_POINT, centre, 4 * a * b, integral)
    if kind is UsdLux.DiskLight:
        r = sizes["radius"]
        integral = disk_light_integral(CENTRE_POINT, centre, r)
        return area_light_factor(CENTRE_POINT, centre, np.pi * r * r, integral)
    return 1.0


@pytest.mark.parametrize("mode", MODES)
def test_distant_and_dome_lights_centimetres_and_metres_render_the_same(mode):
    images = {}
    for mpu in (CENTIMETRES, 1.0):
        stage = _stage(mpu, dome=0.2)
        sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
        sun.AddRotateXOp().Set(60.0)  # n.l = cos 60 on the square
        sun.CreateIntensityAttr(1.0)
        images[mpu] = _render(stage, mode)[0]
    np.testing.assert_allclose(images[CENTIMETRES], images[1.0], rtol=PAIR_RTOL, atol=1e-9)
    # No length in either: the sun (n.l = cos 60) and the dome of 0.2 on the square's
    # fallback material (float32 shading: 1e-5 relative).
    towards = np.array([0.0, -np.sin(np.radians(60.0)), np.cos(np.radians(60.0))])
    expected = preview_shade(ALBEDO, CENTRE_POINT, EYE, sources=[(towards, 1.0)], ambient=0.2)
    assert images[1.0][CENTRE][0] == pytest.approx(expected[0], rel=1e-5)


@pytest.mark.parametrize("mode", MODES)
def test_probe_sphere_light_units(mode):
    """The same file read in metres and in centimetres (USD's value when
    ``metersPerUnit`` is unauthored) is a scene 100 x smaller: a SphereLight of fixed
    luminance subtends the same solid angle, so the image is the same (it was 7004
    against 0.75: the emission used as an intensity fell off over 100 x shorter
    distances). A normalized one keeps its power in watts (UsdLux: the area in m²), so
    the 100 x smaller scene is 10^4 x brighter."""
    centre = {}
    for normalize in (False, True):
        for mpu in (CENTIMETRES, 1.0):
            stage = _stage(1.0)  # authored in metres ...
            UsdGeom.SetStageMetersPerUnit(stage, mpu)  # ... read in mpu
            lamp = UsdLux.SphereLight.Define(stage, "/World/Lamp")
            lamp.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1))
            lamp.CreateRadiusAttr(0.1)
            lamp.CreateIntensityAttr(LUMINANCE)
            lamp.CreateNormalizeAttr(normalize)
            centre[normalize, mpu] = float(_render(stage, mode)[0][CENTRE][0])
    plain = _point_lit_centre(LUMINANCE * np.pi * 0.1**2)
    assert centre[False, 1.0] == pytest.approx(plain, rel=ANALYTIC_RTOL)
    # The same solid angle: the same pixel (the intensity goes with r², the range
    # sqrt(I / LIGHT_CUTOFF_IRRADIANCE) with r, so the range window too is the same).
    assert centre[False, CENTIMETRES] == pytest.approx(centre[False, 1.0], rel=PAIR_RTOL)
    # Normalized: I = 2.5 at both scales, its range 11.2 m; the window is 1 - 1.3e-4
    # at d = 1 m and 1 - 1e-12 at 0.01 m: 10^4 to 1e-3 relative.
    assert centre[True, CENTIMETRES] / centre[True, 1.0] == pytest.approx(1e4, rel=1e-3)


def test_probe_camera_exposure_in_clipping_warning():
    """A stage without lights (the default rig's headlight and dim dome) seen by a
    camera of ``exposure`` 6: every pixel is white, and the camera is the cause (x64 of
    a frame at ~0.44), not the headlight."""
    stage = _stage(1.0)
    stage.RemovePrim("/World/Dome")  # no light at all: the default rig
    UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam")).CreateExposureAttr(6.0)
    beauty, scene = _render(stage, "raster")
    (line,) = [w for w in scene.warnings if "clipped" in w]
    assert "camera /World/Cam" in line and "+6.0 EV" in line and "x64" in line
    assert "brightest light" not in line and "\n" not in line
    # Without the camera's 64 the centre is the square's fallback material under the
    # headlight (along +Z, the view 1.3 degrees off it) and the dome: ~0.6, nothing
    # clipped (corners are darker). The suggested EV brings the median to 0.5:
    # log2(0.5 / median).
    headlight = [((0.0, 0.0, 1.0), HEADLIGHT_IRRADIANCE)]
    unscaled = preview_shade(ALBEDO, CENTRE_POINT, EYE, sources=headlight,
                             ambient=DOME_RADIANCE)[0]  # fmt: skip
    assert beauty[CENTRE][0] / 64.0 == pytest.approx(unscaled, rel=1e-3)
    assert "without them 0% would be" in line
    median = float(np.median(beauty.max(axis=2)[::2, ::2]))
    suggested = float(line.rsplit("--exposure ", 1)[1])
    assert suggested == pytest.approx(np.log2(0.5 / median), abs=0.06)  # printed to 0.1


def test_clipping_warning_names_the_light_when_the_camera_only_adds_to_it():
    """A sun of 10 (0.5 x 10 x cos 60 = 2.5: clipped at EV 0) seen by a camera of
    exposure 1: without the camera's x2 the frame is still clipped, so the sun is
    named, as without a camera exposure."""
    stage = _stage(1.0)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.AddRotateXOp().Set(60.0)
    sun.CreateIntensityAttr(10.0)
    UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam")).CreateExposureAttr(1.0)
    (line,) = [w for w in _render(stage, "raster")[1].warnings if "clipped" in w]
    assert "brightest light /World/Sun" in line and "camera" not in line
