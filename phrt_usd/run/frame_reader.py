"""Reading a rendered frame back as arrays, whatever its products' layout.

``read_frame_files`` reads every file the run's ``ImagePlan`` (``run.products``) gave a
frame and returns each plane once, by what it holds rather than by file or channel name:
a RenderVar's channels are known from the plan (renamed ones included, multi-part files
included), so the default ``frames/NNNN.exr``, a colour-only product, a product of AOVs
beside a colour product and a PNG-only product all read back. The first EXR that holds a
plane gives it; the beauty of a run whose only colour is a ``.png`` is that 8-bit sRGB
preview decoded to linear (``srgb_decode``; clamped to [0, 1] by the preview's tone map).

==============  =======================  ====================================================
key             shape, dtype             from the source (``products.SOURCES``)
==============  =======================  ====================================================
beauty          (H, W, 3) float32        color (linear RGB), else a ``.png`` product decoded
alpha           (H, W) float32           color's A or alpha (coverage)
depth           (H, W) float32           depth, metres; ``inf`` for background
element_id      (H, W) int32             primId / id, -1 for background
traced_mask     (H, W) bool              phrt:traced
normal          (H, W, 3) float32        normal
position        (H, W, 3) float32        position, metres
albedo          (H, W, 3) float32        albedo
reflectivity    (H, W) float32           phrt:reflectivity
motion          (H, W, 2) float32        motion (pixels, x right, y down)
pixel_kind      (H, W) uint8             phrt:pixelKind (``model/pixel_kinds.py``)
==============  =======================  ====================================================

A key is present when some file of the frame holds its plane; H, W are those of the
files' data window (``images.read_exr``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.run.images import DEPTH_BACKGROUND, element_ids, read_exr, read_preview_png
from phrt_usd.run.products import Channel, ImagePlan, expand

#: The key each source's plane is returned under (module docstring, the table).
PLANE_KEYS = {
    "beauty": "beauty",
    "alpha": "alpha",
    "depth": "depth",
    "id": "element_id",
    "traced": "traced_mask",
    "normal": "normal",
    "position": "position",
    "albedo": "albedo",
    "reflectivity": "reflectivity",
    "motion": "motion",
    "pixel_kind": "pixel_kind",
}
#: The largest code of an 8-bit preview.
PREVIEW_MAX = 255.0


def read_frame_files(plan: ImagePlan, out: Path, time: float) -> dict[str, np.ndarray]:
    """The planes of frame ``time`` of a run into ``out`` with ``plan`` (module
    docstring). PhrtError naming the file when one is missing, unreadable or lacks a
    channel the plan gave it, or when the frame's files hold no plane at all."""
    out = Path(out)
    planes: dict[str, np.ndarray] = {}
    previews: list[Path] = []
    for product in plan.products:
        path = _existing(out / expand(product.template, time), time)
        if product.is_png:
            previews.append(path)
            continue
        _, channels = read_exr(path)
        for source, parts in _by_source(product.channels).items():
            key = PLANE_KEYS[source]
            if key not in planes:
                planes[key] = _plane(source, [_channel(channels, c.name, path) for c in parts])
        if product.preview:
            previews.append(_existing(out / expand(product.preview, time), time))
    if "beauty" not in planes and previews:
        encoded = read_preview_png(previews[0]).astype(np.float32) / np.float32(PREVIEW_MAX)
        planes["beauty"] = srgb_decode(encoded)
    if not planes:
        raise PhrtError(f"frame {time:g}: its files hold no image plane ({out})")
    return planes


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Linear float32 values of sRGB-encoded ones in [0, 1] (IEC 61966-2-1; the inverse of
    ``images.srgb_oetf``)."""
    encoded = np.asarray(encoded, dtype=np.float32)
    linear = np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)
    return linear.astype(np.float32)


def _existing(path: Path, time: float) -> Path:
    if not path.is_file():
        raise PhrtError(f"frame {time:g}: {path}: no such image file")
    return path


def _by_source(channels: tuple[Channel, ...]) -> dict[str, list[Channel]]:
    """A product's channels grouped by the plane they hold, in component order."""
    grouped: dict[str, list[Channel]] = {}
    for channel in channels:
        grouped.setdefault(channel.source, []).append(channel)
    return {s: sorted(parts, key=lambda c: c.component) for s, parts in grouped.items()}


def _channel(channels: dict[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    if name not in channels:
        raise PhrtError(f"{path}: no channel {name!r} (channels: {', '.join(sorted(channels))})")
    return channels[name]


def _plane(source: str, arrays: list[np.ndarray]) -> np.ndarray:
    """One source's plane from its channels as stored (module docstring, the table)."""
    if source == "id":
        return element_ids(arrays[0])
    if source == "pixel_kind":
        return arrays[0].astype(np.uint8)
    values = [a.astype(np.float32) for a in arrays]
    if source == "traced":
        return values[0] > 0.5
    if source == "depth":
        depth = values[0]
        depth[depth >= np.float32(DEPTH_BACKGROUND)] = np.inf
        return depth
    return values[0] if len(values) == 1 else np.stack(values, axis=-1)
