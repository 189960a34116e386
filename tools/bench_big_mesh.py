"""Big-mesh benchmark: hybrid against rt (and raster) per phase on a stage of ~1M+
triangles made on the fly, plus the one-time set-up of each renderer.

    uv run python tools/bench_big_mesh.py [--cells 708] [--resolution 640x480]
        [--frames 6] [--threads N] [--append docs/bench-log/DATE-COMMIT-big-mesh.md]

The stage: a height-field ground of ``cells`` x ``cells`` quads (2 cells² triangles:
708 → 1.0M), a 2 m mirror (a reflector, 2 triangles) standing on it, a DistantLight and
a DomeLight, a camera moving along the mirror over ``frames`` frames. Each mode renders
in its own ``FrameRenderer`` (in this process; one warm-up frame untimed), timed per
phase (``FrameStats.phase_ms``), median over the frames; set-up is the renderer's
construction (GL context and upload, BVH build) and its load step (``plan``: the first
frame's raster phases, shadow maps, tables). "G-buffer" is the source each mode used
(``--primary``: the hybrid's default ``auto`` takes the rays here, on llvmpipe with more
triangles than pixels); the hybrid is run a second time with the raster id pass asked
for, to show what that costs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PHASES = ("set_time", "gbuffer", "shade", "select", "trace")
MODES = (
    ("raster", {"mode": "raster", "heuristic": "none", "budget_ms": None}),
    ("hybrid (all)", {"mode": "hybrid", "heuristic": "all", "budget_ms": None}),
    (
        "hybrid (all), --primary raster",
        {"mode": "hybrid", "heuristic": "all", "budget_ms": None, "primary": "raster"},
    ),
    ("rt", {"mode": "rt", "heuristic": "all", "budget_ms": None}),
)


def make_stage(path: Path, cells: int, frames: int, resolution: tuple[int, int]) -> Path:
    """Write the big stage (see the module docstring) to ``path`` (usdc: 1M triangles)."""
    from pxr import Usd, UsdGeom, Vt

    import phrt_usd  # noqa: F401  (registers the schema)
    from phrt_usd.bench.bench_stage import add_lights_and_camera
    from phrt_usd.usd import schema

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    n = cells + 1
    x, z = np.meshgrid(np.linspace(-20, 20, n), np.linspace(-20, 20, n))
    y = 0.3 * np.sin(x * 1.7) * np.cos(z * 1.3)
    points = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells))
    corner = (j * n + i).reshape(-1)
    quads = np.stack([corner, corner + n, corner + n + 1, corner + 1], axis=1)
    ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
    ground.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    ground.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(quads), 4, np.int32)))
    ground.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.reshape(-1).astype(np.int32)))
    ground.CreateDisplayColorAttr([(0.4, 0.6, 0.3)])
    ground.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mirror = UsdGeom.Mesh.Define(stage, "/World/Mirror")
    mirror.CreatePointsAttr([(-1, 0, 0), (1, 0, 0), (1, 2, 0), (-1, 2, 0)])
    mirror.CreateFaceVertexCountsAttr([4])
    mirror.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mirror.CreateDisplayColorAttr([(0.2, 0.2, 0.2)])
    mirror.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    add_lights_and_camera(stage, frames, resolution, (-2.0, 2.0), 2.0, 6.0, -12.0, (-50, 30, 0))
    stage.GetRootLayer().Save()
    return path


def bench(stage_path: Path, width: int, height: int, frames: int, threads: int | None):
    from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
    from phrt_usd.usd.stage import open_stage

    t = time.perf_counter()
    stage = open_stage(stage_path)
    read_s = time.perf_counter() - t
    times = [float(k) for k in range(1, frames + 1)]
    rows = []
    for label, opts in MODES:
        extra = {} if threads is None else {"threads": threads}
        options = RenderOptions(width=width, height=height, **opts, **extra)
        t = time.perf_counter()
        renderer = FrameRenderer(stage, options)
        renderer.plan(times)  # the load step (FrameRenderer.warm_up) belongs to set-up
        setup_s = time.perf_counter() - t
        t = time.perf_counter()
        renderer.render(times[0])  # warm-up: shadow maps, caches
        first_ms = (time.perf_counter() - t) * 1000.0
        frame_ms, phases = [], {p: [] for p in PHASES}
        for k in times[1:]:
            out = renderer.render(k)
            frame_ms.append(out.stats.frame_ms)
            for p in PHASES:
                phases[p].append(out.stats.phase_ms.get(p, 0.0))
        renderer.close()
        rows.append({
            "label": label, "primary": renderer.primary, "setup_s": setup_s, "first_ms": first_ms,
            "frame_ms": statistics.median(frame_ms),
            "phases": {p: statistics.median(v) for p, v in phases.items()},
        })  # fmt: skip
    return stage.scene.geometry.triangle_count, read_s, rows


def markdown(triangles: int, read_s: float, rows: list[dict], res: str, frames: int) -> str:
    rt = next(r for r in rows if r["label"] == "rt")["frame_ms"]
    lines = [
        f"{triangles:,} triangles, {res}, {frames - 1} timed frames a mode (stage read "
        f"{read_s:.1f} s)",
        "",
        "| mode | G-buffer | set-up s | first frame ms | median frame ms | phases ms ("
        + " / ".join(PHASES)
        + ") | ÷ rt |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        phases = " / ".join(f"{r['phases'][p]:.1f}" for p in PHASES)
        lines.append(
            f"| {r['label']} | {r['primary']} | {r['setup_s']:.2f} | {r['first_ms']:.0f} | "
            f"{r['frame_ms']:.1f} | {phases} | {r['frame_ms'] / rt:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=708)
    parser.add_argument("--resolution", default="640x480")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--threads", type=int)
    parser.add_argument("--append", type=Path)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    with tempfile.TemporaryDirectory(prefix="phrt-big-") as tmp:
        stage = make_stage(Path(tmp) / "big.usdc", args.cells, args.frames, (width, height))
        triangles, read_s, rows = bench(stage, width, height, args.frames, args.threads)
    from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

    record = collect_for_tool(__file__, argv, threads=args.threads)
    text = provenance_line(record) + "\n\n"
    text += markdown(triangles, read_s, rows, args.resolution, args.frames)
    print(text)
    if args.append:
        from phrt_usd.bench.bench_stage import append_log

        command = "uv run python tools/bench_big_mesh.py " + " ".join(argv or sys.argv[1:])
        append_log(args.append, f"Big mesh, {stage_note()}".rstrip(", "), command, text)
    return 0


def stage_note() -> str:
    try:
        return f"load {os.getloadavg()[0]:.1f}, "
    except OSError:
        return ""


if __name__ == "__main__":
    sys.exit(main())
