"""Reflection and refraction paths: the bounce loop and what it gathers.

``PathTracer.run`` follows rays from G-buffer pixels through mirror reflections and
refractions, one loop over bounce depth, everything else vectorised over the rays still
alive. At a hit on surface X with reflectivity F and opacity α (α = 1 unless the stage
has transmissive materials)::

    radiance = α * ((1 - F) * local(X) + F * reflected) + (1 - α) * refracted

``local`` is ``shading.shade_local`` with the direct light of ``hit_lighting``'s rule
(the shadow maps where the renderer has them and they decide, shadow rays elsewhere,
lights sampled where a hit has many).
``reflected``/``refracted`` continue as new rays while the depth is below the bounce
limit, and read the environment at the limit. Refraction (Snell's law with the
material's ior, total internal reflection → mirror reflection) is part of the same loop;
it runs only when the stage has transmissive materials, otherwise α = 1 everywhere and
no refraction work is done. Where a hit's local term has no weight (F = 1 mirrors,
α = 0 glass) neither shading nor shadow rays are computed.

Fixed cost per call: hybrid batches are small (farm: 14-8,000 rays), so the loop only
follows paths, each depth one Embree query and one compiled pass over its answer
(``trace_kernels.bounce``: hits and misses, the surface at the hits, what the paths
gather, the next rays), in buffers a ``PathTracer`` keeps from call to call
(``_Buffers``); environment lookups, shadow rays and local shading of all bounces are
gathered and evaluated once per call (``_gather``). Every compiled call is a fixed cost
(its arguments are checked, ``phrt_usd.kernels``), so there are few per depth. Local
shading of a call's hits is ``hit_lighting.HitLighting.shade``'s.

Records: one ``TraceRecord`` per source reflector (pixels, rays, reflectors hit,
reflector bounces, time share), what the selection heuristic reads.

Rays meet surfaces through ``HitSurfaces.nearest``: cut-out holes are passed through
(re-cast from just past them, bounded by ``model.surface.MAX_CUTOUT_LAYERS``; the re-cast
rays are counted with their kind and source).

Arrays: positions rel float64 (``bvh.Float32Boundary``), directions (n, 3) unit float32,
ray origins float32 (cast by the compiled offset, the boundary's rule).
Limits: the paths' first rays are mirror or glossy as the tracer made them (a glossy
pixel's drawn from its lobe: ``glossy``); at deeper bounces (a reflector seen in a
reflection) reflections are mirrors (roughness ignored there).
"""

from __future__ import annotations

import time

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine import shading
from phrt_usd.engine.trace.bounce_layout import (
    G_ENV_DIR,
    G_ENV_SLOT,
    G_ENV_W,
    G_KEY,
    G_LIT_ALBEDO,
    G_LIT_DIR,
    G_LIT_NG,
    G_LIT_NS,
    G_LIT_POS,
    G_LIT_SLOT,
    G_LIT_SRC,
    G_LIT_TRI,
    G_LIT_U,
    G_LIT_V,
    G_LIT_W,
    G_ROWS,
    RAY_DIR,
    RAY_ORIGIN,
    RAY_REFRACTED,
    RAY_ROWS,
    RAY_SRC,
    T_ENV,
    T_SOURCES,
)
from phrt_usd.engine.trace.bvh import Bvh
from phrt_usd.engine.trace.hit_lighting import HitLighting
from phrt_usd.engine.trace.hit_surfaces import HitSurfaces
from phrt_usd.engine.trace.shadow_rays import ShadowRays
from phrt_usd.model.frame import ReflectionResult, TraceRecord

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
trace_kernels = kernels.load("phrt_usd.engine.trace.trace_kernels")
#: ``_gather``'s shadow figures when nothing was shaded.
_NO_SHADOWS = np.zeros(0, np.int64)


class _Buffers:
    """``trace_kernels.bounce``'s buffers, kept by a ``PathTracer`` from call to call:
    allocated only when a call needs more room than any before it, never per depth.

    rays_i (2, 4, L) int64, rays_w (2, L) float64, rays_v (2, 2, L, 3) float32: the live
    rays, double-buffered (``bounce_layout.RAY_*``); gather: the call's gathered entries
    g_i, g_w, g_x, g_v, g_uv, G columns each (``bounce_layout.G_*``)."""

    def __init__(self) -> None:
        self.room = 0  # gathered entries the buffers hold
        self.rays_i = np.empty((2, RAY_ROWS, 0), np.int64)
        self.rays_w = np.empty((2, 0))
        self.rays_v = np.empty((2, 2, 0, 3), np.float32)
        self.gather = self._gather_arrays(0)

    @staticmethod
    def _gather_arrays(n: int) -> tuple[np.ndarray, ...]:
        rows_i, rows_w, rows_x, rows_v, rows_uv = G_ROWS
        return (
            np.empty((rows_i, n), np.int64), np.empty((rows_w, n)), np.empty((rows_x, n, 3)),
            np.empty((rows_v, n, 3), np.float32), np.empty((rows_uv, n), np.float32),
        )  # fmt: skip

    def rays(self, need: int, parity: int, k: int) -> None:
        """Room for ``need`` rays per half, keeping half ``parity``'s first k."""
        if need <= self.rays_w.shape[1]:
            return
        n = max(need, 2 * self.rays_w.shape[1])
        old = (self.rays_i, self.rays_w, self.rays_v)
        self.rays_i = np.empty((2, RAY_ROWS, n), np.int64)
        self.rays_w = np.empty((2, n))
        self.rays_v = np.empty((2, 2, n, 3), np.float32)
        self.rays_i[parity, :, :k] = old[0][parity, :, :k]
        self.rays_w[parity, :k] = old[1][parity, :k]
        self.rays_v[parity, :, :k] = old[2][parity, :, :k]

    def entries(self, need: int, used: int) -> None:
        """Room for ``need`` gathered entries, keeping the first ``used``."""
        if need <= self.room:
            return
        self.room = max(need, 2 * self.room)
        fresh = self._gather_arrays(self.room)
        for old, new in zip(self.gather, fresh, strict=True):
            new[:, :used] = old[:, :used]
        self.gather = fresh


class PathTracer:
    """The bounce loop over one ``Bvh``, its ``HitSurfaces`` and ``ShadowRays``; one call
    at a time (its buffers are reused from call to call; the tracer's callers trace
    round after round). ``lighting``: the direct light at its hits (``HitLighting``:
    the tracer sets its shadow maps and frame seed)."""

    def __init__(self, bvh: Bvh, surfaces: HitSurfaces, shadows: ShadowRays) -> None:
        self._bvh = bvh
        self._surfaces = surfaces
        self._shadows = shadows
        self._buffers = _Buffers()
        self.lighting = HitLighting(bvh, surfaces, shadows)

    def run(
        self,
        pix,
        src,
        origins,
        dirs,
        sources,
        bounce_limit,
        first_kind,
        start,
        lights,
        n_elements,
        counters,
    ):
        """The bounce loop. pix (n,) flat pixel per starting ray, src (n,) int64 source
        index, origins (n, 3) render-relative already offset (float32 as Embree takes
        them, or float64), dirs (n, 3) unit (float32 from here on).

        The loop only follows paths: per depth one ``HitSurfaces.nearest`` (Embree) and
        one ``trace_kernels.bounce`` over its answer (the surface at the hits,
        environment entries, local-shading entries with their corner albedo, reflector
        keys and chains, the children with their offset origins), appended to the
        ``_Buffers``. What a path collects — environment radiance at misses and at the
        bounce limit, local shading (with its shadow rays) at hits — does not steer it,
        so it is gathered over all bounces and evaluated once per call: one environment
        lookup, one shadow batch shaded by one compiled call (``ShadowRays.shade``), one
        accumulation (fixed per-call cost, not per-bounce; hybrid batches are small,
        14-8,000 rays).

        sources : the source ids (``TraceRecord.source``); first_kind : "reflection"
        or "refraction" (the kind of the starting rays); start : ``perf_counter`` at the
        call's start; lights : rel lights; n_elements : the scene's element count;
        counters : the tracer's ``rays_cast``, updated here."""
        surfaces, bvh, buf = self._surfaces, self._bvh, self._buffers
        n_pix, n_src = len(pix), len(sources)
        split = surfaces.transmission
        n_elem = max(n_elements, 1)
        floor, relative = bvh.boundary.offset_factors()
        src = np.asarray(src, np.int64)
        # Gathered counts, path rays cast per source after the first, longest reflector
        # chain per path (bounce_layout.T_*).
        tally = np.zeros(T_SOURCES + n_src + n_pix, np.int64)
        k = n_pix if bounce_limit >= 1 else 0
        buf.rays(k, 0, 0)
        buf.entries(n_pix - k, 0)  # the environment entries without rays
        if k < n_pix:  # no rays: the environment in the first directions
            g_i, g_w, _, g_v, _ = buf.gather
            g_i[G_ENV_SLOT, :n_pix] = np.arange(n_pix)
            g_w[G_ENV_W, :n_pix] = 1.0
            g_v[G_ENV_DIR, :n_pix] = dirs
            tally[T_ENV] = n_pix
        elif k:  # the first rays into live half 0
            trace_kernels.start_rays(
                src, np.ascontiguousarray(dirs, np.float32),
                np.ascontiguousarray(origins, np.float32), int(first_kind == "refraction"),
                buf.rays_i, buf.rays_w, buf.rays_v,
            )  # fmt: skip
        n_refr = k if first_kind == "refraction" else 0
        cast = [0, 0]  # reflection, refraction rays (the counters, once at the end)
        tables = (surfaces.tri_table, bvh.table.frame, bvh.table.corners)
        bound = n_pix - k  # gathered entries can reach this
        if split:  # room for children (refracted ones staged after the live rays)
            buf.rays(2 * k, 0, k)
        parity = 0
        # How far each pixel's first ray went (its reflected surface; inf: none), for the
        # fill of reduced densities (``sparse_pixels``).
        first_hit = np.full(n_pix, np.inf, np.float32)
        for depth in range(bounce_limit if k else 0):
            cast[0] += k - n_refr
            cast[1] += n_refr
            rays_v = buf.rays_v
            d32 = rays_v[parity, RAY_DIR, :k]
            answer, recast = surfaces.nearest(rays_v[parity, RAY_ORIGIN, :k], d32)
            if len(recast):  # re-casts through cut-out holes (HitSurfaces.intersect)
                live = buf.rays_i[parity]
                rays_src = tally[T_SOURCES : T_SOURCES + n_src]
                rays_src += np.bincount(live[RAY_SRC, recast], minlength=n_src)
                recast_refr = int(np.count_nonzero(live[RAY_REFRACTED, recast]))
                cast[0] += len(recast) - recast_refr
                cast[1] += recast_refr
            if depth == 0:
                trace_kernels.hit_distances(
                    *answer, rays_v[parity, RAY_ORIGIN, :k], bvh.table.frame, first_hit
                )
            last = depth + 1 >= bounce_limit
            bound += 2 * k  # misses and children, hits
            if bound > buf.room:
                buf.entries(bound, max(tally[:T_SOURCES].tolist()))
            n_child, n_refr = trace_kernels.bounce(
                *answer, surfaces.mapped_normals(answer, d32), buf.rays_i, buf.rays_w, rays_v,
                parity, k, *tables, split, last, floor, relative, n_elem, n_src, tally,
                *buf.gather,
            )  # fmt: skip
            if last or n_child == 0:
                break
            parity, k = 1 - parity, n_child
            if split:
                buf.rays(2 * k, parity, k)
        counters["reflection"] += cast[0]
        counters["refraction"] += cast[1]
        n_env, n_lit, n_keys, n_textured = tally[:T_SOURCES].tolist()
        radiance, shadow_src, shadow_rays = self._gather(
            n_env, n_lit, n_textured > 0, lights, pix, counters
        )
        seconds = time.perf_counter() - start
        records, rays = self._records(
            sources, src, tally, bounce_limit >= 1, shadow_src, shadow_rays,
            buf.gather[0][G_KEY, :n_keys], n_elem, bounce_limit, seconds,
        )  # fmt: skip
        return ReflectionResult(
            pixel_index=np.asarray(pix, np.int64),
            radiance=radiance,
            records=records,
            rays=rays,
            seconds=seconds,
            hit_distance=first_hit,
        )

    def _gather(self, n_env, n_lit, textured, lights, pix, counters):
        """The deferred part of ``run``: environment and local shading of every bounce
        at once, from the first ``n_env`` / ``n_lit`` gathered entries (``textured``:
        some lit entry's material has an albedo texture; pix (n_pix,) the paths'
        pixels). Returns radiance (n_pix, 3) float32, and the source (m,) int64 and
        shadow rays cast (m,) int64 of every shaded point (empty without direct
        lights)."""
        g_i, g_w, g_x, g_v, g_uv = self._buffers.gather
        total = np.zeros((len(pix), 3))
        if n_env:
            env = shading.environment_radiance(lights, g_v[G_ENV_DIR, :n_env])
            trace_kernels.accumulate(total, g_i[G_ENV_SLOT, :n_env], g_w[G_ENV_W, :n_env], env)
        shadow_src = shadow_rays = _NO_SHADOWS
        if n_lit:
            slot, src = g_i[G_LIT_SLOT, :n_lit], g_i[G_LIT_SRC, :n_lit]
            tri, u, v = g_i[G_LIT_TRI, :n_lit], g_uv[G_LIT_U, :n_lit], g_uv[G_LIT_V, :n_lit]
            rel, ng = g_x[G_LIT_POS, :n_lit], g_x[G_LIT_NG, :n_lit]
            ns, d_in = g_v[G_LIT_NS, :n_lit], g_v[G_LIT_DIR, :n_lit]
            albedo = g_v[G_LIT_ALBEDO, :n_lit]
            into = (total, slot, g_w[G_LIT_W, :n_lit])
            _, rays, cast = self.lighting.shade(
                tri, u, v, rel, ng, ns, d_in, lights, np.take(pix, slot), albedo, into, textured
            )
            if cast:
                shadow_src, shadow_rays = src, rays
                counters["shadow"] += cast
        return total.astype(np.float32), shadow_src, shadow_rays

    @staticmethod
    def _records(
        sources, src, tally, first_cast, shadow_src, shadow_rays, keys, n_elem, bounce_limit,
        seconds,
    ):  # fmt: skip
        """One TraceRecord per source (see ``frame.TraceRecord``) and the call's total
        rays (``trace_kernels.source_tallies`` of ``tally`` and the shadow rays:
        shadow_src, shadow_rays (m,), each shaded point's source and shadow rays). Seconds
        are shared out by each source's share of the rays."""
        n_src = len(sources)
        figures = np.empty((4, n_src), np.int64)
        found = np.empty((2, len(keys)), np.int64)  # key, hits
        n_found = trace_kernels.source_tallies(
            src, tally, first_cast, shadow_src, shadow_rays, keys, n_src * n_elem, figures, found
        )
        pixels, chain_sum, chain_max, rays_src = figures.tolist()
        total = sum(rays_src)
        per_source: list[dict[int, int]] = [{} for _ in range(n_src)]
        if n_found:  # hits per (source, element) key: one dict entry per key found
            for key, count in zip(*found[:, :n_found].tolist(), strict=True):
                per_source[key // n_elem][key % n_elem] = count
        limit = max(bounce_limit, 0)
        # Positional in TraceRecord's field order (source, pixels, rays, hits, max and
        # mean reflector bounces, seconds): keywords cost ~0.4 us a record.
        records = [
            TraceRecord(
                s, p, r, hits, min(c, limit), cs / max(p, 1), seconds * r / total if total else 0.0
            )
            for s, p, r, hits, c, cs in zip(
                sources, pixels, rays_src, per_source, chain_max, chain_sum, strict=True
            )
        ]
        return records, total


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of (n, 3) scaled to unit length (zero rows stay zero instead of NaN)."""
    length = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    return v / np.where(length > 0, length, 1.0)


def refract(d: np.ndarray, ns: np.ndarray, ng_raw: np.ndarray, ior: np.ndarray) -> np.ndarray:
    """Snell refraction of unit directions d (n, 3) at surfaces with shading normals ns
    (n, 3, either side) and outward (front-face) geometric normals ng_raw (n, 3); ior (n,).
    Entering (d against ng_raw) uses η = 1 / ior, leaving uses η = ior. Total internal
    reflection returns the mirror direction. Returns (n, 3) unit float64."""
    entering = np.einsum("ij,ij->i", d, ng_raw) < 0
    eta = np.where(entering, 1.0 / ior, ior)
    n = np.where((np.einsum("ij,ij->i", d, ns) > 0)[:, None], -ns, ns)  # against d
    cos_i = np.clip(-np.einsum("ij,ij->i", d, n), 0.0, 1.0)
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    tir = k < 0
    t = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0.0)))[:, None] * n
    r = d + 2.0 * cos_i[:, None] * n
    return unit(np.where(tir[:, None], r, t))
