"""The surface at ray hits: per-triangle materials and the one surface rule.

``HitSurfaces`` turns Embree hits (triangle id, barycentrics u, v) into what paths and
shading need: rel position, geometric and shading normals (``model.surface``'s rule, the
same as the raster G-buffer's, so ``rt`` and raster agree at grazing pixels), albedo
(texture lookup where the material has one), emission, and the per-triangle material
figures the bounce loop reads (reflector flag, reflectivity F, opacity, ior).

Cut-outs (UsdPreviewSurface ``opacityThreshold``, ``model.surface.Cutouts``, the rule
the raster's id layers use too): ``intersect`` and ``occluded`` are the ray queries of
every traced ray (primary, reflected, refracted, shadow). A hit on a cut-out texel is no
hit: the ray is re-cast from just past it (the float32 boundary's offset to the far
side), at most ``surface.MAX_CUTOUT_LAYERS`` times; a ray still in holes after that is a
miss (a shadow ray: unoccluded). Scenes without cut-outs cast each ray once.

Spaces: rel = world metres minus ``Scene.origin``, float64 (``bvh.Float32Boundary``).
Hit points are rebuilt in float64 from the hit triangle's rel vertices and Embree's
barycentrics (not ``origin + t * dir``), so they lie on the surface to float64 precision.
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine import shading
from phrt_usd.engine.compositing import MATERIAL_MAX_F
from phrt_usd.engine.trace.bounce_layout import (
    TRI_ALPHA,
    TRI_COLUMNS,
    TRI_F,
    TRI_IOR,
    TRI_REFLECTOR,
    TRI_TEXTURED,
)
from phrt_usd.engine.trace.bvh import GLOBAL_IDS, NO_ANIMATED, Bvh, Hits
from phrt_usd.model import preview_surface, surface
from phrt_usd.model.scene import Scene

#: The compiled surface rule (``model.surface_kernels``, through ``phrt_usd.kernels``).
_SURFACE = kernels.load("phrt_usd.model.surface_kernels")

#: Smallest index of refraction used (ior ≤ 0 is meaningless; Snell's law stays finite).
MIN_IOR = 1e-3


class HitSurfaces:
    """Materials of ``scene``'s triangles and the surface at hits on ``bvh``'s geometry
    (its table is read at call time, so animated refreshes are seen).

    tri_reflector : (T,) bool; tri_f : (T,) float64 reflectivity F (0 for
    non-reflectors); transmission : the stage has transmissive materials;
    opacity, ior : (M,) float64 per material (clamped to [0, 1] / ≥ ``MIN_IOR``; cut-out
    rows opaque: their opacity is a presence mask, ``Cutouts``).
    """

    def __init__(self, scene: Scene, bvh: Bvh) -> None:
        self._scene = scene
        self._bvh = bvh
        tri_element = bvh.tri_element
        mats = scene.materials
        reflectivity = np.clip(scene.reflectivity.astype(np.float64), 0.0, 1.0)
        is_reflector = np.array([e.is_reflector for e in scene.elements], dtype=bool)
        n_tri = len(tri_element)
        self.tri_reflector = is_reflector[tri_element] if n_tri else np.zeros(0, bool)
        self.tri_f = np.where(self.tri_reflector, reflectivity[tri_element], 0.0)
        # Reflectors that follow their material (``Element.reflectivity_authored`` off,
        # ``engine/compositing.py``): at a hit the bounce weighs the reflection by one F
        # per triangle, the material's reflection weight averaged over view directions
        # (``preview_surface.mean_reflection``, its channels' mean: no tint, no angle at
        # deeper bounces), and the local part by 1 - F, which ``weighted`` undoes
        # (``local_scale``): local + F reflected, as the primary pixel's rule.
        material = np.array(
            [e.is_reflector and not e.reflectivity_authored for e in scene.elements] or [False]
        )
        follows = material[tri_element] if n_tri else np.zeros(0, bool)
        #: (T,) float64: what a hit's local shading is multiplied by before the bounce's
        #: 1 - F weight (1 but on material-rule reflector triangles).
        self.local_scale = np.ones(n_tri)
        if follows.any():
            rows = preview_surface.surface_columns(
                mats.diffuse, *(preview_surface.material_inputs(mats, name)[:, 0]
                                for name in ("metallic", "useSpecularWorkflow")),
                preview_surface.material_inputs(mats, "specularColor"),
                *(preview_surface.material_inputs(mats, name)[:, 0]
                  for name in ("roughness", "clearcoat", "clearcoatRoughness", "ior",
                               "occlusion")),
                0.0,
            )  # fmt: skip
            mean = preview_surface.mean_reflection(rows).mean(axis=1)
            f_material = np.minimum(mean, MATERIAL_MAX_F)[bvh.tri_material]
            self.tri_f = np.where(follows, f_material, self.tri_f)
            # Only the triangles that follow their material divide (their F is below
            # MATERIAL_MAX_F < 1); an authored F = 1 mirror keeps scale 1 (no 1 / 0).
            np.divide(1.0, 1.0 - self.tri_f, out=self.local_scale, where=follows)
        #: Per triangle: 1 where the ambient's specular part is shaded (no mirror
        #: reflection stands in for it), as the G-buffer's (``lighting``).
        self._specular_ambient = np.where(self.tri_reflector, 0.0, 1.0).astype(np.float32)
        self.transmission = mats.has_transmission
        self.opacity = np.clip(np.asarray(mats.opacity, dtype=np.float64), 0.0, 1.0)
        # A cut-out's opacity is a presence mask: where it is there it is opaque.
        self.opacity[[m for m in mats.cutouts if m < len(self.opacity)]] = 1.0
        self.ior = np.maximum(np.asarray(mats.ior, dtype=np.float64), MIN_IOR)
        emissive = np.asarray(mats.emissive, dtype=np.float32).reshape(-1, 3)
        self._textured_emission = surface.has_texture_input(mats, "emissiveColor")
        self._has_emission = bool(np.any(emissive != 0)) or self._textured_emission
        self._emissive = emissive
        self._textures = list(mats.textures) if scene.geometry.corner_uv is not None else []
        textured = np.array([t is not None for t in self._textures] + [False], bool)
        #: Per triangle: its material has an albedo texture (``colour`` skips the texture
        #: lookup when no hit has).
        self._tri_textured = textured[bvh.tri_material] if self._textures else textured[:0]
        self._inputs = mats.texture_inputs
        #: The cut-out rule of this scene's triangles (``model.surface.Cutouts``).
        self.cutouts = surface.Cutouts(mats, bvh.tri_material, scene.geometry.corner_uv)
        #: Tangent-space normal maps (``model.surface.NormalMaps``).
        self.normal_maps = surface.NormalMaps(mats, bvh.tri_material, scene.geometry.corner_uv)
        #: The bounce loop's per-triangle figures in one (T, TRI_COLUMNS) float64 gather
        #: (``bounce_layout.TRI_*`` columns): F, the material's opacity and ior, the
        #: element id of reflector triangles (-1 elsewhere), 1 where textured.
        self.tri_table = np.empty((n_tri, TRI_COLUMNS))
        self.tri_table[:, TRI_F] = self.tri_f
        self.tri_table[:, TRI_ALPHA] = self.opacity[bvh.tri_material]
        self.tri_table[:, TRI_IOR] = self.ior[bvh.tri_material]
        self.tri_table[:, TRI_REFLECTOR] = np.where(self.tri_reflector, tri_element, -1)
        self.tri_table[:, TRI_TEXTURED] = self._tri_textured if self._textures else 0.0

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[Hits, np.ndarray]:
        """Nearest hits that are there (``Bvh.intersect`` through cut-out holes, see the
        module) of rays from rel ``origins`` (n, 3) along unit ``dirs`` (n, 3), and the
        batch index of every re-cast ray (k,) int64 (one entry per extra ray cast)."""
        hits = self._bvh.intersect(origins, dirs)
        if not self.cutouts.any or len(hits.ray) == 0:
            return hits, hits.ray[:0]
        ray = hits.ray
        tri, u, v = hits.tri.copy(), hits.u.copy(), hits.v.copy()
        extra = []
        # Rays whose current hit is a hole, with the index into (ray, tri, u, v).
        pending = np.flatnonzero(self._holes(tri, u, v))
        for _ in range(surface.MAX_CUTOUT_LAYERS):
            if len(pending) == 0:
                break
            rows = ray[pending]
            d = np.take(dirs, rows, axis=0)
            o, _ = self._past(tri[pending], u[pending], v[pending], d)
            again = self._bvh.intersect(o, d)
            extra.append(rows)
            gone = pending[again.miss]
            tri[gone] = -1  # through the last hole, nothing: a miss
            found = pending[again.ray]
            tri[found], u[found], v[found] = again.tri, again.u, again.v
            pending = found[self._holes(again.tri, again.u, again.v)]
        tri[pending] = -1  # still in holes after the bound: a miss (module docstring)
        keep = tri >= 0
        recast = np.concatenate(extra) if extra else ray[:0]
        if keep.all():
            return Hits(ray, tri, u, v, hits.miss), recast
        miss = np.sort(np.concatenate([hits.miss, ray[~keep]]))
        return Hits(ray[keep], tri[keep], u[keep], v[keep], miss), recast

    def nearest(self, origins: np.ndarray, dirs: np.ndarray):
        """``intersect`` as the bounce kernel takes it, for rays from rel ``origins``
        along unit ``dirs`` ((n, 3) float32 C-contiguous): the eight arrays of
        ``Bvh.answers`` (Embree's answers of both BVHs and their id maps; through cut-out
        holes already merged into global ids, maps empty) and the batch index of every
        re-cast ray (k,) int64."""
        if not self.cutouts.any:
            return self._bvh.answers(origins, dirs), _NO_RAYS
        hits, recast = self.intersect(origins, dirs)
        n = len(origins)
        prim = np.full(n, -1, np.int64)
        u, v = np.zeros(n, np.float32), np.zeros(n, np.float32)
        prim[hits.ray], u[hits.ray], v[hits.ray] = hits.tri, hits.u, hits.v
        return (prim, u, v, *NO_ANIMATED, GLOBAL_IDS, GLOBAL_IDS), recast

    def mapped_normals(self, answer, dirs) -> np.ndarray:
        """Shading normals (n, 3) float32 at the hits of ``nearest``'s ``answer`` along
        unit ``dirs`` (n, 3) float32 (miss rows zero) with the normal maps applied, for
        the bounce kernel to use instead of its own surface rule; (0, 3) when the stage
        has no normal map (the kernel's rule is the whole rule then)."""
        if not self.normal_maps.any:
            return _NO_NORMALS
        prim, u, v = self._bvh.merge(answer)
        hit = np.flatnonzero(prim >= 0)
        _, _, ns = self.geometry(prim[hit], u[hit], v[hit], np.take(dirs, hit, axis=0))
        out = np.zeros((len(prim), 3), np.float32)
        out[hit] = ns
        return out

    def occluded(self, origins, dirs, tfar, threads=None) -> np.ndarray:
        """(n,) bool: something that is there (not a cut-out hole) lies on each ray from
        rel ``origins`` (n, 3) along unit ``dirs`` (n, 3) within ``tfar`` (n,) metres
        (``Bvh.run`` OCCLUDED; through holes by nearest-hit re-casts, see the module)."""
        occluded = self._bvh.run("OCCLUDED", origins, dirs, tfar, threads)
        if not self.cutouts.any or not occluded.any():
            return occluded
        rows = np.flatnonzero(occluded)
        o = np.asarray(origins, np.float64)[rows]
        d = np.asarray(dirs, np.float64)[rows]
        left = np.asarray(tfar, np.float64)[rows]
        for _ in range(surface.MAX_CUTOUT_LAYERS + 1):
            tri, u, v = self._bvh.run("INTERSECT", o, d, left, threads)
            tri = np.asarray(tri, np.int64)
            hit = tri >= 0
            hole = np.zeros(len(rows), dtype=bool)
            hole[hit] = self._holes(tri[hit], u[hit], v[hit])
            occluded[rows[~hit]] = False  # nothing within reach
            if not hole.any():
                return occluded
            # Through the holes: on from just past them, the rest of the way.
            k = np.flatnonzero(hole)
            start = o[k]
            o_next, _ = self._past(tri[k], u[k], v[k], d[k])
            left = left[k] - np.einsum("ij,ij->i", o_next - start, d[k])
            rows, o, d = rows[k], o_next, d[k]
            left = np.maximum(left, 0.0)
        occluded[rows] = False  # still in holes after the bound: unoccluded
        return occluded

    def _holes(self, tri, u, v) -> np.ndarray:
        """(m,) bool: hits (tri, u, v (m,)) on cut-out holes."""
        return self.cutouts.holes(tri, surface.weights_from_uv(u, v))

    def _past(self, tri, u, v, dirs):
        """Rel origins (m, 3) just past hits (tri, u, v) along ``dirs`` (m, 3) (the
        boundary's offset, to the side the ray leaves to) and the hit points."""
        g = np.take(self._bvh.table.frame, tri, axis=0)
        pos = surface.positions(g, u, v)
        return self._bvh.boundary.offset(pos, g[:, 3], dirs), pos

    def at(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, incoming: np.ndarray):
        """Everything shading needs at hits on triangles ``tri`` (m,) with barycentrics u, v:
        rel position (m, 3) float64; geometric normal (m, 3) float64 and shading normal
        (m, 3) float32, both facing against ``incoming`` (m, 3); albedo and emissive
        (m, 3) float32 (emissive (3,) zeros when the stage has no emission)."""
        pos, ng, ns = self.geometry(tri, u, v, incoming)
        albedo, emissive = self.colour(tri, u, v)
        return pos, ng, ns, albedo, emissive

    def geometry(self, tri, u, v, incoming):
        """``at``'s position, geometric normal and shading normal (what a path needs to
        continue; colour is looked up later, once per call), by the compiled surface
        rule (``model.surface_kernels.hit_geometry``)."""
        table = self._bvh.table
        m = len(tri)
        tri = np.ascontiguousarray(tri, dtype=np.int64)
        u = np.ascontiguousarray(u, dtype=np.float32)
        v = np.ascontiguousarray(v, dtype=np.float32)
        incoming = np.ascontiguousarray(incoming, dtype=np.float64)
        pos, ng = np.empty((m, 3)), np.empty((m, 3))
        ns = np.empty((m, 3), dtype=np.float32)
        _SURFACE.hit_geometry(tri, u, v, incoming, table.frame, table.corners, pos, ng, ns)
        if self.normal_maps.any:
            self.normal_maps.apply(ns, tri, surface.weights_from_uv(u, v), incoming, table)
        return pos, ng, ns

    def colour(self, tri, u, v, albedo=None, textured=None):
        """``at``'s albedo (m, 3) float32 (texture lookup where the material has one) and
        emissive ((m, 3) float32, or (3,) zeros without emission). ``albedo``: the
        interpolated corner albedo (m, 3) float32 when the caller has it (the bounce
        kernel's), textures are then applied to it in place. ``textured``: whether some
        hit's material has an albedo texture, when the caller knows (the bounce kernel
        counts them), else None (looked up here)."""
        if albedo is None:
            tri = np.ascontiguousarray(tri, dtype=np.int64)
            u = np.ascontiguousarray(u, dtype=np.float32)
            v = np.ascontiguousarray(v, dtype=np.float32)
            albedo = np.empty((len(tri), 3), dtype=np.float32)
            _SURFACE.hit_albedo(tri, u, v, self._bvh.table.corners, albedo)
        uv = self._scene.geometry.corner_uv
        if textured is None:
            textured = len(self._tri_textured) and self._tri_textured[tri].any()
        if textured or self._textured_emission:
            weights = surface.weights_from_uv(u, v)
        if textured:
            surface.texture_albedo(
                albedo, tri, weights, self._bvh.tri_material, uv, self._textures,
                inputs=self._inputs,
            )  # fmt: skip
        if self._textured_emission:
            emissive = surface.emissive_values(
                self._scene.materials, tri, weights, self._bvh.tri_material, uv
            )
        elif self._has_emission:
            emissive = self._emissive[np.take(self._bvh.tri_material, tri)]
        else:
            emissive = np.zeros(3, np.float32)
        return albedo, emissive

    def surface(self, tri, u, v, albedo) -> np.ndarray:
        """(m, SURFACE_COLUMNS) float32 UsdPreviewSurface rows (``model.preview_surface``)
        of hits on triangles ``tri`` (m,) at barycentrics u, v with their ``albedo``
        (m, 3) (``colour``'s): the material's inputs, textured ones sampled; the
        ambient's specular part left to the reflection on reflector triangles (their
        mirror child carries it, ``shade_kernels.ambient_weight``)."""
        tri = np.asarray(tri, np.int64)
        return shading.point_surface(
            self._scene.materials, self._bvh.tri_material, tri, albedo,
            self._scene.geometry.corner_uv, lambda: surface.weights_from_uv(u, v),
            self._specular_ambient[tri],
        )  # fmt: skip

    def weighted(self, into, tri):
        """``into`` (total, slot, weight) of a batch of hits on triangles ``tri`` with
        each weight times the triangle's ``local_scale`` (None stays None)."""
        if into is None or not np.any(self.local_scale != 1.0):
            return into
        total, slot, weight = into
        return total, slot, weight * self.local_scale[np.asarray(tri, np.int64)]

    def snap(self, rel: np.ndarray, tri: np.ndarray, fallback: np.ndarray):
        """Project rel positions (n, 3) (e.g. from a depth buffer) onto the plane of
        their triangle (n,): removes depth-buffer error before offsetting. Returns the
        positions and the triangles' unit front-face normals (n, 3); rows with tri = -1
        keep their position and get the ``fallback`` (n, 3) normal."""
        ok = tri >= 0
        every = bool(ok.all())
        g = np.take(self._bvh.table.frame, tri if every else np.where(ok, tri, 0), axis=0)
        normal = g[:, 3] if every else np.where(ok[:, None], g[:, 3], fallback)
        out = np.asarray(rel, dtype=np.float64) - g[:, 0]  # relative to vertex 0
        dist = np.einsum("ij,ij->i", out, normal)
        if not every:
            dist[~ok] = 0.0
        out -= dist[:, None] * normal
        out += g[:, 0]
        return out, normal


#: ``nearest``'s re-casts without cut-outs, ``mapped_normals`` without normal maps.
_NO_RAYS = np.zeros(0, np.int64)
_NO_NORMALS = np.zeros((0, 3), np.float32)
