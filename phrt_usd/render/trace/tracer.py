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

``local`` is ``shading.shade_local`` with ray-traced shadows (evaluated after the loop,
see below). ``reflected``/``refracted``
continue as new rays while the depth is below the bounce limit, and read the environment
at the limit. Refraction (Snell's law with the material's ior, total internal reflection
→ mirror reflection) is part of the same bounce loop; it runs only when
``scene.materials.has_transmission``, otherwise α = 1 everywhere and no refraction work is
done. Shadow rays treat transmissive surfaces as opaque.

Robustness: G-buffer positions (possibly from a depth buffer) are first projected onto
their triangle's plane, then every ray origin is offset by ``RAY_OFFSET_*`` along the
geometric normal, on the side the ray leaves to. Where a hit's local term has no weight
(F = 1 mirrors, α = 0 glass) neither shading nor shadow rays are computed, and shadow
rays go only to lights in front of the shading normal and, for LocalLights, within
their range (``shading.light_ranges``): all (point, light) pairs of a batch are chosen
on (n, L) arrays and built into one float32 Embree batch. Shading normals follow the
rasterizer's rule (``_surface``), so ``rt`` and the raster G-buffer agree at grazing
pixels.

Threads: embreex releases the GIL inside ``run``, so batches of ≥ ``PARALLEL_MIN_RAYS``
rays are split over a two-thread pool (measured on this 2-core machine: 76.8k rays on an
82k-triangle mesh, 8.3 → 13.6 Mray/s; smaller batches gain nothing). Local shading of
a call's hits (numpy and shadow rays together) is split the same way from
``PARALLEL_MIN_SHADE_RAYS`` shadow rays on (numpy releases the GIL on large arrays too).

Fixed cost per call: hybrid batches are small (farm: 50-5,000 rays), so the bounce loop
only follows paths; environment lookups, shadow rays and local shading of all bounces are
gathered and evaluated once per call (``Tracer._gather``), reflector pixels are found once
per G-buffer, light tables are cached per ``Lights`` object.

Geometry: two BVHs, static and animated triangles (``Element.animated``); when only
animated elements moved, ``update_geometry`` rebuilds just the small animated BVH (farm:
~0.3 ms instead of a 35-90 ms rebuild of all 54k triangles). Queries ask both.

Limits: mirror reflections only (roughness is ignored), no refit (embreex has none: the
animated BVH is rebuilt when it moves), shadows are hard (light size ignored).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from embreex import rtcore as rtc
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from phrt_usd.model.frame import GBuffer, ReflectionResult, TraceRecord
from phrt_usd.model.scene import NO_HIT, CameraFrame, Lights, LocalLight, Scene
from phrt_usd.render import shading

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

#: Local shading (numpy + shadow rays) of hits is split over the pool only from this many
#: shadow rays (points x lights) on: measured on the sewer (13 lights, 2 cores), 10.6k
#: rays take 2.2 ms split vs 1.9 ms on one thread, 349k rays 49 ms vs 63 ms.
PARALLEL_MIN_SHADE_RAYS = 32768

#: Interpolated shading normals shorter than this are degenerate (the rasterizer's
#: threshold, so both modes pick the geometric normal at the same pixels).
_MIN_NORMAL_LENGTH = 1e-6

#: Embree ray length for "infinite" rays (DistantLight shadow rays); finite in float32.
_FAR = 1e30


@dataclass
class _Hits:
    """Intersections of a batch of rays that hit something (m of the n rays).

    ray : (m,) int64 index of the ray in its batch; tri : (m,) int64 triangle ids;
    u, v : (m,) float32 Embree barycentrics (p = v0 + u (v1 - v0) + v (v2 - v0));
    miss : (n - m,) int64 indices of the rays that hit nothing."""

    ray: np.ndarray
    tri: np.ndarray
    u: np.ndarray
    v: np.ndarray
    miss: np.ndarray


class Tracer:
    """Ray tracing against one ``Scene``.

    Geometry lives in two Embree BVHs: one of the *static* triangles (elements with
    ``Element.animated == False``), built once per topology, and one of the *animated*
    triangles, rebuilt by ``update_geometry`` when they move (embreex has neither refit
    nor instancing, and a committed scene cannot be edited, so the split is the cheap
    way to move a few hundred triangles among 50k). A stage without animated elements
    has only the static BVH and casts one Embree query per batch. Every query asks the
    static BVH first and then the animated one with ``tfar`` = the static hit distance,
    so the second answers only hits that are nearer (see ``_cast``); Embree's per-BVH
    ``primID`` is mapped back to global triangle ids.

    Internally every position is *render-relative*: float64 metres relative to
    ``scene.origin`` (world = relative + origin). Public arguments and results are world.

    rays_cast : cumulative counters by kind ("primary", "reflection", "refraction",
                "shadow"); ``reset_counters()`` zeroes them.
    record_rays : when True, every ray batch of the latest public call is kept in
                  ``last_rays`` (query, origins f32, directions f32, tfar f32 or None),
                  for ``replay_raw`` to compare with raw embreex on the same rays.
    last_build_seconds : wall time of the latest ``update_geometry``.
    last_build_full : True when it rebuilt the static BVH too (False: animated only).
    """

    def __init__(self, scene: Scene, threads: int = 2) -> None:
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self.rays_cast: dict[str, int] = {}
        self.reset_counters()
        self.record_rays = False
        self.last_rays: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.last_build_seconds = 0.0
        self.last_build_full = True
        self._device = rtc.EmbreeDevice()  # shared by this tracer's BVHs
        self.scene: Scene | None = None
        self.update_geometry(scene)

    # ------------------------------------------------------------------ set-up

    def reset_counters(self) -> None:
        self.rays_cast = {"primary": 0, "reflection": 0, "refraction": 0, "shadow": 0}

    def update_geometry(self, scene: Scene) -> None:
        """Bring the tracer to ``scene``'s current geometry (after animated prims moved).

        Cheap path — the same ``Scene`` object with the same topology, origin and
        ``animated`` flags, where only vertices / triangles of animated elements changed:
        the animated triangles' tables are refreshed and their small BVH rebuilt; the
        static BVH is kept (farm: ~1 ms instead of a 35-90 ms full build). Anything else
        (a new scene, a static vertex or triangle changed): full build of both BVHs.
        Static elements' shading normals and albedo are taken as fixed between full
        builds (materials are not animated). Cost in ``last_build_seconds``."""
        start = time.perf_counter()
        moved = self._animated_change(scene)
        if moved is None:
            self._build(scene)
        elif moved:
            self._refresh_animated(scene)
        self.last_build_full = moved is None
        self.last_build_seconds = time.perf_counter() - start

    def _animated_change(self, scene: Scene) -> bool | None:
        """None when ``scene`` needs a full build, else whether any animated triangle
        changed since the last build / refresh. Compares against the tracer's own copies
        of vertices and triangles (exact, float64 / int64)."""
        if scene is not self.scene:
            return None
        geo = scene.geometry
        if (
            geo.vertices.shape != self._vertices.shape
            or geo.triangles.shape != self._triangles.shape
            or not np.array_equal(np.asarray(scene.origin, np.float64), self.origin)
            or [e.animated for e in scene.elements] != self._element_animated
        ):
            return None
        # Flat indices of changed coordinates // 3 = changed rows (few when only animated
        # elements moved; a per-row reduction over the length-3 axis would be slower).
        vert = np.flatnonzero(geo.vertices.reshape(-1) != self._vertices.reshape(-1)) // 3
        tri = np.flatnonzero(geo.triangles.reshape(-1) != self._triangles.reshape(-1)) // 3
        if not (self._vertex_animated[vert].all() and self._tri_animated[tri].all()):
            return None
        # Animated normals can change without moving a vertex (authored time samples).
        rows = self._dynamic_ids
        if len(vert) or len(tri):
            return True
        return not np.array_equal(
            np.asarray(geo.corner_normals[rows], np.float32), self._tri_normals[rows]
        )

    def _build(self, scene: Scene) -> None:
        """Full build: per-triangle tables, both BVHs, the static bounds."""
        self.scene = scene
        geo = scene.geometry
        self.origin = np.asarray(scene.origin, dtype=np.float64).copy()
        self._vertices = np.array(geo.vertices, dtype=np.float64).reshape(-1, 3)
        self._triangles = np.array(geo.triangles, dtype=np.int64).reshape(-1, 3)
        n_tri = len(self._triangles)
        self._tri_element = np.asarray(geo.tri_element, dtype=np.int64)
        self._tri_material = np.asarray(geo.tri_material, dtype=np.int64)
        self._element_animated = [e.animated for e in scene.elements]
        animated = np.array(self._element_animated + [False], dtype=bool)
        self._tri_animated = animated[self._tri_element] if n_tri else np.zeros(0, bool)
        self._vertex_animated = np.zeros(len(self._vertices), dtype=bool)
        self._vertex_animated[self._triangles[self._tri_animated].reshape(-1)] = True
        # Packed per-triangle tables, so one fancy-index gather fetches all a hit needs.
        # _tri_geom (T, 4, 3) float64 render-relative metres: v0, v1 - v0, v2 - v0, unit
        # front-face normal; _tri_normals, _tri_albedo (T, 3, 3) float32: corner shading
        # normals, corner albedo. Filled by _fill_tables.
        self._tri_geom = np.empty((n_tri, 4, 3), np.float64)
        self._tri_normals = np.empty((n_tri, 3, 3), np.float32)
        self._tri_albedo = np.empty((n_tri, 3, 3), np.float32)
        self._fill_tables(geo, slice(None))
        mats = scene.materials
        reflectivity = np.clip(scene.reflectivity.astype(np.float64), 0.0, 1.0)
        is_reflector = np.array([e.is_reflector for e in scene.elements], dtype=bool)
        self._element_reflector = is_reflector
        self._reflector_ids = np.flatnonzero(is_reflector)
        self._pixel_cache: tuple | None = None
        # Per triangle: reflector flag and F (0 for non-reflectors).
        self._tri_reflector = is_reflector[self._tri_element] if n_tri else np.zeros(0, bool)
        self._tri_f = np.where(self._tri_reflector, reflectivity[self._tri_element], 0.0)
        self._transmission = mats.has_transmission
        self._opacity = np.clip(np.asarray(mats.opacity, dtype=np.float64), 0.0, 1.0)
        # ior ≤ 0 is meaningless; clamp so Snell's law stays finite.
        self._ior = np.maximum(np.asarray(mats.ior, dtype=np.float64), 1e-3)
        emissive = np.asarray(mats.emissive, dtype=np.float32).reshape(-1, 3)
        self._has_emission = bool(np.any(emissive != 0))
        self._emissive = emissive
        self._textures = list(mats.textures) if geo.corner_uv is not None else []
        self._lights_key: tuple | None = None
        self._light_cache: tuple | None = None
        # Global ids of each BVH's triangles, with a trailing NO_HIT so that
        # ``np.take(ids, primID)`` maps Embree's miss (-1) to NO_HIT too. The static map
        # is None when every triangle is static (Embree's ids are the global ones).
        static_ids = np.flatnonzero(~self._tri_animated)
        self._dynamic_ids = np.flatnonzero(self._tri_animated)
        every_static = len(static_ids) == n_tri
        self._static_map = None if every_static else np.append(static_ids, NO_HIT)
        self._dynamic_map = np.append(self._dynamic_ids, NO_HIT)
        rel = self._vertices - self.origin
        self._static = self._new_bvh(
            np.ascontiguousarray(rel, dtype=np.float32),
            np.ascontiguousarray(self._triangles[static_ids], dtype=np.int32),
        )
        # Bounds of everything that never moves between full builds (vertices of no
        # animated triangle), for the offset epsilon's scene extent.
        still = rel[~self._vertex_animated]
        self._static_bounds = (still.min(axis=0), still.max(axis=0)) if len(still) else None
        self._dynamic = None
        self._refresh_animated(scene)

    def _refresh_animated(self, scene: Scene) -> None:
        """Animated triangles' tables, vertex copies and BVH from ``scene``'s current
        geometry; the scene extent from the static bounds and the animated vertices."""
        geo = scene.geometry
        rows = self._dynamic_ids
        moved = np.flatnonzero(self._vertex_animated)
        self._vertices[moved] = geo.vertices[moved]
        self._triangles[rows] = geo.triangles[rows]
        self._fill_tables(geo, rows)
        # A triangle soup (D, 3, 3): no index remapping for a few hundred triangles.
        soup = self._vertices[self._triangles[rows]] - self.origin
        self._dynamic = self._new_bvh(np.ascontiguousarray(soup, dtype=np.float32), None)
        # Scene.extent, without a pass over every vertex: the union of the static bounds
        # and the animated vertices' bounds (same vertex set, so the same value).
        boxes = [] if self._static_bounds is None else list(self._static_bounds)
        if len(moved):
            rel = self._vertices[moved] - self.origin
            boxes += [rel.min(axis=0), rel.max(axis=0)]
        if boxes:
            lo, hi = np.min(boxes, axis=0), np.max(boxes, axis=0)
            self.extent = float(max(np.linalg.norm(hi - lo), 1e-12))
        else:
            self.extent = 1.0  # Scene.extent of an empty scene

    def _fill_tables(self, geo, rows) -> None:
        """Rows ``rows`` (index array or slice) of ``_tri_geom`` / ``_tri_normals`` /
        ``_tri_albedo`` from ``self._vertices``, ``self._triangles`` and ``geo``'s corner
        data."""
        tris = self._triangles[rows]
        n = len(tris)
        if n == 0:
            return
        verts = self._vertices
        v0 = verts[tris[:, 0]] - self.origin
        e1 = verts[tris[:, 1]] - verts[tris[:, 0]]
        e2 = verts[tris[:, 2]] - verts[tris[:, 0]]
        normal = np.cross(e1, e2)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        # Degenerate triangles (never hit by Embree) get +Y.
        normal = np.where(length > 0, normal / np.where(length > 0, length, 1.0), (0.0, 1.0, 0.0))
        self._tri_geom[rows] = np.stack([v0, e1, e2, normal], axis=1)
        self._tri_normals[rows] = np.asarray(geo.corner_normals[rows], np.float32).reshape(n, 3, 3)
        self._tri_albedo[rows] = np.asarray(geo.corner_albedo[rows], np.float32).reshape(n, 3, 3)

    def _new_bvh(self, vertices: np.ndarray, triangles: np.ndarray | None):
        """A committed embreex scene of one triangle mesh (float32 render-relative
        vertices (V, 3) + int32 triangles (T, 3), or a (T, 3, 3) soup with ``triangles``
        None), or None when it has no triangle."""
        count = len(vertices) if triangles is None else len(triangles)
        if count == 0:
            return None
        bvh = rtcs.EmbreeScene(self._device)
        if triangles is None:
            TriangleMesh(bvh, vertices)
        else:
            TriangleMesh(bvh, vertices, triangles)
        # Commit now (embreex commits lazily on the first run) so the build is timed
        # here and never inside a trace budget.
        probe = np.zeros((1, 3), dtype=np.float32)
        bvh.run(probe, probe + np.float32(1.0))
        return bvh

    def _relative_lights(self) -> Lights:
        """The scene's lights with LocalLight positions render-relative (what shading
        sees, since it is handed render-relative positions). Cached while the scene's
        ``Lights`` object and its LocalLight objects stay the same."""
        lights = self.scene.lights
        # Identity, not equality (dataclasses of arrays); holding the objects keeps
        # their ids from being reused.
        key = (lights, *lights.local)
        cached = self._lights_key
        if (
            cached is None
            or len(cached) != len(key)
            or any(a is not b for a, b in zip(cached, key, strict=True))
        ):
            origin = self.origin
            local = [
                LocalLight(np.asarray(li.position, np.float64) - origin, li.radiance, li.radius)
                for li in lights.local
            ]
            self._relative = Lights(distant=lights.distant, local=local, dome=lights.dome)
            self._lights_key = key
        return self._relative

    def _light_arrays(self, lights: Lights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(D, 3) unit DistantLight directions, (P, 3) LocalLight positions (both
        float64, as given) and (P,) LocalLight ranges in metres
        (``shading.light_ranges``) of ``lights``; cached for the latest ``Lights``
        object (the tracer's render-relative lights are one object per scene)."""
        cached = self._light_cache
        if cached is not None and cached[0] is lights:
            return cached[1]
        dirs = np.array([li.direction for li in lights.distant], np.float64).reshape(-1, 3)
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
        pos = np.array([li.position for li in lights.local], np.float64).reshape(-1, 3)
        ranges = shading.light_ranges(lights)[len(lights.distant) :]
        self._light_cache = (lights, (dirs, pos, ranges))
        return dirs, pos, ranges

    # ------------------------------------------------------------------ Embree calls

    def _run(self, query: str, origins: np.ndarray, dirs: np.ndarray, tfar=None, threads=None):
        """One ray batch. origins (n, 3) float64 render-relative metres, dirs (n, 3)
        unit, tfar (n,) metres or None; ``threads`` (default the tracer's) 1 inside a
        pool worker. Returns (primID, u, v) with global triangle ids
        (INTERSECT) or (n,) bool occluded. This is the only cast of ray data to float32
        (a no-op for arrays already float32 and contiguous)."""
        o32 = np.ascontiguousarray(origins, dtype=np.float32)
        d32 = np.ascontiguousarray(dirs, dtype=np.float32)
        t32 = None if tfar is None else np.ascontiguousarray(tfar, np.float32)
        if t32 is not None and tfar.dtype != np.float32:
            t32 = np.minimum(t32, np.float32(_FAR))  # float64 inf / huge -> finite
        if self.record_rays:
            self.last_rays.append((query, o32, d32, t32))
        return self._run_raw(query, o32, d32, t32, self.threads if threads is None else threads)

    def _run_raw(self, query, o32, d32, t32, threads, merge: bool = True):
        """Both BVHs on float32 arrays, split into ``threads`` chunks over the pool when
        the batch is large enough (embreex releases the GIL inside ``run``). ``merge``
        False: only the embreex calls, no answer (``replay_raw``)."""
        n = o32.shape[0]
        intersect = query == "INTERSECT"
        if n == 0 or (self._static is None and self._dynamic is None):
            if not merge:
                return None
            if not intersect:
                return np.zeros(n, dtype=bool)
            return np.full(n, NO_HIT, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32)
        if threads > 1 and self._pool is not None and n >= PARALLEL_MIN_RAYS:
            bounds = np.linspace(0, n, min(threads, self.threads) + 1).astype(int)
            futures = [
                self._pool.submit(
                    self._cast,
                    query,
                    o32[a:b],
                    d32[a:b],
                    None if t32 is None else t32[a:b],
                    merge,
                )
                for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            ]
            parts = [f.result() for f in futures]
            if not merge:
                return None
            if intersect:
                return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))
            return np.concatenate(parts)
        return self._cast(query, o32, d32, t32, merge)

    def _cast(self, query, o32, d32, t32, merge: bool):
        """The embreex calls for one chunk of rays, static BVH then animated BVH.

        INTERSECT: the animated BVH gets the static hits' distances as ``tfar`` (embreex
        writes each hit's t into ``dists``), so it reports only nearer hits, which then
        replace the static ones. OCCLUDED: occluded if either BVH says so. Returns
        (primID (n,) int32 / int64 global triangle ids or NO_HIT, u, v (n,) float32) or
        (n,) bool occluded; None when not ``merge``."""
        static, dynamic = self._static, self._dynamic
        if query != "INTERSECT":
            # OCCLUDED reads but never writes ``dists``: both calls share ``t32``.
            a = None if static is None else static.run(o32, d32, t32, query)
            b = None if dynamic is None else dynamic.run(o32, d32, t32, query)
            if not merge:
                return None
            if b is None:
                return a != NO_HIT
            if a is None:
                return b != NO_HIT
            return (a != NO_HIT) | (b != NO_HIT)
        # INTERSECT writes the hit distance into ``dists``: never the caller's array.
        tfar = None if t32 is None else t32.copy()
        near = None
        if static is not None:
            near = static.run(o32, d32, tfar, query, 1)
            tfar = near["tfar"]
        far = None if dynamic is None else dynamic.run(o32, d32, tfar, query, 1)
        if not merge:
            return None
        if near is not None:
            prim, u, v = near["primID"], near["u"], near["v"]
            if self._static_map is not None:
                prim = np.take(self._static_map, prim)
        if far is not None:
            far_prim = np.take(self._dynamic_map, far["primID"])
            if near is None:
                return far_prim, far["u"], far["v"]
            nearer = far_prim >= 0
            if nearer.any():
                prim = np.where(nearer, far_prim, prim)
                u = np.where(nearer, far["u"], u)
                v = np.where(nearer, far["v"], v)
        return prim, u, v

    def _intersect(self, origins: np.ndarray, dirs: np.ndarray) -> _Hits:
        prim, u, v = self._run("INTERSECT", origins, dirs)
        hit = prim >= 0
        ray = np.flatnonzero(hit)
        every = len(ray) == len(prim)
        return _Hits(
            ray=ray,
            tri=(prim if every else np.take(prim, ray)).astype(np.int64, copy=False),
            u=u if every else np.take(u, ray),
            v=v if every else np.take(v, ray),
            miss=ray[:0] if every else np.flatnonzero(~hit),
        )

    def replay_raw(self, threads: int | None = None) -> tuple[int, float]:
        """Re-run raw embreex on exactly the batches in ``last_rays`` (same float32
        arrays, same splitting rule, ``threads`` defaults to the tracer's). Returns
        (rays, seconds) so a benchmark can compare our throughput with Embree's own.

        "Raw embreex on the same rays" = the same ``EmbreeScene.run`` calls we made, on
        both BVHs (the animated one with the static hits' distances as ``tfar``, as
        ``_cast`` does), without merging the two answers or mapping ids. Rays are
        counted once per batch, not once per BVH."""
        threads = self.threads if threads is None else threads
        start = time.perf_counter()
        rays = 0
        for query, o32, d32, t32 in self.last_rays:
            self._run_raw(query, o32, d32, t32, threads, merge=False)
            rays += o32.shape[0]
        return rays, time.perf_counter() - start

    # ------------------------------------------------------------------ surface data

    def offset_epsilon(self, positions: np.ndarray) -> np.ndarray:
        """(n,) float64 metres: the ray-origin offset at world ``positions`` (n, 3)."""
        return self._epsilon(np.asarray(positions, np.float64) - self.origin)

    def _epsilon(self, rel: np.ndarray) -> np.ndarray:
        """``offset_epsilon`` for render-relative positions (n, 3)."""
        a = np.abs(rel)
        # Column-wise maximum: numpy's reduction over a length-3 inner axis is ~5x slower.
        largest = np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])
        return np.maximum(RAY_OFFSET_ABSOLUTE * self.extent, RAY_OFFSET_RELATIVE * largest)

    def _offset(self, rel: np.ndarray, normals: np.ndarray, dirs: np.ndarray, eps=None):
        """Render-relative origins moved off the surface by the offset epsilon (``eps``
        (n,), computed when None) along ``normals``, on the side ``dirs`` leave to."""
        eps = self._epsilon(rel) if eps is None else eps
        side = np.where(np.einsum("ij,ij->i", dirs, normals) >= 0, eps, -eps)
        return rel + side[:, None] * normals

    def _surface(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, incoming: np.ndarray):
        """Everything shading needs at hits on triangles ``tri`` (m,) with barycentrics u, v:
        render-relative position (m, 3) float64; geometric normal (m, 3) float64 and
        shading normal (m, 3) float32, both facing against ``incoming`` (m, 3); albedo and
        emissive (m, 3) float32 (emissive (3,) zeros when the stage has no emission)."""
        pos, ng, ns = self._surface_geometry(tri, u, v, incoming)
        albedo, emissive = self._surface_colour(tri, u, v)
        return pos, ng, ns, albedo, emissive

    def _surface_geometry(self, tri, u, v, incoming):
        """``_surface``'s position, geometric normal and shading normal (what a path
        needs to continue; colour is looked up later, once per call)."""
        g = np.take(self._tri_geom, tri, axis=0)  # np.take: ~3x faster than g[tri]
        pos = g[:, 0] + u[:, None] * g[:, 1] + v[:, None] * g[:, 2]
        # The rasterizer's rule (gbuffer.Rasterizer._derive), so both modes agree at
        # grazing pixels: the geometric normal faces the incoming ray, the interpolated
        # shading normal is flipped to that same side of the triangle, and where it then
        # still faces along the ray (or is degenerate) the geometric normal replaces it.
        side = np.where(np.einsum("ij,ij->i", g[:, 3], incoming) > 0, -1.0, 1.0)
        ng = g[:, 3] * side[:, None]
        s = np.take(self._tri_normals, tri, axis=0)  # (m, 3, 3) corner normals
        w1 = u.astype(np.float32, copy=False)[:, None]
        w2 = v.astype(np.float32, copy=False)[:, None]
        ns = s[:, 0] * (1.0 - w1 - w2) + s[:, 1] * w1 + s[:, 2] * w2  # float32
        ns *= side.astype(np.float32)[:, None]
        ns_len = np.sqrt(np.einsum("ij,ij->i", ns, ns))
        # ``~(len >= ...)`` also catches a NaN interpolated normal.
        bad = ~(ns_len >= _MIN_NORMAL_LENGTH) | (np.einsum("ij,ij->i", ns, incoming) >= 0.0)
        ns /= np.maximum(ns_len, _MIN_NORMAL_LENGTH)[:, None]
        if bad.any():
            ns[bad] = ng[bad]
        return pos, ng, ns

    def _surface_colour(self, tri, u, v):
        """``_surface``'s albedo (m, 3) float32 (texture lookup where the material has
        one) and emissive ((m, 3) float32, or (3,) zeros without emission)."""
        s = np.take(self._tri_albedo, tri, axis=0)  # (m, 3, 3) corner albedo
        w1 = u.astype(np.float32, copy=False)[:, None]
        w2 = v.astype(np.float32, copy=False)[:, None]
        w0 = 1.0 - w1 - w2
        albedo = s[:, 0] * w0 + s[:, 1] * w1 + s[:, 2] * w2
        mat = np.take(self._tri_material, tri)
        for m_id, texture in enumerate(self._textures):
            if texture is None:
                continue
            sel = np.flatnonzero(mat == m_id)
            if len(sel):
                uv_corner = self.scene.geometry.corner_uv[tri[sel]]
                uv = (
                    uv_corner[:, 0] * w0[sel]
                    + uv_corner[:, 1] * w1[sel]
                    + uv_corner[:, 2] * w2[sel]
                )
                albedo[sel] = shading.sample_texture(texture, uv)
        if self._has_emission:
            emissive = self._emissive[mat]
        else:
            emissive = np.zeros(3, np.float32)
        return albedo, emissive

    def _snap_to_triangles(self, rel: np.ndarray, tri: np.ndarray, fallback: np.ndarray):
        """Project render-relative positions (n, 3) (e.g. from a depth buffer) onto the
        plane of their triangle (n,): removes depth-buffer error before offsetting.
        Returns the positions and the triangles' unit front-face normals (n, 3); rows with
        tri = -1 keep their position and get the ``fallback`` (n, 3) normal."""
        ok = tri >= 0
        every = bool(ok.all())
        g = np.take(self._tri_geom, tri if every else np.where(ok, tri, 0), axis=0)
        normal = g[:, 3] if every else np.where(ok[:, None], g[:, 3], fallback)
        out = np.asarray(rel, dtype=np.float64) - g[:, 0]  # relative to vertex 0
        dist = np.einsum("ij,ij->i", out, normal)
        if not every:
            dist[~ok] = 0.0
        out -= dist[:, None] * normal
        out += g[:, 0]
        return out, normal

    # ------------------------------------------------------------------ shadows

    def _shadow(
        self, rel, offset_normals, shading_normals, lights: Lights, pairs=None, threads=None
    ):
        """(n, L) float32 visibility, (n,) int64 shadow rays cast per point and the lit
        LocalLight pairs (``shading.shade_local``'s ``local_pairs``, or None), for
        render-relative positions ``rel`` (n, 3) and render-relative ``lights``.

        Rays are cast only where they can matter: the light in front of the shading
        normal (elsewhere the Lambert term is 0) and, for LocalLights, the point within
        the light's range (``shading.light_ranges``; beyond it the light contributes 0).
        Such pairs, and pairs outside ``pairs`` ((n, L) bool, None = all), report 0.

        All (point, light) pairs are tested at once on (n, L) arrays (with ``pairs``,
        only the wanted pairs, one by one), then one Embree batch is built in float32
        directly (no per-light passes, no extra copies)."""
        n = rel.shape[0]
        n_distant = len(lights.distant)
        n_lights = n_distant + len(lights.local)
        if not lights.has_direct or n == 0:
            return np.ones((n, n_lights), np.float32), np.zeros(n, np.int64), None
        rel = np.asarray(rel, np.float64)
        ns = np.asarray(shading_normals, np.float32)
        dirs, pos, ranges = self._light_arrays(lights)
        # Facing: n·l > 0. For LocalLights n·(p_L - p) = n·p_L - n·p, with the squared
        # distance |p_L|² - 2 p·p_L + |p|² (render-relative: |p| is at most the scene
        # extent, so the cancellation error stays ~1e-16 extent², far below any range²).
        # Written per column (_columns), not as a BLAS product (see gbuffer._transform).
        if pairs is not None:
            # Only the wanted pairs (e.g. a shadow map's uncertain few per cent): facing
            # and range are tested per pair further down, not on (n, L) arrays.
            want = np.asarray(pairs, dtype=bool).reshape(n, n_lights)
        else:
            want = np.empty((n, n_lights), dtype=bool)
            if n_distant:
                want[:, :n_distant] = _columns(ns, dirs.astype(np.float32)) > 0.0
            if len(pos):
                n_dot_p = np.einsum("ij,ij->i", ns, rel.astype(np.float32))
                want[:, n_distant:] = _columns(ns, pos.astype(np.float32)) > n_dot_p[:, None]
                dist2 = (
                    np.einsum("ij,ij->i", pos, pos)[None, :]
                    - 2.0 * _columns(rel, pos)
                    + np.einsum("ij,ij->i", rel, rel)[:, None]
                )
                want[:, n_distant:] &= dist2 < (ranges**2)[None, :]
        vis = np.zeros((n, n_lights), np.float32)
        # Per pair, float32 is enough: positions are render-relative (|p| <= extent) and
        # the offset epsilon is >= 160 float32 ulps of |p| (RAY_OFFSET_RELATIVE), so the
        # offset survives the rounding; Embree sees float32 anyway.
        rel32 = rel.astype(np.float32)
        ng32 = np.asarray(offset_normals, np.float32)
        eps = self._epsilon(rel).astype(np.float32)
        batches = []  # (point, light, dirs (m, 3), tfar (m,), p (m, 3), eps (m,)) per kind
        local = None
        if n_distant:
            point, light = np.nonzero(want[:, :n_distant])
            d = np.take(dirs.astype(np.float32), light, axis=0)
            if pairs is not None:  # facing (see above), per wanted pair
                front = np.flatnonzero(np.einsum("ij,ij->i", np.take(ns, point, axis=0), d) > 0)
                point, light, d = point[front], light[front], d[front]
            far = np.full(len(point), _FAR, np.float32)
            batches.append((point, light, d, far, np.take(rel32, point, axis=0), eps[point]))
        if len(pos):
            point, light = np.nonzero(want[:, n_distant:])
            # np.take: ~3x faster than fancy indexing for row gathers.
            p = np.take(rel32, point, axis=0)
            e = np.take(eps, point)
            to = np.take(pos.astype(np.float32), light, axis=0)
            to -= p
            if pairs is not None:  # facing and range (see above), per wanted pair
                keep = np.einsum("ij,ij->i", np.take(ns, point, axis=0), to) > 0.0
                keep &= np.einsum("ij,ij->i", to, to) < np.take(ranges**2, light)
                keep = np.flatnonzero(keep)
                point, light, p, e, to = point[keep], light[keep], p[keep], e[keep], to[keep]
            dist = np.sqrt(np.einsum("ij,ij->i", to, to))
            np.maximum(dist, np.float32(shading.MIN_LIGHT_DISTANCE), out=dist)
            to /= dist[:, None]
            local = shading.LightPairs(point, light, to, dist)
            # Stop short of the light by the offset so the light's own position is free.
            tfar = np.maximum(dist - e, np.float32(0.0))
            batches.append((point, light + n_distant, to, tfar, p, e))
        point, light, d, tfar, p, e = (
            np.concatenate(parts) if len(batches) > 1 else parts[0]
            for parts in zip(*batches, strict=True)
        )
        m = len(point)
        if m:
            ng = np.take(ng32, point, axis=0)
            ng *= np.where(np.einsum("ij,ij->i", d, ng) >= 0.0, e, -e)[:, None]
            ng += p  # the offset origins
            occluded = self._run("OCCLUDED", ng, d, tfar, threads)
            vis.reshape(-1)[point * n_lights + light] = ~occluded
            if local is not None:  # the lit LocalLight pairs, for shade_local
                free = np.flatnonzero(~occluded[len(point) - len(local[0]) :])
                local = shading.LightPairs(*(np.take(a, free, axis=0) for a in local[:4]))
        return vis, np.bincount(point, minlength=n).astype(np.int64), local

    def shadow_visibility(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        triangle_ids: np.ndarray | None = None,
        pairs: np.ndarray | None = None,
    ) -> np.ndarray:
        """Ray-traced shadows: (n, L) float32, 1 = lit, light order distant then local.

        positions : (n, 3) float64 world metres; normals : (n, 3) world unit shading
        normals (facing the viewer); triangle_ids : optional (n,) triangle of each point
        (snaps depth-buffer positions onto their triangle first); pairs : optional (n, L)
        bool, the (point, light) pairs wanted (e.g. a shadow map's uncertain ones), the
        others are not traced and report 0. No lights: returns (n, 0) and casts nothing.
        Points facing away from a light, or beyond a LocalLight's range
        (``shading.light_ranges``), get 0 without a ray.
        """
        self.last_rays = []
        rel = np.asarray(positions, dtype=np.float64).reshape(-1, 3) - self.origin
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if triangle_ids is not None:
            tri = np.asarray(triangle_ids, np.int64).reshape(-1)
            rel, _ = self._snap_to_triangles(rel, tri, normals)
        lights = self._relative_lights()
        n, n_lights = len(rel), len(lights.distant) + len(lights.local)
        bounds = self._split(n * max(n_lights, 1), n)
        if bounds is None:
            vis, rays, _ = self._shadow(rel, normals, normals, lights, pairs)
        else:  # numpy and Embree work of each chunk on its own pool thread
            parts = [
                self._pool.submit(
                    self._shadow,
                    rel[lo:hi],
                    normals[lo:hi],
                    normals[lo:hi],
                    lights,
                    None if pairs is None else pairs[lo:hi],
                    1,
                )
                for lo, hi in bounds
            ]
            done = [f.result() for f in parts]
            vis = np.concatenate([d[0] for d in done])
            rays = np.concatenate([d[1] for d in done])
        self.rays_cast["shadow"] += int(rays.sum())
        return vis

    # ------------------------------------------------------------------ primary rays

    def primary_gbuffer(self, camera: CameraFrame, width: int, height: int) -> GBuffer:
        """The ``rt`` mode's G-buffer: primary rays through pixel centres, same field
        definitions as the raster G-buffer (``frame.GBuffer``)."""
        self.last_rays = []
        origins, dirs = camera.pixel_rays(width, height)
        n = origins.shape[0]
        hits = self._intersect(origins - self.origin, dirs)
        self.rays_cast["primary"] += n
        element = np.full(n, NO_HIT, np.int32)
        triangle = np.full(n, NO_HIT, np.int32)
        depth = np.full(n, np.inf, np.float32)
        position = np.zeros((n, 3))
        normal = np.zeros((n, 3), np.float32)
        albedo = np.zeros((n, 3), np.float32)
        r = hits.ray
        rel, _, ns, alb, _ = self._surface(hits.tri, hits.u, hits.v, dirs[r])
        element[r] = self._tri_element[hits.tri]
        triangle[r] = hits.tri
        position[r] = rel + self.origin
        normal[r] = ns
        albedo[r] = alb
        depth[r] = (rel - (camera.position - self.origin)) @ camera.forward
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
        pix, src, tri, rel, ng, ns, view = self._source_pixels(gbuffer, sources, None)
        d = _unit(view - 2.0 * np.einsum("ij,ij->i", view, ns)[:, None] * ns)
        origins = self._offset(rel, ng, d)
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
            empty = np.zeros(0, np.int64)
            return ReflectionResult(empty, np.zeros((0, 3), np.float32), [], 0, 0.0)
        tri_flat = gbuffer.triangle_id.reshape(-1)
        hit = tri_flat >= 0
        clear = np.zeros(len(tri_flat), dtype=bool)
        clear[hit] = self._opacity[self._tri_material[tri_flat[hit]]] < 1.0
        elem_flat = gbuffer.element_id.reshape(-1)
        if elements is not None:
            clear &= np.isin(elem_flat, np.asarray(elements, dtype=np.int64))
        sources = [int(e) for e in np.unique(elem_flat[clear])]
        pix, src, tri, rel, ng_front, ns, view = self._source_pixels(gbuffer, sources, clear)
        d = _refract(view, ns, ng_front, self._ior[self._tri_material[tri]])
        origins = self._offset(rel, ng_front, d)
        return self._paths(pix, src, origins, d, sources, bounce_limit, "refraction", start)

    def _reflector_pixels(self, element_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices (m,) and element ids (m,) of the pixels of ``element_id`` (H, W)
        showing a reflector. Cached for the latest id image (a G-buffer is never
        modified once made; the cache holds the array, so its identity stays unique)."""
        cached = self._pixel_cache
        if cached is not None and cached[0] is element_id:
            return cached[1], cached[2]
        elem = element_id.reshape(-1)
        ids = self._reflector_ids
        if len(ids):
            # A range test first (two cheap compares over the image), the table lookup
            # only on the pixels in the reflector id range.
            cand = np.flatnonzero((elem >= ids[0]) & (elem <= ids[-1]))
            cand_elem = np.take(elem, cand)
            keep = np.flatnonzero(np.take(self._element_reflector, cand_elem))
            cand, cand_elem = np.take(cand, keep), np.take(cand_elem, keep)
        else:
            cand = cand_elem = np.zeros(0, np.int64)
        self._pixel_cache = (element_id, cand, cand_elem)
        return cand, cand_elem

    def _source_pixels(self, gbuffer: GBuffer, sources: list[int], mask):
        """Pixels to start paths from: flat indices (n,), index into ``sources`` (n,),
        triangle ids (n,), snapped render-relative positions (n, 3) float64, unit
        front-face triangle normals (n, 3), unit shading normals facing the viewer (n, 3)
        float64, unit view directions (n, 3) float64."""
        # Element id → index in ``sources`` (-1: not a source); the last slot serves id -1.
        n_elem = len(self.scene.elements)
        table = np.full(max(n_elem, max(sources, default=0) + 1) + 1, -1)
        table[[s for s in sources if s >= 0]] = [i for i, s in enumerate(sources) if s >= 0]
        if mask is None and all(0 <= s < n_elem and self._element_reflector[s] for s in sources):
            # Reflector sources (the renderer's case): look only at the G-buffer's
            # reflector pixels, found once per G-buffer (later rounds reuse them).
            cand, cand_elem = self._reflector_pixels(gbuffer.element_id)
            keep = np.flatnonzero(np.take(table, cand_elem) >= 0)
            pix = np.take(cand, keep)
            src = np.take(table, np.take(cand_elem, keep))
        else:
            elem = gbuffer.element_id.reshape(-1)
            chosen = np.take(table >= 0, elem)
            if mask is not None:
                chosen &= mask
            pix = np.flatnonzero(chosen)
            src = np.take(table, np.take(elem, pix))
        tri = np.take(gbuffer.triangle_id.reshape(-1), pix).astype(np.int64)
        # Directions and normals stay float32 (Embree's precision for directions anyway).
        view = _unit(np.take(gbuffer.view_dir.reshape(-1, 3), pix, axis=0).astype(np.float32))
        ns = _unit(np.take(gbuffer.normal.reshape(-1, 3), pix, axis=0).astype(np.float32))
        ns *= np.where(np.einsum("ij,ij->i", ns, view) > 0, -1.0, 1.0).astype(np.float32)[:, None]
        position = np.take(gbuffer.position.reshape(-1, 3), pix, axis=0) - self.origin
        rel, ng = self._snap_to_triangles(position, tri, ns)
        return pix, src, tri, rel, ng, ns, view

    def _paths(self, pix, src, origins, dirs, sources, bounce_limit, first_kind, start):
        """The bounce loop. pix (n,) flat pixel per starting ray, src (n,) source index,
        origins (n, 3) render-relative float64 already offset, dirs (n, 3) unit.

        The loop only follows paths (intersect, surface geometry, children). What a
        path collects — environment radiance at misses and at the bounce limit, local
        shading (with its shadow rays) at hits — does not steer it, so it is gathered
        over all bounces and evaluated once per call: one environment lookup, one shadow
        batch, one ``shade_local``, one accumulation (fixed per-call cost, not
        per-bounce; hybrid batches are small, 50-5,000 rays)."""
        lights = self._relative_lights()
        n_pix, n_src = len(pix), len(sources)
        split = self._transmission
        chain_pix = np.zeros(n_pix, np.int64)  # reflector hits along the longest path
        hit_keys: list[np.ndarray] = []  # source * E + element, one per reflector hit
        n_elem = max(len(self.scene.elements), 1)
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
            self.rays_cast["refraction"] += n_refr
            self.rays_cast["reflection"] += len(slot) - n_refr
            cast_src.append(r_src)
            hits = self._intersect(origins, dirs)
            r = hits.ray
            m = hits.miss
            if len(m):
                env_parts.append((slot[m], weight[m], np.take(dirs, m, axis=0)))
            if len(r) == 0:
                break
            every = len(r) == len(slot)  # all rays hit: no gathers needed
            d_in = dirs if every else np.take(dirs, r, axis=0)
            rel, ng, ns = self._surface_geometry(hits.tri, hits.u, hits.v, d_in)
            refl = np.take(self._tri_reflector, hits.tri)
            f = np.take(self._tri_f, hits.tri)
            if split:
                mat = self._tri_material[hits.tri]
                alpha = self._opacity[mat]
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
                hit_keys.append(src_r[refl] * n_elem + self._tri_element[hits.tri[refl]])
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
                    d_refr = _refract(
                        d_in[gi], ns[gi], self._tri_geom[tri_g, 3], self._ior[mat[gi]]
                    )
                    c_dir = np.concatenate([c_dir, d_refr.astype(c_dir.dtype)])
                    c_idx = np.concatenate([c_idx, gi])
                    c_w = np.concatenate([c_w, w_refr[gi]])
                    c_refr = np.concatenate([c_refr, np.ones(len(gi), dtype=bool)])
            if depth + 1 >= bounce_limit:
                if len(c_idx):
                    env_parts.append((slot_r[c_idx], c_w, c_dir))
                break
            origins = self._offset(np.take(rel, c_idx, axis=0), np.take(ng, c_idx, axis=0), c_dir)
            dirs = c_dir
            slot = slot_r[c_idx]
            r_src = src_r[c_idx]
            weight = c_w
            chain = ch[c_idx]
            refracted = c_refr
        radiance, rays_src = self._gather(env_parts, shade_parts, cast_src, lights, n_pix, n_src)
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

    def _split(self, work: int, n: int) -> list[tuple[int, int]] | None:
        """(start, stop) chunks of ``n`` points to shade over the pool, or None when
        ``work`` (shadow rays they may cast) is below PARALLEL_MIN_SHADE_RAYS or there
        is no pool."""
        if self._pool is None or work < PARALLEL_MIN_SHADE_RAYS or n < self.threads:
            return None
        edges = np.linspace(0, n, self.threads + 1).astype(int).tolist()
        return list(zip(edges[:-1], edges[1:], strict=True))

    def _shade_points(self, tri, u, v, rel, ng, ns, d_in, lights: Lights, threads=None):
        """Local shading with ray-traced shadows at hits (tri, u, v (m,); rel, ng, ns,
        d_in (m, 3), see ``_surface``): (m, 3) float32 radiance and (m,) int64 shadow
        rays cast per point. Safe to run on the pool with ``threads`` = 1."""
        albedo, emissive = self._surface_colour(tri, u, v)
        vis, shadow_rays, lit_pairs = self._shadow(rel, ng, ns, lights, threads=threads)
        local = shading.shade_local(rel, ns, albedo, d_in, emissive, lights, vis, lit_pairs)
        # The caller updates ``rays_cast`` (a dict ``+=`` from pool threads could race).
        return local, shadow_rays

    def _gather(self, env_parts, shade_parts, cast_src, lights, n_pix, n_src):
        """The deferred part of ``_paths``: environment and local shading of every
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
            n_lights = len(lights.distant) + len(lights.local)
            bounds = self._split(len(slot) * max(n_lights, 1), len(slot))
            if bounds is None:
                local, shadow_rays = self._shade_points(tri, u, v, rel, ng, ns, d_in, lights)
            else:
                # Large batches (the sewer: 13 lights, ~300k shadow rays): the whole
                # shading, numpy included, runs in chunks on the pool (numpy and embreex
                # release the GIL), each chunk's Embree batch on its own thread.
                parts = [
                    self._pool.submit(
                        self._shade_points,
                        *(a[lo:hi] for a in (tri, u, v, rel, ng, ns, d_in)),
                        lights,
                        1,
                    )
                    for lo, hi in bounds
                ]
                done = [f.result() for f in parts]
                local = np.concatenate([d[0] for d in done])
                shadow_rays = np.concatenate([d[1] for d in done])
            if lights.has_direct:
                rays_src += np.bincount(src, weights=shadow_rays, minlength=n_src).astype(np.int64)
                self.rays_cast["shadow"] += int(shadow_rays.sum())
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


def _columns(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(n, k) = v (n, 3) @ m (k, 3).T, written per coordinate: numpy hands such skinny
    products to the multithreaded BLAS, whose threads then compete with Embree's."""
    return v[:, 0:1] * m[:, 0][None] + v[:, 1:2] * m[:, 1][None] + v[:, 2:3] * m[:, 2][None]


def _cat(parts) -> np.ndarray:
    """np.concatenate without a copy for a single part."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _bincount(parts: list[np.ndarray], weights, size: int) -> np.ndarray:
    """np.bincount over concatenated index arrays ``parts`` (empty list: zeros)."""
    if not parts:
        return np.zeros(size, np.int64)
    return np.bincount(_cat(parts), weights=weights, minlength=size)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of (n, 3) scaled to unit length (zero rows stay zero instead of NaN)."""
    length = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    return v / np.where(length > 0, length, 1.0)


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
