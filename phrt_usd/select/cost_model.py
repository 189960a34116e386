"""The trace-time cost model: milliseconds of a tracing round predicted from its ray count
and the pixels it made without rays, each kind counted in rays, started from a
calibration on the run's own stage, learned online from the rounds the renderer
measures, with a safety factor that tracks wall-time jitter.

What a policy checks its budget against is a prediction of the rays tracing a candidate
costs (``BudgetedPolicy.predicted_rays`` and ``level_rays`` in
``phrt_usd.select.policies``) and of the time those rays take (``TraceTimeModel`` here).

The rule. A round of ``rays`` rays (every kind the tracer counts: reflection,
refraction, shadow) that ``filled`` and ``reused`` pixels (``model/pixel_kinds.py``) and
``marched`` the first rays of pixels through the G-buffer (screen space on), counted per
source in ``TraceRecord``, takes

    overhead_ms + ms_per_ray * (rays + fill_rays * filled + reuse_rays * reused
                                + screen_space_rays * marched)

milliseconds. Each figure is what one such pixel costs beyond the rays counted, in rays:
a filled pixel the reconstruction from up to 12 traced neighbours, a reused one the
reprojection of its history (one previous pixel read, after the per-pixel tests), a
marched one the screen-space march (and, for the few it resolves, their hit's surface
and shading, whose shadow rays are counted rays; their reflection ray and its bounces
are not cast, which their counted rays show). A traced pixel costs only its rays.

Why the march is priced per marched pixel, not per resolved (screen-space) pixel: every
first ray is marched, resolved or not, and few resolve (sewer frame 241: 4-6 % at the
march's bound of 32 steps), so the step's cost is the march over all of them (~0.3-0.6
us a pixel there, ~0.4-0.8 rays), and a reflector whose rays all leave the screen pays
it too. Priced per resolved pixel, one would cost ~16 rays on the sewer and nothing on
such a reflector.

The calibration measures each (``engine/trace_calibration.py``); the rounds the renderer
measures refine them where they tell them apart (``_fit_kinds``). Under a rays budget
alone nothing but rays counts (the policies price the kinds under a time budget only).
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
#: - A window not full yet is filled up with rounds at TIME_SAFETY_INITIAL (plus the
#:   calibration's spread above it while its line still weighs in the fit), each of the
#:   real rounds' mean weight: one slow round is not the quantile of a young window (on
#:   the farm at T = 1 ms an early round can take 25x its model, which as the quantile
#:   would set the factor to its maximum and starve ~60 frames), while a few slow rounds
#:   in a full window still raise it.
#: On a quiet machine it settles near 1.1-1.2: the selection then plans to use ~85-90 % of
#: the budget. Ratios (measured / modelled ms). Measurements: the weighted window
#: quantile in docs/bench-log/2026-12-03-d62f485-safety-glue-temporal.md, the current
#: fit and the young window's filling in docs/bench-log/2026-12-03-2987843-make-room-hold.md.
TIME_SAFETY_MIN = 1.05
#: The factor before any round was measured (uncalibrated; a calibration's spread is
#: never taken below it), and the ratio of the rounds that fill up a young window: where
#: it settles on a quiet machine.
TIME_SAFETY_INITIAL = 1.1
#: The calibration's spread above TIME_SAFETY_INITIAL fills a young window at this share
#: less for each round measured since (``_young_ratio``). Its largest part is the
#: calibration line's own error at sizes the frames do not trace (on the wet tunnel at
#: T = 16 ms its 2,000-ray rounds took 1.7-1.9x the line through the 200- and 20,000-ray
#: ones: below the thread pool's split a ray costs twice as much) and a repeat slowed by
#: another process; once a round was measured, the line goes through the machine's
#: present speed there (``_speed``) and the rounds' own ratios are the margin's measure.
#: Faded at the prior's weight (0.9 a round), a spread of 1.5-1.75 kept the factor above
#: 1.3 for 10-15 frames: they planned 9-11 ms of T = 16 ms, their reflectors at reduced
#: densities, while the rounds took 0.8-1.15x their central estimate.
CALIBRATION_SPREAD_FADE = 0.5
#: Upper clamp of the calibration's safety factor (``TraceTimeModel.calibrate``): a
#: calibration timed in a loaded spell still lets the first frames plan half the budget;
#: their rounds then correct the factor.
CALIBRATION_SAFETY_MAX = 2.0
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
#: A render with a time budget replaces both by a calibration on its own stage, at the
#: sizes its budget plans, before the first round (``TraceTimeModel.calibrate``;
#: engine/trace_calibration.py).
INITIAL_MS_PER_RAY = 0.004
INITIAL_ROUND_MS = 0.5

#: What filling a skipped pixel of a reduced-density reflector costs, in rays, before a
#: calibration measured it: nothing (a run without one has a rays budget, which counts
#: rays only); reused and marched pixels alike (INITIAL_KIND_RAYS). A run's rounds
#: often mix rays and filled pixels in about the same proportion, which cannot tell the
#: two costs apart (learned online from them alone, a figure 0.6 off the truth was still
#: 0.17-0.22 off after 400 frames of a simulated tracer): the online fit keeps the
#: calibration's figures there (KIND_PRIOR_WEIGHT). On a mirror floor of 64 small
#: reflective spheres (320 x 240, every reflector at a sixteenth: 9,973 rays, 45.6k
#: filled pixels, 8.5-9 ms against 0.3 ms + 0.2 us a ray) a filled pixel took ~0.14 us,
#: ~0.6 rays; calibrations there measure 0.5-1.3.
INITIAL_FILL_RAYS = 0.0
INITIAL_KIND_RAYS = (INITIAL_FILL_RAYS, 0.0, 0.0)
#: Upper clamp of the calibrated cost of a filled pixel: a filled pixel reads a few
#: neighbours, never the cost of several rays (a larger figure is noise in the rounds).
FILL_RAYS_MAX = 4.0
#: Upper clamp of the cost of a reused pixel: its lookup reads one previous pixel, less
#: than the fill it replaces (docs/temporal-reuse.md: ~70 against ~110 ns).
REUSE_RAYS_MAX = FILL_RAYS_MAX
#: Upper clamp of the cost of a marched pixel: a march of at most
#: ``screen_space.MAX_STEPS`` (32) pixels at ~5 ns a step, against ~0.15-0.2 us for a
#: first ray (docs/screen-space.md): about a ray, never the cost of many.
SCREEN_SPACE_RAYS_MAX = 4.0
#: The pixels priced apart from rays, in the order of ``TraceTimeModel``'s per-kind
#: lists (``kind_rays``, ``prior_kind_rays``) and ``learn``'s arguments: filled, reused,
#: and marched in screen space (``TraceRecord``'s counts of the same names).
PRICED_KINDS = ("filled", "reused", "marched")
#: Their clamps, in that order.
KIND_RAYS_MAX = (FILL_RAYS_MAX, REUSE_RAYS_MAX, SCREEN_SPACE_RAYS_MAX)
#: The order the calibration prices them in (indices into PRICED_KINDS): the march from
#: full-density rounds with screen space (against the line of rounds without), then the
#: fill from reduced-density rounds without history, then reuse from rounds with
#: history (which fill what their history does not cover): each from the rounds whose
#: other kinds are priced already.
CALIBRATION_ORDER = (2, 0, 1)
#: The kinds' costs are fitted to the rounds with this forgetting per round (the line's
#: is TIME_MODEL_DECAY): what a kind costs in rays is a property of the stage and the
#: code, not of the machine's load, and three more coefficients need more rounds than
#: two. Over ~100 rounds (30-100 frames), synthetic rounds of 10 % jitter whose reused
#: share varies at random put the mean of each cost over rounds 100-300 within 0.06 rays
#: of the truth; over ~10 (the line's forgetting), 0.1-0.4 rays off, up to 4 where the
#: mix barely varies.
KIND_DECAY = 0.99
#: The calibration's figure of each kind enters that fit as a ridge towards it
#: (pseudo-rounds of RAY_UNIT pixels of the kind alone at that many rays at the line's
#: present ms per ray), weighing what the calibration's own rounds of that kind weigh
#: in the fit (the sum of (pixels / RAY_UNIT)^2 over the configurations that priced it,
#: each size's fastest round: on the sewer at 320 x 240 about 0.6-1.5), never
#: forgotten, and never below KIND_PRIOR_WEIGHT_MIN (a kind the calibration did not
#: see: the rounds decide). A run's rounds often mix the kinds in about the same
#: proportion (every frame's reflectors at the same rates, the same share of history
#: found), which cannot tell them apart; there the calibration's figures stand and the
#: line learns the machine's speed. Where the mix varies (a reflector stepping its rate,
#: a view starting or stopping to reproject) the rounds decide as they outweigh it. The
#: wet tunnel's rounds (sewer 217-276, HEU1, T = 16 ms, screen space on) replayed
#: through the fit: at 0.05 for every kind the fill's figure ranged over 0.09-2.0 rays,
#: at the calibration's weights over 0.19-0.94, for the same error of the predicted
#: round times (mean |log(measured / predicted)| 0.17; 0.24 with the calibration's
#: figures held).
KIND_PRIOR_WEIGHT_MIN = 0.05

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
#: already outweighs it (a frame's rounds are what the budget is charged; the
#: calibration's are only like them). Their weight is forgotten like a measured
#: round's (TIME_MODEL_DECAY per round); when the rounds all trace about the same rays,
#: they decide the line's height there and the prior only its tilt.
PRIOR_WEIGHT = 0.5
#: The prior's weight never falls below this: with identical rounds the two terms cannot
#: be told apart from data, and the remaining prior keeps the normal equations regular.
PRIOR_WEIGHT_MIN = 1e-9
#: A calibrated prior's pseudo-round at 0 rays (its fixed cost) weighs this much more in
#: the line's fit and the kinds', never forgotten, and the line's pseudo-rounds stand at
#: the prior line times the machine's present speed (``_speed``: the recent rounds' ms
#: over the prior line's for them). So the fixed cost keeps the calibration's share of a
#: round's time where the rounds cannot tell it apart, and only there. A policy plans
#: every round to the budget, so its rounds cast about the same equivalent rays (the wet
#: tunnel at T = 16 ms: 16-18k a first round, frame after frame), whose spread cannot
#: separate a fixed cost from a per-ray cost, and when the machine slows the policy steps
#: coarser: fewer rays, more filled pixels, the same equivalent rays at more ms. With the
#: prior forgotten the line took any such change for a fixed cost. Sewer 217-276, HEU1,
#: T = 16 ms, a quiet machine: 1.4-3.4 ms fixed and 0.48-0.55 us a ray, where least
#: squares over the same run's rounds find 0.0 ms and 0.56 us; on a simulated machine
#: slowing 1.8x at frame 235, 8-13 ms and 0.2-0.6 us against a true 0.4 ms and 1.2 us.
#: Priced so, a reflector's rays look cheap and its filled pixels dear (their cost in
#: rays is the line's ms per pixel over its ms per ray): on the simulated machine HEU1
#: traced a few reflectors at full density and dropped the rest rather than trace them
#: all at a sixteenth (the last 12 frames at FLIP 0.22-0.25, the raster's 0.29; 0.19
#: so anchored; over the run 0.11-0.14 against 0.097, three seeds). The anchor leaves the
#: tilt to the rounds wherever their rays spread (its weight against theirs is about
#: that of their spread over their mean): rounds of 200-1,400 rays that all take 1 ms
#: outweigh it three to one, the tunnel's rounds weigh 1/30 of it.
FIXED_COST_PRIOR_WEIGHT = 0.5
#: Solves of the kinds' fit (``_fit_kinds``): the first draws each kind towards its
#: figure at the prior's ms per ray, each next one at the last solve's (three: within
#: 0.001 rays of the fixed point on the tests' rounds).
KIND_RIDGE_SOLVES = 3


class TraceTimeModel:
    """Milliseconds of one tracing round: ``overhead_ms + ms_per_ray * rays``, where
    ``rays`` are the rays cast plus, for each pixel made without rays, its kind's cost in
    rays (``fill_rays``, ``reuse_rays``, ``screen_space_rays``: the module's rule,
    ``equivalent_rays``).

    The line is fitted by exponentially weighted least squares over the rounds seen so
    far (older rounds weigh ``TIME_MODEL_DECAY`` less per round) and a prior line: the
    calibration of ``calibrate`` (or INITIAL_ROUND_MS / INITIAL_MS_PER_RAY without one)
    as two pseudo-rounds at its line times the machine's present speed (``_speed``),
    whose weight is forgotten as rounds come (PRIOR_WEIGHT) but for the calibrated fixed
    cost's (FIXED_COST_PRIOR_WEIGHT). So the fit converges to the measured time also
    when every round traces about the same rays (a still or turntable shot, a policy
    planning each round to the budget): the rounds fix the line's height where they are,
    the prior its tilt. A negative fixed cost is replaced by a line through the origin,
    a non-positive slope by the prior's per-ray cost (noise dominating small rounds), and
    a fixed cost above the median round time of the safety factor's window by that median
    (``_fit_line``).

    The kinds' costs start from the calibration's (``prior_kind_rays``) and are refined
    by the rounds that made such pixels: each round's time at the calibration's speed is
    fitted to its rays and counts by least squares, drawn towards the calibration's
    figures in rays (KIND_PRIOR_WEIGHT), and the line refitted with them (``_fit``).
    Rounds whose mix of kinds never varies leave the calibration's figures as they are,
    and a slower machine is the line's, not a kind's.

    Predictions are multiplied by ``safety``: the JITTER_QUANTILE quantile of (measured /
    modelled) round time over the last JITTER_WINDOW rounds, weighted by the rounds'
    modelled ms, clamped to [TIME_SAFETY_MIN, TIME_SAFETY_MAX]; before the first round,
    the calibration's spread (``prior_safety``; TIME_SAFETY_INITIAL uncalibrated), which
    then fades by CALIBRATION_SPREAD_FADE a round.
    ``expected_ms`` is the central estimate without it.
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
        #: The safety factor of the prior line: the calibration's spread
        #: (``calibrate``), TIME_SAFETY_INITIAL without one.
        self.prior_safety = TIME_SAFETY_INITIAL
        #: What one pixel costs beyond its rays, in rays: filled from its traced
        #: neighbours, reused from the previous frame, its first ray marched in screen
        #: space (the calibration's, refined by the rounds; INITIAL_KIND_RAYS without
        #: either).
        self.fill_rays, self.reuse_rays, self.screen_space_rays = INITIAL_KIND_RAYS
        #: The calibration's figures of those costs (PRICED_KINDS order), in rays: what
        #: the online fit of the kinds is drawn towards, and how strongly (the weight of
        #: the calibration's rounds of each kind, KIND_PRIOR_WEIGHT_MIN).
        self.prior_kind_rays = list(INITIAL_KIND_RAYS)
        self.kind_prior_weight = [KIND_PRIOR_WEIGHT_MIN] * len(PRICED_KINDS)
        #: True once ``calibrate`` set the prior from this stage's own rays.
        self.calibrated = False
        # Weighted sums of the measured rounds over z = (1, rays, filled, reused,
        # marched pixels), the counts in RAY_UNIT: z z^T row-major (25) and z * ms (5),
        # forgotten at TIME_MODEL_DECAY (the line's) and at KIND_DECAY (the kinds').
        self._zz = [0.0] * 25
        self._zm = [0.0] * 5
        self._kind_zz = [0.0] * 25
        self._kind_zm = [0.0] * 5

    @property
    def kind_rays(self) -> tuple[float, float, float]:
        """(``fill_rays``, ``reuse_rays``, ``screen_space_rays``): PRICED_KINDS' costs."""
        return (self.fill_rays, self.reuse_rays, self.screen_space_rays)

    def equivalent_rays(self, rays: float, filled: float = 0.0, reused: float = 0.0,
                        marched: float = 0.0) -> float:  # fmt: skip
        """A round's ``rays`` plus its filled, reused and marched pixels, each at its
        cost in rays: what ``expected_ms``, ``predicted_ms`` and ``rays_within`` count."""
        return (float(rays) + self.fill_rays * filled + self.reuse_rays * reused
                + self.screen_space_rays * marched)  # fmt: skip

    def calibrate(self, samples: list[tuple]) -> None:
        """Set the prior line, the kinds' costs and the prior's safety factor from timed
        calibration rounds ``(rays, ms)`` or ``(rays, ms, filled[, reused[, marched]])``
        (pixel counts; at least one round with none of them, and rounds of two sizes or
        more separate the fixed cost from the per-ray cost) and refit. The line: least
        squares of the relative error of each such size's fastest round
        (``calibration_line``). Each kind in CALIBRATION_ORDER: what the fastest round of
        each configuration that counted it (and no kind priced after it) took beyond the
        line and the kinds priced before it, per pixel of it, in rays, pooled over those
        rounds; a kind no round counted keeps its cost. The safety factor: the
        JITTER_QUANTILE quantile of every round's measured / modelled ms, weighted by
        modelled ms, within [TIME_SAFETY_INITIAL, CALIBRATION_SAFETY_MAX]. It starts the
        factor, and fills a young window as long as the prior weighs in the fit
        (``_young_ratio``). Each kind's figure weighs in the online fit what its rounds
        weigh (KIND_PRIOR_WEIGHT_MIN). Marks the model calibrated; rounds learned before
        stay."""
        pts = []
        for r, m, *counts in samples:
            counts = [float(c) for c in counts[: len(PRICED_KINDS)]]
            counts += [0.0] * (len(PRICED_KINDS) - len(counts))
            if r > 0 and math.isfinite(m) and m > 0 and all(c >= 0 for c in counts):
                pts.append((float(r), float(m), *counts))
        if not pts:
            return
        table = np.array(pts, np.float64)
        rays, ms, counts = table[:, 0], table[:, 1], table[:, 2:]
        # The line and the kinds from each round configuration's fastest repeat (a repeat
        # slowed by another process must not tilt them), the safety factor from every one.
        fastest: dict[tuple[float, ...], float] = {}
        for r, m, *c in pts:
            key = (r, *c)
            fastest[key] = min(m, fastest.get(key, math.inf))
        sizes = np.array([(*key, m) for key, m in sorted(fastest.items())]).reshape(-1, 5)
        made = sizes[:, 1:4]  # pixels of each kind
        full = sizes[~made.any(axis=1)]
        if not len(full):
            return
        overhead, slope = calibration_line(full[:, 0], full[:, 4])
        self.prior_overhead_ms = overhead
        self.prior_ms_per_ray = max(slope, MIN_MS_PER_RAY)
        kinds = np.array(self.kind_rays)
        for position, k in enumerate(CALIBRATION_ORDER):
            later = list(CALIBRATION_ORDER[position + 1 :])
            rows = (made[:, k] > 0) & ~made[:, later].any(axis=1)
            if rows.any():
                kinds[k] = 0.0
                beyond = sizes[rows, 4] - overhead - self.prior_ms_per_ray * (
                    sizes[rows, 0] + made[rows] @ kinds
                )
                per_pixel = max(float(beyond.sum() / made[rows, k].sum()), 0.0)
                kinds[k] = min(per_pixel / self.prior_ms_per_ray, KIND_RAYS_MAX[k])
                weight = float(np.sum((made[rows, k] / RAY_UNIT) ** 2))
                self.kind_prior_weight[k] = max(weight, KIND_PRIOR_WEIGHT_MIN)
        self.fill_rays, self.reuse_rays, self.screen_space_rays = (float(v) for v in kinds)
        self.prior_kind_rays = kinds.tolist()
        self.prior_weight = PRIOR_WEIGHT
        modelled = np.maximum(overhead + self.prior_ms_per_ray * (rays + counts @ kinds), 1e-9)
        spread = weighted_quantile(ms / modelled, modelled, JITTER_QUANTILE)
        self.prior_safety = min(max(spread, TIME_SAFETY_INITIAL), CALIBRATION_SAFETY_MAX)
        self.calibrated = True
        self._fit()
        if self.jitter_ms:
            self._update_safety()
        else:
            self.safety = self.prior_safety

    def learn(self, rays: int, ms: float, planned_rays: float = 0.0, filled: float = 0.0,
              reused: float = 0.0, marched: float = 0.0) -> None:  # fmt: skip
        """One round: ``rays`` cast, ``filled`` and ``reused`` pixels and ``marched``
        first rays (``TraceRecord``'s counts) in ``ms`` wall-clock
        milliseconds; the line learns their ``equivalent_rays``, the kinds' costs what
        the line leaves (``_fit``). ``planned_rays`` (> 0): what the round was predicted
        to cost, in the same rays; the safety factor's ratio is then measured against
        the time modelled for them, so it also covers the error of the prediction."""
        if rays <= 0 or not math.isfinite(ms) or ms < 0.0:
            return
        counts = [float(c) if math.isfinite(c) and c > 0.0 else 0.0
                  for c in (filled, reused, marched)]  # fmt: skip
        equivalent = self.equivalent_rays(rays, *counts)
        m = float(ms)
        if self.rounds > 0 or self.calibrated:
            # (Uncalibrated, the first round only tells how wrong the initial guess was.)
            planned = (planned_rays if planned_rays > 0.0 and math.isfinite(planned_rays)
                       else equivalent)  # fmt: skip
            self.jitter_ms = [*self.jitter_ms[1 - JITTER_WINDOW :], m]
            self.jitter_rays = [*self.jitter_rays[1 - JITTER_WINDOW :], float(planned)]
            actual = max(self.expected_ms(equivalent), 1e-9)
            m = min(max(m, actual / OUTLIER_RATIO), actual * OUTLIER_RATIO)
        k = TIME_MODEL_DECAY
        if not self.calibrated and self.rounds == 0:
            # The initial guess is a guess: the first measured round replaces it at once.
            self.prior_weight = PRIOR_WEIGHT_MIN
        self.prior_weight = max(self.prior_weight * k, PRIOR_WEIGHT_MIN)
        z = np.array([1.0, float(rays) / RAY_UNIT, *(c / RAY_UNIT for c in counts)])
        zz = np.outer(z, z).reshape(-1)
        # The kinds learn the round's time at the prior's speed (``_fit_kinds``): over
        # the machine's speed with it (``_speed``; uncalibrated, as measured: the guess is
        # no reference).
        self._zz = (k * np.asarray(self._zz) + zz).tolist()
        self._zm = (k * np.asarray(self._zm) + z * m).tolist()
        speed = self._speed() if self.calibrated else 1.0
        self._kind_zz = (KIND_DECAY * np.asarray(self._kind_zz) + zz).tolist()
        self._kind_zm = (KIND_DECAY * np.asarray(self._kind_zm) + z * m / speed).tolist()
        self.rounds += 1
        self._fit()
        self._update_safety()

    def _update_safety(self) -> None:
        """``safety`` from the window (none: unchanged): the weighted JITTER_QUANTILE
        quantile (``weighted_quantile``) of measured / modelled ms, modelled by the current
        fit for the rays each round was predicted to cast and weighted by those ms, the
        window filled up to JITTER_WINDOW rounds at ``_young_ratio``, clamped."""
        if not self.jitter_ms:
            return
        # One array pass (this runs after every round, over up to JITTER_WINDOW rounds).
        modelled = np.maximum(self.overhead_ms + self.ms_per_ray * np.asarray(self.jitter_rays),
                              1e-9)  # fmt: skip
        ratios, weights = np.asarray(self.jitter_ms) / modelled, modelled
        padding = JITTER_WINDOW - len(ratios)  # the young window's prior rounds, as one
        if padding > 0:
            ratios = np.append(ratios, self._young_ratio())
            weights = np.append(weights, padding * modelled.mean())
        quantile = weighted_quantile(ratios, weights, JITTER_QUANTILE)
        self.safety = min(max(quantile, TIME_SAFETY_MIN), TIME_SAFETY_MAX)

    def _young_ratio(self) -> float:
        """The ratio the rounds filling up a young window have: TIME_SAFETY_INITIAL plus
        the calibration's spread above it, a share CALIBRATION_SPREAD_FADE less for each
        round measured since the calibration (``prior_weight`` counts them)."""
        rounds = math.log(min(self.prior_weight / PRIOR_WEIGHT, 1.0)) / math.log(TIME_MODEL_DECAY)
        share = CALIBRATION_SPREAD_FADE ** rounds
        return TIME_SAFETY_INITIAL + (self.prior_safety - TIME_SAFETY_INITIAL) * share

    def _fit(self) -> None:
        """The kinds' costs (``_fit_kinds``), the line at those costs (``_fit_line``), and
        the kinds' costs again in the refitted line's rays."""
        self._fit_kinds()
        self._fit_line()
        self._fit_kinds()

    def _fit_kinds(self) -> None:
        """The kinds' costs from the rounds (sums forgotten at KIND_DECAY), each round's
        time at the prior line's speed (``learn``: scaled by the prior's ms per ray over
        the line's then; a slowdown is the line's to learn, not a kind's: on the wet
        tunnel a slower machine makes HEU1 step coarser, more filled pixels as every
        round takes longer, and fitted as measured a filled pixel's cost took up the
        slowdown, 1.0-1.8 rays against a true 0.3-0.4 on the simulated machine of
        FIXED_COST_PRIOR_WEIGHT): weighted least squares of ms = a + b rays + sum_k c_k
        n_k (n_k the pixels of kind k), with the prior line's two pseudo-rounds
        (``_prior_weights``) and, per kind, the ridge (c_k - prior_k B)^2 of weight
        ``kind_prior_weight`` (prior_k ``prior_kind_rays``, B a constant of the fit: the
        prior's ms per RAY_UNIT rays, then the last solve's b, KIND_RIDGE_SOLVES; so a
        kind the rounds cannot tell from the rays, the march, keeps its figure in rays
        without tilting b); each cost c_k / b in rays (what the line then charges for it
        is c_k), clamped to [0, KIND_RAYS_MAX]. Unchanged when the rounds leave no
        solution."""
        (p0, p1), a0 = self._prior_weights(), self.prior_overhead_ms
        b0 = self.prior_ms_per_ray * RAY_UNIT
        normal = np.asarray(self._kind_zz).reshape(5, 5).copy()
        right = np.asarray(self._kind_zm).copy()
        fixed, both = np.eye(5)[0], np.eye(5)[0] + np.eye(5)[1]  # pseudo-rounds at 0 and 1
        normal += p0 * np.outer(fixed, fixed) + p1 * np.outer(both, both)
        right += p0 * a0 * fixed + p1 * (a0 + b0) * both
        q, prior = np.asarray(self.kind_prior_weight), np.asarray(self.prior_kind_rays)
        normal[2:, 2:] += np.diag(q)
        theta, line = None, b0
        for _ in range(KIND_RIDGE_SOLVES):
            try:
                solved = np.linalg.solve(normal, right + np.r_[0.0, 0.0, q * prior * line])
            except np.linalg.LinAlgError:
                break
            if not (solved[1] > 0.0 and np.all(np.isfinite(solved))):
                break
            theta, line = solved, float(solved[1])
        if theta is None:
            return
        rho = np.clip(theta[2:] / theta[1], 0.0, KIND_RAYS_MAX)
        self.fill_rays, self.reuse_rays, self.screen_space_rays = (float(v) for v in rho)

    def _prior_weights(self) -> tuple[float, float]:
        """The weights of the prior's pseudo-rounds at 0 and at RAY_UNIT rays in the fits:
        ``prior_weight`` each, plus FIXED_COST_PRIOR_WEIGHT at 0 rays once calibrated (an
        uncalibrated guess is forgotten)."""
        anchor = FIXED_COST_PRIOR_WEIGHT if self.calibrated else 0.0
        return self.prior_weight + anchor, self.prior_weight

    def _speed(self) -> float:
        """How much slower the machine runs now than the prior says: the rounds' measured
        ms over the prior line's ms for their rays and pixels of each kind at the prior's
        figures (a reference that what the rounds teach does not move), each summed at
        TIME_MODEL_DECAY (the line's forgetting); 1 before any round."""
        zz = np.asarray(self._zz).reshape(5, 5)
        g = np.array([0.0, 1.0, *self.prior_kind_rays])
        per_unit = self.prior_ms_per_ray * RAY_UNIT
        prior = self.prior_overhead_ms * zz[0, 0] + per_unit * float(g @ zz[0])
        measured = float(self._zm[0])
        if not (prior > 0.0 and measured > 0.0 and math.isfinite(measured / prior)):
            return 1.0
        return measured / prior

    def _line_sums(self) -> tuple[float, float, float, float, float]:
        """The rounds' weighted sums of the line's fit: weight, x, ms, x^2, x * ms, x the
        round's ``equivalent_rays`` / RAY_UNIT at the kinds' current costs."""
        zz = np.asarray(self._zz).reshape(5, 5)
        zm = np.asarray(self._zm)
        g = np.array([0.0, 1.0, *self.kind_rays])
        return (float(zz[0, 0]), float(g @ zz[0]), float(zm[0]), float(g @ zz @ g),
                float(g @ zm))  # fmt: skip

    def _fit_line(self) -> None:
        """Weighted least squares of the rounds and the prior's two pseudo-rounds, at the
        prior line times the machine's present speed (``_speed``, ``_prior_weights``)."""
        speed, (p0, p1) = self._speed(), self._prior_weights()
        a0, b0 = speed * self.prior_overhead_ms, speed * self.prior_ms_per_ray * RAY_UNIT
        sw, sr, sm, srr, srm = self._line_sums()
        w = sw + p0 + p1
        r = sr + p1  # the pseudo-rounds at x = 0 and x = 1
        m = sm + p0 * a0 + p1 * (a0 + b0)
        rr = srr + p1
        rm = srm + p1 * (a0 + b0)
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
            self._zm = [v * k for v in self._zm]  # the rounds' ms (the kinds' in rays stay)
            self._kind_zm = [v * k for v in self._kind_zm]
            # The window's rounds scale with the model, so their ratios to it stay.
            self.jitter_ms = [m * k for m in self.jitter_ms]
            self._fit()
        self.jitter_ms = [m * STARVED_RELAX for m in self.jitter_ms]
        self.safety = max(self.safety * STARVED_RELAX, TIME_SAFETY_MIN)

    def expected_ms(self, rays: float) -> float:
        """Central estimate of a round's milliseconds (no safety factor); ``rays``, here
        and in ``predicted_ms`` and ``rays_within``, count a pixel made without rays at
        its kind's cost (``equivalent_rays``)."""
        return self.overhead_ms + self.ms_per_ray * max(rays, 0.0)

    def predicted_ms(self, rays: float) -> float:
        """Conservative milliseconds for a round of ``rays`` rays (``safety`` included)."""
        return self.expected_ms(rays) * self.safety

    def rays_within(self, ms: float) -> float:
        """Most rays a round may cast and still (conservatively) end within ``ms``."""
        return max((ms / self.safety - self.overhead_ms) / self.ms_per_ray, 0.0)


def calibration_line(rays: np.ndarray, ms: np.ndarray) -> tuple[float, float]:
    """(fixed ms, ms per ray) fitted to timed rounds ``rays``, ``ms`` (n,) float64 (ms >
    0): least squares of the relative error (weights 1 / ms^2), so the small rounds decide
    the fixed cost and the large ones the per-ray cost, whatever their ms. A negative
    fixed cost is replaced by the best line through the origin, a non-positive slope
    (rounds of one size, or timings too noisy to show growth) by the line through the
    origin and the slowest round per ray (conservative)."""
    w = 1.0 / ms**2
    sw, sr, sm = w.sum(), (w * rays).sum(), (w * ms).sum()
    srr, srm = (w * rays * rays).sum(), (w * rays * ms).sum()
    det = sw * srr - sr * sr
    slope = (sw * srm - sr * sm) / det if det > 1e-12 * sw * srr else 0.0
    if not slope > 0.0:
        return 0.0, float(np.max(ms / rays))
    overhead = (sm - slope * sr) / sw
    if overhead < 0.0:
        return 0.0, float(srm / srr)
    return float(overhead), float(slope)


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The smallest of ``values`` with at least the share ``q`` of ``weights``' sum at
    or below it."""
    order = np.argsort(values, kind="stable")
    below = np.cumsum(weights[order])
    at = int(np.searchsorted(below, q * below[-1]))
    return float(values[order[min(at, len(order) - 1)]])
