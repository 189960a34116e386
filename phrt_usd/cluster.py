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
  is registered on every worker by ``PhrtWorkerSetup``.
* **Client** gathers each chunk's rows / frame stats in memory as chunks finish, keeps
  one result per chunk (a retried chunk cannot be counted twice), and rewrites the CSV /
  stats.json / selection layer atomically after every finished chunk, so a reader never
  sees a partial file.
* **Faults**: a worker that dies mid-chunk loses that chunk's task; the scheduler runs it
  again on another worker (Dask's ``allowed-failures``); an exception inside a chunk is
  retried ``TASK_RETRIES`` times. Either way the chunk's frames come back exactly once.
* **Security**: a scheduler runs the code sent to it. The local cluster listens on
  loopback only; ``--scheduler`` values are checked (``parse_scheduler_address``) and a
  plain-tcp scheduler on another machine is warned about (``scheduler_warning``).
"""

from __future__ import annotations

import ipaddress
import os
import re
import secrets
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from distributed.diagnostics.plugin import WorkerPlugin

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


def plan_chunks(
    stage: str, n_frames: int, chunk_frames: int, warmup: int, first_index: int = 0
) -> list[Chunk]:
    """Cut ``n_frames`` frames into chunks of ``chunk_frames`` recorded frames."""
    if chunk_frames < 1:
        raise PhrtError(f"--chunk-frames must be >= 1, got {chunk_frames}")
    if warmup < 0:
        raise PhrtError(f"--warmup must be >= 0, got {warmup}")
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
            rows.extend(sweep.frame(sweep.times[i], record=i >= chunk.start))
    finally:
        sweep.close()
    return SweepChunkResult(chunk, rows, sweep.timeline(), list(sweep.recorded), os.getpid())


def render_chunk(chunk: Chunk, job: RenderJob) -> RenderChunkResult:
    """On a worker: render the chunk's frames (warm-up first); recorded frames' images go
    to ``job.out_dir`` when ``job.write_images``."""
    from phrt_usd.render.renderer import FrameRenderer
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
            if i < chunk.start:
                renderer.render(times[i])  # warm-up: the policy learns, nothing is kept
            else:
                frames.append(render_frame(renderer, times[i], out, images))
        runtime = runtime_settings(renderer)
    finally:
        renderer.close()
    return RenderChunkResult(chunk, frames, os.getpid(), scene.warnings[known:], runtime)


class PhrtWorkerSetup(WorkerPlugin):
    """Dask worker plugin: imports phrt_usd on every worker (present and future), which
    selects the OSMesa platform and registers the Phrt schema plugin before any stage
    is opened there."""

    name = "phrt-usd-setup"
    idempotent = True

    def setup(self, worker) -> None:
        import phrt_usd  # noqa: F401


# --------------------------------------------------------------------------- client


#: Where the local cluster listens: scheduler, nannies, workers and the scheduler's HTTP
#: endpoint bind this loopback address only (port 0: any free port), so no other machine
#: can reach them. Processes on this machine still can: see docs/cluster.md, "Security".
LOOPBACK_HOST = "127.0.0.1"

#: Schemes ``--scheduler`` accepts (a bare ``host:port`` is ``tcp://``, Dask's default).
#: ``inproc://`` is left out: it names a scheduler inside the same process, which a new
#: ``phrt`` process never has.
SCHEDULER_SCHEMES = ("tcp", "tls")

_HOSTNAME_LABEL = re.compile(r"(?!-)[A-Za-z0-9_-]{1,63}(?<!-)", re.ASCII)


@dataclass(frozen=True)
class SchedulerAddress:
    """A parsed ``--scheduler`` value: ``scheme://host:port`` (IPv6 hosts without the
    brackets)."""

    scheme: str
    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """True for ``localhost`` and literals in 127.0.0.0/8 or ::1; any other name is
        taken as another machine (no name is looked up)."""
        if self.host.lower().rstrip(".") == "localhost":
            return True
        try:
            ip = ipaddress.ip_address(self.host)
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return ip.is_loopback


def _is_host_name_or_ipv4(host: str) -> bool:
    """An IPv4 literal, or a name of dot-separated labels whose last is not all digits
    (``10.0.0.300`` is a mistyped address, not a name)."""
    try:
        ipaddress.IPv4Address(host)
        return True
    except ValueError:
        labels = host.removesuffix(".").split(".")
        return all(_HOSTNAME_LABEL.fullmatch(label) for label in labels) and not (
            labels[-1].isdigit()
        )


def parse_scheduler_address(address: str) -> SchedulerAddress:
    """Check the form of a ``--scheduler`` value: ``tcp://host:port``, ``tls://host:port``
    or ``host:port`` (tcp); host a name, an IPv4 literal or a bracketed IPv6 literal.
    Anything else is a ``BadOption`` naming the option and the value. No name is
    resolved here."""

    def bad(why: str) -> BadOption:
        return BadOption(
            f"--scheduler {address!r}: {why}; expected tcp://HOST:PORT or tls://HOST:PORT"
        )

    scheme, sep, rest = address.strip().partition("://")
    if not sep:
        scheme, rest = "tcp", address.strip()
    scheme = scheme.lower()
    if scheme not in SCHEDULER_SCHEMES:
        raise bad(f"scheme {scheme!r} not supported")
    if rest.startswith("["):
        host, bracket, tail = rest[1:].partition("]")
        if not bracket or not tail.startswith(":"):
            raise bad("an IPv6 host needs brackets and a port, like [::1]:8786")
        port_text = tail[1:]
        try:
            if not isinstance(ipaddress.ip_address(host), ipaddress.IPv6Address):
                raise ValueError(host)
        except ValueError:
            raise bad(f"{host!r} is not an IPv6 address") from None
    else:
        host, colon, port_text = rest.rpartition(":")
        if not colon:
            raise bad("missing :PORT")
        if not host:
            raise bad("missing host")
        if ":" in host:
            raise bad("an IPv6 host needs brackets, like [::1]:8786")
        if not _is_host_name_or_ipv4(host):
            raise bad(f"{host!r} is not a host name or IP address")
    if not re.fullmatch(r"[0-9]{1,5}", port_text) or not 1 <= int(port_text) <= 65535:
        raise bad(f"port {port_text!r} is not a number in 1..65535")
    return SchedulerAddress(scheme, host, int(port_text))


def tls_client_configured(security=None) -> bool:
    """True when Dask's configuration (or ``security``, a ``distributed.Security``) gives
    the client a CA file and a certificate: without them distributed cannot open a
    ``tls://`` connection at all."""
    if security is None:
        from distributed import Security

        security = Security()
    return bool(security.tls_ca_file and security.tls_client_cert)


def scheduler_warning(address: SchedulerAddress | str) -> str | None:
    """The one-line warning printed before connecting to ``address``, or ``None``: a
    loopback scheduler and a ``tls://`` one (mutual TLS: only holders of a certificate
    of the cluster's CA can connect) get none."""
    if isinstance(address, str):
        address = parse_scheduler_address(address)
    if address.is_loopback or address.scheme == "tls":
        return None
    return (
        f"warning: --scheduler {address} is not on this machine and not encrypted: a Dask "
        "scheduler runs the code sent to it, and anyone who can reach it can run code as "
        "its workers' user; connect only to a cluster you control, over TLS (tls://, "
        "see docs/cluster.md)"
    )


def _connect(address: SchedulerAddress) -> Client:
    """A client of the scheduler at ``address`` (warning first, see ``scheduler_warning``)."""
    from distributed import Client

    if address.scheme == "tls" and not tls_client_configured():
        raise BadOption(
            f"--scheduler {address}: TLS is not configured: set Dask's "
            "distributed.comm.tls.ca-file and distributed.comm.tls.client.cert (and .key) "
            "(see docs/cluster.md)"
        )
    warning = scheduler_warning(address)
    if warning is not None:
        print(warning, file=sys.stderr)
    try:
        return Client(str(address), timeout="20s")
    except OSError as exc:
        raise PhrtError(f"--scheduler {address}: cannot connect ({exc})") from None


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Client]:
    """A ``distributed.Client``: connected to ``scheduler`` (``tcp://host:8786``,
    ``tls://host:8786``; checked by ``parse_scheduler_address``, warned about by
    ``scheduler_warning``), or to a ``LocalCluster`` of ``workers`` single-threaded
    worker processes on this machine listening on loopback only (``LOOPBACK_HOST``, no
    dashboard). The Phrt worker plugin is registered either way. Closed on exit."""
    from distributed import Client, LocalCluster

    if (workers is None) == (scheduler is None):
        raise BadOption("give exactly one of --workers N or --scheduler ADDRESS")
    if scheduler is not None:
        client = _connect(parse_scheduler_address(scheduler))
        cluster = None
    else:
        if workers < 1:
            raise BadOption(f"--workers must be >= 1, got {workers}")
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,  # one chunk at a time per process (OSMesa, Embree)
            processes=True,
            host=LOOPBACK_HOST,  # scheduler, nannies and workers (tcp, or tls if Dask's
            # config sets distributed.comm.require-encryption)
            dashboard_address=None,  # no dashboard; the workers' HTTP endpoints on host
            # The scheduler's HTTP endpoint (metrics, no dashboard): loopback, any port.
            scheduler_kwargs={"dashboard": False, "dashboard_address": f"{LOOPBACK_HOST}:0"},
        )
        client = Client(cluster)
    try:
        client.register_plugin(PhrtWorkerSetup())
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


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
) -> dict[int, object]:
    """Submit one task per chunk, call ``on_result(results so far)`` as each finishes."""
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
    try:
        for future in as_completed(futures):
            result = future.result()
            if result.chunk.index in results:
                continue  # a chunk comes back once; a duplicate would count frames twice
            results[result.chunk.index] = result
            future.release()
            on_result(results)
    finally:
        for future in futures:
            future.cancel()
    return results


def run_sweep_on_cluster(
    spec: SweepSpec,
    client: Client,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    warmup: int = DEFAULT_WARMUP_FRAMES,
    on_chunk: Callable[[int, int], None] | None = None,
) -> dict:
    """``run_sweep`` on a Dask cluster: same files, same rows (timings aside), same
    timeline as one process with a rays budget (docs/cluster.md). ``on_chunk(done,
    total)`` after every finished chunk. Returns ``run_sweep``'s summary dict plus
    ``chunk_pids``: the process id of the worker whose result was kept, per chunk."""
    from phrt_usd.evaluate.sweep import check_spec, finish_sweep, write_sweep_csv
    from phrt_usd.evaluate.sweep_files import SWEEP_CSV
    from phrt_usd.run.frames import parse_frames
    from phrt_usd.run.run_directory import DirectoryLock
    from phrt_usd.usd.stage import open_stage

    check_spec(spec)
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
    with DirectoryLock(spec.out):  # one sweep writes OUT at a time
        results = _gather(client, sweep_chunk, chunks, worker_spec, progress)
        _check_complete(chunks, results)
        timeline: dict = {}
        for chunk in chunks:
            _merge_timeline(timeline, results[chunk.index])
        _remove_stale_temporaries(spec.out)
        summary = finish_sweep(spec, _sweep_rows(chunks, results), timeline, interrupted=False)
    summary["chunk_pids"] = [results[c.index].worker_pid for c in chunks]
    return summary


def run_render_on_cluster(
    job: RenderJob,
    client: Client,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    warmup: int = DEFAULT_WARMUP_FRAMES,
    on_frame: Callable[[int, int], None] | None = None,
) -> dict:
    """``run_render`` on a Dask cluster (no checkpoint / ``--resume``: a lost chunk is
    re-run by the scheduler instead). ``on_frame(done, total)`` after every chunk.
    Returns ``run_render``'s summary dict plus ``chunk_pids`` (see the sweep's)."""
    from phrt_usd.api import summary_of
    from phrt_usd.run.frames import parse_frames
    from phrt_usd.run.render_job import RunRecord, job_run_info, prepare_job, write_run_records
    from phrt_usd.run.run_directory import RunDirectory
    from phrt_usd.usd.stage import open_stage

    if job.resume:
        raise PhrtError("--resume is not available with --workers / --scheduler")
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

    with RunDirectory(out, layer_path, scene, overwrite=job.overwrite, images=images.templates()):
        worker_job = replace(job, out_dir=out.resolve())  # workers write images there
        results = _gather(client, render_chunk, chunks, worker_job, progress)
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
