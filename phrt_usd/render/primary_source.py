"""Where a frame's G-buffer comes from (``--primary``, ``RenderOptions.primary``).

Two sources fill the same ``GBuffer`` fields (``model.frame``) by the same surface rule:
the raster id pass (``render.raster.gbuffer``) and Embree's primary rays
(``Tracer.primary_gbuffer``, the ``rt`` mode's). Their element ids agree on >= 99.5 %
of covered pixels (they may differ where coplanar surfaces z-fight), so the images
agree within the hybrid-against-rt thresholds whichever runs.

Which is cheaper depends on the machine and the stage. On a GPU, or on llvmpipe with
fewer triangles than pixels, the raster is (the paper stages at 640 x 480: 13 ms
against 27-32 ms). With far more triangles than pixels on a software rasterizer the
id pass pays for every triangle's vertices and setup, and the rays win (a 1M-triangle
ground: 60-80 ms against 32 ms). So ``auto`` measures both once, at the renderer's
load step (``FrameRenderer.warm_up``), and keeps the faster for the whole run.

- ``raster``: the id pass (always, in ``raster`` and ``hybrid`` modes);
- ``rays``: primary rays (an Embree scene is built for them if the mode has none);
- ``auto``: ``raster`` unless the renderer has an Embree scene anyway and its primary
  rays were measured clearly faster (``choose``).

``rt`` mode always traces its primary rays.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from phrt_usd.errors import BadOption

PRIMARY_SOURCES = ("auto", "raster", "rays")
DEFAULT_PRIMARY = "auto"

#: ``auto`` picks the rays only when they take less than 1 / RAYS_MARGIN of the raster's
#: time. The two sources are not bit-identical (coplanar ties, see the module), so a
#: run's pixels should not hinge on a near tie of two noisy timings: a 25 % lead is
#: several times the run-to-run scatter of one G-buffer's time here.
RAYS_MARGIN = 1.25

#: Timed calls of each source in ``choose``, alternating; the fastest of each counts (the
#: minimum is the estimate least disturbed by other processes).
TIMED_CALLS = 2


def check_primary(value: object) -> str:
    """``value`` as one of PRIMARY_SOURCES; BadOption (one line) otherwise."""
    if not isinstance(value, str) or value.lower() not in PRIMARY_SOURCES:
        raise BadOption(f"primary must be one of {', '.join(PRIMARY_SOURCES)}, got {value!r}")
    return value.lower()


def choose(
    raster: Callable[[], object],
    rays: Callable[[], object],
    clock: Callable[[], float] = time.perf_counter,
) -> tuple[str, dict]:
    """("raster" | "rays", timings) for ``auto``: each source called TIMED_CALLS times,
    alternating, on the same camera; rays win if their fastest call is under the
    raster's fastest / RAYS_MARGIN. timings: {"raster_ms": ..., "rays_ms": ...};
    ``clock``: seconds (the tests give their own)."""
    best = {"raster_ms": float("inf"), "rays_ms": float("inf")}
    for _ in range(TIMED_CALLS):
        for key, source in (("raster_ms", raster), ("rays_ms", rays)):
            start = clock()
            source()
            best[key] = min(best[key], (clock() - start) * 1000.0)
    chosen = "rays" if best["rays_ms"] * RAYS_MARGIN < best["raster_ms"] else "raster"
    return chosen, best
