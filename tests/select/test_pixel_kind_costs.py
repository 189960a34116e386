"""The time model prices each kind of pixel made without rays apart from rays (filled,
reused, marched in screen space: ``select/cost_model.py``), the calibration measures
each, the rounds refine them, and a policy predicts a reflector's round from the mix of
kinds it learned (``BudgetedPolicy.level_rays``, ``select/pixel_kind_shares.py``). Every
timing here is synthetic."""

from __future__ import annotations

import numpy as np
import pytest
from selection_fakes import element, policy_of, scene, view

from phrt_usd.model.frame import Budget, TraceRecord
from phrt_usd.model.trace_density import DENSITY_FRACTION
from phrt_usd.select.cost_model import TraceTimeModel

#: The synthetic tracer: a round takes OVERHEAD_MS + MS_PER_RAY * (rays + FILL * filled
#: + REUSE * reused + MARCH * marched) ms (a reused pixel cheaper than a filled one, as
#: measured: docs/temporal-reuse.md).
OVERHEAD_MS, MS_PER_RAY = 0.3, 4e-4
FILL, REUSE, MARCH = 0.6, 0.25, 0.8


def round_ms(rays, filled=0.0, reused=0.0, marched=0.0):
    return OVERHEAD_MS + MS_PER_RAY * (rays + FILL * filled + REUSE * reused + MARCH * marched)


def calibration_rounds():
    """Rounds as ``calibrate_tracer`` times them, screen space on: full density at
    growing sizes without it, the largest again with it (every pixel marched), whole
    reflectors at a sixteenth (1/16 start rays, 3 rays each, the rest filled), the
    history's second frame at a half and a sixteenth with history (a few pixels filled
    where history was refused)."""
    rows = [(r, 0, 0, 0) for r in (192, 768, 3072, 12288)]
    rows += [(11000, 0, 0, 4096)]  # 4096 pixels marched, their rays fewer
    rows += [(3840, 19200, 0, 1280), (30720, 0, 10240, 10240), (3840, 1200, 18000, 1280)]
    return [(r, round_ms(r, f, u, m), f, u, m) for r, f, u, m in rows]


def test_calibration_prices_each_kind():
    model = TraceTimeModel()
    model.calibrate(calibration_rounds())
    # Exact rounds: the machine's line and each kind's cost (1e-6: float rounding).
    assert model.prior_ms_per_ray == pytest.approx(MS_PER_RAY, rel=1e-6)
    assert model.prior_overhead_ms == pytest.approx(OVERHEAD_MS, rel=1e-6)
    assert model.kind_rays == pytest.approx((FILL, REUSE, MARCH), rel=1e-6)
    assert model.prior_kind_rays == pytest.approx([FILL, REUSE, MARCH], rel=1e-6)
    # A round of every kind is predicted at its time.
    rays, kinds = 5000, (8000, 20000, 6000)
    assert model.expected_ms(model.equivalent_rays(rays, *kinds)) == pytest.approx(
        round_ms(rays, *kinds), rel=1e-6
    )
    # Without rounds of a kind its cost is unknown: unchanged (0 on a fresh model).
    other = TraceTimeModel()
    other.calibrate([s for s in calibration_rounds() if s[3] == 0])
    assert (other.fill_rays, other.screen_space_rays) == pytest.approx((FILL, MARCH), rel=1e-6)
    assert other.reuse_rays == 0.0


def _learn(model, rng, rounds, share, jitter=0.0):
    """``rounds`` rounds of 3000-8000 rays and 10,000-30,000 skipped pixels, the reused
    share of them drawn by ``share(rng)``, every first ray marched (6 % of the rays' count
    in pixels), timed by the synthetic tracer (lognormal ``jitter``); the model's costs
    after each."""
    out = []
    for _ in range(rounds):
        rays, skipped = rng.uniform(3000, 8000), rng.uniform(10000, 30000)
        reused = share(rng) * skipped
        kinds = (skipped - reused, reused, 0.06 * rays)
        model.learn(round(rays), round_ms(rays, *kinds) * rng.lognormal(0.0, jitter), 0.0,
                    *kinds)  # fmt: skip
        out.append(model.kind_rays)
    return np.array(out)


def _miscalibrated():
    """A calibration that priced a reused pixel as a filled one (0.35 rays too high)."""
    model = TraceTimeModel()
    model.calibrate(calibration_rounds())
    model.reuse_rays = model.prior_kind_rays[1] = FILL
    return model


def test_rounds_whose_reused_share_varies_separate_reuse_from_fill():
    # Exact rounds: from a reuse cost 0.35 rays off, within 0.12 rays of the truth after
    # 100 rounds (what is left is the calibration's pull: its reuse rounds weigh as 4.3
    # rounds of 10,000 reused pixels, KIND_PRIOR_WEIGHT_MIN; and each round enters the
    # fit at the machine's speed against the prior, whose reuse figure is the wrong one,
    # so that speed moves with the round's reused share: measured 0.08-0.11 over three
    # seeds, 0.05-0.08 with the rounds' times as measured, which a slowdown tilts:
    # test_a_slowdown_is_the_lines_not_a_filled_pixels), the march within 0.01 (the
    # ridge holds its figure in rays: measured 0.002), the fill within 0.05 (measured
    # 0.02-0.05), the line the machine's within 8 % (it takes up what that pull leaves:
    # measured 4-7 %).
    for seed in (1, 2, 3):
        model = _miscalibrated()
        assert model.reuse_rays == FILL
        costs = _learn(model, np.random.default_rng(seed), 100, lambda rng: rng.uniform(0, 1))
        assert costs[-1][1] == pytest.approx(REUSE, abs=0.12)
        assert costs[-1][2] == pytest.approx(MARCH, abs=0.01)
        assert costs[-1][0] == pytest.approx(FILL, abs=0.05)
        assert model.ms_per_ray == pytest.approx(MS_PER_RAY, rel=0.08)
    # 10 % jitter per round (the shared machine's): over rounds 100-300 the mean of each
    # within 0.1 rays of the truth (measured within 0.06), and a reused pixel priced
    # below a filled one in every round.
    for seed in (1, 2, 3):
        model = _miscalibrated()
        costs = _learn(model, np.random.default_rng(seed), 300, lambda rng: rng.uniform(0, 1),
                       0.1)  # fmt: skip
        assert costs[100:].mean(axis=0) == pytest.approx((FILL, REUSE, MARCH), abs=0.1)
        assert np.all(costs[100:, 1] < costs[100:, 0])


def test_rounds_of_one_mix_keep_what_they_cannot_tell_apart():
    # Every round marches its first rays in the same proportion to its rays: the march
    # cannot be told from the rays, so the calibration's figure stands (exact rounds:
    # within 0.02 rays), while the rounds' time is predicted right (the line and the
    # kinds together, 1 %).
    model = TraceTimeModel()
    model.calibrate(calibration_rounds())
    costs = _learn(model, np.random.default_rng(3), 100, lambda rng: 0.5)
    assert costs[-1][2] == pytest.approx(MARCH, abs=0.02)
    kinds = (10000, 10000, 300)
    assert model.expected_ms(model.equivalent_rays(5000, *kinds)) == pytest.approx(
        round_ms(5000, *kinds), rel=0.01
    )


def _frame(policy, sc, pixels, budget, records, ms, density):
    """One frame at the render's trace ``density``: begin, a round within ``budget``,
    recording ``records`` (made by ``records(ids, densities)``) in ``ms`` seconds; returns
    the round's ids and densities."""
    policy.begin_frame(view(pixels, trace_density=density), sc)
    ids = policy.next_round(budget)
    densities = policy.round_densities(ids)
    if ids:
        policy.record(records(ids, densities), ms)
    policy.end_frame()
    return ids, densities


def test_a_reflectors_skipped_pixels_are_priced_at_its_reused_share():
    """Under a time budget a reflector at a reduced density costs its rays, its skipped
    pixels at its learned mix of reused and filled (none learned: all filled) and its
    marched pixels; under a rays budget alone, its rays only."""
    sc = scene([element((0.0, 0.0, -4.0))], lights=1)
    policy = policy_of("heu1")
    policy.calibrate(calibration_rounds(), rays=30000, pixels=10000)
    model = policy.time_model
    pixels, level = 4096, 15  # the coarsest density: a sixteenth
    policy.begin_frame(view(np.array([pixels])), sc)
    policy.next_round(Budget(ms=1000.0))
    rays = policy.predicted_rays(0) / 16
    skipped = pixels * 15 / 16
    # No history yet: every skipped pixel filled. The calibration's records marched no
    # pixel (none given): no march priced.
    assert policy.level_rays(0, level) == pytest.approx(rays + FILL * skipped, rel=1e-9)
    policy.next_round(Budget(rays=10**9))
    assert policy.level_rays(0, level) == pytest.approx(rays, rel=1e-9)
    policy.end_frame()
    # A frame traced it at a sixteenth: 3/4 of its skipped pixels reused, every pixel that
    # started rays marched.
    started = pixels // 16

    def records(ids, densities):
        return [TraceRecord(0, pixels, 3 * started, screen_space=20, reused=2880, filled=960,
                            marched=started)]  # fmt: skip

    policy.begin_frame(view(np.array([pixels])), sc)
    policy.next_round(Budget(ms=1000.0))
    policy._require_frame().levels[0] = level
    policy.record(records([0], ["sixteenth"]), 0.002)
    policy.end_frame()
    assert policy.reused_share[0] == pytest.approx(0.75)
    policy.begin_frame(view(np.array([pixels])), sc)
    policy.next_round(Budget(ms=1000.0))
    rays = policy.predicted_rays(0) / 16
    assert rays == pytest.approx(3 * started)
    expected = rays + skipped * (0.75 * model.reuse_rays + 0.25 * model.fill_rays)
    expected += model.screen_space_rays * started  # every pixel that started rays marched
    assert policy.level_rays(0, level) == pytest.approx(expected, rel=1e-9)
    policy.end_frame()


def test_a_rounds_time_is_predicted_from_its_reused_share():
    """A reflector HEU1 traces at a reduced density whose skipped pixels are 3/4 reused:
    once the policy has seen one such frame, the round's predicted central time
    (``FrameNote.expected_trace_ms``) is the synthetic tracer's time for it (exact
    calibration: within 1 %), where pricing its reused pixels as filled (the model
    before per-kind costs) overestimates it by 10 % or more."""
    sc = scene([element((0.0, 0.0, -4.0))], lights=1)
    policy = policy_of("heu1")
    policy.calibrate(calibration_rounds(), rays=30000, pixels=10000)
    pixels = 64000

    def kinds(density):
        """(rays, filled, reused) of a round at ``density``: 3 rays a started pixel."""
        started = pixels * DENSITY_FRACTION[density]
        skipped = pixels - started
        return 3 * started, 0.25 * skipped, 0.75 * skipped

    def records(ids, densities):
        rays, filled, reused = kinds(densities[0])
        return [TraceRecord(0, pixels, round(rays), reused=round(reused), filled=round(filled),
                            marched=0)]  # fmt: skip

    # A budget where the whole reflector does not fit (64000 pixels, 192,000 rays): HEU1
    # steps it to a reduced density. Two frames: the first learns the share.
    budget = Budget(ms=30.0)
    for _ in range(2):
        policy.begin_frame(view(np.array([pixels])), sc)
        ids = policy.next_round(budget)
        (density,) = policy.round_densities(ids)
        assert ids == [0] and density != "full"
        policy.record(records(ids, [density]), round_ms(*kinds(density)) / 1000.0)
        policy.end_frame()
    truth = round_ms(*kinds(density))
    assert policy.last_frame_note.expected_trace_ms == pytest.approx(truth, rel=0.01)
    rays, filled, reused = kinds(density)
    assert round_ms(rays, filled + reused) > 1.1 * truth


def _planned_rounds(model, rng, rounds, slow_from, slow=1.8, budget_ms=16.0, pixels=20000.0):
    """A policy's rounds on the synthetic tracer: each plans the model's whole allowance
    (``rays_within``) on ``pixels`` reflector pixels at 2.2 rays a traced pixel, the
    traced share what the model's fill cost lets fit (the rest filled: a slower machine,
    more filled pixels), 10 % jitter, every round ``slow`` times slower from round
    ``slow_from`` on; the model's (fixed ms, ms per ray, fill rays) after each."""
    out = []
    for k in range(rounds):
        allowance = model.rays_within(budget_ms)
        fill = model.fill_rays
        share = (allowance - fill * pixels) / max(2.2 * pixels - fill * pixels, 1.0)
        share = min(max(share, 1.0 / 16.0), 1.0)
        rays, filled = 2.2 * share * pixels, (1.0 - share) * pixels
        ms = round_ms(rays, filled) * rng.lognormal(0.0, 0.1) * (slow if k >= slow_from else 1.0)
        model.learn(round(rays), ms, 0.0, filled)
        out.append((model.overhead_ms, model.ms_per_ray, model.fill_rays))
    return np.array(out)


def test_rounds_planned_to_the_budget_keep_the_fixed_cost_a_fixed_cost():
    # Every round plans the whole budget, so all cast about the same equivalent rays:
    # their spread cannot tell a fixed cost from a per-ray cost, and the calibration's
    # share of each stands. Over rounds 50-100 of a steady machine the fixed cost stays
    # below 1 ms (the truth 0.3 ms; measured 0.30-0.59 over eight seeds) and the per-ray
    # cost within 10 % (measured 3-8 %); with the prior forgotten, one seed's went to
    # 14 ms and 0.03 of the per-ray cost.
    for seed in (1, 2, 3, 4, 5):
        model = TraceTimeModel()
        model.calibrate(calibration_rounds())
        costs = _planned_rounds(model, np.random.default_rng(seed), 100, slow_from=100)
        assert np.all(costs[50:, 0] < 1.0)
        assert costs[50:, 1] == pytest.approx(MS_PER_RAY, rel=0.1)


def test_a_slowdown_is_the_lines_not_a_filled_pixels():
    # The machine slows 1.8x: the rounds trace fewer pixels and fill more, each slower.
    # Fifty rounds on, the line is the slow machine's (per-ray cost within 12 %: measured
    # 4-8 % over eight seeds; the fixed cost below 1.5 ms, the truth 0.54: measured
    # 1.0-1.34) and a filled pixel costs what it did, in rays (within 0.1 of the truth
    # 0.6: measured 0.05). Fitted to the times as measured, a filled pixel took up the
    # slowdown (1.0-1.5 rays for 100 rounds) and the per-ray cost fell to 0.44-0.69 of
    # the machine's.
    for seed in (1, 2, 3, 4, 5):
        model = TraceTimeModel()
        model.calibrate(calibration_rounds())
        costs = _planned_rounds(model, np.random.default_rng(seed), 200, slow_from=100)
        assert np.all(costs[150:, 0] < 1.5)
        assert costs[150:, 1] == pytest.approx(1.8 * MS_PER_RAY, rel=0.12)
        assert costs[150:, 2] == pytest.approx(FILL, abs=0.1)
