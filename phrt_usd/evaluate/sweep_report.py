"""Human-readable outputs of ``phrt sweep``: error against run time, for people.

``phrt sweep`` (``sweep.py``) writes machine-readable files into its output directory
``OUT``; this module reads them and writes the human-readable ones next to them.

Inputs (the sweep's contract)::

    OUT/sweep.csv        one row per stage x config x frame (columns: see REQUIRED_COLUMNS)
    OUT/timeline.json    {stage: {config: {"reflectors": [paths], "frames": [times],
                                           "selected": [[bool]], "visible": [[bool]]}}}
    OUT/images/<stage>/<frame>/<config>.png       tone-mapped preview of chosen frames
    OUT/images/<stage>/<frame>/<config>_flip.png  FLIP error map vs the reference (magma)
    OUT/images/<stage>/<frame>/all.png            the reference (``all`` config)
    OUT/paper.json       optional: the paper's figures per stage (else PAPER_FIGURES)

Outputs::

    OUT/summary.md                   one table per stage + the paper's figures beside ours
    OUT/error_vs_time.png            mean FLIP against mean frame time, every stage
    OUT/error_vs_time_<stage>.png    the same per stage (only with more than one stage)
    OUT/timeline_<stage>.png         which reflector was traced in which frame, per config
    OUT/report.html                  one static page: plots, tables, timelines, images

Pipeline: ``read_sweep_csv`` → ``summarize`` (one dict per stage x config, in display
order) → ``write_summary_md`` / ``plot_error_vs_time`` / ``plot_selection_timeline`` →
``write_report_html``. ``write_sweep_report`` runs all of it.

Definitions used in the tables (all means are over the config's frames):

- *mean fps* = 1000 / mean frame ms (frames per second of wall time over the whole path,
  not the mean of per-frame fps, which short frames would inflate).
- *transition rate* = transitions / chances to switch, a chance being a reflector visible
  in two consecutive frames (as in ``phrt report``), counted from timeline.json. Without a
  usable timeline (absent, or not the CSV's frame count) the chances are approximated
  from the CSV's per-frame visible counts after the first frame, which also counts
  reflectors that just entered the view; the summary says which was used.
- *temporal FLIP* = mean FLIP between consecutive frames of the config; shown next to the
  reference's for the same frame pairs (camera motion alone gives the reference's value;
  flicker from selection changes shows as the excess).

Limits: the page is static (no JavaScript); images are referenced by relative path, so
``report.html`` must stay next to ``images/`` and the PNGs.
"""

from __future__ import annotations

import csv
import html
import json
import math
import re
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from phrt_usd.errors import PhrtError
from phrt_usd.run.run_files import atomic_path, write_text_atomic

# --- file names ------------------------------------------------------------------------

SWEEP_CSV = "sweep.csv"
TIMELINE_JSON = "timeline.json"
IMAGES_DIR = "images"
PAPER_JSON = "paper.json"
SUMMARY_MD = "summary.md"
ERROR_VS_TIME_PNG = "error_vs_time.png"
REPORT_HTML = "report.html"

#: Name of the reference config (every reflector traced); FLIP/PSNR are measured against it.
REFERENCE_CONFIG = "all"
#: Suffix of a config's FLIP error map in the images directory.
FLIP_MAP_SUFFIX = "_flip"

#: The paper's results (GTX 760, OptiX; DESIGN.md section 1), used when paper.json is absent.
#: transitions_ratio is HEU1's transitions as a fraction of HEU2's.
PAPER_FIGURES: dict[str, dict[str, float]] = {
    "farm": {
        "heu1_fps": 25.4,
        "heu2_fps": 26.4,
        "transitions_ratio": 0.038,
        "heu1_selected": 5,
        "heu2_selected": 4,
    },
    "sewer": {
        "heu1_fps": 21.8,
        "heu2_fps": 23.3,
        "transitions_ratio": 0.046,
        "heu1_selected": 15,
        "heu2_selected": 12,
    },
}

#: Columns of sweep.csv this module reads (others are ignored).
REQUIRED_COLUMNS = (
    "stage",
    "config",
    "heuristic",
    "mode",
    "budget_ms",
    "budget_rays",
    "frame",
    "frame_ms",
    "trace_ms",
    "visible",
    "selected",
    "transitions",
    "flip",
    "flip_reflectors",
    "psnr",
    "flip_temporal",
    "flip_temporal_reference",
)

# --- plot layout -----------------------------------------------------------------------

#: error_vs_time.png: 8 x 5 inches at 100 dpi = 800 x 500 pixels.
PLOT_SIZE_INCHES = (8.0, 5.0)
PLOT_DPI = 100
#: Use a log time axis when the slowest plotted frame time exceeds the fastest by this.
LOG_X_RATIO = 8.0
#: Smallest frame time placed on a log axis (ms); a 0 ms mean would be at -inf.
MIN_LOG_MS = 1e-3
#: Timeline image: height of one reflector row (inches), shrunk so that all rows of all
#: configs fit in TIMELINE_MAX_GRID_INCHES (33 reflectors x 10 configs stay one image).
TIMELINE_ROW_INCHES = 0.1
TIMELINE_MAX_GRID_INCHES = 14.0
TIMELINE_WIDTH_INCHES = 9.0
#: (top, bottom) margins for title and legend + x axis; (left, right) for the reflector
#: names and the config names.
TIMELINE_MARGIN_INCHES = (0.4, 0.8)
TIMELINE_SIDE_INCHES = (1.2, 1.3)
#: Reflector names fill this fraction of their row height; below the smallest readable
#: font size (points) they are left out.
TIMELINE_LABEL_FILL = 0.8
TIMELINE_MIN_LABEL_POINTS = 3.5
#: At most about this many labelled frames on the time axis.
TIMELINE_MAX_XTICKS = 20

HEURISTIC_COLOURS = {"heu1": "tab:blue", "heu2": "tab:orange"}
OTHER_HEURISTIC_COLOUR = "tab:green"
STAGE_LINESTYLES = ("-", "--", ":", "-.")
#: (kind, marker, colour, legend name) of the single-point baselines.
BASELINE_MARKERS = (
    ("reference", "*", "black", "all (reference)"),
    ("raster", "s", "dimgray", "raster only"),
    ("rt", "D", "tab:purple", "rt"),
)
#: The FLIP axis starts this fraction of its top below 0.
Y_MARGIN_FRACTION = 0.04

#: Timeline cell states and their colours (index = state).
TIMELINE_STATES = (
    ("not visible", "#e9e9e9"),
    ("raster (visible, not traced)", "#9ecae1"),
    ("ray-traced", "#d62728"),
    ("traced while not visible", "#f7a1a1"),
)

#: Display order of config kinds in tables and legends.
KIND_ORDER = {"raster": 0, "heuristic": 1, "reference": 2, "rt": 3}
#: Display order of heuristics at one budget; others follow alphabetically.
HEURISTIC_ORDER = {"heu1": 0, "heu2": 1}

MISSING = "—"

#: How the tables' figures are defined; heads summary.md and report.html.
DEFINITIONS = (
    "FLIP and PSNR are measured against the `all` reference (every reflector ray-traced; "
    "PSNR 100 dB = identical). Mean fps = 1000 / mean frame ms. Transition rate = "
    "transitions / chances to switch (reflector visible in two consecutive frames). "
    "Temporal FLIP: between consecutive frames of the config; the reference's for the "
    "same frame pairs beside it (camera motion alone gives the reference's value)."
)


# --- reading ---------------------------------------------------------------------------


def read_sweep_csv(path: Path) -> list[dict[str, str]]:
    """Rows of sweep.csv as dicts of strings; PhrtError if missing, empty or short of columns."""
    path = Path(path)
    if not path.is_file():
        raise PhrtError(f"{path}: sweep results not found (run `phrt sweep` first)")
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in REQUIRED_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise PhrtError(f"{path}: missing column(s) {', '.join(missing)}")
        rows = list(reader)
    if not rows:
        raise PhrtError(f"{path}: no rows")
    return rows


def load_paper_figures(out_dir: Path) -> dict[str, dict[str, float]]:
    """The paper's figures: OUT/paper.json if present, else ``PAPER_FIGURES``."""
    path = Path(out_dir) / PAPER_JSON
    if not path.is_file():
        return {stage: dict(figures) for stage, figures in PAPER_FIGURES.items()}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise PhrtError(f"{path}: cannot read ({error})") from error
    if not isinstance(data, dict):
        raise PhrtError(f"{path}: expected an object {{stage: {{figure: number}}}}")
    paper: dict[str, dict[str, float]] = {}
    for stage, figures in data.items():
        if not isinstance(figures, dict):
            raise PhrtError(f"{path}: figures of stage {stage!r} are not an object")
        for key, value in figures.items():
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
            ):
                raise PhrtError(f"{path}: {stage}.{key} is not a finite number")
        paper[str(stage)] = {str(k): float(v) for k, v in figures.items()}
    return paper


def _number(row: Mapping[str, Any], column: str, *, allow_inf: bool = False) -> float | None:
    """Float value of ``row[column]``, None when empty; PhrtError naming the cell if bad."""
    raw = row.get(column)
    if raw is None or (isinstance(raw, str) and raw.strip() == ""):
        return None
    try:
        value = float(raw)
    except (TypeError, ValueError):
        value = math.nan
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        raise PhrtError(
            f"sweep.csv stage {row.get('stage')!r} config {row.get('config')!r} "
            f"frame {row.get('frame')!r}: column {column} = {raw!r} is not a finite number"
        )
    return value


def _mean(values: Iterable[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return sum(present) / len(present) if present else None


# --- summary ---------------------------------------------------------------------------


def config_kind(heuristic: str, mode: str) -> str:
    """'raster' | 'rt' | 'reference' | 'heuristic' — the config's role in the report."""
    if mode == "raster" or heuristic == "none":
        return "raster"
    if mode == "rt":
        return "rt"
    if heuristic == "all":
        return "reference"
    return "heuristic"


def budget_label(kind: str, budget_ms: float | None, budget_rays: float | None) -> str:
    """Human label of a config's budget: '4 ms', '20000 rays', 'unbounded' or '—'."""
    parts = []
    if budget_ms is not None and math.isfinite(budget_ms):
        parts.append(f"{budget_ms:g} ms")
    if budget_rays is not None and math.isfinite(budget_rays):
        parts.append(f"{int(budget_rays)} rays")
    if parts:
        return ", ".join(parts)
    return "unbounded" if kind == "heuristic" else MISSING


def _budget_sort_key(entry: Mapping[str, Any]) -> tuple:
    """Time budgets ascending, then ray budgets ascending, then unbounded."""
    ms, rays = entry["budget_ms"], entry["budget_rays"]
    if ms is not None and math.isfinite(ms):
        return (0, ms, rays if rays is not None else math.inf)
    if rays is not None and math.isfinite(rays):
        return (1, rays, 0.0)
    return (2, 0.0, 0.0)


def _row_sort_key(entry: Mapping[str, Any]) -> tuple:
    heuristic = entry["heuristic"]
    return (
        KIND_ORDER[entry["kind"]],
        _budget_sort_key(entry) if entry["kind"] == "heuristic" else (0, 0.0, 0.0),
        HEURISTIC_ORDER.get(heuristic, len(HEURISTIC_ORDER)),
        heuristic,
        entry["config"],
    )


def summarize(
    rows: Iterable[Mapping[str, Any]], timeline: Mapping[str, Any] | None = None
) -> list[dict[str, Any]]:
    """One dict per stage x config from sweep.csv rows, in display order.

    Stages keep their order of first appearance; within a stage: raster, heuristics by
    budget (ms budgets ascending, then ray budgets, then unbounded; HEU1 before HEU2 at
    each budget), the ``all`` reference, ``rt``. Keys of each dict:

    stage, config, heuristic, mode, kind (see ``config_kind``), budget_ms / budget_rays
    (float, None = not used, inf = unbounded), budget (label), frames (count),
    mean_frame_ms, median_frame_ms, mean_fps, mean_trace_ms, mean_rays, mean_flip,
    mean_flip_reflectors, mean_psnr, transitions (sum, int), transition_chances (int),
    transition_rate (transitions / chances, None without chances), chances_from
    ("timeline" | "csv"), mean_selected, mean_visible, mean_flip_temporal,
    mean_flip_temporal_reference. Means skip empty cells and are None when every cell is
    empty.

    timeline : timeline.json's object; when it has the config with as many frames as the
               CSV, chances to switch are counted exactly from it (see module doc).
    """
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for row in rows:
        groups.setdefault((str(row["stage"]), str(row["config"])), []).append(row)
    if not groups:
        raise PhrtError("sweep.csv: no rows to summarize")

    stage_order = {stage: i for i, stage in enumerate(dict.fromkeys(s for s, _ in groups))}
    summary = []
    for (stage, config), group in groups.items():
        entry = (timeline or {}).get(stage, {})
        data = entry.get(config) if isinstance(entry, dict) else None
        chances = None
        if data is not None:
            _reflectors, frames, _selected, visible = _timeline_arrays(stage, config, data)
            if len(frames) == len(group):
                # A chance to switch: visible in this frame and the one before.
                chances = int(np.count_nonzero(visible[1:] & visible[:-1]))
        summary.append(_summarize_config(stage, config, group, chances))
    summary.sort(key=lambda e: (stage_order[e["stage"]], _row_sort_key(e)))
    return summary


def _constant(group: list[Mapping[str, Any]], column: str, stage: str, config: str) -> str:
    values = {str(row[column]).strip() for row in group}
    if len(values) != 1:
        raise PhrtError(
            f"sweep.csv stage {stage!r} config {config!r}: column {column} varies "
            f"between frames ({', '.join(sorted(values))})"
        )
    return values.pop()


def _summarize_config(
    stage: str, config: str, group: list[Mapping[str, Any]], chances: int | None
) -> dict:
    """Summary entry of one stage x config; ``chances`` from the timeline, or None."""
    heuristic = _constant(group, "heuristic", stage, config)
    mode = _constant(group, "mode", stage, config)
    kind = config_kind(heuristic, mode)
    _constant(group, "budget_ms", stage, config)
    _constant(group, "budget_rays", stage, config)
    budget_ms = _number(group[0], "budget_ms", allow_inf=True)
    budget_rays = _number(group[0], "budget_rays", allow_inf=True)

    ordered = sorted(group, key=lambda row: _number(row, "frame") or 0.0)
    frame_ms = [_number(r, "frame_ms") for r in ordered]
    if any(v is None for v in frame_ms):
        raise PhrtError(f"sweep.csv stage {stage!r} config {config!r}: empty frame_ms")
    mean_frame_ms = sum(frame_ms) / len(frame_ms)
    transitions = [_number(r, "transitions") or 0.0 for r in ordered]
    chances_from = "timeline"
    if chances is None:
        # Approximation: reflectors visible in every frame that has a predecessor.
        chances = int(round(sum(_number(r, "visible") or 0.0 for r in ordered[1:])))
        chances_from = "csv"
    total_transitions = int(round(sum(transitions)))
    return {
        "stage": stage,
        "config": config,
        "heuristic": heuristic,
        "mode": mode,
        "kind": kind,
        "budget_ms": budget_ms,
        "budget_rays": budget_rays,
        "budget": budget_label(kind, budget_ms, budget_rays),
        "frames": len(ordered),
        "mean_frame_ms": mean_frame_ms,
        "median_frame_ms": statistics.median(frame_ms),
        # A mean frame time of 0 ms (clock resolution) would give infinite fps.
        "mean_fps": 1000.0 / mean_frame_ms if mean_frame_ms > 0.0 else None,
        "mean_trace_ms": _mean(_number(r, "trace_ms") for r in ordered),
        "mean_rays": _mean(_number(r, "rays") for r in ordered),
        "mean_flip": _mean(_number(r, "flip") for r in ordered),
        "mean_flip_reflectors": _mean(_number(r, "flip_reflectors") for r in ordered),
        "mean_psnr": _mean(_number(r, "psnr") for r in ordered),
        "transitions": total_transitions,
        "transition_chances": chances,
        "transition_rate": total_transitions / chances if chances > 0 else None,
        "chances_from": chances_from,
        "mean_selected": _mean(_number(r, "selected") for r in ordered),
        "mean_visible": _mean(_number(r, "visible") for r in ordered),
        "mean_flip_temporal": _mean(_number(r, "flip_temporal") for r in ordered),
        "mean_flip_temporal_reference": _mean(
            _number(r, "flip_temporal_reference") for r in ordered
        ),
    }


def stages_of(summary: list[Mapping[str, Any]]) -> list[str]:
    """Stage names in summary order."""
    return list(dict.fromkeys(e["stage"] for e in summary))


# --- number formatting (shared by the markdown and the HTML tables) ---------------------


def _fixed(digits: int):
    def fmt(value: float | None) -> str:
        return MISSING if value is None else f"{value:.{digits}f}"

    return fmt


def _significant3(value: float | None) -> str:
    """3 significant digits: 0.0123, 0.123, 1.23 (FLIP is in [0, 1], often ≪ 1)."""
    return MISSING if value is None else f"{value:.3g}"


def _percent(value: float | None) -> str:
    return MISSING if value is None else f"{100.0 * value:.2f} %"


#: (header, summary key, formatter) of every table column, in order.
TABLE_COLUMNS: tuple[tuple[str, str, Any], ...] = (
    ("config", "config", str),
    ("heuristic", "heuristic", str),
    ("budget", "budget", str),
    ("frames", "frames", str),
    ("mean frame ms", "mean_frame_ms", _fixed(2)),
    ("median frame ms", "median_frame_ms", _fixed(2)),
    ("mean fps", "mean_fps", _fixed(1)),
    ("mean trace ms", "mean_trace_ms", _fixed(2)),
    ("mean rays", "mean_rays", _fixed(0)),
    ("mean FLIP", "mean_flip", _significant3),
    ("mean FLIP reflectors", "mean_flip_reflectors", _significant3),
    ("mean PSNR dB", "mean_psnr", _fixed(2)),
    ("transitions", "transitions", str),
    ("transition rate", "transition_rate", _percent),
    ("mean selected", "mean_selected", _fixed(2)),
    ("temporal FLIP", "mean_flip_temporal", _significant3),
    ("reference temporal FLIP", "mean_flip_temporal_reference", _significant3),
)


def table_cells(entry: Mapping[str, Any]) -> list[str]:
    """The formatted cells of one summary entry, in ``TABLE_COLUMNS`` order."""
    return [fmt(entry[key]) for _header, key, fmt in TABLE_COLUMNS]


def stage_notes(summary: list[Mapping[str, Any]], stage: str) -> list[str]:
    """Caveats of one stage's table: configs whose transition rate is approximated."""
    approximated = [
        e["config"] for e in summary if e["stage"] == stage and e["chances_from"] == "csv"
    ]
    if not approximated:
        return []
    return [
        "Transition rate approximated from per-frame visible counts (no matching "
        f"timeline.json entry) for: {', '.join(approximated)}."
    ]


def paper_comparison(
    summary: list[Mapping[str, Any]], stage: str, paper: Mapping[str, Mapping[str, float]]
) -> list[str]:
    """Plain-text lines comparing the paper's HEU1/HEU2 figures with this sweep's.

    Ours are given at every budget where both HEU1 and HEU2 were run; the transitions
    ratio is HEU1's transitions over HEU2's (as in the paper).
    """
    lines = []
    figures = paper.get(stage)
    if figures:

        def figure(key: str, scale: float = 1.0, fmt: str = "g") -> str:
            value = figures.get(key)
            return MISSING if value is None else format(scale * value, fmt)

        lines.append(
            "Paper (GTX 760, OptiX): "
            f"fps HEU1 {figure('heu1_fps')} / HEU2 {figure('heu2_fps')}; "
            f"transitions HEU1/HEU2 {figure('transitions_ratio', 100.0, '.1f')} %; "
            f"mean selected HEU1 {figure('heu1_selected')} / HEU2 {figure('heu2_selected')}."
        )
    else:
        lines.append(f"The paper has no figures for stage {stage!r}.")
    by_budget: dict[str, dict[str, Mapping[str, Any]]] = {}
    for entry in summary:
        if entry["stage"] == stage and entry["heuristic"] in ("heu1", "heu2"):
            by_budget.setdefault(entry["budget"], {})[entry["heuristic"]] = entry
    for budget, pair in by_budget.items():
        if len(pair) != 2:
            continue
        heu1, heu2 = pair["heu1"], pair["heu2"]
        ratio = heu1["transitions"] / heu2["transitions"] if heu2["transitions"] else None
        lines.append(
            f"This sweep at budget {budget}: fps HEU1 {_fixed(1)(heu1['mean_fps'])} / "
            f"HEU2 {_fixed(1)(heu2['mean_fps'])}; transitions HEU1/HEU2 "
            f"{_percent(ratio)} ({heu1['transitions']} / {heu2['transitions']}); "
            f"mean selected HEU1 {_fixed(2)(heu1['mean_selected'])} / "
            f"HEU2 {_fixed(2)(heu2['mean_selected'])}."
        )
    return lines


def frontier_flip_at(points: Iterable[tuple[float, float]], ms: float) -> float | None:
    """The lowest mean FLIP a heuristic reached within a cost of ``ms`` (mean frame
    milliseconds, or another cost such as mean traced rays), linearly interpolated:
    ``points`` are its (mean cost, mean FLIP) over budgets.
    The points are reduced to their Pareto frontier (a point slower *and* worse than
    another is dropped: that time buys at least the faster point's error), interpolated
    between neighbours, and held at the slowest point's error beyond it. None when
    ``ms`` is faster than every point (no budget of it was that fast)."""
    frontier: list[tuple[float, float]] = []
    for t, e in sorted(points):
        if not frontier or e < frontier[-1][1]:
            frontier.append((t, e))
    if not frontier or ms < frontier[0][0]:
        return None
    for (t0, e0), (t1, e1) in zip(frontier, frontier[1:], strict=False):
        if ms <= t1:
            # The line is what alternating the two budgets over frames would give.
            return e0 + (e1 - e0) * (ms - t0) / (t1 - t0) if t1 > t0 else e1
    return frontier[-1][1]


#: The cost axes HEU1 and HEU2 are compared on: (summary key, its name, its unit). Frame
#: time is the one that matters; traced rays are its deterministic part (a rays budget
#: selects the same on every machine), free of the timing noise of a few-ms trace phase.
COMPARISON_AXES = (
    ("mean_frame_ms", "mean frame time", "ms"),
    ("mean_rays", "mean traced rays", "rays"),
)


def equal_time_comparison(summary: list[Mapping[str, Any]], stage: str) -> list[str]:
    """Lines comparing HEU1 and HEU2 at equal cost, per budget kind (ms or rays budgets)
    and per axis of ``COMPARISON_AXES`` (rays only for rays budgets): for each HEU1 point
    with some budget, HEU2's frontier error at HEU1's cost (``frontier_flip_at``), and
    the verdict."""
    lines = []

    def bounded(value: float | None) -> bool:
        return value is not None and math.isfinite(value)

    for kind, field in (("ms", "budget_ms"), ("rays", "budget_rays")):
        # Each curve: this kind's budgets plus the unbounded point (no budget at all).
        curves: dict[str, list[Mapping[str, Any]]] = {"heu1": [], "heu2": []}
        for e in summary:
            if e["stage"] != stage or e["heuristic"] not in curves or e["mean_flip"] is None:
                continue
            unbounded = not bounded(e["budget_ms"]) and not bounded(e["budget_rays"])
            if e[field] is not None or unbounded:
                curves[e["heuristic"]].append(e)
        if not any(bounded(e[field]) for e in curves["heu1"]) or not curves["heu2"]:
            continue
        for axis, name, unit in COMPARISON_AXES:
            if (kind == "ms" and unit == "rays") or any(
                e.get(axis) is None for e in curves["heu1"] + curves["heu2"]
            ):
                continue
            heu2 = [(e[axis], e["mean_flip"]) for e in curves["heu2"]]
            wins = compared = 0
            parts = []
            for e in curves["heu1"]:
                if not bounded(e[field]) or e[field] == 0.0:
                    continue  # both heuristics do the same there (everything / nothing)
                other = frontier_flip_at(heu2, e[axis])
                if other is None:
                    parts.append(f"{e['budget']}: cheaper than any HEU2 point")
                    continue
                compared += 1
                wins += e["mean_flip"] <= other
                cost = f"{e[axis]:.2f} ms" if unit == "ms" else f"{e[axis]:.0f} rays"
                parts.append(
                    f"{e['budget']}: {_significant3(e['mean_flip'])} at {cost} "
                    f"vs HEU2 {_significant3(other)}"
                )
            if parts:
                lines.append(
                    f"Equal {name} ({kind} budgets; HEU2 interpolated on its error-"
                    f"{unit} frontier): HEU1 mean FLIP <= HEU2 at {wins} of {compared}. "
                    + "; ".join(parts)
                    + "."
                )
    return lines


# --- summary.md ------------------------------------------------------------------------


def _md_cell(text: str) -> str:
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")


def write_summary_md(
    summary: list[Mapping[str, Any]],
    path: Path,
    paper: Mapping[str, Mapping[str, float]] | None = None,
) -> None:
    """Write summary.md: per stage a heading, one markdown table, the paper comparison."""
    paper = PAPER_FIGURES if paper is None else paper
    lines = [
        "# phrt sweep: error against run time",
        "",
        DEFINITIONS,
        "",
    ]
    header = [h for h, _k, _f in TABLE_COLUMNS]
    for stage in stages_of(summary):
        lines += [f"## Stage {_md_cell(stage)}", ""]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "|".join("---" for _ in header) + "|")
        for entry in summary:
            if entry["stage"] == stage:
                lines.append("| " + " | ".join(_md_cell(c) for c in table_cells(entry)) + " |")
        lines.append("")
        notes = [
            *stage_notes(summary, stage),
            *paper_comparison(summary, stage, paper),
            *equal_time_comparison(summary, stage),
        ]
        lines += [_md_cell(line) + "  " for line in notes]
        lines.append("")
    write_text_atomic(Path(path), "\n".join(lines))


# --- plots -----------------------------------------------------------------------------


def safe_file_part(name: str) -> str:
    """``name`` reduced to [A-Za-z0-9_.-] (others → '_') for use in a file name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "_"


def stage_plot_name(stage: str) -> str:
    return f"error_vs_time_{safe_file_part(stage)}.png"


def timeline_plot_name(stage: str) -> str:
    return f"timeline_{safe_file_part(stage)}.png"


def _short_budget(entry: Mapping[str, Any]) -> str:
    return "∞" if entry["budget"] == "unbounded" else entry["budget"].replace(" ", "")


def _save(fig: Figure, path: Path) -> None:
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=PLOT_DPI, metadata={"Software": None})


def plot_error_vs_time(
    summary: list[Mapping[str, Any]], path: Path, title: str | None = None
) -> None:
    """Mean FLIP (vs ``all``) against mean frame ms, for every stage in ``summary``.

    One line per heuristic per stage through its budgets (each point annotated with its
    budget; colour = heuristic, line style = stage, hollow markers for every stage but
    the first); ray budgets are a separate line with triangles (a different family of
    points). ``all``, ``raster`` and ``rt`` are single points with their own markers. The
    time axis is logarithmic when it spans more than ``LOG_X_RATIO``. 800 x 500 px PNG.
    """
    fig = Figure(figsize=PLOT_SIZE_INCHES, dpi=PLOT_DPI)
    ax = fig.add_subplot()
    stages = stages_of(summary)
    times = []
    for stage_index, stage in enumerate(stages):
        linestyle = STAGE_LINESTYLES[stage_index % len(STAGE_LINESTYLES)]
        # The first stage's markers are filled, the others' hollow.
        filled = stage_index == 0
        prefix = f"{stage} " if len(stages) > 1 else ""
        entries = [e for e in summary if e["stage"] == stage and e["mean_flip"] is not None]
        lines: dict[tuple[str, bool], list[Mapping[str, Any]]] = {}
        for entry in entries:
            times.append(entry["mean_frame_ms"])
            if entry["kind"] == "heuristic":
                by_rays = _budget_sort_key(entry)[0] == 1
                lines.setdefault((entry["heuristic"], by_rays), []).append(entry)
        for (heuristic, by_rays), points in lines.items():
            points = sorted(points, key=lambda e: e["mean_frame_ms"])
            colour = HEURISTIC_COLOURS.get(heuristic, OTHER_HEURISTIC_COLOUR)
            label = f"{prefix}{heuristic.upper()}" + (" (ray budgets)" if by_rays else "")
            xs = [e["mean_frame_ms"] for e in points]
            ys = [e["mean_flip"] for e in points]
            ax.plot(
                xs,
                ys,
                linestyle=linestyle,
                marker="^" if by_rays else "o",
                markersize=5,
                color=colour,
                markerfacecolor=colour if filled else "white",
                label=label,
            )
            for entry, x, y in zip(points, xs, ys, strict=True):
                ax.annotate(
                    _short_budget(entry),
                    (x, y),
                    textcoords="offset points",
                    xytext=(4, 3),
                    fontsize=6,
                    color=colour,
                )
        for kind, marker, colour, name in BASELINE_MARKERS:
            points = [e for e in entries if e["kind"] == kind]
            if points:
                ax.scatter(
                    [e["mean_frame_ms"] for e in points],
                    [e["mean_flip"] for e in points],
                    marker=marker,
                    s=90 if marker == "*" else 40,
                    facecolors=colour if filled else "white",
                    edgecolors=colour,
                    label=f"{prefix}{name}",
                    zorder=3,
                )
    if times:
        low = max(min(times), MIN_LOG_MS)
        if max(times) / low > LOG_X_RATIO:
            ax.set_xscale("log")
    ax.margins(x=0.08)  # room for the budget labels right of the last points
    ax.set_xlabel("mean frame time (ms)")
    ax.set_ylabel("mean FLIP vs all (lower is better)")
    # Start just below 0 so the reference (FLIP 0 against itself) is not hidden by the axis.
    top = max(ax.get_ylim()[1], 1e-6)
    ax.set_ylim(-Y_MARGIN_FRACTION * top, top)
    ax.set_title(title or "Error against run time", fontsize=10)
    ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
    if ax.get_legend_handles_labels()[0]:
        # Outside the axes, so that it never hides a point.
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    _save(fig, path)


def timeline_states(selected: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Cell states (index into TIMELINE_STATES) from (frames, reflectors) bool arrays.

    Returns (reflectors, frames) int8: 0 not visible, 1 raster, 2 traced, 3 traced while
    not visible.
    """
    states = np.where(visible, np.where(selected, 2, 1), np.where(selected, 3, 0))
    return states.T.astype(np.int8)


def _timeline_arrays(
    stage: str, config: str, data: Any
) -> tuple[list[str], list, np.ndarray, np.ndarray]:
    """(reflector paths, frame times, selected, visible) of one config in timeline.json;
    selected / visible are (frames, reflectors) bool. PhrtError if the shapes disagree."""
    where = f"timeline.json stage {stage!r} config {config!r}"
    if not isinstance(data, dict):
        raise PhrtError(f"{where}: expected an object")
    reflectors = data.get("reflectors", [])
    frames = data.get("frames", [])
    shape = (len(frames), len(reflectors))
    arrays = []
    for key in ("selected", "visible"):
        try:
            values = np.asarray(data.get(key, []), dtype=bool).reshape(shape)
        except ValueError as error:
            raise PhrtError(
                f"{where}: {key} is not {shape[0]} frames x {shape[1]} reflectors"
            ) from error
        arrays.append(values)
    return [str(r) for r in reflectors], list(frames), arrays[0], arrays[1]


def plot_selection_timeline(
    stage: str, configs: Mapping[str, Any], path: Path, order: list[str] | None = None
) -> None:
    """Which reflector was ray-traced in which frame, every config of one stage in one image.

    configs : timeline.json's object for one stage, {config: {"reflectors", "frames",
              "selected", "visible"}}; every config must list the same frames. Blocks
              follow ``order`` (configs not in it last), top to bottom.
    One block of rows per config (its name on the right), one row per reflector (prim
    name on the left while rows are tall enough to read), one column per frame.
    """
    order = order or []
    names = [c for c in order if c in configs] + [c for c in configs if c not in order]
    blocks = []
    for name in names:
        reflectors, frame_times, selected, visible = _timeline_arrays(stage, name, configs[name])
        blocks.append((name, reflectors, frame_times, timeline_states(selected, visible)))
    blocks = [b for b in blocks if b[3].size > 0]
    if not blocks:
        raise PhrtError(f"timeline.json stage {stage!r}: no frames or reflectors to draw")
    frames = [float(t) for t in blocks[0][2]]
    for name, _reflectors, other, _states in blocks:
        if [float(t) for t in other] != frames:
            raise PhrtError(
                f"timeline.json stage {stage!r} config {name!r}: frames differ from "
                f"config {blocks[0][0]!r}"
            )

    # Stack the blocks with one empty (masked) row between them.
    rows, labels, block_centres = [], [], []
    for name, reflectors, _frames, states in blocks:
        if rows:
            rows.append(np.full((1, len(frames)), -1, dtype=np.int8))
            labels.append("")
        start = sum(len(r) for r in rows)
        rows.append(states)
        labels += [r.rsplit("/", 1)[-1] for r in reflectors]
        block_centres.append((start + 0.5 * (len(reflectors) - 1), name))
    grid = np.concatenate(rows, axis=0)
    image = np.ma.masked_less(grid, 0)

    row_inches = min(TIMELINE_ROW_INCHES, TIMELINE_MAX_GRID_INCHES / len(grid))
    height = len(grid) * row_inches + TIMELINE_MARGIN_INCHES[0] + TIMELINE_MARGIN_INCHES[1]
    fig = Figure(figsize=(TIMELINE_WIDTH_INCHES, height), dpi=PLOT_DPI)
    ax = fig.add_axes(
        (
            TIMELINE_SIDE_INCHES[0] / TIMELINE_WIDTH_INCHES,
            TIMELINE_MARGIN_INCHES[1] / height,
            1.0 - sum(TIMELINE_SIDE_INCHES) / TIMELINE_WIDTH_INCHES,
            len(grid) * row_inches / height,
        )
    )
    # Masked cells (the gap rows between configs) are white.
    cmap = ListedColormap([colour for _name, colour in TIMELINE_STATES], bad="white")
    norm = BoundaryNorm(np.arange(len(TIMELINE_STATES) + 1) - 0.5, cmap.N)
    ax.imshow(image, aspect="auto", interpolation="nearest", cmap=cmap, norm=norm)
    label_points = row_inches * 72.0 * TIMELINE_LABEL_FILL
    if label_points >= TIMELINE_MIN_LABEL_POINTS:
        ax.set_yticks(range(len(grid)), labels, fontsize=min(label_points, 7.0))
    else:
        ax.set_yticks([])
        ax.set_ylabel("reflectors", fontsize=7)
    for centre, name in block_centres:
        ax.text(1.01, centre, name, transform=ax.get_yaxis_transform(), fontsize=7, va="center")
    step = max(1, len(frames) // TIMELINE_MAX_XTICKS)
    ticks = list(range(0, len(frames), step))
    ax.set_xticks(ticks, [f"{frames[i]:g}" for i in ticks], fontsize=6)
    ax.set_xlabel("time code", fontsize=7)
    ax.set_title(f"Selection timeline: {stage}", fontsize=9)
    handles = [_legend_patch(colour, name) for name, colour in TIMELINE_STATES]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    _save(fig, path)


def _legend_patch(colour: str, label: str) -> Patch:
    return Patch(facecolor=colour, edgecolor="gray", label=label)


# --- report.html -----------------------------------------------------------------------

_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1400px; }
h1 { font-size: 1.4em; } h2 { font-size: 1.2em; margin-top: 1.6em; }
h3 { font-size: 1.0em; }
table { border-collapse: collapse; font-size: 0.8em; margin: 0.5em 0; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; }
td:nth-child(-n+3), th:nth-child(-n+3) { text-align: left; }
p.note { font-size: 0.85em; color: #555; max-width: 60em; }
div.frame { display: flex; flex-wrap: wrap; gap: 6px 28px; }
div.row { display: flex; gap: 6px; margin-bottom: 8px; }
figure { margin: 0; }
figure img { width: 190px; image-rendering: pixelated; border: 1px solid #ccc; }
figcaption { font-size: 0.7em; max-width: 190px; }
img.plot { max-width: 100%; }
"""


def _esc(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _src(out_dir: Path, path: Path) -> str:
    """Relative, URL-quoted reference to ``path`` from report.html in ``out_dir``."""
    return _esc(quote(path.relative_to(out_dir).as_posix()))


def _html_table(entries: list[Mapping[str, Any]]) -> str:
    head = "".join(f"<th>{_esc(h)}</th>" for h, _k, _f in TABLE_COLUMNS)
    body = "".join(
        "<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in table_cells(e)) + "</tr>" for e in entries
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _frame_dirs(stage_dir: Path) -> list[Path]:
    def key(path: Path) -> tuple:
        try:
            return (0, float(path.name), path.name)
        except ValueError:
            return (1, 0.0, path.name)

    dirs = (p for p in stage_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    return sorted(dirs, key=key)


def _frame_row(
    rows: list[Mapping[str, Any]], stage: str, config: str, frame_dir: str
) -> Mapping[str, Any] | None:
    """The CSV row of this stage/config at the frame named by an image directory."""
    try:
        time = float(frame_dir)
    except ValueError:
        time = None
    for row in rows:
        if row["stage"] != stage or row["config"] != config:
            continue
        if str(row["frame"]) == frame_dir:
            return row
        try:
            if time is not None and abs(float(row["frame"]) - time) < 1e-3:
                return row
        except ValueError:
            continue
    return None


def _figure(out_dir: Path, path: Path, caption: str) -> str:
    return (
        f'<figure><img src="{_src(out_dir, path)}" alt="{_esc(caption)}">'
        f"<figcaption>{_esc(caption)}</figcaption></figure>"
    )


def _images_section(
    out_dir: Path, stage: str, order: list[str], rows: list[Mapping[str, Any]]
) -> list[str]:
    stage_dir = out_dir / IMAGES_DIR / stage
    if not stage_dir.is_dir():
        return []
    parts = []
    for frame_dir in _frame_dirs(stage_dir):
        # Hidden files are temp files of interrupted atomic writes.
        pngs = {p.stem: p for p in frame_dir.glob("*.png") if not p.name.startswith(".")}
        reference = pngs.get(REFERENCE_CONFIG)
        configs = [
            name for name in pngs if not name.endswith(FLIP_MAP_SUFFIX) and name != REFERENCE_CONFIG
        ]
        configs.sort(key=lambda c: (order.index(c) if c in order else len(order), c))
        parts.append(f"<h3>{_esc(stage)}, frame {_esc(frame_dir.name)}</h3>")
        parts.append('<div class="frame">')
        for config in configs:
            row = _frame_row(rows, stage, config, frame_dir.name)
            figures_text = ""
            if row is not None:
                flip = _significant3(_number(row, "flip"))
                psnr = _fixed(2)(_number(row, "psnr"))
                figures_text = f", FLIP {flip}, PSNR {psnr} dB vs all"
            cells = [_figure(out_dir, pngs[config], f"{config}{figures_text}")]
            if reference is not None:
                cells.append(_figure(out_dir, reference, "reference: all reflectors traced"))
            flip_map = pngs.get(config + FLIP_MAP_SUFFIX)
            if flip_map is not None:
                cells.append(
                    _figure(
                        out_dir,
                        flip_map,
                        f"FLIP error of {config} vs all (magma: black = 0, yellow = 1)",
                    )
                )
            parts.append('<div class="row">' + "".join(cells) + "</div>")
        if not configs and reference is not None:
            parts.append(
                '<div class="row">'
                + _figure(out_dir, reference, "reference: all reflectors traced")
                + "</div>"
            )
        parts.append("</div>")
    return parts


def write_report_html(
    out_dir: Path,
    summary: list[Mapping[str, Any]],
    paper: Mapping[str, Mapping[str, float]] | None = None,
    rows: list[Mapping[str, Any]] | None = None,
) -> None:
    """Write OUT/report.html: one static page (inline CSS, no scripts, no external URLs).

    Shows the error-vs-time plot(s), one table per stage with the paper comparison, the
    selection timeline PNG per stage, and per chosen frame each config's image beside the
    reference and its FLIP map. Only files that exist in ``out_dir`` are referenced
    (relative paths); the plots and timelines must be written first.
    rows : sweep.csv rows, for per-image FLIP/PSNR captions (optional).
    """
    out_dir = Path(out_dir)
    paper = PAPER_FIGURES if paper is None else paper
    rows = rows or []
    stages = stages_of(summary)
    order_by_stage = {s: [e["config"] for e in summary if e["stage"] == s] for s in stages}
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>phrt sweep: error against run time</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>phrt sweep: error against run time</h1>",
        f'<p class="note">{_esc(DEFINITIONS)}</p>',
    ]
    plot = out_dir / ERROR_VS_TIME_PNG
    if plot.is_file():
        parts.append(
            f'<img class="plot" src="{_src(out_dir, plot)}" '
            'alt="mean FLIP against mean frame time">'
        )
    for stage in stages:
        entries = [e for e in summary if e["stage"] == stage]
        parts.append(f"<h2>Stage {_esc(stage)}</h2>")
        stage_plot = out_dir / stage_plot_name(stage)
        if len(stages) > 1 and stage_plot.is_file():
            parts.append(
                f'<img class="plot" src="{_src(out_dir, stage_plot)}" '
                f'alt="{_esc(f"mean FLIP against mean frame time, {stage}")}">'
            )
        parts.append(_html_table(entries))
        notes = [
            *stage_notes(summary, stage),
            *paper_comparison(summary, stage, paper),
            *equal_time_comparison(summary, stage),
        ]
        parts += [f'<p class="note">{_esc(line)}</p>' for line in notes]
        timeline = out_dir / timeline_plot_name(stage)
        if timeline.is_file():
            parts.append(f"<h3>Selection timeline, {_esc(stage)}</h3>")
            parts.append(
                f'<img class="plot" src="{_src(out_dir, timeline)}" '
                f'alt="{_esc(f"selection timeline of {stage}")}">'
            )
        parts += _images_section(out_dir, stage, order_by_stage[stage], rows)
    parts.append("</body></html>")
    write_text_atomic(out_dir / REPORT_HTML, "\n".join(parts) + "\n")


# --- all of it -------------------------------------------------------------------------


def read_timeline(path: Path) -> dict[str, Any]:
    """timeline.json as {stage: {config: {...}}}; {} if the file is absent."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        timeline = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise PhrtError(f"{path}: cannot read ({error})") from error
    if not isinstance(timeline, dict):
        raise PhrtError(f"{path}: expected an object {{stage: {{config: ...}}}}")
    return timeline


def write_sweep_report(out_dir: Path) -> None:
    """Read the sweep's outputs in ``out_dir`` and write every human-readable output."""
    out_dir = Path(out_dir)
    rows = read_sweep_csv(out_dir / SWEEP_CSV)
    timeline = read_timeline(out_dir / TIMELINE_JSON)
    summary = summarize(rows, timeline)
    paper = load_paper_figures(out_dir)
    write_summary_md(summary, out_dir / SUMMARY_MD, paper)

    stages = stages_of(summary)
    plot_error_vs_time(summary, out_dir / ERROR_VS_TIME_PNG)
    if len(stages) > 1:
        for stage in stages:
            entries = [e for e in summary if e["stage"] == stage]
            plot_error_vs_time(
                entries, out_dir / stage_plot_name(stage), title=f"Error against run time: {stage}"
            )

    for stage, configs in timeline.items():
        if isinstance(configs, dict) and configs:
            order = [e["config"] for e in summary if e["stage"] == stage]
            plot_selection_timeline(stage, configs, out_dir / timeline_plot_name(stage), order)
    # A timeline PNG left by an earlier sweep must not appear in this report.
    for stage in stages:
        if not timeline.get(stage):
            (out_dir / timeline_plot_name(stage)).unlink(missing_ok=True)

    write_report_html(out_dir, summary, paper, rows)
