"""Figures of a sweep (matplotlib, PNG): error against frame time, selection timelines.

    OUT/error_vs_time.png            mean FLIP, temporal error and transition rate against
                                     mean frame time, every stage; Pareto front ringed
    OUT/error_vs_time_<stage>.png    the same per stage (only with more than one stage)
    OUT/timeline_<stage>.png         which reflector was traced in which frame, per config

Inputs are ``sweep_summary.summarize``'s entries and timeline.json's per-stage object.
Every PNG is written through ``atomic_path`` (a reader never sees a partial image).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from phrt_usd.atomic import atomic_path
from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.sweep_summary import budget_sort_key, timeline_arrays

# --- plot layout -----------------------------------------------------------------------

#: error_vs_time.png: 9 x 10 inches at 100 dpi = 900 x 1000 pixels (three panels).
PLOT_SIZE_INCHES = (9.0, 10.0)
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


# --- plots -----------------------------------------------------------------------------


def _short_budget(entry: Mapping[str, Any]) -> str:
    return "∞" if entry["budget"] == "unbounded" else entry["budget"].replace(" ", "")


def _save(fig: Figure, path: Path) -> None:
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=PLOT_DPI, metadata={"Software": None})


#: The panels of error_vs_time.png, top to bottom: (summary key, y label, scale).
ERROR_PANELS = (
    ("mean_flip", "mean FLIP vs reference\n(per frame, lower is better)", 1.0),
    ("mean_temporal_error", "mean temporal error\n(popping, lower is better)", 1.0),
    ("transition_rate", "transition rate (%)", 100.0),
)
#: Ring drawn around the configurations on the Pareto front (points squared).
PARETO_RING_SIZE = 170


def _series(summary: list[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """(stage, variant) pairs in summary order: one family of lines and points each."""
    return list(dict.fromkeys((e["stage"], e.get("variant", "")) for e in summary))


def plot_error_vs_time(
    summary: list[Mapping[str, Any]], path: Path, title: str | None = None
) -> None:
    """Three panels against mean frame ms, one x axis: mean FLIP (vs the reference), mean
    temporal error (``temporal_error.popping_map``) and the transition rate, for
    every stage and variant in ``summary``.

    One line per heuristic per (stage, variant) through its budgets (each point annotated
    with its budget in the FLIP panel; colour = heuristic, line style = (stage, variant),
    hollow markers for every series but the first); ray budgets are a separate line with
    triangles (a different family of points). ``all``, ``raster`` and ``rt`` are single
    points with their own markers. Configurations on the Pareto front of (frame time,
    FLIP, temporal error) (``sweep_summary.mark_pareto``) are ringed in black in every
    panel. The time axis is logarithmic when it spans more than ``LOG_X_RATIO``.
    ``PLOT_SIZE_INCHES`` at ``PLOT_DPI``.
    """
    fig = Figure(figsize=PLOT_SIZE_INCHES, dpi=PLOT_DPI)
    axes = fig.subplots(len(ERROR_PANELS), 1, sharex=True)
    series = _series(summary)
    times = [e["mean_frame_ms"] for e in summary if e["mean_frame_ms"] is not None]
    for ax, (key, ylabel, scale) in zip(axes, ERROR_PANELS, strict=True):
        annotate = key == ERROR_PANELS[0][0]
        for index, (stage, variant) in enumerate(series):
            entries = [
                e
                for e in summary
                if e["stage"] == stage and e.get("variant", "") == variant and e[key] is not None
            ]
            name = " ".join(p for p in (stage if len(series) > 1 else "", variant) if p)
            _plot_series(ax, entries, key, scale, index, f"{name} " if name else "", annotate)
        ringed = [e for e in summary if e.get("pareto") and e[key] is not None]
        if ringed:
            ax.scatter(
                [e["mean_frame_ms"] for e in ringed],
                [scale * e[key] for e in ringed],
                s=PARETO_RING_SIZE,
                facecolors="none",
                edgecolors="black",
                linewidths=1.0,
                label="Pareto front (time, FLIP, temporal)" if annotate else None,
                zorder=4,
            )
        ax.set_ylabel(ylabel, fontsize=8)
        # Start just below 0 so a zero error (the reference) is not hidden by the axis.
        top = max(ax.get_ylim()[1], 1e-6)
        ax.set_ylim(-Y_MARGIN_FRACTION * top, top)
        ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
    if times:
        low = max(min(times), MIN_LOG_MS)
        if max(times) / low > LOG_X_RATIO:
            axes[0].set_xscale("log")
    axes[0].margins(x=0.08)  # room for the budget labels right of the last points
    axes[-1].set_xlabel("mean frame time (ms)")
    axes[0].set_title(title or "Error against run time", fontsize=10)
    if axes[0].get_legend_handles_labels()[0]:
        # Outside the axes, so that it never hides a point.
        axes[0].legend(
            fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0
        )
    fig.tight_layout()
    _save(fig, path)


def _plot_series(ax, entries, key: str, scale: float, index: int, prefix: str, annotate: bool):
    """One (stage, variant)'s lines and baseline points of ``key`` on ``ax`` (see
    ``plot_error_vs_time``); ``index`` picks the line style, 0 fills the markers."""
    linestyle = STAGE_LINESTYLES[index % len(STAGE_LINESTYLES)]
    filled = index == 0
    lines: dict[tuple[str, bool], list[Mapping[str, Any]]] = {}
    for entry in entries:
        if entry["kind"] == "heuristic":
            by_rays = budget_sort_key(entry)[0] == 1
            lines.setdefault((entry["heuristic"], by_rays), []).append(entry)
    for (heuristic, by_rays), points in lines.items():
        points = sorted(points, key=lambda e: e["mean_frame_ms"])
        colour = HEURISTIC_COLOURS.get(heuristic, OTHER_HEURISTIC_COLOUR)
        label = f"{prefix}{heuristic.upper()}" + (" (ray budgets)" if by_rays else "")
        xs = [e["mean_frame_ms"] for e in points]
        ys = [scale * e[key] for e in points]
        ax.plot(
            xs,
            ys,
            linestyle=linestyle,
            marker="^" if by_rays else "o",
            markersize=5,
            color=colour,
            markerfacecolor=colour if filled else "white",
            label=label if annotate else None,
        )
        if annotate:
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
                [scale * e[key] for e in points],
                marker=marker,
                s=90 if marker == "*" else 40,
                facecolors=colour if filled else "white",
                edgecolors=colour,
                label=f"{prefix}{name}" if annotate else None,
                zorder=3,
            )


def timeline_states(selected: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Cell states (index into TIMELINE_STATES) from (frames, reflectors) bool arrays.

    Returns (reflectors, frames) int8: 0 not visible, 1 raster, 2 traced, 3 traced while
    not visible.
    """
    states = np.where(visible, np.where(selected, 2, 1), np.where(selected, 3, 0))
    return states.T.astype(np.int8)


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
        reflectors, frame_times, selected, visible = timeline_arrays(stage, name, configs[name])
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
