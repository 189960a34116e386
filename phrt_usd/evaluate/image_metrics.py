"""Image error against a reference: NVIDIA FLIP and PSNR, whole frame or under a mask,
and the temporal error of a sequence (``temporal_error_map``, docs/temporal-error.md).

Both compare *LDR* images: linear renders go through ``images.tonemap_ldr`` (the same
tone map as the PNG previews) first, so the error is what a viewer of the previews sees.
FLIP runs in its LDR mode on sRGB-encoded input at its default 67 pixels per degree.

Images: (H, W, 3) float32 linear RGB, non-negative; masks (H, W) bool.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.run.images import tonemap_ldr

#: PSNR reported for identical images (the true value is +inf, which JSON/CSV cannot hold).
PSNR_IDENTICAL_DB = 100.0


#: Display mapping of a frame-to-frame change: a change ``d`` in [-1, 1] (difference of two
#: sRGB-encoded frames) is shown as ``CHANGE_GREY + CHANGE_SCALE * d`` in [0, 1], i.e. on
#: a mid-grey at half amplitude, so that every possible change fits the display range
#: without clipping (docs/temporal-error.md).
CHANGE_GREY = 0.5
CHANGE_SCALE = 0.5


def _check_pair(reference: np.ndarray, test: np.ndarray) -> None:
    # flip_evaluator calls sys.exit on bad arguments: validate everything first.
    if reference.shape != test.shape or reference.ndim != 3 or reference.shape[2] != 3:
        raise PhrtError(
            f"image metrics need two (H, W, 3) images of one size, got {reference.shape} "
            f"and {test.shape}"
        )
    if reference.shape[0] < 2 or reference.shape[1] < 2:
        raise PhrtError(f"image metrics need at least 2x2 pixels, got {reference.shape[:2]}")
    for name, img in (("reference", reference), ("test", test)):
        if not np.all(np.isfinite(img)):
            raise PhrtError(f"{name} image contains NaN or Inf")


def flip_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """(H, W) float32 FLIP error in [0, 1] between two linear images (after tone mapping)."""
    _check_pair(reference, test)
    return _flip_display(tonemap_ldr(reference), tonemap_ldr(test))


def _flip_display(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """(H, W) float32 LDR-FLIP of two checked (H, W, 3) sRGB-encoded images in [0, 1]."""
    import flip_evaluator

    ref = np.ascontiguousarray(np.clip(reference, 0.0, 1.0), dtype=np.float32)
    tst = np.ascontiguousarray(np.clip(test, 0.0, 1.0), dtype=np.float32)
    error, _mean, _params = flip_evaluator.evaluate(
        ref, tst, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=False
    )
    error = np.asarray(error, dtype=np.float32)
    return error[..., 0] if error.ndim == 3 else error


def change_image(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 display image of the change from ``previous`` to ``current``
    (linear (H, W, 3) frames): ``CHANGE_GREY + CHANGE_SCALE * (ldr(current) -
    ldr(previous))`` with ``ldr = tonemap_ldr``; in [0, 1] by construction (each ldr value
    is in [0, 1], so the difference is in [-1, 1])."""
    delta = tonemap_ldr(current).astype(np.float32) - tonemap_ldr(previous).astype(np.float32)
    return np.float32(CHANGE_GREY) + np.float32(CHANGE_SCALE) * delta


def temporal_error_map(
    reference_previous: np.ndarray,
    reference: np.ndarray,
    test_previous: np.ndarray,
    test: np.ndarray,
) -> np.ndarray:
    """(H, W) float32 temporal error in [0, 1] of frame t of a test sequence.

    The LDR-FLIP between the reference's frame-to-frame change and the test's, each shown
    as a display image by ``change_image``::

        T_t = FLIP(change_image(R_{t-1}, R_t), change_image(H_{t-1}, H_t))

    0 where the test changes exactly as the reference does (identical sequences, or an
    error that stays the same from frame to frame); high where the test pops (a change
    the reference does not have, e.g. a reflector switching between raster and traced).
    All four images: (H, W, 3) linear RGB, finite, one size (PhrtError otherwise).
    See docs/temporal-error.md for the reasoning and limits.
    """
    _check_pair(reference, test)
    _check_pair(reference, reference_previous)
    _check_pair(reference, test_previous)
    return _flip_display(
        change_image(reference_previous, reference), change_image(test_previous, test)
    )


def mean_over(values: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of an (H, W) map over ``mask`` (all pixels if None); 0.0 for an empty mask."""
    if mask is None:
        return float(values.mean())
    return float(values[mask].mean()) if mask.any() else 0.0


def psnr(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of the tone-mapped images (peak 1), over ``mask`` if given.

    Identical images (or an empty mask) give ``PSNR_IDENTICAL_DB``.
    """
    _check_pair(reference, test)
    diff = (tonemap_ldr(reference) - tonemap_ldr(test)).astype(np.float64)
    sq = np.mean(diff * diff, axis=2)
    mse = mean_over(sq, mask)
    if mse <= 10.0 ** (-PSNR_IDENTICAL_DB / 10.0):
        return PSNR_IDENTICAL_DB
    return float(-10.0 * np.log10(mse))
