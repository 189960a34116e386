"""Frame images: one multi-channel OpenEXR per frame and an 8-bit sRGB PNG preview.

EXR channels (zip compressed, scanline):

=========  =======  ===================================================================
channel    storage  meaning
=========  =======  ===================================================================
R, G, B    half     linear RGB radiance (scene-referred); values above the half range
                    are clamped to ``HALF_MAX``
A          half     coverage, 1 where geometry was hit, 0 for background
Z          float    view depth in metres along the camera's -Z; background is written
                    as the finite ``DEPTH_BACKGROUND`` (1e30), read back as ``inf``
id         float    element id (index into ``Scene.elements``), -1 for background;
                    float32 holds every integer of magnitude ≤ 2**24 exactly
traced     half     1 where the pixel's reflection was ray-traced this frame, else 0
=========  =======  ===================================================================

Why ``id`` is float and not an EXR ``UINT`` channel: EXR and OpenImageIO support a UINT
channel next to half/float ones, but OIIO's Python ``write_image`` takes one buffer type
for all channels and converts floats to integer channels as *normalised* values (1.0 →
2**32-1), so a UINT channel cannot be filled exactly from Python in one pass. float32 is
what compositors expect of an object-id AOV anyway; ids beyond 2**24 raise ``PhrtError``.

Why Z is finite: many compositing operations (``1/Z``, depth merges, blur) turn ``inf``
into NaN; 1e30 m sorts behind everything and stays finite.

The preview is ``tonemap_ldr`` quantised to 8 bits. ``tonemap_ldr`` is the display
transform used wherever an LDR image is needed (the sweep's FLIP error uses it too).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from phrt_usd.atomic import WriteFailed, atomic_path
from phrt_usd.errors import PhrtError

#: Largest finite half-float; brighter radiance is clamped to it in the EXR's RGB.
HALF_MAX = 65504.0
#: Depth written for background pixels (metres). Anything at or beyond it reads as inf.
DEPTH_BACKGROUND = 1e30
#: Largest element id magnitude that float32 stores exactly (2**24).
MAX_EXACT_ID = 2**24

CHANNELS = ("R", "G", "B", "A", "Z", "id", "traced")
_CHANNEL_FORMATS = (
    oiio.HALF,
    oiio.HALF,
    oiio.HALF,
    oiio.HALF,
    oiio.FLOAT,
    oiio.FLOAT,
    oiio.HALF,
)
EXR_COMPRESSION = "zip"


def write_frame_exr(
    path: Path,
    beauty: np.ndarray,
    alpha: np.ndarray,
    depth: np.ndarray,
    element_id: np.ndarray,
    traced_mask: np.ndarray,
    metadata: dict[str, str | float | int] | None = None,
) -> None:
    """Write one frame as a multi-channel EXR, atomically.

    beauty      : (H, W, 3) float32 linear RGB, must be finite (else PhrtError)
    alpha       : (H, W) float in [0, 1], coverage
    depth       : (H, W) float view depth in metres, ``inf`` for background (NaN raises)
    element_id  : (H, W) int32 element ids, -1 for background
    traced_mask : (H, W) bool, pixels whose reflection was ray-traced
    metadata    : optional extra header attributes, e.g. ``{"phrt:time": 12.0}``
    """
    path = Path(path)
    beauty = np.asarray(beauty)
    if beauty.ndim != 3 or beauty.shape[2] != 3:
        raise PhrtError(f"{path}: beauty must be (H, W, 3), got {beauty.shape}")
    height, width = beauty.shape[:2]
    planes = {
        "alpha": np.asarray(alpha),
        "depth": np.asarray(depth),
        "element_id": np.asarray(element_id),
        "traced_mask": np.asarray(traced_mask),
    }
    for name, plane in planes.items():
        if plane.shape != (height, width):
            raise PhrtError(f"{path}: {name} must be {(height, width)}, got {plane.shape}")
    if not np.isfinite(beauty).all():
        bad = np.argwhere(~np.isfinite(beauty))[0]
        raise PhrtError(f"{path}: beauty has NaN/Inf at row {bad[0]}, column {bad[1]}")
    if not np.isfinite(planes["alpha"]).all():
        raise PhrtError(f"{path}: alpha has NaN/Inf")
    if np.isnan(planes["depth"]).any():
        raise PhrtError(f"{path}: depth has NaN")
    ids = planes["element_id"]
    if ids.size and np.abs(ids.astype(np.int64)).max() > MAX_EXACT_ID:
        raise PhrtError(f"{path}: element id beyond {MAX_EXACT_ID} cannot be stored exactly")

    pixels = np.empty((height, width, len(CHANNELS)), dtype=np.float32)
    # Clamp to the half range: larger values would be stored as inf.
    pixels[..., 0:3] = np.clip(beauty, -HALF_MAX, HALF_MAX)
    pixels[..., 3] = planes["alpha"]
    # +inf (background) and absurdly far depths both become the finite background value.
    pixels[..., 4] = np.minimum(planes["depth"], DEPTH_BACKGROUND)
    pixels[..., 5] = ids
    pixels[..., 6] = planes["traced_mask"].astype(np.float32)

    spec = oiio.ImageSpec(width, height, len(CHANNELS), oiio.FLOAT)
    spec.channelnames = CHANNELS
    spec.channelformats = _CHANNEL_FORMATS
    spec.alpha_channel = 3
    spec.z_channel = 4
    spec.attribute("compression", EXR_COMPRESSION)
    spec.attribute("oiio:ColorSpace", "lin_rec709_scene")
    for key, value in (metadata or {}).items():
        spec.attribute(key, value)
    with atomic_path(path, _check_image(spec)) as tmp:
        _write(tmp, spec, pixels)


def read_frame_exr(path: Path) -> dict[str, np.ndarray]:
    """Read a frame written by ``write_frame_exr``.

    Returns ``beauty`` (H, W, 3) float32, ``alpha`` (H, W) float32, ``depth`` (H, W)
    float32 metres with ``inf`` for background, ``element_id`` (H, W) int32,
    ``traced_mask`` (H, W) bool.
    """
    path = Path(path)
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise PhrtError(f"{path}: cannot open image ({oiio.geterror()})")
    try:
        names = list(image.spec().channelnames)
        missing = [c for c in CHANNELS if c not in names]
        if missing:
            raise PhrtError(f"{path}: not a phrt frame, missing channels {missing}")
        data = image.read_image(oiio.FLOAT)
        if data is None:
            raise PhrtError(f"{path}: cannot read pixels ({image.geterror()})")
    finally:
        image.close()
    channel = {name: data[..., names.index(name)] for name in CHANNELS}
    depth = channel["Z"].copy()
    depth[depth >= np.float32(DEPTH_BACKGROUND)] = np.inf
    return {
        "beauty": np.stack([channel["R"], channel["G"], channel["B"]], axis=-1),
        "alpha": channel["A"].copy(),
        "depth": depth,
        "element_id": np.rint(channel["id"]).astype(np.int32),
        "traced_mask": channel["traced"] > 0.5,
    }


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


def write_preview_png(path: Path, beauty: np.ndarray, exposure: float = 0.0) -> None:
    """Write ``tonemap_ldr(beauty)`` as an 8-bit RGB PNG, atomically.

    beauty : (H, W, 3) linear RGB, must be finite (else PhrtError)
    """
    path = Path(path)
    beauty = np.asarray(beauty)
    if beauty.ndim != 3 or beauty.shape[2] != 3:
        raise PhrtError(f"{path}: beauty must be (H, W, 3), got {beauty.shape}")
    if not np.isfinite(beauty).all():
        raise PhrtError(f"{path}: beauty has NaN/Inf")
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
