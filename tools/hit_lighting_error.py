"""The hit-lighting rule's cost and error against the exact evaluation of every
(hit, light) pair (docs/hit-lighting.md).

    uv run python tools/hit_lighting_error.py stages/sewer.usda@241 [--resolution 640x480]
        [--json] [--append docs/bench-log/DATE-COMMIT-hit-lighting.md]

``STAGE@T``: the frame at time code T (default: the middle of the stage's range). The
frame is rendered four times, every reflector traced, no budget: hybrid and rt, each
with the rule (``engine/trace/hit_lighting.py``) and with every pair's shadow ray cast
(``Tracer.exact_hit_lighting``, the evaluation before the rule). Reported per mode:
the rays of the frame's trace rounds (``FrameStats.rays``: reflection and shadow rays),
its traced pixels (``FrameOutput.traced_mask``), their ratio, and the mean FLIP of the
rule's image against the exact one, over the frame and over the traced pixels; and
hybrid against rt, both with the rule.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from phrt_usd.bench.bench_stage import append_log, stage_at
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.image_metrics import flip_map, mean_over
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.usd.stage import open_stage


def render(stage, mode: str, frame: float, width: int, height: int, exact: bool):
    """One frame with every reflector traced (``FrameOutput``), its hits lit by the
    rule or, ``exact``, by every pair's shadow ray."""
    options = RenderOptions(mode=mode, heuristic="all", budget_ms=None, width=width,
                            height=height)  # fmt: skip
    renderer = FrameRenderer(stage, options)
    try:
        renderer.tracer.exact_hit_lighting = exact
        return renderer.render(frame)
    finally:
        renderer.close()


def measure(stage_path: str, frame: float, width: int, height: int) -> dict:
    """The figures of one frame (see the module), by mode, and hybrid against rt."""
    stage = open_stage(stage_path)
    out: dict = {"stage": Path(stage_path).name, "frame": frame, "resolution": [width, height]}
    images = {}
    for mode in ("hybrid", "rt"):
        rule, exact = (render(stage, mode, frame, width, height, e) for e in (False, True))
        images[mode] = rule.beauty
        error = flip_map(exact.beauty, rule.beauty)
        traced = rule.traced_mask
        out[mode] = {
            "traced_pixels": int(traced.sum()),
            "rays": rule.stats.rays,
            "rays_exact": exact.stats.rays,
            "rays_per_traced_pixel": rule.stats.rays / max(int(traced.sum()), 1),
            "rays_per_traced_pixel_exact": exact.stats.rays / max(int(traced.sum()), 1),
            "flip_vs_exact": mean_over(error),
            "flip_vs_exact_traced": mean_over(error, traced) if traced.any() else 0.0,
        }
    out["flip_hybrid_vs_rt"] = float(np.mean(flip_map(images["rt"], images["hybrid"])))
    return out


def markdown(rows: list[dict]) -> str:
    lines = [
        "| stage | size | frame | mode | rays ÷ traced pixel (exact) | FLIP vs exact "
        "(traced pixels) | hybrid vs rt FLIP |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        size = "x".join(map(str, r["resolution"]))
        for mode in ("hybrid", "rt"):
            m = r[mode]
            lines.append(
                f"| {r['stage']} | {size} | {r['frame']:g} | {mode} | "
                f"{m['rays_per_traced_pixel']:.2f} ({m['rays_per_traced_pixel_exact']:.2f}) | "
                f"{m['flip_vs_exact']:.4f} ({m['flip_vs_exact_traced']:.4f}) | "
                f"{r['flip_hybrid_vs_rt']:.4f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stages", nargs="+", help="STAGE or STAGE@TIMECODE")
    ap.add_argument("--resolution", default="640x480")
    ap.add_argument("--json", action="store_true", help="the figures as JSON")
    ap.add_argument("--append", type=Path)
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    rows = []
    for spec in args.stages:
        stage_path, frame = stage_at(spec)
        rows.append(measure(stage_path, frame, width, height))
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    out = provenance_line(collect_for_tool(__file__, argv)) + "\n\n" + markdown(rows)
    print(out)
    if args.append:
        append_log(args.append, "Hit lighting", " ".join(sys.argv), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
