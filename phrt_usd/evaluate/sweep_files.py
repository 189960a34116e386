"""Names of the files in a sweep's output directory ``OUT`` (written by ``sweep.py`` and
``sweep_report``, read by ``sweep_summary`` and ``sweep_html``)."""

from __future__ import annotations

import re

SWEEP_CSV = "sweep.csv"
TIMELINE_JSON = "timeline.json"
#: Optional input: the paper's figures per stage (``sweep_summary.load_paper_figures``).
PAPER_JSON = "paper.json"
SUMMARY_MD = "summary.md"
#: One row per stage x config: the summary's figures (``sweep_summary.SUMMARY_CSV_KEYS``).
SUMMARY_CSV = "summary.csv"
ERROR_VS_TIME_PNG = "error_vs_time.png"
REPORT_HTML = "report.html"
#: Chosen frames' images: ``IMAGES_DIR/<stage>/<frame>/<config>.png`` and the config's
#: FLIP error map ``<config>FLIP_MAP_SUFFIX.png``.
IMAGES_DIR = "images"
FLIP_MAP_SUFFIX = "_flip"
#: ... and its temporal error map ``<config>TEMPORAL_MAP_SUFFIX.png`` (not on the first
#: recorded frame, which has no previous frame).
TEMPORAL_MAP_SUFFIX = "_temporal"


def safe_file_part(name: str) -> str:
    """``name`` reduced to [A-Za-z0-9_.-] (others → '_') for use in a file name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "_"


def stage_plot_name(stage: str) -> str:
    """Error against time of one stage (written only for sweeps of several stages)."""
    return f"error_vs_time_{safe_file_part(stage)}.png"


def timeline_plot_name(stage: str) -> str:
    """Selection timeline of one stage."""
    return f"timeline_{safe_file_part(stage)}.png"
