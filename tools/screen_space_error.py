"""The screen-space step's share, cost and error (docs/screen-space.md).

    uv run python tools/screen_space_error.py stages/sewer.usda@241 [--resolution 640x480]
        [--max-steps 256] [--repeat 3] [--json]

``STAGE@T``: the frame at time code T (default: the middle of the stage's range). The
frame is rendered hybrid with every reflector traced, no budget, twice per repeat in the
same process, alternating: without the screen-space step and with it (the tracer's
``trace_reflections`` given the frame's ``ScreenFrame``); and once in rt. Reported: the
share of traced reflector pixels resolved in screen space, each march outcome's share,
rays per traced pixel, the frame's trace milliseconds (median of the repeats) with and
without, and the mean FLIP of each hybrid image against rt and of the two against each
other. The machine's other load shows in the milliseconds: compare the ratio.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from phrt_usd.bench.bench_stage import stage_at
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace import screen_space, screen_space_kernels
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.model.frame import FrameCamera
from phrt_usd.model.pixel_kinds import SCREEN_SPACE, kind_counts
from phrt_usd.usd.stage import open_stage

#: ``screen_space_kernels`` outcome codes by name.
OUTCOMES = {
    name.lower(): getattr(screen_space_kernels, name)
    for name in ("RESOLVED", "OFF_SCREEN", "BEHIND", "STEPS", "AMBIGUOUS", "REFLECTOR",
                 "TRANSMISSIVE", "HOLE")
}  # fmt: skip


class _WithScreen:
    """The renderer's tracer with every ``trace_reflections`` call given the frame's
    ``ScreenFrame`` (and the outcomes of its marches kept)."""

    def __init__(self, renderer: FrameRenderer, camera: FrameCamera, max_steps: int):
        self.tracer = renderer.tracer
        self.original = self.tracer.trace_reflections
        self.screen = screen_space.ScreenFrame(camera, max_steps)
        self.outcomes: list[np.ndarray] = []
        self.steps: list[np.ndarray] = []
        resolve = screen_space.resolve

        def keep(*args, **kwargs):
            hits = resolve(*args, **kwargs)
            self.outcomes.append(hits.outcome.copy())
            self.steps.append(hits.steps.copy())
            return hits

        self._keep = keep
        self._resolve = resolve

    def __enter__(self):
        screen = self.screen
        self.tracer.trace_reflections = lambda *a, **k: self.original(*a, **k, screen=screen)
        screen_space.resolve = self._keep
        return self

    def __exit__(self, *exc):
        del self.tracer.trace_reflections
        screen_space.resolve = self._resolve


def measure(stage_path: str, frame: float, width: int, height: int, max_steps: int,
            repeat: int) -> dict:  # fmt: skip
    """The figures of one frame (see the module)."""
    stage = open_stage(stage_path)
    options = RenderOptions(mode="hybrid", heuristic="all", budget_ms=None, width=width,
                            height=height)  # fmt: skip
    renderer = FrameRenderer(stage, options)
    try:
        renderer.render(frame)  # warm: BVH, maps, kernels
        camera = FrameCamera.of(frame, renderer.stage_scene.camera(frame), width, height)
        runs: dict[str, list] = {"without": [], "with": []}
        probe: _WithScreen | None = None
        for _ in range(repeat):
            runs["without"].append(renderer.render(frame))
            probe = _WithScreen(renderer, camera, max_steps)
            with probe:
                runs["with"].append(renderer.render(frame))
    finally:
        renderer.close()
    rt_renderer = FrameRenderer(stage, RenderOptions(mode="rt", heuristic="all", budget_ms=None,
                                                     width=width, height=height))  # fmt: skip
    try:
        rt = rt_renderer.render(frame).beauty
    finally:
        rt_renderer.close()
    outcome = np.concatenate(probe.outcomes) if probe and probe.outcomes else np.zeros(0, int)
    steps = np.concatenate(probe.steps) if probe and probe.steps else np.zeros(0, int)
    out: dict = {"stage": Path(stage_path).name, "frame": frame, "resolution": [width, height],
                 "max_steps": max_steps}  # fmt: skip
    for name, frames in runs.items():
        last = frames[-1]
        counts = kind_counts(last.pixel_kind)
        reflector_pixels = counts["traced"] + counts["screen-space"] + counts["filled"]
        out[name] = {
            "trace_ms": float(np.median([f.stats.phase_ms.get("trace", np.nan) for f in frames])),
            "rays": last.stats.rays,
            "reflector_pixels": reflector_pixels,
            "screen_space_pixels": counts["screen-space"],
            "screen_space_share": counts["screen-space"] / max(reflector_pixels, 1),
            "rays_per_reflector_pixel": last.stats.rays / max(reflector_pixels, 1),
            "rays_per_traced_pixel": last.stats.rays / max(counts["traced"], 1),
            "flip_vs_rt": float(np.mean(flip_map(rt, last.beauty))),
        }
    out["flip_with_vs_without"] = float(np.mean(flip_map(runs["without"][-1].beauty,
                                                         runs["with"][-1].beauty)))  # fmt: skip
    n = max(len(outcome), 1)
    out["outcomes"] = {name: int(np.count_nonzero(outcome == code)) / n
                       for name, code in OUTCOMES.items()}  # fmt: skip
    resolved = outcome == screen_space_kernels.RESOLVED
    out["steps_resolved"] = _percentiles(steps[resolved])
    out["steps_unresolved"] = _percentiles(steps[~resolved])
    out["trace_ms_ratio"] = out["with"]["trace_ms"] / out["without"]["trace_ms"]
    out["screen_space_in_frame"] = bool(np.any(runs["with"][-1].pixel_kind == SCREEN_SPACE))
    return out


def _percentiles(values: np.ndarray) -> dict:
    if len(values) == 0:
        return {}
    p = np.percentile(values, [50, 90, 99]).tolist()
    return {"p50": p[0], "p90": p[1], "p99": p[2], "mean": float(np.mean(values))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stages", nargs="+", help="STAGE or STAGE@TIMECODE")
    ap.add_argument("--resolution", default="640x480")
    ap.add_argument("--max-steps", type=int, default=screen_space.MAX_STEPS)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="the figures as JSON (default)")
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    rows = []
    for spec in args.stages:
        stage_path, frame = stage_at(spec)
        rows.append(measure(stage_path, frame, width, height, args.max_steps, args.repeat))
    print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
