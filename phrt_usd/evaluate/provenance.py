"""Where a measurement came from: what a sweep or a benchmark records beside its figures so
that it can be reproduced and cited.

``collect`` gathers, at the time of the measurement:

- ``phrt_version`` and ``commit`` (the git commit of the source tree phrt runs from when
  that is a checkout of phrt-usd, with ``commit_dirty`` when it has uncommitted changes;
  ``"unknown"`` for an installed copy or without git);
- ``command``: the command line (shell-quoted);
- ``machine``: cores (all, and those this process may use), CPU model (``/proc/cpuinfo``,
  else ``platform``), memory, system, Python;
- ``threads`` (the setting, and llvmpipe's render threads where it runs), ``gl`` (the
  OpenGL platform asked for and the one used, and the ``GL_RENDERER`` of the raster
  phase when known), ``kernels`` (how the compiled kernels run, ``phrt_usd.kernels.form``);
- ``metric``: FLIP's mode and viewing conditions (``image_metrics.flip_settings``) and the
  temporal error's settings (its measure, the warp's depth agreement);
- ``seeds``: every seed the measurement uses (the renderer's cost calibration);
- ``libraries``: the versions of the libraries the figures depend on;
- ``date`` (UTC).

``provenance_line`` is the one-line form (the benchmark tools print it, and put the
record itself in their JSON, through ``collect_for_tool``; summary.md and report.html
show ``provenance_items``). Nothing here fails: what cannot be found is
``"unknown"`` or None.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from phrt_usd import base

#: Written where the commit (or another fact) cannot be found.
UNKNOWN = "unknown"
#: Longest wait for a git command (s): provenance must never hold a measurement up.
GIT_TIMEOUT_S = 10.0
#: Import names of the libraries whose versions are recorded (their distribution is
#: looked up, so a fork installed under another distribution name is found too).
LIBRARIES = ("numpy", "pxr", "embreex", "pyrender", "OpenGL", "numba", "flip_evaluator")


def collect(
    *,
    threads: int | None = None,
    gl: str | None = None,
    gl_renderer: str | None = None,
    argv: Sequence[str] | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The provenance of a measurement made in this process (see the module docstring).

    threads: the thread setting used (default: this process's current setting);
    gl: the ``--gl`` value asked for (default ``auto``); gl_renderer: the raster phase's
    ``GL_RENDERER`` when a renderer ran here; argv: the command line (default
    ``sys.argv``); extra: more settings of the measurement (e.g. a sweep's), kept under
    ``settings``."""
    from phrt_usd.evaluate.image_metrics import flip_settings
    from phrt_usd.threads import current_threads, llvmpipe_threads

    commit, dirty = source_commit()
    record: dict[str, Any] = {
        "phrt_version": base.__version__,
        "commit": commit,
        "commit_dirty": dirty,
        "command": command_line(argv),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "threads": {
            "setting": current_threads() if threads is None else int(threads),
            "llvmpipe": llvmpipe_threads(),
        },
        "gl": gl_settings(gl, gl_renderer),
        "kernels": kernels_form(),
        "metric": {"flip": flip_settings(), "temporal_error": temporal_error_settings()},
        "seeds": seeds(),
        "libraries": library_versions(),
    }
    if extra:
        record["settings"] = extra
    return record


def collect_for_tool(
    script: str, argv: Sequence[str] | None = None, **settings: Any
) -> dict[str, Any]:
    """``collect`` for a benchmark tool: the command is ``python tools/<script> ARGS``
    (``script``: the tool's ``__file__``; ``argv``: its arguments, default
    ``sys.argv[1:]``); ``settings`` as ``collect`` takes them."""
    args = list(sys.argv[1:] if argv is None else argv)
    return collect(argv=["python", f"tools/{Path(script).name}", *args], **settings)


def source_commit() -> tuple[str, bool | None]:
    """(commit, dirty) of the phrt-usd checkout this package runs from; (``UNKNOWN``,
    None) for an installed copy, a tree that is not phrt-usd's own checkout (a pipeline's
    repository holding a venv) or when git is missing or refuses."""
    root = Path(base.__file__).resolve().parent.parent
    if not (root / ".git").exists() or not (root / "pyproject.toml").is_file():
        return UNKNOWN, None
    head = _git(root, "rev-parse", "HEAD")
    if head is None or len(head) < 7:
        return UNKNOWN, None
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    return head, (None if status is None else bool(status))


def _git(root: Path, *args: str) -> str | None:
    """Output of ``git -C root ARGS`` (stripped), None when it fails in any way."""
    try:
        done = subprocess.run(
            ["git", "-C", str(root), *args],
            capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def command_line(argv: Sequence[str] | None = None) -> str:
    """The command line, shell-quoted, its program by name only (``phrt sweep ...``)."""
    args = list(sys.argv if argv is None else argv)
    if not args:
        return UNKNOWN
    program = Path(str(args[0])).name or str(args[0])
    return shlex.join([program, *(str(a) for a in args[1:])])


def cpu_model() -> str:
    """The CPU's model name: ``/proc/cpuinfo`` (``model name``, else ``Hardware`` /
    ``Processor`` / ``cpu model``), else ``platform.processor()`` or the machine type."""
    keys = ("model name", "hardware", "processor", "cpu model")
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        text = ""
    found: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        key, value = key.strip().lower(), value.strip()
        if sep and key in keys and value and not value.isdigit() and key not in found:
            found[key] = value
    for key in keys:
        if key in found:
            return found[key]
    return platform.processor() or platform.machine() or UNKNOWN


def memory_gib() -> float | None:
    """Total memory (GiB) from ``/proc/meminfo``; None where it cannot be read."""
    try:
        for line in Path("/proc/meminfo").read_text(encoding="ascii").splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        return None
    return None


def machine() -> dict[str, Any]:
    """Cores (all; usable by this process), CPU model, memory, system, Python."""
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    return {
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "cpu": cpu_model(),
        "memory_gib": memory_gib(),
        "system": platform.platform(),
        "python": platform.python_version(),
    }


def gl_settings(requested: str | None, renderer: str | None = None) -> dict[str, Any]:
    """The OpenGL platform asked for, the one it resolves to in this process (``egl`` or
    ``osmesa``; the loaded one once OpenGL is imported) and the ``GL_RENDERER``."""
    from phrt_usd.engine.raster.gl_platform import DEFAULT_GL, loaded_platform, resolve

    requested = requested or DEFAULT_GL
    try:
        used = loaded_platform() or resolve(requested)
    except Exception:  # noqa: BLE001 - provenance never fails a measurement
        used = UNKNOWN
    return {"requested": requested, "platform": used, "renderer": renderer}


def kernels_form() -> str:
    """How this process's compiled kernels run (``phrt_usd.kernels.form``)."""
    try:
        from phrt_usd import kernels

        return kernels.form()
    except Exception:  # noqa: BLE001 - provenance never fails a measurement
        return UNKNOWN


def temporal_error_settings() -> dict[str, Any]:
    """The temporal error's settings that are not the sequence's own (docs/temporal-error.md)."""
    from phrt_usd.evaluate import temporal_error as te

    return {
        "measure": "warped-frame FLIP beyond the reference's, per pixel",
        "depth_agreement": te.DEPTH_AGREEMENT,
        "flip": "as metric.flip",
    }


def seeds() -> dict[str, int]:
    """Every seed a render or sweep uses: the renderer's cost calibration sample."""
    from phrt_usd.engine.renderer import CALIBRATION_SEED

    return {"calibration": CALIBRATION_SEED}


def library_versions() -> dict[str, str]:
    """{import name: "distribution version"} of ``LIBRARIES`` (``UNKNOWN`` if absent)."""
    from importlib import metadata

    try:
        distributions = metadata.packages_distributions()
    except Exception:  # noqa: BLE001 - provenance never fails a measurement
        distributions = {}
    versions = {}
    for name in LIBRARIES:
        found = UNKNOWN
        for dist in distributions.get(name, [name]):
            try:
                found = f"{dist} {metadata.version(dist)}"
                break
            except metadata.PackageNotFoundError:
                continue
        versions[name] = found
    return versions


def read_provenance(path: Path) -> dict[str, Any] | None:
    """The provenance record in ``path`` (a provenance.json); None when the file is absent
    (a sweep directory of an older phrt). PhrtError naming the file when it cannot be read
    or is not a JSON object."""
    import json

    from phrt_usd.errors import PhrtError

    path = Path(path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise PhrtError(f"{path}: cannot read ({error})") from None
    if not isinstance(data, dict):
        raise PhrtError(f"{path}: expected a JSON object")
    return data


def provenance_items(record: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, text) pairs of a provenance record, in reading order (summary.md and
    report.html list them; ``provenance_line`` joins them)."""
    commit = str(record.get("commit", UNKNOWN))
    if record.get("commit_dirty"):
        commit += " (with uncommitted changes)"
    m = record.get("machine") or {}
    threads = record.get("threads") or {}
    gl = record.get("gl") or {}
    flip = (record.get("metric") or {}).get("flip") or {}
    items = [
        ("phrt", f"{record.get('phrt_version', UNKNOWN)}, commit {commit}"),
        ("command", str(record.get("command", UNKNOWN))),
        (
            "machine",
            f"{m.get('cpu', UNKNOWN)}, {m.get('cores')} cores ({m.get('usable_cores')} "
            f"usable), {m.get('memory_gib')} GiB, {m.get('system', UNKNOWN)}, "
            f"Python {m.get('python', UNKNOWN)}",
        ),
        (
            "threads",
            f"{threads.get('setting')}"
            + (f" (llvmpipe {threads['llvmpipe']})" if threads.get("llvmpipe") else ""),
        ),
        (
            "OpenGL",
            f"{gl.get('platform', UNKNOWN)} (asked: {gl.get('requested', UNKNOWN)})"
            + (f", {gl['renderer']}" if gl.get("renderer") else ""),
        ),
        ("kernels", str(record.get("kernels", UNKNOWN))),
    ]
    if flip:
        items.append(
            (
                "FLIP",
                f"{flip.get('metric')} ({flip.get('implementation')}), display "
                f"{flip.get('monitor_width_m')} m / {flip.get('monitor_resolution_x')} px "
                f"wide seen from {flip.get('monitor_distance_m')} m "
                f"({flip.get('pixels_per_degree')} px per degree)",
            )
        )
    record_seeds = record.get("seeds") or {}
    items.append(
        ("seeds", ", ".join(f"{k} {v}" for k, v in record_seeds.items()) or "none")
    )
    items.append(("date", str(record.get("date", UNKNOWN))))
    return items


def provenance_line(record: dict[str, Any]) -> str:
    """The record on one line: ``provenance: phrt 0.1.0, commit ...; command ...; ...``."""
    return "provenance: " + "; ".join(f"{k} {v}" for k, v in provenance_items(record))
