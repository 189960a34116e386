"""Rendering a frame range to an output directory: images, stats.json, selection layer.

``render_to_directory`` is the run; ``phrt_usd.api.run_render`` adds its summary.

The output directory ``OUT`` belongs to one run at a time (``RunDirectory``): a render
holds ``OUT/.phrt.lock`` for its whole run, refuses an ``OUT`` that holds files unless it
resumes the same run (``resume``) or replaces phrt's own files (``overwrite``), and never
writes outside ``OUT`` except the selection layer the job names (never a layer of the
stage). A run is identified by content (``run_identity``): a digest of the stage's layers,
the camera, the frames, the render settings prim and its products, and every option that
changes pixels or selections.

What a frame writes comes from the stage's render settings (``prepare_job``): the
settings prim (``settings``, else the stage's), its RenderProducts and their vars, or
``image`` / ``aovs`` (``phrt_usd.run.products``); the products' own camera and resolution
are the render's unless the job names a camera or ``resolution_given``.

A run is checkpointed every ``checkpoint_every`` frames (less often in long runs, see
``CHECKPOINT_MAX_SHARE``), when it stops early and when a frame fails: the checkpoint
(``OUT/checkpoint.json``: plain JSON with the finished frames' stats and the selection
policy's memory, never code) is written first, then ``stats.json`` and the selection
layer, each through the one atomic writer. SIGINT / SIGTERM finish the current frame,
write everything and raise ``RenderInterrupted``; ``resume=True`` continues after the last
checkpointed frame with the policy exactly as it was, so the result equals an
uninterrupted run.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import stat
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field, replace
from pathlib import Path

from phrt_usd import kernels
from phrt_usd.atomic import write_text_atomic
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import FrameStats
from phrt_usd.run.frames import parse_frames
from phrt_usd.run.images import DataWindow
from phrt_usd.run.products import (
    ImagePlan,
    default_plan,
    parse_aovs,
    plan_images,
    write_frame_images,
)
from phrt_usd.run.run_directory import RESERVE_FACTOR, RunDirectory
from phrt_usd.run.run_files import (
    CHECKPOINT_FILE,
    SELECTION_LAYER_FILE,
    STATS_FILE,
    frame_stats_from_row,
    frame_stats_row,
    make_run_info,
    to_json_value,
    write_stats,
)
from phrt_usd.run.selection_layer import write_selection_layer
from phrt_usd.threads import llvmpipe_threads
from phrt_usd.usd.render_settings import CameraSettings, read_render_settings
from phrt_usd.usd.stage import StageScene, choose_camera, open_stage, read_stage
from phrt_usd.usd.stage_controls import StageControls

#: Identifies checkpoint files; bump the version when their content changes meaning
#: (2: the cost model's safety factor is a window of rounds, not one tracked number; 3: the
#: policies remember the densities of the previous selection; 4: the safety factor's window
#: holds measured ms and planned rays, its ratios are taken against the current fit).
CHECKPOINT_FORMAT = "phrt-checkpoint"
CHECKPOINT_VERSION = 4
#: Largest checkpoint read back (bytes): a 100,000-frame run's is ~100 MB; anything
#: larger is not one of ours and is refused before it is parsed.
CHECKPOINT_MAX_BYTES = 1 << 30
DEFAULT_CHECKPOINT_EVERY = 10
#: A checkpoint rewrites every finished frame's stats and the selection layer, so its cost
#: grows with the run: after one that took d seconds the next waits at least
#: d * (1 / CHECKPOINT_MAX_SHARE - 1), keeping checkpoints to ~10 % of a long run's time
#: (a 10,000-frame path otherwise spent most of its time writing them).
CHECKPOINT_MAX_SHARE = 0.1


class RenderInterrupted(Exception):
    """Raised after a signal stopped the run and every finished frame was written."""


@dataclass
class RenderJob:
    stage_path: Path
    out_dir: Path
    options: RenderOptions
    frames: str | None = None  # --frames (run.frames): FrameSpec or A:B:STEP, time codes
    camera: str | None = None
    controls: StageControls = field(default_factory=StageControls)  # session layers etc.
    selection_layer: Path | None = None
    resume: bool = False
    overwrite: bool = False  # clear phrt's own files in out_dir first
    write_images: bool = True
    checkpoint_every: int = DEFAULT_CHECKPOINT_EVERY
    settings: str | None = None  # the RenderSettings prim (--settings; else the stage's)
    image: str | None = None  # --image TEMPLATE: one file per frame instead of the products
    aovs: tuple[str, ...] | str = ()  # --aovs: vars added to every EXR ("P,N" or names)
    timestamp: bool = False  # --timestamp: the wall-clock capDate in EXR headers
    resolution_given: bool = False  # options' width/height were asked for: products' yield


@dataclass(frozen=True)
class RunRecord:
    """Where a finished render put its results, and which passes its frames ran."""

    out: Path
    selection_layer: Path
    frames: list[FrameStats]  # every finished frame of the run, in time order
    passes: list[str]
    images: ImagePlan | None = None  # the files of each frame: images.files(out, time)
    runtime: dict = field(default_factory=dict)  # how it ran: see ``runtime_settings``


def render_to_directory(
    job: RenderJob,
    on_frame: Callable[[int, int, FrameStats], None] | None = None,
    stage_scene: StageScene | None = None,
) -> RunRecord:
    """Render ``job`` into its output directory (images, stats.json, selection layer).

    Raises PhrtError before anything is written if ``out_dir`` is not usable (see
    ``RunDirectory``); a frame that fails ends the run with its error after the finished
    frames' records are written."""
    out = job.out_dir
    scene = stage_scene or open_stage(
        job.stage_path, camera=job.camera, controls=job.controls, settings=job.settings
    )
    job, scene, plan = prepare_job(job, scene)
    times = parse_frames(job.frames, scene.frame_range)
    plan.check_files(times)
    layer_path = job.selection_layer or out / SELECTION_LAYER_FILE
    run_info = job_run_info(job, scene, times, plan)
    with RunDirectory(
        out,
        layer_path,
        scene,
        resume=job.resume,
        overwrite=job.overwrite,
        images=plan.templates(),
    ) as run_dir:
        return _Run(job, scene, run_info, layer_path, run_dir, plan).render(times, on_frame)


def prepare_job(job: RenderJob, scene: StageScene) -> tuple[RenderJob, StageScene, ImagePlan]:
    """The job as its render settings make it, the stage read with its camera, and the
    images each frame gets (see the module docstring). The camera: the job's, else the
    products', else the settings'; ``scene`` is read again if it has another. PhrtError
    (one line, naming the prim) for settings, products or vars phrt cannot use."""
    settings = read_render_settings(scene.stage, job.settings)
    plan = plan_images(
        settings,
        job.out_dir,
        image=job.image,
        aovs=parse_aovs(job.aovs) if isinstance(job.aovs, str) else tuple(job.aovs),
        stage=str(job.stage_path),
        timestamp=job.timestamp,
    )
    camera = job.camera or plan.camera or (settings.camera if settings else None)
    if camera and camera != scene.camera_path:
        # A name (``--camera Side``) is resolved to its path once; the stage is read
        # again only for another camera than the one it was read with.
        camera = str(choose_camera(scene.stage, camera).GetPath())
        if camera != scene.camera_path:
            scene = read_stage(scene.stage, camera=camera, settings=job.settings)
    if camera:
        job = replace(job, camera=camera)  # workers of a cluster read the same camera
    opts = job.options
    if plan.resolution and not job.resolution_given:
        if plan.resolution != (opts.width, opts.height):
            width, height = plan.resolution
            job = replace(job, options=replace(opts, width=width, height=height))
    _check_data_window(scene, plan, job.options.width, job.options.height)
    return job, scene, plan


def _check_data_window(scene: StageScene, plan: ImagePlan, width: int, height: int) -> None:
    """PhrtError naming the settings' ``dataWindowNDC`` when it holds no pixel of the
    ``width`` x ``height`` image (every file holds the data window's pixels), before
    any frame is rendered."""
    window = scene.camera_settings.data_window
    if window == CameraSettings.data_window:
        return
    try:
        DataWindow.of(width, height, scene.camera(scene.time).data_window_pixels(width, height))
    except PhrtError:
        raise PhrtError(
            f"{plan.settings}.dataWindowNDC: {window} holds no pixel of the {width}x{height} "
            "image (pixels whose centres lie inside it are written)"
        ) from None


class _Run:
    """One render's state between frames: finished frames, the renderer, and the policy
    memory as of the last finished frame (what a checkpoint must hold so that a resumed
    run continues exactly, even when the run ends inside a frame)."""

    def __init__(self, job, scene, run_info, layer_path, run_dir: RunDirectory, plan):
        self.job, self.scene, self.run_info = job, scene, run_info
        self.layer_path, self.run_dir, self.plan = layer_path, run_dir, plan
        self.done: list[FrameStats] = []
        self.renderer = FrameRenderer(scene, job.options)
        self.runtime = runtime_settings(self.renderer)
        self.run_info.update(self.runtime)  # stats.json and the layer record them
        self.memory = self.renderer.policy.memory()

    def render(self, times: list[float], on_frame) -> RunRecord:
        job, out, renderer = self.job, self.job.out_dir, self.renderer
        renderer.plan(times)
        stop = threading.Event()
        try:
            if job.resume and not self.run_dir.fresh:
                self.done = _load_checkpoint(out, self.run_info, renderer)
                self.memory = renderer.policy.memory()
            else:  # the run's identity goes on disk before its first frame does
                self.checkpoint(records=False)
            finished = {s.time for s in self.done}
            todo = [t for t in times if t not in finished]
            since_checkpoint = 0
            next_checkpoint = 0.0  # time.perf_counter() before which no periodic checkpoint
            with stop_on_signals(stop), self._records_kept():
                for t in todo:
                    written = out if job.write_images else None
                    self.done.append(render_frame(renderer, t, written, self.plan))
                    self.memory = renderer.policy.memory()
                    since_checkpoint += 1
                    if on_frame is not None:
                        on_frame(len(self.done), len(times), self.done[-1])
                    if stop.is_set():
                        break
                    start = time.perf_counter()
                    if since_checkpoint >= job.checkpoint_every and start >= next_checkpoint:
                        self.checkpoint()
                        end = time.perf_counter()
                        next_checkpoint = end + (end - start) * (1 / CHECKPOINT_MAX_SHARE - 1)
                        since_checkpoint = 0
        finally:
            renderer.close()
        if stop.is_set() and len(self.done) < len(times):
            raise RenderInterrupted(
                f"stopped after {len(self.done)} of {len(times)} frames; finished frames are "
                f"in {out} (continue with --resume)"
            )
        return RunRecord(
            out=out,
            selection_layer=self.layer_path,
            frames=sorted(self.done, key=lambda s: s.time),
            passes=sorted({p for s in self.done for p in s.passes}),
            images=self.plan if job.write_images else None,
            runtime=self.runtime,
        )

    @contextmanager
    def _records_kept(self) -> Iterator[None]:
        """Write the checkpoint and records of the finished frames when the block ends,
        however it ends. If the block failed, its error is the one raised; the disk
        reserve is given up first so that the records fit even on a full disk."""
        try:
            yield
        except BaseException:
            self.run_dir.release_reserve()
            with suppress(PhrtError, OSError):
                self.checkpoint()
            raise
        self.checkpoint()

    def checkpoint(self, records: bool = True) -> None:
        """Write the checkpoint, then (with ``records``) stats.json and the selection
        layer, each atomically, and grow the disk reserve to hold them all again."""
        frames = sorted(self.done, key=lambda s: s.time)
        document = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "identity": self.run_info["identity"],
            "frames": [frame_stats_row(f) for f in frames],
            "policy": self.memory,
        }
        out = self.job.out_dir
        text = json.dumps(document, allow_nan=False) + "\n"
        write_text_atomic(out / CHECKPOINT_FILE, text)
        if not records:
            return
        write_run_records(out, self.layer_path, self.job, self.scene, self.run_info, frames)
        written = len(text) + sum(
            p.stat().st_size for p in (out / STATS_FILE, self.layer_path) if p.exists()
        )
        self.run_dir.keep_reserve(RESERVE_FACTOR * written)


def runtime_settings(renderer: FrameRenderer) -> dict:
    """How ``renderer``'s frames run, beside the settings that identify the run (a resumed
    run may run otherwise and make the same pixels): ``threads`` (the setting), ``gl`` (the
    OpenGL platform of the raster phase, None without one), ``llvmpipe_threads``
    (llvmpipe's render threads in this process, None without llvmpipe), ``kernels``
    ("cached": every compiled kernel came from the cache; "compiled": this process
    compiled some, ``phrt_usd.kernels.form``) and ``primary`` (the G-buffer source,
    "raster" or "rays", ``render.primary_source``)."""
    gl = renderer.gl
    return {
        "threads": renderer.options.threads,
        "gl": gl,
        "llvmpipe_threads": llvmpipe_threads() if gl is not None else None,
        "kernels": kernels.form(),
        "primary": renderer.primary,
    }


def render_frame(
    renderer: FrameRenderer, t: float, out: Path | None, images: ImagePlan | None = None
) -> FrameStats:
    """Render frame ``t`` with ``renderer`` (its policy remembers the frame); with an
    output directory ``out``, write the frame's files of ``images`` there, each atomically
    (the default layout, ``frames/NNNN.exr`` and ``.png``, without a plan)."""
    output = renderer.render(t)
    if out is not None:
        stage_scene = renderer.stage_scene
        root = stage_scene.stage.GetRootLayer()
        write_frame_images(
            images or default_plan(),
            out,
            t,
            output,
            stage_scene.camera(t),
            stage_scene.scene,
            frames_per_second=stage_scene.time_codes_per_second,
            camera_path=stage_scene.camera_path,
            stage=root.realPath or root.identifier,
        )
    return output.stats


def job_run_info(
    job: RenderJob, scene: StageScene, times: list[float], images: ImagePlan | None = None
) -> dict:
    """The run object of stats.json, the selection layer and the checkpoint, with the
    run's ``identity`` (see ``run_identity``); ``images``: the run's files (``prepare_job``,
    which this calls when not given)."""
    if images is None:
        job, scene, images = prepare_job(job, scene)
    opts = job.options
    info = make_run_info(
        stage=str(job.stage_path),
        mode=opts.mode,
        heuristic="all" if opts.mode == "rt" else opts.heuristic,
        budget_ms=opts.budget_ms,
        budget_rays=opts.budget_rays,
        resolution=(opts.width, opts.height),
        bounce_limit=opts.bounce_limit,
        selection_weight=opts.selection_weight,
        frame_range=(times[0], times[-1]),
        reflectors=[scene.scene.elements[i].path for i in scene.scene.reflector_ids],
        time_codes_per_second=scene.time_codes_per_second,
    )
    info["target_fps"] = opts.target_fps  # None: a fixed (or no) time budget
    info["threads"] = opts.threads  # --threads (phrt_usd.threads); not in the identity
    info["exposure"] = opts.exposure_ev  # EV applied to every image (--exposure, clamped)
    info["trace_density"] = opts.trace_density  # full | half | quarter | sixteenth
    info["screen_space"] = opts.screen_space  # off | on
    info["camera"] = scene.camera_path
    info["settings"] = images.settings
    info["products"] = images.describe()
    info["composition"] = job.controls.as_dict()
    info["identity"] = run_identity(info, scene, times)
    return info


#: Run settings that change pixels or selections: with the stage's layers, the camera
#: and the frame list they identify a run (``run_identity``).
IDENTITY_KEYS = (
    "mode",
    "heuristic",
    "budget_ms",
    "budget_rays",
    "target_fps",
    "exposure",
    "trace_density",
    "screen_space",
    "bounce_limit",
    "selection_weight",
    "resolution",
    "camera",
    "settings",  # the RenderSettings prim
    "products",  # every file name template of a frame and its channels
    "composition",  # session layers, variants, mask (the mask is in no layer's content)
)


def run_identity(run_info: dict, scene: StageScene, times: list[float]) -> dict:
    """``{"digest", "layers", "options"}``: ``layers`` is a SHA-256 over the content of
    every layer the stage uses (root, sublayers, references, payloads, session; by content,
    so the same file under another name is the same run and an edited one is not),
    ``options`` the ``IDENTITY_KEYS`` settings and the frame list, ``digest`` both."""
    layers = sorted(_layer_digest(layer) for layer in scene.stage.GetUsedLayers())
    layer_digest = hashlib.sha256("\n".join(layers).encode()).hexdigest()
    options = {key: to_json_value(run_info.get(key)) for key in IDENTITY_KEYS}
    options["frames"] = [float(t) for t in times]
    text = json.dumps({"layers": layer_digest, "options": options}, sort_keys=True)
    return {
        "digest": hashlib.sha256(text.encode()).hexdigest(),
        "layers": layer_digest,
        "options": options,
    }


def _layer_digest(layer) -> str:
    """SHA-256 of a layer's file bytes, or of its text when it has no file or unsaved
    edits (anonymous and session layers)."""
    path = layer.realPath
    if path and not layer.dirty and os.path.isfile(path):
        digest = hashlib.sha256()
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        return digest.hexdigest()
    return hashlib.sha256(layer.ExportToString().encode()).hexdigest()


def _load_checkpoint(out: Path, run_info: dict, renderer: FrameRenderer) -> list[FrameStats]:
    """Finished frames of the interrupted run in ``out``, and its policy's memory restored
    into ``renderer.policy``. PhrtError (one line) unless the checkpoint is a phrt
    checkpoint of this very run."""
    path = out / CHECKPOINT_FILE
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        raise PhrtError(f"--resume: {out} holds no checkpoint ({CHECKPOINT_FILE})") from None
    except OSError as error:
        raise PhrtError(f"{path}: cannot read checkpoint ({error.strerror})") from None
    with os.fdopen(fd, "rb") as handle:
        if not stat.S_ISREG(os.fstat(handle.fileno()).st_mode):
            raise PhrtError(f"{path}: not a regular file")
        data = handle.read(CHECKPOINT_MAX_BYTES + 1)
    if len(data) > CHECKPOINT_MAX_BYTES:
        raise PhrtError(f"{path}: larger than any checkpoint phrt writes")
    try:
        state = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise PhrtError(f"{path}: not a readable checkpoint ({error})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise PhrtError(f'{path}: not a phrt checkpoint (no "format": "{CHECKPOINT_FORMAT}")')
    if state.get("version") != CHECKPOINT_VERSION:
        raise PhrtError(
            f"{path}: checkpoint version {state.get('version')!r}, expected {CHECKPOINT_VERSION}"
        )
    _check_same_run(out, state.get("identity"), run_info["identity"])
    frames = state.get("frames")
    if not isinstance(frames, list):
        raise PhrtError(f"{path}: checkpoint has no frame list")
    try:
        done = [frame_stats_from_row(row) for row in frames]
        renderer.policy.restore_memory(state.get("policy"))
    except PhrtError as error:
        raise PhrtError(f"{path}: {error}") from None
    wanted = set(run_info["identity"]["options"]["frames"])
    if any(s.time not in wanted for s in done) or len({s.time for s in done}) != len(done):
        raise PhrtError(f"{path}: checkpoint frames are not frames of this run")
    return done


def _check_same_run(out: Path, saved, current: dict) -> None:
    """PhrtError naming what differs unless ``saved`` is ``current``'s identity."""
    if not isinstance(saved, dict) or saved.get("digest") == current["digest"]:
        if isinstance(saved, dict):
            return
        raise PhrtError(f"--resume: the checkpoint in {out} has no run identity")
    if saved.get("layers") != current["layers"]:
        raise PhrtError(f"--resume: the stage's layers changed since the interrupted run in {out}")
    old = saved.get("options") if isinstance(saved.get("options"), dict) else {}
    for key, value in current["options"].items():
        if old.get(key) != value:
            shown = f"{key} ({old.get(key)!r} vs {value!r})"
            if key == "frames":
                shown = "the frame list"
            raise PhrtError(f"--resume: {shown} differs from the interrupted run in {out}")
    raise PhrtError(f"--resume: the checkpoint in {out} is of another run")


def write_run_records(
    out: Path,
    layer_path: Path,
    job: RenderJob,
    scene: StageScene,
    run_info: dict,
    frames: list[FrameStats],
) -> None:
    """stats.json and the selection layer of ``frames`` (every finished frame), atomically."""
    write_stats(out, run_info, frames)
    write_selection_layer(
        layer_path,
        str(job.stage_path),
        run_info["reflectors"],
        frames,
        run_info,
        scene.time_codes_per_second,
        merge=False,
    )


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """While active, SIGINT/SIGTERM set ``stop`` instead of killing the process."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001 - signal handler signature
        stop.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
