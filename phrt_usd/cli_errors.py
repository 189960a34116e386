"""How the ``phrt`` command reports an error: its exit codes, the one ``error: ...`` line
on stderr or, with ``--json``, the one JSON object ``{"error": message, "code": exit
code}`` on stdout, never a traceback.

Exit codes: 0 success; 1 the stage/prims have problems (validation errors, bad prim) or
the render failed (a frame or a file could not be written, memory ran out); 2 the input
cannot be read (missing file, directory, not USD) or an option is bad (usage errors
too); 130 interrupted.

``fail`` reports one error, ``user_errors`` turns the library's errors into it, and
``JsonUsageErrors``, the command group, does so for click's usage errors when ``--json``
is among the arguments. ``ran_out_of_memory`` / ``out_of_memory`` name a render's
memory running out.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator

import typer
from typer.core import TyperGroup

from phrt_usd.errors import BadOption, PhrtError, UnreadableInput

EXIT_PROBLEMS = 1
EXIT_UNREADABLE = 2
EXIT_INTERRUPTED = 130

#: OpenGL's GL_OUT_OF_MEMORY: the raster phase's buffers did not fit.
GL_OUT_OF_MEMORY = 0x0505


def print_json(obj: dict) -> None:
    """One JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, indent=2, allow_nan=False) + "\n")


def fail(message: str, code: int, json_out: bool = False) -> typer.Exit:
    """Report ``message`` (one line: ``error: ...`` on stderr, or the JSON error object on
    stdout) and return the ``typer.Exit`` to raise."""
    message = " ".join(str(message).split())  # one line, whatever the source
    if json_out:
        print_json({"error": message, "code": code})
    else:
        typer.echo(f"error: {message}", err=True)
    return typer.Exit(code)


@contextlib.contextmanager
def user_errors(exit_code: int = EXIT_PROBLEMS, json_out: bool = False) -> Iterator[None]:
    """Turn an error raised inside the block into one line and an exit code (see the
    module docstring): UnreadableInput and BadOption exit 2, another PhrtError
    ``exit_code``, an OSError (a file phrt could not read or write) 1, memory running
    out 1, Ctrl-C 130."""
    try:
        yield
    except (UnreadableInput, BadOption) as exc:
        raise fail(str(exc), EXIT_UNREADABLE, json_out) from None
    except PhrtError as exc:
        raise fail(str(exc), exit_code, json_out) from None
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        raise fail(f"{where}{exc.strerror or exc}", EXIT_PROBLEMS, json_out) from None
    except KeyboardInterrupt:
        raise fail("interrupted", EXIT_INTERRUPTED, json_out) from None
    except MemoryError:
        message = "memory ran out; free memory, or ask for less"
        raise fail(message, EXIT_PROBLEMS, json_out) from None


#: click's UsageError, of the click typer parses with (recent typer has its own copy).
_UsageError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")


class JsonUsageErrors(TyperGroup):
    """The ``phrt`` command group. With ``--json`` among the arguments, a usage error
    (an unknown option or command, a missing or malformed value: what click would print
    as a box) is the one JSON error object on stdout, exit 2, as every error of a
    ``--json`` command is."""

    def make_context(self, info_name, args, parent=None, **extra):
        args = list(args)
        json_out = "--json" in args
        try:
            ctx = super().make_context(info_name, args, parent=parent, **extra)
        except _UsageError as error:
            if json_out:
                raise _usage_error(error) from None
            raise
        ctx.meta["phrt_json"] = json_out
        return ctx

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except _UsageError as error:
            if ctx.meta.get("phrt_json"):
                raise _usage_error(error) from None
            raise


def _usage_error(error: Exception) -> typer.Exit:
    """The JSON error object of a usage error (``JsonUsageErrors``), naming the command."""
    ctx = getattr(error, "ctx", None)
    where = ctx.command_path if ctx is not None else "phrt"
    return fail(f"{where}: {error.format_message()}", EXIT_UNREADABLE, json_out=True)


def ran_out_of_memory(error: Exception) -> bool:
    """``error`` says memory ran out: Python's MemoryError (numpy's too) or PyOpenGL's
    GLError of GL_OUT_OF_MEMORY."""
    if isinstance(error, MemoryError):
        return True
    return type(error).__name__ == "GLError" and getattr(error, "err", None) == GL_OUT_OF_MEMORY


def out_of_memory(job, scene, done: int) -> str:
    """One line: memory ran out in the render of ``job`` (a ``RenderJob`` of the stage
    read as ``scene``), at which frame (the one after the ``done`` finished ones) and
    resolution, and what to do about it."""
    from phrt_usd.run.frames import parse_frames

    times = parse_frames(job.frames, scene.frame_range)
    at = f"frame {times[done]:g}" if done < len(times) else "the run's records"
    size = f"{job.options.width}x{job.options.height}"
    return (
        f"memory ran out rendering {at} at {size} ({done} of {len(times)} frames finished "
        f"in {job.out_dir}); free memory or render at a smaller --resolution"
    )
