"""The paper's three tables (transitions HEU1/HEU2, mean selected, mean fps) for our
stages, from full camera-path renders with HEU1 and HEU2 under the same budget.

    uv run python tools/paper_tables.py stages/farm.usda stages/sewer.usda \
        --budget-rays 20000 [--budget-ms 10] [--frames A:B:STEP] [--out runs/paper] \
        [--append docs/bench-log/DATE-COMMIT-paper-tables.md]

Each stage × heuristic is one `phrt render` run (no images) into OUT/<stage>-<heu>;
the tables come from `phrt report` on those runs (`build_report(..., vs=...)`).
``--samples N`` renders the stage's whole camera path at N evenly spaced time codes
(the paper's paths run 10,000 frames; ours span 720 time codes) instead of ``--frames``.
``--append FILE`` also appends the tables, with the command, date and core count, to
FILE: a new log file in docs/bench-log/, see BENCHMARKS.md "How to measure".
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
from pathlib import Path

from phrt_usd.api import run_render
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.evaluate.report import build_report
from phrt_usd.run.render_job import RenderJob
from phrt_usd.usd.schema import read_render_params
from phrt_usd.usd.stage import open_stage

#: The paper's Tables 2–4 (GTX 760, OptiX; HEU1 / HEU2).
PAPER = {
    "farm": {"transitions_pct": 3.8, "selected": (5, 4), "fps": (25.4, 26.4), "surfaces": 17},
    "sewer": {"transitions_pct": 4.6, "selected": (15, 12), "fps": (21.8, 23.3), "surfaces": 33},
}


def run_pair(stage_path: Path, out: Path, args: argparse.Namespace) -> dict:
    stage = open_stage(stage_path)
    params = read_render_params(stage.stage)
    runs, use = {}, {}
    for heuristic in ("heu1", "heu2"):
        run_dir = out / f"{stage_path.stem}-{heuristic}"
        options = RenderOptions(
            mode="hybrid",
            heuristic=heuristic,
            width=args.width,
            height=args.height,
            budget_ms=args.budget_ms,
            budget_rays=args.budget_rays,
            selection_weight=params.selection_weight
            if args.selection_weight is None
            else args.selection_weight,
        )
        frames = args.frames
        if args.samples:
            start, end = stage.frame_range
            frames = f"{start!r}:{end!r}:{(end - start) / (args.samples - 1)!r}"
        job = RenderJob(stage_path, run_dir, options, frames=frames, write_images=False)
        summary = run_render(job, stage_scene=stage)
        use[heuristic] = {k: summary[k] for k in BUDGET_USE_KEYS}
        runs[heuristic] = run_dir
        print(f"done {stage_path.stem} {heuristic}", file=sys.stderr)
    report = build_report(runs["heu1"], runs["heu2"])
    report["budget_use"] = use
    return report


#: The run summary's budget-use figures (``phrt_usd.api.trace_summary``).
BUDGET_USE_KEYS = ("mean_budget_use", "budget_bound_frames", "budget_bound_use")


def _use(figures: dict) -> str:
    """"0.36 (0.43 in 360 frames that left a reflector untraced)", or "–" unbudgeted."""
    if figures["mean_budget_use"] is None:
        return "–"
    text = f"{figures['mean_budget_use']:.3f}"
    if figures["budget_bound_use"] is not None:
        text += (
            f" ({figures['budget_bound_use']:.3f} in the {figures['budget_bound_frames']} "
            "frames that left a reflector untraced)"
        )
    return text


def tables(reports: dict[str, dict]) -> str:
    lines = [
        "| stage | transitions HEU1 / HEU2 (ours) | paper | mean selected HEU1 / HEU2 (ours) "
        "| paper | mean fps HEU1 / HEU2 (ours) | paper | reflectors | frames |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in reports.items():
        b = r["vs"]
        paper = PAPER.get(name, {})
        # HEU1's transitions as a percentage of HEU2's, as `phrt report --vs` gives it.
        ratio = r["comparison"]["transitions_ratio_pct"]
        ratio = float("nan") if ratio is None else ratio
        lines.append(
            f"| {name} | {r['transitions']} / {b['transitions']} = {ratio:.1f} % "
            f"| {paper.get('transitions_pct', '–')} % "
            f"| {r['mean_selected']:.2f} / {b['mean_selected']:.2f} "
            f"| {' / '.join(str(v) for v in paper.get('selected', ()))} "
            f"| {r['mean_fps']:.1f} / {b['mean_fps']:.1f} "
            f"| {' / '.join(str(v) for v in paper.get('fps', ()))} "
            f"| {r['reflectors']} | {r['frames']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stages", nargs="+", type=Path)
    ap.add_argument("--budget-rays", type=int, default=None)
    ap.add_argument("--budget-ms", type=float, default=None)
    ap.add_argument("--selection-weight", type=float, default=None)
    ap.add_argument("--frames", default=None)
    ap.add_argument("--samples", type=int, default=None, help="N time codes over the path")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--out", type=Path, default=Path("runs/paper"))
    ap.add_argument("--append", type=Path, default=None)
    args = ap.parse_args(argv)
    reports = {s.stem: run_pair(s, args.out, args) for s in args.stages}
    from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

    text = provenance_line(collect_for_tool(__file__, argv)) + "\n\n" + tables(reports)
    for name, r in reports.items():
        text += (
            f"\n{name}: HEU1 transition rate {r['transition_rate']}, HEU2 "
            f"{r['vs']['transition_rate']}; budget overruns HEU1 {r['budget_overruns']}, "
            f"HEU2 {r['vs']['budget_overruns']} (within T+10 %: {r['budget_within_pct']} % / "
            f"{r['vs']['budget_within_pct']} %); budget use HEU1 "
            f"{_use(r['budget_use']['heu1'])}, HEU2 {_use(r['budget_use']['heu2'])}; "
            f"HEU1 density steps {r['density_steps']} (not transitions: a traced "
            f"reflector's trace density changed)\n"
        )
    print(text)
    if args.append:
        command = "uv run python tools/paper_tables.py " + " ".join(argv or sys.argv[1:])
        with open(args.append, "a") as fh:
            fh.write(
                f"\n### Paper tables, {datetime.date.today().isoformat()}, "
                f"{os.cpu_count()} cores\n\n`{command}`\n\n{text}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
