"""HEU3 (select/benefit_policy.py): selection by learned error removed per predicted ray,
its prior from V and K, HEU1's hysteresis, its memory as JSON, the renderer's observation
of what tracing changed (engine/compositing.py ``observe_fallback_error``) and a render
through the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scenes import mirror_floor_stage, mirror_gallery_stage, mirrored_sphere_pixels
from selection_fakes import element, policy_of, scene, view
from typer.testing import CliRunner

from phrt_usd.cli import app
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import Budget, TraceRecord
from phrt_usd.select.benefit_policy import KEEP_GAIN, PRIOR_SCALE_INITIAL, Heu3Policy
from phrt_usd.select.rounds import TracedRound, run_rounds
from phrt_usd.usd.schema import DEFAULT_SELECTION_WEIGHT
from phrt_usd.usd.stage import open_stage

#: Two reflectors of 1000 pixels each, mirror images of each other about the view axis
#: (equal D, P and so V, and equal predicted cost): only what tracing taught tells them
#: apart. A budget of 2000 rays fits one of them (1000 px * 1 ray * RAYS_SAFETY = 1100),
#: with REJOIN_MARGIN's 30 % of the budget left (1100 + 600 <= 2000), not both.
PAIR = [element((-1.0, 0.0, -5.0)), element((1.0, 0.0, -5.0))]
PIXELS = [1000, 1000]
ONE_FITS = 2000


def frame(policy, sc, fv, budget_rays, errors):
    """One frame through the renderer's round loop (``run_rounds``); the fake tracer casts
    one ray per pixel, its observation step reports ``errors[e]`` as e's fallback error.
    Returns the ids traced, in order."""
    last: list[TraceRecord] = []

    def trace(ids, densities):
        last[:] = [TraceRecord(e, int(fv.pixel_counts[e]), int(fv.pixel_counts[e])) for e in ids]
        return TracedRound(list(last), sum(r.rays for r in last), 1.0)

    def observe():
        for rec in last:
            rec.fallback_error = errors.get(rec.source)

    visible = [int(e) for e in np.flatnonzero(fv.pixel_counts > 0)]
    limits = Budget(rays=budget_rays)
    return run_rounds(policy, fv, sc, visible, limits, trace, observe=observe).selected


@pytest.mark.parametrize("better", [0, 1])
def test_prefers_the_higher_observed_error_per_ray_at_equal_cost(better):
    policy = policy_of("heu3")
    sc = scene(PAIR)
    errors = {better: 0.3, 1 - better: 0.05}
    assert sorted(frame(policy, sc, view(PIXELS), None, errors)) == [0, 1]  # both observed
    # Both were selected, so both are kept alike; one fits: the one whose tracing changed
    # the image more (both ids win in turn, so it is not the tie-break by id).
    assert frame(policy, sc, view(PIXELS), ONE_FITS, errors) == [better]
    policy.begin_frame(view(PIXELS), sc)
    assert policy.benefit(better) > policy.benefit(1 - better) > 0.0
    policy.end_frame()


def test_a_reflector_never_traced_gets_the_v_k_prior():
    policy = policy_of("heu3")
    near_low_k = element((0.0, 0.0, -4.0), K=1.0)
    far_high_k = element((0.0, 0.5, -8.0), K=3.0)
    sc = scene([near_low_k, far_high_k])
    fv = view([1000, 1000])
    policy.begin_frame(fv, sc)
    frame_state = policy._frame
    # Nothing observed yet: benefit = s * V * K with the initial scale, so the first
    # frame ranks by V * K per ray.
    for e in (0, 1):
        want = PRIOR_SCALE_INITIAL * frame_state.V[e] * frame_state.K[e]
        assert policy.benefit(e) == pytest.approx(want, rel=1e-12)
    VK = frame_state.V * frame_state.K
    assert policy.next_round(Budget(rays=ONE_FITS)) == [int(np.argmax(VK[:2]))]
    policy.end_frame()
    # Observe only reflector 0; the prior's scale is then fitted to it (e = s * P / D),
    # and reflector 1, never traced, is predicted s * V * K with that s.
    policy = policy_of("heu3")
    frame(policy, scene([near_low_k]), view([1000]), None, {0: 0.2})
    assert policy.prior_scale() != PRIOR_SCALE_INITIAL
    policy.begin_frame(fv, sc)
    s = policy.prior_scale()
    V, K = policy._frame.V, policy._frame.K
    area = 1000 / (fv.width * fv.height)
    assert s == pytest.approx(0.2 / (V[0] / area), rel=1e-9)  # one observation: exact fit
    assert 1 not in policy.error_per_pixel
    assert policy.benefit(1) == pytest.approx(s * V[1] * K[1], rel=1e-9)
    policy.end_frame()


def test_hysteresis_keeps_the_previous_selection_when_benefits_are_close():
    sc = scene(PAIR)
    # The schema's I: its S * I bonus is ~5 % of these benefits (V ~ 2e-3, I = 1e-4).
    policy = policy_of("heu3", DEFAULT_SELECTION_WEIGHT)
    frame(policy, sc, view(PIXELS), None, {0: 0.2, 1: 0.05})
    assert frame(policy, sc, view(PIXELS), ONE_FITS, {0: 0.2}) == [0]
    # The unselected one now looks 20 % better: within KEEP_GAIN, the selection stays.
    policy.error_per_pixel[1], policy.error_confidence[1] = 0.24, 1.0
    for _ in range(5):
        assert frame(policy, sc, view(PIXELS), ONE_FITS, {0: 0.2}) == [0]
    # Far better (beyond KEEP_GAIN): it takes the place.
    policy.error_per_pixel[1] = 0.2 * KEEP_GAIN * 1.5
    assert frame(policy, sc, view(PIXELS), ONE_FITS, {1: 0.6}) == [1]
    # Without hysteresis (the ranking alone) the 20 % case would have switched at once.
    assert KEEP_GAIN > 1.2


def test_confidence_decays_towards_the_prior_while_untraced():
    sc = scene(PAIR)
    policy = policy_of("heu3")
    frame(policy, sc, view(PIXELS), None, {0: 0.2, 1: 0.05})
    frame(policy, sc, view(PIXELS), ONE_FITS, {0: 0.2})
    assert policy.error_confidence[0] == 1.0 and policy.error_confidence[1] < 1.0
    c = policy.error_confidence[1]
    frame(policy, sc, view(PIXELS), ONE_FITS, {0: 0.2})
    assert policy.error_confidence[1] < c  # one more frame untraced


def test_memory_round_trips_through_json_and_bad_shapes_are_refused():
    sc = scene(PAIR)
    policy = policy_of("heu3")
    errors = {0: 0.2, 1: 0.15}
    frame(policy, sc, view(PIXELS), None, errors)
    for _ in range(3):
        frame(policy, sc, view(PIXELS), ONE_FITS, errors)
    text = json.dumps(policy.memory(), allow_nan=False)
    clone = policy_of("heu3")
    clone.restore_memory(json.loads(text))
    assert clone.error_per_pixel == policy.error_per_pixel
    assert clone.error_confidence == policy.error_confidence
    assert (clone.prior_xy, clone.prior_xx) == (policy.prior_xy, policy.prior_xx)
    for k in range(10):
        pixels = [1000 + 37 * k, 1000 - 23 * k]
        e = {0: 0.2 - 0.01 * k, 1: 0.15 + 0.01 * k}
        assert frame(policy, sc, view(pixels), ONE_FITS, e) == frame(
            clone, sc, view(pixels), ONE_FITS, e
        )
    broken = json.loads(text)
    broken["state"]["str_keys"]["error_per_pixel"] = {"int_keys": [[0, "x"]]}
    with pytest.raises(PhrtError, match="other fields or types"):
        policy_of("heu3").restore_memory(broken)
    with pytest.raises(PhrtError, match="not a heu1"):
        policy_of("heu1").restore_memory(json.loads(text))


def test_non_finite_or_missing_observations_keep_figures_finite():
    sc = scene(PAIR)
    policy = policy_of("heu3")
    frame(policy, sc, view(PIXELS), None, {0: math.nan, 1: None})
    assert policy.error_per_pixel == {0: 0.0}  # NaN counts as no change; None: not seen
    policy.begin_frame(view(PIXELS), sc)
    assert all(math.isfinite(policy.score(e)) for e in (0, 1))
    policy.end_frame()
    assert isinstance(policy, Heu3Policy)


@pytest.mark.slow
def test_renderer_observes_what_tracing_changed_against_the_fallback(tmp_path):
    """The floor mirrors a red ball: the error the policy learns for it is the mean over
    the floor's pixels of |clip(hybrid) - clip(raster fallback)|, computed here from two
    renders of the same frame (heu3 tracing everything, `none` tracing nothing)."""
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda", 80, 60))
    outs = {}
    for name in ("heu3", "none"):
        r = FrameRenderer(stage, RenderOptions(mode="hybrid", heuristic=name, width=80,
                                               height=60, budget_ms=None))  # fmt: skip
        try:
            outs[name] = (r.render(1.0), r.policy)
        finally:
            r.close()
    (traced, policy), (raster, _) = outs["heu3"], outs["none"]
    floor = next(i for i, e in enumerate(stage.scene.elements) if e.path == "/World/Floor")
    mask = traced.traced_mask & (traced.gbuffer.element_id == floor)
    assert mask.sum() > 500  # the floor is traced at all
    diff = np.abs(np.clip(traced.beauty, 0, 1) - np.clip(raster.beauty, 0, 1)).mean(axis=2)
    want = float(diff[mask].mean())
    # Same pixels, same arithmetic in float32 → float64: agreement to rounding.
    assert policy.error_per_pixel[floor] == pytest.approx(want, abs=1e-6)
    # Where the floor mirrors the ball, tracing replaced the sky by a red ball: a change of
    # at least a tenth of the display range (red 0.9 against a grey-blue sky); where it
    # mirrors the sky, the traced ray sees the fallback's own environment: no change but
    # float rounding (1e-3, far below any visible difference). One pixel of rim left out.
    ball = mirrored_sphere_pixels(stage.camera(1.0), 80, 60) & mask
    rim = np.zeros_like(ball)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            rim |= np.roll(np.roll(ball, dy, 0), dx, 1)
    assert ball.sum() > 20
    assert diff[ball].mean() > 0.1
    assert diff[mask & ~rim].max() < 1e-3


@pytest.mark.slow
def test_cli_render_with_heu3_writes_stats(tmp_path):
    gallery = mirror_gallery_stage(tmp_path / "gallery.usda", frames=4)
    out = tmp_path / "run"
    done = CliRunner().invoke(app, [
        "render", str(gallery), "--out", str(out), "--frames", "1:4", "--heuristic", "heu3",
        "--budget-rays", "600", "--resolution", "32x24", "--no-images"])  # fmt: skip
    assert "Traceback" not in done.output
    assert done.exit_code == 0, done.output
    stats = json.loads((out / "stats.json").read_text())
    assert stats["run"]["heuristic"] == "heu3"
    rows = stats["frames"]
    assert len(rows) == 4
    assert all(row["rays"] <= 600 for row in rows)  # the rays budget holds
    assert any(row["selected"] for row in rows)  # it traces something


def test_taking_a_reflector_already_in_view_needs_the_rejoin_margin():
    """1500 rays: a reflector of 1100 predicted rays leaves 400 (27 % of the budget) free,
    above ADMISSION_MARGIN (10 %), below REJOIN_MARGIN (30 %)."""
    sc = scene(PAIR)
    entering = policy_of("heu3")
    assert frame(entering, sc, view([1000, 0]), 1500, {0: 0.2}) == [0]
    assert frame(entering, sc, view([0, 1000]), 1500, {1: 0.2}) == [1]  # new in view
    rejoining = policy_of("heu3")
    assert frame(rejoining, sc, view([1000, 1000]), 1500, {0: 0.2}) == [0]
    assert frame(rejoining, sc, view([0, 1000]), 1500, {1: 0.2}) == []  # a transition
    assert frame(rejoining, sc, view([0, 1000]), 1600, {1: 0.2}) == [1]  # 1100 + 480
