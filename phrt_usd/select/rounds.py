"""A frame's selection rounds: the one loop the renderer (``FrameRenderer.finish``) and the
replay tool (``tools/policy_replay.py``) run.

Per frame (``run_rounds``)::

    calibrate once per run, in a time-budgeted frame with visible reflectors
    policy.begin_frame(view, scene)
    while budget is left and (ids := policy.next_round(budget)):
        traced = trace(ids, policy.round_densities(ids))   # the caller's tracing step
        observe()                        # only for a policy that reads fallback_error
        policy.record(traced.records, traced.ms / 1000)
    metrics = policy.end_frame()

The tracing step is what differs: the renderer traces the round's reflectors and
composites them into the frame (its time measured), the replay tool hands back the
records a capture recorded (its time simulated). Everything else (what is left of the
budget, which ids a round may trace, what the policy is told, the selection time) is
here once, so a replay selects exactly what a render of the same views would.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from phrt_usd.model.frame import (
    Budget,
    FrameNote,
    FrameView,
    ReflectorMetrics,
    SelectionPolicy,
    TraceRecord,
)
from phrt_usd.model.scene import Scene


@dataclass
class TracedRound:
    """What a tracing step did with one round's reflectors.

    records: one ``TraceRecord`` per source reflector traced;
    rays: rays cast in the round (all kinds);
    ms: the round's time charged to the budget (the renderer: trace and composite,
        measured; the replay tool: simulated).
    """

    records: list[TraceRecord]
    rays: int
    ms: float


@dataclass
class Calibration:
    """Timed calibration rounds of a run's tracing, before its first time-budgeted round
    (what ``SelectionPolicy.calibrate`` takes).

    samples: (rays, ms, filled, reused, marched pixels) of each timed round
        (``TraceRecord``'s counts: pixels made without rays, first rays marched in screen
        space; 0 at full density without screen space);
    rays, pixels: rays cast and pixels that started rays over the calibration's rounds;
    wall_ms: wall time the calibration took (the renderer reports it apart);
    records: one ``TraceRecord`` per reflector the full-density rounds traced, its
        pixels and rays summed over them (its own rays per pixel).
    """

    samples: list[tuple]
    rays: int
    pixels: int
    wall_ms: float = 0.0
    records: list[TraceRecord] = field(default_factory=list)


#: The tracing step: (a round's element ids, their trace densities) → what it traced.
TraceStep = Callable[[list[int], list[str]], TracedRound]


@dataclass
class FrameRounds:
    """What a frame's rounds selected and spent.

    selected: element ids traced, in round order;
    densities: element id → the trace density each was traced at;
    trace_ms, rays: the rounds' charged time and rays, summed;
    select_ms: wall time in the policy (begin, rounds, learning, end; measured by the
        loop's clock);
    metrics: the policy's figures for every candidate (``end_frame``);
    note: the policy's note on the frame (``last_frame_note``);
    starved: the budget when the rounds stopped with none of it left before anything
        was traced while reflectors were visible, else None;
    calibration: the run's calibration if this frame ran it, with the prior the policy
        fitted to it (fixed ms, ms per ray, rays per filled, reused and screen-space
        pixel), else None.
    """

    selected: list[int] = field(default_factory=list)
    densities: dict[int, str] = field(default_factory=dict)
    trace_ms: float = 0.0
    rays: int = 0
    select_ms: float = 0.0
    metrics: dict[int, ReflectorMetrics] = field(default_factory=dict)
    note: FrameNote = field(default_factory=FrameNote)
    starved: Budget | None = None
    calibration: tuple[Calibration, tuple[float, ...]] | None = None


def remaining_budget(limits: Budget, trace_ms: float, rays: int) -> Budget:
    """What is left of the frame's ``limits`` (None fields unbounded) after ``trace_ms``
    and ``rays`` were spent."""
    return Budget(
        ms=None if limits.ms is None else limits.ms - trace_ms,
        rays=None if limits.rays is None else limits.rays - rays,
    )


def exhausted(budget: Budget) -> bool:
    """Nothing left of the time or of the rays budget."""
    return (budget.ms is not None and budget.ms <= 0) or (
        budget.rays is not None and budget.rays <= 0
    )


def run_rounds(
    policy: SelectionPolicy,
    view: FrameView,
    scene: Scene,
    visible: Sequence[int],
    limits: Budget,
    trace: TraceStep,
    *,
    calibrate: Callable[[], Calibration] | None = None,
    observe: Callable[[], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> FrameRounds:
    """One frame's selection rounds within ``limits`` (the frame's time and rays budgets,
    None fields unbounded), each round traced by ``trace``.

    visible: the reflectors with pixels in ``view``; only ids with pixels in the view
        (``view.pixel_counts``) and not traced yet this frame are passed to ``trace``;
    calibrate: times the caller's tracing for the policy's time model (at the sizes
        ``limits.ms`` plans: the caller binds it), called before the frame begins when
        the frame is time-budgeted, reflectors are visible and the policy
        ``needs_calibration``;
    observe: fills the last traced round's ``TraceRecord.fallback_error`` (called only
        for a policy that ``observes_fallback_error``, before it learns the round);
    clock: seconds, for the selection time.
    """
    out = FrameRounds()
    if calibrate is not None and limits.ms is not None and visible and policy.needs_calibration:
        done = calibrate()
        fitted = policy.calibrate(done.samples, done.rays, done.pixels, done.records)
        out.calibration = (done, fitted)
    counts = view.pixel_counts
    t = clock()
    policy.begin_frame(view, scene)
    out.select_ms += _ms(clock, t)
    while True:
        budget = remaining_budget(limits, out.trace_ms, out.rays)
        if exhausted(budget):
            if not out.selected and visible:
                out.starved = budget
            break
        t = clock()
        ids = policy.next_round(budget)
        # Only reflectors with pixels in this frame are traced from the G-buffer.
        ids = [i for i in ids if counts[i] > 0 and i not in out.selected]
        densities = policy.round_densities(ids) if ids else []
        out.select_ms += _ms(clock, t)
        if not ids:
            break
        traced = trace(ids, densities)
        out.trace_ms += traced.ms
        out.rays += traced.rays
        out.selected.extend(ids)
        out.densities.update(zip(ids, densities, strict=True))
        t = clock()
        if observe is not None and policy.observes_fallback_error:
            observe()
        # The policy learns the time the budget is charged.
        policy.record(traced.records, traced.ms / 1000.0)
        out.select_ms += _ms(clock, t)
    t = clock()
    out.metrics = policy.end_frame()
    out.select_ms += _ms(clock, t)
    out.note = policy.last_frame_note
    return out


def _ms(clock: Callable[[], float], t0: float) -> float:
    return (clock() - t0) * 1000.0
