"""How each pixel of a frame was made: the codes of the ``pixel_kind`` plane
(``FrameOutput.pixel_kind``, the ``phrt:pixelKind`` RenderVar, docs/pixel-kinds.md).

One uint8 code a pixel, the way the frame's reflection (or, off reflectors, its colour)
was produced:

====  ============  ====================================================================
code  kind          the pixel
====  ============  ====================================================================
0     background    hit no surface: the environment (or black when the dome is hidden)
1     raster        the raster frame: local shading, and on a reflector the environment
                    fallback in the mirror direction (``compositing.base_image``)
2     screen-space  a reflector pixel whose first reflection ray was resolved in the
                    frame's own G-buffer (``engine/trace/screen_space.py``): its hit
                    found by marching the G-buffer, lit as a traced hit
3     traced        a reflector pixel whose reflection rays were traced this frame
4     reused        a reflector pixel traced at a reduced density that started no ray:
                    its reflection is an earlier frame's, reprojected
                    (``engine/reflection_history.py``)
5     filled        a reflector pixel traced at a reduced density that started no ray:
                    its reflection is interpolated from traced neighbours
                    (``engine/trace/sparse_pixels.py``)
====  ============  ====================================================================

A stage that makes a reflector's pixels marks them with its code in
``ReflectionResult.kinds`` (``model/frame.py``); compositing writes the codes of the
pixels it replaces (``compositing.apply_traced``).
"""

from __future__ import annotations

import numpy as np

BACKGROUND = 0
RASTER = 1
SCREEN_SPACE = 2
TRACED = 3
REUSED = 4
FILLED = 5

#: Code → name, in code order (the names docs and the EXR header use).
PIXEL_KINDS: dict[int, str] = {
    BACKGROUND: "background",
    RASTER: "raster",
    SCREEN_SPACE: "screen-space",
    TRACED: "traced",
    REUSED: "reused",
    FILLED: "filled",
}
#: The storage of the codes.
PIXEL_KIND_DTYPE = np.uint8


def raster_kinds(covered: np.ndarray) -> np.ndarray:
    """(H, W) uint8 codes of the raster frame: RASTER where ``covered`` ((H, W) bool),
    BACKGROUND (0) elsewhere; two cheap passes (a frame's finish pays for them)."""
    kinds = np.asarray(covered, dtype=bool).astype(PIXEL_KIND_DTYPE)
    kinds *= PIXEL_KIND_DTYPE(RASTER)
    return kinds


def kind_counts(kinds: np.ndarray) -> dict[str, int]:
    """Pixels of each kind in ``kinds`` (any shape of codes), by name, every kind listed."""
    counts = np.bincount(np.asarray(kinds, dtype=np.int64).reshape(-1), minlength=len(PIXEL_KINDS))
    return {name: int(counts[code]) for code, name in PIXEL_KINDS.items()}
