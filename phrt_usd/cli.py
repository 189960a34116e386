"""The ``phrt`` command line (typer). Thin commands: parse options, call the library,
print. Domain errors (``PhrtError``) end as one ``error: ...`` line on stderr and a
non-zero exit code, never a traceback; see ``user_errors`` (``phrt_usd.cli_errors``).

Exit codes: 0 success; 1 the stage/prims have problems (validation errors, bad prim) or
the render failed (a frame or a file could not be written); 2 the input cannot be read
(missing file, directory, not USD) or an option is bad; 130 interrupted. With ``--json``
an error is one JSON object ``{"error": message, "code": exit code}`` on stdout (a usage
error too: ``cli_errors.JsonUsageErrors``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from phrt_usd.base import __version__
from phrt_usd.cli_errors import (
    EXIT_INTERRUPTED,
    EXIT_PROBLEMS,
    EXIT_UNREADABLE,
    JsonUsageErrors,
    fail,
    out_of_memory,
    print_json,
    ran_out_of_memory,
    user_errors,
)
from phrt_usd.errors import BadOption, PhrtError, UnreadableInput
from phrt_usd.model.render_options import OPTIONS

app = typer.Typer(
    help="Heuristic hybrid rendering of USD stages (raster + selective ray-traced reflections).",
    cls=JsonUsageErrors,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

#: How much commands print on stderr: 0 quiet (errors only), 1 progress, 2 every frame.
_VERBOSITY = {"level": 1}
#: Without a terminal, a progress line at most this often (seconds), and at the end.
PROGRESS_LINE_SECONDS = 5.0


def _version(value: bool) -> None:
    if value:
        typer.echo(f"phrt {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version."),
    ] = False,
    verbose: Annotated[
        bool, typer.Option("--verbose", "-v", help="A line on stderr for every frame.")
    ] = False,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No progress on stderr (errors only).")
    ] = False,
) -> None:
    """Heuristic hybrid rendering of USD stages (raster + selective ray-traced reflections)."""
    if verbose and quiet:
        raise fail("--verbose and --quiet exclude each other", EXIT_UNREADABLE)
    _VERBOSITY["level"] = 0 if quiet else 2 if verbose else 1


def open_input(path: Path, controls=None):
    """Open a stage for a command (composed with ``controls``, a ``StageControls``);
    unreadable input raises UnreadableInput."""
    from phrt_usd.usd.stage import open_usd

    try:
        return open_usd(path, controls)
    except PhrtError as exc:
        raise UnreadableInput(str(exc)) from None


StageArg = Annotated[Path, typer.Argument(help="USD stage (.usda/.usdc/.usd/.usdz).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")]


@app.command()
def validate(stage: StageArg, json_out: JsonOpt = False) -> None:
    """Check the stage with USD's validators and the Phrt rules.

    Prints one line per problem (`ERROR /prim.attribute: ...`, `WARNING ...`). Exit 0 when
    there are no errors (warnings alone pass), 1 with errors, 2 if the stage is unreadable.
    """
    from phrt_usd.usd.validation import validate_stage

    with user_errors(json_out=json_out):
        report = validate_stage(open_input(stage), str(stage))
    if json_out:
        print_json(report.as_dict())
    else:
        for issue in report.issues:
            typer.echo(issue.line(), err=issue.severity == "error")
        if report.ok:
            typer.echo(
                f"ok: {stage} ({len(report.warnings)} warning(s); "
                f"{len(report.reflectors)} reflector(s), "
                f"{len(report.instanced_reflectors)} inside instances)"
            )
    if not report.ok:
        raise typer.Exit(EXIT_PROBLEMS)


@app.command()
def inspect(stage: StageArg, json_out: JsonOpt = False) -> None:
    """Summarise reflectors, camera paths, render settings, lights and needed passes."""
    from phrt_usd.usd.inspection import inspect_stage

    with user_errors(json_out=json_out):
        summary = inspect_stage(open_input(stage), str(stage))
    if json_out:
        print_json(summary)
    else:
        _print_summary(summary)


@app.command()
def author(
    stage: StageArg,
    prims: Annotated[list[str], typer.Argument(help="Gprim paths to mark as reflectors.")],
    priority: Annotated[float, typer.Option(help="Designer priority K (finite, >= 0).")],
    reflectivity: Annotated[
        float | None, typer.Option(help="Reflectivity F in [0, 1] (schema fallback: 1).")
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Layer to write (default: <stage stem>.phrt.usda).")
    ] = None,
    in_place: Annotated[
        bool, typer.Option(help="Edit the stage's root layer itself, in its own format.")
    ] = False,
    force: Annotated[
        bool,
        typer.Option(help="Overwrite an existing overlay (never the stage or a layer it uses)."),
    ] = False,
    on_prototype: Annotated[
        bool,
        typer.Option(
            help="A prim inside an instance: author on its prototype (a class every "
            "instance of it inherits), so every instance gets the reflector."
        ),
    ] = False,
) -> None:
    """Apply PhrtReflectorAPI with priority K to PRIMS, in a new layer over the stage."""
    from phrt_usd.atomic import WriteFailed
    from phrt_usd.usd.authoring import author_reflectors

    with user_errors():
        open_input(stage)  # unreadable input -> exit 2 before anything else
        try:
            result = author_reflectors(
                stage,
                prims,
                priority,
                reflectivity,
                out=out,
                in_place=in_place,
                force=force,
                on_prototype=on_prototype,
            )
        except WriteFailed as exc:  # its one output cannot be written: a bad --out, 2
            raise BadOption(str(exc)) from None
    typer.echo(f"wrote {result.layer}: {len(result.prims)} reflector(s)")


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g}"


def _print_summary(s: dict) -> None:
    from rich.console import Console  # rich only where a table is printed: a cheap start
    from rich.table import Table

    console = Console()
    m = s["metadata"]
    console.print(
        f"[bold]{s['stage']}[/bold]  upAxis {m['upAxis']}, metersPerUnit {m['metersPerUnit']}, "
        f"time codes {m['startTimeCode']:g}..{m['endTimeCode']:g} "
        f"@ {m['timeCodesPerSecond']:g}/s"
    )
    inside = s.get("instanced_reflectors", 0)
    title = f"Reflectors ({len(s['reflectors'])}"
    title += f", {inside} inside instances)" if inside else ")"
    table = Table(title=title)
    for col in ("path", "K", "F", "triangles", "bounds min (m)", "bounds max (m)"):
        table.add_column(col)
    for r in s["reflectors"]:
        b = r["bounds"]
        lo = "-" if b["min_m"] is None else ", ".join(_fmt(x) for x in b["min_m"])
        hi = "-" if b["max_m"] is None else ", ".join(_fmt(x) for x in b["max_m"])
        tris = "-" if r["triangles"] is None else str(r["triangles"])
        where = r["path"] + (f" (prototype {r['prototype']})" if r.get("prototype") else "")
        if r.get("point_instancer"):
            where += f" ({r['instances']} instances of {r['point_instancer']})"
        table.add_row(where, _fmt(r["priority"]), _fmt(r["reflectivity"]), tris, lo, hi)
    console.print(table)
    paths = Table(title=f"Camera paths ({len(s['camera_paths'])})")
    for col in ("path", "camera", "frames", "control points", "interpolation"):
        paths.add_column(col)
    for c in s["camera_paths"]:
        paths.add_row(
            c["path"],
            str(c["camera"]),
            f"{c['start']:g}..{c['end']:g}",
            str(c["control_points"]),
            c["interpolation"],
        )
    console.print(paths)
    rs = s["render_settings"]
    console.print(
        "Render settings: "
        + ", ".join(f"{k}={v}" for k, v in rs.items())
        + ("" if rs["settings_path"] else "  (defaults: no RenderSettings prim)")
    )
    lights = ", ".join(f"{li['type']} {li['path']}" for li in s["lights"]) or "none"
    if s.get("default_light_rig"):
        lights += " (rendered with the default light rig: a dim dome and a headlight)"
    console.print(f"Lights: {lights}")
    cam = s.get("camera") or {}
    if cam.get("path"):
        driven = f", driven by {cam['driven_by']}" if cam.get("driven_by") else ""
        line = f"Camera: {cam['path']} ({cam['source']}{driven})"
        console.print(line, highlight=False, markup=False)
    elif cam.get("problem"):
        console.print(f"Camera: refused: {cam['problem']}", highlight=False, markup=False)
    console.print(f"Passes: {', '.join(s['passes'])}")
    support = s.get("support", [])
    console.print(f"Not supported or approximated ({len(support)} kinds):" if support else
                  "Not supported or approximated: nothing found")  # fmt: skip
    from phrt_usd.usd.support_report import support_lines

    for line in support_lines(support):
        console.print(f"  {line}", highlight=False, markup=False)


#: The demo stage rendered when `phrt render` is given no stage: the package's copy
#: (``phrt_usd/demo/``, which the wheel holds: pyproject.toml), else the checkout's.
DEMO_STAGE = next(
    (p for p in (Path(__file__).resolve().parent / "demo" / "farm.usda",
                 Path(__file__).resolve().parent.parent / "stages" / "farm.usda") if p.is_file()),
    Path(__file__).resolve().parent / "demo" / "farm.usda",
)  # fmt: skip


def _progress():
    """Progress on stderr: a rich bar on a terminal; elsewhere (farm logs, CI) plain
    lines ``render farm.usda: 12/120 frames (10 %)`` every PROGRESS_LINE_SECONDS and at
    the end, or for every frame with ``-v``; nothing with ``-q``."""
    level = _VERBOSITY["level"]
    if sys.stderr.isatty() and level == 1:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

        return Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            console=Console(stderr=True),
        )
    return _LineProgress(enabled=level > 0, every_frame=level == 2)


class _LineProgress:
    """The part of rich's Progress the commands use, as plain stderr lines."""

    def __init__(self, enabled: bool, every_frame: bool) -> None:
        self.enabled, self.every_frame = enabled, every_frame
        self.tasks: dict[int, list] = {}  # id -> [description, total, last printed, done]

    def __enter__(self) -> _LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def add_task(self, description: str, total: float | None = None) -> int:
        self.tasks[len(self.tasks)] = [description, total, 0.0, 0]
        return len(self.tasks) - 1

    def update(self, task: int, completed: int, total: float | None = None) -> None:
        entry = self.tasks[task]
        entry[1] = total if total is not None else entry[1]
        entry[3] = completed
        now = time.monotonic()
        finished = entry[1] is not None and completed >= entry[1]
        if not self.enabled or not (
            self.every_frame or finished or now - entry[2] >= PROGRESS_LINE_SECONDS
        ):
            return
        entry[2] = now
        total = entry[1]
        share = f" ({100.0 * completed / total:.0f} %)" if total else ""
        shown = f"{completed}/{int(total)}" if total else f"{completed}"
        typer.echo(f"{entry[0]}: {shown} frames{share}", err=True)


def _render_option(name: str, more_help: str = "") -> typer.models.OptionInfo:
    """The option of render option ``name``: its help and how its value shows, as the
    table declares them (``model.render_options.OPTIONS``); ``more_help`` follows."""
    option = OPTIONS[name]
    return typer.Option(help=f"{option.help}{more_help}", metavar=option.metavar)


# The render options of `render` and `sweep`, declared once (model.render_options).
ModeOpt = Annotated[str | None, _render_option("mode")]
HeuristicOpt = Annotated[str | None, _render_option("heuristic")]
BudgetMsOpt = Annotated[float | None, _render_option("budget_ms")]
BudgetRaysOpt = Annotated[int | None, _render_option("budget_rays")]
TargetFpsOpt = Annotated[float | None, _render_option("target_fps")]
ResolutionOpt = Annotated[str | None, _render_option("width")]  # WxH: width and height
BounceLimitOpt = Annotated[int | None, _render_option("bounce_limit")]
SelectionWeightOpt = Annotated[float | None, _render_option("selection_weight")]
ThreadsOpt = Annotated[str | None, _render_option("threads")]  # text: parse_threads
GlOpt = Annotated[str | None, _render_option("gl")]
PrimaryOpt = Annotated[str | None, _render_option("primary")]
TraceDensityOpt = Annotated[str | None, _render_option("trace_density")]
ScreenSpaceOpt = Annotated[str | None, _render_option("screen_space")]
ExposureOpt = Annotated[float | None, _render_option("exposure")]
WorkersOpt = Annotated[
    int | None,
    typer.Option(help="Start a Dask LocalCluster of N worker processes (docs/cluster.md)."),
]
SchedulerOpt = Annotated[
    str | None, typer.Option(help="Send chunks to a running Dask scheduler (tcp://host:8786).")
]
ChunkFramesOpt = Annotated[
    int | None, typer.Option(help="Frames recorded per cluster task (default 96).")
]
WarmupOpt = Annotated[
    int | None, typer.Option(help="Unrecorded frames before each chunk (default 8).")
]


@app.command()
def render(
    stage: Annotated[
        Path | None, typer.Argument(help="USD stage (default: the demo stage farm.usda).")
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")] = Path("out"),
    frames: Annotated[
        str | None, typer.Option(help="A:B[:STEP] in stage time codes, both ends included.")
    ] = None,
    mode: ModeOpt = None,
    heuristic: HeuristicOpt = None,
    budget_ms: BudgetMsOpt = None,
    budget_rays: BudgetRaysOpt = None,
    target_fps: TargetFpsOpt = None,
    resolution: ResolutionOpt = None,
    bounce_limit: BounceLimitOpt = None,
    selection_weight: SelectionWeightOpt = None,
    camera: Annotated[
        str | None,
        typer.Option(help="Camera prim path, or the name of a camera prim (unique on the stage)."),
    ] = None,
    session_layer: Annotated[
        list[Path] | None,
        typer.Option(help="A session layer over the stage (repeatable, strongest first)."),
    ] = None,
    variant: Annotated[
        list[str] | None,
        typer.Option(help="A variant selection PRIM:SET=NAME (repeatable)."),
    ] = None,
    mask: Annotated[
        str | None, typer.Option(help="Populate only these prims: PRIM,PRIM,...")
    ] = None,
    selection_layer: Annotated[
        Path | None, typer.Option(help="Selection layer (default OUT/selection.usda).")
    ] = None,
    resume: Annotated[
        bool, typer.Option(help="Continue the interrupted render in OUT (same run only).")
    ] = False,
    overwrite: Annotated[
        bool, typer.Option(help="Replace phrt's files in a non-empty OUT (others stay).")
    ] = False,
    images: Annotated[bool, typer.Option(help="Write EXR + PNG per frame.")] = True,
    settings: Annotated[
        str | None,
        typer.Option(help="RenderSettings prim (default: the stage's renderSettingsPrimPath)."),
    ] = None,
    image: Annotated[
        str | None,
        typer.Option(help="File name TEMPLATE under OUT instead of the products (a.####.exr)."),
    ] = None,
    aovs: Annotated[
        str | None,
        typer.Option(help="Passes added to every EXR: P,N,albedo,motion,pixelKind,..."),
    ] = None,
    timestamp: Annotated[
        bool, typer.Option(help="Write the wall-clock capDate into EXR headers.")
    ] = False,
    strict: Annotated[
        bool,
        typer.Option(help="An unreadable texture is an error (exit 1), not a warning."),
    ] = False,
    exposure: ExposureOpt = None,
    threads: ThreadsOpt = None,
    gl: GlOpt = None,
    primary: PrimaryOpt = None,
    trace_density: TraceDensityOpt = None,
    screen_space: ScreenSpaceOpt = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    chunk_frames: ChunkFramesOpt = None,
    warmup: WarmupOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Render the stage's camera path: images, stats.json and the selection layer."""
    from phrt_usd.api import render_job, run_render
    from phrt_usd.load_line import LoadLine
    from phrt_usd.progress import step as progress_step
    from phrt_usd.run.products import parse_aovs
    from phrt_usd.run.render_job import RenderInterrupted
    from phrt_usd.threads import parse_threads
    from phrt_usd.usd.stage_controls import StageControls

    stage = stage or DEMO_STAGE
    # What the load is doing, on one stderr line once it takes over a second.
    load = LoadLine(stage.name, enabled=_VERBOSITY["level"] > 0 and not json_out)
    with user_errors(json_out=json_out), load:
        from phrt_usd.cluster import check_cluster_options

        # Before anything renders or starts: exit 2 for a bad combination or value.
        check_cluster_options(workers, scheduler, chunk_frames, warmup, resume)
        controls = StageControls.from_options(session_layer or (), variant or (), mask)
        job, scene = render_job(  # options as the Python API takes them (phrt_usd.api)
            open_input(stage, controls),
            out,
            frames,
            stage_path=stage,
            controls=controls,
            mode=mode,
            heuristic=heuristic,
            resolution=resolution,
            budget_ms=budget_ms,
            budget_rays=budget_rays,
            target_fps=target_fps,
            bounce_limit=bounce_limit,
            selection_weight=selection_weight,
            camera=camera,
            selection_layer=selection_layer,
            resume=resume,
            overwrite=overwrite,
            write_images=images,
            settings=settings,
            image=image,
            aovs=parse_aovs(aovs),
            timestamp=timestamp,
            strict=strict,
            threads=None if threads is None else parse_threads(threads),
            gl=gl,
            primary=primary,
            trace_density=trace_density,
            screen_space=screen_space,
            exposure=exposure,
        )
        if scene.warnings:
            load.erase()
        for warning in scene.warnings:
            typer.echo(f"warning: {warning}", err=True)
        warned = len(scene.warnings)
        cluster = {name: value for name, value in (
            ("workers", workers), ("scheduler", scheduler), ("chunk_frames", chunk_frames),
            ("warmup", warmup)) if value is not None}  # fmt: skip
        progress_step("setting up the renderer")
        progress = _progress()
        task = progress.add_task(f"render {stage.name}", total=None)
        live = not isinstance(progress, _LineProgress)  # a live bar: the load line goes in it
        if live:
            load.hand_over(lambda text: progress.update(task, description=text))
        with progress:
            finished = [0]  # frames done so far: where memory ran out, if it does

            def on_frame(done: int, total: int, _stats) -> None:
                finished[0] = done
                if not load.finished:  # the first frame: the load is over
                    load.finish()
                    if live:
                        progress.update(task, description=f"render {stage.name}")
                progress.update(task, completed=done, total=total)

            try:
                summary = run_render(job, on_frame=on_frame, stage_scene=scene, **cluster)
            except RenderInterrupted as exc:
                raise fail(f"interrupted: {exc}", EXIT_INTERRUPTED, json_out) from None
            except Exception as exc:  # memory running out, in numpy or in OpenGL
                if not ran_out_of_memory(exc):
                    raise
                message = out_of_memory(job, scene, finished[0])
                raise fail(message, EXIT_PROBLEMS, json_out) from None
    for warning in summary["warnings"][warned:]:  # found while rendering (e.g. clipping)
        typer.echo(f"warning: {warning}", err=True)
    if json_out:
        print_json(summary)
    else:
        _print_render_summary(summary)


def _print_render_summary(summary: dict) -> None:
    """A render's summary as text: the report, the trace note, the trace budget's use
    and what was written."""
    from rich.console import Console

    from phrt_usd.evaluate.report import print_report

    print_report(summary, Console())
    if summary.get("trace_note"):
        typer.echo(f"note: {summary['trace_note']}")
    if summary.get("mean_budget_use") is not None:
        use = summary["mean_budget_use"]
        line = f"trace budget use: {use:.0%} of T (mean, frames with reflectors in view)"
        if summary.get("budget_bound_use") is not None:
            line += (
                f"; {summary['budget_bound_use']:.0%} in the "
                f"{summary['budget_bound_frames']} frames that left one untraced"
            )
        typer.echo(line)
    typer.echo(_written(summary))


def _written(summary: dict) -> str:
    """``wrote OUT: images frames/$F4.exr, frames/$F4.png (per frame), stats.json, ...``."""
    names = summary.get("images") or []
    images = f"images {', '.join(names)} (per frame), " if names else ""
    return f"wrote {summary['out']}: {images}stats.json, {summary['selection_layer']}"


@app.command()
def report(
    run: Annotated[Path, typer.Argument(help="Run directory or selection layer.")],
    vs: Annotated[Path | None, typer.Option(help="Another run to compare with.")] = None,
    json_out: JsonOpt = False,
) -> None:
    """The paper's metrics (transitions, mean selected, fps, overruns) of a run."""
    from rich.console import Console

    from phrt_usd.evaluate.report import build_report, print_report

    # Every problem report meets is a run it cannot read: exit 2.
    with user_errors(EXIT_UNREADABLE, json_out=json_out):
        result = build_report(run, vs)
    if json_out:
        print_json(result)
    else:
        print_report(result, Console())


@app.command()
def sweep(
    stages: Annotated[list[Path], typer.Argument(help="USD stages.")],
    heuristics: Annotated[str, typer.Option(help="Comma list of heu1, heu2.")] = "heu1,heu2",
    budgets_ms: Annotated[
        str | None, typer.Option(help="Comma list of trace budgets in ms (inf allowed).")
    ] = None,
    budgets_rays: Annotated[
        str | None, typer.Option(help="Comma list of trace budgets in rays.")
    ] = None,
    frames: Annotated[str | None, typer.Option(help="A:B[:STEP] time codes.")] = None,
    resolution: Annotated[str, _render_option("width")] = (
        f"{OPTIONS['width'].default}x{OPTIONS['height'].default}"
    ),
    bounce_limit: Annotated[int, _render_option("bounce_limit")] = OPTIONS["bounce_limit"].default,
    bounce_limits: Annotated[
        str | None,
        typer.Option(help="Comma list of bounce limits to sweep (e.g. 0,1,2,5); replaces "
                     "--bounce-limit."),
    ] = None,
    resolutions: Annotated[
        str | None,
        typer.Option(help="Comma list of WxH to sweep (e.g. 160x120,320x240); replaces "
                     "--resolution."),
    ] = None,
    trace_densities: Annotated[
        str | None,
        typer.Option(help="Comma list of trace densities to sweep (full,half,quarter,sixteenth; "
                     "default full): the policies' hybrid frames; the references trace "
                     "every pixel."),
    ] = None,
    selection_weight: Annotated[
        float | None, _render_option("selection_weight", " Default: the first stage's setting.")
    ] = None,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory (empty, or --overwrite).")
    ] = Path("sweep"),
    overwrite: Annotated[
        bool,
        typer.Option(help="Replace an earlier sweep's files in a non-empty OUT (others stay; "
                     "a sweep cannot be resumed)."),
    ] = False,
    exposure: ExposureOpt = None,
    threads: ThreadsOpt = None,
    gl: GlOpt = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    chunk_frames: ChunkFramesOpt = None,
    warmup: WarmupOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Error against run time: every heuristic x budget (x bounce limit x resolution x
    trace density) against the `all` and `rt` references of the same bounce limit and
    resolution: per
    frame FLIP, PSNR, the temporal error (popping) and transitions; writes sweep.csv,
    provenance.json, summary.md, error_vs_time.png and report.html."""
    from phrt_usd.api import cluster_chunking, parse_resolution
    from phrt_usd.evaluate.sweep import (
        SweepSpec,
        interruption_note,
        parse_budget_list,
        parse_int_list,
        parse_resolution_list,
        run_sweep,
    )
    from phrt_usd.evaluate.sweep_output import claim_sweep_out
    from phrt_usd.threads import parse_threads
    from phrt_usd.usd.schema import read_render_params

    with user_errors(json_out=json_out):
        opened = [open_input(path) for path in stages]  # all readable before starting
        weight = selection_weight
        if weight is None:
            weight = read_render_params(opened[0]).selection_weight
        width, height = parse_resolution(resolution)
        spec = SweepSpec(
            stages=stages,
            heuristics=[h.strip() for h in heuristics.split(",") if h.strip()],
            budgets_ms=parse_budget_list(budgets_ms, float),
            budgets_rays=parse_budget_list(budgets_rays, int),
            frames=frames,
            width=width,
            height=height,
            bounce_limit=bounce_limit,
            selection_weight=weight,
            out=out,
            overwrite=overwrite,
            bounce_limits=parse_int_list(bounce_limits, "--bounce-limits"),
            resolutions=parse_resolution_list(resolutions),
            trace_densities=[d.strip() for d in (trace_densities or "").split(",") if d.strip()],
            # The options given; SweepSpec checks every value by its option (OPTIONS).
            **({} if threads is None else {"threads": parse_threads(threads)}),
            **({} if gl is None else {"gl": gl}),
            **({} if exposure is None else {"exposure": exposure}),
        )
        progress = _progress()
        with progress:
            tasks: dict[str, int] = {}

            def on_frame(stage_name: str, done: int, total: int) -> None:
                if stage_name not in tasks:
                    tasks[stage_name] = progress.add_task(f"sweep {stage_name}", total=total)
                progress.update(tasks[stage_name], completed=done)

            if workers is None and scheduler is None:
                summary = run_sweep(spec, on_frame=on_frame)
            else:
                claim_sweep_out(spec.out, spec.overwrite)  # refused or cleared before a cluster
                from phrt_usd.cluster import dask_client, run_sweep_on_cluster

                with dask_client(workers, scheduler) as client:
                    summary = run_sweep_on_cluster(
                        spec,
                        client,
                        on_chunk=lambda done, total: on_frame("chunks", done, total),
                        **cluster_chunking(chunk_frames, warmup),
                    )
    if summary["interrupted"]:
        raise fail(f"interrupted: {interruption_note(summary)}", EXIT_INTERRUPTED, json_out)
    if json_out:
        print_json(summary)
    else:
        typer.echo(f"wrote {summary['rows']} rows and the report to {summary['out']}")


@app.command()
def kernels(
    check: Annotated[
        bool, typer.Option("--check", help="Exit 1 when a kernel was not compiled already.")
    ] = False,
) -> None:
    """Compile the renderer's kernels into their cache ahead of the first render (once per
    installation, about 20 s), or check that they are there."""
    from phrt_usd import kernels as compiled

    raise typer.Exit(compiled.main(["--check"] if check else []))

