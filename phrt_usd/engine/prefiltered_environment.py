"""The environment as a rough reflector sees it: a textured dome's lat-long map
prefiltered by roughness, what the raster's fallback reflection of a glossy pixel reads
(``compositing.base_image``) and what a glossy reflection fades into
(``engine/trace/glossy.py``), as UE's and EEVEE's prefiltered probes.

The map's mip chain (each level the 2 x 2 box mean of the one before, down to a few
texels across; cached per dome texture) is read at the level whose texel spans the
lobe's spread of reflected directions, 2 alpha radians (alpha = roughness², the GGX
lobe's width), blending the two levels around it. Texels are measured along the
equator (2 pi / width): towards the poles a lat-long texel spans less, so the filter is
wider there than the lobe (as a box-filtered lat-long mip chain is). A constant dome
(the paper stages') is its own prefiltered image: nothing changes there.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from phrt_usd.engine.shading import environment_radiance
from phrt_usd.model.scene import Lights

#: Levels stop when the map is this many texels wide (its coarsest: the dome's colours
#: around the horizon, a few texels).
SMALLEST_WIDTH = 4

#: The latest dome texture's chain: (texture, [DomeLight per level]).
_CHAIN: list = [None]


def _halved(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 → its 2 x 2 box means ((h + 1) // 2, (w + 1) // 2, 3): an odd
    row or column is repeated (the edge's own texels)."""
    h, w = image.shape[:2]
    padded = np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return (0.25 * (padded[0::2, 0::2] + padded[1::2, 0::2] + padded[0::2, 1::2]
                    + padded[1::2, 1::2])).astype(np.float32)  # fmt: skip


def _chain(dome) -> list:
    """The dome at each level of its texture's mip chain (level 0 the dome itself)."""
    cached = _CHAIN[0]
    if cached is not None and cached[0] is dome:
        return cached[1]
    levels = [dome]
    texture = np.asarray(dome.texture, np.float32)
    while texture.shape[1] > SMALLEST_WIDTH and texture.shape[0] > 1:
        texture = _halved(texture)
        levels.append(dataclasses.replace(dome, texture=texture))
    _CHAIN[0] = (dome, levels)
    return levels


def mip_level(rough: np.ndarray, width: int) -> np.ndarray:
    """(n,) float64 the mip level a lobe of roughness ``rough`` (n,) reads of a map
    ``width`` texels around: log2 of its spread, 2 r², over a level-0 texel's angle."""
    spread = 2.0 * np.square(np.asarray(rough, np.float64))
    texel = 2.0 * math.pi / max(int(width), 1)
    return np.log2(np.maximum(spread / texel, 1.0))


def prefiltered_radiance(lights: Lights, directions: np.ndarray, rough: np.ndarray) -> np.ndarray:
    """(n, 3) float32 the environment along ``directions`` (n, 3) as seen by lobes of
    roughness ``rough`` (n,): ``shading.environment_radiance`` where the dome is constant
    or the lobe spans less than a texel, else the blend of the two mip levels around
    the lobe's (module docstring)."""
    directions = np.asarray(directions).reshape(-1, 3)
    rough = np.asarray(rough, np.float64).reshape(-1)
    dome = lights.dome
    if dome is None or dome.texture is None or not len(rough):
        return environment_radiance(lights, directions)
    levels = _chain(dome)
    level = np.minimum(mip_level(rough, np.shape(dome.texture)[1]), len(levels) - 1)
    out = environment_radiance(lights, directions)
    lower = np.floor(level).astype(np.int64)
    for k in np.unique(lower[level > 0.0]).tolist():
        at = np.flatnonzero((lower == k) & (level > 0.0))
        t = (level[at] - k)[:, None].astype(np.float32)
        here = _at_level(lights, levels, k, directions[at])
        above = _at_level(lights, levels, min(k + 1, len(levels) - 1), directions[at])
        out[at] = (1.0 - t) * here + t * above
    return out


def _at_level(lights: Lights, levels: list, k: int, directions: np.ndarray) -> np.ndarray:
    """The environment along ``directions`` from level ``k`` of the dome's chain."""
    if k == 0:
        return environment_radiance(lights, directions)
    return environment_radiance(dataclasses.replace(lights, dome=levels[k]), directions)
