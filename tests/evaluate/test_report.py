"""Report metrics (transitions, fps, budget overruns) and stats.json."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd
from rich.console import Console

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.report import OVERRUN_FACTOR, build_report, print_report
from phrt_usd.evaluate.selection_metrics import selection_metrics
from phrt_usd.model.frame import FrameStats, ReflectorMetrics
from phrt_usd.run.run_files import make_run_info, read_stats, selection_layer_path, write_stats
from phrt_usd.run.selection_layer import STATS_PRIM_PATH, write_selection_layer

REFLECTORS = [f"/World/R{i}" for i in range(6)]


def random_frames(seed: int, count: int = 80, budget_ms: float = 10.0) -> list[FrameStats]:
    """Frames with random visibility (sticky, like a moving camera) and selection."""
    rng = np.random.default_rng(seed)
    visible = rng.random(len(REFLECTORS)) < 0.5
    frames = []
    for t in range(count):
        flip = rng.random(len(REFLECTORS)) < 0.15
        visible = visible ^ flip
        selected = visible & (rng.random(len(REFLECTORS)) < 0.5)
        metrics = {
            p: ReflectorMetrics(V=0.1, C=1.0, R=0.2, Q=1.0, S=False, selected=bool(s), visible=True)
            for p, v, s in zip(REFLECTORS, visible, selected, strict=True)
            if v
        }
        frames.append(
            FrameStats(
                time=float(t + 1),
                phase_ms={"gbuffer": float(rng.uniform(3, 5)), "trace": 9.0},
                frame_ms=float(rng.uniform(20, 60)),
                trace_ms=float(rng.uniform(0.8, 1.2) * budget_ms),
                predicted_trace_ms=budget_ms,
                rays=int(rng.integers(1, 10**6)),
                visible=[p for p, v in zip(REFLECTORS, visible, strict=True) if v],
                selected=[p for p, s in zip(REFLECTORS, selected, strict=True) if s],
                metrics=metrics,
                passes=["gbuffer", "trace"],
            )
        )
    return frames


def write_run(out: Path, frames: list[FrameStats], heuristic: str = "heu1") -> Path:
    info = make_run_info(
        stage="scene.usda",
        mode="hybrid",
        heuristic=heuristic,
        budget_ms=10.0,
        budget_rays=None,
        resolution=(320, 240),
        bounce_limit=5,
        selection_weight=0.001,
        frame_range=(frames[0].time, frames[-1].time),
        reflectors=REFLECTORS,
    )
    write_stats(out, info, frames)
    write_selection_layer(selection_layer_path(out), None, REFLECTORS, frames, info, 24.0)
    return out


def transitions_from_usd(layer: Path) -> tuple[int, int]:
    """(transitions, visible-in-both pairs) straight from the layer's time samples with
    plain Usd calls, independently of phrt_usd.evaluate.report."""
    stage = Usd.Stage.Open(str(layer))
    transitions = pairs = 0
    for prim in stage.TraverseAll():
        selected = prim.GetAttribute("phrt:selected")
        if not selected:
            continue
        visible = prim.GetAttribute("phrt:visible")
        times = selected.GetTimeSamples()
        for before, after in zip(times, times[1:], strict=False):
            if visible.Get(before) and visible.Get(after):
                pairs += 1
                transitions += selected.Get(before) != selected.Get(after)
    return transitions, pairs


def test_transitions_match_an_independent_count_from_usd(tmp_path: Path) -> None:
    out = write_run(tmp_path / "run", random_frames(seed=1))
    report = build_report(out)
    transitions, pairs = transitions_from_usd(out / "selection.usda")
    assert transitions > 0
    assert report["transitions"] == transitions
    assert report["transition_pairs"] == pairs
    assert report["transition_rate"] == pytest.approx(transitions / pairs)


def test_selection_metrics_on_a_hand_made_sequence() -> None:
    # A: visible throughout, selected T F F T → 2 transitions over 3 pairs.
    # B: visible T F T T, selected T F F T → only (2, 3) is visible in both: 1 transition.
    # C: never visible but "selected" flips → not counted.
    selected = np.array([[1, 1, 1], [0, 0, 0], [0, 0, 1], [1, 1, 0]], dtype=bool)
    visible = np.array([[1, 1, 0], [1, 0, 0], [1, 1, 0], [1, 1, 0]], dtype=bool)
    metrics = selection_metrics(selected, visible)
    assert metrics["transitions"] == 3
    assert metrics["transition_pairs"] == 4
    assert metrics["transition_rate"] == 0.75
    assert metrics["mean_selected"] == pytest.approx(6 / 4)
    assert metrics["mean_visible"] == pytest.approx(7 / 4)
    assert metrics["frames"] == 4 and metrics["reflectors"] == 3


def test_density_steps_count_traced_reflectors_changing_density_in_view(tmp_path: Path) -> None:
    # R0 traced in frames 1-4 at full, half, half, quarter: 2 steps. R1 traced at half,
    # then not traced (a transition, not a step), then at quarter: 0 steps. R2 traced at
    # half, out of view, traced at full: 0 steps (not in view in both frames).
    frames = random_frames(seed=5, count=4)
    plan = {
        "/World/R0": ("full", "half", "half", "quarter"),
        "/World/R1": ("half", None, "quarter", "quarter"),
        "/World/R2": ("half", "out", "full", "full"),
    }
    for f, frame in enumerate(frames):
        frame.visible = [p for p, row in plan.items() if row[f] != "out"]
        frame.selected = [p for p, row in plan.items() if row[f] not in (None, "out")]
        frame.densities = {p: row[f] for p, row in plan.items() if row[f] in ("half", "quarter")}
        frame.metrics = {}
    report = build_report(write_run(tmp_path / "run", frames))
    assert report["density_steps"] == 2
    assert report["transitions"] == 2  # R1 dropped and taken back


def test_timing_metrics_follow_their_definitions(tmp_path: Path) -> None:
    frames = random_frames(seed=2)
    report = build_report(write_run(tmp_path / "run", frames))
    frame_ms = np.array([f.frame_ms for f in frames])
    trace_ms = np.array([f.trace_ms for f in frames])
    assert report["frames"] == len(frames)
    assert report["reflectors"] == len(REFLECTORS)
    assert report["mean_fps"] == pytest.approx(1000.0 / frame_ms.mean())
    assert report["median_frame_ms"] == pytest.approx(np.median(frame_ms))
    assert report["budget_ms"] == 10.0
    overruns = int((trace_ms > 10.0 * OVERRUN_FACTOR).sum())
    assert 0 < overruns < len(frames)
    assert report["budget_overruns"] == overruns
    assert report["mean_selected"] == pytest.approx(np.mean([len(f.selected) for f in frames]))
    assert report["mode"] == "hybrid" and report["heuristic"] == "heu1"
    assert report["median_phase_ms"]["trace"] == 9.0
    json.dumps(report, allow_nan=False)  # JSON-ready, no NaN


def test_report_of_a_lone_layer_without_stats_json(tmp_path: Path) -> None:
    frames = random_frames(seed=3)
    out = write_run(tmp_path / "run", frames)
    elsewhere = tmp_path / "other-machine"
    elsewhere.mkdir()
    lone = Path(shutil.copy(out / "selection.usda", elsewhere / "sel.usda"))
    full, alone = build_report(out), build_report(lone)
    assert alone["stats"] is None
    for key in ("frames", "transitions", "mean_selected", "mean_visible", "mean_fps"):
        assert alone[key] == full[key], key
    assert alone["heuristic"] == "heu1"

    # Without the stats prim either, timing is unknown: null, not zero.
    layer = Sdf.Layer.FindOrOpen(str(lone))
    del layer.rootPrims[STATS_PRIM_PATH.name]
    layer.Save()
    bare = build_report(lone)
    assert bare["transitions"] == full["transitions"]
    for key in ("mean_fps", "median_frame_ms", "budget_overruns", "timing_source"):
        assert bare[key] is None, key
    json.dumps(bare, allow_nan=False)


def test_vs_report_gives_the_papers_ratios(tmp_path: Path) -> None:
    a = write_run(tmp_path / "heu1", random_frames(seed=4), "heu1")
    b = write_run(tmp_path / "heu2", random_frames(seed=5), "heu2")
    report = build_report(a, vs=b)
    other = report["vs"]
    assert other["heuristic"] == "heu2"
    comparison = report["comparison"]
    assert comparison["transitions_ratio_pct"] == pytest.approx(
        100.0 * report["transitions"] / other["transitions"]
    )
    assert comparison["same_frames"]
    fps = comparison["figures"]["mean_fps"]
    assert fps["difference"] == pytest.approx(report["mean_fps"] - other["mean_fps"])
    json.dumps(report, allow_nan=False)

    console = Console(record=True, width=120)
    print_report(report, console)
    text = console.export_text()
    assert f"{comparison['transitions_ratio_pct']:.1f} %" in text
    assert "heu2" in text


def test_print_single_report(tmp_path: Path) -> None:
    report = build_report(write_run(tmp_path / "run", random_frames(seed=6)))
    console = Console(record=True, width=120)
    print_report(report, console)
    text = console.export_text()
    assert "transitions" in text and str(report["transitions"]) in text
    assert f"{report['mean_fps']:.1f}" in text


def test_missing_run_raises(tmp_path: Path) -> None:
    with pytest.raises(PhrtError, match="no such run directory"):
        build_report(tmp_path / "nothing")
    with pytest.raises(PhrtError, match="no selection layer"):
        build_report(tmp_path)


def test_stats_round_trip_atomic_and_json_safe(tmp_path: Path) -> None:
    frames = random_frames(seed=7, count=5)
    frames[2].predicted_trace_ms = float("inf")  # must not produce invalid JSON
    frames[3].rays = np.int64(12)  # numpy scalars must serialise
    info = {"mode": "hybrid", "budget_ms": np.float32(10.0)}
    write_stats(tmp_path, info, list(reversed(frames)))
    write_stats(tmp_path, info, frames)  # replaces the file whole
    assert sorted(os.listdir(tmp_path)) == ["stats.json"]
    run_info, rows = read_stats(tmp_path)
    assert run_info == {"mode": "hybrid", "budget_ms": 10.0}
    assert [r["time"] for r in rows] == [f.time for f in frames]
    assert rows[2]["predicted_trace_ms"] is None
    assert rows[3]["rays"] == 12
    assert rows[0]["metrics"][rows[0]["visible"][0]]["V"] == 0.1
    assert set(rows[0]) == {
        "time",
        "phase_ms",
        "frame_ms",
        "trace_ms",
        "predicted_trace_ms",
        "rays",
        "visible",
        "selected",
        "metrics",
        "passes",
        "budget_ms",
        "expected_trace_ms",
        "budget_use",
        "untraced_reason",
        "calibration",
        "densities",
        "pixel_kinds",
    }
    (tmp_path / "stats.json").write_text("{}")
    with pytest.raises(PhrtError, match="not a phrt stats file"):
        read_stats(tmp_path)


def test_run_info_has_the_documented_keys() -> None:
    info = make_run_info(
        stage="s.usda",
        mode="hybrid",
        heuristic="heu1",
        budget_ms=None,
        budget_rays=100000,
        resolution=(320, 240),
        bounce_limit=5,
        selection_weight=0.001,
        frame_range=(1, 600),
        reflectors=REFLECTORS,
    )
    for key in (
        "stage",
        "mode",
        "heuristic",
        "budget_ms",
        "budget_rays",
        "resolution",
        "bounce_limit",
        "selection_weight",
        "frame_range",
        "reflectors",
        "machine",
        "date",
        "phrt_version",
    ):
        assert key in info, key
    assert info["machine"]["cores"] >= 1
