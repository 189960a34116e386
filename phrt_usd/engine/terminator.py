"""The shadow terminator of smooth meshes in the shadow maps' answers (docs/hit-lighting.md,
"Smooth meshes").

A point of a mesh with interpolated normals is shaded as the smooth surface its normals
describe, but a shadow map tests the depth of its flat triangle. Where that triangle
faces away from a light the shading normal faces (n_g·l below ``TERMINATOR_FADE``), the
flat neighbours shadow it in the map though the smooth surface is lit. The maps'
lookups therefore leave a pair they call shadowed within that band *undecided*
(``shaders/cube_lookup.frag``, ``map_lighting``), and it is settled as every undecided
pair is: by a shadow ray from the smooth surface (``trace_kernels.shadow_rays``, which
lifts its origin by Hanika's rule), or without a tracer by the maps' PCF at the point
lifted by the same rule (``Terminator.lifted``).

Shapes: n points (a G-buffer's covered pixels or the tracer's hits); rel = world metres
minus ``Scene.origin``, the space of the ``TriangleTable`` given.
"""

from __future__ import annotations

import numpy as np

from phrt_usd import kernels
from phrt_usd.model.surface import TERMINATOR_FADE, TriangleTable


class Terminator:
    """Which of n points follow a smooth surface in their shadow tests, and how.

    normals   : (n, 3) float32, each point's unit face normal turned to its shading
                normal's side, 0 where its triangle is flat (``FLAT_CORNER_COS``): the
                maps' lookup reads them (the band test)
    triangles : (n,) int64, each point's triangle in ``table`` (-1: none)
    """

    def __init__(self, normals: np.ndarray, triangles: np.ndarray, table: TriangleTable):
        self.normals = normals
        self.triangles = triangles
        self._table = table

    @classmethod
    def of(
        cls, table: TriangleTable, triangles: np.ndarray, shading_normals: np.ndarray
    ) -> Terminator | None:
        """The terminator data of points on ``triangles`` (n,) of ``table`` with unit
        ``shading_normals`` (n, 3) facing the viewer, or None when none of them lies on a
        smooth triangle (then the maps' answers stand as they are)."""
        tri = np.ascontiguousarray(triangles, np.int64).reshape(-1)
        normals = np.empty((len(tri), 3), np.float32)
        smooth = _kernels().terminator_normals(
            tri, np.ascontiguousarray(shading_normals).reshape(-1, 3), table.frame,
            table.corners, normals,
        )  # fmt: skip
        return cls(normals, tri, table) if smooth else None

    def lifted(self, rel: np.ndarray, rows: np.ndarray, to_light: np.ndarray) -> np.ndarray:
        """Points ``rows`` (m,) at ``rel`` (m, 3) float64 as their shadow test against a
        light in unit directions ``to_light`` (m, 3) (or (3,)) sees them: moved onto the
        smooth surface where their face normal turns from the light, the move faded out
        by n_g·l = TERMINATOR_FADE as the shadow rays' (m, 3) float64; flat points stay."""
        rows = np.asarray(rows, np.int64)
        ng = self.normals[rows]
        rel = np.ascontiguousarray(rel, np.float64).reshape(-1, 3)
        lift = np.empty((len(rows), 3))
        _kernels().terminator_lifts(
            rel, self.triangles[rows], ng, self._table.plane, self._table.frame,
            self._table.corners, lift,
        )  # fmt: skip
        up = np.einsum("ij,ij->i", ng, np.broadcast_to(to_light, ng.shape))
        fade = np.clip(1.0 - up / TERMINATOR_FADE, 0.0, 1.0)
        return rel + fade[:, None] * lift


def terminator_band(normals: np.ndarray, to_light: np.ndarray, shadowed: np.ndarray) -> np.ndarray:
    """(m,) bool: the pairs a shadow map's answer leaves undecided for the terminator's
    sake (the GPU lookup's ``terminator_band``): called ``shadowed`` (m,) bool by the map,
    on a smooth triangle (``Terminator.normals`` (m, 3) not 0) whose face normal is
    within TERMINATOR_FADE of turning from the light, unit ``to_light`` (m, 3) or (3,)."""
    up = np.einsum("ij,ij->i", normals, np.broadcast_to(to_light, normals.shape))
    smooth = np.einsum("ij,ij->i", normals, normals) > 0.5
    return shadowed & smooth & (up < TERMINATOR_FADE)


def _kernels():
    """The compiled surface kernels, taken on first use."""
    return kernels.load("phrt_usd.model.surface_kernels")
