"""Reuse across frames: the reflections a frame traced, reprojected into the next one.

A reflector traced at a reduced density starts rays on a pattern of its pixels that
rotates every frame (``sparse_pixels.rotation_phase``): over ``ROTATION_PERIOD`` frames
(2 from "half" up, 4 from "quarter", 8 from "eighth", 16 at "sixteenth") every pixel of
it is traced at least once. Its other
pixels take, where it is still valid, the reflection they had in the previous frame,
reprojected (``REUSED``, ``model/pixel_kinds.py``); only where no valid history exists
are they reconstructed from this frame's samples (``FILLED``, ``sparse_pixels``). A still
view therefore reaches full resolution in one rotation period, and a moving one keeps
what is still true of the last frames.

**Reprojection.** A mirror shows the reflected point at its *virtual image*: along the
pixel's view ray, at the surface's distance plus the reflection's hit distance (exact
for a planar mirror, whatever the camera does). Pixel p of this frame (surface point X,
view direction v) saw, in the previous frame, the same reflected point at the previous
camera's projection of X + h v, h the hit distance (a reflection that left the scene:
the direction v at infinity). h of a pixel not traced this frame is the previous
frame's at the surface's own reprojection (a fixed-point step: for a still camera both
give the same pixel). The element's own motion is not followed: a reflector that moved
or deformed since the previous frame keeps no history.

**Rejection** (history is used only when every test passes, otherwise the pixel is
filled):

- the previous pixel is on screen, of the same element, and its reflection was traced
  at most ``period - 1`` frames ago (``age``): stale history expires within one rotation
  period, which bounds how long anything wrong can persist (a moved object's ghost);
- normals agree within ``NORMAL_AGREEMENT`` and the previous pixel's surface point lies
  on this pixel's tangent plane within ``PLANE_TOLERANCE`` of the view depth (a
  disocclusion, a fold, another part of a curved reflector);
- the reprojected point falls within ``MAX_PIXEL_OFFSET`` of the previous pixel's
  centre (history is read from the nearest pixel: a chain of reuses must not drift);
- the temporal gradient: in each pattern cell, this frame's traced pixel is compared
  with its own reprojected history; a change above ``GRADIENT_LIMIT`` (display-range
  luminance) rejects the history of that cell and the 8 around it (A-SVGF's idea on the
  pattern's own strata: something in the reflection changed there);
- when an element moved or deformed since the previous frame, the range test: history
  outside the range of this frame's traced samples in its cell and the 8 around it (per
  channel, ``RANGE_TOLERANCE``) shows something no longer there (temporal
  anti-aliasing's neighbourhood clamp). Only then: on a still scene it would refuse
  true detail that no nearby sample happens to show.

Traced values replace history outright (mirror reflections have no noise to average
but the hit lighting's light sampling, which the gradient tolerates below its limit).

The pattern rotates only while history is worth looking up (the last probe's verdict,
``MIN_REPROJECTED``): where none would be taken, a rotating subset only flickers, so the
pattern then holds its phase until a probe finds the view reprojecting again.

Arrays: pixels are flat indices ``row * W + col``; radiance (n, 3) float32 linear RGB,
the reflected radiance before the reflector's F; positions float64 world metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phrt_usd.engine.trace.sparse_pixels import (
    LEVEL_PERIOD,
    LEVEL_SPACING,
    one_call,
    pixel_levels,
    rotation_phase,
)
from phrt_usd.model import pixel_kinds
from phrt_usd.model.frame import FrameCamera, GBuffer, ReflectionResult, flat_image

#: The age of a pixel without history (never traced, or not in the frame's
#: reflections).
NO_HISTORY = np.iinfo(np.int16).max
#: The age of a filled pixel: a fill is an estimate from its frame's samples, not a
#: value to carry forward as traced (reuse refuses it); only the accumulation of the
#: next frame's fill reads it (``accumulate``).
FILLED_AGE = NO_HISTORY - 1
#: Farthest the reprojected point may fall from its previous pixel's centre, in pixels
#: along either axis: history is read from the nearest pixel (a bilinear read would blur
#: it), so each reuse may shift the reflection by this much, and a chain of reuses over a
#: moving camera adds the shifts up; 0.25 px keeps a still view (0 px) and the slow
#: parts of a moving one.
MAX_PIXEL_OFFSET = 0.25
#: Least cosine between this pixel's normal and its previous pixel's: 0.95 (18 degrees)
#: keeps a planar reflector's history (the same normal everywhere) and a gently curved
#: one's under small motion, and rejects another facet or a curved part the virtual
#: image does not describe.
NORMAL_AGREEMENT = 0.95
#: Largest distance of the previous pixel's surface point from this pixel's tangent
#: plane, as a share of the view depth: G-buffer positions lie on their triangle's plane
#: (float64), so one plane gives ~1e-7; 0.5 % rejects a step in depth (a disocclusion)
#: of a few centimetres at 5 m and keeps float32 depth-buffer noise.
PLANE_TOLERANCE = 0.005
#: Largest change of a traced pixel's reflection from its reprojected history that keeps
#: the history of its cell, in display-range luminance (x / (1 + x), 0..1): 0.1 is an
#: edge FLIP sees; the hit lighting's light sampling stays well below it where the
#: shadow maps decide (docs/hit-lighting.md), and a moved object or light exceeds it.
GRADIENT_LIMIT = 0.1
#: How far outside the range of this frame's traced samples around it (per channel, in
#: the display range) history may lie and still be taken: 0.04 keeps the hit lighting's
#: sampling noise (below the gradient's limit) and refuses a colour no sample around
#: shows any more (a moved object's ghost, which the cell's own sample may have missed).
RANGE_TOLERANCE = 0.04
#: A round looks up the history of every PROBE_STRIDE-th skipped pixel first, and of
#: all only when at least MIN_REPROJECTED of those reproject onto a previous pixel that
#: passes every per-pixel test but the age (whether that pixel has history yet or not;
#: the gradient is not asked). The lookup and its bookkeeping cost about 70 ns a
#: skipped pixel, the fill it replaces about 110 (sewer 640x480, a sixteenth, 2
#: threads): where little would ever be reused (a moving camera over a rippled floor:
#: under a quarter of the pixels land within MAX_PIXEL_OFFSET of a pixel centre, and
#: 2-3 % end up reused) the full lookup is time taken from the budget for next to
#: nothing, and the probe costs a sixteenth of it. A still view reprojects every pixel
#: onto itself.
PROBE_STRIDE = 16
MIN_REPROJECTED = 0.5
#: A filled pixel (no valid history: a moving view, a rippled reflector) blends this
#: share of its previous value in, read from the nearest previous pixel (within half a
#: pixel: every on-screen reprojection) that passes the per-pixel tests and clamped to
#: the range of the traced samples its fill was made of (``accumulate``): temporal
#: anti-aliasing's exponential average, over about 1 / (1 - ACCUMULATION) frames. A
#: fill's error changes from frame to frame where the camera moves (the traced samples
#: land on other surface points), and the average halves that change; the clamp keeps
#: what no traced sample around shows any more (a ghost) out. Measured on the wet
#: tunnel (docs/temporal-reuse.md, "Accumulating fills").
ACCUMULATION = 0.5
#: The nearest-pixel read of ``accumulate``: any reprojection that lands on a pixel.
ACCUMULATION_OFFSET = 0.5
#: Rec. 709 luminance weights (linear RGB).
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class _Frame:
    """One frame's reflections as the next frame reads them, flat over its H*W pixels:
    radiance (H*W, 3) float32, hit (H*W,) float32 metres (+inf: left the scene), age
    (H*W,) int16 frames since traced (NO_HISTORY: none), and its G-buffer's element
    (H*W,) int32, normal (H*W, 3) float32, position (H*W, 3) float64; its camera's
    clip_from_world (4, 4) float64 (projection times world-to-camera)."""

    radiance: np.ndarray
    hit: np.ndarray
    age: np.ndarray
    element: np.ndarray
    normal: np.ndarray
    position: np.ndarray
    clip_from_world: np.ndarray


class ReflectionHistory:
    """The reflections of the frames one selection policy rendered, for the next frame
    (a renderer keeps one per policy: each policy's frames are their own sequence)."""

    def __init__(self) -> None:
        self._last: _Frame | None = None
        self._frames = 0
        #: The last probe's verdict (None: none yet) and the pattern's last phase.
        self._reprojects: bool | None = None
        self._phase = rotation_phase(0)
        # The reprojection's compiled code loaded now, before any frame's budget is
        # timed: its first call would otherwise take several ms of the second traced
        # frame's trace phase (a frame has history only from the second on).
        _kernels().warm_up()

    def begin(self, gbuffer: GBuffer, camera: FrameCamera, moved: np.ndarray,
              frame: int | None = None) -> FrameReuse:  # fmt: skip
        """The reuse of one frame: its G-buffer and camera, the ids ``moved`` (k,) int64
        of the elements that moved or deformed since the previous frame, ``frame`` the
        frame's index in the run's plan (the pattern's rotation; None: the count of frames
        begun so far). The previous frame is the one last ended (``end``)."""
        index = self._frames if frame is None else int(frame)
        self._frames += 1
        # The pattern rotates while history is taken: with none taken a rotating subset
        # only flickers (the wet tunnel at 5,000-10,000 rays: temporal error 0.032
        # rotating against 0.028 still), so it then holds its last phase.
        phase = rotation_phase(index) if self._reprojects is not False else self._phase
        self._phase = phase
        return FrameReuse(gbuffer, camera, self._last, moved, index, phase)

    def end(self, reuse: FrameReuse) -> None:
        """Keep ``reuse``'s frame as the previous one of the next frame, and whether its
        probe found history worth taking (``FrameReuse.reprojects``)."""
        self._last = reuse.finished()
        if reuse.reprojects is not None:
            self._reprojects = reuse.reprojects


class FrameReuse:
    """One frame's side of the history: it reprojects the previous frame's reflections
    for the tracer (``reprojected``), and collects this frame's (``record``).

    frame : the frame's index in its sequence; phase : the pattern's shift this frame
    (``ReflectionHistory.begin``'s: the rotation's at ``frame`` while history is taken,
    else the last one held)."""

    def __init__(self, gbuffer: GBuffer, camera: FrameCamera, previous: _Frame | None,
                 moved: np.ndarray, frame: int,
                 phase: tuple[int, int] | None = None) -> None:  # fmt: skip
        self.frame = frame
        self.phase = rotation_phase(frame) if phase is None else phase
        #: Whether this frame's probe found history worth looking up (None: no probe).
        self.reprojects: bool | None = None
        self._camera = camera
        self._previous = previous
        height, width = gbuffer.shape
        self._size = (width, height)
        self._element = flat_image(gbuffer.element_id, np.int32, 1)
        self._normal = flat_image(gbuffer.normal, np.float32, 3)
        self._position = flat_image(gbuffer.position, np.float64, 3)
        self._view = flat_image(gbuffer.view_dir, np.float32, 3)
        self._depth = flat_image(gbuffer.depth, np.float32, 1)
        #: (E + 1,) bool per element id (the last: id -1): moved since the previous frame.
        moved = np.asarray(moved, np.int64)
        self._moved_table = np.zeros(max(int(self._element.max(initial=-1)),
                                         int(moved.max(initial=-1))) + 2, np.bool_)  # fmt: skip
        self._moved_table[moved] = True
        self._scene_moved = bool(len(moved))
        #: The pixels each ``reprojected`` took and their ages, and the rounds'
        #: results, kept as history when the frame is finished (``finished``).
        self._taken: list[tuple[np.ndarray, np.ndarray]] = []
        self._results: list[ReflectionResult] = []

    # ------------------------------------------------------------------ reprojection

    def _lookup(self, pix: np.ndarray, hit: np.ndarray | None, period: np.ndarray,
                split=None):  # fmt: skip
        """For pixels ``pix`` (n,) int64: (n,) int64 the previous frame's pixel showing
        what each shows now (the virtual image's reprojection, module docstring; -1: off
        screen or behind the previous camera) and (n,) bool its history passes the
        per-pixel tests (all but the gradient), ``period`` (n,) int64 the frames the
        pixel's density rotates in. ``hit`` (n,) float32 the pixels' hit distances this
        frame, None: the previous frame's (the fixed-point step). Compiled:
        ``history_kernels.history_lookup``, over ``split`` (as ``sparse_pixels.
        fill_skipped``'s: the tracer's pool) when given."""
        prev = self._previous
        n = len(pix)
        q, ok = np.empty(n, np.int64), np.empty(n, np.bool_)
        own = hit is not None
        hit = np.ascontiguousarray(hit if own else np.zeros(0), np.float32)
        width, height = self._size
        if split is None:
            split = one_call
        split(
            _kernels().history_lookup, n, pix, hit, own, self._element, self._normal,
            self._position, self._view, self._depth, np.ascontiguousarray(period, np.int64),
            self._moved_table, prev.element, prev.age, prev.normal, prev.position, prev.hit,
            prev.clip_from_world, width, height, MAX_PIXEL_OFFSET, NORMAL_AGREEMENT,
            PLANE_TOLERANCE, out=(q, ok),
        )  # fmt: skip
        return q, ok

    def reprojected(
        self,
        traced_pix: np.ndarray,
        traced_src: np.ndarray,
        traced_radiance: np.ndarray,
        traced_hit: np.ndarray | None,
        skipped_pix: np.ndarray,
        skipped_src: np.ndarray,
        density,
        split=None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which skipped pixels of a reduced-density round take their history.

        traced_pix, traced_src (n,) int64, traced_radiance (n, 3) float32, traced_hit (n,)
        float32 or None: the round's traced pixels; skipped_pix, skipped_src (m,) int64:
        the pixels its pattern skipped; density: one of TRACE_DENSITIES for every source
        or one per source (``Tracer.trace_reflections``'); split: ``_lookup``'s. History
        is looked up for all skipped pixels only when a probe of every PROBE_STRIDE-th
        finds MIN_REPROJECTED of them reprojected (else none is taken). Returns (m,) bool
        the skipped pixels taking history, (k, 3) float32 their radiance and (k,) float32
        their hit distance (k the count taken)."""
        m = len(skipped_pix)
        none = (np.zeros(m, bool), np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
        if self._previous is None or m == 0:
            return none
        skipped_pix, traced_pix = _int64(skipped_pix), _int64(traced_pix)
        skipped_level = pixel_levels(density, skipped_src)
        traced_level = pixel_levels(density, traced_src)
        period = LEVEL_PERIOD[skipped_level]
        # The probe: every PROBE_STRIDE-th skipped pixel, every test but the age and the
        # gradient (MIN_REPROJECTED).
        probe = np.arange(0, m, PROBE_STRIDE)
        ages = np.full(len(probe), NO_HISTORY + 2, np.int64)  # even NO_HISTORY passes
        found = int(self._lookup(skipped_pix[probe], None, ages)[1].sum())
        self.reprojects = found >= MIN_REPROJECTED * len(probe)
        if not self.reprojects:
            return none
        # The temporal gradient: the pattern cells whose traced pixel changed.
        any_age = np.full(len(traced_pix), FILLED_AGE, np.int64)  # any traced history
        traced_then, traced_ok = self._lookup(traced_pix, traced_hit, any_age, split)
        traced_ok = np.flatnonzero(traced_ok)
        changed = np.zeros(0, np.int64)
        if len(traced_ok):
            change = np.abs(
                _display_luminance(traced_radiance[traced_ok])
                - _display_luminance(self._previous.radiance[traced_then[traced_ok]])
            )
            changed = traced_ok[change > GRADIENT_LIMIT]
        then, take = self._lookup(skipped_pix, None, period, split)
        if len(changed):  # not next to a cell whose traced pixel changed
            take &= ~self._near_cells(skipped_pix, skipped_level, traced_pix[changed],
                                      traced_level[changed])  # fmt: skip
        prev = self._previous
        if self._scene_moved:
            # Something moved: history may show it where it was. Only what lies within
            # the range of this frame's traced samples around it is kept.
            q = then[take]
            inside = self._within_range(
                skipped_pix[take], skipped_level[take], prev.radiance[q],
                traced_pix, traced_level, traced_radiance,
            )  # fmt: skip
            take[np.flatnonzero(take)[~inside]] = False
        q = then[take]
        self._taken.append((skipped_pix[take], (prev.age[q] + 1).astype(np.int16)))
        return take, prev.radiance[q], prev.hit[q]

    def accumulate(self, fill_pix: np.ndarray, fill_hit: np.ndarray, radiance: np.ndarray,
                   low: np.ndarray, high: np.ndarray, split=None,
                   share: float = ACCUMULATION) -> None:  # fmt: skip
        """Blends ``share`` (ACCUMULATION; a glossy pixel's, ``engine/trace/glossy.py``,
        its traced value with its hit distance 0: the surface's reprojection) of the
        filled pixels' ``fill_pix`` (m,) int64 previous
        values into their fill ``radiance`` (m, 3) float32, in place (compiled:
        ``history_kernels.accumulate``), read where their hit distance ``fill_hit`` (m,)
        float32 (the fill's estimate) reprojects them and it passes the per-pixel tests
        (read within ACCUMULATION_OFFSET, any age), clamped per channel to [low, high]
        (m, 3): the range of the traced samples the fill was made of
        (``sparse_pixels.Fill``). split: ``_lookup``'s."""
        prev = self._previous
        if prev is None or len(fill_pix) == 0:
            return
        width, height = self._size
        # Filled ones too (FILLED_AGE + 1 < NO_HISTORY + 1), never-traced ones not.
        (split or one_call)(
            _kernels().accumulate, len(fill_pix), _int64(fill_pix),
            np.ascontiguousarray(fill_hit, np.float32),
            np.ascontiguousarray(low, np.float32), np.ascontiguousarray(high, np.float32),
            float(share), NO_HISTORY + 1, self._element, self._normal, self._position,
            self._view, self._depth, self._moved_table, prev.element, prev.age, prev.normal,
            prev.position, prev.hit, prev.radiance, prev.clip_from_world, width, height,
            ACCUMULATION_OFFSET, NORMAL_AGREEMENT, PLANE_TOLERANCE, out=(radiance,),
        )  # fmt: skip

    def _near_cells(self, pix, pix_level, changed, changed_level) -> np.ndarray:
        """(n,) bool: pixels ``pix`` (n,) (of density levels ``pix_level``) whose pattern
        cell is one of, or next to, the cells of ``changed`` (k,) (levels
        ``changed_level``): the cells are the pattern's spacing s squares, in this
        frame's phase."""
        out = np.zeros(len(pix), bool)
        for level in np.unique(pix_level):
            s = int(LEVEL_SPACING[level])
            here = pix_level == level
            grid = np.zeros(self._grid_shape(s), bool)
            grid[self._cells(changed[changed_level == level], s)] = True
            out[here] = _dilated(grid, np.logical_or)[self._cells(pix[here], s)]
        return out

    def _within_range(self, pix, pix_level, history, traced_pix, traced_level, traced
                      ) -> np.ndarray:  # fmt: skip
        """(n,) bool: the history (n, 3) of pixels ``pix`` (n,) lies, per channel in the
        display range, within RANGE_TOLERANCE of the range of this frame's traced samples
        (``traced`` (k, 3) at ``traced_pix``) in its pattern cell and the 8 around it
        (the neighbourhood clamp of temporal anti-aliasing, on the pattern's cells).
        Without a traced sample around, history cannot be checked and is refused."""
        out = np.zeros(len(pix), bool)
        history, traced = _display(history), _display(traced)
        for level in np.unique(pix_level):
            s = int(LEVEL_SPACING[level])
            here = pix_level == level
            shape = (*self._grid_shape(s), 3)
            low, high = np.full(shape, np.inf, np.float32), np.full(shape, -np.inf, np.float32)
            mine = traced_level == level
            cells = self._cells(traced_pix[mine], s)
            np.minimum.at(low, cells, traced[mine])
            np.maximum.at(high, cells, traced[mine])
            cells = self._cells(pix[here], s)
            low, high = _dilated(low, np.minimum)[cells], _dilated(high, np.maximum)[cells]
            h = history[here]
            out[here] = ((h >= low - RANGE_TOLERANCE) & (h <= high + RANGE_TOLERANCE)).all(axis=1)
        return out

    def _grid_shape(self, spacing: int) -> tuple[int, int]:
        """The cell grid of a pattern of ``spacing`` (``_cells``' rows and columns)."""
        width, height = self._size
        return height // spacing + 3, width // spacing + 3

    def _cells(self, pix: np.ndarray, spacing: int) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (+1: -1 is the partial cell before the phase) of the pattern
        cell of each pixel ``pix`` for a pattern of ``spacing``."""
        row, col = np.divmod(pix, self._size[0])
        return ((row - self.phase[0] % spacing) // spacing + 1,
                (col - self.phase[1] % spacing) // spacing + 1)  # fmt: skip

    # ------------------------------------------------------------------ this frame

    def record(self, result: ReflectionResult) -> None:
        """Keep a round's reflections for this frame's history (written when the frame
        is finished: after its rounds, outside the time their budget counts)."""
        if result.pixel_index.size:
            self._results.append(result)

    def finished(self) -> _Frame | None:
        """This frame as the next one's previous frame (None when nothing was traced):
        traced and screen-space pixels at age 0, reused ones at their reprojected age,
        filled ones at FILLED_AGE (read by the next frame's accumulation only)."""
        if not self._results:
            return None
        n = self._size[0] * self._size[1]
        radiance = np.zeros((n, 3), np.float32)
        hit = np.full(n, np.inf, np.float32)
        age = np.full(n, NO_HISTORY, np.int16)
        for result in self._results:
            pix = result.pixel_index
            radiance[pix] = result.radiance
            if result.hit_distance is not None:
                hit[pix] = result.hit_distance
            traced = np.zeros(len(pix), np.int16)
            if result.kinds is not None:
                traced[result.kinds == pixel_kinds.FILLED] = FILLED_AGE
            age[pix] = traced
        for taken, taken_age in self._taken:
            age[taken] = taken_age
        return _Frame(radiance, hit, age, self._element, self._normal, self._position,
                      self._camera.clip_from_world)


def _display(values: np.ndarray) -> np.ndarray:
    """Linear radiance (any shape) compressed to 0..1 (x / (1 + x)): changes in it are
    about what a display shows, whatever the exposure of a highlight; non-finite and
    negative values count as 0 (nothing derived from them is NaN)."""
    values = np.maximum(np.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    return (values / (1.0 + values)).astype(np.float32)


def _display_luminance(radiance: np.ndarray) -> np.ndarray:
    """(n,) float32 luminance of (n, 3) linear radiance in the display range
    (``_display``)."""
    return _display(radiance @ _LUMINANCE)


def _dilated(grid: np.ndarray, combine) -> np.ndarray:
    """``grid`` (rows, cols[, C]) with every inner cell combined (``np.logical_or``,
    ``np.minimum``, ``np.maximum``) with its 8 neighbours; the border cells, which no
    pixel maps to (``FrameReuse._cells`` pads by one), are left as they are."""
    out = grid.copy()
    inner = out[1:-1, 1:-1]
    rows, cols = grid.shape[0], grid.shape[1]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            combine(inner, grid[1 + dr : rows - 1 + dr, 1 + dc : cols - 1 + dc], out=inner)
    return out


def _int64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.int64)


def _kernels():
    """The compiled reprojection (``history_kernels``), loaded on first use."""
    from phrt_usd import kernels

    return kernels.load("phrt_usd.engine.history_kernels")
