"""The ``motion`` and ``phrt:pixelKind`` RenderVars (``run/products.py``): through
``--aovs`` and through a RenderProduct's vars, the EXR channels, their storage, the
header lines that state their convention, and the planes read back
(``RenderResult.read_frame``) equal to the renderer's own arrays.

The stage: the mirror gallery (``scenes.mirror_gallery_stage``: a camera path past five
mirror panels), 64 x 48, three frames, a rays budget (the pixels do not depend on the
machine's speed).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from pxr import Usd, UsdRender

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scenes import mirror_gallery_stage, render_var  # noqa: E402

import phrt_usd  # noqa: E402
from phrt_usd.engine.renderer import FrameRenderer  # noqa: E402
from phrt_usd.errors import BadOption, PhrtError  # noqa: E402
from phrt_usd.model.pixel_kinds import PIXEL_KINDS, kind_counts  # noqa: E402
from phrt_usd.model.render_options import RenderOptions  # noqa: E402
from phrt_usd.run.products import MOTION_HEADER, parse_aovs  # noqa: E402
from phrt_usd.run.run_files import frame_stats_from_row, read_stats  # noqa: E402
from phrt_usd.usd.stage import open_stage  # noqa: E402

W, H = 64, 48
FRAMES = [1.0, 2.0, 3.0]
OPTIONS = {"resolution": (W, H), "budget_ms": math.inf, "budget_rays": 4000,
           "trace_density": "quarter"}
#: Half storage of motion: 11 significant bits, so 2**-10 relative after the round trip,
#: and 2**-14 absolute near 0 (half's smallest normal step is far below a pixel).
HALF_RTOL, HALF_ATOL = 2**-10, 2**-14


@pytest.fixture(scope="module")
def gallery(tmp_path_factory):
    return mirror_gallery_stage(tmp_path_factory.mktemp("aovs") / "gallery.usda", 3, W, H)


@pytest.fixture(scope="module")
def in_memory(gallery):
    """The same frames rendered in memory: (motion, pixel_kind) per frame."""
    scene = open_stage(gallery)
    options = RenderOptions(width=W, height=H, budget_ms=None, budget_rays=4000,
                            trace_density="quarter")  # fmt: skip
    renderer = FrameRenderer(scene, options)
    try:
        renderer.plan(FRAMES)
        outputs = [renderer.render(t) for t in FRAMES]
        return [(o.motion.copy(), o.pixel_kind.copy()) for o in outputs]
    finally:
        renderer.close()


def _channels(path: Path) -> dict[str, tuple[np.ndarray, object]]:
    part = OpenEXR.File(str(path)).parts[0]
    return {name: (c.pixels, part.header) for name, c in part.channels.items()}


@pytest.mark.slow
def test_aovs_add_motion_and_pixel_kind_channels(gallery, tmp_path, in_memory):
    """``--aovs motion,pixelKind``: channels ``motion.x``, ``motion.y`` (FLOAT) and
    ``pixelKind`` (UINT) in every frame's EXR, the header stating the motion convention
    and the codes; read back equal to the renderer's arrays (float32 and uint8 stored
    exactly); the first frame's motion is 0, the camera path's next frames move."""
    with phrt_usd.render(gallery, tmp_path / "out", frames="1:3", aovs=("motion", "pixelKind"),
                         **OPTIONS) as result:  # fmt: skip
        for t, (motion, kinds) in zip(FRAMES, in_memory, strict=True):
            channels = _channels(result.image(t).exr)
            assert channels["motion.x"][0].dtype == np.float32
            assert channels["pixelKind"][0].dtype == np.uint32
            header = channels["motion.x"][1]
            assert header["phrt/motion"] == MOTION_HEADER
            assert header["phrt/pixelKinds"].startswith("0 background, 1 raster")
            frame = result.read_frame(t)
            assert np.array_equal(frame["motion"], motion)
            assert np.array_equal(frame["pixel_kind"], kinds)
            assert frame["pixel_kind"].dtype == np.uint8
        # stats.json counts each frame's kinds, as the EXR holds them, and reads back.
        _, rows = read_stats(result.out)
        for stats, row in zip(result.frames, rows, strict=True):
            counts = kind_counts(result.read_frame(stats.time)["pixel_kind"])
            assert stats.pixel_kinds == counts == frame_stats_from_row(row).pixel_kinds
            assert sum(counts.values()) == W * H
        assert not result.read_frame(1.0)["motion"].any()
        assert np.abs(result.read_frame(2.0)["motion"]).max() > 1.0
        assert (result.read_frame(2.0)["pixel_kind"] == 5).any()  # filled: quarter density


def _product_stage(gallery: Path, path: Path) -> Path:
    """The gallery with a product of a renamed half ``motion`` var and a ``uchar`` pixel
    kind var beside the colour."""
    stage = Usd.Stage.Open(str(gallery))
    stage.GetRootLayer().Export(str(path))
    stage = Usd.Stage.Open(str(path))
    targets = []
    for name, source, data_type, aov in (
        ("color", "color", "color3h", None),
        ("mv", "motion", "half2", "mv"),
        ("kind", "phrt:pixelKind", "uchar", None),
    ):
        targets.append(render_var(stage, name, source, data_type, aov))
    product = UsdRender.Product.Define(stage, "/Render/Products/Motion")
    product.CreateProductNameAttr("mv.$F4.exr")
    product.CreateOrderedVarsRel().SetTargets(targets)
    settings = UsdRender.Settings.Get(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    stage.GetRootLayer().Save()
    return path


@pytest.mark.slow
def test_render_product_vars_of_motion_and_pixel_kind(gallery, tmp_path, in_memory):
    """A RenderVar ``motion`` renamed ``mv`` stored as half: channels ``mv.x``, ``mv.y``
    (HALF, the renderer's motion within half's rounding); ``phrt:pixelKind`` as uchar:
    UINT codes, exact."""
    stage = _product_stage(gallery, tmp_path / "products.usda")
    with phrt_usd.render(stage, tmp_path / "out", frames="1:3", **OPTIONS) as result:
        for t, (motion, kinds) in zip(FRAMES, in_memory, strict=True):
            channels = _channels(result.out / f"mv.{int(t):04d}.exr")
            assert {"RGBA", "mv.x", "mv.y", "pixelKind"} == set(channels)  # the bindings group RGBA
            assert channels["mv.x"][0].dtype == np.float16
            stored = np.stack([channels["mv.x"][0], channels["mv.y"][0]], -1).astype(np.float32)
            assert np.allclose(stored, motion, rtol=HALF_RTOL, atol=HALF_ATOL)
            assert np.array_equal(channels["pixelKind"][0].astype(np.uint8), kinds)
            frame = result.read_frame(t)
            assert set(frame) >= {"motion", "pixel_kind", "beauty"}


def test_stats_rows_with_bad_pixel_kind_counts_are_refused(gallery, tmp_path):
    """A stats row whose ``pixel_kinds`` names an unknown kind or a count that is not a
    whole number >= 0 is refused in one line; rows without it (written before) read as
    no counts."""
    with phrt_usd.render(gallery, tmp_path / "out", frames="1", **OPTIONS) as result:
        _, rows = read_stats(result.out)
    row = dict(rows[0])
    for bad in ({"glowing": 3}, {"traced": -1}, {"traced": 1.5}, {"traced": True}, [1]):
        with pytest.raises(PhrtError, match="pixel_kinds"):
            frame_stats_from_row({**row, "pixel_kinds": bad})
    del row["pixel_kinds"]
    assert frame_stats_from_row(row).pixel_kinds == {}


def test_aov_names_are_listed_and_checked():
    assert parse_aovs("motion,pixelKind") == ("motion", "pixelKind")
    assert parse_aovs("motionvector,phrt:pixelKind") == ("motionvector", "phrt:pixelKind")
    with pytest.raises(BadOption) as error:
        parse_aovs("motion,bogus")
    assert "motion" in str(error.value) and "pixelKind" in str(error.value)
    assert list(PIXEL_KINDS.values()) == [
        "background", "raster", "screen-space", "traced", "reused", "filled"
    ]


@pytest.mark.slow
def test_cli_aovs_motion(gallery, tmp_path):
    """``phrt render --aovs motion,pixelKind`` from the command line: exit 0, the
    channels in the frame."""
    out = tmp_path / "cli"
    done = subprocess.run(
        [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render", str(gallery),
         "--out", str(out), "--frames", "1:2", "--resolution", f"{W}x{H}", "--budget-rays", "4000",
         "--aovs", "motion,pixelKind"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    channels = _channels(out / "frames" / "0002.exr")
    assert {"motion.x", "motion.y", "pixelKind"} <= set(channels)
