"""Direct lighting of a frame's G-buffer: who answers its shadow queries, per render mode,
then the local shading of every covered pixel (``shading.shade_local``).

- ``rt``: the tracer's shadow rays for every (pixel, light) pair.
- ``raster``: the rasterizer's shadow maps alone; the pairs they cannot decide (shadow
  edges, casters thinner than a texel) get the maps' percentage-closer filtering.
- ``hybrid``: the shadow maps, and those undecided pairs resolved by the tracer's shadow
  rays (only when the renderer has a tracer; without reflectors to trace it has none,
  and the maps' filtering is used as in ``raster``).

The raster side returns the undecided pairs (``map_lighting.UncertainPairs``); the
settling happens here, so the rasterizer never calls the tracer. With the GPU lookup
(``Rasterizer.cube_lookup_on_gpu``) the pairs the maps decide are lit are shaded in the
lookup pass already and only the rest is shaded in numpy; with a shaped LocalLight
(UsdLux ShapingAPI cones, ``shading.cone_falloff``) the GPU pass only looks the maps up
and every pair is shaded in numpy, so the cone has one implementation.

The tracer's hits are lit by the same two steps (``trace/hit_lighting.py``): the maps'
lookup (``map_lookup``) and the shading of what it settled (``shade_settled``), with
its own settling of the undecided pairs (shadow rays, lights sampled where a hit has
many: docs/hit-lighting.md).

Shapes: a G-buffer of H x W pixels, n of them covered, L lights (distant, then local).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from phrt_usd.engine.shading import gather_rows, point_surface, shade_local, shaped_lights
from phrt_usd.engine.terminator import Terminator
from phrt_usd.model import surface
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.light_sampling import has_area_lights
from phrt_usd.model.scene import Lights, Scene

if TYPE_CHECKING:  # the raster half imports OpenGL: only if used
    from phrt_usd.engine.raster.map_lighting import (
        LightTerms,
        MapVisibility,
        PendingLightTerms,
    )
    from phrt_usd.engine.raster.rasterizer import Rasterizer


class Tracer(Protocol):
    """What lighting asks of the tracer (``trace.tracer.Tracer``, not imported here: the
    tracer's hit lighting imports this module): exact shadow rays."""

    def shadow_visibility(self, positions, normals, triangle_ids=None, pairs=None,
                          pixels=None): ...  # fmt: skip


def shade_gbuffer(
    gb: GBuffer,
    scene: Scene,
    mode: str,
    rasterizer: Rasterizer | None,
    tracer: Tracer | None,
) -> tuple[np.ndarray, str | None]:
    """Local shading (H, W, 3) float32 of ``gb``'s covered pixels (0 elsewhere) and the
    shadow pass used, if any ("shadow_rays", "shadow_map" or "shadow_map+rays").

    mode : "rt" (needs ``tracer``), "raster" or "hybrid" (need ``rasterizer``; a
    ``tracer`` there resolves the pairs the shadow maps cannot decide).
    """
    h, w = gb.shape
    covered = gb.covered.reshape(-1)
    if not covered.any():
        return np.zeros((h, w, 3), dtype=np.float32), None
    # Covered pixels as flat indices (enclosed stages cover every pixel: then plain
    # reshapes, no gather at all).
    pix = slice(None) if covered.all() else np.flatnonzero(covered)

    def take(a: np.ndarray) -> np.ndarray:
        flat = a.reshape(h * w, *a.shape[2:])
        return flat if isinstance(pix, slice) else gather_rows(flat, pix)

    pos = take(gb.position)
    nrm = take(gb.normal)
    view = take(gb.view_dir)
    tri, element = take(gb.triangle_id), take(gb.element_id)
    surf = gbuffer_surface(scene, tri, element, take(gb.albedo), pos)
    lights = scene.lights
    n_lights = len(lights.distant) + len(lights.local)
    shadow_pass = None
    # The points' pixels draw the area lights' rays (only a stage with Rect or Disk
    # lights needs them).
    pixels = (_pixels(pix, h * w), w) if has_area_lights(lights) else None
    if n_lights == 0:
        visibility = np.ones((len(pos), 0), dtype=np.float32)
    elif mode == "rt":
        visibility = tracer.shadow_visibility(pos, nrm, tri, pixels=pixels)
        shadow_pass = "shadow_rays"
    else:
        terminator = Terminator.of(
            rasterizer.triangle_table, pos, scene.origin, tri, nrm, lights
        )
        pending = map_lookup(
            rasterizer, lights, pos, nrm, view, filtered=tracer is None, surface=surf,
            terminator=terminator,
        )  # fmt: skip
        visibility = _settled(pending, tracer, tri, pixels)
        shadow_pass = "shadow_map" if tracer is None else "shadow_map+rays"
    if _emits(scene):
        emissive = surface.emissive_at(scene, tri, pos)  # textured too
    else:  # one zero for every point: no per-pixel gathers
        emissive = _NO_EMISSION
    shaded = shade_settled(pos, nrm, surf, view, emissive, lights, visibility)
    if isinstance(pix, slice):  # every pixel covered: the shading is the image
        return shaded.reshape(h, w, 3), shadow_pass
    local = np.zeros((h * w, 3), dtype=np.float32)
    local[pix] = shaded
    return local.reshape(h, w, 3), shadow_pass


#: ``shade_local``'s emission of every point in a scene whose materials emit nothing.
_NO_EMISSION = np.zeros(3, np.float32)


def gbuffer_surface(scene: Scene, tri, element, albedo, positions) -> np.ndarray:
    """(n, SURFACE_COLUMNS) float32 UsdPreviewSurface rows (``model.preview_surface``) of
    n G-buffer pixels: triangles ``tri`` (n,) of elements ``element`` (n,) with their
    ``albedo`` (n, 3) at world ``positions`` (n, 3) (the barycentric weights of textured
    inputs come from them, ``surface.point_weights``); reflector pixels leave the
    ambient's specular part to their reflection (``compositing``)."""
    geo = scene.geometry
    reflector = _reflector_elements(scene)
    specular_ambient = np.where(np.take(reflector, element), 0.0, 1.0).astype(np.float32)
    return point_surface(
        scene.materials, geo.tri_material, tri, albedo, geo.corner_uv,
        lambda: surface.point_weights(geo.vertices, geo.triangles, tri, positions),
        specular_ambient,
    )  # fmt: skip


def _reflector_elements(scene: Scene) -> np.ndarray:
    """(E,) bool: the elements that are reflectors."""
    return np.array([e.is_reflector for e in scene.elements] or [False], dtype=bool)


def _emits(scene: Scene) -> bool:
    """Some material of ``scene`` has a non-zero or textured emissiveColor."""
    materials = scene.materials
    return bool(np.any(materials.emissive)) or surface.has_texture_input(materials, "emissiveColor")


def map_lookup(
    rasterizer: Rasterizer,
    lights: Lights,
    positions: np.ndarray,
    normals: np.ndarray,
    view_dirs: np.ndarray,
    filtered: bool = False,
    surface: np.ndarray | None = None,
    terminator: Terminator | None = None,
) -> MapVisibility | PendingLightTerms:
    """What the shadow maps say about the direct light of points (n, 3) float64 world
    metres with unit ``normals`` facing the viewer and ``view_dirs`` (n, 3) unit from the
    viewer to them, the pairs they cannot decide left open: with the GPU lookup the
    light terms (lit pairs shaded in the lookup pass with the points' ``surface`` rows,
    (n, SURFACE_COLUMNS), else the fallback material of albedo 1:
    ``Rasterizer.map_light_terms``), else, or with a cone-shaped LocalLight
    (only ``shade_local`` evaluates cones), the (n, L) visibility
    (``Rasterizer.map_visibility``; ``filtered``: the undecided pairs get the maps'
    PCF). ``terminator``: the points' moves onto their smooth meshes' surface for the
    shadow tests (``engine/terminator.py``), or None. The G-buffer's and the tracer's
    hits' one lookup."""
    if rasterizer.cube_lookup_on_gpu and not shaped_lights(lights):
        return rasterizer.map_light_terms(
            positions, normals, np.negative(view_dirs), surface=surface, terminator=terminator
        )
    return rasterizer.map_visibility(positions, normals, filtered=filtered, terminator=terminator)


def shade_settled(
    positions: np.ndarray,
    normals: np.ndarray,
    surface: np.ndarray,
    view_dirs: np.ndarray,
    emissive: np.ndarray,
    lights: Lights,
    settled: np.ndarray | LightTerms,
) -> np.ndarray:
    """``shade_local`` (same arguments, (n, 3) float32) with what a ``map_lookup``
    became once its undecided pairs were settled: the (n, L) visibility, or the light
    terms (DistantLight visibility, LocalLight pairs, the GPU's lit sums); an (n, L)
    visibility also for points the maps never saw (``rt``)."""
    if isinstance(settled, np.ndarray):
        return shade_local(positions, normals, surface, view_dirs, emissive, lights, settled)
    return shade_local(
        positions,
        normals,
        surface,
        view_dirs,
        emissive,
        lights,
        settled.distant_visibility,
        local_pairs=settled.local_pairs,
        lit_sums=settled.lit_sums,
    )


def _pixels(pix: slice | np.ndarray, size: int) -> np.ndarray:
    """The covered pixels' flat indices: ``pix`` (an index array, or every pixel)."""
    return np.arange(size) if isinstance(pix, slice) else pix


def _settled(pending, tracer: Tracer | None, triangles: np.ndarray, pixels=None):
    """``pending`` (``MapVisibility`` or ``PendingLightTerms``) of points on
    ``triangles`` (n,) finished: the pairs the shadow maps could not decide resolved by
    ``tracer``'s shadow rays, cast from the points' triangles as rt's are (the smooth
    surface's lift, no self-hits: docs/hit-lighting.md; ``pixels``: the points' (flat
    indices (n,), image width), whose rays sample an area light as rt's do), or without a
    tracer by the maps' own filtering."""
    query = pending.uncertain_pairs()
    if tracer is None or query is None:
        return pending.filtered()
    at = None if pixels is None else (np.take(pixels[0], query.rows), pixels[1])
    exact = tracer.shadow_visibility(
        query.positions, query.normals, np.take(triangles, query.rows), pairs=query.pairs,
        pixels=at,
    )
    return pending.resolved(exact)
