"""Shadow rays: which lights each point sees, by Embree occlusion queries.

``ShadowRays.cast`` takes rel points (see ``bvh.Float32Boundary``) with their offset
(geometric) and shading normals and answers (n, L) visibility, light order distant then
local. Rays go only where they can matter: to lights in front of the shading normal and,
for LocalLights, within their range (``shading.light_ranges``); all (point, light) pairs
of a batch are chosen and built into one float32 Embree batch in one compiled pass
(``trace_kernels.shadow_rays``: numba, ``nogil``, so the pool's chunks run side by side). Origins
are offset by the boundary's epsilon along the offset normal, on the side the ray
leaves to. Transmissive surfaces are opaque; cut-out holes let light through
(``HitSurfaces.occluded``, given ``surfaces``).

Rect and Disk lights as areas (``LocalLight.area_shape``; the rule is
``area_light_kernels``'): a pair of such a light is answered by AREA_LIGHT_RAYS rays to
points of the rect or disk drawn by their share of its irradiance, instead of its one
ray to the centre, and comes out as the share of the light the point sees: soft
shadows. ``shade`` (the traced hits lit by rays) weighs the pair by its area factor too
(the exact irradiance of the whole surface over the point light's; nothing behind the
light); ``cast`` (rt's primary surface, the pairs hybrid's shadow maps leave
undecided, the hits' exact evaluation) answers the share alone, and the shading
multiplies the factor in, as it does for the pairs the maps decide
(``shading.shade_local``), so hybrid with every reflector traced stays rt's image.
Sphere and Cylinder lights stay points (their radius offsets the rays).

``ShadowRays.shade`` is the bounce loop's use: the same rays, then Embree's answer shaded
at once (``trace_kernels.shadow_shade``: visibility, lit LocalLight pairs and
``shading``'s model in one compiled call, the radiance optionally summed into the
paths' pixels), so a trace round pays one compiled call for its local shading.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine import shading
from phrt_usd.engine.trace.bvh import FAR, Bvh
from phrt_usd.engine.trace.hit_surfaces import HitSurfaces
from phrt_usd.model import preview_surface
from phrt_usd.model.light_sampling import (
    AREA_LIGHT_POINTS,
    AREA_LIGHT_RAYS,
    AREA_LIGHT_STEP,
    HIT_LIGHT_PICKS,
)
from phrt_usd.model.scene import Lights

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
_TRACE = kernels.load("phrt_usd.engine.trace.trace_kernels")
_AREA = kernels.load("phrt_usd.engine.trace.area_light_kernels")

#: Shading work (shadow-ray kernel, Embree, shading kernel) on many points is split over
#: the pool, each chunk on its own thread, only from this many possible shadow rays
#: (points x lights) on. Measured on the sewer (13 lights, 2 cores, compiled kernels,
#: ``tools/bench_trace_batches.py``): a 6,312-ray round takes 0.46 ms split against
#: 0.57 ms on one thread, a 12,690-ray round 0.85 against 0.91 ms; but a 486-ray round
#: 0.19 against 0.075 ms (the pool's hand-over costs more than the chunks save).
PARALLEL_MIN_SHADE_RAYS = 4096


class ShadowRays:
    """Shadow rays against one ``Bvh`` (its current geometry and boundary), split over
    ``pool`` (None: one thread) in ``threads`` chunks for large batches; occlusion through
    ``surfaces`` (cut-out holes let light through) when given."""

    def __init__(
        self,
        bvh: Bvh,
        pool: ThreadPoolExecutor | None,
        threads: int,
        surfaces: HitSurfaces | None = None,
    ) -> None:
        self._bvh = bvh
        self._surfaces = surfaces
        self.pool = pool
        self.threads = threads
        self._light_cache: tuple | None = None
        self._table_cache: tuple | None = None
        self._area_cache: tuple | None = None

    def split(self, work: int, n: int) -> list[tuple[int, int]] | None:
        """(start, stop) chunks of ``n`` points to shade over the pool, or None when
        ``work`` (shadow rays they may cast) is below PARALLEL_MIN_SHADE_RAYS or there
        is no pool."""
        if self.pool is None or work < PARALLEL_MIN_SHADE_RAYS or n < self.threads:
            return None
        edges = np.linspace(0, n, self.threads + 1).astype(int).tolist()
        return list(zip(edges[:-1], edges[1:], strict=True))

    def visibility(self, rel, normals, lights: Lights, pairs=None, offsets=None, u0=None,
                   triangles=None, area_offsets=None):  # fmt: skip
        """``cast`` for rel points (n, 3) of shading ``normals`` (n, 3) and offset normals
        ``offsets`` (n, 3; None: ``normals``), in chunks on the pool when the batch is
        large (numpy and Embree work of each chunk on its own thread); ``u0``,
        ``triangles`` and ``area_offsets`` as ``cast``'s (None: ``index_offsets`` of the
        whole batch). Returns (n, L) float32 visibility and (n,) int64 shadow rays cast
        per point."""
        n, n_lights = len(rel), len(lights.distant) + len(lights.local)
        wanted = n * max(n_lights, 1) if pairs is None else int(np.count_nonzero(pairs))
        offsets = normals if offsets is None else offsets
        if area_offsets is None and self.area_table(lights) is not None:
            area_offsets = index_offsets(n)
        bounds = self.split(wanted, n)
        if bounds is None:
            vis, rays, _ = self.cast(rel, offsets, normals, lights, pairs, u0=u0,
                                     triangles=triangles, area_offsets=area_offsets)  # fmt: skip
            return vis, rays
        done = self.in_chunks(
            lambda r, ng, ns, p, u, t, a: self.cast(r, ng, ns, lights, p, 1, u, t, a),
            bounds, rel, offsets, normals, pairs, u0, triangles, area_offsets,
        )  # fmt: skip
        return np.concatenate([d[0] for d in done]), np.concatenate([d[1] for d in done])

    def in_chunks(self, call, bounds, *arrays) -> list:
        """``call(*(a[lo:hi] for a in arrays))`` for each (lo, hi) of ``bounds`` (``split``)
        on the pool, results in chunk order; a None array stays None. The chunks' Embree
        batches were cast side by side, so the ray log keeps them as one batch per query
        (``Bvh.merge_recorded``: raw embreex replays them under its own splitting rule)."""
        since = len(self._bvh.last_rays)
        parts = [
            self.pool.submit(call, *(None if a is None else a[lo:hi] for a in arrays))
            for lo, hi in bounds
        ]
        done = [f.result() for f in parts]
        self._bvh.merge_recorded(since)
        return done

    def light_arrays(self, lights: Lights) -> tuple[np.ndarray, ...]:
        """(D, 3) unit DistantLight directions, (P, 3) LocalLight positions (both
        float64, as given), (P,) LocalLight ranges in metres (``shading.light_ranges``),
        and what light sampling weighs them by: (D + P,) power (the brightest radiance
        channel, >= 0) and (P, 7) cones (``shading.LightTable.cone``) of ``lights``;
        cached for the latest ``Lights`` object (the tracer's render-relative lights
        are one object per scene)."""
        cached = self._light_cache
        if cached is not None and cached[0] is lights:
            return cached[1]
        dirs = np.array([li.direction for li in lights.distant], np.float64).reshape(-1, 3)
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
        pos = np.array([li.position for li in lights.local], np.float64).reshape(-1, 3)
        ranges = shading.light_ranges(lights)[len(lights.distant) :]
        radiance = [li.radiance for li in (*lights.distant, *lights.local)]
        power = np.array(radiance, np.float64).reshape(-1, 3).max(axis=1, initial=0.0)
        power = np.nan_to_num(power, nan=0.0, posinf=1e300)
        arrays = (dirs, pos, ranges, power, self.light_table(lights).cone)
        self._light_cache = (lights, arrays)
        return arrays

    def area_table(self, lights: Lights) -> np.ndarray | None:
        """(P, ``area_light_kernels.AREA_COLUMNS``) float64: each LocalLight's emitting
        surface (``LocalLight.area_shape``; rel centres, as the lights given), or None
        when no light is a Rect or Disk; cached for the latest ``Lights`` object."""
        cached = self._area_cache
        if cached is not None and cached[0] is lights:
            return cached[1]
        table = shading.area_table(lights)
        self._area_cache = (lights, table)
        return table

    def light_table(self, lights: Lights) -> shading.LightTable:
        """``shading.light_table`` of ``lights``, cached for the latest ``Lights`` object
        as ``light_arrays`` (its own identity check of every light: ~0.7 us a round)."""
        cached = self._table_cache
        if cached is not None and cached[0] is lights:
            return cached[1]
        table = shading.light_table(lights)
        self._table_cache = (lights, table)
        return table

    def cast(self, rel, offset_normals, shading_normals, lights: Lights, pairs=None,
             threads=None, u0=None, triangles=None, area_offsets=None):  # fmt: skip
        """(n, L) float32 visibility, (n,) int64 shadow rays cast per point and the lit
        LocalLight pairs (``shading.shade_local``'s ``local_pairs``, or None), for
        render-relative positions ``rel`` (n, 3) and render-relative ``lights``.

        Rays are cast only where they can matter: the light in front of the shading
        normal (elsewhere the Lambert term is 0) and, for LocalLights, the point within
        the light's range (``shading.light_ranges``; beyond it the light contributes 0).
        Such pairs, and pairs outside ``pairs`` ((n, L) bool, None = all), report 0.
        ``u0`` (n,) float64 in [0, 1): the hit-lighting rule's light sampling (see the
        module), each point's draws offset by u0; the visibility (and the lit pairs'
        weight) is then the ray's weight where it is free. None: every pair, exact.
        ``triangles`` (n,) int64: each point's triangle (-1: none), so that a point of a
        smooth (interpolated-normal) mesh is shadowed as its smooth surface is, not as
        its flat triangle (the shadow terminator: ``trace_kernels.shadow_rays``); None:
        every point offset along its offset normal only. A Rect or Disk light's pair is
        answered by the area rule's rays (the module's; its samples drawn by the points'
        ``area_offsets`` (n, 3) in [0, 1)³, None: ``index_offsets``): its visibility (and
        lit pair's weight) is then the share of the light the point sees, which the
        shading multiplies by the area factor (``shading.shade_local``).

        The (point, light) pairs are chosen and their rays built in one compiled pass
        (``trace_kernels.shadow_rays``: float32 Embree batch, point-major, so the lit LocalLight
        pairs come out sorted by point), then cast as one batch."""
        n = rel.shape[0]
        n_distant = len(lights.distant)
        n_lights = n_distant + len(lights.local)
        if not lights.has_direct or n == 0:
            return np.ones((n, n_lights), np.float32), np.zeros(n, np.int64), None
        want = _ALL_PAIRS if pairs is None else np.asarray(pairs, dtype=bool).reshape(n, n_lights)
        areas = True if area_offsets is None else area_offsets
        ray_i, ray_v, ray_f, occluded, extra = self._trace(
            rel, offset_normals, shading_normals, lights, want, threads, u0, triangles, areas,
            share_only=True,
        )  # fmt: skip
        k = len(occluded)
        vis, rays = np.empty((n, n_lights), np.float32), np.empty(n, np.int64)
        lit_i, lit_dir = np.empty((2, k), np.int64), np.empty((k, 3), np.float32)
        lit_dist, lit_w = np.empty(k), np.empty(k, np.float32)
        m = _TRACE.shadow_results(
            ray_i, ray_v, ray_f, occluded, n_distant, vis, rays, lit_i, lit_dir, lit_dist, lit_w
        )
        if extra is not None:
            rays += extra
        # The lit LocalLight pairs, for shade_local (weights only where sampled, lights or
        # areas).
        weight = None if u0 is None and extra is None else lit_w[:m]
        lit = shading.LightPairs(lit_i[0, :m], lit_i[1, :m], lit_dir[:m], lit_dist[:m], weight)
        return vis, rays, lit if len(lights.local) else None

    def shade(self, rel, offset_normals, shading_normals, view_dirs, surface, emissive,
              lights: Lights, threads=None, into=None, u0=None, triangles=None,
              area_offsets=None):  # fmt: skip
        """``shading.shade_local`` of rel points ``rel`` (n, 3) float64 with the
        visibility and lit LocalLight pairs of ``cast`` (every pair wanted), in one
        compiled call after Embree's (``trace_kernels.shadow_shade``: the same kernel
        code without the Python between them; the compiler may round differently, the
        farm and sewer rounds agree within 1e-6): offset_normals (n, 3) float64,
        shading_normals and view_dirs (n, 3) float32 C-contiguous (the bounce loop's
        gathered rows), surface (n, 16) float32 rows (``model.preview_surface``; an
        (n, 3) albedo: the fallback material of that colour),
        emissive (n, 3) or (3,) float32. ``into``: (total (P, 3)
        float64, slot (n,) int64, weight (n,) float64) to add weight times the radiance
        to total[slot] in the same call (``trace_kernels.accumulate``), or None. Returns
        (n, 3) float32 radiance, (n,) int64 shadow rays cast per point and their sum.
        ``u0``, ``triangles``: as ``cast``'s (the hit-lighting rule's light sampling,
        the points' triangles); Rect and Disk lights are areas (the module's rule), each
        point's samples drawn by its ``area_offsets`` (n, 3) in [0, 1)³ (the hits'
        pixels', ``hit_lighting.area_offsets``; None: ``index_offsets``)."""
        n = rel.shape[0]
        table = self.light_table(lights)
        extra = None
        if lights.has_direct and n:
            ray_i, ray_v, ray_f, occluded, extra = self._trace(
                rel, offset_normals, shading_normals, lights, _ALL_PAIRS, threads, u0, triangles,
                True if area_offsets is None else area_offsets,
            )  # fmt: skip
        else:  # no lights (or no points): no rays, ambient and emission only
            ray_i, ray_v, ray_f, occluded = _NO_SHADOW_RAYS
        out, rays = np.empty((n, 3), np.float32), np.empty(n, np.int64)
        f32 = np.float32
        _TRACE.shadow_shade(
            ray_i, ray_v, ray_f, occluded, np.ascontiguousarray(rel, np.float64),
            np.ascontiguousarray(shading_normals, f32), shading.surface_rows(surface, n),
            np.ascontiguousarray(view_dirs, f32),
            np.ascontiguousarray(emissive, f32).reshape(-1, 3), *table, shading.MODEL,
            preview_surface.specular_albedo_table(), out, rays,
            *(_NO_TOTAL if into is None else into),
        )  # fmt: skip
        if extra is None:
            return out, rays, len(occluded)
        rays += extra
        return out, rays, len(occluded) + int(extra.sum())

    def _trace(self, rel, offset_normals, shading_normals, lights: Lights, want, threads,
               u0=None, triangles=None, areas=False, share_only=False):  # fmt: skip
        """The shadow rays of (point, light) pairs (``trace_kernels.shadow_rays``; ``want``
        (n, L) bool or ``_ALL_PAIRS``; ``u0``, ``triangles`` as ``cast``'s) and Embree's
        answer: rays' point and light (2, k) int64, origin and direction (2, k, 3)
        float32, tfar, distance and weight (3, k) float32 (columns beyond k unused),
        occluded (k,) bool; and, with ``areas`` (True, or the points' sample offsets (n,
        3)) where some lights are Rect or Disk lights, the rays each point cast beyond one
        a pair (n,) int64 (``_area_answer``; ``share_only`` as its), else None."""
        n, n_lights = rel.shape[0], len(lights.distant) + len(lights.local)
        dirs, pos, ranges, power, cone = self.light_arrays(lights)
        floor, relative = self._bvh.boundary.offset_factors()
        most = n * n_lights  # one ray per (point, light) pair at most
        ray_i = np.empty((2, most), np.int64)  # point, light
        ray_v = np.empty((2, most, 3), np.float32)  # origin, direction
        ray_f = np.empty((3, most), np.float32)  # tfar, distance, weight
        picks, u0 = (0, _NO_OFFSETS) if u0 is None else (HIT_LIGHT_PICKS, u0)
        table = self._bvh.table
        tri = _NO_TRIANGLES if triangles is None else np.ascontiguousarray(triangles, np.int64)
        k = _TRACE.shadow_rays(
            np.ascontiguousarray(rel, np.float64),
            np.ascontiguousarray(offset_normals, np.float32),
            np.ascontiguousarray(shading_normals, np.float32),
            dirs,
            pos,
            ranges,
            np.ascontiguousarray(want),
            floor,
            relative,
            shading.MIN_LIGHT_DISTANCE,
            FAR,
            power,
            cone,
            picks,
            np.ascontiguousarray(u0, np.float64),
            tri,
            table.plane,
            table.frame,
            table.corners,
            ray_i,
            ray_v,
            ray_f,
        )
        area = self.area_table(lights) if areas is not False else None
        if area is not None:
            offsets = index_offsets(n) if areas is True else areas
            occluded, extra = self._area_answer(
                ray_i, ray_v, ray_f, k, len(lights.distant), shading_normals, area, offsets,
                threads, share_only,
            )  # fmt: skip
            return ray_i, ray_v, ray_f, occluded, extra
        return ray_i, ray_v, ray_f, self._occluded(ray_v[0, :k], ray_v[1, :k], ray_f[0, :k],
                                                   threads), None  # fmt: skip

    def _occluded(self, origins, dirs, tfar, threads) -> np.ndarray:
        """Embree's answer (k,) bool to k shadow rays (cut-out holes let light through
        when the surfaces are given)."""
        if self._surfaces is None:
            return self._bvh.run("OCCLUDED", origins, dirs, tfar, threads)
        return self._surfaces.occluded(origins, dirs, tfar, threads)

    def _area_answer(self, ray_i, ray_v, ray_f, k, n_distant, shading_normals, area, offsets,
                     threads, share_only=False):  # fmt: skip
        """The answer to the k rays of ``_trace`` where some lights are areas: their pairs'
        own rays are not cast, their samples are (``area_light_kernels.area_rays``, one
        Embree batch with the other pairs' rays), and the samples' answer becomes the
        pairs' weights (``area_weights``): the area factor times the visible share, or
        with ``share_only`` the share alone (the shading multiplies the factor in, as
        for every pair it shades). Returns occluded (k,) bool and the rays each point
        cast beyond one a pair (n,) int64."""
        n = len(shading_normals)
        most = k * AREA_LIGHT_RAYS
        parent, sample_v = np.empty(most, np.int64), np.empty((2, most, 3), np.float32)
        sample_f, unshadowed = np.empty((2, most), np.float32), np.empty(k)
        floor, relative = self._bvh.boundary.offset_factors()
        m = _AREA.area_rays(
            ray_i, ray_v, ray_f, k, n_distant, np.ascontiguousarray(shading_normals, np.float32),
            area, np.ascontiguousarray(offsets, np.float64), AREA_LIGHT_POINTS, AREA_LIGHT_STEP,
            AREA_LIGHT_RAYS, floor, relative, not share_only, parent, sample_v, sample_f,
            unshadowed,
        )  # fmt: skip
        if AREA_LIGHT_RAYS == 1:
            # A pair's one sample takes its own ray's place (the same origin): the batch is
            # cast as built, no copy of it; a pair without samples casts a ray of no length.
            # The pairs' directions to the centre come back after (the shading's).
            pairs = parent[:m]
            centre = ray_v[1, pairs]
            ray_v[1, pairs], ray_f[0, pairs] = sample_v[1, :m], sample_f[0, :m]
            idle = unshadowed >= 0.0
            idle[pairs] = False
            ray_f[0, np.flatnonzero(idle)] = 0.0
            occluded = np.zeros(0, bool)
            if k:
                occluded = np.require(self._occluded(ray_v[0, :k], ray_v[1, :k], ray_f[0, :k],
                                                     threads), bool, ["C", "W"])  # fmt: skip
            ray_v[1, pairs] = centre
            samples = occluded[pairs]
        else:
            point = np.flatnonzero(unshadowed < 0.0)  # the point lights' pairs: their rays
            origins = np.concatenate([ray_v[0, point], sample_v[0, :m]])
            dirs = np.concatenate([ray_v[1, point], sample_v[1, :m]])
            tfar = np.concatenate([ray_f[0, point], sample_f[0, :m]])
            answer = self._occluded(origins, dirs, tfar, threads) if len(tfar) else _NO_ANSWER
            occluded = np.zeros(k, bool)
            occluded[point] = answer[: len(point)]
            samples = np.ascontiguousarray(answer[len(point) :])
        extra = np.zeros(n, np.int64)
        _AREA.area_weights(ray_i, ray_f, occluded, unshadowed, parent[:m], sample_f[1, :m],
                           samples, extra)  # fmt: skip
        return occluded, extra


#: The plastic number g = 1.3247... (Roberts 2018): ``index_offsets``' steps.
_PLASTIC = 1.324717957244746


def index_offsets(n: int) -> np.ndarray:
    """(n, 3) float64 in [0, 1)³: area-light sample offsets of n points by their index i
    (i / g, i / g², i / g³ modulo 1: the R3 sequence's steps are the cube's analogue of
    R2's; here the plastic number's powers), where no pixel gives them (a caller of
    ``shade`` without ``area_offsets``)."""
    i = np.arange(n, dtype=np.float64)[:, None]
    return np.mod(i / np.array([_PLASTIC, _PLASTIC**2, _PLASTIC**3]), 1.0)


#: ``trace_kernels.shadow_rays``' "every pair wanted" (an empty mask).
_ALL_PAIRS = np.zeros((0, 0), bool)
#: ``shade``'s ``into`` when the caller sums the radiance itself.
_NO_TOTAL = (np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0))
#: ``_trace``'s answer without rays.
_NO_SHADOW_RAYS = (np.zeros((2, 0), np.int64), np.zeros((2, 0, 3), np.float32),
                   np.zeros((3, 0), np.float32), np.zeros(0, bool))  # fmt: skip
#: ``trace_kernels.shadow_rays``' offsets when every pair is traced (no sampling).
_NO_OFFSETS = np.zeros(0)
#: ``trace_kernels.shadow_rays``' triangles when the caller gives none.
_NO_TRIANGLES = np.zeros(0, np.int64)
#: Embree's answer to no rays.
_NO_ANSWER = np.zeros(0, bool)
