"""The temporal error (evaluate/temporal_error.py, docs/temporal-error.md), the Pareto
front of the sweep summary, and knob sweeps (bounce limits, trace densities) end to end.

Synthetic sequences: a reference background (a sine along x, still or shifting), and
tests that equal it (identical), add a patch in every frame (steady error), add half the
patch in every frame (the steady mean of a switch), or switch the patch on and off every
P frames (popping: at 24 fps, P = 1 is a 12 Hz flicker, P = 2 6 Hz, P = 4 3 Hz).
"""

from __future__ import annotations

import csv
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.evaluate.image_metrics import flip_map, mean_over
from phrt_usd.evaluate.sweep import (
    SweepSpec,
    check_spec,
    parse_int_list,
    parse_resolution_list,
    run_sweep,
)
from phrt_usd.evaluate.sweep_summary import PARETO_MARK, mark_pareto, pareto_front
from phrt_usd.evaluate.temporal_error import (
    SUSTAINED_BETA,
    SUSTAINED_SIGMA,
    TRANSIENT_BETA,
    TRANSIENT_PEAK_HZ,
    TRANSIENT_SIGMA,
    TRANSIENT_WEIGHT,
    TemporalChannels,
    sequence_frames_per_second,
    temporal_error_map,
    temporal_filters,
)
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.stage import open_stage

sys.path.insert(0, str(Path(__file__).parent))
from scenes import mirror_gallery_stage  # noqa: E402

H, W, N = 48, 64, 16
FPS = 24.0
#: Linear radiance added by the patch: well inside the tone map's [0, 1] range on a
#: background of 0.1..0.4, so nothing clips.
PATCH = 0.3


def _reference(moving: bool) -> list[np.ndarray]:
    x = np.arange(W, dtype=np.float32)
    frames = []
    for t in range(N):
        phase = 0.7 * t if moving else 0.0
        row = 0.25 + 0.15 * np.sin(x / 6.0 + phase)
        frames.append(np.broadcast_to(row[None, :, None], (H, W, 3)).astype(np.float32))
    return frames


def _with_patch(image: np.ndarray, amount: float) -> np.ndarray:
    out = image.copy()
    out[12:36, 16:48] += amount
    return out


def _popping(reference: list[np.ndarray], period: int) -> list[np.ndarray]:
    return [_with_patch(r, PATCH if (t // period) % 2 else 0.0) for t, r in enumerate(reference)]


def _scores(reference: list[np.ndarray], test: list[np.ndarray]) -> tuple[float, float]:
    """(mean per-frame FLIP, mean temporal error) of ``test`` against ``reference``."""
    per_frame = np.mean([mean_over(flip_map(r, h)) for r, h in zip(reference, test, strict=True)])
    ref_channels, test_channels = TemporalChannels(FPS), TemporalChannels(FPS)
    temporal = np.mean(
        [
            mean_over(temporal_error_map(ref_channels.push(r), test_channels.push(h)))
            for r, h in zip(reference, test, strict=True)
        ]
    )
    return float(per_frame), float(temporal)


def test_filters_are_the_published_responses():
    """The FIR filters' DFT equals the frequency responses they are sampled from (the
    sustained low-pass and the transient band-pass at their bins), with unit and zero
    gain at 0 Hz; 7 taps at 24 fps, 3 at 4 fps."""
    for fps, taps in ((24.0, 7), (4.0, 3), (60.0, 17)):
        sustained, transient = temporal_filters(fps)
        assert len(sustained) == len(transient) == taps
        assert sustained.sum() == pytest.approx(1.0, abs=1e-12)
        assert transient.sum() == pytest.approx(0.0, abs=1e-12)
        f = np.linspace(0.0, fps / 2.0, taps // 2 + 1)
        shift = np.fft.ifftshift  # the filters are centred; the DFT wants tap 0 first
        want_s = np.exp(-(f**SUSTAINED_BETA) / SUSTAINED_SIGMA)
        peak = TRANSIENT_PEAK_HZ**TRANSIENT_BETA
        want_t = np.exp(-((f**TRANSIENT_BETA - peak) ** 2) / TRANSIENT_SIGMA)
        # 1e-6: the responses are real and even, so the DFT of the centred taps is them
        # exactly up to rounding; the transient's 0 Hz value (3e-7) is set to 0.
        assert np.abs(np.fft.rfft(shift(sustained))) == pytest.approx(want_s, abs=1e-6)
        assert np.abs(np.fft.rfft(shift(transient))) == pytest.approx(want_t, abs=1e-6)
    sustained, transient = temporal_filters(24.0)
    assert np.all(sustained > 0.0)  # a low-pass without ringing: sustained stays in [0, 1]


def test_identical_is_zero_and_a_steady_error_on_a_still_reference_is_its_flip():
    reference = _reference(moving=True)
    assert _scores(reference, [r.copy() for r in reference]) == (0.0, 0.0)
    still = _reference(moving=False)
    per_frame, temporal = _scores(still, [_with_patch(r, PATCH) for r in still])
    assert per_frame > 0.05
    # Nothing flickers: the transient channels are 0 and the sustained ones the frames
    # themselves (up to float32 rounding of the filter's sum).
    assert temporal == pytest.approx(per_frame, rel=1e-3)


@pytest.mark.parametrize("moving", [False, True])
def test_switching_scores_above_its_steady_mean_though_per_frame_flip_says_the_opposite(moving):
    """The patch switched on and off at 12 and 6 Hz against half the patch in every frame,
    the mean a viewer's eye integrates it to: per frame the switch looks better (the patch
    is absent half the time), over time it is worse, as ColorVideoVDP scores the sewer's
    alternation of traced and raster frames (5.1 JOD) against their mean (7.1). (At 3 Hz
    on the moving background the measure scores the switch 0.92 x the mean, where
    ColorVideoVDP still scores it worse: a limit, docs/temporal-error.md.)"""
    reference = _reference(moving)
    blend_frame, blend_temporal = _scores(reference, [_with_patch(r, PATCH / 2) for r in reference])
    for period in (1, 2):
        pop_frame, pop_temporal = _scores(reference, _popping(reference, period))
        assert pop_frame < blend_frame
        # 1.05: measured 1.34 / 1.46 (still), 1.09 / 1.19 (moving) for periods 1 / 2.
        assert pop_temporal > 1.05 * blend_temporal, period


def test_flicker_near_five_hz_scores_most():
    """The same patch switched every 1, 2 and 4 frames at 24 fps: 6 Hz (period 2) is
    nearest the transient channel's 5 Hz peak and scores above 12 Hz and 3 Hz (as in
    ColorVideoVDP, which scores it 0.6 JOD against 2.9 and 2.7 at 320x240)."""
    reference = _reference(moving=False)
    scores = {p: _scores(reference, _popping(reference, p))[1] for p in (1, 2, 4)}
    # 1.05: measured 1.09 (against 12 Hz) and 1.29 (against 3 Hz).
    assert scores[2] > 1.05 * scores[1] and scores[2] > 1.05 * scores[4]


def test_frame_rate_of_a_recorded_sequence():
    assert sequence_frames_per_second([217.0, 223.0, 229.0, 235.0], 24.0) == 4.0
    assert sequence_frames_per_second([5.0], 30.0) == 30.0
    with pytest.raises(PhrtError, match="frame rate"):
        sequence_frames_per_second([1.0, 2.0], 0.0)


def test_bad_inputs_raise_instead_of_exiting():
    a = np.zeros((H, W, 3), np.float32)
    channels = TemporalChannels(FPS)
    channels.push(a)
    with pytest.raises(PhrtError, match="after frames of"):
        channels.push(a[:-1])
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(PhrtError, match="finite"):
        TemporalChannels(FPS).push(bad)
    for fps in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(PhrtError, match="frames per second"):
            TemporalChannels(fps)
    small = TemporalChannels(FPS).push(a[:-1])
    with pytest.raises(PhrtError, match="one size"):
        temporal_error_map(channels.push(a), small)


def _gallery_frames(tmp_path, times) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(traced, raster) beauty images of the mirror gallery at ``times``: every reflector
    ray-traced (``all``) and the raster fallback of the same G-buffer."""
    path = tmp_path / f"gallery_{len(list(tmp_path.glob('gallery_*.usda')))}.usda"
    stage = open_stage(mirror_gallery_stage(path, frames=40))
    options = RenderOptions(mode="hybrid", heuristic="all", width=W, height=H, budget_ms=None)
    renderer = FrameRenderer(stage, options)
    policy = make_policy(
        "all", selection_weight=options.selection_weight, bounce_limit=options.bounce_limit
    )
    traced, raster = [], []
    try:
        for t in times:
            prep = renderer.prepare(t)
            traced.append(renderer.finish(prep, policy, options).beauty)
            raster.append(prep.image)
    finally:
        renderer.close()
    return traced, raster


def test_rendered_reflectors_popping_between_raster_and_traced(tmp_path):
    """Real renders: the five mirrors traced in two frames, then raster in two, and so on
    (6 Hz at 24 fps), against the mean of the traced and raster frames in every frame,
    both measured against the all-traced frames, with the camera still and moving."""
    for times in ([18.0] * N, [10.0 + t for t in range(N)]):
        traced, raster = _gallery_frames(tmp_path, times)
        popping = [traced[t] if (t // 2) % 2 else raster[t] for t in range(N)]
        blend = [0.5 * (a + b) for a, b in zip(traced, raster, strict=True)]
        pop_frame, pop_temporal = _scores(traced, popping)
        blend_frame, blend_temporal = _scores(traced, blend)
        assert pop_frame < blend_frame  # per frame the switch looks better ...
        # ... over time it does not: measured 1.95x (still), 1.20x (moving); 1.1 as margin.
        assert pop_temporal > 1.1 * blend_temporal


def test_pareto_front_of_a_hand_made_set():
    points = [
        (1.0, 0.5, 0.5),  # fastest: on the front
        (2.0, 0.1, 0.4),  # on the front
        (2.0, 0.2, 0.1),  # worse FLIP, better temporal error than the previous: on it
        (3.0, 0.2, 0.4),  # dominated by (2, 0.1, 0.4)
        (3.0, 0.0, 0.0),  # exact: on the front
        (4.0, 0.0, 0.0),  # slower and no better: dominated
        (2.0, 0.1, 0.4),  # equal to a front point: equal points are all kept
    ]
    assert pareto_front(points) == [True, True, True, False, True, False, True]


def test_mark_pareto_per_stage_and_variant_and_without_temporal_error():
    def entry(stage, variant, ms, flip, temporal):
        keys = ("mean_frame_ms", "mean_flip", "mean_temporal_error")
        values = dict(zip(keys, (ms, flip, temporal), strict=True))
        return {"stage": stage, "variant": variant} | values

    summary = [
        entry("s", "b0", 1.0, 0.2, 0.1), entry("s", "b0", 2.0, 0.3, 0.2),
        # Another variant's reference: not compared with b0's configs.
        entry("s", "b2", 5.0, 0.4, 0.3), entry("s", "b2", 6.0, 0.0, 0.0),
        # A CSV without a temporal error: the front is of (time, FLIP) alone.
        entry("t", "", 1.0, 0.2, None), entry("t", "", 2.0, 0.2, None),
    ]  # fmt: skip
    mark_pareto(summary)
    assert [e["pareto"] for e in summary] == [True, False, True, True, True, False]


def test_knob_lists_are_parsed_and_checked():
    assert parse_int_list("0, 1,5", "--bounce-limits") == [0, 1, 5]
    assert parse_resolution_list("160x120,32X24") == [(160, 120), (32, 24)]
    with pytest.raises(BadOption, match="--resolutions: '160' is not WxH"):
        parse_resolution_list("160")
    with pytest.raises(BadOption, match="--bounce-limits: 'two' is not an integer"):
        parse_int_list("1,two", "--bounce-limits")
    base = {"stages": [], "heuristics": ["heu1"], "budgets_rays": [100]}
    with pytest.raises(BadOption, match="bounce limit must be in 0..16"):
        check_spec(SweepSpec(**base, bounce_limits=[1, 17]))
    with pytest.raises(BadOption, match="--bounce-limits: a value is given twice"):
        check_spec(SweepSpec(**base, bounce_limits=[1, 1]))
    with pytest.raises(BadOption, match="resolution 0x10 out of range"):
        check_spec(SweepSpec(**base, resolutions=[(0, 10)]))


def test_sweep_over_two_bounce_limits(tmp_path):
    """3 frames x bounce limits 0 and 2 at 64x48, HEU1 with a rays budget: the CSV has
    the new columns, every configuration is measured against its own bounce limit's
    references, and the summary, plot and report show the temporal error and Pareto."""
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=3)
    out = tmp_path / "sweep"
    summary = run_sweep(
        SweepSpec(
            stages=[stage], heuristics=["heu1"], budgets_rays=[600], frames="1:3",
            width=64, height=48, bounce_limits=[0, 2], out=out,
        )  # fmt: skip
    )
    labels = ["raster", "heu1@600rays", "all", "rt"]
    assert summary["configs"] == [f"{c} b{b}" for b in (0, 2) for c in labels]
    with (out / "sweep.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 3 * 2 * len(labels)
    for row in rows:
        bounce = row["config"].rsplit(" b", 1)[1]
        assert row["bounce_limit"] == bounce and row["resolution"] == "64x48"
        # Every frame has one (the first frame stands in for the frames before it), in
        # [0, 1 + TRANSIENT_WEIGHT].
        assert 0.0 <= float(row["temporal_error"]) <= 1.0 + TRANSIENT_WEIGHT
        if row["config"].startswith("all "):
            # Each variant's reference is its own: zero error against itself, per frame
            # and temporally.
            assert float(row["flip"]) == 0.0
            assert float(row["temporal_error"]) == 0.0
        if bounce == "0":
            assert int(row["rays"]) == 0  # bounce limit 0: no reflection rays at all
        elif row["config"] == "all b2":
            assert int(row["rays"]) > 0
    timeline = json.loads((out / "timeline.json").read_text())
    assert set(timeline["gallery"]) == set(summary["configs"])

    text = (out / "summary.md").read_text()
    # The headers of a stage's tables (sweep_tables.TABLES), each starting with config.
    header = " ".join(line for line in text.splitlines() if line.startswith("| config"))
    for column in ("mean temporal error", "Pareto", "bounce limit", "resolution"):
        assert f" {column} |" in header
    table = [line for line in text.splitlines() if line.startswith("| ") and "b0 |" in line]
    assert any(PARETO_MARK in line for line in table)  # b0 has its own front
    assert "[64x48, bounce 2] Equal mean traced rays" not in text  # one heuristic only
    image = oiio.ImageInput.open(str(out / "error_vs_time.png"))
    assert image is not None and (image.spec().width, image.spec().height) == (900, 1000)
    image.close()
    html = (out / "report.html").read_text()
    assert "<th>mean temporal error</th>" in html and "<th>Pareto</th>" in html
    assert "images/gallery/1/all%20b2.png" in html  # b2's configs shown beside all b2
    assert "temporal error" in html and "vs all b2" in html
    # Every report frame carries a temporal error map.
    frames = sorted((out / "images" / "gallery").iterdir(), key=lambda p: float(p.name))
    assert len(frames) >= 2
    assert all((f / "heu1@600rays b2_temporal.png").is_file() for f in frames)
    assert f"images/gallery/{frames[1].name}/heu1%40600rays%20b2_temporal.png" in html


def test_sweep_over_trace_densities(tmp_path):
    """3 frames at full and quarter density (160x120, the gallery's mirrors, every visible
    reflector traced): each density's references are full-density frames (zero error
    between the two variants' ``all``), the quarter-density frames trace fewer rays and
    differ from the reference by a little, and the CSV and summary name the density."""
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=3)
    out = tmp_path / "sweep"
    spec = SweepSpec(
        stages=[stage], heuristics=["heu1"], budgets_ms=[None], frames="1:3",
        width=160, height=120, trace_densities=["full", "quarter"], out=out,
    )  # fmt: skip
    summary = run_sweep(spec)
    labels = ["raster", "heu1@inf", "all", "rt"]
    assert summary["configs"] == [f"{c} {d}" for d in ("full", "quarter") for c in labels]
    with (out / "sweep.csv").open(newline="") as handle:
        rows = {(r["config"], r["frame"]): r for r in csv.DictReader(handle)}
    for frame in ("1.0", "2.0", "3.0"):
        full, quarter = rows[("heu1@inf full", frame)], rows[("heu1@inf quarter", frame)]
        assert full["trace_density"] == "full" and quarter["trace_density"] == "quarter"
        assert rows[("all quarter", frame)]["trace_density"] == "quarter"  # the variant's
        # The references trace every pixel in both variants: the same frame.
        assert rows[("all quarter", frame)]["rays"] == rows[("all full", frame)]["rays"]
        assert 0 < int(quarter["rays"]) < int(full["rays"])
        # Unbounded HEU1 traces what all traces: no error at full density; at a quarter
        # of the pixels the fill's blur (none where the mirrors show smooth content),
        # less than the raster fallback's.
        assert float(full["flip"]) == 0.0
        assert float(quarter["flip"]) < float(rows[("raster quarter", frame)]["flip"])
    assert sum(float(rows[("heu1@inf quarter", f)]["flip"]) for f in ("1.0", "2.0", "3.0")) > 0
    text = (out / "summary.md").read_text()
    header = " ".join(line for line in text.splitlines() if line.startswith("| config"))
    assert " trace density |" in header
    with pytest.raises(BadOption, match="--trace-densities: a value is given twice"):
        check_spec(replace(spec, trace_densities=["half", "half"]))
    with pytest.raises(BadOption, match="trace density must be one of"):
        check_spec(replace(spec, trace_densities=["eighth"]))
