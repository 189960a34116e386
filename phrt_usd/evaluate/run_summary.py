"""The summary of a render: what ``phrt render --json`` prints and ``RenderResult.summary``
holds (``phrt_usd.api``, docs/api.md).

``summary_of(record)``: the report of the run's selection layer
(``evaluate.report.build_report``: frames, mean_fps, median_frame_ms, mean_selected,
transitions, reflectors, budget_ms, budget_overruns, ...) plus ``out``,
``selection_layer``, the ``passes`` its frames ran, ``images`` (each frame's file name
templates), how it ran (``runtime``: threads, gl, llvmpipe_threads, kernels) and what its
hybrid frames traced (``trace_summary``). ``finish_summary(summary, stage_scene)`` adds
what the stage read for the render says: ``warnings`` (those found while rendering among
them), ``default_light_rig`` and ``support`` (what the stage uses that the render ignores
or approximates: ``usd.support_report``). A render's summary is finished once, here, for
the API and the CLI alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from phrt_usd.evaluate.report import build_report
from phrt_usd.model.frame import FrameStats
from phrt_usd.run.render_job import RunRecord
from phrt_usd.usd.stage import StageScene
from phrt_usd.usd.support_report import support_report


def summary_of(record: RunRecord) -> dict:
    """The summary of a finished run, from its records alone (see the module
    docstring); ``finish_summary`` adds what the stage read for it says."""
    summary = build_report(record.selection_layer)
    products = record.images.products if record.images is not None else ()
    summary.update(
        out=str(record.out),
        selection_layer=str(record.selection_layer),
        passes=record.passes,
        # File name templates of a frame's images, relative to ``out`` (frame tokens kept).
        images=[name for p in products for name in (p.template, p.preview) if name],
        **record.runtime,
    )
    summary.update(trace_summary(record.frames))
    return summary


def trace_summary(frames: Sequence[FrameStats]) -> dict:
    """What a run's hybrid frames traced:

    - ``untraced_frames``: frames with visible reflectors that traced nothing;
    - ``mean_budget_use``: trace ms / T over the time-budgeted frames with visible
      reflectors (None without any);
    - ``budget_bound_frames``, ``budget_bound_use``: those of them that left a visible
      reflector untraced, and their mean use (budget idle there is budget the policy
      chose not to spend; where all in view was traced, nothing was left to spend it on);
    - ``trace_prediction_error``: median |expected - measured| / measured trace ms after
      the first three frames (None without traced frames);
    - ``trace_note``: one line when hybrid frames with visible reflectors traced nothing
      (the first reason), else None."""
    seen = [f for f in frames if f.visible]
    untraced = [f for f in seen if not f.selected and f.untraced_reason is not None]
    uses = [f.budget_use for f in seen if f.budget_use is not None]
    bound = [
        f.budget_use
        for f in seen
        if f.budget_use is not None and not set(f.visible) <= set(f.selected)
    ]
    errors = [
        abs(f.expected_trace_ms - f.trace_ms) / f.trace_ms
        for f in list(frames)[3:]
        if f.selected and f.trace_ms > 0.0
    ]
    note = None
    if untraced:
        share = "all" if len(untraced) == len(seen) else f"{len(untraced)} of {len(seen)}"
        note = (
            f"hybrid traced nothing in {share} of the frames with visible reflectors"
            f" ({len(untraced)}/{len(seen)}); e.g. t={untraced[0].time:g}:"
            f" {untraced[0].untraced_reason}"
        )
    return {
        "untraced_frames": len(untraced),
        "mean_budget_use": float(np.mean(uses)) if uses else None,
        "budget_bound_frames": len(bound),
        "budget_bound_use": float(np.mean(bound)) if bound else None,
        "trace_prediction_error": float(np.median(errors)) if errors else None,
        "trace_note": note,
    }


def finish_summary(summary: dict, stage_scene: StageScene) -> dict:
    """``summary`` with what the stage read for the render says (see the module
    docstring): its ``warnings``, ``default_light_rig`` (the stage has no lights:
    ``usd.default_lights``) and ``support``. Returns ``summary``."""
    summary["warnings"] = list(stage_scene.warnings)
    summary["default_light_rig"] = stage_scene.scene.lights.default_rig
    summary["support"] = support_report(stage_scene.stage)
    return summary
