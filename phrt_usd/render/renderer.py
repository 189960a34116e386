"""One frame of the heuristic hybrid renderer, in the three modes.

Per frame (``FrameRenderer.render``):

1. ``set_time``   animated prims re-evaluated; rasterizer / Embree scene updated if moved.
2. ``gbuffer``    raster G-buffer (pyrender) — or, in ``rt`` mode, primary rays (Embree).
3. ``shade``      local shading of every covered pixel (shadow map in raster/hybrid,
                  shadow rays in ``rt``); reflectors get the environment fallback.
4. ``select`` + ``trace``  rounds of: the selection policy picks reflectors that fit the
                  remaining budget, the tracer traces their pixels, the policy learns
                  from what the rays hit. Skipped when no reflector is visible or known.
5. ``composite``  traced radiance replaces the fallback in the traced pixels.

Modes: ``raster`` (no tracing), ``hybrid`` (the heuristic chooses), ``rt`` (Embree for
everything, all reflectors traced: the reference).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from phrt_usd.errors import BadOption
from phrt_usd.model.frame import (
    Budget,
    FrameStats,
    FrameView,
    GBuffer,
    ReflectorMetrics,
    SelectionPolicy,
)
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.render.compositing import (
    apply_traced,
    base_image,
    element_reflectivity,
    pixel_reflectivity,
)
from phrt_usd.render.lighting import shade_gbuffer
from phrt_usd.select.policies import UPCOMING_CAMERAS, make_policy
from phrt_usd.threads import DEFAULT_THREADS
from phrt_usd.usd.schema import (
    DEFAULT_BOUNCE_LIMIT,
    DEFAULT_BUDGET_MS,
    DEFAULT_HEURISTIC,
    DEFAULT_MODE,
    DEFAULT_RESOLUTION,
    DEFAULT_SELECTION_WEIGHT,
    HEURISTICS,
    MAX_BOUNCE_LIMIT,
    MODES,
)
from phrt_usd.usd.stage import StageScene

#: Largest frame side in pixels (OpenGL's usual maximum framebuffer size).
MAX_RESOLUTION_SIDE = 16384
#: Largest frame in pixels: the G-buffer, shading planes and images take ~100 bytes a
#: pixel, so 2**26 pixels (e.g. 8192x8192) already need several GB.
MAX_RESOLUTION_PIXELS = 2**26
#: Largest --budget-rays: far above any frame's need (a 2**26-pixel frame at 16 bounces
#: casts ~1e9 rays) and small enough for every int64 figure and USD's integer metadata.
MAX_BUDGET_RAYS = 10**12


@dataclass
class RenderOptions:
    """How to render. ``None`` budgets are unbounded. Defaults are the schema's
    (``PhrtRenderSettingsAPI`` fallbacks in ``usd.schema``), declared there once."""

    mode: str = DEFAULT_MODE
    heuristic: str = DEFAULT_HEURISTIC
    width: int = DEFAULT_RESOLUTION[0]
    height: int = DEFAULT_RESOLUTION[1]
    budget_ms: float | None = DEFAULT_BUDGET_MS
    budget_rays: int | None = None
    bounce_limit: int = DEFAULT_BOUNCE_LIMIT
    selection_weight: float = DEFAULT_SELECTION_WEIGHT
    threads: int = DEFAULT_THREADS  # the tracer's pool (phrt_usd.threads)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise BadOption(f"unknown mode {self.mode!r}; expected one of {', '.join(MODES)}")
        if self.heuristic not in HEURISTICS:
            raise BadOption(
                f"unknown heuristic {self.heuristic!r}; expected one of {', '.join(HEURISTICS)}"
            )
        side, pixels = MAX_RESOLUTION_SIDE, MAX_RESOLUTION_PIXELS
        if not (1 <= self.width <= side and 1 <= self.height <= side):
            raise BadOption(f"resolution {self.width}x{self.height} out of range 1..{side}")
        if self.width * self.height > pixels:
            raise BadOption(
                f"resolution {self.width}x{self.height}: more than {pixels} pixels a frame"
            )
        if self.budget_ms is not None and not (self.budget_ms >= 0 and np.isfinite(self.budget_ms)):
            raise BadOption(f"--budget-ms must be a finite number >= 0, got {self.budget_ms}")
        if self.budget_rays is not None and not 0 <= self.budget_rays <= MAX_BUDGET_RAYS:
            raise BadOption(
                f"--budget-rays must be in 0..{MAX_BUDGET_RAYS}, got {self.budget_rays}"
            )
        if not 0 <= self.bounce_limit <= MAX_BOUNCE_LIMIT:
            raise BadOption(
                f"bounce limit must be in 0..{MAX_BOUNCE_LIMIT}, got {self.bounce_limit}"
            )
        if not (self.selection_weight >= 0 and np.isfinite(self.selection_weight)):
            raise BadOption(f"selection weight I must be finite and >= 0: {self.selection_weight}")


@dataclass
class PreparedFrame:
    """A frame after G-buffer and local shading, before any tracing.

    local: (H, W, 3) float32 local shading; reflectivity: (H, W) float32 F per pixel;
    image: (H, W, 3) float32 the raster frame (environment fallback in reflectors);
    pixel_counts: (E,) int64 pixels per element; screen_boxes: (E, 4) see FrameView.
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


@dataclass
class FrameOutput:
    """A rendered frame: beauty (H, W, 3) float32 linear RGB, alpha (H, W) float32,
    the G-buffer, traced_mask (H, W) bool and the frame's stats."""

    beauty: np.ndarray
    alpha: np.ndarray
    gbuffer: GBuffer
    traced_mask: np.ndarray
    stats: FrameStats


class FrameRenderer:
    """Renders frames of one stage with fixed options; keeps per-run state (the
    rasterizer's uploaded geometry, the Embree scene, the policy's memory)."""

    def __init__(self, stage_scene: StageScene, options: RenderOptions):
        self.stage_scene = stage_scene
        self.options = options
        scene = stage_scene.scene
        self._reflector_ids = scene.reflector_ids
        self._element_f = element_reflectivity(scene)  # F per element: fixed for a run
        self._animated = any(e.animated for e in scene.elements)
        self._geometry_time: float | None = None
        self._rasterizer = None
        self._tracer = None
        if options.mode != "rt":
            from phrt_usd.render.raster.rasterizer import Rasterizer

            self._rasterizer = Rasterizer(scene, options.width, options.height)
        # Embree is only needed to trace (reflectors in hybrid, everything in rt).
        if options.mode == "rt" or (
            options.mode == "hybrid" and len(self._reflector_ids) and options.heuristic != "none"
        ):
            from phrt_usd.render.trace.tracer import Tracer

            self._tracer = Tracer(scene, threads=options.threads)
        #: The frames this renderer will render, in order (``plan``), and the cameras of
        #: those looked up so far, by time code.
        self._planned: list[float] = []
        self._planned_index: dict[float, int] = {}
        self._cameras: dict[float, CameraFrame] = {}
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
        known before the render starts). Without a plan, views have no upcoming cameras."""
        self._planned = [float(t) for t in times]
        self._planned_index = {}
        for k, t in enumerate(self._planned):
            self._planned_index.setdefault(t, k)
        self._cameras = {}

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
        moved = self.stage_scene.set_time(time_code)
        # Several renderers may share one StageScene: re-upload whenever this renderer's
        # geometry is from another time and something in the scene is animated.
        if moved or (self._animated and self._geometry_time != time_code):
            self._geometry_time = time_code
            if self._rasterizer is not None:
                self._rasterizer.update_geometry(self.scene)
            if self._tracer is not None:
                self._tracer.update_geometry(self.scene)
        camera, upcoming = self._path_cameras(time_code)
        phase["set_time"] = _ms(t)

        scene = self.scene
        t = time.perf_counter()
        if opts.mode == "rt":
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
        )

    def finish(
        self, prep: PreparedFrame, policy: SelectionPolicy, opts: RenderOptions
    ) -> FrameOutput:
        """Phases 4–5: selection rounds and tracing within ``opts``' budget, compositing.

        Leaves ``prep`` untouched, so several policies / budgets can finish one frame.
        """
        scene = self.scene
        t_finish = time.perf_counter()
        image = prep.image.copy()
        phase = dict(prep.phase_ms)
        passes = list(prep.passes)
        pixel_counts = prep.pixel_counts
        gb = prep.gbuffer
        visible_ids = [int(i) for i in self._reflector_ids if pixel_counts[i] > 0]
        traced_mask = np.zeros(gb.shape, dtype=bool)
        trace_ms = 0.0
        select_ms = 0.0
        rays = 0
        metrics: dict[int, ReflectorMetrics] = {}
        selected: list[int] = []
        if self._tracer is not None and opts.mode != "raster":
            view = FrameView(
                prep.time,
                prep.camera,
                opts.width,
                opts.height,
                pixel_counts,
                prep.screen_boxes,
                prep.upcoming_cameras,
            )
            t = time.perf_counter()
            policy.begin_frame(view, scene)
            select_ms += _ms(t)
            while True:
                budget = _remaining(opts, trace_ms, rays)
                if (budget.ms is not None and budget.ms <= 0) or (
                    budget.rays is not None and budget.rays <= 0
                ):
                    break
                t = time.perf_counter()
                ids = policy.next_round(budget)
                select_ms += _ms(t)
                # Only reflectors with pixels in this frame are traced from the G-buffer.
                ids = [i for i in ids if pixel_counts[i] > 0 and i not in selected]
                if not ids:
                    break
                t = time.perf_counter()
                result = self._tracer.trace_reflections(gb, ids, opts.bounce_limit)
                apply_traced(image, prep.local, prep.reflectivity, result, traced_mask)
                round_ms = _ms(t)
                trace_ms += round_ms
                rays += result.rays
                selected.extend(ids)
                t = time.perf_counter()
                # The policy learns the time the budget is charged (trace + composite).
                policy.record(result.records, round_ms / 1000.0)
                select_ms += _ms(t)
            t = time.perf_counter()
            metrics = policy.end_frame()
            select_ms += _ms(t)
            if selected:
                passes.append("trace")
                if scene.materials.has_transmission:
                    passes.append("refraction")
        phase["select"] = select_ms
        phase["trace"] = trace_ms

        alpha = gb.covered.astype(np.float32)
        frame_ms = prep.prepare_ms + _ms(t_finish)
        elements = scene.elements
        stats = FrameStats(
            time=prep.time,
            phase_ms=phase,
            frame_ms=frame_ms,
            trace_ms=trace_ms,
            predicted_trace_ms=sum(metrics[i].predicted_ms for i in selected if i in metrics),
            rays=rays,
            visible=[elements[i].path for i in visible_ids],
            selected=[elements[i].path for i in selected],
            metrics={elements[i].path: m for i, m in metrics.items()},
            passes=passes,
        )
        return FrameOutput(image, alpha, gb, traced_mask, stats)

    def _screen_boxes(self, gb: GBuffer) -> np.ndarray:
        """(E, 4) pixel bounds (col_min, row_min, col_max, row_max) of every reflector's
        visible pixels, NaN for elements without any (see FrameView.screen_boxes)."""
        n = len(self.scene.elements)
        boxes = np.full((n, 4), np.nan)
        refl = np.asarray(self._reflector_ids, dtype=np.int64)
        if len(refl) == 0:
            return boxes
        # Reflector index per element id (index -1, the background, maps to -1).
        index = np.full(n + 1, -1, dtype=np.int64)
        index[refl] = np.arange(len(refl))
        k = index[gb.element_id]
        rows, cols = np.nonzero(k >= 0)
        if len(rows) == 0:
            return boxes
        k = k[rows, cols]
        h, w = gb.shape
        # (H, R) / (W, R) occupancy: a reflector's first and last occupied row and
        # column are its box (argmax finds the first True).
        in_row = np.zeros((h, len(refl)), dtype=bool)
        in_row[rows, k] = True
        in_col = np.zeros((w, len(refl)), dtype=bool)
        in_col[cols, k] = True
        seen = in_row.any(axis=0)
        boxes[refl[seen]] = np.stack(
            [
                in_col.argmax(axis=0),
                in_row.argmax(axis=0),
                w - 1 - in_col[::-1].argmax(axis=0),
                h - 1 - in_row[::-1].argmax(axis=0),
            ],
            axis=1,
        )[seen]
        return boxes

    def _shade_local(self, gb: GBuffer) -> tuple[np.ndarray, str | None]:
        """Local shading (H, W, 3) of covered pixels and the shadow pass used, if any
        (``lighting.shade_gbuffer``: who answers the shadow queries in this mode)."""
        return shade_gbuffer(gb, self.scene, self.options.mode, self._rasterizer, self._tracer)


def _remaining(opts: RenderOptions, trace_ms: float, rays: int) -> Budget:
    """Budget left after ``trace_ms`` and ``rays`` were spent (unbounded in ``rt``)."""
    if opts.mode == "rt":
        return Budget()
    return Budget(
        ms=None if opts.budget_ms is None else opts.budget_ms - trace_ms,
        rays=None if opts.budget_rays is None else opts.budget_rays - rays,
    )


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
