"""Tracing large reflectors at reduced density: which of their pixels start rays, and how
the others get their reflection from traced neighbours (``--trace-density
half|quarter|sixteenth``, HEU1's density steps).

The pixels of a reflector with at least SPARSE_MIN_PIXELS pixels in a frame are traced
on a pattern: ``half`` a checkerboard (row + column even), ``quarter`` one pixel of each
2 x 2 block (row and column even), ``sixteenth`` one of each 4 x 4 block (row and column
multiples of 4). Each skipped pixel takes the bilinear interpolation of the traced
pixels of the same reflector around it: their mean weighted by (s - |dy|) (s - |dx|)
within s - 1 rows and columns, s the pattern's spacing (PATTERN_SPACING). On the
checkerboard that is the mean of its 4 axis neighbours; at quarter density of the 2
traced ones in its row or column, or of the 4 diagonal ones. One on the reflector's
edge has fewer, an isolated one none and keeps the raster fallback. A share of the rays
for a reflection at that resolution, as real-time renderers trace large reflections;
the reflection is smoothed over s - 1 pixels, and its edges against other surfaces stay
exact (pixels of another element are never used). Smaller reflectors are traced whole:
their savings are small and their edges are most of their pixels.

Measured on the sewer's wet tunnel (frames 217-276 every 6th, 320 x 240, every
reflector traced): mean FLIP against full density 0.027 (half), 0.046 (quarter) and
0.074 (sixteenth), where the raster fallback alone is 0.179
(docs/bench-log/2026-12-03-2987843-make-room-hold.md).

Pixels are flat indices ``row * width + col`` of the G-buffer; ``src`` is each pixel's
index into the round's sources (``Tracer.trace_reflections``).
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.model.trace_density import SPARSE_MIN_PIXELS, TRACE_DENSITIES

#: Spacing of each reduced density's traced pixels: a skipped pixel's traced neighbours
#: lie within spacing - 1 rows and columns (the checkerboard's within 1, as at quarter).
PATTERN_SPACING = {"half": 2, "quarter": 2, "sixteenth": 4}
#: PATTERN_SPACING by index of TRACE_DENSITIES (1 at full density: every pixel traced).
_SPACING = np.array([PATTERN_SPACING.get(d, 1) for d in TRACE_DENSITIES], np.int64)


def _pixel_levels(density, src: np.ndarray) -> np.ndarray:
    """(n,) int64 index in TRACE_DENSITIES of the density of each pixel's source (``src``
    (n,) int64): ``density`` one of TRACE_DENSITIES for every source, or a sequence of
    them, one per source."""
    if isinstance(density, str):
        return np.full(len(src), TRACE_DENSITIES.index(density), np.int64)
    levels = np.array([TRACE_DENSITIES.index(d) for d in density], np.int64)
    return levels[src] if len(levels) else np.zeros(len(src), np.int64)


def traced_subset(
    pix: np.ndarray, src: np.ndarray, n_sources: int, width: int, density
) -> np.ndarray:
    """(n,) bool: which of the round's pixels ``pix`` (n,) int64 of sources ``src`` (n,)
    int64 start rays at ``density``, one of TRACE_DENSITIES for every source or a
    sequence of them, one per source: every pixel of a source traced at "full" or with
    fewer than SPARSE_MIN_PIXELS pixels, the pattern's pixels of the others."""
    counts = np.bincount(src, minlength=n_sources)
    row, col = np.divmod(pix, width)
    level = _pixel_levels(density, src)
    step = _SPACING[level]
    on_grid = (row % step == 0) & (col % step == 0)
    on_pattern = np.where(level == TRACE_DENSITIES.index("half"), (row + col) % 2 == 0, on_grid)
    return (counts[src] < SPARSE_MIN_PIXELS) | on_pattern


def fill_skipped(
    traced_pix: np.ndarray,
    traced_src: np.ndarray,
    radiance: np.ndarray,
    skipped_pix: np.ndarray,
    skipped_src: np.ndarray,
    width: int,
    height: int,
    row_of: np.ndarray | None = None,
    density="quarter",
) -> tuple[np.ndarray, np.ndarray]:
    """Radiance of the skipped pixels from the traced pixels of the same source around
    them, bilinear on the pattern's grid (module docstring; ``trace_kernels.fill_skipped``,
    one pass: ~10 ns a pixel at spacing 2, ~5x that at 4).

    traced_pix, traced_src : (n,) int64 the traced pixels (each once) and their sources
    radiance : (n, 3) float32 traced radiance of those pixels
    skipped_pix, skipped_src : (m,) int64 the skipped pixels and their sources
    row_of : (width * height,) int32 all -1, a table the kernel uses and leaves as it
        found it (a caller tracing round after round keeps one); None: a new one
    density : the density the sources were traced at, one of TRACE_DENSITIES but "full"
        for every source, or a sequence of them, one per source (index ``skipped_src``)
    Returns (k,) int64 the skipped pixels with at least one traced neighbour and (k, 3)
    float32 their interpolated radiance (the others keep the fallback)."""
    if row_of is None:
        row_of = np.full(width * height, -1, np.int32)
    m = len(skipped_pix)
    spacing = _SPACING[_pixel_levels(density, _int64(skipped_src))]
    out_pix, out_rad = np.empty(m, np.int64), np.empty((m, 3), np.float32)
    k = _trace_kernels().fill_skipped(
        row_of, _int64(traced_pix), _int64(traced_src),
        np.ascontiguousarray(radiance, np.float32), _int64(skipped_pix), _int64(skipped_src),
        spacing, width, height, out_pix, out_rad,
    )  # fmt: skip
    return out_pix[:k], out_rad[:k]


def _int64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.int64)


def _trace_kernels():
    """The compiled trace kernels (loaded on first use: this module is imported by the
    options, long before anything is traced)."""
    return kernels.load("phrt_usd.engine.trace.trace_kernels")
