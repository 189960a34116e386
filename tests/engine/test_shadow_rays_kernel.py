"""``ShadowRays.cast`` (rays chosen and built in one compiled pass) against the numpy
set-up it replaced (``tests/shadow_rays_reference.py``), on a scene with DistantLights and
LocalLights, random points and normals, with and without a wanted-pairs mask.

The two test facing and range with differently rounded arithmetic (float64 here, the
reference partly float32), so a pair within float32 rounding of n·l = 0 or of a light's
range may be decided differently: such pairs carry no light (n·l ~ 0, window ~ 0) and
are excluded from the comparison.
"""

from __future__ import annotations

import numpy as np
import pytest
import shadow_rays_reference as ref
from scenes import box_between, parts_scene

from phrt_usd.engine import shading
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model.scene import DistantLight, Lights, LocalLight


def _setup():
    lights = Lights(
        distant=[DistantLight(np.array([0.3, 1.0, 0.2]), np.ones(3))],
        local=[
            LocalLight(np.array([1.0, 2.0, 0.0]), np.full(3, 0.5)),  # range 5 m
            LocalLight(np.array([-2.0, 1.5, 1.0]), np.full(3, 2.0)),
        ],
    )
    parts = [
        dict(mesh=box_between((-10, -0.2, -10), (10, 0.0, 10))),  # the floor
        dict(mesh=box_between((-1, 0.5, -1), (0.5, 1.0, 0.5))),
        dict(mesh=box_between((1.5, 0.0, 1.5), (2.0, 3.0, 2.0))),
    ]
    tracer = Tracer(parts_scene(parts, lights), threads=1)
    rng = np.random.default_rng(6)
    n = 4000
    pos = np.column_stack([rng.uniform(-6, 6, n), rng.uniform(-0.5, 3.5, n), rng.uniform(-6, 6, n)])
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rel = tracer.bvh.boundary.relative(pos)
    return tracer, rel, nrm, tracer._relative_lights()


def _marginal(rel, nrm, lights):
    """(n, L) bool: pairs within float32 rounding of n·l = 0 or of the light's range."""
    ranges = shading.light_ranges(lights)[len(lights.distant) :]
    cols = [np.abs(nrm @ li.direction) < 1e-5 for li in lights.distant]
    for li, r in zip(lights.local, ranges, strict=True):
        to = li.position - rel
        d = np.linalg.norm(to, axis=1)
        cols.append(
            (np.abs(np.einsum("ij,ij->i", nrm, to)) < 1e-5 * d) | (np.abs(d - r) < 1e-5 * r)
        )
    return np.column_stack(cols)


@pytest.mark.parametrize("masked", [False, True])
def test_shadow_ray_kernel_matches_numpy_reference(masked):
    tracer, rel, nrm, lights = _setup()
    shadows = tracer._shadows
    n_lights = len(lights.distant) + len(lights.local)
    pairs = None
    if masked:
        pairs = np.random.default_rng(1).uniform(size=(len(rel), n_lights)) < 0.4
    vis, rays, local = shadows.cast(rel, nrm, nrm, lights, pairs)
    want_vis, want_rays, want_local = ref.cast(shadows, rel, nrm, nrm, lights, pairs)
    ok = ~_marginal(rel, nrm, lights)
    assert 0.05 < float(want_vis[ok].mean()) < 0.8  # lit and shadowed pairs both tested
    np.testing.assert_array_equal(vis[ok], want_vis[ok])
    clean = ok.all(axis=1)
    np.testing.assert_array_equal(rays[clean], want_rays[clean])
    # The lit LocalLight pairs: same pairs, sorted by point, same directions and distances.
    key = local.point * 8 + local.light
    want_key = want_local.point * 8 + want_local.light
    assert np.all(np.diff(local.point) >= 0)
    keep = clean[local.point]
    want_keep = clean[want_local.point]
    np.testing.assert_array_equal(np.sort(key[keep]), np.sort(want_key[want_keep]))
    order, want_order = np.argsort(key[keep]), np.argsort(want_key[want_keep])
    np.testing.assert_allclose(
        local.l_dir[keep][order], want_local.l_dir[want_keep][want_order], atol=1e-6
    )
    np.testing.assert_allclose(
        local.dist[keep][order], want_local.dist[want_keep][want_order], rtol=1e-6
    )
