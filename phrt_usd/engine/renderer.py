"""One frame of the heuristic hybrid renderer, in the three modes.

Per frame (``FrameRenderer.render``):

1. ``set_time``   animated prims re-evaluated; rasterizer / Embree scene brought to the
                  scene's version (only the elements that changed).
2. ``gbuffer``    raster G-buffer (the id pass) — or primary rays (Embree): always in
                  ``rt`` mode, else where ``--primary`` chose them (``primary_source``).
3. ``shade``      local shading of every covered pixel (shadow map in raster/hybrid,
                  shadow rays in ``rt``); reflectors get the environment fallback.
4. ``select`` + ``trace``  rounds of: the selection policy picks reflectors that fit the
                  remaining budget, the tracer traces their pixels, the policy learns
                  from what the rays hit. Skipped when no reflector is visible or known.
5. ``composite``  traced radiance replaces the fallback in the traced pixels.

Modes: ``raster`` (no tracing), ``hybrid`` (the heuristic chooses), ``rt`` (Embree for
everything, all reflectors traced: the reference; its raster phase only renders the
shadow maps its traced hits are lit by, as hybrid's are, on stages of more than two
lights: docs/hit-lighting.md).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from phrt_usd import progress
from phrt_usd.engine import frame_pixels
from phrt_usd.engine.clipping_warning import clipping_warning
from phrt_usd.engine.compositing import base_image, element_reflectivity, pixel_reflectivity
from phrt_usd.engine.lighting import shade_gbuffer
from phrt_usd.engine.motion import MotionField, MotionTracker
from phrt_usd.engine.primary_source import choose, is_software
from phrt_usd.engine.reflection_history import ReflectionHistory
from phrt_usd.engine.trace_calibration import CALIBRATION_SEED, calibrate_tracer
from phrt_usd.engine.trace_rounds import ReflectionRounds
from phrt_usd.model.frame import (
    Budget,
    FrameCamera,
    FrameStats,
    FrameView,
    GBuffer,
    SelectionPolicy,
)
from phrt_usd.model.light_sampling import maps_light_hits
from phrt_usd.model.pixel_kinds import kind_counts
from phrt_usd.model.render_options import MAX_EXPOSURE_EV, RenderOptions
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.select.heu1_forecast import UPCOMING_CAMERAS
from phrt_usd.select.policies import make_policy
from phrt_usd.select.rounds import Calibration, FrameRounds, run_rounds
from phrt_usd.small_pages import small_pages
from phrt_usd.threads import apply_threads
from phrt_usd.usd.default_lights import aim_headlight
from phrt_usd.usd.schema import mark_material_reflections
from phrt_usd.usd.stage import StageScene

#: With ``--target-fps``, a frame's trace budget T leaves this share of the frame period
#: unbudgeted: what runs after the last tracing round (the policy's end of frame, its
#: metrics, the stats) is not measured before T is set, and timer and scheduler jitter
#: between frames would otherwise push every frame slightly past the period.
TARGET_FPS_MARGIN = 0.05
#: Largest finite float32: scaled radiance is clamped to it (an EXR holds no Inf).
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass
class PreparedFrame:
    """A frame after G-buffer and local shading, before any tracing.

    local: (H, W, 3) float32 local shading; reflectivity: (H, W) float32 F per pixel;
    image: (H, W, 3) float32 the raster frame (environment fallback in reflectors);
    pixel_counts: (E,) int64 pixels per element; screen_boxes: (E, 4) see FrameView;
    motion: the frame's motion vectors from the previous frame (``engine/motion.py``),
    computed when first read; its ``camera`` is the frame's (``FrameCamera``).
    """

    time: float
    camera: CameraFrame
    upcoming_cameras: tuple[CameraFrame, ...]  # see FrameView
    gbuffer: GBuffer
    local: np.ndarray
    reflectivity: np.ndarray
    image: np.ndarray
    pixel_counts: np.ndarray
    screen_boxes: np.ndarray
    phase_ms: dict[str, float]
    passes: list[str]
    prepare_ms: float
    motion: MotionField


@dataclass
class FrameOutput:
    """A rendered frame: beauty (H, W, 3) float32 linear RGB (times 2**exposure and the
    camera's exposure scale: ``RenderOptions.exposure``), alpha (H, W) float32,
    the G-buffer, traced_mask (H, W) bool (traced or filled from traced neighbours), the
    frame's stats and its camera (``FrameCamera``: world-to-camera and projection at the
    frame's time code); pixel_kind (H, W) uint8 how each pixel was made
    (``model/pixel_kinds.py``); motion_field the motion vectors from the previous frame
    (``engine/motion.py``), read through ``motion``."""

    beauty: np.ndarray
    alpha: np.ndarray
    gbuffer: GBuffer
    traced_mask: np.ndarray
    stats: FrameStats
    camera: FrameCamera
    pixel_kind: np.ndarray | None = None
    motion_field: MotionField | None = None

    @property
    def motion(self) -> np.ndarray:
        """(H, W, 2) float32 motion in pixels from the previous frame: this frame's
        position minus the previous one's, x right, y down (``engine/motion.py``;
        computed on first use); zeros without a previous frame."""
        if self.motion_field is None:
            return np.zeros((*self.gbuffer.shape, 2), np.float32)
        return self.motion_field.vectors


class FrameRenderer:
    """Renders frames of one stage with fixed options; keeps per-run state (the
    rasterizer's uploaded geometry, the Embree scene, the policy's memory)."""

    def __init__(self, stage_scene: StageScene, options: RenderOptions):
        self.stage_scene = stage_scene
        self.options = options
        scene = stage_scene.scene
        self._reflector_ids = scene.reflector_ids
        # Reflectors without an authored phrt:reflectivity follow their material
        # (engine/compositing.py), in the raster, the traced hits and the composite.
        mark_material_reflections(stage_scene.stage, scene.elements)
        self._element_f = element_reflectivity(scene)  # the rule per element: fixed for a run
        self._rasterizer = None
        self._tracer = None
        #: The OpenGL platform the raster phase runs on (None: no raster phase). In ``rt``
        #: the raster phase only renders the shadow maps the traced hits are lit by, and
        #: only on stages whose hits use them (``light_sampling.maps_light_hits``).
        self.gl: str | None = None
        apply_threads(options.threads)  # before any GL context or pool exists
        if options.mode != "rt" or maps_light_hits(scene.lights):
            from phrt_usd.engine.raster.gl_platform import activate

            self.gl = activate(options.gl)  # before pyrender / OpenGL are imported
            from phrt_usd.engine.raster.rasterizer import Rasterizer

            progress.step("uploading the geometry")
            with small_pages():  # arrays written once (phrt_usd.small_pages)
                self._rasterizer = Rasterizer(scene, options.width, options.height)
        #: The G-buffer source, "raster" or "rays" (``primary_source.choose``).
        self.primary = (
            "rays"
            if options.mode == "rt" or self._rasterizer is None
            else choose(
                options.primary,
                software_gl=is_software(self._rasterizer.gl_renderer),
                triangles=scene.geometry.triangle_count,
                pixels=options.width * options.height,
            )
        )
        # Embree is only needed to trace (reflectors in hybrid, everything in rt), or for
        # primary rays.
        traces = len(self._reflector_ids) and options.heuristic != "none"
        if self.primary == "rays" or (options.mode == "hybrid" and traces):
            from phrt_usd.engine.trace.tracer import Tracer

            self._tracer = Tracer(scene, threads=options.threads)
            if self._rasterizer is not None:  # hits lit by the maps, in rt as in hybrid
                self._tracer.use_shadow_maps(self._rasterizer)
        #: The frames this renderer will render, in order (``plan``), and the cameras of
        #: those looked up so far, by time code.
        self._planned: list[float] = []
        self._planned_index: dict[float, int] = {}
        self._cameras: dict[float, CameraFrame] = {}
        #: Selection ms of the last frame each policy finished (id(policy) → ms): the
        #: estimate of this frame's selection when --target-fps sets T.
        self._select_ms: dict[int, float] = {}
        #: The reflections each policy's last frame traced, for its next frame to reuse
        #: (id(policy) → (policy, history); holding the policy keeps its id unique).
        self._histories: dict[int, tuple[SelectionPolicy, ReflectionHistory]] = {}
        if options.exposure_ev != options.exposure:
            stage_scene.warnings.append(
                f"--exposure {options.exposure:g} EV clamped to {options.exposure_ev:+g} EV "
                f"(|EV| <= {MAX_EXPOSURE_EV:g} keeps radiance finite in float32)"
            )
        #: The clipping warning was given (once per run, ``_check_clipping``).
        self._clipping_warned = False
        #: Motion vectors: the animated vertices of the last frame prepared, its time code.
        self._motion = MotionTracker(scene)
        self._last_time: float | None = None
        policy_name = "all" if options.mode == "rt" else options.heuristic
        self.policy = make_policy(
            policy_name,
            selection_weight=options.selection_weight,
            bounce_limit=options.bounce_limit,
        )

    @property
    def tracer(self):
        """The Embree tracer, or None when this mode and scene need no tracing."""
        return self._tracer

    @property
    def scene(self) -> Scene:
        return self.stage_scene.scene

    def close(self) -> None:
        if self._rasterizer is not None:
            self._rasterizer.close()

    def plan(self, times: Sequence[float]) -> None:
        """Tell the renderer the time codes it will render, in order. Each frame's
        ``FrameView`` then carries the cameras of the next UPCOMING_CAMERAS planned
        frames, which HEU1 uses to forecast a reflector's cost (a stage's camera path is
        known before the render starts). Without a plan, views have no upcoming cameras.
        With a raster phase (outside ``rt``), the first planned frame is prepared once
        here (``warm_up``)."""
        self._planned = [float(t) for t in times]
        self._planned_index = {}
        for k, t in enumerate(self._planned):
            self._planned_index.setdefault(t, k)
        self._cameras = {}
        if self._planned and self._rasterizer is not None and self.options.mode != "rt":
            self.warm_up(self._planned[0])

    def warm_up(self, time_code: float) -> None:
        """The one-time work of the raster phase, done before the first frame as a
        renderer's load step: phases 1-3 at ``time_code``, their result discarded. That
        compiles the OpenGL programs, uploads the geometry, renders the static shadow
        maps and starts the pools, so the first frame costs what a steady frame does
        (without this step it took 8x one, most of it the first shadow maps and light pass).
        Selection and tracing are not run: the policy and its cost model learn from
        rendered frames only, and the image of any frame is the same with or without
        this (everything it leaves behind is a cache of the scene at a time code)."""
        progress.step("preparing the first frame")
        with small_pages():  # the tables and maps it makes are written once
            self.prepare(time_code)

    def _path_cameras(self, time_code: float) -> tuple[CameraFrame, tuple[CameraFrame, ...]]:
        """The camera at ``time_code`` and those of the planned frames after it (at most
        UPCOMING_CAMERAS). Each planned camera is looked up once per run, so a frame's
        camera is the object earlier views listed as upcoming (policies cache by it)."""
        k = self._planned_index.get(float(time_code))
        if k is None:
            return self.stage_scene.camera(time_code), ()
        times = self._planned[k : k + 1 + UPCOMING_CAMERAS]
        cameras = {
            t: self._cameras[t] if t in self._cameras else self.stage_scene.camera(t)
            for t in times
        }
        self._cameras = cameras  # earlier frames' cameras are not needed again
        current, *ahead = cameras.values()
        return current, tuple(ahead)

    def render(self, time_code: float) -> FrameOutput:
        """Render one frame with this renderer's options and selection policy."""
        return self.finish(self.prepare(time_code), self.policy, self.options)

    def prepare(self, time_code: float) -> PreparedFrame:
        """Phases 1–3: scene at ``time_code``, G-buffer, local shading, raster fallback."""
        opts = self.options
        phase: dict[str, float] = {}
        passes: list[str] = []
        t_frame = time.perf_counter()

        t = time.perf_counter()
        previous = self._previous_time(time_code)
        if (previous is not None and self._motion.tracks_geometry
                and self._motion.time != previous):  # fmt: skip
            # Out of order (the first frame after a resume, a chunk's start): the animated
            # elements' vertices at the previous planned frame, for the motion vectors.
            self.stage_scene.set_time(previous)
            self._motion.advance(self.scene, previous)
        self.stage_scene.set_time(time_code)
        moved = self._motion.advance(self.scene, time_code)
        # Each holder of geometry compares the scene's geometry version with its own and
        # re-sends only the elements changed since (several renderers may share one
        # StageScene: versions, not this frame's SceneChange, say what each lacks).
        if self._rasterizer is not None:
            self._rasterizer.update_geometry(self.scene)
        if self._tracer is not None:
            self._tracer.update_geometry(self.scene)
            self._tracer.begin_frame(time_code)  # its light sampling's seed
        camera, upcoming = self._path_cameras(time_code)
        # The default light rig's headlight follows the camera (usd/default_lights.py).
        self.scene.replace_lights(aim_headlight(self.scene.lights, camera))
        phase["set_time"] = _ms(t)

        scene = self.scene
        t = time.perf_counter()
        if self.primary == "rays":
            gb = self._tracer.primary_gbuffer(camera, opts.width, opts.height)
            passes.append("primary_rays")
        else:
            gb = self._rasterizer.render(camera)
            passes.append("gbuffer")
        phase["gbuffer"] = _ms(t)

        t = time.perf_counter()
        local, shadow_pass = self._shade_local(gb)
        if shadow_pass:
            passes.append(shadow_pass)
        reflectivity = pixel_reflectivity(gb, self._element_f)
        image = base_image(gb, scene, local, reflectivity)
        phase["shade"] = _ms(t)
        pixel_counts = np.bincount(gb.element_id[gb.covered], minlength=len(scene.elements))
        screen_boxes = self._screen_boxes(gb)
        motion = self._motion_field(gb, camera, previous, float(time_code), moved)
        self._last_time = float(time_code)
        return PreparedFrame(
            float(time_code),
            camera,
            upcoming,
            gb,
            local,
            reflectivity,
            image,
            pixel_counts,
            screen_boxes,
            phase,
            passes,
            _ms(t_frame),
            motion,
        )

    def finish(
        self, prep: PreparedFrame, policy: SelectionPolicy, opts: RenderOptions
    ) -> FrameOutput:
        """Phases 4–5: selection rounds and tracing within ``opts``' budget
        (``select.rounds.run_rounds``, traced by ``trace_rounds.ReflectionRounds``),
        compositing.

        Leaves ``prep`` untouched, so several policies / budgets can finish one frame.
        """
        scene = self.scene
        t_finish = time.perf_counter()
        phase = dict(prep.phase_ms)
        passes = list(prep.passes)
        gb = prep.gbuffer
        visible_ids = [int(i) for i in self._reflector_ids if prep.pixel_counts[i] > 0]
        frame_budget_ms = self._frame_budget_ms(prep, policy, opts)
        history = reuse = screen = None
        # History in both tracing modes: rt traces every mirror pixel (none is reused or
        # filled), but a glossy pixel's few samples are accumulated across frames in rt
        # as in hybrid (``trace/glossy.py``), so hybrid with every reflector traced is rt.
        if self._tracer is not None and opts.mode in ("hybrid", "rt"):
            history = self._histories.setdefault(id(policy), (policy, ReflectionHistory()))[1]
            reuse = history.begin(gb, prep.motion.camera, self._moved_elements(prep),
                                  self._planned_index.get(prep.time))  # fmt: skip
            if opts.mode == "hybrid" and opts.screen_space == "on":
                from phrt_usd.engine.trace.screen_space import ScreenFrame

                screen = ScreenFrame(prep.motion.camera)
        step = ReflectionRounds(
            self._tracer, gb, prep.local, prep.reflectivity, prep.image, opts.bounce_limit,
            reuse, screen,
        )  # fmt: skip
        rounds = FrameRounds()
        untraced_reason = None
        calibration = None
        if self._tracer is not None and opts.mode != "raster":
            view = FrameView(
                prep.time,
                prep.camera,
                opts.width,
                opts.height,
                prep.pixel_counts,
                prep.screen_boxes,
                prep.upcoming_cameras,
                opts.trace_density,
            )
            rounds = run_rounds(
                policy, view, scene, visible_ids, _frame_limits(opts, frame_budget_ms), step,
                calibrate=partial(calibrate_tracer, self._tracer, gb, visible_ids,
                                  self.options.bounce_limit, CALIBRATION_SEED, frame_budget_ms,
                                  prep.motion.camera if reuse is not None else None, screen),
                observe=step.observe_fallback_error,
            )  # fmt: skip
            if rounds.calibration is not None:
                calibration = _calibration_stats(*rounds.calibration)
                phase["calibrate"] = calibration["wall_ms"]
            if rounds.starved is not None:
                untraced_reason = _no_budget_reason(rounds.starved, prep, opts, frame_budget_ms)
            elif not rounds.selected and visible_ids:
                untraced_reason = rounds.note.untraced_reason
            self._select_ms[id(policy)] = rounds.select_ms
            if rounds.selected:
                passes.append("trace")
                if scene.materials.has_transmission:
                    passes.append("refraction")
        if history is not None:
            history.end(reuse)
        phase["select"] = rounds.select_ms
        phase["trace"] = rounds.trace_ms
        selected = rounds.selected

        # heuristic "none" is raster-only by request: nothing to explain.
        asked_to_trace = opts.heuristic != "none"
        if (opts.mode == "hybrid" and asked_to_trace and visible_ids and not selected
                and untraced_reason is None):
            untraced_reason = (
                "no tracer: the stage has no reflectors to trace"
                if self._tracer is None
                else f"heuristic {opts.heuristic} traces nothing"
            )
        image = step.image
        scale = 2.0**opts.exposure_ev * prep.camera.exposure_scale
        if scale != 1.0:  # exposure: the image's radiance, finite (float32 max at most)
            image = np.minimum(image * np.float32(scale), np.float32(_FLOAT32_MAX))
        self._check_clipping(image, gb, prep.time, opts.exposure_ev, prep.camera.exposure_scale)
        alpha = gb.covered.astype(np.float32)
        # The calibration runs once per run and is reported apart (FrameStats.calibration).
        frame_ms = prep.prepare_ms + _ms(t_finish) - phase.get("calibrate", 0.0)
        budget_use = None
        if (frame_budget_ms is not None and frame_budget_ms > 0 and visible_ids
                and policy.follows_budget):  # fmt: skip
            budget_use = rounds.trace_ms / frame_budget_ms
        elements = scene.elements
        metrics = rounds.metrics
        stats = FrameStats(
            time=prep.time,
            phase_ms=phase,
            frame_ms=frame_ms,
            trace_ms=rounds.trace_ms,
            predicted_trace_ms=sum(metrics[i].predicted_ms for i in selected if i in metrics),
            rays=rounds.rays,
            visible=[elements[i].path for i in visible_ids],
            selected=[elements[i].path for i in selected],
            metrics={elements[i].path: m for i, m in metrics.items()},
            passes=passes,
            budget_ms=frame_budget_ms,
            expected_trace_ms=float(rounds.note.expected_trace_ms) if selected else 0.0,
            budget_use=budget_use,
            untraced_reason=untraced_reason if opts.mode == "hybrid" else None,
            calibration=calibration,
            densities={elements[e].path: d for e, d in rounds.densities.items()
                       if d != opts.trace_density},  # fmt: skip
            pixel_kinds=kind_counts(step.pixel_kind),  # after frame_ms: not in the frame time
        )
        return FrameOutput(
            image, alpha, gb, step.traced_mask, stats, prep.motion.camera, step.pixel_kind,
            prep.motion,
        )

    def _moved_elements(self, prep: PreparedFrame) -> np.ndarray:
        """(k,) int64 ids of the elements that moved or deformed since the previous
        frame (``MotionTracker``'s vertices): their reflections keep no history."""
        vertices = prep.motion.vertices
        if vertices is None or not len(vertices.tri_rows):
            return np.zeros(0, np.int64)
        return np.unique(self.scene.geometry.tri_element[vertices.tri_rows]).astype(np.int64)

    def _previous_time(self, time_code: float) -> float | None:
        """The frame motion vectors start from (``engine/motion.py``): the one before
        ``time_code`` in the plan (None for the first planned frame); for a frame outside
        the plan, the last frame prepared (None before any)."""
        k = self._planned_index.get(float(time_code))
        if k is None:
            return self._last_time
        return self._planned[k - 1] if k > 0 else None

    def _motion_field(self, gb: GBuffer, camera: CameraFrame, previous: float | None,
                      time_code: float, moved) -> MotionField:  # fmt: skip
        """The frame's ``MotionField``: its G-buffer, its camera and the previous frame's
        (None without one), the vertices that moved since (``MotionTracker.advance``)."""
        height, width = gb.shape
        current = FrameCamera.of(time_code, camera, width, height)
        if previous is None:
            return MotionField(gb, current)
        before = FrameCamera.of(previous, self.stage_scene.camera(previous), width, height)
        return MotionField(gb, current, before, moved)

    def _frame_budget_ms(
        self, prep: PreparedFrame, policy: SelectionPolicy, opts: RenderOptions
    ) -> float | None:
        """This frame's time budget T (ms), None when not time-budgeted: ``budget_ms``;
        with ``target_fps``, the period 1000 / F less this frame's raster and shading
        (``prep.prepare_ms``), the previous frame's selection and the margin, >= 0."""
        if opts.mode == "rt":
            return None
        if opts.target_fps is not None:
            return target_fps_budget_ms(
                opts.target_fps, prep.prepare_ms, self._select_ms.get(id(policy), 0.0)
            )
        return opts.budget_ms

    def _screen_boxes(self, gb: GBuffer) -> np.ndarray:
        """(E, 4) pixel bounds (col_min, row_min, col_max, row_max) of every reflector's
        visible pixels, NaN for elements without any (see FrameView.screen_boxes)."""
        n_elements = len(self.scene.elements)
        return frame_pixels.screen_boxes(gb.element_id, self._reflector_ids, n_elements)

    def _check_clipping(
        self, image: np.ndarray, gb: GBuffer, t: float, ev: float, camera_scale: float
    ) -> None:
        """Once per run: the clipping warning of a mostly clipped frame
        (``clipping_warning``; ``camera_scale``, the camera's exposure scale, named when it
        is the cause) into ``StageScene.warnings``, the render's warning path."""
        if self._clipping_warned:
            return
        warning = clipping_warning(
            image, gb, t, ev, self.scene.lights, self.stage_scene.stage,
            camera_scale, self.stage_scene.camera_path,
        )  # fmt: skip
        if warning is not None:
            self._clipping_warned = True
            self.stage_scene.warnings.append(warning)

    def _shade_local(self, gb: GBuffer) -> tuple[np.ndarray, str | None]:
        """Local shading (H, W, 3) of covered pixels and the shadow pass used, if any
        (``lighting.shade_gbuffer``: who answers the shadow queries in this mode; raster
        mode's shadows are the maps' alone, whether or not it built Embree for its
        primary rays)."""
        tracer = None if self.options.mode == "raster" else self._tracer
        return shade_gbuffer(gb, self.scene, self.options.mode, self._rasterizer, tracer)


def target_fps_budget_ms(target_fps: float, prepare_ms: float, select_ms: float) -> float:
    """A frame's trace budget T (ms) under ``target_fps``: the period 1000 / F less the
    measured raster and shading (``prepare_ms``), the selection (``select_ms``, the
    previous frame's: this one's is not known yet) and TARGET_FPS_MARGIN of the period;
    >= 0 (a raster slower than the period leaves nothing to trace), finite."""
    period = 1000.0 / target_fps
    spent = max(float(prepare_ms), 0.0) + max(float(select_ms), 0.0)
    t = period * (1.0 - TARGET_FPS_MARGIN) - spent
    return float(t) if t > 0.0 and np.isfinite(t) else 0.0


def _no_budget_reason(budget: Budget, prep: PreparedFrame, opts, frame_budget_ms) -> str:
    """Why a frame with visible reflectors had no budget at all to trace, with numbers."""
    if budget.rays is not None and budget.rays <= 0:
        return f"budget {budget.rays} rays"
    if opts.target_fps is not None:
        return (
            f"budget 0 ms: target {opts.target_fps:g} fps ({1000.0 / opts.target_fps:.2f} ms)"
            f" less raster and shading {prep.prepare_ms:.2f} ms, the last selection and the"
            f" {TARGET_FPS_MARGIN:.0%} margin leave nothing"
        )
    return f"budget {frame_budget_ms:g} ms"


def _frame_limits(opts: RenderOptions, budget_ms: float | None) -> Budget:
    """The frame's trace budgets: the time budget ``budget_ms`` and the rays budget
    (unbounded in ``rt``)."""
    if opts.mode == "rt":
        return Budget()
    return Budget(ms=budget_ms, rays=opts.budget_rays)


#: The pixel counts of a calibration round after its rays and ms, and the costs the
#: time model prices them at (``select.cost_model.PRICED_KINDS``), by stats.json key.
_ROUND_KINDS = ("filled", "reused", "marched")
_KIND_COSTS = ("fill_rays", "reuse_rays", "screen_space_rays")


def _calibration_stats(done: Calibration, prior: tuple[float, ...]) -> dict:
    """What stats.json reports of the run's calibration: the timed rounds (rays, ms,
    pixels of each kind made without rays), the time model the policy fitted to them
    (fixed ms, ms per ray, each kind's cost in rays), the rays per pixel they cast,
    their wall ms."""
    return {
        "rounds": [{"rays": r, "ms": m, **dict(zip(_ROUND_KINDS, kinds, strict=False))}
                   for r, m, *kinds in done.samples],  # fmt: skip
        "overhead_ms": prior[0],
        "ms_per_ray": prior[1],
        **dict(zip(_KIND_COSTS, prior[2:], strict=True)),
        "rays_per_pixel": done.rays / max(done.pixels, 1),
        "wall_ms": done.wall_ms,
    }


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
