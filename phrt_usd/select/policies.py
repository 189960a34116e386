"""Which reflectors to ray-trace each frame: what every policy shares (``BudgetedPolicy``),
the HEU2 baseline, the fixed policies ``all``, ``none`` and ``list``
(``phrt_usd.model.frame.SelectionPolicy``), and ``make_policy`` to pick one by name (the
paper's HEU1 is ``phrt_usd.select.heu1_policy``, HEU3 ``benefit_policy``).

Every policy computes the Table 1 metrics of the frame's candidates
(``phrt_usd.select.metrics``) and remembers across frames what tracing taught it: Q, rays
per pixel, which reflector reflects which, the previous selection (saved and restored as
plain data through ``phrt_usd.select.policy_memory``).

Budget: ``C`` has no unit. What the budget is checked against is a calibrated prediction
of the rays tracing a candidate costs (``pixels * rays per pixel``) and of
the time those rays take (``phrt_usd.select.cost_model.TraceTimeModel``). Both are learned
online from the renderer's ``record`` calls.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import (
    Budget,
    FrameNote,
    FrameView,
    ReflectorMetrics,
    SelectionPolicy,
    TraceRecord,
)
from phrt_usd.model.light_sampling import shadow_rays_per_hit
from phrt_usd.model.reflection_roughness import element_figures, started_share
from phrt_usd.model.scene import Scene
from phrt_usd.model.trace_density import TRACE_DENSITIES, traced_fraction
from phrt_usd.select.cost_model import TIME_MODEL_DECAY, TraceTimeModel
from phrt_usd.select.metrics import (
    camera_distance,
    centrality,
    clip_weight,
    distance_factor,
    processing_costs,
    screen_centrality,
    visibility,
    visible_area,
)
from phrt_usd.select.pixel_kind_shares import (
    average_into,
    learn_reused_share,
    made_without_rays,
    skipped_cost,
)
from phrt_usd.select.policy_memory import from_plain, same_shape, to_plain

#: A rays budget admits predicted rays up to budget / RAYS_SAFETY: rays per pixel learned
#: in earlier frames under-predict when a reflector starts reflecting more reflectors
#: (deeper bounces; traced rays / predicted rays, 97 % quantile: sewer 1.02, farm 1.07).
#: A time budget has no such margin of its own: the time model's safety factor is the
#: quantile of measured round time over the time modelled for the *predicted* rays
#: (``record``), so it covers both errors, measured.
RAYS_SAFETY = 1.1

#: Weight of the newest observation in a reflector's rays-per-pixel average.
RAYS_PER_PIXEL_ALPHA = 0.5

#: Fewest rays per traced pixel: the reflection ray itself.
MIN_RAYS_PER_PIXEL = 1.0

#: A reflector's rays per pixel from the calibration's rounds is drawn towards their mean
#: as if this many more of its pixels had cast the mean: the rounds sample pixels at
#: random, so a small reflector may have been traced at a handful. Without its own
#: figure, a cluttered mirror floor's first frame cast 1.7x the rays predicted (the mean
#: is mostly the floor's; the selected spheres reflect more).
CALIBRATION_PRIOR_PIXELS = 16.0

#: HEU1's hysteresis in cost (ours; the paper's I is hysteresis in relevance): a reflector
#: not selected in the previous frame joins only if this fraction of the round's budget
#: stays free after it. Predicted costs jitter by a few per cent from frame to frame;
#: without a margin, a selection whose total hovers at the budget drops one reflector
#: and takes it back on alternate frames.
ADMISSION_MARGIN = 0.1


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
    #: (E,) float64 each element's gain from tracing and (E, L) its shares of pixels that
    #: start rays at each density (``model.reflection_roughness.element_figures``).
    G: np.ndarray = field(default_factory=lambda: np.ones(0))
    ray_shares: np.ndarray = field(default_factory=lambda: np.ones((0, 1)))
    traced: list[int] = field(default_factory=list)  # selected this frame, in order
    predicted_rays: dict[int, float] = field(default_factory=dict)  # at selection time
    predicted_ms: dict[int, float] = field(default_factory=dict)  # at selection time
    predicted_trace_ms: float = 0.0  # sum over rounds of the predicted round time
    round_rays: float = 0.0  # predicted rays of the round in progress (0 between rounds)
    #: Sum over rounds of the central estimate of the round time (no safety factors).
    expected_trace_ms: float = 0.0
    #: Why the first round selected nothing while reflectors were visible (numbers in it).
    untraced_reason: str | None = None
    first_allowance: float | None = None  # the first round's budget in rays (HEU1 margin)
    #: HEU1: forecasts of this frame's selection, summed (a number, or per lookahead frame).
    forecast_used: float | np.ndarray = 0.0
    unfit_claims: set[int] = field(default_factory=set)  # HEU1: kept, claimed, did not fit
    held: bool = False  # HEU1: the previous selection was held through a starved frame
    #: ``predicted_rays`` per element as of the last recorded round (it changes only when
    #: ``record`` learns rays per pixel; every round asks for it per candidate).
    rays: dict[int, float] = field(default_factory=dict)
    growth: dict[int, float] = field(default_factory=dict)  # HEU1: growth() of this frame
    #: Trace density of each reflector taken at other than full density (index into
    #: ``model.trace_density.TRACE_DENSITIES``; HEU1's density steps); absent: full.
    levels: dict[int, int] = field(default_factory=dict)
    #: What a pixel costs beyond its rays in this frame's ``level_rays``, in rays
    #: (filled, reused, marched): the time model's ``kind_rays`` under a time budget, 0
    #: under a rays budget alone (which counts rays).
    kind_rays: tuple[float, float, float] = (0.0, 0.0, 0.0)


class BudgetedPolicy(ABC):
    """What every policy shares: the per-frame metrics, the memory across frames (Q,
    rays per pixel, which reflector reflects which, the previous selection) and the cost
    model. Subclasses decide only which ids a round traces (``_choose``). Implements all
    of ``SelectionPolicy`` (``phrt_usd.model.frame``), what the round loop reads."""

    name = "base"
    #: True when ``record`` reads ``TraceRecord.fallback_error`` (the renderer fills it
    #: only then: it costs a pass over the traced pixels).
    observes_fallback_error = False
    #: False for the fixed policies (all, none, list): what they trace does not depend on
    #: the budget, so the renderer reports no budget use for them.
    follows_budget = True

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
        #: The previous frame's selection traced at other than full density: element id
        #: → index into ``model.trace_density.TRACE_DENSITIES`` (HEU1's density steps).
        self.previous_levels: dict[int, int] = {}
        self._global_rays = 0.0  # decayed sums for the mean rays per pixel
        self._global_pixels = 0.0
        #: Decayed sums over the recorded pixels that started rays: those whose first ray
        #: was marched in screen space, and all (the marched share, 1 with it on).
        self._marched = [0.0, 0.0]
        #: Per reflector, the share of its skipped pixels reused rather than filled
        #: (``select.pixel_kind_shares``).
        self.reused_share: dict[int, float] = {}
        self._frame: _FrameState | None = None
        self._reflector_cache: tuple[tuple[int, int], np.ndarray] | None = None
        #: Predicted trace time of the last finished frame (ms, time safety included).
        self.last_predicted_trace_ms = 0.0
        #: Of the last finished frame: the central trace-time estimate (ms) and why
        #: nothing was traced (None if something was, or nothing was visible).
        self.last_frame_note = FrameNote()

    #: Attributes that are caches or the frame in progress, not memory across frames:
    #: left out of ``memory()`` and rebuilt on demand after ``restore_memory``
    #: (subclasses add their own caches).
    CACHE_ATTRIBUTES = frozenset({"_frame", "_reflector_cache", "last_frame_note"})

    @property
    def needs_calibration(self) -> bool:
        """True while the time model has no calibration of this stage's tracing."""
        return not self.time_model.calibrated

    def calibrate(
        self, samples: list[tuple], rays: int, pixels: int,
        records: Sequence[TraceRecord] = (),
    ) -> tuple[float, ...]:  # fmt: skip
        """A calibration of this stage's tracing before the first round: timed rounds
        ``(rays, ms, filled, reused, screen-space pixels)`` set the time model's prior
        (``TraceTimeModel.calibrate``); their ``rays`` over the ``pixels`` that started
        rays seed the mean rays per pixel, which predicts reflectors never traced, and
        each reflector's ``records`` its own rays per pixel, drawn towards that mean by
        CALIBRATION_PRIOR_PIXELS (a reflector sampled at a few pixels), unless a trace
        already taught them; their marched pixels, whether screen space is on. Returns
        the prior: (fixed ms, ms per ray, rays per filled, reused and marched pixel)."""
        model = self.time_model
        model.calibrate(samples)
        if self._global_pixels <= 0.0 and pixels > 0 and rays > 0:
            self._global_rays, self._global_pixels = float(rays), float(pixels)
            counted = [r for r in records if r.pixels > 0 and r.marched is not None]
            if counted:  # full density: every pixel started rays
                self._marched = [float(sum(r.marched for r in counted)),
                                 float(sum(r.pixels for r in counted))]  # fmt: skip
        if self._global_pixels > 0.0:
            mean, k = self._global_rays / self._global_pixels, CALIBRATION_PRIOR_PIXELS
            for rec in records:
                if rec.pixels > 0 and rec.rays >= 0 and rec.source not in self.rays_per_pixel:
                    rpp = (rec.rays + k * mean) / (rec.pixels + k)
                    self.rays_per_pixel[int(rec.source)] = max(rpp, MIN_RAYS_PER_PIXEL)
        return model.prior_overhead_ms, model.prior_ms_per_ray, *model.kind_rays

    def memory(self) -> dict:
        """The policy's memory across frames as plain JSON data (for checkpoints): every
        attribute but the caches, between frames. ``restore_memory`` on a fresh policy of
        the same name and parameters makes it select exactly as this one would."""
        if self._frame is not None:
            raise PhrtError("a policy's memory is saved between frames only")
        state = {k: v for k, v in vars(self).items() if k not in self.CACHE_ATTRIBUTES}
        state["time_model"] = vars(self.time_model)
        return {"policy": self.name, "state": to_plain(state)}

    def restore_memory(self, memory: dict) -> None:
        """Set the memory saved by ``memory()``; PhrtError if it is not this policy's or
        does not have this policy's attributes and types (nothing is changed then)."""
        if not isinstance(memory, dict) or memory.get("policy") != self.name:
            raise PhrtError(f"saved policy memory is not a {self.name} policy's")
        state = from_plain(memory.get("state"))
        expected = {k: v for k, v in vars(self).items() if k not in self.CACHE_ATTRIBUTES}
        model = state.pop("time_model", None) if isinstance(state, dict) else None
        if (
            not isinstance(state, dict)
            or not isinstance(model, dict)
            or not same_shape(state, {k: v for k, v in expected.items() if k != "time_model"})
        ):
            raise PhrtError(f"saved {self.name} policy memory has other fields or types")
        if not same_shape(model, vars(self.time_model)) or len(model["jitter_ms"]) != len(
            model["jitter_rays"]
        ):
            raise PhrtError(f"saved {self.name} cost model has other fields or types")
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
        G, ray_shares = element_figures(scene)
        self._frame = _FrameState(
            view=view, scene=scene, pixels=pixels, centers=centers, D=D,
            V=visibility(A, P, D), K=K, G=G, ray_shares=ray_shares,
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
        frame.kind_rays = self.time_model.kind_rays if budget.ms is not None else (0.0,) * 3
        ids = self._choose(budget)
        if not ids and not frame.traced:
            frame.untraced_reason = self._untraced_reason(budget)
            if self._starved_by_time(budget):
                self.time_model.relax()
        cost = {e: self.level_rays(e, frame.levels.get(e, 0)) for e in ids}
        for e in ids:
            level = frame.levels.get(e, 0)
            frame.predicted_rays[e] = self.predicted_rays(e) * self.level_share(e, level)
        if ids:
            # The round's predicted time (fixed overhead included), shared among its
            # reflectors by cost, so that summing predicted_ms over a frame's selection
            # gives the frame's predicted trace time.
            rays = sum(cost.values())
            round_ms = self.time_model.predicted_ms(rays)
            for e in ids:
                share = cost[e] / rays if rays > 0.0 else 1.0 / len(ids)
                frame.predicted_ms[e] = round_ms * share
            frame.predicted_trace_ms += round_ms
            frame.expected_trace_ms += self.time_model.expected_ms(rays)
            frame.round_rays = rays
        frame.traced.extend(ids)
        return ids

    def record(self, records: list[TraceRecord], seconds: float) -> None:
        frame = self._require_frame()
        frame.rays.clear()  # rays per pixel change below
        n = len(frame.scene.elements)
        total_rays = 0
        made = np.zeros(3)  # pixels filled, reused and marched in screen space
        for rec in records:
            total_rays += max(int(rec.rays), 0)
            src = int(rec.source)
            if not 0 <= src < n:
                continue
            kinds = made_without_rays(rec, frame.levels.get(src))
            made += kinds
            learn_reused_share(self.reused_share, src, kinds[0], kinds[1])
            if rec.marched is not None:  # of the pixels that started rays, those marched
                k, started = TIME_MODEL_DECAY, rec.pixels - kinds[0] - kinds[1]
                self._marched = [k * self._marched[0] + kinds[2], k * self._marched[1] + started]
            bounces = max(int(rec.max_reflector_bounces), 0)
            # Q = 1 + bounces, capped at the bounce limit (Q >= 1 even for a limit of 0).
            self.Q[src] = float(min(1 + bounces, max(self.bounce_limit, 1)))
            if rec.pixels > 0 and rec.rays >= 0:
                # Rays per pixel at full density: a record counts every covered pixel,
                # rays start at the density's share of them.
                level = frame.levels.get(src, 0)
                pixels = rec.pixels * self._started(src, level, rec.pixels)
                rpp = max(rec.rays / pixels, MIN_RAYS_PER_PIXEL)
                average_into(self.rays_per_pixel, src, rpp, RAYS_PER_PIXEL_ALPHA)
                self._global_rays = TIME_MODEL_DECAY * self._global_rays + rec.rays
                self._global_pixels = TIME_MODEL_DECAY * self._global_pixels + pixels
            # The latest trace of a source replaces what it was seen to reflect before.
            hits = {}
            for j, count in rec.hits.items():
                j = int(j)
                if j != src and 0 <= j < n and frame.scene.elements[j].is_reflector:
                    hits[j] = min(max(count, 0) / max(rec.pixels, 1), 1.0)
            self.reflects[src] = hits
            self.discovered.update(hits)
        self.time_model.learn(
            total_rays, float(seconds) * 1000.0, frame.round_rays, *made.tolist()
        )
        frame.round_rays = 0.0

    def end_frame(self) -> dict[int, ReflectorMetrics]:
        frame = self._require_frame()
        metrics = self.metrics()
        self.previous_selection = set(frame.traced)
        self.previous_levels = {e: v for e, v in frame.levels.items() if e in frame.traced}
        self.last_predicted_trace_ms = frame.predicted_trace_ms
        self.last_frame_note = FrameNote(
            expected_trace_ms=frame.expected_trace_ms,
            untraced_reason=frame.untraced_reason if not frame.traced else None,
        )
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
        V_gained = float(frame.V[element]) * float(frame.G[element])  # rough: less (G)
        return (S * self.selection_weight + V_gained) * float(frame.K[element])

    def predicted_rays(self, element: int) -> float:
        """Predicted rays to trace ``element``'s pixels: pixels * rays per pixel (the
        budgets' margins are in ``ray_allowance``). Rays per pixel: the element's own
        learned average; else the mean over everything traced so far; else Q * (1 +
        the shadow rays a hit casts at most, ``light_sampling.shadow_rays_per_hit``)
        (one reflection ray and its hit's shadow rays, per bounce) times the share of
        its pixels that start rays (``model.reflection_roughness.ray_share``)."""
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
                n_lights = len(lights.distant) + len(lights.local)
                rpp = self.q_of(element) * (1 + shadow_rays_per_hit(n_lights))
                # Only its share of pixels that start rays (a glossy reflector's pattern).
                rpp *= float(frame.ray_shares[element, 0])
        frame.rays[element] = rays = pixels * max(rpp, MIN_RAYS_PER_PIXEL)
        return rays

    def level_share(self, element: int, level: int) -> float:
        """Share of ``element``'s pixels this frame that start rays at density
        TRACE_DENSITIES[level], relative to full density (``_started``)."""
        return self._started(element, level, float(self._require_frame().pixels[element]))

    def _started(self, element: int, level: int, pixels: float) -> float:
        """``model.reflection_roughness.started_share`` of ``element`` at ``level`` for
        ``pixels`` (``traced_fraction`` for a mirror; a glossy reflector's own pattern
        saves less)."""
        return started_share(self._require_frame().ray_shares[element], pixels, level)

    def level_rays(self, element: int, level: int) -> float:
        """What tracing ``element`` at density TRACE_DENSITIES[level] costs, in rays: its
        ``predicted_rays`` at that density's share of its pixels; under a time budget
        also its other pixels at the expected mix of reused and filled (its
        ``reused_share``; never traced at a reduced density: all filled), and its pixels
        that start rays at the march's cost when screen space is on (the share of the
        recent rounds' pixels that were marched), each at the time model's cost
        (``kind_rays``; ``select.pixel_kind_shares``)."""
        share = self.level_share(element, level)
        frame = self._require_frame()
        rays = self.predicted_rays(element) * share
        fill, reuse, march = frame.kind_rays
        if not (fill or reuse or march):
            return rays
        pixels = float(frame.pixels[element])
        # The share that starts rays: the level's, at level 0 the view's own density's
        # (whose rays per pixel count every covered pixel); of all its covered pixels (a
        # glossy reflector's own pattern skips some at full density too, whose filter
        # costs as a fill: ``model.reflection_roughness``).
        traced = share if level else traced_fraction(pixels, frame.view.trace_density)
        traced *= float(frame.ray_shares[element, 0])
        cost = skipped_cost(pixels, traced, self.reused_share.get(element, 0.0), fill, reuse)
        if march and self._marched[1] > 0.0:
            cost += march * pixels * traced * self._marched[0] / self._marched[1]
        return rays + cost

    def fewest_rays(self, element: int) -> float:
        """The fewest predicted rays this policy could trace ``element`` with: at full
        density (HEU1: at its coarsest density step)."""
        return self.predicted_rays(element)

    def round_densities(self, ids: list[int]) -> list[str]:
        """The trace density of each of a round's ``ids`` (the renderer's argument to
        ``Tracer.trace_reflections``): the view's, unless the policy chose a coarser one."""
        frame = self._require_frame()
        levels = frame.levels
        return [TRACE_DENSITIES[levels[e]] if e in levels else frame.view.trace_density
                for e in ids]  # fmt: skip

    def predicted_ms(self, rays: float) -> float:
        """Milliseconds a candidate's ``rays`` add to a round (time safety included; the
        round's fixed overhead is not, see ``TraceTimeModel``). Used for the metrics of
        candidates not selected; selected ones get their share of their round's time."""
        return self.time_model.ms_per_ray * max(rays, 0.0) * self.time_model.safety

    def ray_allowance(self, budget: Budget) -> float:
        """The budget as a number of predicted rays: the smaller of ``budget.rays`` /
        RAYS_SAFETY and the rays the time model says fit in ``budget.ms`` (its safety
        factor included); ``inf`` when both are None."""
        allowance = self._rays_budget_allowance(budget)
        if budget.ms is not None:
            ms = 0.0 if math.isnan(budget.ms) else float(budget.ms)  # NaN: nothing is known
            allowance = min(allowance, self.time_model.rays_within(ms))
        return allowance

    @staticmethod
    def _rays_budget_allowance(budget: Budget) -> float:
        """Predicted rays a rays budget admits: ``budget.rays`` / RAYS_SAFETY (inf
        without one)."""
        if budget.rays is None:
            return math.inf
        return float(max(budget.rays, 0)) / RAYS_SAFETY

    def _untraced_reason(self, budget: Budget) -> str | None:
        """Why a first round selected nothing, with the numbers: the budget against the
        cheapest visible candidate's predicted cost, or the policy's choice when that one
        fits. None when no reflector is visible."""
        frame = self._require_frame()
        visible = self._untraced_visible()
        if not visible:
            return None
        e = min(visible, key=lambda v: (self.fewest_rays(v), v))
        rays = self.fewest_rays(e)
        ms = self.time_model.predicted_ms(rays)
        name = getattr(frame.scene.elements[e], "path", f"element {e}")
        what = f"{name}, {rays:.0f} rays, {ms:.2f} ms"
        if rays > self._rays_budget_allowance(budget):
            return f"budget {budget.rays} rays < cheapest predicted cost ({what})"
        if budget.ms is not None and not ms <= budget.ms:
            return f"budget {budget.ms:.2f} ms < cheapest predicted cost ({what})"
        return f"{self.name} selected nothing though the cheapest fits ({what})"

    def _starved_by_time(self, budget: Budget) -> bool:
        """True if a visible candidate would fit the rays budget but not the time one."""
        if budget.ms is None or not budget.ms > 0.0 or not self._untraced_visible():
            return False
        cheapest = min(self.fewest_rays(e) for e in self._untraced_visible())
        rays_ok = cheapest <= self._rays_budget_allowance(budget)
        return rays_ok and cheapest > self.time_model.rays_within(budget.ms)

    def metrics(self) -> dict[int, ReflectorMetrics]:
        """Figures for every candidate as of now (after the last recorded round)."""
        frame = self._require_frame()
        traced = set(frame.traced)
        candidates = self.candidates()
        C = self.costs_C(candidates)
        out = {}
        densities = dict(zip(frame.traced, self.round_densities(frame.traced), strict=True))
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
                trace_density=(traced_fraction(frame.pixels[e], densities[e])
                               if e in densities else math.nan),
            )  # fmt: skip
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
    follows_budget = False

    def _choose(self, budget: Budget) -> list[int]:
        return self._untraced_visible()


class NonePolicy(BudgetedPolicy):
    """Nothing is traced (raster only)."""

    name = "none"
    follows_budget = False

    def _choose(self, budget: Budget) -> list[int]:
        return []


class ListPolicy(BudgetedPolicy):
    """The given element ids that are visible reflectors, in one round, whatever the
    budget."""

    name = "list"
    follows_budget = False

    def __init__(self, explicit: list[int], *, selection_weight: float, bounce_limit: int):
        super().__init__(selection_weight=selection_weight, bounce_limit=bounce_limit)
        self.explicit = sorted({int(e) for e in explicit})

    def _choose(self, budget: Budget) -> list[int]:
        wanted = set(self.explicit)
        return [e for e in self._untraced_visible() if e in wanted]


POLICY_NAMES = ("heu1", "heu2", "all", "none", "list", "heu3")

#: Policies of other modules of this phase by name (``register_policy``): they subclass
#: BudgetedPolicy, so this module cannot import them. ``phrt_usd.select`` imports them,
#: so they are registered before any ``make_policy`` call.
REGISTERED_POLICIES: dict[str, type] = {}


def register_policy(cls: type) -> type:
    """Class decorator: ``make_policy(cls.name)`` makes a ``cls``."""
    REGISTERED_POLICIES[cls.name] = cls
    return cls


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
    if key == "heu2":
        return Heu2Policy(**common)
    if key == "all":
        return AllPolicy(**common)
    if key == "none":
        return NonePolicy(**common)
    if key in REGISTERED_POLICIES:  # heu1: select/heu1_policy.py, heu3: benefit_policy.py
        return REGISTERED_POLICIES[key](**common)
    if key == "list":
        if explicit is None:
            raise PhrtError("heuristic 'list' needs an explicit list of reflectors")
        return ListPolicy(explicit, **common)
    raise PhrtError(
        f"unknown heuristic {name!r} (phrt:heuristic): expected one of {', '.join(POLICY_NAMES)}"
    )
