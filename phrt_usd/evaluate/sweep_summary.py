"""Sweep results as figures: reading sweep.csv, per-config summaries, summary.csv.

Reads what ``phrt sweep`` (``sweep.py``) wrote into its output directory ``OUT``::

    OUT/sweep.csv        one row per stage x config x frame (columns: see REQUIRED_COLUMNS)
    OUT/timeline.json    {stage: {config: {"reflectors": [paths], "frames": [times],
                                           "selected": [[bool]], "visible": [[bool]]}}}
    OUT/paper.json       optional: the paper's figures per stage (else PAPER_FIGURES)

``read_sweep_csv`` → ``summarize`` (one dict per stage x config, in display order) →
``write_summary_csv``; ``sweep_tables`` writes the same figures as text (summary.md,
and the tables and notes of report.html).

Definitions used in the tables (all means and percentiles are over the config's frames):

- *spread* = the mean, median, 5th and 95th percentile (``numpy.percentile``, linear
  interpolation) of frame time, trace time, FLIP and temporal error (``SPREAD_COLUMNS``).
- *budget adherence* = the share of a config's frames whose trace phase (``trace_ms``)
  is within its time budget T + 10 % (``report.OVERRUN_FACTOR``, the design's target);
  for a rays budget, the share whose traced rays are within it; None (n/a) without a
  budget (raster, references, unbounded).

- *mean fps* = 1000 / mean frame ms (frames per second of wall time over the whole path,
  not the mean of per-frame fps, which short frames would inflate).
- *transitions* = the sum of sweep.csv's per-frame ``transitions`` (counted by the sweep
  with ``selection_metrics``, whose module states the definition).
- *transition rate* = transitions / chances to switch, a chance being a reflector visible
  in two consecutive frames (``selection_metrics.transition_chances``, as in ``phrt
  report``), counted from timeline.json. Without a usable timeline (absent, or not the
  CSV's frame count) the chances are approximated from the CSV's per-frame visible counts
  after the first frame, which also counts reflectors that just entered the view; the
  summary says which was used.
- *temporal error* = mean over the config's frames (but its first: it has no previous
  one) of sweep.csv's ``temporal_error``: the mean over the pixels the warp keeps of
  ``temporal_error.popping_map``, the config's warped-frame error (its previous frame
  warped to the current one by exact motion vectors, compared with FLIP) beyond the
  reference's own (docs/temporal-error.md); 0 for a config whose frames equal the
  reference's and for a steady error that moves with the surfaces, more where a reflector
  pops between raster and traced.
- *variant* = the resolution and bounce limit of a config (``sweep.Variant``); errors are
  measured against the reference of the same variant, so comparisons (equal time, the
  Pareto front) stay within one stage and variant.
- *Pareto front* = the configs of one stage and variant that no other config of it beats
  on all of (mean frame ms, mean FLIP, mean temporal error) (``pareto_front``).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from phrt_usd.atomic import write_text_atomic
from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.report import OVERRUN_FACTOR
from phrt_usd.evaluate.selection_metrics import transition_chances
from phrt_usd.evaluate.sweep_files import PAPER_JSON

#: The paper's results (GTX 760, OptiX; docs/design.md §1), used when paper.json is absent.
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
    "temporal_error",
)
#: Columns read when present (sweeps of one variant before knob sweeps lack them).
OPTIONAL_COLUMNS = ("resolution", "bounce_limit", "trace_density", "temporal_error_reflectors")

#: sweep.csv columns summarised by their spread (``spread``): column → summary key stem
#: (``mean_<stem>``, ``median_<stem>``, ``p5_<stem>``, ``p95_<stem>``).
SPREAD_COLUMNS = {
    "frame_ms": "frame_ms",
    "trace_ms": "trace_ms",
    "flip": "flip",
    "temporal_error": "temporal_error",
}
#: The percentiles of a spread besides the median, and their key prefixes.
SPREAD_PERCENTILES = ((5.0, "p5"), (95.0, "p95"))
#: Design target of budget adherence: the trace phase within T + 10 % in this share of
#: frames (docs/design.md §3, "Budget"); a config below it is named under its table.
BUDGET_TARGET = 0.99

#: Display order of config kinds in tables and legends.
KIND_ORDER = {"raster": 0, "heuristic": 1, "reference": 2, "rt": 3}
#: Display order of heuristics at one budget; others follow alphabetically.
HEURISTIC_ORDER = {"heu1": 0, "heu2": 1}

MISSING = "—"

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
    data = _read_json_object(path, "{stage: {figure: number}}")
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


def csv_number(row: Mapping[str, Any], column: str, *, allow_inf: bool = False) -> float | None:
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


def spread(values: Iterable[float | None], stem: str) -> dict[str, float | None]:
    """``mean_<stem>``, ``median_<stem>``, ``p5_<stem>``, ``p95_<stem>`` of the values
    that are not None (all None when there are none)."""
    present = np.array([v for v in values if v is not None], dtype=np.float64)
    keys = [f"mean_{stem}", f"median_{stem}"] + [f"{p}_{stem}" for _q, p in SPREAD_PERCENTILES]
    if present.size == 0:
        return dict.fromkeys(keys)
    # The mean as a plain sum, as everywhere else in the summary (the same float).
    figures = [float(sum(present.tolist()) / present.size), float(np.median(present))]
    figures += [float(np.percentile(present, q)) for q, _p in SPREAD_PERCENTILES]
    return dict(zip(keys, figures, strict=True))


def budget_adherence(
    rows: list[Mapping[str, Any]], budget_ms: float | None, budget_rays: float | None
) -> tuple[float | None, str]:
    """(share of ``rows`` within the config's budget, what was checked): ``"time"`` for a
    finite ms budget (``trace_ms`` <= budget x ``OVERRUN_FACTOR``), ``"rays"`` for a finite
    rays budget (``rays`` <= budget), (None, ``""``) without a finite budget. A frame with
    an empty cell does not count as within."""
    if budget_ms is not None and math.isfinite(budget_ms):
        limit, column, kind = budget_ms * OVERRUN_FACTOR, "trace_ms", "time"
    elif budget_rays is not None and math.isfinite(budget_rays):
        limit, column, kind = budget_rays, "rays", "rays"
    else:
        return None, ""
    if not rows:
        return None, kind
    values = [csv_number(r, column) for r in rows]
    return sum(v is not None and v <= limit for v in values) / len(rows), kind


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


def budget_sort_key(entry: Mapping[str, Any]) -> tuple:
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
        budget_sort_key(entry) if entry["kind"] == "heuristic" else (0, 0.0, 0.0),
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
    mean_frame_ms, median_frame_ms, p5_frame_ms, p95_frame_ms, mean_fps, the same four
    of trace_ms, flip and temporal_error (``spread``), budget_within (share of frames
    within budget, ``budget_adherence``; None = n/a), budget_checked ("time" | "rays" |
    ""), mean_rays, mean_flip_reflectors, mean_psnr, transitions (sum, int),
    transition_chances (int),
    transition_rate (transitions / chances, None without chances), chances_from
    ("timeline" | "csv"), density_steps (sum, int: a traced reflector's trace density
    changed, not a transition; 0 without the column), mean_selected, mean_visible,
    mean_temporal_error_reflectors, resolution ("WxH" or ""),
    bounce_limit (int or None), trace_density (the variant's, one of TRACE_DENSITIES; ""
    without the column), variant (e.g. "320x240, bounce 2"; "" without those columns),
    pareto (bool, see ``mark_pareto``). Means skip empty cells and are None when every
    cell is empty.

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
            _reflectors, frames, _selected, visible = timeline_arrays(stage, config, data)
            if len(frames) == len(group):
                chances = int(np.count_nonzero(transition_chances(visible)))
        summary.append(_summarize_config(stage, config, group, chances))
    variant_order = {v: i for i, v in enumerate(dict.fromkeys(e["variant"] for e in summary))}
    summary.sort(
        key=lambda e: (stage_order[e["stage"]], variant_order[e["variant"]], _row_sort_key(e))
    )
    mark_pareto(summary)
    return summary


#: The objectives of the Pareto front (summary keys, all minimised).
PARETO_OBJECTIVES = ("mean_frame_ms", "mean_flip", "mean_temporal_error")

#: Table cell of a config on the Pareto front.
PARETO_MARK = "◆"


def pareto_front(points: list[tuple[float, ...]]) -> list[bool]:
    """Which of ``points`` (each a tuple of objectives, all minimised) are non-dominated:
    no other point is <= in every objective and < in at least one. Equal points are
    all kept. O(n^2), n = configs of one stage and variant."""
    array = np.asarray(points, dtype=np.float64).reshape(len(points), -1)
    keep = []
    for p in array:
        dominated = np.all(array <= p, axis=1) & np.any(array < p, axis=1)
        keep.append(not bool(dominated.any()))
    return keep


def mark_pareto(summary: list[dict[str, Any]]) -> None:
    """Set each entry's ``pareto``: on the Pareto front of ``PARETO_OBJECTIVES`` among the
    entries of its stage and variant. An objective some entry of the group lacks (e.g.
    the temporal error of a CSV without one) is left out for the whole group."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for entry in summary:
        groups.setdefault((entry["stage"], entry["variant"]), []).append(entry)
    for entries in groups.values():
        keys = [k for k in PARETO_OBJECTIVES if all(e[k] is not None for e in entries)]
        if not keys:
            for entry in entries:
                entry["pareto"] = False
            continue
        front = pareto_front([tuple(e[k] for k in keys) for e in entries])
        for entry, on_front in zip(entries, front, strict=True):
            entry["pareto"] = on_front


def variant_label(resolution: str, bounce_limit: int | None, trace_density: str = "") -> str:
    """'320x240, bounce 2, half density' (parts that are known; full density is not
    named), '' when none is."""
    parts = ([resolution] if resolution else []) + (
        [f"bounce {bounce_limit}"] if bounce_limit is not None else []
    )
    if trace_density and trace_density != "full":
        parts.append(f"{trace_density} density")
    return ", ".join(parts)


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
    budget_ms = csv_number(group[0], "budget_ms", allow_inf=True)
    budget_rays = csv_number(group[0], "budget_rays", allow_inf=True)
    resolution = ""
    bounce = None
    if "resolution" in group[0]:
        resolution = _constant(group, "resolution", stage, config)
    if "bounce_limit" in group[0]:
        _constant(group, "bounce_limit", stage, config)
        value = csv_number(group[0], "bounce_limit")
        bounce = None if value is None else int(value)
    density = ""
    if "trace_density" in group[0]:
        density = _constant(group, "trace_density", stage, config)

    ordered = sorted(group, key=lambda row: csv_number(row, "frame") or 0.0)
    frame_ms = [csv_number(r, "frame_ms") for r in ordered]
    if any(v is None for v in frame_ms):
        raise PhrtError(f"sweep.csv stage {stage!r} config {config!r}: empty frame_ms")
    mean_frame_ms = sum(frame_ms) / len(frame_ms)
    within, checked = budget_adherence(ordered, budget_ms, budget_rays)
    spreads: dict[str, float | None] = {}
    for column, stem in SPREAD_COLUMNS.items():
        spreads |= spread((csv_number(r, column) for r in ordered), stem)
    transitions = [csv_number(r, "transitions") or 0.0 for r in ordered]
    chances_from = "timeline"
    if chances is None:
        # Approximation: reflectors visible in every frame that has a predecessor.
        chances = int(round(sum(csv_number(r, "visible") or 0.0 for r in ordered[1:])))
        chances_from = "csv"
    total_transitions = int(round(sum(transitions)))
    # Absent from sweeps written before the column: 0.
    steps = int(round(sum(csv_number(r, "density_steps") or 0.0 for r in ordered)))
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
        **spreads,
        # A mean frame time of 0 ms (clock resolution) would give infinite fps.
        "mean_fps": 1000.0 / mean_frame_ms if mean_frame_ms > 0.0 else None,
        "budget_within": within,
        "budget_checked": checked,
        "mean_rays": _mean(csv_number(r, "rays") for r in ordered),
        "mean_flip_reflectors": _mean(csv_number(r, "flip_reflectors") for r in ordered),
        "mean_psnr": _mean(csv_number(r, "psnr") for r in ordered),
        "transitions": total_transitions,
        "transition_chances": chances,
        "transition_rate": total_transitions / chances if chances > 0 else None,
        "chances_from": chances_from,
        "density_steps": steps,
        "mean_selected": _mean(csv_number(r, "selected") for r in ordered),
        "mean_visible": _mean(csv_number(r, "visible") for r in ordered),
        "mean_temporal_error_reflectors": _mean(
            csv_number(r, "temporal_error_reflectors") for r in ordered
        ),
        "resolution": resolution,
        "bounce_limit": bounce,
        "trace_density": density,
        "variant": variant_label(resolution, bounce, density),
        "pareto": False,
    }


def stages_of(summary: list[Mapping[str, Any]]) -> list[str]:
    """Stage names in summary order."""
    return list(dict.fromkeys(e["stage"] for e in summary))


#: Columns of summary.csv: the summary entry's keys, numbers unrounded.
SUMMARY_CSV_KEYS = (
    "stage", "config", "heuristic", "mode", "kind", "budget", "budget_ms", "budget_rays",
    "resolution", "bounce_limit", "trace_density", "frames", "mean_frame_ms",
    "median_frame_ms", "p5_frame_ms", "p95_frame_ms", "mean_fps",
    "mean_trace_ms", "median_trace_ms", "p5_trace_ms", "p95_trace_ms", "budget_within",
    "budget_checked", "mean_rays",
    "mean_flip", "median_flip", "p5_flip", "p95_flip", "mean_flip_reflectors", "mean_psnr",
    "transitions", "transition_chances", "transition_rate", "chances_from", "density_steps",
    "mean_selected", "mean_visible", "mean_temporal_error", "median_temporal_error",
    "p5_temporal_error", "p95_temporal_error", "mean_temporal_error_reflectors", "pareto",
)  # fmt: skip


def write_summary_csv(summary: list[Mapping[str, Any]], path: Path) -> None:
    """Write summary.csv: one row per summary entry (``SUMMARY_CSV_KEYS``); None is an
    empty cell, an unbounded budget is ``inf``, ``pareto`` is 1 or 0."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(SUMMARY_CSV_KEYS)
    for entry in summary:
        cells = []
        for key in SUMMARY_CSV_KEYS:
            value = entry.get(key)
            if key == "pareto":
                value = int(bool(value))
            cells.append("" if value is None else value)
        writer.writerow(cells)
    write_text_atomic(Path(path), buf.getvalue())


# --- timeline.json -------------------------------------------------------------------


def read_timeline(path: Path) -> dict[str, Any]:
    """timeline.json as {stage: {config: {...}}}; {} if the file is absent."""
    path = Path(path)
    if not path.is_file():
        return {}
    return _read_json_object(path, "{stage: {config: ...}}")


def _read_json_object(path: Path, layout: str) -> dict[str, Any]:
    """The JSON object in ``path``; PhrtError naming the file when it cannot be read or
    is not an object (``layout``: the object expected, for the message)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise PhrtError(f"{path}: cannot read ({error})") from error
    if not isinstance(data, dict):
        raise PhrtError(f"{path}: expected an object {layout}")
    return data


def timeline_arrays(
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
