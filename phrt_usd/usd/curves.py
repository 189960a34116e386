"""BasisCurves as tubes or ribbons: each curve swept by a circle of its width, or, where
the curves author ``normals``, by a flat strip of its width facing them; in the prim's
space.

UsdGeomBasisCurves as the schema defines it: ``curveVertexCounts`` split ``points`` into
curves; ``type`` ``linear`` (a polyline through the points) or ``cubic`` with ``basis``
``bezier`` (segments of 4 points stepping by 3), ``bspline`` or ``catmullRom`` (segments
stepping by 1); ``wrap`` ``nonperiodic``, ``periodic`` (closed: the segments wrap around)
or ``pinned`` (bspline and catmullRom: a phantom point mirrored at each end, ``2 P0 -
P1``, so the curve reaches its end points; for bezier the same as nonperiodic). Cubic
segments are sampled at ``SEGMENT_SAMPLES`` parameter steps.

``widths`` (diameters, stage units) in any interpolation: ``constant`` and ``uniform``
(one per curve) as they are; ``vertex`` (one per point) and ``varying`` (one per segment
end) interpolated linearly along the curve's parameter; unauthored, ``DEFAULT_WIDTH``
(Storm's). A ``hermite`` basis is drawn as its polyline. A colour primvar is carried
along the same way (``tube_corner_colours``).

The tube: ``TUBE_SIDES`` sides, a ring per sample in a frame carried along the curve by
parallel transport (no twist), its normals radial; the ends are open. The ribbon (as the
schema and Storm draw curves with authored ``normals``): a pair of vertices per sample,
``width / 2`` either side of the curve along ``tangent x normal``, the normal (carried
along the curve as widths are, then made perpendicular to the tangent) the strip's
normal at both; its triangles wound to face the normal.

``tube_geometry`` raises ``PhrtError`` (one line naming the attribute) for counts that do
not add up to the points or widths of the wrong count.
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdGeom

from phrt_usd.errors import PhrtError
from phrt_usd.usd.values import safe_normalize

#: Sides of the circle a curve's tube is swept with.
TUBE_SIDES = 8
#: Samples of each cubic segment along its parameter (the segment's start included, its
#: end being the next segment's start).
SEGMENT_SAMPLES = 4
#: Width of curves without ``widths`` (stage units), as Storm draws them.
DEFAULT_WIDTH = 1.0

#: Cubic bases: (4 x 4 matrix M, step): a segment's point at t is
#: ``[t^3, t^2, t, 1] @ M @ [P0, P1, P2, P3]``; segments start every ``step`` points.
_BASES = {
    "bezier": (np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 3, 0, 0], [1, 0, 0, 0]]), 3),
    "bspline": (np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 0, 3, 0], [1, 4, 1, 0]]) / 6, 1),
    "catmullRom": (
        np.array([[-1, 3, -3, 1], [2, -5, 4, -1], [-1, 0, 1, 0], [0, 2, 0, 0]]) / 2,
        1,
    ),
}


def _segments(n: int, basis: str, wrap: str) -> np.ndarray:
    """(s, 4) indices of a cubic curve's segments into its ``n`` points extended by
    one phantom point at each end (index 0 and n + 1, used by ``pinned``)."""
    _, step = _BASES[basis]
    start = np.arange(0, n, step)
    if wrap == "periodic":
        start = start[: n // step]
        return (start[:, None] + np.arange(4)) % n + 1
    if wrap == "pinned" and basis != "bezier":
        return np.arange(n - 1)[:, None] + np.arange(4)  # P_-1, P0, P1, P2 first
    start = start[start + 3 < n]
    return start[:, None] + np.arange(4) + 1


def _polylines(points, counts, kind: str, basis: str, wrap: str):
    """(samples (m, 3), curve index per sample (m,), parameter u in [0, 1] per sample)."""
    out, owner, param = [], [], []
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cubic = kind == "cubic" and basis in _BASES
    matrix = _BASES[basis][0] if cubic else None
    t = np.arange(SEGMENT_SAMPLES) / SEGMENT_SAMPLES
    powers = np.stack([t**3, t**2, t, np.ones_like(t)], axis=1) @ matrix if cubic else None
    for c, n in enumerate(counts):
        p = points[offsets[c] : offsets[c] + n]
        if n < 2:
            continue
        closed = wrap == "periodic"
        seg = _segments(n, basis, wrap) if cubic else np.zeros((0, 4), np.int64)
        if len(seg):
            ext = np.concatenate([2 * p[:1] - p[1:2], p, 2 * p[-1:] - p[-2:-1]])
            samples = np.einsum("tk,skd->std", powers, ext[seg]).reshape(-1, 3)
            last = (np.ones(4) @ matrix) @ ext[seg[-1]]  # the last segment's end, t = 1
            samples = np.concatenate([samples, samples[:1] if closed else last[None]])
        else:  # linear, or too few points for one cubic segment: the polyline
            samples = np.concatenate([p, p[:1]]) if closed else p
        out.append(samples)
        owner.append(np.full(len(samples), c))
        param.append(np.linspace(0.0, 1.0, len(samples)))
    if not out:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(out), np.concatenate(owner), np.concatenate(param)


def _along(values, interp: str, where: str, counts, kind, basis, wrap, owner, u):
    """(m, k) values of a primvar (``values`` (v, k), interpolation ``interp``) at each
    sample: ``constant`` as is, ``uniform`` per curve, ``vertex`` (one per point) and
    ``varying`` (one per segment end of a cubic curve) interpolated linearly along the
    curve's parameter. ``PhrtError`` naming ``where`` for a count that does not fit."""
    if interp == UsdGeom.Tokens.constant or len(values) == 1:
        return np.repeat(values[:1], len(owner), axis=0)
    if interp == UsdGeom.Tokens.uniform:
        per = np.ones(len(counts), np.int64)
    elif interp == UsdGeom.Tokens.vertex or kind != "cubic" or basis not in _BASES:
        per = np.asarray(counts, np.int64)
    else:  # varying: one per segment end
        per = np.array([len(_segments(n, basis, wrap)) + (wrap != "periodic")
                        for n in counts], np.int64)  # fmt: skip
    if per.sum() != len(values):
        raise PhrtError(
            f"{where}: {len(values)} values for {interp} interpolation, need {int(per.sum())}"
        )
    start = np.concatenate([[0], np.cumsum(per)[:-1]])[owner]
    x = u * (per[owner] - 1)
    k = np.minimum(np.floor(x).astype(np.int64), np.maximum(per[owner] - 2, 0))
    f = np.clip(x - k, 0.0, 1.0)[:, None]
    nxt = np.minimum(k + 1, per[owner] - 1)
    return values[start + k] * (1 - f) + values[start + nxt] * f


def _widths(prim: Usd.Prim, time: Usd.TimeCode, counts, kind, basis, wrap, owner, u):
    """(m,) width at each sample (see the module)."""
    curves = UsdGeom.BasisCurves(prim)
    values = curves.GetWidthsAttr().Get(time)
    if values is None or len(values) == 0:
        return np.full(len(owner), DEFAULT_WIDTH)
    w = np.abs(np.nan_to_num(np.asarray(values, np.float64))).reshape(-1, 1)
    where = f"{prim.GetPath()}.widths"
    interp = curves.GetWidthsInterpolation()
    return _along(w, interp, where, counts, kind, basis, wrap, owner, u)[:, 0]


def _curve_layout(prim: Usd.Prim, time: Usd.TimeCode):
    """(points (p, 3), counts, type, basis, wrap) of a BasisCurves prim; ``PhrtError``
    for counts that do not add up or points that are not finite."""
    curves = UsdGeom.BasisCurves(prim)
    points = np.asarray(curves.GetPointsAttr().Get(time) or [], np.float64).reshape(-1, 3)
    counts = np.asarray(curves.GetCurveVertexCountsAttr().Get(time) or [], np.int64)
    if (counts < 0).any() or counts.sum() != len(points):
        raise PhrtError(
            f"{prim.GetPath()}.curveVertexCounts: the counts add up to {int(counts.sum())}, "
            f"the curves have {len(points)} points"
        )
    if not np.all(np.isfinite(points)):
        raise PhrtError(f"{prim.GetPath()}.points: not every point is finite")
    kind = str(curves.GetTypeAttr().Get(time) or "cubic")
    basis = str(curves.GetBasisAttr().Get(time) or "bezier")
    wrap = str(curves.GetWrapAttr().Get(time) or "nonperiodic")
    return points, counts, kind, basis, wrap


def tube_corner_colours(prim: Usd.Prim, time: Usd.TimeCode, values, interp: str, where: str):
    """(T, 3, 3) the colour primvar ``values`` ((v, 3), interpolation ``interp``) at the
    corners of ``tube_geometry``'s triangles: each ring (or ribbon pair) takes its
    sample's value."""
    points, counts, kind, basis, wrap = _curve_layout(prim, time)
    samples, owner, u = _polylines(points, counts, kind, basis, wrap)
    per_sample = _along(np.asarray(values, np.float64).reshape(-1, 3), interp, where,
                        counts, kind, basis, wrap, owner, u)  # fmt: skip
    if _authored_normals(prim, time) is not None:
        return per_sample[_ribbon_triangles(owner) // 2]
    return per_sample[_triangles(owner) // TUBE_SIDES]


def _authored_normals(prim: Usd.Prim, time: Usd.TimeCode):
    """((v, 3) normals, interpolation) of curves that author ``normals`` (ribbons), else
    None."""
    curves = UsdGeom.BasisCurves(prim)
    values = curves.GetNormalsAttr().Get(time)
    if values is None or len(values) == 0:
        return None
    normals = np.nan_to_num(np.asarray(values, np.float64)).reshape(-1, 3)
    return normals, str(curves.GetNormalsInterpolation())


def _ribbon_triangles(owner: np.ndarray) -> np.ndarray:
    """(T, 3) the ribbon's triangles over pairs of vertices (2 i: the ``+ side`` one,
    2 i + 1 the ``- side`` one, per sample i): one quad between consecutive samples of
    one curve, wound so that its geometric normal is ``tangent x side`` (the normal)."""
    k = np.flatnonzero(owner[1:] == owner[:-1])
    a0, a1, b0, b1 = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
    return np.concatenate([np.stack([a0, b0, b1], 1), np.stack([a0, b1, a1], 1)]).astype(
        np.int64
    )


def _triangles(owner: np.ndarray) -> np.ndarray:
    """(T, 3) the tube's triangles over rings of ``TUBE_SIDES`` vertices, one ring per
    sample: the quads between consecutive samples of one curve, (a, c, b) and (a, d, c)
    facing out."""
    k = np.flatnonzero(owner[1:] == owner[:-1])
    j = np.arange(TUBE_SIDES)
    a = (k[:, None] * TUBE_SIDES + j).reshape(-1)
    d = (k[:, None] * TUBE_SIDES + (j + 1) % TUBE_SIDES).reshape(-1)
    b, c = a + TUBE_SIDES, d + TUBE_SIDES
    return np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)]).astype(np.int64)


def _frames(samples: np.ndarray, owner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normal, binormal) (m, 3) each: a frame per sample carried along each curve by
    parallel transport from a start normal perpendicular to the first tangent."""
    first = np.r_[True, owner[1:] != owner[:-1]]
    tangent = _tangents(samples, owner)
    normal = np.zeros_like(samples)
    # A start normal: the tangent crossed with the axis it is least aligned with.
    axis = np.eye(3)[np.argmin(np.abs(tangent[first]), axis=1)]
    normal[first] = safe_normalize(np.cross(tangent[first], axis))
    starts = np.flatnonzero(first)
    lengths = np.diff(np.r_[starts, len(samples)])
    for k in range(1, int(lengths.max()) if len(lengths) else 0):
        rows = starts[lengths > k] + k
        prev = normal[rows - 1]
        t = tangent[rows]
        n = prev - np.sum(prev * t, axis=1, keepdims=True) * t
        ok = np.linalg.norm(n, axis=1) > 1e-9
        normal[rows] = np.where(ok[:, None], safe_normalize(n), prev)
    return normal, np.cross(tangent, normal)


def _tangents(samples: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(m, 3) unit tangent per sample (central differences within each curve)."""
    ahead = np.roll(samples, -1, axis=0)
    behind = np.roll(samples, 1, axis=0)
    first = np.r_[True, owner[1:] != owner[:-1]]
    last = np.r_[owner[1:] != owner[:-1], True]
    ahead[last] = samples[last]
    behind[first] = samples[first]
    return safe_normalize(ahead - behind)


def tube_geometry(prim: Usd.Prim, time: Usd.TimeCode):
    """Points (n, 3), triangles (T, 3) counter-clockwise from outside (a ribbon's: seen
    from its normals' side), corner normals (T, 3, 3) of the tubes, or the ribbons where
    ``normals`` are authored, of a BasisCurves prim, in its space (the module)."""
    points, counts, kind, basis, wrap = _curve_layout(prim, time)
    samples, owner, u = _polylines(points, counts, kind, basis, wrap)
    radius = 0.5 * _widths(prim, time, counts, kind, basis, wrap, owner, u)
    authored = _authored_normals(prim, time)
    if authored is not None:
        where = f"{prim.GetPath()}.normals"
        along = _along(authored[0], authored[1], where, counts, kind, basis, wrap, owner, u)
        tangent = _tangents(samples, owner)
        facing = safe_normalize(along - np.sum(along * tangent, axis=1, keepdims=True) * tangent)
        side = safe_normalize(np.cross(tangent, facing))
        pair = np.stack([samples + radius[:, None] * side, samples - radius[:, None] * side], 1)
        triangles = _ribbon_triangles(owner)
        return pair.reshape(-1, 3), triangles, np.repeat(facing, 2, axis=0)[triangles]
    normal, binormal = _frames(samples, owner)
    angle = 2 * np.pi * np.arange(TUBE_SIDES) / TUBE_SIDES
    radial = (np.cos(angle)[None, :, None] * normal[:, None, :]
              + np.sin(angle)[None, :, None] * binormal[:, None, :])  # fmt: skip
    ring_points = samples[:, None, :] + radius[:, None, None] * radial
    triangles = _triangles(owner)
    return ring_points.reshape(-1, 3), triangles, radial.reshape(-1, 3)[triangles]
