"""The selection layer: which reflectors each rendered frame ray-traced, as a USD layer.

The layer holds only ``over`` specs, so it opens on its own and as a sublayer of the
rendered stage without defining or changing any renderable prim:

* an ``over`` at every reflector's prim path (ancestors get ``over``s too) with
  time samples at every rendered frame's time code:
  ``bool phrt:selected``, ``bool phrt:visible`` (every frame), and ``float phrt:V``,
  ``phrt:C``, ``phrt:R``, ``phrt:Q``, ``bool phrt:S`` (the heuristic's figures, paper
  Table 1) in frames where the reflector was a selection candidate, ``float
  phrt:traceDensity`` (the share of its pixels that started rays) where it was traced, a
  value block (``None``) in the others — so ``Get(t)`` never interpolates a figure into a
  frame where it was not computed;
* a reflector inside an instance cannot take opinions at its own path (an instance proxy
  of a scene-graph instance, ``/World/Tree_3/Leaves``; USD ignores opinions below an
  instanceable prim) or has no prim path at all (a PointInstancer instance,
  ``/World/Trees.instance[3]/Leaves``). Its samples go on its *host*, the nearest prim
  that takes opinions (the outermost instance root, or the PointInstancer, or that
  one's instance root): ``uniform string[] phrt:instanced:paths`` (the element paths)
  and time-sampled arrays aligned with it, ``bool[] phrt:instanced:selected``,
  ``bool[] phrt:instanced:visible``, ``float[] phrt:instanced:V`` ... (NaN where the
  element was not a candidate: an array cannot hold a value block);
* ``over PhrtRenderStats`` with per-frame ``double phrt:stats:frameMs``, ``traceMs``,
  ``predictedTraceMs`` and ``int64 phrt:stats:rays``, ``int phrt:stats:selectedCount``,
  ``visibleCount``;
* layer metadata: ``timeCodesPerSecond`` (the stage's, so a sublayer is not re-timed),
  ``startTimeCode``/``endTimeCode`` spanning every rendered frame, and
  ``customLayerData = {dictionary phrt = {...run settings...}}``.

Written with ``Sdf`` APIs directly (tens of thousands of samples in well under a second)
and saved atomically. See ``docs/selection-layer.md``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Sdf, Tf, Vt

from phrt_usd.atomic import WriteFailed, atomic_path
from phrt_usd.errors import BadOption, PhrtError, usd_error_reason
from phrt_usd.model.frame import FrameStats, ReflectorMetrics
from phrt_usd.run.run_files import check_run_info
from phrt_usd.usd.stage import open_usd

#: Prim holding the per-frame render statistics (an ``over``: never defined, never drawn).
STATS_PRIM_PATH = Sdf.Path("/PhrtRenderStats")
#: Key of the run settings dictionary in the layer's customLayerData.
LAYER_DATA_KEY = "phrt"
#: Stage fallback when neither the caller nor the stage gives timeCodesPerSecond.
DEFAULT_TIME_CODES_PER_SECOND = 24.0

SELECTED = "phrt:selected"
VISIBLE = "phrt:visible"

#: Per-frame figures of a candidate: attribute name, value type, ReflectorMetrics field.
FIGURE_ATTRIBUTES: tuple[tuple[str, Any, str], ...] = (
    ("phrt:V", Sdf.ValueTypeNames.Float, "V"),
    ("phrt:C", Sdf.ValueTypeNames.Float, "C"),
    ("phrt:R", Sdf.ValueTypeNames.Float, "R"),
    ("phrt:Q", Sdf.ValueTypeNames.Float, "Q"),
    ("phrt:S", Sdf.ValueTypeNames.Bool, "S"),
    ("phrt:traceDensity", Sdf.ValueTypeNames.Float, "trace_density"),
)

#: Per-frame statistics on the stats prim: attribute name, value type, value of a frame.
STATS_ATTRIBUTES: tuple[tuple[str, Any, Callable[[FrameStats], Any]], ...] = (
    ("phrt:stats:frameMs", Sdf.ValueTypeNames.Double, lambda f: float(f.frame_ms)),
    ("phrt:stats:traceMs", Sdf.ValueTypeNames.Double, lambda f: float(f.trace_ms)),
    (
        "phrt:stats:predictedTraceMs",
        Sdf.ValueTypeNames.Double,
        lambda f: float(f.predicted_trace_ms),
    ),
    ("phrt:stats:rays", Sdf.ValueTypeNames.Int64, lambda f: int(f.rays)),
    ("phrt:stats:selectedCount", Sdf.ValueTypeNames.Int, lambda f: len(f.selected)),
    ("phrt:stats:visibleCount", Sdf.ValueTypeNames.Int, lambda f: len(f.visible)),
)


#: Extensions a selection layer may have: USD's text (``.usda``) and crate (``.usdc``,
#: ``.usd``) layers, the encodings Sdf writes by extension.
LAYER_SUFFIXES = (".usda", ".usdc", ".usd")


def check_layer_path(path: Path | str, where: str = "selection layer") -> None:
    """BadOption (naming ``where``) unless ``path`` has an extension of LAYER_SUFFIXES;
    a render checks it before its first frame (``run_directory.RunDirectory``)."""
    if Path(path).suffix not in LAYER_SUFFIXES:
        raise BadOption(f"{where} {path}: extension must be {', '.join(LAYER_SUFFIXES)}")


def write_selection_layer(
    path: Path,
    stage_path: Path | str | None,
    reflector_paths: list[str],
    frames: list[FrameStats],
    run_info: dict[str, Any],
    time_codes_per_second: float | None = None,
    merge: bool = True,
    instance_roots: dict[str, str | None] | None = None,
) -> Path:
    """Write (or merge into) the selection layer at ``path`` (``.usda`` or ``.usdc``).

    reflector_paths: every reflector prim path of the stage; each gets ``phrt:selected``
    / ``phrt:visible`` samples at every frame of ``frames`` (False when it was not
    selected / not visible). time_codes_per_second: the stage's; ``None`` reads it from
    ``stage_path``. With ``merge`` and an existing file, samples at the rendered frames'
    time codes are replaced and all others kept (rendering a sub-range updates that
    sub-range); the run settings must match (same mode and heuristic) or PhrtError.
    instance_roots: element path → host prim of a reflector inside an instance (module
    doc); ``None`` finds them from the path itself (``.instance[i]``) and the stage at
    ``stage_path`` (its instance proxies). Returns ``path``.
    """
    path = Path(path)
    check_layer_path(path)
    tcps = _time_codes_per_second(stage_path, time_codes_per_second)
    layer = _open_for_merge(path, run_info, tcps) if merge and path.exists() else None
    if layer is None:
        layer = Sdf.Layer.CreateAnonymous(path.suffix)
    frames = sorted(frames, key=lambda f: f.time)

    # Every reflector gets samples at every new frame, including reflectors only the old
    # layer knew about, so no stale sample survives at a re-rendered time code.
    reflectors = list(dict.fromkeys(reflector_paths))
    for frame in frames:
        reflectors.extend(p for p in (*frame.visible, *frame.selected, *frame.metrics))
    reflectors.extend(_reflector_paths_in(layer))
    reflectors = list(dict.fromkeys(reflectors))

    old_instanced = _instanced_samples(layer)
    reflectors = list(dict.fromkeys([*reflectors, *old_instanced]))
    hosts = _hosts(reflectors, stage_path if instance_roots is None else None)
    if instance_roots is not None:
        hosts.update(
            {p: instance_roots[p] for p in reflectors if instance_roots.get(p) is not None}
        )
    membership = [(set(f.selected), set(f.visible)) for f in frames]
    with Sdf.ChangeBlock():
        for reflector in reflectors:
            if reflector not in hosts:
                _write_reflector(layer, reflector, frames, membership)
        _write_instanced(layer, hosts, old_instanced, frames, membership)
        _write_stats_prim(layer, frames)
        _write_metadata(layer, stage_path, run_info, frames, tcps)

    with atomic_path(path, check=_check_layer) as tmp:
        if not layer.Export(str(tmp)):
            raise WriteFailed(f"selection layer {path}: USD could not write the file")
    return path


def _check_layer(path: Path) -> None:
    """A check for ``atomic_path``: the written file opens as a USD layer again."""
    try:
        ok = Sdf.Layer.OpenAsAnonymous(str(path)) is not None
    except Exception:  # noqa: BLE001 - USD raises Tf.ErrorException
        ok = False
    if not ok:
        raise WriteFailed(f"selection layer {path}: the written file does not parse as USD")


@dataclass
class SelectionRecord:
    """Everything read back from a selection layer.

    times     : (F,) float64 rendered time codes, increasing
    reflectors: R reflector prim paths, sorted
    selected  : (F, R) bool, ``phrt:selected`` (False where no sample)
    visible   : (F, R) bool, ``phrt:visible`` (False where no sample)
    stats     : stats attribute name without namespace (``frameMs``, ``traceMs``, ...) →
                {time code: value} for the frames that have one
    run_info  : the layer's customLayerData["phrt"] as plain Python values
    """

    times: np.ndarray
    reflectors: list[str]
    selected: np.ndarray
    visible: np.ndarray
    stats: dict[str, dict[float, float]] = field(default_factory=dict)
    run_info: dict[str, Any] = field(default_factory=dict)
    time_codes_per_second: float = DEFAULT_TIME_CODES_PER_SECOND


def read_selection(layer_path: Path) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """(times (F,), reflectors (R paths), selected (F, R) bool, visible (F, R) bool)."""
    record = read_selection_record(layer_path)
    return record.times, record.reflectors, record.selected, record.visible


def read_selection_record(layer_path: Path) -> SelectionRecord:
    """Read a selection layer (samples, stats prim and run settings) into a record.
    PhrtError (one line) for a file that is not a readable selection layer."""
    layer = _open_layer(Path(layer_path))
    try:
        return _read_record(layer)
    except (Tf.ErrorException, UnicodeDecodeError, TypeError, ValueError) as error:
        # Damaged content that parsed as USD: wrong value types, undecodable strings.
        reason = usd_error_reason(error) if isinstance(error, Tf.ErrorException) else error
        raise PhrtError(f"selection layer {layer_path}: unreadable ({reason})") from None


def _read_record(layer: Sdf.Layer) -> SelectionRecord:
    instanced = _instanced_samples(layer)
    plain = [p for p in _reflector_paths_in(layer) if p not in instanced]
    reflectors = sorted([*plain, *instanced])

    def of(path: str, name: str) -> dict[float, Any]:
        if path in instanced:
            return instanced[path].get(name, {})
        return _samples(layer, Sdf.Path(path).AppendProperty(name))

    samples = {name: [of(p, name) for p in reflectors] for name in (SELECTED, VISIBLE)}
    stats = {
        name.rsplit(":", 1)[1]: {
            t: float(v) for t, v in _samples(layer, STATS_PRIM_PATH.AppendProperty(name)).items()
        }
        for name, _, _ in STATS_ATTRIBUTES
    }
    times = set()
    for per_reflector in samples[SELECTED]:
        times.update(per_reflector)
    times.update(stats["frameMs"])
    times = np.array(sorted(times), dtype=np.float64)
    row = {t: i for i, t in enumerate(times.tolist())}
    arrays = {}
    for name, per_reflector in samples.items():
        array = np.zeros((len(times), len(reflectors)), dtype=bool)
        for column, values in enumerate(per_reflector):
            for t, value in values.items():
                array[row[t], column] = bool(value)
        arrays[name] = array
    data = layer.customLayerData.get(LAYER_DATA_KEY, {})
    run_info = _from_vt(dict(data))
    check_run_info(run_info)
    return SelectionRecord(
        times=times,
        reflectors=reflectors,
        selected=arrays[SELECTED],
        visible=arrays[VISIBLE],
        stats={k: v for k, v in stats.items() if v},
        run_info=run_info,
        time_codes_per_second=float(layer.timeCodesPerSecond),
    )


# --- writing ---------------------------------------------------------------------------


def _write_reflector(
    layer: Sdf.Layer,
    reflector: str,
    frames: list[FrameStats],
    membership: list[tuple[set[str], set[str]]],
) -> None:
    """Samples of one reflector at every frame of ``frames`` (creating its ``over``).

    membership: per frame, (selected paths, visible paths) as sets.
    """
    try:
        prim_path = Sdf.Path(reflector)
    except Exception:  # noqa: BLE001 - Sdf raises Tf errors of varying types
        prim_path = Sdf.Path()
    if prim_path.isEmpty or not prim_path.IsAbsolutePath() or not prim_path.IsPrimPath():
        raise PhrtError(f"selection layer: {reflector!r} is not an absolute prim path")
    prim = layer.GetPrimAtPath(prim_path) or Sdf.CreatePrimInLayer(layer, prim_path)
    selected = _attribute(prim, SELECTED, Sdf.ValueTypeNames.Bool)
    visible = _attribute(prim, VISIBLE, Sdf.ValueTypeNames.Bool)
    figures = [(_attribute(prim, name, kind), key) for name, kind, key in FIGURE_ATTRIBUTES]
    for frame, (selected_paths, visible_paths) in zip(frames, membership, strict=True):
        layer.SetTimeSample(selected, frame.time, reflector in selected_paths)
        layer.SetTimeSample(visible, frame.time, reflector in visible_paths)
        metrics: ReflectorMetrics | None = frame.metrics.get(reflector)
        for attribute, key in figures:
            value = Sdf.ValueBlock() if metrics is None else _finite(getattr(metrics, key))
            layer.SetTimeSample(attribute, frame.time, value)


def _finite(value: Any) -> Any:
    """bools pass; a non-finite float becomes a value block (USD would store NaN/inf)."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    value = float(value)
    return value if np.isfinite(value) else Sdf.ValueBlock()


def _write_stats_prim(layer: Sdf.Layer, frames: list[FrameStats]) -> None:
    prim = layer.GetPrimAtPath(STATS_PRIM_PATH) or Sdf.CreatePrimInLayer(layer, STATS_PRIM_PATH)
    for name, kind, value_of in STATS_ATTRIBUTES:
        attribute = _attribute(prim, name, kind, custom=True)
        for frame in frames:
            value = value_of(frame)
            if isinstance(value, float) and not np.isfinite(value):
                value = Sdf.ValueBlock()
            layer.SetTimeSample(attribute, frame.time, value)


def _write_metadata(
    layer: Sdf.Layer,
    stage_path: Path | str | None,
    run_info: dict[str, Any],
    frames: list[FrameStats],
    tcps: float,
) -> None:
    layer.timeCodesPerSecond = tcps
    if frames:
        first, last = frames[0].time, frames[-1].time
        if layer.HasStartTimeCode():
            first = min(first, layer.startTimeCode)
        if layer.HasEndTimeCode():
            last = max(last, layer.endTimeCode)
        layer.startTimeCode, layer.endTimeCode = first, last
    info = dict(run_info)
    if stage_path is not None:
        info["stage"] = str(stage_path)
    data = dict(layer.customLayerData)
    data[LAYER_DATA_KEY] = _to_vt(info)
    layer.customLayerData = data


def _attribute(prim: Sdf.PrimSpec, name: str, kind: Any, custom: bool = False) -> Sdf.Path:
    """Path of attribute ``name`` on ``prim``, creating a varying spec if needed.

    The reflector figures are declared by ``PhrtReflectorAPI`` (schemas/phrt/schema.usda),
    so they are not ``custom``; the stats prim's attributes belong to no schema and are.
    """
    spec = prim.attributes.get(name)
    if spec is None:
        spec = Sdf.AttributeSpec(prim, name, kind, Sdf.VariabilityVarying, custom)
    elif spec.typeName != kind:
        raise PhrtError(f"selection layer: {spec.path} has type {spec.typeName}, not {kind}")
    return spec.path


def _to_vt(value: Any) -> Any:
    """Python value → something a VtDictionary holds; ``None`` entries are dropped."""
    if isinstance(value, dict):
        return {str(k): _to_vt(v) for k, v in value.items() if v is not None}
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, list | tuple):
        items = [v for v in value if v is not None]
        if all(isinstance(v, str) for v in items):
            return Vt.StringArray(items)
        if all(isinstance(v, int) and not isinstance(v, bool) for v in items):
            return Vt.IntArray(items)
        return Vt.DoubleArray([float(v) for v in items])
    if isinstance(value, np.generic):
        return value.item()
    return value


def _from_vt(value: Any) -> Any:
    """VtDictionary contents → plain Python (arrays become lists)."""
    if isinstance(value, dict):
        return {k: _from_vt(v) for k, v in value.items()}
    if hasattr(value, "__len__") and not isinstance(value, str):
        return [_from_vt(v) for v in value]
    return value


# --- reading ---------------------------------------------------------------------------


def _open_layer(path: Path) -> Sdf.Layer:
    """Fresh in-memory copy of the layer file (bypasses the layer registry's cache, which
    could hold an older version of a file we rewrote)."""
    if not path.is_file():
        raise PhrtError(f"selection layer {path}: no such file")
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path))
    except Exception as error:  # noqa: BLE001 - USD raises Tf.ErrorException
        reason = usd_error_reason(error)
        raise PhrtError(f"selection layer {path}: cannot open ({reason})") from None
    if layer is None:
        raise PhrtError(f"selection layer {path}: cannot open")
    return layer


def _open_for_merge(path: Path, run_info: dict[str, Any], tcps: float) -> Sdf.Layer:
    layer = _open_layer(path)
    old = _from_vt(dict(layer.customLayerData.get(LAYER_DATA_KEY, {})))
    for key in ("mode", "heuristic"):
        if key in old and key in run_info and old[key] != run_info[key]:
            raise PhrtError(
                f"selection layer {path}: was written with {key} {old[key]!r}, this run "
                f"uses {run_info[key]!r}; write to another path or do not merge"
            )
    if layer.HasTimeCodesPerSecond() and layer.timeCodesPerSecond != tcps:
        raise PhrtError(
            f"selection layer {path}: timeCodesPerSecond {layer.timeCodesPerSecond} "
            f"differs from the stage's {tcps}; write to another path or do not merge"
        )
    return layer


def _reflector_paths_in(layer: Sdf.Layer) -> list[str]:
    """Paths of every prim spec in ``layer`` that carries ``phrt:selected``."""
    found: list[str] = []

    def visit(prim: Sdf.PrimSpec) -> None:
        if SELECTED in prim.attributes:
            found.append(str(prim.path))
        for child in prim.nameChildren:
            visit(child)

    for root in layer.rootPrims:
        visit(root)
    return found


def _samples(layer: Sdf.Layer, attribute: Sdf.Path) -> dict[float, Any]:
    """{time code: value} of an attribute's samples; blocked samples are left out."""
    values = {}
    for t in layer.ListTimeSamplesForPath(attribute):
        value = layer.QueryTimeSample(attribute, t)
        if value is not None and not isinstance(value, Sdf.ValueBlock):
            values[float(t)] = value
    return values


def _time_codes_per_second(stage_path: Path | str | None, given: float | None) -> float:
    if given is not None:
        if not np.isfinite(given) or given <= 0:
            raise PhrtError(f"selection layer: timeCodesPerSecond {given} must be positive")
        return float(given)
    if stage_path is None:
        return DEFAULT_TIME_CODES_PER_SECOND
    root = Sdf.Layer.FindOrOpen(str(stage_path))
    if root is None:
        raise PhrtError(f"{stage_path}: cannot open stage to read timeCodesPerSecond")
    return float(root.timeCodesPerSecond)


# --- reflectors inside instances -------------------------------------------------------

#: Host attributes of instanced reflectors (module doc): the element paths, and per
#: time code one array entry per path.
INSTANCED_PATHS = "phrt:instanced:paths"
INSTANCED_PREFIX = "phrt:instanced:"
#: (sample name as a per-prim attribute, array value type, value where there is none).
INSTANCED_ARRAYS: tuple[tuple[str, Any, Any], ...] = (
    (SELECTED, Sdf.ValueTypeNames.BoolArray, False),
    (VISIBLE, Sdf.ValueTypeNames.BoolArray, False),
    *(
        (name, Sdf.ValueTypeNames.FloatArray if kind == Sdf.ValueTypeNames.Float
         else Sdf.ValueTypeNames.BoolArray, np.nan if kind == Sdf.ValueTypeNames.Float
         else False)
        for name, kind, _ in FIGURE_ATTRIBUTES
    ),
)  # fmt: skip


def _instanced_name(name: str) -> str:
    """``phrt:selected`` → ``phrt:instanced:selected``."""
    return INSTANCED_PREFIX + name.split(":", 1)[1]


def _host_prefix(path: str) -> str | None:
    """The instancer prim path of a PointInstancer element path (the part before its
    first ``.instance[``), None for a prim path."""
    head, sep, _ = path.partition(".instance[")
    return head if sep else None


#: (stage real path, its mtime, reflectors) → hosts: a render writes its layer at every
#: checkpoint and the stage is opened for this once, not every time.
_HOSTS_CACHE: dict[tuple, dict[str, str]] = {}


def _hosts(reflectors: list[str], stage_path: Path | str | None) -> dict[str, str]:
    """element path → host prim path for the reflectors that cannot take opinions at
    their own path: PointInstancer elements always; instance proxies when the stage at
    ``stage_path`` is given (opened once per stage file and reflector list)."""
    key = None
    if stage_path is not None and Path(stage_path).is_file():
        real = os.path.realpath(stage_path)
        key = (real, os.stat(real).st_mtime_ns, tuple(reflectors))
        if key in _HOSTS_CACHE:
            return dict(_HOSTS_CACHE[key])
    hosts = _find_hosts(reflectors, stage_path)
    if key is not None:
        _HOSTS_CACHE.clear()  # one stage at a time is all a render needs
        _HOSTS_CACHE[key] = dict(hosts)
    return hosts


def _find_hosts(reflectors: list[str], stage_path: Path | str | None) -> dict[str, str]:
    stage = None
    if stage_path is not None and Path(stage_path).is_file():
        try:
            stage = open_usd(stage_path)
        except PhrtError:
            stage = None  # the render opened it; the path forms below still apply
    hosts = {}
    for path in reflectors:
        prefix = _host_prefix(path)
        host = prefix if prefix is not None else None
        prim = stage.GetPrimAtPath(host or path) if stage is not None else None
        if prim and prim.IsInstanceProxy():
            while prim.IsInstanceProxy():
                prim = prim.GetParent()
            host = str(prim.GetPath())
        if host is not None:
            hosts[path] = host
    return hosts


def _instanced_samples(layer: Sdf.Layer) -> dict[str, dict[str, dict[float, Any]]]:
    """element path → {per-prim attribute name → {time code: value}} from every host in
    ``layer``; entries with no value (False / NaN fill) are kept as written, NaN figures
    left out."""
    found: dict[str, dict[str, dict[float, Any]]] = {}

    def visit(prim: Sdf.PrimSpec) -> None:
        paths_attr = prim.attributes.get(INSTANCED_PATHS)
        if paths_attr is not None and paths_attr.default is not None:
            paths = list(paths_attr.default)
            for path in paths:
                found.setdefault(path, {})
            for name, _, _ in INSTANCED_ARRAYS:
                attr = prim.path.AppendProperty(_instanced_name(name))
                for t, values in _samples(layer, attr).items():
                    if len(values) != len(paths):
                        raise PhrtError(
                            f"selection layer: {attr} has {len(values)} entries at time "
                            f"{t}, {INSTANCED_PATHS} names {len(paths)}"
                        )
                    for path, value in zip(paths, values, strict=True):
                        if isinstance(value, float) and not np.isfinite(value):
                            continue
                        found[path].setdefault(name, {})[t] = value
        for child in prim.nameChildren:
            visit(child)

    for root in layer.rootPrims:
        visit(root)
    return found


def _write_instanced(
    layer: Sdf.Layer,
    hosts: dict[str, str],
    old: dict[str, dict[str, dict[float, Any]]],
    frames: list[FrameStats],
    membership: list[tuple[set[str], set[str]]],
) -> None:
    """The host arrays of every instanced reflector: the old layer's samples at other
    time codes kept, the rendered frames' replaced."""
    by_host: dict[str, list[str]] = {}
    for path, host in hosts.items():
        by_host.setdefault(host, []).append(path)
    for host, paths in by_host.items():
        paths = sorted(paths)
        samples = {p: {k: dict(v) for k, v in old.get(p, {}).items()} for p in paths}
        for frame, (selected, visible) in zip(frames, membership, strict=True):
            for p in paths:
                per = samples[p]
                per.setdefault(SELECTED, {})[frame.time] = p in selected
                per.setdefault(VISIBLE, {})[frame.time] = p in visible
                metrics = frame.metrics.get(p)
                for name, _, key in FIGURE_ATTRIBUTES:
                    values = per.setdefault(name, {})
                    values.pop(frame.time, None)
                    if metrics is not None:
                        value = _finite(getattr(metrics, key))
                        if not isinstance(value, Sdf.ValueBlock):
                            values[frame.time] = value
        spec = layer.GetPrimAtPath(host) or Sdf.CreatePrimInLayer(layer, Sdf.Path(host))
        names = spec.attributes.get(INSTANCED_PATHS) or Sdf.AttributeSpec(
            spec, INSTANCED_PATHS, Sdf.ValueTypeNames.StringArray, Sdf.VariabilityUniform, True
        )
        names.default = Vt.StringArray(paths)
        times = sorted({t for p in paths for t in samples[p].get(SELECTED, {})})
        for name, kind, fill in INSTANCED_ARRAYS:
            attr = _attribute(spec, _instanced_name(name), kind, custom=True)
            layer.GetAttributeAtPath(attr).ClearInfo("timeSamples")
            for t in times:
                row = [samples[p].get(name, {}).get(t, fill) for p in paths]
                array = Vt.BoolArray if isinstance(fill, bool) else Vt.FloatArray
                layer.SetTimeSample(attr, t, array(row))
