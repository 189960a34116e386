"""HEU1: the paper's heuristic on a Selection Graph, made transition-aware (the class
docstring lists what is the paper's and what is ours; docs/heuristic.md,
"Transition-aware selection"). Its cost forecasts (pixel growth, the lookahead over the
camera path) are in ``heu1_forecast``, its density steps in ``heu1_density``. Registered
with ``policies.make_policy`` as "heu1" when ``phrt_usd.select`` is imported, like HEU3
(``benefit_policy``).
"""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.model.frame import Budget, FrameView, ReflectorMetrics
from phrt_usd.model.scene import Scene
from phrt_usd.model.trace_density import COARSEST
from phrt_usd.select.heu1_density import DensitySteps
from phrt_usd.select.heu1_forecast import (
    FORECAST_HORIZON,
    FORECAST_MAX,
    GROWTH_MAX,
    GROWTH_WINDOW,
    BoxAreas,
    pixel_growth,
)
from phrt_usd.select.policies import ADMISSION_MARGIN, BudgetedPolicy, register_policy
from phrt_usd.select.selection_graph import Node, SelectionGraph


@register_policy
class Heu1Policy(DensitySteps, BudgetedPolicy):
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
      reflectors taken before it. A reflector entering the view is taken freely, unless
      (entering) the lookahead forecasts it to cost more than the whole budget while its
      box is on screen: it would be dropped in view, a transition for a few frames;
    * with a lookahead (upcoming cameras) a forecast is a curve, one predicted cost per
      upcoming frame (box screen area there / now), and the horizon budget is checked
      frame by frame against the sum of the selection's curves, not against the sum of
      their peaks (reflectors that peak at different frames, or leave the view, can be
      kept together); a kept reflector forecast to outgrow the budget charges its curve
      only up to that frame;
    * density steps (when the render traces at full density): a kept reflector that no
      longer fits is traced at a rate of k/16 of its pixels, the finest that fits
      (``sparse_pixels``), instead of being dropped, a reflector entering the view that
      does not fit is taken at such a density, and one forecast to outgrow the budget at
      the finest density that fits now (it steps coarser as it grows); when even
      its coarsest density does not fit, reflectors of the round step coarser to make
      room for it (for a claim, or one entering the view: taken later it would be a
      transition); a reflector below full density steps back to the finest density
      that fits with the admission margin. A
      step changes how sharp a reflection is, not whether it is traced (no transition:
      docs/heuristic.md);
    * hold: when the time model lets none of the previous frame's selection be traced
      (a slow spell it has just learned: even the cheapest claim is predicted above T)
      while the rays budget would, the claims still in view are traced at their
      coarsest density all the same, for one frame. Dropping them all would cost two
      transitions each once the spell passes (on the farm at T = 1 ms, 13 of a run's 14);
      holding costs that frame's overrun, and its measured round corrects the model. A
      second starved frame in a row drops them;
    * leftover: rounds after the first fill what the measured rounds left of T, and the
      admission margin there is a share of that leftover, not of the whole budget (with
      a time budget the first round plans only ~1/safety of T, and a margin of
      10 % of T took most of what was left).

    Deviations from the paper (§4.2: the most relevant nodes whose cost fits, S·I as
    the only hysteresis): the keep step, the admission margin, the forecasts, the
    shrinking/outgrowing rules, the density steps and the hold above are ours (docs/heuristic.md,
    "Transition-aware selection"); the relevance R, the Selection Graph walk and the
    rounds while time remains are the paper's.
    """

    name = "heu1"
    CACHE_ATTRIBUTES = BudgetedPolicy.CACHE_ATTRIBUTES | {"_box_areas", "_growth_curves"}

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
        #: The previous frame held its claims (``_hold``): this one may not.
        self.held = False
        #: This frame's lookahead growth per reflector in view (element id → largest
        #: bounding-box screen area over the upcoming cameras / the current one, >= 1);
        #: empty when the view has no upcoming cameras.
        self.lookahead_growth: dict[int, float] = {}
        #: Screen area of every reflector's box per camera of the path (a cache).
        self._box_areas = BoxAreas()
        #: This frame's lookahead per reflector in view: element id → (W,) float64 screen
        #: area of its box at each of the next W <= LOOKAHEAD_FRAMES upcoming cameras / its
        #: area now (>= 0, finite; 0 where the box is off-screen); {} without upcoming
        #: cameras.
        self._growth_curves: dict[int, np.ndarray] = {}

    def begin_frame(self, view: FrameView, scene: Scene) -> None:
        super().begin_frame(view, scene)
        frame = self._require_frame()
        history = {}
        for e in np.flatnonzero(frame.pixels > 0).tolist():
            history[e] = [*self.pixel_history.get(e, [])[-GROWTH_WINDOW:], int(frame.pixels[e])]
        self.pixel_history = history  # a reflector out of view starts afresh
        self._growth_curves = self._box_areas.growth_curves(
            view, scene, self._reflectors_of(scene), np.fromiter(history, int)
        )
        self.lookahead_growth = {
            e: float(max(curve.max(initial=1.0), 1.0)) for e, curve in self._growth_curves.items()
        }

    def end_frame(self) -> dict[int, ReflectorMetrics]:
        frame = self._require_frame()
        visible = set(np.flatnonzero(frame.pixels > 0).tolist())
        self.forced_out = ((self.forced_out | frame.unfit_claims) & visible) - set(frame.traced)
        self.previous_visible = visible
        self.held = frame.held
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
            growth[element] = pixel_growth(self.pixel_history.get(element, []))
        return growth[element]

    def forecast_rays(self, element: int) -> float:
        """Predicted rays within the forecast's horizon: with upcoming cameras,
        ``predicted_rays`` times the lookahead growth (LOOKAHEAD_FRAMES ahead); otherwise
        ``predicted_rays * g**H`` with the pixel growth g clamped to [1, GROWTH_MAX] and
        H = FORECAST_HORIZON. Finite (<= FORECAST_MAX)."""
        growth = self.lookahead_growth.get(element)
        if growth is None:
            growth = min(max(self.growth(element), 1.0), GROWTH_MAX) ** FORECAST_HORIZON
        return float(min(self.predicted_rays(element) * growth, FORECAST_MAX))

    def forecast_curve(self, element: int) -> float | np.ndarray:
        """With upcoming cameras: (W,) float64 predicted rays at each of the next W
        frames (``predicted_rays`` scaled by its box's screen area there over now: 0 once
        the box is off-screen); without: ``forecast_rays`` (one number)."""
        curve = self._growth_curves.get(element)
        if curve is None:
            return self.forecast_rays(element)
        return np.minimum(self.predicted_rays(element) * curve, FORECAST_MAX)

    def _node(self, e: int, reserve: float, budget: float) -> Node:
        frame = self._require_frame()
        kept = e in self.previous_selection
        level = self._level(e)
        forecast = self._level_forecast(e, level)
        over = np.asarray(forecast) > budget
        if kept and over.any():
            # It will outgrow the whole budget within the horizon and be dropped whatever
            # is decided now: what it holds of the budget is not a lasting commitment
            # (with a lookahead: from the frame it outgrows the budget on).
            forecast = 0.0 if np.ndim(forecast) == 0 else np.where(np.cumsum(over), 0.0, forecast)
        return Node(
            element=e,
            R=self.relevance_R(e),
            cost=self.level_rays(e, level),
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
        charges no forecast). Left out: candidates in view in the previous frame, not
        selected then, and shrinking now (taking one would be a transition for a
        reflector that is on its way out of the view), and, with a lookahead, candidates
        entering the view whose forecast outgrows ``budget`` while their box is on
        screen (``_outgrows``)."""
        frame = self._require_frame()
        done = set(frame.traced)
        return SelectionGraph(
            self._node(e, reserve, budget)
            for e in self.candidates()
            if e not in done and not self._leaving(e) and not self._outgrows(e, budget)
        )

    def _outgrows(self, e: int, budget: float, level: int = 0) -> bool:
        """Entering the view (not in view in the previous frame, so not selected then),
        and with a lookahead forecast to cost more than ``budget`` at density ``level``
        in one of the next LOOKAHEAD_FRAMES frames: it would be dropped while in view,
        one transition for a few frames of tracing (class docstring, "entering")."""
        if e in self.previous_visible or e in self.previous_selection:
            return False
        curve = self._growth_curves.get(e)
        return curve is not None and bool(np.any(self.level_rays(e, level) * curve > budget))

    def _leaving(self, e: int) -> bool:
        """In view in the previous frame, not selected then, and shrinking now."""
        return (
            e in self.previous_visible and e not in self.previous_selection and self.growth(e) < 1.0
        )

    def _choose(self, budget: Budget) -> list[int]:
        frame = self._require_frame()
        ids = self._choose_within(budget)
        if not ids and not frame.traced:
            ids = self._hold(budget)
        return ids

    def _hold(self, budget: Budget) -> list[int]:
        """HEU1's hold (ours, class docstring): the previous frame's selection still in
        view, each at its coarsest density, when the time model lets none of them be
        traced in this frame (``_starved_by_time``) and the previous frame was no hold;
        else []."""
        frame = self._require_frame()
        claims = sorted(e for e in self.previous_selection if frame.pixels[e] > 0)
        if self.held or not claims or not self._starved_by_time(budget):
            return []
        level = COARSEST if self._steps() else 0
        for e in claims:
            if self.level_share(e, level) < 1.0:
                frame.levels[e] = level
        frame.held = True
        return claims

    def _choose_within(self, budget: Budget) -> list[int]:
        """The round's selection within ``budget`` (class docstring)."""
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
        # The horizon budget is the whole frame's budget, also in later rounds; the margin
        # is a share of what this round may spend (class docstring, "leftover").
        reserve = ADMISSION_MARGIN * allowance
        graph = self.graph(reserve=reserve, budget=frame.first_allowance)
        ids = graph.select(allowance, horizon_budget=frame.first_allowance - frame.forecast_used)
        if not ids and not frame.traced:
            # The admission margin would leave the whole budget idle (and the cost model
            # without a round to learn from: a still shot then never traced again). Once
            # taken, a reflector is kept without margin, so this delays no more than the
            # margin's first admission.
            graph = self.graph(reserve=0.0, budget=frame.first_allowance)
            ids = graph.select(allowance, horizon_budget=frame.first_allowance)
        for e in ids:
            frame.forecast_used = frame.forecast_used + graph.nodes[e].forecast
            if level := self._level(e):
                frame.levels[e] = level
        unfit = list(graph.unfit_claims)
        if self._steps():
            spent = sum(graph.nodes[e].cost for e in ids)
            ids += self._density_steps(ids, unfit, allowance - spent, reserve)
            unfit = [e for e in unfit if e not in ids]
        if not frame.traced:
            # The first round's keep step decides which claims cost pushes out; in later
            # rounds, kept reflectors not taken yet are ones that already lost or missed.
            frame.unfit_claims.update(unfit)
        return ids

