"""Compare selection policies on one stage's frames against the ``all`` reference, in one
process: each frame is rasterized once and finished by the reference and by every policy
(as ``phrt sweep`` does, which accepts heu1 and heu2 only). Prints per-policy mean FLIP,
transitions (``evaluate/selection_metrics.py``), mean selected, rays, trace ms and budget
use, and writes them with per-frame rows and the run's provenance
(``evaluate/provenance.py``: version, commit, command, machine, FLIP's settings) as JSON.

    uv run python tools/policy_compare.py stages/sewer.usda 217 336 16 none,heu1,heu3 out.json
    uv run python tools/policy_compare.py stages/sewer.usda 217 276 r20000 heu1,heu3 out.json

BUDGET is milliseconds (``--budget-ms``) or ``rN`` for N rays (``--budget-rays``).
320x240 (``--resolution WxH``), the schema's bounce limit and selection weight
(docs/heuristic.md, "HEU3").
A policy named ``NAME@DENSITY`` traces at that density (``--trace-density``, e.g.
``heu3@quarter``; the reference ``all`` always at full density).

``--oracle POLICY`` adds "oracle": in every frame, the selection a policy would make if it
knew the truth, at the rays POLICY traced in that frame. Each visible reflector is traced
alone and its FLIP gain against the reference measured (the image's mean FLIP drop);
then reflectors are taken by gain per ray, skipping what does not fit, and the chosen
set is traced and scored like any policy. It bounds what better estimates of a
reflector's worth could buy at that ray count (whole reflectors, gains taken as
additive: reflectors cover disjoint pixels).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from phrt_usd.engine.compositing import apply_traced
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.evaluate.image_metrics import flip_map, mean_over
from phrt_usd.evaluate.provenance import collect_for_tool, provenance_line
from phrt_usd.evaluate.selection_metrics import transitions_per_frame
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.stage import open_stage


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stage")
    ap.add_argument("first", type=int)
    ap.add_argument("last", type=int)
    ap.add_argument("budget", help="ms, or rN for N rays")
    ap.add_argument("policies", help="comma list, e.g. none,heu1,heu3")
    ap.add_argument("out", help="JSON file")
    ap.add_argument("--oracle", metavar="POLICY", help="add the oracle at POLICY's rays")
    ap.add_argument("--resolution", default="320x240", help="WxH (default 320x240)")
    args = ap.parse_args()
    width, height = (int(v) for v in args.resolution.split("x"))
    if args.budget.startswith("r"):
        budget = {"budget_ms": None, "budget_rays": int(args.budget[1:])}
    else:
        budget = {"budget_ms": float(args.budget)}
    names = args.policies.split(",")
    stage = open_stage(args.stage)
    base = RenderOptions(mode="hybrid", heuristic="all", width=width, height=height,
                         budget_ms=None)  # fmt: skip
    renderer = FrameRenderer(stage, base)
    times = [float(t) for t in range(args.first, args.last + 1)]
    renderer.plan(times)

    def policy(name):
        return make_policy(name, selection_weight=base.selection_weight,
                           bounce_limit=base.bounce_limit)  # fmt: skip

    reference = policy("all")
    # NAME@DENSITY: policy NAME at that trace density (full without one).
    spec = {n: (n.partition("@")[0], n.partition("@")[2] or "full") for n in names}
    policies = {n: policy(h) for n, (h, _d) in spec.items()}
    options = {
        n: replace(base, heuristic=h, trace_density=d, **budget) for n, (h, d) in spec.items()
    }
    paths = [stage.scene.elements[i].path for i in stage.scene.reflector_ids]
    rows: dict[str, list[dict]] = {n: [] for n in names}
    if args.oracle:
        rows["oracle"] = []
    try:
        for t in times:
            prep = renderer.prepare(t)
            ref = renderer.finish(prep, reference, base)
            for n in names:
                out = renderer.finish(prep, policies[n], options[n])
                s = out.stats
                rows[n].append({
                    "time": t, "flip": mean_over(flip_map(ref.beauty, out.beauty)),
                    "trace_ms": s.trace_ms, "rays": s.rays, "budget_use": s.budget_use,
                    "visible": [p in s.visible for p in paths],
                    "selected": [p in s.selected for p in paths]})  # fmt: skip
            if args.oracle:
                rays = rows[args.oracle][-1]["rays"]
                rows["oracle"].append(oracle_row(renderer, prep, ref.beauty, rays, paths, t))
    finally:
        renderer.close()
    summary = {}
    for n in rows:
        visible = np.array([r["visible"] for r in rows[n]])
        selected = np.array([r["selected"] for r in rows[n]])
        summary[n] = {
            "flip": float(np.mean([r["flip"] for r in rows[n]])),
            "transitions": int(transitions_per_frame(selected, visible).sum()),
            "mean_selected": float(selected.sum(axis=1).mean()),
            "mean_visible": float(visible.sum(axis=1).mean()),
            "mean_rays": float(np.mean([r["rays"] for r in rows[n]])),
            "mean_trace_ms": float(np.mean([r["trace_ms"] for r in rows[n]])),
            "budget_use": float(np.mean([r["budget_use"] or 0.0 for r in rows[n]])),
        }
    record = collect_for_tool(__file__)
    print(provenance_line(record))
    print(json.dumps(summary, indent=1))
    with open(args.out, "w") as f:
        json.dump({"provenance": record, "summary": summary, "rows": rows}, f)


def oracle_row(renderer, prep, reference, rays: int, paths: list[str], t: float) -> dict:
    """The oracle's row of frame ``prep`` (module docstring) within ``rays`` rays."""
    tracer, gb = renderer.tracer, prep.gbuffer
    bounce = renderer.options.bounce_limit

    def traced_image(ids):
        image = prep.image.copy()
        result = tracer.trace_reflections(gb, ids, bounce)
        apply_traced(image, prep.local, prep.reflectivity, result, np.zeros(gb.shape, bool))
        return image, result

    base = mean_over(flip_map(reference, prep.image))
    gains = []
    for e in (int(i) for i in renderer.scene.reflector_ids if prep.pixel_counts[i] > 0):
        image, result = traced_image([e])
        gains.append((base - mean_over(flip_map(reference, image)), result.rays, e))
    chosen, used = [], 0
    for _gain, cost, e in sorted(gains, key=lambda g: -g[0] / max(g[1], 1)):
        if used + cost <= rays:
            chosen.append(e)
            used += cost
    image, result = traced_image(chosen) if chosen else (prep.image, None)
    ids = set(chosen)
    visible = {int(i) for i in renderer.scene.reflector_ids if prep.pixel_counts[i] > 0}
    by_path = {renderer.scene.elements[i].path: i for i in renderer.scene.reflector_ids}
    return {
        "time": t, "flip": mean_over(flip_map(reference, image)), "trace_ms": 0.0,
        "rays": result.rays if result else 0, "budget_use": None,
        "visible": [by_path[p] in visible for p in paths],
        "selected": [by_path[p] in ids for p in paths],
    }  # fmt: skip


if __name__ == "__main__":
    main()
