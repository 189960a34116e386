"""Per-frame data passed between the render phases (the contracts between modules).

    G-buffer (engine/raster/gbuffer.py, or engine/trace/tracer.py in ``rt`` mode)
      → candidates and selection rounds (select/policies.py, a ``SelectionPolicy``)
      → reflection tracing of the selected reflectors' pixels (engine/trace/tracer.py)
      → compositing (engine/compositing.py) → images (run/images.py), stats and layer
        (run/selection_layer.py)

Images are (H, W, ...) arrays, row 0 at the top, in linear RGB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from phrt_usd.model.scene import CameraFrame, Scene


@dataclass
class GBuffer:
    """What rasterization (or, in ``rt`` mode, primary rays) found at each pixel.

    element_id  : (H, W) int32, element id, -1 for background
    triangle_id : (H, W) int32, triangle id, -1 for background
    depth       : (H, W) float32, view depth in metres (along the camera's -Z), inf for
                  background
    position    : (H, W, 3) float64 world metres (undefined where element_id == -1)
    normal      : (H, W, 3) float32 world-space unit shading normal, facing the camera
    albedo      : (H, W, 3) float32 linear RGB
    view_dir    : (H, W, 3) float32 world-space unit direction from the eye to the pixel
    """

    element_id: np.ndarray
    triangle_id: np.ndarray
    depth: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    view_dir: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.element_id.shape  # type: ignore[return-value]

    @property
    def covered(self) -> np.ndarray:
        """(H, W) bool, True where something was hit."""
        return self.element_id >= 0


def flat_image(image: np.ndarray, dtype, channels: int) -> np.ndarray:
    """A G-buffer image (H, W[, C]) as contiguous (H*W[, C]) of ``dtype`` (no copy when
    it already is): how the compiled per-pixel passes read it."""
    shape = (-1,) if channels == 1 else (-1, channels)
    return np.ascontiguousarray(image, dtype=dtype).reshape(shape)


@dataclass
class TraceRecord:
    """What tracing one selected reflector's pixels found (one per source reflector).

    rays: rays cast for this source (reflection + refraction + shadow rays, all bounces).
    hits: reflector element id → number of reflection rays that hit it, at any bounce
          (reflectors the secondary rays discovered, including off-screen ones).
    max_reflector_bounces: longest chain of reflector-to-reflector bounces seen
          (0 when no ray hit another reflector), capped at the bounce limit.
    mean_reflector_bounces: mean over this source's pixels of that chain length.
    seconds: wall time attributed to this source (its share of the batch by rays).
    fallback_error: mean over this source's traced pixels of how far the traced frame is
          from the raster fallback it replaced (``compositing.observe_fallback_error``:
          displayed values, in [0, 1]); None until the renderer has composited the round.
    screen_space, reused, filled: of ``pixels``, how many were made each way
          (``model/pixel_kinds.py``: resolved in screen space, reprojected from the
          previous frame, reconstructed from traced neighbours); the rest were traced
          (or, at a reduced density, kept the fallback: an isolated skipped pixel).
    marched: of ``pixels``, how many had their first ray marched through the G-buffer
          (screen space on: every pixel that started rays, resolved or not; the march
          is what the screen-space step costs). The tracer counts these four for every
          reflection round (``Tracer.trace_reflections``); None: not counted (a record
          made elsewhere: a replay, a test).
    """

    source: int
    pixels: int
    rays: int
    hits: dict[int, int] = field(default_factory=dict)
    max_reflector_bounces: int = 0
    mean_reflector_bounces: float = 0.0
    seconds: float = 0.0
    fallback_error: float | None = None
    screen_space: int | None = None
    reused: int | None = None
    filled: int | None = None
    marched: int | None = None


@dataclass
class ReflectionResult:
    """Result of tracing the pixels of a batch of selected reflectors.

    pixel_index : (n,) int64 flat pixel indices (row * W + col) that were traced
    radiance    : (n, 3) float32 linear RGB reflected (and refracted) radiance arriving
                  at those pixels, before mixing with the reflector's F
    records     : one TraceRecord per source reflector in the batch
    rays        : total rays cast (all kinds)
    seconds     : wall time of the whole batch
    kinds       : (n,) uint8 how each of those pixels was made (``model/pixel_kinds.py``:
                  traced, filled, ...), None when every one was traced
    hit_distance : (n,) float32 metres from each pixel's surface to what its reflection
                  ray hit first (+inf: it left the scene; filled pixels: the fill's
                  estimate, ``engine/trace/sparse_pixels.py``), None when not known
    """

    pixel_index: np.ndarray
    radiance: np.ndarray
    records: list[TraceRecord]
    rays: int
    seconds: float
    kinds: np.ndarray | None = None
    hit_distance: np.ndarray | None = None


@dataclass
class FrameView:
    """What a selection policy sees of a frame before tracing.

    pixel_counts: (E,) int64 pixels per element id in the G-buffer (A * W * H).
    screen_boxes: (E, 4) float64 pixel bounds (col_min, row_min, col_max, row_max) of
        each reflector's visible pixels, NaN where it has none; None if not computed.
    upcoming_cameras: the cameras of the next frames of the render, in order (at most
        ``select.heu1_forecast.UPCOMING_CAMERAS``; empty when the renderer does not know them, e.g.
        for the last frame or a single-frame render). A stage's camera path is known in
        advance, so HEU1 can forecast a reflector's cost from it.
    trace_density: the render's trace density (``--trace-density``); only at "full" may
        a policy trace some reflectors more coarsely (HEU1's density steps).
    """

    time: float
    camera: CameraFrame
    width: int
    height: int
    pixel_counts: np.ndarray
    screen_boxes: np.ndarray | None = None
    upcoming_cameras: tuple[CameraFrame, ...] = ()
    trace_density: str = "full"


@dataclass
class Budget:
    """Remaining trace budget of the current frame. ``None`` fields are unbounded.

    ms: wall-clock milliseconds left for tracing (``--budget-ms``, or what
        ``--target-fps`` leaves of the frame period);
    rays: rays left (``--budget-rays``, deterministic on every machine).
    """

    ms: float | None = None
    rays: int | None = None


@dataclass
class ReflectorMetrics:
    """The heuristic's figures for one candidate in one frame (paper, Table 1)."""

    V: float
    C: float
    R: float
    Q: float
    S: bool
    selected: bool
    visible: bool
    predicted_rays: float = 0.0
    predicted_ms: float = 0.0
    #: Share of the reflector's pixels that started rays, at the density it was traced
    #: at (1 full, 0.5 half, 0.25 quarter, 0.0625 sixteenth; 1 under 64 pixels: traced
    #: whole); NaN when it was not traced.
    trace_density: float = math.nan


@dataclass
class FrameNote:
    """A policy's note on the frame it last finished (``SelectionPolicy.last_frame_note``).

    expected_trace_ms: the central estimate of the trace time made before each round
        (no safety factors), summed over the frame's rounds;
    untraced_reason: why nothing was traced while reflectors were visible (with numbers),
        else None.
    """

    expected_trace_ms: float = 0.0
    untraced_reason: str | None = None


class SelectionPolicy(Protocol):
    """How reflectors are chosen per frame; implemented in ``phrt_usd.select.policies``.
    This is everything the round loop (``phrt_usd.select.rounds.run_rounds``, which the
    renderer and the replay tool run) reads of a policy. Per frame::

        if policy.needs_calibration:                # time-budgeted, reflectors visible
            policy.calibrate(samples, rays, pixels, records)
        policy.begin_frame(view, scene)
        while (ids := policy.next_round(budget)):   # budget shrinks after each round
            result = tracer.trace(...ids..., policy.round_densities(ids))
            policy.record(result.records, result.seconds)
        metrics = policy.end_frame()                # element id → ReflectorMetrics
        policy.last_frame_note                      # FrameNote
    """

    #: True when ``record`` reads ``TraceRecord.fallback_error`` (the renderer fills it
    #: only then: it costs a pass over the traced pixels).
    observes_fallback_error: bool
    #: False when what the policy traces does not depend on the budget (``all``,
    #: ``none``, ``list``): the renderer reports no budget use for it.
    follows_budget: bool
    #: Of the last finished frame (``end_frame``).
    last_frame_note: FrameNote

    @property
    def needs_calibration(self) -> bool:
        """True while the policy's trace-time model has not been calibrated."""
        ...

    def calibrate(
        self, samples: list[tuple], rays: int, pixels: int, records: list[TraceRecord],
    ) -> tuple[float, ...]:  # fmt: skip
        """Timed calibration rounds ``(rays, ms, filled, reused, marched pixels)``,
        ``rays`` over the ``pixels`` that started rays in all, and per reflector traced
        at full density its pixels, rays and marched pixels (``records``); returns the
        trace-time model fitted to them: (fixed ms, ms per ray, rays per filled, reused
        and marched pixel)."""
        ...

    def begin_frame(self, view: FrameView, scene: Scene) -> None: ...

    def next_round(self, budget: Budget) -> list[int]: ...

    def round_densities(self, ids: list[int]) -> list[str]: ...

    def record(self, records: list[TraceRecord], seconds: float) -> None: ...

    def end_frame(self) -> dict[int, ReflectorMetrics]: ...


@dataclass(frozen=True)
class FrameCamera:
    """The camera a frame was rendered with, as the matrices that reproject it.

    time : the frame's time code
    camera_from_world : (4, 4) float64 world-to-camera, world metres → camera space
        (metres, USD's / OpenGL's: looks down -Z, +Y up), column vectors:
        ``p_cam = camera_from_world @ (x, y, z, 1)``
    projection : (4, 4) float64 OpenGL clip-from-camera of the frame's image
        (``CameraFrame.projection``: the image window at the frame's width x height,
        aperture offsets and conform policy included; the camera's clipping range). NDC
        (x, y) is pixel (col, row) = ((x + 1) W / 2, (1 - y) H / 2), row 0 at the top;
        the G-buffer's ``depth`` is -z of camera space.
    """

    time: float
    camera_from_world: np.ndarray
    projection: np.ndarray

    @classmethod
    def of(cls, time: float, camera: CameraFrame, width: int, height: int) -> FrameCamera:
        """The matrices of ``camera`` for a ``width`` x ``height`` frame at ``time``."""
        return cls(float(time), camera.camera_from_world, camera.projection(width, height))

    @property
    def clip_from_world(self) -> np.ndarray:
        """(4, 4) float64 world → clip space: ``projection @ camera_from_world``."""
        return self.projection @ self.camera_from_world


@dataclass
class FrameStats:
    """Everything recorded about one rendered frame (stats.json row, selection layer)."""

    time: float
    phase_ms: dict[str, float]  # e.g. {"read": .., "gbuffer": .., "shade": .., "trace": ..}
    frame_ms: float
    trace_ms: float
    predicted_trace_ms: float
    rays: int
    visible: list[str]  # reflector prim paths visible in the frame
    selected: list[str]  # reflector prim paths traced in the frame
    metrics: dict[str, ReflectorMetrics]  # prim path → figures (candidates only)
    passes: list[str]  # render passes that ran, e.g. ["gbuffer", "shadow_map", "trace"]
    #: The frame's trace budget T in ms when time-budgeted (``--budget-ms``, or what
    #: ``--target-fps`` left of the frame period), else None.
    budget_ms: float | None = None
    #: Central estimate of the trace time made before each round (no safety factors),
    #: summed over the frame's rounds: set against ``trace_ms`` for the cost model's error.
    expected_trace_ms: float = 0.0
    #: trace_ms / budget_ms in a time-budgeted frame with visible reflectors, else None.
    budget_use: float | None = None
    #: Why nothing was traced in a hybrid frame with visible reflectors (with numbers).
    untraced_reason: str | None = None
    #: The run's trace-time calibration, on the frame that ran it: rays, ms of each timed
    #: round, the fitted fixed ms and ms per ray, its wall ms (not in frame_ms).
    calibration: dict | None = None
    #: Selected reflectors traced at another density than the render's (HEU1's density
    #: steps): prim path → one of ``model.trace_density.TRACE_DENSITIES`` but "full".
    densities: dict[str, str] = field(default_factory=dict)
    #: Pixels of each kind (``model/pixel_kinds.py``: "background", "raster",
    #: "screen-space", "traced", "reused", "filled" → count); empty in records written
    #: before it was kept.
    pixel_kinds: dict[str, int] = field(default_factory=dict)
