"""The sweep's summary as text for people: table columns and cells, the notes under each
stage's tables (budget adherence, the paper's figures, the equal-time comparison) and
summary.md. ``sweep_html`` shows the same tables and notes in report.html.

Inputs are ``sweep_summary.summarize``'s entries; every figure is formatted here, so the
markdown and the HTML tables agree cell for cell.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from phrt_usd.atomic import write_text_atomic
from phrt_usd.evaluate.provenance import provenance_items
from phrt_usd.evaluate.report import OVERRUN_FACTOR
from phrt_usd.evaluate.sweep_summary import (
    BUDGET_TARGET,
    MISSING,
    PAPER_FIGURES,
    PARETO_MARK,
    stages_of,
)

#: How the tables' figures are defined; heads summary.md and report.html.
DEFINITIONS = (
    "FLIP and PSNR are measured against the `all` reference (every reflector ray-traced; "
    "PSNR 100 dB = identical). Mean, median, p5 and p95 are over the config's frames "
    "(p5 / p95: the 5th / 95th percentile). Mean fps = 1000 / mean frame ms. Within "
    "budget: the share of frames whose trace phase took at most the time budget T + 10 % "
    "(for a rays budget: whose traced rays are within it; n/a without a budget). "
    "Transition rate = "
    "transitions / chances to switch (reflector visible in two consecutive frames). "
    "Temporal error: each sequence's previous frame warped to the current one by exact "
    "motion vectors (occluded pixels masked) and compared with FLIP; the config's warped "
    "error beyond the reference's own, per pixel (0 = no change the reference does not "
    "make; popping between raster and ray tracing scores high; docs/temporal-error.md). "
    "Pareto: not beaten on all of frame time, FLIP and "
    "temporal error by another config of the same stage and variant (resolution, bounce "
    "limit, trace density), whose reference the errors are measured against (the "
    "references trace every pixel at any trace density)."
)


# --- number formatting (shared by the markdown and the HTML tables) ---------------------


def format_fixed(digits: int):
    def fmt(value: float | None) -> str:
        return MISSING if value is None else f"{value:.{digits}f}"

    return fmt


def format_significant3(value: float | None) -> str:
    """3 significant digits: 0.0123, 0.123, 1.23 (FLIP is in [0, 1], often ≪ 1)."""
    return MISSING if value is None else f"{value:.3g}"


def format_percent(value: float | None) -> str:
    return MISSING if value is None else f"{100.0 * value:.2f} %"


def format_pareto(value: bool) -> str:
    return PARETO_MARK if value else ""


def format_optional(value: Any) -> str:
    return MISSING if value is None or value == "" else str(value)


def format_share(value: float | None) -> str:
    """A share of frames: ``97.5 %``; ``n/a`` where it does not apply (no budget)."""
    return "n/a" if value is None else f"{100.0 * value:.1f} %"


#: (header, summary key, formatter) of a table column.
Column = tuple[str, str, Any]

#: Every table starts with the config: what its row is.
CONFIG_COLUMN: Column = ("config", "config", str)

#: The tables of a stage, each (title, columns), config first: narrow enough to read on
#: a laptop screen (report.html is checked at 1280 px), instead of one wide table.
TABLES: tuple[tuple[str, tuple[Column, ...]], ...] = (
    ("Frame time and budget", (
        CONFIG_COLUMN,
        ("budget", "budget", str),
        ("frames", "frames", str),
        ("mean frame ms", "mean_frame_ms", format_fixed(2)),
        ("median frame ms", "median_frame_ms", format_fixed(2)),
        ("p5 frame ms", "p5_frame_ms", format_fixed(2)),
        ("p95 frame ms", "p95_frame_ms", format_fixed(2)),
        ("mean fps", "mean_fps", format_fixed(1)),
        ("mean trace ms", "mean_trace_ms", format_fixed(2)),
        ("p95 trace ms", "p95_trace_ms", format_fixed(2)),
        ("within budget", "budget_within", format_share),
        ("mean rays", "mean_rays", format_fixed(0)),
    )),
    ("Error against the reference: FLIP and PSNR", (
        CONFIG_COLUMN,
        ("mean FLIP", "mean_flip", format_significant3),
        ("median FLIP", "median_flip", format_significant3),
        ("p5 FLIP", "p5_flip", format_significant3),
        ("p95 FLIP", "p95_flip", format_significant3),
        ("mean FLIP reflectors", "mean_flip_reflectors", format_significant3),
        ("mean PSNR dB", "mean_psnr", format_fixed(2)),
        ("Pareto", "pareto", format_pareto),
    )),
    ("Error against the reference: temporal error", (
        CONFIG_COLUMN,
        ("mean temporal error", "mean_temporal_error", format_significant3),
        ("median temporal error", "median_temporal_error", format_significant3),
        ("p5 temporal error", "p5_temporal_error", format_significant3),
        ("p95 temporal error", "p95_temporal_error", format_significant3),
        ("mean temporal error reflectors", "mean_temporal_error_reflectors",
         format_significant3),
    )),
    ("Selection and variant", (
        CONFIG_COLUMN,
        ("heuristic", "heuristic", str),
        ("resolution", "resolution", format_optional),
        ("bounce limit", "bounce_limit", format_optional),
        ("trace density", "trace_density", format_optional),
        ("mean selected", "mean_selected", format_fixed(2)),
        ("transitions", "transitions", str),
        ("transition rate", "transition_rate", format_percent),
        ("density steps", "density_steps", str),
    )),
)  # fmt: skip


def table_cells(entry: Mapping[str, Any], columns: Iterable[Column]) -> list[str]:
    """The formatted cells of one summary entry, in the order of ``columns``."""
    return [fmt(entry[key]) for _header, key, fmt in columns]


def budget_notes(summary: list[Mapping[str, Any]], stage: str) -> list[str]:
    """How each budgeted config of a stage held its budget: the configs whose trace phase
    stayed within T + 10 % in fewer than ``BUDGET_TARGET`` of their frames are named with
    their share, the limit and their mean and p95 trace time; then those that held it;
    then the rays budgets' shares."""
    entries = [e for e in summary if e["stage"] == stage and e.get("budget_checked")]
    lines = []
    timed = [e for e in entries if e["budget_checked"] == "time"]
    missed = [e for e in timed if (e["budget_within"] or 0.0) < BUDGET_TARGET]
    held = [e for e in timed if e not in missed]
    target = f"{100.0 * BUDGET_TARGET:g} %"
    if missed:
        parts = [
            f"{e['config']} within {e['budget_ms'] * OVERRUN_FACTOR:.3g} ms in "
            f"{format_share(e['budget_within'])} of frames (mean trace "
            f"{format_fixed(2)(e['mean_trace_ms'])} ms, p95 {format_fixed(2)(e['p95_trace_ms'])}"
            " ms)"
            for e in missed
        ]
        lines.append(
            f"Time budget NOT held (trace phase within T + 10 % in fewer than {target} of "
            "frames): " + "; ".join(parts) + "."
        )
    if held:
        lines.append(
            f"Time budget held (trace phase within T + 10 % in at least {target} of frames): "
            + ", ".join(f"{e['config']} ({format_share(e['budget_within'])})" for e in held)
            + "."
        )
    rays = [e for e in entries if e["budget_checked"] == "rays"]
    if rays:
        lines.append(
            "Rays budget (traced rays within the budget): "
            + ", ".join(f"{e['config']} {format_share(e['budget_within'])} of frames" for e in rays)
            + "."
        )
    return lines


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

    Ours are given at every budget (and variant) where both HEU1 and HEU2 were run; the
    transitions ratio is HEU1's transitions over HEU2's (as in the paper).
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
    several = len(variants_of(summary, stage)) > 1
    by_budget: dict[tuple[str, str], dict[str, Mapping[str, Any]]] = {}
    for entry in summary:
        if entry["stage"] == stage and entry["heuristic"] in ("heu1", "heu2"):
            key = (entry.get("variant", ""), entry["budget"])
            by_budget.setdefault(key, {})[entry["heuristic"]] = entry
    for (variant, budget), pair in by_budget.items():
        if len(pair) != 2:
            continue
        heu1, heu2 = pair["heu1"], pair["heu2"]
        ratio = heu1["transitions"] / heu2["transitions"] if heu2["transitions"] else None
        where = f"{budget}, {variant}" if several else budget
        lines.append(
            f"This sweep at budget {where}: fps HEU1 {format_fixed(1)(heu1['mean_fps'])} / "
            f"HEU2 {format_fixed(1)(heu2['mean_fps'])}; transitions HEU1/HEU2 "
            f"{format_percent(ratio)} ({heu1['transitions']} / {heu2['transitions']}); "
            f"mean selected HEU1 {format_fixed(2)(heu1['mean_selected'])} / "
            f"HEU2 {format_fixed(2)(heu2['mean_selected'])}."
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


#: The errors HEU1 and HEU2 are compared on at equal cost: (summary key, its name).
COMPARISON_ERRORS = (
    ("mean_flip", "mean FLIP"),
    ("mean_temporal_error", "temporal error"),
)


def variants_of(summary: list[Mapping[str, Any]], stage: str) -> list[str]:
    """The variants (``variant`` labels) of one stage in summary order; [""] for entries
    without one."""
    return list(dict.fromkeys(e.get("variant", "") for e in summary if e["stage"] == stage))


def equal_time_comparison(summary: list[Mapping[str, Any]], stage: str) -> list[str]:
    """Lines comparing HEU1 and HEU2 at equal cost, per variant of the stage, per budget
    kind (ms or rays budgets), per axis of ``COMPARISON_AXES`` (rays only for rays
    budgets) and per error of ``COMPARISON_ERRORS`` (when every point has it): for each
    HEU1 point with some budget, HEU2's frontier error at HEU1's cost
    (``frontier_flip_at``), and the verdict. Lines of a stage with several variants start
    with the variant in brackets."""
    variants = variants_of(summary, stage)
    lines = []
    for variant in variants:
        prefix = f"[{variant}] " if len(variants) > 1 else ""
        entries = [
            e for e in summary if e["stage"] == stage and e.get("variant", "") == variant
        ]
        lines += [prefix + line for line in _equal_cost_lines(entries)]
    return lines


def _equal_cost_lines(entries: list[Mapping[str, Any]]) -> list[str]:
    """``equal_time_comparison``'s lines for the entries of one stage and variant."""
    lines = []

    def bounded(value: float | None) -> bool:
        return value is not None and math.isfinite(value)

    for kind, field in (("ms", "budget_ms"), ("rays", "budget_rays")):
        for error, error_name in COMPARISON_ERRORS:
            # Each curve: this kind's budgets plus the unbounded point (no budget at all).
            curves: dict[str, list[Mapping[str, Any]]] = {"heu1": [], "heu2": []}
            for e in entries:
                if e["heuristic"] not in curves or e.get(error) is None:
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
                heu2 = [(e[axis], e[error]) for e in curves["heu2"]]
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
                    wins += e[error] <= other
                    cost = f"{e[axis]:.2f} ms" if unit == "ms" else f"{e[axis]:.0f} rays"
                    parts.append(
                        f"{e['budget']}: {format_significant3(e[error])} at {cost} "
                        f"vs HEU2 {format_significant3(other)}"
                    )
                if parts:
                    lines.append(
                        f"Equal {name} ({kind} budgets; HEU2 interpolated on its error-"
                        f"{unit} frontier): HEU1 {error_name} <= HEU2 at {wins} of "
                        f"{compared}. " + "; ".join(parts) + "."
                    )
    return lines


# --- summary.md ------------------------------------------------------------------------


def _md_cell(text: str) -> str:
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")


def stage_note_lines(
    summary: list[Mapping[str, Any]], stage: str, paper: Mapping[str, Mapping[str, float]]
) -> list[str]:
    """Every note under a stage's tables, in order: caveats, budget adherence, the paper's
    figures beside ours, the equal-time comparison."""
    return [
        *stage_notes(summary, stage),
        *budget_notes(summary, stage),
        *paper_comparison(summary, stage, paper),
        *equal_time_comparison(summary, stage),
    ]


#: Said where a sweep directory has no provenance.json (written by an older phrt).
NO_PROVENANCE = "not recorded (this sweep directory has no provenance.json)"


def write_summary_md(
    summary: list[Mapping[str, Any]],
    path: Path,
    paper: Mapping[str, Mapping[str, float]] | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> None:
    """Write summary.md: the definitions, the provenance (``provenance.json``), then per
    stage a heading, the ``TABLES`` and the notes (``stage_note_lines``)."""
    paper = PAPER_FIGURES if paper is None else paper
    lines = ["# phrt sweep: error against run time", "", DEFINITIONS, "", "## Provenance", ""]
    if provenance:
        lines += [f"- {label}: {_md_cell(text)}" for label, text in provenance_items(provenance)]
    else:
        lines.append(f"- {NO_PROVENANCE}")
    lines.append("")
    for stage in stages_of(summary):
        lines += [f"## Stage {_md_cell(stage)}", ""]
        entries = [e for e in summary if e["stage"] == stage]
        for title, columns in TABLES:
            lines += [f"### {title}", ""]
            lines.append("| " + " | ".join(h for h, _k, _f in columns) + " |")
            lines.append("|" + "|".join("---" for _ in columns) + "|")
            for entry in entries:
                cells = table_cells(entry, columns)
                lines.append("| " + " | ".join(_md_cell(c) for c in cells) + " |")
            lines.append("")
        lines += [_md_cell(line) + "  " for line in stage_note_lines(summary, stage, paper)]
        lines.append("")
    write_text_atomic(Path(path), "\n".join(lines))


