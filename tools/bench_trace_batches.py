"""Trace-phase throughput by batch size: ``Tracer.trace_reflections`` against raw embreex
on the very same rays, and the fixed cost of a round.

    uv run python tools/bench_trace_batches.py stages/farm.usda@560 stages/sewer.usda@270
        [--resolution 640x480] [--batches 500,5000,10000,50000] [--reps 21]
        [--append docs/bench-log/DATE-COMMIT-trace.md]

``STAGE@T``: the frame at time code T (default: the middle of the stage's range). One
frame's G-buffer is prepared (hybrid, every reflector a candidate). Each reflector is
traced once alone to learn its rays; for each target batch size the reflectors whose rays
add up closest to it (within 0.7-1.3x, largest first) form one round. A round is timed
``--reps`` times as the renderer calls it (ray set-up, Embree, hit surfaces, shading with
shadow rays, bookkeeping: everything the budget is charged for), and after each the
exact float32 batches it gave Embree are replayed raw (``Bvh.replay_raw``: the same
``embreex`` calls on both BVHs, nothing else): share = raw ÷ ours, medians. The fixed
cost is the median round of the reflector with the fewest rays. A batch size no
reflector set comes near is left out (a stage with small reflectors has no 50k round).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from phrt_usd.bench.bench_stage import append_log, stage_at
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.usd.stage import open_stage

#: A round stands for a target batch size when its rays are within these factors of it.
BATCH_TOLERANCE = (0.7, 1.3)


def _timed(call, reps: int) -> float:
    """Median seconds of ``call()`` over ``reps`` calls."""
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(stage_path: str, frame: float, width: int, height: int, batches, reps: int):
    """Rows (batch target, rays, reflectors, ours ms, raw ms, share) of one stage."""
    stage = open_stage(stage_path)
    options = RenderOptions(mode="hybrid", heuristic="all", budget_ms=None,
                            width=width, height=height)  # fmt: skip
    renderer = FrameRenderer(stage, options)
    try:
        prep = renderer.prepare(frame)
        tracer, gb, limit = renderer.tracer, prep.gbuffer, options.bounce_limit
        visible = [int(i) for i in renderer.scene.reflector_ids if prep.pixel_counts[i] > 0]
        rays = {i: tracer.trace_reflections(gb, [i], limit).rays for i in visible}

        def row(target, chosen):
            def ours():
                return tracer.trace_reflections(gb, chosen, limit)

            ours_s = _timed(ours, reps)
            tracer.record_rays = True
            raw_s = []
            for _ in range(reps):
                result = ours()
                raw_s.append(tracer.replay_raw()[1])
            tracer.record_rays = False
            raw = statistics.median(raw_s)
            return (target, result.rays, len(chosen), ours_s * 1e3, raw * 1e3, raw / ours_s)

        rows = []
        for target in batches:
            chosen, total = [], 0
            for i in sorted(visible, key=lambda i: -rays[i]):
                if total + rays[i] <= target * BATCH_TOLERANCE[1]:
                    chosen.append(i)
                    total += rays[i]
            if chosen and total >= target * BATCH_TOLERANCE[0]:
                rows.append(row(target, chosen))
        if visible:
            rows.append(row("fixed (fewest rays)", [min(visible, key=lambda i: rays[i])]))
        return rows
    finally:
        renderer.close()


def markdown(stage_path: str, frame: float, res: str, rows) -> str:
    lines = [
        f"#### {Path(stage_path).stem} {res}, frame {frame:g}",
        "",
        "| batch | rays | reflectors | ours ms | raw embreex ms | raw ÷ ours |",
        "|---|---|---|---|---|---|",
    ]
    for target, rays, n, ours, raw, share in rows:
        lines.append(f"| {target} | {rays:,} | {n} | {ours:.3f} | {raw:.3f} | {share:.0%} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stages", nargs="+", help="STAGE or STAGE@TIMECODE")
    ap.add_argument("--resolution", default="640x480")
    ap.add_argument("--batches", default="500,5000,10000,50000")
    ap.add_argument("--reps", type=int, default=21)
    ap.add_argument("--append", type=Path)
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    batches = [int(b) for b in args.batches.split(",")]
    text = []
    for spec in args.stages:
        stage_path, frame = stage_at(spec)
        rows = measure(stage_path, frame, width, height, batches, args.reps)
        text.append(markdown(stage_path, frame, args.resolution, rows))
    out = provenance_line(collect_for_tool(__file__, argv)) + "\n\n" + "\n".join(text)
    print(out)
    if args.append:
        append_log(args.append, "Trace batches", " ".join(sys.argv), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
