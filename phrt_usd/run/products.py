"""Which image files a frame gets and what they hold: RenderProducts, ``--image``, ``--aovs``.

``plan_images`` turns the render settings' products (``phrt_usd.usd.render_settings``)
into an ``ImagePlan``; ``write_frame_images`` writes one frame of it.

**Files.** Every RenderProduct of the settings is one file per frame, named by its
``productName`` with the frame tokens expanded (``$F``, ``$F4``, ``${F4}``, ``####``,
``%04d``, ``%d``: the time code rounded to 1/1000, zero-padded to the digits asked; a
fractional one keeps 3 decimals, ``0012.500``; ``frames.frame_text``). Names are
relative to ``--out``; an absolute name must lie inside ``--out``, and ``..`` is
refused: the run directory is the one place a render writes, locks and clears
(``run_directory``), so a product outside it is refused rather than moved. ``.exr``
products hold their vars' channels, ``.png`` products the 8-bit sRGB preview of
``color`` (and nothing else). ``--image TEMPLATE`` replaces the products with one file
named TEMPLATE holding the first product's vars (or the default channels). With neither,
the default layout: ``frames/$F4.exr`` (``CHANNELS`` of ``images``) and its preview
``frames/$F4.png``. No two frames of a run may write one file: a name without a frame
token for more than one frame, two names that expand to one file at some frame
(``img.$F4.exr`` and ``img.####.exr``, ``$F`` and ``$F4`` from frame 1000) and two
frames that round to the same 1/1000 are refused before the first frame renders
(``ImagePlan.check_files``: compared by the expanded names of every frame, exit 2).

**Vars → channels.** A RenderVar's ``sourceName`` picks what it holds:

==================  =============================================  ================  =======
sourceName          meaning                                        channels          storage
==================  =============================================  ================  =======
color, Ci, C.* lpe  beauty: linear RGB, coverage in A              R, G, B, A        dataType
alpha, a            coverage                                       A                 dataType
depth, z, Z,        view depth in metres along the camera's -Z,    Z                 dataType
cameraDepth         background 1e30 (``images.DEPTH_BACKGROUND``)
normal, N           world-space unit shading normal (0 background) N.x, N.y, N.z     dataType
position, P         world position in metres (0 background)        P.x, P.y, P.z     dataType
albedo              linear RGB albedo (0 background)               albedo.R/.G/.B    dataType
primId, id          element id, manifest in the header             id                uint
phrt:traced         1 where the reflection was ray-traced          traced            dataType
phrt:reflectivity   the reflector's F at the pixel (0 elsewhere)   reflectivity      dataType
motion,             screen-space motion from the previous frame:   motion.x,         dataType
motionvector        pixels, this frame's position minus the        motion.y
                    previous one's, +x right, +y down; 0 on the
                    run's first frame (``engine/motion.py``)
phrt:pixelKind,     how the pixel was made: 0 background,          pixelKind         uint
pixelKind           1 raster, 2 screen-space, 3 traced, 4 reused,
                    5 filled (``model/pixel_kinds.py``)
==================  =============================================  ================  =======

``driver:parameters:aov:name`` renames a var's channels (``N`` → ``Nworld.x``; not color,
alpha or depth, whose names are the ones EXR readers look for). Storage follows the
var's ``dataType``: half types (``half``, ``color3h``, ``normal3h``, ...) are HALF,
``int``/``uint``/``bool`` (``phrt:traced`` only) UINT, others FLOAT; ids and pixel kinds
are always UINT. ``--aovs`` adds vars by source name to every EXR (``P`` float, ``N`` /
``albedo`` / ``reflectivity`` / ``traced`` half, ``depth`` / ``motion`` float, ``id`` /
``pixelKind`` uint), after the product's own.
A product whose ``driver:parameters:OpenEXR:multipart`` is true gets one part per var
(parts named after the var's channels: ``rgba``, ``depth``, ``N``, ...).

**Header** (every EXR): ``worldToCamera`` and ``worldToNDC`` (OpenEXR's standard
attributes, ``M44f``, row vectors as Imath multiplies them, world = the stage's world in
metres: camera space is left-handed, +z the viewing direction, as OpenEXR defines it;
NDC (0, 0) is the image's top-left corner, (1, 1) its bottom-right, after dividing by w,
over the camera's ``CameraFrame.image_window``: aperture offsets and the conform policy
included), ``displayWindow`` / ``dataWindow`` (the whole image / the pixels the file
holds: the settings' ``dataWindowNDC``, ``CameraFrame.data_window_pixels``; every file of
a frame, EXR and PNG, holds only those pixels, ``images.DataWindow``),
``framesPerSecond`` (rational), ``software`` (``phrt-usd VERSION``), ``phrt/version``,
``phrt/timeCode`` (double), ``phrt/stage``, ``phrt/camera``, ``phrt/renderSettings`` and
``phrt/renderProduct`` (when there is one), ``phrt/metersPerUnit`` (double), with a
``motion`` var ``phrt/motion`` (its convention, one line), with a ``pixelKind`` var
``phrt/pixelKinds`` (its codes, ``0 background, 1 raster, ...``), and, with an
``id`` channel, the manifest of the ids in the frame (``images.write_exr``: id → the
element's prim path; a PointInstancer's instances are ``/Instancer.instance[i]/...``). The
wall-clock ``capDate`` and ``utcOffset`` only with ``timestamp`` (``--timestamp``), so
identical renders write identical bytes.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from fractions import Fraction
from functools import lru_cache
from pathlib import Path, PurePosixPath

import numpy as np

from phrt_usd.base import __version__
from phrt_usd.engine.compositing import element_reflectivity, pixel_reflectivity
from phrt_usd.engine.renderer import FrameOutput
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.model.pixel_kinds import PIXEL_KINDS, raster_kinds
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.run.frames import FRAME_DECIMALS, frame_text
from phrt_usd.run.images import (
    DataWindow,
    check_beauty,
    stored,
    stored_depth,
    stored_ids,
    write_exr,
    write_preview_png,
)
from phrt_usd.run.run_files import FRAME_DIGITS, FRAMES_DIR
from phrt_usd.usd.render_settings import RenderSettingsSpec, RenderVarSpec

# --- sources ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Source:
    """What a RenderVar can hold (module docstring, the table)."""

    key: str  # the plane of the frame: beauty+alpha, alpha, depth, normal, ...
    names: tuple[str, ...]  # sourceNames that select it (the first is the --aovs name)
    base: str  # channel base name ("" for color / depth / alpha: fixed names)
    suffixes: tuple[str, ...]  # channel name suffixes, one per component
    storage: str  # the storage --aovs and the default layout use


SOURCES: tuple[Source, ...] = (
    Source("color", ("color", "Ci", "C.*"), "", ("R", "G", "B", "A"), "half"),
    Source("alpha", ("alpha", "a"), "", ("A",), "half"),
    Source("depth", ("depth", "z", "Z", "cameraDepth"), "", ("Z",), "float"),
    Source("normal", ("normal", "N"), "N", (".x", ".y", ".z"), "half"),
    Source("position", ("position", "P"), "P", (".x", ".y", ".z"), "float"),
    Source("albedo", ("albedo",), "albedo", (".R", ".G", ".B"), "half"),
    Source("id", ("primId", "id"), "id", ("",), "uint"),
    Source("traced", ("phrt:traced", "traced"), "traced", ("",), "half"),
    Source("reflectivity", ("phrt:reflectivity", "reflectivity"), "reflectivity", ("",), "half"),
    Source("motion", ("motion", "motionvector"), "motion", (".x", ".y"), "float"),
    Source("pixel_kind", ("phrt:pixelKind", "pixelKind"), "pixelKind", ("",), "uint"),
)
#: Sources whose channels are UINT whatever the var's dataType (exact codes).
UINT_SOURCES = frozenset({"id", "pixel_kind"})
#: The header line of a file with a ``motion`` var (module docstring).
MOTION_HEADER = (
    "pixels, this frame's position minus the previous frame's, +x right, +y down "
    "(rows from the top); 0 on a run's first frame"
)
_BY_NAME = {name: s for s in SOURCES for name in s.names}
#: The default layout's vars (``images.CHANNELS``).
DEFAULT_SOURCES = ("color", "depth", "id", "traced")
HALF_TYPES = frozenset(
    "half half2 half3 half4 color3h color4h normal3h point3h vector3h texCoord2h "
    "texCoord3h quath".split()
)
INT_TYPES = frozenset("int uint int64 uint64 bool uchar".split())
#: The default layout's file name templates, relative to the run directory.
DEFAULT_TEMPLATE = f"{FRAMES_DIR}/$F{FRAME_DIGITS}.exr"
DEFAULT_PREVIEW = f"{FRAMES_DIR}/$F{FRAME_DIGITS}.png"
IMAGE_SUFFIXES = (".exr", ".png")


@dataclass(frozen=True)
class Channel:
    """One channel of a product: its name, the source plane and component it holds, its
    storage ("half" | "float" | "uint") and the part it goes to in a multi-part file."""

    name: str
    source: str
    component: int
    storage: str
    part: str


def _channels(source: Source, storage: str, base: str | None) -> list[Channel]:
    if source.key == "color":
        color = [Channel(c, "beauty", i, storage, "rgba") for i, c in enumerate("RGB")]
        return [*color, Channel("A", "alpha", 0, storage, "rgba")]
    if not source.base:  # alpha, depth
        return [Channel(source.suffixes[0], source.key, 0, storage, source.key)]
    base = base or source.base
    return [
        Channel(base + suffix, source.key, i, storage, base)
        for i, suffix in enumerate(source.suffixes)
    ]


def var_channels(var: RenderVarSpec) -> list[Channel]:
    """The channels of a RenderVar (module docstring); PhrtError naming the var for a
    source phrt does not render or a dataType that cannot hold it."""
    source = _BY_NAME.get(var.source_name)
    if source is None or (var.source_type == "lpe") != (var.source_name == "C.*"):
        known = ", ".join(s.names[0] for s in SOURCES)
        raise PhrtError(
            f"{var.path}: sourceName {var.source_name!r} ({var.source_type}) is not a pass "
            f"phrt renders ({known})"
        )
    data_type = var.data_type
    if source.key in UINT_SOURCES:
        storage = "uint"
    elif data_type in INT_TYPES:
        if source.key != "traced":
            raise PhrtError(f"{var.path}: dataType {data_type} cannot hold {source.key}")
        storage = "uint"
    else:
        storage = "half" if data_type in HALF_TYPES else "float"
    return _channels(source, storage, var.aov_name if source.base else None)


def aov_channels(names: tuple[str, ...] | list[str]) -> list[Channel]:
    """The channels of ``--aovs`` source names; BadOption for an unknown one."""
    channels: list[Channel] = []
    for name in names:
        source = _BY_NAME.get(name)
        if source is None:
            known = ", ".join(name for s in SOURCES for name in s.names if name != "C.*")
            raise BadOption(f"--aovs {name!r}: not a pass phrt renders ({known})")
        channels += _channels(source, source.storage, None)
    return channels


def parse_aovs(text: str | None) -> tuple[str, ...]:
    """``"P,N,albedo"`` → ``("P", "N", "albedo")`` (checked; BadOption otherwise)."""
    names = tuple(n.strip() for n in (text or "").split(",") if n.strip())
    aov_channels(names)
    return names


# --- frame name templates ----------------------------------------------------------------

_TOKEN = re.compile(r"\$\{F(\d*)\}|\$F(\d*)|(#+)|%(0?\d*)d")


def has_frame_token(template: str) -> bool:
    return _TOKEN.search(template) is not None


@lru_cache(maxsize=256)
def _split(template: str) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """(literal texts, token widths) of ``template``: one more literal than tokens, a
    token's width the digits it pads to (0: none)."""
    literals, widths, last = [], [], 0
    for match in _TOKEN.finditer(template):
        braced, dollar, hashes, printf = match.groups()
        digits = braced if braced is not None else dollar if dollar is not None else printf
        literals.append(template[last : match.start()])
        widths.append(len(hashes) if hashes is not None else int(digits) if digits else 0)
        last = match.end()
    literals.append(template[last:])
    return tuple(literals), tuple(widths)


def expand(template: str, time: float) -> str:
    """``template`` with its frame tokens replaced by time code ``time`` (module doc,
    ``frames.frame_text``)."""
    frame_text(time)  # PhrtError if not finite, even without a token
    literals, widths = _split(template)
    pieces = [literals[0]]
    for width, literal in zip(widths, literals[1:], strict=True):
        pieces += [frame_text(time, width), literal]
    return "".join(pieces)


def template_pattern(template: str) -> re.Pattern:
    """A regex matching every name ``template`` expands to, whatever the frame."""
    literals, _ = _split(template)
    frame = rf"-?\d+(?:\.\d{{{FRAME_DECIMALS}}})?"
    return re.compile("^" + frame.join(re.escape(literal) for literal in literals) + "$")


def relative_template(out: Path, template: str, where: str, error=PhrtError) -> str:
    """``template`` as a POSIX path relative to ``out``: a relative name as it is, an
    absolute one inside ``out`` made relative; ``error`` (naming ``where``) for a name
    outside ``out``, with ``..``, or not ending in ``.exr`` / ``.png``."""
    if not template:
        raise error(f"{where}: productName is empty")
    if "\0" in template:
        raise error(f"{where}: {template!r} is not a file name")
    path = PurePosixPath(template)
    if path.is_absolute():
        try:
            path = PurePosixPath(os.path.realpath(path)).relative_to(os.path.realpath(out))
        except ValueError:
            raise error(
                f"{where}: {template!r} is outside the output directory {out}; products are "
                "written under --out (give a relative name, or use --image)"
            ) from None
    if ".." in path.parts or not path.parts or path.name in ("", "."):
        raise error(f"{where}: {template!r} leaves the output directory (no '..' allowed)")
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise error(f"{where}: {template!r}: phrt writes .exr or .png images")
    return str(path)


# --- the plan -----------------------------------------------------------------------------


def _shown(time: float) -> str:
    """A time code as errors show it: ``1000``, ``1.0002``."""
    return f"{time:.12g}"


@dataclass(frozen=True)
class ProductPlan:
    """One file per frame: ``template`` (relative to the run directory) and its channels."""

    template: str
    channels: tuple[Channel, ...]
    product: str | None = None  # the RenderProduct prim, None for the default / --image
    multipart: bool = False
    preview: str | None = None  # template of a PNG preview beside it (default layout)

    @property
    def is_png(self) -> bool:
        return self.template.lower().endswith(".png")

    def describe(self) -> dict:
        """What stats.json and the selection layer record and the run identity compares:
        ``channels`` (``"name:storage"``), ``multipart``, and ``product`` / ``preview``
        when there are (plain values a USD dictionary holds too)."""
        entry: dict = {
            "channels": [f"{c.name}:{c.storage}" for c in self.channels],
            "multipart": self.multipart,
        }
        if self.product:
            entry["product"] = self.product
        if self.preview:
            entry["preview"] = self.preview
        return entry


@dataclass(frozen=True)
class ImagePlan:
    """Every file a frame of a run gets (see the module docstring)."""

    products: tuple[ProductPlan, ...]
    settings: str | None = None  # the RenderSettings prim, None when the stage has none
    resolution: tuple[int, int] | None = None  # the products' own resolution, if authored
    camera: str | None = None  # the products' own camera, if authored
    stage: str | None = None  # the stage named in headers (None: the root layer's path)
    timestamp: bool = False  # capDate / utcOffset in EXR headers
    image: bool = False  # the one product is --image's

    def check_files(self, times: Sequence[float]) -> None:
        """Refuse, before any frame renders, a run that would write one file twice (each
        frame's files replacing another's): BadOption (exit 2), one line naming the
        products (their prim paths, or ``--image``) and the frames, when

        * a name has no frame token and there is more than one frame;
        * two frames round to the same 1/1000 of a time code (``frames.frame_text``), so
          every name writes them alike;
        * two names expand to the same file (``img.$F4.exr`` and ``img.####.exr`` at
          every frame, ``$F`` and ``$F4`` from frame 1000 on, ``a.1$F3.exr`` at 1 and
          ``a.$F4.exr`` at 1001): compared by the expanded names of every frame of
          ``times``."""
        named = self._named_templates()
        if len(times) > 1:
            for template, who in named:
                if not has_frame_token(template):
                    raise BadOption(
                        f"{who}: no frame token ($F4, ####, %04d) for {len(times)} frames"
                    )
        ordered = sorted(times)
        # frame_text rounds, so a frame's text never decreases with its time: two frames
        # written alike are neighbours in time.
        texts = [frame_text(t) for t in ordered]
        for i in range(1, len(ordered)):
            if texts[i] == texts[i - 1]:
                name = expand(self.templates()[0], ordered[i])
                raise BadOption(
                    f"--frames: frames {_shown(ordered[i - 1])} and {_shown(ordered[i])} both "
                    f"write {name} (file names tell time codes apart to 1/1000); render "
                    "frames at least 0.001 apart"
                )
        by_suffix: dict[str, list[tuple[str, str]]] = {}
        for template, who in named:  # names that differ in extension never meet
            by_suffix.setdefault(PurePosixPath(template).suffix, []).append((template, who))
        for group in by_suffix.values():
            if len(group) > 1:
                _check_distinct(group, ordered)

    def _named_templates(self) -> list[tuple[str, str]]:
        """(template, the product writing it as errors name it) of every file name of a
        frame, in the order of ``templates``."""
        named = []
        for product in self.products:
            if self.image:
                who = f"--image {product.template!r}"
            elif product.product:
                who = f"{product.product}.productName {product.template!r}"
            else:
                who = repr(product.template)
            named.append((product.template, who))
        return named + [(p.preview, repr(p.preview)) for p in self.products if p.preview]
    def templates(self) -> list[str]:
        """Every file name template of the run (products and previews)."""
        names = [p.template for p in self.products]
        return names + [p.preview for p in self.products if p.preview]

    def files(self, out: Path, time: float) -> list[Path]:
        """The files frame ``time`` is written to, in ``out``."""
        return [Path(out) / expand(t, time) for t in self.templates()]

    def describe(self) -> dict[str, dict]:
        """File name template → ``ProductPlan.describe()`` of every product."""
        return {p.template: p.describe() for p in self.products}


def _check_distinct(named: list[tuple[str, str]], times: list[float]) -> None:
    """BadOption naming the first frame at which two of the (template, who) ``named``
    write one file (``ImagePlan.check_files``). Each (template, frame) name is held as its
    hash, so a million-frame run needs megabytes, not a million strings; equal hashes are
    compared by their names."""
    count = len(times)
    texts: dict[int, list[str]] = {}  # token width -> every frame's text
    hashes = np.empty(len(named) * count, np.int64)
    for index, (template, _) in enumerate(named):
        literals, widths = _split(template)
        for width in widths:
            if width not in texts:
                texts[width] = [frame_text(t, width) for t in times]
        rows = zip(*(texts[width] for width in widths), strict=True) if widths else [()] * count
        hashes[index * count : (index + 1) * count] = [
            hash(literals[0] + "".join(a + b for a, b in zip(row, literals[1:], strict=True)))
            for row in rows
        ]
    order = np.argsort(hashes, kind="stable")
    same = np.flatnonzero(hashes[order][1:] == hashes[order][:-1])
    firsts, seconds = order[same], order[same + 1]
    earliest = np.argsort(np.minimum(firsts % count, seconds % count), kind="stable")
    for first, second in zip(firsts[earliest], seconds[earliest], strict=True):
        (a, ta), (b, tb) = divmod(int(first), count), divmod(int(second), count)
        if a == b:
            continue  # one name's frames are distinct (checked before): a hash collision
        name = expand(named[a][0], times[ta])
        if name != expand(named[b][0], times[tb]):
            continue
        if ta == tb:
            at = f"at frame {_shown(times[ta])}"
        else:
            at = f"at frames {_shown(times[ta])} and {_shown(times[tb])}"
        raise BadOption(
            f"{named[a][1]} and {named[b][1]} both write {name} {at}; give them names "
            "that differ"
        )


def default_plan(aovs: tuple[str, ...] = ()) -> ImagePlan:
    """The default layout (``frames/NNNN.exr`` + ``.png``), with ``--aovs`` added."""
    channels = aov_channels(DEFAULT_SOURCES)
    return ImagePlan(
        (ProductPlan(DEFAULT_TEMPLATE, _add(channels, aovs), preview=DEFAULT_PREVIEW),)
    )


def _add(channels: list[Channel], aovs: tuple[str, ...]) -> tuple[Channel, ...]:
    """``channels`` then those of ``aovs`` whose names are not there yet."""
    names = {c.name for c in channels}
    extra = [c for c in aov_channels(aovs) if c.name not in names]
    return tuple(channels + extra)


def plan_images(
    settings: RenderSettingsSpec | None,
    out: Path,
    *,
    image: str | None = None,
    aovs: tuple[str, ...] = (),
    stage: str | None = None,
    timestamp: bool = False,
) -> ImagePlan:
    """The images of a run into ``out`` (module docstring). PhrtError naming the product
    (BadOption for ``--image`` / ``--aovs``) for a name or var phrt cannot write; see also
    ``ImagePlan.check_files``."""
    specs = settings.products if settings is not None else ()
    for spec in specs:
        if spec.product_type != "raster":
            raise PhrtError(
                f"{spec.path}: productType {spec.product_type!r} is not supported "
                "(phrt writes raster products)"
            )
    products: list[ProductPlan] = []
    if image is not None:
        template = relative_template(out, image, f"--image {image!r}", BadOption)
        first = specs[0] if specs else None
        channels = _product_channels(first) if first else list(aov_channels(DEFAULT_SOURCES))
        multipart = bool(first and first.multipart)
        products.append(
            ProductPlan(template, _add(channels, aovs), first.path if first else None, multipart)
        )
        used = specs[:1]
    else:
        for spec in specs:
            template = relative_template(out, spec.product_name, f"{spec.path}.productName")
            png = template.lower().endswith(".png")  # --aovs go to every EXR only
            channels = _add(_product_channels(spec), () if png else aovs)
            products.append(ProductPlan(template, channels, spec.path, spec.multipart))
        used = specs
    base = ImagePlan((), settings.path if settings else None, stage=stage, timestamp=timestamp)
    if not products:
        return replace(base, products=default_plan(aovs).products)
    for plan in products:  # names that meet are refused by ImagePlan.check_files
        where = plan.product if image is None else "--image"
        if plan.is_png and {c.source for c in plan.channels} - {"beauty", "alpha"}:
            raise PhrtError(f"{where}: a .png holds the color var only; name it .exr")
    return replace(
        base,
        products=tuple(products),
        image=image is not None,
        resolution=_common(used, "resolution"),
        camera=_common(used, "camera"),
    )


def _product_channels(spec) -> list[Channel]:
    """A product's channels: its vars' in order (the default channels if it has none);
    PhrtError naming the var whose channels repeat another's."""
    if not spec.vars:
        return list(aov_channels(DEFAULT_SOURCES))
    channels: list[Channel] = []
    names: dict[str, str] = {}
    for var in spec.vars:
        for channel in var_channels(var):
            if channel.name in names:
                raise PhrtError(
                    f"{var.path}: channel {channel.name} is also written by {names[channel.name]}"
                )
            names[channel.name] = var.path
            channels.append(channel)
    return channels


def _common(specs, attribute: str):
    """The products' common authored ``attribute`` (None if none authors it); PhrtError if
    two products differ: one render has one resolution and one camera."""
    values = {(getattr(s, attribute), s.path) for s in specs if getattr(s, attribute)}
    distinct = {v for v, _ in values}
    if len(distinct) > 1:
        shown = ", ".join(f"{p}: {v}" for v, p in sorted(values, key=str))
        raise PhrtError(f"products differ in {attribute} ({shown}); phrt renders one per run")
    return next(iter(distinct)) if distinct else None


# --- writing a frame ----------------------------------------------------------------------


def write_frame_images(
    plan: ImagePlan,
    out: Path,
    time: float,
    output: FrameOutput,
    camera: CameraFrame,
    scene: Scene,
    *,
    frames_per_second: float,
    camera_path: str,
    stage: str,
) -> list[Path]:
    """Write frame ``time``'s files of ``plan`` into ``out`` (each atomically); returns
    them. ``output`` is the rendered frame, ``camera`` its camera; every file holds the
    pixels of the camera's data window (``CameraFrame.data_window_pixels``, module
    docstring)."""
    out = Path(out)
    height, width = output.gbuffer.shape
    window = DataWindow.of(width, height, camera.data_window_pixels(width, height))
    planes = _Planes(output, scene)
    base = frame_header(
        camera,
        width,
        height,
        time,
        frames_per_second=frames_per_second,
        stage=plan.stage or stage,
        camera_path=camera_path,
        meters_per_unit=scene.meters_per_unit,
        timestamp=plan.timestamp,
    )
    if plan.settings:
        base["phrt/renderSettings"] = plan.settings
    written = []
    for product in plan.products:
        path = confined(out, expand(product.template, time))
        if product.is_png:
            write_preview_png(path, planes.get("beauty", path), window=window)
        else:
            header = dict(base)
            if product.product:
                header["phrt/renderProduct"] = product.product
            _write_product_exr(path, product, planes, header, scene, window)
        written.append(path)
        if product.preview:
            preview = confined(out, expand(product.preview, time))
            write_preview_png(preview, planes.get("beauty", path), window=window)
            written.append(preview)
    return written


def _write_product_exr(
    path: Path, product: ProductPlan, planes, header, scene, window: DataWindow
) -> None:
    parts: dict[str, dict[str, np.ndarray]] = {}
    for channel in product.channels:
        part = channel.part if product.multipart else ""
        plane = planes.get(channel.source, path)
        values = plane if plane.ndim == 2 else plane[..., channel.component]
        if channel.source == "id":
            values = stored_ids(path, values)
        elif channel.storage == "uint":
            values = values.astype(np.uint32)
        else:
            values = stored(values, channel.storage)
        parts.setdefault(part, {})[channel.name] = values
    manifest = None
    sources = {c.source for c in product.channels}
    if "motion" in sources:
        header = {**header, "phrt/motion": MOTION_HEADER}
    if "pixel_kind" in sources:
        kinds = ", ".join(f"{code} {name}" for code, name in PIXEL_KINDS.items())
        header = {**header, "phrt/pixelKinds": kinds}
    if "id" in sources:
        ids = np.unique(window.crop(planes.get("id", path), path))  # the ids in the file
        manifest = {int(i): scene.elements[i].path for i in ids if i >= 0}
    id_channel = next((c.name for c in product.channels if c.source == "id"), "id")
    write_exr(path, parts, header, manifest, id_channel, window)


class _Planes:
    """The frame's planes by source key, each computed once when first asked for."""

    def __init__(self, output: FrameOutput, scene: Scene):
        self.output, self.scene = output, scene
        self.cache: dict[str, np.ndarray] = {}

    def get(self, key: str, path: Path) -> np.ndarray:
        if key not in self.cache:
            self.cache[key] = self._compute(key, path)
        return self.cache[key]

    def _compute(self, key: str, path: Path) -> np.ndarray:
        out, gb = self.output, self.output.gbuffer
        if key == "beauty":
            return check_beauty(path, out.beauty)
        if key == "alpha":
            alpha = np.asarray(out.alpha, dtype=np.float32)
            if not np.isfinite(alpha).all():
                raise PhrtError(f"{path}: alpha has NaN/Inf")
            return alpha
        if key == "depth":
            return stored_depth(path, gb.depth)
        if key == "id":
            return np.asarray(gb.element_id)
        if key == "traced":
            return np.asarray(out.traced_mask, dtype=np.float32)
        if key == "reflectivity":
            return pixel_reflectivity(gb, element_reflectivity(self.scene))
        if key == "pixel_kind":
            if out.pixel_kind is None:
                return raster_kinds(gb.covered)
            return np.asarray(out.pixel_kind)
        if key == "motion":
            motion = np.asarray(out.motion, dtype=np.float32)
            if not np.isfinite(motion).all():
                raise PhrtError(f"{path}: motion has NaN/Inf")
            return motion
        plane = {"normal": gb.normal, "position": gb.position, "albedo": gb.albedo}[key]
        values = np.where(gb.covered[..., None], plane, 0.0)
        if not np.isfinite(values).all():
            raise PhrtError(f"{path}: {key} has NaN/Inf")
        return values


def confined(out: Path, relative: str) -> Path:
    """``out / relative``, PhrtError if a link on the way leads it out of ``out``."""
    path = Path(out) / relative
    root = os.path.realpath(out)
    parent = os.path.realpath(path.parent)
    if os.path.commonpath([root, parent]) != root:
        raise PhrtError(f"{path}: leads out of the output directory {out} (a symlink)")
    return path


# --- header -------------------------------------------------------------------------------


def exr_camera_matrices(
    camera: CameraFrame, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """(worldToCamera, worldToNDC) as OpenEXR defines them (module docstring): (4, 4)
    float64 matrices for row vectors (``[x, y, z, 1] @ M``). NDC spans the camera's
    ``image_window`` (aperture offsets, conform policy and pixel aspect included) over
    the whole ``width`` x ``height`` image, the EXR's display window."""
    flip = np.diag([1.0, 1.0, -1.0, 1.0])  # USD's camera looks down -z, EXR's down +z
    camera_from_world = flip @ np.linalg.inv(camera.world_from_camera)
    # At distance z (EXR camera space, x right, y up) the window spans left..right and
    # bottom..top times z: ndc_x = (x / z - left) / (right - left), ndc_y = (top - y / z)
    # / (top - bottom), written for the homogeneous divide by w = z.
    left, right, bottom, top = camera.image_window(width, height)
    sx, sy = 1.0 / (right - left), 1.0 / (top - bottom)
    near, far = camera.near, camera.far
    projection = np.array(
        [
            [sx, 0.0, -left * sx, 0.0],
            [0.0, -sy, top * sy, 0.0],
            [0.0, 0.0, far / (far - near), -far * near / (far - near)],
            [0.0, 0.0, 1.0, 0.0],
        ]
    )
    return camera_from_world.T, (projection @ camera_from_world).T


def frame_header(
    camera: CameraFrame,
    width: int,
    height: int,
    time: float,
    *,
    frames_per_second: float,
    stage: str,
    camera_path: str,
    meters_per_unit: float,
    timestamp: bool = False,
) -> dict[str, object]:
    """The header attributes every EXR of frame ``time`` carries (module docstring)."""
    to_camera, to_ndc = exr_camera_matrices(camera, width, height)
    header: dict[str, object] = {
        "worldToCamera": to_camera.astype(np.float32),
        "worldToNDC": to_ndc.astype(np.float32),
        "framesPerSecond": Fraction(frames_per_second).limit_denominator(1_000_000),
        "software": f"phrt-usd {__version__}",
        "phrt/version": __version__,
        "phrt/timeCode": np.array([float(time)]),
        "phrt/stage": str(stage),
        "phrt/camera": str(camera_path),
        "phrt/metersPerUnit": np.array([float(meters_per_unit)]),
    }
    if timestamp:
        header["capDate"] = datetime.now(UTC).strftime("%Y:%m:%d %H:%M:%S")
        header["utcOffset"] = 0.0
    return header
