"""Startup benchmark: how long ``phrt render`` takes from the command's start to its first
image file, and the first frame against the steady ones, on a small stage made here.

    uv run python tools/bench_startup.py [--runs 5] [--frames 10] [--threads N]
        [--gl auto|egl|osmesa] [--append docs/bench-log/DATE-COMMIT-startup.md]

Each run is a fresh ``phrt render STAGE --frames 1:F --out DIR --overwrite -q --json``
subprocess (the venv's ``phrt`` script). Measured per run: *first image*: the
modification time of the first frame's first file (written through the atomic writer,
so its last write) minus the wall clock just before the process was started; *command*:
the whole command's wall time and its CPU time (user + sys of the child, all threads:
less sensitive than wall time to other processes on a shared machine); from
``stats.json``: the first frame's ``frame_ms`` and the median of the others (*steady*).
Printed: medians over the runs.

Two Python set-ups, since a cold interpreter recompiles every module it imports unless
bytecode is cached: *cached* (``PYTHONPYCACHEPREFIX`` in a directory of this tool's,
``PYTHONDONTWRITEBYTECODE`` unset, one unrecorded run first: what an installed phrt
sees from its second start on) and *as is* (this environment unchanged; here
PYTHONDONTWRITEBYTECODE=1 is set, so every run compiles everything).

The stage (written to a temporary directory): a 4 m mirror floor (2 triangles, a
reflector), a 1 m box (12 triangles), a DistantLight and a DomeLight, a camera moving
along +x over the frames, 320x240: a few dozen triangles.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
#: The stage's image size (the issue's small-stage case).
RESOLUTION = (320, 240)
#: Where the cached set-up keeps its bytecode (outside the repo and the venv).
PYCACHE = Path(tempfile.gettempdir()) / "phrt-bench-startup-pycache"


def make_stage(path: Path, frames: int) -> Path:
    """Write the small stage (see the module docstring) to ``path``."""
    from pxr import Gf, Usd, UsdGeom

    import phrt_usd  # noqa: F401  (registers the schema)
    from phrt_usd.bench.bench_stage import add_lights_and_camera
    from phrt_usd.usd import schema

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    floor.CreatePointsAttr([(-2, 0, -2), (-2, 0, 2), (2, 0, 2), (2, 0, -2)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateDisplayColorAttr([(0.3, 0.3, 0.3)])
    schema.apply_reflector(floor.GetPrim(), priority=1.0, reflectivity=0.8)
    box = UsdGeom.Cube.Define(stage, "/World/Box")
    box.CreateSizeAttr(1.0)
    box.CreateDisplayColorAttr([(0.8, 0.2, 0.1)])
    UsdGeom.Xformable(box).AddTranslateOp().Set(Gf.Vec3d(0, 0.5, 0))
    add_lights_and_camera(stage, frames, RESOLUTION, (-1.0, 1.0), 1.5, 5.0, -15.0, (-60, 30, 0))
    stage.GetRootLayer().Save()
    return path


def phrt_command() -> list[str]:
    """The venv's ``phrt`` script (what a user runs), else the CLI through typer."""
    script = Path(sys.executable).parent / "phrt"
    if script.exists():
        return [str(script)]
    return [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]


def environment(cached: bool) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYOPENGL_PLATFORM", None)  # the command chooses (--gl)
    if cached:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(PYCACHE)
    elif env.get("PYTHONPYCACHEPREFIX") == str(PYCACHE):
        del env["PYTHONPYCACHEPREFIX"]  # "as is" must not read this tool's cache
    return env


def one_run(stage: Path, out: Path, frames: int, extra: list[str], env: dict) -> dict:
    """One ``phrt render`` subprocess: seconds to its first image file and in all, and
    its first and steady frame ms (stats.json)."""
    command = [*phrt_command(), "-q", "render", str(stage), "--frames", f"1:{frames}",
               "--out", str(out), "--overwrite", "--json", *extra]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.time()
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    wall = time.time() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        raise SystemExit(f"phrt render failed ({done.returncode}): {done.stderr.strip()}")
    summary = json.loads(done.stdout)
    first_files = sorted((out / "frames").glob("0001.*"))
    first_image = min(p.stat().st_mtime for p in first_files) - start
    rows = json.loads((out / "stats.json").read_text())["frames"]
    frame_ms = [r["frame_ms"] for r in sorted(rows, key=lambda r: r["time"])]
    return {
        "first_image_s": first_image,
        "command_s": wall,
        "command_cpu_s": cpu,
        "first_ms": frame_ms[0],
        "steady_ms": statistics.median(frame_ms[1:]) if len(frame_ms) > 1 else None,
        "gl": summary.get("gl"),
        "threads": summary.get("threads"),
    }


def measure(stage: Path, work: Path, runs: int, frames: int, extra: list[str], cached: bool):
    env = environment(cached)
    if cached:  # fills the bytecode cache; not recorded
        one_run(stage, work / "warm", frames, extra, env)
    results = [one_run(stage, work / f"run{i}", frames, extra, env) for i in range(runs)]

    def med(key: str) -> float:
        return statistics.median(r[key] for r in results)

    return {
        "setup": "cached bytecode" if cached else "as is",
        "first_image_s": med("first_image_s"),
        "first_image_range": (
            min(r["first_image_s"] for r in results),
            max(r["first_image_s"] for r in results),
        ),  # fmt: skip
        "command_s": med("command_s"),
        "command_cpu_s": med("command_cpu_s"),
        "first_ms": med("first_ms"),
        "steady_ms": med("steady_ms"),
        "gl": results[0]["gl"],
        "threads": results[0]["threads"],
    }


def markdown(rows: list[dict], runs: int, frames: int, extra: list[str]) -> str:
    lines = [
        "| Python set-up | first image (median, range) | whole command | its CPU (user + sys) "
        "| first frame | steady frame (median) | first ÷ steady | GL | threads |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lo, hi = r["first_image_range"]
        lines.append(
            f"| {r['setup']} | {r['first_image_s']:.2f} s ({lo:.2f}–{hi:.2f}) | "
            f"{r['command_s']:.2f} s | {r['command_cpu_s']:.2f} s | {r['first_ms']:.1f} ms | "
            f"{r['steady_ms']:.1f} ms | "
            f"{r['first_ms'] / r['steady_ms']:.2f} | {r['gl']} | {r['threads']} |"
        )
    opts = " ".join(extra)
    head = (f"{runs} runs of `phrt -q render STAGE --frames 1:{frames} --overwrite --json"
            f"{' ' + opts if opts else ''}` per set-up; the small stage of "
            "`tools/bench_startup.py` (16 triangles, 320x240).")  # fmt: skip
    return head + "\n\n" + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--threads", type=int)
    parser.add_argument("--gl")
    parser.add_argument("--as-is", action="store_true", help="also the environment as is")
    parser.add_argument("--append", type=Path, help="append the table to this log file")
    args = parser.parse_args(argv)
    extra = [*(["--threads", str(args.threads)] if args.threads else []),
             *(["--gl", args.gl] if args.gl else [])]  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="phrt-startup-") as tmp:
        work = Path(tmp)
        stage = make_stage(work / "small.usda", args.frames)
        rows = [measure(stage, work, args.runs, args.frames, extra, cached=True)]
        if args.as_is:
            rows.append(measure(stage, work, args.runs, args.frames, extra, cached=False))
    from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

    record = collect_for_tool(__file__, argv, threads=args.threads, gl=args.gl)
    text = provenance_line(record) + "\n\n" + markdown(rows, args.runs, args.frames, extra)
    print(text)
    if args.append:
        from phrt_usd.bench.bench_stage import append_log

        command = "uv run python tools/bench_startup.py " + " ".join(argv or sys.argv[1:])
        append_log(args.append, "Startup", command, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
