"""Reuse across frames measured (docs/temporal-reuse.md): a still view's convergence to
full density, and a moving sequence with and without reuse.

    uv run python tools/reuse_convergence.py stages/sewer.usda --still 241 \
        --moving 217-240 [--density sixteenth] [--resolution 320x240] [--json]

``--still T``: frame T rendered again and again by one renderer (a still camera over a
still scene: the rotating pattern's frames), every reflector traced at ``--density``;
per frame, mean FLIP against the same frame at full density, the trace ms and the pixel
kinds. ``--moving A-B``: the consecutive frames A..B at ``--density`` with reuse and
with reuse switched off (history never kept: the fill alone), in one run; the mean
FLIP of each against full density and their mean trace ms.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from phrt_usd.engine import reflection_history
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.usd.stage import open_stage


def _renderer(stage, density: str, width: int, height: int) -> FrameRenderer:
    options = RenderOptions(mode="hybrid", heuristic="all", budget_ms=None, width=width,
                            height=height, trace_density=density)  # fmt: skip
    return FrameRenderer(stage, options)


def still(stage, t: float, density: str, width: int, height: int, frames: int) -> list[dict]:
    full = _renderer(stage, "full", width, height).render(t).beauty
    renderer = _renderer(stage, density, width, height)
    rows = []
    for k in range(frames):
        out = renderer.render(t)
        rows.append({"frame": k + 1, "flip": float(flip_map(full, out.beauty).mean()),
                     "trace_ms": out.stats.trace_ms, "pixel_kinds": out.stats.pixel_kinds})
    return rows


def _sequence(stage, times, density, width, height):
    renderer = _renderer(stage, density, width, height)
    renderer.plan(times)
    return [renderer.render(t) for t in times]


def moving(stage, times, density: str, width: int, height: int) -> dict:
    full = _sequence(stage, times, "full", width, height)
    reused = _sequence(stage, times, density, width, height)
    keep = reflection_history.ReflectionHistory.end
    reflection_history.ReflectionHistory.end = lambda self, reuse: None  # the fill alone
    try:
        filled = _sequence(stage, times, density, width, height)
    finally:
        reflection_history.ReflectionHistory.end = keep

    def figures(outs):
        return {
            "flip": float(np.mean([flip_map(f.beauty, o.beauty).mean()
                                   for f, o in zip(full, outs, strict=True)])),  # fmt: skip
            "trace_ms": float(np.mean([o.stats.trace_ms for o in outs[1:]])),
            "reused_share": float(np.mean([o.stats.pixel_kinds["reused"] for o in outs[1:]])
                                  / max(np.mean([sum(o.stats.pixel_kinds[k] for k in (
                                      "traced", "reused", "filled")) for o in outs[1:]]), 1)),
        }  # fmt: skip

    return {"frames": [times[0], times[-1]], "reuse": figures(reused), "fill": figures(filled)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage")
    parser.add_argument("--still", type=float)
    parser.add_argument("--still-frames", type=int, default=17)
    parser.add_argument("--moving", help="A-B: consecutive time codes")
    parser.add_argument("--density", default="sixteenth")
    parser.add_argument("--resolution", default="320x240")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    width, height = (int(v) for v in args.resolution.split("x"))
    stage = open_stage(args.stage)
    out: dict = {"stage": args.stage, "density": args.density, "resolution": [width, height],
                 "provenance": collect_for_tool(__file__)}  # fmt: skip
    if args.still is not None:
        out["still"] = still(stage, args.still, args.density, width, height, args.still_frames)
    if args.moving:
        a, b = (int(v) for v in args.moving.split("-"))
        out["moving"] = moving(stage, [float(t) for t in range(a, b + 1)], args.density, width,
                               height)  # fmt: skip
    if args.json:
        print(json.dumps(out))
        return
    print(provenance_line(out["provenance"]))
    for row in out.get("still", []):
        print(f"still frame {row['frame']:2d}: FLIP {row['flip']:.4f}  trace "
              f"{row['trace_ms']:.1f} ms  {row['pixel_kinds']}")  # fmt: skip
    if "moving" in out:
        for name in ("reuse", "fill"):
            f = out["moving"][name]
            print(f"moving {args.moving} {name}: mean FLIP {f['flip']:.4f}  trace "
                  f"{f['trace_ms']:.2f} ms  reused {f['reused_share']:.1%}")  # fmt: skip


if __name__ == "__main__":
    main()
