"""The frame-rate rows of BENCHMARKS.md's current figures, re-measured in one run: each
figure from ``--runs`` runs of the peers benchmark, one value a cell (the median over the
runs) with its spread (the runs' lowest and highest), and the command that gives it.

    uv run python tools/current_figures.py stages/farm.usda stages/sewer.usda \
        [--resolutions 320x240,640x480] [--frames 1:720:24] [--budget-ms 10] [--runs 3] \
        [--json OUT.json] [--append docs/bench-log/DATE-COMMIT-figures.md]

Run it alone on the machine (nothing else running): it reads wall-clock times. Each run
is one ``tools/bench_peers.py --skip-mitsuba`` child process over the same frames
(default every 24th frame of the 720-frame paths), so the runs are as independent as
separate invocations. Per stage and resolution it reports:

* hybrid (HEU1 at T = ``--budget-ms``): median frame, fps, and ÷ pyrender's lit
  one-node render of the same triangles in the same run (``bench_peers.bench_pyrender``);
* raster-only's median frame and ÷ pyrender.

The trace phase's share of raw ``embreex`` per frame is ``bench_peers``' own figure on
consecutive frames: on frames 24 apart most frames calibrate the tracer afresh, whose
rays its replay counts but whose time is the ``calibrate`` phase's, not the trace's.

Targets: ``TARGET_FPS`` per resolution and ÷ pyrender ≤ 1 (docs/design.md §3).
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

from phrt_usd.bench.bench_stage import append_log
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

HERE = Path(__file__).resolve().parent
#: The frame-rate targets by resolution (docs/design.md §3).
TARGET_FPS = {"320x240": 30.0, "640x480": 15.0}


def one_run(stages: list[str], resolutions: str, frames: str, budget_ms: float) -> dict:
    """One ``bench_peers.py --skip-mitsuba`` child's JSON figures."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "peers.json"
        command = [sys.executable, str(HERE / "bench_peers.py"), *stages,
                   "--resolutions", resolutions, "--frames", frames,
                   "--budget-ms", str(budget_ms), "--skip-mitsuba", "--json", str(out)]  # fmt: skip
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        return json.loads(out.read_text())


def figures(run: dict) -> dict[str, dict[str, float]]:
    """Per "stage|WxH": the figures of one run."""
    got = {}
    for key, result in run.items():
        if "|" not in key or "ours" not in result:
            continue
        ours, pyrender = result["ours"], result["pyrender"]["frame_ms"]
        hybrid, raster = ours["hybrid"], ours["raster"]
        row = {
            "hybrid_ms": hybrid["frame_ms"],
            "fps": 1000.0 / hybrid["frame_ms"],
            "hybrid_per_pyrender": hybrid["frame_ms"] / pyrender,
            "raster_per_pyrender": raster["frame_ms"] / pyrender,
            "pyrender_ms": pyrender,
        }
        got[key] = row
    return got


def spread(values: list[float], fmt: str) -> str:
    """``median (lowest–highest)`` of the runs' values."""
    med = statistics.median(values)
    if len(values) == 1:
        return fmt.format(med)
    return f"{fmt.format(med)} ({fmt.format(min(values))}–{fmt.format(max(values))})"


def table(runs: list[dict[str, dict[str, float]]], budget_ms: float, command: str,
          commit: str, date: str) -> str:  # fmt: skip
    """The current-figures rows in BENCHMARKS.md's columns."""
    header = ("figure", "value (median of runs, lowest–highest)", "target", "met", "commit",
              "date", "command")  # fmt: skip
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for key in runs[0]:
        stage, res = key.split("|")
        name = f"{Path(stage).stem} {res.replace('x', '×')}"
        values = {f: [r[key][f] for r in runs if f in r[key]] for f in runs[0][key]}
        fps = statistics.median(values["fps"])
        ratio = statistics.median(values["hybrid_per_pyrender"])
        target = TARGET_FPS.get(res)
        met_fps = "—" if target is None else ("✓" if fps >= target else "✗")
        target_text = "reported" if target is None else f"≥ {target:g} fps"
        rows = [
            (f"real time, {name} (hybrid HEU1, T = {budget_ms:g} ms)",
             spread(values["fps"], "{:.1f}") + " fps", target_text, met_fps),
            (f"hybrid median frame ÷ pyrender, {name}",
             spread(values["hybrid_per_pyrender"], "{:.2f}"), "≤ 1",
             "✓" if ratio <= 1.0 else "✗"),
            (f"raster-only median frame ÷ pyrender, {name}",
             spread(values["raster_per_pyrender"], "{:.2f}"), "reported", "—"),
        ]  # fmt: skip
        for figure, value, target_cell, met in rows:
            cells = (figure, value, target_cell, met, commit, date, f"`{command}`")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stages", nargs="+")
    ap.add_argument("--resolutions", default="320x240,640x480")
    ap.add_argument("--frames", default="1:720:24", help="A:B[:STEP] or N (bench_peers)")
    ap.add_argument("--budget-ms", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None, help="write every run's figures here")
    ap.add_argument("--append", type=Path, default=None, help="append the table to this log")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    load_before = os.getloadavg()[0]
    runs = []
    for k in range(args.runs):
        runs.append(figures(one_run(args.stages, args.resolutions, args.frames, args.budget_ms)))
        print(f"run {k + 1} of {args.runs} done", file=sys.stderr)
    record = collect_for_tool(__file__, argv)
    command = "uv run python tools/current_figures.py " + " ".join(argv or sys.argv[1:])
    text = (
        f"load average (1 min) {load_before:.1f} before, {os.getloadavg()[0]:.1f} after\n\n"
        + provenance_line(record) + "\n\n"
        + table(runs, args.budget_ms, command, record.get("commit", "?")[:7],
                record.get("date", "?")[:10])
    )  # fmt: skip
    print(text)
    if args.json:
        record_json = json.dumps({"runs": runs, "provenance": record}, indent=1, default=str)
        args.json.write_text(record_json)
    if args.append:
        append_log(args.append, "Current figures", command, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
