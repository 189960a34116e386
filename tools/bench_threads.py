"""Thread scaling: the same frames rendered with ``--threads 1`` and ``--threads 2`` (or
``--threads-list``), alternating, in one run.

    uv run python tools/bench_threads.py stages/farm.usda stages/sewer.usda \
        --resolutions 320x240,640x480 --frames 541:580 --rounds 3 \
        [--append docs/bench-log/DATE-COMMIT-threads.md]

A thread setting is per process where it matters (llvmpipe reads ``LP_NUM_THREADS`` once,
when the process's first GL context is made), so every (stage, resolution, setting,
round) is its own ``phrt -q render STAGE --frames F --resolution WxH --mode M
--heuristic H --budget-ms T --threads N --json`` subprocess; settings alternate within
each round so that the machine's load drifts over all of them alike. Per run: the median
``frame_ms`` and phase times over its frames after the first (stats.json; the first
frame carries one-time work); per setting: the median over its rounds. Printed: medians,
fps, and each setting's speed-up over the first (median ms of the first ÷ median ms of
this one). The machine's load average is logged before and after: on a shared machine
other processes take cores from the threads being measured.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

PHASES = ("set_time", "gbuffer", "shade", "select", "trace")


def phrt_command() -> list[str]:
    """The venv's ``phrt`` script, else the CLI through typer."""
    script = Path(sys.executable).parent / "phrt"
    if script.exists():
        return [str(script)]
    return [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]


def one_run(stage: str, out: Path, args, resolution: str, threads: int) -> dict:
    """One render subprocess: median frame ms and phase ms over its frames after the
    first, and what it ran with (threads, llvmpipe threads, GL platform)."""
    command = [*phrt_command(), "-q", "render", stage, "--frames", args.frames,
               "--resolution", resolution, "--mode", args.mode, "--heuristic", args.heuristic,
               "--budget-ms", str(args.budget_ms), "--threads", str(threads),
               "--out", str(out), "--overwrite", "--json"]  # fmt: skip
    if args.gl:
        command += ["--gl", args.gl]
    env = dict(os.environ)
    env.pop("PYOPENGL_PLATFORM", None)  # the command chooses (--gl)
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=3600)
    if done.returncode != 0:
        raise SystemExit(f"phrt render failed ({done.returncode}): {done.stderr.strip()}")
    summary = json.loads(done.stdout)
    rows = sorted(json.loads((out / "stats.json").read_text())["frames"], key=lambda r: r["time"])
    steady = rows[1:] or rows
    return {
        "frame_ms": statistics.median(r["frame_ms"] for r in steady),
        "phases": {p: statistics.median(r["phase_ms"].get(p, 0.0) for r in steady) for p in PHASES},
        "frames": len(steady),
        "threads": summary["threads"],
        "llvmpipe": summary.get("llvmpipe_threads"),
        "gl": summary.get("gl"),
    }


def bench(stage: str, resolution: str, args, work: Path) -> list[dict]:
    runs: dict[int, list[dict]] = {n: [] for n in args.threads_list}
    for r in range(args.rounds):
        order = args.threads_list if r % 2 == 0 else args.threads_list[::-1]
        for n in order:
            runs[n].append(one_run(stage, work / f"t{n}-r{r}", args, resolution, n))
    rows = []
    for n in args.threads_list:
        rs = runs[n]
        rows.append({
            "threads": n,
            "frame_ms": statistics.median(x["frame_ms"] for x in rs),
            "spread": (min(x["frame_ms"] for x in rs), max(x["frame_ms"] for x in rs)),
            "phases": {p: statistics.median(x["phases"][p] for x in rs) for p in PHASES},
            "frames": rs[0]["frames"],
            "llvmpipe": rs[0]["llvmpipe"],
            "gl": rs[0]["gl"],
        })  # fmt: skip
    return rows


def markdown(stage: str, resolution: str, rows: list[dict], rounds: int) -> str:
    base = rows[0]["frame_ms"]
    lines = [
        f"#### {Path(stage).stem} {resolution} ({rows[0]['frames']} frames a run, "
        f"{rounds} runs a setting, alternating)",
        "",
        "| --threads | llvmpipe threads | GL | median frame ms (runs' range) | fps | "
        "phases ms (" + " / ".join(PHASES) + f") | speed-up over {rows[0]['threads']} |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lo, hi = row["spread"]
        phases = " / ".join(f"{row['phases'][p]:.1f}" for p in PHASES)
        lines.append(
            f"| {row['threads']} | {row['llvmpipe']} | {row['gl']} | {row['frame_ms']:.1f} "
            f"({lo:.1f}–{hi:.1f}) | {1000.0 / row['frame_ms']:.1f} | {phases} | "
            f"{base / row['frame_ms']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def load() -> str:
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "?"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stages", nargs="+")
    parser.add_argument("--resolutions", default="320x240")
    parser.add_argument("--frames", default="541:580", help="A:B[:STEP] time codes")
    parser.add_argument("--threads-list", default="1,2", help="settings to compare, first = base")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--mode", default="hybrid")
    parser.add_argument("--heuristic", default="heu1")
    parser.add_argument("--budget-ms", type=float, default=10.0)
    parser.add_argument("--gl", help="auto | egl | osmesa (default: phrt's)")
    parser.add_argument("--append", type=Path, help="append the tables to this log file")
    args = parser.parse_args(argv)
    args.threads_list = [int(v) for v in args.threads_list.split(",")]
    before = load()
    blocks = []
    with tempfile.TemporaryDirectory(prefix="phrt-threads-") as tmp:
        for stage in args.stages:
            for resolution in args.resolutions.split(","):
                rows = bench(stage, resolution, args, Path(tmp))
                block = markdown(stage, resolution, rows, args.rounds)
                print(block, flush=True)
                blocks.append(block)
    from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

    # The settings compared are in the tables; the record gives the rest of the machine.
    record = collect_for_tool(__file__, argv, gl=args.gl)
    note = f"load average (1 min) {before} before, {load()} after\n\n{provenance_line(record)}"
    print(note)
    if args.append:
        from phrt_usd.bench.bench_stage import append_log

        command = "uv run python tools/bench_threads.py " + " ".join(argv or sys.argv[1:])
        append_log(args.append, "Threads", command, f"{note}\n\n" + "\n".join(blocks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
