"""Compositing: local shading, the raster fallback for reflections, and traced results
combined into one frame.

A reflector's pixel is its local shading plus its mirror reflection, weighted by one of
two rules:

- **The material** (``phrt:reflectivity`` unauthored): ``local + W * reflected``, W (RGB)
  the specular lobes' directional albedo at the pixel's view angle (split sum:
  ``shade_kernels.reflection_weight``, UsdPreviewSurface's Fresnel from F0 / F90 and its
  roughness, the clear coat's on top): a dielectric reflects ~4 % face on and more at
  grazing angles, a metal reflects tinted by its albedo. ``local`` leaves out the
  ambient's specular part, which the reflection stands in for.
- **An explicit F** (``phrt:reflectivity`` authored, ``Element.reflectivity_authored``):
  ``(1 - F) * local + F * reflected``, whatever the material says (the override of the
  paper's stages).

Non-reflectors have F = 0. ``reflected`` is the ray-traced radiance for pixels of
selected reflectors and, for all others, the environment seen in the mirror direction
(the raster path's cube-map-like fallback: no geometry in the reflection), prefiltered
by a glossy pixel's roughness (``prefiltered_environment``). Background
pixels show the environment behind them, unless the dome is hidden from camera rays
(``DomeLight.camera_visible``): then they stay black (alpha is 0 there).

Both rules are one form for the tracer's fill: a pixel's scalar f (``PixelReflectivity``,
the largest channel of W, or F) and ``local`` chosen so that ``(fallback - (1 - f) local)
/ f`` is the fallback's reflected environment (the fill's sky rule,
``trace/fill_kernels.py``); the RGB weight and the pixel's true local part are kept
beside f for ``apply_traced``.

Images: (H, W, 3) float32 linear RGB, row 0 at the top.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine.lighting import gbuffer_surface
from phrt_usd.engine.prefiltered_environment import prefiltered_radiance
from phrt_usd.engine.shading import environment_radiance, surface_weights
from phrt_usd.engine.trace import glossy
from phrt_usd.model import pixel_kinds
from phrt_usd.model.frame import GBuffer, ReflectionResult
from phrt_usd.model.scene import Scene

#: The largest scalar f of a material-rule pixel: its local image is divided by 1 - f
#: (the fill's form, module docstring), which stays finite here (a white metal's W is 1
#: at every angle; float32 keeps the quotient to ~1e-4 of it).
MATERIAL_MAX_F = 0.999


@dataclass
class ElementReflectivity:
    """The reflection rule of every element id (``element_reflectivity``).

    f        : (E + 1,) float32 F per element id, a trailing 0 for the background (-1)
    material : (E + 1,) bool, the reflectors whose reflection follows the material
    scene    : the scene (its materials, for the material rule's weights)
    """

    f: np.ndarray
    material: np.ndarray
    scene: Scene


class PixelReflectivity(np.ndarray):
    """(H, W) float32 f per pixel (``pixel_reflectivity``), and when some pixel follows
    its material ``weight`` (H, W, 3) float32, W of the module docstring (F on the
    explicit rule's pixels), and ``local`` (H, W, 3) float32 the pixels' local part
    (``base_image`` sets it), else both None: the plain ``(1 - F) local + F reflected``."""

    weight: np.ndarray | None = None
    local: np.ndarray | None = None
    material: np.ndarray | None = None  # (H, W) bool: the pixels of the material rule

    def __array_finalize__(self, obj) -> None:
        # Views and slices are plain values: the weights stay with the frame's array.
        self.weight = None
        self.local = None
        self.material = None


def reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Mirror ``directions`` (n, 3) about unit ``normals`` (n, 3): d - 2 (d·n) n."""
    return directions - 2.0 * np.sum(directions * normals, axis=1, keepdims=True) * normals


def pixel_reflectivity(gbuffer: GBuffer, element_reflectivity) -> np.ndarray:
    """(H, W) float32 f of the pixels (0 for background): F of the element seen at each,
    or on a material-rule reflector's pixels the largest channel of its weight W (then a
    ``PixelReflectivity`` holding W, module docstring).

    element_reflectivity: an ``ElementReflectivity``, or (E + 1,) float32 F per element
    id with a trailing 0 that the background id -1 indexes (every F explicit)."""
    if not isinstance(element_reflectivity, ElementReflectivity):
        return element_reflectivity[gbuffer.element_id]
    rule = element_reflectivity
    f = rule.f[gbuffer.element_id].view(PixelReflectivity)
    follows = rule.material[gbuffer.element_id]
    if not follows.any():
        return f
    weight = np.repeat(f[..., None], 3, axis=2).view(np.ndarray).astype(np.float32)
    at = np.nonzero(follows)
    surface = gbuffer_surface(
        rule.scene, gbuffer.triangle_id[at], gbuffer.element_id[at], gbuffer.albedo[at],
        gbuffer.position[at],
    )  # fmt: skip
    _, w = surface_weights(surface, gbuffer.normal[at], -gbuffer.view_dir[at])
    weight[at] = w
    f[at] = np.minimum(w.max(axis=1), MATERIAL_MAX_F)
    f.weight, f.material = weight, follows
    return f


def element_reflectivity(scene: Scene) -> ElementReflectivity:
    """The reflection rule of every element id (``ElementReflectivity``): F per element
    (0 for non-reflectors), the material's where ``phrt:reflectivity`` is unauthored."""
    material = [e.is_reflector and not e.reflectivity_authored for e in scene.elements]
    return ElementReflectivity(
        np.append(scene.reflectivity, np.float32(0.0)),
        np.array([*material, False], bool),
        scene,
    )


def base_image(
    gbuffer: GBuffer, scene: Scene, local: np.ndarray, reflectivity: np.ndarray
) -> np.ndarray:
    """The raster frame: local shading everywhere, environment fallback in reflectors.

    local        : (H, W, 3) float32 local shading (zero where uncovered); with
                   material-rule pixels turned in place into the fill's form (module
                   docstring, ``_material_local``)
    reflectivity : (H, W) float32 f per pixel (``pixel_reflectivity``)
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
    dome = scene.lights.dome
    if dome is not None and dome.texture is not None and glossy.has_glossy(scene):
        # A glossy pixel's fallback: the dome prefiltered by its lobe.
        rough = glossy.pixel_roughness(scene, gbuffer, pixels)
        if (rough > 0.0).any():
            env = prefiltered_radiance(scene.lights, directions, rough)
    image = np.empty((h, w, 3), np.float32)
    weight = getattr(reflectivity, "weight", None)
    if weight is not None:
        _material_local(local, reflectivity, pixels, env)
    shade_kernels.blend(
        np.ascontiguousarray(local, np.float32).reshape(-1, 3), f, pixels, env, image.reshape(-1, 3)
    )
    return image


def _material_local(local, reflectivity, pixels, env) -> None:
    """For a frame with material-rule pixels: keep each reflector pixel's local part
    (``(1 - F) local`` under an explicit F, ``local`` under the material's:
    ``reflectivity.material``) in ``reflectivity.local``, and turn ``local`` (in place)
    into the fill's form (module docstring): ``(L + (W - f) env) / (1 - f)``, so that
    ``(1 - f) local + f env`` is ``L + W env``, the pixel's fallback, and the fill's sky
    rule reads ``env`` back.
    pixels (m,) flat indices and env (m, 3) their mirror direction's environment
    (background pixels among them have f = 0 and are left alone)."""
    flat = local.reshape(-1, 3)
    f = np.asarray(reflectivity, np.float32).reshape(-1)
    weight = reflectivity.weight.reshape(-1, 3)
    reflectors = f[pixels] > 0.0
    at, env = pixels[reflectors], env[reflectors]
    fa = f[at][:, None]
    true_local = flat.copy()
    explicit = ~reflectivity.material.reshape(-1)[at][:, None]
    true_local[at] = np.where(explicit, (1.0 - fa) * flat[at], flat[at])
    reflectivity.local = true_local.reshape(local.shape)
    open_f = fa < 1.0
    fill = (true_local[at] + (weight[at] - fa) * env) / np.where(open_f, 1.0 - fa, 1.0)
    flat[at] = np.where(open_f, fill, flat[at])


def apply_traced(
    image: np.ndarray,
    local: np.ndarray,
    reflectivity: np.ndarray,
    result: ReflectionResult,
    traced_mask: np.ndarray,
    pixel_kind: np.ndarray | None = None,
) -> None:
    """Replace the fallback reflection of traced pixels with the traced radiance, in place.

    image, local : (H, W, 3) float32; reflectivity : (H, W) float32
                   (``pixel_reflectivity``'s, after ``base_image``);
    traced_mask  : (H, W) bool, set where pixels were traced (or filled from traced
                   neighbours);
    pixel_kind   : (H, W) uint8 (``model/pixel_kinds.py``), None: not kept; set to each
                   replaced pixel's kind (``result.kinds``, TRACED where it has none).
    """
    if result.pixel_index.size == 0:
        return
    flat_image = image.reshape(-1, 3)
    idx = result.pixel_index
    weight = getattr(reflectivity, "weight", None)
    if weight is not None and getattr(reflectivity, "local", None) is not None:
        # L + W reflected (module docstring), W = F on the explicit rule's pixels.
        true_local = reflectivity.local.reshape(-1, 3)
        flat_image[idx] = true_local[idx] + weight.reshape(-1, 3)[idx] * result.radiance
    else:
        f = np.asarray(reflectivity).reshape(-1)[idx][:, None]
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
