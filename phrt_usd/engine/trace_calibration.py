"""The run's trace-time calibration (``calibrate_tracer``): before the first time-budgeted
round of a run, the renderer's tracing step is timed on the frame's own reflector pixels
at the sizes the frame's budget will plan, at full and at reduced densities, with the
previous frame's reflections reused and with screen space when the run has it, and the
policy's time model fits its prior line, the cost of each kind of pixel made without
rays and its safety factor to those rounds (``TraceTimeModel.calibrate``).

Why at the budget's size. A round of a size the run has not traced yet costs 1.5-2.5x
its repeats (its buffers are allocated and touched for the first time; from 4096 shadow
rays and 8192 rays on, the work is split over the thread pool). On a mirror floor with 64
small reflective spheres at 320 x 240 (48,621 reflector pixels), the same 155k-ray round
took 123, 78, 41 and 50 ms in turn, and rounds of 8,000 / 16,000 / 48,000 pixels 9.7 /
26.6 / 62.9 ms the first time against 7.9 / 13.9 / 34.1 the second. Why at the coarsest
density too. A reflector traced at a reduced density also fills its skipped pixels from
the traced ones, a cost per pixel that no count of rays shows: on that floor, every
reflector at a sixteenth cast 9,973 rays in 8.5-9 ms, where the rounds at full density
cast 155k in 32 ms. A calibration of 64 and 512 pixels at full density (a few ms) saw
neither, so the first frame (HEU1 stepping 44 of its 61 reflectors to a sixteenth) took
16-18 ms against T = 9 ms (third-party assets: 58 and 81 ms against 9).

So the calibration traces, each round through the renderer's own tracing step
(``ReflectionRounds``: ``Tracer.trace_reflections`` and compositing, timed as a frame's
rounds are) on a copy of the frame's G-buffer keeping only the round's pixels' element
ids, so that each round does a real round's work over the whole image:

* at full density without screen space, random samples of the reflector pixels growing
  from CALIBRATION_PIXELS (CALIBRATION_GROWTH times, or to what the last size says takes
  CALIBRATION_AIM T) until a round takes the budget T (at most CALIBRATION_ROUND_MAX_MS)
  or every pixel; each size once untimed, then timed CALIBRATION_REPEATS times: the
  line (rays alone);
* with screen space on, the largest of those samples again with it, timed
  CALIBRATION_REPEATS times (its first march warmed on the smallest sample, untimed):
  the march's cost per marched pixel, from the same pixels with and without it;
* at the reduced densities CALIBRATION_DENSITIES (a sixteenth and a half), whole
  reflectors in a seeded random order up to SPARSE_PIXELS_FACTOR times the largest
  full-density sample's pixels, without history; each once untimed, then timed
  CALIBRATION_REPEATS times: the fill's cost per filled pixel;
* and the same reflectors as a still view's frames (``_History``,
  ``_reduced_density_rounds``): the untimed half-density round is the first frame, a
  half-density round in the pattern's other phase the second (its skipped pixels are
  the first's traced ones: they take their history; untimed, REUSE_DENSITY says why),
  and each timed round at a sixteenth is followed by one after that second frame
  (every pixel has history at most a frame old: nearly all of its skipped pixels are
  reused, the rest filled where the temporal gradient refuses a cell): the lookup's
  cost per reused pixel, timed in turn with the fill it replaces.

Why a pair of rounds for the march. Every first ray is marched when screen space is on,
so rounds of random samples march a constant share of their pixels (all of them): a fit
of their times cannot tell the march from the rays. The same pixels with and without it
differ by the march alone (and the rays its resolved pixels do not cast, which the count
of rays shows). Why the still view for reuse: it is the one view where the history of
every skipped pixel is valid, so the reused pixels' count is known and large, and what
the lookups cost is not mixed with a view's rejections. Both are the renderer's own code
on the frame's own pixels; what they cost apart from rays is priced per pixel in rays
(``select/cost_model.py``, its rule).

Its wall time is once per run, reported apart from the frame's time
(``FrameStats.calibration``): on sewer frame 241 (320 x 240, T = 16 ms, a fresh
process, the machine shared) 12-14 T with screen space off and 17-19 T with it on,
against 12-13 T before reuse and the march were timed (the history's second frame and
two rounds at a sixteenth; the two rounds of the largest sample with screen space).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from phrt_usd.engine.reflection_history import ReflectionHistory
from phrt_usd.engine.trace_rounds import ReflectionRounds
from phrt_usd.model.frame import FrameCamera, GBuffer, TraceRecord
from phrt_usd.select.rounds import Calibration

#: The smallest calibration round, in pixels (the run's first trace is one of its size,
#: untimed): about one small reflector, so the fit sees a round's fixed cost.
CALIBRATION_PIXELS = 64
#: Each full-density size is at most this many times the last (about 1.3 T of timed
#: rounds per repeat up to the size that takes T) ...
CALIBRATION_GROWTH = 4
#: ... and at most the size the last one's time per pixel says takes this many times T:
#: the last size is then about T to 1.5 T rather than up to 4 T (the fixed cost in a
#: smaller round's time per pixel makes the aim short rather than long).
CALIBRATION_AIM = 1.5
#: Timed rounds of each size after its untimed one: two show the spread the safety
#: factor starts from.
CALIBRATION_REPEATS = 2
#: The seed of the pixel samples (the run's provenance reports it).
CALIBRATION_SEED = 0
#: The largest full-density round stops growing once a round takes this many ms, whatever
#: the budget: bounds the calibration's wall time for large budgets (their first frame's
#: rounds are then a prediction of the line beyond what was timed).
CALIBRATION_ROUND_MAX_MS = 50.0
#: The coarsest-density rounds cover this many times the largest full-density round's
#: pixels: at a sixteenth they cast ~1/16 of the rays and fill the rest, which takes
#: about as long as the full-density round (the floor above: 0.19 against 0.66 us a pixel).
SPARSE_PIXELS_FACTOR = 4
#: The reduced densities the calibration times on those whole reflectors: the coarsest
#: and the finest. A filled pixel's cost depends on the density (the finest pattern's
#: rounds cast half the rays, often below the pool's split, and fill most of a small
#: reflector from its edges): priced from the coarsest alone, the first frame of a
#: cluttered floor at T = 4 ms, HEU1 stepping small spheres to a half or a quarter, took
#: 1.4-1.5 T.
CALIBRATION_DENSITIES = ("sixteenth", "half")
#: The density whose two phases make the still view's history: its pattern rotates in
#: two frames (``sparse_pixels.ROTATION_PERIOD``), so the second frame's skipped pixels
#: are the first's traced ones, and after it every pixel was traced or reused within a
#: frame (history every density's rotation period accepts).
HISTORY_DENSITY = "half"
#: The density reused pixels are timed at: the coarsest, whose skipped pixels are 15 in
#: 16. A round with history also looks up each traced pixel's own history (the temporal
#: gradient), a cost of its traced pixels, not of its reused ones: at a sixteenth one
#: such lookup for 15 reused pixels, at a half one for each. On sewer frame 241 (320 x
#: 240) the half-density round with history took as long as the one that filled
#: (14.2 / 14.1 ms), the sixteenth's 6.0 against 7.4 ms: timed at a half too, a reused
#: pixel was priced as a filled one. So the history's second frame, at a half, is traced
#: for its history only.
REUSE_DENSITY = "sixteenth"


def calibrate_tracer(
    tracer, gb: GBuffer, visible_ids: list[int], bounce_limit: int, seed: int,
    budget_ms: float | None = None, camera: FrameCamera | None = None, screen=None,
) -> Calibration:  # fmt: skip
    """Time ``tracer`` on this frame's own reflector pixels (of ``visible_ids``) at the
    sizes a frame of ``budget_ms`` plans, at full and at reduced densities, with the
    previous frame's reflections reused (with ``camera``, the frame's ``FrameCamera``;
    None: not timed) and with screen space (with ``screen``, the run's
    ``screen_space.ScreenFrame``; None: the run has none) (module docstring); samples
    drawn with ``seed``. Returns every timed round's (rays, ms, filled, reused, marched
    pixels), and per reflector its pixels, rays and marched pixels over the
    full-density rounds traced as the run traces (its own rays per pixel, for the
    policy's first predictions)."""
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    rounds = _CalibrationRounds(tracer, gb, visible_ids, bounce_limit, screen)
    flat = rounds.pixels
    stop_ms = min(float(budget_ms or 0.0), CALIBRATION_ROUND_MAX_MS)
    samples: list[tuple[int, float, int, int, int]] = []
    n = CALIBRATION_PIXELS
    largest = 0
    while True:
        pick = rng.choice(flat, size=min(n, len(flat)), replace=False)
        rounds.trace(pick, "full", screen=False)  # the first round of this size: untimed
        if screen is not None and n == CALIBRATION_PIXELS:
            rounds.trace(pick, "full")  # the run's first march (its first call is slow)
        timed = [rounds.trace(pick, "full", screen=False) for _ in range(CALIBRATION_REPEATS)]
        samples.extend(timed)
        largest = len(pick)
        fastest = min(t[1] for t in timed)
        if largest == len(flat) or fastest >= stop_ms:
            break
        aim = n * CALIBRATION_AIM * stop_ms / max(fastest, 1e-3)  # by its time per pixel
        n = max(int(min(n * CALIBRATION_GROWTH, aim)), n + 1)
    if screen is not None:  # the largest size again, its first rays marched first
        samples.extend(rounds.trace(pick, "full") for _ in range(CALIBRATION_REPEATS))
    whole = _whole_reflectors(gb, visible_ids, SPARSE_PIXELS_FACTOR * largest, rng)
    if len(whole):
        timed_reuse = camera is not None and {HISTORY_DENSITY, REUSE_DENSITY} <= set(
            CALIBRATION_DENSITIES
        )
        history = _History(whole, rounds, camera) if timed_reuse else None
        samples.extend(_reduced_density_rounds(rounds, whole, history))
    wall_ms = (time.perf_counter() - start) * 1000.0
    records = [TraceRecord(e, pixels, rays, marched=marched)
               for e, (pixels, rays, marched) in sorted(rounds.sources.items())]  # fmt: skip
    return Calibration(samples, rounds.rays, rounds.traced_pixels, wall_ms, records)


class _CalibrationRounds:
    """Rounds of chosen G-buffer pixels through the renderer's tracing step, each on a
    copy of ``gb`` keeping only those pixels' element ids, with the run's ``screen``
    (a ``screen_space.ScreenFrame``, None: none) unless told not to; counts the rays and
    the pixels that started rays over the rounds traced as the run traces (timed and
    untimed)."""

    def __init__(self, tracer, gb: GBuffer, visible_ids: list[int], bounce_limit: int,
                 screen=None) -> None:  # fmt: skip
        self._tracer = tracer
        self._gb = gb
        self._bounce_limit = bounce_limit
        self._screen = screen
        self._ids = gb.element_id.reshape(-1)
        #: The flat indices of the visible reflectors' pixels.
        self.pixels = np.flatnonzero(np.isin(self._ids, visible_ids))
        self._blank = np.zeros((*gb.shape, 3), np.float32)
        self._whole = np.ones(gb.shape, np.float32)
        self.rays = 0
        self.traced_pixels = 0
        #: Per reflector, its pixels, rays and marched pixels over the full-density
        #: rounds traced as the run traces.
        self.sources: dict[int, tuple[int, int, int]] = {}

    def gbuffer(self, pick: np.ndarray) -> GBuffer:
        """The copy of ``gb`` a round of the pixels ``pick`` (flat indices) traces."""
        ids = np.full(self._ids.size, -1, self._ids.dtype)
        ids[pick] = self._ids[pick]
        return dataclasses.replace(self._gb, element_id=ids.reshape(self._gb.shape))

    def trace(self, pick: np.ndarray, density: str, reuse=None, screen: bool = True,
              sub: GBuffer | None = None) -> tuple[int, float, int, int, int]:  # fmt: skip
        """One round of the pixels ``pick`` (flat indices) at ``density``, with ``reuse``
        (a ``FrameReuse``, None: none) on ``sub`` (``gbuffer(pick)``, made when None),
        with the run's screen space unless ``screen`` is False: its rays, its ms and its
        filled, reused and marched pixels (``TraceRecord``'s counts)."""
        sub = self.gbuffer(pick) if sub is None else sub
        sources = np.unique(sub.element_id.reshape(-1)[pick]).tolist()
        frame = self._screen if screen else None
        step = ReflectionRounds(self._tracer, sub, self._blank, self._whole, self._blank,
                                self._bounce_limit, reuse, frame)  # fmt: skip
        traced = step(sources, [density] * len(sources))
        filled, reused, marched = (sum(getattr(r, kind) or 0 for r in traced.records)
                                   for kind in ("filled", "reused", "marched"))  # fmt: skip
        if screen or self._screen is None:  # traced as the run traces
            if density == "full":
                for r in traced.records:
                    pixels, rays, ran = self.sources.get(r.source, (0, 0, 0))
                    self.sources[r.source] = (pixels + r.pixels, rays + r.rays,
                                              ran + (r.marched or 0))  # fmt: skip
            self.rays += int(traced.rays)
            self.traced_pixels += sum(r.pixels for r in traced.records) - filled - reused
        return int(traced.rays), float(traced.ms), filled, reused, marched


class _History:
    """The calibration's own rounds of the pixels ``pick`` as the frames of a still view
    (a ``ReflectionHistory`` with ``camera``, nothing moving): ``begin`` a frame,
    ``trace`` it, ``end`` it (``_reduced_density_rounds`` says which)."""

    def __init__(self, pick: np.ndarray, rounds: _CalibrationRounds, camera: FrameCamera):
        self._pick = pick
        self._rounds = rounds
        self._sub = rounds.gbuffer(pick)
        self._camera = camera
        self._history = ReflectionHistory()
        self._still = np.zeros(0, np.int64)  # nothing moved

    def begin(self, frame: int):
        """A ``FrameReuse`` of the ``frame``-th frame, the last ended its previous one."""
        return self._history.begin(self._sub, self._camera, self._still, frame)

    def end(self, reuse) -> None:
        self._history.end(reuse)

    def trace(self, density: str, reuse) -> tuple[int, float, int, int, int]:
        return self._rounds.trace(self._pick, density, reuse, sub=self._sub)



def _reduced_density_rounds(rounds: _CalibrationRounds, whole: np.ndarray,
                            history: _History | None) -> list[tuple]:  # fmt: skip
    """Timed rounds of the whole reflectors ``whole`` at each of CALIBRATION_DENSITIES
    (REUSE_DENSITY last), each density's after an untimed one: CALIBRATION_REPEATS
    without history (filled pixels). With ``history`` (None: reuse not timed),
    HISTORY_DENSITY's untimed round is the still view's first frame and a round in the
    pattern's other phase its second (its skipped pixels, the first's traced ones,
    reused: every pixel's history is then at most a frame old; not a sample), and each
    round at REUSE_DENSITY is followed by one with that history (fill and reuse timed in
    turn, under the same load of the machine)."""
    out = []
    for density in sorted(CALIBRATION_DENSITIES, key=lambda d: d == REUSE_DENSITY):
        first = history.begin(0) if history is not None and density == HISTORY_DENSITY else None
        rounds.trace(whole, density, first)  # untimed (and the history's first frame)
        for _ in range(CALIBRATION_REPEATS):
            out.append(rounds.trace(whole, density))
            if history is not None and density == REUSE_DENSITY:
                out.append(history.trace(density, history.begin(2)))
        if first is not None:
            history.end(first)
            second = history.begin(1)
            history.trace(density, second)  # for its history only (see REUSE_DENSITY)
            history.end(second)
    return out


def _whole_reflectors(
    gb: GBuffer, visible_ids: list[int], pixels: int, rng: np.random.Generator
) -> np.ndarray:
    """Flat indices of every pixel of visible reflectors taken in a random order (``rng``)
    until they cover ``pixels`` (all of them if they cover fewer)."""
    ids = gb.element_id.reshape(-1)
    counts = np.bincount(ids[ids >= 0], minlength=max(visible_ids, default=0) + 1)
    order = rng.permutation(np.asarray(sorted(visible_ids), np.int64))
    cover = np.cumsum(counts[order])
    taken = order[: int(np.searchsorted(cover, pixels)) + 1]
    return np.flatnonzero(np.isin(ids, taken))
