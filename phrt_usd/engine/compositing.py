"""Compositing: local shading, the raster fallback for reflections, and traced results
combined into one frame.

Every covered pixel is ``(1 - F) * local + F * reflected`` with F the element's
reflectivity (0 for non-reflectors). ``reflected`` is the ray-traced radiance for pixels
of selected reflectors and, for all others, the environment seen in the mirror
direction (the raster path's cube-map-like fallback: no geometry in the reflection).
Background pixels show the environment behind them, unless the dome is hidden from
camera rays (``DomeLight.camera_visible``): then they stay black (alpha is 0 there).

Images: (H, W, 3) float32 linear RGB, row 0 at the top.
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine.shading import environment_radiance
from phrt_usd.model import pixel_kinds
from phrt_usd.model.frame import GBuffer, ReflectionResult
from phrt_usd.model.scene import Scene


def reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Mirror ``directions`` (n, 3) about unit ``normals`` (n, 3): d - 2 (d·n) n."""
    return directions - 2.0 * np.sum(directions * normals, axis=1, keepdims=True) * normals


def pixel_reflectivity(gbuffer: GBuffer, element_reflectivity: np.ndarray) -> np.ndarray:
    """(H, W) float32 F of the element seen at each pixel (0 for background).

    element_reflectivity: (E + 1,) float32 F per element id, with a trailing 0 that the
    background id -1 indexes (see ``element_reflectivity``)."""
    return element_reflectivity[gbuffer.element_id]


def element_reflectivity(scene: Scene) -> np.ndarray:
    """(E + 1,) float32 F per element id plus a trailing 0 for the background (id -1)."""
    return np.append(scene.reflectivity, np.float32(0.0))


def base_image(
    gbuffer: GBuffer, scene: Scene, local: np.ndarray, reflectivity: np.ndarray
) -> np.ndarray:
    """The raster frame: local shading everywhere, environment fallback in reflectors.

    local        : (H, W, 3) float32 local shading (zero where uncovered)
    reflectivity : (H, W) float32 F per pixel
    Returns (H, W, 3) float32.
    """
    h, w = gbuffer.shape
    dome = scene.lights.dome
    background = dome is None or dome.camera_visible
    f = np.ascontiguousarray(reflectivity, np.float32).reshape(-1)
    shade_kernels = kernels.load("phrt_usd.engine.shade_kernels")  # compiled, on first use

    pixels, directions = shade_kernels.fallback_rays(
        np.ascontiguousarray(gbuffer.covered).reshape(-1),
        f,
        np.ascontiguousarray(gbuffer.view_dir, np.float32).reshape(-1, 3),
        np.ascontiguousarray(gbuffer.normal, np.float32).reshape(-1, 3),
        background,
    )
    env = environment_radiance(scene.lights, directions)
    image = np.empty((h, w, 3), np.float32)
    shade_kernels.blend(
        np.ascontiguousarray(local, np.float32).reshape(-1, 3), f, pixels, env, image.reshape(-1, 3)
    )
    return image


def apply_traced(
    image: np.ndarray,
    local: np.ndarray,
    reflectivity: np.ndarray,
    result: ReflectionResult,
    traced_mask: np.ndarray,
    pixel_kind: np.ndarray | None = None,
) -> None:
    """Replace the fallback reflection of traced pixels with the traced radiance, in place.

    image, local : (H, W, 3) float32; reflectivity : (H, W) float32;
    traced_mask  : (H, W) bool, set where pixels were traced (or filled from traced
                   neighbours);
    pixel_kind   : (H, W) uint8 (``model/pixel_kinds.py``), None: not kept; set to each
                   replaced pixel's kind (``result.kinds``, TRACED where it has none).
    """
    if result.pixel_index.size == 0:
        return
    flat_image = image.reshape(-1, 3)
    idx = result.pixel_index
    f = reflectivity.reshape(-1)[idx][:, None]
    flat_image[idx] = (1.0 - f) * local.reshape(-1, 3)[idx] + f * result.radiance
    traced_mask.reshape(-1)[idx] = True
    if pixel_kind is not None:
        kinds = pixel_kinds.TRACED if result.kinds is None else result.kinds
        pixel_kind.reshape(-1)[idx] = kinds


def observe_fallback_error(
    result: ReflectionResult, image: np.ndarray, fallback: np.ndarray, element_id: np.ndarray
) -> None:
    """Set each record's ``fallback_error``: the mean over its source's traced pixels of
    ``mean_rgb |clip(image) - clip(fallback)|``, what tracing changed on screen there.

    image    : (H, W, 3) float32 linear RGB after ``apply_traced`` of ``result``;
    fallback : (H, W, 3) float32 the raster frame of the same pixels (``base_image``);
    element_id : (H, W) int32 (``GBuffer.element_id``): a traced pixel's source reflector.
    Values are clipped to [0, 1] as the display transform clips them (``tonemap_ldr``,
    run/images.py, which this phase cannot import; its sRGB encoding is left out), so a
    highlight far above white counts as white, and NaN counts as 0: the figure is finite,
    in [0, 1]. Sources without traced pixels get 0.
    """
    idx = result.pixel_index
    if idx.size == 0:
        for rec in result.records:
            rec.fallback_error = 0.0
        return
    traced = np.clip(np.nan_to_num(image.reshape(-1, 3)[idx]), 0.0, 1.0)
    raster = np.clip(np.nan_to_num(fallback.reshape(-1, 3)[idx]), 0.0, 1.0)
    diff = np.abs(traced - raster).mean(axis=1, dtype=np.float64)
    sources, inverse = np.unique(element_id.reshape(-1)[idx], return_inverse=True)
    mean = np.bincount(inverse, weights=diff) / np.bincount(inverse)
    by_source = dict(zip(sources.tolist(), mean.tolist(), strict=True))
    for rec in result.records:
        rec.fallback_error = float(by_source.get(int(rec.source), 0.0))
