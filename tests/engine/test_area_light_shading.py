"""Rect and Disk lights shaded as areas wherever a pair is shaded: the area factor (the
light's exact unshadowed irradiance over the point light's at its centre,
``area_light_kernels._factor``) in the compiled shading (``shading.shade_local``), the
GPU light pass (``shaders/cube_lookup.frag``'s ``area_factor``) and the traced hits'
weights, so that raster, hybrid and rt show the area's irradiance on a floor under a
rect and a disk, nothing behind a light, and nothing non-finite anywhere.

The floor stage (``_floor_stage``): a grey square (albedo 0.5, the fallback material)
6 x 6 m in the plane z = 0 facing +Z, a black dome, the camera at z = 2.5 looking down;
a 1 x 0.6 m RectLight at (-0.8, 0, 1) and a DiskLight of radius 0.4 at (0.8, 0, 0.7),
both facing down, of luminance LUMINANCE (not normalized). A floor point's value is,
per light, L × its irradiance integral ∫ cos θ_e cos θ_p / d² dA (closed forms for a
parallel rect and disk: ``shading_reference.rect_light_integral``,
``disk_light_integral``) × π f n·l / n·l at the
direction of the light's centre (the rule's BRDF).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Gf, UsdGeom, UsdLux
from scenes import first_frame, grey_square_stage, parts_scene, quad
from shading_reference import brdf_cos
from shading_reference import disk_light_integral as disk_integral
from shading_reference import rect_light_integral as rect_integral

from phrt_usd import kernels
from phrt_usd.engine import shading
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.engine.trace.hit_lighting import HitLighting
from phrt_usd.model.preview_surface import fallback_surface
from phrt_usd.model.scene import DomeLight, Lights, LocalLight
from phrt_usd.usd import schema

_AREA = kernels.load("phrt_usd.engine.trace.area_light_kernels")

ALBEDO = 0.5
#: The lights' luminance: bright enough that their range (``shading.light_ranges``,
#: ~sqrt(L A / 0.02) m) puts the range window within 1e-6 of 1 over the floor.
LUMINANCE = 5000.0
RECT_AT, RECT_HALF = np.array([-0.8, 0.0, 1.0]), (0.5, 0.3)
DISK_AT, DISK_R = np.array([0.8, 0.0, 0.7]), 0.4
EYE = (0.0, 0.0, 2.5)
UP = np.array([0.0, 0.0, 1.0])


def _floor_stage(flip_rect: bool = False):
    stage = grey_square_stage(ALBEDO, 3.0, EYE)
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(0.0)
    rect = UsdLux.RectLight.Define(stage, "/World/Rect")
    rect.AddTranslateOp().Set(Gf.Vec3d(*RECT_AT))
    if flip_rect:
        rect.AddRotateXOp().Set(180.0)  # emits up, away from the floor
    rect.CreateWidthAttr(2 * RECT_HALF[0])
    rect.CreateHeightAttr(2 * RECT_HALF[1])
    disk = UsdLux.DiskLight.Define(stage, "/World/Disk")
    disk.AddTranslateOp().Set(Gf.Vec3d(*DISK_AT))
    disk.CreateRadiusAttr(DISK_R)
    for light in (rect, disk):
        light.CreateIntensityAttr(LUMINANCE)
    return stage


def _expected(points, to_eye, rect: bool = True) -> np.ndarray:
    """The floor points' (n, 3) values seen along ``to_eye`` (n, 3): module docstring."""
    surface = fallback_surface(np.full((len(points), 3), ALBEDO))
    normals = np.tile(UP, (len(points), 1))
    total = np.zeros(len(points))
    lights = [(DISK_AT, lambda p: disk_integral(p, DISK_AT, DISK_R))]
    if rect:
        lights.append((RECT_AT, lambda p: rect_integral(p, RECT_AT, *RECT_HALF)))
    for centre, integral in lights:
        to_light = centre - points
        to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
        over_cos = brdf_cos(surface, normals, to_eye, to_light)[:, 0] / to_light[:, 2]
        total += LUMINANCE * np.array([integral(p) for p in points]) * over_cos
    return total


#: Rendered against the closed forms over the whole floor the camera sees. Every floor
#: point sees both lights whole (nothing casts shadows): the area factor is exact up to
#: float32 shading (the rect's, GLSL's float32 polygon sum) and the disk's outline (a
#: 24-gon of its area: ~1e-3 off the disk's integral near it), so 3e-3 everywhere.
FLOOR_RTOL = 3e-3


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "hybrid", "rt"])
def test_a_floor_under_a_rect_and_a_disk_shows_their_areas(mode):
    """Every floor pixel of raster (the GPU light pass), hybrid and rt (the compiled
    shading of rt's shadow-ray visibility) equals the closed forms within FLOOR_RTOL;
    under the rect's centre the point light of its intensity would be 1.22 times as
    bright, under the disk's 1.33 times: the test tells an area from a point."""
    out = first_frame(_floor_stage(), mode, 96, 72)
    cov = out.gbuffer.covered
    points = out.gbuffer.position[cov].astype(np.float64)
    to_eye = np.asarray(EYE) - points
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    values = out.beauty[cov][:, 0].astype(np.float64)
    expected = _expected(points, to_eye)
    assert cov.sum() > 0.9 * 96 * 72
    np.testing.assert_allclose(values, expected, rtol=FLOOR_RTOL)
    # The point light's near-field excess under each centre, which the test resolves.
    h_rect, h_disk = RECT_AT[2], DISK_AT[2]
    area_rect = 4 * RECT_HALF[0] * RECT_HALF[1]
    point_rect = area_rect / h_rect**2 / rect_integral(RECT_AT * [1, 1, 0], RECT_AT, *RECT_HALF)
    point_disk = np.pi * DISK_R**2 / h_disk**2 / disk_integral(DISK_AT * [1, 1, 0], DISK_AT,
                                                               DISK_R)  # fmt: skip
    assert point_rect > 1.2 and point_disk > 1.3


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "hybrid", "rt"])
def test_nothing_behind_a_rect_light_is_lit_in_any_mode(mode):
    """The rect turned to emit upwards lights nothing of the floor below it: the floor
    shows the disk's light alone (within FLOOR_RTOL), where a point light would add the
    rect's intensity from its centre."""
    out = first_frame(_floor_stage(flip_rect=True), mode, 48, 36)
    cov = out.gbuffer.covered
    points = out.gbuffer.position[cov].astype(np.float64)
    to_eye = np.asarray(EYE) - points
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    np.testing.assert_allclose(out.beauty[cov][:, 0], _expected(points, to_eye, rect=False),
                               rtol=FLOOR_RTOL)  # fmt: skip


def _shape_light(kind: str, centre, u, v, radiance: float = 50.0) -> LocalLight:
    """A Rect or Disk LocalLight (kind "rect", "disk"; "" a point) at ``centre`` of half
    axes ``u``, ``v`` (3,), emitting along -(u x v) (its -Z)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    axis = -np.cross(u, v)
    length = np.linalg.norm(axis)
    axis = axis / length if length > 0.0 else np.array([0.0, 0.0, -1.0])
    return LocalLight(np.asarray(centre, float), np.full(3, radiance), axis=axis,
                      area_shape=kind, area_u=u, area_v=v)  # fmt: skip


#: The lights the GLSL factor is compared on: a rect facing down, a rect tilted and
#: stretched, a disk, an ellipse (a scaled disk).
SHAPES = {
    "rect": ("rect", (0.0, 0.0, 1.0), (0.5, 0, 0), (0, 0.3, 0)),
    "tilted_rect": ("rect", (0.2, -0.1, 1.2), (0.6, 0.0, 0.3), (0.0, 0.25, 0.1)),
    "disk": ("disk", (0.1, 0.1, 0.9), (0.4, 0, 0), (0, 0.4, 0)),
    "ellipse": ("disk", (0.0, 0.3, 1.0), (0.5, 0.0, 0.2), (0.0, 0.2, 0.0)),
}


def _gpu_and_kernel(light: LocalLight | list, positions, normals, to_eye):
    """The direct light (k, 3) of k points lit by ``light`` alone (or a list of lights):
    the GPU light pass's lit sums (``Rasterizer.map_light_terms``; nothing casts a shadow
    near them: a 1 m quad 100 m away is the scene) and ``shading.shade_local``'s (the
    compiled factor), both with the fallback material of albedo 0.6, a black dome."""
    local = light if isinstance(light, list) else [light]
    lights = Lights(local=local, dome=DomeLight(color=np.zeros(3)))
    scene = parts_scene([dict(mesh=quad(1.0, center=(100.0, 0.0, 0.0)))], lights=lights)
    surface = fallback_surface(np.full((len(positions), 3), 0.6))
    with Rasterizer(scene, 64, 64) as r:
        r.cube_lookup_on_gpu = True
        terms = r.map_light_terms(positions, normals.astype(np.float32),
                                  to_eye.astype(np.float32), surface=surface)  # fmt: skip
    assert not len(terms.rows)  # every pair decided by the maps (lit)
    kernel = shading.shade_local(positions, normals, surface, -to_eye, np.zeros(3), lights,
                                 None)  # fmt: skip
    return terms.lit_sums[:, :3].astype(np.float64), kernel.astype(np.float64)


def _random_points(k: int, seed: int):
    """k points within 2.5 m of the lights, half below and some above them, with random
    unit normals and eyes (both on the same side)."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform([-2.5, -2.5, -1.0], [2.5, 2.5, 2.5], (k, 3))
    normals = rng.normal(size=(k, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    to_eye = normals + 0.7 * rng.normal(size=(k, 3))
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    return positions, normals, to_eye


#: GPU (float32 GLSL) against compiled (float64) area factor times the same BRDF: the
#: polygon's terms in float32 (~1e-7 relative each, the shader's own atan) cancel to the
#: irradiance, down to ~1/300 of them where a light is seen near its plane or its horizon:
#: measured 2.9e-4 at most over these draws (llvmpipe's atan left 1.3 %); 1e-3 of it,
#: and an atol of 1e-5 of a pair's brightest (~100).
GLSL_RTOL, GLSL_ATOL = 1e-3, 1e-3


@pytest.mark.parametrize("name", list(SHAPES))
def test_glsl_area_factor_is_the_kernels_at_random_points(name):
    """The light pass's ``area_factor`` (GLSL) and ``area_light_kernels._factor`` (through
    ``shading.shade_local``) shade 2048 random (point, light) pairs alike, within
    GLSL_RTOL / GLSL_ATOL: points in front of, beside and behind the light (0 there),
    normals facing it or not."""
    kind, centre, u, v = SHAPES[name]
    light = _shape_light(kind, centre, u, v)
    positions, normals, to_eye = _random_points(2048, 5)
    gpu, kernel = _gpu_and_kernel(light, positions, normals, to_eye)
    assert np.all(np.isfinite(gpu)) and np.all(np.isfinite(kernel))
    lit = kernel[:, 0] > 1e-3
    assert lit.sum() > 400  # many pairs lit by the light, and many not
    assert (~lit).sum() > 400
    np.testing.assert_allclose(gpu, kernel, rtol=GLSL_RTOL, atol=GLSL_ATOL)
    # Behind the light (the side it does not emit to): nothing.
    behind = (positions - light.position) @ light.axis < 0.0
    assert behind.sum() > 200
    assert gpu[behind].max() == 0.0 and kernel[behind].max() == 0.0


def test_glsl_area_factor_in_a_tiled_pass():
    """Past 16 LocalLights the pass walks each tile's lights from the light table (TILED,
    six texels a light with the shapes): a disk and a rect among 16 dim point lights
    spread around the points shade as the compiled shading does (GLSL_RTOL /
    GLSL_ATOL), the areas' pairs included."""
    rng = np.random.default_rng(8)
    points = [LocalLight(rng.uniform(-3.0, 3.0, 3), np.full(3, 0.5)) for _ in range(16)]
    areas = [_shape_light(*SHAPES["ellipse"]), _shape_light(*SHAPES["tilted_rect"])]
    lights = points[:7] + areas[:1] + points[7:] + areas[1:]
    positions, normals, to_eye = _random_points(2048, 6)
    gpu, kernel = _gpu_and_kernel(lights, positions, normals, to_eye)
    only_points, _ = _gpu_and_kernel(points, positions, normals, to_eye)
    assert np.all(np.isfinite(gpu))
    assert (gpu[:, 0] > only_points[:, 0] + 1e-3).sum() > 400  # lit by the areas too
    np.testing.assert_allclose(gpu, kernel, rtol=GLSL_RTOL, atol=GLSL_ATOL)


def test_the_factor_is_exact_where_closed_forms_hold():
    """``area_light_kernels.area_columns`` on a floor point facing up under a rect and a
    disk facing down: the closed forms' integral over A cos θ_p,c / d_c² (module
    docstring's ``rect_integral``, ``disk_integral``; the disk's 24-gon: 1e-3)."""
    area = shading.area_table(Lights(local=[
        _shape_light("rect", RECT_AT, (RECT_HALF[0], 0, 0), (0, RECT_HALF[1], 0)),
        _shape_light("disk", DISK_AT, (DISK_R, 0, 0), (0, DISK_R, 0)),
    ]))  # fmt: skip
    points = np.array([[0.0, 0.0, 0.0], [-0.8, 0.1, 0.0], [0.5, -0.4, 0.2]])
    vis = np.ones((3, 2), np.float32)
    _AREA.area_columns(area, 0, points, np.tile(UP.astype(np.float32), (3, 1)), 1e-4, vis)
    for q, (centre, size, integral) in enumerate([
        (RECT_AT, 4 * RECT_HALF[0] * RECT_HALF[1], lambda p: rect_integral(p, RECT_AT,
                                                                           *RECT_HALF)),
        (DISK_AT, np.pi * DISK_R**2, lambda p: disk_integral(p, DISK_AT, DISK_R)),
    ]):  # fmt: skip
        for i, p in enumerate(points):
            d = centre - p
            point_light = size * d[2] / np.linalg.norm(d) ** 3
            want = integral(p) / point_light
            assert vis[i, q] == pytest.approx(want, rel=2e-6 if q == 0 else 1e-3)


#: Points at the edge of a 1 x 1 m rect, on its plane, beside and behind it, and lights
#: of zero size: where the polygon formula divides by lengths that vanish.
_COORD = st.floats(-1.5, 1.5, allow_nan=False, width=32)


@settings(max_examples=200, deadline=None)
@given(x=_COORD, y=_COORD, z=st.sampled_from([0.0, 1e-7, -1e-7, 0.3, -0.3]),
       nx=_COORD, ny=_COORD, nz=_COORD, kind=st.sampled_from(["rect", "disk"]),
       size=st.sampled_from([0.5, 1e-9, 0.0]), snap=st.booleans())  # fmt: skip
def test_the_factor_is_finite_and_non_negative_everywhere(x, y, z, nx, ny, nz, kind, size,
                                                          snap):  # fmt: skip
    """A point anywhere near a light facing down at the origin (on its plane z = 0, at
    its edge x = ±size, just above or below it), any normal, a light of no size: the
    factor is finite and >= 0, 0 above the light (behind it, z > 0) and on its plane
    but for rounding, and the shading of the pair finite."""
    if snap:
        x = size if x > 0 else -size  # on the edge's line
    light = _shape_light(kind, (0.0, 0.0, 0.0), (size, 0, 0), (0, size, 0))
    lights = Lights(local=[light], dome=DomeLight(color=np.zeros(3)))
    area = shading.area_table(lights)
    normal = np.array([nx, ny, nz], np.float64)
    if not np.linalg.norm(normal) > 1e-3:
        normal = np.array([0.0, 0.0, 1.0])
    normal = (normal / np.linalg.norm(normal)).astype(np.float32)[None]
    point = np.array([[x, y, -z]])
    vis = np.ones((1, 1), np.float32)
    _AREA.area_columns(area, 0, point, normal, shading.MIN_LIGHT_DISTANCE, vis)
    factor = float(vis[0, 0])
    assert np.isfinite(factor) and factor >= 0.0
    if -z >= 0.0:  # behind the light or in its plane
        assert factor == 0.0
    if size == 0.0:  # a light of no area lights nothing
        assert factor == 0.0
    out = shading.shade_local(point, normal, fallback_surface(np.full((1, 3), 0.5)),
                              -normal, np.zeros(3), lights, None)  # fmt: skip
    assert np.all(np.isfinite(out)) and np.all(out >= 0.0)


@pytest.mark.parametrize("size", [0.5, 0.0])
@pytest.mark.parametrize("kind", ["rect", "disk"])
def test_the_light_pass_is_finite_on_a_lights_plane_and_edge(kind, size):
    """The GPU light pass and the compiled shading at points on a light's plane (z = 0),
    on its edge's lines, just in front and behind, for a 1 m light and one of no size:
    finite everywhere, equal (GLSL_RTOL / GLSL_ATOL), 0 for the light of no size."""
    light = _shape_light(kind, (0.0, 0.0, 1.0), (size, 0, 0), (0, size, 0))
    xs = np.array([-0.5, -0.25, 0.0, 0.5, 0.75, 1.5])
    x, y, z = np.meshgrid(xs, xs, [1.0, 1.0 - 1e-6, 1.0 + 1e-6, 0.99])
    positions = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    positions = positions[np.linalg.norm(positions - light.position, axis=1) > 1e-3]
    rng = np.random.default_rng(2)
    normals = rng.normal(size=positions.shape) + [0.0, 0.0, 1.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    gpu, kernel = _gpu_and_kernel(light, positions, normals, normals)
    assert np.all(np.isfinite(gpu)) and np.all(np.isfinite(kernel))
    np.testing.assert_allclose(gpu, kernel, rtol=GLSL_RTOL, atol=GLSL_ATOL)
    if size == 0.0:
        assert gpu.max() == 0.0 and kernel.max() == 0.0
    else:
        assert gpu.max() > 1.0


def _penumbra_stage(card: bool):
    """A 1 x 1 m rect facing down at (-1, 0, 1.5) over the floor, seen from above, and
    with ``card`` an opaque card at z = 0.5 over x < 0: a floor point at x sees the
    light where its x_l > -2 x (a penumbra from x = 0.25 to 0.75 m; the centre's shadow
    edge at x = 0.5)."""
    stage = grey_square_stage(ALBEDO, 3.0, EYE)
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(0.0)
    rect = UsdLux.RectLight.Define(stage, "/World/Rect")
    rect.AddTranslateOp().Set(Gf.Vec3d(-1.0, 0.0, 1.5))
    rect.CreateIntensityAttr(LUMINANCE)
    if card:
        mesh = UsdGeom.Mesh.Define(stage, "/World/Card")
        mesh.CreatePointsAttr([(-3, -3, 0.5), (0, -3, 0.5), (0, 3, 0.5), (-3, 3, 0.5)])
        mesh.CreateFaceVertexCountsAttr([4])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return stage


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["rt", "raster"])
def test_the_primary_surface_has_the_areas_penumbra_in_rt_and_the_centres_in_raster(mode):
    """The floor seen directly under the penumbra stage, over the same floor without the
    card: in rt the share of the rect's irradiance each floor pixel sees, a dither of
    its one area ray (0 or 1) whose mean over 0.1 m strips of the floor (~600 pixels)
    is the closed form of the visible part of the rect over the whole (a rect again: x_l
    from max(-1.5, -2 x) to -0.5) within 0.05 (measured 0.012 at most; the dither of 13
    lattice points over 600 pixels), 0.02 on average; in raster the shadow map's
    test from the light's centre: dark below x = 0.45, lit from x = 0.55 (the maps' PCF
    band between), under the area's irradiance (FLOOR_RTOL where lit)."""
    size = (192, 144)  # ~1.5 cm pixels on the floor
    shadowed = first_frame(_penumbra_stage(True), mode, *size)
    open_ = first_frame(_penumbra_stage(False), mode, *size)
    points = shadowed.gbuffer.position.reshape(-1, 3).astype(np.float64)
    keep = np.flatnonzero((np.abs(points[:, 1]) < 0.5) & (points[:, 0] > 0.05)
                          & (points[:, 0] < 1.0) & (np.abs(points[:, 2]) < 1e-3))  # fmt: skip
    share = shadowed.beauty.reshape(-1, 3)[keep, 0] / open_.beauty.reshape(-1, 3)[keep, 0]
    x = points[keep, 0]
    centre = np.array([-1.0, 0.0, 1.5])
    if mode == "raster":
        np.testing.assert_array_equal(share[x < 0.45], 0.0)
        np.testing.assert_allclose(share[x > 0.55], 1.0, rtol=1e-6)
        lit = keep[x > 0.55]
        to_eye = np.asarray(EYE) - points[lit]
        to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
        surface = fallback_surface(np.full((len(lit), 3), ALBEDO))
        to_light = centre - points[lit]
        to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
        over_cos = brdf_cos(surface, np.tile(UP, (len(lit), 1)), to_eye, to_light)[:, 0]
        over_cos /= to_light[:, 2]
        want = [LUMINANCE * rect_integral(points[i], centre, 0.5, 0.5) for i in lit] * over_cos
        np.testing.assert_allclose(open_.beauty.reshape(-1, 3)[lit, 0], want, rtol=FLOOR_RTOL)
        return
    np.testing.assert_array_equal(share[x < 0.24], 0.0)  # the umbra
    np.testing.assert_allclose(share[x > 0.76], 1.0, rtol=1e-6)  # the whole light seen
    penumbra = (x > 0.3) & (x < 0.7)
    assert set(np.unique(np.round(share[penumbra], 6))) == {0.0, 1.0}  # a dither

    def seen(p) -> float:
        lo = max(-1.5, -2.0 * p[0])
        if lo >= -0.5:
            return 0.0
        part = [(lo - 0.5) / 2, 0.0, 1.5]
        return rect_integral(p, part, (-0.5 - lo) / 2, 0.5) / rect_integral(p, centre, 0.5, 0.5)

    errors = []
    for lo in np.arange(0.2, 0.8, 0.1):
        strip = (x >= lo) & (x < lo + 0.1)
        assert strip.sum() >= 50
        expected = np.mean([seen(p) for p in points[keep[strip]]])
        errors.append(abs(share[strip].mean() - expected))
    assert max(errors) < 0.05 and np.mean(errors) < 0.02, errors


def _mirror_stage():
    """The floor under the module's rect (alone of the two area lights), two dim
    SphereLights below the floor (they light none of it but make three lights: the
    shadow maps light the traced hits, ``light_sampling.maps_light_hits``), a mirror
    (reflectivity 1) 6 x 6 m at z = 3 facing down and the camera at z = 2.5 looking up
    at it, so every pixel is a traced reflection of the floor."""
    stage = grey_square_stage(ALBEDO, 3.0, EYE)
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/Cam")).AddRotateXOp().Set(180.0)  # up
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(0.0)
    mirror = UsdGeom.Mesh.Define(stage, "/World/Mirror")
    mirror.CreatePointsAttr([(-3, -3, 3), (-3, 3, 3), (3, 3, 3), (3, -3, 3)])
    mirror.CreateFaceVertexCountsAttr([4])
    mirror.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    rect = UsdLux.RectLight.Define(stage, "/World/Rect")
    rect.AddTranslateOp().Set(Gf.Vec3d(*RECT_AT))
    rect.CreateWidthAttr(2 * RECT_HALF[0])
    rect.CreateHeightAttr(2 * RECT_HALF[1])
    rect.CreateIntensityAttr(LUMINANCE)
    for k, x in enumerate((-2.0, 2.0)):
        below = UsdLux.SphereLight.Define(stage, f"/World/Below{k}")
        below.AddTranslateOp().Set(Gf.Vec3d(x, 0.0, -1.0))
        below.CreateIntensityAttr(1.0)
    return stage


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["hybrid", "rt"])
def test_hits_lit_through_the_maps_show_the_areas_irradiance(mode, monkeypatch):
    """The reflection of the floor under the rect, its hits lit through the shadow maps
    (the GPU light pass shades them, ``HitLighting._with_maps``): every traced pixel is
    the floor point's closed form (FLOOR_RTOL), as the hits lit by rays are
    (tests/engine/test_area_lights.py)."""
    with_maps = []
    original = HitLighting._with_maps

    def spy(self, *args, **kwargs):
        with_maps.append(len(args[0]))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(HitLighting, "_with_maps", spy)
    w, h = 96, 72  # 6,912 hits x 3 lights: over hit_lighting.MAP_MIN_PAIRS
    out = first_frame(_mirror_stage(), mode, w, h)
    assert sum(with_maps) == w * h  # every hit lit through the maps
    assert out.traced_mask.all()
    m = out.gbuffer.position.reshape(-1, 3).astype(np.float64)
    d = m - np.asarray(EYE)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = d * np.array([1.0, 1.0, -1.0])
    floor = m + r * (3.0 / d[:, 2:3])  # where the reflected ray meets z = 0
    values = out.beauty.reshape(-1, 3)[:, 0].astype(np.float64)
    surface = fallback_surface(np.full((len(floor), 3), ALBEDO))
    to_light = RECT_AT - floor
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    over_cos = brdf_cos(surface, np.tile(UP, (len(floor), 1)), -r, to_light)[:, 0]
    over_cos /= to_light[:, 2]
    want = np.array([LUMINANCE * rect_integral(p, RECT_AT, *RECT_HALF) for p in floor])
    np.testing.assert_allclose(values, want * over_cos, rtol=FLOOR_RTOL)
