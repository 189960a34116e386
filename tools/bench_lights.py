"""The shade phase's time against the number of lights in view: a floor lit by N sphere
lights (``phrt_usd.bench.light_grid``: each floor point within reach of 1 to 4 of them,
whatever N), rendered from above at each size, and what the lights' cut-off costs the
image.

    uv run python tools/bench_lights.py [--lights 1,4,16,64] [--resolutions 320x240,640x480]
        [--modes raster,rt] [--frames 7] [--json] [--append docs/bench-log/FILE.md]

Per mode, N and size: the median over ``--frames`` renders of the same frame (after one
that builds the shadow maps) of ``FrameStats.phase_ms["shade"]`` (the direct light of
the G-buffer, its shadow lookups or rays and the raster fallback), its ratio to N = 1,
and the LocalLights reaching a covered pixel on average (range from intensity and
fall-off, ``shading.light_ranges``). Shading costs by the lights that reach each pixel
(``light_pass.LOOKUP_TILE``, ``shade_kernels.CULL_BLOCK_POINTS``), so the time grows
with that count, not with N.

The cut-off's error (``--window-error``, on by default): every LocalLight contributes 0
beyond its range, where its unshadowed irradiance falls to ``LIGHT_CUTOFF_IRRADIANCE``,
and ``range_window`` fades it there. Measured on the floor's pixels, unshadowed: the
direct light of every light with its window against plain 1/d² with no range, as the
mean and largest absolute difference per pixel (display units: a white surface facing
a unit DistantLight shows 1) and relative to the mean lit level.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from phrt_usd.bench.bench_stage import append_log
from phrt_usd.bench.light_grid import light_grid_stage
from phrt_usd.engine import shading
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.usd.stage import open_stage

#: Renders of the frame before those timed: the first builds the shadow maps.
WARM_UP_FRAMES = 1


def reaching(gb, lights) -> float:
    """Mean LocalLights whose range reaches a covered pixel of G-buffer ``gb``."""
    pos = gb.position[gb.covered]
    centres = np.array([li.position for li in lights.local]).reshape(-1, 3)
    ranges = shading.light_ranges(lights)[len(lights.distant) :]
    count = np.zeros(len(pos))
    for c, r in zip(centres, ranges, strict=True):
        count += ((pos - c) ** 2).sum(axis=1) < r * r
    return float(count.mean()) if len(pos) else 0.0


def window_error(gb, lights) -> dict:
    """The cut-off's error at the covered pixels of ``gb`` (see the module): mean and
    largest |windowed - unwindowed| direct light (Lambert, albedo 1, unshadowed, the
    brightest channel) and the mean lit level."""
    pos, nrm = gb.position[gb.covered], gb.normal[gb.covered].astype(np.float64)
    windowed, plain = np.zeros(len(pos)), np.zeros(len(pos))
    ranges = shading.light_ranges(lights)[len(lights.distant) :]
    for li, r in zip(lights.local, ranges, strict=True):
        to = li.position - pos
        d2 = np.maximum((to**2).sum(axis=1), shading.MIN_LIGHT_DISTANCE**2)
        cos = np.maximum((to * nrm).sum(axis=1) / np.sqrt(d2), 0.0)
        e = float(np.max(li.radiance)) * cos / d2
        plain += e
        windowed += e * shading.range_window(np.sqrt(d2), r)
    diff = np.abs(plain - windowed)
    return {
        "mean_abs": float(diff.mean()),
        "max_abs": float(diff.max()),
        "mean_level": float(plain.mean()),
        "relative": float(diff.mean() / max(plain.mean(), 1e-30)),
    }


def measure(mode: str, n: int, width: int, height: int, frames: int, directory: Path) -> dict:
    """Shade-phase figures of one light count at one size (see the module)."""
    path = light_grid_stage(directory / f"lights_{n}_{width}x{height}.usda", n, width, height)
    options = RenderOptions(mode=mode, heuristic="none", budget_ms=None, width=width,
                            height=height)  # fmt: skip
    renderer = FrameRenderer(open_stage(str(path)), options)
    try:
        for _ in range(WARM_UP_FRAMES):
            renderer.render(1.0)
        shade = [renderer.render(1.0).stats.phase_ms["shade"] for _ in range(frames)]
        gb = renderer.prepare(1.0).gbuffer
        lights = renderer.scene.lights
        return {
            "mode": mode, "lights": n, "resolution": [width, height],
            "shade_ms": float(np.median(shade)), "shade_ms_runs": shade,
            "reaching_per_pixel": reaching(gb, lights),
            "window_error": window_error(gb, lights),
        }  # fmt: skip
    finally:
        renderer.close()


def markdown(rows: list[dict], sizes: list[tuple[int, int]]) -> str:
    """The tables: shade ms by mode, N and size with ratios to N = 1; the cut-off's
    error by N."""
    names = [f"{w}x{h}" for w, h in sizes]
    head = "| mode | N | lights reaching a pixel | " + " | ".join(
        f"shade ms {s} | ÷ N=1" for s in names
    )
    lines = [head + " |", "|---" * (3 + 2 * len(names)) + "|"]
    by = {(r["mode"], r["lights"], tuple(r["resolution"])): r for r in rows}
    for mode in dict.fromkeys(r["mode"] for r in rows):
        counts = sorted({r["lights"] for r in rows if r["mode"] == mode})
        for n in counts:
            first = by[(mode, n, sizes[0])]
            cells = [mode, str(n), f"{first['reaching_per_pixel']:.2f}"]
            for size in sizes:
                ms, base = by[(mode, n, size)]["shade_ms"], by[(mode, counts[0], size)]["shade_ms"]
                cells += [f"{ms:.1f}", f"{ms / base:.2f}"]
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "| N | cut-off error: mean abs | largest abs | mean lit level | mean relative |",
              "|---|---|---|---|---|"]  # fmt: skip
    seen = set()
    for r in rows:
        if r["lights"] in seen or tuple(r["resolution"]) != sizes[-1]:
            continue
        seen.add(r["lights"])
        e = r["window_error"]
        lines.append(f"| {r['lights']} | {e['mean_abs']:.5f} | {e['max_abs']:.5f} | "
                     f"{e['mean_level']:.4f} | {100 * e['relative']:.2f} % |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lights", default="1,4,16,64", help="light counts, comma-separated")
    ap.add_argument("--resolutions", default="320x240,640x480")
    ap.add_argument("--modes", default="raster", help="render modes: raster, hybrid, rt")
    ap.add_argument("--frames", type=int, default=7, help="timed renders per row")
    ap.add_argument("--json", action="store_true", help="the figures as JSON")
    ap.add_argument("--append", type=Path, help="append the tables to this log file")
    args = ap.parse_args(argv)
    counts = [int(v) for v in args.lights.split(",")]
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.resolutions.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="phrt-bench-lights-") as tmp:
        for mode in args.modes.split(","):
            for width, height in sizes:
                for n in counts:
                    rows.append(measure(mode, n, width, height, args.frames, Path(tmp)))
                    print(f"{mode} {width}x{height} N={n}: {rows[-1]['shade_ms']:.1f} ms",
                          file=sys.stderr)  # fmt: skip
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    out = provenance_line(collect_for_tool(__file__, argv)) + "\n\n" + markdown(rows, sizes)
    print(out)
    if args.append:
        append_log(args.append, "Shade time against lights", " ".join(sys.argv), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
