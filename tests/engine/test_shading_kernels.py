"""The compiled shading kernels (``phrt_usd.engine.shading``) against their numpy
reference (``tests/shading_reference.py``, the vectorised code they replaced): the same
model on random points, lights of every kind, every optional input, and extreme values.

Tolerances: the kernels sum in float64 where the reference rounds its terms to float32,
so results agree to a few float32 ulps (rtol 1e-5) plus an absolute 1e-6 for terms that
cancel (the GGX peak of a float32-rounded cosine near 1).
"""

from __future__ import annotations

import numpy as np
import pytest
import shading_reference as ref

from phrt_usd.engine import shading
from phrt_usd.model import preview_surface as ps
from phrt_usd.model.scene import DistantLight, DomeLight, Lights, LocalLight

RTOL, ATOL = 1e-5, 1e-6


def _points(rng: np.random.Generator, n: int, extent: float):
    """n random points in [-extent, extent]^3 metres, isotropic unit normals and view
    directions (float32), albedo in [0, 1) (float32)."""
    pos = rng.uniform(-extent, extent, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    albedo = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    return pos, nrm.astype(np.float32), view.astype(np.float32), albedo


def _lights(shaped: bool) -> Lights:
    spot = dict(axis=np.array([0.0, -1.0, 0.0]), cone_angle=40.0, cone_softness=0.3, focus=2.0)
    return Lights(
        distant=[
            DistantLight(np.array([0.3, 1.0, 0.2]), np.array([1.0, 0.9, 0.8])),
            DistantLight(np.array([-1.0, 0.5, 0.0]), np.array([0.2, 0.2, 0.3])),
        ],
        local=[
            LocalLight(np.array([1.0, 2.0, 0.0]), np.full(3, 3.0)),
            LocalLight(
                np.array([-3.0, 0.0, 1.0]), np.array([2.0, 1.0, 0.5]), **(spot if shaped else {})
            ),
            LocalLight(np.array([0.0, -2.0, 4.0]), np.full(3, 3.0)),
        ],
        dome=DomeLight(color=np.array([0.1, 0.2, 0.3])),
    )


def _pairs(rng, pos, nrm, lights, sort: bool):
    """Lit LocalLight pairs as the tracer makes them (in range, facing), weighted."""
    ranges = shading.light_ranges(lights)[len(lights.distant) :]
    point, light = [], []
    for k, li in enumerate(lights.local):
        to = li.position - pos
        ok = (np.linalg.norm(to, axis=1) < ranges[k]) & (np.einsum("ij,ij->i", nrm, to) > 0)
        ok &= rng.uniform(size=len(pos)) > 0.3
        point.append(np.flatnonzero(ok))
        light.append(np.full(ok.sum(), k))
    point, light = np.concatenate(point), np.concatenate(light)
    if sort:
        order = np.argsort(point, kind="stable")
        point, light = point[order], light[order]
    l_dir, dist = shading.pair_directions(lights, pos, point, light)
    weight = rng.uniform(0.1, 1.0, len(point)).astype(np.float32)
    return shading.LightPairs(point, light, l_dir, dist, weight)


@pytest.mark.parametrize("shaped", [False, True])
@pytest.mark.parametrize("case", ["visibility", "all_lit", "pairs", "pairs_unweighted", "sums"])
def test_shade_kernel_matches_numpy_reference(shaped, case):
    rng = np.random.default_rng(11)
    n = 2000
    pos, nrm, view, albedo = _points(rng, n, 6.0)
    lights = _lights(shaped)
    emissive = rng.uniform(0.0, 0.2, (n, 3)).astype(np.float32)
    vis = rng.uniform(0.0, 1.0, (n, 5)).astype(np.float32)
    vis[vis < 0.3] = 0.0
    # Random UsdPreviewSurface inputs: both workflows, clear coats, every roughness.
    surface = ps.surface_columns(
        albedo, rng.uniform(0.0, 1.0, n), rng.uniform(size=n) < 0.3,
        rng.uniform(0.0, 1.0, (n, 3)), rng.uniform(0.0, 1.0, n),
        np.where(rng.uniform(size=n) < 0.5, rng.uniform(0.0, 1.0, n), 0.0),
        rng.uniform(0.0, 1.0, n), rng.uniform(1.0, 3.0, n), rng.uniform(0.0, 1.0, n),
        rng.uniform(size=n) < 0.7,
    )  # fmt: skip
    args = (pos, nrm, surface, view, emissive, lights)
    pairs = sums = None
    if case == "all_lit":
        vis = None
    elif case.startswith("pairs"):
        pairs = _pairs(rng, pos, nrm, lights, sort=False)
        if case == "pairs_unweighted":
            pairs = tuple(pairs[:4])
    elif case == "sums":
        sums = rng.uniform(0.0, 1.0, (n, 4)).astype(np.float32)
        pairs = _pairs(rng, pos, nrm, lights, sort=True)
        vis = vis[:, :2]
    want = ref.shade_chunk(*args, vis, pairs, sums)
    got = shading.shade_local(*args, vis, pairs, lit_sums=sums)
    assert got.dtype == np.float32 and got.shape == (n, 3)
    assert float(want.max()) > 0.5  # the lights do reach the points
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)


def test_shade_kernel_constant_emissive_and_no_lights():
    rng = np.random.default_rng(2)
    pos, nrm, view, albedo = _points(rng, 50, 3.0)
    for lights in (Lights(), Lights(dome=DomeLight(color=np.array([0.3, 0.2, 0.1])))):
        em = np.array([0.1, 0.0, 0.5], np.float32)
        vis = np.ones((50, 0), np.float32)
        want = ref.shade_chunk(pos, nrm, albedo, view, em, lights, vis)
        got = shading.shade_local(pos, nrm, albedo, view, em, lights, vis)
        np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)


def test_shade_kernel_extreme_inputs_stay_finite():
    """Points on a light, at 1e30 m, a light of huge radiance and range, zero normals:
    finite, and equal to the reference where the reference is finite (a 1e30 light reaches
    7e15 m: its 1/d² light stays within float32)."""
    pos = np.array([[0.0, 0.0, 0.0], [1e30, -1e30, 0.0], [1e-300, 0.0, 0.0], [3.0, 0.0, 0.0]])
    nrm = np.array([[0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 0, 0]], np.float32)
    view = np.tile(np.array([0.0, -1.0, 0.0], np.float32), (4, 1))
    albedo = np.ones((4, 3), np.float32)
    lights = Lights(
        distant=[DistantLight(np.array([0.0, 1e-300, 0.0]), np.ones(3))],
        local=[LocalLight(np.zeros(3), np.ones(3)), LocalLight(np.ones(3), np.full(3, 1e30))],
    )
    vis = np.ones((4, 3), np.float32)
    got = shading.shade_local(pos, nrm, albedo, view, np.zeros(3), lights, vis)
    assert np.all(np.isfinite(got))
    want = ref.shade_chunk(pos, nrm, albedo, view, np.zeros(3), lights, vis)
    ok = np.all(np.isfinite(want), axis=1)
    np.testing.assert_allclose(got[ok], want[ok], rtol=RTOL, atol=ATOL)


def test_environment_kernel_matches_numpy_reference():
    """Lat-long lookups of random directions (any length), the poles and the seam, with
    and without a rotated dome. Directions without one (zero, NaN, Inf, ~1e-40) look up
    the pole: in a rotated dome the reference's pole comes out of a rotation and back,
    its longitude (meaningless there) of rounding, so there the test only asks for
    one finite value for all of them."""
    rng = np.random.default_rng(5)
    tex = rng.uniform(0.0, 4.0, (16, 32, 3)).astype(np.float32)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    )
    dirs = rng.normal(size=(3000, 3)) * rng.uniform(1e-3, 1e3, (3000, 1))
    valid = np.array(
        [[1e30, 1e30, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1], [-1e-3, 0, -1]]  # poles, seam
    )
    none = np.array([[0, 0, 0], [np.nan, 1, 0], [np.inf, 0, 0], [0, 1e-40, 0]])
    dirs = np.concatenate([dirs, valid, none])
    some = slice(0, -len(none))
    for dome in (
        None,
        DomeLight(color=np.array([0.5, 1.0, 2.0])),
        DomeLight(color=np.array([0.5, 1.0, 2.0]), texture=tex),
        DomeLight(color=np.ones(3), texture=tex, world_from_light=rot),
    ):
        lights = Lights(dome=dome)
        rotated = dome is not None and not np.array_equal(dome.world_from_light, np.eye(3))
        for d in (dirs, dirs.astype(np.float32)):
            got = shading.environment_radiance(lights, d)
            want = ref.environment_radiance(lights, d)
            assert got.dtype == np.float32 and np.all(np.isfinite(got))
            rows = some if rotated else slice(None)
            np.testing.assert_allclose(got[rows], want[rows], rtol=RTOL, atol=ATOL)
            assert np.all(got[-len(none) :] == got[-1])


def test_window_and_cone_kernels_match_numpy_reference():
    d = np.concatenate([np.linspace(0.0, 12.0, 500), [1e200, np.inf]])
    for r in (0.0, -1.0, 1e-3, 5.0, 1e150):
        with np.errstate(over="ignore"):  # the reference squares 1e200
            want = ref.range_window(d, r)
        np.testing.assert_allclose(shading.range_window(d, r), want, atol=1e-12)
    rng = np.random.default_rng(9)
    emission = rng.normal(size=(4000, 3))
    emission /= np.linalg.norm(emission, axis=1, keepdims=True)
    for angle, soft, focus in [
        (180, 0, 0),
        (30, 0, 0),
        (30, 0.5, 0),
        (90, 1, 3),
        (180, 0, 5),
        (0, 0, 0),
    ]:
        light = LocalLight(
            np.zeros(3), np.ones(3), axis=np.array([0.0, 0.0, -1.0]),
            cone_angle=float(angle), cone_softness=float(soft), focus=float(focus),
        )  # fmt: skip
        got = shading.cone_falloff(light, emission)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, ref.cone_falloff(light, emission), rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("dome", ["none", "texture", "hidden"])
def test_base_image_kernel_matches_numpy_reference(dome):
    """The raster frame (environment behind uncovered pixels, mirrored in reflectors)
    against the numpy reference, on a random G-buffer."""
    from phrt_usd.engine import compositing
    from phrt_usd.model.frame import GBuffer
    from phrt_usd.model.scene import MaterialTable, Scene

    rng = np.random.default_rng(4)
    h, w = 24, 32
    element = rng.integers(-1, 4, (h, w)).astype(np.int32)
    nrm = rng.normal(size=(h, w, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=2, keepdims=True)).astype(np.float32)
    view = rng.normal(size=(h, w, 3))
    view = (view / np.linalg.norm(view, axis=2, keepdims=True)).astype(np.float32)
    gb = GBuffer(
        element, element, np.ones((h, w), np.float32), rng.normal(size=(h, w, 3)), nrm,
        np.full((h, w, 3), 0.5, np.float32), view,
    )  # fmt: skip
    tex = rng.uniform(0.0, 3.0, (8, 16, 3)).astype(np.float32)
    lights = Lights(
        dome=None
        if dome == "none"
        else DomeLight(color=np.ones(3), texture=tex, camera_visible=dome != "hidden")
    )
    scene = Scene.__new__(Scene)
    scene.lights = lights
    empty = np.zeros(0, np.float32)
    scene.materials = MaterialTable(np.zeros((0, 3), np.float32), empty, empty, empty, empty,
                                    np.zeros((0, 3), np.float32))  # no material: no glossy
    local = np.where(element[..., None] >= 0, rng.uniform(0, 2, (h, w, 3)), 0).astype(np.float32)
    f = np.array([0.0, 0.5, 1.0, 0.0, 0.0], np.float32)[element]  # F of ids 0..3, then -1
    got = compositing.base_image(gb, scene, local, f)
    assert got.dtype == np.float32 and got.shape == (h, w, 3)
    np.testing.assert_allclose(got, ref.base_image(gb, scene, local, f), rtol=RTOL, atol=ATOL)


def test_pair_directions_kernel_matches_numpy_reference():
    rng = np.random.default_rng(8)
    pos, *_ = _points(rng, 300, 5.0)
    lights = _lights(shaped=False)
    pos[0] = lights.local[1].position  # a point on a light: the clamped distance
    point = rng.integers(0, 300, 900)
    point[0] = 0
    light = rng.integers(0, 3, 900)
    light[0] = 1
    got = shading.pair_directions(lights, pos, point, light)
    want = ref.pair_directions(lights, pos, point, light)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        # Equal up to the rounding of the sum of squares (numpy's einsum sums with SIMD).
        np.testing.assert_allclose(g, w, rtol=1e-12 if g.dtype == np.float64 else 1e-7)
    assert [a.shape for a in shading.pair_directions(lights, pos, point[:0], light[:0])] == [
        (0, 3),
        (0,),
    ]


def test_one_pass_environment_matches_the_numpy_angles(monkeypatch):
    """Small environment batches run as one compiled pass (scalar libm angles): the
    texels of the numpy route, for float32 and float64 directions, poles and the seam
    included, a rotated dome."""
    rng = np.random.default_rng(13)
    tex = rng.uniform(0.0, 2.0, (32, 64, 3)).astype(np.float32)
    rot = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    lights = Lights(dome=DomeLight(color=np.array([0.5, 1.0, 2.0]), texture=tex,
                                   world_from_light=rot))  # fmt: skip
    edge = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1e-3, 1, 0], [0, 0, 0], [np.nan, 1, 0]]
    dirs = np.concatenate([rng.normal(size=(shading.ENV_ONE_PASS_MAX - len(edge), 3)), edge])
    for d in (dirs, dirs.astype(np.float32)):
        one_pass = shading.environment_radiance(lights, d)
        monkeypatch.setattr(shading, "ENV_ONE_PASS_MAX", -1)
        numpy_angles = shading.environment_radiance(lights, d)
        monkeypatch.undo()
        assert one_pass.dtype == np.float32 and np.all(np.isfinite(one_pass))
        np.testing.assert_allclose(one_pass, numpy_angles, rtol=1e-6, atol=1e-6)


def test_threaded_environment_matches_one_chunk(monkeypatch):
    """Large environment batches are split over the shading pool: same texels."""
    rng = np.random.default_rng(12)
    tex = rng.uniform(0.0, 2.0, (32, 64, 3)).astype(np.float32)
    lights = Lights(dome=DomeLight(color=np.ones(3), texture=tex))
    dirs = rng.normal(size=(3 * shading.SHADE_MIN_THREADED_POINTS + 7, 3))
    monkeypatch.setattr(shading, "SHADE_THREADS", 3)
    threaded = shading.environment_radiance(lights, dirs)
    monkeypatch.setattr(shading, "SHADE_THREADS", 1)
    np.testing.assert_array_equal(threaded, shading.environment_radiance(lights, dirs))
