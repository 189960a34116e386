"""Selection figures of a rendered path: how many reflectors were traced, and transitions.

Every count of transitions in phrt (``phrt report``, the sweep's per-frame ``transitions``
column, ``tools/policy_replay.py``) is made here, from two arrays over F frames and R
reflectors::

    selected, visible : (F, R) bool    row f = the f-th rendered frame, in time order;
                                       column r = one reflector (same order in both)

``visible[f, r]``: reflector r has pixels in frame f; ``selected[f, r]``: it was ray-traced
there. Consecutive rows are consecutive rendered frames (a gap between merged sub-ranges
of a run counts as consecutive).

Transition (paper §5.1): a reflector visible in two consecutive frames f-1 and f whose
``selected`` differs between them, i.e. it switched between raster and ray tracing while
it stayed in view. A reflector entering or leaving the view is never a transition, however
it is drawn. A *chance* (to switch) is a pair (f, r) with r visible in both f-1 and f;
``transition_rate`` = transitions / chances. A transition is an *admission* when the
reflector is selected in the later frame, a *drop* when it is not.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from phrt_usd.model.trace_density import TRACE_DENSITIES


def transition_chances(visible: np.ndarray) -> np.ndarray:
    """(F-1, R) bool: reflector r visible in both frame f and frame f+1 (rows f = 0..F-2).

    visible : (F, R) bool; F = 0 gives (0, R).
    """
    return visible[1:] & visible[:-1]


def transition_mask(selected: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(F-1, R) bool: reflector r makes a transition between frame f and frame f+1.

    selected, visible : (F, R) bool (see the module docstring for the definition).
    """
    return transition_chances(visible) & (selected[1:] != selected[:-1])


def transitions_per_frame(selected: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(F,) int64: transitions from the frame before into each frame (0 for the first).

    selected, visible : (F, R) bool.
    """
    counts = np.zeros(selected.shape[0], dtype=np.int64)
    counts[1:] = np.count_nonzero(transition_mask(selected, visible), axis=1)
    return counts


def admissions_and_drops(selected: np.ndarray, visible: np.ndarray) -> tuple[int, int]:
    """(admissions, drops): the transitions into selected, and out of it.

    selected, visible : (F, R) bool. admissions + drops = transitions.
    """
    switched = transition_mask(selected, visible)
    admissions = int(np.count_nonzero(switched & selected[1:]))
    return admissions, int(np.count_nonzero(switched)) - admissions


def density_levels(densities: Mapping[str, str], reflectors: Sequence[str]) -> np.ndarray:
    """(R,) int64 levels of one frame for ``density_steps``: the index in
    ``model.trace_density.TRACE_DENSITIES`` of each of ``reflectors`` (prim paths) that
    ``densities`` (a frame's ``FrameStats.densities``: path → density) names, else 0."""
    return np.array([TRACE_DENSITIES.index(densities[p]) if p in densities else 0
                     for p in reflectors], dtype=np.int64).reshape(-1)  # fmt: skip


def density_steps(selected: np.ndarray, visible: np.ndarray, levels: np.ndarray) -> int:
    """Density steps: a reflector traced in two consecutive frames, in view in both, at
    another trace density in the later one (HEU1's density steps; not transitions, the
    reflection stays ray-traced and only its sharpness changes).

    selected, visible : (F, R) bool; levels : (F, R) int64 trace density of each traced
    reflector (index into ``model.trace_density.TRACE_DENSITIES``; 0 where not traced).
    """
    both = transition_chances(visible) & selected[1:] & selected[:-1]
    return int(np.count_nonzero(both & (levels[1:] != levels[:-1])))


def selection_metrics(selected: np.ndarray, visible: np.ndarray) -> dict[str, Any]:
    """Selection figures of F frames (rows, in time order) × R reflectors (columns).

    selected, visible : (F, R) bool

    Keys: frames, reflectors, mean_selected and mean_visible (reflectors per frame; None
    without frames), transitions, transition_pairs (chances), transition_rate (None
    without chances).
    """
    frames = int(selected.shape[0])
    transitions = int(np.count_nonzero(transition_mask(selected, visible)))
    pairs = int(np.count_nonzero(transition_chances(visible)))
    return {
        "frames": frames,
        "reflectors": int(selected.shape[1]),
        "mean_selected": float(selected.sum(axis=1).mean()) if frames else None,
        "mean_visible": float(visible.sum(axis=1).mean()) if frames else None,
        "transitions": transitions,
        "transition_pairs": pairs,
        "transition_rate": transitions / pairs if pairs else None,
    }
