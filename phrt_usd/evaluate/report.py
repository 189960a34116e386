"""Metrics of a finished render, read back from its selection layer (and stats.json).

``build_report(run)`` takes a run directory (``OUT/selection.usda`` + ``OUT/stats.json``)
or a selection layer file on its own, e.g. one copied from another machine.

Sources: selection figures (``frames``, ``mean_selected``, ``mean_visible``,
``transitions``) always come from the layer's ``phrt:selected``/``phrt:visible`` samples.
Per-frame timing comes from the layer's ``/PhrtRenderStats`` samples (written by the same
renders, merged frame by frame like the selection), else from a ``stats.json`` next to
the layer, else the timing fields are ``null``. ``stats.json`` also gives the median
time of each render phase.

Transitions and ``transition_rate`` are counted by ``selection_metrics`` (its module states
the definition, paper §5.1) over the layer's frames in increasing time code. With ``vs``,
``comparison.transitions_ratio_pct`` = 100 × transitions(run) / transitions(vs) is the
paper's Table 2 figure (HEU1/HEU2).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.selection_metrics import density_levels, density_steps, selection_metrics
from phrt_usd.run.run_files import read_stats, selection_layer_path, stats_path

if TYPE_CHECKING:  # rich is imported where the tables are drawn (a cheap start)
    from rich.console import Console
from phrt_usd.run.selection_layer import SelectionRecord, read_selection_record

#: A frame's trace phase "overruns" its budget when it took more than this × budget_ms
#: (the design target allows 10 % over).
OVERRUN_FACTOR = 1.1
#: Layer names looked for in a run directory, in order.
LAYER_NAMES = ("selection.usda", "selection.usdc", "selection.usd")


def build_report(run_dir_or_layer: Path, vs: Path | None = None) -> dict[str, Any]:
    """The report as one JSON-ready object (no NaN/Inf; unknown figures are ``None``).

    Keys: frames, reflectors, mean_selected, mean_visible, transitions,
    transition_pairs, transition_rate, density_steps (None without stats.json),
    mean_fps, median_frame_ms, mean_frame_ms, median_trace_ms, budget_ms,
    budget_overruns, budget_within_pct, mode, heuristic, median_phase_ms, timing_source,
    layer, stats. With ``vs``: also ``vs`` (the other
    run's report) and ``comparison`` (ratios and differences, this run vs the other).
    """
    report, times = _single_report(Path(run_dir_or_layer))
    if vs is not None:
        other, other_times = _single_report(Path(vs))
        report["vs"] = other
        report["comparison"] = compare(report, other)
        report["comparison"]["same_frames"] = bool(np.array_equal(times, other_times))
    return report


def timing_metrics(
    frame_ms: np.ndarray, trace_ms: np.ndarray, budget_ms: float | None
) -> dict[str, Any]:
    """Timing figures of the frames that have them.

    frame_ms, trace_ms : (n,) float milliseconds per frame (same frames)
    """
    if frame_ms.size == 0:
        return {key: None for key in _TIMING_KEYS}
    mean_frame = float(frame_ms.mean())
    overruns = None
    within = None
    if budget_ms is not None and trace_ms.size:
        overruns = int(np.count_nonzero(trace_ms > budget_ms * OVERRUN_FACTOR))
        within = 100.0 * (1.0 - overruns / trace_ms.size)
    return {
        "timed_frames": int(frame_ms.size),
        # A frame time of 0 ms cannot be measured; no fps rather than infinity.
        "mean_fps": 1000.0 / mean_frame if mean_frame > 0 else None,
        "mean_frame_ms": mean_frame,
        "median_frame_ms": float(np.median(frame_ms)),
        "median_trace_ms": float(np.median(trace_ms)) if trace_ms.size else None,
        "budget_overruns": overruns,
        "budget_within_pct": within,
    }


_TIMING_KEYS = (
    "timed_frames",
    "mean_fps",
    "mean_frame_ms",
    "median_frame_ms",
    "median_trace_ms",
    "budget_overruns",
    "budget_within_pct",
)


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Run ``a`` against run ``b``: the paper's Table 2/3 figures and differences."""

    def ratio_pct(key: str) -> float | None:
        x, y = a.get(key), b.get(key)
        return 100.0 * x / y if x is not None and y else None

    def diff(key: str) -> float | None:
        x, y = a.get(key), b.get(key)
        return x - y if x is not None and y is not None else None

    keys = (
        "transitions",
        "transition_rate",
        "mean_selected",
        "mean_visible",
        "mean_fps",
        "median_frame_ms",
        "budget_overruns",
    )
    return {
        "transitions_ratio_pct": ratio_pct("transitions"),
        "transition_rate_ratio_pct": ratio_pct("transition_rate"),
        "figures": {k: {"a": a.get(k), "b": b.get(k), "difference": diff(k)} for k in keys},
    }


def _single_report(run: Path) -> tuple[dict[str, Any], np.ndarray]:
    """(report of one run, its rendered time codes (F,))."""
    layer, stats_file = _locate(run)
    record = read_selection_record(layer)
    run_info: dict[str, Any] = dict(record.run_info)
    stats_rows: list[dict[str, Any]] = []
    if stats_file is not None:
        stats_run, stats_rows = read_stats(stats_file)
        run_info = {**stats_run, **run_info}

    report: dict[str, Any] = {
        "layer": str(layer),
        "stats": str(stats_file) if stats_file is not None else None,
        "stage": run_info.get("stage"),
        "mode": run_info.get("mode"),
        "heuristic": run_info.get("heuristic"),
        "budget_ms": _number(run_info.get("budget_ms")),
        "budget_rays": run_info.get("budget_rays"),
        "resolution": run_info.get("resolution"),
    }
    report.update(selection_metrics(record.selected, record.visible))
    report["density_steps"] = _density_steps(record, stats_rows)

    frame_ms, trace_ms, source = _timings(record, stats_rows)
    report.update(timing_metrics(frame_ms, trace_ms, report["budget_ms"]))
    report["timing_source"] = source
    report["median_phase_ms"] = _median_phases(stats_rows)
    if report["mean_selected"] is None:
        raise PhrtError(f"selection layer {layer}: no rendered frames in it")
    return _clean(report), record.times


def _density_steps(record: SelectionRecord, stats_rows: list[dict[str, Any]]) -> int | None:
    """``density_steps`` of the run, from its stats.json's per-frame densities (None
    without stats.json)."""
    if not stats_rows:
        return None
    row_of = {t: f for f, t in enumerate(record.times.tolist())}
    levels = np.zeros(record.selected.shape, np.int64)
    for row in stats_rows:
        f = row_of.get(row.get("time"))
        if f is not None:
            levels[f] = density_levels(row.get("densities") or {}, record.reflectors)
    return density_steps(record.selected, record.visible, levels)


def _locate(run: Path) -> tuple[Path, Path | None]:
    """(selection layer, stats.json or None) of a run directory or a layer file."""
    if run.is_dir():
        for name in LAYER_NAMES:
            if (run / name).is_file():
                layer = run / name
                break
        else:
            raise PhrtError(f"{run}: no selection layer ({selection_layer_path(run).name})")
        stats = stats_path(run)
        return layer, stats if stats.is_file() else None
    if not run.is_file():
        raise PhrtError(f"{run}: no such run directory or selection layer")
    sibling = stats_path(run.parent)
    return run, sibling if sibling.is_file() else None


def _timings(
    record: SelectionRecord, stats_rows: list[dict[str, Any]]
) -> tuple[np.ndarray, np.ndarray, str | None]:
    """(frame_ms (n,), trace_ms (n,), source) over the layer's frames that have timing."""
    frame_samples = record.stats.get("frameMs", {})
    trace_samples = record.stats.get("traceMs", {})
    times = [t for t in record.times.tolist() if t in frame_samples and t in trace_samples]
    if times:
        return (
            np.array([frame_samples[t] for t in times], dtype=np.float64),
            np.array([trace_samples[t] for t in times], dtype=np.float64),
            "layer",
        )
    layer_times = set(record.times.tolist())
    rows = [
        r
        for r in stats_rows
        if r.get("time") in layer_times
        and r.get("frame_ms") is not None
        and r.get("trace_ms") is not None
    ]
    if rows:
        return (
            np.array([r["frame_ms"] for r in rows], dtype=np.float64),
            np.array([r["trace_ms"] for r in rows], dtype=np.float64),
            "stats.json",
        )
    return np.zeros(0), np.zeros(0), None


def _median_phases(rows: list[dict[str, Any]]) -> dict[str, float] | None:
    """Median milliseconds of each render phase over stats.json rows (None without)."""
    phases: dict[str, list[float]] = {}
    for row in rows:
        for name, ms in (row.get("phase_ms") or {}).items():
            if ms is not None:
                phases.setdefault(name, []).append(float(ms))
    return {name: float(np.median(v)) for name, v in phases.items()} or None


def _number(value: Any) -> float | None:
    """A budget as float; ``None``, negative (the "not used" convention) → None."""
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) and value >= 0 else None


def _clean(value: Any) -> Any:
    """Numpy scalars → Python; non-finite floats → None (JSON has no NaN/Inf)."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


# --- rich tables -----------------------------------------------------------------------

_ROWS = (
    ("frames", "frames", "{:d}"),
    ("reflectors", "reflectors", "{:d}"),
    ("mean_selected", "mean selected", "{:.2f}"),
    ("mean_visible", "mean visible", "{:.2f}"),
    ("transitions", "transitions", "{:d}"),
    ("transition_rate", "transition rate", "{:.2%}"),
    ("density_steps", "density steps (not transitions)", "{:d}"),
    ("mean_fps", "mean fps", "{:.1f}"),
    ("median_frame_ms", "median frame (ms)", "{:.2f}"),
    ("median_trace_ms", "median trace (ms)", "{:.2f}"),
    ("budget_ms", "budget (ms)", "{:g}"),
    ("budget_overruns", "budget overruns (>110 %)", "{:d}"),
    ("budget_within_pct", "frames within budget", "{:.1f} %"),
)


def _fmt(value: Any, pattern: str) -> str:
    if value is None:
        return "–"
    try:
        return pattern.format(value)
    except (ValueError, TypeError):
        return str(value)


def print_report(report: dict[str, Any], console: Console) -> None:
    """Draw the report as rich tables (one run, or the run against ``vs``)."""
    from rich.table import Table

    title = f"{report.get('mode') or '?'} / {report.get('heuristic') or '?'}"
    other = report.get("vs")
    if other is None:
        table = Table(title=f"phrt report: {title}", caption=report.get("layer"))
        table.add_column("metric")
        table.add_column("value", justify="right")
        for key, label, pattern in _ROWS:
            table.add_row(label, _fmt(report.get(key), pattern))
        console.print(table)
    else:
        other_title = f"{other.get('mode') or '?'} / {other.get('heuristic') or '?'}"
        table = Table(title=f"phrt report: A = {title}  vs  B = {other_title}")
        for column in ("metric", "A", "B", "A − B"):
            table.add_column(column, justify="left" if column == "metric" else "right")
        for key, label, pattern in _ROWS:
            a, b = report.get(key), other.get(key)
            difference = (
                a - b if isinstance(a, int | float) and isinstance(b, int | float) else None
            )
            table.add_row(label, _fmt(a, pattern), _fmt(b, pattern), _fmt(difference, pattern))
        console.print(table)
        comparison = report.get("comparison", {})
        paper = Table(title="as in the paper (Tables 2 and 3)")
        for column in ("transitions A/B", "mean selected A / B", "mean fps A / B"):
            paper.add_column(column, justify="right")
        paper.add_row(
            _fmt(comparison.get("transitions_ratio_pct"), "{:.1f} %"),
            f"{_fmt(report.get('mean_selected'), '{:.1f}')} / "
            f"{_fmt(other.get('mean_selected'), '{:.1f}')}",
            f"{_fmt(report.get('mean_fps'), '{:.1f}')} / {_fmt(other.get('mean_fps'), '{:.1f}')}",
        )
        console.print(paper)
        if not comparison.get("same_frames", True):
            console.print("[yellow]note: the two runs rendered different frames[/yellow]")
    phases = report.get("median_phase_ms")
    if phases:
        table = Table(title="median phase times (ms)")
        for name in phases:
            table.add_column(name, justify="right")
        table.add_row(*(f"{ms:.2f}" for ms in phases.values()))
        console.print(table)
