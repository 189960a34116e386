"""The numpy form of the surface rule's side rule, as it stood before it was compiled
(``model.surface_kernels._orient``): the reference ``tests/model/test_surface_kernels.py``
checks the kernels against."""

from __future__ import annotations

import numpy as np

from phrt_usd.model.surface import MIN_NORMAL_LENGTH, TriangleTable


def viewer_side(facing: np.ndarray) -> np.ndarray:
    """(m,) float64: -1 where the viewer sees a triangle's back face, else +1, from
    ``facing`` (m,) = front-face normal · incoming ray direction as the caller's hit
    computed it (> 0: the ray runs along the normal, so the back face is seen)."""
    return np.where(facing > 0.0, -1.0, 1.0)


def orient_shading_normals(normals, side, incoming, table: TriangleTable, tri) -> np.ndarray:
    """The side rule (``model.surface``), in place on ``normals`` (m, 3) float32, the
    interpolated corner normals of triangles ``tri`` (m,): returns them unit and facing
    the viewer. side : (m,) ``viewer_side``; incoming : (m, 3) unit ray directions."""
    normals *= side.astype(np.float32)[:, None]
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    # ``~(length >= ...)`` also catches a NaN interpolated normal.
    bad = ~(length >= MIN_NORMAL_LENGTH) | (np.einsum("ij,ij->i", normals, incoming) >= 0.0)
    normals /= np.maximum(length, MIN_NORMAL_LENGTH)[:, None]
    if bad.any():
        rows = np.flatnonzero(bad)
        front = np.take(table.frame, np.take(tri, rows), axis=0)[:, 3]
        normals[rows] = front * side[rows][:, None]
    return normals
