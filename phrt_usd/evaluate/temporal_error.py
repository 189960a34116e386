"""The temporal error of a frame sequence against a reference sequence: what a viewer of the
sequences sees over time, as a sustained (temporally integrated) and a transient (flicker)
channel, each compared with LDR-FLIP (docs/temporal-error.md).

The two channels and their temporal filters are ColorVideoVDP's (Mantiuk et al. 2024,
"ColorVideoVDP: A visual difference predictor for image, video and display distortions",
ACM ToG 43(4); the parameter values of its release 0.5.7); FLIP stands in for its spatial
model (contrast sensitivity, masking, pooling), and the weight of the transient channel is
ours, calibrated against ColorVideoVDP (``TRANSIENT_WEIGHT``).

Sequences are streamed: ``TemporalChannels.push`` takes the next frame of one sequence and
returns its two channels at that frame; ``temporal_error_map`` compares two sequences'
channels at one frame.

Frames: (H, W, 3) float32 linear RGB, non-negative, finite. Channels: (H, W, 3) float32 in
the display's sRGB-encoded domain (``images.tonemap_ldr``).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.image_metrics import check_pair, flip_display
from phrt_usd.run.images import tonemap_ldr

#: Support of the temporal filters in seconds (ColorVideoVDP's 250 ms, over which its
#: channels' impulse responses have decayed). At F frames per second a filter has
#: 2 * ceil(F * SPAN / 2) + 1 taps (7 at 24 fps, 3 at 4 fps).
TEMPORAL_FILTER_SPAN_S = 0.25
#: Sustained channel, frequency response exp(-f**BETA / SIGMA) (f in Hz): a low-pass that
#: keeps 48 % at 3 Hz and 2 % at 12 Hz (ColorVideoVDP's achromatic sustained channel, used
#: here for all three colour channels).
SUSTAINED_BETA = 1.3314
SUSTAINED_SIGMA = 5.79336
#: Transient channel, exp(-(f**BETA - PEAK**BETA)**2 / SIGMA): a band-pass peaking at PEAK Hz,
#: where flicker is most visible (ColorVideoVDP's achromatic transient channel).
TRANSIENT_BETA = 0.1898
TRANSIENT_SIGMA = 0.12314
TRANSIENT_PEAK_HZ = 5.0
#: Weight of the transient channel's FLIP against the sustained one's (ours). FLIP of the
#: transient images (changes of a few per cent on a grey) is small beside FLIP of images,
#: where ColorVideoVDP sees flicker at low contrast: it scores a patch flickering at 6 Hz
#: far worse than the same patch shown steadily (0.6 against 2.9 JOD), which the sum ranks
#: so from a weight of 1.3 on. 1.5 is the round value above it; checked against
#: ColorVideoVDP in docs/temporal-error.md (rank correlations on rendered and synthetic
#: sequences, and how they move with the weight).
TRANSIENT_WEIGHT = 1.5

#: Display mapping of the transient channel: a value ``d`` in [-1, 1] (the filter's output
#: on sRGB-encoded frames in [0, 1] stays within +-0.8: its positive and its negative taps
#: each sum to at most 0.79 from 1 to 10,000 frames per second) is shown as
#: ``CHANGE_GREY + CHANGE_SCALE * d`` in [0, 1], on a mid-grey at half amplitude, so FLIP
#: compares displayable images and +d and -d are equally far from the grey.
CHANGE_GREY = 0.5
CHANGE_SCALE = 0.5

#: Highest frame rate the filters are made for: 2501 taps, far beyond any rendered
#: sequence; keeps the filter length finite for absurd rates.
MAX_FRAMES_PER_SECOND = 1e4


def sequence_frames_per_second(times: list[float], time_codes_per_second: float) -> float:
    """Frames per second of a recorded sequence of stage time codes ``times`` (ascending):
    the stage's time codes per second over the median step between recorded frames (a
    sweep of every 6th time code at 24 per second is a 4 fps sequence); the stage's rate
    for fewer than two frames."""
    steps = np.diff(np.asarray(times, dtype=np.float64))
    steps = steps[steps > 0.0]
    rate = float(time_codes_per_second)
    if len(steps):
        rate /= float(np.median(steps))
    if not (math.isfinite(rate) and rate > 0.0):
        raise PhrtError(f"temporal error: no frame rate from time codes per second {rate}")
    return rate


def temporal_filters(frames_per_second: float) -> tuple[np.ndarray, np.ndarray]:
    """(sustained, transient) FIR filters, each (N,) float64 with N odd (module
    constants), for a sequence of ``frames_per_second`` (finite, > 0): the inverse real FFT
    of each frequency response sampled from 0 Hz to the Nyquist rate. The sustained one
    sums to 1 (a still image passes unchanged), the transient one to 0 (a still image gives
    0)."""
    fps = float(frames_per_second)
    if not (math.isfinite(fps) and fps > 0.0):
        raise PhrtError(f"temporal error: frames per second must be finite and > 0, got {fps}")
    fps = min(fps, MAX_FRAMES_PER_SECOND)
    taps = 2 * math.ceil(fps * TEMPORAL_FILTER_SPAN_S / 2.0) + 1
    f = np.linspace(0.0, fps / 2.0, taps // 2 + 1)
    sustained = np.exp(-(f**SUSTAINED_BETA) / SUSTAINED_SIGMA)
    peak = TRANSIENT_PEAK_HZ**TRANSIENT_BETA
    transient = np.exp(-((f**TRANSIENT_BETA - peak) ** 2) / TRANSIENT_SIGMA)
    sustained_k, transient_k = (
        np.fft.fftshift(np.fft.irfft(response, n=taps)) for response in (sustained, transient)
    )
    # Exact unit and zero gain at 0 Hz (the sampled responses give them up to rounding).
    return sustained_k / sustained_k.sum(), transient_k - transient_k.mean()


class TemporalChannels:
    """One sequence's two channels, frame by frame: the filters run over the last N
    display frames (N = the filters' length), oldest first; before N frames were pushed
    the first frame stands in for the missing ones (ColorVideoVDP's "replicate" padding),
    so a still sequence has no transient from its first frame on."""

    def __init__(self, frames_per_second: float) -> None:
        self.sustained_filter, self.transient_filter = temporal_filters(frames_per_second)
        self._frames: deque[np.ndarray] = deque(maxlen=len(self.sustained_filter))

    def push(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Add the next (H, W, 3) linear frame; its (sustained, transient) channels, each
        (H, W, 3) float32 (sustained in [0, 1], transient in [-1, 1])."""
        if frame.ndim != 3 or frame.shape[2] != 3 or not np.all(np.isfinite(frame)):
            raise PhrtError(f"temporal error needs finite (H, W, 3) frames, got {frame.shape}")
        if self._frames and self._frames[-1].shape != frame.shape:
            raise PhrtError(
                f"temporal error: a frame of {frame.shape} after frames of "
                f"{self._frames[-1].shape}"
            )
        shown = tonemap_ldr(frame).astype(np.float32)
        if not self._frames:
            self._frames.extend([shown] * self._frames.maxlen)
        else:
            self._frames.append(shown)
        sustained = np.zeros_like(shown)
        transient = np.zeros_like(shown)
        for image, s, t in zip(
            self._frames, self.sustained_filter, self.transient_filter, strict=True
        ):
            sustained += np.float32(s) * image
            transient += np.float32(t) * image
        return np.clip(sustained, 0.0, 1.0), np.clip(transient, -1.0, 1.0)


def temporal_error_map(
    reference: tuple[np.ndarray, np.ndarray], test: tuple[np.ndarray, np.ndarray]
) -> np.ndarray:
    """(H, W) float32 temporal error in [0, 1 + TRANSIENT_WEIGHT] at one frame, from the
    (sustained, transient) channels of the reference's and the test's sequences
    (``TemporalChannels.push``)::

        E = FLIP(sustained_R, sustained_H)
            + TRANSIENT_WEIGHT * FLIP(CHANGE_GREY + CHANGE_SCALE * transient_R,
                                      CHANGE_GREY + CHANGE_SCALE * transient_H)

    0 where the test's sequence equals the reference's; a steady error on a still
    reference scores its per-frame FLIP; a reflector switching between raster and traced
    scores the error of what the eye integrates plus its flicker, most near 5 Hz."""
    (ref_s, ref_t), (test_s, test_t) = reference, test
    check_pair(ref_s, test_s)
    check_pair(ref_s, ref_t)
    check_pair(ref_s, test_t)
    sustained = flip_display(ref_s, test_s)
    transient = flip_display(
        CHANGE_GREY + CHANGE_SCALE * ref_t, CHANGE_GREY + CHANGE_SCALE * test_t
    )
    return sustained + np.float32(TRANSIENT_WEIGHT) * transient
