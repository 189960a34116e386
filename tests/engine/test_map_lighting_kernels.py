"""The compiled bookkeeping of ``render.raster.map_lighting`` (which pairs the shadow
maps left undecided, which of them an exact test found lit) against the numpy code it
replaced (kept here as the reference)."""

from __future__ import annotations

import numpy as np
import pytest

from phrt_usd.engine.raster.light_pass import LOOKUP_LIGHTS_PER_PASS
from phrt_usd.engine.shade_kernels import lights_reaching, lit_local_pairs, undecided_rows
from phrt_usd.model.preview_surface import fallback_surface


def _reference_undecided(bits, n_local, active, gpu_distant, distant_unsure):
    """The numpy bookkeeping (all lights looked up), with the looked-up lights'
    columns then placed at ``active``."""
    if gpu_distant:
        shifts = 16 + np.arange(distant_unsure.shape[1], dtype=np.uint32)
        distant_unsure = (bits[:, :1] >> shifts) & 1 > 0
    unsure_rows = bits.any(axis=1)
    if distant_unsure.shape[1]:
        unsure_rows |= distant_unsure.any(axis=1)
    rows = np.flatnonzero(unsure_rows)
    looked_up = np.zeros((len(rows), len(active)), dtype=bool)
    for p, start in enumerate(range(0, len(active), LOOKUP_LIGHTS_PER_PASS)):
        count = min(LOOKUP_LIGHTS_PER_PASS, len(active) - start)
        shifts = np.arange(count, dtype=np.uint32)
        looked_up[:, start : start + count] = (bits[rows, p, None] >> shifts) & 1 > 0
    local_unsure = np.zeros((len(rows), n_local), dtype=bool)
    local_unsure[:, active] = looked_up
    return rows, local_unsure, distant_unsure


@pytest.mark.parametrize(
    ("n_local", "n_distant", "gpu_distant", "subset"),
    [
        (13, 0, False, False),
        (13, 0, False, True),
        (20, 2, True, False),
        (20, 2, True, True),
        (0, 1, True, False),
        (5, 3, False, False),
        (40, 0, False, True),
    ],
)
def test_undecided_matches_numpy_reference(n_local, n_distant, gpu_distant, subset):
    rng = np.random.default_rng(n_local + n_distant)
    n = 3000
    active = np.arange(n_local)
    if subset:  # the lights that reach the points, as light_terms looks them up
        active = np.flatnonzero(rng.uniform(size=n_local) < 0.6)
    passes = max(-(-len(active) // LOOKUP_LIGHTS_PER_PASS), 1 if gpu_distant else 0)
    bits = np.zeros((n, passes), np.uint32)
    for p in range(passes):
        count = min(LOOKUP_LIGHTS_PER_PASS, len(active) - p * LOOKUP_LIGHTS_PER_PASS)
        for j in range(max(count, 0)):
            bits[:, p] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << j
    if gpu_distant:
        for k in range(n_distant):
            bits[:, 0] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << (16 + k)
    numpy_unsure = rng.uniform(size=(n, n_distant)) < (0.0 if gpu_distant else 0.05)
    got_distant = numpy_unsure.copy()
    rows, local = undecided_rows(
        bits, n_local, active, LOOKUP_LIGHTS_PER_PASS, gpu_distant, got_distant
    )
    want_rows, want_local, want_distant = _reference_undecided(
        bits, n_local, active, gpu_distant, numpy_unsure
    )
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(local, want_local)
    np.testing.assert_array_equal(got_distant, want_distant)


def test_lit_local_pairs_match_numpy_reference():
    rng = np.random.default_rng(3)
    m, lights = 500, 7
    rows = np.sort(rng.choice(10_000, m, replace=False))
    unsure = rng.uniform(size=(m, lights)) < 0.3
    exact = np.where(rng.uniform(size=(m, lights)) < 0.5, 0.0, 1.0).astype(np.float32)
    point, light, weight = lit_local_pairs(rows, unsure, exact)
    at, want_light = np.nonzero(unsure)
    want_weight = exact[at, want_light]
    lit = want_weight > 0.0
    np.testing.assert_array_equal(point, rows[at][lit])
    np.testing.assert_array_equal(light, want_light[lit])
    np.testing.assert_array_equal(weight, want_weight[lit])


def test_reaching_keeps_every_light_that_reaches_a_point():
    """A LocalLight is left out of the lookup only when no point is within its range:
    the box test never drops a light a point needs (brute force over the points)."""
    rng = np.random.default_rng(4)
    pos = rng.uniform(-5.0, 5.0, (2000, 3)) * [1.0, 0.2, 1.0]
    centres = rng.uniform(-20.0, 20.0, (300, 3))
    ranges = rng.uniform(0.0, 10.0, 300)
    ranges[:5] = 0.0  # black lights reach nothing
    got = lights_reaching(pos, centres, ranges)
    d2 = ((pos[:, None, :] - centres[None]) ** 2).sum(-1)
    needed = (d2 < ranges**2).any(axis=0)
    assert np.all(got[needed]) and not np.any(got[:5])
    assert 0 < needed.sum() < got.sum() < len(got)  # the box keeps a few more, not all
    assert not np.any(lights_reaching(pos[:0], centres, ranges))


def test_lights_out_of_reach_are_left_out_and_shading_is_unchanged(monkeypatch):
    """A LocalLight whose range reaches none of the points is not looked up: the GPU
    light terms with it (and with lights that do reach) shade exactly as the (n, L)
    visibility matrix in numpy."""
    from scenes import box, look_at, parts_scene

    from phrt_usd.engine import shading
    from phrt_usd.engine.raster import map_lighting
    from phrt_usd.engine.raster.rasterizer import Rasterizer
    from phrt_usd.model.scene import Lights, LocalLight

    lights = Lights(
        local=[
            LocalLight(np.array([500.0, 3.0, 0.0]), np.full(3, 5.0)),  # range ~16 m
            LocalLight(np.array([0.6, 3.5, 0.4]), np.array([20.0, 15.0, 10.0])),
            LocalLight(np.array([-400.0, 1.0, 1.5]), np.full(3, 5.0)),
        ]
    )
    parts = [
        {"mesh": box((10.0, 0.2, 10.0), (0.0, -0.1, 0.0))},
        {"mesh": box((2.0, 0.1, 1.5), (0.0, 1.5, 0.0)), "albedo": (0.8, 0.2, 0.2)},
    ]
    scene = parts_scene(parts, lights=lights)
    looked_up = []
    lookup = map_lighting.LightPass.lookup

    def spy(self, *args, **kwargs):
        looked_up.append(kwargs.get("active"))
        return lookup(self, *args, **kwargs)

    monkeypatch.setattr(map_lighting.LightPass, "lookup", spy)
    with Rasterizer(scene, 160, 120) as r:
        g = r.render(look_at(np.array([0.0, 7.0, 8.0]), np.zeros(3)))
        cov = g.covered
        pos, nrm, albedo, view = g.position[cov], g.normal[cov], g.albedo[cov], g.view_dir[cov]
        vis = r.shadow_visibility(pos, nrm)
        surface = fallback_surface(albedo)
        terms = r.light_terms(pos, nrm, -view, surface=surface)
    assert [list(a) for a in looked_up if a is not None] == [[1]]
    expected = shading.shade_local(pos, nrm, surface, view, np.zeros(3), lights, vis)
    got = shading.shade_local(
        pos, nrm, surface, view, np.zeros(3), lights, terms.distant_visibility,
        local_pairs=terms.local_pairs, lit_sums=terms.lit_sums,
    )  # fmt: skip
    assert float(got.max()) > 0.1
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)
