"""The tracer's geometry: Embree BVHs of a ``Scene``, kept current, and the float32 boundary.

``Bvh`` owns two Embree BVHs, static and animated triangles (``Element.animated``), and
the per-triangle surface table (``model.surface.TriangleTable``). ``update`` compares
the scene's geometry version with the one it was brought to (``Scene.versions``; no
array is compared) and decides between nothing, a refresh of the elements that changed
since (their table rows and vertex copies) with a rebuild of the small animated BVH
(farm: ~0.3 ms), and a full build (35-90 ms for the farm's 54k triangles). Queries ask
both BVHs. embreex has neither refit nor instancing, and a committed scene cannot be
edited, so the split is the cheap way to move a few hundred triangles among 50k.

``Float32Boundary`` is the one place where float64 world metres meet Embree's float32
(cf. trimesh's ``ray_pyembree._EmbreeWrap``): positions are taken relative to
``Scene.origin`` in float64 ("rel"), cast to float32 only at the Embree call or where
the compiled offset writes a ray's origin (``offset_rays``, ``trace_kernels``), and ray
origins are offset off their surface by an epsilon that survives that cast.

The opt-in ray log (``Bvh.record_rays`` / ``last_rays`` / ``replay_raw``) keeps the exact
float32 batches given to Embree, so benchmarks can time raw embreex on the same rays.

Threads: embreex releases the GIL inside ``run``, so batches of ≥ ``PARALLEL_MIN_RAYS``
rays are split over the caller's thread pool (measured on this 2-core machine: 76.8k
rays on an 82k-triangle mesh, 8.3 Mray/s on one thread, 13.6 on two; smaller batches
gain nothing).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from embreex import rtcore as rtc
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from phrt_usd import kernels, progress
from phrt_usd.model.scene import NO_HIT, ElementTriangles, Scene
from phrt_usd.model.surface import TriangleTable
from phrt_usd.small_pages import small_pages

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
trace_kernels = kernels.load("phrt_usd.engine.trace.trace_kernels")

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
FAR = 1e30

#: ``answers``' animated part without an animated BVH, and its static map when Embree's
#: static ids are the global ones.
NO_ANIMATED = (np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, np.float32))
GLOBAL_IDS = np.zeros(0, np.int64)


class Float32Boundary:
    """Render-relative float64 on our side, float32 on Embree's.

    The rule here has a compiled form for the per-ray loops (``trace_kernels``: the
    offset from ``offset_factors``, the float32 origins written in the same pass); the
    numpy methods stay for the rest of the tracer and as the tests' reference.

    origin : (3,) float64 world metres (``Scene.origin``); rel = world - origin.
    extent : the scene's diagonal in metres (kept by ``Bvh``), for the offset epsilon.
    """

    def __init__(self, origin: np.ndarray) -> None:
        self.origin = np.asarray(origin, dtype=np.float64).copy()
        self.extent = 1.0  # Scene.extent of an empty scene

    def relative(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) float64 rel metres of world ``points`` (n, 3)."""
        return np.asarray(points, dtype=np.float64) - self.origin

    def vertices(self, points: np.ndarray) -> np.ndarray:
        """Contiguous float32 rel coordinates of world ``points`` (..., 3), for Embree."""
        return np.ascontiguousarray(points - self.origin, dtype=np.float32)

    @staticmethod
    def rays(origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None):
        """The cast of one ray batch: rel origins (n, 3), unit dirs (n, 3), tfar (n,)
        metres or None → contiguous float32 arrays (a no-op for arrays that already
        are); float64 inf / huge tfar become ``FAR``."""
        o32 = np.ascontiguousarray(origins, dtype=np.float32)
        d32 = np.ascontiguousarray(dirs, dtype=np.float32)
        t32 = None if tfar is None else np.ascontiguousarray(tfar, np.float32)
        if t32 is not None and tfar.dtype != np.float32:
            t32 = np.minimum(t32, np.float32(FAR))  # float64 inf / huge -> finite
        return o32, d32, t32

    def epsilon(self, rel: np.ndarray) -> np.ndarray:
        """(n,) float64 metres: the ray-origin offset at rel positions (n, 3)."""
        a = np.abs(rel)
        # Column-wise maximum: numpy's reduction over a length-3 inner axis is ~5x slower.
        largest = np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])
        return np.maximum(RAY_OFFSET_ABSOLUTE * self.extent, RAY_OFFSET_RELATIVE * largest)

    def offset_factors(self) -> tuple[float, float]:
        """(floor, relative) of ``epsilon`` = max(floor, relative * |rel|_max): what the
        compiled offset (``trace_kernels``) takes instead of this object."""
        return RAY_OFFSET_ABSOLUTE * self.extent, RAY_OFFSET_RELATIVE

    def offset(self, rel: np.ndarray, normals: np.ndarray, dirs: np.ndarray, eps=None):
        """Rel origins (n, 3) float64 moved off the surface by the offset epsilon (``eps``
        (n,), computed when None) along ``normals`` (n, 3), on the side ``dirs`` leave
        to. (``offset_rays`` is the same rule compiled, cast for Embree.)"""
        eps = self.epsilon(rel) if eps is None else eps
        side = np.where(np.einsum("ij,ij->i", dirs, normals) >= 0, eps, -eps)
        return rel + side[:, None] * normals

    def offset_rays(self, rel: np.ndarray, normals: np.ndarray, dirs: np.ndarray):
        """``offset`` in one compiled pass (``trace_kernels.offset_origins``), returned as
        the float32 origins (n, 3) Embree takes: rel (n, 3) float64, normals (n, 3)
        float64 unit, dirs (n, 3) float32 or float64."""
        rel = np.ascontiguousarray(rel, np.float64)
        normals = np.ascontiguousarray(normals, np.float64)
        out = np.empty(rel.shape, np.float32)
        floor, relative = self.offset_factors()
        trace_kernels.offset_origins(rel, normals, np.ascontiguousarray(dirs), floor, relative, out)
        return out


@dataclass
class BvhUpdate:
    """What one ``Bvh.update`` did.

    full : both BVHs and the whole table were built
    elements : (k,) int64 ascending, the elements whose table rows and vertex copies
               were refreshed (every element when full)
    table_rows : triangle rows of the table filled again
    animated_triangles : triangles the animated BVH was rebuilt from (all of them: it
               is rebuilt whole), 0 when it was not
    """

    full: bool
    elements: np.ndarray
    table_rows: int
    animated_triangles: int


@dataclass
class Hits:
    """Intersections of a batch of rays that hit something (m of the n rays).

    ray : (m,) int64 index of the ray in its batch; tri : (m,) int64 triangle ids;
    u, v : (m,) float32 Embree barycentrics (p = v0 + u (v1 - v0) + v (v2 - v0));
    miss : (n - m,) int64 indices of the rays that hit nothing."""

    ray: np.ndarray
    tri: np.ndarray
    u: np.ndarray
    v: np.ndarray
    miss: np.ndarray


class Bvh:
    """Embree BVHs of one ``Scene`` (see the module).

    Every query asks the static BVH first and then the animated one with ``tfar`` = the
    static hit distance, so the second answers only hits that are nearer (``_cast``);
    Embree's per-BVH ``primID`` is mapped back to global triangle ids. A stage without
    animated elements has only the static BVH and casts one Embree query per batch.

    boundary : the ``Float32Boundary`` (origin, extent, offsets).
    table : the ``TriangleTable`` of the current geometry (rel).
    geometry_version : the ``Scene.versions.geometry`` the BVHs and table hold.
    last_update : what the latest ``update`` did (``BvhUpdate``).
    tri_element, tri_material : (T,) int64 per-triangle element / material ids.
    static, dynamic : the embreex scenes (None when empty).
    record_rays : when True, ``run`` keeps every batch in ``last_rays`` (query, origins
                  f32, directions f32, tfar f32 or None); callers empty the list.
    """

    def __init__(self, scene: Scene, threads: int = 1, pool: ThreadPoolExecutor | None = None):
        self.threads = max(1, int(threads))
        self._pool = pool
        self.record_rays = False
        self.last_rays: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._device = rtc.EmbreeDevice()  # shared by this object's BVHs
        self.scene: Scene | None = None
        self.geometry_version = 0
        self.update(scene)

    # ------------------------------------------------------------------ building

    def update(self, scene: Scene) -> bool:
        """Bring the BVHs and table to ``scene``'s current geometry version; True when
        that was a full build. What was done: ``last_update``.

        Versions are compared, never arrays (``Scene.versions``). The version held →
        nothing. The same ``Scene`` object with only animated elements changed since:
        their table rows and vertex copies are refreshed and the animated BVH rebuilt
        (whole: embreex has no refit, so its cost is that of every animated triangle);
        the static BVH is kept. Anything else (another scene, another vertex or
        triangle count or origin, a static element changed): full build of both."""
        elements = self._changed_animated(scene)
        if elements is None:
            with small_pages():  # copies and table written once: phrt_usd.small_pages
                self._build(scene)
        elif len(elements):
            self._refresh_animated(scene, elements)
        else:
            self.last_update = BvhUpdate(False, elements, 0, 0)
        self.geometry_version = scene.versions.geometry
        return elements is None

    def _changed_animated(self, scene: Scene) -> np.ndarray | None:
        """The elements changed since the version held, (k,) int64 ascending, all
        animated (empty: nothing changed); None when ``scene`` needs a full build."""
        if scene is not self.scene:
            return None
        geo = scene.geometry
        if (
            geo.vertices.shape != self._vertices.shape
            or geo.triangles.shape != self._triangles.shape
            or not np.array_equal(np.asarray(scene.origin, np.float64), self.boundary.origin)
        ):
            return None
        if scene.versions.geometry == self.geometry_version:
            return np.zeros(0, dtype=np.int64)
        elements = scene.versions.changed_since(self.geometry_version)
        if not self._element_animated[elements].all():
            return None
        return elements

    def _build(self, scene: Scene) -> None:
        """Full build: copies, table, both BVHs, the static bounds."""
        self.scene = scene
        geo = scene.geometry
        progress.step(f"building the BVH of {geo.triangle_count:,} triangles")
        self.boundary = Float32Boundary(scene.origin)
        self._vertices = np.array(geo.vertices, dtype=np.float64).reshape(-1, 3)
        self._triangles = np.array(geo.triangles, dtype=np.int64).reshape(-1, 3)
        n_tri = len(self._triangles)
        self.tri_element = np.asarray(geo.tri_element, dtype=np.int64)
        self.tri_material = np.asarray(geo.tri_material, dtype=np.int64)
        self._element_triangles = ElementTriangles(self.tri_element, len(scene.elements))
        self._element_animated = np.array([e.animated for e in scene.elements], dtype=bool)
        animated = np.append(self._element_animated, False)
        self._tri_animated = animated[self.tri_element] if n_tri else np.zeros(0, bool)
        self._vertex_animated = np.zeros(len(self._vertices), dtype=bool)
        self._vertex_animated[self._triangles[self._tri_animated].reshape(-1)] = True
        self.table = TriangleTable(n_tri)
        self._fill(geo, slice(None))
        # Global ids of each BVH's triangles, with a trailing NO_HIT so that
        # ``np.take(ids, primID)`` maps Embree's miss (-1) to NO_HIT too. The static map
        # is empty when every triangle is static (Embree's ids are the global ones).
        static_ids = np.flatnonzero(~self._tri_animated)
        self._dynamic_ids = np.flatnonzero(self._tri_animated)
        every_static = len(static_ids) == n_tri
        static_map = GLOBAL_IDS if every_static else np.append(static_ids, NO_HIT)
        self._maps = (static_map, np.append(self._dynamic_ids, NO_HIT))
        rel = self.boundary.relative(self._vertices)
        static_triangles = self._triangles if every_static else self._triangles[static_ids]
        self.static = self._new_bvh(
            np.ascontiguousarray(rel, dtype=np.float32),
            np.ascontiguousarray(static_triangles, dtype=np.int32),
        )
        del static_triangles
        # Bounds of everything that never moves between full builds (vertices of no
        # animated triangle), for the offset epsilon's scene extent.
        still = rel if every_static else rel[~self._vertex_animated]
        self._static_bounds = (still.min(axis=0), still.max(axis=0)) if len(still) else None
        self.dynamic = None
        self._rebuild_animated()
        every = np.arange(len(scene.elements), dtype=np.int64)
        self.last_update = BvhUpdate(True, every, n_tri, len(self._dynamic_ids))

    def _refresh_animated(self, scene: Scene, elements: np.ndarray) -> None:
        """The table rows and vertex copies of the animated ``elements`` (k,) from
        ``scene``'s current geometry, then the animated BVH."""
        geo = scene.geometry
        rows = self._element_triangles.rows(elements)
        # Winding may flip with a transform's sign: the rows' corners, then vertices.
        self._triangles[rows] = geo.triangles[rows]
        moved = np.unique(self._triangles[rows])
        self._vertices[moved] = geo.vertices[moved]
        self._fill(geo, rows)
        self._rebuild_animated()
        self.last_update = BvhUpdate(False, elements, len(rows), len(self._dynamic_ids))

    def _rebuild_animated(self) -> None:
        """The animated BVH from the vertex and triangle copies, and the scene extent
        from the static bounds and the animated vertices."""
        rows = self._dynamic_ids
        # A triangle soup (D, 3, 3): no index remapping for a few hundred triangles.
        soup = self.boundary.vertices(self._vertices[self._triangles[rows]])
        self.dynamic = self._new_bvh(soup, None)
        # Scene.extent, without a pass over every vertex: the union of the static bounds
        # and the animated vertices' bounds (same vertex set, so the same value).
        boxes = [] if self._static_bounds is None else list(self._static_bounds)
        animated = np.flatnonzero(self._vertex_animated)
        if len(animated):
            rel = self.boundary.relative(self._vertices[animated])
            boxes += [rel.min(axis=0), rel.max(axis=0)]
        if boxes:
            lo, hi = np.min(boxes, axis=0), np.max(boxes, axis=0)
            self.boundary.extent = float(max(np.linalg.norm(hi - lo), 1e-12))
        else:
            self.boundary.extent = 1.0  # Scene.extent of an empty scene

    def _fill(self, geo, rows) -> None:
        """Table rows ``rows`` (index array or slice) from the vertex / triangle copies
        and ``geo``'s corner data."""
        self.table.fill(
            self._vertices,
            self._triangles,
            self.boundary.origin,
            geo.corner_normals,
            geo.corner_albedo,
            rows,
        )

    def _new_bvh(self, vertices: np.ndarray, triangles: np.ndarray | None):
        """A committed embreex scene of one triangle mesh (float32 rel vertices (V, 3) +
        int32 triangles (T, 3), or a (T, 3, 3) soup with ``triangles`` None), or None
        when it has no triangle."""
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

    # ------------------------------------------------------------------ Embree calls

    def run(self, query: str, origins: np.ndarray, dirs: np.ndarray, tfar=None, threads=None):
        """One ray batch. origins (n, 3) float64 rel metres, dirs (n, 3) unit, tfar (n,)
        metres or None; ``threads`` (default this object's) 1 inside a pool worker.
        Returns (primID, u, v) with global triangle ids (INTERSECT) or (n,) bool
        occluded. The only cast of ray data to float32 (``Float32Boundary.rays``)."""
        o32, d32, t32 = Float32Boundary.rays(origins, dirs, tfar)
        if self.record_rays:  # copies: callers reuse their ray buffers
            self.last_rays.append((query, o32.copy(), d32.copy(), t32))
        return self._run_raw(query, o32, d32, t32, self.threads if threads is None else threads)

    def _run_raw(self, query, o32, d32, t32, threads, merge: bool = True):
        """Both BVHs on float32 arrays, split into ``threads`` chunks over the pool when
        the batch is large enough (embreex releases the GIL inside ``run``). ``merge``
        False: only the embreex calls, no answer (``replay_raw``)."""
        n = o32.shape[0]
        if n == 0 or (self.static is None and self.dynamic is None):
            if not merge:
                return None
            if query == "OCCLUDED":
                return np.zeros(n, dtype=bool)
            miss = np.full(n, NO_HIT, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32)
            return miss if query == "INTERSECT" else miss + NO_ANIMATED
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
            if isinstance(parts[0], tuple):
                return tuple(np.concatenate(p) for p in zip(*parts, strict=True))
            return np.concatenate(parts)
        return self._cast(query, o32, d32, t32, merge)

    def _cast(self, query, o32, d32, t32, merge: bool):
        """The embreex calls for one chunk of rays, static BVH then animated BVH.

        INTERSECT: the animated BVH gets the static hits' distances as ``tfar`` (embreex
        writes each hit's t into ``dists``), so it reports only nearer hits, which then
        replace the static ones (``merge``). OCCLUDED: occluded if either BVH says so.
        Returns (primID (n,) int32 / int64 global triangle ids or NO_HIT, u, v (n,)
        float32) or (n,) bool occluded; ANSWERS: the two BVHs' answers unmerged
        (``answers``); None when not ``merge``."""
        static, dynamic = self.static, self.dynamic
        if query == "OCCLUDED":
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
            near = static.run(o32, d32, tfar, "INTERSECT", 1)
            tfar = near["tfar"]
        far = None if dynamic is None else dynamic.run(o32, d32, tfar, "INTERSECT", 1)
        if not merge:
            return None
        if near is None:
            n = o32.shape[0]
            answer = (np.full(n, NO_HIT, np.int32), np.zeros(n, np.float32))
            answer += (np.zeros(n, np.float32),)
        else:
            answer = (near["primID"], near["u"], near["v"])
        answer += NO_ANIMATED if far is None else (far["primID"], far["u"], far["v"])
        return answer if query == "ANSWERS" else self.merge(answer + self._maps)

    def answers(self, o32: np.ndarray, d32: np.ndarray) -> tuple[np.ndarray, ...]:
        """Nearest hits of rays from rel origins ``o32`` along unit directions ``d32``
        ((n, 3) float32 C-contiguous, as Embree takes them: the bounce loop's buffers) as
        the two BVHs gave them, for a compiled caller to merge (``merge`` is the rule):
        static (prim (n,) int32 ids of the static BVH, NO_HIT for a miss, u, v (n,)
        float32), animated (the same, only hits nearer than the static ones; three empty
        arrays when there is no animated BVH), then the two BVHs' id maps (int64, per
        BVH triangle its global id, then NO_HIT; the static one empty when Embree's
        static ids are the global ones)."""
        if self.record_rays:  # copies: callers reuse their ray buffers
            self.last_rays.append(("INTERSECT", o32.copy(), d32.copy(), None))
        if 0 < len(o32) < PARALLEL_MIN_RAYS:  # one chunk, on this thread
            return self._cast("ANSWERS", o32, d32, None, True) + self._maps
        return self._run_raw("ANSWERS", o32, d32, None, self.threads) + self._maps

    @staticmethod
    def merge(answer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``answers``' eight arrays → (prim (n,) global triangle ids or NO_HIT, u, v)."""
        prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map = answer
        if len(static_map):
            prim = np.take(static_map, prim)
        if len(far_prim):
            far_prim = np.take(dynamic_map, far_prim)
            nearer = far_prim >= 0
            if nearer.any():
                prim = np.where(nearer, far_prim, prim)
                u = np.where(nearer, far_u, u)
                v = np.where(nearer, far_v, v)
        return prim, u, v

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """Nearest hits of rays from rel ``origins`` (n, 3) along unit ``dirs`` (n, 3)."""
        prim, u, v = self.run("INTERSECT", origins, dirs)
        n = len(prim)
        ray, tri, miss = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        hu, hv = np.empty(n, np.float32), np.empty(n, np.float32)
        h = trace_kernels.split_hits(prim, u, v, ray, tri, hu, hv, miss)
        return Hits(ray=ray[:h], tri=tri[:h], u=hu[:h], v=hv[:h], miss=miss[: n - h])

    def merge_recorded(self, since: int) -> None:
        """The batches recorded from ``last_rays[since]`` on ran side by side (chunks of
        one batch on the pool, each cast with one thread): keep them as one batch per
        query, so ``replay_raw`` gives raw embreex the same rays under its own splitting
        rule rather than replaying the chunks one after another. A chunk's later casts
        (cut-out re-casts) join the same batch: raw embreex pays fewer calls than we did,
        never more."""
        if not self.record_rays or len(self.last_rays) - since < 2:
            return
        groups: dict[tuple[str, bool], list] = {}
        for query, o32, d32, t32 in self.last_rays[since:]:
            groups.setdefault((query, t32 is None), []).append((o32, d32, t32))
        self.last_rays[since:] = [
            (query, *(np.concatenate([p[i] for p in parts]) for i in (0, 1)),
             None if no_tfar else np.concatenate([p[2] for p in parts]))
            for (query, no_tfar), parts in groups.items()
        ]  # fmt: skip

    def replay_raw(self, threads: int | None = None) -> tuple[int, float]:
        """Re-run raw embreex on exactly the batches in ``last_rays`` (same float32
        arrays, same splitting rule, ``threads`` defaults to this object's). Returns
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
