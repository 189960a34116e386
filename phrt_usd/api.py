"""The Python API pipelines call, and the layer the ``phrt render`` command is a shell around.

* ``render(stage_or_path, out=None, frames=None, **options) -> RenderResult``: a whole
  render (images, ``stats.json``, selection layer) and what it found.
* ``open(stage_or_path, frames=None, **options) -> Renderer``: a context-managed renderer
  that returns a frame's arrays (``FrameOutput``) without writing anything.
* ``render_options(stage, settings=None, **overrides) -> RenderOptions``: the stage's
  render settings with the caller's overrides, as the CLI reads them.
* ``render_job(...) -> (RenderJob, StageScene)`` and ``run_render(job)``: the two steps
  ``render`` takes, for callers (the CLI) that print as the job runs; ``run_render`` runs
  it in this process or on a Dask cluster (``workers`` / ``scheduler``).

Options (``**options``; ``None`` means "not given": the stage's render settings decide):
the render options, each declared once with its type, default, range or choices and help
in ``phrt_usd.model.render_options.OPTIONS`` (``mode``, ``heuristic``, ``budget_ms``
(``math.inf``: unbounded), ``budget_rays``, ``target_fps`` (exclusive with
``budget_ms``), ``bounce_limit``, ``selection_weight``, ``threads``, ``gl``, ``primary``,
``trace_density``, ``exposure``; the ``RenderOptions`` fields), with ``resolution``
(``(w, h)`` or ``"WxH"``) or ``width`` / ``height``; for ``render`` the ``RenderJob``
fields ``camera``, ``selection_layer``, ``resume``, ``overwrite``, ``write_images``,
``checkpoint_every``; ``strict`` (an unreadable texture is an error, not a warning and
the input's fallback); and how a stage file is composed: ``session_layers`` (files,
strongest first), ``variants`` (``{"/World/Car": {"paint": "red"}}`` or
``["/World/Car:paint=red"]``), ``mask`` (prim paths the stage is populated with). An
unknown name or a bad value raises ``BadOption`` (one line, through ``phrt_usd.checks``)
before anything is read or written. See ``docs/api.md``.

The summary (``run_render``, ``RenderResult.summary``) is what ``phrt render --json``
prints, finished here once for the API and the CLI (``phrt_usd.evaluate.run_summary``):
the report of the run's selection layer (frames, mean_fps, median_frame_ms,
mean_selected, transitions, reflectors, budget_ms, budget_overruns, ...) plus ``out``,
``selection_layer``, the ``passes`` its frames ran, how it ran: ``threads`` (the
setting), ``gl`` (the OpenGL platform of its raster phase, None without one: ``rt`` on
a stage of at most two lights), ``llvmpipe_threads`` (llvmpipe's render threads, None
without) and ``kernels``
(``cached``, or ``compiled`` when this process compiled kernels missing from the cache:
``phrt_usd.kernels.form``), what its hybrid frames traced, and the stage's
``warnings``, ``default_light_rig`` and ``support``.
"""

from __future__ import annotations

import math
import numbers
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Usd

from phrt_usd.checks import (
    check_bool,
    check_finite,
    check_integer,
    check_number,
    check_range,
    check_token,
)
from phrt_usd.engine.renderer import FrameOutput, FrameRenderer
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.evaluate.run_summary import (  # noqa: F401 - trace_summary: the API's too
    finish_summary,
    summary_of,
    trace_summary,
)
from phrt_usd.model.frame import FrameStats
from phrt_usd.model.render_options import OPTIONS, RenderOptions
from phrt_usd.run.frame_reader import read_frame_files
from phrt_usd.run.frames import SAME_FRAME, parse_frames
from phrt_usd.run.products import ImagePlan
from phrt_usd.run.render_job import RenderJob, render_to_directory
from phrt_usd.usd.schema import read_render_params
from phrt_usd.usd.stage import StageScene, open_stage, open_usd, read_stage
from phrt_usd.usd.stage_controls import StageControls
from phrt_usd.usd.textures import TextureError

#: What the API renders: a stage file or an open stage.
StageInput = str | os.PathLike | Usd.Stage
#: Which frames: a ``--frames`` spec (``"1:9x4"``, ``"1:9:2"``, ``"1,5,9"``), one time
#: code, a sequence of time codes, or None for the stage's whole range.
FramesInput = str | float | Sequence[float] | None
#: ``on_frame(done, total, stats)``, called after every rendered frame.
OnFrame = Callable[[int, int, FrameStats], None]

#: Options ``render_options`` takes: the render options (the table's order) and
#: ``resolution``.
RENDER_OPTION_NAMES: tuple[str, ...] = (*OPTIONS, "resolution")
#: RenderJob fields the API fills in itself; the others are options of ``render``.
_JOB_FILLED = ("stage_path", "out_dir", "options", "frames")
#: How a stage file is composed when opened (``StageControls``; the CLI's
#: ``--session-layer``, ``--variant``, ``--mask``).
COMPOSITION_OPTION_NAMES = ("session_layers", "variants", "mask")
#: How the stage is read: ``strict`` (the CLI's ``--strict``) makes a fallback the render
#: would take for an unreadable texture an error (``_refuse_fallbacks``).
READ_OPTION_NAMES = ("strict",)
#: Options ``open`` takes beside the render options (it writes no run directory).
_OPEN_OPTIONS = ("camera", "controls")


def job_option_names() -> tuple[str, ...]:
    """The ``render`` options that go to the ``RenderJob`` (camera, selection_layer,
    resume, overwrite, write_images, checkpoint_every, ...)."""
    return tuple(f.name for f in fields(RenderJob) if f.name not in _JOB_FILLED)


# --------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------


def render_options(
    stage: Usd.Stage, settings: str | None = None, **overrides: Any
) -> RenderOptions:
    """``RenderOptions`` from the stage's render settings (the prim ``settings``, else the
    stage's ``renderSettingsPrimPath``, else the only one, else the schema's defaults;
    ``usd.schema.read_render_params``) with ``overrides`` (see the module docstring; a
    ``None`` override is not given). A rays budget given without ``budget_ms`` replaces
    the stage's time budget (a deterministic run); ``budget_ms=math.inf`` is unbounded.
    Raises ``BadOption`` (one line) for an unknown name or a bad value."""
    _known(overrides, RENDER_OPTION_NAMES, "render option")
    given = {name: value for name, value in overrides.items() if value is not None}
    params = read_render_params(stage, settings)
    width, height = _resolution(given, params.resolution)
    rays = given.get("budget_rays", params.budget_rays)
    fps = given.get("target_fps")
    if "budget_ms" in given:
        ms = _unbounded(check_number(given["budget_ms"], "budget_ms"))
        # A budget given here replaces the stage's frame-rate target (both given: BadOption).
    elif "budget_rays" in given or fps is not None:
        ms = None  # a rays budget alone is the deterministic budget
    elif params.target_fps is not None:
        ms, fps = None, params.target_fps  # the stage's phrt:targetFps replaces its budget
    else:
        ms = _unbounded(params.budget_ms)
    # The stage's settings (the options a schema attribute sets), under the caller's
    # options; RenderOptions checks each value by its option (OPTIONS).
    values = {name: getattr(params, name) for name, o in OPTIONS.items() if o.schema_attribute}
    values.update((name, value) for name, value in given.items() if name in OPTIONS)
    values.update(width=width, height=height, budget_ms=ms, budget_rays=rays, target_fps=fps)
    return RenderOptions(**values)


def _known(options: dict[str, Any], names: Sequence[str], kind: str) -> None:
    """BadOption naming the first (sorted) of ``options`` not in ``names``."""
    for name in sorted(set(options) - set(names))[:1]:
        check_token(name, names, kind)


def _unbounded(ms: float | None) -> float | None:
    """An infinite time budget is no time budget."""
    return None if ms is not None and ms == math.inf else ms


def parse_resolution(text: str) -> tuple[int, int]:
    """``"320x240"`` → (320, 240); BadOption otherwise (ranges: ``RenderOptions``)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise BadOption(f"--resolution {text!r}: expected WxH, e.g. 320x240") from None
    return width, height


def _resolution(given: dict[str, Any], default: tuple[int, int]) -> tuple[int, int]:
    """(width, height) from ``resolution`` ((w, h) or "WxH") or ``width`` / ``height``."""
    if "resolution" not in given:
        width = check_integer(given.get("width", default[0]), "width")
        return width, check_integer(given.get("height", default[1]), "height")
    if "width" in given or "height" in given:
        raise BadOption("give resolution or width/height, not both")
    value = given["resolution"]
    if isinstance(value, str):
        return parse_resolution(value)
    if not isinstance(value, Sequence) or len(value) != 2:
        raise BadOption(f"resolution must be (width, height) or 'WxH', got {value!r}")
    return check_integer(value[0], "width"), check_integer(value[1], "height")


def _check_job_options(options: dict[str, Any]) -> None:
    """BadOption for a RenderJob option of the wrong kind (the fields checked by type)."""
    for name in ("resume", "overwrite", "write_images"):
        if name in options:
            check_bool(options[name], name)
    if "checkpoint_every" in options:
        every = check_integer(options["checkpoint_every"], "checkpoint_every")
        check_range(every, 1, None, "checkpoint_every")
    controls = options.get("controls")
    if controls is not None and not isinstance(controls, StageControls):
        raise BadOption(f"controls must be a StageControls, got {controls!r}")
    camera = options.get("camera")
    if camera is not None and not isinstance(camera, str):
        raise BadOption(f"camera must be a prim path or camera name string, got {camera!r}")
    layer = options.get("selection_layer")
    if layer is not None:
        if not isinstance(layer, str | os.PathLike):
            raise BadOption(f"selection_layer must be a path, got {layer!r}")
        options["selection_layer"] = Path(layer)


def frames_spec(frames: FramesInput) -> str | None:
    """The ``--frames`` text of ``frames`` (see ``FramesInput``); BadOption if it is none."""
    if frames is None or isinstance(frames, str):
        return frames
    if isinstance(frames, numbers.Real) and not isinstance(frames, bool):
        frames = [frames]
    if isinstance(frames, Sequence | np.ndarray) and len(frames):
        codes = [check_number(t, "frames") for t in frames]
        if all(math.isfinite(t) for t in codes):
            return ",".join(repr(t) for t in codes)
        raise BadOption(f"frames must be finite time codes, got {list(frames)!r}")
    raise BadOption(f"frames must be a spec like '1:9x4', a time code or a list, got {frames!r}")


# --------------------------------------------------------------------------------------
# Stages and jobs
# --------------------------------------------------------------------------------------


def stage_controls(
    session_layers: Any = None, variants: Any = None, mask: Any = None
) -> StageControls:
    """``StageControls`` from the composition options (see the module docstring); a
    single path or prim path may stand for a list of one. BadOption for a bad value."""
    layers = [session_layers] if isinstance(session_layers, str | os.PathLike) else session_layers
    if isinstance(variants, dict):
        variants = [f"{prim}:{vset}={name}" for prim, sets in variants.items()
                    for vset, name in _items("variants", sets)]  # fmt: skip
    masked = [mask] if isinstance(mask, str) else mask
    for name, value in (("session_layers", layers), ("variants", variants), ("mask", masked)):
        if value is not None and (isinstance(value, str) or not isinstance(value, Sequence)):
            raise BadOption(f"{name} must be a list, got {value!r}")
    if any(not isinstance(v, str) for v in (*(variants or ()), *(masked or ()))):
        raise BadOption("variants and mask take strings (prim paths, PRIM:SET=NAME)")
    if any(not isinstance(v, str | os.PathLike) for v in layers or ()):
        raise BadOption(f"session_layers must be layer file paths, got {layers!r}")
    return StageControls.from_options(layers or (), variants or (), ",".join(masked or ()))


def _items(name: str, value: Any) -> list[tuple[str, str]]:
    if not isinstance(value, dict):
        raise BadOption(f"{name} must map prim paths to {{variant set: name}}, got {value!r}")
    return [(str(k), str(v)) for k, v in value.items()]


def open_stage_input(
    stage_or_path: StageInput, controls: StageControls | None = None
) -> tuple[Usd.Stage, Path]:
    """The open stage and the file that names it (the root layer's path, or its
    identifier for an in-memory stage). A file is opened composed with ``controls``; an
    open stage is taken as it is. PhrtError (one line) for an unreadable file."""
    if isinstance(stage_or_path, Usd.Stage):
        root = stage_or_path.GetRootLayer()
        return stage_or_path, Path(root.realPath or root.identifier)
    if isinstance(stage_or_path, str | os.PathLike):
        return open_usd(stage_or_path, controls), Path(os.fspath(stage_or_path))
    raise BadOption(
        f"expected a stage file path or a Usd.Stage, got {type(stage_or_path).__name__}"
    )


def render_job(
    stage_or_path: StageInput,
    out: str | os.PathLike,
    frames: FramesInput = None,
    *,
    settings: str | None = None,
    stage_path: str | os.PathLike | None = None,
    **options: Any,
) -> tuple[RenderJob, StageScene]:
    """The job ``render`` runs and the stage read for it: options checked first
    (BadOption), then the stage opened and read (PhrtError). ``stage_path`` names the
    stage in the run's records when an open stage is given (default: its root layer's
    path). An open stage is rendered as it is composed; ``controls`` (a ``StageControls``)
    then records how it was opened, and ``session_layers`` / ``variants`` / ``mask``, which
    only a stage file can take, raise BadOption."""
    spec, job_options, render, scene, named = _prepare(
        stage_or_path, frames, settings, options, job_option_names()
    )
    job = RenderJob(
        stage_path=Path(stage_path) if stage_path is not None else named,
        out_dir=Path(out),
        options=render,
        frames=spec,
        **job_options,
    )
    return job, scene


def _prepare(stage_or_path, frames, settings, options, job_names):
    """(frames spec, job options, RenderOptions, StageScene, stage file) of a call."""
    _known(
        options,
        (*RENDER_OPTION_NAMES, *COMPOSITION_OPTION_NAMES, *READ_OPTION_NAMES, *job_names),
        "option",
    )
    given = {k: v for k, v in options.items() if v is not None}
    job_options = {k: v for k, v in given.items() if k in job_names}
    if settings is not None and "settings" in job_names:
        job_options["settings"] = settings  # the job writes that prim's products
    if "resolution_given" in job_names and "resolution_given" not in job_options:
        # a resolution asked for wins over the products' own
        job_options["resolution_given"] = bool({"resolution", "width", "height"} & set(given))
    _check_job_options(job_options)
    composition = {k: v for k, v in given.items() if k in COMPOSITION_OPTION_NAMES}
    controls = job_options.get("controls")
    if composition:
        if controls is not None:
            raise BadOption("give controls or session_layers/variants/mask, not both")
        if isinstance(stage_or_path, Usd.Stage):
            raise BadOption(
                f"{', '.join(composition)}: an open stage is already composed; pass the "
                "stage file, or open it with these yourself"
            )
        controls = job_options["controls"] = stage_controls(**composition)
    spec = frames_spec(frames)
    stage, named = open_stage_input(stage_or_path, controls)
    render = render_options(
        stage, settings, **{k: v for k, v in options.items() if k in RENDER_OPTION_NAMES}
    )
    scene = read_stage(stage, camera=job_options.get("camera"), settings=settings)
    if given.get("strict"):
        _refuse_fallbacks(scene)
    return spec, job_options, render, scene, named


def _refuse_fallbacks(scene: StageScene) -> None:
    """``strict``: a texture the render would replace by its input's fallback (a
    warning otherwise) is an error: ``TextureError`` naming the first one (the CLI
    exits 1, as for a failed render)."""
    problems = scene.texture_problems
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise TextureError(f"{problems[0]}{more}; --strict makes a texture fallback an error")


def run_render(
    job: RenderJob,
    on_frame: OnFrame | None = None,
    stage_scene: StageScene | None = None,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    chunk_frames: int | None = None,
    warmup: int | None = None,
) -> dict:
    """Render ``job`` and return its finished summary (see the module docstring).
    ``on_frame(done, total, stats)`` after every frame; ``stage_scene``: the stage already
    read, if any. On a Dask cluster (``phrt_usd.cluster``, docs/cluster.md) when
    ``workers`` (a local cluster of that many processes) or ``scheduler`` (the address of
    a running one) is given: ``chunk_frames`` frames a task after ``warmup`` unrecorded
    ones, ``on_frame(done, total, None)`` after every chunk.
    Raises ``PhrtError`` (one line) for bad input, a busy or non-empty output directory,
    or a failed frame (after the finished frames' records are written);
    ``RenderInterrupted`` after SIGINT / SIGTERM."""
    scene = stage_scene or open_stage(
        job.stage_path, camera=job.camera, controls=job.controls, settings=job.settings
    )
    if workers is None and scheduler is None:
        return finish_summary(summary_of(render_to_directory(job, on_frame, scene)), scene)
    from phrt_usd.cluster import dask_client, run_render_on_cluster

    chunks = cluster_chunking(chunk_frames, warmup)
    per_chunk = None if on_frame is None else (lambda done, total: on_frame(done, total, None))
    with dask_client(workers, scheduler) as client:
        summary = run_render_on_cluster(job, client, on_frame=per_chunk, **chunks)
    # Warnings the workers found while rendering, once each (``render_warnings``).
    found = summary.pop("render_warnings", [])
    scene.warnings += [w for w in found if w not in scene.warnings]
    return finish_summary(summary, scene)


def cluster_chunking(chunk_frames: int | None, warmup: int | None) -> dict:
    """The chunking arguments of a cluster run, defaults filled in (``phrt_usd.cluster``:
    96 frames a chunk, 8 warm-up frames) and checked (BadOption)."""
    from phrt_usd.cluster import DEFAULT_CHUNK_FRAMES, DEFAULT_WARMUP_FRAMES, check_chunking

    chunks = {
        "chunk_frames": DEFAULT_CHUNK_FRAMES if chunk_frames is None else chunk_frames,
        "warmup": DEFAULT_WARMUP_FRAMES if warmup is None else warmup,
    }
    check_chunking(**chunks)
    return chunks


# --------------------------------------------------------------------------------------
# render(): a whole run and its result
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameImages:
    """The image files of one rendered frame: each RenderProduct's (or ``image``'s), else
    the default ``frames/NNNN.exr`` and its ``.png`` preview (``phrt_usd.run.products``)."""

    time: float
    files: tuple[Path, ...]

    @property
    def exr(self) -> Path | None:
        """The frame's first EXR (the default layout's every-channel EXR), if any."""
        return next((f for f in self.files if f.suffix.lower() == ".exr"), None)

    @property
    def png(self) -> Path | None:
        """The frame's first PNG (the default layout's preview), if any."""
        return next((f for f in self.files if f.suffix.lower() == ".png"), None)


@dataclass(frozen=True)
class RenderResult:
    """What ``render`` made. ``summary``: the ``phrt render --json`` fields; ``frames``:
    each frame's ``FrameStats`` in time order; ``images``: each frame's files (empty with
    ``write_images=False``); ``out``: the run directory; ``selection_layer``: its layer.

    With ``out=None`` the run directory is a temporary directory this result owns: it is
    removed by ``cleanup()``, on leaving a ``with`` block, or when the result is garbage
    collected; copy what you keep."""

    summary: dict[str, Any]
    frames: tuple[FrameStats, ...]
    images: tuple[FrameImages, ...]
    out: Path
    selection_layer: Path
    _temporary: tempfile.TemporaryDirectory | None = field(default=None, repr=False, compare=False)
    _plan: ImagePlan | None = field(default=None, repr=False, compare=False)  # for read_frame

    @property
    def temporary(self) -> bool:
        """True when ``out`` is a temporary directory this result removes."""
        return self._temporary is not None

    def image(self, time: float | None = None) -> FrameImages:
        """The files of the frame at time code ``time`` (default: the first frame)."""
        if not self.images:
            raise PhrtError(f"{self.out}: this render wrote no images (write_images=False)")
        if time is None:
            return self.images[0]
        for images in self.images:
            if abs(images.time - float(time)) <= SAME_FRAME:
                return images
        shown = ", ".join(f"{i.time:g}" for i in self.images[:8])
        more = ", ..." if len(self.images) > 8 else ""
        raise PhrtError(f"no frame at time code {time:g} in this render ({shown}{more})")

    def read_frame(self, time: float | None = None) -> dict[str, np.ndarray]:
        """The planes of a frame, read back from whatever files its RenderProducts (or the
        default layout) wrote (``run.frame_reader.read_frame_files``): ``beauty`` (H, W, 3)
        float32 linear RGB, and as the products hold them ``alpha``, ``depth`` (inf for
        background), ``element_id`` (H, W) int32, ``traced_mask`` (H, W) bool,
        ``normal``, ``position``, ``albedo``, ``reflectivity``, ``motion`` (H, W, 2),
        ``pixel_kind`` (H, W) uint8. The default layout gives
        beauty, alpha, depth, element_id and traced_mask."""
        images = self.image(time)
        if self._plan is None:
            raise PhrtError(f"{self.out}: this result does not know its image files")
        return read_frame_files(self._plan, self.out, images.time)

    def cleanup(self) -> None:
        """Remove the temporary run directory (nothing for a caller's ``out``)."""
        if self._temporary is not None:
            self._temporary.cleanup()

    def __enter__(self) -> RenderResult:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cleanup()


def render(
    stage_or_path: StageInput,
    out: str | os.PathLike | None = None,
    frames: FramesInput = None,
    *,
    settings: str | None = None,
    on_frame: OnFrame | None = None,
    exposure: float = 0.0,
    **options: Any,
) -> RenderResult:
    """Render the stage's frames into ``out`` (default: a new temporary directory the
    result owns) and return the ``RenderResult``.

    ``stage_or_path``: a stage file or an open ``Usd.Stage`` (rendered as it is in memory,
    unsaved edits included). ``frames``: see ``FramesInput``. ``settings``: the
    RenderSettings prim to read. ``exposure``: EV, every image's radiance x 2**exposure
    before it is written (``--exposure``; |EV| > 40 clamped, with a warning).
    ``options``: see the module docstring.
    Raises ``BadOption`` for bad options, ``PhrtError`` (one line) for an unreadable
    stage, a busy or non-empty ``out`` (unless ``resume`` / ``overwrite``) or a failed
    frame, ``RenderInterrupted`` after SIGINT / SIGTERM."""
    temporary = None
    if out is None:  # unknown names fail before a directory is made, bad values remove it
        names = (
            *RENDER_OPTION_NAMES, *COMPOSITION_OPTION_NAMES, *READ_OPTION_NAMES,
            *job_option_names(),
        )  # fmt: skip
        _known(options, names, "option")
        temporary = tempfile.TemporaryDirectory(prefix="phrt-render-")
        out = temporary.name
    try:
        job, scene = render_job(
            stage_or_path, out, frames, settings=settings, exposure=exposure, **options
        )
        record = render_to_directory(job, on_frame, scene)
        summary = summary_of(record)
    except BaseException:
        if temporary is not None:
            temporary.cleanup()
        raise
    finish_summary(summary, scene)
    images = ()
    if record.images is not None:
        images = tuple(
            FrameImages(s.time, tuple(record.images.files(record.out, s.time)))
            for s in record.frames
        )
    return RenderResult(
        summary=summary,
        frames=tuple(record.frames),
        images=images,
        out=record.out,
        selection_layer=record.selection_layer,
        _temporary=temporary,
        _plan=record.images,
    )


# --------------------------------------------------------------------------------------
# open(): a renderer for frames in memory
# --------------------------------------------------------------------------------------


class Renderer:
    """Frames of one stage as arrays, with fixed options; nothing is written. Close it
    (``close()`` or a ``with`` block): it holds an OpenGL context and the Embree scene.

    ``options``: the ``RenderOptions``; ``stage_scene``: the stage read for rendering;
    ``frames``: the time codes planned (HEU1 forecasts along them; frames outside the plan
    render too, with the weaker forecast); ``policy``: the selection policy, which
    remembers earlier frames (render frames in time order)."""

    def __init__(self, stage_scene: StageScene, options: RenderOptions, frames: list[float]):
        self.stage_scene = stage_scene
        self.options = options
        self.frames = frames
        self._renderer: FrameRenderer | None = FrameRenderer(stage_scene, options)
        self._renderer.plan(frames)

    @property
    def closed(self) -> bool:
        return self._renderer is None

    @property
    def policy(self):
        return self._live().policy

    def _live(self) -> FrameRenderer:
        if self._renderer is None:
            raise PhrtError("this renderer is closed")
        return self._renderer

    def render(self, time: float) -> FrameOutput:
        """Render the frame at time code ``time``: ``FrameOutput`` with ``beauty`` (H, W, 3)
        float32 linear RGB, ``alpha``, the ``gbuffer``, ``traced_mask``, ``stats``,
        ``camera`` (``FrameCamera``: world-to-camera and projection), ``pixel_kind`` and
        ``motion`` (from the previous planned frame: render frames in plan order)."""
        renderer = self._live()
        time = check_finite(check_number(time, "time"), "time", "a finite time code")
        return renderer.render(time)

    def close(self) -> None:
        """Release the GL context and buffers (again: nothing)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open(  # noqa: A001 - phrt_usd.open, as the issue names it
    stage_or_path: StageInput,
    frames: FramesInput = None,
    *,
    settings: str | None = None,
    **options: Any,
) -> Renderer:
    """A ``Renderer`` of the stage (a context manager: ``with phrt_usd.open(path) as r:
    r.render(t)``). ``frames`` are planned for HEU1's forecast (default: the stage's whole
    range); ``options``: the render and composition options of the module docstring,
    ``camera`` and ``controls``.
    Raises ``BadOption`` for bad options, ``PhrtError`` for an unreadable stage."""
    spec, _job, render, scene, _named = _prepare(
        stage_or_path, frames, settings, options, _OPEN_OPTIONS
    )
    return Renderer(scene, render, parse_frames(spec, scene.frame_range))
