"""Which reflectors to ray-trace each frame: the paper's HEU1, the HEU2 baseline, and the
fixed policies ``all``, ``none`` and ``list`` (``phrt_usd.model.frame.SelectionPolicy``).

Metrics (paper, Table 1; every interpretation is spelled out in ``docs/heuristic.md``):

* ``A`` visible projected area: pixels of the element in the G-buffer / (W * H), in [0, 1].
* ``P`` centrality of the bounding-box centre: ``1 - max(|ndc_x|, |ndc_y|)`` clamped to
  [0, 1] (1 at the view centre, 0 on or outside the image border, 0 behind the camera).
* ``D`` Euclidean distance from the eye to the bounding-box centre, metres, >= ``D_MIN``.
* ``V = A * P / D`` (1 / metre).
* ``Q = 1 + reflector-to-reflector bounces`` of the reflector's rays, learned from its
  ``TraceRecord``s, remembered across frames, in [1, bounce limit].
* ``O`` for a reflector ``i`` reflecting ``j``: 1 while |c_i - c_j| <= D_i, then +1 per
  doubling: ``1 + floor(log2(|c_i - c_j| / D_i))``.
* ``C_i = V_i * Q_i + sum_j V_j' * Q_j / O_ij`` over the reflectors ``j`` that ``i`` was
  seen to reflect, with ``V_j' = max(V_j, V_i * f_ij)`` (``f_ij``: fraction of i's pixels
  whose rays hit j), so a reflector seen only through ``i`` still adds to ``C_i``.
* ``R = (S * I + V) * K``.

Budget: ``C`` has no unit. What the budget is checked against is a calibrated prediction
of the rays tracing a candidate costs (``pixels * rays per pixel * RAYS_SAFETY``) and of
the time those rays take (``TraceTimeModel``). Both are learned online from the renderer's
``record`` calls.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import Budget, FrameView, ReflectorMetrics, SelectionPolicy, TraceRecord
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.select.selection_graph import Node, SelectionGraph

#: Smallest camera distance D in metres. D is a bounding-box-centre distance, so it can be
#: ~0 when the eye is inside a large reflector's box; V = A*P/D then stays <= 1 / D_MIN.
#: A micrometre is below any sensible camera near plane, so it never changes a real ranking.
D_MIN = 1e-6

#: K (phrt:priority) and I (phrt:selectionWeight) are clipped to [0, WEIGHT_MAX] (NaN → 0)
#: so R = (S*I + V)*K <= ~1e24 stays finite in float64 whatever the stage says.
WEIGHT_MAX = 1e12

#: Predicted rays are multiplied by this: rays per pixel learned in earlier frames
#: under-predict when a reflector starts reflecting more reflectors (deeper bounces).
RAYS_SAFETY = 1.1

#: Predicted trace milliseconds are multiplied by a time safety factor: wall time jitters
#: from round to round (caches, the OS, other processes on the two cores). The factor is
#: the JITTER_QUANTILE quantile of measured / modelled round time, tracked online, and
#: never below TIME_SAFETY_MIN: on a quiet machine it settles near 1.1 (with RAYS_SAFETY
#: the selection then plans to use ~1 / 1.2 = 83 % of the budget); on a loaded machine
#: it grows so that rounds still end within the budget.
TIME_SAFETY_MIN = 1.05
TIME_SAFETY_INITIAL = 1.1
TIME_SAFETY_MAX = 10.0
JITTER_QUANTILE = 0.97
#: Step of the online quantile tracker (ratio units): +STEP*q on a round slower than
#: the factor predicts, -STEP*(1-q) otherwise, so ~3 % of rounds exceed it.
JITTER_STEP = 0.2
#: When the time budget lets nothing at all be traced in a frame, the safety factor is
#: multiplied by this. Otherwise a noisy spell could raise it so far that nothing is ever
#: traced again, and without rounds there is nothing to learn from: the factor creeps back
#: until a round fits, and that round's measurement then corrects it.
STARVED_RELAX = 0.97

#: Before anything was measured: 0.004 ms per ray (250k rays/s, slower than embreex plus
#: numpy shading on one laptop core) and 0.5 ms fixed cost per tracing round.
INITIAL_MS_PER_RAY = 0.004
INITIAL_ROUND_MS = 0.5

#: HEU1's hysteresis in cost (ours; the paper's I is hysteresis in relevance): a reflector
#: not selected in the previous frame joins only if this fraction of the round's budget
#: stays free after it. Predicted costs jitter by a few per cent from frame to frame;
#: without a margin, a selection whose total hovers at the budget drops one reflector
#: and takes it back on alternate frames.
ADMISSION_MARGIN = 0.1

#: HEU1's growth forecast (ours, docs/heuristic.md "Transition-aware selection"): a
#: reflector's predicted rays are extrapolated FORECAST_HORIZON frames (1 s at 24 fps)
#: ahead from the growth of its pixel count over the last GROWTH_WINDOW frames it was in
#: view: the geometric mean growth per frame, clamped to [1, GROWTH_MAX] (a shrinking
#: reflector is forecast at its current cost; one glitchy frame cannot forecast infinity).
#: When the renderer knows the frames to come (``FrameView.upcoming_cameras``: a stage's
#: camera path is known before the render starts), the forecast is instead the largest
#: cost over the next LOOKAHEAD_FRAMES frames, scaled from the current cost by the screen
#: area of the reflector's bounding box (``box_screen_area``; each upcoming camera's
#: areas are computed once and reused by the following frames). Measured on both stages
#: (docs/heuristic.md): 48 frames gave fewer transitions than 24 at the same mean selected
#: count; longer ones shut out reflectors that grow late.
LOOKAHEAD_FRAMES = 48
#: Box areas are computed for LOOKAHEAD_BATCH cameras at a time (one array pass instead of
#: one per frame: the per-call overhead was ~0.2 ms of HEU1's selection time per frame);
#: renderers pass UPCOMING_CAMERAS upcoming cameras so that a batch is computed before the
#: window reaches it.
LOOKAHEAD_BATCH = 48
UPCOMING_CAMERAS = LOOKAHEAD_FRAMES + LOOKAHEAD_BATCH
FORECAST_HORIZON = 24
GROWTH_WINDOW = 4
GROWTH_MAX = 2.0
#: A pixel history counts as a trend when its net change (in log pixels) is at least this
#: share of its total up-and-down travel (1: monotone).
TREND_MIN = 0.5
#: Forecasts are capped here so that sums of them stay finite.
FORECAST_MAX = 1e300

#: Lower bound of the learned ms per ray (1e10 rays/s): keeps ms → rays finite.
MIN_MS_PER_RAY = 1e-7

#: Weight of older rounds in the time model (exponential forgetting per round).
TIME_MODEL_DECAY = 0.9

#: Weight of the newest observation in a reflector's rays-per-pixel average.
RAYS_PER_PIXEL_ALPHA = 0.5

#: Fewest rays per traced pixel: the reflection ray itself.
MIN_RAYS_PER_PIXEL = 1.0


# --------------------------------------------------------------------------- metrics


def visible_area(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """A: (n,) pixel counts → (n,) float64 fraction of the image, in [0, 1]."""
    total = max(int(width) * int(height), 1)
    return np.clip(np.asarray(pixels, dtype=np.float64) / total, 0.0, 1.0)


def centrality(centers: np.ndarray, camera: CameraFrame, width: int, height: int) -> np.ndarray:
    """P: (n, 3) world-metre points → (n,) float64 in [0, 1].

    ``1 - max(|ndc_x|, |ndc_y|)``: 1 at the view centre, falling linearly to 0 on the
    image border (a square falloff matching the rectangular view plane), 0 outside the
    image and behind the camera.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if len(centers) == 0:
        return np.zeros(0)
    with np.errstate(over="ignore", invalid="ignore"):
        projected = camera.project(centers, width, height)
        ndc_x = projected[:, 0] / width * 2.0 - 1.0
        ndc_y = 1.0 - projected[:, 1] / height * 2.0
        p = 1.0 - np.maximum(np.abs(ndc_x), np.abs(ndc_y))
    p = np.where(projected[:, 2] > 0.0, p, 0.0)  # behind the eye: not in view
    # Points on the eye plane project to +-inf (or NaN for 0/0): they are not in view.
    return np.clip(np.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)


def screen_centrality(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """P from screen-space boxes: (n, 4) pixel (col_min, row_min, col_max, row_max) →
    (n,) float64 in [0, 1], the falloff of ``centrality`` at the box centre (pixel
    centres at +0.5)."""
    boxes = np.nan_to_num(np.asarray(boxes, dtype=np.float64).reshape(-1, 4), nan=-1e9)
    cx = 0.5 * (boxes[:, 0] + boxes[:, 2]) + 0.5
    cy = 0.5 * (boxes[:, 1] + boxes[:, 3]) + 0.5
    ndc_x = cx / max(width, 1) * 2.0 - 1.0
    ndc_y = 1.0 - cy / max(height, 1) * 2.0
    return np.clip(1.0 - np.maximum(np.abs(ndc_x), np.abs(ndc_y)), 0.0, 1.0)


def box_screen_area(
    bounds_min: np.ndarray,
    bounds_max: np.ndarray,
    cameras: Sequence[CameraFrame],
    width: int,
    height: int,
) -> np.ndarray:
    """Pixels covered by the screen rectangle of axis-aligned boxes, clipped to the image,
    for each of several cameras.

    bounds_min, bounds_max: (n, 3) float64 world metres → (len(cameras), n) float64 in
    [0, W * H]. A box wholly behind a camera's eye covers 0; one that reaches from in front
    of the eye to behind it projects to an unbounded rectangle and counts as the whole
    image (the camera is at or inside it). Occlusion is not considered: this bounds what
    the box's contents can cover, and is used for ratios between cameras.
    """
    lo = np.asarray(bounds_min, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(bounds_max, dtype=np.float64).reshape(-1, 3)
    n, m = len(lo), len(cameras)
    if n == 0 or m == 0:
        return np.zeros((m, n))
    # (n * 8, 3) corners: bit k of the corner index picks lo or hi on axis k.
    pick = ((np.arange(8)[:, None] >> np.arange(3)) & 1).astype(bool)
    corners = np.where(pick[None], hi[:, None, :], lo[:, None, :]).reshape(-1, 3)
    cam_from_world = np.linalg.inv(np.stack([c.world_from_camera for c in cameras]))
    # (m, n * 8, 3) camera-space corners, as CameraFrame.project computes them.
    pc = corners @ cam_from_world[:, :3, :3].transpose(0, 2, 1) + cam_from_world[:, None, :3, 3]
    tan = np.array([c.tan_half_fov(width, height) for c in cameras])  # (m, 2)
    depth = (-pc[..., 2]).reshape(m, n, 8)
    in_front = np.any(depth > 0.0, axis=2)
    straddles = in_front & np.any(depth <= 0.0, axis=2)
    # A corner on the eye plane divides by ~0; such a box straddles or touches the eye
    # and is replaced below, so its (inf / NaN) rectangle is only clipped away here.
    safe = np.where(np.abs(depth) < 1e-300, 1e-300, depth)
    with np.errstate(over="ignore", invalid="ignore"):
        ndc_x = pc[..., 0].reshape(m, n, 8) / (safe * tan[:, 0, None, None])
        ndc_y = pc[..., 1].reshape(m, n, 8) / (safe * tan[:, 1, None, None])
    x = np.clip(np.nan_to_num((ndc_x + 1.0) * 0.5 * width, nan=0.0), 0.0, float(width))
    y = np.clip(np.nan_to_num((1.0 - ndc_y) * 0.5 * height, nan=0.0), 0.0, float(height))
    area = (x.max(axis=2) - x.min(axis=2)) * (y.max(axis=2) - y.min(axis=2))
    area = np.where(straddles, float(width) * float(height), area)
    return np.where(in_front, area, 0.0)


def camera_distance(centers: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """D: (n, 3) world-metre points, (3,) eye → (n,) float64 metres, >= D_MIN."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = np.linalg.norm(centers - np.asarray(eye, dtype=np.float64), axis=1)
    return np.clip(np.nan_to_num(d, nan=D_MIN, posinf=np.finfo(np.float64).max), D_MIN, None)


def visibility(A: np.ndarray, P: np.ndarray, D: np.ndarray) -> np.ndarray:
    """V = A * P / D (paper eq. 1), float64, finite: D is clamped to >= D_MIN."""
    A = np.clip(np.asarray(A, dtype=np.float64), 0.0, 1.0)
    P = np.clip(np.asarray(P, dtype=np.float64), 0.0, 1.0)
    D = np.clip(np.asarray(D, dtype=np.float64), D_MIN, None)
    return A * P / D


def distance_factor(separation: np.ndarray, D: np.ndarray | float) -> np.ndarray:
    """O: 1 while ``separation <= D``, +1 each time it doubles: 1 + floor(log2(sep / D)).

    separation: (n,) metres between the two reflectors' bounding-box centres;
    D: the reflecting element's camera distance (metres, clamped >= D_MIN). Result (n,)
    float64 >= 1, at most ~2100 even for 1e300 m / 1e-6 m.
    """
    D = np.clip(np.asarray(D, dtype=np.float64), D_MIN, None)
    sep = np.nan_to_num(np.asarray(separation, dtype=np.float64), nan=0.0)
    with np.errstate(over="ignore"):
        ratio = np.maximum(sep / D, 1.0)  # <= D counts as 1 (no doubling yet)
    ratio = np.minimum(ratio, np.finfo(np.float64).max)  # inf/huge → largest float
    return 1.0 + np.floor(np.log2(ratio))


def processing_costs(
    V: np.ndarray,
    Q: np.ndarray,
    owner: np.ndarray,
    reflected_V: np.ndarray,
    reflected_Q: np.ndarray,
    reflected_O: np.ndarray,
) -> np.ndarray:
    """C = V*Q + sum_j V_j*Q_j/O_j (paper eq. 2) for n elements at once.

    V, Q: (n,) the elements' own figures; owner: (m,) int index into the n elements of
    each reflected reflector; reflected_V, reflected_Q, reflected_O: (m,) its figures.
    All inputs finite and >= 0 (O >= 1), so every C is finite and >= 0. Returns (n,)."""
    V = np.asarray(V, dtype=np.float64)
    rv = np.asarray(reflected_V, dtype=np.float64)
    rq = np.asarray(reflected_Q, dtype=np.float64)
    ro = np.maximum(np.asarray(reflected_O, dtype=np.float64), 1.0)
    reflected = np.bincount(np.asarray(owner, dtype=np.int64), rv * rq / ro, minlength=len(V))
    return V * np.asarray(Q, dtype=np.float64) + reflected


def processing_cost(
    V: float, Q: float, reflected_V: np.ndarray, reflected_Q: np.ndarray, reflected_O: np.ndarray
) -> float:
    """``processing_costs`` of one element reflecting the (m,) reflectors given."""
    owner = np.zeros(len(np.atleast_1d(reflected_V)), dtype=np.int64)
    return float(processing_costs([V], [Q], owner, reflected_V, reflected_Q, reflected_O)[0])


def relevance(S: np.ndarray, weight: float, V: np.ndarray, K: np.ndarray) -> np.ndarray:
    """R = (S * I + V) * K (paper eq. 3) with I = ``weight``; I and K clipped to
    [0, WEIGHT_MAX]."""
    I_ = clip_weight(weight)
    K_ = clip_weight(K)
    S_ = np.asarray(S, dtype=np.float64)
    V_ = np.nan_to_num(np.asarray(V, dtype=np.float64), nan=0.0, posinf=1.0 / D_MIN)
    return (S_ * I_ + V_) * K_


def clip_weight(w: np.ndarray | float) -> np.ndarray:
    """K or I as float64 in [0, WEIGHT_MAX]; NaN → 0 (see WEIGHT_MAX)."""
    w = np.nan_to_num(np.asarray(w, dtype=np.float64), nan=0.0, posinf=WEIGHT_MAX)
    return np.clip(w, 0.0, WEIGHT_MAX)


# --------------------------------------------------------------------------- cost model


class TraceTimeModel:
    """Milliseconds of one tracing round: ``overhead_ms + ms_per_ray * rays``.

    Fitted by exponentially weighted least squares over the rounds seen so far (older
    rounds weigh ``TIME_MODEL_DECAY`` less per round). When the fit gives a negative
    overhead, the line goes through the origin instead (``ms_per_ray = sum ms / sum
    rays``, conservative for rounds larger than average). When the rounds' ray counts are
    too alike to separate the two terms, or time does not grow with rays (small rounds
    dominated by noise), ``ms_per_ray`` keeps its previous value and the overhead absorbs
    the mean time.

    Predictions are multiplied by ``safety``, an online estimate of the JITTER_QUANTILE
    quantile of (measured / modelled) round time, clamped to [TIME_SAFETY_MIN,
    TIME_SAFETY_MAX].
    """

    def __init__(self) -> None:
        self.overhead_ms = INITIAL_ROUND_MS
        self.ms_per_ray = INITIAL_MS_PER_RAY
        self.rounds = 0
        self.safety = TIME_SAFETY_INITIAL
        # Weighted sums: weight, rays, ms, rays^2, rays*ms.
        self._w = self._r = self._m = self._rr = self._rm = 0.0

    def learn(self, rays: int, ms: float) -> None:
        """One round: ``rays`` cast in ``ms`` wall-clock milliseconds."""
        if rays <= 0 or not math.isfinite(ms) or ms < 0.0:
            return
        r, m = float(rays), float(ms)
        if self.rounds > 0:  # the first round only tells how wrong the initial guess was
            ratio = m / (self.overhead_ms + self.ms_per_ray * r)
            q = JITTER_QUANTILE
            step = JITTER_STEP * (q if ratio > self.safety else -(1.0 - q))
            self.safety = min(max(self.safety + step, TIME_SAFETY_MIN), TIME_SAFETY_MAX)
        k = TIME_MODEL_DECAY
        self._w = k * self._w + 1.0
        self._r = k * self._r + r
        self._m = k * self._m + m
        self._rr = k * self._rr + r * r
        self._rm = k * self._rm + r * m
        self.rounds += 1
        spread = self._w * self._rr - self._r * self._r  # w^2 * variance of rays
        slope = intercept = -1.0
        if spread > 1e-6 * self._w * self._rr:  # ray counts differ enough to fit a line
            slope = (self._w * self._rm - self._r * self._m) / spread
            intercept = (self._m - slope * self._r) / self._w
        if slope > 0.0 and intercept >= 0.0:
            self.overhead_ms, self.ms_per_ray = intercept, slope
        elif slope > 0.0:  # negative overhead: a line through the origin instead
            self.overhead_ms, self.ms_per_ray = 0.0, self._m / self._r
        else:
            # No growth with rays visible (rounds too alike, or noise dominates): the rounds
            # tell their mean time, not the per-ray cost, which keeps its previous value.
            self.overhead_ms = max(self._m / self._w - self.ms_per_ray * self._r / self._w, 0.0)
        self.ms_per_ray = max(self.ms_per_ray, MIN_MS_PER_RAY)

    def relax(self) -> None:
        """Nothing fitted the time budget this frame: lower the safety factor a little."""
        self.safety = max(self.safety * STARVED_RELAX, TIME_SAFETY_MIN)

    def predicted_ms(self, rays: float) -> float:
        """Conservative milliseconds for a round of ``rays`` rays (``safety`` included)."""
        return (self.overhead_ms + self.ms_per_ray * max(rays, 0.0)) * self.safety

    def rays_within(self, ms: float) -> float:
        """Most rays a round may cast and still (conservatively) end within ``ms``."""
        return max((ms / self.safety - self.overhead_ms) / self.ms_per_ray, 0.0)


# ------------------------------------------------------------- memory as plain data


def _to_plain(value):
    """Policy memory → JSON data: sets become ``{"set": [...]}``, dicts with int keys
    ``{"int_keys": [[k, v], ...]}`` (JSON keys are strings), tuples lists."""
    if isinstance(value, set | frozenset):
        return {"set": sorted(_to_plain(v) for v in value)}
    if isinstance(value, dict):
        if all(isinstance(k, str) for k in value):
            return {"str_keys": {k: _to_plain(v) for k, v in value.items()}}
        return {"int_keys": [[int(k), _to_plain(v)] for k, v in value.items()]}
    if isinstance(value, list | tuple):
        return [_to_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise PhrtError(f"policy memory holds a {type(value).__name__}, not plain data")


def _from_plain(value):
    """Inverse of ``_to_plain``; PhrtError for anything it could not have written."""
    if isinstance(value, dict):
        if set(value) == {"set"} and isinstance(value["set"], list):
            return {_hashable(_from_plain(v)) for v in value["set"]}
        if set(value) == {"str_keys"} and isinstance(value["str_keys"], dict):
            return {k: _from_plain(v) for k, v in value["str_keys"].items()}
        if set(value) == {"int_keys"} and isinstance(value["int_keys"], list):
            pairs = value["int_keys"]
            if not all(isinstance(p, list) and len(p) == 2 and type(p[0]) is int for p in pairs):
                raise PhrtError("policy memory: a malformed int-keyed table")
            return {k: _from_plain(v) for k, v in pairs}
        raise PhrtError("policy memory: an unknown table")
    if isinstance(value, list):
        return [_from_plain(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise PhrtError("policy memory: not plain data")


def _hashable(value):
    if isinstance(value, list | dict | set):
        raise PhrtError("policy memory: a set holds a table")
    return value


def _same_shape(got, want) -> bool:
    """``got`` has ``want``'s keys and, recursively, compatible types (a number where a
    number was, a container where one was). The policies' memory tables are keyed by
    element id and hold numbers (or tables and lists of numbers), so the content of a
    table that is empty in ``want`` must be that."""
    if isinstance(want, dict):
        if not isinstance(got, dict):
            return False
        if not want:
            return all(isinstance(k, int) and _numeric(v) for k, v in got.items())
        return set(got) == set(want) and all(_same_shape(got[k], want[k]) for k in want)
    if isinstance(want, set | list):
        return isinstance(got, type(want)) and all(_number(v) for v in got)
    if isinstance(want, bool):
        return isinstance(got, bool)
    if isinstance(want, int | float):
        return _number(got)
    if want is None:
        return got is None or _number(got)
    return type(got) is type(want)


def _number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _numeric(value) -> bool:
    """A number, or a list or int-keyed table of numbers (any depth)."""
    if isinstance(value, dict):
        return all(isinstance(k, int) and _numeric(v) for k, v in value.items())
    if isinstance(value, list | set):
        return all(_numeric(v) for v in value)
    return _number(value)


# --------------------------------------------------------------------------- policies


@dataclass
class _FrameState:
    """What a policy knows about the frame in progress (arrays indexed by element id)."""

    view: FrameView
    scene: Scene
    pixels: np.ndarray  # (E,) int64 pixels per element (0 past the G-buffer's ids)
    centers: np.ndarray  # (E, 3) float64 world metres, bounding-box centres
    D: np.ndarray  # (E,) float64 metres
    V: np.ndarray  # (E,) float64
    K: np.ndarray  # (E,) float64 priorities (clipped)
    traced: list[int] = field(default_factory=list)  # selected this frame, in order
    predicted_rays: dict[int, float] = field(default_factory=dict)  # at selection time
    predicted_ms: dict[int, float] = field(default_factory=dict)  # at selection time
    predicted_trace_ms: float = 0.0  # sum over rounds of the predicted round time
    first_allowance: float | None = None  # the first round's budget in rays (HEU1 margin)
    forecast_used: float = 0.0  # HEU1: forecasts of this frame's selection, summed
    unfit_claims: set[int] = field(default_factory=set)  # HEU1: kept, claimed, did not fit
    #: ``predicted_rays`` per element as of the last recorded round (it changes only when
    #: ``record`` learns rays per pixel; every round asks for it per candidate).
    rays: dict[int, float] = field(default_factory=dict)
    growth: dict[int, float] = field(default_factory=dict)  # HEU1: growth() of this frame


class BudgetedPolicy(ABC):
    """What every policy shares: the per-frame metrics, the memory across frames (Q,
    rays per pixel, which reflector reflects which, the previous selection) and the cost
    model. Subclasses decide only which ids a round traces (``_choose``)."""

    name = "base"

    def __init__(self, *, selection_weight: float, bounce_limit: int) -> None:
        if not (math.isfinite(selection_weight) and selection_weight >= 0.0):
            raise PhrtError(
                f"phrt:selectionWeight must be a finite number >= 0, got {selection_weight}"
            )
        if bounce_limit < 0:
            raise PhrtError(f"phrt:bounceLimit must be >= 0, got {bounce_limit}")
        self.selection_weight = float(clip_weight(selection_weight))
        self.bounce_limit = int(bounce_limit)
        self.time_model = TraceTimeModel()
        # Memory across frames, keyed by element id.
        self.Q: dict[int, float] = {}
        self.rays_per_pixel: dict[int, float] = {}
        self.reflects: dict[int, dict[int, float]] = {}  # source → {reflector: f}
        self.discovered: set[int] = set()  # reflectors hit by secondary rays, ever
        self.previous_selection: set[int] = set()
        self._global_rays = 0.0  # decayed sums for the mean rays per pixel
        self._global_pixels = 0.0
        self._frame: _FrameState | None = None
        self._reflector_cache: tuple[tuple[int, int], np.ndarray] | None = None
        #: Predicted trace time of the last finished frame (ms, time safety included).
        self.last_predicted_trace_ms = 0.0

    #: Attributes that are caches or the frame in progress, not memory across frames:
    #: left out of ``memory()`` and rebuilt on demand after ``restore_memory``.
    CACHE_ATTRIBUTES = frozenset({"_frame", "_reflector_cache", "_box_areas", "_box_areas_key"})

    def memory(self) -> dict:
        """The policy's memory across frames as plain JSON data (for checkpoints): every
        attribute but the caches, between frames. ``restore_memory`` on a fresh policy of
        the same name and parameters makes it select exactly as this one would."""
        if self._frame is not None:
            raise PhrtError("a policy's memory is saved between frames only")
        state = {k: v for k, v in vars(self).items() if k not in self.CACHE_ATTRIBUTES}
        state["time_model"] = vars(self.time_model)
        return {"policy": self.name, "state": _to_plain(state)}

    def restore_memory(self, memory: dict) -> None:
        """Set the memory saved by ``memory()``; PhrtError if it is not this policy's or
        does not have this policy's attributes and types (nothing is changed then)."""
        if not isinstance(memory, dict) or memory.get("policy") != self.name:
            raise PhrtError(f"saved policy memory is not a {self.name} policy's")
        state = _from_plain(memory.get("state"))
        expected = {k: v for k, v in vars(self).items() if k not in self.CACHE_ATTRIBUTES}
        model = state.pop("time_model", None) if isinstance(state, dict) else None
        if (
            not isinstance(state, dict)
            or not isinstance(model, dict)
            or set(model) != set(vars(self.time_model))
            or not _same_shape(state, {k: v for k, v in expected.items() if k != "time_model"})
        ):
            raise PhrtError(f"saved {self.name} policy memory has other fields or types")
        if not all(isinstance(v, int | float) for v in model.values()):
            raise PhrtError(f"saved {self.name} cost model holds a non-number")
        vars(self).update(state)
        vars(self.time_model).update(model)

    # ---- SelectionPolicy

    def begin_frame(self, view: FrameView, scene: Scene) -> None:
        n = len(scene.elements)
        refl = self._reflectors_of(scene)
        pixels = np.zeros(n, dtype=np.int64)
        counts = np.asarray(view.pixel_counts, dtype=np.int64).reshape(-1)[:n]
        pixels[refl[refl < len(counts)]] = np.maximum(counts[refl[refl < len(counts)]], 0)
        # Per-element arrays, filled for reflectors only (scenes may hold many instances).
        centers = np.zeros((n, 3))
        centers[refl] = np.array([scene.elements[i].center for i in refl]).reshape(-1, 3)
        K = np.zeros(n)
        K[refl] = clip_weight(np.array([scene.elements[i].priority for i in refl]))
        A = visible_area(pixels, view.width, view.height)
        P = np.zeros(n)
        P[refl] = centrality(centers[refl], view.camera, view.width, view.height)
        if view.screen_boxes is not None:
            # A visible reflector's centrality follows the bounding box of its visible
            # pixels: a pond whose 3D box centre is off-screen still counts as central
            # when its visible part is (docs/heuristic.md, "P").
            boxes = np.asarray(view.screen_boxes, dtype=np.float64)[refl]
            seen = pixels[refl] > 0
            P[refl[seen]] = screen_centrality(boxes[seen], view.width, view.height)
        D = camera_distance(centers, view.camera.position)
        self._frame = _FrameState(
            view=view, scene=scene, pixels=pixels, centers=centers, D=D,
            V=visibility(A, P, D), K=K,
        )  # fmt: skip

    def _reflectors_of(self, scene: Scene) -> np.ndarray:
        """(R,) int64 reflector element ids, computed once per scene object (the reflector
        flags of a stage's elements do not change during a run)."""
        key = (id(scene), len(scene.elements))
        if self._reflector_cache is None or self._reflector_cache[0] != key:
            ids = np.array([i for i, e in enumerate(scene.elements) if e.is_reflector])
            self._reflector_cache = (key, ids.astype(np.int64).reshape(-1))
        return self._reflector_cache[1]

    def next_round(self, budget: Budget) -> list[int]:
        frame = self._require_frame()
        ids = self._choose(budget)
        if not ids and not frame.traced and self._starved_by_time(budget):
            self.time_model.relax()
        for e in ids:
            frame.predicted_rays[e] = self.predicted_rays(e)
        if ids:
            # The round's predicted time (fixed overhead included), shared among its
            # reflectors by rays, so that summing predicted_ms over a frame's selection
            # gives the frame's predicted trace time.
            rays = sum(frame.predicted_rays[e] for e in ids)
            round_ms = self.time_model.predicted_ms(rays)
            for e in ids:
                share = frame.predicted_rays[e] / rays if rays > 0.0 else 1.0 / len(ids)
                frame.predicted_ms[e] = round_ms * share
            frame.predicted_trace_ms += round_ms
        frame.traced.extend(ids)
        return ids

    def record(self, records: list[TraceRecord], seconds: float) -> None:
        frame = self._require_frame()
        frame.rays.clear()  # rays per pixel change below
        n = len(frame.scene.elements)
        total_rays = 0
        for rec in records:
            total_rays += max(int(rec.rays), 0)
            src = int(rec.source)
            if not 0 <= src < n:
                continue
            bounces = max(int(rec.max_reflector_bounces), 0)
            # Q = 1 + bounces, capped at the bounce limit (Q >= 1 even for a limit of 0).
            self.Q[src] = float(min(1 + bounces, max(self.bounce_limit, 1)))
            if rec.pixels > 0 and rec.rays >= 0:
                rpp = max(rec.rays / rec.pixels, MIN_RAYS_PER_PIXEL)
                old = self.rays_per_pixel.get(src)
                a = RAYS_PER_PIXEL_ALPHA
                self.rays_per_pixel[src] = rpp if old is None else a * rpp + (1 - a) * old
                self._global_rays = TIME_MODEL_DECAY * self._global_rays + rec.rays
                self._global_pixels = TIME_MODEL_DECAY * self._global_pixels + rec.pixels
            # The latest trace of a source replaces what it was seen to reflect before.
            hits = {}
            for j, count in rec.hits.items():
                j = int(j)
                if j != src and 0 <= j < n and frame.scene.elements[j].is_reflector:
                    hits[j] = min(max(count, 0) / max(rec.pixels, 1), 1.0)
            self.reflects[src] = hits
            self.discovered.update(hits)
        self.time_model.learn(total_rays, float(seconds) * 1000.0)

    def end_frame(self) -> dict[int, ReflectorMetrics]:
        frame = self._require_frame()
        metrics = self.metrics()
        self.previous_selection = set(frame.traced)
        self.last_predicted_trace_ms = frame.predicted_trace_ms
        self._frame = None
        return metrics

    # ---- figures

    def candidates(self) -> list[int]:
        """Ascending element ids: reflectors visible in this frame, plus reflectors
        discovered by secondary rays in this frame's earlier rounds or earlier frames."""
        frame = self._require_frame()
        visible = set(np.flatnonzero(frame.pixels > 0).tolist())
        return sorted(visible | {e for e in self.discovered if e < len(frame.pixels)})

    def q_of(self, element: int) -> float:
        """Q of a reflector: learned from its last trace, 1 until it was traced."""
        return self.Q.get(element, 1.0)

    def cost_C(self, element: int) -> float:
        """The paper's C for ``element`` in the current frame (see the module docstring)."""
        return self.costs_C([element])[element]

    def costs_C(self, elements: list[int]) -> dict[int, float]:
        """``cost_C`` of each of ``elements``, in one array pass over every (element,
        reflected reflector) pair: the metrics ask for every candidate's C, and
        per-element numpy calls would cost far more than the sums."""
        frame = self._require_frame()
        ids = np.array(sorted(set(elements)), dtype=np.int64)
        pairs = [(k, j, f) for k, e in enumerate(ids.tolist())
                 for j, f in sorted(self.reflects.get(e, {}).items())]  # fmt: skip
        owner = np.array([k for k, _j, _f in pairs], dtype=np.int64)
        js = np.array([j for _k, j, _f in pairs], dtype=np.int64)
        f = np.array([f for _k, _j, f in pairs], dtype=np.float64)
        src = ids[owner]
        seen_V = np.maximum(frame.V[js], frame.V[src] * f)  # visible itself, or through src
        sep = np.linalg.norm(frame.centers[js] - frame.centers[src], axis=1)
        C = processing_costs(
            frame.V[ids], [self.q_of(e) for e in ids.tolist()], owner, seen_V,
            [self.q_of(j) for j in js.tolist()], distance_factor(sep, frame.D[src]),
        )  # fmt: skip
        return dict(zip(ids.tolist(), C.tolist(), strict=True))

    def relevance_R(self, element: int) -> float:
        frame = self._require_frame()
        S = 1.0 if element in self.previous_selection else 0.0
        # Scalar form of ``relevance``: I and K are clipped already, V is finite (D >= D_MIN),
        # so R <= (1 + WEIGHT_MAX) * WEIGHT_MAX stays finite; this runs per node and round.
        return (S * self.selection_weight + float(frame.V[element])) * float(frame.K[element])

    def predicted_rays(self, element: int) -> float:
        """Conservative rays to trace ``element``'s pixels: pixels * rays per pixel *
        RAYS_SAFETY. Rays per pixel: the element's own learned average; else the mean over
        everything traced so far; else Q * (1 + number of lights) (one reflection ray plus
        one shadow ray per light, per bounce)."""
        frame = self._require_frame()
        cached = frame.rays.get(element)
        if cached is not None:
            return cached
        pixels = float(frame.pixels[element])
        rpp = self.rays_per_pixel.get(element)
        if rpp is None:
            if self._global_pixels > 0.0:
                rpp = self._global_rays / self._global_pixels
            else:
                lights = frame.scene.lights
                rpp = self.q_of(element) * (1 + len(lights.distant) + len(lights.local))
        frame.rays[element] = rays = pixels * max(rpp, MIN_RAYS_PER_PIXEL) * RAYS_SAFETY
        return rays

    def predicted_ms(self, rays: float) -> float:
        """Milliseconds a candidate's ``rays`` add to a round (time safety included; the
        round's fixed overhead is not, see ``TraceTimeModel``). Used for the metrics of
        candidates not selected; selected ones get their share of their round's time."""
        return self.time_model.ms_per_ray * max(rays, 0.0) * self.time_model.safety

    def ray_allowance(self, budget: Budget) -> float:
        """The budget as a number of (predicted) rays: the smaller of ``budget.rays`` and
        the rays the time model says fit in ``budget.ms``; ``inf`` when both are None."""
        allowance = math.inf
        if budget.rays is not None:
            allowance = min(allowance, float(max(budget.rays, 0)))
        if budget.ms is not None:
            ms = 0.0 if math.isnan(budget.ms) else float(budget.ms)  # NaN: nothing is known
            allowance = min(allowance, self.time_model.rays_within(ms))
        return allowance

    def _starved_by_time(self, budget: Budget) -> bool:
        """True if a visible candidate would fit the rays budget but not the time one."""
        if budget.ms is None or not budget.ms > 0.0 or not self._untraced_visible():
            return False
        cheapest = min(self.predicted_rays(e) for e in self._untraced_visible())
        rays_ok = budget.rays is None or cheapest <= budget.rays
        return rays_ok and cheapest > self.time_model.rays_within(budget.ms)

    def metrics(self) -> dict[int, ReflectorMetrics]:
        """Figures for every candidate as of now (after the last recorded round)."""
        frame = self._require_frame()
        traced = set(frame.traced)
        candidates = self.candidates()
        C = self.costs_C(candidates)
        out = {}
        for e in candidates:
            rays = frame.predicted_rays.get(e, self.predicted_rays(e))
            out[e] = ReflectorMetrics(
                V=float(frame.V[e]),
                C=C[e],
                R=self.relevance_R(e),
                Q=self.q_of(e),
                S=e in self.previous_selection,
                selected=e in traced,
                visible=bool(frame.pixels[e] > 0),
                predicted_rays=rays,
                predicted_ms=frame.predicted_ms.get(e, self.predicted_ms(rays)),
            )
        return out

    # ---- for subclasses

    def _untraced_visible(self) -> list[int]:
        frame = self._require_frame()
        done = set(frame.traced)
        return [int(e) for e in np.flatnonzero(frame.pixels > 0) if int(e) not in done]

    @abstractmethod
    def _choose(self, budget: Budget) -> list[int]:
        """Element ids to trace in this round, within ``budget``."""

    def _require_frame(self) -> _FrameState:
        if self._frame is None:
            raise RuntimeError(f"{type(self).__name__}: begin_frame() was not called")
        return self._frame


class Heu1Policy(BudgetedPolicy):
    """The paper's heuristic on a Selection Graph rebuilt from the untraced candidates
    every round, made transition-aware (docs/heuristic.md):

    * reflectors selected in the previous frame keep their claim while no candidate that
      could be taken is more relevant (R with the paper's S·I bonus), and the claimed
      ones are kept cheapest first, as many as fit (when they no longer all fit, the
      fewest are dropped);
    * the others are taken by relevance R among those whose predicted cost fits, with
      the admission margin; a reflector already in view in the previous frame (so that
      taking it is a transition) must in addition not be shrinking, and its cost forecast
      FORECAST_HORIZON frames ahead must fit the budget left by the forecasts of the
      reflectors taken before it. A reflector entering the view is taken freely.
    """

    name = "heu1"

    def __init__(self, *, selection_weight: float, bounce_limit: int) -> None:
        super().__init__(selection_weight=selection_weight, bounce_limit=bounce_limit)
        #: Pixel counts of each reflector in view over its last consecutive frames in view
        #: (at most GROWTH_WINDOW + 1, oldest first, the current frame last).
        self.pixel_history: dict[int, list[int]] = {}
        #: Reflectors with pixels in the previous frame.
        self.previous_visible: set[int] = set()
        #: Reflectors the keep step could not fit while in view, not selected since and
        #: still in view: they are no challengers of kept reflectors (``Node.challenger``).
        self.forced_out: set[int] = set()
        #: This frame's lookahead growth per reflector in view (element id → largest
        #: bounding-box screen area over the upcoming cameras / the current one, >= 1);
        #: empty when the view has no upcoming cameras.
        self.lookahead_growth: dict[int, float] = {}
        #: Screen area of every reflector's box per camera of the path, computed once per
        #: camera (the renderer passes the same CameraFrame objects frame after frame, the
        #: current one included): id(camera) → (camera, (R,) float64 pixels, in the order
        #: of the reflector ids). The camera is held so that its id cannot be reused while
        #: cached. Boxes are those of the frame that computed the batch (animation is not
        #: forecast), the current camera's too, so growth compares like with like.
        self._box_areas: dict[int, tuple[CameraFrame, np.ndarray]] = {}
        self._box_areas_key: tuple = ()  # (width, height, reflector count) of the cache

    def begin_frame(self, view: FrameView, scene: Scene) -> None:
        super().begin_frame(view, scene)
        frame = self._require_frame()
        history = {}
        for e in np.flatnonzero(frame.pixels > 0).tolist():
            history[e] = [*self.pixel_history.get(e, [])[-GROWTH_WINDOW:], int(frame.pixels[e])]
        self.pixel_history = history  # a reflector out of view starts afresh
        self.lookahead_growth = self._lookahead_growth(view, scene, np.fromiter(history, int))

    def _lookahead_growth(self, view: FrameView, scene: Scene, ids: np.ndarray) -> dict[int, float]:
        """Element id → peak screen area of its box over now and the next LOOKAHEAD_FRAMES
        upcoming cameras / its area now (>= 1, finite), for the reflectors ``ids`` in
        view; {} without upcoming cameras."""
        ahead = view.upcoming_cameras[:LOOKAHEAD_FRAMES]
        if not ahead or len(ids) == 0:
            return {}
        refl = self._reflectors_of(scene)  # ascending element ids
        w, h = view.width, view.height
        if self._box_areas_key != (w, h, len(refl)):
            self._box_areas, self._box_areas_key = {}, (w, h, len(refl))
        cached = self._box_areas
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
            self._box_areas = cached
        cols = np.searchsorted(refl, ids)
        now = cached[id(view.camera)][1][cols]
        peak = np.stack([cached[id(c)][1] for c in ahead])[:, cols].max(axis=0)
        # A reflector in view has pixels, so a box area under one pixel is a sliver at
        # the image edge: growth is measured from one pixel, which keeps it finite.
        growth = np.maximum(peak, now) / np.maximum(now, 1.0)
        growth = np.clip(np.nan_to_num(growth, nan=1.0, posinf=FORECAST_MAX), 1.0, FORECAST_MAX)
        return dict(zip(ids.tolist(), growth.tolist(), strict=True))

    def end_frame(self) -> dict[int, ReflectorMetrics]:
        frame = self._require_frame()
        visible = set(np.flatnonzero(frame.pixels > 0).tolist())
        self.forced_out = ((self.forced_out | frame.unfit_claims) & visible) - set(frame.traced)
        self.previous_visible = visible
        return super().end_frame()

    def growth(self, element: int) -> float:
        """Per-frame growth of ``element``'s pixel count: the geometric mean over its
        recent frames in view when they show a trend (net change in log pixels at least
        TREND_MIN of the up-and-down travel), else 1 (also with fewer than two frames).
        Finite, > 0.

        Only a steady trend counts: a camera moving smoothly makes a reflector's pixel
        count grow or shrink steadily, while counts that jitter (partial occlusion,
        animation) would otherwise extrapolate to a wildly wrong forecast."""
        growth = self._require_frame().growth  # the history is fixed within a frame
        if element not in growth:
            growth[element] = self._pixel_growth(element)
        return growth[element]

    def _pixel_growth(self, element: int) -> float:
        """``growth`` computed from the pixel history."""
        h = self.pixel_history.get(element, [])  # at most GROWTH_WINDOW + 1 counts: scalars
        if len(h) < 2 or h[0] <= 0:
            return 1.0
        logs = [math.log(max(c, 1.0)) for c in h]
        steps = [b - a for a, b in zip(logs, logs[1:], strict=False)]
        travel = sum(abs(d) for d in steps)
        if travel > 0.0 and abs(sum(steps)) < TREND_MIN * travel:
            return 1.0  # up and down more than it moved: no trend to extrapolate
        return float((h[-1] / h[0]) ** (1.0 / (len(h) - 1)))

    def forecast_rays(self, element: int) -> float:
        """Predicted rays within the forecast's horizon: with upcoming cameras,
        ``predicted_rays`` times the lookahead growth (LOOKAHEAD_FRAMES ahead); otherwise
        ``predicted_rays * g**H`` with the pixel growth g clamped to [1, GROWTH_MAX] and
        H = FORECAST_HORIZON. Finite (<= FORECAST_MAX)."""
        growth = self.lookahead_growth.get(element)
        if growth is None:
            growth = min(max(self.growth(element), 1.0), GROWTH_MAX) ** FORECAST_HORIZON
        return float(min(self.predicted_rays(element) * growth, FORECAST_MAX))

    def _node(self, e: int, reserve: float, budget: float) -> Node:
        frame = self._require_frame()
        kept = e in self.previous_selection
        forecast = self.forecast_rays(e)
        if kept and forecast > budget:
            # It will outgrow the whole budget within the horizon and be dropped whatever
            # is decided now: what it holds of the budget is not a lasting commitment.
            forecast = 0.0
        return Node(
            element=e,
            R=self.relevance_R(e),
            cost=self.predicted_rays(e),
            traceable=bool(frame.pixels[e] > 0),
            reserve=0.0 if kept else reserve,
            kept=kept,
            forecast=forecast,
            admission=not kept and e in self.previous_visible,
            challenger=e not in self.forced_out,
        )

    def graph(self, reserve: float = 0.0, budget: float = math.inf) -> SelectionGraph:
        """The Selection Graph of the untraced candidates, as of now. Candidates not
        selected in the previous frame need ``reserve`` budget left beyond their cost;
        ``budget`` is the frame's whole budget (a kept reflector forecast beyond it
        charges no forecast). Candidates in view in the previous frame, not selected
        then, and shrinking now are left out: taking one would be a transition for a
        reflector that is on its way out of the view."""
        frame = self._require_frame()
        done = set(frame.traced)
        return SelectionGraph(
            self._node(e, reserve, budget)
            for e in self.candidates()
            if e not in done and not self._leaving(e)
        )

    def _leaving(self, e: int) -> bool:
        """In view in the previous frame, not selected then, and shrinking now."""
        return (
            e in self.previous_visible and e not in self.previous_selection and self.growth(e) < 1.0
        )

    def _choose(self, budget: Budget) -> list[int]:
        frame = self._require_frame()
        allowance = self.ray_allowance(budget)
        if not allowance > 0.0:
            return []
        if frame.first_allowance is None:
            frame.first_allowance = allowance
        elif all(self.predicted_rays(e) > allowance for e in self._untraced_visible()):
            # A later round in which nothing fits: no graph needed (the first round's is,
            # for the claims the keep step could not fit).
            return []
        # The margin and the horizon budget are shares of the whole frame's budget, also
        # in later rounds.
        reserve = ADMISSION_MARGIN * frame.first_allowance
        graph = self.graph(reserve=reserve, budget=frame.first_allowance)
        ids = graph.select(allowance, horizon_budget=frame.first_allowance - frame.forecast_used)
        if not frame.traced:
            # The first round's keep step decides which claims cost pushes out; in later
            # rounds, kept reflectors not taken yet are ones that already lost or missed.
            frame.unfit_claims.update(graph.unfit_claims)
        frame.forecast_used += sum(graph.nodes[e].forecast for e in ids)
        return ids


class Heu2Policy(BudgetedPolicy):
    """The paper's distance baseline: the visible reflectors nearest the camera
    (bounding-box centre distance, ties by id) that fit the budget, skipping any that
    does not fit; no hysteresis (the previous selection plays no part)."""

    name = "heu2"

    def _choose(self, budget: Budget) -> list[int]:
        frame = self._require_frame()
        remaining = self.ray_allowance(budget)
        chosen = []
        for e in sorted(self._untraced_visible(), key=lambda e: (frame.D[e], e)):
            cost = self.predicted_rays(e)
            if cost <= remaining:
                chosen.append(e)
                remaining -= cost
        return chosen


class AllPolicy(BudgetedPolicy):
    """Every visible reflector, in one round, whatever the budget (the reference)."""

    name = "all"

    def _choose(self, budget: Budget) -> list[int]:
        return self._untraced_visible()


class NonePolicy(BudgetedPolicy):
    """Nothing is traced (raster only)."""

    name = "none"

    def _choose(self, budget: Budget) -> list[int]:
        return []


class ListPolicy(BudgetedPolicy):
    """The given element ids that are visible reflectors, in one round, whatever the
    budget."""

    name = "list"

    def __init__(self, explicit: list[int], *, selection_weight: float, bounce_limit: int):
        super().__init__(selection_weight=selection_weight, bounce_limit=bounce_limit)
        self.explicit = sorted({int(e) for e in explicit})

    def _choose(self, budget: Budget) -> list[int]:
        wanted = set(self.explicit)
        return [e for e in self._untraced_visible() if e in wanted]


POLICY_NAMES = ("heu1", "heu2", "all", "none", "list")


def make_policy(
    name: str,
    *,
    selection_weight: float,
    bounce_limit: int,
    explicit: list[int] | None = None,
) -> SelectionPolicy:
    """A fresh policy by name ("heu1", "heu2", "all", "none", "list"); ``explicit`` is
    the element id list for "list". Raises ``PhrtError`` for an unknown name or bad
    parameters."""
    key = name.strip().lower()
    common = {"selection_weight": selection_weight, "bounce_limit": bounce_limit}
    if key == "heu1":
        return Heu1Policy(**common)
    if key == "heu2":
        return Heu2Policy(**common)
    if key == "all":
        return AllPolicy(**common)
    if key == "none":
        return NonePolicy(**common)
    if key == "list":
        if explicit is None:
            raise PhrtError("heuristic 'list' needs an explicit list of reflectors")
        return ListPolicy(explicit, **common)
    raise PhrtError(
        f"unknown heuristic {name!r} (phrt:heuristic): expected one of {', '.join(POLICY_NAMES)}"
    )
