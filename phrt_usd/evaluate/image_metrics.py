"""Image error against a reference: NVIDIA FLIP and PSNR, whole frame or under a mask (the
temporal error of a sequence, built on FLIP, is ``temporal_error``).

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


def check_pair(reference: np.ndarray, test: np.ndarray) -> None:
    """PhrtError unless both are finite (H, W, 3) images of one size, at least 2x2: what
    ``flip_display`` needs (flip_evaluator calls sys.exit on bad arguments)."""
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
    check_pair(reference, test)
    return flip_display(tonemap_ldr(reference), tonemap_ldr(test))


def flip_display(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """(H, W) float32 LDR-FLIP of two checked (H, W, 3) sRGB-encoded images in [0, 1]."""
    import flip_evaluator

    ref = np.ascontiguousarray(np.clip(reference, 0.0, 1.0), dtype=np.float32)
    tst = np.ascontiguousarray(np.clip(test, 0.0, 1.0), dtype=np.float32)
    error, _mean, _params = flip_evaluator.evaluate(
        ref, tst, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=False
    )
    error = np.asarray(error, dtype=np.float32)
    return error[..., 0] if error.ndim == 3 else error


def mean_over(values: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of an (H, W) map over ``mask`` (all pixels if None); 0.0 for an empty mask."""
    if mask is None:
        return float(values.mean())
    return float(values[mask].mean()) if mask.any() else 0.0


def psnr(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of the tone-mapped images (peak 1), over ``mask`` if given.

    Identical images (or an empty mask) give ``PSNR_IDENTICAL_DB``.
    """
    check_pair(reference, test)
    diff = (tonemap_ldr(reference) - tonemap_ldr(test)).astype(np.float64)
    sq = np.mean(diff * diff, axis=2)
    mse = mean_over(sq, mask)
    if mse <= 10.0 ** (-PSNR_IDENTICAL_DB / 10.0):
        return PSNR_IDENTICAL_DB
    return float(-10.0 * np.log10(mse))
