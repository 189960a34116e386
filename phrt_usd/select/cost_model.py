"""The trace-time cost model: milliseconds of a tracing round predicted from its ray count,
learned online from the rounds the renderer measures, with a safety factor that tracks
wall-time jitter.

What a policy checks its budget against is a prediction of the rays tracing a candidate
costs (``BudgetedPolicy.predicted_rays`` in ``phrt_usd.select.policies``) and of the time
those rays take (``TraceTimeModel`` here).
"""

from __future__ import annotations

import math

import numpy as np

#: Predicted trace milliseconds are multiplied by a time safety factor: wall time jitters
#: from round to round (caches, the OS, other processes on the two cores). The factor is
#: the JITTER_QUANTILE quantile of measured / modelled round time over the last
#: JITTER_WINDOW rounds, each round weighted by its modelled milliseconds, and never below
#: TIME_SAFETY_MIN. Each part has its reason:
#: - Modelled by the current fit, recomputed after every round: the factor covers the
#:   error of the model that predicts the next round, not the start-up error of a model
#:   since corrected (the farm's first rounds take ~4x the calibration's fixed cost;
#:   measured against the model of their own time, those ratios would hold the factor
#:   near 4 and starve ~30 frames after the fit has learned the fixed cost).
#: - Weighted by time because what the budget must absorb is milliseconds: a 0.05 ms
#:   round taking 4x its model costs less than a 10 ms round taking 1.1x (on the sewer at
#:   T = 16 ms the few sub-millisecond rounds run at 3-4x their model, the others' 97 %
#:   quantile is 1.17-1.29).
#: - Over a window, so that a loaded spell raises the factor within a few rounds and is
#:   forgotten JITTER_WINDOW rounds after it ends.
#: - A window not full yet is filled up with rounds at TIME_SAFETY_INITIAL, each of the
#:   real rounds' mean weight: one slow round is not the quantile of a young window (on
#:   the farm at T = 1 ms an early round can take 25x its model, which as the quantile
#:   would set the factor to its maximum and starve ~60 frames), while a few slow rounds
#:   in a full window still raise it.
#: On a quiet machine it settles near 1.1-1.2: the selection then plans to use ~85-90 % of
#: the budget. Ratios (measured / modelled ms). Measurements: the weighted window
#: quantile in docs/bench-log/2026-12-03-d62f485-safety-glue-temporal.md, the current
#: fit and the young window's filling in docs/bench-log/2026-12-03-2987843-make-room-hold.md.
TIME_SAFETY_MIN = 1.05
#: The factor before any round was measured, and the ratio of the rounds that fill up a
#: young window: where it settles on a quiet machine.
TIME_SAFETY_INITIAL = 1.1
#: Upper clamp of the factor: a round stuck behind another process (10-100x its model)
#: would otherwise plan nothing at all for JITTER_WINDOW rounds.
TIME_SAFETY_MAX = 10.0
#: 95 %, not 99 %: the frame's later rounds spend what the measured rounds left of the
#: budget, so one slow round costs the frame its leftover rounds, not the budget.
JITTER_QUANTILE = 0.95
#: Rounds in the window: a tracing frame makes 1-3 rounds, so 3-8 s of frames at 24 fps.
#: Long enough for a steady quantile with sub-millisecond rounds (the farm at T = 1 ms,
#: ±30-50 % round jitter), where the quantile of a shorter window swings with every slow
#: round entering or leaving it, and the frame's ray allowance with it (64 rounds against
#: 192: docs/bench-log/2026-12-03-454500a-window-192.md). A loaded spell is forgotten 192
#: rounds after it ends.
JITTER_WINDOW = 192
#: When the time budget lets nothing at all be traced in a frame, the safety factor is
#: multiplied by this. Otherwise a noisy spell could raise it so far that nothing is ever
#: traced again, and without rounds there is nothing to learn from: the factor creeps back
#: until a round fits, and that round's measurement then corrects it.
STARVED_RELAX = 0.97
#: Once the safety factor is down at TIME_SAFETY_MIN, a starved frame also scales the
#: model's times (prior and measured rounds) by this: a calibration or rounds timed in a
#: loaded spell could otherwise predict every reflector over the budget for ever. The
#: first round that then fits is measured and corrects the model; with a budget truly too
#: small this probes once every ~log(predicted / budget) / log(1 / 0.75) frames.
STARVED_SCALE = 0.75

#: Before anything was measured or calibrated: 0.004 ms per ray (250k rays/s, slower than
#: embreex plus numpy shading on one laptop core) and 0.5 ms fixed cost per tracing round.
#: A render with a time budget replaces both by a calibration on its own stage before the
#: first round (``TraceTimeModel.calibrate``; ``FrameRenderer`` in engine/renderer.py).
INITIAL_MS_PER_RAY = 0.004
INITIAL_ROUND_MS = 0.5

#: Lower bound of the learned ms per ray (1e10 rays/s): keeps ms → rays finite.
MIN_MS_PER_RAY = 1e-7

#: Weight of older rounds in the time model (exponential forgetting per round). The
#: policies' mean rays per pixel over all reflectors forgets older traces at this rate too
#: (per traced reflector).
TIME_MODEL_DECAY = 0.9

#: A measured round enters the fit clipped to [1 / OUTLIER_RATIO, OUTLIER_RATIO] times
#: the model's expectation (once it has one: calibrated or a round seen). On the shared
#: machine a round sometimes takes 10x its usual time (another process on the cores); one
#: such round would otherwise hold the whole line up for ~10 rounds. A lasting change of
#: speed still moves the model by up to 3x per round; the safety factor sees the round
#: unclipped.
OUTLIER_RATIO = 3.0

#: Rays are fitted in units of RAY_UNIT rays (a round casts 1e2..1e6 rays): keeps the
#: normal equations' sums of squares well conditioned.
RAY_UNIT = 1e4
#: The prior line (the initial guess, or the calibration) enters the fit as two
#: pseudo-rounds, one at 0 rays (the fixed cost) and one at RAY_UNIT rays (fixed cost plus
#: the per-ray cost), each of weight PRIOR_WEIGHT at the start: the first measured round
#: already outweighs it (the calibration's rounds are small and on a (1, n) image, so they
#: miss part of a real round's fixed cost). Their weight is forgotten like a measured
#: round's (TIME_MODEL_DECAY per round); when the rounds all trace about the same rays,
#: they decide the line's height there and the prior only its tilt.
PRIOR_WEIGHT = 0.5
#: The prior's weight never falls below this: with identical rounds the two terms cannot
#: be told apart from data, and the remaining prior keeps the normal equations regular.
PRIOR_WEIGHT_MIN = 1e-9


class TraceTimeModel:
    """Milliseconds of one tracing round: ``overhead_ms + ms_per_ray * rays``.

    Fitted by exponentially weighted least squares over the rounds seen so far (older
    rounds weigh ``TIME_MODEL_DECAY`` less per round) and a prior line: the calibration
    of ``calibrate`` (or INITIAL_ROUND_MS / INITIAL_MS_PER_RAY without one) as two
    pseudo-rounds whose weight is forgotten as rounds come (PRIOR_WEIGHT). So the fit
    converges to the measured time also when every round traces about the same rays (a
    still or turntable shot): the rounds fix the line's height where they are, the prior
    only its tilt. A negative fixed cost is replaced by a line through the origin, a
    non-positive slope by the prior's per-ray cost (noise dominating small rounds), and a
    fixed cost above the median round time of the safety factor's window by that median
    (``_fit``).

    Predictions are multiplied by ``safety``: the JITTER_QUANTILE quantile of (measured /
    modelled) round time over the last JITTER_WINDOW rounds, weighted by the rounds'
    modelled ms, clamped to [TIME_SAFETY_MIN, TIME_SAFETY_MAX]; ``expected_ms`` is the
    central estimate without it.
    """

    def __init__(self) -> None:
        self.overhead_ms = INITIAL_ROUND_MS
        self.ms_per_ray = INITIAL_MS_PER_RAY
        self.rounds = 0
        self.safety = TIME_SAFETY_INITIAL
        #: The window of the safety factor, oldest first: each round's measured ms and the
        #: rays it was predicted to cast (``learn``'s ``planned_rays``, else its rays).
        self.jitter_ms: list[float] = []
        self.jitter_rays: list[float] = []
        #: The prior line (ms, ms per ray) and its current weight.
        self.prior_overhead_ms = INITIAL_ROUND_MS
        self.prior_ms_per_ray = INITIAL_MS_PER_RAY
        self.prior_weight = PRIOR_WEIGHT
        #: True once ``calibrate`` set the prior from this stage's own rays.
        self.calibrated = False
        # Weighted sums of the measured rounds: weight, x, ms, x^2, x*ms (x = rays/RAY_UNIT).
        self._w = self._r = self._m = self._rr = self._rm = 0.0

    def calibrate(self, samples: list[tuple[int, float]]) -> None:
        """Set the prior line from timed calibration rounds ``(rays, ms)`` (at least one;
        two sizes separate the fixed cost from the per-ray cost) and refit. Marks the
        model calibrated; rounds learned before stay."""
        pts = [(float(r), float(m)) for r, m in samples if r > 0 and math.isfinite(m) and m >= 0]
        if not pts:
            return
        pts.sort()
        (r1, m1), (r2, m2) = pts[0], pts[-1]
        slope = (m2 - m1) / (r2 - r1) if r2 > r1 else 0.0
        if slope > 0.0:
            overhead = m1 - slope * r1
            if overhead < 0.0:  # a line through the origin instead
                overhead, slope = 0.0, sum(m for _r, m in pts) / sum(r for r, _m in pts)
        else:  # timings too noisy to show growth: all of it per ray (conservative)
            overhead, slope = 0.0, max(m for _r, m in pts) / r2
        self.prior_overhead_ms = max(overhead, 0.0)
        self.prior_ms_per_ray = max(slope, MIN_MS_PER_RAY)
        self.prior_weight = PRIOR_WEIGHT
        self.calibrated = True
        self._fit()

    def learn(self, rays: int, ms: float, planned_rays: float = 0.0) -> None:
        """One round: ``rays`` cast in ``ms`` wall-clock milliseconds. ``planned_rays``
        (> 0): the rays the round was predicted to cast; the safety factor's ratio is then
        measured against the time modelled for them, so it also covers the error of the
        ray prediction (the fit itself always learns the rays cast)."""
        if rays <= 0 or not math.isfinite(ms) or ms < 0.0:
            return
        x, m = float(rays) / RAY_UNIT, float(ms)
        if self.rounds > 0 or self.calibrated:
            # (Uncalibrated, the first round only tells how wrong the initial guess was.)
            planned = planned_rays if planned_rays > 0.0 and math.isfinite(planned_rays) else rays
            self.jitter_ms = [*self.jitter_ms[1 - JITTER_WINDOW :], m]
            self.jitter_rays = [*self.jitter_rays[1 - JITTER_WINDOW :], float(planned)]
            actual = max(self.expected_ms(rays), 1e-9)
            m = min(max(m, actual / OUTLIER_RATIO), actual * OUTLIER_RATIO)
        k = TIME_MODEL_DECAY
        if not self.calibrated and self.rounds == 0:
            # The initial guess is a guess: the first measured round replaces it at once.
            self.prior_weight = PRIOR_WEIGHT_MIN
        self.prior_weight = max(self.prior_weight * k, PRIOR_WEIGHT_MIN)
        self._w = k * self._w + 1.0
        self._r = k * self._r + x
        self._m = k * self._m + m
        self._rr = k * self._rr + x * x
        self._rm = k * self._rm + x * m
        self.rounds += 1
        self._fit()
        self._update_safety()

    def _update_safety(self) -> None:
        """``safety`` from the window (none: unchanged): the weighted JITTER_QUANTILE
        quantile (the smallest ratio with at least that share of the window's weight at or
        below it) of measured / modelled ms, modelled by the current fit for the rays
        each round was predicted to cast and weighted by those ms, the window filled up
        to JITTER_WINDOW rounds at TIME_SAFETY_INITIAL, clamped."""
        if not self.jitter_ms:
            return
        # One array pass (this runs after every round, over up to JITTER_WINDOW rounds).
        modelled = np.maximum(self.overhead_ms + self.ms_per_ray * np.asarray(self.jitter_rays),
                              1e-9)  # fmt: skip
        ratios, weights = np.asarray(self.jitter_ms) / modelled, modelled
        padding = JITTER_WINDOW - len(ratios)  # the young window's prior rounds, as one
        if padding > 0:
            ratios = np.append(ratios, TIME_SAFETY_INITIAL)
            weights = np.append(weights, padding * modelled.mean())
        order = np.argsort(ratios, kind="stable")
        below = np.cumsum(weights[order])
        at = int(np.searchsorted(below, JITTER_QUANTILE * below[-1]))
        quantile = float(ratios[order[min(at, len(order) - 1)]])
        self.safety = min(max(quantile, TIME_SAFETY_MIN), TIME_SAFETY_MAX)

    def _fit(self) -> None:
        """Weighted least squares of the rounds and the prior's two pseudo-rounds."""
        p, a0, b0 = self.prior_weight, self.prior_overhead_ms, self.prior_ms_per_ray * RAY_UNIT
        w = self._w + 2.0 * p
        r = self._r + p  # the pseudo-rounds at x = 0 and x = 1
        m = self._m + p * a0 + p * (a0 + b0)
        rr = self._rr + p
        rm = self._rm + p * (a0 + b0)
        det = w * rr - r * r  # > 0: the pseudo-rounds at two different x
        slope = (w * rm - r * m) / det if det > 0.0 else -1.0
        intercept = (m - slope * r) / w
        if slope > 0.0 and intercept >= 0.0:
            overhead, per_unit = intercept, slope
        elif slope > 0.0:  # negative fixed cost: a line through the origin instead
            overhead, per_unit = 0.0, rm / rr
        else:  # time does not grow with rays: the prior's per-ray cost, height from the mean
            per_unit = b0
            overhead = max((m - per_unit * r) / w, 0.0)
        typical = float(np.median(self.jitter_ms)) if self.jitter_ms else math.inf
        if overhead > typical:
            # Every round costs the fixed cost and more, so the window's median round time
            # bounds it: the line through that bound that fits the rounds best. Unbounded,
            # a spell of slow rounds of about the same rays (no spread to tell the fixed
            # cost from the per-ray cost) fits a flat line at their time, and every
            # reflector, however small, is predicted above the budget. The median, not the
            # fastest round: a frame's first round also groups the G-buffer's reflector
            # pixels, so later rounds' fixed cost is lower (capped at the fastest, the
            # farm's prediction error is 35 % rather than 12 %). A lasting rise of the
            # fixed cost is followed once it fills half the window (~96 rounds); until
            # then the safety factor covers it. Measurements:
            # docs/bench-log/2026-12-03-8cbb651-fixed-cost-bound.md.
            overhead = typical
            per_unit = max((rm - overhead * r) / rr, 0.0) if rr > 0.0 else b0
        self.overhead_ms = float(overhead)
        self.ms_per_ray = max(float(per_unit) / RAY_UNIT, MIN_MS_PER_RAY)

    def relax(self) -> None:
        """Nothing fitted the time budget this frame: lower the safety factor a little
        (every measured ms of its window, STARVED_RELAX), and once it is at its minimum,
        the modelled times (STARVED_SCALE)."""
        if self.safety <= TIME_SAFETY_MIN:
            k = STARVED_SCALE
            self.prior_overhead_ms *= k
            self.prior_ms_per_ray = max(self.prior_ms_per_ray * k, MIN_MS_PER_RAY)
            self._m *= k
            self._rm *= k
            # The window's rounds scale with the model, so their ratios to it stay.
            self.jitter_ms = [m * k for m in self.jitter_ms]
            self._fit()
        self.jitter_ms = [m * STARVED_RELAX for m in self.jitter_ms]
        self.safety = max(self.safety * STARVED_RELAX, TIME_SAFETY_MIN)

    def expected_ms(self, rays: float) -> float:
        """Central estimate of a round's milliseconds (no safety factor)."""
        return self.overhead_ms + self.ms_per_ray * max(rays, 0.0)

    def predicted_ms(self, rays: float) -> float:
        """Conservative milliseconds for a round of ``rays`` rays (``safety`` included)."""
        return self.expected_ms(rays) * self.safety

    def rays_within(self, ms: float) -> float:
        """Most rays a round may cast and still (conservatively) end within ``ms``."""
        return max((ms / self.safety - self.overhead_ms) / self.ms_per_ray, 0.0)
