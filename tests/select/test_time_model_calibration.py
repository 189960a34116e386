"""The time model's calibration: the line and the cost of a filled pixel fitted to timed
rounds, the safety factor it starts from, and what a policy charges a reflector traced
at a reduced density. Every timing here is synthetic (no timing asserts)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from selection_fakes import element, policy_of, scene, view

from phrt_usd.model.frame import Budget, TraceRecord
from phrt_usd.model.trace_density import COARSEST, traced_fraction
from phrt_usd.select.cost_model import (
    CALIBRATION_SAFETY_MAX,
    TIME_SAFETY_INITIAL,
    TraceTimeModel,
    calibration_line,
)

#: The synthetic tracer: a round takes OVERHEAD_MS + MS_PER_RAY * rays + MS_PER_FILLED *
#: filled pixels (a filled pixel costs 0.6 rays, as measured on a cluttered mirror floor).
OVERHEAD_MS, MS_PER_RAY, MS_PER_FILLED = 0.3, 4e-4, 2.4e-4


def round_ms(rays, filled=0):
    return OVERHEAD_MS + MS_PER_RAY * rays + MS_PER_FILLED * filled


def calibration_rounds(scale=None):
    """Rounds as ``calibrate_tracer`` times them: full density at growing sizes, then a
    coarsest-density round of whole reflectors (1/16 of its pixels start rays, 3 rays
    each). ``scale`` (a function of the round index) multiplies each round's time."""
    sizes = [(64 * 3, 0), (256 * 3, 0), (1024 * 3, 0), (4096 * 3, 0), (1024 * 3, 15360)]
    return [(r, round_ms(r, f) * (scale(k) if scale else 1.0), f)
            for k, (r, f) in enumerate(sizes)]  # fmt: skip


def test_calibration_fits_the_line_and_the_cost_of_a_filled_pixel():
    model = TraceTimeModel()
    model.calibrate(calibration_rounds())
    assert model.calibrated
    # Exact rounds: the fit recovers the synthetic machine (1e-6: float rounding only).
    assert model.prior_overhead_ms == pytest.approx(OVERHEAD_MS, rel=1e-6)
    assert model.prior_ms_per_ray == pytest.approx(MS_PER_RAY, rel=1e-6)
    assert model.fill_rays == pytest.approx(MS_PER_FILLED / MS_PER_RAY, rel=1e-6)
    # So a coarsest-density round of 20k covered pixels (1,250 traced, 3 rays each) is
    # predicted at its time, filled pixels included (1e-6 again).
    rays, filled = 3750, 18750
    assert model.expected_ms(rays + model.fill_rays * filled) == pytest.approx(
        round_ms(rays, filled), rel=1e-6
    )
    # Without rounds at a reduced density the filled pixels' cost is unknown: unchanged.
    other = TraceTimeModel()
    other.calibrate([(r, m, f) for r, m, f in calibration_rounds() if f == 0])
    assert other.fill_rays == TraceTimeModel().fill_rays


def test_a_slow_repeat_does_not_tilt_the_calibrated_line():
    # Each size timed twice; one repeat of the smallest took 3x (another process on the
    # cores): the line comes from each size's fastest round, the spread from all.
    rounds = []
    for k, (r, m, f) in enumerate(calibration_rounds()):
        rounds += [(r, m * (3.0 if k == 0 else 1.0), f), (r, m, f)]
    model = TraceTimeModel()
    model.calibrate(rounds)
    # 1e-6: the fastest repeats are exact.
    assert model.prior_ms_per_ray == pytest.approx(MS_PER_RAY, rel=1e-6)
    assert model.prior_overhead_ms == pytest.approx(OVERHEAD_MS, rel=1e-6)
    # The slow repeat is a small round: weighted by its ms it does not set the factor.
    assert model.safety == TIME_SAFETY_INITIAL


def test_calibration_line_weighs_relative_error():
    # Sizes from 200 to 12,800 rays: least squares of the relative error let the small
    # rounds decide the fixed cost (0.38 ms of their time) and the large the per-ray.
    rays = np.array([200.0, 800.0, 3200.0, 12800.0])
    ms = np.array([round_ms(r) for r in rays]) * np.array([1.02, 0.98, 1.02, 0.98])
    overhead, slope = calibration_line(rays, ms)
    # 2 % jitter: the fixed cost within 20 %, the per-ray cost within 5 %.
    assert overhead == pytest.approx(OVERHEAD_MS, rel=0.2)
    assert slope == pytest.approx(MS_PER_RAY, rel=0.05)


def test_calibration_spread_starts_the_safety_factor_and_fades_with_its_prior():
    # The calibration's largest round took 1.6x its line (a loaded spell): the first
    # frame plans with that margin ...
    model = TraceTimeModel()
    model.calibrate(calibration_rounds(lambda k: 1.6 if k == 3 else 1.0))
    assert 1.3 <= model.safety <= CALIBRATION_SAFETY_MAX
    first = model.safety
    # ... which fades as the rounds the renderer measures take the prior's place in the
    # fit (exact rounds: 40 of them leave the prior ~1 % of its weight).
    for k in range(40):
        rays = 2000 + 500 * (k % 5)
        model.learn(rays, round_ms(rays))
    assert model.safety < first
    # 0.05: the young window still holds the prior's ratio at its share of the weight.
    assert model.safety <= TIME_SAFETY_INITIAL + 0.05
    # Uncalibrated, the factor starts where it always did.
    assert TraceTimeModel().safety == TIME_SAFETY_INITIAL


def test_first_round_planned_within_the_budget_by_the_calibrated_model():
    """A stage never seen: the first round's planned cost, filled pixels included, is
    what the calibrated model says fits T (its safety factor included)."""
    T = 6.0
    sc = scene([element((x, 0.0, -4.0)) for x in (-2.0, 0.0, 2.0)], lights=2)
    policy = policy_of("heu1")
    policy.calibrate(calibration_rounds(), rays=30000, pixels=10000)
    pixels = np.array([9000, 8000, 7000])  # every reflector at full density: ~30 ms
    policy.begin_frame(view(pixels), sc)
    ids = policy.next_round(Budget(ms=T))
    assert ids  # something fits, at reduced densities
    densities = policy.round_densities(ids)
    shares = [traced_fraction(pixels[e], d) for e, d in zip(ids, densities, strict=True)]
    assert min(shares) < 1.0
    # Its planned cost, filled pixels at the calibrated cost, fits T by the model ...
    model = policy.time_model
    filled = sum(pixels[e] * (1.0 - s) for e, s in zip(ids, shares, strict=True))
    planned = sum(policy.predicted_rays(e) * s for e, s in zip(ids, shares, strict=True))
    assert model.predicted_ms(planned + model.fill_rays * filled) <= T
    # ... and the time the synthetic machine takes for it is within T (the calibration
    # saw the machine exactly: the plan keeps the safety factor's margin).
    rays = sum(pixels[e] * s * 3.0 for e, s in zip(ids, shares, strict=True))
    assert round_ms(rays, filled) <= T
    policy.record([TraceRecord(e, int(pixels[e]), int(pixels[e] * 3)) for e in ids], 0.004)
    policy.end_frame()


def test_calibration_seeds_each_reflectors_rays_per_pixel():
    """The calibration's rounds traced each visible reflector at some of its pixels: its
    own rays per pixel predicts it (drawn towards the rounds' mean by 16 pixels), not the
    mean of all reflectors, which a large plain one dominates."""
    sc = scene([element((0.0, 0.0, -4.0)), element((2.0, 0.0, -4.0))], lights=2)
    policy = policy_of("heu1")
    records = [TraceRecord(0, 4000, 8000), TraceRecord(1, 400, 3200)]  # 2 and 8 rays a pixel
    policy.calibrate(calibration_rounds(), rays=11200, pixels=4400, records=records)
    policy.begin_frame(view(np.array([1000, 1000])), sc)
    mean = 11200 / 4400
    assert policy.predicted_rays(0) == pytest.approx(1000 * (8000 + 16 * mean) / 4016)
    assert policy.predicted_rays(1) == pytest.approx(1000 * (3200 + 16 * mean) / 416)
    policy.end_frame()


def test_filled_pixels_count_under_a_time_budget_only():
    """Under a rays budget a reflector costs its rays (deterministic runs unchanged);
    under a time budget also its filled pixels, at the calibrated cost."""
    sc = scene([element((0.0, 0.0, -4.0))], lights=1)
    policy = policy_of("heu1")
    policy.calibrate(calibration_rounds(), rays=30000, pixels=10000)
    fill = policy.time_model.fill_rays
    assert fill > 0.0
    pixels = np.array([4096])
    costs = {}
    for budget in (Budget(rays=10**6), Budget(ms=1000.0)):
        policy.begin_frame(view(pixels), sc)
        policy.next_round(budget)
        costs[budget.ms is None] = policy.level_rays(0, COARSEST)
        policy.end_frame()
    share = 1.0 / 16.0  # the coarsest density's
    assert costs[False] - costs[True] == pytest.approx(fill * 4096 * (1.0 - share))
    assert math.isfinite(costs[True]) and costs[True] > 0.0


def test_rounds_learn_their_filled_pixels_at_the_calibrated_cost():
    """Rounds mixing rays and filled pixels, timed by the synthetic machine: the line
    the model learns stays the machine's (the filled pixels counted at the calibrated
    cost, not taken for rays)."""
    model = TraceTimeModel()
    model.calibrate(calibration_rounds())
    rng = np.random.default_rng(2)
    for _ in range(60):
        rays, filled = int(rng.uniform(1000, 8000)), int(rng.uniform(0, 30000))
        model.learn(rays, round_ms(rays, filled), filled=filled)
    # 1e-6: exact rounds, exact calibration.
    assert model.ms_per_ray == pytest.approx(MS_PER_RAY, rel=1e-6)
    assert model.overhead_ms == pytest.approx(OVERHEAD_MS, rel=1e-6)


def test_calibration_spread_fades_once_rounds_are_measured():
    # The calibration's largest round took 1.6x its line: the first frame plans with its
    # spread (1.32); three exact rounds later the factor is within 0.05 of
    # TIME_SAFETY_INITIAL (the excess halved a round: 1.1 + 0.22 / 8 = 1.13). Faded with
    # the prior's weight (0.9 a round) it was still 1.26, and ~1.2 ten rounds on.
    model = TraceTimeModel()
    model.calibrate(calibration_rounds(lambda k: 1.6 if k == 3 else 1.0))
    assert model.safety >= 1.3
    for rays in (3000, 3500, 4000):
        model.learn(rays, round_ms(rays))
    assert model.safety <= TIME_SAFETY_INITIAL + 0.05
