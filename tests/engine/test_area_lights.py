"""Rect and Disk lights as areas at the traced hits (``engine/trace/shadow_rays.py``,
``area_light_kernels.py``), in rt and hybrid alike: their irradiance follows the
emitting surface (UsdLux: a rect of width x height, a disk of radius, in the light's XY
plane, a Lambertian emitter along its -Z), their shadows are soft, nothing behind them
is lit; the primary surface's pairs carry the same area factor (``shading``), rt's and
hybrid's resolved by the same rays (``tests/engine/test_area_light_shading.py``).

The stage (``_stage``): a grey square (albedo 0.5, UsdPreviewSurface's fallback
material) 6 x 6 m in the plane z = 0 facing +Z, lit by one light above it facing down,
a black dome; a mirror (``phrt:reflectivity`` 1) 6 x 6 m at z = 3 facing down, and the
camera at z = 2.5 looking up at it (20 mm lens, 20 x 15 mm aperture), so every pixel is
a traced reflection of the square: camera ray d to the mirror point m, reflected
r = (d_x, d_y, -d_z), the square's point f = m + 3 r / d_z (``_hits``). A pixel's
expected value is the light's luminance L (its intensity over its area) times the area
integral of cos θ_e cos θ_p / d² at f (``area_irradiance``: a 200 x 200 midpoint sum,
or the closed forms on the light's axis), times the BRDF's π f n·l at the direction of
the light's centre over its n·l, seen along -r (the rule, ``area_light_kernels``).
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux
from scenes import grey_square_stage
from shading_reference import brdf_cos

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.usd import schema
from phrt_usd.usd.stage import read_stage

#: Whole frames: the quick loop leaves them out.
pytestmark = pytest.mark.slow

ALBEDO = 0.5
EYE = np.array([0.0, 0.0, 2.5])
MIRROR_Z = 3.0
W, H = 64, 48
UP = np.array([0.0, 0.0, 1.0])
MODES = ("rt", "hybrid")


def _quad(stage, path: str, corners, s: float) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([tuple(np.asarray(c, float) * s) for c in corners])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return mesh


def _stage(light_type, at, sizes: dict, rotate_x: float = 0.0, card: bool = False,
           mpu: float = 1.0):  # fmt: skip
    """The module's stage authored in units of ``mpu`` metres, with a light of
    ``light_type`` (luminance 1, not normalized) at ``at`` (3,) metres turned
    ``rotate_x`` degrees about X (0: facing down) of ``sizes`` (inputs, metres);
    ``card``: an opaque card at z = 0.5 over x < 0 (a straight edge along y at x = 0)."""
    s = 1.0 / mpu
    stage = grey_square_stage(ALBEDO, 3.0, EYE, meters_per_unit=mpu)
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/Cam")).AddRotateXOp().Set(180.0)  # up
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(0.0)
    z = MIRROR_Z
    mirror = _quad(stage, "/World/Mirror", [(-3, -3, z), (-3, 3, z), (3, 3, z), (3, -3, z)], s)
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    light = light_type.Define(stage, "/World/Light")
    light.AddTranslateOp().Set(Gf.Vec3d(*(np.asarray(at, float) * s)))
    if rotate_x:
        light.AddRotateXOp().Set(rotate_x)
    light.CreateIntensityAttr(1.0)
    for name, value in sizes.items():
        light.GetPrim().GetAttribute(f"inputs:{name}").Set(value * s)
    if card:
        _quad(stage, "/World/Card", [(-3, -3, 0.5), (0, -3, 0.5), (0, 3, 0.5), (-3, 3, 0.5)], s)
    return stage


def _render(stage, mode: str, width: int = W, height: int = H):
    """(values (n,) red channel, the square's points f (n, 3) and the directions from f
    to the viewer (n, 3)) of the frame's traced mirror pixels."""
    scene = read_stage(stage)
    options = RenderOptions(mode=mode, width=width, height=height, heuristic="all",
                            budget_ms=None)  # fmt: skip
    renderer = FrameRenderer(scene, options)
    try:
        out = renderer.render(1.0)
    finally:
        renderer.close()
    traced = out.traced_mask.reshape(-1)
    assert traced.sum() == width * height  # every pixel a traced reflection
    m = out.gbuffer.position.reshape(-1, 3).astype(np.float64)
    d = m - EYE
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = d * np.array([1.0, 1.0, -1.0])
    f = m + r * (MIRROR_Z / d[:, 2:3])
    return out.beauty.reshape(-1, 3)[:, 0].astype(np.float64), f, -r


def area_irradiance(p, centre, u, v, disk: bool = False, grid: int = 200, seen=None) -> float:
    """∫ cos θ_e cos θ_p / d² dA over a light of half axes ``u``, ``v`` (3,) at ``centre``
    emitting along -Z onto a point ``p`` facing +Z (midpoint sum; a disk's cells outside
    its ellipse left out; ``seen``: the light's points (..., 3) -> bool the point sees,
    the others left out)."""
    a = (np.arange(grid) + 0.5) / grid * 2.0 - 1.0
    ga, gb = np.meshgrid(a, a)
    inside = (ga * ga + gb * gb <= 1.0) if disk else np.ones_like(ga, bool)
    y = centre + ga[..., None] * u + gb[..., None] * v
    if seen is not None:
        inside = inside & seen(y)
    d = y - p
    dist = np.linalg.norm(d, axis=-1)
    cos = np.maximum(d[..., 2] / dist, 0.0)  # θ_e (the light emits along -Z) and θ_p
    cell = 4.0 * np.linalg.norm(u) * np.linalg.norm(v) / grid**2
    return float((cos * cos / dist**2 * inside).sum() * cell)


def _brdf_over_cos(p, to_eye, centre) -> float:
    """π f n·l / n·l of the square's material at ``p`` seen along ``to_eye``, lit from
    the light's ``centre``."""
    to_light = centre - p
    to_light /= np.linalg.norm(to_light)
    surface = fallback_surface(np.full((1, 3), ALBEDO))
    return float(brdf_cos(surface, UP[None], to_eye[None], to_light[None])[0, 0] / to_light[2])


#: A pixel's value against the integral where the whole light is seen: exact (Lambert's
#: formula), float32 shading (the rect measured within 1.4e-6); the disk's polygon (24
#: corners, of its area: ~1e-3) and the reference sum's ragged disk rim dominate.
PIXEL_RTOL = 3e-3


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("shape", ["rect", "disk"])
def test_irradiance_under_a_large_area_light_follows_its_area(shape, mode):
    """Reflected points of the square within 8 cm of the light's axis show L × the area's
    integral × the BRDF, which on the axis is the closed form: a rect of half sizes a, b
    at height h, 2 [X / √(1 + X²) atan(Y / √(1 + X²)) + Y / √(1 + Y²) atan(X / √(1 +
    Y²))], X = a / h, Y = b / h; a disk of radius R, π R² / (R² + h²). A point of the
    same intensity (L × area), as the primary surface and the raster shade it, would be
    6.1 (rect) and 5 (disk) times as bright there: the near field of a large light."""
    centre, u, v = np.array([0.0, 0.0, 1.0]), np.array([2.0, 0, 0]), np.array([0, 2.0, 0])
    if shape == "rect":
        stage = _stage(UsdLux.RectLight, centre, {"width": 4.0, "height": 4.0})
        x = y = 2.0
        on_axis = 2.0 * 2 * x / np.sqrt(1 + x * x) * np.arctan(y / np.sqrt(1 + x * x))
        area = 16.0
    else:
        stage = _stage(UsdLux.DiskLight, centre, {"radius": 2.0})
        on_axis, area = np.pi * 4.0 / (4.0 + 1.0), np.pi * 4.0
    disk = shape == "disk"
    # The reference sum against the closed form (midpoint error, the disk's ragged rim).
    assert area_irradiance(np.zeros(3), centre, u, v, disk) == pytest.approx(on_axis, rel=2e-3)
    assert area / on_axis > 4.9
    values, points, to_eye = _render(stage, mode)
    near = np.flatnonzero(np.hypot(points[:, 0], points[:, 1]) < 0.08)
    assert len(near) >= 4
    expected = np.array([
        area_irradiance(points[i], centre, u, v, disk) * _brdf_over_cos(points[i], to_eye[i],
                                                                        centre)
        for i in near
    ])  # fmt: skip
    np.testing.assert_allclose(values[near], expected, rtol=PIXEL_RTOL)


@pytest.mark.parametrize("mode", MODES)
def test_an_area_light_casts_a_penumbra_in_its_reflection(mode):
    """A 1 x 1 m rect at x = -1, 1.5 m above the square, a card at z = 0.5 over x < 0:
    from a point of the square at x the light is seen where its xl > -2x, a penumbra from
    x = 0.25 to 0.75 m, where a point at its centre casts a hard edge at x = 0.5. A
    reflected point's value over the same stage's without the card is 0 in the umbra, 1
    where the whole light is seen, and in the penumbra 0 or 1 by its one sample ray
    (``light_sampling.AREA_LIGHT_RAYS``) to a point of the light that changes from pixel
    to pixel: a dither whose mean over 0.1 m wide strips of the square (~250 pixels) is
    the share of the light's integral (``area_irradiance``) the strip sees, within 0.05
    (measured 0.010 at most, rt and hybrid alike), 0.02 on average over the strips."""
    centre, u, v = np.array([-1.0, 0.0, 1.5]), np.array([0.5, 0, 0]), np.array([0, 0.5, 0])
    sizes = {"width": 1.0, "height": 1.0}
    size = (2 * W, 2 * H)  # 2.8 cm pixels on the square
    shadowed, points, _ = _render(_stage(UsdLux.RectLight, centre, sizes, card=True), mode,
                                  *size)  # fmt: skip
    open_, _, _ = _render(_stage(UsdLux.RectLight, centre, sizes), mode, *size)
    x = points[:, 0]
    keep = np.flatnonzero((np.abs(points[:, 1]) < 1.0) & (x > 0.0) & (x < 1.0))
    share = shadowed[keep] / open_[keep]
    x = x[keep]
    np.testing.assert_array_equal(share[x < 0.24], 0.0)  # the umbra
    np.testing.assert_allclose(share[x > 0.76], 1.0, rtol=1e-6)  # the whole light seen
    penumbra = (x > 0.3) & (x < 0.7)
    assert set(np.unique(np.round(share[penumbra], 6))) == {0.0, 1.0}  # a dither
    expected = np.array([
        area_irradiance(points[i], centre, u, v, grid=100,
                        seen=lambda y, px=points[i, 0]: y[..., 0] > -2.0 * px)
        / area_irradiance(points[i], centre, u, v, grid=100) for i in keep
    ])  # fmt: skip
    errors = []
    for lo in np.arange(0.2, 0.8, 0.1):
        strip = (x >= lo) & (x < lo + 0.1)
        assert strip.sum() >= 200
        errors.append(abs(share[strip].mean() - expected[strip].mean()))
    assert max(errors) < 0.05 and np.mean(errors) < 0.02, errors


def test_nothing_behind_an_area_light_is_lit_at_the_hits():
    """A rect turned to face up (rotated 180° about X: it emits along +Z) 1 m above the
    square lights nothing below it, in the reflection (the emitter's cosine is 0 there)
    and on the primary surface alike (the area factor, ``shading.shade_local``), while
    the same light facing down lights the square seen directly."""
    stage = _stage(UsdLux.RectLight, (0.0, 0.0, 1.0), {"width": 1.0, "height": 1.0}, 180.0)
    values, _, _ = _render(stage, "rt")
    assert values.max() == 0.0
    for turn, lit in ((180.0, False), (0.0, True)):
        direct = grey_square_stage(ALBEDO, 3.0, (0.0, 0.0, 2.5))
        UsdLux.DomeLight.Define(direct, "/World/Dome").CreateIntensityAttr(0.0)
        light = UsdLux.RectLight.Define(direct, "/World/Light")
        light.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.0))
        light.AddRotateXOp().Set(turn)
        scene = read_stage(direct)
        renderer = FrameRenderer(scene, RenderOptions(mode="rt", width=W, height=H))
        try:
            brightest = renderer.render(1.0).beauty.max()
        finally:
            renderer.close()
        assert brightest > 0.1 if lit else brightest == 0.0


@pytest.mark.parametrize("shape", ["rect", "disk"])
def test_area_lights_at_the_hits_in_centimetres_and_metres_render_the_same(shape):
    """The penumbra stage authored in centimetres (every length x 100) and in metres:
    one image, to float32 rounding (as ``tests/usd/test_light_units.py``'s pairs)."""
    kind, sizes = ((UsdLux.RectLight, {"width": 1.0, "height": 1.0}) if shape == "rect"
                   else (UsdLux.DiskLight, {"radius": 0.5}))  # fmt: skip
    images = [_render(_stage(kind, (-1.0, 0.0, 1.5), sizes, card=True, mpu=mpu), "rt")[0]
              for mpu in (0.01, 1.0)]  # fmt: skip
    assert images[1].max() > 0.1
    np.testing.assert_allclose(images[0], images[1], rtol=1e-4, atol=1e-6)
