"""The temporal error (image_metrics.temporal_error_map, docs/temporal-error.md), the
Pareto front of the sweep summary, and a knob sweep (two bounce limits) end to end.

Synthetic sequences: a reference whose background moves (a sine shifting along x), and
tests that equal it (identical), add a patch on every other frame (popping) or add the
same patch on every frame (steady error).
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

from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.evaluate.image_metrics import flip_map, mean_over, temporal_error_map
from phrt_usd.evaluate.sweep import (
    SweepSpec,
    check_spec,
    parse_int_list,
    parse_resolution_list,
    run_sweep,
)
from phrt_usd.evaluate.sweep_summary import PARETO_MARK, mark_pareto, pareto_front
from phrt_usd.render.renderer import FrameRenderer, RenderOptions
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.stage import open_stage

sys.path.insert(0, str(Path(__file__).parent))
from scenes import mirror_gallery_stage  # noqa: E402

H, W, N = 48, 64, 6
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


def _scores(reference: list[np.ndarray], test: list[np.ndarray]) -> tuple[float, float]:
    """(mean per-frame FLIP, mean temporal error) of ``test`` against ``reference``."""
    per_frame = np.mean([mean_over(flip_map(r, h)) for r, h in zip(reference, test, strict=True)])
    temporal = np.mean(
        [
            mean_over(temporal_error_map(reference[t - 1], reference[t], test[t - 1], test[t]))
            for t in range(1, N)
        ]
    )
    return float(per_frame), float(temporal)


def test_popping_scores_high_temporally_steady_error_low_identical_zero():
    reference = _reference(moving=True)
    popping = [_with_patch(r, PATCH if t % 2 else 0.0) for t, r in enumerate(reference)]
    steady = [_with_patch(r, PATCH) for r in reference]
    identical_frame, identical_temporal = _scores(reference, [r.copy() for r in reference])
    pop_frame, pop_temporal = _scores(reference, popping)
    steady_frame, steady_temporal = _scores(reference, steady)
    assert identical_frame == 0.0 and identical_temporal == 0.0  # FLIP of equal images is 0
    # Per frame, the pop carries the patch in half the frames: about half the steady
    # error's mean (0.5 analytically; 0.6 leaves room for FLIP's spatial filtering).
    assert pop_frame <= 0.6 * steady_frame
    # Temporally the order flips: the pop changes in every frame pair, the steady patch
    # does not. The steady error's temporal score is not exactly 0 here only because the
    # constant linear offset changes after the sRGB encoding as the background moves
    # (measured ratio ~4.8; 3 keeps a margin).
    assert pop_temporal >= 3.0 * steady_temporal
    assert steady_temporal > 0.0


def test_steady_error_on_a_still_reference_is_exactly_zero():
    reference = _reference(moving=False)
    steady = [_with_patch(r, PATCH) for r in reference]
    per_frame, temporal = _scores(reference, steady)
    assert per_frame > 0.05  # the error is there in every frame ...
    assert temporal == 0.0  # ... but it never changes: nothing pops


def test_full_frame_pop_is_near_the_top_of_the_scale():
    black = np.zeros((H, W, 3), np.float32)
    white = np.ones((H, W, 3), np.float32)
    # Reference still black; the test jumps to white (change +1, shown white on the
    # reference's grey) or back (change -1, black on grey): FLIP(grey, white) ~0.85 and
    # FLIP(grey, black) ~0.93 at half amplitude (CHANGE_SCALE), so both above 0.8.
    assert mean_over(temporal_error_map(black, black, black, white)) > 0.8
    assert mean_over(temporal_error_map(black, black, white, black)) > 0.8


def test_bad_inputs_raise_instead_of_exiting():
    a = np.zeros((H, W, 3), np.float32)
    with pytest.raises(PhrtError, match="one size"):
        temporal_error_map(a, a, a[:-1], a)
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(PhrtError, match="NaN"):
        temporal_error_map(a, a, bad, a)


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
    """Real renders: the five mirrors traced in every other frame (a configuration that
    flips its selection each frame) against the same mirrors never traced (raster only),
    both measured against the all-traced frames."""
    # Still camera (one time code six times): the raster-only error never changes, so its
    # temporal error is exactly 0; the popping sequence has half the per-frame error
    # (three of six frames equal the reference exactly) and a temporal error on every
    # frame pair.
    traced, raster = _gallery_frames(tmp_path, [18.0] * N)
    popping = [traced[t] if t % 2 else raster[t] for t in range(N)]
    pop_frame, pop_temporal = _scores(traced, popping)
    raster_frame, raster_temporal = _scores(traced, raster)
    assert raster_frame > 0.0 and raster_temporal == 0.0
    assert pop_frame == pytest.approx(0.5 * raster_frame, rel=1e-6)
    assert pop_temporal > 0.0
    # Moving camera: the raster error moves with the mirrors, so it has a temporal error
    # too, but the popping one stays above it while its per-frame error stays below
    # (measured 0.0023 vs 0.0015 temporal, 0.0019 vs 0.0040 per frame; margins 1.2, 0.6).
    traced, raster = _gallery_frames(tmp_path, [15.0 + t for t in range(N)])
    popping = [traced[t] if t % 2 else raster[t] for t in range(N)]
    pop_frame, pop_temporal = _scores(traced, popping)
    raster_frame, raster_temporal = _scores(traced, raster)
    assert pop_frame <= 0.6 * raster_frame
    assert pop_temporal >= 1.2 * raster_temporal


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
        # One-frame sweep: no temporal error; the front is of (time, FLIP) alone.
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
        first = row["frame"] == "1.0"
        # No previous frame on the first: no temporal error, else a number in [0, 1].
        assert (row["temporal_error"] == "") == first, row
        if not first:
            assert 0.0 <= float(row["temporal_error"]) <= 1.0
        if row["config"].startswith("all "):
            # Each variant's reference is its own: zero error against itself, per frame
            # and temporally.
            assert float(row["flip"]) == 0.0
            assert first or float(row["temporal_error"]) == 0.0
        if bounce == "0":
            assert int(row["rays"]) == 0  # bounce limit 0: no reflection rays at all
        elif row["config"] == "all b2":
            assert int(row["rays"]) > 0
    timeline = json.loads((out / "timeline.json").read_text())
    assert set(timeline["gallery"]) == set(summary["configs"])

    text = (out / "summary.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| config"))
    for column in ("temporal error", "Pareto", "bounce limit", "resolution"):
        assert f" {column} |" in header
    table = [line for line in text.splitlines() if line.startswith("| ") and "b0 |" in line]
    assert any(PARETO_MARK in line for line in table)  # b0 has its own front
    assert "[64x48, bounce 2] Equal mean traced rays" not in text  # one heuristic only
    image = oiio.ImageInput.open(str(out / "error_vs_time.png"))
    assert image is not None and (image.spec().width, image.spec().height) == (900, 1000)
    image.close()
    html = (out / "report.html").read_text()
    assert "<th>temporal error</th>" in html and "<th>Pareto</th>" in html
    assert "images/gallery/1/all%20b2.png" in html  # b2's configs shown beside all b2
    assert "temporal error" in html and "vs all b2" in html
    # Report frames after the first carry a temporal error map, the first (no previous
    # frame) none.
    frames = sorted((out / "images" / "gallery").iterdir(), key=lambda p: float(p.name))
    assert len(frames) >= 2
    assert not (frames[0] / "heu1@600rays b2_temporal.png").exists()
    assert (frames[1] / "heu1@600rays b2_temporal.png").is_file()
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
    header = next(line for line in text.splitlines() if line.startswith("| config"))
    assert " trace density |" in header
    with pytest.raises(BadOption, match="--trace-densities: a value is given twice"):
        check_spec(replace(spec, trace_densities=["half", "half"]))
    with pytest.raises(BadOption, match="trace density must be one of"):
        check_spec(replace(spec, trace_densities=["eighth"]))
