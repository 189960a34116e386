"""The Selection Graph of the paper (§4.1–4.2): which candidate reflectors to ray-trace.

One node per candidate reflector, holding the paper's relevance ``R`` and the calibrated
``cost`` the budget is checked against (predicted rays, see ``phrt_usd.select.policies``), which
takes the place of the paper's processing cost ``C`` here (``C`` is reported in the
policy's metrics but decides nothing). Two kinds of edges:

* the **cost list**: every node points to the next cheaper node (``next_cheaper``); the
  list starts at the most expensive node (``most_expensive``);
* **relevance edges**: every node points to all nodes that are *more relevant* and cost no
  more than it does (``more_relevant``).

Ties are broken by element id so the graph, and therefore the selection, is a pure
function of its nodes (the order in which nodes are given does not matter):

* cost order: higher ``cost`` first; equal cost → lower element id first;
* relevance order: higher ``R`` is more relevant; equal ``R`` → lower element id is more
  relevant.

Selection (``select``) has two steps. **Keep**: the nodes selected in the previous frame
(``kept``) keep their claim while they are at least as relevant as the strongest
*challenger* (the most relevant other node that could be taken, ``Node.challenger``);
their R includes the paper's ``S·I`` bonus, so a newcomer displaces one only by beating
its V by more than I.
The claimed nodes are taken first, cheapest first (the cost list walked from its tail), as
many as fit: when they no longer all fit, the fewest are dropped, the most expensive ones
(each drop is a visible switch from ray tracing to raster). **Admit**: among the other
nodes (kept ones that lost their claim included),
greedy by relevance. It walks the cost list from its head to the first node that fits the
remaining budget (the *entry*); every node from the entry on fits. The most relevant node
that fits is then the entry itself or one of its relevance edges, because every fitting
node costs no more than the entry. That node is taken, its cost subtracted, and the walk
continues from the entry (the remaining budget only shrinks, so nodes before it can never
fit again). The result is "greedy by relevance among the nodes that fit", which is what
the paper describes: the most relevant nodes whose cost fits the time left.

The graph is small (tens of nodes): it is plain Python lists and dicts, and a node's
relevance edges are listed when the walk first asks for them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Node:
    """One candidate reflector.

    element: element id (index into ``Scene.elements``).
    R: the paper's relevance (unitless, finite, >= 0).
    cost: what the budget is measured in (predicted rays, >= 0).
    traceable: False for candidates that cannot be traced on their own (no pixels in
        this frame: reflectors only seen through another reflector). They stay in the
        graph, and in its lists, but are never selected.
    reserve: budget that must remain free *beyond* ``cost`` for the node to be taken
        (the admission margin for nodes not selected in the previous frame; 0 for the
        ones that were, so a kept selection is not dropped for small cost noise).
    kept: selected in the previous frame: taken in the keep step (cheapest first),
        before any other node, unless a node that could be taken is more relevant.
    forecast: the node's cost forecast some frames ahead (unit of ``cost``, finite,
        >= 0): one number, or a (W,) float64 array, one forecast per frame of a horizon
        of W frames (HEU1's lookahead along the camera path). Every node taken uses up
        its forecast of the *horizon budget* of ``select`` (frame by frame for arrays).
    admission: the node is taken only if its ``forecast`` also fits what is left of the
        horizon budget, in every frame of the horizon (HEU1 sets it for reflectors that
        would switch to ray tracing while in view).
    challenger: the node can displace kept nodes less relevant than itself. HEU1 clears
        it for reflectors whose claim the keep step could not fit (``unfit_claims``):
        such a node may take free budget, but not push out the reflectors it was dropped
        in favour of (which would bring it back, and drop it again, every other frame).
    """

    element: int
    R: float
    cost: float
    traceable: bool = True
    reserve: float = 0.0
    kept: bool = False
    forecast: float | np.ndarray = 0.0
    admission: bool = False
    challenger: bool = True


class SelectionGraph:
    """Cost list + relevance edges over a set of ``Node``s (see the module docstring)."""

    def __init__(self, nodes: Iterable[Node]) -> None:
        self.nodes: dict[int, Node] = {}
        for node in nodes:
            if node.element in self.nodes:
                raise ValueError(f"duplicate node for element {node.element}")
            self.nodes[node.element] = node

        # Cost list: most expensive first, ties by ascending element id.
        self.by_cost: list[int] = sorted(self.nodes, key=lambda e: (-self.nodes[e].cost, e))
        self.most_expensive: int | None = self.by_cost[0] if self.by_cost else None
        self.next_cheaper: dict[int, int | None] = {
            e: (self.by_cost[k + 1] if k + 1 < len(self.by_cost) else None)
            for k, e in enumerate(self.by_cost)
        }

        # Relevance edges, each list ordered most relevant first, built on first use:
        # the admit walk only visits the edges of its entries.
        self._by_relevance = sorted(self.nodes, key=lambda e: (-self.nodes[e].R, e))
        self._relevance_rank = {e: k for k, e in enumerate(self._by_relevance)}
        self.more_relevant: dict[int, list[int]] = _Edges(self._relevance_edges)
        #: Set by ``select``: claimed kept nodes that did not fit.
        self.unfit_claims: list[int] = []

    def is_more_relevant(self, a: int, b: int) -> bool:
        """True if node ``a`` is more relevant than node ``b`` (higher R, ties: lower id)."""
        ra, rb = self.nodes[a].R, self.nodes[b].R
        return ra > rb or (ra == rb and a < b)

    def _relevance_edges(self, e: int) -> list[int]:
        """Node ``e``'s relevance edges: the nodes ahead of it in relevance order that cost
        no more than it does, most relevant first."""
        cost = self.nodes[e].cost
        ahead = self._by_relevance[: self._relevance_rank[e]]
        return [t for t in ahead if self.nodes[t].cost <= cost]

    def select(self, budget: float, horizon_budget: float | np.ndarray = math.inf) -> list[int]:
        """Keep, then admit (module docstring), within ``budget``.

        ``budget`` is in the unit of ``Node.cost`` (``float('inf')`` = unbounded). Returns
        element ids in the order they were taken (kept nodes cheapest first, then the
        others most relevant first); the sum of their costs is <= ``budget``. A
        non-positive or NaN budget selects nothing.

        ``horizon_budget`` (same unit; a number, or a (W,) array with one budget per
        frame of the horizon, the shape of the array forecasts) is a second tally: every
        node taken uses up its ``forecast`` of it, and an ``admission`` node is available
        only while its forecast fits what is left in every frame (kept nodes can take it
        below zero, which then blocks every admission node). The default, unbounded,
        leaves the forecasts out.

        Afterwards ``unfit_claims`` lists the claimed nodes the keep step could not fit
        (cheapest first); they are not taken in the admit step either.
        """
        self.unfit_claims: list[int] = []
        if not budget > 0.0:  # also catches NaN
            return []
        remaining = float(budget)
        horizon_left = np.asarray(horizon_budget, dtype=np.float64)

        def fits_horizon(n: Node) -> bool:
            return not n.admission or bool(np.all(n.forecast <= horizon_left))

        chosen: list[int] = []

        # The strongest challenger: the most relevant other node that could be taken.
        # A kept node less relevant than it (its R includes the S·I bonus) has lost its
        # claim to be kept, as in the paper, and competes by relevance below.
        challenger = max(
            (
                n.R
                for n in self.nodes.values()
                if not n.kept
                and n.challenger
                and n.traceable
                and n.cost + n.reserve <= remaining
                and fits_horizon(n)
            ),
            default=-math.inf,
        )
        claimed = {e for e, n in self.nodes.items() if n.kept and n.R >= challenger}
        # Keep: the claimed nodes, cheapest first, until one no longer fits (no costlier
        # one would either).
        keep = [e for e in reversed(self.by_cost) if e in claimed and self.nodes[e].traceable]
        for k, e in enumerate(keep):
            n = self.nodes[e]
            if n.cost > remaining:
                self.unfit_claims = keep[k:]
                break
            chosen.append(e)
            remaining -= n.cost
            horizon_left = horizon_left - n.forecast
        taken: set[int] = set(chosen)

        def available(e: int) -> bool:
            n = self.nodes[e]
            if e in taken or e in claimed or not n.traceable or n.cost + n.reserve > remaining:
                return False
            return fits_horizon(n)

        # Admit: greedy by relevance among the other nodes.
        entry = self.most_expensive
        while entry is not None:
            # Walk down the cost list to the most expensive node that can still be taken.
            if entry in taken or self.nodes[entry].cost > remaining:
                entry = self.next_cheaper[entry]
                continue
            # Every node that fits costs <= the entry: the best one is the first available
            # of its relevance edges (ordered by relevance), else the entry itself.
            best = next((t for t in self.more_relevant[entry] if available(t)), None)
            if best is None:
                if not available(entry):
                    entry = self.next_cheaper[entry]
                    continue
                best = entry
            taken.add(best)
            chosen.append(best)
            remaining -= self.nodes[best].cost
            horizon_left = horizon_left - self.nodes[best].forecast
        return chosen


class _Edges(dict):
    """``SelectionGraph.more_relevant``: a dict that fills an entry on first lookup."""

    def __init__(self, edges_of) -> None:
        super().__init__()
        self._edges_of = edges_of

    def __missing__(self, e: int) -> list[int]:
        self[e] = edges = self._edges_of(e)
        return edges
