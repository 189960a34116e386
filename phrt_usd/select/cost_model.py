"""The trace-time cost model: milliseconds of a tracing round predicted from its ray count,
learned online from the rounds the renderer measures, with a safety factor that tracks
wall-time jitter.

What a policy checks its budget against is a prediction of the rays tracing a candidate
costs (``BudgetedPolicy.predicted_rays`` in ``phrt_usd.select.policies``) and of the time
those rays take (``TraceTimeModel`` here).
"""

from __future__ import annotations

import math

#: Predicted trace milliseconds are multiplied by a time safety factor: wall time jitters
#: from round to round (caches, the OS, other processes on the two cores). The factor is
#: the JITTER_QUANTILE quantile of measured / modelled round time, tracked online, and
#: never below TIME_SAFETY_MIN: on a quiet machine it settles near 1.1 (with RAYS_SAFETY
#: the selection then plans to use ~1 / 1.2 = 83 % of the budget); on a loaded machine
#: it grows so that rounds still end within the budget. Ratios (measured / modelled ms).
TIME_SAFETY_MIN = 1.05
#: The factor until measured rounds move it: where it settles on a quiet machine.
TIME_SAFETY_INITIAL = 1.1
#: Upper clamp of the factor: every slow round raises it by JITTER_STEP * JITTER_QUANTILE,
#: without bound otherwise over a long loaded spell.
TIME_SAFETY_MAX = 10.0
JITTER_QUANTILE = 0.97
#: Step of the online quantile tracker (ratio units): +STEP*q on a round slower than
#: the factor predicts, -STEP*(1-q) otherwise, so ~3 % of rounds exceed it.
JITTER_STEP = 0.2
#: When the time budget lets nothing at all be traced in a frame, the safety factor is
#: multiplied by this. Otherwise a noisy spell could raise it so far that nothing is ever
#: traced again, and without rounds there is nothing to learn from: the factor creeps back
#: until a round fits, and that round's measurement then corrects it.
STARVED_RELAX = 0.97

#: Before anything was measured: 0.004 ms per ray (250k rays/s, slower than embreex plus
#: numpy shading on one laptop core) and 0.5 ms fixed cost per tracing round.
INITIAL_MS_PER_RAY = 0.004
INITIAL_ROUND_MS = 0.5

#: Lower bound of the learned ms per ray (1e10 rays/s): keeps ms → rays finite.
MIN_MS_PER_RAY = 1e-7

#: Weight of older rounds in the time model (exponential forgetting per round). The
#: policies' mean rays per pixel over all reflectors forgets older traces at this rate too
#: (per traced reflector).
TIME_MODEL_DECAY = 0.9


class TraceTimeModel:
    """Milliseconds of one tracing round: ``overhead_ms + ms_per_ray * rays``.

    Fitted by exponentially weighted least squares over the rounds seen so far (older
    rounds weigh ``TIME_MODEL_DECAY`` less per round). When the fit gives a negative
    overhead, the line goes through the origin instead (``ms_per_ray = sum ms / sum
    rays``, conservative for rounds larger than average). When the rounds' ray counts are
    too alike to separate the two terms, or time does not grow with rays (small rounds
    dominated by noise), ``ms_per_ray`` keeps its previous value and the overhead absorbs
    the mean time.

    Predictions are multiplied by ``safety``, an online estimate of the JITTER_QUANTILE
    quantile of (measured / modelled) round time, clamped to [TIME_SAFETY_MIN,
    TIME_SAFETY_MAX].
    """

    def __init__(self) -> None:
        self.overhead_ms = INITIAL_ROUND_MS
        self.ms_per_ray = INITIAL_MS_PER_RAY
        self.rounds = 0
        self.safety = TIME_SAFETY_INITIAL
        # Weighted sums: weight, rays, ms, rays^2, rays*ms.
        self._w = self._r = self._m = self._rr = self._rm = 0.0

    def learn(self, rays: int, ms: float) -> None:
        """One round: ``rays`` cast in ``ms`` wall-clock milliseconds."""
        if rays <= 0 or not math.isfinite(ms) or ms < 0.0:
            return
        r, m = float(rays), float(ms)
        if self.rounds > 0:  # the first round only tells how wrong the initial guess was
            ratio = m / (self.overhead_ms + self.ms_per_ray * r)
            q = JITTER_QUANTILE
            step = JITTER_STEP * (q if ratio > self.safety else -(1.0 - q))
            self.safety = min(max(self.safety + step, TIME_SAFETY_MIN), TIME_SAFETY_MAX)
        k = TIME_MODEL_DECAY
        self._w = k * self._w + 1.0
        self._r = k * self._r + r
        self._m = k * self._m + m
        self._rr = k * self._rr + r * r
        self._rm = k * self._rm + r * m
        self.rounds += 1
        spread = self._w * self._rr - self._r * self._r  # w^2 * variance of rays
        slope = intercept = -1.0
        if spread > 1e-6 * self._w * self._rr:  # ray counts differ enough to fit a line
            slope = (self._w * self._rm - self._r * self._m) / spread
            intercept = (self._m - slope * self._r) / self._w
        if slope > 0.0 and intercept >= 0.0:
            self.overhead_ms, self.ms_per_ray = intercept, slope
        elif slope > 0.0:  # negative overhead: a line through the origin instead
            self.overhead_ms, self.ms_per_ray = 0.0, self._m / self._r
        else:
            # No growth with rays visible (rounds too alike, or noise dominates): the rounds
            # tell their mean time, not the per-ray cost, which keeps its previous value.
            self.overhead_ms = max(self._m / self._w - self.ms_per_ray * self._r / self._w, 0.0)
        self.ms_per_ray = max(self.ms_per_ray, MIN_MS_PER_RAY)

    def relax(self) -> None:
        """Nothing fitted the time budget this frame: lower the safety factor a little."""
        self.safety = max(self.safety * STARVED_RELAX, TIME_SAFETY_MIN)

    def predicted_ms(self, rays: float) -> float:
        """Conservative milliseconds for a round of ``rays`` rays (``safety`` included)."""
        return (self.overhead_ms + self.ms_per_ray * max(rays, 0.0)) * self.safety

    def rays_within(self, ms: float) -> float:
        """Most rays a round may cast and still (conservatively) end within ``ms``."""
        return max((ms / self.safety - self.overhead_ms) / self.ms_per_ray, 0.0)
