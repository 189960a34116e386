"""The rotating traced subset (``sparse_pixels.rotation_phase``): over its rotation
period, a reduced-density pattern starts a ray at every pixel of a large reflector
exactly once, from any starting frame, so a still view can be completed by reuse."""

import numpy as np
import pytest

from phrt_usd.engine.trace.sparse_pixels import ROTATION_PERIOD, rotation_phase, traced_subset
from phrt_usd.model.trace_density import DENSITY_FRACTION, TRACE_DENSITIES

WIDTH, HEIGHT = 24, 20  # multiples of no spacing on purpose: the pattern wraps at edges


@pytest.mark.parametrize("density", ["half", "quarter", "eighth", "sixteenth"])
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


@pytest.mark.parametrize("density", TRACE_DENSITIES[1:])
@pytest.mark.parametrize("start", [0, 3, 7])
def test_every_rate_traces_its_share_and_every_pixel_within_its_period(density, start):
    """At a rate of k/16, each 4 x 4 block starts rays at exactly k pixels in every frame
    (the predicted share is the traced one), and over the period of its regular pattern
    (the largest power of two of ranks it holds) every pixel is traced at least once
    (reuse ages out history after that period)."""
    width, height = 16, 12  # whole 4 x 4 blocks: the share is exact
    pix = np.arange(width * height, dtype=np.int64)
    src = np.zeros(len(pix), np.int64)
    counts = np.zeros(len(pix), np.int64)
    for frame in range(start, start + ROTATION_PERIOD[density]):
        traced = traced_subset(pix, src, 1, width, density, rotation_phase(frame))
        blocks = traced.reshape(height // 4, 4, width // 4, 4).sum(axis=(1, 3))
        assert np.all(blocks == round(16 * DENSITY_FRACTION[density]))
        counts += traced
    assert counts.min() >= 1


@pytest.mark.parametrize("phase", [(0, 0), (2, 3)])
def test_a_finer_rate_traces_every_pixel_a_coarser_one_does(phase):
    """The rates are nested: stepping a reflector one rate finer adds pixels and keeps
    every traced one (its history and its fill lattice stay)."""
    width = 20
    pix = np.arange(width * 16, dtype=np.int64)
    src = np.zeros(len(pix), np.int64)
    masks = [traced_subset(pix, src, 1, width, d, phase) for d in TRACE_DENSITIES]
    for finer, coarser in zip(masks, masks[1:], strict=False):
        assert np.all(finer >= coarser) and finer.sum() > coarser.sum()
