"""The shadow terminator of smooth meshes in the shadow maps' lookups (docs/hit-lighting.md,
"Smooth meshes").

A point of a mesh with interpolated normals is shaded as the smooth surface its normals
describe, but it lies on its flat triangle. Near the terminator, where that triangle
faces away from a light the shading normal faces, the flat neighbours shadow it though
the smooth surface is lit. The shadow rays start from the point lifted onto the smooth
surface (``trace_kernels.shadow_rays``, Hanika's rule, the lift faded out by n_g·l =
``TERMINATOR_FADE``); the maps' lookups test the same lifted point against each light
(``shaders/cube_lookup.frag``, ``map_lighting``, ``shadow_maps.distant_lookups``), so
that raster, hybrid and rt shadow a smooth mesh alike, and a pair the maps leave
undecided there goes to the same ray.

Shapes: n points (a G-buffer's covered pixels or the tracer's hits); rel = world metres
minus ``Scene.origin``, the space of the ``TriangleTable`` given.
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine.shading import on_pool
from phrt_usd.model.scene import Lights
from phrt_usd.model.surface import TERMINATOR_FADE, TriangleTable


class Terminator:
    """How n points' shadow tests follow the smooth surface.

    normals : (n, 3) float32, each point's unit face normal turned to its shading
              normal's side (its n_g, the fade's cosine), 0 where it does not move
    lifts   : (n, 3) float32 metres, each point's move onto the smooth surface (0 on a
              flat triangle, ``FLAT_CORNER_COS``, or at a concave corner)
    """

    def __init__(self, normals: np.ndarray, lifts: np.ndarray):
        self.normals = normals
        self.lifts = lifts

    @classmethod
    def of(
        cls, table: TriangleTable, points: np.ndarray, origin: np.ndarray,
        triangles: np.ndarray, shading_normals: np.ndarray, lights: Lights,
    ) -> Terminator | None:  # fmt: skip
        """The moves of ``points`` (n, 3) (``table``'s space is points - ``origin`` (3,))
        on ``triangles`` (n,) of ``table`` with unit ``shading_normals`` (n, 3) facing the
        viewer, for the shadow tests of ``lights``, or None when none of them moves (then
        the maps' lookups stay as they are). On a stage of DistantLights only, a point
        that none of them lights within the fade keeps its place: its move would be faded
        out to nothing, or the light does not reach it (the farm: most of its smooth
        points)."""
        tri = np.ascontiguousarray(triangles, np.int64).reshape(-1)
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        origin = np.asarray(origin, np.float64).reshape(3)
        ns = np.ascontiguousarray(shading_normals).reshape(-1, 3)
        normals = np.empty((len(tri), 3), np.float32)
        lifts = np.empty((len(tri), 3), np.float32)
        distant = np.array([d.direction for d in lights.distant], np.float64).reshape(-1, 3)
        distant /= np.maximum(np.linalg.norm(distant, axis=1, keepdims=True), 1e-300)
        local = bool(lights.local)
        moved = []

        def run(part: slice) -> None:  # a gather of table rows a point: on the shading pool
            moved.append(_kernels().terminator_lifts(
                points[part], origin, tri[part], ns[part], table.smooth, table.plane,
                table.frame, table.corners, distant, local, TERMINATOR_FADE, normals[part],
                lifts[part],
            ))  # fmt: skip

        on_pool(run, len(tri))
        return cls(normals, lifts) if sum(moved) else None

    def lifted(self, rel: np.ndarray, rows: np.ndarray, to_light: np.ndarray) -> np.ndarray:
        """Points ``rows`` (m,) at ``rel`` (m, 3) float64 as their shadow test against a
        light in directions ``to_light`` (m, 3) or (3,) (any length; 0: no move) sees
        them (m, 3) float64: moved onto the smooth surface where their face normal turns
        from the light, the move faded out by n_g·l = TERMINATOR_FADE, as the shadow
        rays'."""
        rows = np.asarray(rows, np.int64)
        ng = self.normals[rows]
        to_light = np.broadcast_to(np.asarray(to_light, np.float64), ng.shape)
        length = np.linalg.norm(to_light, axis=1)
        up = np.einsum("ij,ij->i", ng, to_light) / np.maximum(length, 1e-300)
        up[length == 0.0] = np.inf  # no direction (a point at the light): no move
        fade = np.clip(1.0 - up / TERMINATOR_FADE, 0.0, 1.0)
        return np.asarray(rel, np.float64) + fade[:, None] * self.lifts[rows]


def _kernels():
    """The compiled surface kernels, taken on first use."""
    return kernels.load("phrt_usd.model.surface_kernels")
