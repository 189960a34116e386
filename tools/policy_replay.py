"""Replay selection policies offline on a recorded camera path (rays budgets only).

With a rays budget a policy's choices depend only on what the renderer shows it: each
frame's ``FrameView`` (pixel counts, screen boxes, camera) and, for each reflector it
traces, that reflector's ``TraceRecord`` (rays, pixels, bounces, reflectors hit). A
reflector's record does not depend on which other reflectors are traced with it (its
rays start from its own G-buffer pixels), so one ``all`` render that records every
visible reflector's record per frame lets any policy be replayed exactly, without
rendering: the replay runs the renderer's round loop (``FrameRenderer.finish``) with the
recorded records instead of the tracer. The first step checks that: replaying HEU1 and
HEU2 gives the same transitions and mean selected as real ``paper_tables`` runs.

    uv run python tools/policy_replay.py capture stages/farm.usda runs/replay/farm.pkl \
        [--frames A:B:STEP] [--images runs/replay/farm.npz]
    uv run python tools/policy_replay.py replay runs/replay/farm.pkl \
        --budgets 500,1000,2000,4000 [--heuristics heu1,heu2] [--images runs/replay/farm.npz]

``capture`` renders the stage's full camera path (or ``--frames``) once (hybrid, ``all``,
unbounded; 320x240 unless told; no image files, but with ``--images`` the frames' raster
and ``all`` images in one npz). ``replay`` prints, per heuristic and budget: transitions
(split into admissions of reflectors already in view and drops while in view), mean
selected, mean traced rays, the HEU1/HEU2 ratio and, with ``--images``, the mean FLIP
against ``all`` of each policy's images composed from the recording (``compose``: equal to
``phrt sweep``'s figures on the same frames, e.g. farm 521:640:2 at 1000 rays: 0.00442 /
0.00422 both ways).
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from phrt_usd.frame import Budget
from phrt_usd.heuristic import UPCOMING_CAMERAS, AllPolicy, make_policy
from phrt_usd.image_metrics import flip_map
from phrt_usd.render_job import parse_frames
from phrt_usd.renderer import FrameRenderer, RenderOptions
from phrt_usd.schema import read_render_params
from phrt_usd.stage_reader import open_stage


class _CapturePolicy(AllPolicy):
    """``all`` that keeps what it was shown and what tracing found, frame by frame."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        #: One SimpleNamespace per frame: ``view`` (FrameView), ``elements`` (per element:
        #: is_reflector, priority, center, bounds) and ``records`` (element id → TraceRecord of
        #: every visible reflector). Plain types, so the pickle loads anywhere.
        self.frames: list[SimpleNamespace] = []

    def begin_frame(self, view, scene) -> None:
        super().begin_frame(view, scene)
        elements = [
            SimpleNamespace(
                is_reflector=e.is_reflector,
                priority=e.priority,
                center=e.center,
                bounds_min=e.bounds_min,
                bounds_max=e.bounds_max,
            )  # fmt: skip
            for e in scene.elements
        ]
        self.frames.append(SimpleNamespace(view=view, elements=elements, records={}))

    def record(self, records, seconds) -> None:
        super().record(records, seconds)
        for rec in records:
            self.frames[-1].records[int(rec.source)] = rec


def capture(
    stage_path: Path,
    out: Path,
    width: int,
    height: int,
    frames: str | None = None,
    images: Path | None = None,
) -> None:
    """Record ``frames`` (default: the whole path) into ``out``; with ``images``, also an
    npz of per frame (F, H, W) element ids, the raster image and the ``all`` image
    (F, H, W, 3) float32 and the ``all`` run's traced mask, from which the image of any
    selection is composed exactly (``compose``)."""
    stage = open_stage(stage_path)
    params = read_render_params(stage.stage)
    options = RenderOptions(
        mode="hybrid", heuristic="all", width=width, height=height,
        budget_ms=None, budget_rays=None, bounce_limit=params.bounce_limit,
    )  # fmt: skip
    renderer = FrameRenderer(stage, options)
    policy = _CapturePolicy(selection_weight=0.0, bounce_limit=params.bounce_limit)
    renderer.policy = policy
    times = parse_frames(frames, stage.frame_range)
    stacks: dict[str, list[np.ndarray]] = {"ids": [], "raster": [], "all": [], "traced": []}
    try:
        for k, t in enumerate(times):
            prep = renderer.prepare(t)
            output = renderer.finish(prep, policy, options)
            if images is not None:
                stacks["ids"].append(prep.gbuffer.element_id.astype(np.int32))
                stacks["raster"].append(prep.image.astype(np.float32))
                stacks["all"].append(output.beauty.astype(np.float32))
                stacks["traced"].append(output.traced_mask)
            if k % 100 == 0:
                print(f"{stage_path.stem}: frame {k}/{len(times)}", file=sys.stderr)
    finally:
        renderer.close()
    lights = stage.scene.lights
    data = {
        "stage": str(stage_path),
        "selection_weight": params.selection_weight,
        "bounce_limit": params.bounce_limit,
        "lights": SimpleNamespace(distant=list(lights.distant), local=list(lights.local)),
        "reflectors": [int(i) for i in stage.scene.reflector_ids],
        "frames": policy.frames,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as fh:
        pickle.dump(data, fh)
    if images is not None:
        np.savez(images, times=np.asarray(times), **{k: np.stack(v) for k, v in stacks.items()})


def compose(images, f: int, selected_ids: list[int]) -> np.ndarray:
    """(H, W, 3) float32: frame ``f``'s image when exactly ``selected_ids`` are traced.

    A reflector's traced pixels depend only on its own G-buffer pixels (its rays follow
    other reflectors whether or not those are selected), so the image of a selection is
    the ``all`` image on the selected reflectors' traced pixels and the raster image
    elsewhere."""
    take = images["traced"][f] & np.isin(images["ids"][f], selected_ids)
    return np.where(take[..., None], images["all"][f], images["raster"][f])


def mean_flip(images, selected: np.ndarray, reflectors: list[int]) -> float:
    """Mean over frames of the mean FLIP against the ``all`` image, for (F, R) bool
    ``selected`` over ``reflectors``."""
    refl = np.asarray(reflectors)
    errors = [
        float(flip_map(images["all"][f], compose(images, f, refl[row].tolist())).mean())
        for f, row in enumerate(selected)
    ]
    return float(np.mean(errors))


def replay(
    data: dict,
    heuristic: str,
    budget_rays: int,
    selection_weight: float | None = None,
    lookahead: bool = True,
):
    """Run ``heuristic`` over the recorded frames with a rays budget, the way
    ``FrameRenderer.finish`` does; with ``lookahead`` each view gets the next recorded
    frames' cameras as ``upcoming_cameras``, as a render of the whole path does. Returns
    (selected, visible): (F, R) bool arrays over the recorded reflectors, in frame order."""
    weight = data["selection_weight"] if selection_weight is None else selection_weight
    policy = make_policy(heuristic, selection_weight=weight, bounce_limit=data["bounce_limit"])
    refl = data["reflectors"]
    column = {e: k for k, e in enumerate(refl)}
    selected = np.zeros((len(data["frames"]), len(refl)), dtype=bool)
    visible = np.zeros_like(selected)
    frames = data["frames"]
    for f, frame in enumerate(frames):
        scene = SimpleNamespace(elements=frame.elements, lights=data["lights"])
        counts = frame.view.pixel_counts
        ahead = frames[f + 1 : f + 1 + UPCOMING_CAMERAS] if lookahead else []
        view = replace(frame.view, upcoming_cameras=tuple(g.view.camera for g in ahead))
        policy.begin_frame(view, scene)
        rays, chosen = 0, []
        while budget_rays - rays > 0:
            ids = policy.next_round(Budget(rays=budget_rays - rays))
            ids = [i for i in ids if counts[i] > 0 and i not in chosen]
            if not ids:
                break
            records = [frame.records[i] for i in ids]
            rays += sum(r.rays for r in records)
            chosen.extend(ids)
            policy.record(records, 1e-6 * sum(r.rays for r in records))
        policy.end_frame()
        for e in chosen:
            selected[f, column[e]] = True
        for e in refl:
            visible[f, column[e]] = counts[e] > 0
    return selected, visible


def mean_rays(data: dict, selected: np.ndarray) -> float:
    """Mean traced rays per frame of an (F, R) ``selected`` (the recorded records' rays)."""
    refl = data["reflectors"]
    return float(
        np.mean(
            [
                sum(frame.records[refl[r]].rays for r in np.flatnonzero(row))
                for frame, row in zip(data["frames"], selected, strict=True)
            ]
        )
    )


def transition_counts(selected: np.ndarray, visible: np.ndarray) -> dict:
    """Transitions as ``phrt report`` counts them, split by kind: an *admission* is a
    reflector in view in both frames that becomes selected, a *drop* one that stops
    being selected. ``entered_selected``: selected on the frame it came into view
    (free)."""
    both = visible[1:] & visible[:-1]
    adm = int(np.count_nonzero(both & selected[1:] & ~selected[:-1]))
    drop = int(np.count_nonzero(both & ~selected[1:] & selected[:-1]))
    entered = int(np.count_nonzero(visible[1:] & ~visible[:-1] & selected[1:]))
    return {
        "transitions": adm + drop,
        "admissions": adm,
        "drops": drop,
        "entered_selected": entered,
        "mean_selected": float(selected.sum(axis=1).mean()),
        "mean_visible": float(visible.sum(axis=1).mean()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("stage", type=Path)
    cap.add_argument("out", type=Path)
    cap.add_argument("--width", type=int, default=320)
    cap.add_argument("--height", type=int, default=240)
    cap.add_argument("--frames", default=None, help="A:B[:STEP] time codes (default: the path)")
    cap.add_argument("--images", type=Path, default=None, help="also write images (.npz)")
    rep = sub.add_parser("replay")
    rep.add_argument("recording", type=Path)
    rep.add_argument("--budgets", required=True, help="comma list of rays budgets")
    rep.add_argument("--heuristics", default="heu1,heu2")
    rep.add_argument("--selection-weight", type=float, default=None)
    rep.add_argument("--no-lookahead", action="store_true", help="views without upcoming cameras")
    rep.add_argument("--images", type=Path, default=None, help="capture's images: add mean FLIP")
    args = ap.parse_args(argv)
    if args.command == "capture":
        capture(args.stage, args.out, args.width, args.height, args.frames, args.images)
        return 0
    with open(args.recording, "rb") as fh:
        data = pickle.load(fh)
    heuristics = [h.strip() for h in args.heuristics.split(",") if h.strip()]
    images = np.load(args.images) if args.images else None
    print(
        "| budget | heuristic | transitions (adm + drop) | entered selected | mean selected "
        "| mean rays | mean FLIP |"
    )
    print("|---|---|---|---|---|---|---|")
    for budget in (int(b) for b in args.budgets.split(",")):
        out = {}
        for h in heuristics:
            lookahead = not args.no_lookahead
            selected, visible = replay(data, h, budget, args.selection_weight, lookahead=lookahead)
            out[h] = c = transition_counts(selected, visible)
            flip = (
                "" if images is None else f"{mean_flip(images, selected, data['reflectors']):.5f}"
            )
            print(
                f"| {budget} | {h} | {c['transitions']} ({c['admissions']} + {c['drops']}) "
                f"| {c['entered_selected']} | {c['mean_selected']:.2f} "
                f"| {mean_rays(data, selected):.0f} | {flip} |"
            )
        if "heu1" in out and "heu2" in out and out["heu2"]["transitions"]:
            pct = 100.0 * out["heu1"]["transitions"] / out["heu2"]["transitions"]
            print(f"| {budget} | heu1/heu2 | {pct:.1f} % | | | | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
