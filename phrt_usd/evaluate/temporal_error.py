"""The temporal error of a frame sequence against a reference sequence: popping, seen as
the warped-frame error the reference does not have (docs/temporal-error.md).

Per frame t and sequence X, the previous frame is warped to this one by the frame's
exact motion vectors (``engine/motion.py``): each pixel reads the previous frame where
its surface point was (bilinear), and pixels whose surface was not visible there are
masked (``FrameWarp``: the point was off screen or behind the camera, another element or
a nearer surface covered it). The *warped error* of X at a pixel is the LDR-FLIP of
``ldr(X_t)`` against ``ldr(warp(X_{t-1}))`` (``warped_error_map``): 0 where the pixel
shows what its surface showed a frame before. A consistent moving sequence scores about
0; a reflection that switches between raster and traced scores the switch. Real changes
the warp does not follow (a reflection sliding over its mirror, a moving highlight) score
too, so the sequence is judged against the reference's own warped error, pixel by pixel::

    popping_t(p) = max(0, e_t(H)(p) - e_t(R)(p))      over the pixels the warp keeps

(``popping_map``), 0 for the reference against itself. The sweep's ``temporal_error`` is
its mean over the kept pixels; ``warped_error`` and ``warped_error_reference`` the two
sequences' own means.

Frames: (H, W, 3) float32 linear RGB, finite. Maps: (H, W) float32 in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.image_metrics import check_pair, flip_display
from phrt_usd.run.images import tonemap_ldr

#: A surface point is the one the previous frame saw at its position when their inverse
#: depths agree within this share: a plane's inverse depth is linear on screen, so the
#: bilinear mean of the previous frame's at the taps is the point's own up to float32
#: rounding (1e-7) and a surface's curvature over one pixel (far below 1 % for the
#: stages' meshes); an occluder in front differs by its distance. Surfaces within 1 % of
#: each other's depth are taken as one.
DEPTH_AGREEMENT = 0.01
#: A bilinear tap whose weight is at most this reads nothing (a motion of a whole number
#: of pixels reads one pixel): its element and depth are not compared.
TAP_WEIGHT_MIN = 1e-6


@dataclass(frozen=True)
class FrameWarp:
    """How frame t reads frame t - 1 (module docstring), for every sequence of the same
    frames: each pixel's four bilinear taps into the previous frame (``taps`` (H * W, 4)
    int64 flat indices, ``weights`` (H * W, 4) float32, summing to 1) and ``valid`` (H, W)
    bool, the pixels whose surface point the previous frame showed at that position."""

    taps: np.ndarray
    weights: np.ndarray
    valid: np.ndarray

    @classmethod
    def between(
        cls,
        motion: np.ndarray,
        element_id: np.ndarray,
        previous_element_id: np.ndarray,
        previous_depth: np.ndarray,
        expected_depth: np.ndarray | None = None,
    ) -> FrameWarp:
        """The warp of a frame with ``motion`` (H, W, 2) pixels (``engine/motion.py``:
        this frame's position minus the previous one's, x right, y down) and
        ``element_id`` (H, W) (-1 background) onto the previous frame's
        ``previous_element_id`` and view ``previous_depth`` (H, W) (inf background).

        A pixel is kept when its previous position lies on the image, every tap that
        weighs (TAP_WEIGHT_MIN) shows the same element (background: background), and,
        with ``expected_depth`` ((H, W): the depth the pixel's point had in the previous
        camera, ``MotionField.previous_depth``; NaN behind it), the taps' bilinear inverse
        depth agrees with it (DEPTH_AGREEMENT). Without ``expected_depth`` (files hold
        none) the element alone decides."""
        height, width = element_id.shape
        if motion.shape != (height, width, 2) or previous_depth.shape != (height, width):
            raise PhrtError(
                f"warp: motion {motion.shape} and depth {previous_depth.shape} do not fit "
                f"a {width}x{height} frame"
            )
        rows, cols = np.divmod(np.arange(height * width), width)
        # Pixel centres are at index + 0.5: the previous centre's index coordinates.
        x = cols - np.asarray(motion[..., 0], dtype=np.float64).reshape(-1)
        y = rows - np.asarray(motion[..., 1], dtype=np.float64).reshape(-1)
        with np.errstate(invalid="ignore"):
            on_image = (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)
        x = np.where(on_image, x, cols)
        y = np.where(on_image, y, rows)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        xa, xb = np.clip(x0, 0, width - 1), np.clip(x0 + 1, 0, width - 1)
        ya, yb = np.clip(y0, 0, height - 1) * width, np.clip(y0 + 1, 0, height - 1) * width
        taps = [ya + xa, ya + xb, yb + xa, yb + xb]
        gx, gy = 1.0 - fx, 1.0 - fy
        weights = [gx * gy, fx * gy, gx * fy, fx * fy]
        # Tap by tap on (H * W,) arrays: reductions over a short axis cost several times it.
        ids = np.asarray(element_id).reshape(-1)
        then_ids = np.asarray(previous_element_id).reshape(-1)
        weighs = [w > TAP_WEIGHT_MIN for w in weights]
        valid = on_image
        for tap, weigh in zip(taps, weighs, strict=True):
            valid &= (then_ids[tap] == ids) | ~weigh
        if expected_depth is not None:
            expected = np.asarray(expected_depth, dtype=np.float64).reshape(-1)
            with np.errstate(divide="ignore"):
                inverse = (1.0 / np.asarray(previous_depth, dtype=np.float64)).reshape(-1)
            seen = np.zeros(height * width)
            total = np.zeros(height * width)
            for tap, weight, weigh in zip(taps, weights, weighs, strict=True):
                used = np.where(weigh, weight, np.float32(0.0))
                seen += used * inverse[tap]
                total += used
            seen /= np.maximum(total, 1e-30)
            with np.errstate(divide="ignore", invalid="ignore"):
                want = 1.0 / expected
                agree = np.abs(seen - want) <= DEPTH_AGREEMENT * want
            valid &= (ids < 0) | (np.isfinite(expected) & (expected > 0.0) & agree)
        taps, weights = np.stack(taps, axis=1), np.stack(weights, axis=1)
        return cls(taps, weights, valid.reshape(height, width))

    @classmethod
    def still(cls, height: int, width: int) -> FrameWarp:
        """Every pixel reads itself (a still camera over a still scene, no occlusion)."""
        taps = np.repeat(np.arange(height * width, dtype=np.int64)[:, None], 4, axis=1)
        weights = np.zeros((height * width, 4), np.float32)
        weights[:, 0] = 1.0
        return cls(taps, weights, np.ones((height, width), dtype=bool))

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape  # type: ignore[return-value]

    def warp(self, previous: np.ndarray) -> np.ndarray:
        """(H, W, C) float32 the previous frame's ``previous`` (H, W, C) read at each
        pixel's previous position (bilinear); meaningful where ``valid``."""
        height, width = self.shape
        flat = np.asarray(previous, dtype=np.float32).reshape(height * width, -1)
        out = np.einsum("nk,nkc->nc", self.weights, flat[self.taps])
        return out.reshape(height, width, -1)


def warped_error_map(current: np.ndarray, previous: np.ndarray, warp: FrameWarp) -> np.ndarray:
    """(H, W) float32 LDR-FLIP of the linear frame ``current`` against the linear
    ``previous`` one warped to it (both (H, W, 3), tone-mapped by ``images.tonemap_ldr``
    first); 0 at the pixels ``warp`` masks (there the warped frame is the current one)."""
    check_pair(current, previous)
    return warped_display_error(tonemap_ldr(current), tonemap_ldr(previous), warp)


def warped_display_error(current: np.ndarray, previous: np.ndarray, warp: FrameWarp) -> np.ndarray:
    """``warped_error_map`` of display frames (sRGB-encoded, in [0, 1])."""
    if current.shape[:2] != warp.shape:
        raise PhrtError(f"warp of a {warp.shape} frame applied to one of {current.shape[:2]}")
    warped = np.where(warp.valid[..., None], warp.warp(previous), current)
    error = flip_display(current, warped)
    return np.where(warp.valid, error, np.float32(0.0)).astype(np.float32)


class WarpedSequence:
    """One sequence's warped error frame by frame: ``push`` takes the next linear frame
    and the warp from the previous one (None: no previous frame, e.g. the first) and
    returns its warped error map, None when there is nothing to compare."""

    def __init__(self) -> None:
        self._previous: np.ndarray | None = None

    def push(self, frame: np.ndarray, warp: FrameWarp | None) -> np.ndarray | None:
        if frame.ndim != 3 or frame.shape[2] != 3 or not np.all(np.isfinite(frame)):
            raise PhrtError(f"temporal error needs finite (H, W, 3) frames, got {frame.shape}")
        shown = tonemap_ldr(frame).astype(np.float32)
        previous, self._previous = self._previous, shown
        if previous is None or warp is None:
            return None
        if previous.shape != shown.shape:
            raise PhrtError(
                f"temporal error: a frame of {frame.shape} after frames of {previous.shape}"
            )
        return warped_display_error(shown, previous, warp)


def popping_map(test: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) float32 ``max(0, test - reference)`` of two warped error maps of the same
    frame (module docstring): the warped error the reference does not have."""
    if test.shape != reference.shape:
        raise PhrtError(f"popping: maps of {test.shape} and {reference.shape}")
    return np.maximum(test - reference, np.float32(0.0)).astype(np.float32)


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
