"""HEU1 spends the budget it can without giving up its low transitions (issue 19): a
still camera where whole reflectors fill most of the budget, the leftover of a frame's
first round filled in later rounds, and an entering reflector the lookahead shows
outgrowing the whole budget kept out. Fake frames, no rendering (``test_heuristic``'s
fakes)."""

from __future__ import annotations

import numpy as np
from selection_fakes import camera, element, run_frame, scene, transitions, view

from phrt_usd.model.frame import Budget, TraceRecord
from phrt_usd.model.trace_density import DENSITY_FRACTION, TRACE_DENSITIES, traced_fraction
from phrt_usd.select.heu1_forecast import LOOKAHEAD_FRAMES
from phrt_usd.select.policies import ADMISSION_MARGIN, RAYS_SAFETY, make_policy


def heu1():
    return make_policy("heu1", selection_weight=1e-4, bounce_limit=2)


def test_still_camera_budget_that_fits_three_reflectors_is_mostly_spent_without_switching():
    # Eight reflectors of ~1000 pixels at 2 rays per pixel (one light: the first guess is
    # right) and 7500 rays: three fit with RAYS_SAFETY and the admission margin
    # (3 * 2200 + 750 <= 7500), four never (8800). Pixel counts jitter by 2 % per frame.
    n, budget = 8, 7500
    assert 3 * 2000 * RAYS_SAFETY + ADMISSION_MARGIN * budget <= budget < 4 * 2000 * RAYS_SAFETY
    sc = scene([element((1.5 * i - 5.0, 0.0, -8.0)) for i in range(n)], lights=1)
    rng = np.random.default_rng(3)
    policy = heu1()
    selections, uses, levels = [], [], []
    for t in range(100):
        pixels = (1000 * rng.uniform(0.98, 1.02, n)).astype(np.int64)
        metrics, rounds = run_frame(policy, sc, view(pixels, time=t), budget_rays=budget,
                                    rays_per_pixel=2.0)  # fmt: skip
        chosen = {e for ids in rounds for e in ids}
        selections.append(chosen)
        levels.append(dict(policy.previous_levels))
        share = {e: DENSITY_FRACTION[TRACE_DENSITIES[lv]] for e, lv in levels[-1].items()}
        uses.append(sum(2 * int(pixels[e]) * share.get(e, 1.0) for e in chosen) / budget)
    # Spent: three whole reflectors are 0.78-0.82 of the budget every frame (a fourth at a
    # sixteenth adds 0.03); 0.75 leaves only the pixel jitter. Nothing idle for want of a
    # candidate that fits.
    assert min(uses) >= 0.75 and max(uses) <= 1.0
    # Stable: the 2 % jitter must not switch a reflector (hysteresis, admission margin),
    # nor step a trace density.
    assert transitions(selections, range(n)) == 0
    assert all(lv == levels[0] for lv in levels)


def test_leftover_of_the_first_round_is_filled_with_a_margin_of_the_leftover():
    # Round 1 (1000 rays): A (800 px, 880 predicted) is taken; B (100 px, 110 predicted)
    # does not fit beside it with the margin (880 + 110 + 100 > 1000). A traces 800 rays,
    # so round 2 has 200 left: B fits with a margin of 10 % of that leftover (110 + 20),
    # not with one of 10 % of the whole budget (110 + 100 > 200).
    # At a fixed density (no density step of A makes room for B in round 1).
    sc = scene([element((0.0, 0.0, -8.0)), element((1.0, 0.0, -8.0))])
    policy = heu1()
    fv = view([800, 100], trace_density="half")
    _metrics, rounds = run_frame(policy, sc, fv, budget_rays=1000)
    assert rounds == [[0], [1]]
    assert 110 + ADMISSION_MARGIN * 1000 > 200 >= 110 + ADMISSION_MARGIN * 200


def test_entering_reflector_forecast_to_outgrow_the_whole_budget_is_not_taken():
    # Reflector 1 enters the view with 300 pixels (330 predicted rays of a 1000 budget).
    # The upcoming cameras approach it: its box will cover over 3 times its area now,
    # more than the whole budget, so it would be dropped while in view (a transition):
    # with the lookahead it is not taken at full density; without upcoming cameras, or
    # when the cameras stay put, it is. With density steps (the render at full density)
    # it is taken at full density all the same: it fits now, and as it grows it steps
    # coarser (no transition) down to a sixteenth, whose forecast fits the budget; only a
    # reflector that would outgrow even that is left out.
    sc = scene([element((0.0, 0.0, -8.0)), element((1.0, 0.0, -8.0))])
    approach = tuple(camera((0.8, 0.0, -5.0 * k / LOOKAHEAD_FRAMES)) for k in range(1, 40))
    still = tuple(camera() for _ in range(1, 40))
    for upcoming, taken, density in (
        ((), "full", "full"), (still, "full", "full"), (approach, None, "half"),
        (approach, "full", "full"),
    ):  # fmt: skip
        policy = heu1()
        fv = view([0, 300], trace_density=density)
        fv.upcoming_cameras = upcoming
        policy.begin_frame(fv, sc)
        growth = policy.lookahead_growth.get(1, 1.0)
        if upcoming is approach:
            assert growth * policy.predicted_rays(1) > 1000
        ids = policy.next_round(Budget(rays=1000))
        assert (1 in ids) is (taken is not None), (len(upcoming), ids)
        if taken is not None:
            assert policy.round_densities([1]) == [taken]
        if upcoming is approach and density == "full":
            allowance = policy._require_frame().first_allowance  # 1000 less the safety
            assert policy._outgrows(1, allowance, 0)
            assert not policy._outgrows(1, allowance, TRACE_DENSITIES.index("sixteenth"))
        policy.end_frame()


def test_density_steps_make_room_for_a_reflector_entering_the_view():
    # Reflector 0 (2000 pixels) fills most of a 2300-ray budget (2091 predicted rays with
    # RAYS_SAFETY). Reflector 1 enters with 30 pixels (traced whole: under
    # SPARSE_MIN_PIXELS): beside 0 at full density it does not fit with the admission
    # margin (2000 + 30 + 209 > 2091), so HEU1 steps 0 to 14/16 (each 1/16 frees 125 of
    # the 148 rays needed) and
    # takes 1 as it enters; taken later, while
    # in view, it would be a transition. At a fixed density nothing steps, and 0 tracing
    # 20 % more rays than predicted leaves no round for 1: it stays out.
    sc = scene([element((0.0, 0.0, -8.0)), element((1.0, 0.0, -8.0))])
    for density, taken in (("full", True), ("half", False)):
        policy = heu1()
        run_frame(policy, sc, view([2000, 0], trace_density=density), budget_rays=2300)
        m, rounds = run_frame(policy, sc, view([2000, 30], trace_density=density), 2300, 1.2)
        assert m[1].selected is taken
        if taken:
            assert rounds == [[0, 1]]  # one round: the room is made before it is traced
            assert policy.previous_levels == {0: 2}  # 0 at 14/16, 1 whole (no level)
            assert m[1].trace_density == 1.0


def test_room_steps_the_reflector_that_frees_the_fewest_rays_that_suffice():
    # Three reflectors at full density, 4000 / 1000 / 600 pixels (1 ray a pixel): a step
    # of 1/16 frees 250 / 62.5 / 37.5 rays. 60 needed: the 1000-pixel one (62.5, the
    # fewest that suffice); 400: the largest twice (250 frees most, then 250 is the
    # fewest that suffices for 150); 2500: the largest ten times; more than every step
    # to a sixteenth frees: none.
    sc = scene([element((0.0, 0.0, -8.0)), element((1.0, 0.0, -8.0)), element((2.0, 0.0, -8.0))])
    policy = heu1()
    policy.begin_frame(view([4000, 1000, 600]), sc)
    assert policy._room([0, 1, 2], 0.0) == {}
    assert policy._room([0, 1, 2], 60.0) == {1: 1}
    assert policy._room([0, 1, 2], 400.0) == {0: 2}
    assert policy._room([0, 1, 2], 2500.0) == {0: 10}
    assert policy._room([0, 1, 2], 5600.0 * (15 / 16) + 1.0) is None
    policy.end_frame()


def test_a_frame_the_time_model_starves_holds_the_claims_once():
    # Two reflectors traced in frame 0 (30 and 2000 pixels, 0.001 ms a ray: 2.03 ms of a
    # 10 ms budget). Then a slow spell puts even the cheapest above 0.25 ms (safety 10: 30
    # rays, traced whole at any density, 0.3 ms, the large one's sixteenth 125 rays
    # 1.25 ms):
    # the first starved frame traces both all the same, the large one at its coarsest
    # density (the hold); a second starved frame in a row drops them. A frame whose
    # selection fits is no hold, so the next starved frame holds again.
    sc = scene([element((0.0, 0.0, -8.0)), element((1.0, 0.0, -8.0))])
    policy = heu1()
    policy.time_model.calibrate([(100, 0.1), (1000, 1.0)])

    def frame(ms, safety=1.1):
        """One frame at a safety factor of ``safety``: {traced id: its density}."""
        pixels = [30, 2000]
        policy.begin_frame(view(pixels), sc)
        policy.time_model.safety = safety
        ids = policy.next_round(Budget(ms=ms))
        traced = dict(zip(ids, policy.round_densities(ids), strict=True))
        if ids:  # one ray a traced pixel, 0.001 ms a ray
            rays = {e: round(pixels[e] * traced_fraction(pixels[e], d)) for e, d in traced.items()}
            policy.record([TraceRecord(e, pixels[e], rays[e], {}, 0, 0.0) for e in ids],
                          1e-6 * sum(rays.values()))  # fmt: skip
        policy.end_frame()
        return traced

    full = {0: "full", 1: "full"}
    assert frame(10.0) == full
    assert frame(0.25, safety=10.0) == {0: "full", 1: "sixteenth"}  # held
    assert frame(0.25, safety=10.0) == {}  # starved again: dropped
    assert frame(10.0) == full
    assert set(frame(0.25, safety=10.0)) == {0, 1}
