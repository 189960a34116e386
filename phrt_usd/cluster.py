"""Scale-out: a long render or a sweep, cut into chunks of frames, on a Dask cluster.

The engine is Dask's distributed scheduler (``distributed.Client``); this module only
decides what one task does and puts the results back together. See ``docs/cluster.md``.

* **Chunk** (``Chunk``): consecutive frames of one stage's frame list. A render chunk runs
  the job's one configuration; a sweep chunk runs *every* configuration of the sweep and
  both references on those frames, because they all share the frame's G-buffer and
  shading (a chunk per configuration would rasterize every frame once per
  configuration).
* **Warm-up**: a chunk starting at frame index ``start`` first renders the
  ``warmup`` frames before it without recording them, so the selection policies'
  memory (S, Q, rays per pixel, discovered reflectors), the previous selection
  (transitions) and the previous image (temporal FLIP) are in place when recording
  starts. The first chunk of a path has no warm-up (nothing precedes it).
* **Workers** open the stage themselves from its path (absolute; it must be readable on
  every worker: same machine or a shared file system) and write frame images straight
  into the output directory (same assumption), each file atomically. The schema plugin
  is registered on every worker by the worker plugin of ``cluster_client``.
* **Client** gathers each chunk's rows / frame stats in memory as chunks finish, keeps
  one result per chunk (a retried chunk cannot be counted twice), and rewrites the CSV /
  stats.json / selection layer atomically after every finished chunk, so a reader never
  sees a partial file.
* **Faults**: a worker that dies mid-chunk loses that chunk's task; the scheduler runs it
  again on another worker (Dask's ``allowed-failures``); an exception inside a chunk is
  retried ``TASK_RETRIES`` times. Either way the chunk's frames come back exactly once.
* **Interrupts** (SIGINT / SIGTERM, Ctrl-C; or a caller's ``stop`` event): the client
  cancels the chunks not finished, each running one stops before its next frame
  (``_chunk_cancelled``), and once none runs (``STOP_WAIT_SECONDS`` at most) the files
  hold exactly the finished chunks' frames: stats.json, the selection layer and the
  images of the same frames (a render), the CSV and timeline (a sweep).
* **Connecting** (``cluster_client``): Dask is imported only when a cluster is used
  (the ``phrt-usd[cluster]`` extra); the local cluster authenticates its workers with
  TLS, ``--scheduler`` is probed before distributed reads from it.
"""

from __future__ import annotations

import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from phrt_usd.cluster_client import (  # dask_client: the commands' way in
    check_workers,
    dask_client,  # noqa: F401
    parse_scheduler_address,
    require_distributed,
)
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.model.frame import FrameStats

if TYPE_CHECKING:
    from distributed import Client

    from phrt_usd.evaluate.sweep import SweepSpec
    from phrt_usd.run.render_job import RenderJob

#: Frames recorded per chunk by default. A chunk pays a fixed start-up (opening the stage,
#: building the rasterizer and the Embree scene: ~0.2-2 s) plus ``warmup`` extra frames;
#: at ~0.2 s per sweep frame (160x120) 96 frames keep both under ~15 % of the chunk.
DEFAULT_CHUNK_FRAMES = 96

#: Warm-up frames rendered, not recorded, before a chunk's first frame. With a rays budget
#: (``--budget-rays``) the selections of a chunk equal the unchunked run's after the
#: warm-up on the stages measured in docs/cluster.md; it is a measured figure, not a
#: guarantee (HEU1's hysteresis S can carry a different choice further; see the doc).
DEFAULT_WARMUP_FRAMES = 8

#: Times a chunk whose code raised is run again (worker deaths are handled by the
#: scheduler's own ``distributed.scheduler.allowed-failures``, default 3).
TASK_RETRIES = 2

#: How often the client looks for a stop request while it waits for chunks (seconds).
POLL_SECONDS = 0.1
#: How long an interrupted run waits for its running chunks to stop (each stops before
#: its next frame, so a frame's time) before it gives up waiting (seconds).
STOP_WAIT_SECONDS = 60.0


@dataclass(frozen=True)
class Chunk:
    """Frames ``[start, stop)`` of ``stage``'s frame list, recorded after ``warmup``
    unrecorded frames (fewer at the start of the path). ``index``: position in the run."""

    stage: str
    index: int
    start: int
    stop: int
    warmup: int

    @property
    def first_rendered(self) -> int:
        """Index of the first frame the chunk renders (warm-up included)."""
        return max(0, self.start - self.warmup)


def check_chunking(chunk_frames: int, warmup: int) -> None:
    """BadOption unless ``chunk_frames >= 1`` and ``warmup >= 0``."""
    if chunk_frames < 1:
        raise BadOption(f"--chunk-frames must be >= 1, got {chunk_frames}")
    if warmup < 0:
        raise BadOption(f"--warmup must be >= 0, got {warmup}")


def check_cluster_options(
    workers: int | None,
    scheduler: str | None,
    chunk_frames: int | None = None,
    warmup: int | None = None,
    resume: bool = False,
) -> None:
    """The cluster options of a command, checked before anything is rendered or
    started: BadOption (exit 2) for ``--workers`` with ``--scheduler``, either with
    ``--resume``, ``--chunk-frames`` / ``--warmup`` without either or out of range, a
    ``--workers`` count out of ``max_local_workers``, and Dask not installed."""
    option = "--workers" if workers is not None else "--scheduler"
    if workers is None and scheduler is None:
        if chunk_frames is not None or warmup is not None:
            raise BadOption("--chunk-frames and --warmup apply to --workers / --scheduler only")
        return
    if workers is not None and scheduler is not None:
        raise BadOption("give exactly one of --workers N or --scheduler ADDRESS")
    if resume:
        raise BadOption(f"--resume is not available with {option}: a cluster render is not "
                        "checkpointed (run it again, or render without the cluster)")  # fmt: skip
    check_chunking(
        DEFAULT_CHUNK_FRAMES if chunk_frames is None else chunk_frames,
        DEFAULT_WARMUP_FRAMES if warmup is None else warmup,
    )
    if workers is not None:
        check_workers(workers)
    else:
        parse_scheduler_address(scheduler)
    require_distributed(option)


def plan_chunks(
    stage: str, n_frames: int, chunk_frames: int, warmup: int, first_index: int = 0
) -> list[Chunk]:
    """Cut ``n_frames`` frames into chunks of ``chunk_frames`` recorded frames."""
    check_chunking(chunk_frames, warmup)
    return [
        Chunk(stage, first_index + k, a, min(a + chunk_frames, n_frames), warmup)
        for k, a in enumerate(range(0, n_frames, chunk_frames))
    ]


# --------------------------------------------------------------------------- workers


@dataclass
class SweepChunkResult:
    """What a sweep chunk sends back: its CSV rows (frame order, configurations in the
    sweep's order), its part of timeline.json, and who rendered it."""

    chunk: Chunk
    rows: list[dict]
    timeline: dict
    times: list[float]
    worker_pid: int


@dataclass
class RenderChunkResult:
    """What a render chunk sends back: the recorded frames' stats, in frame order, and
    the warnings the render found while rendering (e.g. the clipping warning), which the
    client's stage never sees otherwise."""

    chunk: Chunk
    frames: list[FrameStats]
    worker_pid: int
    warnings: list[str] = field(default_factory=list)
    #: How the worker's frames ran (``render_job.runtime_settings``: threads, gl,
    #: llvmpipe_threads, kernels).
    runtime: dict = field(default_factory=dict)


def sweep_chunk(chunk: Chunk, spec: SweepSpec) -> SweepChunkResult:
    """On a worker: sweep the chunk's frames (warm-up first), rows kept in memory."""
    from phrt_usd.evaluate.sweep import StageSweep

    sweep = StageSweep(chunk.stage, spec)
    rows: list[dict] = []
    try:
        for i in range(chunk.first_rendered, chunk.stop):
            if _chunk_cancelled():
                break  # the run was interrupted: nothing of this chunk is kept
            rows.extend(sweep.frame(sweep.times[i], record=i >= chunk.start))
    finally:
        sweep.close()
    return SweepChunkResult(chunk, rows, sweep.timeline(), list(sweep.recorded), os.getpid())


def render_chunk(chunk: Chunk, job: RenderJob) -> RenderChunkResult:
    """On a worker: render the chunk's frames (warm-up first); recorded frames' images go
    to ``job.out_dir`` when ``job.write_images``."""
    from phrt_usd.engine.renderer import FrameRenderer
    from phrt_usd.run.frames import parse_frames
    from phrt_usd.run.render_job import prepare_job, render_frame, runtime_settings
    from phrt_usd.usd.stage import open_stage

    scene = open_stage(chunk.stage, camera=job.camera, controls=job.controls, settings=job.settings)
    _, _, images = prepare_job(job, scene)  # the job came prepared: the files of a frame
    times = parse_frames(job.frames, scene.frame_range)
    renderer = FrameRenderer(scene, job.options)
    renderer.plan(times[chunk.first_rendered : chunk.stop])
    known = len(scene.warnings)  # those of reading the stage: the client has them too
    frames = []
    out = Path(job.out_dir) if job.write_images else None
    try:
        for i in range(chunk.first_rendered, chunk.stop):
            if _chunk_cancelled():
                break  # the run was interrupted: no more images of this chunk
            if i < chunk.start:
                renderer.render(times[i])  # warm-up: the policy learns, nothing is kept
            else:
                frames.append(render_frame(renderer, times[i], out, images))
        runtime = runtime_settings(renderer)
    finally:
        renderer.close()
    return RenderChunkResult(chunk, frames, os.getpid(), scene.warnings[known:], runtime)


def _chunk_cancelled() -> bool:
    """On a worker: whether the client gave up the task running this chunk (a stopped
    run; Dask cannot stop a running task, so the chunk checks before each frame). False
    outside a Dask task (a chunk called directly)."""
    try:
        from distributed import get_worker
        from distributed.worker import thread_state

        task = get_worker().state.tasks.get(thread_state.key)
    except (ImportError, ValueError, AttributeError):
        return False
    return task is None or task.state == "cancelled"


# --------------------------------------------------------------------------- client


def stage_address(stage: Path | str) -> str:
    """How workers are told where the stage is: an absolute path if it exists here (they
    share the file system), else the string as given (a path valid on the workers)."""
    path = Path(stage)
    return str(path.resolve()) if path.exists() else str(stage)


def _gather(
    client: Client,
    function: Callable,
    chunks: list[Chunk],
    argument: object,
    on_result: Callable[[dict[int, object]], None],
    stop: threading.Event,
) -> tuple[dict[int, object], bool | None]:
    """Submit one task per chunk, call ``on_result(results so far)`` as each finishes;
    returns the results by chunk index and None, or, when ``stop`` was set, the finished
    chunks' results and whether every other chunk stopped in time: they are cancelled
    and waited for until none runs (``_wait_until_stopped``)."""
    from distributed import as_completed

    token = secrets.token_hex(4)
    futures = [
        client.submit(
            function,
            chunk,
            argument,
            key=f"phrt-{function.__name__}-{token}-{chunk.index}",
            pure=False,
            retries=TASK_RETRIES,
        )
        for chunk in chunks
    ]
    results: dict[int, object] = {}  # by chunk index: one per chunk, whatever was retried
    finishing = as_completed(futures)
    try:
        while not finishing.is_empty() and not stop.is_set():
            if not finishing.has_ready():
                stop.wait(POLL_SECONDS)
                continue
            for future in finishing.next_batch(block=False):
                result = future.result()
                if result.chunk.index in results:
                    continue  # a chunk comes back once; a duplicate would count frames twice
                results[result.chunk.index] = result
                future.release()
                on_result(results)
    finally:
        client.cancel(futures)
    if not stop.is_set():
        return results, None
    keys = {future.key for future in futures}
    return results, _wait_until_stopped(client, keys, STOP_WAIT_SECONDS)


def _wait_until_stopped(client: Client, keys: set, timeout: float) -> bool:
    """Wait until no worker runs any task of ``keys`` (cancelled, each stops before its
    next frame), at most ``timeout`` seconds; whether they all stopped. The keys are
    looked for in every worker's running tasks (the scheduler forgets cancelled ones)."""
    deadline = time.monotonic() + timeout
    idle_polls = 0
    while True:
        try:
            stacks = client.call_stack()
        except OSError:
            return False  # the scheduler is gone: nothing more can be known
        running = {key for per_worker in stacks.values() for key in per_worker} & keys
        idle_polls = 0 if running else idle_polls + 1
        # Twice idle: a task a worker was about to start when the cancel arrived has
        # started and checked by then.
        if idle_polls >= 2:
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(POLL_SECONDS)


def run_sweep_on_cluster(
    spec: SweepSpec,
    client: Client,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    warmup: int = DEFAULT_WARMUP_FRAMES,
    on_chunk: Callable[[int, int], None] | None = None,
    stop: threading.Event | None = None,
) -> dict:
    """``run_sweep`` on a Dask cluster: same files, same rows (timings aside), same
    timeline as one process with a rays budget (docs/cluster.md). ``on_chunk(done,
    total)`` after every finished chunk. SIGINT / SIGTERM (or setting ``stop``) stops
    it: the files then hold the finished chunks' rows, ``interrupted`` is True. Returns
    ``run_sweep``'s summary dict plus ``chunk_pids``: the process id of the worker whose
    result was kept, per chunk (None for a chunk not finished)."""
    from phrt_usd.evaluate.sweep import check_spec, finish_sweep, write_sweep_csv
    from phrt_usd.evaluate.sweep_files import SWEEP_CSV
    from phrt_usd.run.frames import parse_frames
    from phrt_usd.run.render_job import stop_on_signals
    from phrt_usd.run.run_directory import DirectoryLock
    from phrt_usd.usd.stage import open_stage

    check_spec(spec)
    check_chunking(chunk_frames, warmup)
    spec.out.mkdir(parents=True, exist_ok=True)
    chunks: list[Chunk] = []
    for stage in spec.stages:
        n_frames = len(parse_frames(spec.frames, open_stage(stage).frame_range))
        chunks += plan_chunks(stage_address(stage), n_frames, chunk_frames, warmup, len(chunks))

    def progress(results: dict) -> None:
        write_sweep_csv(spec.out / SWEEP_CSV, _sweep_rows(chunks, results))
        if on_chunk is not None:
            on_chunk(len(results), len(chunks))

    # Workers write report images into the output directory: give them an absolute path.
    worker_spec = replace(spec, out=spec.out.resolve())
    stop = stop or threading.Event()
    with DirectoryLock(spec.out), stop_on_signals(stop):  # one sweep writes OUT at a time
        results, stopped = _gather(client, sweep_chunk, chunks, worker_spec, progress, stop)
        interrupted = stopped is not None
        if not interrupted:
            _check_complete(chunks, results)
        timeline: dict = {}
        for chunk in chunks:
            if chunk.index in results:
                _merge_timeline(timeline, results[chunk.index])
        _remove_stale_temporaries(spec.out)
        rows = _sweep_rows(chunks, results)
        summary = finish_sweep(spec, rows, timeline, interrupted=interrupted)
    summary["chunk_pids"] = [getattr(results.get(c.index), "worker_pid", None) for c in chunks]
    return summary


def run_render_on_cluster(
    job: RenderJob,
    client: Client,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    warmup: int = DEFAULT_WARMUP_FRAMES,
    on_frame: Callable[[int, int], None] | None = None,
    stop: threading.Event | None = None,
) -> dict:
    """``run_render`` on a Dask cluster (no checkpoint / ``--resume``: a lost chunk is
    re-run by the scheduler instead). ``on_frame(done, total)`` after every chunk.
    SIGINT / SIGTERM (or setting ``stop``) stops it: RenderInterrupted, after which
    stats.json, the selection layer and the images hold the same frames, those of the
    finished chunks (``_keep_finished``). Returns ``run_render``'s summary dict plus
    ``chunk_pids`` (see the sweep's)."""
    from phrt_usd.evaluate.run_summary import summary_of
    from phrt_usd.run.frames import parse_frames
    from phrt_usd.run.render_job import (
        RunRecord,
        job_run_info,
        prepare_job,
        stop_on_signals,
        write_run_records,
    )
    from phrt_usd.run.run_directory import RunDirectory
    from phrt_usd.usd.stage import open_stage

    if job.resume:
        raise BadOption("--resume is not available with --workers / --scheduler: a cluster "
                        "render is not checkpointed")  # fmt: skip
    check_chunking(chunk_frames, warmup)
    out = Path(job.out_dir)
    scene = open_stage(
        job.stage_path, camera=job.camera, controls=job.controls, settings=job.settings
    )
    job, scene, images = prepare_job(job, scene)  # the products' camera and resolution
    times = parse_frames(job.frames, scene.frame_range)
    images.check_files(times)
    layer_path = job.selection_layer or out / "selection.usda"
    run_info = job_run_info(job, scene, times, images)
    chunks = plan_chunks(stage_address(job.stage_path), len(times), chunk_frames, warmup)

    def write(results: dict) -> list[FrameStats]:
        frames = [f for c in chunks if c.index in results for f in results[c.index].frames]
        write_run_records(out, layer_path, job, scene, run_info, frames)
        return frames

    def progress(results: dict) -> None:
        frames = write(results)
        if on_frame is not None:
            on_frame(len(frames), len(times))

    stop = stop or threading.Event()
    with (
        RunDirectory(out, layer_path, scene, overwrite=job.overwrite, images=images.templates()),
        stop_on_signals(stop),
    ):
        worker_job = replace(job, out_dir=out.resolve())  # workers write images there
        results, stopped = _gather(client, render_chunk, chunks, worker_job, progress, stop)
        if stopped is not None:
            kept = write(results)
            _keep_finished(out, images if job.write_images else None, times, kept)
            raise _interrupted(out, kept, times, len(results), len(chunks), stopped)
        _check_complete(chunks, results)
        frames = write(results)
        if sorted(f.time for f in frames) != sorted(times):
            raise PhrtError(f"cluster render of {job.stage_path}: frames missing or repeated")
        _remove_stale_temporaries(out)
    passes = sorted({p for s in frames for p in s.passes})
    ordered = sorted(frames, key=lambda s: s.time)
    # How the frames ran, as a one-process render reports it: the first chunk's worker
    # (every worker runs the same options).
    runtime = results[chunks[0].index].runtime if chunks else {}
    summary = summary_of(
        RunRecord(out, layer_path, ordered, passes, images if job.write_images else None,
                  runtime=runtime)  # fmt: skip
    )
    summary["chunk_pids"] = [results[c.index].worker_pid for c in chunks]
    # Warnings found while rendering, once each, in chunk order (``render_warnings``).
    found = [w for c in chunks for w in results[c.index].warnings]
    summary["render_warnings"] = list(dict.fromkeys(found))
    return summary


def _keep_finished(out: Path, images, times: list[float], kept: list[FrameStats]) -> None:
    """After a stopped render whose records hold ``kept``: delete the image files
    (``images``, an ``ImagePlan``; None without images) that stopped chunks wrote of
    frames not kept, and temp files a stopped write left. Only this run's files are
    named: the plan's file names of this run's frames inside ``out``, which was empty of
    them when the run started (``RunDirectory``)."""
    if images is not None:
        finished = {f.time for f in kept}
        for t in times:
            if t not in finished:
                for path in images.files(out, t):
                    path.unlink(missing_ok=True)
    _remove_stale_temporaries(out)


def _interrupted(out: Path, kept: list, times: list, done: int, total: int, stopped: bool):
    """The RenderInterrupted of a stopped cluster render: how many frames were kept."""
    from phrt_usd.run.render_job import RenderInterrupted

    message = (
        f"stopped after {len(kept)} of {len(times)} frames ({done} of {total} chunks "
        f"finished); stats.json, the selection layer and the images in {out} hold exactly "
        "those frames"
    )
    if not stopped:
        message += (
            f"; chunks still running on the cluster after {STOP_WAIT_SECONDS:g} s may "
            "still write images of other frames"
        )
    return RenderInterrupted(message)


def _sweep_rows(chunks: list[Chunk], results: dict) -> list[dict]:
    """Rows of the finished chunks in the single-process order (stage, frame, config)."""
    return [row for c in chunks if c.index in results for row in results[c.index].rows]


def _merge_timeline(timeline: dict, result: SweepChunkResult) -> None:
    """Append a chunk's timeline (chunks in frame order) to the stage's entry."""
    name = Path(result.chunk.stage).stem
    stage = timeline.setdefault(name, {})
    for label, part in result.timeline.items():
        entry = stage.setdefault(
            label, {"reflectors": part["reflectors"], "frames": [], "selected": [], "visible": []}
        )
        entry["frames"] += part["frames"]
        entry["selected"] += part["selected"]
        entry["visible"] += part["visible"]


def _check_complete(chunks: list[Chunk], results: dict) -> None:
    """Every chunk came back once with exactly its frames (never silently short)."""
    for chunk in chunks:
        result = results.get(chunk.index)
        if result is None:
            raise PhrtError(f"{chunk.stage}: chunk {chunk.index} never finished")
        n = len(result.times) if isinstance(result, SweepChunkResult) else len(result.frames)
        if n != chunk.stop - chunk.start:
            raise PhrtError(
                f"{chunk.stage}: chunk {chunk.index} returned {n} frames, "
                f"expected {chunk.stop - chunk.start}"
            )


def _remove_stale_temporaries(out: Path) -> None:
    """Delete temp files (``.name.…tmp…``) a killed worker left mid-write. Only called
    once every chunk has finished, when no writer is left."""
    for path in Path(out).rglob(".*.tmp*"):
        if path.is_file():
            path.unlink(missing_ok=True)
