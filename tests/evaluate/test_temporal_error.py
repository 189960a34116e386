"""The sweep's temporal error end to end (the warped-frame measure itself:
tests/evaluate/test_warped_error.py, docs/temporal-error.md), the Pareto front of the
sweep summary, and knob sweeps (bounce limits, trace densities).
"""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import OpenImageIO as oiio
import pytest
from scenes import mirror_gallery_stage

from phrt_usd.errors import BadOption
from phrt_usd.evaluate.sweep import (
    TEMPORAL_COLUMNS,
    SweepSpec,
    check_spec,
    parse_int_list,
    parse_resolution_list,
    run_sweep,
)
from phrt_usd.evaluate.sweep_summary import PARETO_MARK, mark_pareto, pareto_front


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


@pytest.mark.slow
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
    rows_by = {(r["config"], r["frame"]): r for r in rows}
    for row in rows:
        bounce = row["config"].rsplit(" b", 1)[1]
        assert row["bounce_limit"] == bounce and row["resolution"] == "64x48"
        temporal = [row[c] for c in TEMPORAL_COLUMNS]
        if row["frame"] == "1.0":  # no previous frame: nothing to warp
            assert temporal == [""] * len(TEMPORAL_COLUMNS)
        else:  # FLIP means over the warp's pixels, in [0, 1]
            assert all(0.0 <= float(v) <= 1.0 for v in temporal)
            reference = rows_by[(f"all b{bounce}", row["frame"])]
            assert row["warped_error_reference"] == reference["warped_error"]
        if row["config"].startswith("all "):
            # Each variant's reference is its own: zero error against itself, per frame
            # and temporally.
            assert float(row["flip"]) == 0.0
            assert row["frame"] == "1.0" or float(row["temporal_error"]) == 0.0
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
    # Every report frame but the first (no previous frame) carries a temporal error map.
    frames = sorted((out / "images" / "gallery").iterdir(), key=lambda p: float(p.name))
    assert len(frames) >= 2
    assert not (frames[0] / "heu1@600rays b2_temporal.png").exists()
    assert all((f / "heu1@600rays b2_temporal.png").is_file() for f in frames[1:])
    assert f"images/gallery/{frames[1].name}/heu1%40600rays%20b2_temporal.png" in html


@pytest.mark.slow
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
        check_spec(replace(spec, trace_densities=["17/16"]))
