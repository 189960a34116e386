"""Trace densities: how many of a reflector's pixels start rays (``--trace-density``,
HEU1's density steps). The patterns themselves and the fill of the skipped pixels are
``engine.trace.sparse_pixels``; the policies need only the shares, to predict rays.
"""

from __future__ import annotations

import math

from phrt_usd.checks import check_choice

#: Reflectors with fewer pixels than this in a frame are traced at every pixel: below
#: ~6 x 6 pixels the rays saved are a few dozen and most pixels lie on the reflector's
#: edge, where a skipped pixel has fewer traced neighbours. Not higher, so that HEU1 can
#: step the farm's barrels (32-255 pixels near its path's end at 160 x 120) a few
#: sixteenths coarser to make room rather than drop them whole: at 64, the farm's sweep
#: dropped a 55-pixel barrel HEU2 kept, and HEU2 had both the lower FLIP and the lower
#: temporal error at 300 rays (docs/heuristic.md, "Where HEU1 and HEU2 trade"; the floor
#: at 64 against 256: docs/bench-log/2026-12-03-2987843-make-room-hold.md).
SPARSE_MIN_PIXELS = 32
#: And at least this many of its pixels must start rays at the rate (so a sixteenth
#: needs 64 pixels, as before the rate, an eighth 32): fewer samples leave most of a small
#: reflector's skipped pixels on its edge with one traced neighbour or none.
SPARSE_MIN_SAMPLES = 4

#: The trace densities are a rate: a reflector traced at k/16 (k = 1..16) starts rays at
#: the pixels of each 4 x 4 block whose rank in an ordered-dither (Bayer) matrix is below
#: k (``engine/trace/sparse_pixels.py``). The powers of two are the regular patterns and
#: have names: "half" the checkerboard, "quarter" one pixel of each 2 x 2 block, "eighth"
#: the checkerboard of those, "sixteenth" one of each 4 x 4 block; the rates between them
#: add pixels to the coarser pattern, so that HEU1 can set a reflector's rate in steps of
#: 1/16 of its pixels rather than halve it. "sixteenth" is a last step before dropping a
#: reflector: on the farm at T = 1 ms, reflectors already at a quarter grow to 4x the
#: budget's rays near the path's end, and a drop there is a transition.
RATE_STEPS = 16
_NAMED_RATES = {16: "full", 8: "half", 4: "quarter", 2: "eighth", 1: "sixteenth"}
#: The densities, finest first (HEU1's density steps walk them in this order; a level is
#: an index into this tuple).
TRACE_DENSITIES = tuple(_NAMED_RATES.get(k, f"{k}/{RATE_STEPS}") for k in range(RATE_STEPS, 0, -1))
#: Index of the coarsest density in TRACE_DENSITIES.
COARSEST = len(TRACE_DENSITIES) - 1
#: Pixels of each 4 x 4 block that start rays (k above), by index of TRACE_DENSITIES.
LEVEL_RANKS = tuple(range(RATE_STEPS, 0, -1))
#: Share of a large reflector's pixels each density starts rays at (the patterns').
DENSITY_FRACTION = {d: k / RATE_STEPS for d, k in zip(TRACE_DENSITIES, LEVEL_RANKS, strict=True)}


def sparse_floor(density: str) -> int:
    """The fewest pixels a reflector traced at ``density`` must have to start rays at
    that share of them (SPARSE_MIN_PIXELS, SPARSE_MIN_SAMPLES); smaller ones are traced
    whole."""
    return max(SPARSE_MIN_PIXELS, math.ceil(SPARSE_MIN_SAMPLES / DENSITY_FRACTION[density]))


def traced_fraction(pixels: float, density: str) -> float:
    """Share of a reflector's ``pixels`` that start rays at ``density`` (1 below its
    ``sparse_floor``: small reflectors are traced whole)."""
    return 1.0 if pixels < sparse_floor(density) else DENSITY_FRACTION[density]


def check_density(value: object) -> str:
    """``value`` as one of TRACE_DENSITIES; BadOption (one line) otherwise."""
    return check_choice(value, TRACE_DENSITIES, "trace density")
