"""The renderer's tracing step of a frame's selection rounds (``select.rounds.run_rounds``):
``ReflectionRounds``, a round's reflectors traced from the G-buffer (their skipped pixels
reusing the previous frames' reflections, ``engine/reflection_history.py``) and
composited into the frame, timed (the run's trace-time calibration times the same step:
``engine/trace_calibration.py``).
"""

from __future__ import annotations

import time

import numpy as np

from phrt_usd.engine.compositing import apply_traced, observe_fallback_error
from phrt_usd.model.frame import GBuffer, ReflectionResult
from phrt_usd.model.pixel_kinds import raster_kinds
from phrt_usd.select.rounds import TracedRound


class ReflectionRounds:
    """The renderer's tracing step: each round's reflectors traced from the frame's
    G-buffer (``Tracer.trace_reflections``) and their radiance composited into ``image``
    (``apply_traced``), the time of both measured: what the budget is charged.

    image: (H, W, 3) float32 the frame, the raster fallback until traced;
    traced_mask: (H, W) bool the pixels traced (or filled) so far;
    pixel_kind: (H, W) uint8 how each pixel was made so far (``model/pixel_kinds.py``).
    """

    def __init__(
        self,
        tracer,
        gbuffer: GBuffer,
        local: np.ndarray,
        reflectivity: np.ndarray,
        fallback: np.ndarray,
        bounce_limit: int,
        reuse=None,
        screen=None,
    ) -> None:
        self._tracer = tracer
        self._gbuffer = gbuffer
        self._local = local
        self._reflectivity = reflectivity
        self._fallback = fallback
        self._bounce_limit = bounce_limit
        #: The frame's ``reflection_history.FrameReuse`` (None: no reuse): the pattern's
        #: rotation, the history skipped pixels take, and where this frame's is kept.
        self._reuse = reuse
        #: The frame's ``screen_space.ScreenFrame`` (None: every first ray to Embree).
        self._screen = screen
        self.image = fallback.copy()
        self.traced_mask = np.zeros(gbuffer.shape, dtype=bool)
        self.pixel_kind = raster_kinds(gbuffer.covered)
        self._last: ReflectionResult | None = None

    def __call__(self, ids: list[int], densities: list[str]) -> TracedRound:
        t = time.perf_counter()
        result = self._tracer.trace_reflections(
            self._gbuffer, ids, self._bounce_limit, densities, self._reuse, self._screen,
            (self._fallback, self._local, self._reflectivity),
        )
        if self._reuse is not None:
            self._reuse.record(result)
        apply_traced(
            self.image, self._local, self._reflectivity, result, self.traced_mask, self.pixel_kind
        )
        ms = (time.perf_counter() - t) * 1000.0
        self._last = result
        return TracedRound(result.records, result.rays, ms)

    def observe_fallback_error(self) -> None:
        """What the last round changed against the raster fallback, per source, into its
        records (``compositing.observe_fallback_error``; for a policy that learns it)."""
        if self._last is not None:
            observe_fallback_error(self._last, self.image, self._fallback, self._gbuffer.element_id)
