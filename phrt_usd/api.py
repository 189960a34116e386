"""The Python API pipelines and the CLI call: render a job and get its summary.

``run_render`` renders a ``RenderJob`` (``phrt_usd.run.render_job``) into its output
directory and returns the summary ``phrt render --json`` prints: the report of the run's
selection layer (``phrt_usd.evaluate.report.build_report``: frames, mean_fps,
median_frame_ms, mean_selected, transitions, reflectors, budget_ms, budget_overruns, ...)
plus ``out``, ``selection_layer`` and the ``passes`` its frames ran.
"""

from __future__ import annotations

from collections.abc import Callable

from phrt_usd.evaluate.report import build_report
from phrt_usd.model.frame import FrameStats
from phrt_usd.run.render_job import RenderJob, RunRecord, render_to_directory
from phrt_usd.usd.stage import StageScene


def run_render(
    job: RenderJob,
    on_frame: Callable[[int, int, FrameStats], None] | None = None,
    stage_scene: StageScene | None = None,
) -> dict:
    """Render ``job`` and return its summary (see the module docstring). ``on_frame(done,
    total, stats)`` after every frame; ``stage_scene``: the stage already read, if any.
    Raises ``PhrtError`` (one line) for bad input, a busy or non-empty output directory,
    or a failed frame (after the finished frames' records are written)."""
    return summary_of(render_to_directory(job, on_frame, stage_scene))


def summary_of(record: RunRecord) -> dict:
    """The summary of a finished run (see the module docstring)."""
    summary = build_report(record.selection_layer)
    summary.update(
        out=str(record.out), selection_layer=str(record.selection_layer), passes=record.passes
    )
    return summary
