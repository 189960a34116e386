"""Image error against a reference: NVIDIA FLIP and PSNR, whole frame or under a mask (the
temporal error of a sequence, built on FLIP, is ``temporal_error``).

Both compare *LDR* images: linear renders go through ``images.tonemap_ldr`` (the same
tone map as the PNG previews) first, so the error is what a viewer of the previews sees.
FLIP runs in its LDR mode on sRGB-encoded input under its default viewing conditions,
stated here (``FLIP_VIEWING``: a 0.7 m wide display of 3840 pixels seen from 0.7 m, about
67 pixels per degree) and recorded in every sweep's provenance (``flip_settings``).

Images: (H, W, 3) float32 linear RGB, non-negative; masks (H, W) bool.
"""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.run.images import tonemap_ldr

#: FLIP's viewing conditions, as flip-evaluator takes them (``parameters={"vc": [...]}``):
#: the viewer's distance to the display (m), the display's width in pixels and in metres.
#: These are FLIP's own defaults (its paper's 0.7 m wide 4K monitor seen from 0.7 m),
#: stated so that they are recorded and never change with a flip-evaluator release.
FLIP_MONITOR_DISTANCE_M = 0.7
FLIP_MONITOR_RESOLUTION_X = 3840
FLIP_MONITOR_WIDTH_M = 0.7
FLIP_VIEWING = (FLIP_MONITOR_DISTANCE_M, FLIP_MONITOR_RESOLUTION_X, FLIP_MONITOR_WIDTH_M)

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
        ref, tst, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=False,
        parameters={"vc": list(FLIP_VIEWING)},
    )  # fmt: skip
    error = np.asarray(error, dtype=np.float32)
    return error[..., 0] if error.ndim == 3 else error


def flip_pixels_per_degree() -> float:
    """Pixels per degree of visual angle of ``FLIP_VIEWING`` (FLIP's formula: distance x
    pixels per metre x pi / 180; 67.02 for FLIP's defaults)."""
    return FLIP_MONITOR_DISTANCE_M * (FLIP_MONITOR_RESOLUTION_X / FLIP_MONITOR_WIDTH_M) * (
        math.pi / 180.0
    )


def flip_settings() -> dict:
    """How FLIP is run here, for a result's provenance: the mode, the input, the viewing
    conditions and flip-evaluator's version."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        release = version("flip-evaluator")
    except PackageNotFoundError:
        release = "unknown"
    return {
        "metric": "LDR-FLIP",
        "implementation": f"flip-evaluator {release}",
        "input": "sRGB-encoded by tonemap_ldr (clamp to [0, 1], sRGB OETF)",
        "monitor_distance_m": FLIP_MONITOR_DISTANCE_M,
        "monitor_width_m": FLIP_MONITOR_WIDTH_M,
        "monitor_resolution_x": FLIP_MONITOR_RESOLUTION_X,
        "pixels_per_degree": round(flip_pixels_per_degree(), 4),
    }


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
