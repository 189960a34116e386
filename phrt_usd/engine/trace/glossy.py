"""Glossy reflections: a reflector's roughness decides its reflection.

A reflector whose material is a UsdPreviewSurface (``MaterialTable.glossy``) reflects by
the roughness r of its pixel (``roughness``, constant or textured; where the clear coat's
lobe reflects more than the base's at the pixel's view angle, Schlick's Fresnel of each
compared, ``clearcoatRoughness``: ``pixel_roughness``). A reflector without one (only a
``displayColor``) keeps a mirror: the Phrt reflector schema declares it one.

- **r ≤ MIRROR_ROUGHNESS**: the exact mirror ray, as before.
- **MIRROR_ROUGHNESS < r < FADE_END**: one ray a pixel drawn from the visible normals of
  the GGX lobe of alpha = r² about the pixel's shading normal (Heitz 2018;
  ``glossy_kernels.glossy_rays``), its two uniforms a hash of the pixel and the frame
  (``hit_lighting.frame_seed``): hybrid and ``rt`` trace the same rays at full density,
  a frame rendered again is bit-identical, and successive frames draw other samples. A
  draw leaving below the surface is drawn again (``DRAWS`` tries, then the mirror ray).
  The sample's radiance is weighted by BRDF·cos / pdf over the lobe's directional
  albedo, with the Fresnel left to the reflection's weight as the split sum leaves it
  (``compositing``: W, or an authored F): G2(v, l) / G1(v) over its mean over the lobe's
  draws that leave above the surface (``conditional_albedo_table``), so the weighted
  sample's mean is the lobe's normalised average of the reflected radiance, and the
  pixel stays ``local + W · reflected`` (``(1 - F) local + F reflected``).
- **FADE_START ≤ r < FADE_END**: the traced reflection is faded into the environment in
  the mirror direction (the raster's fallback, ``compositing.base_image``), linearly,
  as UE's and EEVEE's ray-traced reflections fade into their probes above a roughness.
- **r ≥ FADE_END**: no ray; the pixel keeps the raster's fallback. Its reflector's
  record still counts it, so the rays per pixel a policy learns fall with roughness.

One sample a pixel is noisy; three steps make it a clean image:

- **fireflies**: a sample brighter than FIREFLY_RATIO times the median luminance of the
  samples in the 3 x 3 around it is scaled down to that (``clamp_fireflies``): a rare
  direction (a small bright light, a highlight) that one sample cannot average would
  otherwise be a lone bright pixel for a frame; the energy lost is that of the rare
  directions only.
- **spatial**: the edge-aware Gaussian mean of the samples within ``filter_radius(r)``
  steps of the pattern's spacing (1 at full density), on the pixel's element, its
  tangent plane and agreeing normals (``denoise``): the radius grows with roughness
  (the lobe's blur), 0 below ~0.06 (no filter: the near-mirrors).
- **temporal** (hybrid and rt: ``engine/reflection_history.py``): a traced glossy pixel blends
  ``accumulation(r)`` of its previous value in, read at the *surface's* reprojection
  (the reflection's hit distance set to 0 for r ≥ SURFACE_REPROJECTION_ROUGHNESS: a
  wide lobe has no single virtual image), clamped to the range of this frame's samples
  around it; more history for rougher pixels.

Arrays: pixels flat ``row * W + col``; radiance (n, 3) float32 linear RGB, before the
reflector's weight.
"""

from __future__ import annotations

import functools

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine.lighting import gbuffer_surface
from phrt_usd.engine.prefiltered_environment import prefiltered_radiance
from phrt_usd.model import pixel_kinds, preview_surface
from phrt_usd.model.frame import GBuffer, flat_image
from phrt_usd.model.reflection_roughness import (
    FADE_END,
    FADE_START,
    MIRROR_ROUGHNESS,
    fade,
    rate_level,
)
from phrt_usd.model.trace_density import LEVEL_RANKS

#: From this roughness on, a glossy pixel's history is reprojected by its surface's
#: motion (its hit distance set to 0), below it by the mirror's virtual image.
SURFACE_REPROJECTION_ROUGHNESS = 0.1
#: The spatial filter's radius: BLUR_RADII times the lobe's blur on screen (``filter_
#: radius``: alpha = r² radians of reflected directions, times the reflection's reach
#: hit / (depth + hit), in pixels), 1 to MAX_RADIUS pixels: 0.15 reflecting something
#: far at 320 pixels across 90 degrees blurs ~4.6 pixels, 0.3 ~18 (capped).
BLUR_RADII = 1.0
MAX_RADIUS = 8
#: The pattern's part of the radius, in spacings of the glossy samples' pattern
#: (``RATE_BY_ROUGHNESS``), added to the lobe's in quadrature: 1.5 reaches samples on
#: both sides of every skipped pixel.
PATTERN_REACH = 1.5
#: The least radius, in pixels per unit of roughness (0.15: 3, 0.3: 5, 0.45: 8): the
#: variance of one sample a pixel grows with the lobe's width, and contact reflections
#: (reach near 0) would otherwise keep it all.
RADIUS_PER_ROUGHNESS = 16.0
#: A sample's luminance is capped at this times the median of the 3 x 3 around it.
FIREFLY_RATIO = 4.0
#: The filter's guides: the normals' agreement (n·n')^NORMAL_POWER, and the tangent plane
#: within PLANE_TOLERANCE of the view depth (a step in depth, another surface).
NORMAL_POWER = 32
PLANE_TOLERANCE = 0.01
#: Draws of a direction before the mirror ray is kept (a draw below the surface).
DRAWS = 4
#: The share of its previous value a traced glossy pixel keeps (hybrid's accumulation):
#: ACCUMULATION_MIN at SURFACE_REPROJECTION_ROUGHNESS, growing with roughness to
#: ACCUMULATION_MAX at FADE_START, in ACCUMULATION_STEPS groups (one compiled call each).
ACCUMULATION_MIN = 0.5
ACCUMULATION_MAX = 0.8
ACCUMULATION_STEPS = 4
#: The accumulation's clamp: the range of this frame's filtered values in the 3 x 3
#: around a pixel, widened by this share of itself on each side (the filtered values of
#: one frame vary less than its history does from them).
ACCUMULATION_MARGIN = 0.5
#: The glossy kernels split over the tracer's pool from this many rows on (their rows
#: cost 0.1-0.5 us each: the pool's hand-over, ~20 us, pays from a few thousand).
PARALLEL_ROWS = 4096
#: The conditional albedo table's size (roughness rows, cosine columns) and samples.
TABLE_ROUGHNESS = 32
TABLE_COSINES = 32
TABLE_SAMPLES = 256


def _kernels():
    """The compiled glossy kernels (``glossy_kernels``, through ``phrt_usd.kernels``)."""
    return kernels.load("phrt_usd.engine.trace.glossy_kernels")


def filter_radius(rough: np.ndarray, reach: np.ndarray, pixel_angle: float) -> np.ndarray:
    """(n,) int64 the spatial filter's radius in pixels at roughness ``rough`` (n,) and
    reach ``reach`` (n,) (hit / (depth + hit) of the samples around: 1 far, 0 at
    contact), ``pixel_angle`` radians a pixel: twice the lobe's blur on screen, alpha
    (the spread of the lobe's reflected directions, radians) times the reach over the
    pixel angle, at least ``rough`` times RADIUS_PER_ROUGHNESS (one sample a pixel needs
    neighbours, the more the wider its lobe's spread of values) and 1, at most
    MAX_RADIUS; 0 for mirrors."""
    rough = np.asarray(rough, np.float64)
    blur = rough * rough * np.asarray(reach, np.float64) / max(pixel_angle, 1e-9)
    least = np.maximum(np.ceil(rough * RADIUS_PER_ROUGHNESS), 1.0)
    radius = np.clip(np.maximum(np.ceil(BLUR_RADII * blur), least), 1, MAX_RADIUS)
    return np.where(rough > MIRROR_ROUGHNESS, radius, 0).astype(np.int64)


def accumulation(rough: np.ndarray) -> np.ndarray:
    """(n,) float64 the share of history a traced glossy pixel keeps at ``rough``
    (quantised to ACCUMULATION_STEPS values; 0 below SURFACE_REPROJECTION_ROUGHNESS)."""
    r = np.asarray(rough, np.float64)
    t = np.clip((r - SURFACE_REPROJECTION_ROUGHNESS)
                / (FADE_START - SURFACE_REPROJECTION_ROUGHNESS), 0.0, 1.0)  # fmt: skip
    t = np.round(t * (ACCUMULATION_STEPS - 1)) / (ACCUMULATION_STEPS - 1)
    share = ACCUMULATION_MIN + (ACCUMULATION_MAX - ACCUMULATION_MIN) * t
    return np.where(r >= SURFACE_REPROJECTION_ROUGHNESS, share, 0.0)


@functools.cache
def conditional_albedo_table() -> np.ndarray:
    """(TABLE_ROUGHNESS, TABLE_COSINES) float32: the mean of G2(v, l) / G1(v) over the
    visible-normal draws of the GGX lobe of roughness i / (rows - 1) (alpha its square)
    seen at n·v = j / (columns - 1) whose reflection leaves above the surface (the
    draws ``glossy_rays`` keeps), on a Hammersley set: a kept sample's weight is
    G2 / G1 over this mean, so the weights average 1. Computed once a process."""
    table = np.empty((TABLE_ROUGHNESS, TABLE_COSINES))
    mu = np.maximum(np.linspace(0.0, 1.0, TABLE_COSINES), 1e-4)[:, None]
    for i, rough in enumerate(np.linspace(0.0, 1.0, TABLE_ROUGHNESS)):
        alpha = max(rough, MIRROR_ROUGHNESS) ** 2
        a2 = alpha * alpha
        _, nl = preview_surface.visible_normal_draws(alpha, mu, TABLE_SAMPLES)
        kept = nl > 1e-4
        lam_v = preview_surface.smith_lambda(mu, a2)
        lam_l = preview_surface.smith_lambda(np.where(kept, nl, 1.0), a2)
        ratio = (1.0 + lam_v) / (1.0 + lam_v + lam_l)
        count = kept.sum(-1)
        table[i] = np.where(count > 0, (ratio * kept).sum(-1) / np.maximum(count, 1), 1.0)
    return np.ascontiguousarray(table, np.float32)


def has_glossy(scene) -> bool:
    """Whether some material of ``scene`` reflects by its roughness (``MaterialTable.
    glossy``) with a roughness that is not a mirror's, or a textured one."""
    materials = scene.materials
    glossy = np.asarray(materials.glossy, bool)
    if not glossy.any():
        return False
    m = np.flatnonzero(glossy)
    rough = np.asarray(materials.roughness, np.float32)[m]
    coat = np.zeros(len(m), np.float32)
    if len(materials.clearcoat):
        coat = np.asarray(materials.clearcoat, np.float32)[m]
    textured = any(
        materials.texture_input(int(i), name) is not None
        for i in m
        for name in ("roughness", "clearcoat", "clearcoatRoughness")
    )
    return bool(textured or (rough > MIRROR_ROUGHNESS).any() or (coat > 0).any())


def pixel_roughness(scene, gbuffer: GBuffer, pix: np.ndarray) -> np.ndarray:
    """(n,) float32 the roughness of the reflection lobe at G-buffer pixels ``pix`` (n,)
    int64 (module docstring; 0: a mirror). Textured inputs are sampled at the pixels'
    positions (``lighting.gbuffer_surface``)."""
    pix = np.asarray(pix, np.int64)
    out = np.zeros(len(pix), np.float32)
    glossy = np.asarray(scene.materials.glossy, bool)
    if not len(pix) or not glossy.any():
        return out
    tri = np.take(gbuffer.triangle_id.reshape(-1), pix).astype(np.int64)
    material = np.take(scene.geometry.tri_material, np.maximum(tri, 0))
    known = (tri >= 0) & (material < len(glossy))
    at = np.flatnonzero(known)
    at = at[glossy[material[at]]]
    if not len(at):
        return out
    constant = _constant_roughness(scene.materials)
    if constant is not None:  # no texture on the lobe's inputs, no clear coat: a lookup
        out[at] = constant[material[at]]
        return out
    p = pix[at]
    surface = gbuffer_surface(
        scene, tri[at], np.take(gbuffer.element_id.reshape(-1), p),
        gbuffer.albedo.reshape(-1, 3)[p], gbuffer.position.reshape(-1, 3)[p],
    )  # fmt: skip
    rough = surface[:, preview_surface.ROUGHNESS].copy()
    coat = surface[:, preview_surface.CLEARCOAT]
    if (coat > 0.0).any():
        normal = gbuffer.normal.reshape(-1, 3)[p]
        view = gbuffer.view_dir.reshape(-1, 3)[p]
        mu = np.clip(np.abs(np.einsum("ij,ij->i", normal, view)), 0.0, 1.0)
        s5 = ((1.0 - mu) ** 5)[:, None]
        f0 = surface[:, preview_surface.F0 : preview_surface.F0 + 3]
        f90 = surface[:, preview_surface.F90 : preview_surface.F90 + 3]
        base = (f0 + (f90 - f0) * s5).max(axis=1)
        fc0 = surface[:, preview_surface.CLEARCOAT_F0]
        top = coat * (fc0 + (1.0 - fc0) * s5[:, 0])
        rough = np.where(top > (1.0 - top) * base,
                         surface[:, preview_surface.CLEARCOAT_ROUGHNESS], rough)  # fmt: skip
    out[at] = np.clip(rough, 0.0, 1.0)
    return out


_CONSTANT: list = [None]


def _constant_roughness(materials) -> np.ndarray | None:
    """(M,) float32 each material's constant roughness (clipped to [0, 1]) when no
    material has a texture on ``roughness``, ``clearcoat`` or ``clearcoatRoughness`` nor
    a clear coat (a pixel's lobe is then its material's), else None. Cached for the
    latest table."""
    cached = _CONSTANT[0]
    if cached is not None and cached[0] is materials:
        return cached[1]
    inputs = ("roughness", "clearcoat", "clearcoatRoughness")
    textured = any(materials.texture_input(m, name) is not None
                   for m in range(len(materials.roughness)) for name in inputs)  # fmt: skip
    coat = np.asarray(materials.clearcoat, np.float32)
    value = None
    if not textured and not (coat > 0.0).any():
        value = np.clip(np.asarray(materials.roughness, np.float32), 0.0, 1.0)
    _CONSTANT[0] = (materials, value)
    return value


class GlossyRound:
    """One reflection round's glossy pixels (``Tracer.trace_reflections``): the rough
    image of its pixels, their rays, and their radiance made clean.

    rough_image : (H*W,) float32 the round's pixels' roughness (traced and skipped),
    0 elsewhere; past : (pixels, sources) the pixels at or past FADE_END (no rays)."""

    def __init__(self, gbuffer: GBuffer, rough_image: np.ndarray, past, split) -> None:
        self.gbuffer = gbuffer
        #: The glossy pixels their pattern skips (pixels, sources): ``split``.
        self.skipped = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        #: The glossy pattern's spacing at each pixel (``split``), 1 elsewhere.
        self.spacing_image: np.ndarray | None = None
        self._split = split
        self._table: np.ndarray | None = None
        self.reach_image: np.ndarray | None = None
        self.rough_image = rough_image
        self.past = past
        self.weight_image: np.ndarray | None = None
        self.mirror_image: np.ndarray | None = None

    @classmethod
    def of(cls, scene, gbuffer: GBuffer, pix, src, density, seed: float, split):
        """The glossy side of a round's candidate pixels ``pix`` (n,) int64 of sources
        ``src`` (n,) (``Tracer._source_pixels``'): (round, mirror pixels, their sources,
        (glossy pixels that start rays, their sources)), the round NO_ROUND and every
        pixel a mirror when none is glossy. The pixels at or past FADE_END cast nothing (kept
        in ``past``); density, seed: ``split``'s; split: the tracer's pool
        (``Tracer._split``, taking ``min_rows``)."""
        rough = pixel_roughness(scene, gbuffer, pix)
        if not (rough > MIRROR_ROUGHNESS).any():
            return NO_ROUND, pix, src, None
        past = rough >= FADE_END
        image = np.zeros(gbuffer.element_id.size, np.float32)
        image[pix] = rough
        split = functools.partial(split, min_rows=PARALLEL_ROWS)
        round_ = cls(gbuffer, image, (pix[past], src[past]), split)
        mirror, mirror_src, traced, traced_src = round_.split(
            pix[~past], src[~past], density, gbuffer.shape[1], seed
        )
        return round_, mirror, mirror_src, (traced, traced_src)

    def split(self, pix, src, density, width: int, seed: float):
        """The round's candidate pixels ``pix`` (n,) of sources ``src`` (n,) (past the
        fade left out) split into the mirrors (returned first: pixels, sources, for the
        density's pattern) and the glossy pixels that start rays (pixels, sources): those
        on the pattern of the coarser of their source's density (``density``, as
        ``Tracer.trace_reflections``') and their roughness's rate (``rate_level``), in a
        phase of the frame (``seed``: ``hit_lighting.frame_seed``, so hybrid and rt draw
        the same pattern). The glossy pixels it skips are kept (``skipped``): the filter
        reconstructs them (``finish``)."""
        from phrt_usd.engine.trace import sparse_pixels

        rough = np.take(self.rough_image, pix)
        g = rough > MIRROR_ROUGHNESS
        gp, gs = pix[g], src[g]
        level = np.maximum(sparse_pixels.pixel_levels(density, gs), rate_level(rough[g]))
        phase = sparse_pixels.rotation_phase(int(seed * 2.0**16))
        row, col = np.divmod(gp, width)
        rank = sparse_pixels.BAYER_RANKS[(row - phase[0]) % 4, (col - phase[1]) % 4]
        on = rank < np.asarray(LEVEL_RANKS, np.int64)[level]
        self.skipped = (gp[~on], gs[~on])
        self.spacing_image = np.ones(len(self.rough_image), np.int64)
        self.spacing_image[gp] = sparse_pixels.LEVEL_SPACING[level]
        return pix[~g], src[~g], gp[on], gs[on]

    def draw_rays(self, first: dict, seed: float, offset, bounce_limit: int = 1):
        """The glossy pixels' rays in place, of ``first`` (``Tracer._source_pixels``'
        arrays: pixels pix, surface rel, ng, ns, view): its mirror directions dir (n, 3)
        float32 become drawn ones and its origins org (n, 3) float32 their offset
        origins; the weights kept by pixel for the filter and the mirror directions for
        the fade. seed: the frame's (``hit_lighting.frame_seed``); offset: (floor,
        relative); nothing below a ``bounce_limit`` of 1 (no rays)."""
        if bounce_limit < 1:
            return
        pix, rel, ng, ns, view = (first[k] for k in ("pix", "rel", "ng", "ns", "view"))
        dirs, origins = first["dir"], first["org"]
        n = len(pix)
        rough = np.take(self.rough_image, pix)
        weight = np.ones(n, np.float32)
        if n == 0 or not (rough > MIRROR_ROUGHNESS).any():
            return
        size = len(self.rough_image)
        self.mirror_image = np.zeros((size, 3), np.float32)
        self.mirror_image[pix] = dirs
        self._split(
            _kernels().glossy_rays, n, np.ascontiguousarray(pix, np.int64),
            np.ascontiguousarray(rel, np.float64), np.ascontiguousarray(ng, np.float64),
            np.ascontiguousarray(ns, np.float32), np.ascontiguousarray(view, np.float32),
            np.ascontiguousarray(rough, np.float32), int(seed * 2.0**32),
            conditional_albedo_table(), MIRROR_ROUGHNESS, float(offset[0]),
            float(offset[1]), DRAWS, int(self.gbuffer.shape[1]), out=(dirs, origins, weight),
        )  # fmt: skip
        self.weight_image = np.ones(size, np.float32)
        self.weight_image[pix] = weight

    def weigh(self, result) -> None:
        """Before the fill reads the round's traced ``result``, in place: its glossy
        samples' fireflies clamped (among the samples of their pattern, ``split``),
        their reach kept (``reach_image``: hit / (depth + hit), 1 for a ray that left the
        scene: how far the lobe's blur spreads on screen, ``finish``), and their hit
        distances from SURFACE_REPROJECTION_ROUGHNESS on set to 0 (their history
        reprojects by the surface; the fill's hit guide has nothing to tell apart)."""
        idx = np.ascontiguousarray(result.pixel_index, np.int64)
        if self.weight_image is None or not len(idx):
            return
        rough = np.take(self.rough_image, idx)
        active = rough > MIRROR_ROUGHNESS
        gb = self.gbuffer
        hit = result.hit_distance
        depth = np.take(gb.depth.reshape(-1), idx).astype(np.float64)
        if hit is None:
            reach = np.ones(len(idx))
        else:
            h = hit.astype(np.float64)
            far = ~np.isfinite(h)
            h[far] = 0.0
            reach = np.where(far, 1.0, h / np.maximum(depth + h, 1e-9))
        self.reach_image = np.full(len(self.rough_image), np.nan, np.float32)
        self.reach_image[idx[active]] = reach[active]
        # Among the samples of the pixel's glossy pattern (the mirrors are copied as
        # they are).
        spacing = np.take(self.spacing_image, idx)
        rad = np.ascontiguousarray(result.radiance, np.float32)
        out = np.empty_like(rad)
        self._neighbourhood(idx, rad, active, spacing, self.reach_image, FIREFLY_RATIO,
                            out)  # fmt: skip
        result.radiance = out
        if hit is not None:
            wide = rough >= SURFACE_REPROJECTION_ROUGHNESS
            result.hit_distance = np.where(wide, np.float32(0.0), hit)

    def _neighbourhood(self, idx, rad, active, spacing, reach, ratio, out):
        """``glossy_kernels.clamp_fireflies`` over the rows of pixels ``idx``: out the
        clamped radiance; returns (low, high, reach_mean)."""
        gb = self.gbuffer
        height, width = gb.shape
        n = len(idx)
        table = np.full(width * height, -1, np.int32)
        table[idx] = np.arange(n, dtype=np.int32)
        low, high = np.empty_like(rad), np.empty_like(rad)
        reach_mean = np.empty(n, np.float32)
        self._split(
            _kernels().clamp_fireflies, n, idx, rad, np.ascontiguousarray(active, np.bool_),
            np.ascontiguousarray(spacing, np.int64), table,
            flat_image(gb.element_id, np.int32, 1), reach, width, height, float(ratio),
            out=(out, low, high, reach_mean),
        )  # fmt: skip
        self._table = table
        return low, high, reach_mean

    def pixel_angle(self) -> float:
        """The angle in radians between the view rays of two neighbouring pixels at the
        image's centre (the filter's unit)."""
        gb = self.gbuffer
        h, w = gb.shape
        r, c = h // 2, min(w // 2, w - 2)
        if w < 2:
            return 1.0
        a, b = gb.view_dir[r, c].astype(np.float64), gb.view_dir[r, c + 1].astype(np.float64)
        cos = float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30))
        return max(float(np.arccos(np.clip(cos, -1.0, 1.0))), 1e-6)

    def finish(self, result, lights, reuse, sources) -> None:
        """The round's complete ``result`` (every pixel traced, reused or filled) made
        clean, in place: the spatial filter of its glossy pixels (radius: the lobe's
        blur on screen, ``filter_radius``), the fade into the environment (``lights``'
        in the mirror direction), and with ``reuse`` (hybrid's ``FrameReuse``) the traced
        pixels' accumulation; its records count the pixels that cast no ray
        (``count_past``; ``sources`` the round's)."""
        result.records = self.count_past(result.records, sources)
        if self.weight_image is None or not len(result.pixel_index):
            return
        self._with_skipped(result)
        idx = np.ascontiguousarray(result.pixel_index, np.int64)
        rough = np.take(self.rough_image, idx)
        active = rough > MIRROR_ROUGHNESS
        gb = self.gbuffer
        height, width = gb.shape
        n = len(idx)
        rad = np.ascontiguousarray(result.radiance, np.float32)
        kinds = result.kinds
        traced = (kinds == pixel_kinds.TRACED) | (kinds == pixel_kinds.SCREEN_SPACE)
        # Reused and filled pixels: no sample of their own (weight 1: a mean of samples);
        # the glossy pattern's skipped pixels: none at all (weight 0: the filter's).
        weight = np.where(traced, np.take(self.weight_image, idx), np.float32(1.0))
        weight[len(idx) - len(self.skipped[0]):] = 0.0
        weight = weight.astype(np.float32)
        same = np.empty_like(rad)
        _, _, reach = self._neighbourhood(idx, rad, active, np.ones(n, np.int64),
                                          self.reach_image, np.inf, same)  # fmt: skip
        known = np.isfinite(reach)
        typical = float(np.median(reach[known & active])) if (known & active).any() else 1.0
        reach = np.where(known, reach, typical)
        radius = np.where(active, filter_radius(rough, reach, self.pixel_angle()), 0)
        # The pattern's reach added (the two blurs' variances add): PATTERN_REACH times
        # the spacing of the samples' pattern, so that a skipped pixel has samples on
        # more than one side.
        spacing = np.take(self.spacing_image, idx)
        reach_px = np.where(spacing > 1, PATTERN_REACH * spacing, 0.0)
        radius = np.where(active, np.ceil(np.sqrt(radius**2.0 + reach_px**2)), 0)
        radius = np.minimum(radius, MAX_RADIUS).astype(np.int64)
        radius = np.ascontiguousarray(radius, np.int64)
        sums = np.empty((n, 4))
        sums[:, :3] = rad * weight[:, None]
        sums[:, 3] = weight
        guides = (flat_image(gb.normal, np.float32, 3), flat_image(gb.position, np.float64, 3),
                  flat_image(gb.depth, np.float32, 1))  # fmt: skip
        element = flat_image(gb.element_id, np.int32, 1)
        ones = np.ones(n, np.int64)
        for axis in (0, 1):
            passed = np.empty_like(sums)
            self._split(_kernels().denoise_pass, n, idx, sums, radius, ones, self._table,
                        element, *guides, width, height, NORMAL_POWER, PLANE_TOLERANCE, axis,
                        out=(passed,))  # fmt: skip
            sums = passed
        # A pixel without a filter has its one sample, times its weight (whose mean is 1).
        out = np.where(radius[:, None] > 0, sums[:, :3] / np.maximum(sums[:, 3:], 1e-30),
                       rad * weight[:, None]).astype(np.float32)  # fmt: skip
        # The accumulation's clamp: the range of the filtered values in the 3 x 3 around
        # (the samples' own range is that of one or two draws of a wide lobe, which cut
        # the history towards whichever side they fell on).
        low, high, _ = self._neighbourhood(idx, out, active, np.ones(n, np.int64),
                                           self.reach_image, np.inf, np.empty_like(out))
        spread = ACCUMULATION_MARGIN * (high - low)
        low, high = low - spread, high + spread
        if len(self.skipped[0]):  # skipped ones without a sample in reach: left out
            lone = sums[:, 3] <= 0.0
            lone[: n - len(self.skipped[0])] = False
            if lone.any():
                keep = ~lone
                self._drop(result, keep)
                idx, rough, active, traced = idx[keep], rough[keep], active[keep], traced[keep]
                out, low, high = out[keep], low[keep], high[keep]
        faded = fade(rough)
        if self.mirror_image is not None and (faded > 0.0).any():
            at = np.flatnonzero(faded > 0.0)
            env = prefiltered_radiance(lights, self.mirror_image[idx[at]], rough[at])
            t = faded[at][:, None]
            for a in (out, low, high):
                a[at] = (1.0 - t) * a[at] + t * env
        if reuse is not None:
            share = accumulation(rough)
            take = active & (share > 0.0)
            for value in np.unique(share[take]):
                at = np.flatnonzero(take & (share == value))
                part = np.ascontiguousarray(out[at])
                reuse.accumulate(idx[at], np.zeros(len(at), np.float32), part,
                                 np.ascontiguousarray(low[at]), np.ascontiguousarray(high[at]),
                                 self._split, share=float(value))  # fmt: skip
                out[at] = part
        result.radiance = out

    def _with_skipped(self, result) -> None:
        """``result`` with the glossy pattern's skipped pixels appended, in place (kind
        FILLED, no radiance yet, hit distance 0: the surface's reprojection)."""
        pix = self.skipped[0]
        n = len(result.pixel_index)
        kinds = result.kinds
        if kinds is None:
            kinds = np.full(n, pixel_kinds.TRACED, np.uint8)
        result.kinds = np.concatenate([kinds, np.full(len(pix), pixel_kinds.FILLED, np.uint8)])
        result.pixel_index = np.concatenate([result.pixel_index, pix])
        result.radiance = np.concatenate(
            [result.radiance, np.zeros((len(pix), 3), np.float32)])
        if result.hit_distance is not None:
            result.hit_distance = np.concatenate(
                [result.hit_distance, np.zeros(len(pix), np.float32)])

    @staticmethod
    def _drop(result, keep) -> None:
        """``result``'s rows of ``keep`` (n,) bool only, in place."""
        result.pixel_index = result.pixel_index[keep]
        result.radiance = result.radiance[keep]
        result.kinds = result.kinds[keep]
        if result.hit_distance is not None:
            result.hit_distance = result.hit_distance[keep]

    def count_past(self, records, sources) -> list:
        """``records`` with each source's pixels that cast no ray of their own counted in
        its pixels: past FADE_END, and skipped by the glossy pattern (only the pixels its
        density skips are counted already): what a policy divides its rays by."""
        import dataclasses

        pix = np.concatenate([self.past[0], self.skipped[0]])
        src = np.concatenate([self.past[1], self.skipped[1]])
        if not len(pix):
            return records
        counts = np.bincount(src, minlength=len(sources))
        return [dataclasses.replace(r, pixels=r.pixels + int(c))
                for r, c in zip(records, counts.tolist(), strict=True)]  # fmt: skip


class _NoRound:
    """A round without glossy pixels: every step leaves it as it is."""

    def draw_rays(self, first, seed, offset, bounce_limit=1) -> None:
        pass

    def weigh(self, result) -> None:
        pass

    def finish(self, result, lights, reuse, sources) -> None:
        pass


#: The glossy side of a round without glossy pixels (``Tracer._source_pixels``).
NO_ROUND = _NoRound()


def warm_up() -> None:
    """The glossy kernels compiled (or loaded) and the table made."""
    conditional_albedo_table()
    _kernels().warm_up()
