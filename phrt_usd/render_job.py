"""Rendering a frame range to an output directory: images, stats.json, selection layer.

A run is checkpointed every ``checkpoint_every`` frames (less often in long runs, see
``CHECKPOINT_MAX_SHARE``) and when it stops early: the
checkpoint (``OUT/checkpoint.pkl``: finished frames' stats and the selection policy's
memory) is written atomically first, then ``stats.json`` and the selection layer are
rewritten from it. SIGINT / SIGTERM finish the current frame, write everything and raise
``RenderInterrupted``; ``resume=True`` continues after the last checkpointed frame with
the policy exactly as it was, so the result equals an uninterrupted run.
"""

from __future__ import annotations

import os
import pickle
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.frame import FrameStats
from phrt_usd.images import write_frame_exr, write_preview_png
from phrt_usd.renderer import FrameRenderer, RenderOptions
from phrt_usd.report import build_report
from phrt_usd.run_files import frame_image_paths, make_run_info, write_stats
from phrt_usd.selection_layer import write_selection_layer
from phrt_usd.stage_reader import StageScene, open_stage

CHECKPOINT_NAME = "checkpoint.pkl"
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
    frames: str | None = None  # "A:B[:STEP]" in time codes, both ends included
    camera: str | None = None
    selection_layer: Path | None = None
    resume: bool = False
    write_images: bool = True
    checkpoint_every: int = DEFAULT_CHECKPOINT_EVERY


def parse_frames(spec: str | None, default: tuple[float, float]) -> list[float]:
    """``"A:B[:STEP]"`` → time codes A, A+STEP, … up to and including B (stage time codes).

    ``None`` gives the default range with step 1; ``"A"`` alone is one frame.
    """
    if spec is None:
        start, end, step = default[0], default[1], 1.0
    else:
        try:
            parts = [float(p) for p in spec.split(":")]
        except ValueError:
            raise PhrtError(f"--frames {spec!r}: expected A:B[:STEP] with numbers") from None
        if len(parts) == 1:
            parts = [parts[0], parts[0]]
        if len(parts) not in (2, 3):
            raise PhrtError(f"--frames {spec!r}: expected A:B[:STEP]")
        start, end = parts[0], parts[1]
        step = parts[2] if len(parts) == 3 else 1.0
    if not all(np.isfinite([start, end, step])) or step <= 0 or end < start:
        raise PhrtError(f"--frames {spec!r}: need finite A <= B and STEP > 0")
    count = int(np.floor((end - start) / step + 1e-9)) + 1
    return [float(start + i * step) for i in range(count)]


def run_render(
    job: RenderJob,
    on_frame: Callable[[int, int, FrameStats], None] | None = None,
    stage_scene: StageScene | None = None,
) -> dict:
    """Render ``job`` and return the summary object (DESIGN.md §2 keys and more)."""
    out = job.out_dir
    scene = stage_scene or open_stage(job.stage_path, camera=job.camera)
    times = parse_frames(job.frames, scene.frame_range)
    out.mkdir(parents=True, exist_ok=True)
    layer_path = job.selection_layer or out / "selection.usda"
    run_info = job_run_info(job, scene, times)

    renderer = FrameRenderer(scene, job.options)
    renderer.plan(times)
    done: list[FrameStats] = []
    if job.resume:
        done, policy = _load_checkpoint(out, run_info)
        if policy is not None:
            renderer.policy = policy
    finished = {s.time for s in done}
    todo = [t for t in times if t not in finished]

    stop = threading.Event()
    since_checkpoint = 0
    next_checkpoint = 0.0  # time.perf_counter() before which no periodic checkpoint
    try:
        with stop_on_signals(stop):
            for t in todo:
                done.append(render_frame(renderer, t, out if job.write_images else None))
                since_checkpoint += 1
                if on_frame is not None:
                    on_frame(len(done), len(times), done[-1])
                if stop.is_set():
                    break
                start = time.perf_counter()
                if since_checkpoint >= job.checkpoint_every and start >= next_checkpoint:
                    _checkpoint(out, layer_path, job, scene, run_info, done, renderer)
                    end = time.perf_counter()
                    next_checkpoint = end + (end - start) * (1 / CHECKPOINT_MAX_SHARE - 1)
                    since_checkpoint = 0
        _checkpoint(out, layer_path, job, scene, run_info, done, renderer)
    finally:
        renderer.close()
    if stop.is_set() and len(done) < len(times):
        raise RenderInterrupted(
            f"stopped after {len(done)} of {len(times)} frames; finished frames are in {out} "
            "(continue with --resume)"
        )
    summary = build_report(layer_path)
    summary.update(
        out=str(out),
        selection_layer=str(layer_path),
        passes=sorted({p for s in done for p in s.passes}),
    )
    return summary


def render_frame(renderer: FrameRenderer, t: float, out: Path | None) -> FrameStats:
    """Render frame ``t`` with ``renderer`` (its policy remembers the frame); with an
    output directory ``out``, write the frame's EXR and PNG there (atomically)."""
    output = renderer.render(t)
    if out is not None:
        exr, png = frame_image_paths(out, t)
        write_frame_exr(
            exr,
            output.beauty,
            output.alpha,
            output.gbuffer.depth,
            output.gbuffer.element_id,
            output.traced_mask,
        )
        write_preview_png(png, output.beauty)
    return output.stats


def job_run_info(job: RenderJob, scene: StageScene, times: list[float]) -> dict:
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
    info["camera"] = scene.camera_path
    return info


# Options that must match between an interrupted run and its --resume.
_RESUME_KEYS = (
    "stage",
    "mode",
    "heuristic",
    "budget_ms",
    "budget_rays",
    "bounce_limit",
    "selection_weight",
    "resolution",
)


def _load_checkpoint(out: Path, run_info: dict) -> tuple[list[FrameStats], object | None]:
    path = out / CHECKPOINT_NAME
    if not path.exists():
        return [], None
    try:
        with open(path, "rb") as fh:
            state = pickle.load(fh)
    except (OSError, pickle.UnpicklingError, EOFError) as exc:
        raise PhrtError(f"{path}: cannot read checkpoint ({exc})") from None
    for key in _RESUME_KEYS:
        if state["run_info"].get(key) != run_info.get(key):
            raise PhrtError(
                f"--resume: {key} differs from the interrupted run in {out} "
                f"({state['run_info'].get(key)!r} vs {run_info.get(key)!r})"
            )
    return list(state["frames"]), state["policy"]


def _checkpoint(
    out: Path,
    layer_path: Path,
    job: RenderJob,
    scene: StageScene,
    run_info: dict,
    frames: list[FrameStats],
    renderer: FrameRenderer,
) -> None:
    """Write the checkpoint, then stats.json and the selection layer, each atomically."""
    frames = sorted(frames, key=lambda s: s.time)
    tmp = out / (CHECKPOINT_NAME + ".tmp")
    with open(tmp, "wb") as fh:
        pickle.dump({"run_info": run_info, "frames": frames, "policy": renderer.policy}, fh)
    os.replace(tmp, out / CHECKPOINT_NAME)
    write_run_records(out, layer_path, job, scene, run_info, frames)


def write_run_records(
    out: Path,
    layer_path: Path,
    job: RenderJob,
    scene: StageScene,
    run_info: dict,
    frames: list[FrameStats],
) -> None:
    """stats.json and the selection layer (merged with frames already in it), atomically."""
    write_stats(out, run_info, frames)
    write_selection_layer(
        layer_path,
        str(job.stage_path),
        run_info["reflectors"],
        frames,
        run_info,
        scene.time_codes_per_second,
        merge=True,
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
