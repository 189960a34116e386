"""The compiled bookkeeping of ``render.raster.map_lighting`` (which pairs the shadow
maps left undecided, which of them an exact test found lit) against the numpy code it
replaced (kept here as the reference)."""

from __future__ import annotations

import numpy as np
import pytest

from phrt_usd.engine.raster.light_pass import LOOKUP_LIGHTS_PER_PASS
from phrt_usd.engine.shade_kernels import lit_local_pairs, tile_lights, undecided_rows
from phrt_usd.model.preview_surface import fallback_surface


def _reference_undecided(bits, n_local, slots, tile_of_row, gpu_distant, distant_unsure):
    """The numpy bookkeeping: bit j of pass p of row i is LocalLight
    ``slots[tile_of_row[i], 16 p + j]``."""
    if gpu_distant:
        shifts = 16 + np.arange(distant_unsure.shape[1], dtype=np.uint32)
        distant_unsure = (bits[:, :1] >> shifts) & 1 > 0
    unsure_rows = bits.any(axis=1)
    if distant_unsure.shape[1]:
        unsure_rows |= distant_unsure.any(axis=1)
    rows = np.flatnonzero(unsure_rows)
    local_unsure = np.zeros((len(rows), n_local), dtype=bool)
    for r, i in enumerate(rows):
        for p in range(bits.shape[1]):
            for j in range(LOOKUP_LIGHTS_PER_PASS):
                s = p * LOOKUP_LIGHTS_PER_PASS + j
                if s < slots.shape[1] and (bits[i, p] >> j) & 1 and slots[tile_of_row[i], s] >= 0:
                    local_unsure[r, slots[tile_of_row[i], s]] = True
    return rows, local_unsure, distant_unsure


@pytest.mark.parametrize(
    ("n_local", "n_distant", "gpu_distant", "subset", "tiled"),
    [
        (13, 0, False, False, False),
        (13, 0, False, True, False),
        (20, 2, True, False, False),
        (20, 2, True, True, True),
        (0, 1, True, False, False),
        (5, 3, False, False, True),
        (40, 0, False, True, True),
    ],
)
def test_undecided_matches_numpy_reference(n_local, n_distant, gpu_distant, subset, tiled):
    rng = np.random.default_rng(n_local + n_distant)
    n, tile = 3000, 64 if tiled else 1 << 30
    n_tiles = -(-n // tile)
    slots = np.full((n_tiles, n_local), -1, np.int64)
    for t in range(n_tiles):  # each tile's lights: all, or those that reach it
        keep = np.arange(n_local)
        if subset:
            keep = np.flatnonzero(rng.uniform(size=n_local) < 0.6)
        slots[t, : len(keep)] = keep
    most = int((slots >= 0).sum(axis=1).max()) if n_local else 0
    slots = np.ascontiguousarray(slots[:, :most])
    passes = max(-(-most // LOOKUP_LIGHTS_PER_PASS), 1 if gpu_distant else 0)
    bits = np.zeros((n, passes), np.uint32)
    for p in range(passes):
        count = min(LOOKUP_LIGHTS_PER_PASS, most - p * LOOKUP_LIGHTS_PER_PASS)
        for j in range(max(count, 0)):
            bits[:, p] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << j
    if gpu_distant:
        for k in range(n_distant):
            bits[:, 0] |= (rng.uniform(size=n) < 0.05).astype(np.uint32) << (16 + k)
    numpy_unsure = rng.uniform(size=(n, n_distant)) < (0.0 if gpu_distant else 0.05)
    got_distant = numpy_unsure.copy()
    tile_of_row = (np.arange(n) // tile).astype(np.int32)
    rows, local = undecided_rows(
        bits, n_local, slots, LOOKUP_LIGHTS_PER_PASS, gpu_distant, got_distant, tile_of_row
    )
    want_rows, want_local, want_distant = _reference_undecided(
        bits, n_local, slots, tile_of_row, gpu_distant, numpy_unsure
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


def test_tile_lists_keep_every_light_that_reaches_a_point():
    """A LocalLight is left out of a tile's list only when no point of the tile is
    within its range (plus the margin): the box test never drops a light a point needs
    (brute force over each tile's points), and drops most of the far ones. Tiles are
    runs of at most 64 consecutive points, cut where the points jump (a row's end)."""
    rng = np.random.default_rng(4)
    width, tile, n = 150, 64, 150 * 150
    col, row = np.arange(n) % width, np.arange(n) // width
    # Points laid out as an image of a floor: consecutive points are near, but for the
    # jump from one row's end to the next row's start.
    pos = np.stack([col * 0.1, rng.uniform(0.0, 0.01, n), row * 0.1], axis=1)
    origin = np.array([3.0, 0.0, -2.0])
    centres = rng.uniform(-5.0, 25.0, (300, 3)) * [1.0, 0.1, 1.0]
    ranges = rng.uniform(0.0, 4.0, 300)
    ranges[:5] = 0.0  # black lights reach nothing
    point_tile = np.empty(n, np.int32)
    slots, counts = tile_lights(pos + origin, origin, tile, 4.0, centres, ranges, 1e-3,
                                point_tile)  # fmt: skip
    assert np.all(np.diff(point_tile) >= 0) and point_tile[-1] == len(slots) - 1
    sizes = np.bincount(point_tile)
    assert sizes.max() <= tile
    # A row of 150 points: tiles of 64, 64 and 22, none across two rows.
    assert len(slots) == 3 * 150 and np.all(np.diff(row[np.r_[0, np.cumsum(sizes)[:-1]]]) >= 0)
    assert all(len(set(row[point_tile == t])) == 1 for t in range(0, len(slots), 37))
    kept_total = 0
    for t in range(len(slots)):
        kept = set(slots[t, : counts[t]].tolist())
        assert np.all(slots[t, counts[t] :] == -1)
        assert list(slots[t, : counts[t]]) == sorted(kept)  # increasing: same sums
        d2 = ((pos[point_tile == t, None, :] - centres[None]) ** 2).sum(-1)
        needed = set(np.flatnonzero((d2 < ranges**2).any(axis=0)).tolist())
        assert needed <= kept and not kept & set(range(5))
        kept_total += len(kept)
    assert kept_total < 0.2 * len(slots) * len(centres)  # most lights reach no tile
    none = tile_lights(pos[:0], origin, tile, 4.0, centres, ranges, 1e-3, point_tile[:0])
    assert len(none[0]) == 0


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
        result = lookup(self, *args, **kwargs)
        if isinstance(result, tuple):  # the shading lookup: its tiles' lights
            slots = result[2].slots
            looked_up.append(set(slots[slots >= 0].tolist()))
        return result

    monkeypatch.setattr(map_lighting.LightPass, "lookup", spy)
    with Rasterizer(scene, 160, 120) as r:
        g = r.render(look_at(np.array([0.0, 7.0, 8.0]), np.zeros(3)))
        cov = g.covered
        pos, nrm, albedo, view = g.position[cov], g.normal[cov], g.albedo[cov], g.view_dir[cov]
        vis = r.shadow_visibility(pos, nrm)
        surface = fallback_surface(albedo)
        terms = r.light_terms(pos, nrm, -view, surface=surface)
    assert looked_up == [{1}]
    expected = shading.shade_local(pos, nrm, surface, view, np.zeros(3), lights, vis)
    got = shading.shade_local(
        pos, nrm, surface, view, np.zeros(3), lights, terms.distant_visibility,
        local_pairs=terms.local_pairs, lit_sums=terms.lit_sums,
    )  # fmt: skip
    assert float(got.max()) > 0.1
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)
