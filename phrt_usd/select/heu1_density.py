"""HEU1's density steps (ours, docs/heuristic.md "Transition-aware selection"): when the
render traces at full density, a reflector that does not fit is traced at a rate of k/16
of its pixels, k = 15 down to 1 (``engine/trace/sparse_pixels.py``), instead of being
dropped or left out, reflectors of its round step coarser to make room for it, and one
below full density steps back finer once that fits. A step changes how sharp a
reflection is, not whether it is traced (no transition).
"""

from __future__ import annotations

import numpy as np

from phrt_usd.model.trace_density import COARSEST


class DensitySteps:
    """HEU1's density levels and steps, mixed into ``Heu1Policy`` (a ``BudgetedPolicy``,
    whose frame state and predicted rays they read, with HEU1's forecasts:
    ``forecast_curve``, ``_outgrows``, ``previous_visible``). A level is an index into
    ``model.trace_density.TRACE_DENSITIES`` (0 full, COARSEST the coarsest); the frame's
    levels (``_FrameState.levels``) hold the reflectors taken below full density.
    Methods only: the mixin has no state of its own (the policy's memory is unchanged).
    """

    def _steps(self) -> bool:
        """Density steps are on: the render traces at full density (``FrameView``)."""
        return self._require_frame().view.trace_density == "full"

    def fewest_rays(self, element: int) -> float:
        return self.level_rays(element, COARSEST if self._steps() else 0)

    def _level(self, e: int) -> int:
        """The density level ``e`` is offered at: a kept reflector's previous one (index
        into ``model.trace_density.TRACE_DENSITIES``), else full."""
        kept = e in self.previous_selection and self._steps()
        return self.previous_levels.get(e, 0) if kept else 0

    def _level_forecast(self, e: int, level: int) -> float | np.ndarray:
        """``forecast_curve`` of ``e`` traced at ``level`` (the density's share of it)."""
        return self.forecast_curve(e) * self.level_share(e, level)

    def _density_steps(
        self, ids: list[int], unfit: list[int], remaining: float, reserve: float
    ) -> list[int]:
        """HEU1's density steps (ours, ``Heu1Policy``'s docstring): after the graph's
        choice ``ids`` (``remaining`` rays of the round's allowance left), a claim the
        keep step could not fit (``unfit``, cheapest first) is taken at the finest coarser
        density that fits instead of being dropped, and a reflector entering the view that
        the graph did not take (too costly now, or forecast to outgrow the budget) at the
        finest density that fits with ``reserve`` to spare, full included, unless even its
        coarsest density is forecast to outgrow the budget (it would be dropped in view).
        Should it outgrow the density it is taken at, it steps coarser later (no
        transition); entering coarser than it fits cost the farm's sweep FLIP at 500 and
        1,000 rays for no lower temporal error (docs/heuristic.md). When even a
        reflector's coarsest density does not fit, reflectors of this round step coarser
        to make room for it (``_room``), if that frees enough.
        Then a reflector taken below full density (and not stepped to make room) steps to
        the finest density whose extra rays fit with ``reserve`` to spare. Its forecast is
        not asked: should it outgrow that density, it steps coarser again, by 1/16 of its
        pixels at a time, which is no transition (asking it, the farm's sweep read higher
        FLIP and temporal error at every rays budget from 200 to 1,000: docs/heuristic.md,
        "A rate, not four steps"). Returns the reflectors taken here; records their levels
        and forecasts in the frame."""
        frame = self._require_frame()
        budget = frame.first_allowance
        coarser = range(1, COARSEST + 1)
        taken: list[int] = []

        def take(e: int, level: int) -> None:
            nonlocal remaining
            # The finest density as cheap as ``level``: full below its ``sparse_floor``, where
            # every density traces every pixel (no step to report).
            level = next(v for v in range(level + 1)
                         if self.level_rays(e, v) <= self.level_rays(e, level))  # fmt: skip
            remaining -= self._set_level(e, level)
            taken.append(e)

        squeezed: set[int] = set()  # stepped coarser to make room: no step back this round

        def make_room(cost: float) -> bool:
            """Step reflectors of this round coarser until ``cost`` fits what remains."""
            nonlocal remaining
            freed = self._room(ids + taken, cost - remaining)
            if freed is None:
                return False
            squeezed.update(freed)
            for c, level in freed.items():
                remaining -= self._set_level(c, level, was=frame.levels.get(c, 0))
            return True

        for e in unfit:
            level = next((v for v in coarser if v > self._level(e)
                          and self.level_rays(e, v) <= remaining), None)  # fmt: skip
            if level is None and make_room(self.level_rays(e, COARSEST)):
                level = COARSEST
            if level is not None:
                take(e, level)
        chosen = set(ids)
        entering = [e for e in self._untraced_visible()
                    if e not in chosen and e not in self.previous_visible]  # fmt: skip
        for e in sorted(entering, key=lambda e: (-self.relevance_R(e), e)):
            if self._outgrows(e, budget, COARSEST):
                continue  # it would be dropped in view: a transition for a few frames
            level = next((v for v in range(COARSEST + 1)
                          if self.level_rays(e, v) + reserve <= remaining), None)  # fmt: skip
            if level is None:
                if make_room(self.level_rays(e, COARSEST) + reserve):
                    level = COARSEST
            if level is not None:
                take(e, level)
        for e in ids:
            level = frame.levels.get(e, 0)
            if not level or e in squeezed:
                continue
            room = remaining - reserve + self.level_rays(e, level)
            finer = next((v for v in range(level) if self.level_rays(e, v) <= room), None)
            if finer is not None:
                remaining -= self._set_level(e, finer, was=level)
        return taken

    def _set_level(self, e: int, level: int, was: int | None = None) -> float:
        """Record ``e`` traced at density ``level`` in this frame, in place of density
        ``was`` (None: not taken yet): its level (absent at full density) and its
        forecast in the frame's ``forecast_used``. Returns the predicted rays this adds
        to the round (negative when it frees some)."""
        frame = self._require_frame()
        if level:
            frame.levels[e] = level
        else:
            frame.levels.pop(e, None)
        frame.forecast_used = frame.forecast_used + self._level_forecast(e, level)
        added = self.level_rays(e, level)
        if was is not None:
            frame.forecast_used = frame.forecast_used - self._level_forecast(e, was)
            added -= self.level_rays(e, was)
        return added

    def _room(self, traced: list[int], need: float) -> dict[int, int] | None:
        """Density steps down of reflectors of this round (``traced``: taken in it, not
        traced yet) that free at least ``need`` predicted rays: element id → its new
        level, one step at a time, each time the step that frees the fewest rays among
        those that free enough, else the one that frees the most. {} if nothing is needed;
        None (nothing stepped) if even every step to the coarsest density frees too
        little."""
        if need <= 0.0:
            return {}
        frame = self._require_frame()
        levels = {c: frame.levels.get(c, 0) for c in traced}
        steps: dict[int, int] = {}
        while need > 0.0:
            saving = {c: self.level_rays(c, v) - self.level_rays(c, v + 1)
                      for c, v in levels.items() if v < COARSEST}  # fmt: skip
            saving = {c: x for c, x in saving.items() if x > 0.0}
            if not saving:
                return None
            enough = [c for c, x in saving.items() if x >= need]
            c = min(enough, key=lambda c: (saving[c], c)) if enough else max(
                saving, key=lambda c: (saving[c], -c))
            levels[c] += 1
            steps[c] = levels[c]
            need -= saving[c]
        return steps
