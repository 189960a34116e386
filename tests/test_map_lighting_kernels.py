"""The compiled bookkeeping of ``render.raster.map_lighting`` (which pairs the shadow
maps left undecided, which of them an exact test found lit) against the numpy code it
replaced (kept here as the reference)."""

from __future__ import annotations

import numpy as np
import pytest

from phrt_usd.render.raster.light_pass import LOOKUP_LIGHTS_PER_PASS
from phrt_usd.render.shade_kernels import lit_local_pairs, undecided_rows


def _reference_undecided(bits, n_local, gpu_distant, distant_unsure):
    if gpu_distant:
        shifts = 16 + np.arange(distant_unsure.shape[1], dtype=np.uint32)
        distant_unsure = (bits[:, :1] >> shifts) & 1 > 0
    unsure_rows = bits.any(axis=1)
    if distant_unsure.shape[1]:
        unsure_rows |= distant_unsure.any(axis=1)
    rows = np.flatnonzero(unsure_rows)
    local_unsure = np.zeros((len(rows), n_local), dtype=bool)
    for p, start in enumerate(range(0, n_local, LOOKUP_LIGHTS_PER_PASS)):
        count = min(LOOKUP_LIGHTS_PER_PASS, n_local - start)
        shifts = np.arange(count, dtype=np.uint32)
        local_unsure[:, start : start + count] = (bits[rows, p, None] >> shifts) & 1 > 0
    return rows, local_unsure, distant_unsure


@pytest.mark.parametrize(
    ("n_local", "n_distant", "gpu_distant"),
    [(13, 0, False), (20, 2, True), (0, 1, True), (5, 3, False), (40, 0, False)],
)
def test_undecided_matches_numpy_reference(n_local, n_distant, gpu_distant):
    rng = np.random.default_rng(n_local + n_distant)
    n = 3000
    passes = max(-(-n_local // LOOKUP_LIGHTS_PER_PASS), 1 if gpu_distant else 0)
    bits = np.zeros((n, passes), np.uint32)
    for p in range(passes):
        count = min(LOOKUP_LIGHTS_PER_PASS, n_local - p * LOOKUP_LIGHTS_PER_PASS)
        for j in range(max(count, 0)):
            bits[:, p] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << j
    if gpu_distant:
        for k in range(n_distant):
            bits[:, 0] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << (16 + k)
    numpy_unsure = rng.uniform(size=(n, n_distant)) < (0.0 if gpu_distant else 0.05)
    got_distant = numpy_unsure.copy()
    rows, local = undecided_rows(bits, n_local, LOOKUP_LIGHTS_PER_PASS, gpu_distant, got_distant)
    want_rows, want_local, want_distant = _reference_undecided(
        bits, n_local, gpu_distant, numpy_unsure
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
