"""HEU1's cost forecasts (ours, docs/heuristic.md "Transition-aware selection"): how a
reflector's pixel count grew over its last frames in view (``pixel_growth``) and, when the
camera path ahead is known, how the screen area of its bounding box changes over the
next frames (``BoxAreas.growth_curves``). ``Heu1Policy`` scales a reflector's predicted
rays by them.
"""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.model.frame import FrameView
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.select.metrics import box_screen_area

#: HEU1's growth forecast (ours, docs/heuristic.md "Transition-aware selection"): a
#: reflector's predicted rays are extrapolated FORECAST_HORIZON frames (1 s at 24 fps)
#: ahead from the growth of its pixel count over the last GROWTH_WINDOW frames it was in
#: view: the geometric mean growth per frame, clamped to [1, GROWTH_MAX] (a shrinking
#: reflector is forecast at its current cost; one glitchy frame cannot forecast infinity).
FORECAST_HORIZON = 24
GROWTH_WINDOW = 4
GROWTH_MAX = 2.0
#: A pixel history counts as a trend when its net change (in log pixels) is at least this
#: share of its total up-and-down travel (1: monotone).
TREND_MIN = 0.5
#: Forecasts (rays) are capped here so that sums of them stay finite.
FORECAST_MAX = 1e300

#: HEU1's lookahead: when the renderer knows the frames to come
#: (``FrameView.upcoming_cameras``: a stage's camera path is known before the render
#: starts), the forecast is instead the largest cost over the next LOOKAHEAD_FRAMES frames,
#: scaled from the current cost by the screen area of the reflector's bounding box
#: (``box_screen_area``; each upcoming camera's areas are computed once and reused by the
#: following frames). Measured on both stages (docs/heuristic.md): 48 frames gave fewer
#: transitions than 24 at the same mean selected count; longer ones shut out reflectors
#: that grow late.
LOOKAHEAD_FRAMES = 48
#: Box areas are computed for LOOKAHEAD_BATCH cameras at a time (one array pass instead of
#: one per frame, whose per-call overhead costs ~0.2 ms of HEU1's selection time a frame);
#: renderers pass UPCOMING_CAMERAS upcoming cameras so that a batch is computed before the
#: window reaches it.
LOOKAHEAD_BATCH = 48
UPCOMING_CAMERAS = LOOKAHEAD_FRAMES + LOOKAHEAD_BATCH


def pixel_growth(history: list[int]) -> float:
    """Per-frame growth of a reflector's pixel count over ``history`` (its counts in its
    last consecutive frames in view, oldest first, at most GROWTH_WINDOW + 1): the
    geometric mean when they show a trend (net change in log pixels at least TREND_MIN of
    the up-and-down travel), else 1 (also with fewer than two frames). Finite, > 0."""
    h = history  # at most GROWTH_WINDOW + 1 counts: scalars
    if len(h) < 2 or h[0] <= 0:
        return 1.0
    logs = [math.log(max(c, 1.0)) for c in h]
    steps = [b - a for a, b in zip(logs, logs[1:], strict=False)]
    travel = sum(abs(d) for d in steps)
    if travel > 0.0 and abs(sum(steps)) < TREND_MIN * travel:
        return 1.0  # up and down more than it moved: no trend to extrapolate
    return float((h[-1] / h[0]) ** (1.0 / (len(h) - 1)))


class BoxAreas:
    """Screen area of every reflector's box per camera of the path, computed once per
    camera (the renderer passes the same CameraFrame objects frame after frame, the
    current one included): id(camera) → (camera, (R,) float64 pixels, in the order of the
    reflector ids). The camera is held so that its id cannot be reused while cached.
    Boxes are those of the frame that computed the batch (animation is not forecast), the
    current camera's too, so growth compares like with like. A cache: no policy memory."""

    def __init__(self) -> None:
        self.areas: dict[int, tuple[CameraFrame, np.ndarray]] = {}
        self.key: tuple = ()  # (width, height, reflector count) of the cache

    def __len__(self) -> int:
        """Cameras cached."""
        return len(self.areas)

    def growth_curves(
        self, view: FrameView, scene: Scene, refl: np.ndarray, ids: np.ndarray
    ) -> dict[int, np.ndarray]:
        """Element id → (W,) float64 screen area of its box at each of the next W <=
        LOOKAHEAD_FRAMES upcoming cameras / its area now (>= 0, finite; 0 where the box is
        off-screen), for the reflectors ``ids`` in view; ``refl`` the scene's reflector
        ids, ascending. {} without upcoming cameras."""
        ahead = view.upcoming_cameras[:LOOKAHEAD_FRAMES]
        if not ahead or len(ids) == 0:
            return {}
        w, h = view.width, view.height
        if self.key != (w, h, len(refl)):
            self.areas, self.key = {}, (w, h, len(refl))
        cached = self.areas
        if any(id(c) not in cached for c in (view.camera, *ahead)):
            # One call for every camera of the view not cached yet, the ones beyond the
            # window included: with the renderer's UPCOMING_CAMERAS that is one call per
            # LOOKAHEAD_BATCH frames.
            path = {id(c): c for c in (view.camera, *view.upcoming_cameras)}
            new = {k: c for k, c in path.items() if k not in cached}
            lo = np.array([scene.elements[i].bounds_min for i in refl], dtype=np.float64)
            hi = np.array([scene.elements[i].bounds_max for i in refl], dtype=np.float64)
            areas = box_screen_area(lo, hi, list(new.values()), w, h)
            cached = {k: v for k, v in cached.items() if k in path}  # drop cameras passed
            cached.update(zip(new, zip(new.values(), areas, strict=True), strict=True))
            self.areas = cached
        cols = np.searchsorted(refl, ids)
        now = cached[id(view.camera)][1][cols]
        later = np.stack([cached[id(c)][1] for c in ahead])[:, cols]  # (W, n)
        # A reflector in view has pixels, so a box area under one pixel is a sliver at
        # the image edge: growth is measured from one pixel, which keeps it finite.
        growth = later / np.maximum(now, 1.0)
        growth = np.clip(np.nan_to_num(growth, nan=0.0, posinf=FORECAST_MAX), 0.0, FORECAST_MAX)
        return {e: growth[:, k] for k, e in enumerate(ids.tolist())}
