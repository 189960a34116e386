"""Replay selection policies offline on a recorded camera path (rays or simulated time budgets).

With a rays budget a policy's choices depend only on what the renderer shows it: each
frame's ``FrameView`` (pixel counts, screen boxes, camera) and, for each reflector it
traces, that reflector's ``TraceRecord`` (rays, pixels, bounces, reflectors hit). A
reflector's record does not depend on which other reflectors are traced with it (its
rays start from its own G-buffer pixels), so one ``all`` render that records every
visible reflector's record per frame lets any policy be replayed exactly, without
rendering: the replay runs the renderer's round loop (``select.rounds.run_rounds``) with
the recorded records as its tracing step instead of the tracer. The first step checks
that: replaying HEU1 and HEU2 gives the same transitions and mean selected as real
``paper_tables`` runs.

    uv run python tools/policy_replay.py capture stages/farm.usda runs/replay/farm.json.gz \
        [--frames A:B:STEP] [--images runs/replay/farm.npz]
    uv run python tools/policy_replay.py replay runs/replay/farm.json.gz \
        --budgets 500,1000,2000,4000 [--heuristics heu1,heu2] [--images runs/replay/farm.npz]

``--budgets-ms 10,16`` replays time budgets T instead: each round takes a synthetic time
(``SimulatedTime``: the least-squares line of the capture's own ``all`` rounds, or
``--overhead-ms`` / ``--ms-per-ray``, times seeded lognormal ``--jitter``), the policy is
calibrated on the first frame with visible reflectors as the renderer does it, and
``budget use`` is trace ms / T as in ``stats.json`` (with a rays budget: traced rays /
budget), over the frames with visible reflectors. Deterministic for a given seed, but
only as right as the line: real rounds on a loaded machine vary more.

``capture`` renders the stage's full camera path (or ``--frames``) once (hybrid, ``all``,
unbounded; 320x240 unless told; no image files, but with ``--images`` the frames' raster
and ``all`` images in one npz). ``replay`` prints, per heuristic and budget: transitions
(split into admissions of reflectors already in view and drops while in view), mean
selected, mean traced rays, the HEU1/HEU2 ratio and, with ``--images``, the mean FLIP
against ``all`` of each policy's images composed from the recording (``compose``: equal to
``phrt sweep``'s figures on the same frames, e.g. farm 521:640:2 at 1000 rays: 0.00442 /
0.00422 both ways).

A recording is plain data: JSON (gzip-compressed when its name ends in ``.gz``) with
``"format": "phrt-replay-recording"`` and ``"version"`` (``RECORDING_VERSION``), read
back by ``load_recording`` (shared with ``tools/transition_bound.py``). Its objects are
a closed list of known types (``CameraFrame``, ``FrameView``, ``TraceRecord``,
``DistantLight``, ``LocalLight``, a frame's element table), each read field by field
with its type checked; numpy arrays are ``{"dtype", "shape", "data"}`` with a few
numeric dtypes and ``data`` the flat values in C order. Floats are written by ``repr``
(NaN and infinities as JSON's ``NaN`` / ``Infinity`` extension), so they read back bit
for bit and a replay of the file selects exactly what a replay of the capture in memory
does. Reading never unpickles, imports or evaluates anything: a file that is not such a
recording is refused with one line, as is an ``--images`` npz that is not a capture's
(loaded with ``allow_pickle=False``).
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import sys
import zipfile
import zlib
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from phrt_usd.atomic import atomic_path, write_bytes_atomic
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace_calibration import (
    CALIBRATION_AIM,
    CALIBRATION_GROWTH,
    CALIBRATION_PIXELS,
    CALIBRATION_REPEATS,
    CALIBRATION_ROUND_MAX_MS,
    SPARSE_PIXELS_FACTOR,
)
from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.evaluate.selection_metrics import (
    admissions_and_drops,
    density_steps,
    selection_metrics,
)
from phrt_usd.model.frame import Budget, FrameView, TraceRecord
from phrt_usd.model.reflection_roughness import element_figures, started_share
from phrt_usd.model.scene import CameraFrame, DistantLight, LocalLight
from phrt_usd.model.trace_density import TRACE_DENSITIES, traced_fraction
from phrt_usd.run.frames import parse_frames
from phrt_usd.select.heu1_forecast import UPCOMING_CAMERAS
from phrt_usd.select.policies import AllPolicy, make_policy
from phrt_usd.select.rounds import Calibration, TracedRound, run_rounds
from phrt_usd.usd.schema import read_render_params
from phrt_usd.usd.stage import open_stage


class _CapturePolicy(AllPolicy):
    """``all`` that keeps what it was shown and what tracing found, frame by frame."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        #: One SimpleNamespace per frame: ``view`` (FrameView), ``elements`` (per element:
        #: is_reflector, priority, center, bounds) and ``records`` (element id → TraceRecord of
        #: every visible reflector). Known types only, so ``save_recording`` can write it.
        self.frames: list[SimpleNamespace] = []

    def begin_frame(self, view, scene) -> None:
        super().begin_frame(view, scene)
        elements = [
            SimpleNamespace(
                is_reflector=e.is_reflector,
                priority=e.priority,
                center=e.center,
                bounds_min=e.bounds_min,
                bounds_max=e.bounds_max,
            )  # fmt: skip
            for e in scene.elements
        ]
        self.frames.append(SimpleNamespace(view=view, elements=elements, records={}))

    def record(self, records, seconds) -> None:
        super().record(records, seconds)
        for rec in records:
            self.frames[-1].records[int(rec.source)] = rec


def capture(
    stage_path: Path,
    out: Path,
    width: int,
    height: int,
    frames: str | None = None,
    images: Path | None = None,
) -> None:
    """Record ``frames`` (default: the whole path) into ``out``; with ``images``, also an
    npz of per frame (F, H, W) element ids, the raster image and the ``all`` image
    (F, H, W, 3) float32 and the ``all`` run's traced mask, from which the image of any
    selection is composed exactly (``compose``)."""
    stage = open_stage(stage_path)
    params = read_render_params(stage.stage)
    options = RenderOptions(
        mode="hybrid", heuristic="all", width=width, height=height,
        budget_ms=None, budget_rays=None, bounce_limit=params.bounce_limit,
    )  # fmt: skip
    renderer = FrameRenderer(stage, options)
    policy = _CapturePolicy(selection_weight=0.0, bounce_limit=params.bounce_limit)
    renderer.policy = policy
    times = parse_frames(frames, stage.frame_range)
    stacks: dict[str, list[np.ndarray]] = {"ids": [], "raster": [], "all": [], "traced": []}
    try:
        for k, t in enumerate(times):
            prep = renderer.prepare(t)
            output = renderer.finish(prep, policy, options)
            if images is not None:
                stacks["ids"].append(prep.gbuffer.element_id.astype(np.int32))
                stacks["raster"].append(prep.image.astype(np.float32))
                stacks["all"].append(output.beauty.astype(np.float32))
                stacks["traced"].append(output.traced_mask)
            if k % 100 == 0:
                print(f"{stage_path.stem}: frame {k}/{len(times)}", file=sys.stderr)
    finally:
        renderer.close()
    lights = stage.scene.lights
    data = {
        "stage": str(stage_path),
        "selection_weight": params.selection_weight,
        "bounce_limit": params.bounce_limit,
        "lights": SimpleNamespace(distant=list(lights.distant), local=list(lights.local)),
        "reflectors": [int(i) for i in stage.scene.reflector_ids],
        "reflection_figures": element_figures(stage.scene),
        "frames": policy.frames,
    }
    save_recording(out, data)
    if images is not None:
        arrays = {k: np.stack(v) for k, v in stacks.items()}
        with atomic_path(images) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, times=np.asarray(times), **arrays)


# ------------------------------------------------------------------ recording files

#: The ``format`` and ``version`` a recording file names; any other is refused.
RECORDING_FORMAT = "phrt-replay-recording"
#: 8: the elements' reflection figures (``model.reflection_roughness.element_figures``:
#: gain from tracing, share of pixels that start rays);
#: 7: LocalLight's emitting surface (area_shape, area_u, area_v);
#: 6: TraceRecord's pixel kinds (screen_space, reused, filled, marched);
#: 5: FrameView.trace_density; 4: CameraFrame.exposure_scale, the lights' path and
#: LocalLight's cone; 3: TraceRecord.fallback_error; 2: CameraFrame's vertical aperture,
#: offsets, conform policy.
RECORDING_VERSION = 8


class RecordingError(PhrtError):
    """A file that is not a recording (or a capture's images) this tool can read; its
    message is one line naming the file and what is wrong."""


#: The only dtypes a recording's arrays have (by name).
_DTYPES = {name: np.dtype(name) for name in ("bool", "int64", "float64")}


class _Array:
    """Field kind: an ndarray of one of ``dtypes`` whose shape matches ``shape`` (``None``
    = any length on that axis)."""

    def __init__(self, dtypes: tuple[str, ...], *shape: int | None) -> None:
        self.dtypes, self.shape = dtypes, shape


class _Optional:
    def __init__(self, kind) -> None:
        self.kind = kind


class _Tuple:
    def __init__(self, kind) -> None:
        self.kind = kind


_F8 = ("float64",)
_VEC3 = _Array(_F8, 3)
_INT_MAP = "int_map"  # dict[int, int], written as [[key, value], ...] in insertion order

#: The closed list of classes a recording holds: class → field → kind (``int``,
#: ``float``, ``_INT_MAP``, an ``_Array`` / ``_Optional`` / ``_Tuple``, or another class
#: of this table). Decoding calls only these constructors, with checked fields.
_SCHEMAS: dict[type, dict[str, object]] = {
    CameraFrame: {
        "world_from_camera": _Array(_F8, 4, 4),
        "focal_length": float,
        "horizontal_aperture": float,
        "near": float,
        "far": float,
        "vertical_aperture": _Optional(float),
        "horizontal_aperture_offset": float,
        "vertical_aperture_offset": float,
        "conform_policy": str,
        "pixel_aspect": float,
        "data_window": _Tuple(float),
        "exposure_scale": float,
    },
    FrameView: {
        "time": float,
        "camera": CameraFrame,
        "width": int,
        "height": int,
        "pixel_counts": _Array(("int64",), None),
        "screen_boxes": _Optional(_Array(_F8, None, 4)),
        "upcoming_cameras": _Tuple(CameraFrame),
        "trace_density": str,
    },
    TraceRecord: {
        "source": int,
        "pixels": int,
        "rays": int,
        "hits": _INT_MAP,
        "max_reflector_bounces": int,
        "mean_reflector_bounces": float,
        "seconds": float,
        "fallback_error": _Optional(float),
        "screen_space": _Optional(int),
        "reused": _Optional(int),
        "filled": _Optional(int),
        "marched": _Optional(int),
    },
    DistantLight: {"direction": _VEC3, "radiance": _VEC3, "angle": float, "path": str},
    LocalLight: {
        "position": _VEC3,
        "radiance": _VEC3,
        "radius": float,
        "path": str,
        "axis": _VEC3,
        "cone_angle": float,
        "cone_softness": float,
        "focus": float,
        "area_shape": str,
        "area_u": _VEC3,
        "area_v": _VEC3,
    },
}

#: A frame's elements (``_CapturePolicy``) as one table of columns, name → kind; element
#: i's attributes are row i of each column.
_ELEMENT_COLUMNS = {
    "is_reflector": _Array(("bool",), None),
    "priority": _Array(_F8, None),
    "center": _Array(_F8, None, 3),
    "bounds_min": _Array(_F8, None, 3),
    "bounds_max": _Array(_F8, None, 3),
}


def _fail(where: str, what: str):
    raise RecordingError(f"{where}: {what}")


# --- writing


def _encode(value, kind, where: str):
    """``value`` (of ``kind``) → JSON data; RecordingError if it is not of that kind (the
    capture holds something this format version does not know)."""
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            _fail(where, f"expected an int, not {type(value).__name__}")
        return int(value)
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, float | int | np.integer):
            _fail(where, f"expected a float, not {type(value).__name__}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            _fail(where, f"expected a string, not {type(value).__name__}")
        return value
    if kind == _INT_MAP:
        if not isinstance(value, dict):
            _fail(where, f"expected a dict, not {type(value).__name__}")
        return [
            [_encode(k, int, where), _encode(v, int, f"{where}[{k}]")] for k, v in value.items()
        ]
    if isinstance(kind, _Optional):
        return None if value is None else _encode(value, kind.kind, where)
    if isinstance(kind, _Tuple):
        if not isinstance(value, tuple | list):
            _fail(where, f"expected a tuple, not {type(value).__name__}")
        return [_encode(v, kind.kind, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(kind, _Array):
        return _encode_array(value, kind, where)
    schema = _SCHEMAS[kind]
    if type(value) is not kind:
        _fail(where, f"expected a {kind.__name__}, not {type(value).__name__}")
    if set(vars(value)) != set(schema):
        unknown = sorted(set(vars(value)) ^ set(schema))
        _fail(where, f"{kind.__name__} field {unknown[0]!r} is not in the format")
    return {name: _encode(getattr(value, name), k, f"{where}.{name}") for name, k in schema.items()}


def _encode_array(value, kind: _Array, where: str) -> dict:
    if not isinstance(value, np.ndarray) or value.dtype.name not in kind.dtypes:
        got = value.dtype.name if isinstance(value, np.ndarray) else type(value).__name__
        _fail(where, f"expected an array of {'/'.join(kind.dtypes)}, not {got}")
    if not _shape_fits(value.shape, kind.shape):
        _fail(where, f"array shape {value.shape} is not {kind.shape}")
    return {"dtype": value.dtype.name, "shape": list(value.shape), "data": value.ravel().tolist()}


def _shape_fits(shape, want) -> bool:
    return len(shape) == len(want) and all(
        w is None or s == w for s, w in zip(shape, want, strict=True)
    )


def _encode_elements(elements: list, where: str) -> dict:
    table = {}
    for name, kind in _ELEMENT_COLUMNS.items():
        column = [getattr(e, name) for e in elements]
        if name == "is_reflector":
            if not all(isinstance(v, bool | np.bool_) for v in column):
                _fail(f"{where}.{name}", "an element's value is not a bool")
            array = np.array(column, dtype=bool)
        elif name == "priority":
            array = np.array([_encode(v, float, f"{where}.{name}") for v in column])
        else:
            for v in column:
                _encode_array(v, _VEC3, f"{where}.{name}")
            array = np.array(column, dtype=np.float64).reshape(len(column), 3)
        table[name] = _encode_array(array, kind, f"{where}.{name}")
    return table


def encode_recording(data: dict) -> dict:
    """A capture's recording (``capture``'s ``data``) → the JSON data of its file."""
    lights = data["lights"]
    frames = []
    for f, frame in enumerate(data["frames"]):
        where = f"frames[{f}]"
        records = []
        for key, rec in frame.records.items():
            if key != rec.source:
                _fail(f"{where}.records[{key}]", f"holds the record of source {rec.source}")
            records.append(_encode(rec, TraceRecord, f"{where}.records[{key}]"))
        frames.append(
            {
                "view": _encode(frame.view, FrameView, f"{where}.view"),
                "elements": _encode_elements(frame.elements, f"{where}.elements"),
                "records": records,
            }
        )
    return {
        "format": RECORDING_FORMAT,
        "version": RECORDING_VERSION,
        "stage": str(data["stage"]),
        "selection_weight": _encode(data["selection_weight"], float, "selection_weight"),
        "bounce_limit": _encode(data["bounce_limit"], int, "bounce_limit"),
        "lights": {
            "distant": _encode(lights.distant, _Tuple(DistantLight), "lights.distant"),
            "local": _encode(lights.local, _Tuple(LocalLight), "lights.local"),
        },
        "reflectors": _encode(data["reflectors"], _Tuple(int), "reflectors"),
        "reflection_figures": [
            _encode_array(np.asarray(a, np.float64), _FIGURES[k], f"reflection_figures[{k}]")
            for k, a in enumerate(data["reflection_figures"])
        ],
        "frames": frames,
    }


def save_recording(path: Path, data: dict) -> None:
    """Write ``data`` to ``path`` as a recording (gzip when the name ends in ``.gz``),
    atomically, and read it back before it replaces anything under that name."""
    raw = json.dumps(encode_recording(data), separators=(",", ":")).encode("utf-8")
    if Path(path).name.endswith(".gz"):
        raw = gzip.compress(raw, compresslevel=6, mtime=0)
    write_bytes_atomic(Path(path), raw, check=load_recording)


# --- reading


def _object(value, names, where: str) -> dict:
    """``value`` as a JSON object with exactly the fields ``names``."""
    if not isinstance(value, dict):
        _fail(where, f"expected an object, not {_json_type(value)}")
    missing = [n for n in names if n not in value]
    if missing:
        _fail(where, f"missing field {missing[0]!r}")
    extra = sorted(set(value) - set(names))
    if extra:
        _fail(where, f"unknown field {extra[0]!r}")
    return value


def _json_type(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    return "an array" if isinstance(value, list) else "an object"


def _list(value, where: str) -> list:
    if not isinstance(value, list):
        _fail(where, f"expected an array, not {_json_type(value)}")
    return value


def _decode(value, kind, where: str):
    """JSON data → a value of ``kind``; RecordingError unless ``value`` is exactly what
    ``_encode`` writes for that kind."""
    if kind is int:
        if type(value) is not int:
            _fail(where, f"expected an integer, not {_json_type(value)}")
        return value
    if kind is float:
        if type(value) not in (float, int):
            _fail(where, f"expected a number, not {_json_type(value)}")
        return float(value)
    if kind is str:
        if type(value) is not str:
            _fail(where, f"expected a string, not {_json_type(value)}")
        return value
    if kind == _INT_MAP:
        table = {}
        for i, pair in enumerate(_list(value, where)):
            if not (isinstance(pair, list) and len(pair) == 2):
                _fail(f"{where}[{i}]", "expected a [key, value] pair")
            key = _decode(pair[0], int, f"{where}[{i}]")
            if key in table:
                _fail(f"{where}[{i}]", f"a second entry for {key}")
            table[key] = _decode(pair[1], int, f"{where}[{i}]")
        return table
    if isinstance(kind, _Optional):
        return None if value is None else _decode(value, kind.kind, where)
    if isinstance(kind, _Tuple):
        items = _list(value, where)
        return tuple(_decode(v, kind.kind, f"{where}[{i}]") for i, v in enumerate(items))
    if isinstance(kind, _Array):
        return _decode_array(value, kind, where)
    schema = _SCHEMAS[kind]
    obj = _object(value, schema, where)
    return kind(**{name: _decode(obj[name], k, f"{where}.{name}") for name, k in schema.items()})


def _decode_array(value, kind: _Array, where: str) -> np.ndarray:
    obj = _object(value, ("dtype", "shape", "data"), where)
    name = obj["dtype"]
    if not isinstance(name, str) or name not in kind.dtypes:
        _fail(f"{where}.dtype", f"expected {'/'.join(map(repr, kind.dtypes))}, not {name!r}")
    shape = _list(obj["shape"], f"{where}.shape")
    if not all(type(n) is int and n >= 0 for n in shape) or not _shape_fits(shape, kind.shape):
        _fail(f"{where}.shape", f"{shape} is not an array shape {kind.shape}")
    data = _list(obj["data"], f"{where}.data")
    if len(data) != math.prod(shape):
        _fail(f"{where}.data", f"{len(data)} values for shape {shape}")
    dtype = _DTYPES[name]
    if dtype.kind == "b":
        ok = all(type(v) is bool for v in data)
    elif dtype.kind == "i":
        info = np.iinfo(dtype)
        ok = all(type(v) is int and info.min <= v <= info.max for v in data)
    else:
        ok = all(type(v) in (float, int) for v in data)
    if not ok:
        _fail(f"{where}.data", f"holds values that are not {name}")
    return np.array(data, dtype=dtype).reshape(shape)


def _decode_elements(value, where: str) -> list[SimpleNamespace]:
    obj = _object(value, _ELEMENT_COLUMNS, where)
    columns = {n: _decode(obj[n], k, f"{where}.{n}") for n, k in _ELEMENT_COLUMNS.items()}
    n = len(columns["is_reflector"])
    if any(len(c) != n for c in columns.values()):
        _fail(where, "columns of different lengths")
    is_reflector = columns["is_reflector"].tolist()
    priority = columns["priority"].tolist()
    return [
        SimpleNamespace(
            is_reflector=is_reflector[i],
            priority=priority[i],
            center=columns["center"][i],
            bounds_min=columns["bounds_min"][i],
            bounds_max=columns["bounds_max"][i],
        )
        for i in range(n)
    ]


def _decode_frame(value, reflectors: list[int], where: str) -> SimpleNamespace:
    obj = _object(value, ("view", "elements", "records"), where)
    view = _decode(obj["view"], FrameView, f"{where}.view")
    elements = _decode_elements(obj["elements"], f"{where}.elements")
    records = {}
    for i, item in enumerate(_list(obj["records"], f"{where}.records")):
        rec = _decode(item, TraceRecord, f"{where}.records[{i}]")
        if rec.source in records:
            _fail(f"{where}.records[{i}]", f"a second record of source {rec.source}")
        records[rec.source] = rec
    # What replay and transition_bound index, so a bad file fails here, not inside them.
    counts = view.pixel_counts
    if view.width < 1 or view.height < 1 or not view.camera.focal_length > 0.0:
        _fail(f"{where}.view", "no image size or focal length")
    if len(elements) != len(counts):
        _fail(where, f"{len(elements)} elements but {len(counts)} pixel counts")
    if [i for i, e in enumerate(elements) if e.is_reflector] != reflectors:
        _fail(where, "its reflector elements are not the recording's reflectors")
    lacking = [e for e in reflectors if counts[e] > 0 and e not in records]
    if lacking:
        _fail(where, f"no record of reflector {lacking[0]}, which is in view")
    return SimpleNamespace(view=view, elements=elements, records=records)


_RECORDING_FIELDS = (
    "format", "version", "stage", "selection_weight", "bounce_limit", "lights", "reflectors",
    "reflection_figures", "frames",
)  # fmt: skip
#: The kinds of a recording's reflection figures (``element_figures``: a float per
#: element, a row of one per trace density per element).
_FIGURES = (_Array(_F8, None), _Array(_F8, None, None))


def decode_recording(value) -> dict:
    """The JSON data of a recording file → the recording (``capture``'s ``data``)."""
    if not isinstance(value, dict) or value.get("format") != RECORDING_FORMAT:
        got = value.get("format") if isinstance(value, dict) else None
        raise RecordingError(
            f"not a replay recording (format {got!r}, expected {RECORDING_FORMAT!r})"
            if isinstance(got, str)
            else "not a replay recording (no format name)"
        )
    if value.get("version") != RECORDING_VERSION:
        raise RecordingError(
            f"recording version {value.get('version')!r} is not supported "
            f"(this tool reads version {RECORDING_VERSION})"
        )
    obj = _object(value, _RECORDING_FIELDS, "recording")
    if not isinstance(obj["stage"], str):
        _fail("stage", f"expected a string, not {_json_type(obj['stage'])}")
    lights = _object(obj["lights"], ("distant", "local"), "lights")
    reflectors = list(_decode(obj["reflectors"], _Tuple(int), "reflectors"))
    frames = [
        _decode_frame(item, reflectors, f"frames[{f}]")
        for f, item in enumerate(_list(obj["frames"], "frames"))
    ]
    return {
        "stage": obj["stage"],
        "selection_weight": _decode(obj["selection_weight"], float, "selection_weight"),
        "bounce_limit": _decode(obj["bounce_limit"], int, "bounce_limit"),
        "lights": SimpleNamespace(
            distant=list(_decode(lights["distant"], _Tuple(DistantLight), "lights.distant")),
            local=list(_decode(lights["local"], _Tuple(LocalLight), "lights.local")),
        ),
        "reflectors": reflectors,
        "reflection_figures": tuple(
            _decode_array(item, _FIGURES[k], f"reflection_figures[{k}]")
            for k, item in enumerate(_list(obj["reflection_figures"], "reflection_figures"))
        ),
        "frames": frames,
    }


def load_recording(path: Path) -> dict:
    """Read a recording file written by ``save_recording`` (gzip or not: told by its first
    bytes). Never unpickles or evaluates anything; RecordingError (one line) for a file
    that is not such a recording."""
    try:
        raw = Path(path).read_bytes()
    except OSError as error:
        raise RecordingError(f"{path}: cannot read ({error.strerror or error})") from None
    try:
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        value = json.loads(raw)
    except (OSError, EOFError, zlib.error) as error:
        raise RecordingError(f"{path}: not a replay recording (bad gzip: {error})") from None
    except (ValueError, RecursionError) as error:
        # JSONDecodeError and UnicodeDecodeError are ValueErrors.
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise RecordingError(f"{path}: not a replay recording (not JSON: {reason})") from None
    try:
        return decode_recording(value)
    except RecordingError as error:
        raise RecordingError(f"{path}: {error}") from None


#: A capture's images npz: name → (dtype kind, ndim); every array has the frame count first.
_IMAGE_ARRAYS = {"ids": ("i", 3), "raster": ("f", 4), "all": ("f", 4), "traced": ("b", 3)}


def load_images(path: Path, n_frames: int) -> dict[str, np.ndarray]:
    """The arrays of ``capture``'s ``--images`` npz (``allow_pickle=False``: an object
    array or a pickle is refused), checked against a recording of ``n_frames`` frames."""
    try:
        npz = np.load(path, allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise ValueError("not an npz archive")
        with npz:
            missing = [k for k in _IMAGE_ARRAYS if k not in npz.files]
            if missing:
                raise ValueError(f"no array {missing[0]!r}")
            images = {k: npz[k] for k in _IMAGE_ARRAYS}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise RecordingError(f"{path}: not a capture's images ({error})") from None
    shape = images["ids"].shape
    for name, (dtype_kind, ndim) in _IMAGE_ARRAYS.items():
        a = images[name]
        if a.dtype.kind != dtype_kind or a.ndim != ndim or a.shape[:3] != shape[:3]:
            raise RecordingError(f"{path}: not a capture's images ({name!r}: {a.dtype} {a.shape})")
    if images["raster"].shape[3:] != (3,) or images["all"].shape != images["raster"].shape:
        raise RecordingError(f"{path}: not a capture's images (image shapes)")
    if shape[0] != n_frames:
        raise RecordingError(f"{path}: {shape[0]} frames of images, the recording has {n_frames}")
    return images


def compose(images, f: int, selected_ids: list[int]) -> np.ndarray:
    """(H, W, 3) float32: frame ``f``'s image when exactly ``selected_ids`` are traced.

    A reflector's traced pixels depend only on its own G-buffer pixels (its rays follow
    other reflectors whether or not those are selected), so the image of a selection is
    the ``all`` image on the selected reflectors' traced pixels and the raster image
    elsewhere."""
    take = images["traced"][f] & np.isin(images["ids"][f], selected_ids)
    return np.where(take[..., None], images["all"][f], images["raster"][f])


def mean_flip(images, selected: np.ndarray, reflectors: list[int]) -> float:
    """Mean over frames of the mean FLIP against the ``all`` image, for (F, R) bool
    ``selected`` over ``reflectors``."""
    refl = np.asarray(reflectors)
    errors = [
        float(flip_map(images["all"][f], compose(images, f, refl[row].tolist())).mean())
        for f, row in enumerate(selected)
    ]
    return float(np.mean(errors))


@dataclass(frozen=True)
class SimulatedTime:
    """A synthetic trace round time for time-budgeted replays: ``(overhead_ms +
    ms_per_ray * rays) * lognormal(0, jitter)``, drawn from a generator seeded with
    ``seed`` (so a replay is deterministic). ``fit_time`` gives this machine's line from
    a capture's own ``all`` rounds."""

    overhead_ms: float
    ms_per_ray: float
    jitter: float = 0.1
    seed: int = 0

    def round_ms(self, rays: int, rng: np.random.Generator) -> float:
        return (self.overhead_ms + self.ms_per_ray * rays) * float(rng.lognormal(0.0, self.jitter))


def fit_time(data: dict, jitter: float = 0.1, seed: int = 0) -> SimulatedTime:
    """The least-squares line (ms against rays) through the capture's rounds (one
    ``all`` round per frame with visible reflectors: the sum of its records' seconds),
    with a fixed cost >= 0 and a cost per ray > 0."""
    pts = [
        (sum(r.rays for r in recs), 1000.0 * sum(r.seconds for r in recs))
        for recs in (list(f.records.values()) for f in data["frames"])
        if recs
    ]
    if len(pts) < 2:
        raise RecordingError("the recording has fewer than two traced frames: no time line")
    x, y = np.array(pts, dtype=np.float64).T
    slope, intercept = np.polyfit(x, y, 1)
    if not slope > 0.0:
        slope, intercept = float(np.sum(y) / max(np.sum(x), 1.0)), 0.0
    return SimulatedTime(max(float(intercept), 0.0), float(slope), jitter, seed)


def _calibration(frame, sim: SimulatedTime, rng: np.random.Generator, budget_ms: float,
                 available: int) -> Calibration:  # fmt: skip
    """What ``engine.trace_calibration.calibrate_tracer`` hands the policy on the first
    time-budgeted frame with visible reflectors (``available`` reflector pixels), at that
    frame's mean rays per pixel: CALIBRATION_REPEATS timed rounds of each size growing
    from CALIBRATION_PIXELS as the renderer's do until one takes ``budget_ms``, then of
    whole reflectors at the coarsest density (their filled pixels cost nothing in the
    simulated time); each reflector's own rays per pixel from the capture's records."""
    records = list(frame.records.values())
    rpp = sum(r.rays for r in records) / max(sum(r.pixels for r in records), 1)
    samples, n, started = [], CALIBRATION_PIXELS, 0
    while True:
        pixels = min(n, available)
        timed = [sim.round_ms(round(pixels * rpp), rng) for _ in range(CALIBRATION_REPEATS)]
        samples.extend((round(pixels * rpp), ms, 0) for ms in timed)
        started += pixels * CALIBRATION_REPEATS
        stop_ms = min(budget_ms, CALIBRATION_ROUND_MAX_MS)
        if pixels == available or min(timed) >= stop_ms:
            break
        aim = n * CALIBRATION_AIM * stop_ms / max(min(timed), 1e-3)
        n = max(int(min(n * CALIBRATION_GROWTH, aim)), n + 1)
    covered = min(SPARSE_PIXELS_FACTOR * pixels, available)
    traced = round(covered * traced_fraction(covered, TRACE_DENSITIES[-1]))
    rays = round(traced * rpp)
    samples.extend((rays, sim.round_ms(rays, rng), covered - traced)
                   for _ in range(CALIBRATION_REPEATS))  # fmt: skip
    started += traced * CALIBRATION_REPEATS
    return Calibration(samples, round(started * rpp), started, records=records)


class _RecordedRounds:
    """The replay's tracing step of one frame: the capture's records of the round's
    reflectors (a reflector traced at a reduced density casts its share of its recorded,
    full-density rays, ``model.reflection_roughness.started_share``; its pixel kinds not
    counted), timed by ``sim`` (a time budget) or
    at 1 us a ray (a rays budget: the time is not read)."""

    def __init__(self, frame, sim: SimulatedTime | None, rng: np.random.Generator,
                 shares: np.ndarray) -> None:  # fmt: skip
        self.frame, self.sim, self.rng = frame, sim, rng
        #: (E, L) the elements' shares of pixels that start rays at each density (the
        #: recording's ``reflection_figures``).
        self.shares = shares

    def __call__(self, ids: list[int], densities: list[str]) -> TracedRound:
        counts = self.frame.view.pixel_counts
        # The recorded pixel kinds are the full-density capture's, not this density's:
        # not counted (the policy takes the density's skipped pixels as filled).
        shares = self.shares
        records = [
            replace(self.frame.records[i], rays=round(self.frame.records[i].rays * started_share(
                        shares[i], counts[i], TRACE_DENSITIES.index(d))),
                    screen_space=None, reused=None, filled=None, marched=None)
            for i, d in zip(ids, densities, strict=True)
        ]  # fmt: skip
        rays = sum(r.rays for r in records)
        ms = self.sim.round_ms(rays, self.rng) if self.sim is not None else 1e-3 * rays
        return TracedRound(records, rays, ms)


def replay(
    data: dict,
    heuristic: str,
    budget_rays: int | None,
    selection_weight: float | None = None,
    lookahead: bool = True,
    budget_ms: float | None = None,
    sim: SimulatedTime | None = None,
    spent: list | None = None,
):
    """Run ``heuristic`` over the recorded frames with a rays budget, through the
    renderer's round loop (``select.rounds.run_rounds``) with the recorded records as its
    tracing step; with ``lookahead`` each view gets the next recorded frames' cameras as
    ``upcoming_cameras``, as a render of the whole path does. Returns (selected, visible):
    (F, R) bool arrays over the recorded reflectors, in frame order.

    With ``budget_ms`` (and ``budget_rays`` None) the budget is a time T per frame and
    rounds take ``sim``'s synthetic time (calibrated on the first frame with visible
    reflectors, as the renderer does); ``spent``, if given, receives each frame's
    (simulated trace ms, traced rays, {element: density level} of the reflectors traced
    below full density): a reflector traced at a reduced density casts that share of its
    recorded rays."""
    weight = data["selection_weight"] if selection_weight is None else selection_weight
    policy = make_policy(heuristic, selection_weight=weight, bounce_limit=data["bounce_limit"])
    refl = data["reflectors"]
    column = {e: k for k, e in enumerate(refl)}
    selected = np.zeros((len(data["frames"]), len(refl)), dtype=bool)
    visible = np.zeros_like(selected)
    frames = data["frames"]
    timed = budget_ms is not None
    if timed and (sim is None or budget_rays is not None):
        raise ValueError("a time-budgeted replay needs sim and no rays budget")
    if not timed and budget_rays is None:
        raise ValueError("a replay needs a rays budget or a time budget")
    rng = np.random.default_rng(sim.seed if sim is not None else 0)
    limits = Budget(ms=budget_ms) if timed else Budget(rays=budget_rays)
    for f, frame in enumerate(frames):
        scene = SimpleNamespace(elements=frame.elements, lights=data["lights"],
                                reflection_figures=data["reflection_figures"])  # fmt: skip
        counts = frame.view.pixel_counts
        ahead = frames[f + 1 : f + 1 + UPCOMING_CAMERAS] if lookahead else []
        view = replace(frame.view, upcoming_cameras=tuple(g.view.camera for g in ahead))
        in_view = [e for e in refl if counts[e] > 0]
        rounds = run_rounds(
            policy, view, scene, in_view, limits,
            _RecordedRounds(frame, sim if timed else None, rng, data["reflection_figures"][1]),
            calibrate=partial(_calibration, frame, sim, rng, budget_ms,
                              int(counts[in_view].sum())),
        )  # fmt: skip
        if spent is not None:
            levels = {e: TRACE_DENSITIES.index(d) for e, d in rounds.densities.items()
                      if d != "full"}  # fmt: skip
            spent.append((rounds.trace_ms, rounds.rays, levels))
        for e in rounds.selected:
            selected[f, column[e]] = True
        for e in in_view:
            visible[f, column[e]] = True
    return selected, visible


def mean_rays(data: dict, selected: np.ndarray) -> float:
    """Mean traced rays per frame of an (F, R) ``selected`` (the recorded records' rays)."""
    refl = data["reflectors"]
    return float(
        np.mean(
            [
                sum(frame.records[refl[r]].rays for r in np.flatnonzero(row))
                for frame, row in zip(data["frames"], selected, strict=True)
            ]
        )
    )


def transition_counts(selected: np.ndarray, visible: np.ndarray) -> dict:
    """Transitions of (F, R) bool ``selected`` / ``visible`` as ``phrt report`` counts them
    (``selection_metrics``), split by kind: an *admission* is a reflector in view in both
    frames that becomes selected, a *drop* one that stops being selected.
    ``entered_selected``: selected on the frame it came into view (free)."""
    metrics = selection_metrics(selected, visible)
    adm, drop = admissions_and_drops(selected, visible)
    entered = int(np.count_nonzero(visible[1:] & ~visible[:-1] & selected[1:]))
    return {
        "transitions": metrics["transitions"],
        "admissions": adm,
        "drops": drop,
        "entered_selected": entered,
        "mean_selected": metrics["mean_selected"],
        "mean_visible": metrics["mean_visible"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("stage", type=Path)
    cap.add_argument("out", type=Path)
    cap.add_argument("--width", type=int, default=320)
    cap.add_argument("--height", type=int, default=240)
    cap.add_argument("--frames", default=None, help="A:B[:STEP] time codes (default: the path)")
    cap.add_argument("--images", type=Path, default=None, help="also write images (.npz)")
    rep = sub.add_parser("replay")
    rep.add_argument("recording", type=Path)
    rep.add_argument("--budgets", default="", help="comma list of rays budgets")
    rep.add_argument(
        "--budgets-ms", default="", help="comma list of time budgets T (ms), simulated time"
    )
    rep.add_argument("--overhead-ms", type=float, default=None, help="simulated round: fixed ms")
    rep.add_argument("--ms-per-ray", type=float, default=None, help="simulated round: ms per ray")
    rep.add_argument("--jitter", type=float, default=0.1, help="lognormal sigma of round times")
    rep.add_argument("--seed", type=int, default=0)
    rep.add_argument("--heuristics", default="heu1,heu2")
    rep.add_argument("--selection-weight", type=float, default=None)
    rep.add_argument("--no-lookahead", action="store_true", help="views without upcoming cameras")
    rep.add_argument("--images", type=Path, default=None, help="capture's images: add mean FLIP")
    args = ap.parse_args(argv)
    try:
        if args.command == "capture":
            capture(args.stage, args.out, args.width, args.height, args.frames, args.images)
            return 0
        data = load_recording(args.recording)
        images = load_images(args.images, len(data["frames"])) if args.images else None
        sim = fit_time(data, args.jitter, args.seed) if args.budgets_ms else None
    except PhrtError as error:
        print(f"policy_replay: {error}", file=sys.stderr)
        return 1
    if sim is not None:
        sim = SimulatedTime(
            sim.overhead_ms if args.overhead_ms is None else args.overhead_ms,
            sim.ms_per_ray if args.ms_per_ray is None else args.ms_per_ray,
            args.jitter,
            args.seed,
        )
        print(
            f"simulated round: ({sim.overhead_ms:.3f} ms + {sim.ms_per_ray * 1e3:.4f} us/ray"
            f" x rays) x lognormal(0, {sim.jitter}), seed {sim.seed}"
        )
    heuristics = [h.strip() for h in args.heuristics.split(",") if h.strip()]
    budgets = [("rays", int(b)) for b in args.budgets.split(",") if b.strip()]
    budgets += [("ms", float(b)) for b in args.budgets_ms.split(",") if b.strip()]
    if not budgets:
        print("policy_replay: give --budgets and/or --budgets-ms", file=sys.stderr)
        return 2
    print(
        "| budget | heuristic | transitions (adm + drop) | entered selected | mean selected "
        "| mean rays | budget use | density steps | mean FLIP |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for kind, budget in budgets:
        out = {}
        label = f"{budget} rays" if kind == "rays" else f"{budget:g} ms"
        for h in heuristics:
            lookahead = not args.no_lookahead
            times: list[float] = []
            selected, visible = replay(
                data, h, budget if kind == "rays" else None, args.selection_weight,
                lookahead=lookahead, budget_ms=budget if kind == "ms" else None, sim=sim,
                spent=times,
            )  # fmt: skip
            out[h] = c = transition_counts(selected, visible)
            flip = (
                "" if images is None else f"{mean_flip(images, selected, data['reflectors']):.5f}"
            )
            use = budget_use(visible, [t[0 if kind == "ms" else 1] for t in times], budget)
            levels = np.zeros(selected.shape, np.int64)
            column = {e: k for k, e in enumerate(data["reflectors"])}
            for f, (_, _, frame_levels) in enumerate(times):
                for e, level in frame_levels.items():
                    levels[f, column[e]] = level
            steps = density_steps(selected, visible, levels)
            print(
                f"| {label} | {h} | {c['transitions']} ({c['admissions']} + {c['drops']}) "
                f"| {c['entered_selected']} | {c['mean_selected']:.2f} "
                f"| {np.mean([t[1] for t in times]):.0f} | {use:.3f} | {steps} | {flip} |"
            )
        if "heu1" in out and "heu2" in out and out["heu2"]["transitions"]:
            pct = 100.0 * out["heu1"]["transitions"] / out["heu2"]["transitions"]
            print(f"| {label} | heu1/heu2 | {pct:.1f} % | | | | | | |")
    return 0


def budget_use(visible: np.ndarray, spent: list[float], budget) -> float:
    """Mean over the frames with visible reflectors (``visible`` (F, R) bool) of the
    share of the budget spent: ``spent`` (F,) each frame's simulated trace ms or traced
    rays (``replay``'s), over ``budget``, as ``stats.json``'s ``budget_use``."""
    seen = visible.any(axis=1)
    if not seen.any():
        return float("nan")
    return float(np.mean(np.asarray(spent, dtype=np.float64)[seen] / budget))

if __name__ == "__main__":
    raise SystemExit(main())
