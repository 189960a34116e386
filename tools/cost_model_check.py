"""How well the trace-time cost model predicts: renders shots with a time budget and
prints, per shot, the median |expected - measured| / measured trace time of the frames
after the first three (``FrameStats.expected_trace_ms`` against ``trace_ms``), the
calibration, the mean budget use (trace ms / T) and the frames that traced nothing.

Shots: the paper stages (``stages/farm.usda``, ``stages/sewer.usda``, frames sampled
along their paths) and three of a small stage this tool writes (five mirror panels and a
mirror floor): ``still`` (fixed camera), ``turntable`` (orbiting the centre) and ``fly``
(a straight fly-through towards the panels). Timings are the machine's, so figures vary
from run to run.

    uv run python tools/cost_model_check.py [--budget-ms 16] [--target-fps F]
        [--resolution 320x240] [--frames 24] [--shots farm,sewer,still,turntable,fly]
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux

import phrt_usd
from phrt_usd.usd import schema

ROOT = Path(__file__).resolve().parent.parent
PAPER = {"farm": ROOT / "stages" / "farm.usda", "sewer": ROOT / "stages" / "sewer.usda"}
#: Frames skipped before the error is measured (the issue's "after the first three").
WARMUP_FRAMES = 3


def _quad(stage, path, half, color, reflect=None):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-half, 0, -half), (half, 0, -half), (half, 0, half), (-half, 0, half)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    mesh.CreateDisplayColorAttr([color])
    if reflect is not None:
        schema.apply_reflector(mesh.GetPrim(), priority=reflect[0], reflectivity=reflect[1])
    return mesh


def write_shot(path: Path, kind: str, frames: int) -> Path:
    """A mirror floor, five mirror panels, a light and a camera moving as ``kind`` says."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    _quad(stage, "/World/Floor", 12.0, (0.5, 0.5, 0.5), reflect=(1.0, 0.5))
    for i in range(5):
        panel = _quad(stage, f"/World/Panel{i}", 1.2, (0.6, 0.6, 0.7), reflect=(1.0 + i, 0.9))
        xf = UsdGeom.Xformable(panel)
        angle = 2 * math.pi * i / 5
        xf.AddTranslateOp().Set(Gf.Vec3d(4 * math.cos(angle), 1.3, 4 * math.sin(angle)))
        xf.AddRotateYOp().Set(-math.degrees(angle) + 90.0)
        xf.AddRotateXOp().Set(90.0)
    light = UsdLux.DistantLight.Define(stage, "/World/Sun")
    UsdGeom.Xformable(light).AddRotateXYZOp().Set(Gf.Vec3f(-50, 30, 0))
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    op = UsdGeom.Xformable(cam).AddTransformOp()
    for f in range(1, frames + 1):
        s = (f - 1) / max(frames - 1, 1)
        if kind == "still":
            eye = Gf.Vec3d(0, 4, 11)
        elif kind == "turntable":
            a = 2 * math.pi * s
            eye = Gf.Vec3d(11 * math.sin(a), 4, 11 * math.cos(a))
        else:  # fly: from far out, through the ring of panels
            eye = Gf.Vec3d(0.5, 2.0, 14 - 16 * s)
        target = Gf.Vec3d(0, 1, 0) if kind != "fly" else eye + Gf.Vec3d(0, -0.1, -1)
        look = Gf.Matrix4d().SetLookAt(eye, target, Gf.Vec3d(0, 1, 0)).GetInverse()
        op.Set(look, Usd.TimeCode(f))
    stage.GetRootLayer().Save()
    return path


def measure(stage: Path, frames: str, options: dict) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        result = phrt_usd.render(stage, Path(tmp) / "run", frames, write_images=False, **options)
        stats = list(result.frames)
    after = stats[WARMUP_FRAMES:]
    errors = [abs(f.expected_trace_ms - f.trace_ms) / f.trace_ms
              for f in after if f.selected and f.trace_ms > 0]  # fmt: skip
    uses = [f.budget_use for f in stats if f.budget_use is not None]
    cal = next((f.calibration for f in stats if f.calibration), None)
    return {
        "frames": len(stats),
        "traced_frames": sum(bool(f.selected) for f in stats),
        "untraced_visible": sum(bool(f.visible and not f.selected) for f in stats),
        "median_rel_error": float(np.median(errors)) if errors else None,
        "p90_rel_error": float(np.percentile(errors, 90)) if errors else None,
        "mean_budget_use": float(np.mean(uses)) if uses else None,
        "calibration_ms": None if cal is None else round(cal["wall_ms"], 2),
        "calibrated_us_per_ray": None if cal is None else round(cal["ms_per_ray"] * 1e3, 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget-ms", type=float, default=16.0)
    ap.add_argument("--target-fps", type=float, default=None)
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--frames", type=int, default=24, help="frames per shot")
    ap.add_argument("--heuristic", default="heu1")
    ap.add_argument("--shots", default="farm,sewer,still,turntable,fly")
    args = ap.parse_args()
    options = {"resolution": args.resolution, "heuristic": args.heuristic}
    if args.target_fps is not None:
        options["target_fps"] = args.target_fps
    else:
        options["budget_ms"] = args.budget_ms
    n = args.frames
    print("shot       frames traced untraced  median_err  p90_err  budget_use  cal_ms  us/ray")
    with tempfile.TemporaryDirectory() as tmp:
        for shot in args.shots.split(","):
            if shot in PAPER:
                # Frames spread over the 720-frame path, where the reflectors are in view.
                stage, frames = PAPER[shot], f"1:720:{max(720 // n, 1)}"
            else:
                stage, frames = write_shot(Path(tmp) / f"{shot}.usda", shot, n), f"1:{n}"
            r = measure(stage, frames, options)

            def fmt(v, spec):
                return "-" if v is None else format(v, spec)

            print(f"{shot:10} {r['frames']:6} {r['traced_frames']:6} {r['untraced_visible']:8}"
                  f"  {fmt(r['median_rel_error'], '10.1%')}  {fmt(r['p90_rel_error'], '7.1%')}"
                  f"  {fmt(r['mean_budget_use'], '10.2f')}  {fmt(r['calibration_ms'], '6')}"
                  f"  {fmt(r['calibrated_us_per_ray'], '6')}")  # fmt: skip


if __name__ == "__main__":
    main()
