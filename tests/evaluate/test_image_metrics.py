"""FLIP and PSNR: zero error for identical images, growing with a planted difference."""

from __future__ import annotations

import numpy as np
import pytest

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.image_metrics import PSNR_IDENTICAL_DB, flip_map, mean_over, psnr


def _image(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0.05, 0.8, 64 * 48 * 3).reshape(48, 64, 3)
    return (base + 0.05 * rng.random((48, 64, 3))).astype(np.float32)


def test_identical_images_have_no_error():
    img = _image()
    assert float(flip_map(img, img).max()) == 0.0
    assert psnr(img, img) == PSNR_IDENTICAL_DB


@pytest.mark.slow
def test_error_grows_with_the_planted_difference():
    ref = _image()
    flips, psnrs = [], []
    for amount in (0.05, 0.2, 0.6):
        test = ref.copy()
        test[10:30, 20:40] += amount  # a planted bright patch
        error = flip_map(ref, test)
        mask = np.zeros(ref.shape[:2], dtype=bool)
        mask[10:30, 20:40] = True
        assert mean_over(error, ~mask) < 0.5 * mean_over(error, mask)  # error is where planted
        flips.append(mean_over(error))
        psnrs.append(psnr(ref, test))
    assert flips[0] < flips[1] < flips[2]
    assert psnrs[0] > psnrs[1] > psnrs[2]
    assert psnr(ref, test, mask=~mask) == PSNR_IDENTICAL_DB  # untouched pixels match


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((48, 64), np.float32),
        np.zeros((1, 64, 3), np.float32),
        np.full((48, 64, 3), np.nan),
    ],
)
def test_bad_input_is_a_clear_error_not_an_exit(bad):
    # flip_evaluator calls sys.exit on bad arguments; ours must raise PhrtError first.
    with pytest.raises(PhrtError):
        flip_map(bad, bad)
