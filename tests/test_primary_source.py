"""The G-buffer source (``--primary``, ``render.primary_source``): the choice rule, the
option's checks, and that the rays' G-buffer renders the raster's frame."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scenes import mirror_floor_stage
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.errors import BadOption
from phrt_usd.pytest_plugin import assert_images_close
from phrt_usd.render.primary_source import RAYS_MARGIN, TIMED_CALLS, check_primary, choose
from phrt_usd.render.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd.stage import open_stage

#: Covered pixels whose element id must agree between the two sources: the raster's
#: id-against-Embree target (they differ only where coplanar surfaces z-fight).
ID_AGREEMENT = 0.995
#: Mean FLIP allowed between the two sources' frames: the hybrid-against-rt threshold
#: (tests/test_render.py), which the same G-buffer difference is held to there.
SOURCES_FLIP = 0.02


class _Clock:
    """A clock that only source calls advance: each call of ``source(seconds)`` takes
    the next of ``seconds``."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def source(self, seconds: list[float]):
        def call() -> None:
            self.now += seconds.pop(0)

        return call


@pytest.mark.parametrize(
    ("raster_s", "rays_s", "expected"),
    [
        ([0.080, 0.060], [0.030, 0.032], "rays"),  # a 1M-triangle ground on llvmpipe
        ([0.013, 0.012], [0.030, 0.027], "raster"),  # the paper stages
        # Rays 10 % faster: within the margin, the raster stays (no choice on a near tie).
        ([0.010, 0.010], [0.009, 0.009], "raster"),
    ],
)
def test_choose_keeps_the_clearly_faster_source(raster_s, rays_s, expected):
    clock = _Clock()
    fastest = {"raster_ms": min(raster_s) * 1e3, "rays_ms": min(rays_s) * 1e3}
    chosen, timings = choose(clock.source(raster_s), clock.source(rays_s), clock)
    assert chosen == expected
    # The fastest call of each counts (the estimate least disturbed by other processes).
    assert timings == pytest.approx(fastest)
    assert len(raster_s) == len(rays_s) == 0  # TIMED_CALLS calls of each were made
    assert TIMED_CALLS == 2 and RAYS_MARGIN > 1.0


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


def _frame(stage, primary: str, mode: str = "hybrid"):
    options = RenderOptions(
        mode=mode, heuristic="all", width=160, height=120, budget_ms=None, primary=primary
    )
    renderer = FrameRenderer(stage, options)
    try:
        renderer.plan([1.0])
        return renderer.primary, renderer.primary_timings, renderer.render(1.0)
    finally:
        renderer.close()


def test_rays_render_the_raster_frame(tmp_path):
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    source_r, timings_r, raster = _frame(stage, "raster")
    source_y, timings_y, rays = _frame(stage, "rays")
    assert (source_r, source_y) == ("raster", "rays") and timings_r is timings_y is None
    assert "gbuffer" in raster.stats.passes and "primary_rays" not in raster.stats.passes
    assert "primary_rays" in rays.stats.passes and "gbuffer" not in rays.stats.passes
    covered = raster.gbuffer.covered | rays.gbuffer.covered
    agree = raster.gbuffer.element_id[covered] == rays.gbuffer.element_id[covered]
    assert covered.sum() > 1000 and agree.mean() >= ID_AGREEMENT
    assert rays.traced_mask.any()  # the hybrid traced its reflector from the rays' G-buffer
    assert_images_close(
        rays.beauty, raster.beauty, max_mean_flip=SOURCES_FLIP, min_psnr=None, name="primary"
    )


def test_auto_measures_both_sources_once(tmp_path):
    stage = open_stage(mirror_floor_stage(tmp_path / "mirror.usda"))
    source, timings, out = _frame(stage, "auto")
    assert source in ("raster", "rays")
    assert set(timings) == {"raster_ms", "rays_ms"}
    assert all(np.isfinite(v) and v > 0 for v in timings.values())
    assert ("primary_rays" if source == "rays" else "gbuffer") in out.stats.passes
    # Without an Embree scene (raster mode) auto keeps the raster and measures nothing.
    assert _frame(stage, "auto", mode="raster")[:2] == ("raster", None)
    # Asked for by name, the rays serve a raster-mode frame too (Embree built for them).
    source, _, out = _frame(stage, "rays", mode="raster")
    assert source == "rays" and "primary_rays" in out.stats.passes and not out.traced_mask.any()


def test_the_run_records_its_source(tmp_path):
    stage = mirror_floor_stage(tmp_path / "mirror.usda")
    result = phrt_usd.render(stage, tmp_path / "api", frames="1", primary="rays")
    assert result.summary["primary"] == "rays" and result.summary["primary_ms"] is None
    run = json.loads((tmp_path / "api" / "stats.json").read_text())["run"]
    assert run["primary"] == "rays"
    cli = CliRunner().invoke(
        app, ["render", str(stage), "--out", str(tmp_path / "cli"), "--frames", "1", "--json"]
    )
    assert cli.exit_code == 0, cli.stderr
    summary = json.loads(cli.stdout)
    assert summary["primary"] in ("raster", "rays") and set(summary["primary_ms"]) == {
        "raster_ms", "rays_ms",
    }  # fmt: skip
    assert Path(tmp_path / "cli" / "stats.json").exists()
