"""Names of the files in a sweep's output directory ``OUT`` (written by ``sweep.py`` and
``sweep_report``, read by ``sweep_summary`` and ``sweep_html``)."""

from __future__ import annotations

import re
from pathlib import Path

from phrt_usd.run.run_files import LOCK_FILE

SWEEP_CSV = "sweep.csv"
TIMELINE_JSON = "timeline.json"
#: Optional input: the paper's figures per stage (``sweep_summary.load_paper_figures``).
PAPER_JSON = "paper.json"
SUMMARY_MD = "summary.md"
#: One row per stage x config: the summary's figures (``sweep_summary.SUMMARY_CSV_KEYS``).
SUMMARY_CSV = "summary.csv"
ERROR_VS_TIME_PNG = "error_vs_time.png"
REPORT_HTML = "report.html"
#: Where the sweep's figures came from (``provenance.collect``): version, commit, command,
#: machine, threads, OpenGL, FLIP's viewing conditions, seeds, the sweep's settings.
PROVENANCE_JSON = "provenance.json"
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


#: The files a sweep writes at the top of ``OUT`` under fixed names.
FIXED_NAMES = (SWEEP_CSV, TIMELINE_JSON, SUMMARY_MD, SUMMARY_CSV, ERROR_VS_TIME_PNG,
               REPORT_HTML, PROVENANCE_JSON)  # fmt: skip
#: ... and under names made from a stage's (``stage_plot_name``, ``timeline_plot_name``).
_STAGE_PLOT = re.compile(r"^(error_vs_time|timeline)_[A-Za-z0-9_.-]+\.png$")
#: A temp file ``atomic_path`` leaves when killed mid-write: ``.<stem>.<random>.tmp<ext>``.
_TEMP_FILE = re.compile(r"^\.(.+)\.[^.]+\.tmp(\.[^.]+)$")
#: Files a sweep may find in ``OUT`` that are not an earlier sweep's: the optional input
#: ``PAPER_JSON`` and the lock of the run that holds ``OUT``.
INPUT_NAMES = (PAPER_JSON, LOCK_FILE)


def is_sweep_file(name: str) -> bool:
    """Whether a file named ``name`` at the top of ``OUT`` is one a sweep writes (or the
    temp file of one, left by a killed write)."""
    temp = _TEMP_FILE.match(name)
    if temp:
        name = temp.group(1) + temp.group(2)
    return name in FIXED_NAMES or bool(_STAGE_PLOT.match(name))


def is_report_image(path: Path) -> bool:
    """Whether ``path``, relative to ``IMAGES_DIR``, is a report image a sweep writes:
    ``<stage>/<frame>/<name>.png`` (or the temp file of one)."""
    return len(path.parts) == 3 and path.suffix == ".png"
