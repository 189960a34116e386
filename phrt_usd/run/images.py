"""Frame images: multi-channel OpenEXR files and 8-bit sRGB PNG previews.

EXRs are written with the ``OpenEXR`` bindings (``write_exr``: exact ``UINT`` channels,
matrix, rational and double header attributes, multi-part files), PNGs with OpenImageIO.
Both go through the one atomic writer. ``phrt_usd.run.products`` decides which files and
channels a frame gets; this module encodes them.

The default layout's channels (``write_frame_exr``; zip compressed, scanline):

=========  =======  ===================================================================
channel    storage  meaning
=========  =======  ===================================================================
R, G, B    half     linear RGB radiance (scene-referred); values above the half range
                    are clamped to ``HALF_MAX``
A          half     coverage, 1 where geometry was hit, 0 for background
Z          float    view depth in metres along the camera's -Z; background is written
                    as the finite ``DEPTH_BACKGROUND`` (1e30), read back as ``inf``
id         uint     element id (index into ``Scene.elements``); background (element id
                    -1) is ``ID_BACKGROUND`` (2**32 - 1, the bits of int32 -1); the
                    header's manifest names each id's prim (``phrt_usd.run.products``)
traced     half     1 where the pixel's reflection was ray-traced this frame, else 0
=========  =======  ===================================================================

Why ids stay ≤ ``MAX_EXACT_ID`` (2**24) although the channel is an exact uint32: many
tools read every channel as float32 (Nuke, OpenImageIO's float reads), where larger ids
would merge; a larger id raises ``PhrtError``.

Why Z is finite: many compositing operations (``1/Z``, depth merges, blur) turn ``inf``
into NaN; 1e30 m sorts behind everything and stays finite.

**Data window.** A file may hold only part of the image (UsdRender ``dataWindowNDC``,
``CameraFrame.data_window_pixels``): ``DataWindow`` names those pixels. An EXR then has
OpenEXR's two windows as production renderers write them: ``displayWindow`` the whole
W x H image, ``dataWindow`` the pixels held (inclusive corners, (0, 0) the top-left
pixel), and its channels hold only those pixels; a PNG holds only those pixels (PNG has
no display window). The writers take planes of the whole image and crop them.

Files carry no wall-clock time unless asked (``capDate``, see ``products``), so
identical renders are identical files.

The preview is ``tonemap_ldr`` quantised to 8 bits. ``tonemap_ldr`` is the display
transform used wherever an LDR image is needed (the sweep's FLIP error uses it too).
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenEXR
import OpenImageIO as oiio

from phrt_usd.atomic import WriteFailed, atomic_path, write_bytes_atomic
from phrt_usd.errors import PhrtError

#: Largest finite half-float; brighter radiance is clamped to it in half channels.
HALF_MAX = 65504.0
#: Depth written for background pixels (metres). Anything at or beyond it reads as inf.
DEPTH_BACKGROUND = 1e30
#: Largest element id written (2**24: what float32 readers still tell apart).
MAX_EXACT_ID = 2**24
#: The uint32 ``id`` of background pixels: element id -1 as uint32 bits.
ID_BACKGROUND = 2**32 - 1

#: The default layout's channels, in the order ``read_frame_exr`` knows them.
CHANNELS = ("R", "G", "B", "A", "Z", "id", "traced")
EXR_COMPRESSION = OpenEXR.ZIP_COMPRESSION
#: The colour space of RGB channels (EXR's ``colorInteropID``, as OpenImageIO names it).
COLOR_INTEROP_ID = "lin_rec709_scene"
#: The header attribute holding the id manifest as JSON text (``{"id": "prim path"}``).
MANIFEST_ATTR = "phrt/idManifest"
#: The storage types of EXR channels: numpy dtypes the OpenEXR bindings map to HALF,
#: FLOAT and UINT.
STORAGE = {"half": np.float16, "float": np.float32, "uint": np.uint32}


# --- the pixels a file holds -------------------------------------------------------------


@dataclass(frozen=True)
class DataWindow:
    """The pixels a file holds of a ``width`` x ``height`` image (module docstring):
    columns ``col0 <= c < col1`` and rows ``row0 <= r < row1``, row 0 at the top, as
    ``CameraFrame.data_window_pixels`` returns them. PhrtError if it holds no pixel or
    leaves the image."""

    width: int
    height: int
    col0: int
    row0: int
    col1: int
    row1: int

    def __post_init__(self):
        if not (0 <= self.col0 < self.col1 <= self.width and 0 <= self.row0 < self.row1
                <= self.height):  # fmt: skip
            raise PhrtError(
                f"data window columns {self.col0}..{self.col1}, rows {self.row0}..{self.row1} "
                f"holds no pixel of the {self.width}x{self.height} image"
            )

    @classmethod
    def full(cls, width: int, height: int) -> DataWindow:
        """Every pixel of the image."""
        return cls(int(width), int(height), 0, 0, int(width), int(height))

    @classmethod
    def of(cls, width: int, height: int, pixels: tuple[int, int, int, int]) -> DataWindow:
        """From ``CameraFrame.data_window_pixels(width, height)`` (col0, row0, col1, row1)."""
        return cls(int(width), int(height), *(int(p) for p in pixels))

    @property
    def is_full(self) -> bool:
        return (self.col0, self.row0, self.col1, self.row1) == (0, 0, self.width, self.height)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) held."""
        return self.row1 - self.row0, self.col1 - self.col0

    def crop(self, plane: np.ndarray, path: Path | str = "image") -> np.ndarray:
        """The held pixels of ``plane`` (H, W, ...) of the whole image (a view); PhrtError
        naming ``path`` if the plane is not the image's size."""
        plane = np.asarray(plane)
        if plane.shape[:2] != (self.height, self.width):
            raise PhrtError(
                f"{path}: planes must be {self.height}x{self.width} (rows x columns) for this "
                f"data window, got {plane.shape[:2]}"
            )
        return plane[self.row0 : self.row1, self.col0 : self.col1]

    def exr_windows(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """OpenEXR's ``displayWindow`` (the whole image) and ``dataWindow`` (the held
        pixels), each ((xMin, yMin), (xMax, yMax)) inclusive, int32."""

        def box(x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
            return np.array([x0, y0], np.int32), np.array([x1 - 1, y1 - 1], np.int32)

        return {
            "displayWindow": box(0, 0, self.width, self.height),
            "dataWindow": box(self.col0, self.row0, self.col1, self.row1),
        }


# --- encoding the renderer's planes ----------------------------------------------------


def check_beauty(path: Path, beauty: np.ndarray) -> np.ndarray:
    """``beauty`` as (H, W, 3) float32; PhrtError naming the first NaN/Inf pixel."""
    beauty = np.asarray(beauty)
    if beauty.ndim != 3 or beauty.shape[2] != 3:
        raise PhrtError(f"{path}: beauty must be (H, W, 3), got {beauty.shape}")
    if not np.isfinite(beauty).all():
        bad = np.argwhere(~np.isfinite(beauty))[0]
        raise PhrtError(f"{path}: beauty has NaN/Inf at row {bad[0]}, column {bad[1]}")
    return beauty.astype(np.float32, copy=False)


def check_plane(path: Path, name: str, plane: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``plane`` as an array of ``shape``; PhrtError naming it otherwise."""
    plane = np.asarray(plane)
    if plane.shape != tuple(shape):
        raise PhrtError(f"{path}: {name} must be {tuple(shape)}, got {plane.shape}")
    return plane


def stored_depth(path: Path, depth: np.ndarray) -> np.ndarray:
    """View depth as written: float32, +inf and beyond as ``DEPTH_BACKGROUND``; PhrtError
    for NaN."""
    depth = np.asarray(depth)
    if np.isnan(depth).any():
        raise PhrtError(f"{path}: depth has NaN")
    return np.minimum(depth, DEPTH_BACKGROUND).astype(np.float32)


def stored_ids(path: Path, element_id: np.ndarray) -> np.ndarray:
    """Element ids as written: uint32, -1 (background) as ``ID_BACKGROUND``; PhrtError for
    an id beyond ``MAX_EXACT_ID`` or below -1."""
    ids = np.asarray(element_id).astype(np.int64)
    if ids.size and (ids.max() > MAX_EXACT_ID or ids.min() < -1):
        raise PhrtError(f"{path}: element id beyond {MAX_EXACT_ID} cannot be stored exactly")
    return np.where(ids < 0, ID_BACKGROUND, ids).astype(np.uint32)


def stored(values: np.ndarray, storage: str) -> np.ndarray:
    """``values`` in ``storage`` ("half" | "float" | "uint"); half clamps to ±HALF_MAX
    (larger values would be stored as inf)."""
    if storage == "half":
        return np.clip(values, -HALF_MAX, HALF_MAX).astype(np.float16)
    return np.ascontiguousarray(values, dtype=STORAGE[storage])


# --- EXR files ---------------------------------------------------------------------------


def write_frame_exr(
    path: Path,
    beauty: np.ndarray,
    alpha: np.ndarray,
    depth: np.ndarray,
    element_id: np.ndarray,
    traced_mask: np.ndarray,
    metadata: Mapping[str, object] | None = None,
    manifest: Mapping[int, str] | None = None,
    window: DataWindow | None = None,
) -> None:
    """Write one frame in the default layout (``CHANNELS``, module docstring), atomically.

    beauty      : (H, W, 3) float32 linear RGB, must be finite (else PhrtError)
    alpha       : (H, W) float in [0, 1], coverage
    depth       : (H, W) float view depth in metres, ``inf`` for background (NaN raises)
    element_id  : (H, W) int32 element ids, -1 for background
    traced_mask : (H, W) bool, pixels whose reflection was ray-traced (or, at a reduced
                  ``--trace-density``, filled from traced neighbours)
    metadata    : extra header attributes (see ``write_exr``), e.g. ``{"phrt/timeCode": 12.0}``
    manifest    : element id → prim path of the ids in the frame (``MANIFEST_ATTR``)
    window      : the pixels the file holds (``DataWindow``; None: all)
    """
    path = Path(path)
    beauty = check_beauty(path, beauty)
    shape = beauty.shape[:2]
    alpha = check_plane(path, "alpha", alpha, shape)
    depth = check_plane(path, "depth", depth, shape)
    element_id = check_plane(path, "element_id", element_id, shape)
    traced_mask = check_plane(path, "traced_mask", traced_mask, shape)
    if not np.isfinite(alpha).all():
        raise PhrtError(f"{path}: alpha has NaN/Inf")
    channels = {
        "R": stored(beauty[..., 0], "half"),
        "G": stored(beauty[..., 1], "half"),
        "B": stored(beauty[..., 2], "half"),
        "A": stored(alpha, "half"),
        "Z": stored_depth(path, depth),
        "id": stored_ids(path, element_id),
        "traced": stored(traced_mask.astype(np.float32), "half"),
    }
    write_exr(path, {"": channels}, metadata, manifest, window=window)


def write_exr(
    path: Path,
    parts: Mapping[str, Mapping[str, np.ndarray]],
    header: Mapping[str, object] | None = None,
    manifest: Mapping[int, str] | None = None,
    manifest_channel: str = "id",
    window: DataWindow | None = None,
) -> None:
    """Write an EXR of ``parts`` (part name → channel name → (H, W) float16 / float32 /
    uint32 array of the whole image, storage HALF / FLOAT / UINT), atomically and zip
    compressed. With ``window`` (``DataWindow`` of the (H, W) image) the file holds only
    its pixels, its ``displayWindow`` the whole image and its ``dataWindow`` those pixels.

    One part named ``""`` is a single-part file; several parts make a multi-part file,
    each part named by its key. ``header`` attributes go on every part: ``str``,
    ``int``, ``float`` (stored as float32), a (1,) float64 array (a double), a (4, 4)
    float32 / float64 array (``M44f`` / ``M44d``), a ``fractions.Fraction``
    (a rational). ``manifest`` (id → prim path) is written twice: as the OpenEXR
    ``idManifest`` of ``manifest_channel`` (ids not hashed) and as JSON text in
    ``MANIFEST_ATTR`` (keys are decimal ids), which any EXR reader can show."""
    path = Path(path)
    shapes = {a.shape for channels in parts.values() for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise PhrtError(f"{path}: channels must all be one (H, W) size, got {sorted(shapes)}")
    full = next(iter(shapes))
    window = window or DataWindow.full(full[1], full[0])
    parts = {n: {c: window.crop(a, path) for c, a in ch.items()} for n, ch in parts.items()}
    attributes: dict[str, object] = {
        "compression": EXR_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "colorInteropID": COLOR_INTEROP_ID,
    }
    for key, value in (header or {}).items():
        # the bindings read an array's memory as C order, whatever its strides
        attributes[key] = np.ascontiguousarray(value) if isinstance(value, np.ndarray) else value
    if not window.is_full:
        attributes.update(window.exr_windows())
    if manifest is not None:
        attributes["idManifest"] = _id_manifest(manifest, manifest_channel)
        attributes[MANIFEST_ATTR] = json.dumps(
            {str(int(k)): str(v) for k, v in sorted(manifest.items())}, separators=(",", ":")
        )
    names = list(parts)
    if names == [""]:
        image = OpenEXR.File(attributes, _contiguous(parts[""]))
    else:
        image = OpenEXR.File(
            [OpenEXR.Part(dict(attributes), _contiguous(parts[n]), name=n) for n in names]
        )
    buffer = io.BytesIO()
    try:
        image.write(buffer)
    except (RuntimeError, TypeError, ValueError) as error:
        raise PhrtError(f"{path}: cannot encode EXR ({error})") from None
    write_bytes_atomic(path, buffer.getvalue(), _check_exr(window, [len(parts[n]) for n in names]))


def _contiguous(channels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for name, array in channels.items():
        if array.dtype not in (np.float16, np.float32, np.uint32):
            raise PhrtError(f"channel {name}: dtype {array.dtype} is not half, float or uint")
        out[name] = np.ascontiguousarray(array)
    return out


def _id_manifest(manifest: Mapping[int, str], channel: str) -> OpenEXR.IDManifest:
    """OpenEXR's own id manifest: one channel group, ids not hashed, stable for the run."""
    result = OpenEXR.IDManifest()
    group = result.add(channel)
    group.setComponent("prim")
    group.setEncodingScheme(OpenEXR.ID_MANIFEST_ID_SCHEME)
    group.setHashScheme(OpenEXR.ID_MANIFEST_NOTHASHED)
    group.setLifetime(OpenEXR.LIFETIME_SHOT)
    for key, value in sorted(manifest.items()):
        group.insert(int(key), str(value))
    return result


def _check_exr(window: DataWindow, counts: list[int]) -> Callable[[Path], None]:
    """A check for ``atomic_path``: the written file's header reads back with the display
    and data windows of ``window`` and the channel count of every part (pixels are not
    decoded)."""
    windows = {k: tuple(map(tuple, v)) for k, v in window.exr_windows().items()}
    expected = [(windows["displayWindow"], windows["dataWindow"], n) for n in counts]

    def check(path: Path) -> None:
        try:
            image = OpenEXR.File(str(path), header_only=True)
            got = [_windows_and_channels(p.header) for p in image.parts]
        except (RuntimeError, KeyError, IndexError, TypeError) as error:
            raise WriteFailed(f"{path}: written image does not open ({error})") from None
        if got != expected:
            raise WriteFailed(f"{path}: written image has the wrong size")

    return check


def _windows_and_channels(header: Mapping[str, object]) -> tuple[tuple, tuple, int]:
    """(display window, data window, channel count) from a part's header, the windows as
    ((xMin, yMin), (xMax, yMax)) int tuples."""

    def box(name: str) -> tuple:
        low, high = header[name]
        return (int(low[0]), int(low[1])), (int(high[0]), int(high[1]))

    return box("displayWindow"), box("dataWindow"), len(header["channels"])


def read_exr(path: Path) -> tuple[dict[str, object], dict[str, np.ndarray]]:
    """(header of the first part, channel name → (h, w) array of every part) of an EXR:
    the pixels of its ``dataWindow`` (the whole ``displayWindow`` unless the file holds
    a data window, ``DataWindow``). Arrays keep their storage: float16, float32 or uint32.
    PhrtError if it cannot be read."""
    path = Path(path)
    try:
        image = OpenEXR.File(str(path), separate_channels=True)
        header = dict(image.parts[0].header)
        channels = {
            name: np.asarray(channel.pixels)
            for part in image.parts
            for name, channel in part.channels.items()
        }
    except (RuntimeError, OSError, IndexError) as error:
        raise PhrtError(f"{path}: cannot read EXR ({error})") from None
    return header, channels


def read_manifest(header: Mapping[str, object]) -> dict[int, str]:
    """id → prim path from an EXR header written by ``write_exr`` (empty if it has none)."""
    text = header.get(MANIFEST_ATTR)
    if not isinstance(text, str):
        return {}
    return {int(k): v for k, v in json.loads(text).items()}


def element_ids(ids: np.ndarray) -> np.ndarray:
    """(H, W) int32 element ids (-1 background) from an ``id`` channel as read: uint32
    (``ID_BACKGROUND`` is -1) or the float ids of files written before uint ids."""
    if ids.dtype == np.uint32:
        return ids.view(np.int32).copy()
    return np.rint(ids.astype(np.float64)).astype(np.int32)


def read_frame_exr(path: Path) -> dict[str, np.ndarray]:
    """Read a frame written by ``write_frame_exr``.

    Returns ``beauty`` (H, W, 3) float32, ``alpha`` (H, W) float32, ``depth`` (H, W)
    float32 metres with ``inf`` for background, ``element_id`` (H, W) int32,
    ``traced_mask`` (H, W) bool; H, W those of the file's data window (``read_exr``).
    """
    path = Path(path)
    _, channel = read_exr(path)
    missing = [c for c in CHANNELS if c not in channel]
    if missing:
        raise PhrtError(f"{path}: not a phrt frame, missing channels {missing}")
    depth = channel["Z"].astype(np.float32)
    depth[depth >= np.float32(DEPTH_BACKGROUND)] = np.inf
    return {
        "beauty": np.stack([channel[c].astype(np.float32) for c in "RGB"], axis=-1),
        "alpha": channel["A"].astype(np.float32),
        "depth": depth,
        "element_id": element_ids(channel["id"]),
        "traced_mask": channel["traced"].astype(np.float32) > 0.5,
    }


# --- previews -------------------------------------------------------------------------


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values in [0, 1] (same shape, float32)."""
    linear = np.clip(linear, 0.0, 1.0).astype(np.float32)
    return np.where(
        linear <= 0.0031308,
        12.92 * linear,
        1.055 * np.power(linear, 1.0 / 2.4, dtype=np.float32) - 0.055,
    ).astype(np.float32)


def tonemap_ldr(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Display transform: linear HDR (H, W, 3) → sRGB-encoded (H, W, 3) float32 in [0, 1].

    ``value = srgb_oetf(clip(rgb * 2**exposure, 0, 1))`` per channel — a plain clamp, no
    highlight compression, so radiance ≤ 1 (any diffuse surface under unit light) keeps
    its exact colour. This is the image a viewer shows and what LDR-FLIP expects
    (sRGB-encoded values in [0, 1]). NaN maps to 0.
    """
    scaled = np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0) * np.float32(2.0**exposure)
    return srgb_oetf(scaled)


def write_preview_png(
    path: Path, beauty: np.ndarray, exposure: float = 0.0, window: DataWindow | None = None
) -> None:
    """Write ``tonemap_ldr(beauty)`` as an 8-bit RGB PNG, atomically.

    beauty : (H, W, 3) linear RGB of the whole image, must be finite (else PhrtError)
    window : the pixels the file holds (``DataWindow`` of the (H, W) image; None: all)
    """
    path = Path(path)
    beauty = np.asarray(beauty)
    if beauty.ndim != 3 or beauty.shape[2] != 3:
        raise PhrtError(f"{path}: beauty must be (H, W, 3), got {beauty.shape}")
    if not np.isfinite(beauty).all():
        raise PhrtError(f"{path}: beauty has NaN/Inf")
    if window is not None:
        beauty = window.crop(beauty, path)
    write_png_atomic(path, np.rint(tonemap_ldr(beauty, exposure) * 255.0).astype(np.uint8))


def write_png_atomic(path: Path, pixels: np.ndarray) -> None:
    """Write (H, W, 3) uint8 display-referred sRGB ``pixels`` as a PNG, atomically."""
    height, width = pixels.shape[:2]
    spec = oiio.ImageSpec(width, height, 3, oiio.UINT8)
    spec.attribute("oiio:ColorSpace", "srgb_rec709_scene")
    with atomic_path(Path(path), _check_image(spec)) as tmp:
        _write(tmp, spec, np.ascontiguousarray(pixels, dtype=np.uint8))


def read_preview_png(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 pixels of a preview PNG."""
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise PhrtError(f"{path}: cannot open image ({oiio.geterror()})")
    try:
        data = image.read_image(oiio.UINT8)
    finally:
        image.close()
    return np.asarray(data)[..., :3]


def _write(path: Path, spec: oiio.ImageSpec, pixels: np.ndarray) -> None:
    """Write ``pixels`` (H, W, C) with ``spec`` to ``path``; PhrtError on failure, the
    close included (a full disk shows there first)."""
    output = oiio.ImageOutput.create(str(path))
    if output is None:
        raise PhrtError(f"{path}: no image writer for this extension ({oiio.geterror()})")
    ok = output.open(str(path), spec) and output.write_image(pixels)
    closed = output.close()
    if not (ok and closed):
        raise WriteFailed(f"{path}: cannot write image ({output.geterror() or 'close failed'})")


def _check_image(spec: oiio.ImageSpec) -> Callable[[Path], None]:
    """A check for ``atomic_path``: the written file opens as an image of ``spec``'s size
    and channel count (the header and the file's length are read, not every pixel)."""

    def check(path: Path) -> None:
        image = oiio.ImageInput.open(str(path))
        if image is None:
            raise WriteFailed(f"{path}: written image does not open ({oiio.geterror()})")
        try:
            got = image.spec()
            if (got.width, got.height, got.nchannels) != (
                spec.width,
                spec.height,
                spec.nchannels,
            ):
                raise WriteFailed(f"{path}: written image has the wrong size")
        finally:
            image.close()

    return check
