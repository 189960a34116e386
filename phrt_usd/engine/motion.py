"""Motion vectors: where each pixel's surface was on screen in the previous frame.

The convention (the ``motion`` RenderVar, EXR channels ``motion.x`` and ``motion.y``,
docs/motion-vectors.md): per pixel, in **pixels**, the pixel's position in this frame
**minus** the position its surface point had in the previous frame, **+x right, +y
down** (rows count down from the top, as the image's do). The pixel (col, row) of this
frame showed, in the previous one, at (col - motion.x, row - motion.y); a still camera
over a still scene gives 0 everywhere. Positions are pixel centres: (col + 0.5, row +
0.5) this frame, the exact projection of the surface point in the previous one.

Exact, from what the frame already holds:

- the surface point of a covered pixel is the G-buffer's ``position`` (float64 world
  metres, the pixel's ray on its triangle's plane); a point of a static element was where
  it is, and is projected with the previous frame's camera (``FrameCamera``:
  world-to-camera and projection at that time code);
- a point of an element that moved or deformed since the previous frame (an animated
  element: ``Element.animated``, announced by ``Scene.versions``) keeps its barycentric
  coordinates on its triangle: its previous position is the same combination of the
  triangle's previous vertices (``MotionTracker`` keeps the animated elements' vertices
  of the previous frame). That is exact for rigid transforms and for deformations alike
  (topology does not change over time);
- a background pixel sees the environment at infinity: its direction is projected with
  the previous camera's rotation (translation moves nothing at infinity).

Rules and limits: the *previous frame* is the frame before this one in the renderer's
plan (``FrameRenderer.plan``, the run's frames in order), so a resumed run and a chunk
with warm-up frames give the files an uninterrupted run gives; the first planned frame
has zero motion (so has every pixel of a frame without a previous one). A surface point
behind the previous camera (no previous pixel) has motion 0 and no previous depth
(``MotionField.previous_depth`` is NaN there). An element edited in memory that is not
flagged animated is taken as still (its previous vertices were never kept).

The field is computed when first asked for (``MotionField.vectors``), outside the
frame's timed phases: a frame that writes no motion and reuses nothing pays nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from phrt_usd.model.frame import FrameCamera, GBuffer
from phrt_usd.model.scene import ElementTriangles, Scene

#: A triangle whose barycentric system has a determinant below this share of its squared
#: edge lengths is degenerate (a sliver or a point): its pixels move by the mean motion of
#: its corners instead.
DEGENERATE_TRIANGLE = 1e-12


@dataclass(frozen=True)
class VertexMotion:
    """The vertices of the elements that moved or deformed between two frames.

    tri_rows     : (n,) int64 ascending triangle rows of those elements
    tri_vertices : (n, 3) int64 their corners' vertex indices (this frame's winding)
    vertex_ids   : (v,) int64 ascending vertex indices of those corners
    previous, current : (v, 3) float64 world metres of those vertices at the previous
                   frame and at this one
    """

    tri_rows: np.ndarray
    tri_vertices: np.ndarray
    vertex_ids: np.ndarray
    previous: np.ndarray
    current: np.ndarray

    def previous_points(self, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(m, 3) float64 previous world positions of ``points`` (m, 3) lying on
        ``triangles`` (m,) int64 rows: the same barycentric coordinates on the previous
        vertices; points on other triangles are returned unchanged."""
        out = np.array(points, dtype=np.float64, copy=True)
        if not len(self.tri_rows) or not len(triangles):
            return out
        k = np.minimum(np.searchsorted(self.tri_rows, triangles), len(self.tri_rows) - 1)
        hit = self.tri_rows[k] == triangles
        if not hit.any():
            return out
        corners = np.searchsorted(self.vertex_ids, self.tri_vertices[k[hit]])  # (h, 3)
        now, before = self.current[corners], self.previous[corners]  # (h, 3, 3)
        out[hit] = _same_barycentrics(out[hit], now, before)
        return out


def _same_barycentrics(points: np.ndarray, now: np.ndarray, before: np.ndarray) -> np.ndarray:
    """(h, 3) the points with the barycentric coordinates ``points`` (h, 3) have on the
    triangles ``now`` (h, 3 corners, 3) placed on ``before`` (h, 3, 3); a degenerate
    triangle (DEGENERATE_TRIANGLE) moves its points by its corners' mean motion."""
    e1, e2, d = now[:, 1] - now[:, 0], now[:, 2] - now[:, 0], points - now[:, 0]
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    d1, d2 = (d * e1).sum(1), (d * e2).sum(1)
    det = d11 * d22 - d12 * d12
    good = det > DEGENERATE_TRIANGLE * d11 * d22
    safe = np.where(good, det, 1.0)
    b1 = (d22 * d1 - d12 * d2) / safe
    b2 = (d11 * d2 - d12 * d1) / safe
    moved = (
        before[:, 0]
        + b1[:, None] * (before[:, 1] - before[:, 0])
        + b2[:, None] * (before[:, 2] - before[:, 0])
    )
    shifted = points + (before - now).mean(axis=1)
    return np.where(good[:, None], moved, shifted)


def project_points(camera: FrameCamera, points: np.ndarray, width: int, height: int):
    """Pixel positions (n, 2) float64 (col, row: pixel centres at +0.5, row 0 at the top)
    and view depths (n,) float64 of world ``points`` (n, 3) through ``camera``'s
    matrices; a point at depth <= 0 (behind the camera) gets NaN pixels."""
    clip = _affine(camera.clip_from_world, points, 1.0)
    depth = -_affine(camera.camera_from_world[2:3], points, 1.0)[0]
    return _pixels(clip, width, height), depth


def project_directions(camera: FrameCamera, directions: np.ndarray, width: int, height: int):
    """Pixel positions (n, 2) float64 of world ``directions`` (n, 3) (points at infinity)
    through ``camera``; NaN for a direction behind it."""
    return _pixels(_affine(camera.clip_from_world, directions, 0.0), width, height)


def _affine(matrix: np.ndarray, points: np.ndarray, w: float) -> list[np.ndarray]:
    """The rows of ``matrix`` (k, 4) applied to ``points`` (n, 3) with homogeneous
    coordinate ``w`` (1 points, 0 directions): k arrays (n,) float64, one multiply-add a
    component (small matrix products through BLAS cost several times that)."""
    x, y, z = (np.ascontiguousarray(points[:, i], dtype=np.float64) for i in range(3))
    return [m[0] * x + m[1] * y + m[2] * z + m[3] * w for m in matrix]


def _pixels(clip: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """Pixel (col, row) of clip-space points (x, y, z, w arrays (n,)): NDC (x, y) →
    ((x + 1) W / 2, (1 - y) H / 2) (``FrameCamera``); NaN where w <= 0."""
    x, y, _, w = clip
    ahead = w > 0.0
    inverse = np.where(ahead, 0.5 / np.where(ahead, w, 1.0), np.nan)
    out = np.empty((len(w), 2), np.float64)
    out[:, 0] = (x * inverse + 0.5) * width
    out[:, 1] = (0.5 - y * inverse) * height
    return out


def pixel_directions(camera: FrameCamera, width: int, height: int) -> np.ndarray:
    """(H * W, 3) float64 world directions (not normalised) through the pixel centres
    of ``camera``'s image, row-major: its projection inverted at NDC depth 0."""
    cols = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    rows = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    x, y = np.meshgrid(cols, rows)
    ndc = np.stack([x.ravel(), y.ravel(), np.zeros(x.size), np.ones(x.size)], axis=1)
    cam = ndc @ np.linalg.inv(camera.projection).T
    cam = cam[:, :3] / cam[:, 3:4]  # a point on each pixel's ray; the eye is the origin
    world_from_camera = np.linalg.inv(camera.camera_from_world)
    return cam @ world_from_camera[:3, :3].T


@dataclass
class MotionField:
    """The motion vectors of one frame (module docstring), computed when first asked for.

    gbuffer  : the frame's G-buffer (positions, triangle and element ids)
    camera   : the frame's camera; previous: the previous frame's, None for none
    vertices : the elements that moved or deformed since the previous frame, None: none
    """

    gbuffer: GBuffer
    camera: FrameCamera
    previous: FrameCamera | None = None
    vertices: VertexMotion | None = None
    _vectors: np.ndarray | None = field(default=None, repr=False)
    _previous_depth: np.ndarray | None = field(default=None, repr=False)

    @property
    def has_previous(self) -> bool:
        """False for a frame without a previous one (all motion 0)."""
        return self.previous is not None

    @property
    def vectors(self) -> np.ndarray:
        """(H, W, 2) float32 motion in pixels, (x right, y down), this frame's position
        minus the previous frame's (module docstring); 0 without a previous frame."""
        if self._vectors is None:
            self._compute()
        return self._vectors

    @property
    def previous_depth(self) -> np.ndarray:
        """(H, W) float32 view depth (metres) each covered pixel's surface point had in
        the previous frame's camera: inf for background, NaN behind that camera; this
        frame's depth without a previous frame. What a reprojection compares with the
        previous frame's depth to find pixels that were hidden then."""
        if self._previous_depth is None:
            self._compute()
        return self._previous_depth

    def _compute(self) -> None:
        gb = self.gbuffer
        height, width = gb.shape
        vectors = np.zeros((height, width, 2), np.float32)
        depth = np.array(gb.depth, dtype=np.float32, copy=True)
        if self.previous is None:
            self._vectors, self._previous_depth = vectors, depth
            return
        flat = vectors.reshape(-1, 2)
        covered = np.flatnonzero(gb.covered.reshape(-1))
        background = np.flatnonzero(~gb.covered.reshape(-1))

        def centres(pixels: np.ndarray) -> np.ndarray:
            rows, cols = np.divmod(pixels, width)
            return np.stack([cols + 0.5, rows + 0.5], axis=1)

        if len(covered):
            points = gb.position.reshape(-1, 3)[covered].astype(np.float64)
            if self.vertices is not None:
                tris = gb.triangle_id.reshape(-1)[covered].astype(np.int64)
                points = self.vertices.previous_points(tris, points)
            then, then_depth = project_points(self.previous, points, width, height)
            ahead = then_depth > 0.0
            move = centres(covered) - then
            move[~ahead] = 0.0
            flat[covered] = move
            depth.reshape(-1)[covered] = np.where(ahead, then_depth, np.nan)
        if len(background):
            directions = pixel_directions(self.camera, width, height)[background]
            then = project_directions(self.previous, directions, width, height)
            move = centres(background) - then
            flat[background] = np.nan_to_num(move, nan=0.0)
        self._vectors, self._previous_depth = vectors, depth


class MotionTracker:
    """What one renderer remembers for motion vectors: the vertices of the scene's
    animated elements at the last time code it recorded (``time``), and the geometry
    version then, so that it finds which of them changed since (``Scene.versions``)."""

    def __init__(self, scene: Scene) -> None:
        self._elements = np.array(
            [i for i, e in enumerate(scene.elements) if e.animated], dtype=np.int64
        )
        self._rows = (
            ElementTriangles(scene.geometry.tri_element, len(scene.elements))
            if len(self._elements)
            else None
        )
        self._tracked = set(self._elements.tolist())
        #: element → (triangle rows, their vertex indices (n, 3), the element's sorted
        #: vertex ids, their positions at ``time``).
        self._kept: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._version = -1
        #: The time code whose vertices are kept, None before the first record.
        self.time: float | None = None

    @property
    def tracks_geometry(self) -> bool:
        """True when the scene has animated elements (else motion is the camera's)."""
        return bool(len(self._elements))

    def advance(self, scene: Scene, time: float) -> VertexMotion | None:
        """Record the animated elements' vertices at ``time`` (the scene as it is now)
        and return how those that changed since the last record moved (None when none
        did, or on the first record)."""
        first = self.time is None
        changed = (
            self._elements
            if first
            else np.array(
                [e for e in scene.versions.changed_since(self._version).tolist()
                 if e in self._tracked], dtype=np.int64)
        )  # fmt: skip
        self.time = float(time)
        self._version = scene.versions.geometry
        if not len(changed):
            return None
        geo = scene.geometry
        pieces = []
        for e in changed.tolist():
            before = self._kept.get(e)
            if before is None:
                tri_rows = self._rows.rows(np.array([e]))
                tri_vertices = geo.triangles[tri_rows].astype(np.int64)
                vertex_ids = np.unique(tri_vertices)
            else:
                tri_rows, _, vertex_ids, _ = before
                tri_vertices = geo.triangles[tri_rows].astype(np.int64)  # winding may flip
            now = np.array(geo.vertices[vertex_ids], dtype=np.float64)
            self._kept[e] = (tri_rows, tri_vertices, vertex_ids, now)
            if before is not None:
                pieces.append((tri_rows, tri_vertices, vertex_ids, before[3], now))
        if first or not pieces:
            return None
        return _joined(pieces)


def _joined(pieces) -> VertexMotion:
    """One ``VertexMotion`` of per-element (tri_rows, tri_vertices, vertex_ids, previous,
    current) pieces, sorted by triangle row and vertex id."""
    tri_rows = np.concatenate([p[0] for p in pieces])
    tri_vertices = np.concatenate([p[1] for p in pieces])
    vertex_ids = np.concatenate([p[2] for p in pieces])
    previous = np.concatenate([p[3] for p in pieces])
    current = np.concatenate([p[4] for p in pieces])
    order = np.argsort(tri_rows, kind="stable")
    ids, first = np.unique(vertex_ids, return_index=True)
    return VertexMotion(
        tri_rows[order], tri_vertices[order], ids, previous[first], current[first]
    )
