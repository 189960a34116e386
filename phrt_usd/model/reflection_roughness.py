"""What a reflector's roughness does to its reflection: the rule the tracer
(``engine/trace/glossy.py``) and the selection (``select/policies.py``) share.

A reflector whose material reflects by its roughness (``MaterialTable.glossy``: a bound
UsdPreviewSurface) reflects a mirror ray at or below MIRROR_ROUGHNESS, rays drawn from
its GGX lobe above it, on a pattern that thins with roughness (RATE_BY_ROUGHNESS: the
filter that reconstructs the lobe's blur averages the samples anyway), and fades into
the raster's environment fallback from FADE_START to FADE_END, where it casts no ray.

For the selection: a reflector's **gain from tracing** is the share of its reflection
the rays make, 1 - ``fade`` (the fallback makes the rest; a reflector past FADE_END
gains nothing), and its **ray shares** the share of its pixels that start rays at each
trace density (``ray_share``: at full density 1 for a mirror, the rate's pattern for a
glossy pixel, 0 past the fade; at a reduced density the coarser of that and the
density's pattern, so a glossy reflector stepped to a coarser density saves less).
Per element, both are taken at its material's constant roughness (a textured
roughness at the input's constant value; the clear coat is not looked at), weighed by
its triangles.

Plain numpy; no USD, OpenGL or numba here.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.model.trace_density import DENSITY_FRACTION, TRACE_DENSITIES, traced_fraction

#: At or below this roughness a reflection is the exact mirror ray: the lobe (alpha =
#: r² = 0.0025) spreads reflected rays by a few tenths of a degree, under a pixel of the
#: renderer's usual views except at grazing angles, where a one-sample estimate of it
#: only sparkles (the sewer's water, 0.05, under its lights) and its filter would blur
#: the reflection more than the lobe does.
MIRROR_ROUGHNESS = 0.05
#: From this roughness on the traced reflection fades into the raster's environment
#: fallback, linearly, reaching it at FADE_END (no rays from there on); UE's ray-traced
#: reflections stop at 0.6 by default, fading over the last part, EEVEE's at a chosen
#: maximum roughness the same way.
FADE_START = 0.5
FADE_END = 0.7
#: The ray rate of glossy pixels by roughness: from each roughness on, at most the
#: density named (a glossy pixel starts rays on the coarser of its reflector's density
#: and this one's pattern). The tracer's filter reaches 1.5 pattern spacings and at
#: least ~16 r pixels, so the pixels between the samples are reconstructed by the
#: filter that averages the samples anyway (0.1: a checkerboard, 0.15: a 2 x 2 grid,
#: 0.35: a 4 x 4 one).
RATE_BY_ROUGHNESS = ((0.1, "half"), (0.15, "quarter"), (0.35, "sixteenth"))


def fade(rough) -> np.ndarray:
    """(n,) float32 the share of a pixel's reflection the environment fallback makes at
    roughness ``rough`` (n,): 0 below FADE_START, 1 from FADE_END, linear between."""
    t = (np.asarray(rough, np.float32) - FADE_START) / (FADE_END - FADE_START)
    return np.clip(t, 0.0, 1.0).astype(np.float32)


def tracing_gain(rough) -> np.ndarray:
    """(n,) float64 what tracing makes of a reflection at roughness ``rough``: 1 -
    ``fade`` (docs/heuristic.md: the relevance's gain)."""
    return 1.0 - fade(rough).astype(np.float64)


def rate_level(rough) -> np.ndarray:
    """(n,) int64 the index in TRACE_DENSITIES of the glossy ray rate at roughness
    ``rough`` (n,) (RATE_BY_ROUGHNESS; 0, full, below the first)."""
    rough = np.asarray(rough, np.float64).reshape(-1)
    level = np.zeros(len(rough), np.int64)
    for least, name in RATE_BY_ROUGHNESS:
        level = np.where(rough >= least, TRACE_DENSITIES.index(name), level)
    return level


_FRACTIONS = np.array([DENSITY_FRACTION[d] for d in TRACE_DENSITIES])


def ray_share(rough, level: int = 0) -> np.ndarray:
    """(n,) float64 the share of pixels of roughness ``rough`` (n,) of a glossy material
    that start rays at density TRACE_DENSITIES[level]: at or below MIRROR_ROUGHNESS the
    density's, above the coarser of it and the rate's pattern (``rate_level``), 0 from
    FADE_END."""
    rough = np.asarray(rough, np.float64).reshape(-1)
    fraction = np.minimum(_FRACTIONS[rate_level(rough)], _FRACTIONS[level])
    share = np.where(rough > MIRROR_ROUGHNESS, fraction, _FRACTIONS[level])
    return np.where(rough >= FADE_END, 0.0, share)


def started_share(shares: np.ndarray, pixels: float, level: int) -> float:
    """Share of a reflector's ``pixels`` that start rays at density TRACE_DENSITIES[level]
    relative to full density's, from its ``shares`` (L,) (``element_figures``' row):
    1 at full density and below the density's sparse floor (traced whole:
    ``traced_fraction``), else shares[level] / shares[0] (a mirror's: the density's
    fraction)."""
    base = traced_fraction(pixels, TRACE_DENSITIES[level])
    if base >= 1.0:
        return 1.0
    full = float(shares[0])
    return float(shares[level]) / full if full > 0.0 else base


def material_roughness(materials) -> np.ndarray:
    """(M,) float64 each material's reflection roughness: its constant ``roughness``
    where it reflects by it (``MaterialTable.glossy``), else 0 (a mirror)."""
    glossy = np.asarray(getattr(materials, "glossy", np.zeros(0, bool)), bool)
    rough = np.asarray(materials.roughness, np.float64).reshape(-1)
    out = np.zeros(len(rough))
    m = min(len(glossy), len(rough))
    out[:m] = np.where(glossy[:m], np.clip(rough[:m], 0.0, 1.0), 0.0)
    return out


_ELEMENT_CACHE: list = [None]


def element_figures(scene) -> tuple[np.ndarray, np.ndarray]:
    """((E,) tracing gain, (E, L) ray shares) of every element of ``scene``, the means
    over its triangles of ``tracing_gain`` and of ``ray_share`` at each of the L trace
    densities at its materials' roughness (an element without triangles: 1, and the
    densities' fractions). Cached for the latest scene object and
    material table. A scene may carry them already (``reflection_figures``: a replay's
    recording, ``tools/policy_replay.py``, whose scene has no materials); a scene without
    surfaces (a test's) has mirrors."""
    figures = getattr(scene, "reflection_figures", None)
    if figures is not None:
        return figures
    n = len(scene.elements)
    if not hasattr(scene, "materials") or not hasattr(scene, "geometry"):  # no surfaces
        return np.ones(n), np.broadcast_to(_FRACTIONS, (n, len(_FRACTIONS)))
    key = _ELEMENT_CACHE[0]
    if key is not None and key[0] is scene and key[1] is scene.materials:
        return key[2]
    rough = material_roughness(scene.materials)
    if not len(rough):
        rough = np.zeros(1)
    geo = scene.geometry
    tri_rough = np.take(rough, np.asarray(geo.tri_material, np.int64), mode="clip")
    element = np.asarray(geo.tri_element, np.int64)
    count = np.bincount(element, minlength=n)[:n].astype(np.float64)

    def mean(per_triangle: np.ndarray, empty: float) -> np.ndarray:
        total = np.bincount(element, weights=per_triangle, minlength=n)[:n]
        return np.where(count > 0, total / np.maximum(count, 1.0), empty)

    shares = np.stack([mean(ray_share(tri_rough, level), _FRACTIONS[level])
                       for level in range(len(TRACE_DENSITIES))], axis=1)  # fmt: skip
    result = (mean(tracing_gain(tri_rough), 1.0), shares)
    _ELEMENT_CACHE[0] = (scene, scene.materials, result)
    return result
