"""The trace-time cost model: convergence on alike rounds (synthetic timings), the
calibration once per run (real renders of a small stage), and what stats.json says when
nothing is traced. No timing asserts: every timing a threshold reads is synthetic."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scenes import mirror_gallery_stage

from phrt_usd.api import run_render
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.run.render_job import RenderJob
from phrt_usd.select.cost_model import JITTER_WINDOW, TraceTimeModel


def true_ms(rays, rng=None, overhead=0.3, per_ray=4e-4, jitter=0.05):
    """A synthetic tracer: ``overhead + per_ray * rays`` ms with lognormal jitter (5 %)."""
    ms = overhead + per_ray * rays
    return ms * (rng.lognormal(0.0, jitter) if rng is not None else 1.0)


@pytest.mark.parametrize("calibrated", [False, True])
def test_alike_rounds_converge_to_the_measured_time(calibrated):
    """Every round traces ~30k rays (a still shot): the old fit kept its prior's 0.004 ms
    per ray (~120 ms) for ever. The prediction there must reach the measured ~12 ms."""
    rng = np.random.default_rng(3)
    model = TraceTimeModel()
    if calibrated:  # a calibration whose rate is 2x off (a noisy start)
        model.calibrate([(500, true_ms(500) * 2.0), (4000, true_ms(4000) * 2.0)])
        assert model.calibrated
    for _ in range(30):
        rays = int(30000 * rng.uniform(0.99, 1.01))
        model.learn(rays, true_ms(rays, rng))
    # 10 %: the jitter is 5 % per round, averaged over ~10 rounds of weight.
    assert model.expected_ms(30000) == pytest.approx(true_ms(30000), rel=0.10)
    assert model.safety < 1.3  # predictions were right: the margin stays small


def test_varied_rounds_recover_fixed_and_per_ray_cost():
    rng = np.random.default_rng(4)
    model = TraceTimeModel()
    model.calibrate([(500, true_ms(500)), (4000, true_ms(4000))])
    for _ in range(80):
        rays = int(rng.uniform(2000, 60000))
        model.learn(rays, true_ms(rays, rng, overhead=1.0, per_ray=2e-4))
    # The calibration's line (0.3 ms + 4e-4 ms/ray) is forgotten: the rounds' line stands.
    assert model.ms_per_ray == pytest.approx(2e-4, rel=0.1)
    assert model.overhead_ms == pytest.approx(1.0, abs=0.5)


def test_calibration_sets_the_line_and_is_finite_for_bad_samples():
    model = TraceTimeModel()
    model.calibrate([(512, 0.3 + 512e-4), (64, 0.3 + 64e-4)])
    assert model.prior_ms_per_ray == pytest.approx(1e-4)
    assert model.prior_overhead_ms == pytest.approx(0.3)
    assert model.expected_ms(10000) == pytest.approx(1.3)
    other = TraceTimeModel()
    other.calibrate([(100, 5.0), (1000, 1.0)])  # slower with fewer rays: noise
    assert other.ms_per_ray > 0 and np.isfinite(other.rays_within(10.0))
    other.calibrate([(0, 1.0), (10, float("nan"))])  # nothing usable: unchanged
    assert np.isfinite(other.expected_ms(1e6))


def _stats(out):
    return json.loads((out / "stats.json").read_text())["frames"]


@pytest.mark.slow
def test_calibration_runs_once_per_run_and_resume_keeps_it(tmp_path):
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=8)
    options = RenderOptions(width=64, height=48, budget_ms=50.0)
    out = tmp_path / "run"
    run_render(RenderJob(stage_path=stage, out_dir=out, options=options, frames="1:3"))
    frames = _stats(out)
    calibrated = [f for f in frames if f["calibration"] is not None]
    assert len(calibrated) == 1  # the first frame with a visible reflector, only
    cal = calibrated[0]["calibration"]
    # Rounds of two sizes at least (the fixed cost apart from the per-ray cost).
    rounds = cal["rounds"]
    assert len({r["rays"] for r in rounds}) >= 2 and all(r["rays"] > 0 for r in rounds)
    assert cal["ms_per_ray"] > 0 and "calibrate" in calibrated[0]["phase_ms"]
    # A time-budgeted frame with visible reflectors reports T, its use and a prediction.
    traced = [f for f in frames if f["selected"]]
    assert traced and all(f["budget_ms"] == 50.0 for f in frames)
    assert all(f["expected_trace_ms"] > 0 and f["budget_use"] is not None for f in traced)
    # A deterministic (rays) budget needs no time model: no calibration.
    out2 = tmp_path / "rays"
    rays = RenderOptions(width=64, height=48, budget_ms=None, budget_rays=10**6)
    run_render(RenderJob(stage_path=stage, out_dir=out2, options=rays, frames="1:2"))
    assert all(f["calibration"] is None for f in _stats(out2))


def test_policy_memory_keeps_the_calibration(tmp_path):
    """Checkpointed memory is plain JSON and carries the calibrated model: a resumed run
    does not calibrate again."""
    from phrt_usd.select.policies import make_policy

    policy = make_policy("heu1", selection_weight=1e-4, bounce_limit=2)
    policy.calibrate([(64, 0.4), (512, 0.9)], rays=576, pixels=576)
    text = json.dumps(policy.memory(), allow_nan=False)
    clone = make_policy("heu1", selection_weight=1e-4, bounce_limit=2)
    clone.restore_memory(json.loads(text))
    assert clone.time_model.calibrated
    assert vars(clone.time_model) == vars(policy.time_model)


def test_nothing_traced_says_why(tmp_path):
    """A budget below any reflector's predicted cost: every frame with visible reflectors
    records the reason with the budget in it, and the summary has one line saying so."""
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=4)
    options = RenderOptions(width=64, height=48, budget_ms=1e-4)
    out = tmp_path / "run"
    summary = run_render(RenderJob(stage_path=stage, out_dir=out, options=options))
    seen = [f for f in _stats(out) if f["visible"]]
    assert seen and not any(f["selected"] for f in seen)
    assert all("budget 0.00 ms < cheapest predicted cost" in f["untraced_reason"] for f in seen)
    assert summary["untraced_frames"] == len(seen)
    assert summary["trace_note"].startswith("hybrid traced nothing in all of")


def test_rows_written_before_the_new_fields_still_read(tmp_path):
    """stats.json rows from before budget_ms / expected_trace_ms / ... were recorded read
    back with those fields at their defaults (a resumed older run)."""
    from phrt_usd.run.run_files import frame_stats_from_row

    row = {"time": 1.0, "phase_ms": {"trace": 1.0}, "frame_ms": 5.0, "trace_ms": 1.0,
           "predicted_trace_ms": 1.2, "rays": 10, "visible": [], "selected": [],
           "metrics": {}, "passes": []}  # fmt: skip
    stats = frame_stats_from_row(row)
    assert stats.budget_ms is None and stats.untraced_reason is None
    with pytest.raises(Exception, match="untraced_reason"):
        frame_stats_from_row({**row, "untraced_reason": 3})
    # A reflector's figures without their required fields (an empty table: found by
    # tests/run/test_run_fuzz.py) are refused with the reader's one line, not a TypeError.
    with pytest.raises(PhrtError, match="metrics of /World/Mirror0: not reflector figures"):
        frame_stats_from_row({**row, "metrics": {"/World/Mirror0": {}}})


def test_budget_use_is_also_reported_where_the_policy_left_a_reflector_untraced():
    """Budget idle in a frame that traced all in view had nothing to be spent on; the
    summary reports apart the frames that left a visible reflector untraced."""
    from phrt_usd.api import trace_summary
    from phrt_usd.model.frame import FrameStats

    def frame(t, visible, selected, use):
        return FrameStats(time=t, phase_ms={}, frame_ms=1.0, trace_ms=1.0,
                          predicted_trace_ms=1.0, rays=1, visible=visible, selected=selected,
                          metrics={}, passes=[], budget_use=use)  # fmt: skip

    frames = [frame(1.0, ["/a", "/b"], ["/a"], 0.4), frame(2.0, ["/a"], ["/a"], 0.2),
              frame(3.0, [], [], None)]  # fmt: skip
    summary = trace_summary(frames)
    assert summary["mean_budget_use"] == pytest.approx(0.3)
    assert summary["budget_bound_frames"] == 1
    assert summary["budget_bound_use"] == pytest.approx(0.4)
    assert trace_summary(frames[1:])["budget_bound_use"] is None


def test_safety_forgets_a_loaded_spell_within_its_window():
    """A spell of rounds at 3x their time raises the predictions (fit times factor) to
    cover it within a few rounds, and the spell is forgotten JITTER_WINDOW rounds after
    it ends (the tracker it replaced took ~60 frames, during which kept reflectors were
    predicted over the budget)."""
    rng = np.random.default_rng(6)
    model = TraceTimeModel()
    model.calibrate([(500, true_ms(500)), (4000, true_ms(4000))])

    def rounds(n, slow=1.0):
        for _ in range(n):
            rays = int(rng.uniform(20000, 40000))
            model.learn(rays, true_ms(rays, rng) * slow)

    rounds(100)
    quiet = model.safety
    # 1.2: the 95 % quantile of 5 % lognormal jitter is ~1.09.
    assert quiet < 1.2
    rounds(10, slow=3.0)
    # 10 of the window's 64 rounds (~3x) are above its 95 % quantile: the predictions
    # cover them (2.7: the spell's 3x less the 5 % jitter's spread and the fixed cost).
    assert model.predicted_ms(30000) > 2.7 * true_ms(30000)
    rounds(JITTER_WINDOW // 2)
    assert model.safety > 2.5  # the fit is back at quiet times, the spell still in view
    rounds(JITTER_WINDOW // 2)
    assert model.safety == pytest.approx(quiet, abs=0.1)


def test_safety_weighs_rounds_by_their_time():
    """Sub-millisecond rounds at 4x their model (a tail seen on the sewer) must not set
    the margin of 10 ms rounds: the quantile is of milliseconds, not of rounds."""
    rng = np.random.default_rng(7)
    model = TraceTimeModel()
    model.calibrate([(500, true_ms(500)), (4000, true_ms(4000))])
    for k in range(200):
        rays = 200 if k % 5 == 0 else 25000  # one round in five tiny and 4x slow
        model.learn(rays, true_ms(rays, rng) * (4.0 if rays == 200 else 1.0))
    # 1.2 as above: the tiny rounds hold ~1 % of the window's milliseconds.
    assert model.safety < 1.2


def test_safety_covers_the_ray_prediction_error():
    """Rounds that cast 20 % more rays than planned: the factor is measured against the
    planned rays, so it grows to cover them, while the fit learns the rays cast."""
    rng = np.random.default_rng(8)
    model = TraceTimeModel()
    model.calibrate([(500, true_ms(500)), (4000, true_ms(4000))])
    for _ in range(100):
        planned = rng.uniform(20000, 40000)
        rays = int(1.2 * planned)
        model.learn(rays, true_ms(rays, rng), planned_rays=planned)
    assert model.expected_ms(30000) == pytest.approx(true_ms(30000), rel=0.10)
    assert model.safety > 1.15  # ~1.2 x the jitter's quantile, less the fixed cost's share


def test_the_fixed_cost_is_bounded_by_the_windows_median_round():
    """Rounds that all take 1 ms whatever their rays (a slow spell) fit a flat line at
    1 ms: every reflector, however small, would be priced at the whole 1 ms budget. While
    the spell is under half the window, the fixed cost stays at the median round's time
    (0.4 ms; the spell raises the safety factor instead); once it is most of the window,
    the model follows it."""
    rng = np.random.default_rng(4)
    model = TraceTimeModel()
    model.calibrate([(64, 0.076), (512, 0.167)])
    for _ in range(JITTER_WINDOW // 2 + 2):
        model.learn(300, 0.4)
    for _ in range(JITTER_WINDOW // 2 - 2):
        model.learn(int(rng.integers(200, 1400)), 1.0)
    assert model.overhead_ms == pytest.approx(0.4)  # the flat line's would be ~0.88
    assert model.predicted_ms(20) < 0.8
    for _ in range(JITTER_WINDOW // 2):
        model.learn(int(rng.integers(200, 1400)), 1.0)
    assert model.expected_ms(20) > 0.8
