"""``--screen-space on`` end to end: the render through the API and the CLI makes
screen-space pixels on a stage where first reflection rays land on screen, its image
stays the traced one's, and rt mode refuses it (exit 2, one line)."""

import json

from pxr import Usd, UsdGeom
from scenes import mirror_floor_stage
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.evaluate.image_metrics import flip_map

W, H = 160, 120


def _floor_with_box(tmp_path):
    """The mirror floor with a diffuse box standing on it in front of the ball: its
    sides' reflections are on screen and unoccluded."""
    path = mirror_floor_stage(tmp_path / "floor.usda", W, H)
    stage = Usd.Stage.Open(str(path))
    box = UsdGeom.Cube.Define(stage, "/World/Box")
    box.CreateSizeAttr(0.6)
    box.CreateDisplayColorAttr([(0.1, 0.6, 0.2)])
    UsdGeom.Xformable(box).AddTranslateOp().Set((0.8, 0.3, 0.5))
    stage.GetRootLayer().Save()
    return path


def test_screen_space_through_api_and_cli(tmp_path):
    stage = _floor_with_box(tmp_path)
    common = {"heuristic": "all", "budget_ms": float("inf"), "aovs": ["pixelKind"]}
    off = phrt_usd.render(stage, tmp_path / "off", frames="1", **common)
    on = phrt_usd.render(stage, tmp_path / "on", frames="1", screen_space="on", **common)
    kinds = on.frames[0].pixel_kinds  # FrameStats
    assert kinds["screen-space"] > 0
    assert off.frames[0].pixel_kinds["screen-space"] == 0
    # The resolved hits are the traced ones (docs/screen-space.md): the suite's "same
    # image" FLIP.
    assert flip_map(off.read_frame()["beauty"], on.read_frame()["beauty"]).mean() <= 0.02
    run = json.loads((tmp_path / "on" / "stats.json").read_text())["run"]
    assert run["screen_space"] == "on"
    cli = CliRunner().invoke(app, ["render", str(stage), "-o", str(tmp_path / "cli"),
                                   "--heuristic", "all", "--budget-ms", "inf",
                                   "--screen-space", "on", "--json"])  # fmt: skip
    assert cli.exit_code == 0, cli.output
    frames = json.loads((tmp_path / "cli" / "stats.json").read_text())["frames"]
    assert frames[0]["pixel_kinds"]["screen-space"] == kinds["screen-space"]


def test_rt_mode_refuses_screen_space(tmp_path):
    stage = _floor_with_box(tmp_path)
    cli = CliRunner().invoke(app, ["render", str(stage), "-o", str(tmp_path / "rt"),
                                   "--mode", "rt", "--screen-space", "on"])  # fmt: skip
    assert cli.exit_code == 2
    assert "--screen-space on: rt mode traces every ray" in cli.output
    assert "Traceback" not in cli.output
