"""Reduced-density tracing (``engine/trace/sparse_pixels.py``, ``--trace-density
half|quarter|sixteenth``): which pixels start rays, how the others are filled, and what the tracer
and the run report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pxr import Usd
from scenes import look_at, mirror_floor_stage, parts_scene, quad, ray_sphere_hit, sphere
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.engine.trace.sparse_pixels import (
    BAYER_RANKS,
    FillGuides,
    fill_skipped,
    pattern_spacing,
    traced_subset,
)
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.errors import BadOption
from phrt_usd.model.trace_density import DENSITY_FRACTION, check_density, sparse_floor


def _pattern(row, col, density):
    """The pixels a large reflector traces at ``density`` (a regular pattern)."""
    if density == "half":
        return (row + col) % 2 == 0
    if density == "eighth":  # the checkerboard of the 2 x 2 grid
        return (row % 2 == 0) & (col % 2 == 0) & ((row + col) % 4 == 0)
    step = pattern_spacing(density)
    return (row % step == 0) & (col % step == 0)


@pytest.mark.parametrize("density", ["half", "quarter", "eighth", "sixteenth"])
def test_large_reflectors_start_rays_on_the_pattern_small_ones_everywhere(density):
    width, height = 40, 30
    pix = np.arange(width * height, dtype=np.int64)
    # Source 0: one pixel fewer than the density's floor; source 1: the rest.
    src = (pix >= sparse_floor(density) - 1).astype(np.int64)
    keep = traced_subset(pix, src, 2, width, density)
    assert keep[src == 0].all()
    row, col = np.divmod(pix[src == 1], width)
    np.testing.assert_array_equal(keep[src == 1], _pattern(row, col, density))


def test_a_small_reflector_is_thinned_only_while_it_keeps_four_samples():
    # 40 pixels (a 5 x 8 patch): from 32 pixels a reflector may be thinned, but only while
    # at least 4 of its pixels start rays: at 13/16 (32.5 of them) and at an eighth (5)
    # it is, at a sixteenth (2.5: that needs 64 pixels) it is traced whole.
    assert [sparse_floor(d) for d in ("13/16", "eighth", "sixteenth")] == [32, 32, 64]
    width = 8
    pix = np.arange(40, dtype=np.int64)
    src = np.zeros(40, np.int64)
    for density, thinned in (("13/16", True), ("eighth", True), ("sixteenth", False)):
        keep = traced_subset(pix, src, 1, width, density)
        assert (not keep.all()) is thinned, density
        if thinned:  # the density's ordered-dither ranks
            row, col = np.divmod(pix, width)
            rate = round(DENSITY_FRACTION[density] * 16)
            np.testing.assert_array_equal(keep, BAYER_RANKS[row % 4, col % 4] < rate)


def test_a_skipped_pixel_without_traced_neighbours_keeps_the_fallback():
    """Pixel 7 ((1, 3) of a 4 x 4 image) has no traced pixel of its source in its cell nor
    within a quarter's spacing - 1; pixel 1 is of another source than the traced one."""
    guides = FillGuides(np.tile(np.float32([0, 0, 1]), (16, 1)), np.zeros((16, 3)),
                        np.ones(16, np.float32), 4, 4)  # fmt: skip
    filled, radiance, hit, *_ = fill_skipped(
        np.array([0], np.int64), np.array([0], np.int64), np.ones((1, 3), np.float32),
        np.ones(1, np.float32), np.array([7, 1], np.int64), np.array([0, 1], np.int64), guides,
    )  # fmt: skip
    assert not filled.any() and radiance.shape == (0, 3) and hit.shape == (0,)


def test_density_is_checked_and_refused_in_rt_mode():
    assert check_density("HALF") == "half"
    with pytest.raises(BadOption, match="trace density"):
        RenderOptions(trace_density="17/16")
    with pytest.raises(BadOption, match="rt mode"):
        RenderOptions(mode="rt", trace_density="half")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("density", "share"), [("half", 0.5), ("quarter", 0.25), ("sixteenth", 1 / 16)]
)
def test_mirror_floor_at_reduced_density_traces_its_share_and_the_same_reflection(
    density, share
):
    """The mirror floor of test_tracer's first test at reduced density: its share of the
    rays (within 5 points: the pattern on a trapezoid), a radiance for every floor pixel
    but the few without a traced neighbour, records counting every covered pixel, and
    the reflected sphere where the mirrored geometry puts it (97 %: the fill blurs its
    outline by one pixel, two at quarter density)."""
    center, radius = np.array([0.3, 1.0, -0.5]), 0.6
    parts = [
        dict(mesh=quad(60.0), F=1.0),
        dict(mesh=sphere(radius, center, 5), albedo=(1, 0, 0), emissive=(1, 0, 0), smooth=True),
    ]
    tracer = Tracer(parts_scene(parts))
    camera = look_at((0.0, 3.0, 6.0), (0.0, 0.0, 0.0))
    gb = tracer.primary_gbuffer(camera, 160, 120)
    full = tracer.trace_reflections(gb, [0], bounce_limit=5)
    half = tracer.trace_reflections(gb, [0], 5, density=density)
    floor = int((gb.element_id == 0).sum())
    assert floor >= sparse_floor(density)
    # The pattern's share of the first rays; the sky-lit scene casts no shadow rays.
    assert (share - 0.05) * full.rays <= half.rays <= (share + 0.05) * full.rays
    assert len(np.unique(half.pixel_index)) == len(half.pixel_index)
    assert len(half.pixel_index) >= 0.999 * floor
    assert half.records[0].pixels == full.records[0].pixels == floor
    assert half.records[0].rays == half.rays
    dirs = gb.view_dir.reshape(-1, 3)[half.pixel_index].astype(np.float64)
    mirrored = center * np.array([1.0, -1.0, 1.0])
    expected = ray_sphere_hit(camera.position, dirs, mirrored, radius)
    assert np.mean(expected == (half.radiance[:, 0] > 0.5)) >= 0.97
    # Where full and half both have the pixel, they agree except along the outline.
    same = np.isin(half.pixel_index, full.pixel_index)
    by_pixel = np.empty((gb.element_id.size, 3), np.float32)
    by_pixel[full.pixel_index] = full.radiance
    diff = np.abs(by_pixel[half.pixel_index[same]] - half.radiance[same]).max(axis=1)
    assert np.mean(diff < 1e-4) >= 0.95


@pytest.mark.slow
def test_densities_per_source_trace_each_source_as_its_own_density_would():
    """HEU1's density steps trace a round's sources at different densities: each source's
    pixels, rays and radiance are those of a round at that source's density alone."""
    parts = [
        dict(mesh=quad(60.0), F=1.0),
        dict(mesh=sphere(0.6, (0.3, 1.0, -0.5), 5), F=0.8, smooth=True),
    ]
    tracer = Tracer(parts_scene(parts))
    gb = tracer.primary_gbuffer(look_at((0.0, 3.0, 6.0), (0.0, 0.0, 0.0)), 160, 120)
    assert min((gb.element_id == e).sum() for e in (0, 1)) >= sparse_floor("quarter")
    mixed = tracer.trace_reflections(gb, [0, 1], 5, density=["quarter", "full"])
    alone = [tracer.trace_reflections(gb, [0], 5, density="quarter"),
             tracer.trace_reflections(gb, [1], 5, density="full")]  # fmt: skip
    for record, single in zip(mixed.records, alone, strict=True):
        assert (record.pixels, record.rays) == (single.records[0].pixels, single.rays)
    by_pixel = np.zeros((gb.element_id.size, 3), np.float32)
    by_pixel[mixed.pixel_index] = mixed.radiance
    for single in alone:
        np.testing.assert_allclose(by_pixel[single.pixel_index], single.radiance, atol=1e-5)
    assert len(mixed.pixel_index) == sum(len(r.pixel_index) for r in alone)


@pytest.mark.slow
def test_the_cli_and_the_api_run_at_half_density_and_record_it(tmp_path):
    """End to end on the mirror-floor stage: the API and the CLI render at half density,
    record it in stats.json (part of the run's identity: a full-density run does not
    resume it), trace fewer rays than at full density, and a bad value is one line
    (exit 2) before anything is written."""
    stage = mirror_floor_stage(tmp_path / "mirror.usda")
    common = {"frames": "1", "heuristic": "all", "budget_ms": math.inf}
    phrt_usd.render(stage, tmp_path / "full", **common)
    phrt_usd.render(stage, tmp_path / "half", trace_density="half", **common)
    runs = {d: json.loads((tmp_path / d / "stats.json").read_text()) for d in ("full", "half")}
    assert runs["half"]["run"]["trace_density"] == "half"
    assert runs["full"]["run"]["trace_density"] == "full"
    assert runs["half"]["run"]["identity"] != runs["full"]["run"]["identity"]
    full_rays, half_rays = (runs[d]["frames"][0]["rays"] for d in ("full", "half"))
    assert 0 < half_rays < 0.7 * full_rays
    argv = ["render", str(stage), "--out", str(tmp_path / "cli"), "--frames", "1",
            "--heuristic", "all", "--trace-density", "half", "--json"]  # fmt: skip
    cli = CliRunner().invoke(app, argv)
    assert cli.exit_code == 0, cli.stderr
    assert "trace" in json.loads(cli.stdout)["passes"]
    bad = CliRunner().invoke(app, [*argv[:3], str(tmp_path / "bad"), "--trace-density", "x"])
    assert bad.exit_code == 2
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1 and "trace density must be one of full, 15/16" in lines[0], lines
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_heu1_takes_a_reflector_too_large_for_its_budget_at_a_coarser_density(tmp_path):
    """End to end (API, then CLI): HEU1 with a rays budget that holds the mirror floor
    only at a reduced density traces it at that density (the floor enters the view in
    the first frame: no transition), records the density in stats.json and the share in
    the selection layer's ``phrt:traceDensity``; at a fixed density (``--trace-density
    half``) it makes no density steps of its own."""
    stage = mirror_floor_stage(tmp_path / "mirror.usda")
    every = {"frames": "1", "heuristic": "all", "budget_ms": math.inf}
    phrt_usd.render(stage, tmp_path / "all", **every)
    first = json.loads((tmp_path / "all" / "stats.json").read_text())["frames"][0]
    # A fresh policy's first prediction of the floor (its prior), the same for HEU1: 40 %
    # of it fits 5/16 of the floor with the admission margin (10 % of the allowance:
    # 5/16 + 0.04 <= 0.4 < 6/16 + 0.04), the finest rate that fits.
    predicted = first["metrics"]["/World/Floor"]["predicted_rays"]
    budget = int(0.4 * predicted)
    argv = ["render", str(stage), "--out", str(tmp_path / "heu1"), "--frames", "1",
            "--heuristic", "heu1", "--budget-rays", str(budget), "--json"]  # fmt: skip
    cli = CliRunner().invoke(app, argv)
    assert cli.exit_code == 0, cli.stderr
    frame = json.loads((tmp_path / "heu1" / "stats.json").read_text())["frames"][0]
    assert frame["densities"] == {"/World/Floor": "5/16"}
    assert 0 < frame["rays"] <= budget
    layer = Usd.Stage.Open(str(tmp_path / "heu1" / "selection.usda"))
    assert layer.GetPrimAtPath("/World/Floor").GetAttribute("phrt:traceDensity").Get(1) == 5 / 16
    phrt_usd.render(stage, tmp_path / "fixed", frames="1", heuristic="heu1",
                    budget_rays=budget, trace_density="half")  # fmt: skip
    fixed = json.loads((tmp_path / "fixed" / "stats.json").read_text())["frames"][0]
    assert fixed["densities"] == {}
