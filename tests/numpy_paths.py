"""The numpy forms of the trace phase's per-ray code, kept as the reference the compiled
kernels (``phrt_usd.engine.trace.trace_kernels``) are tested against: the bounce loop,
its gather and records (``NumpyPathTracer``), and the first rays from G-buffer pixels
(``numpy_first_rays``), as they were before the kernels replaced them."""

from __future__ import annotations

import time

import numpy as np

from phrt_usd.engine import shading
from phrt_usd.engine.trace.paths import PathTracer, refract, unit
from phrt_usd.model.frame import ReflectionResult, TraceRecord


class NumpyPathTracer(PathTracer):
    """``PathTracer`` with the numpy bounce loop (same shading, shadows, surfaces)."""

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
        """The bounce loop. pix (n,) flat pixel per starting ray, src (n,) source index,
        origins (n, 3) render-relative float64 already offset, dirs (n, 3) unit.

        The loop only follows paths (intersect, surface geometry, children). What a
        path collects — environment radiance at misses and at the bounce limit, local
        shading (with its shadow rays) at hits — does not steer it, so it is gathered
        over all bounces and evaluated once per call: one environment lookup, one shadow
        batch, one ``shade_local``, one accumulation (fixed per-call cost, not
        per-bounce; hybrid batches are small, 50-5,000 rays).

        sources : the source ids (``TraceRecord.source``); first_kind : "reflection"
        or "refraction" (the kind of the starting rays); start : ``perf_counter`` at the
        call's start; lights : rel lights; n_elements : the scene's element count;
        counters : the tracer's ``rays_cast``, updated here."""
        n_pix, n_src = len(pix), len(sources)
        split = self._surfaces.transmission
        chain_pix = np.zeros(n_pix, np.int64)  # reflector hits along the longest path
        hit_keys: list[np.ndarray] = []  # source * E + element, one per reflector hit
        n_elem = max(n_elements, 1)
        cast_src: list[np.ndarray] = []  # source of every ray cast, per bounce
        # Deferred work, one entry per bounce: environment (slot, weight, dir) and local
        # shading (slot, weight, source, tri, u, v, position, ng, ns, incoming dir).
        env_parts: list[tuple] = []
        shade_parts: list[tuple] = []
        # Live ray state (k rays): pixel slot, source, weight, reflector chain, kind.
        slot = np.arange(n_pix)
        r_src = src
        weight = np.ones(n_pix)
        chain = np.zeros(n_pix, np.int64)
        refracted = np.full(n_pix, first_kind == "refraction")
        if bounce_limit < 1:
            env_parts.append((slot, weight, dirs))
            slot = slot[:0]
        for depth in range(max(bounce_limit, 0)):
            if len(slot) == 0:
                break
            n_refr = int(np.count_nonzero(refracted))
            counters["refraction"] += n_refr
            counters["reflection"] += len(slot) - n_refr
            cast_src.append(r_src)
            hits, recast = self._surfaces.intersect(origins, dirs)
            if len(recast):  # re-casts through cut-out holes (HitSurfaces.intersect)
                cast_src.append(r_src[recast])
                n_refr = int(np.count_nonzero(refracted[recast]))
                counters["refraction"] += n_refr
                counters["reflection"] += len(recast) - n_refr
            r = hits.ray
            m = hits.miss
            if len(m):
                env_parts.append((slot[m], weight[m], np.take(dirs, m, axis=0)))
            if len(r) == 0:
                break
            every = len(r) == len(slot)  # all rays hit: no gathers needed
            d_in = dirs if every else np.take(dirs, r, axis=0)
            rel, ng, ns = self._surfaces.geometry(hits.tri, hits.u, hits.v, d_in)
            refl = np.take(self._surfaces.tri_reflector, hits.tri)
            f = np.take(self._surfaces.tri_f, hits.tri)
            if split:
                mat = self._bvh.tri_material[hits.tri]
                alpha = self._surfaces.opacity[mat]
            else:
                alpha = 1.0
            w = weight if every else weight[r]
            slot_r = slot if every else slot[r]
            src_r = r_src if every else r_src[r]
            # Local shading (and its shadow rays) only where it carries weight: a perfect
            # mirror (F = 1) or clear glass (α = 0) shows none of its own surface.
            w_local = w * alpha * (1.0 - f)
            lit = np.flatnonzero(w_local > 0)
            if len(lit) == len(r):
                shade_parts.append(
                    (slot_r, w_local, src_r, hits.tri, hits.u, hits.v, rel, ng, ns, d_in)
                )
            elif len(lit):
                shade_parts.append(
                    (slot_r[lit], w_local[lit], src_r[lit], hits.tri[lit], hits.u[lit])
                    + (hits.v[lit],)
                    + tuple(np.take(a, lit, axis=0) for a in (rel, ng, ns, d_in))
                )
            ch = chain if every else chain[r]
            ch = ch + refl
            if split:
                np.maximum.at(chain_pix, slot_r, ch)
            else:
                chain_pix[slot_r] = ch  # chains only grow along a path
            if refl.any():
                hit_keys.append(src_r[refl] * n_elem + self._bvh.tri_element[hits.tri[refl]])
            # Children: reflected rays (weight w α F), refracted rays (weight w (1 - α)).
            w_refl = w * alpha * f
            go = np.flatnonzero(w_refl > 0)
            if not split and len(go) == 0:
                break
            # Mirror of a unit vector about a unit normal: unit already, no renormalising.
            d_go = np.take(d_in, go, axis=0)
            ns_go = np.take(ns, go, axis=0)
            c_dir = d_go - (2.0 * np.einsum("ij,ij->i", d_go, ns_go))[:, None] * ns_go
            c_idx, c_w = go, w_refl[go]
            c_refr = np.zeros(len(go), dtype=bool)
            if split:
                w_refr = w * (1.0 - alpha)
                gi = np.flatnonzero(w_refr > 0)
                if len(gi):
                    tri_g = hits.tri[gi]
                    front = self._bvh.table.frame[tri_g, 3]
                    d_refr = refract(d_in[gi], ns[gi], front, self._surfaces.ior[mat[gi]])
                    c_dir = np.concatenate([c_dir, d_refr.astype(c_dir.dtype)])
                    c_idx = np.concatenate([c_idx, gi])
                    c_w = np.concatenate([c_w, w_refr[gi]])
                    c_refr = np.concatenate([c_refr, np.ones(len(gi), dtype=bool)])
            if depth + 1 >= bounce_limit:
                if len(c_idx):
                    env_parts.append((slot_r[c_idx], c_w, c_dir))
                break
            origins = self._bvh.boundary.offset(
                np.take(rel, c_idx, axis=0), np.take(ng, c_idx, axis=0), c_dir
            )
            dirs = c_dir
            slot = slot_r[c_idx]
            r_src = src_r[c_idx]
            weight = c_w
            chain = ch[c_idx]
            refracted = c_refr
        radiance, rays_src = self._gather(
            env_parts, shade_parts, cast_src, lights, n_pix, n_src, counters
        )
        seconds = time.perf_counter() - start
        return ReflectionResult(
            pixel_index=pix.astype(np.int64),
            radiance=radiance,
            records=self._records(
                sources, src, chain_pix, rays_src, hit_keys, n_elem, bounce_limit, seconds
            ),
            rays=int(rays_src.sum()),
            seconds=seconds,
        )

    def _gather(self, env_parts, shade_parts, cast_src, lights, n_pix, n_src, counters):
        """The deferred part of ``run``: environment and local shading of every
        bounce at once. Returns radiance (n_pix, 3) float32 and rays cast per source
        (n_src,) int64 (path rays + shadow rays)."""
        rays_src = _bincount(cast_src, None, n_src).astype(np.int64)
        slots, values = [], []
        if env_parts:
            slot, weight, dirs = (_cat(p) for p in zip(*env_parts, strict=True))
            env = shading.environment_radiance(lights, dirs)
            slots.append(slot)
            values.append(weight[:, None] * env)
        if shade_parts:
            slot, w, src, tri, u, v, rel, ng, ns, d_in = (
                _cat(p) for p in zip(*shade_parts, strict=True)
            )
            # Shading as before ``ShadowRays.shade``: visibility and lit pairs from
            # ``cast``, then ``shade_local``.
            albedo, emissive = self._surfaces.colour(tri, u, v)
            surface = self._surfaces.surface(tri, u, v, albedo)
            vis, shadow_rays, lit_pairs = self._shadows.cast(rel, ng, ns, lights)
            local = shading.shade_local(rel, ns, surface, d_in, emissive, lights, vis, lit_pairs)
            if lights.has_direct:
                rays_src += np.bincount(src, weights=shadow_rays, minlength=n_src).astype(np.int64)
                counters["shadow"] += int(shadow_rays.sum())
            slots.append(slot)
            values.append(w[:, None] * local)
        radiance = np.zeros((n_pix, 3), np.float32)
        if slots:
            slot = _cat(slots)
            value = _cat(values)
            # Slots repeat across bounces (and refraction splits paths): sum per channel.
            for c in range(3):
                radiance[:, c] = np.bincount(slot, weights=value[:, c], minlength=n_pix)
        return radiance, rays_src

    @staticmethod
    def _records(sources, src, chain_pix, rays_src, hit_keys, n_elem, bounce_limit, seconds):
        """One TraceRecord per source (see ``frame.TraceRecord``); seconds are shared out
        by each source's share of the rays."""
        n_src = len(sources)
        total = int(rays_src.sum())
        per_source: list[dict[int, int]] = [{} for _ in range(n_src)]
        if hit_keys:
            # Hits per (source, element) key: a bincount over the n_src * E keys (small),
            # then one dict entry per non-zero count.
            counts = np.bincount(_cat(hit_keys), minlength=n_src * n_elem)
            keys = np.flatnonzero(counts)
            for key, count in zip(keys.tolist(), counts[keys].tolist(), strict=True):
                per_source[key // n_elem][key % n_elem] = count
        pixels = np.bincount(src, minlength=n_src)
        chain_sum = np.bincount(src, weights=chain_pix, minlength=n_src)
        chain_max = np.zeros(n_src, np.int64)
        np.maximum.at(chain_max, src, chain_pix)
        return [
            TraceRecord(
                source=s,
                pixels=int(pixels[i]),
                rays=int(rays_src[i]),
                hits=per_source[i],
                max_reflector_bounces=int(min(chain_max[i], max(bounce_limit, 0))),
                mean_reflector_bounces=float(chain_sum[i] / max(pixels[i], 1)),
                seconds=seconds * float(rays_src[i]) / total if total else 0.0,
            )
            for i, s in enumerate(sources)
        ]


def _cat(parts) -> np.ndarray:
    """np.concatenate without a copy for a single part."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _bincount(parts: list[np.ndarray], weights, size: int) -> np.ndarray:
    """np.bincount over concatenated index arrays ``parts`` (empty list: zeros)."""
    if not parts:
        return np.zeros(size, np.int64)
    return np.bincount(_cat(parts), weights=weights, minlength=size)


def numpy_first_rays(tracer, gbuffer, sources: list[int]):
    """Reflection rays from the G-buffer pixels of ``sources`` as numpy computed them
    (flat pixel order): pix, src, rel origins offset (n, 3) float64, dirs (n, 3)
    float32, and the snapped rel positions, front normals, shading normals, views."""
    n_elem = len(tracer.scene.elements)
    table = np.full(max(n_elem, max(sources, default=0) + 1) + 1, -1)
    table[[s for s in sources if s >= 0]] = [i for i, s in enumerate(sources) if s >= 0]
    elem = gbuffer.element_id.reshape(-1)
    pix = np.flatnonzero(np.take(table >= 0, elem))
    src = np.take(table, np.take(elem, pix))
    tri = np.take(gbuffer.triangle_id.reshape(-1), pix).astype(np.int64)
    view = unit(np.take(gbuffer.view_dir.reshape(-1, 3), pix, axis=0).astype(np.float32))
    ns = unit(np.take(gbuffer.normal.reshape(-1, 3), pix, axis=0).astype(np.float32))
    ns *= np.where(np.einsum("ij,ij->i", ns, view) > 0, -1.0, 1.0).astype(np.float32)[:, None]
    position = np.take(gbuffer.position.reshape(-1, 3), pix, axis=0)
    rel, ng = tracer.surfaces.snap(position - tracer.bvh.boundary.origin, tri, ns)
    d = unit(view - 2.0 * np.einsum("ij,ij->i", view, ns)[:, None] * ns)
    origins = tracer.bvh.boundary.offset(rel, ng, d)
    return pix, src, origins, d, rel, ng, ns, view


def numpy_trace_reflections(tracer, gbuffer, sources: list[int], bounce_limit: int):
    """``Tracer.trace_reflections`` through the numpy forms (counters updated)."""
    start = time.perf_counter()
    pix, src, origins, d, *_ = numpy_first_rays(tracer, gbuffer, sources)
    paths = NumpyPathTracer(tracer.bvh, tracer.surfaces, tracer._shadows)
    return paths.run(
        pix, src, origins, d, sources, bounce_limit, "reflection", start,
        tracer._relative_lights(), len(tracer.scene.elements), tracer.rays_cast,
    )  # fmt: skip


def numpy_primary_gbuffer(tracer, camera, width: int, height: int):
    """``Tracer.primary_gbuffer`` as numpy computed it (``CameraFrame.pixel_rays``)."""
    from phrt_usd.model.frame import GBuffer  # noqa: PLC0415
    from phrt_usd.model.scene import NO_HIT  # noqa: PLC0415

    origin = tracer.bvh.boundary.origin
    origins, dirs = camera.pixel_rays(width, height)
    n = origins.shape[0]
    cos = np.maximum(dirs @ camera.forward, 1e-6)
    start = max(float(camera.near), 0.0) / cos
    hits, _ = tracer.surfaces.intersect(origins - origin + dirs * start[:, None], dirs)
    element = np.full(n, NO_HIT, np.int32)
    triangle = np.full(n, NO_HIT, np.int32)
    depth = np.full(n, np.inf, np.float32)
    position = np.zeros((n, 3))
    normal = np.zeros((n, 3), np.float32)
    albedo = np.zeros((n, 3), np.float32)
    r = hits.ray
    rel, _, ns, alb, _ = tracer.surfaces.at(hits.tri, hits.u, hits.v, dirs[r])
    hit_depth = (rel - (camera.position - origin)) @ camera.forward
    keep = hit_depth <= float(camera.far)
    r, tri = r[keep], hits.tri[keep]
    element[r] = tracer.bvh.tri_element[tri]
    triangle[r] = tri
    position[r] = rel[keep] + origin
    normal[r] = ns[keep]
    albedo[r] = alb[keep]
    depth[r] = hit_depth[keep]
    shape = (height, width)
    return GBuffer(
        element_id=element.reshape(shape),
        triangle_id=triangle.reshape(shape),
        depth=depth.reshape(shape),
        position=position.reshape(shape + (3,)),
        normal=normal.reshape(shape + (3,)),
        albedo=albedo.reshape(shape + (3,)),
        view_dir=dirs.astype(np.float32).reshape(shape + (3,)),
    )
