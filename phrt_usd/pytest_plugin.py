"""The pytest plugin (entry point ``pytest11``, name ``phrt``): render stages in tests and
compare images against committed references. See ``docs/pipeline-tests.md``.

Installed with phrt-usd, pytest loads it in every project of that environment:

* fixtures ``phrt_render`` (a callable: ``phrt_render(stage_or_path, frames=None,
  **options) -> RenderResult``, each call into a new folder of the test's ``tmp_path``),
  ``phrt_open`` (``phrt_usd.open`` whose renderers are closed after the test),
  ``phrt_reference_dir`` (the test file's reference folder) and
  ``phrt_update_references`` (whether ``--phrt-update-references`` was given);
* ``assert_images_close(actual, reference, *, max_mean_flip, min_psnr)``: on failure it
  writes ``<test>.actual.png``, ``<test>.reference.png`` and ``<test>.error.png`` (the FLIP
  map) into ``phrt-failures/`` next to the test file and names them in the message;
* ``--phrt-update-references``: ``assert_images_close`` writes the actual image as the
  reference file instead of comparing (the terminal summary lists what it wrote);
* ini options ``phrt_reference_dir`` (default ``references``) and ``phrt_failure_dir``
  (default ``phrt-failures``), folders relative to each test file's folder.

Importing this module loads no renderer: the fixtures import ``phrt_usd.api`` when used.
"""

from __future__ import annotations

import itertools
import math
import numbers
import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from phrt_usd.atomic import atomic_path, write_text_atomic
from phrt_usd.errors import BadOption, PhrtError

if TYPE_CHECKING:
    from phrt_usd.api import Renderer, RenderResult

UPDATE_OPTION = "--phrt-update-references"
REFERENCE_DIR_INI = "phrt_reference_dir"
DEFAULT_REFERENCE_DIR = "references"
FAILURE_DIR_INI = "phrt_failure_dir"
DEFAULT_FAILURE_DIR = "phrt-failures"
#: Default bound on the mean FLIP error: the one under which this project calls two
#: renders the same picture (hybrid with every reflector traced vs the rt reference,
#: docs/design.md §3). An 8-bit PNG of a frame is ~0.007 from the frame itself.
DEFAULT_MAX_MEAN_FLIP = 0.02
#: Default lower bound on PSNR (dB). A mean over the frame misses a small change (a
#: 160x120 frame that lost its mirrored sphere is 0.017 in mean FLIP, but 26 dB); 8-bit
#: quantisation of a PNG reference alone costs at most 59 dB (uniform error of half a
#: step: 20 log10(255 * sqrt(12))), so 40 dB leaves room for it and for edge pixels that
#: rasterise differently on another OpenGL build.
DEFAULT_MIN_PSNR = 40.0
#: Image file kinds ``assert_images_close`` writes as references.
REFERENCE_SUFFIXES = (".png", ".exr")

#: An image: an (H, W, 3) array (float: linear RGB; uint8/uint16: sRGB-encoded) or a file.
ImageInput = np.ndarray | str | os.PathLike

#: The test running now and the pytest config (set by the hooks below).
_STATE: dict[str, Any] = {"item": None, "config": None}
_WRITTEN = pytest.StashKey[list]()


# --------------------------------------------------------------------------------------
# Hooks
# --------------------------------------------------------------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("phrt", "phrt-usd image comparisons")
    group.addoption(
        UPDATE_OPTION,
        action="store_true",
        default=False,
        help="assert_images_close writes the actual image as the reference file "
        "instead of comparing",
    )
    parser.addini(
        REFERENCE_DIR_INI,
        f"reference images folder, relative to each test file (default {DEFAULT_REFERENCE_DIR})",
        default=DEFAULT_REFERENCE_DIR,
    )
    parser.addini(
        FAILURE_DIR_INI,
        "folder for the images of failed comparisons, relative to each test file "
        f"(default {DEFAULT_FAILURE_DIR})",
        default=DEFAULT_FAILURE_DIR,
    )


def pytest_configure(config: pytest.Config) -> None:
    _STATE["config"] = config
    config.stash[_WRITTEN] = []


def pytest_unconfigure(config: pytest.Config) -> None:
    if _STATE["config"] is config:
        _STATE["config"] = None


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    _STATE["item"] = item
    try:
        return (yield)
    finally:
        _STATE["item"] = None


def pytest_terminal_summary(terminalreporter, exitstatus, config: pytest.Config) -> None:
    written = config.stash.get(_WRITTEN, [])
    if written:
        terminalreporter.section("phrt references written")
        for path in written:
            terminalreporter.write_line(str(path))


# --------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------


@pytest.fixture
def phrt_update_references(request: pytest.FixtureRequest) -> bool:
    """True when pytest runs with ``--phrt-update-references``."""
    return bool(request.config.getoption(UPDATE_OPTION))


@pytest.fixture
def phrt_reference_dir(request: pytest.FixtureRequest) -> Path:
    """The test file's reference folder (ini ``phrt_reference_dir``, default
    ``references/`` next to the test file); it need not exist yet."""
    return Path(request.path).parent / request.config.getini(REFERENCE_DIR_INI)


@pytest.fixture
def phrt_render(tmp_path: Path) -> Callable[..., RenderResult]:
    """``phrt_render(stage_or_path, frames=None, **options) -> RenderResult``:
    ``phrt_usd.render`` into a new folder of ``tmp_path`` per call (``render-0``, ...).
    Options as ``phrt_usd.render`` takes them; give ``budget_rays`` for a run that is the
    same on every machine (a time budget selects by the machine's speed)."""
    from phrt_usd.api import render

    count = itertools.count()

    def run(stage_or_path, frames=None, **options) -> RenderResult:
        return render(stage_or_path, tmp_path / f"render-{next(count)}", frames, **options)

    return run


@pytest.fixture
def phrt_open() -> Iterator[Callable[..., Renderer]]:
    """``phrt_open(stage_or_path, frames=None, **options) -> Renderer`` (``phrt_usd.open``);
    every renderer it made is closed when the test ends."""
    from phrt_usd.api import open as open_renderer

    made: list[Renderer] = []

    def run(stage_or_path, frames=None, **options) -> Renderer:
        made.append(open_renderer(stage_or_path, frames, **options))
        return made[-1]

    yield run
    for renderer in made:
        renderer.close()


# --------------------------------------------------------------------------------------
# assert_images_close
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageComparison:
    """The figures of a passed comparison: mean FLIP in [0, 1] and PSNR in dB
    (``evaluate.image_metrics``); None for both when the reference was written instead."""

    mean_flip: float | None
    psnr: float | None


def assert_images_close(
    actual: ImageInput,
    reference: ImageInput,
    *,
    max_mean_flip: float | None = DEFAULT_MAX_MEAN_FLIP,
    min_psnr: float | None = DEFAULT_MIN_PSNR,
    name: str | None = None,
    failure_dir: str | os.PathLike | None = None,
) -> ImageComparison:
    """Assert that ``actual`` looks like ``reference``: mean FLIP ≤ ``max_mean_flip`` and
    PSNR ≥ ``min_psnr`` (None: not checked; defaults ``DEFAULT_MAX_MEAN_FLIP``,
    ``DEFAULT_MIN_PSNR``), both on the tone-mapped LDR images (``evaluate.image_metrics``:
    what a viewer of the previews sees).

    Images: (H, W, 3) arrays (float: linear RGB as renders give; uint8 / uint16:
    sRGB-encoded) or image files (``.exr``: linear R, G, B; else 8/16-bit sRGB, e.g. PNG).
    On failure (or a missing reference, or images of two sizes) the actual, the reference
    and the FLIP error map are written as ``<test name>[.<name>].{actual,reference,error}.png``
    into the failure folder (``failure_dir``, else ``phrt-failures/`` next to the test
    file, else ``./phrt-failures`` outside a test) and the AssertionError names them; a
    passing comparison removes those of an earlier failure. With
    ``--phrt-update-references`` and a reference *file* (``.png`` or ``.exr``), the actual
    is written there instead and nothing is compared. Bad arguments raise ``BadOption`` /
    ``PhrtError`` before any metric runs (the FLIP library exits the process on bad
    input)."""
    __tracebackhide__ = True
    _check_thresholds(max_mean_flip, min_psnr)
    act = load_image(actual, "actual")
    paths = _failure_paths(name, failure_dir)
    ref_file = Path(reference) if isinstance(reference, str | os.PathLike) else None
    if ref_file is not None and _updating():
        write_reference(ref_file, act)
        _STATE["config"].stash[_WRITTEN].append(ref_file)
        _remove(paths)
        return ImageComparison(None, None)
    if ref_file is not None and not ref_file.is_file():
        _fail(f"no reference image {ref_file} (write it with pytest {UPDATE_OPTION})", paths, act)
    ref = load_image(reference, "reference")
    if act.shape != ref.shape:
        sizes = f"actual {act.shape[1]}x{act.shape[0]}, reference {ref.shape[1]}x{ref.shape[0]}"
        _fail(f"images differ in size: {sizes}", paths, act, ref)
    for label, image in (("actual", act), ("reference", ref)):
        bad = int((~np.isfinite(image)).any(axis=2).sum())
        if bad:
            _fail(f"{label} image has NaN/Inf in {bad} pixel(s)", paths, act, ref)
    from phrt_usd.evaluate.image_metrics import flip_map, psnr

    error = flip_map(ref, act)
    mean_flip, db = float(error.mean()), psnr(ref, act)
    wrong = []
    if max_mean_flip is not None and mean_flip > max_mean_flip:
        wrong.append(f"mean FLIP {mean_flip:.4f} > {max_mean_flip:g}")
    if min_psnr is not None and db < min_psnr:
        wrong.append(f"PSNR {db:.2f} dB < {min_psnr:g} dB")
    if wrong:
        _fail(f"images differ: {', '.join(wrong)}", paths, act, ref, error)
    _remove(paths)
    return ImageComparison(mean_flip, db)


def _check_thresholds(max_mean_flip: Any, min_psnr: Any) -> None:
    if max_mean_flip is None and min_psnr is None:
        raise BadOption("assert_images_close: give max_mean_flip or min_psnr")
    for label, value in (("max_mean_flip", max_mean_flip), ("min_psnr", min_psnr)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise BadOption(f"assert_images_close: {label} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise BadOption(f"assert_images_close: {label} must be finite, got {value}")
    if max_mean_flip is not None and not 0 <= max_mean_flip <= 1:
        raise BadOption(
            f"assert_images_close: max_mean_flip must be in [0, 1], got {max_mean_flip}"
        )


def _updating() -> bool:
    config = _STATE["config"]
    return bool(config is not None and config.getoption(UPDATE_OPTION))


# ---- images in and out ---------------------------------------------------------------


def load_image(image: ImageInput, label: str = "image") -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an array or image file (see
    ``assert_images_close``); PhrtError (one line) for anything else."""
    if isinstance(image, str | os.PathLike):
        image = _read_image_file(Path(image), label)
    if not isinstance(image, np.ndarray):
        raise PhrtError(f"{label}: expected an image array or file, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise PhrtError(f"{label}: expected an (H, W, 3) RGB image, got shape {image.shape}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise PhrtError(f"{label}: need at least 2x2 pixels, got {image.shape[1]}x{image.shape[0]}")
    if image.dtype in (np.uint8, np.uint16):
        return _srgb_decode(image.astype(np.float32) / np.iinfo(image.dtype).max)
    if image.dtype.kind != "f":
        raise PhrtError(f"{label}: pixels must be float (linear) or uint8/uint16 (sRGB), "
                        f"got {image.dtype}")  # fmt: skip
    return image.astype(np.float32, copy=False)


def _srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Linear values of sRGB-encoded ones in [0, 1] (the inverse of ``srgb_oetf``)."""
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4).astype(
        np.float32
    )


def _read_image_file(path: Path, label: str) -> np.ndarray:
    import OpenImageIO as oiio

    if not path.is_file():
        raise PhrtError(f"{label}: {path}: no such image file")
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise PhrtError(f"{label}: {path}: cannot open image ({oiio.geterror()})")
    try:
        names = list(image.spec().channelnames)
        linear = path.suffix.lower() == ".exr"
        data = image.read_image(oiio.FLOAT if linear else oiio.UINT16)
        if data is None:
            raise PhrtError(f"{label}: {path}: cannot read pixels ({image.geterror()})")
    finally:
        image.close()
    data = np.asarray(data)
    if data.ndim == 2:
        data = data[..., None]
    rgb = [names.index(c) for c in ("R", "G", "B")] if {"R", "G", "B"} <= set(names) else None
    if rgb is None and data.shape[2] in (1, 2):  # grey, grey + alpha
        rgb = [0, 0, 0]
    if rgb is None and data.shape[2] >= 3:
        rgb = [0, 1, 2]
    return data[..., rgb] if linear else data[..., rgb].astype(np.uint16)


def write_reference(path: Path, image: np.ndarray) -> None:
    """Write linear ``image`` as a reference file: ``.png`` the 8-bit sRGB preview
    (``run.images.write_preview_png``), ``.exr`` half-float linear RGB; atomically."""
    __tracebackhide__ = True
    from phrt_usd.run.images import write_preview_png

    path = Path(path)
    if path.suffix.lower() not in REFERENCE_SUFFIXES:
        raise BadOption(f"{path}: references are written as {' or '.join(REFERENCE_SUFFIXES)}")
    if not np.isfinite(image).all():
        raise AssertionError(f"actual image has NaN/Inf: not written as the reference {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".png":
        write_preview_png(path, image)
    else:
        _write_rgb_exr(path, image)


def _write_rgb_exr(path: Path, image: np.ndarray) -> None:
    import OpenImageIO as oiio

    from phrt_usd.run.images import HALF_MAX

    height, width = image.shape[:2]
    spec = oiio.ImageSpec(width, height, 3, oiio.HALF)
    spec.attribute("compression", "zip")
    spec.attribute("oiio:ColorSpace", "lin_rec709_scene")
    with atomic_path(path) as tmp:
        output = oiio.ImageOutput.create(str(tmp))
        pixels = np.ascontiguousarray(np.clip(image, -HALF_MAX, HALF_MAX), dtype=np.float32)
        ok = output is not None and output.open(str(tmp), spec) and output.write_image(pixels)
        if output is None or not (output.close() and ok):
            raise PhrtError(f"{path}: cannot write image ({oiio.geterror()})")


# ---- failure images --------------------------------------------------------------------


def _failure_paths(name: str | None, failure_dir: str | os.PathLike | None) -> dict[str, Path]:
    """Where a failed comparison's images go (see ``assert_images_close``)."""
    item, config = _STATE["item"], _STATE["config"]
    stem = _file_part(item.name) if item is not None else "image"
    if name:
        stem = f"{stem}.{_file_part(str(name))}" if item is not None else _file_part(str(name))
    if failure_dir is not None:
        folder = Path(failure_dir)
    elif item is not None and config is not None:
        folder = Path(item.path).parent / config.getini(FAILURE_DIR_INI)
    else:
        folder = Path.cwd() / DEFAULT_FAILURE_DIR
    return {kind: folder / f"{stem}.{kind}.png" for kind in ("actual", "reference", "error")}


def _file_part(text: str) -> str:
    """``test_shot[farm-200]`` → ``test_shot_farm-200_``: a file name on every system."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text).strip(".") or "image"


def _fail(message: str, paths, actual, reference=None, error=None):
    """Write the images that exist and raise AssertionError naming them."""
    __tracebackhide__ = True
    from phrt_usd.run.images import write_png_atomic, write_preview_png

    folder = paths["actual"].parent
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / ".gitignore").exists():  # failure images are never committed
        write_text_atomic(folder / ".gitignore", "# written by phrt_usd.pytest_plugin\n*\n")
    _remove(paths)
    written = []
    for kind, image in (("actual", actual), ("reference", reference)):
        if image is not None:
            write_preview_png(paths[kind], np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0))
            written.append(kind)
    if error is not None:
        write_png_atomic(paths["error"], _magma(error))
        written.append("error")
    item = _STATE["item"]
    if item is not None:
        item.user_properties.append(("phrt_images", [str(paths[k]) for k in written]))
    lines = "".join(f"\n  {kind + ':':<10} {paths[kind]}" for kind in written)
    raise AssertionError(f"{message}{lines}")


def _magma(error: np.ndarray) -> np.ndarray:
    """(H, W) FLIP error in [0, 1] → (H, W, 3) uint8 magma colours (FLIP's own palette)."""
    from matplotlib import colormaps

    rgb = colormaps["magma"](np.clip(error, 0.0, 1.0))[..., :3]
    return np.rint(rgb * 255.0).astype(np.uint8)


def _remove(paths: dict[str, Path]) -> None:
    for path in paths.values():
        path.unlink(missing_ok=True)
