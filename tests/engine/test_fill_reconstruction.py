"""The reconstruction of reduced densities (``engine/trace/sparse_pixels.fill_skipped``,
``engine/trace/fill_kernels.py``): exact on linear ramps, no bleeding across the edges
its guides see, no blocks, and on the sewer's wet tunnel no worse than the bilinear fill
it replaces."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from repo_paths import STAGES
from scenes import look_at, parts_scene, quad, sphere

from phrt_usd.engine.renderer import FrameRenderer
from phrt_usd.engine.trace.sparse_pixels import (
    FillGuides,
    fill_skipped,
    pattern_spacing,
    traced_subset,
)
from phrt_usd.engine.trace.tracer import Tracer, fill_guides
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.model.render_options import RenderOptions
from phrt_usd.run.images import tonemap_ldr
from phrt_usd.usd.stage import open_stage

#: The regular patterns and two rates between them (their extra traced pixels keep
#: their values; the fill interpolates on the coarser pattern's lattice).
DENSITIES = ["half", "quarter", "eighth", "sixteenth", "12/16", "5/16"]


def _plane(height: int, width: int, depth: float = 5.0) -> FillGuides:
    """Guides of a flat mirror facing the camera: one normal, positions on the plane z = 0
    (1 cm a pixel), one view depth."""
    row, col = np.divmod(np.arange(height * width), width)
    position = np.stack([0.01 * col, 0.01 * row, np.zeros(height * width)], axis=1)
    normal = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (height * width, 1))
    return FillGuides(normal, position, np.full(height * width, depth, np.float32), width, height)


def _split_pattern(height, width, density, src, phase=(0, 0)):
    """Every pixel of a (height, width) image of sources ``src`` (flat): the traced mask
    of ``traced_subset`` and the pixels."""
    pix = np.arange(height * width, dtype=np.int64)
    return pix, traced_subset(pix, src, int(src.max()) + 1, width, density, phase)


def _fill(pix, src, radiance, traced, guides, density, hit=None, phase=(0, 0)):
    """fill_skipped of the untraced pixels: {pixel: radiance}, and the hit estimates."""
    hit = np.full(int(traced.sum()), 2.0, np.float32) if hit is None else hit[traced]
    filled, got, got_hit, *_ = fill_skipped(
        pix[traced], src[traced], radiance[traced], hit, pix[~traced], src[~traced], guides,
        density, phase=phase,
    )  # fmt: skip
    return dict(zip(pix[~traced][filled].tolist(), got, strict=True)), got_hit


def _raster(height, width, sky, reflectivity=0.4, local=0.3):
    """Raster images (fallback, local, reflectivity), (H, W, ...) float32, of a reflector
    whose fallback reflection is ``sky`` (H*W, 3): fallback = (1 - F) local + F sky."""
    f = np.full((height, width), reflectivity, np.float32)
    loc = np.full((height, width, 3), local, np.float32)
    fallback = (1.0 - f[..., None]) * loc + f[..., None] * sky.reshape(height, width, 3)
    return fallback.astype(np.float32), loc, f


@pytest.mark.parametrize("density", ["half", "eighth", "sixteenth", "5/16"])
def test_a_reflection_of_the_sky_is_reconstructed_exactly(density):
    """Every traced ray left the scene (hit +inf) and saw the environment in its mirror
    direction, which the raster fallback shows at every pixel: a skipped pixel takes its
    own fallback reflection, however much the sky varies between samples (a rippled
    pond's highlights; 1e-5: float32 rounding of the fallback's blend, divided by F).
    Without the raster images, or with a reflectivity under ENV_MIN_REFLECTIVITY, the
    fill interpolates as before (the sky's detail between samples is lost)."""
    height, width = 24, 32
    src = np.zeros(height * width, np.int64)
    pix, traced = _split_pattern(height, width, density, src)
    sky = np.random.default_rng(7).random((height * width, 3)).astype(np.float32) * 4.0
    inf = np.full(height * width, np.inf, np.float32)
    guides = _plane(height, width)
    with_sky = FillGuides.of(_GBufferLike(guides), _raster(height, width, sky))
    got, _hit = _fill(pix, src, sky, traced, with_sky, density, hit=inf)
    assert len(got) == int((~traced).sum())
    for p, value in got.items():
        np.testing.assert_allclose(value, sky[p], rtol=1e-5, atol=1e-5)
    for off in (guides, FillGuides.of(_GBufferLike(guides),
                                      _raster(height, width, sky, reflectivity=0.005))):
        got, _hit = _fill(pix, src, sky, traced, off, density, hit=inf)
        error = np.mean([np.abs(v - sky[p]).max() for p, v in got.items()])
        assert error > 0.1  # random sky: interpolation cannot know it


def test_the_sky_rule_keeps_reflected_geometry():
    """Samples whose rays hit something (finite hit distance) are interpolated as before,
    the raster images given or not: the rule changes only what the sky stands for."""
    height, width = 24, 32
    src = np.zeros(height * width, np.int64)
    pix, traced = _split_pattern(height, width, "quarter", src)
    radiance = np.random.default_rng(8).random((height * width, 3)).astype(np.float32)
    sky = np.full((height * width, 3), 9.0, np.float32)
    guides = _plane(height, width)
    plain, _ = _fill(pix, src, radiance, traced, guides, "quarter")
    ruled, _ = _fill(pix, src, radiance, traced,
                     FillGuides.of(_GBufferLike(guides), _raster(height, width, sky)), "quarter")
    assert plain.keys() == ruled.keys()
    for p in plain:
        np.testing.assert_array_equal(plain[p], ruled[p])


class _GBufferLike:
    """What ``FillGuides.of`` reads of a G-buffer, from a ``FillGuides`` of flat images."""

    def __init__(self, guides: FillGuides):
        shape = (guides.height, guides.width)
        self.shape = shape
        self.normal = guides.normal.reshape(*shape, 3)
        self.position = guides.position.reshape(*shape, 3)
        self.depth = guides.depth.reshape(shape)


@pytest.mark.parametrize("phase", [(0, 0), (1, 3)])
@pytest.mark.parametrize("density", DENSITIES)
def test_a_linear_ramp_is_reproduced_at_interior_pixels(density, phase):
    """Radiance linear in (row, col), a different ramp per source, two sources side by
    side, the pattern shifted by ``phase``, traced pixels in any order: every skipped
    pixel gets a value, and where its cell and the lattice points beyond it lie on its
    source (2 lattice steps, 2 spacings) the value is the ramp's (Catmull-Rom reproduces
    linear functions; 1e-5 relative: float32 radiance). The fill also reports the traced
    pixels' hit distance as its estimate (one distance everywhere)."""
    step = pattern_spacing(density)
    height, width = 8 * step + 3, 12 * step
    split = 6 * step
    row, col = np.divmod(np.arange(height * width), width)
    src = (col >= split).astype(np.int64)
    pix, traced = _split_pattern(height, width, density, src, phase)
    radiance = np.stack([0.5 + 0.01 * row, 0.2 + 0.02 * col, 100.0 * src + row - col], axis=1)
    radiance = radiance.astype(np.float32)
    order = np.random.default_rng(3).permutation(len(pix))  # traced in any order
    pix, src, radiance, traced = pix[order], src[order], radiance[order], traced[order]
    got, hit = _fill(pix, src, radiance, traced, _plane(height, width), density, phase=phase)
    assert sorted(got) == sorted(pix[~traced].tolist())
    np.testing.assert_allclose(hit, 2.0, rtol=1e-5)
    reach = 2 * step
    for p, value in got.items():
        r, c = divmod(p, width)
        lo, hi = (0, split) if c < split else (split, width)
        if reach <= r < height - reach and lo + reach <= c < hi - reach:
            want = np.array([0.5 + 0.01 * r, 0.2 + 0.02 * c, 100.0 * (c >= split) + r - c])
            np.testing.assert_allclose(value, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("edge_kind", ["element", "normal", "depth"])
@pytest.mark.parametrize("density", DENSITIES)
def test_an_edge_does_not_bleed(density, edge_kind):
    """Two sides of a vertical edge: two reflectors, or one reflector folded at a right
    angle (its normals), or one reflector with a step of 1 m towards the camera (its
    positions leave each other's plane). One side reflects 1, the other 0: every filled
    pixel takes only samples of its own side (exactly its side's value: a filled value
    is a weighted mean of same-side samples, each corrected by same-side curvature
    only)."""
    step = pattern_spacing(density)
    height, width = 6 * step + 1, 10 * step + 1
    edge = 5 * step + 1  # between lattice columns: cells straddle it
    guides = _plane(height, width)
    row, col = np.divmod(np.arange(height * width), width)
    right = col >= edge
    src = np.zeros(height * width, np.int64)
    if edge_kind == "element":
        src = right.astype(np.int64)
    elif edge_kind == "normal":  # the right side turns into the plane x = its edge's
        guides.normal[right] = (1.0, 0.0, 0.0)
        guides.position[right, 2] = guides.position[right, 0] - 0.01 * edge
        guides.position[right, 0] = 0.01 * edge
    else:
        guides.position[right, 2] = 1.0
    radiance = np.repeat(np.where(right, 0.0, 1.0)[:, None], 3, axis=1).astype(np.float32)
    pix = np.arange(height * width, dtype=np.int64)
    traced = traced_subset(pix, np.zeros_like(src), 1, width, density)
    got, _ = _fill(pix, src, radiance, traced, guides, density)
    assert len(got) == int((~traced).sum())
    for p, value in got.items():
        np.testing.assert_array_equal(value, radiance[p], err_msg=f"pixel {divmod(p, width)}")


def test_without_hit_distances_the_fill_has_no_hit_guide():
    """hit_distance None (a result that did not measure it) fills as if every ray had
    left the scene: all alike, so the hit-distance guide weighs every corner the same."""
    height, width = 21, 23
    src = np.zeros(height * width, np.int64)
    pix, traced = _split_pattern(height, width, "quarter", src)
    radiance = np.random.default_rng(5).random((height * width, 3)).astype(np.float32)
    guides = _plane(height, width)
    args = (pix[traced], src[traced], radiance[traced])
    unknown = fill_skipped(*args, None, pix[~traced], src[~traced], guides, "quarter")
    far = np.full(int(traced.sum()), np.inf, np.float32)
    left = fill_skipped(*args, far, pix[~traced], src[~traced], guides, "quarter")
    for a, b in zip(unknown, left, strict=True):
        np.testing.assert_array_equal(a, b)


def _block_ratio(luma: np.ndarray, label: np.ndarray, step: int) -> float:
    """Mean |second difference| along rows and columns centred on the pattern's lattice
    lines (where the bilinear fill creased) over its mean centred elsewhere, on the
    three-pixel stencils within one ``label`` (>= 0; -1: not measured): 1 for an image
    with no structure on the pattern's grid."""
    on, off = [], []
    for image, lab in ((luma, label), (luma.T, label.T)):
        second = np.abs(image[:, :-2] - 2.0 * image[:, 1:-1] + image[:, 2:])
        ok = (lab[:, 1:-1] >= 0) & (lab[:, :-2] == lab[:, 1:-1]) & (lab[:, 2:] == lab[:, 1:-1])
        lattice = (np.arange(1, image.shape[1] - 1) % step == 0)[None, :]
        on.append(second[ok & lattice])
        off.append(second[ok & ~lattice])
    return float(np.concatenate(on).mean() / np.concatenate(off).mean())


@pytest.mark.parametrize("density", ["quarter", "sixteenth"])
def test_a_smooth_reflection_shows_no_blocks(density):
    """A smooth radiance (periods of 60 and 78 pixels) on a flat mirror: the second
    differences on the pattern's lattice lines are no larger than between them. Bound
    1.25: Catmull-Rom's residual structure at these periods measured 1.11-1.27 with the
    separable form, the bilinear fill's creases 8.3-17 (its second differences vanish
    inside the cells). Interior pixels only (2 spacings from the image's edge, where the
    fill is linear for want of samples beyond)."""
    step = pattern_spacing(density)
    height, width = 120, 160
    row, col = np.divmod(np.arange(height * width), width)
    value = 0.5 + 0.3 * np.sin(2 * np.pi * row / 60) * np.cos(2 * np.pi * col / 78)
    radiance = np.repeat(value[:, None], 3, axis=1).astype(np.float32)
    src = np.zeros(height * width, np.int64)
    pix, traced = _split_pattern(height, width, density, src)
    got, _ = _fill(pix, src, radiance, traced, _plane(height, width), density)
    image = value.copy()
    image[list(got)] = [v[0] for v in got.values()]
    label = np.full((height, width), -1)
    label[2 * step : -2 * step, 2 * step : -2 * step] = 0
    assert _block_ratio(image.reshape(height, width), label, step) <= 1.25


@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**32 - 1), st.sampled_from(DENSITIES)
)
def test_any_layout_fills_within_its_own_sources_values(width, height, seed, density):
    """Any image size, any sources, any traced subset (not only the patterns), any
    normals and depths, traced pixels in any order, a reused table: a skipped pixel with
    a traced pixel of its source within the pattern's spacing - 1 rows and columns gets
    a value, and every value lies within the range of its source's traced values within
    2 spacings (the clamp to the corners used, no other source); the table is left all
    -1."""
    rng = np.random.default_rng(seed)
    n = width * height
    pix = rng.permutation(n)[: rng.integers(0, n + 1)].astype(np.int64)
    src = rng.integers(0, 3, len(pix)).astype(np.int64)
    traced = rng.random(len(pix)) < 0.5
    normal = rng.normal(size=(n, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    guides = FillGuides(normal, rng.normal(size=(n, 3)), rng.uniform(1, 9, n).astype(np.float32),
                        width, height)  # fmt: skip
    radiance = rng.random((int(traced.sum()), 3)).astype(np.float32)
    hit = np.where(rng.random(int(traced.sum())) < 0.2, np.inf, rng.uniform(0, 9, len(radiance)))
    table = np.full(n, -1, np.int32)
    filled, got, got_hit, *_ = fill_skipped(
        pix[traced], src[traced], radiance, hit.astype(np.float32), pix[~traced], src[~traced],
        guides, density, table,
    )  # fmt: skip
    filled = pix[~traced][filled]
    assert (table == -1).all()
    assert np.all(got_hit >= -1e-3)  # distances, +inf where the taps' rays left the scene
    step = pattern_spacing(density)
    where = {int(p): (int(s), radiance[i]) for i, (p, s) in enumerate(
        zip(pix[traced], src[traced], strict=True))}  # fmt: skip
    filled_at = dict(zip(filled.tolist(), got, strict=True))
    for p, s in zip(pix[~traced].tolist(), src[~traced].tolist(), strict=True):
        r, c = divmod(p, width)

        def around(reach, r=r, c=c, s=s):
            return [where[q][1] for q in (y * width + x for y in range(r - reach, r + reach + 1)
                    for x in range(c - reach, c + reach + 1) if 0 <= y < height and 0 <= x < width)
                    if q in where and where[q][0] == s]  # fmt: skip

        if around(step - 1):
            assert p in filled_at
        if p in filled_at:
            values = np.array(around(2 * step))
            assert len(values)
            assert np.all(filled_at[p] >= values.min(axis=0) - 1e-6)
            assert np.all(filled_at[p] <= values.max(axis=0) + 1e-6)


def test_traced_pixels_keep_their_values_and_report_their_hit_distance():
    """The mirror floor reflecting a sphere, at a sixteenth: the pixels the pattern
    traces have the full density's radiance exactly, and each traced pixel's hit
    distance is where its mirror ray meets the sphere (1e-3 relative: float32 rays and a
    tessellated sphere, 5 subdivisions, whose facets lie within 1e-4 m of it) or +inf
    where it meets nothing."""
    center, radius = np.array([0.3, 1.0, -0.5]), 0.6
    parts = [
        dict(mesh=quad(60.0), F=1.0),
        dict(mesh=sphere(radius, center, 5), albedo=(1, 0, 0), emissive=(1, 0, 0)),
    ]
    tracer = Tracer(parts_scene(parts))
    camera = look_at((0.0, 3.0, 6.0), (0.0, 0.0, 0.0))
    gb = tracer.primary_gbuffer(camera, 160, 120)
    full = tracer.trace_reflections(gb, [0], 5)
    sparse = tracer.trace_reflections(gb, [0], 5, density="sixteenth")
    keep = traced_subset(full.pixel_index, np.zeros(len(full.pixel_index), np.int64), 1, 160,
                         "sixteenth")  # fmt: skip
    by_pixel = dict(zip(sparse.pixel_index.tolist(), sparse.radiance, strict=True))
    for p, value in zip(full.pixel_index[keep].tolist(), full.radiance[keep], strict=True):
        np.testing.assert_array_equal(by_pixel[p], value)
    points = gb.position.reshape(-1, 3)[full.pixel_index]
    view = gb.view_dir.reshape(-1, 3)[full.pixel_index].astype(np.float64)
    mirrored = view * np.array([1.0, -1.0, 1.0])  # the floor is the plane y = 0
    oc = points - center
    b = np.einsum("ij,ij->i", oc, mirrored)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius * radius)
    # Clear hits and clear misses (the tessellation differs from the sphere at its rim).
    hits, misses = disc > 0.01 * radius**2, disc < -0.01 * radius**2
    assert hits.sum() > 100 and misses.sum() > 100
    assert np.isinf(full.hit_distance[misses]).all()
    np.testing.assert_allclose(full.hit_distance[hits], -b[hits] - np.sqrt(disc[hits]), rtol=1e-3)


#: The sewer's wet tunnel frames of the density figures (docs/heuristic.md), a third of
#: them: the test's run time.
SEWER_FRAMES = (217.0, 241.0, 265.0)


@pytest.mark.slow
def test_probe_reduced_densities_show_as_blocks():
    """The sewer's wet tunnel at 320 x 240, every reflector traced: at each reduced
    density the mean FLIP against full density stays within its limit. Under the earlier
    Lambert / Blinn-Phong shading this fill measured 0.0236, 0.0437, 0.0715 (half,
    quarter, sixteenth) against the bilinear fill's 0.0255, 0.0441, 0.0730 (the renderer
    with the bilinear fill of the commit before it), which were the limits. The
    UsdPreviewSurface BRDF's sharp lamp highlights on the wet floor raised every
    density's error by 3-11 % (the fill unchanged: 0.0261, 0.0464, 0.0736), and the
    bilinear fill no longer exists to measure against: the limits are now this fill's
    own figures under the BRDF plus 2 % (FLIP of seeded renders: the margin covers float
    rounding between machines), a guard against regressions of the fill; that it has no
    blocks is the ratio below. At a sixteenth the reflectors' second differences centred on the
    pattern's lattice lines over those centred between them stay under 1.6 (this fill:
    1.15-1.53; the bilinear fill: 3.2-5.1; the full-density image: 1.00-1.01; what is
    left is the traced pixels' own, often aliased, detail, which they keep exactly).
    The error falls as the rate rises: each rate's mean FLIP is at most that of the next
    coarser regular pattern (what a rate between two adds is traced pixels, kept exact)."""
    limits = {d: 1.02 * v for d, v in (("half", 0.0261), ("quarter", 0.0464),
                                         ("sixteenth", 0.0736))}  # fmt: skip
    coarser = {"12/16": "half", "half": "5/16", "5/16": "quarter", "quarter": "eighth",
               "eighth": "sixteenth"}  # fmt: skip
    stage = open_stage(STAGES / "sewer.usda")
    renderers = {
        d: FrameRenderer(stage, RenderOptions(mode="hybrid", heuristic="all", width=320,
                                              height=240, budget_ms=None, trace_density=d))
        for d in ["full", *DENSITIES]
    }  # fmt: skip
    flips: dict[str, list[float]] = {d: [] for d in DENSITIES}
    try:
        for t in SEWER_FRAMES:
            frames = {d: r.render(t) for d, r in renderers.items()}
            full = frames["full"].beauty
            for d in DENSITIES:
                flips[d].append(float(flip_map(full, frames[d].beauty).mean()))
            element = frames["sixteenth"].gbuffer.element_id
            label = np.where(np.isin(element, stage.scene.reflector_ids), element, -1)
            luma = tonemap_ldr(frames["sixteenth"].beauty).mean(axis=2)
            assert _block_ratio(luma, label, pattern_spacing("sixteenth")) <= 1.6, t
    finally:
        for r in renderers.values():
            r.close()
    for d, limit in limits.items():
        assert np.mean(flips[d]) <= limit, (d, flips[d])
    for d, c in coarser.items():
        assert np.mean(flips[d]) <= np.mean(flips[c]), (d, flips[d], c, flips[c])


def test_the_sky_rule_is_off_on_stages_with_transmissive_materials():
    """A glass pane's traced radiance mixes in what it refracts, which the raster's
    fallback reflection does not show: there the fill's guides carry no raster images."""
    height, width = 4, 6
    raster = _raster(height, width, np.zeros((height * width, 3), np.float32))
    gb = _GBufferLike(_plane(height, width))
    for opacity, kept in ((1.0, True), (0.4, False)):
        parts = [{"mesh": quad(1.0), "F": 0.5}, {"mesh": sphere(0.3, (0, 0, 1)),
                                                  "opacity": opacity}]  # fmt: skip
        tracer = Tracer(parts_scene(parts))
        guides = fill_guides(gb, raster, tracer.surfaces.transmission)
        assert (len(guides.raster[0]) > 0) is kept
