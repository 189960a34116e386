"""Embree ray tracing of a ``Scene``: the tracer the renderer and the benchmarks call.

Pipeline phase: after the G-buffer and the selection of reflectors, ``Tracer`` turns the
G-buffer pixels of the selected reflectors into reflected radiance
(``trace_reflections``; ``trace_refraction`` for transmissive surfaces). It also serves
the ``rt`` reference mode (``primary_gbuffer``: the G-buffer from primary rays) and
ray-traced shadows (``shadow_visibility``).

The tracer is a shell over one role per module:

- ``bvh``: the Embree BVHs (static and animated triangles), change detection between
  frames, the float32 boundary (rel coordinates, ray-origin offsets) and the opt-in ray
  log of the benchmarks (``record_rays`` / ``last_rays`` / ``replay_raw`` here);
- ``hit_surfaces``: materials per triangle and the surface at hits, through the one
  surface rule of ``model.surface`` (the raster G-buffer's too, so ``rt`` and raster
  agree at grazing pixels);
- ``shadow_rays``: visibility of lights by occlusion rays;
- ``hit_lighting``: the direct light at the paths' hits (shadow maps where the renderer
  has them and they decide, ``use_shadow_maps``; shadow rays elsewhere, lights sampled
  where a hit has many);
- ``paths``: the bounce loop and the per-source ``TraceRecord`` s the heuristic reads;
- ``screen_space``: first rays resolved in the frame's own G-buffer before the bounce
  loop (``--screen-space on``);
- ``sparse_pixels``: reduced densities, their rotating pattern, and the skipped pixels
  reused (``engine/reflection_history.py``) or filled;
- ``glossy``: a glossy reflector's pixels (its roughness): rays drawn from the GGX lobe
  on a pattern that thins with roughness, the filter and accumulation that make them a
  clean image, the fade into the raster's environment and no rays past it.

This module picks the pixels paths start from (reflector pixels, found once per
G-buffer), turns them into first rays, and keeps the ray counters.

Coordinate spaces: every array crossing this module's API is world space, metres,
float64 positions. Inside, everything is rel (world minus ``Scene.origin``, float64);
Embree sees float32 rel coordinates, cast where the ray origins are made (the offset
rule of ``bvh.Float32Boundary``, compiled in ``trace_kernels``) or at the Embree call.
Robustness: G-buffer positions (possibly from a depth buffer) are first projected onto
their triangle's plane (as ``HitSurfaces.snap``), then every ray origin is offset along
the geometric normal on the side the ray leaves to (``bvh.Float32Boundary.offset``).

The per-pixel and per-ray work is compiled (``trace_kernels``: first rays from pixels,
the ``rt`` pixel rays and G-buffer rows), split over the pool from
``PARALLEL_MIN_KERNEL_ROWS`` rows on.

Limits: glossy reflections at the first bounce only (deeper bounces are mirrors), one
sample a glossy pixel a frame, no refit (embreex has none: the
animated BVH is rebuilt when it moves), shadows are hard (light size ignored).
"""

from __future__ import annotations

import dataclasses
import operator
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine import lighting
from phrt_usd.engine.trace import glossy, screen_space, sparse_pixels
from phrt_usd.engine.trace.bvh import Bvh
from phrt_usd.engine.trace.hit_lighting import MapLookup, area_offsets, frame_seed
from phrt_usd.engine.trace.hit_surfaces import HitSurfaces
from phrt_usd.engine.trace.paths import PathTracer, refract
from phrt_usd.engine.trace.shadow_rays import ShadowRays
from phrt_usd.model import pixel_kinds
from phrt_usd.model.frame import GBuffer, ReflectionResult, flat_image
from phrt_usd.model.scene import NO_HIT, CameraFrame, Lights, Scene
from phrt_usd.model.trace_density import check_density
from phrt_usd.threads import DEFAULT_THREADS

#: The compiled trace kernels (``trace_kernels``, through ``phrt_usd.kernels``).
trace_kernels = kernels.load("phrt_usd.engine.trace.trace_kernels")

#: Compiled per-pixel loops over fewer rows than this run on the calling thread (below
#: it handing chunks to the pool costs more than it saves).
PARALLEL_MIN_KERNEL_ROWS = 16384


class Tracer:
    """Ray tracing against one ``Scene``.

    Public arguments and results are world space; ``bvh`` holds the geometry (its
    ``boundary`` the origin and extent), ``surfaces`` the materials and surface rule.

    rays_cast : cumulative counters by kind ("primary", "reflection", "refraction",
                "shadow"); ``reset_counters()`` zeroes them.
    record_rays : when True, every ray batch of the latest public call is kept in
                  ``last_rays`` (query, origins f32, directions f32, tfar f32 or None),
                  for ``replay_raw`` to compare with raw embreex on the same rays.
    last_build_seconds : wall time of the latest ``update_geometry``.
    last_build_full : True when it rebuilt the static BVH too (False: animated only).
    """

    def __init__(self, scene: Scene, threads: int = DEFAULT_THREADS) -> None:
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self.rays_cast: dict[str, int] = {}
        self.reset_counters()
        self._hit_maps: MapLookup | None = None  # ``use_shadow_maps``
        self._frame_seed = 0.0  # ``begin_frame``
        self.exact_hit_lighting = False  # every pair traced (``HitLighting.exact``)
        start = time.perf_counter()
        self.bvh = Bvh(scene, self.threads, self._pool)
        self._bind(scene)
        self.last_build_full = True
        self.last_build_seconds = time.perf_counter() - start

    # ------------------------------------------------------------------ set-up

    def reset_counters(self) -> None:
        self.rays_cast = {"primary": 0, "reflection": 0, "refraction": 0, "shadow": 0}

    @property
    def record_rays(self) -> bool:
        return self.bvh.record_rays

    @record_rays.setter
    def record_rays(self, value: bool) -> None:
        self.bvh.record_rays = bool(value)

    @property
    def last_rays(self) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
        return self.bvh.last_rays

    @last_rays.setter
    def last_rays(self, batches: list) -> None:
        self.bvh.last_rays = batches

    def replay_raw(self, threads: int | None = None) -> tuple[int, float]:
        """(rays, seconds) of raw embreex on the batches in ``last_rays``
        (``Bvh.replay_raw``)."""
        return self.bvh.replay_raw(threads)

    def update_geometry(self, scene: Scene) -> None:
        """Bring the tracer to ``scene``'s current geometry version: ``Bvh.update``
        (nothing when it holds that version; the changed elements and the animated BVH
        when only animated elements changed; else a full build), then, after a full
        build, the materials. Cost in ``last_build_seconds``."""
        start = time.perf_counter()
        full = self.bvh.update(scene)
        if full:
            self._bind(scene)
        self.last_build_full = full
        self.last_build_seconds = time.perf_counter() - start

    def _bind(self, scene: Scene) -> None:
        """Everything that follows a full build: materials, reflector ids, caches."""
        self.scene = scene
        self.surfaces = HitSurfaces(scene, self.bvh)
        self._shadows = ShadowRays(self.bvh, self._pool, self.threads, self.surfaces)
        self._paths = PathTracer(self.bvh, self.surfaces, self._shadows)
        is_reflector = np.array([e.is_reflector for e in scene.elements], dtype=bool)
        self._element_reflector = is_reflector
        self._reflector_ids = np.flatnonzero(is_reflector)
        self._reflector_set = set(self._reflector_ids.tolist())
        self._pixel_cache: tuple | None = None
        self._image_cache: tuple | None = None
        self._glossy = glossy.has_glossy(scene)  # some reflection follows roughness
        self._lights_key: tuple | None = None
        #: ``sparse_pixels.fill_skipped``'s pixel table, kept for the G-buffer size.
        self._fill_table: np.ndarray | None = None

    def use_shadow_maps(self, rasterizer) -> None:
        """Light the paths' hits with ``rasterizer``'s shadow maps where they decide
        (``hit_lighting``; without maps every pair takes a ray, lights sampled)."""
        self._hit_maps = lambda positions, normals, view_dirs, surface, terminator: (
            lighting.map_lookup(rasterizer, self.scene.lights, positions, normals, view_dirs,
                                surface=surface, terminator=terminator)
        )  # fmt: skip

    def begin_frame(self, time_code: float) -> None:
        """The frame the next traces belong to: the seed of the light sampling at hits
        (``hit_lighting.frame_seed``), so a frame traces the same way every time."""
        self._frame_seed = frame_seed(time_code)

    def _relative_lights(self) -> Lights:
        """The scene's lights with LocalLight positions rel (what shading sees, since it
        is handed rel positions). Cached while the scene's ``Lights`` object and its
        LocalLight objects stay the same."""
        lights = self.scene.lights
        # Identity, not equality (dataclasses of arrays); holding the objects keeps
        # their ids from being reused.
        key = (lights, *lights.local)
        cached = self._lights_key
        if cached is None or len(cached) != len(key) or any(map(operator.is_not, cached, key)):
            origin = self.bvh.boundary.origin
            local = [
                dataclasses.replace(li, position=np.asarray(li.position, np.float64) - origin)
                for li in lights.local
            ]
            self._relative = dataclasses.replace(lights, local=local)
            self._lights_key = key
        return self._relative

    def offset_epsilon(self, positions: np.ndarray) -> np.ndarray:
        """(n,) float64 metres: the ray-origin offset at world ``positions`` (n, 3)."""
        boundary = self.bvh.boundary
        return boundary.epsilon(boundary.relative(positions))

    # ------------------------------------------------------------------ shadows

    def shadow_visibility(self, positions: np.ndarray, normals: np.ndarray,
                          triangle_ids: np.ndarray | None = None, pairs: np.ndarray | None = None,
                          pixels: tuple | None = None) -> np.ndarray:  # fmt: skip
        """Ray-traced shadows: (n, L) float32, 1 = lit, light order distant then local.

        positions : (n, 3) float64 world metres; normals : (n, 3) world unit shading
        normals (facing the viewer); triangle_ids : optional (n,) triangle of each point
        (snaps depth-buffer positions onto their triangle first); pairs : optional (n, L)
        bool, the (point, light) pairs wanted (e.g. a shadow map's uncertain ones), the
        others are not traced and report 0. No lights: returns (n, 0) and casts nothing.
        Points facing away from a light, or beyond a LocalLight's range
        (``shading.light_ranges``), get 0 without a ray. pixels : optional (flat indices
        (n,), image width), whose offsets draw the area lights' rays as the hits' are
        (``hit_lighting.area_offsets``; ``shadow_rays``' area rule: a visible share).
        """
        self.last_rays = []
        rel = self.bvh.boundary.relative(np.asarray(positions).reshape(-1, 3))
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        tri = None
        if triangle_ids is not None:
            tri = np.asarray(triangle_ids, np.int64).reshape(-1)
            rel, _ = self.surfaces.snap(rel, tri, normals)
        spots = None if pixels is None else area_offsets(*pixels, self._frame_seed)
        vis, rays = self._shadows.visibility(
            rel, normals, self._relative_lights(), pairs, triangles=tri, area_offsets=spots
        )
        self.rays_cast["shadow"] += int(rays.sum())
        return vis

    # ------------------------------------------------------------------ primary rays

    def primary_gbuffer(self, camera: CameraFrame, width: int, height: int) -> GBuffer:
        """The ``rt`` mode's G-buffer: primary rays through pixel centres, same field
        definitions as the raster G-buffer (``frame.GBuffer``). The camera's clipping
        range holds as in the raster: a ray starts where its view depth is ``near``, and a
        nearest hit deeper than ``far`` is a miss."""
        self.last_rays = []
        origin = self.bvh.boundary.origin
        n = width * height
        xs, ys = camera.pixel_plane(width, height)
        cam = np.asarray(camera.world_from_camera, dtype=np.float64)
        rot = np.ascontiguousarray(cam[:3, :3])
        # A camera transform with scale or shear needs the directions normalised again.
        renormalise = not np.allclose(rot.T @ rot, np.eye(3), rtol=0.0, atol=1e-12)
        eye = cam[:3, 3] - origin
        fwd = np.ascontiguousarray(camera.forward, dtype=np.float64)
        dirs = np.empty((n, 3))
        o32, d32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        self._split(
            trace_kernels.primary_rays, n, xs, ys, rot, renormalise, eye, fwd,
            float(camera.near), out=(dirs, o32, d32),
        )  # fmt: skip
        hits, recast = self.surfaces.intersect(o32, d32)
        self.rays_cast["primary"] += n + len(recast)  # cut-out re-casts: primary rays too
        element = np.full(n, NO_HIT, np.int32)
        triangle = np.full(n, NO_HIT, np.int32)
        depth = np.full(n, np.inf, np.float32)
        position = np.zeros((n, 3))
        normal = np.zeros((n, 3), np.float32)
        albedo = np.zeros((n, 3), np.float32)
        rows = (element, triangle, depth, position, normal, albedo)

        def fill(lo: int, hi: int) -> None:  # the G-buffer rows of hits lo..hi
            r, tri, u, v = (a[lo:hi] for a in (hits.ray, hits.tri, hits.u, hits.v))
            rel, _, ns, alb, _ = self.surfaces.at(tri, u, v, np.take(dirs, r, axis=0))
            trace_kernels.primary_fill(
                r, tri, rel, ns, alb, eye, fwd, float(camera.far), origin,
                self.bvh.tri_element, *rows,
            )  # fmt: skip

        self._split(fill, len(hits.ray), out=())
        shape = (height, width)
        return GBuffer(
            element_id=element.reshape(shape),
            triangle_id=triangle.reshape(shape),
            depth=depth.reshape(shape),
            position=position.reshape(shape + (3,)),
            normal=normal.reshape(shape + (3,)),
            albedo=albedo.reshape(shape + (3,)),
            view_dir=d32.reshape(shape + (3,)),
        )

    def _split(self, kernel, n: int, *args, out: tuple,
               min_rows: int = PARALLEL_MIN_KERNEL_ROWS) -> None:  # fmt: skip
        """``kernel(*args, lo, hi, *out)`` over rows 0..n, in ``threads`` chunks on the
        pool from ``min_rows`` rows on (the kernels release the GIL)."""
        if self._pool is None or n < min_rows:
            kernel(*args, 0, n, *out)
            return
        edges = np.linspace(0, n, self.threads + 1).astype(int).tolist()
        jobs = [
            self._pool.submit(kernel, *args, lo, hi, *out)
            for lo, hi in zip(edges[:-1], edges[1:], strict=True)
        ]
        for job in jobs:
            job.result()

    # ------------------------------------------------------------------ paths

    def trace_reflections(
        self, gbuffer: GBuffer, sources: list[int], bounce_limit: int, density="full",
        reuse=None, screen=None, raster=None,
    ) -> ReflectionResult:
        """Mirror-reflection radiance for every G-buffer pixel whose element is in
        ``sources`` (no primary rays: rays start at the G-buffer position / normal /
        view_dir). ``bounce_limit`` is the most reflection rays along one path; a
        reflector hit at the last one reads the environment for its reflected part
        (``bounce_limit`` < 1: no rays, the environment in the mirror direction).

        ``density`` one of ``model.trace_density.TRACE_DENSITIES`` (for every source, or
        a sequence of them, one per source): large reflectors start rays on a pattern of
        their pixels and fill the others from traced neighbours (``sparse_pixels``; with
        ``raster``, the raster frame's fallback, local and reflectivity images, its sky
        rule: ``fill_guides``); their records then
        count every covered pixel, so rays per pixel stay what a frame's pixel counts
        predict at that density (hits scaled alike). ``reuse`` (an
        ``engine.reflection_history.FrameReuse``, None: none) shifts the pattern by the
        frame's ``phase`` (a rotating subset, ``sparse_pixels.rotation_phase``) and gives
        skipped pixels their reprojected history where it is valid, the fill the others.
        ``screen`` (a ``screen_space.ScreenFrame``, None: none) resolves first rays in
        screen space where the G-buffer decides them (kind SCREEN_SPACE), the bounce loop
        the rest. Each record counts its pixels of each kind (``with_kind_counts``)."""
        start = time.perf_counter()
        self.last_rays = []
        sources = [int(s) for s in sources]
        phase = (0, 0) if reuse is None else reuse.phase
        density = checked_densities(density, len(sources))
        first = self._source_pixels(gbuffer, sources, None, True, self._glossy, density, phase,
                                    glossy_pixels=self._glossy)  # fmt: skip
        pix, src, d, origins = first["pix"], first["src"], first["dir"], first["org"]
        gloss = first["glossy"]  # glossy pixels' rays drawn from their lobes
        gloss.draw_rays(first, self._frame_seed, self.bvh.boundary.offset_factors(), bounce_limit)
        hits = None
        if screen is not None and bounce_limit >= 1 and len(pix):
            self._paths.lighting.prepare(self._hit_maps, self._frame_seed, gbuffer.shape[1],
                                         self.exact_hit_lighting)  # fmt: skip
            hits = screen_space.resolve(
                screen, gbuffer.depth, pix, origins, d, self._images(gbuffer),
                self.bvh.boundary.origin, self.bvh.table.frame, self.surfaces,
                self._paths.lighting, self._relative_lights(), self._split,
            )  # fmt: skip
            self.rays_cast["shadow"] += hits.shadow_cast
            rest = hits.unresolved
            all_pix, all_src = pix, src
            pix, src, d, origins = pix[rest], src[rest], d[rest], origins[rest]
        result = self._run_paths(
            pix, src, origins, d, sources, bounce_limit, "reflection", start, gbuffer.shape[1]
        )
        if hits is not None:
            result, src = screen_space.merge(result, src, hits, all_pix, all_src, sources, start)
        gloss.weigh(result)
        if first["skipped"] is not None:
            height, width = gbuffer.shape
            if self._fill_table is None or len(self._fill_table) != width * height:
                self._fill_table = np.full(width * height, -1, np.int32)
            result = sparse_pixels.complete(
                result, src, first["skipped"],
                fill_guides(gbuffer, raster, self.surfaces.transmission), density,
                phase, reuse, self._fill_table, self._split, start,
            )  # fmt: skip
        gloss.finish(result, self._relative_lights(), reuse, sources)
        return with_kind_counts(result, gbuffer.element_id, marched=hits is not None)

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
        surfaces, tri_material = self.surfaces, self.bvh.tri_material
        if not surfaces.transmission:
            empty = np.zeros(0, np.int64)
            return ReflectionResult(empty, np.zeros((0, 3), np.float32), [], 0, 0.0)
        tri_flat = gbuffer.triangle_id.reshape(-1)
        hit = tri_flat >= 0
        clear = np.zeros(len(tri_flat), dtype=bool)
        clear[hit] = surfaces.opacity[tri_material[tri_flat[hit]]] < 1.0
        elem_flat = gbuffer.element_id.reshape(-1)
        if elements is not None:
            clear &= np.isin(elem_flat, np.asarray(elements, dtype=np.int64))
        sources = [int(e) for e in np.unique(elem_flat[clear])]
        first = self._source_pixels(gbuffer, sources, clear, reflect=False, surface=True)
        pix, src, tri, ng_front = first["pix"], first["src"], first["tri"], first["ng"]
        ior = surfaces.ior[tri_material[tri]]
        # Directions are float32 from here on (Embree's precision for them anyway).
        d = refract(first["view"], first["ns"], ng_front, ior).astype(np.float32)
        origins = self.bvh.boundary.offset_rays(first["rel"], ng_front, d)
        return self._run_paths(
            pix, src, origins, d, sources, bounce_limit, "refraction", start, gbuffer.shape[1]
        )

    def _run_paths(self, pix, src, origins, dirs, sources, bounce_limit, first_kind, start,
                   width):  # fmt: skip
        """``PathTracer.run`` with this tracer's rel lights, element count and counters,
        its hits lit with its shadow maps and frame seed (``width``: the G-buffer's)."""
        lights = self._relative_lights()
        n_elements = len(self.scene.elements)
        self._paths.lighting.prepare(self._hit_maps, self._frame_seed, width,
                                     self.exact_hit_lighting)  # fmt: skip
        return self._paths.run(
            pix, src, origins, dirs, sources, bounce_limit, first_kind, start,
            lights, n_elements, self.rays_cast,
        )  # fmt: skip

    def _reflector_pixels(self, element_id: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """The pixels of ``element_id`` (H, W) showing a reflector, grouped by element:
        flat indices (m,) int64 (row-major within an element) and offsets (E + 1 ints),
        element e's pixels being ``[offsets[e], offsets[e + 1])``. Cached for the latest
        id image (a G-buffer is never modified once made; the cache holds the array, so
        its identity stays unique)."""
        cached = self._pixel_cache
        if cached is not None and cached[0] is element_id:
            return cached[1], cached[2]
        elem = element_id.reshape(-1)
        ids = self._reflector_ids
        n_elem = len(self._element_reflector)
        if len(ids):
            # A range test first (two cheap compares over the image), the table lookup
            # only on the pixels in the reflector id range.
            cand = np.flatnonzero((elem >= ids[0]) & (elem <= ids[-1]))
            cand_elem = np.take(elem, cand)
            keep = np.flatnonzero(np.take(self._element_reflector, cand_elem))
            cand, cand_elem = np.take(cand, keep), np.take(cand_elem, keep)
            order = np.argsort(cand_elem, kind="stable")
            cand = np.take(cand, order)
            counts = np.bincount(cand_elem, minlength=n_elem)
        else:
            cand, counts = np.zeros(0, np.int64), np.zeros(n_elem, np.int64)
        offsets = [0, *np.cumsum(counts).tolist()]
        self._pixel_cache = (element_id, cand, offsets)
        return cand, offsets

    def _images(self, gbuffer: GBuffer) -> tuple[np.ndarray, ...]:
        """``gbuffer``'s triangle, position, normal and view images flat as
        ``trace_kernels.source_rays`` reads them (``model.frame.flat_image``), cached for the latest
        G-buffer's arrays (never modified once made, see ``_reflector_pixels``)."""
        images = (gbuffer.triangle_id, gbuffer.position, gbuffer.normal, gbuffer.view_dir)
        cached = self._image_cache
        if cached is not None and all(map(operator.is_, cached[0], images)):
            return cached[1]
        flat = (
            flat_image(gbuffer.triangle_id, np.int32, 1),
            flat_image(gbuffer.position, np.float64, 3),
            flat_image(gbuffer.normal, np.float32, 3),
            flat_image(gbuffer.view_dir, np.float32, 3),
        )  # fmt: skip
        self._image_cache = (images, flat)
        return flat

    def _source_pixels(
        self, gbuffer: GBuffer, sources: list[int], mask, reflect: bool, surface: bool,
        density="full", phase=(0, 0), glossy_pixels: bool = False,
    ) -> dict:
        """Pixels to start paths from (``trace_kernels.source_rays``), a dict of arrays:
        pix (n,) flat indices, src (n,) index into ``sources``, tri (n,) triangle ids;
        with ``surface`` rel (n, 3) float64 positions snapped onto their triangle, ng
        (n, 3) float64 unit front-face triangle normals, ns (n, 3) float32 unit shading
        normals facing the viewer, view (n, 3) float32 unit view directions; with
        ``reflect`` dir (n, 3) float32 mirror directions and org (n, 3) float32 offset
        origins (the arrays not asked for have no rows). A source listed twice takes
        the index of its last entry. ``density`` other than "full" (one for every
        source, or one per source, as ``trace_reflections``'): only the pixels
        ``sparse_pixels.traced_subset`` keeps, and "skipped" the others (pixels (m,),
        their sources (m,), covered pixels per source (len(sources),)), else None;
        "glossy" the round's ``glossy.GlossyRound`` with ``glossy_pixels``, else NO_ROUND."""
        index = {s: i for i, s in enumerate(sources)}
        if mask is None and all(s in self._reflector_set for s in index):
            # Reflector sources (the renderer's case): look only at the G-buffer's
            # reflector pixels, found once per G-buffer and grouped by element (later
            # rounds reuse them): each source's pixels are one slice.
            pixels, offsets = self._reflector_pixels(gbuffer.element_id)
            if len(index) == 1:  # one slice, source index 0
                (s,) = index
                cand = pixels[offsets[s] : offsets[s + 1]]
                cand_src = np.zeros(len(cand), np.int64)
            else:  # the slices gathered in one compiled pass (numpy: ~2 us a source)
                spans = [(offsets[s], offsets[s + 1], i) for s, i in index.items()]
                spans = np.array(spans, np.int64).reshape(-1, 3)
                k = sum(offsets[s + 1] - offsets[s] for s in index)
                cand, cand_src = np.empty(k, np.int64), np.empty(k, np.int64)
                trace_kernels.gather_spans(pixels, spans, cand, cand_src)
        else:
            # Element id → index in ``sources`` (-1: not a source); the last slot serves
            # id -1.
            n_elem = len(self.scene.elements)
            table = np.full(max(n_elem, max(sources, default=0) + 1) + 1, -1, np.int64)
            table[[s for s in index if s >= 0]] = [i for s, i in index.items() if s >= 0]
            elem = gbuffer.element_id.reshape(-1)
            chosen = np.take(table >= 0, elem)
            if mask is not None:
                chosen &= mask
            cand = np.flatnonzero(chosen)
            cand_src = np.take(table, np.take(elem, cand))
        gloss, traced_glossy = glossy.NO_ROUND, None
        if glossy_pixels and len(cand):  # glossy pixels start rays on their own pattern
            gloss, cand, cand_src, traced_glossy = glossy.GlossyRound.of(
                self.scene, gbuffer, cand, cand_src, density, self._frame_seed, self._split)
        cand, cand_src, skipped = _density_subset(
            cand, cand_src, len(sources), gbuffer.shape[1], density, phase, traced_glossy
        )
        k = len(cand)
        out = {"tri": np.empty(k, np.int64)}
        if surface:
            out["rel"], out["ng"] = np.empty((k, 3)), np.empty((k, 3))
            out["ns"], out["view"] = np.empty((k, 3), np.float32), np.empty((k, 3), np.float32)
        else:
            out["rel"], out["ng"], out["ns"], out["view"] = _NO_SURFACE
        if reflect:
            out["dir"], out["org"] = np.empty((k, 3), np.float32), np.empty((k, 3), np.float32)
        else:
            out["dir"], out["org"] = _NO_RAYS
        floor, relative = self.bvh.boundary.offset_factors()
        self._split(
            trace_kernels.source_rays, k, cand, *self._images(gbuffer),
            self.bvh.boundary.origin, self.bvh.table.frame, floor, relative,
            out=tuple(out.values()),
        )  # fmt: skip
        out["pix"], out["src"], out["skipped"] = cand, cand_src, skipped
        out["glossy"] = gloss
        return out


def _density_subset(cand, cand_src, n_sources: int, width: int, density, phase,
                    traced_glossy=None):  # fmt: skip
    """``Tracer._source_pixels``' pixels ``cand`` (n,) of sources ``cand_src`` (n,) that
    start rays at ``density`` (``sparse_pixels.traced_subset`` in ``phase``), their
    sources, and the skipped ones (pixels, sources, covered pixels per source), None
    when none is skipped; with ``traced_glossy`` (pixels, sources: the glossy ones that
    start rays, ``glossy.GlossyRound.of``) appended to those that start rays and counted
    as covered."""
    skipped = None
    if density != "full":
        keep = sparse_pixels.traced_subset(cand, cand_src, n_sources, width, density, phase)
        if not keep.all():  # only small reflectors: traced whole
            covered = np.bincount(cand_src, minlength=n_sources)
            if traced_glossy is not None:
                covered += np.bincount(traced_glossy[1], minlength=n_sources)
            skipped = (cand[~keep], cand_src[~keep], covered)
            cand, cand_src = cand[keep], cand_src[keep]
    if traced_glossy is not None:
        cand = np.concatenate([cand, traced_glossy[0]])
        cand_src = np.concatenate([cand_src, traced_glossy[1]])
    return cand, cand_src, skipped


def checked_densities(density, sources: int) -> str | list[str]:
    """``trace_reflections``' ``density`` checked (``model.trace_density.check_density``):
    one density for every source, or a sequence of one per source of ``sources``
    (ValueError for another count; one density "full" when all are)."""
    if isinstance(density, str):
        return check_density(density)
    density = [check_density(d) for d in density]
    if len(density) != sources:
        raise ValueError(f"{len(density)} densities for {sources} sources")
    return "full" if all(d == "full" for d in density) else density


def fill_guides(gbuffer: GBuffer, raster, transmission: bool) -> sparse_pixels.FillGuides:
    """The fill's guides: the G-buffer's, and ``raster`` for its sky rule unless the stage
    has transmissive materials (``transmission``: their traced radiance mixes in
    refraction, which the raster's fallback reflection does not show)."""
    return sparse_pixels.FillGuides.of(gbuffer, None if transmission else raster)


#: The pixel kinds a ``TraceRecord`` counts (the rest of its pixels were traced), by
#: field name.
_COUNTED_KINDS = {
    "screen_space": pixel_kinds.SCREEN_SPACE,
    "reused": pixel_kinds.REUSED,
    "filled": pixel_kinds.FILLED,
}


def with_kind_counts(result: ReflectionResult, element_id: np.ndarray,
                     marched: bool = False) -> ReflectionResult:  # fmt: skip
    """``result`` (a reflection round, complete) with each record's pixels of each kind
    counted (``TraceRecord.screen_space``, ``reused``, ``filled``) from its ``kinds``
    and the G-buffer's ``element_id`` (H, W) at its pixels, and its pixels whose first
    ray was ``marched`` in screen space (``TraceRecord.marched``: the traced and the
    screen-space ones when the step ran, else none): what the time model prices apart
    from rays (``select.cost_model``)."""
    if result.kinds is None:  # every pixel traced (and none marched: the step would mark)
        counts = {name: 0 for name in _COUNTED_KINDS}
        result.records = [dataclasses.replace(r, **counts, marched=r.pixels if marched else 0)
                          for r in result.records]  # fmt: skip
        return result
    ids = np.take(element_id.reshape(-1), result.pixel_index).astype(np.int64)
    n_ids, n_kinds = int(ids.max(initial=-1)) + 1, len(pixel_kinds.PIXEL_KINDS)
    # One pass: (element, kind) pairs counted together, a row per element id.
    table = np.bincount(ids * n_kinds + result.kinds, minlength=n_ids * n_kinds)
    table = table.reshape(n_ids, n_kinds)
    records = []
    for r in result.records:
        row = table[r.source] if 0 <= r.source < n_ids else np.zeros(n_kinds, np.int64)
        counts = {name: int(row[code]) for name, code in _COUNTED_KINDS.items()}
        started = int(row[pixel_kinds.TRACED]) + counts["screen_space"]
        records.append(dataclasses.replace(r, **counts, marched=started if marched else 0))
    result.records = records
    return result


#: ``_source_pixels``' outputs not asked for (no rows): the surface (rel, ng, ns, view)
#: and the mirror rays (dir, org).
_NO_SURFACE = (np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 3), np.float32),
               np.empty((0, 3), np.float32))  # fmt: skip
_NO_RAYS = (np.empty((0, 3), np.float32), np.empty((0, 3), np.float32))
