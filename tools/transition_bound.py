"""Fewest transitions any selection can make on a recorded camera path (an offline bound).

For a recording made by ``tools/policy_replay.py capture`` and a rays budget B, solve the
integer program

    minimise    sum over frames f >= 1 and reflectors r in view at f-1 and f of |x[f,r] - x[f-1,r]|
    subject to  sum_r rays[f,r] * x[f,r] <= B             for every frame f
                sum_{f,r} x[f,r] >= frames * mean_selected
                x[f,r] in {0, 1},  x[f,r] = 0 where r is not in view at f

where ``rays[f,r]`` is what tracing r cost at f in the recording (its ``TraceRecord``).
The solution knows the whole camera path, so no online policy can do better with the
same costs; real policies also plan with a safety factor on predicted rays, which only
makes them more constrained. ``mean_selected`` defaults to HEU2's on the same budget
(replayed), the constraint the brief puts on HEU1. Solved with scipy's HiGHS MILP.

    uv run --with scipy python tools/transition_bound.py runs/replay/farm.json.gz \
        --budgets 500,1000,2000,4000

``--max-transitions 2,4,9`` solves the other side of the trade instead: the most rays any
selection traces (mean over frames with visible reflectors of traced rays / B, the
``budget use`` of ``policy_replay.py replay``) with at most that many transitions:

    maximise    sum_{f,r} rays[f,r] * x[f,r]
    subject to  the budget per frame as above,  transitions <= K

The recording is read with ``policy_replay.load_recording`` (plain JSON data, never
unpickled); a file that is not one is refused with one line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from policy_replay import RecordingError, load_recording, replay, transition_counts  # noqa: E402


def recorded_costs(data: dict) -> tuple[np.ndarray, np.ndarray]:
    """(F, R) float64 rays per reflector and frame (0 out of view) and (F, R) bool in view,
    over the recording's reflectors."""
    refl = data["reflectors"]
    rays = np.zeros((len(data["frames"]), len(refl)))
    visible = np.zeros(rays.shape, dtype=bool)
    for f, frame in enumerate(data["frames"]):
        for k, e in enumerate(refl):
            if frame.view.pixel_counts[e] > 0:
                visible[f, k] = True
                rays[f, k] = frame.records[e].rays
    return rays, visible


def _shared_rows(rays: np.ndarray, visible: np.ndarray, budget: float):
    """The constraints both programs share, as COO lists over the variables x[f, k]
    (reflector k traced in frame f: binary, index ``f * R + k``) and t[j] (pair j changes
    state: in [0, 1], index ``F * R + j``): each frame's traced rays fit ``budget``, and
    t[j] >= |x[f, k] - x[f - 1, k]| for every reflector visible in both frames (``pairs``,
    (m, 2): frame - 1, reflector). Returns (rows, cols, vals, lo, hi, pairs, t_index)."""
    F, R = rays.shape
    n_x = F * R
    x_index = np.arange(n_x).reshape(F, R)
    pairs = np.argwhere(visible[1:] & visible[:-1])
    t_index = n_x + np.arange(len(pairs))
    rows, cols, vals, lo, hi = [], [], [], [], []
    row = 0
    for f in range(F):  # budget per frame
        ks = np.flatnonzero(visible[f])
        rows += [row] * len(ks)
        cols += x_index[f, ks].tolist()
        vals += rays[f, ks].tolist()
        lo.append(-np.inf)
        hi.append(budget)
        row += 1
    for j, (f0, k) in enumerate(pairs):  # t >= x[f] - x[f-1] and t >= x[f-1] - x[f]
        a, b = x_index[f0, k], x_index[f0 + 1, k]
        for sign in (1.0, -1.0):
            rows += [row, row, row]
            cols += [t_index[j], a, b]
            vals += [1.0, sign, -sign]
            lo.append(0.0)
            hi.append(np.inf)
            row += 1
    return rows, cols, vals, lo, hi, pairs, t_index


def fewest_transitions(
    rays: np.ndarray, visible: np.ndarray, budget: float, mean_selected: float, time_limit: float
) -> tuple[float, float, str]:
    """(transitions, mean selected, solver status) of the optimum (or of the best
    solution found within ``time_limit`` seconds; the status says which)."""
    from scipy.optimize import Bounds, LinearConstraint, milp  # uv run --with scipy
    from scipy.sparse import coo_matrix

    F, R = rays.shape
    n_x = F * R
    rows, cols, vals, lo, hi, pairs, _ = _shared_rows(rays, visible, budget)
    m = len(pairs)
    row = len(lo)
    cost = np.concatenate([np.zeros(n_x), np.ones(m)])
    # Enough selections on average.
    ks = np.flatnonzero(visible.reshape(-1))
    rows += [row] * len(ks)
    cols += ks.tolist()
    vals += [1.0] * len(ks)
    lo.append(np.ceil(mean_selected * F - 1e-9))
    hi.append(np.inf)
    row += 1
    A = coo_matrix((vals, (rows, cols)), shape=(row, n_x + m)).tocsr()
    upper = np.concatenate([visible.reshape(-1).astype(float), np.ones(m)])
    integrality = np.concatenate([np.ones(n_x), np.zeros(m)])
    res = milp(
        cost,
        constraints=LinearConstraint(A, lo, hi),
        integrality=integrality,
        bounds=Bounds(np.zeros(n_x + m), upper),
        options={"time_limit": time_limit, "mip_rel_gap": 0.0},
    )
    if res.x is None:
        return float("nan"), float("nan"), res.message
    x = np.round(res.x[:n_x]).reshape(F, R)
    counts = transition_counts(x.astype(bool), visible)
    status = "optimal" if res.status == 0 else f"best found ({res.message})"
    # The proven lower bound of the objective when not solved to optimality.
    bound = getattr(res, "mip_dual_bound", None)
    if res.status != 0 and bound is not None:
        status += f", bound >= {bound:.1f}"
    return float(counts["transitions"]), float(counts["mean_selected"]), status


def most_rays(
    rays: np.ndarray, visible: np.ndarray, budget: float, max_transitions: int, time_limit: float
) -> tuple[float, int, float, str]:
    """(budget use, transitions, mean selected, solver status) of the selection that
    traces the most rays within ``budget`` per frame with at most ``max_transitions``
    transitions (or of the best found within ``time_limit`` seconds)."""
    from scipy.optimize import Bounds, LinearConstraint, milp  # uv run --with scipy
    from scipy.sparse import coo_matrix

    F, R = rays.shape
    n_x = F * R
    rows, cols, vals, lo, hi, pairs, t_index = _shared_rows(rays, visible, budget)
    m = len(pairs)
    row = len(lo)
    rows += [row] * m
    cols += t_index.tolist()
    vals += [1.0] * m
    lo.append(-np.inf)
    hi.append(float(max_transitions))
    row += 1
    A = coo_matrix((vals, (rows, cols)), shape=(row, n_x + m)).tocsr()
    upper = np.concatenate([visible.reshape(-1).astype(float), np.ones(m)])
    integrality = np.concatenate([np.ones(n_x), np.zeros(m)])
    cost = np.concatenate([-rays.reshape(-1), np.zeros(m)])
    res = milp(
        cost,
        constraints=LinearConstraint(A, lo, hi),
        integrality=integrality,
        bounds=Bounds(np.zeros(n_x + m), upper),
        options={"time_limit": time_limit},
    )
    if res.x is None:
        return float("nan"), -1, float("nan"), res.message
    x = np.round(res.x[:n_x]).reshape(F, R).astype(bool)
    counts = transition_counts(x, visible)
    seen = visible.any(axis=1)
    use = float(np.mean((rays * x).sum(axis=1)[seen] / budget)) if seen.any() else float("nan")
    status = "optimal" if res.status == 0 else f"best found ({res.message})"
    return use, int(counts["transitions"]), float(counts["mean_selected"]), status


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--budgets", required=True, help="comma list of rays budgets")
    ap.add_argument("--time-limit", type=float, default=120.0, help="seconds per budget")
    ap.add_argument(
        "--max-transitions", default="", help="comma list of K: most rays with <= K transitions"
    )
    args = ap.parse_args(argv)
    try:
        data = load_recording(args.recording)
    except RecordingError as error:
        print(f"transition_bound: {error}", file=sys.stderr)
        return 1
    rays, visible = recorded_costs(data)
    if args.max_transitions:
        print(
            "| budget | at most K transitions | budget use | transitions | mean selected | solver |"
        )
        print("|---|---|---|---|---|---|")
        for budget in (int(b) for b in args.budgets.split(",")):
            for k in (int(k) for k in args.max_transitions.split(",")):
                use, t, mean, status = most_rays(rays, visible, budget, k, args.time_limit)
                print(f"| {budget} | {k} | {use:.3f} | {t} | {mean:.2f} | {status} |", flush=True)
        return 0
    print(
        "| budget | HEU2 transitions | HEU2 mean selected | fewest transitions at that mean "
        "(offline) | its mean selected | solver |"
    )
    print("|---|---|---|---|---|---|")
    for budget in (int(b) for b in args.budgets.split(",")):
        heu2 = transition_counts(*replay(data, "heu2", budget))
        t, mean, status = fewest_transitions(
            rays, visible, budget, heu2["mean_selected"], args.time_limit
        )
        print(
            f"| {budget} | {heu2['transitions']} | {heu2['mean_selected']:.2f} | {t:.0f} "
            f"| {mean:.2f} | {status} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
