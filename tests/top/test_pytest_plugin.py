"""The pytest plugin (entry point pytest11 `phrt`) as a pipeline uses it: a throw-away
project in a temp dir whose tests render its stage and compare against references, run in
a fresh pytest process; and assert_images_close's checks in this process."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom
from scenes import mirror_floor_stage

# Imported before any pytester fixture: pytester removes the modules a test imported when
# it ends, and the image libraries' bindings abort the process when imported twice.
import phrt_usd.evaluate.image_metrics  # noqa: F401
import phrt_usd.run.images  # noqa: F401
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.pytest_plugin import (
    DEFAULT_MAX_MEAN_FLIP,
    DEFAULT_MIN_PSNR,
    MAX_STEM,
    _short,
    assert_images_close,
    load_image,
)
from phrt_usd.run.images import srgb_oetf
from phrt_usd.usd import schema

pytest_plugins = ["pytester"]

#: The user's cache folder, read before pytester points HOME at its temporary folder:
#: the throw-away projects' renders load phrt's compiled kernels from the user's cache
#: (``$XDG_CACHE_HOME/phrt-usd``) instead of compiling them afresh in every pytest run.
USER_CACHE = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
#: The throw-away project's frame: small, so that each pytest run renders in a second.
WIDTH, HEIGHT = 64, 48
#: The backdrop's flat colour: 8-bit rounding of this wall as the stage lights it costs
#: ~0.028 in mean FLIP on its own (measured over 40 random colours, the largest), above
#: DEFAULT_MAX_MEAN_FLIP: a PNG reference of the frame fails an identical re-render
#: unless the comparison takes the PNG's rounding out.
WALL_COLOUR = (0.438, 0.892, 0.614)
#: The changed stage's ball colour (red before): what a look change does to a shot.
CHANGED_BALL = (0.05, 0.2, 0.9)

#: The throw-away project's test module: the worked example of docs/pipeline-tests.md,
#: its references in both kinds (the default EXR and a PNG preview).
PIPELINE_TESTS = """
from pathlib import Path

from phrt_usd.pytest_plugin import assert_images_close

STAGE = Path(__file__).parent / "shot.usda"


def test_shot_matches_its_reference(phrt_render):
    result = phrt_render(STAGE)  # no time budget: the frame depends on the stage alone
    assert result.summary["frames"] == 1 and result.summary["mean_selected"] == 1
    figures = assert_images_close(result.read_frame()["beauty"])  # references/test_shot/
    # An identical re-render: the same pixels, and the EXR reference holds them exactly.
    assert figures.mean_flip in (None, 0.0)


def test_shot_matches_its_png_reference(phrt_render, phrt_reference):
    figures = assert_images_close(
        phrt_render(STAGE).read_frame()["beauty"], phrt_reference(suffix=".png")
    )
    # The PNG's 8-bit rounding is taken out of the comparison: exactly equal again.
    assert figures.mean_flip in (None, 0.0)
"""


def shot_stage(path):
    """mirror_floor_stage at WIDTH x HEIGHT with a flat WALL_COLOUR wall behind the ball
    (the wall at z = -3, 40 m wide, from y = -5 to 20 m, facing the camera)."""
    mirror_floor_stage(path, WIDTH, HEIGHT)
    stage = Usd.Stage.Open(str(path))
    wall = UsdGeom.Mesh.Define(stage, "/World/Wall")
    wall.CreatePointsAttr([(-20, -5, -3), (20, -5, -3), (20, 20, -3), (-20, 20, -3)])
    wall.CreateFaceVertexCountsAttr([4])
    wall.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    wall.CreateDisplayColorAttr([Gf.Vec3f(*WALL_COLOUR)])
    stage.GetRootLayer().Save()
    return path


@pytest.fixture
def project(pytester, monkeypatch):
    """An empty throw-away project whose pytest runs use the user's kernel cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", USER_CACHE)
    return pytester


@pytest.fixture
def pipeline(project):
    """A pipeline repository: a stage (mirror floor, red ball, flat wall) and its tests."""
    pytester = project
    shot_stage(pytester.path / "shot.usda")
    pytester.makepyfile(test_shot=PIPELINE_TESTS)
    return pytester


def _failure_images(output: str) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for kind, path in re.findall(r"^E?\s+(actual|reference|error):\s+(\S+\.png)$", output, re.M):
        found.setdefault(kind, []).append(path)
    return found


@pytest.mark.slow
def test_update_then_identical_rerender_passes_then_changed_stage_fails(pipeline):
    """The CI's sequence: references written by --phrt-update-references, the identical
    render passing (PNG reference of flat colours included), a changed material colour
    failing with the failure images."""
    own = pipeline.path / "references" / "test_shot"
    failures = pipeline.path / "phrt-failures" / "test_shot"
    exr = own / "test_shot_matches_its_reference.exr"
    png = own / "test_shot_matches_its_png_reference.png"

    # 1. Write the references: each named after its test, in a folder of the module.
    update = pipeline.runpytest_subprocess("--phrt-update-references", "-p", "no:cacheprovider")
    update.assert_outcomes(passed=2)
    update.stdout.fnmatch_lines(["*phrt references written*"])
    update.stdout.fnmatch_lines([str(exr)])
    update.stdout.fnmatch_lines([str(png)])
    assert load_image(exr).shape == load_image(png).shape == (HEIGHT, WIDTH, 3)

    # 2. The identical render passes against both (the throw-away tests assert mean FLIP 0).
    pipeline.runpytest_subprocess("-p", "no:cacheprovider").assert_outcomes(passed=2)
    assert not failures.exists()

    # 3. A changed material colour fails both, each writing its three images.
    stage = Usd.Stage.Open(str(pipeline.path / "shot.usda"))
    UsdGeom.Gprim(stage.GetPrimAtPath("/World/Ball")).GetDisplayColorAttr().Set(
        [Gf.Vec3f(*CHANGED_BALL)]
    )
    stage.GetRootLayer().Save()
    changed = pipeline.runpytest_subprocess("-p", "no:cacheprovider")
    changed.assert_outcomes(failed=2)
    output = changed.stdout.str()
    # Counted in the failures' own tracebacks ("E   AssertionError: ..."): the short summary
    # repeats the message as wide as the terminal is, which differs between machines.
    raised = r"^E +AssertionError: images differ: .*PSNR \d+\.\d+ dB < 40 dB"
    assert len(re.findall(raised, output, flags=re.MULTILINE)) == 2
    images = _failure_images(output)
    for test, reference in (("test_shot_matches_its_reference", exr),
                            ("test_shot_matches_its_png_reference", png)):  # fmt: skip
        for kind in ("actual", "reference", "error"):
            path = failures / f"{test}.{kind}.png"
            assert str(path) in images[kind] and load_image(path).shape == (HEIGHT, WIDTH, 3)
        actual = load_image(failures / f"{test}.actual.png")
        # The failure's reference image is the reference file's preview (8-bit rounding:
        # half a step of 255 after the sRGB encoding, compared encoded).
        shown = srgb_oetf(load_image(failures / f"{test}.reference.png"))
        assert np.abs(shown - srgb_oetf(load_image(reference))).max() <= 0.5 / 255 + 1e-6
        assert not np.array_equal(actual, load_image(failures / f"{test}.reference.png"))
    assert (failures / ".gitignore").read_text().strip().endswith("*")


#: Two tests and more rendering one stage, each with its own reference, and two tests
#: naming one file (the second fails, naming the first).
PAIR_TESTS = """
from pathlib import Path

import pytest

from phrt_usd.pytest_plugin import assert_images_close

STAGE = Path(__file__).parent / "shot.usda"


def test_hybrid(phrt_render):
    assert_images_close(phrt_render(STAGE).read_frame()["beauty"])


def test_raster(phrt_render):
    assert_images_close(phrt_render(STAGE, mode="raster").read_frame()["beauty"])


@pytest.mark.parametrize("mode", ["hybrid", "raster"])
def test_modes(phrt_render, mode):
    assert_images_close(phrt_render(STAGE, mode=mode).read_frame()["beauty"])


class TestShot:
    def test_hybrid(self, phrt_render):
        assert_images_close(phrt_render(STAGE).read_frame()["beauty"])


def test_first_of_a_shared_file(phrt_render, phrt_reference_dir):
    image = phrt_render(STAGE).read_frame()["beauty"]
    assert_images_close(image, phrt_reference_dir / "shared.exr")


def test_second_of_a_shared_file(phrt_render, phrt_reference_dir):
    image = phrt_render(STAGE, mode="raster").read_frame()["beauty"]
    assert_images_close(image, phrt_reference_dir / "shared.exr")
"""


@pytest.mark.slow
def test_two_tests_rendering_one_stage_get_their_own_reference_files(project):
    pytester = project
    shot_stage(pytester.path / "shot.usda")
    pytester.makepyfile(test_pair=PAIR_TESTS)
    own = pytester.path / "references" / "test_pair"

    update = pytester.runpytest_subprocess("--phrt-update-references", "-p", "no:cacheprovider")
    update.assert_outcomes(passed=6, failed=1)
    update.stdout.fnmatch_lines(["*shared.exr is already the reference of "
                                 "test_pair.py::test_first_of_a_shared_file*"])  # fmt: skip
    names = ["test_hybrid", "test_raster", "test_modes_hybrid_", "test_modes_raster_",
             "TestShot.test_hybrid"]  # fmt: skip
    assert sorted(p.name for p in own.iterdir()) == sorted(f"{n}.exr" for n in names)
    # The raster render has no mirrored ball: the two files hold two different frames.
    hybrid, raster = load_image(own / "test_hybrid.exr"), load_image(own / "test_raster.exr")
    assert not np.array_equal(hybrid, raster)

    # Each compares against its own: none was overwritten by another test's image.
    compare = pytester.runpytest_subprocess("-k", "not shared", "-p", "no:cacheprovider")
    compare.assert_outcomes(passed=5, deselected=2)


#: A time budget no reflector fits in (ms): the stage's own budget selects nothing.
TIGHT_BUDGET_MS = 0.001


@pytest.mark.slow
def test_fixtures_of_the_plugin(pipeline):
    tight = Usd.Stage.Open(str(shot_stage(pipeline.path / "tight.usda")))
    schema.apply_render_settings(tight.GetPrimAtPath("/Render/Settings"), budget_ms=TIGHT_BUDGET_MS)
    tight.GetRootLayer().Save()
    pipeline.makepyfile(
        test_fixtures="""
        from pathlib import Path

        import phrt_usd

        def test_fixtures(phrt_render, phrt_open, phrt_reference_dir, phrt_reference,
                          phrt_update_references, tmp_path):
            stage = Path(__file__).parent / "shot.usda"
            first, second = phrt_render(stage, mode="raster"), phrt_render(stage, mode="raster")
            assert first.out.parent == second.out.parent == tmp_path != first.out
            renderer = phrt_open(stage, mode="raster", resolution=(32, 24))
            assert renderer.render(1).beauty.shape == (24, 32, 3)
            assert phrt_reference_dir == Path(__file__).parent / "refs"
            own = phrt_reference_dir / "test_fixtures" / "test_fixtures"
            assert phrt_reference() == own.with_suffix(".exr")
            assert phrt_reference("1001", ".png") == own.parent / "test_fixtures.1001.png"
            assert phrt_update_references is False
            pytest_renderer.append(renderer)

        pytest_renderer = []

        def test_renderer_closed_after_the_test():
            assert pytest_renderer[0].closed

        def test_no_time_budget_unless_given(phrt_render, tmp_path):
            tight = Path(__file__).parent / "tight.usda"
            # The stage's own time budget: nothing fits, the mirror is not traced ...
            assert phrt_usd.render(tight, tmp_path / "own").summary["mean_selected"] == 0
            # ... the fixture's default: no time budget, the frame depends on the stage.
            assert phrt_render(tight).summary["mean_selected"] == 1
            # A rays budget given is kept (and is as deterministic).
            assert phrt_render(tight, budget_rays=1).summary["mean_selected"] == 0
        """
    )
    pipeline.makeini("[pytest]\nphrt_reference_dir = refs\n")
    pipeline.runpytest_subprocess("test_fixtures.py").assert_outcomes(passed=3)


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


#: A flat colour whose 8-bit rounding alone is ~0.039 in mean FLIP (the largest of 300
#: random colours; their median is ~0.019): a PNG of it fails DEFAULT_MAX_MEAN_FLIP
#: against the very frame it was written from, unless the rounding is taken out.
FLAT_COLOUR = (0.0344, 0.987, 0.817)


@pytest.mark.slow
def test_stored_references_compare_equal_to_the_frame_they_were_written_from(tmp_path):
    """A re-render of a frame against the reference written from it: no difference in
    any storage (PNG, half EXR, 8/16-bit arrays); the rounding is taken out, not allowed for."""
    from phrt_usd.evaluate.image_metrics import flip_map
    from phrt_usd.pytest_plugin import write_reference

    flat = np.broadcast_to(np.float32(FLAT_COLOUR), (24, 32, 3)).copy()
    frame = np.clip(flat + _image(2, flat.shape) * 0.05, 0.0, None)  # a little texture
    for image in (flat, frame):
        write_reference(tmp_path / "ref.png", image)
        write_reference(tmp_path / "ref.exr", image)
        png = load_image(tmp_path / "ref.png")
        if image is flat:  # what comparing as stored would give: the reported failure
            assert flip_map(png, image).mean() > DEFAULT_MAX_MEAN_FLIP
        for reference in (tmp_path / "ref.png", tmp_path / "ref.exr", image.astype(np.float16)):
            figures = assert_images_close(image, reference, failure_dir=tmp_path)
            assert (figures.mean_flip, figures.psnr) == (0.0, 100.0)
        encoded = np.rint(srgb_oetf(image) * 65535).astype(np.uint16)
        assert assert_images_close(image, encoded).mean_flip == 0.0  # 16-bit sRGB array
        assert assert_images_close(tmp_path / "ref.png", image).mean_flip == 0.0  # either side
    # A float reference is compared as it is: the 8-bit actual's rounding counts there.
    with pytest.raises(AssertionError, match="mean FLIP"):
        assert_images_close(tmp_path / "ref.png", frame * 0 + flat, failure_dir=tmp_path)


def test_long_test_names_make_short_file_names_that_stay_distinct():
    long_a, long_b = "test_" + "a" * 300, "test_" + "a" * 299 + "b"
    assert len(_short(long_a)) == MAX_STEM and _short(long_a) != _short(long_b)
    assert _short("test_shot_farm_200_") == "test_shot_farm_200_"
