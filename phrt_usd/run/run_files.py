"""The run directory: where a render's files live, ``stats.json``, and atomic file writes.

Layout of a render's output directory ``OUT``::

    OUT/frames/NNNN.exr     one multi-channel EXR per rendered frame (see images.py)
    OUT/frames/NNNN.png     8-bit sRGB preview of the same frame
    OUT/<productName>       instead of frames/: each RenderProduct's file per frame, or
                            --image's (see products.py; recorded in stats.json's run
                            ``products``; --overwrite deletes those the run it starts
                            names, never what a file in OUT lists: run_directory.py)
    OUT/stats.json          run settings + one row per rendered frame (this module)
    OUT/selection.usda      the selection layer (see selection_layer.py)
    OUT/checkpoint.json     finished frames and the policy's memory, for --resume
    OUT/.phrt.lock          held (flock) by the render writing OUT; names its pid
    OUT/.phrt.reserve       disk held back while rendering, so records fit on a full disk

``NNNN`` is the frame's time code (``frames.frame_text``): integral time codes are
zero-padded to 4 digits (``0012``, ``-003``), fractional ones keep 3 decimals
(``0012.500``), so time codes are told apart to 1/1000 of a time code (a render refuses
frames closer than that before its first frame).

Every file is written through ``phrt_usd.atomic`` (checked, fsynced, renamed into place).
"""

from __future__ import annotations

import json
import math
import os
import platform
from dataclasses import MISSING, asdict, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from phrt_usd.atomic import write_text_atomic
from phrt_usd.base import __version__
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import FrameStats, ReflectorMetrics
from phrt_usd.model.pixel_kinds import PIXEL_KINDS
from phrt_usd.model.trace_density import TRACE_DENSITIES
from phrt_usd.run.frames import frame_text

FRAMES_DIR = "frames"
STATS_FILE = "stats.json"
SELECTION_LAYER_FILE = "selection.usda"
CHECKPOINT_FILE = "checkpoint.json"
LOCK_FILE = ".phrt.lock"
RESERVE_FILE = ".phrt.reserve"
#: Digits of the default layout's frame names (``frames/0012.exr``, ``$F4``).
FRAME_DIGITS = 4

#: Identifies stats.json files written by this module; bump the version on breaking change.
STATS_FORMAT = "phrt-stats"
STATS_VERSION = 1


# --- layout ----------------------------------------------------------------------------


def frame_name(time: float) -> str:
    """File stem of the frame at time code ``time``: ``0012``, ``-003``, ``0012.500``."""
    return frame_text(time, FRAME_DIGITS)


def frame_image_paths(out: Path, time: float) -> tuple[Path, Path]:
    """(EXR path, PNG path) of the frame at time code ``time`` in run directory ``out``."""
    stem = frame_name(time)
    frames = Path(out) / FRAMES_DIR
    return frames / f"{stem}.exr", frames / f"{stem}.png"


def stats_path(out: Path) -> Path:
    return Path(out) / STATS_FILE


def selection_layer_path(out: Path) -> Path:
    """Default selection layer path of run directory ``out`` (``OUT/selection.usda``)."""
    return Path(out) / SELECTION_LAYER_FILE


# --- stats.json ------------------------------------------------------------------------


def make_run_info(
    *,
    stage: str | None,
    mode: str,
    heuristic: str,
    budget_ms: float | None,
    budget_rays: int | None,
    resolution: tuple[int, int],
    bounce_limit: int,
    selection_weight: float,
    frame_range: tuple[float, float],
    reflectors: list[str],
    time_codes_per_second: float = 24.0,
) -> dict[str, Any]:
    """The ``run`` object of stats.json (and the selection layer's customLayerData).

    ``budget_ms`` / ``budget_rays`` are ``None`` when that budget is not used;
    ``resolution`` is (width, height) pixels; ``frame_range`` is (first, last) time code of
    the render; ``reflectors`` are all reflector prim paths of the stage. Machine, date and
    phrt version are filled in here.
    """
    return {
        "stage": stage,
        "mode": mode,
        "heuristic": heuristic,
        "budget_ms": budget_ms,
        "budget_rays": budget_rays,
        "resolution": [int(resolution[0]), int(resolution[1])],
        "bounce_limit": int(bounce_limit),
        "selection_weight": float(selection_weight),
        "frame_range": [float(frame_range[0]), float(frame_range[1])],
        "time_codes_per_second": float(time_codes_per_second),
        "reflectors": list(reflectors),
        "machine": {
            "cores": os.cpu_count(),
            "cpu": platform.processor() or platform.machine(),
            "system": platform.system(),
            "python": platform.python_version(),
        },
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "phrt_version": __version__,
    }


def to_json_value(value: Any) -> Any:
    """``value`` with numpy scalars/arrays made plain and non-finite floats made ``None``.

    JSON has no NaN/Inf; a non-finite figure (which the renderer should never produce) is
    written as ``null`` rather than losing the whole file of a long render.
    """
    if isinstance(value, dict):
        return {str(k): to_json_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_json_value(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_json_value(value.tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def frame_stats_from_row(row: Any) -> FrameStats:
    """Inverse of ``frame_stats_row`` for rows read back from a file; PhrtError (naming
    the field) unless ``row`` has every field with its type."""
    everything = {f.name for f in fields(FrameStats)}
    required = {f.name for f in fields(FrameStats) if f.name not in _OPTIONAL_FRAME_FIELDS}
    if not isinstance(row, dict) or not required <= set(row) <= everything:
        raise PhrtError("a frame record without the fields of a phrt frame")

    def number(name: str, value: Any) -> float:
        if value is None:  # a non-finite figure, written as null (see to_json_value)
            return math.nan
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise PhrtError(f"frame record field {name}: not a number")
        return float(value)

    def paths(name: str) -> list[str]:
        value = row[name]
        if not isinstance(value, list) or not all(isinstance(p, str) for p in value):
            raise PhrtError(f"frame record field {name}: not a list of prim paths")
        return list(value)

    metrics = {}
    if not isinstance(row["metrics"], dict) or not isinstance(row["phase_ms"], dict):
        raise PhrtError("frame record fields metrics / phase_ms: not tables")
    names = {f.name for f in fields(ReflectorMetrics)}
    needed = {f.name for f in fields(ReflectorMetrics) if f.default is MISSING}
    for path, m in row["metrics"].items():
        if not isinstance(m, dict) or not needed <= set(m) <= names:
            raise PhrtError(f"frame record metrics of {path}: not reflector figures")
        metrics[path] = ReflectorMetrics(
            **{k: (bool(v) if k in ("S", "selected", "visible") else number(k, v))
               for k, v in m.items()}
        )  # fmt: skip
    time = number("time", row["time"])
    rays = number("rays", row["rays"])
    if not math.isfinite(time) or rays != int(rays):
        raise PhrtError("frame record: time not finite or rays not whole")
    return FrameStats(
        time=time,
        phase_ms={str(k): number(f"phase_ms.{k}", v) for k, v in row["phase_ms"].items()},
        frame_ms=number("frame_ms", row["frame_ms"]),
        trace_ms=number("trace_ms", row["trace_ms"]),
        predicted_trace_ms=number("predicted_trace_ms", row["predicted_trace_ms"]),
        rays=int(rays),
        visible=paths("visible"),
        selected=paths("selected"),
        metrics=metrics,
        passes=paths("passes"),
        **_optional_frame_fields(row, number),
    )


#: FrameStats fields that rows written before they existed lack (read as their defaults).
_OPTIONAL_FRAME_FIELDS = (
    "budget_ms", "expected_trace_ms", "budget_use", "untraced_reason", "calibration",
    "densities", "pixel_kinds",
)  # fmt: skip


def _optional_frame_fields(row: dict, number) -> dict[str, Any]:
    """The optional fields of ``row`` (see _OPTIONAL_FRAME_FIELDS), checked."""
    out: dict[str, Any] = {}
    for name in ("budget_ms", "budget_use"):
        if row.get(name) is not None:
            out[name] = number(name, row[name])
    if "expected_trace_ms" in row:
        out["expected_trace_ms"] = number("expected_trace_ms", row["expected_trace_ms"])
    reason = row.get("untraced_reason")
    if reason is not None and not isinstance(reason, str):
        raise PhrtError("frame record field untraced_reason: not text")
    out["untraced_reason"] = reason
    calibration = row.get("calibration")
    if calibration is not None and not isinstance(calibration, dict):
        raise PhrtError("frame record field calibration: not a table")
    out["calibration"] = calibration
    densities = row.get("densities", {})
    if not isinstance(densities, dict) or not all(
        isinstance(k, str) and v in TRACE_DENSITIES for k, v in densities.items()
    ):
        raise PhrtError("frame record field densities: not a table of trace densities")
    out["densities"] = dict(densities)
    kinds = row.get("pixel_kinds", {})
    if not isinstance(kinds, dict) or not all(
        k in PIXEL_KINDS.values() and isinstance(v, int) and not isinstance(v, bool) and v >= 0
        for k, v in kinds.items()
    ):
        raise PhrtError("frame record field pixel_kinds: not a table of pixel counts by kind")
    out["pixel_kinds"] = dict(kinds)
    return out


def frame_stats_row(frame: FrameStats) -> dict[str, Any]:
    """One stats.json row: time, phase_ms, frame_ms, trace_ms, predicted_trace_ms, rays,
    visible, selected, metrics (prim path → ReflectorMetrics fields), passes, budget_ms
    (the frame's T), expected_trace_ms, budget_use, untraced_reason, calibration,
    densities, pixel_kinds."""
    return to_json_value(asdict(frame))


def write_stats(out: Path, run_info: dict[str, Any], frames: list[FrameStats]) -> Path:
    """Write ``OUT/stats.json`` atomically (rows sorted by time); returns its path.

    Cheap enough to call after every frame, so an interrupted render keeps its stats.
    """
    document = {
        "format": STATS_FORMAT,
        "version": STATS_VERSION,
        "run": to_json_value(run_info),
        "frames": [frame_stats_row(f) for f in sorted(frames, key=lambda f: f.time)],
    }
    path = stats_path(out)
    write_text_atomic(path, json.dumps(document, indent=1, allow_nan=False) + "\n")
    return path


def read_stats(out: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """(run_info, frame rows as dicts) from ``OUT/stats.json`` (``out`` may also be the
    file itself). Raises PhrtError if it is missing or not a phrt stats file."""
    path = Path(out)
    if path.is_dir():
        path = stats_path(path)
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PhrtError(f"{path}: no stats file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise PhrtError(f"{path}: cannot read stats ({error})") from None
    if not isinstance(document, dict) or document.get("format") != STATS_FORMAT:
        raise PhrtError(f'{path}: not a phrt stats file (no "format": "{STATS_FORMAT}")')
    if document.get("version") != STATS_VERSION:
        raise PhrtError(
            f"{path}: stats version {document.get('version')}, expected {STATS_VERSION}"
        )
    run, rows = document.get("run", {}), document.get("frames", [])
    if not isinstance(rows, list):
        raise PhrtError(f'{path}: "frames" is not a list of frame records')
    try:
        check_run_info(run)
        for row in rows:
            frame_stats_from_row(row)
    except PhrtError as error:
        raise PhrtError(f"{path}: {error}") from None
    return run, rows


#: Types of the run settings readers use (stats.json "run", the layer's customLayerData).
_RUN_INFO_TYPES: dict[str, tuple[type, ...]] = {
    "stage": (str,),
    "mode": (str,),
    "heuristic": (str,),
    "budget_ms": (int, float),
    "budget_rays": (int,),
    "target_fps": (int, float),
    "exposure": (int, float),
    "trace_density": (str,),
    "screen_space": (str,),
    "bounce_limit": (int,),
    "selection_weight": (int, float),
    "time_codes_per_second": (int, float),
    "camera": (str,),
    "settings": (str,),
    "products": (dict,),
    "threads": (int,),  # how the run ran (run.render_job.runtime_settings)
    "gl": (str,),
    "llvmpipe_threads": (int,),
    "kernels": (str,),
    "primary": (str,),
}


def check_run_info(run: Any) -> None:
    """PhrtError unless ``run`` is a table whose known settings have their types
    (``None`` allowed: an unused budget); ``resolution`` is two whole numbers."""
    if not isinstance(run, dict):
        raise PhrtError("run settings are not a table")
    for key, kinds in _RUN_INFO_TYPES.items():
        value = run.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, kinds)):
            raise PhrtError(f"run setting {key}: {value!r} is not a {kinds[0].__name__}")
    resolution = run.get("resolution")
    if resolution is not None and not (
        isinstance(resolution, list)
        and len(resolution) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in resolution)
    ):
        raise PhrtError(f"run setting resolution: {resolution!r} is not [width, height]")
