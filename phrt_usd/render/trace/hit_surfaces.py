"""The surface at ray hits: per-triangle materials and the one surface rule.

``HitSurfaces`` turns Embree hits (triangle id, barycentrics u, v) into what paths and
shading need: rel position, geometric and shading normals (``model.surface``'s rule, the
same as the raster G-buffer's, so ``rt`` and raster agree at grazing pixels), albedo
(texture lookup where the material has one), emission, and the per-triangle material
figures the bounce loop reads (reflector flag, reflectivity F, opacity, ior).

Spaces: rel = world metres minus ``Scene.origin``, float64 (``bvh.Float32Boundary``).
Hit points are rebuilt in float64 from the hit triangle's rel vertices and Embree's
barycentrics (not ``origin + t * dir``), so they lie on the surface to float64 precision.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.model import surface
from phrt_usd.model.scene import Scene
from phrt_usd.render.trace.bvh import Bvh

#: Smallest index of refraction used (ior ≤ 0 is meaningless; Snell's law stays finite).
MIN_IOR = 1e-3


class HitSurfaces:
    """Materials of ``scene``'s triangles and the surface at hits on ``bvh``'s geometry
    (its table is read at call time, so animated refreshes are seen).

    tri_reflector : (T,) bool; tri_f : (T,) float64 reflectivity F (0 for
    non-reflectors); transmission : the stage has transmissive materials;
    opacity, ior : (M,) float64 per material (clamped to [0, 1] / ≥ ``MIN_IOR``).
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
        self.transmission = mats.has_transmission
        self.opacity = np.clip(np.asarray(mats.opacity, dtype=np.float64), 0.0, 1.0)
        self.ior = np.maximum(np.asarray(mats.ior, dtype=np.float64), MIN_IOR)
        emissive = np.asarray(mats.emissive, dtype=np.float32).reshape(-1, 3)
        self._has_emission = bool(np.any(emissive != 0))
        self._emissive = emissive
        self._textures = list(mats.textures) if scene.geometry.corner_uv is not None else []

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
        continue; colour is looked up later, once per call)."""
        table = self._bvh.table
        g = np.take(table.frame, tri, axis=0)  # np.take: ~3x faster than g[tri]
        pos = surface.positions(g, u, v)
        side = surface.viewer_side(np.einsum("ij,ij->i", g[:, 3], incoming))
        ng = g[:, 3] * side[:, None]
        corners = np.take(table.corners, tri, axis=0)  # (m, 3, 6)
        ns = surface.interpolate(corners[:, :, :3], surface.weights_from_uv(u, v))
        ns = surface.orient_shading_normals(ns, side, incoming, table, tri)
        return pos, ng, ns

    def colour(self, tri, u, v):
        """``at``'s albedo (m, 3) float32 (texture lookup where the material has one) and
        emissive ((m, 3) float32, or (3,) zeros without emission)."""
        weights = surface.weights_from_uv(u, v)
        corners = np.take(self._bvh.table.corners, tri, axis=0)  # (m, 3, 6)
        albedo = surface.interpolate(corners[:, :, 3:], weights)
        if self._textures:
            surface.texture_albedo(
                albedo,
                tri,
                weights,
                self._bvh.tri_material,
                self._scene.geometry.corner_uv,
                self._textures,
            )
        if self._has_emission:
            emissive = self._emissive[np.take(self._bvh.tri_material, tri)]
        else:
            emissive = np.zeros(3, np.float32)
        return albedo, emissive

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
