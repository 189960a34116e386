"""Tracing a large reflector at half density: which of its pixels start rays, and how the
others get their reflection from traced neighbours (``--trace-density half``).

The pixels of a reflector with at least HALF_DENSITY_MIN_PIXELS pixels are traced on a
checkerboard (the pixels whose row + column is even); each skipped pixel takes the mean
radiance of its traced 4-neighbours of the same reflector (all of them are on the
checkerboard: a skipped interior pixel has four, one on the reflector's edge fewer, an
isolated one none and keeps the raster fallback). Half the rays for a reflection at half
the resolution, as real-time renderers trace large reflectors; the reflection is
smoothed over one pixel, and its edges against other surfaces stay exact (neighbours of
another element are never used). Smaller reflectors are traced whole: their savings are
small and their edges are most of their pixels.

Pixels are flat indices ``row * width + col`` of the G-buffer; ``src`` is each pixel's
index into the round's sources (``Tracer.trace_reflections``).
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.errors import BadOption

#: Reflectors with fewer pixels than this in a frame are traced at every pixel. 256
#: pixels is a 16 x 16 patch: below it most pixels lie on the reflector's edge, where a
#: skipped pixel has fewer traced neighbours, and the rays saved are a few hundred.
HALF_DENSITY_MIN_PIXELS = 256

#: The trace densities: every pixel, or the checkerboard of large reflectors.
TRACE_DENSITIES = ("full", "half")


def check_density(value: object) -> str:
    """``value`` as one of TRACE_DENSITIES; BadOption (one line) otherwise."""
    if not isinstance(value, str) or value.lower() not in TRACE_DENSITIES:
        raise BadOption(
            f"trace density must be one of {', '.join(TRACE_DENSITIES)}, got {value!r}"
        )
    return value.lower()


def traced_subset(pix: np.ndarray, src: np.ndarray, n_sources: int, width: int) -> np.ndarray:
    """(n,) bool: which of the round's pixels ``pix`` (n,) int64 of sources ``src`` (n,)
    int64 start rays at half density: every pixel of a source with fewer than
    HALF_DENSITY_MIN_PIXELS pixels, the checkerboard ones of the others."""
    counts = np.bincount(src, minlength=n_sources)
    row, col = np.divmod(pix, width)
    return (counts[src] < HALF_DENSITY_MIN_PIXELS) | ((row + col) % 2 == 0)


def fill_skipped(
    traced_pix: np.ndarray,
    traced_src: np.ndarray,
    radiance: np.ndarray,
    skipped_pix: np.ndarray,
    skipped_src: np.ndarray,
    width: int,
    height: int,
    row_of: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Radiance of the skipped pixels from their traced 4-neighbours of the same source
    (``trace_kernels.fill_skipped``, one pass: ~4 ns a pixel).

    traced_pix, traced_src : (n,) int64 the traced pixels (each once) and their sources
    radiance : (n, 3) float32 traced radiance of those pixels
    skipped_pix, skipped_src : (m,) int64 the skipped pixels and their sources
    row_of : (width * height,) int32 all -1, a table the kernel uses and leaves as it
        found it (a caller tracing round after round keeps one); None: a new one
    Returns (k,) int64 the skipped pixels with at least one traced neighbour and (k, 3)
    float32 the mean radiance of those neighbours (the others keep the fallback)."""
    if row_of is None:
        row_of = np.full(width * height, -1, np.int32)
    m = len(skipped_pix)
    out_pix, out_rad = np.empty(m, np.int64), np.empty((m, 3), np.float32)
    k = _trace_kernels().fill_skipped(
        row_of, _int64(traced_pix), _int64(traced_src),
        np.ascontiguousarray(radiance, np.float32), _int64(skipped_pix), _int64(skipped_src),
        width, height, out_pix, out_rad,
    )  # fmt: skip
    return out_pix[:k], out_rad[:k]


def _int64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.int64)


def _trace_kernels():
    """The compiled trace kernels (loaded on first use: this module is imported by the
    options, long before anything is traced)."""
    return kernels.load("phrt_usd.render.trace.trace_kernels")
