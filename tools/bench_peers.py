"""Peer benchmark: our three modes against pyrender, raw embreex and Mitsuba 3, side by side.

    uv run python tools/bench_peers.py stages/farm.usda stages/sewer.usda \
        --resolutions 320x240,640x480 --frames 5 --profile 30 \
        --append docs/bench-log/DATE-COMMIT-peers.md

For each stage x resolution, on the same frames (``--frames N``: N frames spread evenly
along the stage's frame range, or an explicit ``A:B[:STEP]``), in one run:

* ours: ``hybrid`` (HEU1, T = ``--budget-ms``), ``rt`` and ``raster``, median frame and
  phase times (``FrameRenderer.render``; one untimed warm-up frame per configuration);
* raw embreex on exactly the rays our trace phase cast (hybrid and rt), replayed right
  after each frame with the tracer's own threading: the tracing limit; and on every ray
  an rt frame cast (primary, shadow, reflection): the limit of a full Embree frame;
* pyrender's own lit render of the same geometry (one node with per-corner vertex
  colours, the stage's distant lights as DirectionalLights and local lights as
  PointLights, default flags: no shadows), one untimed render first: the raster floor;
* Mitsuba 3 on the same scene and cameras (``phrt_usd.bench.mitsuba_export``), ``path``
  integrator, 1 spp, ``max_depth`` 7 (= 6 bounces), in ``scalar_rgb`` and, when
  ``libLLVM-19`` is installed, ``llvm_ad_rgb``. A Mitsuba variant is process-wide and
  ``DRJIT_LIBLLVM_PATH`` must be set before import, so each variant runs in a child
  process (this script with ``--only mitsuba-<variant>``) that prints JSON. Timed per
  frame: moving the sensor, ``mi.render`` and reading the image into numpy; the scene is
  exported once at the first frame's time (animated prims stay there).

Prints markdown tables of medians and ratios (ours / peer), optionally appends them, the
command, core count, date and git commit to ``--append`` (a new log file in
docs/bench-log/, see BENCHMARKS.md "How to measure"). ``--profile N`` also runs
pyinstrument over N hybrid frames per stage and lists the functions with the most own
time (pyinstrument samples the main thread only: time in worker threads shows up as the
main thread waiting for them).
"""

from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.run.frames import parse_frames
from phrt_usd.usd.stage import StageScene, open_stage

PHASES = ("set_time", "gbuffer", "shade", "select", "trace")
#: Mitsuba integrator depth (camera segment included: 7 = up to 6 bounces), the depth of
#: the reference measurement quoted in the issue.
MITSUBA_MAX_DEPTH = 7
MITSUBA_VARIANTS = ("scalar_rgb", "llvm_ad_rgb")
#: Where Debian's ``libllvm19`` puts its shared library (drjit's LLVM backend fails
#: against Debian's default LLVM 15).
LIBLLVM19_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so*", "/usr/lib/*/libLLVM.so.19*")
#: Tracer calls that make up our ``trace`` phase; the others (primary rays, shadow rays)
#: belong to the gbuffer and shade phases.
TRACE_CALLS = ("trace_reflections", "trace_refraction")
FRAME_CALLS = ("primary_gbuffer", "shadow_visibility", *TRACE_CALLS)
REPO = Path(__file__).resolve().parent.parent


def frame_times(stage: StageScene, spec: str) -> list[float]:
    """Time codes to bench: ``N`` (N frames evenly spread over the frame range, ends
    included) or ``A:B[:STEP]`` (``phrt_usd.run.frames.parse_frames``)."""
    if spec.isdigit():
        start, end = stage.frame_range
        return [float(round(t)) for t in np.linspace(start, end, max(int(spec), 1))]
    return parse_frames(spec, stage.frame_range)


def libllvm19() -> str | None:
    """Path of an installed libLLVM-19 shared library, or None."""
    for pattern in LIBLLVM19_GLOBS:
        hits = sorted(glob.glob(pattern))
        if hits:
            return hits[0]
    return None


def _median(values: list[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


# ------------------------------------------------------------------------------ ours


class RayLog:
    """Wraps a tracer's public calls so every Embree batch of a frame is kept, per call
    name (``Tracer.last_rays`` only holds the latest call's batches)."""

    def __init__(self, tracer) -> None:
        self.tracer = tracer
        self.batches: dict[str, list] = {name: [] for name in FRAME_CALLS}
        tracer.record_rays = True
        for name in FRAME_CALLS:
            setattr(tracer, name, self._wrap(name, getattr(tracer, name)))

    def _wrap(self, name: str, method: Callable) -> Callable:
        def call(*args, **kwargs):
            out = method(*args, **kwargs)
            self.batches[name].extend(self.tracer.last_rays)
            return out

        return call

    def clear(self) -> None:
        for v in self.batches.values():
            v.clear()

    def replay(self, names: tuple[str, ...]) -> tuple[int, float]:
        """Raw embreex on the logged batches of ``names``: (rays, seconds)."""
        self.tracer.last_rays = [b for n in names for b in self.batches[n]]
        if not self.tracer.last_rays:
            return 0, 0.0
        return self.tracer.replay_raw()


def bench_ours(stage: StageScene, times: list[float], w: int, h: int, budget_ms: float) -> dict:
    """Median frame / phase ms of our three modes, plus raw embreex on their rays."""
    configs = {
        "hybrid": RenderOptions(mode="hybrid", heuristic="heu1", budget_ms=budget_ms),
        "rt": RenderOptions(mode="rt", heuristic="all", budget_ms=None),
        "raster": RenderOptions(mode="raster", heuristic="none", budget_ms=None),
    }
    out: dict[str, dict] = {}
    for label, base in configs.items():
        opts = RenderOptions(**{**base.__dict__, "width": w, "height": h})
        renderer = FrameRenderer(stage, opts)
        renderer.plan(times)
        renderer.render(times[0])  # warm-up: first upload, shadow maps, caches
        log = RayLog(renderer.tracer) if renderer.tracer is not None else None
        frame_ms, phases = [], {p: [] for p in PHASES}
        trace = {"rays": 0, "our_s": 0.0, "raw_s": 0.0}
        whole = {"rays": 0, "raw_s": 0.0, "raw_ms": []}
        for t in times:
            if log is not None:
                log.clear()
            stats = renderer.render(t).stats
            frame_ms.append(stats.frame_ms)
            for p in PHASES:
                phases[p].append(stats.phase_ms.get(p, 0.0))
            if log is None:
                continue
            rays, seconds = log.replay(TRACE_CALLS)
            if rays:
                trace["rays"] += rays
                trace["our_s"] += stats.trace_ms / 1000.0
                trace["raw_s"] += seconds
            if label == "rt":
                rays, seconds = log.replay(FRAME_CALLS)
                whole["rays"] += rays
                whole["raw_s"] += seconds
                whole["raw_ms"].append(seconds * 1000.0)
        renderer.close()
        row = {
            "frame_ms": _median(frame_ms),
            "phase_ms": {p: _median(v) for p, v in phases.items()},
            "frames": len(times),
        }
        if trace["rays"] and trace["our_s"] > 0 and trace["raw_s"] > 0:
            row["trace_rays_per_frame"] = trace["rays"] / len(times)
            row["trace_ours_mrays_s"] = trace["rays"] / trace["our_s"] / 1e6
            row["trace_raw_mrays_s"] = trace["rays"] / trace["raw_s"] / 1e6
            row["trace_raw_ms"] = trace["raw_s"] * 1000.0 / len(times)
        if whole["rays"]:
            row["frame_rays"] = whole["rays"] / len(times)
            row["frame_raw_ms"] = _median(whole["raw_ms"])
            row["frame_raw_mrays_s"] = whole["rays"] / whole["raw_s"] / 1e6
        out[label] = row
    return out


# -------------------------------------------------------------------------- pyrender


def bench_pyrender(stage: StageScene, times: list[float], w: int, h: int) -> dict:
    """pyrender's lit render of the stage's geometry at ``times[0]``, one node."""
    import pyrender
    import trimesh

    from phrt_usd.bench.mitsuba_export import corner_colors

    stage.set_time(times[0])
    scene = stage.scene
    geo = scene.geometry
    corners = (geo.vertices[geo.triangles] - scene.origin).reshape(-1, 3)
    n = geo.triangle_count
    colors = np.clip(corner_colors(scene).reshape(-1, 3), 0.0, 1.0)
    mesh = trimesh.Trimesh(
        vertices=corners,
        faces=np.arange(3 * n).reshape(n, 3),
        vertex_colors=np.concatenate([colors, np.ones((3 * n, 1))], axis=1),
        vertex_normals=np.asarray(geo.corner_normals, np.float64).reshape(-1, 3),
        process=False,
    )
    pr_scene = pyrender.Scene(ambient_light=np.full(3, 0.2), bg_color=np.zeros(4))
    pr_scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=True))
    for light in scene.lights.distant:
        # pyrender's DirectionalLight shines down its node's -Z: point -Z along -direction.
        towards = np.asarray(light.direction, np.float64)
        pose = _look_pose(np.zeros(3), -towards)
        intensity = float(np.max(light.radiance))
        color = np.asarray(light.radiance) / max(intensity, 1e-12)
        pr_scene.add(pyrender.DirectionalLight(color=color, intensity=intensity), pose=pose)
    for light in scene.lights.local:
        pose = np.eye(4)
        pose[:3, 3] = np.asarray(light.position) - scene.origin
        intensity = float(np.max(light.radiance))
        color = np.asarray(light.radiance) / max(intensity, 1e-12)
        pr_scene.add(pyrender.PointLight(color=color, intensity=intensity), pose=pose)
    cam0 = stage.camera(times[0])
    _, ty = cam0.tan_half_fov(w, h)
    camera = pyrender.PerspectiveCamera(
        yfov=2.0 * np.arctan(ty), aspectRatio=w / h, znear=cam0.near, zfar=cam0.far
    )
    cam_node = pr_scene.add(camera, pose=np.eye(4))
    renderer = pyrender.OffscreenRenderer(w, h)
    poses = []
    for t in times:
        pose = np.array(stage.camera(t).world_from_camera, dtype=np.float64)
        pose[:3, 3] -= scene.origin
        poses.append(pose)
    pr_scene.set_pose(cam_node, poses[0])
    renderer.render(pr_scene)  # untimed: uploads the mesh, compiles shaders
    frame_ms = []
    for pose in poses:
        t0 = time.perf_counter()
        pr_scene.set_pose(cam_node, pose)
        renderer.render(pr_scene)
        frame_ms.append((time.perf_counter() - t0) * 1000.0)
    renderer.delete()
    return {"frame_ms": _median(frame_ms), "frames": len(times)}


def _look_pose(position: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(4, 4) pose whose -Z axis points along ``direction`` (any up)."""
    f = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(f, helper)
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, -f, position
    return pose


# --------------------------------------------------------------------------- Mitsuba


def bench_mitsuba(
    variant: str,
    jobs: list[tuple[str, int, int, list[float]]],
    png_dir: Path | None,
    png_frame: float | None = None,
) -> dict:
    """Run in a child process: Mitsuba ``variant`` on every (stage, w, h, times) job.
    Returns {"stage|WxH": {"frame_ms", "load_ms", "first_ms", "frames"}}."""
    import mitsuba as mi

    mi.set_variant(variant)
    from phrt_usd.bench import mitsuba_export

    results = {}
    stages: dict[str, StageScene] = {}
    saved: set[str] = set()
    for stage_path, w, h, times in jobs:
        stage = stages.setdefault(stage_path, open_stage(stage_path))
        stage.set_time(times[0])
        t0 = time.perf_counter()
        mi_scene = mitsuba_export.load_scene(
            stage.scene, stage.camera(times[0]), w, h, MITSUBA_MAX_DEPTH
        )
        load_ms = (time.perf_counter() - t0) * 1000.0
        t0 = time.perf_counter()
        np.asarray(mi.render(mi_scene, spp=1))  # untimed: BVH build, kernel compilation
        first_ms = (time.perf_counter() - t0) * 1000.0
        # Untimed too: the first render after a sensor update (llvm: its kernel variant).
        mitsuba_export.set_camera(mi_scene, stage.camera(times[-1]), stage.scene.origin)
        np.asarray(mi.render(mi_scene, spp=1))
        frame_ms = []
        for i, t in enumerate(times):
            t0 = time.perf_counter()
            mitsuba_export.set_camera(mi_scene, stage.camera(t), stage.scene.origin)
            image = np.asarray(mi.render(mi_scene, spp=1, seed=i + 1))
            frame_ms.append((time.perf_counter() - t0) * 1000.0)
        if png_dir is not None and stage_path not in saved:  # first resolution of a stage
            saved.add(stage_path)
            t_png = times[0] if png_frame is None else png_frame
            _save_mitsuba_png(mi, mi_scene, stage, t_png, png_dir, Path(stage_path).stem)
        results[f"{stage_path}|{w}x{h}"] = {
            "frame_ms": _median(frame_ms),
            "load_ms": load_ms,
            "first_ms": first_ms,
            "frames": len(times),
            "image_mean": [float(v) for v in image.reshape(-1, 3).mean(axis=0)],
        }
    return results


def _save_mitsuba_png(mi, mi_scene, stage, t, png_dir: Path, stem: str) -> None:
    """A low-noise Mitsuba image (64 spp) of frame ``t`` for the visual check."""
    from phrt_usd.bench import mitsuba_export
    from phrt_usd.run.images import write_preview_png

    mitsuba_export.set_camera(mi_scene, stage.camera(t), stage.scene.origin)
    image = np.asarray(mi.render(mi_scene, spp=64), dtype=np.float32)
    png_dir.mkdir(parents=True, exist_ok=True)
    write_preview_png(png_dir / f"{stem}_t{t:g}_mitsuba_{mi.variant()}.png", image)


def run_mitsuba_child(
    variant: str,
    jobs: list[tuple[str, int, int, list[float]]],
    png_dir: Path | None,
    png_frame: float | None,
) -> dict | str:
    """Results of ``bench_mitsuba`` in a child process, or a one-line reason it did not
    run (missing libLLVM-19, import failure...)."""
    env = dict(os.environ)
    if variant.startswith("llvm"):
        lib = libllvm19()
        if lib is None:
            return "libLLVM-19 not installed (apt-get install libllvm19)"
        env["DRJIT_LIBLLVM_PATH"] = lib
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--only",
        f"mitsuba-{variant}",
        "--jobs-json",
        json.dumps(jobs),
    ]
    if png_dir is not None:
        cmd += ["--png-dir", str(png_dir)]
        if png_frame is not None:
            cmd += ["--png-frame", str(png_frame)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return f"failed: {tail}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------- profiling


def profile_hybrid(stage_path: str, w: int, h: int, n_frames: int, budget_ms: float, top: int):
    """pyinstrument over ``n_frames`` hybrid (HEU1) frames spread along the path.

    Returns (rows, total_s): rows are (own seconds, share of the loop, function, file:line),
    the functions with the most own time summed over every call site.
    """
    from pyinstrument import Profiler

    stage = open_stage(stage_path)
    times = frame_times(stage, str(n_frames))
    opts = RenderOptions(mode="hybrid", heuristic="heu1", budget_ms=budget_ms, width=w, height=h)
    renderer = FrameRenderer(stage, opts)
    renderer.render(times[0])
    profiler = Profiler(interval=0.0005)
    t0 = time.perf_counter()
    profiler.start()
    for t in times:
        renderer.render(t)
    profiler.stop()
    total = time.perf_counter() - t0
    renderer.close()
    own: dict[tuple[str, str], float] = {}
    stack = [profiler.last_session.root_frame()]
    while stack:
        frame = stack.pop()
        if frame is None:
            continue
        if not frame.is_synthetic:
            where = f"{_short_path(frame.file_path)}:{frame.line_no}"
            key = (frame.function or "?", where)
            own[key] = own.get(key, 0.0) + frame.total_self_time
        stack.extend(frame.children)
    ranked = sorted(own.items(), key=lambda kv: kv[1], reverse=True)[:top]
    rows = [(s, s / total, fn, where) for (fn, where), s in ranked]
    return rows, total


def _short_path(path: str | None) -> str:
    if not path:
        return "?"
    for marker in ("site-packages/", "/work/main/", str(REPO) + "/"):
        if marker in path:
            return path.split(marker, 1)[1]
    return path


def git_commit() -> str:
    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=False
        ).stdout.strip()

    head = git("rev-parse", "--short", "HEAD")
    dirty = git("status", "--porcelain", "--untracked-files=no", "phrt_usd")
    return head + (" (+ uncommitted changes in phrt_usd/)" if dirty else "")


# -------------------------------------------------------------------------- markdown


def _ratio(ours: float, peer: float | None) -> str:
    if peer is None or not np.isfinite(peer) or peer <= 0:
        return "–"
    return f"{ours / peer:.2f}"


def markdown_block(stage_path: str, res: str, ours: dict, pyr: dict, mits: dict) -> str:
    """One stage x resolution: rows of medians, ratios of our hybrid and rt to each."""
    hyb, rt = ours["hybrid"]["frame_ms"], ours["rt"]["frame_ms"]
    lines = [
        f"#### {Path(stage_path).stem} {res} ({ours['hybrid']['frames']} frames)\n",
        "| renderer | median ms | fps | phases ms (set_time / gbuffer / shade / select / "
        "trace) | hybrid ÷ this | rt ÷ this |",
        "|---|---|---|---|---|---|",
    ]

    def row(name: str, ms: float | None, phases: str = "") -> None:
        if ms is None or not np.isfinite(ms):
            lines.append(f"| {name} | – | – | {phases} | – | – |")
            return
        lines.append(
            f"| {name} | {ms:.1f} | {1000.0 / ms:.1f} | {phases} | {_ratio(hyb, ms)} "
            f"| {_ratio(rt, ms)} |"
        )

    for label, name in (
        ("hybrid", "ours hybrid (HEU1, T = budget)"),
        ("rt", "ours rt"),
        ("raster", "ours raster"),
    ):
        r = ours[label]
        phases = " / ".join(f"{r['phase_ms'][p]:.1f}" for p in PHASES)
        row(name, r["frame_ms"], phases)
    row("pyrender lit, one node (no shadows)", pyr.get("frame_ms"))
    rt_row = ours["rt"]
    if "frame_raw_ms" in rt_row:
        row(
            f"raw embreex, all rays of our rt frame ({rt_row['frame_rays'] / 1e3:.0f} k rays, "
            f"{rt_row['frame_raw_mrays_s']:.2f} Mrays/s)",
            rt_row["frame_raw_ms"],
        )
    for variant in MITSUBA_VARIANTS:
        m = mits.get(variant)
        name = f"Mitsuba 3 `{variant}`, path, 1 spp, max_depth {MITSUBA_MAX_DEPTH}"
        if isinstance(m, dict):
            row(name, m["frame_ms"])
        else:
            lines.append(f"| {name} | {m or 'not run'} | | | | |")
    lines.append("")
    for label in ("hybrid", "rt"):
        r = ours[label]
        if "trace_ours_mrays_s" in r:
            share = r["trace_ours_mrays_s"] / r["trace_raw_mrays_s"]
            lines.append(
                f"- {label} trace phase: {r['trace_rays_per_frame']:,.0f} rays/frame (mean); "
                f"ours {r['trace_ours_mrays_s']:.2f} Mrays/s vs raw embreex on the same rays "
                f"{r['trace_raw_mrays_s']:.2f} Mrays/s ({r['trace_raw_ms']:.1f} ms/frame) = "
                f"**{share:.0%}** of raw"
            )
        else:
            lines.append(f"- {label}: no rays traced on these frames")
    lines.append(f"- targets: {targets(res, ours, mits)}")
    return "\n".join(lines) + "\n"


#: The issue's targets: hybrid frame time <= Mitsuba's 1-spp frame, >= 20 fps at 320x240,
#: trace phase >= 50 % of raw embreex's throughput on the same rays.
TARGET_FPS_320 = 20.0
TARGET_TRACE_SHARE = 0.5


def targets(res: str, ours: dict, mits: dict) -> str:
    """One line: each target met or missed, and by how much."""
    hyb = ours["hybrid"]["frame_ms"]
    parts = []
    for variant in MITSUBA_VARIANTS:
        m = mits.get(variant)
        if isinstance(m, dict):
            ratio = hyb / m["frame_ms"]
            verdict = "met" if ratio <= 1.0 else f"missed, {ratio:.2f}x Mitsuba's time"
            parts.append(f"hybrid / Mitsuba `{variant}` = {ratio:.2f} (<= 1: {verdict})")
    if res == "320x240":
        fps = 1000.0 / hyb
        verdict = "met" if fps >= TARGET_FPS_320 else f"missed by {TARGET_FPS_320 / fps:.1f}x"
        parts.append(f"hybrid {fps:.1f} fps (>= {TARGET_FPS_320:.0f}: {verdict})")
    r = ours["hybrid"]
    if "trace_ours_mrays_s" in r:
        share = r["trace_ours_mrays_s"] / r["trace_raw_mrays_s"]
        verdict = "met" if share >= TARGET_TRACE_SHARE else "missed"
        parts.append(f"hybrid trace {share:.0%} of raw embreex (>= 50 %: {verdict})")
    return "; ".join(parts)


def markdown_profile(stage_path: str, res: str, n: int, rows, total: float, commit: str) -> str:
    lines = [
        f"#### Profile: {Path(stage_path).stem} {res}, hybrid HEU1, {n} frames, "
        f"{total:.2f} s, commit {commit}\n",
        "| own s | share | function | where |",
        "|---|---|---|---|",
    ]
    for s, share, fn, where in rows:
        lines.append(f"| {s:.3f} | {share:.1%} | `{fn}` | `{where}` |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stages", nargs="*")
    ap.add_argument("--resolutions", default="320x240,640x480")
    ap.add_argument("--frames", default="5", help="N (spread along the path) or A:B[:STEP]")
    ap.add_argument("--budget-ms", type=float, default=10.0, help="hybrid's budget T")
    ap.add_argument("--profile", type=int, default=0, help="pyinstrument over N hybrid frames")
    ap.add_argument("--profile-top", type=int, default=12)
    ap.add_argument("--append", type=Path, default=None, help="append the tables to this file")
    ap.add_argument("--json", type=Path, default=None, help="write all figures as JSON")
    ap.add_argument("--png-dir", type=Path, default=None, help="save rt / Mitsuba images here")
    ap.add_argument("--png-frame", type=float, default=None, help="frame of those images")
    ap.add_argument("--skip-mitsuba", action="store_true")
    ap.add_argument("--only", default=None, help=argparse.SUPPRESS)  # child: mitsuba-<variant>
    ap.add_argument("--jobs-json", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.only:
        variant = args.only.removeprefix("mitsuba-")
        jobs = [(s, w, h, list(t)) for s, w, h, t in json.loads(args.jobs_json)]
        print(json.dumps(bench_mitsuba(variant, jobs, args.png_dir, args.png_frame)))
        return 0
    if not args.stages:
        ap.error("give at least one stage")

    load_before = os.getloadavg()
    resolutions = [tuple(int(v) for v in r.lower().split("x")) for r in args.resolutions.split(",")]
    jobs, results = [], {}
    for stage_path in args.stages:
        stage = open_stage(stage_path)
        times = frame_times(stage, args.frames)
        for w, h in resolutions:
            key = f"{stage_path}|{w}x{h}"
            ours = bench_ours(stage, times, w, h, args.budget_ms)
            pyr = bench_pyrender(stage, times, w, h)
            results[key] = {"times": times, "ours": ours, "pyrender": pyr, "mitsuba": {}}
            jobs.append((stage_path, w, h, times))
            print(f"done ours + pyrender {stage_path} {w}x{h}", file=sys.stderr)
            if args.png_dir is not None and (w, h) == resolutions[0]:
                t_png = times[0] if args.png_frame is None else args.png_frame
                _save_ours_png(stage, Path(stage_path).stem, t_png, w, h, args.png_dir)
    if not args.skip_mitsuba:
        for variant in MITSUBA_VARIANTS:
            got = run_mitsuba_child(variant, jobs, args.png_dir, args.png_frame)
            print(f"done mitsuba {variant}", file=sys.stderr)
            for key in results:
                results[key]["mitsuba"][variant] = got.get(key) if isinstance(got, dict) else got

    blocks = [
        markdown_block(key.split("|")[0], key.split("|")[1], r["ours"], r["pyrender"], r["mitsuba"])
        for key, r in results.items()
    ]
    commit = git_commit()
    if args.profile:
        w, h = resolutions[0]
        for stage_path in args.stages:
            rows, total = profile_hybrid(
                stage_path, w, h, args.profile, args.budget_ms, args.profile_top
            )
            results[f"profile|{stage_path}"] = {"rows": rows, "total_s": total}
            blocks.append(
                markdown_profile(stage_path, f"{w}x{h}", args.profile, rows, total, commit)
            )
    load = f"load average (1 min) {load_before[0]:.1f} before, {os.getloadavg()[0]:.1f} after"
    from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line

    record = collect_for_tool(__file__, argv)
    load += "\n\n" + provenance_line(record)
    text = "\n".join(blocks)
    print(load + "\n\n" + text)
    if args.json:
        results["provenance"] = record
        args.json.write_text(json.dumps(results, indent=1, default=str))
    if args.append:
        command = "uv run python tools/bench_peers.py " + " ".join(argv or sys.argv[1:])
        stamp = datetime.date.today().isoformat()
        with open(args.append, "a") as fh:
            fh.write(
                f"\n### Peers, {stamp}, {os.cpu_count()} cores, commit {commit}\n\n"
                f"`{command}`\n\n{load}\n\n{text}"
            )
    return 0


def _save_ours_png(stage: StageScene, stem: str, t: float, w: int, h: int, png_dir: Path) -> None:
    """Our rt frame ``t`` for the visual check against Mitsuba's."""
    from phrt_usd.run.images import write_preview_png

    renderer = FrameRenderer(
        stage, RenderOptions(mode="rt", heuristic="all", budget_ms=None, width=w, height=h)
    )
    out = renderer.render(t)
    renderer.close()
    png_dir.mkdir(parents=True, exist_ok=True)
    write_preview_png(png_dir / f"{stem}_t{t:g}_ours_rt.png", out.beauty)


if __name__ == "__main__":
    raise SystemExit(main())
