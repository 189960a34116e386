"""Human-readable outputs of ``phrt sweep``: error against run time, for people.

``phrt sweep`` (``sweep.py``) writes machine-readable files into its output directory
``OUT`` (sweep.csv, timeline.json, provenance.json, images/; see ``sweep_summary`` and
``sweep_html``);
``write_sweep_report`` reads them and writes the human-readable ones next to them::

    OUT/summary.md                   provenance, tables per stage, budget adherence, the
                                     paper's figures beside ours
    OUT/summary.csv                  the same figures, one row per stage x config
    OUT/error_vs_time.png            mean FLIP, temporal error, transition rate against
                                     mean frame time, every stage (Pareto front ringed)
    OUT/error_vs_time_<stage>.png    the same per stage (only with more than one stage)
    OUT/timeline_<stage>.png         which reflector was traced in which frame, per config
    OUT/report.html                  one static page: provenance, links to the CSVs,
                                     plots, tables, timelines, images

Pipeline: ``sweep_summary`` (``read_sweep_csv`` → ``summarize``) → ``sweep_tables``
(``write_summary_md``) →
``sweep_plots`` (``plot_error_vs_time``, ``plot_selection_timeline``) → ``sweep_html``
(``write_report_html``, which links the plots, so it comes last).
"""

from __future__ import annotations

from pathlib import Path

from phrt_usd.evaluate.provenance import read_provenance
from phrt_usd.evaluate.sweep_files import (
    ERROR_VS_TIME_PNG,
    PROVENANCE_JSON,
    SUMMARY_CSV,
    SUMMARY_MD,
    SWEEP_CSV,
    TIMELINE_JSON,
    stage_plot_name,
    timeline_plot_name,
)
from phrt_usd.evaluate.sweep_html import write_report_html
from phrt_usd.evaluate.sweep_plots import plot_error_vs_time, plot_selection_timeline
from phrt_usd.evaluate.sweep_summary import (
    load_paper_figures,
    read_sweep_csv,
    read_timeline,
    stages_of,
    summarize,
    write_summary_csv,
)
from phrt_usd.evaluate.sweep_tables import write_summary_md


def write_sweep_report(out_dir: Path) -> None:
    """Read the sweep's outputs in ``out_dir`` and write every human-readable output."""
    out_dir = Path(out_dir)
    rows = read_sweep_csv(out_dir / SWEEP_CSV)
    timeline = read_timeline(out_dir / TIMELINE_JSON)
    summary = summarize(rows, timeline)
    paper = load_paper_figures(out_dir)
    provenance = read_provenance(out_dir / PROVENANCE_JSON)
    write_summary_md(summary, out_dir / SUMMARY_MD, paper, provenance)
    write_summary_csv(summary, out_dir / SUMMARY_CSV)

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

    write_report_html(out_dir, summary, paper, rows, provenance)
