"""The pytest plugin (entry point pytest11 `phrt`) as a pipeline uses it: a throw-away
project in a temp dir whose tests render its stage and compare against references, run in
a fresh pytest process; and assert_images_close's checks in this process."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scenes import mirror_floor_stage

# Imported before any pytester fixture: pytester removes the modules a test imported when
# it ends, and the image libraries' bindings abort the process when imported twice.
import phrt_usd.evaluate.image_metrics  # noqa: F401
import phrt_usd.run.images  # noqa: F401
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.pytest_plugin import DEFAULT_MIN_PSNR, assert_images_close, load_image

pytest_plugins = ["pytester"]

#: The throw-away project's test module: the worked example of docs/pipeline-tests.md.
PIPELINE_TESTS = '''
from pathlib import Path

from phrt_usd.pytest_plugin import assert_images_close

STAGE = Path(__file__).parent / "shot.usda"
RAYS = 1_000_000  # a rays budget: the same selection on every machine


def test_hybrid_shot_matches_reference(phrt_render, phrt_reference_dir):
    result = phrt_render(STAGE, budget_rays=RAYS)
    assert result.summary["frames"] == 1 and result.summary["mean_selected"] == 1
    assert_images_close(result.read_frame()["beauty"], phrt_reference_dir / "shot.png")


def test_raster_shot_matches_reference(phrt_render, phrt_reference_dir):
    result = phrt_render(STAGE, mode="raster")  # no ray-traced mirror: must fail
    assert_images_close(result.read_frame()["beauty"], phrt_reference_dir / "shot.png")
'''


@pytest.fixture
def pipeline(pytester):
    """A pipeline repository: a stage (mirror floor, red sphere) and its tests."""
    mirror_floor_stage(pytester.path / "shot.usda")
    pytester.makepyfile(test_shot=PIPELINE_TESTS)
    return pytester


def _failure_images(output: str) -> dict[str, str]:
    return dict(re.findall(r"^E?\s+(actual|reference|error):\s+(\S+\.png)$", output, re.M))


def test_pipeline_tests_with_references(pipeline):
    references = pipeline.path / "references"
    failures = pipeline.path / "phrt-failures"

    # 1. No reference yet: both tests fail, naming the option that writes them.
    first = pipeline.runpytest_subprocess("-p", "no:cacheprovider")
    first.assert_outcomes(failed=2)
    first.stdout.fnmatch_lines(["*no reference image *shot.png (write it with pytest "
                                "--phrt-update-references)*"])  # fmt: skip
    assert (failures / "test_hybrid_shot_matches_reference.actual.png").is_file()
    assert (failures / ".gitignore").read_text().strip().endswith("*")

    # 2. Regenerate the reference from the hybrid render.
    update = pipeline.runpytest_subprocess("--phrt-update-references", "-k", "hybrid")
    update.assert_outcomes(passed=1, deselected=1)
    update.stdout.fnmatch_lines(["*phrt references written*", f"{references / 'shot.png'}"])
    assert load_image(references / "shot.png").shape == (120, 160, 3)

    # 3. Compare: the hybrid render passes (its stale failure image is removed), the
    #    raster one, without the mirrored sphere, fails and writes the three images.
    second = pipeline.runpytest_subprocess()
    second.assert_outcomes(passed=1, failed=1)
    output = second.stdout.str()
    assert re.search(rf"images differ: .*PSNR \d+\.\d+ dB < {DEFAULT_MIN_PSNR:g} dB", output)
    images = _failure_images(output)
    assert set(images) == {"actual", "reference", "error"}
    stem = failures / "test_raster_shot_matches_reference"
    for kind, path in images.items():
        assert path == f"{stem}.{kind}.png" and load_image(path).shape == (120, 160, 3)
    assert not (failures / "test_hybrid_shot_matches_reference.actual.png").exists()
    actual, reference = load_image(images["actual"]), load_image(images["reference"])
    assert not np.array_equal(actual, reference)
    np.testing.assert_array_equal(reference, load_image(references / "shot.png"))

    # 4. The hybrid test alone passes: the run is green.
    assert pipeline.runpytest_subprocess("-k", "hybrid").ret == 0


def test_fixtures_of_the_plugin(pipeline):
    pipeline.makepyfile(
        test_fixtures="""
        from pathlib import Path

        def test_fixtures(phrt_render, phrt_open, phrt_reference_dir, phrt_update_references,
                          tmp_path):
            stage = Path(__file__).parent / "shot.usda"
            first, second = phrt_render(stage, mode="raster"), phrt_render(stage, mode="raster")
            assert first.out.parent == second.out.parent == tmp_path != first.out
            renderer = phrt_open(stage, mode="raster", resolution=(32, 24))
            assert renderer.render(1).beauty.shape == (24, 32, 3)
            assert phrt_reference_dir == Path(__file__).parent / "refs"
            assert phrt_update_references is False
            pytest_renderer.append(renderer)

        pytest_renderer = []

        def test_renderer_closed_after_the_test():
            assert pytest_renderer[0].closed
        """
    )
    pipeline.makeini("[pytest]\nphrt_reference_dir = refs\n")
    pipeline.runpytest_subprocess("test_fixtures.py").assert_outcomes(passed=2)


# ---- assert_images_close in this process ---------------------------------------------


def _image(seed: int = 0, shape=(24, 32, 3)) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, shape).astype(np.float32)


def test_close_images_pass_and_report_their_figures(tmp_path):
    image = _image()
    same = assert_images_close(image, image.copy(), failure_dir=tmp_path)
    assert same.mean_flip == 0.0 and same.psnr == 100.0
    noisy = np.clip(image + _image(1) * 1e-3, 0, None)
    figures = assert_images_close(noisy, image, failure_dir=tmp_path)
    assert 0 < figures.mean_flip < 0.02 and figures.psnr > DEFAULT_MIN_PSNR
    assert list(tmp_path.iterdir()) == []  # nothing written for a pass


def test_different_images_fail_with_the_three_images(tmp_path):
    with pytest.raises(AssertionError) as failed:
        assert_images_close(_image(0), _image(1), failure_dir=tmp_path, name="noise")
    message = str(failed.value)
    assert "mean FLIP" in message and "PSNR" in message
    stem = "test_different_images_fail_with_the_three_images.noise"
    for kind in ("actual", "reference", "error"):
        path = tmp_path / f"{stem}.{kind}.png"
        assert f"{path}" in message and load_image(path).shape == (24, 32, 3)
    # A threshold left out is not checked: the same pair passes on a lenient FLIP alone.
    assert_images_close(_image(0), _image(1), max_mean_flip=1.0, min_psnr=None)


def test_sizes_and_non_finite_pixels_fail_as_assertions(tmp_path):
    with pytest.raises(AssertionError, match="differ in size: actual 32x24, reference 16x8"):
        assert_images_close(_image(), _image(shape=(8, 16, 3)), failure_dir=tmp_path)
    bad = _image()
    bad[3, 4, 1] = np.nan
    with pytest.raises(AssertionError, match=r"actual image has NaN/Inf in 1 pixel"):
        assert_images_close(bad, _image(), failure_dir=tmp_path)


@pytest.mark.parametrize(
    "actual,message",
    [
        (np.zeros((24, 32)), r"\(H, W, 3\)"),
        (np.zeros((1, 32, 3)), "at least 2x2"),
        (np.zeros((24, 32, 3), dtype=np.complex64), "must be float"),
        (np.zeros((24, 32, 3), dtype=bool), "must be float"),
        ([[0.0]], "expected an image array or file"),
        ("missing.png", "no such image file"),
    ],
    ids=["2d", "1px", "complex", "bool", "list", "missing"],
)
def test_bad_images_raise_before_any_metric(actual, message, tmp_path):
    with pytest.raises(PhrtError, match=message):
        assert_images_close(actual, _image(), failure_dir=tmp_path)


@pytest.mark.parametrize(
    "thresholds,message",
    [
        ({"max_mean_flip": None, "min_psnr": None}, "give max_mean_flip or min_psnr"),
        ({"max_mean_flip": 1.5}, r"in \[0, 1\]"),
        ({"min_psnr": float("nan")}, "finite"),
        ({"min_psnr": "40"}, "must be a number"),
    ],
)
def test_bad_thresholds_raise_bad_option(thresholds, message):
    with pytest.raises(BadOption, match=message):
        assert_images_close(_image(), _image(), **thresholds)


def test_png_and_8_bit_images_are_srgb_and_exr_is_linear(tmp_path):
    from phrt_usd.pytest_plugin import write_reference
    from phrt_usd.run.images import srgb_oetf

    image = _image(shape=(12, 16, 3))
    write_reference(tmp_path / "ref.png", image)
    write_reference(tmp_path / "ref.exr", image)
    np.testing.assert_allclose(load_image(tmp_path / "ref.exr"), image, rtol=2**-10, atol=1e-6)
    # The PNG holds the 8-bit sRGB preview: decoded to linear, re-encoded it is the preview.
    png = srgb_oetf(load_image(tmp_path / "ref.png"))
    assert np.abs(png - srgb_oetf(image)).max() <= 0.5 / 255 + 1e-6
    assert_images_close(image, tmp_path / "ref.png")  # quantisation stays within defaults
    with pytest.raises(BadOption, match="written as .png or .exr"):
        write_reference(tmp_path / "ref.jpg", image)
