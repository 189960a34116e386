"""What the benchmark tools share: the lights, moving camera and render settings of the
small stages they write on the fly, their ``STAGE@T`` arguments and their ``--append``
log entry."""

from __future__ import annotations

import datetime
import os
from pathlib import Path

from pxr import Gf, Usd, UsdGeom, UsdLux, UsdRender


def add_lights_and_camera(
    stage: Usd.Stage,
    frames: int,
    resolution: tuple[int, int],
    track: tuple[float, float],
    height: float,
    distance: float,
    tilt: float,
    sun_rotation: tuple[float, float, float],
) -> None:
    """A DistantLight (intensity 2, rotated ``sun_rotation`` XYZ degrees) and a dome at
    0.5; a 24 mm camera over a 36 mm film back of the image's aspect, moving along x
    from ``track[0]`` to ``track[1]`` over time codes 1..``frames`` at y = ``height``,
    z = ``distance``, tilted ``tilt`` degrees about X; render settings at ``resolution``
    targeting it (the stage's ``renderSettingsPrimPath``), and the stage's time range."""
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(*sun_rotation))
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateIntensityAttr(0.5)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * resolution[1] / resolution[0])
    move = UsdGeom.Xformable(cam).AddTranslateOp()
    for t in range(1, frames + 1):
        x = track[0] + (track[1] - track[0]) * (t - 1) / max(frames - 1, 1)
        move.Set(Gf.Vec3d(x, height, distance), t)
    UsdGeom.Xformable(cam).AddRotateXOp().Set(tilt)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(*resolution))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)


def stage_at(spec: str) -> tuple[str, float]:
    """A tool's ``STAGE`` or ``STAGE@T`` argument: the stage's path and the time code T
    (default: the middle of the stage's frame range, rounded)."""
    from phrt_usd.usd.stage import open_stage

    stage_path, _, at = spec.partition("@")
    if at:
        return stage_path, float(at)
    start, end = open_stage(stage_path).frame_range
    return stage_path, float(round((start + end) / 2))


def append_log(path: Path, title: str, command: str, text: str) -> None:
    """Append ``text`` to the log file ``path`` under ``### TITLE, DATE UTC, N cores``
    and the command that made it (BENCHMARKS.md, "How to measure")."""
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    with Path(path).open("a") as log:
        log.write(f"\n### {title}, {stamp}, {os.cpu_count()} cores\n\n`{command}`\n\n{text}")
