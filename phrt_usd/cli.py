"""The ``phrt`` command line (typer). Thin commands: parse options, call the library,
print. Domain errors (``PhrtError``) end as one ``error: ...`` line on stderr and a
non-zero exit code, never a traceback; see ``user_errors``.

Exit codes: 0 success; 1 the stage/prims have problems (validation errors, bad prim);
2 the input cannot be read (missing file, directory, not USD) or a bad option.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

import phrt_usd  # noqa: F401  (registers the schema plugin before any stage opens)
from phrt_usd.errors import PhrtError

EXIT_PROBLEMS = 1
EXIT_UNREADABLE = 2

app = typer.Typer(
    help="Heuristic hybrid rendering of USD stages (raster + selective ray-traced reflections).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


class UnreadableInput(PhrtError):
    """The input cannot be read at all (exit 2)."""


@contextlib.contextmanager
def user_errors(exit_code: int = EXIT_PROBLEMS) -> Iterator[None]:
    """Turn a PhrtError raised inside the block into ``error: <message>`` on stderr and
    ``typer.Exit(exit_code)`` (UnreadableInput always exits 2)."""
    try:
        yield
    except UnreadableInput as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EXIT_UNREADABLE) from None
    except PhrtError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exit_code) from None


def open_input(path: Path):
    """Open a stage for a command; unreadable input raises UnreadableInput."""
    from phrt_usd.validation import open_stage

    try:
        return open_stage(path)
    except PhrtError as exc:
        raise UnreadableInput(str(exc)) from None


def print_json(obj: dict) -> None:
    """One JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, indent=2, allow_nan=False) + "\n")


StageArg = Annotated[Path, typer.Argument(help="USD stage (.usda/.usdc/.usd/.usdz).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")]


@app.command()
def validate(stage: StageArg, json_out: JsonOpt = False) -> None:
    """Check the stage with USD's validators and the Phrt rules.

    Prints one line per problem (`ERROR /prim.attribute: ...`, `WARNING ...`). Exit 0 when
    there are no errors (warnings alone pass), 1 with errors, 2 if the stage is unreadable.
    """
    from phrt_usd.validation import validate_stage

    with user_errors():
        report = validate_stage(open_input(stage), str(stage))
    if json_out:
        print_json(report.as_dict())
    else:
        for issue in report.issues:
            typer.echo(issue.line(), err=issue.severity == "error")
        if report.ok:
            typer.echo(f"ok: {stage} ({len(report.warnings)} warning(s))")
    if not report.ok:
        raise typer.Exit(EXIT_PROBLEMS)


@app.command()
def inspect(stage: StageArg, json_out: JsonOpt = False) -> None:
    """Summarise reflectors, camera paths, render settings, lights and needed passes."""
    from phrt_usd.inspection import inspect_stage

    with user_errors():
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
    in_place: Annotated[bool, typer.Option(help="Edit the stage's root layer itself.")] = False,
) -> None:
    """Apply PhrtReflectorAPI with priority K to PRIMS, in a new layer over the stage."""
    from phrt_usd.authoring import author_reflectors

    with user_errors():
        open_input(stage)  # unreadable input -> exit 2 before anything else
        result = author_reflectors(stage, prims, priority, reflectivity, out, in_place)
    typer.echo(f"wrote {result.layer}: {len(result.prims)} reflector(s)")


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g}"


def _print_summary(s: dict) -> None:
    console = Console()
    m = s["metadata"]
    console.print(
        f"[bold]{s['stage']}[/bold]  upAxis {m['upAxis']}, metersPerUnit {m['metersPerUnit']}, "
        f"time codes {m['startTimeCode']:g}..{m['endTimeCode']:g} "
        f"@ {m['timeCodesPerSecond']:g}/s"
    )
    table = Table(title=f"Reflectors ({len(s['reflectors'])})")
    for col in ("path", "K", "F", "triangles", "bounds min (m)", "bounds max (m)"):
        table.add_column(col)
    for r in s["reflectors"]:
        b = r["bounds"]
        lo = "-" if b["min_m"] is None else ", ".join(_fmt(x) for x in b["min_m"])
        hi = "-" if b["max_m"] is None else ", ".join(_fmt(x) for x in b["max_m"])
        tris = "-" if r["triangles"] is None else str(r["triangles"])
        table.add_row(r["path"], _fmt(r["priority"]), _fmt(r["reflectivity"]), tris, lo, hi)
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
    console.print(f"Lights: {lights}")
    console.print(f"Passes: {', '.join(s['passes'])}")
