"""Embree ray tracing: reflection and refraction paths, shadow rays, primary rays (``rt``).

Pipeline phase: after the G-buffer and the selection of reflectors, ``Tracer`` turns the
G-buffer pixels of the selected reflectors into reflected radiance. It also serves the
``rt`` reference mode (``primary_gbuffer``: the G-buffer from primary rays) and ray-traced
shadows (``shadow_visibility``).

Coordinate spaces: every array crossing this module's API is world space, metres, float64
positions. Inside, Embree sees float32 coordinates *relative to* ``Scene.origin``; the cast
happens only at the Embree call (``Tracer._run``). Hit points are rebuilt in float64 from
the hit triangle's float64 vertices and Embree's barycentrics (not ``origin + t * dir``),
so they lie on the surface to float64 precision.

Paths (``trace_reflections``, ``trace_refraction``): one loop over bounce depth, everything
else vectorised over the rays still alive. At a hit on surface X with reflectivity F and
opacity α (α = 1 unless the stage has transmissive materials)::

    radiance = α * ((1 - F) * local(X) + F * reflected) + (1 - α) * refracted

``local`` is ``shading.shade_local`` with ray-traced shadows. ``reflected``/``refracted``
continue as new rays while the depth is below the bounce limit, and read the environment
at the limit. Refraction (Snell's law with the material's ior, total internal reflection
→ mirror reflection) is part of the same bounce loop; it runs only when
``scene.materials.has_transmission``, otherwise α = 1 everywhere and no refraction work is
done. Shadow rays treat transmissive surfaces as opaque.

Limits: mirror reflections only (roughness is ignored), one geometry rebuild per
``update_geometry`` (embreex has no refit), shadows are hard (light size ignored).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from phrt_usd import shading
from phrt_usd.frame import GBuffer, ReflectionResult, TraceRecord
from phrt_usd.scene import NO_HIT, CameraFrame, Scene

#: Ray-origin offset along the geometric normal, in two parts (the larger one wins)::
#:
#:     eps = max(RAY_OFFSET_ABSOLUTE * scene.extent, RAY_OFFSET_RELATIVE * |p - origin|_max)
#:
#: The absolute part covers the float32 rounding of triangle vertices relative to
#: ``scene.origin`` (≈ 6e-8 * extent) with a 16x margin, so even a 1e-3 m scene gets an
#: offset proportional to its size and nothing leaks through thin features. The relative
#: part covers the float32 rounding of the ray origin itself (≈ 6e-8 * |p - origin|, 160x
#: margin). Positions are always taken relative to ``scene.origin``, so a scene 1e6 m from
#: the world origin is as precise as one at the origin. Computed in float64.
RAY_OFFSET_ABSOLUTE = 1e-6
RAY_OFFSET_RELATIVE = 1e-5

#: Batches smaller than this run on one thread (splitting costs more than it saves).
PARALLEL_MIN_RAYS = 8192

#: Embree ray length for "infinite" rays (DistantLight shadow rays); finite in float32.
_FAR = 1e30


@dataclass
class _Hits:
    """Intersections of a batch of rays that hit something (m of the n rays).

    ray : (m,) int64 index of the ray in its batch; tri : (m,) int64 triangle ids;
    u, v : (m,) float64 Embree barycentrics (p = v0 + u (v1 - v0) + v (v2 - v0))."""

    ray: np.ndarray
    tri: np.ndarray
    u: np.ndarray
    v: np.ndarray


class Tracer:
    """Ray tracing against one ``Scene`` (one Embree BVH, rebuilt by ``update_geometry``).

    rays_cast : cumulative counters by kind ("primary", "reflection", "refraction",
                "shadow"); ``reset_counters()`` zeroes them.
    record_rays : when True, every Embree batch of the latest public call is kept in
                  ``last_rays`` (query, origins f32, directions f32, tfar f32 or None),
                  for ``replay_raw`` to compare with raw embreex on the same rays.
    last_build_seconds : wall time of the latest BVH build.
    """

    def __init__(self, scene: Scene, threads: int = 2) -> None:
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self.rays_cast: dict[str, int] = {}
        self.reset_counters()
        self.record_rays = False
        self.last_rays: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.last_build_seconds = 0.0
        self.update_geometry(scene)

    # ------------------------------------------------------------------ set-up

    def reset_counters(self) -> None:
        self.rays_cast = {"primary": 0, "reflection": 0, "refraction": 0, "shadow": 0}

    def update_geometry(self, scene: Scene) -> None:
        """(Re)build the BVH and the per-triangle tables from ``scene`` (after animated
        prims moved). embreex offers no refit, so this is a full build; its cost is kept
        in ``last_build_seconds``."""
        start = time.perf_counter()
        self.scene = scene
        geo = scene.geometry
        self.origin = np.asarray(scene.origin, dtype=np.float64)
        self.extent = scene.extent
        tris = np.asarray(geo.triangles, dtype=np.int64).reshape(-1, 3)
        verts = np.asarray(geo.vertices, dtype=np.float64).reshape(-1, 3)
        # Per-triangle float64 tables (world metres) for exact hit points and normals.
        self._v0 = verts[tris[:, 0]]
        self._e1 = verts[tris[:, 1]] - self._v0
        self._e2 = verts[tris[:, 2]] - self._v0
        normal = np.cross(self._e1, self._e2)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        # Degenerate triangles are never hit by Embree; give them +Y to stay finite.
        self._tri_normal = np.where(length > 0, normal / np.where(length > 0, length, 1), 0.0)
        self._tri_normal[length[:, 0] == 0] = (0.0, 1.0, 0.0)
        self._tri_element = np.asarray(geo.tri_element, dtype=np.int64)
        self._tri_material = np.asarray(geo.tri_material, dtype=np.int64)
        self._corner_normals = np.asarray(geo.corner_normals, dtype=np.float32)
        self._corner_albedo = np.asarray(geo.corner_albedo, dtype=np.float32)
        mats = scene.materials
        self._reflectivity = scene.reflectivity.astype(np.float64)
        self._is_reflector = np.array([e.is_reflector for e in scene.elements], dtype=bool)
        self._transmission = mats.has_transmission
        self._opacity = np.clip(np.asarray(mats.opacity, dtype=np.float64), 0.0, 1.0)
        # ior ≤ 0 is meaningless; clamp so Snell's law stays finite.
        self._ior = np.maximum(np.asarray(mats.ior, dtype=np.float64), 1e-3)
        self._emissive = np.asarray(mats.emissive, dtype=np.float32).reshape(-1, 3)
        self._textures = list(mats.textures) if geo.corner_uv is not None else []
        self._embree = rtcs.EmbreeScene()
        if len(tris):
            TriangleMesh(
                self._embree,
                np.ascontiguousarray(verts - self.origin, dtype=np.float32),
                np.ascontiguousarray(tris, dtype=np.int32),
            )
            # Commit now (embreex commits lazily on the first run) so the build is timed
            # here and never inside a trace budget.
            probe = np.zeros((1, 3), dtype=np.float32)
            self._embree.run(probe, probe + np.float32(1.0))
        self.last_build_seconds = time.perf_counter() - start

    # ------------------------------------------------------------------ Embree calls

    def _run(self, query: str, origins: np.ndarray, dirs: np.ndarray, tfar=None):
        """One Embree batch. origins (n, 3) float64 world metres, dirs (n, 3) world unit,
        tfar (n,) metres or None. Returns Embree's dict (INTERSECT) or (n,) bool occluded.
        The batch is split over the thread pool when large enough (embreex releases the
        GIL inside ``run``)."""
        o32 = np.ascontiguousarray(origins - self.origin, dtype=np.float32)
        d32 = np.ascontiguousarray(dirs, dtype=np.float32)
        t32 = None if tfar is None else np.ascontiguousarray(np.minimum(tfar, _FAR), np.float32)
        if self.record_rays:
            self.last_rays.append((query, o32, d32, None if t32 is None else t32.copy()))
        return self._run_raw(query, o32, d32, t32, self.threads)

    def _run_raw(self, query, o32, d32, t32, threads):
        n = o32.shape[0]
        output = 1 if query == "INTERSECT" else None
        if n == 0 or len(self._v0) == 0:
            if query == "OCCLUDED":
                return np.zeros(n, dtype=bool)
            return {
                "primID": np.full(n, NO_HIT, np.int32),
                "u": np.zeros(n, np.float32),
                "v": np.zeros(n, np.float32),
                "tfar": np.full(n, np.inf, np.float32),
            }
        if threads > 1 and self._pool is not None and n >= PARALLEL_MIN_RAYS:
            bounds = np.linspace(0, n, min(threads, self.threads) + 1).astype(int)
            futures = [
                self._pool.submit(
                    self._embree.run,
                    o32[a:b],
                    d32[a:b],
                    None if t32 is None else t32[a:b].copy(),
                    query,
                    output,
                )
                for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            ]
            parts = [f.result() for f in futures]
            if output:
                out = {
                    k: np.concatenate([p[k] for p in parts]) for k in ("primID", "u", "v", "tfar")
                }
            else:
                out = np.concatenate(parts)
        else:
            out = self._embree.run(o32, d32, None if t32 is None else t32.copy(), query, output)
        if output:
            return out
        return out != NO_HIT

    def _intersect(self, origins: np.ndarray, dirs: np.ndarray) -> _Hits:
        res = self._run("INTERSECT", origins, dirs)
        ray = np.flatnonzero(res["primID"] >= 0)
        return _Hits(
            ray=ray,
            tri=res["primID"][ray].astype(np.int64),
            u=res["u"][ray].astype(np.float64),
            v=res["v"][ray].astype(np.float64),
        )

    def replay_raw(self, threads: int | None = None) -> tuple[int, float]:
        """Re-run raw embreex on exactly the batches in ``last_rays`` (same float32
        arrays, same splitting rule, ``threads`` defaults to the tracer's). Returns
        (rays, seconds) so a benchmark can compare our throughput with Embree's own."""
        threads = self.threads if threads is None else threads
        start = time.perf_counter()
        rays = 0
        for query, o32, d32, t32 in self.last_rays:
            self._run_raw(query, o32, d32, t32, threads)
            rays += o32.shape[0]
        return rays, time.perf_counter() - start

    # ------------------------------------------------------------------ surface data

    def offset_epsilon(self, positions: np.ndarray) -> np.ndarray:
        """(n,) float64 metres: the ray-origin offset at world ``positions`` (n, 3)."""
        rel = np.max(np.abs(positions - self.origin), axis=1)
        return np.maximum(RAY_OFFSET_ABSOLUTE * self.extent, RAY_OFFSET_RELATIVE * rel)

    def _surface(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, incoming: np.ndarray):
        """Everything shading needs at hits: position (m, 3) float64, geometric normal and
        shading normal (m, 3) both facing against ``incoming`` (m, 3), albedo (m, 3)
        float32, emissive (m, 3) float32."""
        pos = self._v0[tri] + u[:, None] * self._e1[tri] + v[:, None] * self._e2[tri]
        ng = self._tri_normal[tri]
        ng = np.where((np.einsum("ij,ij->i", ng, incoming) > 0)[:, None], -ng, ng)
        w = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float32)  # (m, 3) corner weights
        ns = np.einsum("mc,mck->mk", w, self._corner_normals[tri]).astype(np.float64)
        ns_len = np.linalg.norm(ns, axis=1, keepdims=True)
        bad = ~(ns_len[:, 0] > 1e-12)  # zero / NaN interpolated normal: use the geometric one
        ns = np.where(bad[:, None], ng, ns / np.where(bad[:, None], 1.0, ns_len))
        ns = np.where((np.einsum("ij,ij->i", ns, incoming) > 0)[:, None], -ns, ns)
        albedo = np.einsum("mc,mck->mk", w, self._corner_albedo[tri])
        mat = self._tri_material[tri]
        for m_id, texture in enumerate(self._textures):
            if texture is None:
                continue
            sel = np.flatnonzero(mat == m_id)
            if len(sel):
                uv = np.einsum("mc,mck->mk", w[sel], self.scene.geometry.corner_uv[tri[sel]])
                albedo[sel] = shading.sample_texture(texture, uv)
        emissive = self._emissive[mat] if len(self._emissive) else np.zeros((len(tri), 3))
        return pos, ng, ns, albedo.astype(np.float32), emissive

    def _snap_to_triangles(self, positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Project (n, 3) positions (e.g. from a depth buffer) onto the plane of their
        triangle (n,) (-1 = leave as is): removes depth-buffer error before offsetting."""
        out = np.array(positions, dtype=np.float64, copy=True)
        ok = tri >= 0
        t = tri[ok]
        ng = self._tri_normal[t]
        dist = np.einsum("ij,ij->i", out[ok] - self._v0[t], ng)
        out[ok] -= dist[:, None] * ng
        return out

    # ------------------------------------------------------------------ shadows

    def _shadow(self, positions, offset_normals, shading_normals):
        """(n, L) float32 visibility and (n,) int64 shadow rays cast per point.

        Rays are cast only where the light is in front of the shading normal (elsewhere the
        Lambert term is 0 anyway and visibility is reported as 0)."""
        lights = self.scene.lights
        n = positions.shape[0]
        if not lights.has_direct or n == 0:
            n_lights = len(lights.distant) + len(lights.local)
            return np.ones((n, n_lights), np.float32), np.zeros(n, np.int64)
        dirs, dist = shading.light_directions(lights, positions)
        n_lights = dirs.shape[1]
        facing = np.einsum("nk,nlk->nl", shading_normals, dirs) > 0
        point, light = np.nonzero(facing)
        vis = np.zeros((n, n_lights), np.float32)
        if len(point):
            d = dirs[point, light]
            ng = offset_normals[point]
            side = np.where(np.einsum("ij,ij->i", d, ng) >= 0, 1.0, -1.0)
            eps = self.offset_epsilon(positions[point])
            origin = positions[point] + (side * eps)[:, None] * ng
            # Stop short of a LocalLight by the offset so the light's own position is free.
            tfar = np.where(np.isfinite(dist[point, light]), dist[point, light] - eps, _FAR)
            occluded = self._run("OCCLUDED", origin, d, np.maximum(tfar, 0.0))
            vis[point, light] = np.where(occluded, 0.0, 1.0)
            self.rays_cast["shadow"] += len(point)
        return vis, facing.sum(axis=1)

    def shadow_visibility(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        triangle_ids: np.ndarray | None = None,
    ) -> np.ndarray:
        """Ray-traced shadows: (n, L) float32, 1 = lit, light order distant then local.

        positions : (n, 3) float64 world metres; normals : (n, 3) world unit shading
        normals (facing the viewer); triangle_ids : optional (n,) triangle of each point
        (snaps depth-buffer positions onto their triangle first). No lights: returns
        (n, 0) and casts nothing. Points facing away from a light get 0 without a ray.
        """
        self.last_rays = []
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if triangle_ids is not None:
            positions = self._snap_to_triangles(positions, np.asarray(triangle_ids))
        vis, _ = self._shadow(positions, normals, normals)
        return vis

    # ------------------------------------------------------------------ primary rays

    def primary_gbuffer(self, camera: CameraFrame, width: int, height: int) -> GBuffer:
        """The ``rt`` mode's G-buffer: primary rays through pixel centres, same field
        definitions as the raster G-buffer (``frame.GBuffer``)."""
        self.last_rays = []
        origins, dirs = camera.pixel_rays(width, height)
        n = origins.shape[0]
        hits = self._intersect(origins, dirs)
        self.rays_cast["primary"] += n
        element = np.full(n, NO_HIT, np.int32)
        triangle = np.full(n, NO_HIT, np.int32)
        depth = np.full(n, np.inf, np.float32)
        position = np.zeros((n, 3))
        normal = np.zeros((n, 3), np.float32)
        albedo = np.zeros((n, 3), np.float32)
        r = hits.ray
        pos, _, ns, alb, _ = self._surface(hits.tri, hits.u, hits.v, dirs[r])
        element[r] = self._tri_element[hits.tri]
        triangle[r] = hits.tri
        position[r] = pos
        normal[r] = ns
        albedo[r] = alb
        depth[r] = (pos - camera.position) @ camera.forward
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

    # ------------------------------------------------------------------ paths

    def trace_reflections(
        self, gbuffer: GBuffer, sources: list[int], bounce_limit: int
    ) -> ReflectionResult:
        """Mirror-reflection radiance for every G-buffer pixel whose element is in
        ``sources`` (no primary rays: rays start at the G-buffer position / normal /
        view_dir). ``bounce_limit`` is the most reflection rays along one path; a
        reflector hit at the last one reads the environment for its reflected part
        (``bounce_limit`` < 1: no rays, the environment in the mirror direction)."""
        start = time.perf_counter()
        self.last_rays = []
        sources = [int(s) for s in sources]
        pix, src, pos, ns, view = self._source_pixels(gbuffer, sources, None)
        d = view - 2.0 * np.einsum("ij,ij->i", view, ns)[:, None] * ns
        d = _unit(d)
        origins = self._offset(pos, self._tri_normal_or(gbuffer, pix, ns), d)
        return self._paths(pix, src, origins, d, sources, bounce_limit, "reflection", start)

    def trace_refraction(
        self, gbuffer: GBuffer, bounce_limit: int, elements: list[int] | None = None
    ) -> ReflectionResult:
        """Transmitted radiance behind transmissive surfaces (material opacity < 1) seen
        in the G-buffer, optionally only those of ``elements``. The first ray refracts at
        the G-buffer surface (Snell, ior of the material; total internal reflection
        reflects), then follows the same bounce loop as reflections. The result is the
        radiance arriving through the surface, before mixing with (1 - opacity).
        Does no work at all (empty result, 0 rays) when nothing in the scene is
        transmissive. Records are per element id."""
        start = time.perf_counter()
        self.last_rays = []
        if not self._transmission:
            return ReflectionResult(np.zeros(0, np.int64), np.zeros((0, 3), np.float32), [], 0, 0.0)
        tri_flat = gbuffer.triangle_id.reshape(-1)
        hit = tri_flat >= 0
        clear = np.zeros(len(tri_flat), dtype=bool)
        clear[hit] = self._opacity[self._tri_material[tri_flat[hit]]] < 1.0
        elem_flat = gbuffer.element_id.reshape(-1)
        if elements is not None:
            clear &= np.isin(elem_flat, np.asarray(elements, dtype=np.int64))
        sources = sorted({int(e) for e in np.unique(elem_flat[clear])})
        pix, src, pos, ns, view = self._source_pixels(gbuffer, sources, clear)
        tri = tri_flat[pix].astype(np.int64)
        ng_raw = self._tri_normal[tri]
        d = _refract(view, ns, ng_raw, self._ior[self._tri_material[tri]])
        origins = self._offset(pos, ng_raw, d)
        return self._paths(pix, src, origins, d, sources, bounce_limit, "refraction", start)

    def _source_pixels(self, gbuffer: GBuffer, sources: list[int], mask):
        """Pixels to start paths from: flat indices (n,), source index into ``sources``
        (n,), snapped positions (n, 3) float64, unit shading normals facing the viewer
        (n, 3) float64, unit view directions (n, 3) float64."""
        elem = gbuffer.element_id.reshape(-1)
        if mask is None:
            mask = np.isin(elem, np.asarray(sources, dtype=np.int64)) & (elem >= 0)
        pix = np.flatnonzero(mask)
        lookup = {s: i for i, s in enumerate(sources)}
        table = np.full(max(sources, default=-1) + 2, -1, np.int64)
        for s, i in lookup.items():
            if s >= 0:
                table[s] = i
        src = table[elem[pix]]
        tri = gbuffer.triangle_id.reshape(-1)[pix].astype(np.int64)
        pos = self._snap_to_triangles(gbuffer.position.reshape(-1, 3)[pix], tri)
        view = _unit(gbuffer.view_dir.reshape(-1, 3)[pix].astype(np.float64))
        ns = _unit(gbuffer.normal.reshape(-1, 3)[pix].astype(np.float64))
        ns = np.where((np.einsum("ij,ij->i", ns, view) > 0)[:, None], -ns, ns)
        return pix, src, pos, ns, view

    def _tri_normal_or(self, gbuffer: GBuffer, pix: np.ndarray, fallback: np.ndarray):
        """Geometric normals (n, 3) of the pixels' triangles (shading normal where the
        G-buffer has no triangle id)."""
        tri = gbuffer.triangle_id.reshape(-1)[pix].astype(np.int64)
        return np.where((tri >= 0)[:, None], self._tri_normal[np.maximum(tri, 0)], fallback)

    def _offset(self, positions, normals, dirs):
        """Origins moved off the surface by ``offset_epsilon`` along ``normals``, on the
        side the outgoing ``dirs`` leave to."""
        side = np.where(np.einsum("ij,ij->i", dirs, normals) >= 0, 1.0, -1.0)
        return positions + (side * self.offset_epsilon(positions))[:, None] * normals

    def _paths(self, pix, src, origins, dirs, sources, bounce_limit, first_kind, start):
        """The bounce loop. pix (n,) flat pixel per starting ray, src (n,) source index,
        origins (n, 3) float64 already offset, dirs (n, 3) unit. Returns the result."""
        lights = self.scene.lights
        n_pix, n_src = len(pix), len(sources)
        radiance = np.zeros((n_pix, 3))
        chain_pix = np.zeros(n_pix, np.int64)  # reflector hits along the longest path
        rays_src = np.zeros(n_src, np.int64)
        hit_pairs: list[np.ndarray] = []  # keys source * E + element of reflector hits
        n_elem = max(len(self.scene.elements), 1)
        # Active ray state (k rays): pixel slot, source, origin, dir, weight, chain, kind.
        slot = np.arange(n_pix)
        r_src = src
        weight = np.ones(n_pix)
        chain = np.zeros(n_pix, np.int64)
        kinds = np.full(n_pix, first_kind == "refraction")  # True = refraction ray
        if bounce_limit < 1:
            radiance += shading.environment_radiance(lights, dirs)
            slot = slot[:0]
        for depth in range(max(bounce_limit, 0)):
            if len(slot) == 0:
                break
            n_refr = int(kinds.sum())
            self.rays_cast["refraction"] += n_refr
            self.rays_cast["reflection"] += len(slot) - n_refr
            rays_src += np.bincount(r_src, minlength=n_src)
            hits = self._intersect(origins, dirs)
            miss = np.ones(len(slot), dtype=bool)
            miss[hits.ray] = False
            if miss.any():
                env = shading.environment_radiance(lights, dirs[miss])
                _accumulate(radiance, slot[miss], weight[miss, None] * env)
            r = hits.ray
            if len(r) == 0:
                break
            d_in = dirs[r]
            pos, ng, ns, albedo, emissive = self._surface(hits.tri, hits.u, hits.v, d_in)
            vis, shadow_rays = self._shadow(pos, ng, ns)
            rays_src += np.bincount(r_src[r], weights=shadow_rays, minlength=n_src).astype(np.int64)
            local = shading.shade_local(pos, ns, albedo, d_in, emissive, lights, vis)
            elem = self._tri_element[hits.tri]
            refl = self._is_reflector[elem]
            f = np.where(refl, self._reflectivity[elem], 0.0)
            if self._transmission:
                mat = self._tri_material[hits.tri]
                alpha = self._opacity[mat]
            else:
                alpha = np.ones(len(r))
            w = weight[r]
            _accumulate(radiance, slot[r], (w * alpha * (1.0 - f))[:, None] * local)
            ch = chain[r] + refl
            np.maximum.at(chain_pix, slot[r], ch)
            if refl.any():
                hit_pairs.append(r_src[r][refl] * n_elem + elem[refl])
            # Children: reflected rays (weight w α F), refracted rays (weight w (1 - α)).
            d_refl = _unit(d_in - 2.0 * np.einsum("ij,ij->i", d_in, ns)[:, None] * ns)
            w_refl = w * alpha * f
            go_refl = w_refl > 0
            child_dirs = [d_refl[go_refl]]
            child_idx = [np.flatnonzero(go_refl)]
            child_w = [w_refl[go_refl]]
            child_kind = [np.zeros(int(go_refl.sum()), dtype=bool)]
            if self._transmission:
                w_refr = w * (1.0 - alpha)
                go_refr = w_refr > 0
                if go_refr.any():
                    gi = np.flatnonzero(go_refr)
                    tri_g = hits.tri[gi]
                    d_refr = _refract(d_in[gi], ns[gi], self._tri_normal[tri_g], self._ior[mat[gi]])
                    child_dirs.append(d_refr)
                    child_idx.append(gi)
                    child_w.append(w_refr[gi])
                    child_kind.append(np.ones(len(gi), dtype=bool))
            c_dir = np.concatenate(child_dirs)
            c_idx = np.concatenate(child_idx)
            c_w = np.concatenate(child_w)
            if depth + 1 >= bounce_limit:
                if len(c_idx):
                    env = shading.environment_radiance(lights, c_dir)
                    _accumulate(radiance, slot[r][c_idx], c_w[:, None] * env)
                break
            origins = self._offset(pos[c_idx], ng[c_idx], c_dir)
            dirs = c_dir
            slot = slot[r][c_idx]
            r_src = r_src[r][c_idx]
            weight = c_w
            chain = ch[c_idx]
            kinds = np.concatenate(child_kind)
        seconds = time.perf_counter() - start
        total = int(rays_src.sum())
        counts: dict[tuple[int, int], int] = {}
        if hit_pairs:
            keys, cnt = np.unique(np.concatenate(hit_pairs), return_counts=True)
            counts = {
                (int(k // n_elem), int(k % n_elem)): int(c) for k, c in zip(keys, cnt, strict=True)
            }
        pixels_src = np.bincount(src, minlength=n_src) if n_src else np.zeros(0, np.int64)
        chain_sum = np.bincount(src, weights=chain_pix, minlength=n_src) if n_src else []
        chain_max = np.zeros(n_src, np.int64)
        if n_pix:
            np.maximum.at(chain_max, src, chain_pix)
        records = []
        for i, s in enumerate(sources):
            hits_i = {e: c for (si, e), c in counts.items() if si == i}
            records.append(
                TraceRecord(
                    source=s,
                    pixels=int(pixels_src[i]),
                    rays=int(rays_src[i]),
                    hits=hits_i,
                    max_reflector_bounces=int(min(chain_max[i], max(bounce_limit, 0))),
                    mean_reflector_bounces=float(chain_sum[i] / max(pixels_src[i], 1)),
                    seconds=seconds * float(rays_src[i]) / total if total else 0.0,
                )
            )
        return ReflectionResult(
            pixel_index=pix.astype(np.int64),
            radiance=radiance.astype(np.float32),
            records=records,
            rays=total,
            seconds=seconds,
        )


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of (n, 3) scaled to unit length (zero rows stay zero instead of NaN)."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def _accumulate(target: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
    """target[index] += values, with repeated indices summed (refraction splits paths)."""
    for c in range(3):
        target[:, c] += np.bincount(index, weights=values[:, c], minlength=target.shape[0])


def _refract(d: np.ndarray, ns: np.ndarray, ng_raw: np.ndarray, ior: np.ndarray) -> np.ndarray:
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
    return _unit(np.where(tir[:, None], r, t))
