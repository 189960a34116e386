"""The rotating traced subset (``sparse_pixels.rotation_phase``): over its rotation
period, a reduced-density pattern starts a ray at every pixel of a large reflector
exactly once, from any starting frame, so a still view can be completed by reuse."""

import numpy as np
import pytest

from phrt_usd.engine.trace.sparse_pixels import ROTATION_PERIOD, rotation_phase, traced_subset

WIDTH, HEIGHT = 24, 20  # multiples of no spacing on purpose: the pattern wraps at edges


@pytest.mark.parametrize("density", ["half", "quarter", "sixteenth"])
@pytest.mark.parametrize("start", [0, 1, 5, 13])
def test_every_pixel_traced_once_per_period(density, start):
    pix = np.arange(WIDTH * HEIGHT, dtype=np.int64)
    src = np.zeros(len(pix), np.int64)  # one reflector, larger than SPARSE_MIN_PIXELS
    period = ROTATION_PERIOD[density]
    counts = np.zeros(len(pix), np.int64)
    for frame in range(start, start + period):
        counts += traced_subset(pix, src, 1, WIDTH, density, rotation_phase(frame))
    # Away from the image's last partial cells every pixel is visited exactly once; the
    # pattern is periodic in the image's coordinates, so the edges are too.
    assert counts.min() == 1 and counts.max() == 1


def test_half_alternates_every_frame():
    """The checkerboard's parity flips every frame: two frames complete it."""
    parities = {(sum(rotation_phase(k)) % 2) for k in range(2)}
    assert parities == {0, 1}
    for k in range(32):
        assert sum(rotation_phase(k)) % 2 != sum(rotation_phase(k + 1)) % 2
