"""tools/conformance.py on a folder of two stages made here: a camera-less quad (gets a
wrapper camera framing its bounds, renders in raster and rt, a contact sheet) and a file
USD cannot parse (recorded as failed with one line, the run goes on).

The quad spans x in [-1, 1], y in [-0.5, 0.5] at z = 0, facing +Z; the wrapper camera looks
at it head on (``--view 0,0``) with the tool's 50 mm lens over a 36 mm film back at 32 x 24
(vertical aperture 27 mm). Its corners all lie at depth d, so the fit is d = max(1 / tan_h,
0.5 / tan_v) with tan_h = 0.36 * FILL and tan_v = 0.27 * FILL: the width binds, and the
quad covers FILL = 90 % of the image width (columns 1.6 to 30.4 px) and 0.5 / d / 0.27 =
60 % of its height (rows 4.8 to 19.2 px): 28 x 14 pixel centres of the 32 x 24. Every edge
is >= 0.2 px from a pixel centre, so the count is exact in both modes.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdLux
from repo_paths import TOOLS

from phrt_usd.run.images import write_png_atomic

sys.path.insert(0, str(TOOLS))
import conformance  # noqa: E402

W, H = 32, 24
COVERED = 28 * 14 / (W * H)  # the pixel centres inside the quad's image (module docstring)


def _quad_stage(path: Path) -> None:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mesh = UsdGeom.Mesh.Define(stage, "/World/Quad")
    mesh.CreatePointsAttr([(-1, -0.5, 0), (1, -0.5, 0), (1, 0.5, 0), (-1, 0.5, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateExtentAttr([(-1, -0.5, 0), (1, 0.5, 0)])
    mesh.CreateDisplayColorAttr([(0.8, 0.2, 0.1)])
    # 0.9: the red channel stays below 1.0 (0.8 x 0.9 + the 0.25 x 0.9 highlight), so the
    # render's clipping warning (a frame mostly > 1.0) does not make the status "warnings".
    UsdLux.DistantLight.Define(stage, "/World/Sun").CreateIntensityAttr(0.9)
    stage.GetRootLayer().Save()


@pytest.mark.slow
def test_wrapper_camera_sheet_and_a_broken_asset(tmp_path):
    assets, out = tmp_path / "assets", tmp_path / "out"
    assets.mkdir()
    _quad_stage(assets / "quad.usda")
    (assets / "broken.usda").write_text('#usda 1.0\ndef Xform "A" {{{\n')
    (assets / "screenshots").mkdir()  # the quad's own picture: pure green, found by the tool
    green = np.zeros((12, 16, 3), np.uint8)
    green[..., 1] = 255
    write_png_atomic(assets / "screenshots" / "quad.png", green)
    before = {p: p.read_bytes() for p in assets.rglob("*") if p.is_file()}

    code = conformance.main([str(assets), str(out), "--resolution", f"{W}x{H}",
                             "--view", "0,0", "--no-isolate"])  # fmt: skip

    assert code == 0
    assert {p: p.read_bytes() for p in assets.rglob("*") if p.is_file()} == before  # untouched
    results = {a["name"]: a for a in json.loads((out / "results.json").read_text())["assets"]}

    quad = results["quad"]
    assert quad["camera"] == "wrapper" and quad["error"] is None
    wrapper = Usd.Stage.Open(str(out / "wrappers" / "quad.usda"))
    assert wrapper.GetRootLayer().subLayerPaths[0] == str((assets / "quad.usda").resolve())
    assert UsdGeom.Camera(wrapper.GetPrimAtPath(conformance.WRAPPER_CAMERA))
    for mode in quad["modes"]:
        assert mode["error"] is None, mode
        assert mode["covered"] == COVERED, (mode["mode"], mode["covered"] * W * H)

    sheet = conformance.read_picture(out / "quad.png")
    # two renders and the reference, each PANEL_WIDTH wide with GAP between
    assert sheet.shape[1] == 3 * conformance.PANEL_WIDTH + 2 * conformance.GAP
    assert quad["reference"] == str(assets / "screenshots" / "quad.png")
    panel_height = conformance.PANEL_WIDTH * H // W
    raster_panel = sheet[:panel_height, : conformance.PANEL_WIDTH]
    centre = raster_panel[panel_height // 2, conformance.PANEL_WIDTH // 2]
    corner = raster_panel[2, 2]  # outside the quad (it starts 5 % in from the left)
    # the lit quad is at the centre of the panel, far brighter than the dark background
    # (0.3 of the display range: the background is the environment's dim grey)
    assert centre.mean() > corner.mean() + 0.3, (centre, corner)
    # the reference panel holds the picture in its colours (all channels read); 0.02 allows
    # the resize filter's rounding
    reference = sheet[panel_height // 2, 2 * (conformance.PANEL_WIDTH + conformance.GAP) + 128]
    assert np.allclose(reference, [0, 1, 0], atol=0.02), reference

    broken = results["broken"]
    assert broken["error"] and "\n" not in broken["error"] and broken["modes"] == []
    index = (out / "index.md").read_text()
    assert quad["agreement"] == 1.0  # raster and rt cover the same pixels
    assert "| [quad](quad.png) | ok | wrapper |" in index
    assert "| broken | failed | – |" in index
    assert str(out) not in index and str(assets) not in index  # OUT/..., ASSETS/...


def test_list_file_gives_an_asset_its_exposure(tmp_path):
    listed = tmp_path / "assets.txt"
    listed.write_text("# comment\nA | a.usda\nB | b.usda | | | 0,0 | -13.5\n")
    a, b = conformance.read_list(tmp_path, listed)
    assert (a.exposure, b.exposure, b.view) == (0.0, -13.5, (0.0, 0.0))
    listed.write_text("B | b.usda | | | | inf\n")
    try:
        conformance.read_list(tmp_path, listed)
    except SystemExit as stop:
        assert "EV 'inf' is not a finite number" in str(stop)
    else:
        raise AssertionError("a non-finite EV was accepted")
