"""The G-buffer source (``--primary``, ``render.primary_source``): the choice rule, the
option's checks, and that the rays' G-buffer renders the raster's frame."""

from __future__ import annotations

import json

import pytest
from scenes import mirror_floor_stage
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.engine.primary_source import (
    RAYS_TRIANGLES_PER_PIXEL,
    check_primary,
    choose,
    is_software,
)
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.errors import BadOption
from phrt_usd.pytest_plugin import assert_images_close
from phrt_usd.usd.stage import open_stage

#: Covered pixels whose element id must agree between the two sources: the raster's
#: id-against-Embree target (they differ only where coplanar surfaces z-fight).
ID_AGREEMENT = 0.995
#: Mean FLIP allowed between the two sources' frames: the hybrid-against-rt threshold
#: (tests/engine/test_render.py), which the same G-buffer difference is held to there.
SOURCES_FLIP = 0.02


@pytest.mark.parametrize(
    ("option", "software", "triangles", "pixels", "expected"),
    [
        ("auto", True, 1_002_530, 640 * 480, "rays"),  # 1M-triangle ground, llvmpipe
        ("auto", True, 44_540, 640 * 480, "raster"),  # the sewer at 640 x 480
        ("auto", False, 1_002_530, 640 * 480, "raster"),  # a GPU draws it
        ("auto", True, 307_200, 640 * 480, "raster"),  # exactly one a pixel: not more
        ("auto", True, 10, 0, "rays"),  # no pixels: finite, no division
        ("raster", True, 1_002_530, 640 * 480, "raster"),  # asked for: always
        ("rays", False, 10, 640 * 480, "rays"),
    ],
)
def test_choose(option, software, triangles, pixels, expected):
    assert choose(option, software, triangles, pixels) == expected
    assert RAYS_TRIANGLES_PER_PIXEL == 1.0  # the docstring's reasoning is about this value


def test_software_renderers_are_recognised():
    assert is_software("llvmpipe (LLVM 19.1.7, 256 bits)") and is_software("Mesa softpipe")
    assert not is_software("NVIDIA GeForce RTX 4090/PCIe/SSE2")


def test_bad_values_are_one_line_errors(tmp_path):
    with pytest.raises(BadOption, match="primary must be one of auto, raster, rays, got 'gpu'"):
        check_primary("gpu")
    with pytest.raises(BadOption, match="rt mode traces every ray"):
        RenderOptions(mode="rt", primary="raster")
    stage = mirror_floor_stage(tmp_path / "mirror.usda")
    argv = ["render", str(stage), "--out", str(tmp_path / "o"), "--primary", "lasers"]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "primary must be one of auto, raster, rays" in lines[0], lines
    assert not (tmp_path / "o").exists()  # refused before anything was written


def _frame(stage, primary: str, mode: str = "hybrid", width: int = 160, height: int = 120):
    options = RenderOptions(
        mode=mode, heuristic="all", width=width, height=height, budget_ms=None, primary=primary
    )
    renderer = FrameRenderer(stage, options)
    try:
        renderer.plan([1.0])
        return renderer.primary, renderer.render(1.0)
    finally:
        renderer.close()


@pytest.mark.slow
def test_rays_render_the_raster_frame(tmp_path):
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    source_r, raster = _frame(stage, "raster")
    source_y, rays = _frame(stage, "rays")
    assert (source_r, source_y) == ("raster", "rays")
    assert "gbuffer" in raster.stats.passes and "primary_rays" not in raster.stats.passes
    assert "primary_rays" in rays.stats.passes and "gbuffer" not in rays.stats.passes
    covered = raster.gbuffer.covered | rays.gbuffer.covered
    agree = raster.gbuffer.element_id[covered] == rays.gbuffer.element_id[covered]
    assert covered.sum() > 1000 and agree.mean() >= ID_AGREEMENT
    assert rays.traced_mask.any()  # the hybrid traced its reflector from the rays' G-buffer
    assert_images_close(
        rays.beauty, raster.beauty, max_mean_flip=SOURCES_FLIP, min_psnr=None, name="primary"
    )


@pytest.mark.slow
def test_auto_follows_the_triangles_a_pixel(tmp_path):
    """The test stage has a few dozen triangles: at 160 x 120 the raster, at 4 x 3 (12
    pixels) the rays where the raster is software (llvmpipe, as on any machine without
    a GPU), in hybrid and in raster mode alike (raster mode then builds Embree for its
    primary rays alone, so it is never the slowest mode on a heavy stage)."""
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    triangles = stage.scene.geometry.triangle_count
    assert 12 < triangles < 160 * 120
    assert _frame(stage, "auto")[0] == "raster"
    with Rasterizer(stage.scene, 4, 3) as rasterizer:
        software = is_software(rasterizer.gl_renderer)
    source, out = _frame(stage, "auto", width=4, height=3)
    assert source == ("rays" if software else "raster")
    assert ("primary_rays" if software else "gbuffer") in out.stats.passes
    source, out = _frame(stage, "auto", mode="raster", width=4, height=3)
    assert source == ("rays" if software else "raster") and not out.traced_mask.any()
    # Asked for by name, the rays serve a raster-mode frame too (Embree built for them).
    source, out = _frame(stage, "rays", mode="raster")
    assert source == "rays" and "primary_rays" in out.stats.passes and not out.traced_mask.any()
    assert "shadow_map" in out.stats.passes  # the maps' shadows, no rays: raster mode's own


@pytest.mark.slow
def test_the_run_records_its_source(tmp_path):
    stage = mirror_floor_stage(tmp_path / "mirror.usda")
    result = phrt_usd.render(stage, tmp_path / "api", frames="1", primary="rays")
    assert result.summary["primary"] == "rays"
    run = json.loads((tmp_path / "api" / "stats.json").read_text())["run"]
    assert run["primary"] == "rays"
    cli = CliRunner().invoke(
        app, ["render", str(stage), "--out", str(tmp_path / "cli"), "--frames", "1", "--json"]
    )
    assert cli.exit_code == 0, cli.stderr
    assert json.loads(cli.stdout)["primary"] == "raster"
