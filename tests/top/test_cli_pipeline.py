"""The CLI as pipelines drive it: version, progress in logs, verbosity, composition
controls (session layers, variants, population masks) recorded with the run."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from scenes import mirror_gallery_stage

import phrt_usd

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
RENDER = ["--budget-rays", "600", "--resolution", "32x24"]


def _run(*args: str) -> subprocess.CompletedProcess:
    # stderr is a pipe here, never a terminal: what a render farm's log sees.
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    return mirror_gallery_stage(tmp_path_factory.mktemp("cli") / "gallery.usda", frames=4)


@pytest.mark.slow
def test_version():
    done = _run("--version")
    assert done.returncode == 0 and done.stdout.strip() == f"phrt {phrt_usd.__version__}"


@pytest.mark.slow
def test_progress_lines_without_a_terminal(gallery, tmp_path):
    """Default: a line at the start and at the end (with a percentage); -v: one per frame;
    -q: nothing but errors."""
    done = _run("render", str(gallery), "--out", str(tmp_path / "a"), "--frames", "1:4",
                *RENDER, "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if re.search(r"\d+/4 frames \(\d+ %\)", ln)]
    assert lines and lines[-1].endswith("4/4 frames (100 %)"), done.stderr
    verbose = _run("-v", "render", str(gallery), "--out", str(tmp_path / "b"), "--frames",
                   "1:4", *RENDER)  # fmt: skip
    assert len(re.findall(r"\d/4 frames", verbose.stderr)) == 4, verbose.stderr
    quiet = _run("-q", "render", str(gallery), "--out", str(tmp_path / "c"), "--frames",
                 "1:4", *RENDER, "--json")  # fmt: skip
    assert quiet.returncode == 0 and "frames" not in quiet.stderr, quiet.stderr
    assert json.loads(quiet.stdout)["frames"] == 4
    both = _run("-v", "-q", "render", str(gallery))
    assert both.returncode == 2 and "exclude" in both.stderr


def _ball_stage(tmp_path: Path) -> Path:
    """scenes.mirror_floor_stage with a variant set ``colour`` on /World/Ball: ``red``
    (the default, the stage's own colour) and ``blue``."""
    from pxr import Usd, UsdGeom
    from scenes import mirror_floor_stage

    path = mirror_floor_stage(tmp_path / "ball.usda", width=64, height=48)
    stage = Usd.Stage.Open(str(path))
    ball = stage.GetPrimAtPath("/World/Ball")
    colours = ball.GetVariantSets().AddVariantSet("colour")
    for name, rgb in (("red", (0.9, 0.05, 0.05)), ("blue", (0.05, 0.05, 0.9))):
        colours.AddVariant(name)
        colours.SetVariantSelection(name)
        with colours.GetVariantEditContext():
            UsdGeom.Gprim(ball).GetDisplayColorAttr().Set([rgb])
    colours.SetVariantSelection("red")
    UsdGeom.Gprim(ball).GetDisplayColorAttr().Clear()  # the variants alone say the colour
    stage.GetRootLayer().Save()
    return path


def _ball_colour(out: Path) -> tuple[float, float, float] | None:
    """Mean beauty over the ball's own pixels (by element id), None if none."""
    import numpy as np

    from phrt_usd.run.images import read_frame_exr
    from phrt_usd.usd.stage import open_stage

    stats = json.loads((out / "stats.json").read_text())
    scene = open_stage(stats["run"]["stage"]).scene
    ball = [i for i, e in enumerate(scene.elements) if e.path == "/World/Ball"]
    frame = read_frame_exr(out / "frames" / "0001.exr")
    pixels = np.isin(frame["element_id"], ball)
    return tuple(frame["beauty"][pixels].mean(axis=0)) if pixels.any() else None


@pytest.mark.slow
def test_session_layer_variant_and_mask_change_the_picture_and_are_recorded(tmp_path):
    stage = _ball_stage(tmp_path)
    session = tmp_path / "shot.usda"
    session.write_text('#usda 1.0\n\nover "World"\n{\n    over "Ball"\n    {\n'
                       "        color3f[] primvars:displayColor = [(0.05, 0.9, 0.05)]\n"
                       "    }\n}\n")  # fmt: skip
    runs = {
        "default": [],
        "variant": ["--variant", "/World/Ball:colour=blue"],
        "session": ["--session-layer", str(session)],
        "mask": ["--mask", "/World/Floor,/World/Camera,/World/Sun,/World/Sky,/Render"],
    }
    colours = {}
    for name, args in runs.items():
        out = tmp_path / name
        done = _run("render", str(stage), "--out", str(out), *RENDER, *args, "--json")
        assert done.returncode == 0, done.stderr
        colours[name] = _ball_colour(out)
        recorded = json.loads((out / "stats.json").read_text())["run"]["composition"]
        assert bool(recorded["variants"]) == (name == "variant")
        assert bool(recorded["session_layers"]) == (name == "session")
        assert bool(recorded["mask"]) == (name == "mask")
    red, blue, green = colours["default"], colours["variant"], colours["session"]
    # Each variant's dominant channel is the one its colour names (lit, shaded, but
    # never so much that another channel overtakes it).
    assert red[0] > 2 * max(red[1], red[2]), red
    assert blue[2] > 2 * max(blue[0], blue[1]), blue
    assert green[1] > 2 * max(green[0], green[2]), green
    assert colours["mask"] is None  # the ball is not on the masked stage
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "variant" / "selection.usda"))
    assert list(layer.customLayerData["phrt"]["composition"]["variants"]) == [
        "/World/Ball:colour=blue"]  # fmt: skip
    # Another variant is another run: --resume refuses it.
    done = _run("render", str(stage), "--out", str(tmp_path / "variant"), *RENDER, "--resume")
    assert done.returncode == 1 and "differs" in done.stderr or "changed" in done.stderr


@pytest.mark.slow
@pytest.mark.parametrize(
    "args, problem",
    [
        (["--variant", "/World/Ball:colour"], "PRIM:SET=NAME"),
        (["--variant", "/World/Ball:colour=green"], "no variant 'green'"),
        (["--variant", "/World/Ball:size=big"], "no variant set 'size'"),
        (["--variant", "/Nope:colour=red"], "no prim /Nope"),
        (["--session-layer", "/no/such.usda"], "no such file"),
        (["--session-layer", __file__], "cannot open"),
        (["--mask", "World"], "not an absolute prim path"),
    ],
)
def test_bad_composition_controls_exit_2(tmp_path, args, problem):
    done = _run("render", str(_ball_stage(tmp_path)), "--out", str(tmp_path / "o"), *args)
    assert done.returncode == 2 and problem in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
