"""The frame's per-pixel figures (``phrt_usd.engine.frame_pixels``) against the numpy
code they replaced (kept here as the reference)."""

from __future__ import annotations

import numpy as np

from phrt_usd.engine.frame_pixels import clipped_share, screen_boxes


def _reference_boxes(element_id, reflector_ids, n):
    """The numpy screen boxes (occupancy per row and column, argmax of the first)."""
    boxes = np.full((n, 4), np.nan)
    refl = np.asarray(reflector_ids, dtype=np.int64)
    if len(refl) == 0:
        return boxes
    index = np.full(n + 1, -1, dtype=np.int64)  # id -1, the background, maps to -1
    index[refl] = np.arange(len(refl))
    k = index[element_id]
    rows, cols = np.nonzero(k >= 0)
    if len(rows) == 0:
        return boxes
    k = k[rows, cols]
    h, w = element_id.shape
    in_row = np.zeros((h, len(refl)), dtype=bool)
    in_row[rows, k] = True
    in_col = np.zeros((w, len(refl)), dtype=bool)
    in_col[cols, k] = True
    seen = in_row.any(axis=0)
    boxes[refl[seen]] = np.stack(
        [
            in_col.argmax(axis=0),
            in_row.argmax(axis=0),
            w - 1 - in_col[::-1].argmax(axis=0),
            h - 1 - in_row[::-1].argmax(axis=0),
        ],
        axis=1,
    )[seen]
    return boxes


def _reference_share(image, covered, step, level):
    covered = covered[::step, ::step]
    if not covered.any():
        return 0.0
    peak = image[::step, ::step][covered].max(axis=1)
    return float(np.mean(peak > level))


def test_screen_boxes_match_numpy_reference():
    rng = np.random.default_rng(1)
    h, w, n = 37, 53, 9
    ids = rng.integers(-1, n, (h, w)).astype(np.int32)
    ids[ids == 4] = 3  # element 4 is nowhere on screen
    ids[:10] = np.where(ids[:10] == 6, 0, ids[:10])  # 6 only in the lower rows
    for refl in ([], [4], [0, 2, 4, 6, 8], list(range(n))):
        got = screen_boxes(ids, np.array(refl, np.int64), n)
        np.testing.assert_array_equal(got, _reference_boxes(ids, refl, n))
    assert np.all(np.isnan(screen_boxes(np.full((4, 4), -1, np.int32), np.arange(3), 3)))


def test_clipped_share_matches_numpy_reference():
    rng = np.random.default_rng(2)
    image = rng.uniform(0.0, 2.0, (31, 45, 3)).astype(np.float32)
    image[3, 4] = [np.nan, 5.0, 5.0]  # NaN peak: not clipped, as numpy's max has it
    covered = rng.uniform(size=(31, 45)) > 0.3
    for step in (1, 2, 3):
        for level in (0.5, 1.0, 1.9):
            got = clipped_share(image, covered, step, level)
            assert got == _reference_share(image, covered, step, level)
    assert clipped_share(image, np.zeros((31, 45), bool), 2, 1.0) == 0.0
