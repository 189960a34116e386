"""Reflection and refraction paths: the bounce loop and what it gathers.

``PathTracer.run`` follows rays from G-buffer pixels through mirror reflections and
refractions, one loop over bounce depth, everything else vectorised over the rays still
alive. At a hit on surface X with reflectivity F and opacity α (α = 1 unless the stage
has transmissive materials)::

    radiance = α * ((1 - F) * local(X) + F * reflected) + (1 - α) * refracted

``local`` is ``shading.shade_local`` with ray-traced shadows (``shadow_rays``).
``reflected``/``refracted`` continue as new rays while the depth is below the bounce
limit, and read the environment at the limit. Refraction (Snell's law with the
material's ior, total internal reflection → mirror reflection) is part of the same loop;
it runs only when the stage has transmissive materials, otherwise α = 1 everywhere and
no refraction work is done. Where a hit's local term has no weight (F = 1 mirrors,
α = 0 glass) neither shading nor shadow rays are computed.

Fixed cost per call: hybrid batches are small (farm: 50-8,000 rays), so the loop only
follows paths, each depth's per-ray work in one compiled pass (``trace_kernels.bounce``,
into buffers allocated per depth); environment lookups, shadow rays and local shading
of all bounces are gathered and evaluated once per call (``_gather``). Local shading of
a call's hits is split over the pool from ``shadow_rays.PARALLEL_MIN_SHADE_RAYS`` shadow
rays on (numpy releases the GIL on large arrays, embreex inside ``run``).

Records: one ``TraceRecord`` per source reflector (pixels, rays, reflectors hit,
reflector bounces, time share), what the selection heuristic reads.

Rays meet surfaces through ``HitSurfaces.intersect``: cut-out holes are passed through
(re-cast from just past them, bounded by ``model.surface.MAX_CUTOUT_LAYERS``; the re-cast
rays are counted with their kind and source).

Arrays: positions rel float64 (``bvh.Float32Boundary``), directions (n, 3) unit float32,
ray origins float32 (cast by the compiled offset, the boundary's rule).
Limits: mirror reflections only (roughness is ignored).
"""

from __future__ import annotations

import time

import numpy as np

from phrt_usd import kernels
from phrt_usd.model.frame import ReflectionResult, TraceRecord
from phrt_usd.model.scene import Lights
from phrt_usd.render import shading
from phrt_usd.render.trace.bvh import Bvh
from phrt_usd.render.trace.hit_surfaces import HitSurfaces
from phrt_usd.render.trace.shadow_rays import ShadowRays

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
trace_kernels = kernels.load("phrt_usd.render.trace.trace_kernels")
#: Rows of ``trace_kernels.bounce``'s int64, float64 and float32 output buffers (as the
#: kernel module declares them; read without compiling it).
_ROWS_I, _ROWS_W, _ROWS_V = 8, 3, 3


class PathTracer:
    """The bounce loop over one ``Bvh``, its ``HitSurfaces`` and ``ShadowRays``."""

    def __init__(self, bvh: Bvh, surfaces: HitSurfaces, shadows: ShadowRays) -> None:
        self._bvh = bvh
        self._surfaces = surfaces
        self._shadows = shadows

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

        The loop only follows paths: per depth one ``HitSurfaces.intersect``, the surface
        geometry at the hits and one ``trace_kernels.bounce`` (environment entries,
        local-shading entries, reflector keys and chains, the children with their offset
        origins). What a path collects — environment radiance at misses and at the
        bounce limit, local shading (with its shadow rays) at hits — does not steer it,
        so it is gathered over all bounces and evaluated once per call: one environment
        lookup, one shadow batch, one ``shade_local``, one accumulation (fixed per-call
        cost, not per-bounce; hybrid batches are small, 50-8,000 rays).

        sources : the source ids (``TraceRecord.source``); first_kind : "reflection"
        or "refraction" (the kind of the starting rays); start : ``perf_counter`` at the
        call's start; lights : rel lights; n_elements : the scene's element count;
        counters : the tracer's ``rays_cast``, updated here."""
        surfaces, bvh = self._surfaces, self._bvh
        n_pix, n_src = len(pix), len(sources)
        split = surfaces.transmission
        n_elem = max(n_elements, 1)
        floor, relative = bvh.boundary.offset_factors()
        src = np.asarray(src, np.int64)
        chain_pix = np.zeros(n_pix, np.int64)  # reflector hits along the longest path
        key_parts: list[np.ndarray] = []  # source * E + element, one per reflector hit
        # Deferred work, one entry per bounce: environment (slot, weight, dir) and local
        # shading (slot, weight, source, tri, u, v, position, ng, ns, incoming dir).
        env_parts: list[tuple] = []
        shade_parts: list[tuple] = []
        # Live ray state (k rays): pixel slot, source, weight, reflector chain, kind.
        slot = np.arange(n_pix)
        r_src = src
        weight = np.ones(n_pix)
        chain = np.zeros(n_pix, np.int64)
        dirs = np.ascontiguousarray(dirs, np.float32)
        refracted = np.full(n_pix, first_kind == "refraction")
        n_refr = n_pix if first_kind == "refraction" else 0
        rays_src = np.zeros(n_src, np.int64)  # path rays cast per source
        if bounce_limit < 1:
            env_parts.append((slot, weight, dirs))
            slot = slot[:0]
        elif n_pix:
            rays_src += np.bincount(src, minlength=n_src)
        tables = (
            surfaces.tri_reflector, surfaces.tri_f, bvh.tri_material, bvh.tri_element,
            surfaces.opacity, surfaces.ior, bvh.table.frame,
        )  # fmt: skip
        for depth in range(max(bounce_limit, 0)):
            k = len(slot)
            if k == 0:
                break
            counters["refraction"] += n_refr
            counters["reflection"] += k - n_refr
            hits, recast = surfaces.intersect(origins, dirs)
            if len(recast):  # re-casts through cut-out holes (HitSurfaces.intersect)
                rays_src += np.bincount(r_src[recast], minlength=n_src)
                recast_refr = int(np.count_nonzero(refracted[recast]))
                counters["refraction"] += recast_refr
                counters["reflection"] += len(recast) - recast_refr
            m = len(hits.ray)
            d_in = dirs if m == k else np.take(dirs, hits.ray, axis=0)
            rel, ng, ns = surfaces.geometry(hits.tri, hits.u, hits.v, d_in)
            last = depth + 1 >= bounce_limit
            n_out = 2 * m if split else m
            # One buffer per dtype, rows as trace_kernels.BOUNCE_ROWS (views below).
            width = k + n_out
            out_i = np.empty((_ROWS_I, width), np.int64)
            out_w = np.empty((_ROWS_W, width))
            out_v = np.empty((_ROWS_V, width, 3), np.float32)
            c_refr = np.empty(width, bool)
            n_env, n_lit, n_keys, n_child, n_child_refr = trace_kernels.bounce(
                hits.ray, hits.miss, hits.tri, rel, ng, ns, slot, r_src, weight, chain, dirs,
                *tables, split, last, floor, relative, n_elem, chain_pix, rays_src,
                out_i, out_w, out_v, c_refr,
            )  # fmt: skip
            env = (out_i[0], out_w[0], out_v[0])
            lit = (out_i[1], out_w[1], out_i[2], out_i[3])
            keys = out_i[4]
            child = (out_i[5], out_i[6], out_w[2], out_i[7], c_refr, out_v[1], out_v[2])
            if n_env:
                env_parts.append(tuple(a[:n_env] for a in env))
            if n_lit:
                rows, w_local, lit_slot, lit_src = (a[:n_lit] for a in lit)
                hit_rows = (hits.tri, hits.u, hits.v, rel, ng, ns, d_in)
                if n_lit < m:
                    hit_rows = tuple(np.take(a, rows, axis=0) for a in hit_rows)
                shade_parts.append((lit_slot, w_local, lit_src, *hit_rows))
            if n_keys:
                key_parts.append(keys[:n_keys])
            if last or n_child == 0:
                break
            slot, r_src, weight, chain, refracted, dirs, origins = (a[:n_child] for a in child)
            n_refr = n_child_refr
        radiance, shadow_src, shadow_rays = self._gather(
            env_parts, shade_parts, lights, n_pix, counters
        )
        seconds = time.perf_counter() - start
        records, rays = self._records(
            sources, src, chain_pix, rays_src, shadow_src, shadow_rays, key_parts, n_elem,
            bounce_limit, seconds,
        )  # fmt: skip
        return ReflectionResult(
            pixel_index=np.asarray(pix, np.int64),
            radiance=radiance,
            records=records,
            rays=rays,
            seconds=seconds,
        )

    def _shade_points(self, tri, u, v, rel, ng, ns, d_in, lights: Lights, threads=None):
        """Local shading with ray-traced shadows at hits (tri, u, v (m,); rel, ng, ns,
        d_in (m, 3), see ``HitSurfaces.at``): (m, 3) float32 radiance and (m,) int64 shadow
        rays cast per point. Safe to run on the pool with ``threads`` = 1."""
        albedo, emissive = self._surfaces.colour(tri, u, v)
        vis, shadow_rays, lit_pairs = self._shadows.cast(rel, ng, ns, lights, threads=threads)
        local = shading.shade_local(rel, ns, albedo, d_in, emissive, lights, vis, lit_pairs)
        # The caller updates ``rays_cast`` (a dict ``+=`` from pool threads could race).
        return local, shadow_rays

    def _shade_hits(self, tri, u, v, rel, ng, ns, d_in, lights: Lights):
        """``_shade_points`` of every gathered hit: (m, 3) radiance and (m,) shadow rays
        per hit. Large batches (the sewer: 13 lights, ~300k shadow rays) run in chunks
        on the pool (the kernels and embreex release the GIL), each chunk's Embree batch
        on its own thread."""
        n_lights = len(lights.distant) + len(lights.local)
        bounds = self._shadows.split(len(tri) * max(n_lights, 1), len(tri))
        if bounds is None:
            return self._shade_points(tri, u, v, rel, ng, ns, d_in, lights)
        parts = [
            self._shadows.pool.submit(
                self._shade_points,
                *(a[lo:hi] for a in (tri, u, v, rel, ng, ns, d_in)),
                lights,
                1,
            )
            for lo, hi in bounds
        ]
        done = [f.result() for f in parts]
        return np.concatenate([d[0] for d in done]), np.concatenate([d[1] for d in done])

    def _gather(self, env_parts, shade_parts, lights, n_pix, counters):
        """The deferred part of ``run``: environment and local shading of every bounce
        at once. Returns radiance (n_pix, 3) float32, and the source (m,) int64 and
        shadow rays cast (m,) int64 of every shaded point (empty without direct
        lights)."""
        total = np.zeros((n_pix, 3))
        if env_parts:
            slot, weight, dirs = (_cat(p) for p in zip(*env_parts, strict=True))
            env = shading.environment_radiance(lights, dirs)
            trace_kernels.accumulate(total, slot, weight, env)
        no_shadows = np.zeros(0, np.int64)
        shadow_src, shadow_rays = no_shadows, no_shadows
        if shade_parts:
            slot, w, src, tri, u, v, rel, ng, ns, d_in = (
                _cat(p) for p in zip(*shade_parts, strict=True)
            )
            local, rays = self._shade_hits(tri, u, v, rel, ng, ns, d_in, lights)
            if lights.has_direct:
                shadow_src, shadow_rays = src, np.asarray(rays, np.int64)
                counters["shadow"] += int(shadow_rays.sum())
            trace_kernels.accumulate(total, slot, w, np.ascontiguousarray(local, np.float32))
        return total.astype(np.float32), shadow_src, shadow_rays

    @staticmethod
    def _records(
        sources, src, chain_pix, rays_src, shadow_src, shadow_rays, key_parts, n_elem,
        bounce_limit, seconds,
    ):  # fmt: skip
        """One TraceRecord per source (see ``frame.TraceRecord``) and the call's total
        rays. rays_src (sources,) int64: path rays cast per source; shadow_src,
        shadow_rays (m,): each shaded point's source and shadow rays. Seconds are shared
        out by each source's share of the rays."""
        n_src = len(sources)
        pixels = np.zeros(n_src, np.int64)
        chain_sum = np.zeros(n_src)
        chain_max = np.zeros(n_src, np.int64)
        rays_src = rays_src.copy()
        trace_kernels.source_tallies(
            src, chain_pix, shadow_src, shadow_rays, pixels, chain_sum, chain_max, rays_src
        )
        total = int(rays_src.sum())
        per_source: list[dict[int, int]] = [{} for _ in range(n_src)]
        if key_parts:
            # Hits per (source, element) key: a bincount over the n_src * E keys (small),
            # then one dict entry per non-zero count.
            counts = np.bincount(_cat(key_parts), minlength=n_src * n_elem)
            keys = np.flatnonzero(counts)
            for key, count in zip(keys.tolist(), counts[keys].tolist(), strict=True):
                per_source[key // n_elem][key % n_elem] = count
        limit = max(bounce_limit, 0)
        records = [
            TraceRecord(
                source=s,
                pixels=p,
                rays=r,
                hits=per_source[i],
                max_reflector_bounces=min(c, limit),
                mean_reflector_bounces=cs / max(p, 1),
                seconds=seconds * r / total if total else 0.0,
            )
            for i, (s, p, r, c, cs) in enumerate(
                zip(sources, pixels.tolist(), rays_src.tolist(), chain_max.tolist(),
                    chain_sum.tolist(), strict=True)
            )
        ]  # fmt: skip
        return records, total


def _cat(parts) -> np.ndarray:
    """np.concatenate without a copy for a single part."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


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
