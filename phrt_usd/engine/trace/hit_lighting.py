"""Direct light at the tracer's hits (reflection and refraction bounces): the one rule of
``rt`` and ``hybrid`` alike (docs/hit-lighting.md states it with its measured error).

For each hit and light (``shading``'s light order, distant then local):

1. **Maps first.** Where the renderer has shadow maps (``hybrid`` and ``rt`` alike:
   ``Tracer.use_shadow_maps``, the raster light pass's own lookup,
   ``lighting.map_lookup``, the test and code of the primary surface) and they decide
   the pair (lit or shadowed over the whole texel neighbourhood), their answer is the
   visibility and no ray is cast; the lit pairs are shaded in the GPU lookup pass, as
   the primary surface's are.
2. **Rays where they do not.** The pairs the maps cannot decide (shadow edges, casters
   thinner than a texel), and every pair where the maps are not used (a tracer without
   a raster; a stage of at most HIT_LIGHT_PICKS lights, ``light_sampling.
   maps_light_hits``, and a batch of fewer than MAP_MIN_PAIRS possible pairs: there the
   lookup pass costs more than the rays), are *undecided*; each gets a shadow ray
   (``shadow_rays``). A Rect or Disk light is an area whoever decides its pair: its
   irradiance is the surface's (``area_light_kernels``' factor); a ray of such a pair
   goes to a point of its surface (``area_offsets``) and answers the share of it the
   hit sees, a map answers from the light's centre.
3. **Lights sampled where a hit has many.** A hit with more than
   ``model.light_sampling.HIT_LIGHT_PICKS`` undecided pairs of a positive unshadowed share
   (``shade_kernels.light_share``: the light's brightest channel x n·l, and for a
   LocalLight its window / d² and cone) casts HIT_LIGHT_PICKS rays
   (``shade_kernels.light_draws``): while two picks or more are left, a light of at
   least the mean share per pick left is traced exactly; the picks left are systematic
   draws over the other lights' shares, a light of share s drawn c times out of S in
   all over p picks weighing c S / (p s), 1 in expectation (unbiased). The draws'
   offset is the pixel's in a 2D low-discrepancy pattern (R2), shifted per frame by a
   hash of its time code (``frame_seed``): reproducible, different each frame, and
   neighbouring pixels' offsets spread over [0, 1), so their errors offset each other
   (a dither, which FLIP and the eye see less of than white noise); the noise left is
   the reconstruction's.

Everything else (ambient, emission, the shading model) is ``shading.shade_local``'s.
Spaces: positions rel (``bvh.Float32Boundary``); the map lookup takes world metres.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine import lighting
from phrt_usd.engine.terminator import Terminator
from phrt_usd.engine.trace.bvh import Bvh
from phrt_usd.engine.trace.hit_surfaces import HitSurfaces
from phrt_usd.engine.trace.shadow_rays import ShadowRays
from phrt_usd.model.light_sampling import has_area_lights, maps_light_hits
from phrt_usd.model.scene import Lights

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
_TRACE = kernels.load("phrt_usd.engine.trace.trace_kernels")
#: The origin of rel positions in rel space (``Terminator.of`` of hits given rel).
_ORIGIN = np.zeros(3)

#: The shadow maps' lookup of hits: (world positions (n, 3) float64, shading normals
#: (n, 3) facing the ray's origin, ray directions (n, 3), the hits' surface rows (n,
#: SURFACE_COLUMNS) the GPU pass shades with, or None: the fallback material, the hits on
#: smooth meshes (``engine/terminator.py``) or None) ->
#: ``map_lighting``'s ``MapVisibility`` or ``PendingLightTerms`` (``lighting.map_lookup``
#: bound to a rasterizer and the scene's lights).
MapLookup = Callable[
    [np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, Terminator | None], object
]

#: A batch of hits is looked up in the shadow maps only from this many (hit, light)
#: pairs on. The lookup pass costs ~0.6 ms however few points it has; past that, maps
#: and sampled rays cost about the same per hit, the maps casting a third of the rays
#: with no sampling noise. Measured (sewer frame 241, 13 lights, whole rule, median of
#: 15, shared 2-core machine): 800 hits 1.03 ms with the maps against 0.50 ms by rays,
#: 1,600 hits 1.36 against 0.93 ms, 6,400 hits 3.8 against 3.5 ms, 66,627 hits 69
#: against 65 ms; one light (farm), 400 hits: 0.81 against 0.07 ms. From 16,384 pairs
#: (1,260 hits with 13 lights) the maps cost at most ~1.5 times the rays.
MAP_MIN_PAIRS = 16384

#: The R2 sequence's steps (Roberts 2018, from the plastic number g = 1.3247...): the
#: offset of pixel (x, y) is fract(x / g + y / g² + the frame's shift).
_PLASTIC = 1.324717957244746
_R2_STEPS = (1.0 / _PLASTIC, 1.0 / _PLASTIC**2)


_U64 = (1 << 64) - 1  # splitmix64 works modulo 2**64


def frame_seed(time_code: float) -> float:
    """The light sampling's shift of a frame in [0, 1): a hash (splitmix64's finaliser,
    Steele, Lea & Flood 2014) of its time code's float64 bits."""
    x = struct.unpack("<Q", struct.pack("<d", float(time_code)))[0]
    x = (x + 0x9E3779B97F4A7C15) & _U64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _U64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _U64
    return ((x ^ (x >> 31)) >> 11) * 2.0**-53


def area_offsets(pixels: np.ndarray, width: int, seed: float) -> np.ndarray:
    """(m, 3) float64 in [0, 1)³: how the hits seen from ``pixels`` (m,) (flat indices of
    an image ``width`` pixels wide) sample a Rect or Disk light in the frame of shift
    ``seed`` (``frame_seed``; ``shadow_rays``' area rule): the shift of the light's
    lattice (two columns) and the draw among its points (the third). Pixel (x, y):
    (x / g + y / g², x / g² + y / g, x / g³ + y / g) + the frame's shifts, modulo 1 (g
    the plastic number): neighbouring pixels sample the light at points
    spread over it, others each frame, so a penumbra comes out as a dither."""
    x, y = np.divmod(np.asarray(pixels, np.int64), max(int(width), 1))[::-1]
    first = x * _R2_STEPS[0] + y * _R2_STEPS[1] + np.mod(seed * _PLASTIC, 1.0)
    second = x * _R2_STEPS[1] + y * _R2_STEPS[0] + np.mod(seed * _PLASTIC**2, 1.0)
    draw = x / _PLASTIC**3 + y * _R2_STEPS[0] + seed
    return np.mod(np.stack([first, second, draw], axis=1), 1.0)


def light_offsets(pixels: np.ndarray, width: int, seed: float) -> np.ndarray:
    """(m,) float64 in [0, 1): the draws' offset of hits seen from ``pixels`` (m,) flat
    indices of an image ``width`` pixels wide, in the frame of shift ``seed``
    (``frame_seed``)."""
    x, y = np.divmod(np.asarray(pixels, np.int64), max(int(width), 1))[::-1]
    return np.mod(x * _R2_STEPS[0] + y * _R2_STEPS[1] + seed, 1.0)


class HitLighting:
    """The rule of the module over one ``Bvh``'s ``HitSurfaces`` and ``ShadowRays``.

    maps : the shadow maps' lookup (``Tracer.use_shadow_maps``), None: no maps;
    frame_seed : this frame's sampling shift (``frame_seed``); width : the traced
    image's; exact : every pair traced, no maps and no sampling (the evaluation the
    rule's error is measured against, ``tools/hit_lighting_error.py``). The tracer
    sets all four before each trace (``prepare``)."""

    def __init__(self, bvh: Bvh, surfaces: HitSurfaces, shadows: ShadowRays) -> None:
        self._bvh = bvh
        self._surfaces = surfaces
        self._shadows = shadows
        self.maps: MapLookup | None = None
        self.frame_seed = 0.0
        self.width = 1
        self.exact = False

    def prepare(self, maps: MapLookup | None, seed: float, width: int, exact: bool) -> None:
        """The next traces' shadow maps, frame seed, image width and exactness."""
        self.maps, self.frame_seed, self.width, self.exact = maps, seed, width, exact

    def shade(self, tri, u, v, rel, ng, ns, d_in, lights: Lights, pixels, albedo=None,
              into=None, textured=None):  # fmt: skip
        """Local shading of hits (tri, u, v (m,); rel, ng, ns, d_in (m, 3), see
        ``HitSurfaces.at``; pixels (m,) the pixel each hit's path started from; albedo
        (m, 3) float32 corner albedo or None, ``HitSurfaces.colour``'s, as
        ``textured``) by the module's rule with render-relative ``lights``: (m, 3)
        float32 radiance, (m,) int64 shadow rays cast per hit and their sum; with
        ``into`` (total, slot, weight) the radiance times weight also added to
        total[slot] (``trace_kernels.accumulate``)."""
        n_lights = len(lights.distant) + len(lights.local)
        into = self._surfaces.weighted(into, tri)  # material-rule reflectors' local part
        u0 = None if self.exact else light_offsets(pixels, self.width, self.frame_seed)
        spots = None
        if has_area_lights(lights):  # the area pairs' rays (``_with_rays``, ``_with_maps``)
            spots = area_offsets(pixels, self.width, self.frame_seed)
        if (self.maps is not None and not self.exact and maps_light_hits(lights)
                and len(tri) * n_lights >= MAP_MIN_PAIRS):  # fmt: skip
            return self._with_maps(tri, u, v, rel, ng, ns, d_in, lights, u0, albedo, into,
                                   textured, spots)  # fmt: skip
        return self._with_rays(tri, u, v, rel, ng, ns, d_in, lights, u0, albedo, into, textured,
                               spots)  # fmt: skip

    def _with_maps(self, tri, u, v, rel, ng, ns, d_in, lights, u0, albedo, into, textured,
                   spots=None):  # fmt: skip
        """``shade`` with the shadow maps deciding what they can (steps 1-3); ``spots``
        as ``_points``'."""
        albedo, emissive = self._surfaces.colour(tri, u, v, albedo, textured)
        surf = self._surfaces.surface(tri, u, v, albedo)
        world = rel + self._bvh.boundary.origin
        terminator = Terminator.of(self._bvh.table, rel, _ORIGIN, tri, ns, lights)  # smooth
        pending = self.maps(world, ns, d_in, surf, terminator)  # shaded with their BRDF
        query = pending.uncertain_pairs()
        rays = np.zeros(len(tri), np.int64)
        if query is None:
            settled = pending.filtered()
        else:  # the undecided pairs: rays, lights sampled where a hit has many
            rows = query.rows
            take = (np.take(a, rows, axis=0) for a in (rel, ng, ns, u0, tri))
            r_rel, r_ng, r_ns, r_u0, r_tri = take
            r_spots = None if spots is None else np.take(spots, rows, axis=0)
            exact, rays[rows] = self._shadows.visibility(
                r_rel, r_ns, lights, query.pairs, offsets=r_ng, u0=r_u0, triangles=r_tri,
                area_offsets=r_spots,
            )
            settled = pending.resolved(exact)
        local = lighting.shade_settled(rel, ns, surf, d_in, emissive, lights, settled)
        if into is not None:
            _TRACE.accumulate(*into, local)
        return local, rays, int(rays.sum())

    def _points(self, tri, u, v, rel, ng, ns, d_in, albedo, u0, lights: Lights, threads=None,
                into=None, textured=None, spots=None):  # fmt: skip
        """``shade`` of hits without maps (steps 2-3) in one compiled call after Embree's
        (``ShadowRays.shade``; ``spots``: ``area_offsets`` of the hits, where the stage has
        area lights); safe to run on the pool with ``threads`` = 1 and no ``into``."""
        albedo, emissive = self._surfaces.colour(tri, u, v, albedo, textured)
        surf = self._surfaces.surface(tri, u, v, albedo)
        # The caller updates ``rays_cast`` (a dict ``+=`` from pool threads could race).
        return self._shadows.shade(
            rel, ng, ns, d_in, surf, emissive, lights, threads=threads, into=into, u0=u0,
            triangles=tri, area_offsets=spots,
        )

    def _with_rays(self, tri, u, v, rel, ng, ns, d_in, lights, u0, albedo, into, textured,
                   spots=None):  # fmt: skip
        """``_points`` of every hit; large batches (from ``shadow_rays.
        PARALLEL_MIN_SHADE_RAYS`` possible rays) run in chunks on the pool (the kernels
        and embreex release the GIL), each chunk's Embree batch on its own thread."""
        n_lights = len(lights.distant) + len(lights.local)
        bounds = self._shadows.split(len(tri) * max(n_lights, 1), len(tri))
        if bounds is None:
            return self._points(
                tri, u, v, rel, ng, ns, d_in, albedo, u0, lights, into=into, textured=textured,
                spots=spots,
            )  # fmt: skip
        chunk_textured = None if textured else textured  # a chunk looks its own textures up
        done = self._shadows.in_chunks(
            lambda *rows: self._points(*rows[:-1], lights, 1, None, chunk_textured, rows[-1]),
            bounds, tri, u, v, rel, ng, ns, d_in, albedo, u0, spots,
        )  # fmt: skip
        local, rays = (np.concatenate([d[i] for d in done]) for i in (0, 1))
        if into is not None:  # the chunks' sums could race: one pass over them all
            _TRACE.accumulate(*into, local)
        return local, rays, sum(d[2] for d in done)
