"""Reduced-density tracing (``engine/trace/sparse_pixels.py``, ``--trace-density
half|quarter|sixteenth``): which pixels start rays, how the others are filled, and what the tracer
and the run report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pxr import Usd
from scenes import look_at, mirror_floor_stage, parts_scene, quad, ray_sphere_hit, sphere
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.engine.trace.sparse_pixels import PATTERN_SPACING, fill_skipped, traced_subset
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.errors import BadOption
from phrt_usd.model.trace_density import SPARSE_MIN_PIXELS, check_density


def _pattern(row, col, density):
    """The pixels a large reflector traces at ``density``."""
    if density == "half":
        return (row + col) % 2 == 0
    step = PATTERN_SPACING[density]
    return (row % step == 0) & (col % step == 0)


def _bilinear(value_of, r, c, step, width, height, same):
    """The tent-weighted mean the fill computes for pixel (r, c): traced pixels q within
    step - 1 rows and columns with ``same(y, x)``, weighted (step - |dy|)(step - |dx|);
    ``value_of(q)`` their radiance or None when not traced. None without any."""
    total, acc = 0.0, 0.0
    for y in range(r - step + 1, r + step):
        for x in range(c - step + 1, c + step):
            if (y, x) != (r, c) and 0 <= y < height and 0 <= x < width and same(y, x):
                v = value_of(y * width + x)
                if v is not None:
                    w = (step - abs(y - r)) * (step - abs(x - c))
                    acc, total = acc + w * np.asarray(v, np.float64), total + w
    return None if total == 0.0 else acc / total


@pytest.mark.parametrize("density", ["half", "quarter", "sixteenth"])
def test_large_reflectors_start_rays_on_the_pattern_small_ones_everywhere(density):
    width, height = 40, 30
    pix = np.arange(width * height, dtype=np.int64)
    # Source 0: the first SPARSE_MIN_PIXELS - 1 pixels; source 1: the rest.
    src = (pix >= SPARSE_MIN_PIXELS - 1).astype(np.int64)
    keep = traced_subset(pix, src, 2, width, density)
    assert keep[src == 0].all()
    row, col = np.divmod(pix[src == 1], width)
    np.testing.assert_array_equal(keep[src == 1], _pattern(row, col, density))


@pytest.mark.parametrize("density", ["half", "quarter", "sixteenth"])
def test_skipped_pixels_interpolate_their_traced_neighbours_of_the_same_source(density):
    """On a radiance linear in (row, col) the bilinear interpolation of an interior
    skipped pixel's traced neighbours (symmetric about it on every pattern) is the value
    itself. Edge pixels weigh the traced neighbours they have; a neighbour of another
    source is never used, and the input order of the traced pixels does not matter."""
    step = PATTERN_SPACING[density]
    width, height = 6 * step, 5 * step
    split = 3 * step  # two sources side by side, each starting on the grid
    pix = np.arange(width * height, dtype=np.int64)
    row, col = np.divmod(pix, width)
    src = (col >= split).astype(np.int64)
    value = np.stack([row, col, 100.0 * src + row + col], axis=1).astype(np.float32)
    traced = _pattern(row, col, density)
    order = np.random.default_rng(3).permutation(int(traced.sum()))
    args = (pix[traced][order], src[traced][order], value[traced][order])
    filled, radiance = fill_skipped(
        *args, pix[~traced], src[~traced], width, height, density=density
    )
    np.testing.assert_array_equal(filled, pix[~traced])  # every one has a neighbour
    got = dict(zip(filled.tolist(), radiance.tolist(), strict=True))
    for p in filled.tolist():
        r, c = divmod(p, width)
        want = _bilinear(
            lambda q: value[q] if traced[q] else None, r, c, step, width, height,
            lambda y, x, c=c: (x >= split) == (c >= split),
        )  # fmt: skip
        np.testing.assert_allclose(got[p], want, rtol=1e-6)
        # Interior: its whole window in the image and on its source.
        lo, hi = (0, split) if c < split else (split, width)
        if step - 1 <= r < height - step + 1 and lo + step - 1 <= c < hi - step + 1:
            np.testing.assert_allclose(got[p], value[p], rtol=1e-5)


def test_a_skipped_pixel_without_traced_neighbours_keeps_the_fallback():
    filled, radiance = fill_skipped(
        np.array([0], np.int64), np.array([0], np.int64), np.ones((1, 3), np.float32),
        np.array([7, 1], np.int64), np.array([0, 1], np.int64), 4, 4,
    )  # fmt: skip
    assert filled.size == 0 and radiance.shape == (0, 3)


def test_density_is_checked_and_refused_in_rt_mode():
    assert check_density("HALF") == "half"
    with pytest.raises(BadOption, match="trace density"):
        RenderOptions(trace_density="eighth")
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
    assert floor >= SPARSE_MIN_PIXELS
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
    assert min((gb.element_id == e).sum() for e in (0, 1)) >= SPARSE_MIN_PIXELS
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
    assert len(lines) == 1 and "trace density must be one of full, half, quarter" in lines[0], lines
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**32 - 1),
    st.sampled_from(["quarter", "sixteenth"]),
)  # fmt: skip
def test_fill_is_the_weighted_mean_of_traced_same_source_neighbours_on_any_layout(
    width, height, seed, density
):
    """Any image size, any sources, any traced subset (not only the patterns), traced
    pixels in any order, a reused table: each skipped pixel with a traced pixel of its
    source within the pattern's spacing - 1 gets their tent-weighted mean, the others
    none; the table is left all -1."""
    rng = np.random.default_rng(seed)
    n = width * height
    pix = rng.permutation(n)[: rng.integers(0, n + 1)].astype(np.int64)
    src = rng.integers(0, 3, len(pix)).astype(np.int64)
    traced = rng.random(len(pix)) < 0.5
    radiance = rng.random((int(traced.sum()), 3)).astype(np.float32)
    table = np.full(n, -1, np.int32)
    filled, got = fill_skipped(
        pix[traced], src[traced], radiance, pix[~traced], src[~traced], width, height, table,
        density,
    )  # fmt: skip
    assert (table == -1).all()
    where = {int(p): (int(s), radiance[i]) for i, (p, s) in enumerate(
        zip(pix[traced], src[traced], strict=True))}  # fmt: skip
    want_pix, want = [], []
    for p, s in zip(pix[~traced].tolist(), src[~traced].tolist(), strict=True):
        r, c = divmod(p, width)
        mean = _bilinear(
            lambda q, s=s: where[q][1] if q in where and where[q][0] == s else None,
            r, c, PATTERN_SPACING[density], width, height, lambda y, x: True,
        )  # fmt: skip
        if mean is not None:
            want_pix.append(p)
            want.append(mean)
    np.testing.assert_array_equal(filled, np.array(want_pix, np.int64))
    np.testing.assert_allclose(got, np.array(want, np.float32).reshape(-1, 3), rtol=1e-5)


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
    # of it fits a quarter of the floor with the admission margin, not half of it.
    predicted = first["metrics"]["/World/Floor"]["predicted_rays"]
    budget = int(0.4 * predicted)
    argv = ["render", str(stage), "--out", str(tmp_path / "heu1"), "--frames", "1",
            "--heuristic", "heu1", "--budget-rays", str(budget), "--json"]  # fmt: skip
    cli = CliRunner().invoke(app, argv)
    assert cli.exit_code == 0, cli.stderr
    frame = json.loads((tmp_path / "heu1" / "stats.json").read_text())["frames"][0]
    assert frame["densities"] == {"/World/Floor": "quarter"}
    assert 0 < frame["rays"] <= budget
    layer = Usd.Stage.Open(str(tmp_path / "heu1" / "selection.usda"))
    assert layer.GetPrimAtPath("/World/Floor").GetAttribute("phrt:traceDensity").Get(1) == 0.25
    phrt_usd.render(stage, tmp_path / "fixed", frames="1", heuristic="heu1",
                    budget_rays=budget, trace_density="half")  # fmt: skip
    fixed = json.loads((tmp_path / "fixed" / "stats.json").read_text())["frames"][0]
    assert fixed["densities"] == {}
