"""Texture files read through USD's asset resolver (``pxr.Ar``), decoded by OpenImageIO.

A UsdUVTexture's ``inputs:file`` may name a file on disk, a file inside a ``.usdz``
package (``scene.usdz[textures/wood.png]``) or any asset a resolver plugin serves. The
bytes always come from ``ArGetResolver().OpenAsset`` of the resolved path; OpenImageIO's
Python binding has no in-memory reader, so the bytes of a package-internal asset are
written to a private temporary file with the asset's extension and decoded from there
(a plain file on disk is decoded in place).

``read_texture`` raises ``TextureError`` (one line naming the attribute) for a path that
does not resolve or bytes that do not decode; ``phrt_usd.usd.materials`` turns that into a
warning and the input's fallback (or an error with ``--strict``).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import OpenImageIO as oiio
from pxr import Ar, Sdf

from phrt_usd.errors import PhrtError


class TextureError(PhrtError):
    """A texture that cannot be resolved or decoded (one line, naming the attribute)."""


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function, inverse (values in [0, 1])."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def auto_is_srgb(eight_bit: bool, pixels: np.ndarray) -> bool:
    """``sourceColorSpace = auto`` without colour-space metadata, as the UsdPreviewSurface
    specification (and Storm) decide: sRGB for 8-bit files of 3 or 4 channels, else raw
    (an 8-bit grey map, e.g. roughness or opacity, is data)."""
    return bool(eight_bit and pixels.shape[2] in (3, 4))


def resolved_path(value, where: str) -> str:
    """The resolved path of an ``SdfAssetPath`` value (or a string): the path USD's
    composition anchored and resolved, else the resolver's answer. Raises
    ``TextureError`` when nothing resolves."""
    if isinstance(value, Sdf.AssetPath):
        path, authored = value.resolvedPath, value.path
    else:
        path, authored = "", str(value or "")
    if not path and authored:
        path = str(Ar.GetResolver().Resolve(authored))
    if not path:
        raise TextureError(f"{where}: texture file {authored!r} not found")
    return path


def _decode(path: str, where: str) -> tuple[np.ndarray, bool, str]:
    """(pixels (h, w, c), 8-bit file?, wrap metadata or "") of a file on disk: uint8
    codes of an unsigned 8-bit file (``read_texture`` turns them into float32 through a
    table), else float32."""
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise TextureError(f"{where}: cannot decode texture {path!r} ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        codes = spec.format.basetype == oiio.UINT8
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "uint8" if codes else "float")
        eight_bit = spec.format.basetype in (oiio.UINT8, oiio.INT8)
        wrap = str(spec.getattribute("wrapmodes") or "")
    finally:
        inp.close()
    if pixels is None:
        raise TextureError(f"{where}: cannot decode texture {path!r}")
    kind = np.uint8 if codes else np.float32
    pixels = np.asarray(pixels, dtype=kind).reshape(spec.height, spec.width, -1)
    return pixels, eight_bit, wrap


def _refuse_special_file(path: str, where: str) -> None:
    """``TextureError`` when ``path``, or the package a package-relative path
    (``scene.usdz[textures/wood.png]``) is in, exists on disk as something other than a
    regular file: a directory, or a device or pipe, which would be read without end
    (``/dev/zero``) or block. Paths only a resolver plugin serves pass."""
    outer = Ar.SplitPackageRelativePathOuter(path)[0] if Ar.IsPackageRelativePath(path) else path
    if os.path.exists(outer) and not os.path.isfile(outer):
        kind = "a directory" if os.path.isdir(outer) else "a device, pipe or socket"
        raise TextureError(f"{where}: texture file {outer!r} is not a regular file ({kind})")


def read_asset_pixels(path: str, where: str) -> tuple[np.ndarray, bool, str]:
    """Decode the asset at resolved ``path`` (its bytes through ``Ar``): (pixels
    (h, w, c) row 0 = top, uint8 codes of an unsigned 8-bit file else float32, 8-bit
    file?, the file's wrap metadata or "")."""
    resolver = Ar.GetResolver()
    if os.path.isfile(path):
        return _decode(path, where)
    _refuse_special_file(path, where)
    asset = resolver.OpenAsset(Ar.ResolvedPath(path))
    if asset is None:
        raise TextureError(f"{where}: cannot open texture {path!r}")
    data = asset.GetBuffer()
    if not data:  # USD gives no buffer for an empty asset
        raise TextureError(f"{where}: texture {path!r} is empty")
    ext = resolver.GetExtension(path) or "img"
    fd, tmp = tempfile.mkstemp(suffix=f".{ext}", prefix="phrt-texture-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return _decode(tmp, where)
    finally:
        os.unlink(tmp)


def read_texture(value, where: str, color_space: str = "auto") -> tuple[np.ndarray, str]:
    """(image (h, w, c) float32 linear, row 0 = top, c = the file's channels; wrap
    metadata) of an ``inputs:file`` value. color_space: ``sourceColorSpace`` — "sRGB"
    converts the colour channels to linear, "raw" does not, "auto" converts 8-bit files
    of 3 or 4 channels only (``auto_is_srgb``); alpha is never converted. Non-finite
    texels read as 0."""
    pixels, eight_bit, wrap = read_asset_pixels(resolved_path(value, where), where)
    srgb = color_space == "sRGB" or (color_space == "auto" and auto_is_srgb(eight_bit, pixels))
    colour = 1 if pixels.shape[2] <= 2 else 3
    if pixels.dtype == np.uint8:  # 256 codes: each channel through its table, one gather
        out = _LINEAR_CODES[pixels]
        if srgb:
            out[..., :colour] = _SRGB_CODES[pixels[..., :colour]]
        return out, wrap
    pixels = np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0)
    if srgb:
        pixels[..., :colour] = _srgb_to_linear(np.clip(pixels[..., :colour], 0.0, 1.0))
    return np.ascontiguousarray(pixels, dtype=np.float32), wrap


#: float32 of each 8-bit code: code / 255, and that decoded as sRGB (the tables
#: ``read_texture`` reads 8-bit files through; a 2048² RGB texture's decode took ~0.25 s
#: computed per texel).
_LINEAR_CODES = (np.arange(256, dtype=np.float32) / np.float32(255.0)).astype(np.float32)
_SRGB_CODES = _srgb_to_linear(_LINEAR_CODES.astype(np.float64)).astype(np.float32)
