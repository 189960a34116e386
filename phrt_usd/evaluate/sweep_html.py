"""report.html of a sweep: one static page of its plots, tables, timelines and images.

Reads from ``OUT`` (all optional but the summary): the PNGs of ``sweep_plots`` and the
chosen frames' images the sweep wrote::

    OUT/images/<stage>/<frame>/<config>.png       tone-mapped preview of chosen frames
    OUT/images/<stage>/<frame>/<config>_flip.png  FLIP error map vs the reference (magma)
    OUT/images/<stage>/<frame>/<config>_temporal.png  temporal error map (magma)
    OUT/images/<stage>/<frame>/all.png            the reference (``all`` config)

and links the sweep's data files (sweep.csv, summary.csv, timeline.json, provenance.json,
summary.md) by relative path. Its tables (``sweep_tables.TABLES``, config first) fit a
laptop screen: the page is no wider than 1280 px (tests/evaluate/test_report_html_browser.py
checks it in Chromium); a table wider than the window scrolls inside its own box, its
config column held in place.

Limits: the page is static (no JavaScript); images and files are referenced by relative
path, so ``report.html`` must stay next to ``images/``, the PNGs and the CSVs.
"""

from __future__ import annotations

import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import quote

from phrt_usd.atomic import write_text_atomic
from phrt_usd.evaluate.provenance import provenance_items
from phrt_usd.evaluate.sweep_files import (
    ERROR_VS_TIME_PNG,
    FLIP_MAP_SUFFIX,
    IMAGES_DIR,
    PROVENANCE_JSON,
    REPORT_HTML,
    SUMMARY_CSV,
    SUMMARY_MD,
    SWEEP_CSV,
    TEMPORAL_MAP_SUFFIX,
    TIMELINE_JSON,
    stage_plot_name,
    timeline_plot_name,
)
from phrt_usd.evaluate.sweep_summary import PAPER_FIGURES, csv_number, stages_of
from phrt_usd.evaluate.sweep_tables import (
    DEFINITIONS,
    NO_PROVENANCE,
    TABLES,
    Column,
    format_fixed,
    format_significant3,
    stage_note_lines,
    table_cells,
)

#: Name of the reference config (every reflector traced); FLIP/PSNR are measured against it.
REFERENCE_CONFIG = "all"

#: The data files the page links, with what each holds (only those present are linked).
DATA_FILES = (
    (SWEEP_CSV, "every frame of every config"),
    (SUMMARY_CSV, "one row per stage and config: these tables' figures, unrounded"),
    (TIMELINE_JSON, "which reflector each config traced in each frame"),
    (PROVENANCE_JSON, "version, commit, command, machine, settings"),
    (SUMMARY_MD, "these tables as markdown"),
)


_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1400px; }
h1 { font-size: 1.4em; } h2 { font-size: 1.2em; margin-top: 1.6em; }
h3 { font-size: 1.0em; }
div.table { max-width: 100%; overflow-x: auto; }
table { border-collapse: collapse; font-size: 0.8em; margin: 0.5em 0; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; font-weight: normal; }
td:first-child, th:first-child { text-align: left; position: sticky; left: 0;
  background: #fff; }
th:first-child { background: #f0f0f0; }
p.note { font-size: 0.85em; color: #555; max-width: 60em; }
dl.provenance { font-size: 0.8em; display: grid; grid-template-columns: max-content 1fr;
  gap: 1px 12px; max-width: 100%; }
dl.provenance dt { font-weight: bold; }
dl.provenance dd { margin: 0; overflow-wrap: anywhere; }
ul.files { font-size: 0.85em; }
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


def _html_table(entries: list[Mapping[str, Any]], columns: tuple[Column, ...]) -> str:
    """One of ``TABLES`` in its own scrolling box (wider than the window, it scrolls
    there, never the page)."""
    head = "".join(f"<th>{_esc(h)}</th>" for h, _k, _f in columns)
    body = "".join(
        "<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in table_cells(e, columns)) + "</tr>"
        for e in entries
    )
    table = f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    return f'<div class="table">{table}</div>'


def _provenance_section(provenance: Mapping[str, Any] | None) -> list[str]:
    """Where the figures came from (``provenance.json``), as a definition list."""
    parts = ["<h2>Provenance</h2>"]
    if not provenance:
        return parts + [f'<p class="note">{_esc(NO_PROVENANCE)}</p>']
    items = "".join(
        f"<dt>{_esc(label)}</dt><dd>{_esc(text)}</dd>"
        for label, text in provenance_items(dict(provenance))
    )
    return parts + [f'<dl class="provenance">{items}</dl>']


def _files_section(out_dir: Path) -> list[str]:
    """Relative links to the sweep's data files (``DATA_FILES``) that exist."""
    links = [
        f'<li><a href="{_src(out_dir, out_dir / name)}">{_esc(name)}</a>: {_esc(what)}</li>'
        for name, what in DATA_FILES
        if (out_dir / name).is_file()
    ]
    return ["<h2>Data</h2>", f'<ul class="files">{"".join(links)}</ul>'] if links else []


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


def _references_of(entries: list[Mapping[str, Any]]) -> dict[str, str]:
    """Config → the name of the reference it is measured against: the ``all`` config of
    its variant (``REFERENCE_CONFIG`` for configs not in ``entries``)."""
    by_variant = {
        e.get("variant", ""): e["config"] for e in entries if e.get("kind") == "reference"
    }
    return {
        e["config"]: by_variant.get(e.get("variant", ""), REFERENCE_CONFIG) for e in entries
    }


def _images_section(
    out_dir: Path,
    stage: str,
    order: list[str],
    rows: list[Mapping[str, Any]],
    references: Mapping[str, str] | None = None,
) -> list[str]:
    stage_dir = out_dir / IMAGES_DIR / stage
    if not stage_dir.is_dir():
        return []
    references = references or {}
    reference_names = set(references.values()) | {REFERENCE_CONFIG}
    parts = []
    for frame_dir in _frame_dirs(stage_dir):
        # Hidden files are temp files of interrupted atomic writes.
        pngs = {p.stem: p for p in frame_dir.glob("*.png") if not p.name.startswith(".")}
        configs = [
            name
            for name in pngs
            if not name.endswith((FLIP_MAP_SUFFIX, TEMPORAL_MAP_SUFFIX))
            and name not in reference_names
        ]
        configs.sort(key=lambda c: (order.index(c) if c in order else len(order), c))
        parts.append(f"<h3>{_esc(stage)}, frame {_esc(frame_dir.name)}</h3>")
        parts.append('<div class="frame">')
        for config in configs:
            reference_name = references.get(config, REFERENCE_CONFIG)
            reference = pngs.get(reference_name)
            row = _frame_row(rows, stage, config, frame_dir.name)
            figures_text = ""
            if row is not None:
                flip = format_significant3(csv_number(row, "flip"))
                psnr = format_fixed(2)(csv_number(row, "psnr"))
                temporal = format_significant3(csv_number(row, "temporal_error"))
                figures_text = (
                    f", FLIP {flip}, PSNR {psnr} dB, temporal error {temporal} "
                    f"vs {reference_name}"
                )
            cells = [_figure(out_dir, pngs[config], f"{config}{figures_text}")]
            if reference is not None:
                caption = f"reference {reference_name}: all reflectors traced"
                cells.append(_figure(out_dir, reference, caption))
            flip_map = pngs.get(config + FLIP_MAP_SUFFIX)
            if flip_map is not None:
                cells.append(
                    _figure(
                        out_dir,
                        flip_map,
                        f"FLIP error of {config} vs {reference_name} "
                        "(magma: black = 0, yellow = 1)",
                    )
                )
            temporal_map = pngs.get(config + TEMPORAL_MAP_SUFFIX)
            if temporal_map is not None:
                cells.append(
                    _figure(
                        out_dir,
                        temporal_map,
                        f"temporal error of {config}: its warped-frame error beyond "
                        f"{reference_name}'s (magma: black = 0, yellow = 1)",
                    )
                )
            parts.append('<div class="row">' + "".join(cells) + "</div>")
        only_references = [] if configs else sorted(reference_names & set(pngs))
        for name in only_references:
            parts.append(
                '<div class="row">'
                + _figure(out_dir, pngs[name], f"reference {name}: all reflectors traced")
                + "</div>"
            )
        parts.append("</div>")
    return parts


def write_report_html(
    out_dir: Path,
    summary: list[Mapping[str, Any]],
    paper: Mapping[str, Mapping[str, float]] | None = None,
    rows: list[Mapping[str, Any]] | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> None:
    """Write OUT/report.html: one static page (inline CSS, no scripts, no external URLs).

    Shows the provenance and links to the data files, the error-vs-time plot(s)
    (per-frame FLIP, temporal error, transitions; the Pareto front ringed), per stage the
    ``TABLES`` (the Pareto column marks the front) with the notes (budget adherence, the
    paper comparison, equal time), the selection timeline PNG per stage, and per chosen
    frame each config's image beside the reference and its FLIP map. Only files that
    exist in ``out_dir`` are referenced (relative paths); the plots and timelines must be
    written first.
    rows : sweep.csv rows, for per-image FLIP/PSNR captions (optional).
    provenance : provenance.json's record (None: not recorded).
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
        *_provenance_section(provenance),
        *_files_section(out_dir),
    ]
    plot = out_dir / ERROR_VS_TIME_PNG
    if plot.is_file():
        parts.append(
            f'<img class="plot" src="{_src(out_dir, plot)}" '
            'alt="mean FLIP, temporal error and transition rate against mean frame time">'
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
        for title, columns in TABLES:
            parts.append(f"<h3>{_esc(title)}, {_esc(stage)}</h3>")
            parts.append(_html_table(entries, columns))
        notes = stage_note_lines(summary, stage, paper)
        parts += [f'<p class="note">{_esc(line)}</p>' for line in notes]
        timeline = out_dir / timeline_plot_name(stage)
        if timeline.is_file():
            parts.append(f"<h3>Selection timeline, {_esc(stage)}</h3>")
            parts.append(
                f'<img class="plot" src="{_src(out_dir, timeline)}" '
                f'alt="{_esc(f"selection timeline of {stage}")}">'
            )
        parts += _images_section(
            out_dir, stage, order_by_stage[stage], rows, _references_of(entries)
        )
    parts.append("</body></html>")
    write_text_atomic(out_dir / REPORT_HTML, "\n".join(parts) + "\n")
