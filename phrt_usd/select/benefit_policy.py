"""HEU3 (ours, beyond the paper): trace the reflectors that buy the most image error per
predicted ray, learned from what tracing each one changed (docs/heuristic.md, "HEU3").

Every traced round tells the policy, per source reflector, how far the traced frame is
from the raster fallback it replaced (``TraceRecord.fallback_error``, the mean over the
reflector's traced pixels of the displayed change, set by
``render.compositing.observe_fallback_error``). Tracing a reflector again removes about
that much error from each of its pixels, so its *benefit* in a frame is

    b = K * A * e

with A its visible area (share of the image), K its priority and e its error per pixel:
the exponentially averaged observations (weight ERROR_ALPHA for the newest), blended with
the prior by a confidence that starts at 1 when observed and decays by CONFIDENCE_DECAY
per frame it is not traced. The prior for a reflector never traced is ``s * P / D``, so
that its benefit is ``s * V * K`` (V = A * P / D, Table 1): the paper's relevance in the
units of error, with the scale s fitted (decayed least squares through the origin) to the
observations, ``e ≈ s * P / D``; before any observation s = PRIOR_SCALE_INITIAL, which
only scales, so the first frame ranks by V * K per ray.

Selection is a greedy knapsack on benefit per predicted ray (``predicted_rays`` and the
time model of HEU1, ``BudgetedPolicy``), skipping what does not fit and going on, in
rounds while budget remains. HEU1's transition control: a reflector selected in the
previous frame has the paper's S * I added to its relevance (``(S * I * s + b)``, b in
V * K units through s) and its benefit per ray multiplied by KEEP_GAIN, so it is kept
unless a challenger buys KEEP_GAIN times more error per ray; a reflector not selected in
the previous frame joins only if ADMISSION_MARGIN of the frame's budget stays free after
it (as HEU1's admission), REJOIN_MARGIN if it was in view then (taking it is a
transition).

Memory (checkpoints, ``BudgetedPolicy.memory``): the per-reflector tables and the prior
fit's sums below are plain numbers keyed by element id, shape-checked on restore.
"""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.model.frame import Budget, TraceRecord
from phrt_usd.select.policies import ADMISSION_MARGIN, BudgetedPolicy, register_policy

#: Weight of the newest observation in a reflector's error per pixel (as
#: RAYS_PER_PIXEL_ALPHA for its rays per pixel): what a reflector shows changes with the
#: view, so half of the estimate is the latest trace.
ERROR_ALPHA = 0.5
#: A reflector's confidence in its observed error decays by this per frame it is not
#: traced (half-life ~70 frames, ~3 s at 24 fps): an estimate from a far-away view
#: gives way to the prior slowly, not so fast that a dropped reflector is retried (two
#: transitions) every few frames.
CONFIDENCE_DECAY = 0.99
#: Below this confidence the observation is forgotten (the prior alone predicts).
CONFIDENCE_MIN = 1e-3
#: Forgetting of the prior fit's sums per observation (as TIME_MODEL_DECAY per round).
PRIOR_DECAY = 0.9
#: The prior's scale s before anything was observed: any positive value ranks the
#: never-traced reflectors alike (by V * K per ray); 1 is the identity.
PRIOR_SCALE_INITIAL = 1.0
#: Benefit-per-ray factor of a reflector selected in the previous frame (hysteresis): a
#: challenger must remove this many times more error per ray to displace it. 2 keeps
#: selections whose estimates jitter by tens of per cent between frames; a reflector
#: worth half of a challenger is still traded.
KEEP_GAIN = 2.0
#: A reflector in view in the previous frame but not selected then (taking it now is a
#: transition) joins only if this share of the frame's budget stays free after it, more
#: than ADMISSION_MARGIN: at small budgets (a few thousand rays) the rays that fit move
#: by tens of per cent from frame to frame with the time model, and a reflector dropped
#: for that would otherwise be taken back on the next frame. One entering the view is
#: no transition and needs ADMISSION_MARGIN only.
REJOIN_MARGIN = 0.3
#: Errors and scales are clamped here so that products and sums stay finite.
VALUE_MAX = 1e12


@register_policy
class Heu3Policy(BudgetedPolicy):
    """Greedy knapsack on learned benefit per predicted ray, with HEU1's hysteresis (the
    module docstring)."""

    name = "heu3"
    observes_fallback_error = True

    def __init__(self, *, selection_weight: float, bounce_limit: int) -> None:
        super().__init__(selection_weight=selection_weight, bounce_limit=bounce_limit)
        #: Element id → exponentially averaged observed error per traced pixel, [0, 1].
        self.error_per_pixel: dict[int, float] = {}
        #: Element id → confidence in ``error_per_pixel``, (CONFIDENCE_MIN, 1].
        self.error_confidence: dict[int, float] = {}
        #: Decayed sums of the prior fit e ≈ s * x with x = P / D: sum x * e, sum x * x.
        self.prior_xy = 0.0
        self.prior_xx = 0.0
        #: Reflectors with pixels in the previous frame (REJOIN_MARGIN).
        self.previous_visible: set[int] = set()

    # ---- learning

    def record(self, records: list[TraceRecord], seconds: float) -> None:
        frame = self._require_frame()
        n = len(frame.scene.elements)
        for rec in records:
            src = int(rec.source)
            error = rec.fallback_error
            if not 0 <= src < n or error is None or rec.pixels <= 0:
                continue
            error = min(max(float(error), 0.0), 1.0) if math.isfinite(error) else 0.0
            old = self.error_per_pixel.get(src)
            a = ERROR_ALPHA
            self.error_per_pixel[src] = error if old is None else a * error + (1 - a) * old
            self.error_confidence[src] = 1.0
            x = self._prior_x(src)
            if x > 0.0:
                self.prior_xy = PRIOR_DECAY * self.prior_xy + x * error
                self.prior_xx = PRIOR_DECAY * self.prior_xx + x * x
        super().record(records, seconds)

    def end_frame(self):
        frame = self._require_frame()
        traced = set(frame.traced)
        for e in list(self.error_confidence):
            if e not in traced:
                c = self.error_confidence[e] * CONFIDENCE_DECAY
                if c < CONFIDENCE_MIN:
                    del self.error_confidence[e]
                    del self.error_per_pixel[e]
                else:
                    self.error_confidence[e] = c
        self.previous_visible = set(np.flatnonzero(frame.pixels > 0).tolist())
        return super().end_frame()

    # ---- figures

    def prior_scale(self) -> float:
        """s of the prior e ≈ s * P / D: fitted to the observations, else the initial."""
        if self.prior_xx > 0.0:
            return float(min(max(self.prior_xy / self.prior_xx, 0.0), VALUE_MAX))
        return PRIOR_SCALE_INITIAL

    def _prior_x(self, element: int) -> float:
        """P / D of ``element`` in this frame (V / A; 0 for a reflector out of view)."""
        frame = self._require_frame()
        pixels = float(frame.pixels[element])
        if pixels <= 0.0:
            return 0.0
        area = pixels / max(frame.view.width * frame.view.height, 1)
        return float(min(frame.V[element] / area, VALUE_MAX))

    def error_estimate(self, element: int) -> float:
        """Predicted error per pixel tracing ``element`` removes: the observed average
        blended with the prior ``s * P / D * G`` (G the gain from tracing at its
        roughness, docs/heuristic.md) by the observation's confidence. >= 0."""
        gain = float(self._require_frame().G[element])  # a rough reflector's: less
        prior = min(self.prior_scale() * self._prior_x(element) * gain, VALUE_MAX)
        c = self.error_confidence.get(element, 0.0)
        if c <= 0.0:
            return prior
        return c * self.error_per_pixel[element] + (1.0 - c) * prior

    def benefit(self, element: int) -> float:
        """K * A * error estimate: the share of the image's mean error tracing
        ``element`` removes in this frame, weighted by its priority. >= 0, finite."""
        frame = self._require_frame()
        area = float(frame.pixels[element]) / max(frame.view.width * frame.view.height, 1)
        return float(min(frame.K[element] * area * self.error_estimate(element), VALUE_MAX))

    def relevance_R(self, element: int) -> float:
        """HEU3's R: the benefit with the paper's S * I bonus, ``(S * I * s + b) * K``
        (b the benefit without K), what stats and the selection layer report as R."""
        frame = self._require_frame()
        S = 1.0 if element in self.previous_selection else 0.0
        bonus = S * self.selection_weight * self.prior_scale() * float(frame.K[element])
        return float(min(bonus + self.benefit(element), VALUE_MAX))

    def score(self, element: int) -> float:
        """Benefit per predicted ray, times KEEP_GAIN for last frame's selection."""
        rays = max(self.predicted_rays(element), 1.0)
        gain = KEEP_GAIN if element in self.previous_selection else 1.0
        return gain * self.relevance_R(element) / rays

    # ---- selection

    def _choose(self, budget: Budget) -> list[int]:
        frame = self._require_frame()
        remaining = self.ray_allowance(budget)
        if not remaining > 0.0:
            return []
        if frame.first_allowance is None:
            frame.first_allowance = remaining
        reserve = ADMISSION_MARGIN * frame.first_allowance
        rejoin = REJOIN_MARGIN * frame.first_allowance
        candidates = self._untraced_visible()
        scores = np.array([self.score(e) for e in candidates], dtype=np.float64)
        chosen = []
        # Highest score first; ties by id (deterministic).
        for k in sorted(range(len(candidates)), key=lambda k: (-scores[k], candidates[k])):
            e = candidates[k]
            cost = self.predicted_rays(e)
            if e in self.previous_selection:
                need = cost
            else:
                need = cost + (rejoin if e in self.previous_visible else reserve)
            if need <= remaining:
                chosen.append(e)
                remaining -= cost
        return chosen
