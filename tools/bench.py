"""Frame-time benchmark: per-phase medians of raster / hybrid (all selected) / rt, and the
trace phase's ray throughput against raw embreex on exactly the same rays, same run.

    uv run python tools/bench.py stages/farm.usda stages/sewer.usda \
        --resolutions 320x240,640x480 --frames 1:720:24 \
        [--append docs/bench-log/DATE-COMMIT-frame-phases.md]

Prints the run's provenance (``provenance_line``: version, commit, command, machine,
threads, OpenGL) and a markdown table (and appends both, with the command, date and core
count, to the file given by --append: a new log file in docs/bench-log/, see BENCHMARKS.md "How to
measure"). Timings are wall-clock medians over the chosen frames; the
first frame of every configuration is rendered once untimed as warm-up.
"""

from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
from pathlib import Path

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.run.frames import parse_frames
from phrt_usd.usd.stage import open_stage

CONFIGS = (
    ("raster", RenderOptions(mode="raster", heuristic="none", budget_ms=None)),
    ("hybrid (all)", RenderOptions(mode="hybrid", heuristic="all", budget_ms=None)),
    ("hybrid (heu1, T=10 ms)", RenderOptions(mode="hybrid", heuristic="heu1", budget_ms=10.0)),
    ("rt", RenderOptions(mode="rt", heuristic="all", budget_ms=None)),
)
PHASES = ("set_time", "gbuffer", "shade", "select", "trace")


def bench_stage(stage_path: str, width: int, height: int, frames: str) -> list[dict]:
    stage = open_stage(stage_path)
    times = parse_frames(frames, stage.frame_range)
    rows = []
    for label, base in CONFIGS:
        opts = RenderOptions(**{**base.__dict__, "width": width, "height": height})
        renderer = FrameRenderer(stage, opts)
        renderer.plan(times)
        tracer = renderer.tracer
        renderer.render(times[0])  # warm-up: first upload, shadow map, caches
        frame_ms, phases = [], {p: [] for p in PHASES}
        our_rays = our_s = raw_rays = raw_s = 0.0
        for t in times:
            if tracer is not None:
                tracer.record_rays = True
            out = renderer.render(t)
            frame_ms.append(out.stats.frame_ms)
            for p in PHASES:
                phases[p].append(out.stats.phase_ms.get(p, 0.0))
            if label == "hybrid (all)" and out.stats.rays:
                # Throughput of our whole trace phase (set-up + shading included) vs raw
                # Embree on the same ray batches, replayed right after.
                our_rays += out.stats.rays
                our_s += out.stats.trace_ms / 1000.0
                rays, seconds = tracer.replay_raw()
                raw_rays += rays
                raw_s += seconds
        renderer.close()
        row = {
            "stage": Path(stage_path).stem,
            "resolution": f"{width}x{height}",
            "config": label,
            "frames": len(times),
            "median_frame_ms": statistics.median(frame_ms),
            **{f"{p}_ms": statistics.median(v) for p, v in phases.items()},
        }
        if our_s > 0 and raw_s > 0:
            row["ours_mrays_s"] = our_rays / our_s / 1e6
            row["raw_mrays_s"] = raw_rays / raw_s / 1e6
        rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    head = (
        "| stage | res | config | median frame ms | fps | set_time | gbuffer | shade | "
        "select | trace | trace Mrays/s (ours / raw embreex = ratio) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        tp = ""
        if "ours_mrays_s" in r:
            ratio = r["ours_mrays_s"] / r["raw_mrays_s"]
            tp = f"{r['ours_mrays_s']:.2f} / {r['raw_mrays_s']:.2f} = {ratio:.0%}"
        lines.append(
            f"| {r['stage']} | {r['resolution']} | {r['config']} | {r['median_frame_ms']:.1f} "
            f"| {1000 / r['median_frame_ms']:.1f} | {r['set_time_ms']:.1f} | "
            f"{r['gbuffer_ms']:.1f} | {r['shade_ms']:.1f} | {r['select_ms']:.1f} | "
            f"{r['trace_ms']:.1f} | {tp} |"
        )
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stages", nargs="+")
    ap.add_argument("--resolutions", default="320x240,640x480")
    ap.add_argument("--frames", default=None, help="A:B[:STEP] (default: the stage's range)")
    ap.add_argument("--append", type=Path, default=None, help="append the table to this file")
    args = ap.parse_args(argv)
    rows = []
    for stage in args.stages:
        for res in args.resolutions.split(","):
            w, h = (int(v) for v in res.lower().split("x"))
            rows += bench_stage(stage, w, h, args.frames)
            print(f"done {stage} {res}", file=sys.stderr)
    table = provenance_line(collect_for_tool(__file__, argv)) + "\n\n" + markdown(rows)
    print(table)
    if args.append:
        command = "uv run python tools/bench.py " + " ".join(argv or sys.argv[1:])
        stamp = datetime.date.today().isoformat()
        with open(args.append, "a") as fh:
            fh.write(
                f"\n### Frame phases, {stamp}, {os.cpu_count()} cores\n\n"
                f"`{command}`\n\n{table}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
