"""The renderer's side of a frame's selection rounds (``select.rounds.run_rounds``): the
tracing step (``ReflectionRounds``: a round's reflectors traced from the G-buffer and
composited into the frame) and the run's trace-time calibration (``calibrate_tracer``:
timed rounds over the first time-budgeted frame's own reflector pixels).
"""

from __future__ import annotations

import time

import numpy as np

from phrt_usd.engine.compositing import apply_traced, observe_fallback_error
from phrt_usd.model.frame import GBuffer, ReflectionResult
from phrt_usd.model.pixel_kinds import raster_kinds
from phrt_usd.select.rounds import Calibration, TracedRound

#: The trace-time calibration (``calibrate_tracer``): timed rounds over this many
#: reflector pixels of the first frame with visible reflectors, sampled with a fixed seed
#: (CALIBRATION_SEED). Two sizes separate a round's fixed cost from its per-ray cost; each
#: size is timed CALIBRATION_REPEATS times after one warm-up round and its fastest time
#: kept (the others carry the noise of the shared machine). A few thousand rays: a few
#: ms, once.
CALIBRATION_PIXELS = (64, 512)
CALIBRATION_REPEATS = 3
CALIBRATION_SEED = 0
#: The GBuffer's per-pixel arrays, in its field order (the calibration samples them).
GBUFFER_FIELDS = ("element_id", "triangle_id", "depth", "position", "normal", "albedo", "view_dir")


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
    ) -> None:
        self._tracer = tracer
        self._gbuffer = gbuffer
        self._local = local
        self._reflectivity = reflectivity
        self._fallback = fallback
        self._bounce_limit = bounce_limit
        self.image = fallback.copy()
        self.traced_mask = np.zeros(gbuffer.shape, dtype=bool)
        self.pixel_kind = raster_kinds(gbuffer.covered)
        self._last: ReflectionResult | None = None

    def __call__(self, ids: list[int], densities: list[str]) -> TracedRound:
        t = time.perf_counter()
        result = self._tracer.trace_reflections(self._gbuffer, ids, self._bounce_limit, densities)
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


def calibrate_tracer(
    tracer, gb: GBuffer, visible_ids: list[int], bounce_limit: int, seed: int
) -> Calibration:
    """Time ``tracer`` on this frame's own reflector pixels (of ``visible_ids``): rounds of
    CALIBRATION_PIXELS pixels sampled with ``seed``, each size CALIBRATION_REPEATS times
    after one warm-up round, its fastest time kept. The pixels are taken out of the
    G-buffer into a (1, n) one, so the rounds go through the real
    ``Tracer.trace_reflections`` and compositing."""
    start = time.perf_counter()
    flat = np.flatnonzero(np.isin(gb.element_id.reshape(-1), visible_ids))
    rng = np.random.default_rng(seed)
    total_rays = total_pixels = 0
    sizes = (CALIBRATION_PIXELS[0],) + CALIBRATION_PIXELS * CALIBRATION_REPEATS
    best: dict[int, tuple[int, float]] = {}
    for k, n in enumerate(sizes):
        pick = np.sort(rng.choice(flat, size=n, replace=len(flat) < n))
        sub = GBuffer(*(getattr(gb, f).reshape(-1, *getattr(gb, f).shape[2:])[pick][None]
                        for f in GBUFFER_FIELDS))  # fmt: skip
        ids = sorted(set(sub.element_id.reshape(-1).tolist()))
        image = np.zeros((1, n, 3), np.float32)
        t = time.perf_counter()
        result = tracer.trace_reflections(sub, ids, bounce_limit)
        apply_traced(image, image.copy(), np.ones((1, n), np.float32), result,
                     np.zeros((1, n), bool))  # fmt: skip
        ms = (time.perf_counter() - t) * 1000.0
        if k == 0:
            continue  # the warm-up round: caches, the pool's threads
        total_rays += result.rays
        total_pixels += n
        if n not in best or ms < best[n][1]:
            best[n] = (int(result.rays), ms)
    wall_ms = (time.perf_counter() - start) * 1000.0
    return Calibration(list(best.values()), total_rays, total_pixels, wall_ms)
