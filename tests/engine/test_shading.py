"""Tests of the shared local shading model (phrt_usd.engine.shading)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phrt_usd.engine import shading
from phrt_usd.model import preview_surface, surface
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, DistantLight, DomeLight, Lights, LocalLight

UP = np.array([[0.0, 1.0, 0.0]])
DOWN = -UP


def _surface_points(rng: np.random.Generator, n: int, extent: float):
    """``n`` random shading points: positions (n, 3) uniform in the cube [-extent,
    extent]^3 metres, unit normals and unit view directions (n, 3) drawn isotropically,
    albedo (n, 3) float32 uniform in [0, 1)."""
    pos = rng.uniform(-extent, extent, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    albedo = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    return pos, nrm, view, albedo


def _shade(lights, albedo=(0.5, 0.5, 0.5), view=DOWN, normal=UP, pos=((0.0, 0.0, 0.0),), vis=None,
           surface=None):  # fmt: skip
    n_lights = len(lights.distant) + len(lights.local)
    vis = np.ones((1, n_lights), np.float32) if vis is None else vis
    return shading.shade_local(
        np.array(pos, dtype=np.float64),
        normal,
        np.array([albedo], np.float32) if surface is None else surface,
        view,
        np.zeros(3, np.float32),
        lights,
        vis,
    )[0]


def test_lambert_cosine_law_and_ambient():
    """A surface row without a specular lobe (F0 = F90 = 0: the BRDF's diffuse lobe
    alone, which then takes all the energy) is Lambert's law without the 1/π: albedo x
    cos at every angle, plus albedo x the ambient."""
    dome = DomeLight(color=np.array([0.1, 0.1, 0.1]))
    lambert = preview_surface.fallback_surface(np.full((1, 3), 0.5))
    lambert[:, preview_surface.F0 : preview_surface.F90 + 3] = 0.0
    for angle in (0.0, 30.0, 60.0, 89.0):
        a = np.radians(angle)
        light = DistantLight(np.array([np.sin(a), np.cos(a), 0.0]), np.ones(3))
        view = np.array([[np.sin(a), 0.0, np.cos(a)]])
        got = _shade(Lights(distant=[light], dome=dome), view=-view, surface=lambert)
        expected = 0.5 * 0.1 + 0.5 * np.cos(a)
        np.testing.assert_allclose(got, [expected] * 3, rtol=1e-5)


def test_direct_light_is_the_brdf_and_ambient_its_albedo():
    """UsdPreviewSurface's fallback material (roughness 0.5, ior 1.5) lit by one
    DistantLight at several angles: the BRDF's π f n·l (the numpy form of
    ``tests/shading_reference.py``) plus the dome times the directional albedo."""
    import shading_reference as ref

    dome = DomeLight(color=np.array([0.1, 0.1, 0.1]))
    surf = preview_surface.fallback_surface(np.full((1, 3), 0.5))
    for angle in (0.0, 30.0, 60.0, 89.0):
        a = np.radians(angle)
        light = DistantLight(np.array([np.sin(a), np.cos(a), 0.0]), np.ones(3))
        view = np.array([[np.sin(a), 0.0, np.cos(a)]])  # to the eye
        got = _shade(Lights(distant=[light], dome=dome), view=-view, surface=surf)
        expected = 0.1 * ref.ambient_weight(surf, UP, view) + ref.brdf_cos(
            surf, UP, view, light.direction[None, :]
        )
        np.testing.assert_allclose(got, expected[0], rtol=1e-5)


def test_light_behind_surface_and_shadowed_give_ambient_only():
    import shading_reference as ref

    lights = Lights(distant=[DistantLight(np.array([0.0, -1.0, 0.0]), np.ones(3))])
    surf = preview_surface.fallback_surface(np.full((1, 3), 0.5))
    ambient = ref.ambient_weight(surf, UP, -DOWN)[0] * DEFAULT_ENVIRONMENT
    np.testing.assert_allclose(_shade(lights), ambient, rtol=1e-6)
    lit_from_above = Lights(distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    shadowed = _shade(lit_from_above, vis=np.zeros((1, 1), np.float32))
    np.testing.assert_allclose(shadowed, ambient, rtol=1e-6)


def test_local_light_inverse_square_and_finite_at_the_light():
    def at(height):
        light = LocalLight(np.array([0.0, height, 0.0]), np.full(3, 4.0))
        return _shade(Lights(local=[light]), albedo=(1.0, 1.0, 1.0), view=np.array([[1.0, 0, 0]]))

    r = shading.light_ranges(Lights(local=[LocalLight(np.zeros(3), np.full(3, 4.0))]))[0]
    window = shading.range_window(np.array([1.0, 2.0]), r)
    ratio = (at(1.0) - DEFAULT_ENVIRONMENT) / (at(2.0) - DEFAULT_ENVIRONMENT)
    np.testing.assert_allclose(ratio, 4.0 * window[0] / window[1], rtol=1e-4)
    assert np.all(np.isfinite(at(0.0)))  # surface point exactly at the light


def test_local_light_range_cuts_off_smoothly():
    """A LocalLight reaches exactly as far as LIGHT_CUTOFF_IRRADIANCE says, fades to 0
    there without a step, and contributes nothing beyond."""
    intensity = 8.0
    r = shading.light_ranges(Lights(local=[LocalLight(np.zeros(3), np.full(3, intensity))]))[0]
    assert np.isclose(intensity / r**2, shading.LIGHT_CUTOFF_IRRADIANCE)
    d = np.linspace(0.0, 1.5 * r, 3001)
    w = shading.range_window(d, r)
    assert w[0] == 1.0 and np.all(w[d >= r] == 0.0) and np.all(np.diff(w) <= 0.0)
    assert np.max(np.abs(np.diff(w))) < 5e-3  # no step anywhere (a ring in the image)

    def at(height):
        light = LocalLight(np.array([0.0, height, 0.0]), np.full(3, intensity))
        return _shade(Lights(local=[light]), albedo=(1.0, 1.0, 1.0), view=np.array([[1.0, 0, 0]]))

    ambient = DEFAULT_ENVIRONMENT.astype(np.float32)
    np.testing.assert_allclose(at(1.01 * r), ambient, rtol=1e-6)
    assert np.all(at(0.95 * r) > ambient) and np.all(at(0.5 * r) > at(0.95 * r))
    ranges = shading.light_ranges(
        Lights(
            distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))],
            local=[LocalLight(np.zeros(3), np.zeros(3))],
        )
    )
    assert ranges[0] == np.inf and ranges[1] == 0.0  # black light reaches nowhere


def test_light_directions_order_and_distances():
    lights = Lights(
        distant=[DistantLight(np.array([0.0, 2.0, 0.0]), np.ones(3))],
        local=[LocalLight(np.array([3.0, 4.0, 0.0]), np.ones(3))],
    )
    dirs, dist = shading.light_directions(lights, np.zeros((2, 3)))
    assert dirs.shape == (2, 2, 3) and dist.shape == (2, 2)
    np.testing.assert_allclose(dirs[0, 0], [0, 1, 0])
    np.testing.assert_allclose(dirs[0, 1], [0.6, 0.8, 0])
    assert np.isinf(dist[0, 0]) and dist[0, 1] == 5.0


def test_environment_fallbacks_and_latlong_convention():
    none = shading.environment_radiance(Lights(), UP)
    np.testing.assert_allclose(none, [DEFAULT_ENVIRONMENT])
    const = Lights(dome=DomeLight(color=np.array([0.3, 0.2, 0.1])))
    np.testing.assert_allclose(shading.environment_radiance(const, DOWN), [[0.3, 0.2, 0.1]])
    np.testing.assert_allclose(shading.ambient_radiance(const), [0.3, 0.2, 0.1])
    # OpenEXR lat-long: column 0 is longitude +π (-Z), the middle column longitude 0 (+Z),
    # a quarter from the right longitude +π/2 (+X).
    w, h = 16, 8
    tex = np.zeros((h, w, 3), np.float32)
    tex[:, :, 0] = np.arange(w)[None, :] + 0.5  # red = continuous column coordinate
    lights = Lights(dome=DomeLight(color=np.ones(3), texture=tex))
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    col = shading.environment_radiance(lights, dirs)[:, 0]
    np.testing.assert_allclose(col, [w / 2, w / 4, 3 * w / 4], atol=1e-4)
    # world_from_light rotates the dome: a Z-up stage's dome has its pole along world +Z.
    tex2 = np.zeros((h, w, 3), np.float32)
    tex2[0] = 1.0
    z_up = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # light +Y → world +Z
    rotated = Lights(dome=DomeLight(color=np.ones(3), texture=tex2, world_from_light=z_up))
    np.testing.assert_allclose(shading.environment_radiance(rotated, [[0, 0, 1.0]]), [[1, 1, 1]])


def test_ambient_is_solid_angle_mean_and_cached():
    h, w = 64, 128
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    tex = np.zeros((h, w, 3), np.float32)
    tex[lat > 0] = 1.0  # bright upper hemisphere: half the sphere's solid angle
    lights = Lights(dome=DomeLight(color=np.full(3, 2.0), texture=tex))
    amb = shading.ambient_radiance(lights)
    np.testing.assert_allclose(amb, [1.0, 1.0, 1.0], rtol=1e-3)
    assert shading.ambient_radiance(lights) is not amb  # a fresh array every call
    np.testing.assert_allclose(shading.ambient_radiance(lights), amb)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(min_value=-1e30, max_value=1e30, allow_nan=False),
    st.floats(min_value=-1e30, max_value=1e30, allow_nan=False),
)
def test_shading_finite_for_extreme_positions(x, y):
    lights = Lights(
        distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3))],
        local=[LocalLight(np.array([0.0, 0.0, 0.0]), np.ones(3))],
    )
    got = shading.shade_local(
        np.array([[x, y, 0.0]]),
        UP,
        np.ones((1, 3)),
        DOWN,
        np.zeros(3),
        lights,
        np.ones((1, 2), np.float32),
    )
    assert np.all(np.isfinite(got))


def test_sample_texture_st_origin_bottom_left():
    tex = np.zeros((4, 4, 3), np.float32)
    tex[3, 0] = 1.0  # bottom-left texel
    got = surface.sample_bilinear_wrap(tex, np.array([[0.125, 0.125], [0.875, 0.875]]))
    np.testing.assert_allclose(got, [[1, 1, 1], [0, 0, 0]])


def test_local_pairs_give_the_same_shading_as_visibility():
    """The tracer's shortcut (lit LocalLight pairs with their directions) evaluates the
    same model as the (n, L) visibility matrix."""
    rng = np.random.default_rng(3)
    n = 500
    pos, nrm, view, albedo = _surface_points(rng, n, 6.0)
    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.array([1.0, 0.9, 0.8]))],
        local=[
            LocalLight(np.array([1.0, 2.0, 0.0]), np.full(3, 0.5)),  # range 5 m
            LocalLight(np.array([-3.0, 0.0, 1.0]), np.array([2.0, 1.0, 0.5])),
            LocalLight(np.array([0.0, -2.0, 4.0]), np.full(3, 0.5)),
        ],
    )
    vis = (rng.uniform(size=(n, 4)) > 0.3).astype(np.float32)
    ranges = shading.light_ranges(lights)
    points, lights_k, dirs, dists = [], [], [], []
    for k, light in enumerate(lights.local):
        to = light.position - pos
        dist = np.linalg.norm(to, axis=1)
        ok = (vis[:, 1 + k] > 0) & (dist < ranges[1 + k]) & (np.einsum("ij,ij->i", nrm, to) > 0)
        vis[~ok, 1 + k] = 0.0  # what the tracer reports for such pairs
        points.append(np.flatnonzero(ok))
        lights_k.append(np.full(ok.sum(), k))
        dirs.append(to[ok] / dist[ok, None])
        dists.append(dist[ok])
    pairs = tuple(np.concatenate(a) for a in (points, lights_k, dirs, dists))
    assert 0 < len(pairs[0]) < 3 * n
    em = np.zeros(3, np.float32)
    full = shading.shade_local(pos, nrm, albedo, view, em, lights, vis)
    short = shading.shade_local(pos, nrm, albedo, view, em, lights, vis, pairs)
    np.testing.assert_allclose(short, full, rtol=1e-4, atol=1e-6)


def test_threaded_shade_local_matches_one_chunk(monkeypatch):
    """Large batches are split over threads; the result must equal one-piece shading
    (points are independent), visibility columns and per-point emissive included."""
    rng = np.random.default_rng(7)
    n = 3 * shading.SHADE_MIN_THREADED_POINTS
    pos, nrm, view, albedo = _surface_points(rng, n, 5.0)
    emissive = rng.uniform(0.0, 0.1, (n, 3)).astype(np.float32)
    lights = Lights(
        distant=[DistantLight(np.array([0.3, -1.0, 0.2]), np.full(3, 2.0))],
        local=[
            LocalLight(np.array([1.0, 2.0, 0.0]), np.array([4.0, 3.0, 2.0])),
            LocalLight(np.array([-3.0, 1.0, 2.0]), np.full(3, 0.5)),
        ],
    )
    vis = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    vis[vis < 0.3] = 0.0
    monkeypatch.setattr(shading, "SHADE_THREADS", 3)  # uneven chunks, on any machine
    threaded = shading.shade_local(pos, nrm, albedo, view, emissive, lights, vis)
    monkeypatch.setattr(shading, "SHADE_THREADS", 1)
    single = shading.shade_local(pos, nrm, albedo, view, emissive, lights, vis)
    assert threaded.shape == (n, 3) and threaded.dtype == np.float32
    # Equal up to float32 rounding: numpy's SIMD loops may round a chunk's first and last
    # elements differently from the same elements inside one long array (seen: 1 ulp).
    np.testing.assert_allclose(threaded, single, rtol=1e-6, atol=1e-7)
    assert float(threaded.max()) > 0.0
    # Weighted LocalLight pairs (sorted by point) and GPU-style local sums split with
    # the points too.
    point = np.sort(rng.choice(n, n // 2, replace=False))
    light = rng.integers(0, 2, len(point))
    l_dir, dist = shading.pair_directions(lights, pos, point, light)
    weight = rng.uniform(0.1, 1.0, len(point)).astype(np.float32)
    pairs = shading.LightPairs(point, light, l_dir, dist, weight)
    sums = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    runs = []
    for threads in (3, 1):
        monkeypatch.setattr(shading, "SHADE_THREADS", threads)
        runs.append(
            shading.shade_local(
                pos, nrm, albedo, view, emissive, lights, vis[:, :1], pairs, lit_sums=sums
            )
        )
    np.testing.assert_allclose(runs[0], runs[1], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("threads", [1, 3])
def test_gather_rows_is_take(monkeypatch, threads):
    """``gather_rows`` on the shading pool (uneven slices) gives np.take's rows."""
    monkeypatch.setattr(shading, "SHADE_THREADS", threads)
    rng = np.random.default_rng(5)
    n = 3 * shading.SHADE_MIN_THREADED_POINTS
    for a in (rng.normal(size=(n, 3)), rng.integers(0, 9, n).astype(np.int32)):
        index = np.flatnonzero(rng.uniform(size=n) < 0.9)
        got = shading.gather_rows(a, index)
        assert got.dtype == a.dtype
        np.testing.assert_array_equal(got, np.take(a, index, axis=0))
