"""The pytest plugin (entry point ``pytest11``, name ``phrt``): render stages in tests and
compare images against committed references. See ``docs/pipeline-tests.md``.

Installed with phrt-usd, pytest loads it in every project of that environment:

* fixtures ``phrt_render`` (a callable: ``phrt_render(stage_or_path, frames=None,
  **options) -> RenderResult``, each call into a new folder of the test's ``tmp_path``;
  without a budget option no time budget, so a frame renders the same every time),
  ``phrt_open`` (``phrt_usd.open`` likewise, whose renderers are closed after the test),
  ``phrt_reference`` (this test's own reference file), ``phrt_reference_dir`` (the test
  file's reference folder) and ``phrt_update_references`` (whether
  ``--phrt-update-references`` was given);
* ``assert_images_close(actual, reference=None, *, max_mean_flip, min_psnr)``: the
  reference defaults to the test's own file, ``references/<module>/<test>.exr`` next to
  the test file (pytest-regressions' naming; one file is never two tests' reference);
  both images are compared at the coarser one's storage, so a re-render of the frame
  compares equal to the reference it wrote; on failure it writes ``<test>.actual.png``,
  ``<test>.reference.png`` and ``<test>.error.png`` (the FLIP map) into
  ``phrt-failures/<module>/`` next to the test file and names them in the message;
* ``--phrt-update-references``: ``assert_images_close`` writes the actual image as the
  reference file instead of comparing (the terminal summary lists what it wrote);
* ini options ``phrt_reference_dir`` (default ``references``) and ``phrt_failure_dir``
  (default ``phrt-failures``), folders relative to each test file's folder.

Importing this module loads no renderer: the fixtures import ``phrt_usd.api`` when used.
"""

from __future__ import annotations

import hashlib
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
#: docs/design.md §3). It bounds what rendering may change, not storage: the rounding of
#: a stored reference is taken out of every comparison (``PRECISIONS``), since 8-bit
#: rounding alone costs a frame of flat colours up to ~0.04 in mean FLIP.
DEFAULT_MAX_MEAN_FLIP = 0.02
#: Default lower bound on PSNR (dB). A mean over the frame misses a small change (a
#: 160x120 frame that lost its mirrored sphere is 0.017 in mean FLIP, but 26 dB); 40 dB
#: leaves room for edge pixels that rasterise differently on another OpenGL build (the
#: same build renders the same frame to the same pixels: 100 dB, ``PSNR_IDENTICAL_DB``).
DEFAULT_MIN_PSNR = 40.0
#: Image file kinds ``assert_images_close`` writes as references.
REFERENCE_SUFFIXES = (".png", ".exr")
#: The kind of a test's own reference (``phrt_reference``): half-float linear EXR, the
#: storage of a frame's beauty in phrt's EXRs, so the reference holds the frame exactly.
DEFAULT_REFERENCE_SUFFIX = ".exr"
#: How an image's pixels were stored, coarsest first: 8 and 16 bits (sRGB-encoded, the
#: preview's tone map), half and single float (linear). ``assert_images_close`` brings
#: the finer of its two images to the coarser one's storage before comparing, so the
#: rounding of a stored reference is never a difference: a re-render of a frame compares
#: equal (mean FLIP 0) to the reference written from it, PNG or EXR.
PRECISIONS = ("8-bit", "16-bit", "half", "float")
#: The integer type of the sRGB-encoded precisions.
ENCODED = {"8-bit": np.uint8, "16-bit": np.uint16}
#: Render options that set a budget; without one ``phrt_render`` / ``phrt_open`` render
#: with ``budget_ms=math.inf`` (``_deterministic``).
BUDGET_OPTIONS = ("budget_ms", "budget_rays", "target_fps")
#: Longest file name stem made from a test's name; a longer one is cut and ends with a
#: hash of the whole name (file systems refuse names over 255 bytes).
MAX_STEM = 120

#: An image: an (H, W, 3) array (float: linear RGB; uint8/uint16: sRGB-encoded) or a file.
ImageInput = np.ndarray | str | os.PathLike

#: The test running now and the pytest config (set by the hooks below).
_STATE: dict[str, Any] = {"item": None, "config": None}
_WRITTEN = pytest.StashKey[list]()
#: Reference file (resolved) → node id of the test that compares against it in this pytest run.
_OWNERS = pytest.StashKey[dict]()


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
    config.stash[_OWNERS] = {}


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
    ``references/`` next to the test file); it need not exist yet. A test's own
    references are in its ``<module>/`` folder (``phrt_reference``)."""
    return _reference_root(request.node, request.config)


@pytest.fixture
def phrt_reference(request: pytest.FixtureRequest) -> Callable[..., Path]:
    """``phrt_reference(name=None, suffix=".exr") -> Path``: this test's own reference
    file, ``<phrt_reference_dir>/<module>/<test>[.<name>]<suffix>`` (``reference_path``),
    what ``assert_images_close`` compares against when given no reference."""

    def path(name: str | None = None, suffix: str = DEFAULT_REFERENCE_SUFFIX) -> Path:
        return reference_path(request.node, request.config, name, suffix)

    return path


@pytest.fixture
def phrt_render(tmp_path: Path) -> Callable[..., RenderResult]:
    """``phrt_render(stage_or_path, frames=None, **options) -> RenderResult``:
    ``phrt_usd.render`` into a new folder of ``tmp_path`` per call (``render-0``, ...).
    Options as ``phrt_usd.render`` takes them; without ``budget_ms``, ``budget_rays`` or
    ``target_fps`` there is no time budget (``_deterministic``: a time budget selects by
    the machine's speed and load, so a frame would not render the same every time)."""
    from phrt_usd.api import render

    count = itertools.count()

    def run(stage_or_path, frames=None, **options) -> RenderResult:
        out = tmp_path / f"render-{next(count)}"
        return render(stage_or_path, out, frames, **_deterministic(options))

    return run


@pytest.fixture
def phrt_open() -> Iterator[Callable[..., Renderer]]:
    """``phrt_open(stage_or_path, frames=None, **options) -> Renderer`` (``phrt_usd.open``,
    with ``phrt_render``'s budget default); every renderer it made is closed when the
    test ends."""
    from phrt_usd.api import open as open_renderer

    made: list[Renderer] = []

    def run(stage_or_path, frames=None, **options) -> Renderer:
        made.append(open_renderer(stage_or_path, frames, **_deterministic(options)))
        return made[-1]

    yield run
    for renderer in made:
        renderer.close()


def _deterministic(options: dict[str, Any]) -> dict[str, Any]:
    """``options`` with ``budget_ms=math.inf`` when they set no budget (``BUDGET_OPTIONS``):
    the frame then depends on the stage alone. Every visible reflector is traced (within
    the stage's rays budget, if it authors one: a rays budget selects the same reflectors
    on every machine); a stage's time budget or frame-rate target would select by how
    fast this machine runs at that moment."""
    if any(options.get(name) is not None for name in BUDGET_OPTIONS):
        return options
    return {**options, "budget_ms": math.inf}


# --------------------------------------------------------------------------------------
# Reference and failure file names
# --------------------------------------------------------------------------------------


def node_stem(item: pytest.Item) -> str:
    """A file name stem of test ``item``, as pytest-regressions names its files: the
    test's name (parametrize id included) with each character other than a letter, digit
    or underscore made ``_`` (``test_shot[farm-200]`` → ``test_shot_farm_200_``); a
    method's class name(s) in front, joined by ``.`` (``TestShot.test_frame``). A stem
    over ``MAX_STEM`` characters is cut and ends with a hash of the whole name."""
    classes = [node.name for node in item.listchain() if isinstance(node, pytest.Class)]
    return _short(".".join(re.sub(r"\W", "_", part) for part in (*classes, item.name)))


def _short(stem: str) -> str:
    if len(stem) <= MAX_STEM:
        return stem
    digest = hashlib.sha1(stem.encode()).hexdigest()[:12]
    return f"{stem[: MAX_STEM - len(digest) - 1]}-{digest}"


def _name_part(name: str) -> str:
    """``name`` (of one comparison among several of a test) as a file name part."""
    return _short(re.sub(r"\W", "_", str(name))) or "_"


def _reference_root(item: pytest.Item, config: pytest.Config) -> Path:
    return Path(item.path).parent / config.getini(REFERENCE_DIR_INI)


def reference_path(
    item: pytest.Item,
    config: pytest.Config,
    name: str | None = None,
    suffix: str = DEFAULT_REFERENCE_SUFFIX,
) -> Path:
    """Test ``item``'s own reference file: ``<reference dir>/<module>/<test>[.<name>]
    <suffix>``, the reference folder (ini ``phrt_reference_dir``) next to the test file,
    a folder named after the test module, the file after the test (``node_stem``) and
    ``name``; BadOption for a suffix not in ``REFERENCE_SUFFIXES``."""
    if suffix not in REFERENCE_SUFFIXES:
        raise BadOption(f"reference suffix {suffix!r}: one of {', '.join(REFERENCE_SUFFIXES)}")
    stem = node_stem(item) + (f".{_name_part(name)}" if name else "")
    return _reference_root(item, config) / Path(item.path).stem / f"{stem}{suffix}"


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
    reference: ImageInput | None = None,
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
    ``reference`` None (in a test): the test's own file, ``reference_path`` (with
    ``name``), ``references/<module>/<test>[.<name>].exr``. A reference file belongs to
    one test: another test of the pytest run comparing against it fails, naming both. The
    finer of the two images is first brought to the coarser one's storage
    (``PRECISIONS``): the rounding of a PNG or half-float reference is no difference.
    On failure (or a missing reference, or images of two sizes) the actual, the reference
    and the FLIP error map are written as ``<test>[.<name>].{actual,reference,error}.png``
    into the failure folder (``failure_dir``, else ``phrt-failures/<module>/`` next to
    the test file, else ``./phrt-failures`` outside a test) and the AssertionError names
    them; a passing comparison removes those of an earlier failure. With
    ``--phrt-update-references`` and a reference *file* (``.png`` or ``.exr``), the actual
    is written there instead and nothing is compared (a second comparison of the test
    against a file it wrote in this run compares). Bad arguments raise ``BadOption`` /
    ``PhrtError`` before any metric runs (the FLIP library exits the process on bad
    input)."""
    __tracebackhide__ = True
    _check_thresholds(max_mean_flip, min_psnr)
    if reference is None:
        reference = _own_reference(name)
    act, act_precision = _load(actual, "actual")
    paths = _failure_paths(name, failure_dir)
    ref_file = Path(reference) if isinstance(reference, str | os.PathLike) else None
    if ref_file is not None:
        _claim(ref_file)
    if ref_file is not None and _updating() and not _written_now(ref_file):
        write_reference(ref_file, act)
        _STATE["config"].stash[_WRITTEN].append(ref_file)
        _remove(paths)
        return ImageComparison(None, None)
    if ref_file is not None and not ref_file.is_file():
        _fail(f"no reference image {ref_file} (write it with pytest {UPDATE_OPTION})", paths, act)
    ref, ref_precision = _load(reference, "reference")
    if act.shape != ref.shape:
        sizes = f"actual {act.shape[1]}x{act.shape[0]}, reference {ref.shape[1]}x{ref.shape[0]}"
        _fail(f"images differ in size: {sizes}", paths, act, ref)
    for label, image in (("actual", act), ("reference", ref)):
        bad = int((~np.isfinite(image)).any(axis=2).sum())
        if bad:
            _fail(f"{label} image has NaN/Inf in {bad} pixel(s)", paths, act, ref)
    coarser = min(act_precision, ref_precision, key=PRECISIONS.index)
    act, ref = at_precision(act, coarser), at_precision(ref, coarser)
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


def _own_reference(name: str | None) -> Path:
    """The running test's own reference file (``reference_path``); BadOption outside a
    test, where there is no test to name it after."""
    item, config = _STATE["item"], _STATE["config"]
    if item is None or config is None:
        raise BadOption("assert_images_close: give a reference (no pytest test is running)")
    return reference_path(item, config, name)


def _claim(reference: Path) -> None:
    """Record that the running test compares against ``reference``; AssertionError when
    another test of this pytest run already does (under ``--phrt-update-references`` the
    later test's image would silently replace the earlier one's)."""
    __tracebackhide__ = True
    item, config = _STATE["item"], _STATE["config"]
    if item is None or config is None:
        return
    owner = config.stash[_OWNERS].setdefault(reference.resolve(), item.nodeid)
    if owner != item.nodeid:
        raise AssertionError(
            f"reference {reference} is already the reference of {owner}: two tests would "
            "share one file; leave out the reference argument to compare against this "
            "test's own file (references/<module>/<test>.exr)"
        )


def _written_now(reference: Path) -> bool:
    """True when this pytest run already wrote ``reference`` (by the same test: ``_claim``)."""
    config = _STATE["config"]
    written = config.stash[_WRITTEN] if config is not None else []
    return any(reference.resolve() == path.resolve() for path in written)


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
    return _load(image, label)[0]


def _load(image: ImageInput, label: str) -> tuple[np.ndarray, str]:
    """``load_image`` and how the pixels were stored (one of ``PRECISIONS``)."""
    precision = None
    if isinstance(image, str | os.PathLike):
        image, precision = _read_image_file(Path(image), label)
    if not isinstance(image, np.ndarray):
        raise PhrtError(f"{label}: expected an image array or file, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise PhrtError(f"{label}: expected an (H, W, 3) RGB image, got shape {image.shape}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise PhrtError(f"{label}: need at least 2x2 pixels, got {image.shape[1]}x{image.shape[0]}")
    encoded = {np.dtype(t): p for p, t in ENCODED.items()}.get(image.dtype)
    if encoded is not None:
        return _decode(image), encoded
    if image.dtype.kind != "f":
        raise PhrtError(f"{label}: pixels must be float (linear) or uint8/uint16 (sRGB), "
                        f"got {image.dtype}")  # fmt: skip
    precision = precision or ("half" if image.dtype == np.float16 else "float")
    return image.astype(np.float32, copy=False), precision


def _decode(encoded: np.ndarray) -> np.ndarray:
    """Linear float32 RGB of sRGB-encoded uint8 / uint16 pixels."""
    from phrt_usd.run.frame_reader import srgb_decode

    return srgb_decode(encoded.astype(np.float32) / np.float32(np.iinfo(encoded.dtype).max))


def at_precision(linear: np.ndarray, precision: str) -> np.ndarray:
    """``linear`` as it reads back after being stored at ``precision`` (``PRECISIONS``):
    8 / 16 bits as phrt's previews encode them (``tonemap_ldr``, rounded; what
    ``write_reference`` writes to a PNG), half float clamped to its range, float as is."""
    if precision in ENCODED:
        from phrt_usd.run.images import tonemap_ldr

        dtype = ENCODED[precision]
        top = float(np.iinfo(dtype).max)
        return _decode(np.rint(tonemap_ldr(linear) * np.float32(top)).astype(dtype))
    if precision == "half":
        from phrt_usd.run.images import HALF_MAX

        return np.clip(linear, -HALF_MAX, HALF_MAX).astype(np.float16).astype(np.float32)
    return linear


def _read_image_file(path: Path, label: str) -> tuple[np.ndarray, str]:
    """The R, G, B pixels of an image file as stored (EXR: float32 of its half or float
    channels; others: uint8 for 8-bit files, else uint16) and their precision."""
    import OpenImageIO as oiio

    if not path.is_file():
        raise PhrtError(f"{label}: {path}: no such image file")
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise PhrtError(f"{label}: {path}: cannot open image ({oiio.geterror()})")
    try:
        spec = image.spec()
        names = list(spec.channelnames)
        linear = path.suffix.lower() == ".exr"
        eight_bit = spec.format == oiio.UINT8
        data = image.read_image(oiio.FLOAT if linear else oiio.UINT8 if eight_bit else oiio.UINT16)
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
    if not linear:
        return data[..., rgb], "8-bit" if eight_bit else "16-bit"
    formats = list(spec.channelformats) or [spec.format] * len(names)
    half = all(formats[i] == oiio.HALF for i in set(rgb) if i < len(formats))
    return data[..., rgb], "half" if half else "float"


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
    """Where a failed comparison's images go (see ``assert_images_close``): named after
    the test like its reference (``node_stem``), in a folder of its module, so that no
    two tests' failure images share a name."""
    item, config = _STATE["item"], _STATE["config"]
    parts = [node_stem(item)] if item is not None else []
    if name:
        parts.append(_name_part(name))
    stem = ".".join(parts) or "image"
    if failure_dir is not None:
        folder = Path(failure_dir)
    elif item is not None and config is not None:
        folder = Path(item.path).parent / config.getini(FAILURE_DIR_INI) / Path(item.path).stem
    else:
        folder = Path.cwd() / DEFAULT_FAILURE_DIR
    return {kind: folder / f"{stem}.{kind}.png" for kind in ("actual", "reference", "error")}


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
