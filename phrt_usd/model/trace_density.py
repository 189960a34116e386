"""Trace densities: how many of a reflector's pixels start rays (``--trace-density``,
HEU1's density steps). The patterns themselves and the fill of the skipped pixels are
``engine.trace.sparse_pixels``; the policies need only the shares, to predict rays.
"""

from __future__ import annotations

from phrt_usd.checks import check_choice

#: Reflectors with fewer pixels than this in a frame are traced at every pixel: below an
#: 8 x 8 patch the rays saved are a few dozen and most pixels lie on the reflector's
#: edge, where a skipped pixel has fewer traced neighbours. Not higher, so that HEU1 can
#: step the farm's barrels (64-255 pixels near its path's end) coarser to make room
#: rather than drop them whole (the floor at 64 pixels against 256:
#: docs/bench-log/2026-12-03-2987843-make-room-hold.md; docs/heuristic.md, "Density steps").
SPARSE_MIN_PIXELS = 64

#: The trace densities: every pixel; the checkerboard, one pixel in each 2 x 2 block or
#: one in each 4 x 4 block of large reflectors. Finest first (HEU1's density steps walk
#: them in this order). "sixteenth" is a last step before dropping a reflector: on the
#: farm at T = 1 ms, reflectors already at a quarter grow to 4x the budget's rays near the
#: path's end, and a drop there is a transition.
TRACE_DENSITIES = ("full", "half", "quarter", "sixteenth")
#: Index of the coarsest density in TRACE_DENSITIES.
COARSEST = len(TRACE_DENSITIES) - 1
#: Share of a large reflector's pixels each density starts rays at (the patterns').
DENSITY_FRACTION = {"full": 1.0, "half": 0.5, "quarter": 0.25, "sixteenth": 1.0 / 16.0}


def traced_fraction(pixels: float, density: str) -> float:
    """Share of a reflector's ``pixels`` that start rays at ``density`` (1 below
    SPARSE_MIN_PIXELS: small reflectors are traced whole)."""
    return 1.0 if pixels < SPARSE_MIN_PIXELS else DENSITY_FRACTION[density]


def check_density(value: object) -> str:
    """``value`` as one of TRACE_DENSITIES; BadOption (one line) otherwise."""
    return check_choice(value, TRACE_DENSITIES, "trace density")
