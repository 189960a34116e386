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

Shapes: a G-buffer of H x W pixels, n of them covered, L lights (distant, then local).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from phrt_usd.engine.shading import gather_rows, shade_local, shaped_lights
from phrt_usd.model import surface
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import Scene

if TYPE_CHECKING:  # the raster and trace halves import OpenGL / Embree: only if used
    from phrt_usd.engine.raster.rasterizer import Rasterizer
    from phrt_usd.engine.trace.tracer import Tracer


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
    lights = scene.lights
    n_lights = len(lights.distant) + len(lights.local)
    shadow_pass = None
    local_pairs = lit_sums = None
    if n_lights == 0:
        visibility = np.ones((len(pos), 0), dtype=np.float32)
    elif mode == "rt":
        visibility = tracer.shadow_visibility(pos, nrm)
        shadow_pass = "shadow_rays"
    else:
        if rasterizer.cube_lookup_on_gpu and not shaped_lights(lights):
            # Lit pairs shaded in the GPU lookup pass; the rest comes back as
            # DistantLight visibility and the LocalLight pairs the maps could not
            # decide.
            terms = _settled(rasterizer.map_light_terms(pos, nrm, np.negative(view)), tracer)
            visibility = terms.distant_visibility
            local_pairs, lit_sums = terms.local_pairs, terms.lit_sums
        else:  # all lights, distant then local (the order shade_local expects); also
            # with spot cones, which only shade_local evaluates (shading.cone_falloff)
            pending = rasterizer.map_visibility(pos, nrm, filtered=tracer is None)
            visibility = _settled(pending, tracer)
        shadow_pass = "shadow_map" if tracer is None else "shadow_map+rays"
    if _emits(scene):
        emissive = surface.emissive_at(scene, take(gb.triangle_id), pos)  # textured too
    else:  # one zero for every point: no per-pixel gathers
        emissive = _NO_EMISSION
    shaded = shade_local(
        pos,
        nrm,
        take(gb.albedo),
        view,
        emissive,
        lights,
        visibility,
        local_pairs=local_pairs,
        lit_sums=lit_sums,
    )
    if isinstance(pix, slice):  # every pixel covered: the shading is the image
        return shaded.reshape(h, w, 3), shadow_pass
    local = np.zeros((h * w, 3), dtype=np.float32)
    local[pix] = shaded
    return local.reshape(h, w, 3), shadow_pass


#: ``shade_local``'s emission of every point in a scene whose materials emit nothing.
_NO_EMISSION = np.zeros(3, np.float32)


def _emits(scene: Scene) -> bool:
    """Some material of ``scene`` has a non-zero or textured emissiveColor."""
    materials = scene.materials
    return bool(np.any(materials.emissive)) or surface.has_texture_input(materials, "emissiveColor")


def _settled(pending, tracer: Tracer | None):
    """``pending`` (``MapVisibility`` or ``PendingLightTerms``) finished: the pairs the
    shadow maps could not decide resolved by ``tracer``'s shadow rays, or without a
    tracer by the maps' own filtering."""
    query = pending.uncertain_pairs()
    if tracer is None or query is None:
        return pending.filtered()
    exact = tracer.shadow_visibility(query.positions, query.normals, pairs=query.pairs)
    return pending.resolved(exact)
