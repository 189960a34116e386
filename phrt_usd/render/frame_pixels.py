"""Figures of a frame's pixels the renderer needs every frame, as compiled one-pass
kernels (numba, ``nogil``): the screen box of every reflector (``screen_boxes``, for
``FrameView.screen_boxes``) and the share of clipped pixels (``clipped_share``, the
clipping warning of ``FrameRenderer``).

Images are (H, W, ...) arrays, row 0 at the top; element ids as ``GBuffer.element_id``
(-1: background).
"""

from __future__ import annotations

import numba
import numpy as np


def screen_boxes(element_id: np.ndarray, reflector_ids: np.ndarray, n_elements: int) -> np.ndarray:
    """(E, 4) float64 pixel bounds (col_min, row_min, col_max, row_max) of the visible
    pixels of every element of ``reflector_ids`` (R,) int, NaN for the other elements
    and for reflectors without pixels; E = ``n_elements``, ``element_id`` (H, W) int."""
    boxes = np.full((n_elements, 4), np.nan)
    refl = np.asarray(reflector_ids, dtype=np.int64)
    if len(refl) == 0:
        return boxes
    index = np.full(n_elements, -1, dtype=np.int64)  # reflector index per element id
    index[refl] = np.arange(len(refl))
    found = _boxes_kernel(np.ascontiguousarray(element_id), index, len(refl))
    seen = found[:, 2] >= 0
    boxes[refl[seen]] = found[seen]
    return boxes


@numba.njit(nogil=True, cache=True)
def _boxes_kernel(element_id, index, n_reflectors):  # pragma: no cover - compiled
    """(R, 4) int64 (col_min, row_min, col_max, row_max) of the pixels whose element has
    reflector index ``index[id]`` >= 0; col_max -1 for a reflector without pixels."""
    h, w = element_id.shape
    found = np.empty((n_reflectors, 4), np.int64)
    found[:, 0], found[:, 1], found[:, 2], found[:, 3] = w, h, -1, -1
    for row in range(h):
        for col in range(w):
            e = element_id[row, col]
            if e < 0:
                continue
            k = index[e]
            if k < 0:
                continue
            found[k, 0] = min(found[k, 0], col)
            found[k, 1] = min(found[k, 1], row)
            found[k, 2] = max(found[k, 2], col)
            found[k, 3] = max(found[k, 3], row)
    return found


def clipped_share(image: np.ndarray, covered: np.ndarray, step: int, level: float) -> float:
    """Share in [0, 1] of the covered pixels of every ``step``-th row and column of
    ``image`` (H, W, 3) whose brightest channel exceeds ``level`` (a pixel with a NaN
    channel does not: its brightest channel is NaN); 0 when none is covered.
    ``covered`` (H, W) bool."""
    covered_n, clipped_n = _clipped_kernel(image, covered, step, level)
    return clipped_n / covered_n if covered_n else 0.0


@numba.njit(nogil=True, cache=True)
def _clipped_kernel(image, covered, step, level):  # pragma: no cover - compiled
    """(covered, clipped) pixel counts of ``clipped_share``."""
    covered_n = clipped_n = 0
    for row in range(0, image.shape[0], step):
        for col in range(0, image.shape[1], step):
            if not covered[row, col]:
                continue
            covered_n += 1
            r, g, b = image[row, col, 0], image[row, col, 1], image[row, col, 2]
            if r != r or g != g or b != b:  # NaN: numpy's max would be NaN, not > level
                continue
            if max(r, g, b) > level:
                clipped_n += 1
    return covered_n, clipped_n
