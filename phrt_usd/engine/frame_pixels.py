"""Figures of a frame's pixels the renderer needs every frame, as compiled one-pass
kernels (``shade_kernels``): the screen box of every reflector (``screen_boxes``, for
``FrameView.screen_boxes``) and the share of clipped pixels (``clipped_share``, the
clipping warning of ``FrameRenderer``).

Images are (H, W, ...) arrays, row 0 at the top; element ids as ``GBuffer.element_id``
(-1: background).
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels


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
    found = _shade().screen_box_bounds(np.ascontiguousarray(element_id), index, len(refl))
    seen = found[:, 2] >= 0
    boxes[refl[seen]] = found[seen]
    return boxes


def clipped_share(image: np.ndarray, covered: np.ndarray, step: int, level: float) -> float:
    """Share in [0, 1] of the covered pixels of every ``step``-th row and column of
    ``image`` (H, W, 3) whose brightest channel exceeds ``level`` (a pixel with a NaN
    channel does not: its brightest channel is NaN); 0 when none is covered.
    ``covered`` (H, W) bool."""
    covered_n, clipped_n = _shade().clipped_counts(image, covered, step, level)
    return clipped_n / covered_n if covered_n else 0.0


def _shade():
    """The compiled kernels (``shade_kernels``), taken on first use."""
    return kernels.load("phrt_usd.engine.shade_kernels")
