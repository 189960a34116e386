"""Glossy reflections (``engine/trace/glossy.py``, ``model/reflection_roughness.py``): a
reflector's roughness blurs its reflection, in rt and hybrid alike, into a clean image
(no blocks, no fireflies), and rt's frames converge to the lobe's true average."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade
from scenes import sky_view_stage

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace import glossy
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.model import reflection_roughness
from phrt_usd.usd import schema
from phrt_usd.usd.stage import open_stage

WIDTH, HEIGHT = 96, 72
#: The floor's rows the reflected box's edges are measured on: below the box's contact
#: line, the upper half of its mirror image (the mirror's render shows it on rows
#: 43-58).
EDGE_ROWS = range(46, 57)
#: Rec. 709 luminance.
LUMA = np.array([0.2126, 0.7152, 0.0722])


def _material(stage, path: str, colour, roughness: float, metallic: float = 0.0,
              emissive=None) -> UsdShade.Material:  # fmt: skip
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(metallic))
    if emissive is not None:
        shader.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*emissive))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def _stage(path, roughness: float, wall: bool = False) -> str:
    """A 12 m floor (a reflector of a grey metallic UsdPreviewSurface of ``roughness``,
    its reflection by the material) under a light-blue dome and a sun, the camera 1.2 m
    up, 4 m back, looking at a red 1 m box standing on it (its mirror image on the floor
    below it); with ``wall``, instead of the box a 4 x 2 m wall 2 m behind the origin,
    black and emitting orange (its radiance is its emission: no lighting noise), and no
    sun."""
    stage = sky_view_stage(path, (0.5, 0.6, 0.8), (0.0, 1.2, 4.0), (0.0, 0.3, 0.0))
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    h = 6.0
    floor.CreatePointsAttr([(-h, 0, -h), (-h, 0, h), (h, 0, h), (h, 0, -h)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    look = _material(stage, "/World/Looks/Floor", (0.8, 0.8, 0.8), roughness, metallic=1.0)
    UsdShade.MaterialBindingAPI.Apply(floor.GetPrim()).Bind(look)
    schema.apply_reflector(floor.GetPrim(), priority=1.0, reflectivity=None)
    if wall:
        mesh = UsdGeom.Mesh.Define(stage, "/World/Wall")
        mesh.CreatePointsAttr([(-2, 0, -2), (2, 0, -2), (2, 2, -2), (-2, 2, -2)])
        mesh.CreateFaceVertexCountsAttr([4])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        glow = _material(stage, "/World/Looks/Wall", (0.0, 0.0, 0.0), 1.0,
                         emissive=(3.0, 1.2, 0.3))  # fmt: skip
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(glow)
    else:
        sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
        sun.CreateIntensityAttr(2.0)
        UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-60.0, 30.0, 0.0))
        box = UsdGeom.Cube.Define(stage, "/World/Box")
        box.CreateSizeAttr(1.0)
        box.CreateDisplayColorAttr([Gf.Vec3f(0.9, 0.05, 0.05)])
        UsdGeom.Xformable(box).AddTranslateOp().Set(Gf.Vec3d(0.0, 0.5, 0.0))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.GetRootLayer().Save()
    return str(path)


def _renderer(path: str, mode: str, **options) -> FrameRenderer:
    options = {"heuristic": "all", "budget_ms": None, **options}
    return FrameRenderer(open_stage(path), RenderOptions(mode=mode, width=WIDTH,
                                                         height=HEIGHT, **options))


def _render(path: str, mode: str, time: float = 1.0, **options):
    renderer = _renderer(path, mode, **options)
    try:
        return renderer.render(time)
    finally:
        renderer.close()


def _blur(image: np.ndarray) -> float:
    """The mean of ``_edge_width`` over the reflection's upper rows (EDGE_ROWS: its
    blur is measured on several rows, each of a few samples' noise)."""
    return float(np.mean([_edge_width(image, row) for row in EDGE_ROWS]))


def _edge_width(image: np.ndarray, row: int = EDGE_ROWS[0]) -> float:
    """The mean 10-90 % width in pixels of the two side edges of the red reflection
    along ``row``: redness (R - (G + B) / 2) normalised to its peak on the row, from the
    first column over 10 % to the first over 90 % on the left, and mirrored on the
    right."""
    line = image[row].astype(np.float64)
    red = line[:, 0] - 0.5 * (line[:, 1] + line[:, 2])
    red = (red - np.median(red)) / max(red.max() - np.median(red), 1e-9)
    widths = []
    for profile in (red, red[::-1]):
        at10 = int(np.argmax(profile >= 0.1))
        at90 = int(np.argmax(profile >= 0.9))
        widths.append(at90 - at10)
    return float(np.mean(widths))


#: The floor's element id in the stages of ``_stage`` (its first gprim).
FLOOR = 0


def _floor(out) -> np.ndarray:
    """(H, W) bool: the floor's pixels whose 5 x 5 neighbourhood is all floor (away from
    the box's silhouette and the horizon)."""
    floor = out.gbuffer.element_id == FLOOR
    inner = floor.copy()
    for dr in range(-2, 3):
        for dc in range(-2, 3):
            inner &= np.roll(np.roll(floor, dr, axis=0), dc, axis=1)
    inner[:2], inner[-2:], inner[:, :2], inner[:, -2:] = False, False, False, False
    return inner


def _luminance(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float64) @ LUMA


def _firefly_ratio(image: np.ndarray, mask: np.ndarray) -> float:
    """The largest luminance of a pixel of ``mask`` over the median of the 5 x 5 around
    it."""
    lum = _luminance(image)
    stack = np.stack([np.roll(np.roll(lum, dr, axis=0), dc, axis=1)
                      for dr in range(-2, 3) for dc in range(-2, 3)])  # fmt: skip
    median = np.median(stack, axis=0)
    return float((lum[mask] / np.maximum(median[mask], 1e-6)).max())


def _tile_ratio(error: np.ndarray, mask: np.ndarray) -> float:
    """The largest mean of ``error`` over the pixels of one of the 16 classes (row mod
    4, column mod 4) of ``mask``, over the mean of all: the reduced densities' patterns
    are 2 x 2 and 4 x 4 lattices, so a reconstruction that shows its tiles (traced
    pixels exact, filled ones off) puts its error into some of the classes."""
    rows, cols = np.nonzero(mask)
    classes = (rows % 4) * 4 + cols % 4
    values = error[rows, cols]
    means = np.bincount(classes, weights=values, minlength=16) / np.maximum(
        np.bincount(classes, minlength=16), 1)
    return float(means.max() / max(values.mean(), 1e-12))


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    directory = tmp_path_factory.mktemp("glossy")
    paths = {r: _stage(directory / f"floor_{r}.usda", r) for r in (0.05, 0.15, 0.3)}
    elements = open_stage(paths[0.3]).scene.elements
    assert elements[FLOOR].path == "/World/Floor" and elements[FLOOR].is_reflector
    return paths


@pytest.mark.slow
def test_the_reflection_blurs_more_the_rougher_the_floor_in_rt_and_hybrid(stages):
    """The red box's mirror image on the floor: its side edges' 10-90 % width grows with
    roughness, strictly, 0.05 < 0.15 < 0.3, in rt, hybrid at full density and hybrid at
    the density HEU1 chooses under a rays budget (which steps the floor coarser). At
    0.05 (the mirror's ray) the edge is sharp (at most 2 px: the pixel grid and the
    sun's lit/shaded box face), at 0.3 it spreads over at least 4 px (measured: rt and
    hybrid 0 / 7.3 / 9.2 px, HEU1, which steps the glossy floors to a sixteenth, 1 / 9.0
    / 9.5: its reconstruction's reach adds to the lobe's blur)."""
    widths: dict[str, list[float]] = {"rt": [], "hybrid": [], "heu1": []}
    for r in (0.05, 0.15, 0.3):
        widths["rt"].append(_blur(_render(stages[r], "rt").beauty))
        widths["hybrid"].append(_blur(_render(stages[r], "hybrid").beauty))
        out = _render(stages[r], "hybrid", heuristic="heu1", budget_rays=1500)
        assert out.stats.densities, "the budget leaves the floor at full density"
        widths["heu1"].append(_blur(out.beauty))
    for mode, w in widths.items():
        assert w[0] < w[1] < w[2], (mode, widths)
        assert w[0] <= 2.0 and w[2] >= 4.0, (mode, widths)


@pytest.mark.slow
def test_glossy_hybrid_is_clean_and_within_flip_of_rt(stages):
    """At roughness 0.3: hybrid with every reflector traced is within mean FLIP 0.02 of
    rt (the threshold of every reflector in hybrid; here they trace the same rays, the
    difference is the G-buffer's source); at the density HEU1 chooses under a rays
    budget (asserted to be reduced) the error against rt shows no 2 x 2 / 4 x 4 tiles
    (no class of pixel positions modulo 4 carries more than 1.6 x the mean error: a
    tiled fill that copies its traced samples measures 2.5-4), and no floor pixel in
    rt or hybrid is brighter than 3 x the median of its 5 x 5 neighbourhood (the blurred
    reflection of a lit box on a metal floor varies smoothly: a firefly is a lone pixel
    several times its surroundings; the box's edge, red against sky, stays under 3)."""
    rt = _render(stages[0.3], "rt")
    full = _render(stages[0.3], "hybrid")
    heu1 = _render(stages[0.3], "hybrid", heuristic="heu1", budget_rays=1500)
    assert heu1.stats.densities, "the budget leaves the floor at full density"
    assert float(flip_map(rt.beauty, full.beauty).mean()) <= 0.02
    mask = _floor(rt)
    error = np.abs(_luminance(heu1.beauty) - _luminance(rt.beauty))
    assert _tile_ratio(error, mask) <= 1.6
    for out in (rt, full, heu1):
        assert _firefly_ratio(out.beauty, mask) <= 3.0


def test_the_tile_and_firefly_checks_can_fail():
    """The checks above on images made to fail them: an error carried by one pixel of
    each 2 x 2 block (a tiled reconstruction), and a lone pixel 5 x its surroundings."""
    mask = np.ones((40, 40), bool)
    rng = np.random.default_rng(1)
    smooth = rng.uniform(0.9, 1.1, (40, 40))
    tiled = smooth.copy()
    tiled[::2, ::2] += 1.0
    assert _tile_ratio(smooth, mask) <= 1.6 < _tile_ratio(tiled, mask)
    image = np.repeat(smooth[..., None], 3, axis=2)
    assert _firefly_ratio(image, mask) <= 3.0
    image[20, 20] *= 5.0
    assert _firefly_ratio(image, mask) > 3.0


@pytest.mark.slow
def test_glossy_draws_are_a_hash_of_pixel_and_frame(tmp_path):
    """rt and hybrid at full density trace the same rays, and a frame rendered again is
    bit-identical, while another frame draws other rays (its image differs)."""
    path = _stage(tmp_path / "floor.usda", 0.3)
    renderer = _renderer(path, "rt")
    try:
        first, again = renderer.render(1.0).beauty, renderer.render(1.0).beauty
        other = renderer.render(2.0).beauty
    finally:
        renderer.close()
    assert np.array_equal(first, again)
    assert not np.array_equal(first, other)


def _reference(out, emission, sky, samples: int = 2048) -> np.ndarray:
    """(H, W, 3) the wall stage's reflected radiance at its floor pixels, by integrating
    the GGX lobe (alpha = 0.3²) about +Y with ``samples`` visible-normal draws a pixel
    (numpy, a Hammersley set rotated per pixel), each weighted G2 / G1 over the kept
    draws' sum: the wall's ``emission`` where the reflected ray meets it (x in [-2, 2],
    y in [0, 2] at z = -2), the ``sky`` elsewhere. The floor's reflection weight is the
    metal's W times this (the pixel's local part: its diffuse, 0 for a metal)."""
    gb = out.gbuffer
    floor = gb.element_id == FLOOR
    rows, cols = np.nonzero(floor)
    p = gb.position[rows, cols].astype(np.float64)
    v = -gb.view_dir[rows, cols].astype(np.float64)  # to the eye; normal +Y
    alpha = 0.3**2
    a2 = alpha * alpha
    i = np.arange(samples)
    u1 = (i + 0.5) / samples
    u2 = np.modf(i * 0.6180339887498949)[0]
    shift = np.modf(np.arange(len(rows)) * 0.7548776662466927)[0][:, None]
    u2 = np.modf(u2[None, :] + shift)[0]
    u1 = np.broadcast_to(u1, u2.shape)
    # Local frame: n = +Y; tangent x, bitangent z.
    vx, vy, vz = v[:, 0:1], v[:, 2:3], v[:, 1:2]
    hx, hy, hz = alpha * vx, alpha * vy, vz
    norm = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / norm, hy / norm, hz / norm
    lensq = hx * hx + hy * hy
    inv = 1.0 / np.sqrt(np.maximum(lensq, 1e-30))
    t1x, t1y = -hy * inv, hx * inv
    t2x, t2y, t2z = -hz * t1y, hz * t1x, hx * t1y - hy * t1x
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + hz)
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    up = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    mx = alpha * (p1 * t1x + p2 * t2x + up * hx)
    my = alpha * (p1 * t1y + p2 * t2y + up * hy)
    mz = np.maximum(p2 * t2z + up * hz, 0.0)
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    mx, my, mz = mx / norm, my / norm, mz / norm
    vm = vx * mx + vy * my + vz * mz
    lx, ly, lz = 2 * vm * mx - vx, 2 * vm * my - vy, 2 * vm * mz - vz

    def lam(c):
        c = np.maximum(c, 1e-7)
        return 0.5 * (np.sqrt(1.0 + a2 * (1.0 - c * c) / (c * c)) - 1.0)

    kept = lz > 1e-4
    weight = np.where(kept, (1.0 + lam(vz)) / (1.0 + lam(vz) + lam(np.where(kept, lz, 1.0))), 0)
    # World direction (x, y, z) = (lx, lz, ly); the wall's plane z = -2.
    dx, dy, dz = lx, lz, ly
    t = (-2.0 - p[:, 2:3]) / np.where(dz < 0, dz, -1e-30)
    hit_x, hit_y = p[:, 0:1] + t * dx, p[:, 1:2] + t * dy
    on_wall = (dz < 0) & (np.abs(hit_x) <= 2.0) & (hit_y >= 0.0) & (hit_y <= 2.0)
    share = (weight * on_wall).sum(1) / np.maximum(weight.sum(1), 1e-30)
    radiance = share[:, None] * emission + (1.0 - share[:, None]) * sky
    out_image = np.zeros((*gb.shape, 3))
    out_image[rows, cols] = radiance
    return out_image


@pytest.mark.slow
def test_rt_frames_converge_to_the_lobe_average(tmp_path):
    """A static glossy view (roughness 0.3) of an emitting wall over a metal floor: the
    mean of rt's frames approaches the lobe's average computed independently (2,048
    visible-normal draws a pixel, numpy): the mean reflected radiance's relative error
    over the floor falls from the first frame to the mean of 16 (each frame draws other
    rays on another pattern phase) and ends below 4 % (measured: 4.6 % for one frame,
    3.4 % for 16; what stays is the filter's bias: it averages neighbouring pixels'
    lobes, wider than a lobe's blur where the wall's reflection ends). Mirror
    reflections of the same view are 13 % off."""
    path = _stage(tmp_path / "wall.usda", 0.3, wall=True)
    errors = _wall_errors(path, "rt", 16)
    one, mean = errors[0], errors[-1]
    assert mean < one, (one, mean)
    assert mean <= 0.04, (one, mean)


def _wall_errors(path, mode: str, frames: int) -> list[float]:
    """The relative error of each of ``frames`` frames (time codes 1, 2, ...) of the wall
    stage at ``path`` rendered in ``mode`` by one renderer, against ``_reference``: the
    floor's reflected radiance (its pixel over the metal's weight W, from the raster's
    fallback: W times the sky)."""
    renderer = _renderer(path, mode)
    try:
        outs = [renderer.render(float(t)) for t in range(1, frames + 1)]
    finally:
        renderer.close()
    floor = _floor(outs[0])
    sky = np.array([0.5, 0.6, 0.8])
    reference = _reference(outs[0], np.array([3.0, 1.2, 0.3]), sky)[floor]
    weight = _render(path, "raster").beauty[floor].astype(np.float64) / sky

    def error(image) -> float:
        reflected = image[floor].astype(np.float64) / np.maximum(weight, 1e-6)
        return float(np.abs(reflected - reference).sum() / np.abs(reference).sum())

    return [error(out.beauty) for out in outs] + [error(np.mean([o.beauty for o in outs], 0))]


@pytest.mark.slow
def test_hybrid_accumulates_a_still_glossy_view(tmp_path):
    """hybrid blends a glossy pixel's history in (reprojected by the surface): over 8
    frames of the wall stage's still view its error against the lobe's average falls
    below 0.9 x its first frame's (measured 4.6 % then 3.6-4.0 % from the second frame
    on; rt, which keeps no history, stays at 4.1-4.9 % frame by frame)."""
    path = _stage(tmp_path / "wall.usda", 0.3, wall=True)
    errors = _wall_errors(path, "hybrid", 8)[:-1]
    assert max(errors[2:]) < 0.9 * errors[0], errors


def test_the_selection_sees_roughness():
    """A reflector's gain from tracing falls to 0 across the fade (0.5 to 0.7), and its
    share of pixels that start rays follows the glossy rate (a quarter at 0.3, none past
    the fade); a mirror's is 1."""
    gain = reflection_roughness.tracing_gain([0.0, 0.3, 0.6, 0.7, 0.9])
    np.testing.assert_allclose(gain, [1.0, 1.0, 0.5, 0.0, 0.0], atol=1e-6)
    share = reflection_roughness.ray_share([0.0, 0.05, 0.12, 0.3, 0.4, 0.8])
    np.testing.assert_allclose(share, [1.0, 1.0, 0.5, 0.25, 0.0625, 0.0])
    assert glossy.filter_radius(np.array([0.05, 0.15, 0.3]), np.ones(3), 0.01).tolist() == [
        0, 3, 8]


def _striped_dome_stage(path, roughness: float) -> str:
    """``_stage``'s floor and camera (no box) under a dome whose lat-long map has 16
    vertical stripes, black and white (a 64 x 32 PNG beside the stage)."""
    from PIL import Image

    stripes = np.zeros((32, 64, 3), np.uint8)
    for k in range(0, 64, 8):
        stripes[:, k : k + 4] = 255
    texture = path.with_suffix(".png")
    Image.fromarray(stripes).save(texture)
    _stage(path, roughness, wall=True)
    stage = Usd.Stage.Open(str(path))
    stage.RemovePrim("/World/Wall")
    dome = UsdLux.DomeLight(stage.GetPrimAtPath("/World/Sky"))
    dome.CreateColorAttr(Gf.Vec3f(1.0, 1.0, 1.0))
    dome.CreateTextureFileAttr(str(texture))
    stage.GetRootLayer().Save()
    return str(path)


@pytest.mark.slow
def test_a_rough_reflector_shows_the_environment_prefiltered(tmp_path):
    """Past the fade (roughness 0.8) the floor's reflection is the raster's fallback in
    every mode, the striped dome prefiltered by the lobe: along the floor's near rows
    its luminance varies less than a fifth as much as a mirror floor's (the mirror shows
    the stripes at full contrast; the lobe spans about 13 of the map's 64 texels, two
    stripes), and rt shows what raster shows there (no ray is traced for it)."""
    spread = {}
    for r in (0.0, 0.8):
        path = _striped_dome_stage(tmp_path / f"dome_{r}.usda", r)
        out = _render(path, "raster")
        floor = _floor(out)
        rows = np.flatnonzero(floor.any(axis=1))[-12:]
        lum = _luminance(out.beauty)
        spread[r] = float(np.mean([lum[row][floor[row]].std() for row in rows]))
        if r == 0.8:
            rt = _render(path, "rt")
            np.testing.assert_allclose(rt.beauty[floor], out.beauty[floor], rtol=1e-4,
                                       atol=1e-5)  # fmt: skip
    assert spread[0.8] < 0.2 * spread[0.0], spread


@pytest.mark.slow
def test_a_textured_roughness_is_read_per_pixel(tmp_path):
    """A reflector whose ``roughness`` is a texture (left half 0.02, right half 0.4,
    8-bit raw): the lobe of each of its pixels takes the texel under it (within an
    8-bit step), so the left half keeps mirror rays and the right half is glossy."""
    from pxr import Sdf
    from textured_stages import define_texture, textured_quad_stage, write_image

    stage, surface = textured_quad_stage(tmp_path)
    texels = np.zeros((8, 8, 3))
    texels[:, :4], texels[:, 4:] = 0.02, 0.4
    write_image(tmp_path / "rough.png", texels)
    texture = define_texture(stage, "/Looks/Quad/Rough", "./rough.png",
                             sourceColorSpace=(Sdf.ValueTypeNames.Token, "raw"))  # fmt: skip
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(
        texture.ConnectableAPI(), "r")
    schema.apply_reflector(stage.GetPrimAtPath("/Quad"), priority=1.0)
    stage.GetRootLayer().Save()
    loaded = open_stage(stage.GetRootLayer().realPath)
    renderer = FrameRenderer(loaded, RenderOptions(mode="rt", width=48, height=36,
                                                   heuristic="all", budget_ms=None))  # fmt: skip
    try:
        gb = renderer.render(1.0).gbuffer
    finally:
        renderer.close()
    quad = gb.element_id == 0
    rows, cols = np.nonzero(quad)
    rough = glossy.pixel_roughness(loaded.scene, gb, rows * gb.shape[1] + cols)
    # Away from the quad's borders, where the bilinear taps read the wrap mode's black.
    u = (cols - cols.min()) / np.ptp(cols)
    v = (rows - rows.min()) / np.ptp(rows)
    inner = (v > 0.15) & (v < 0.85)
    left, right = inner & (u > 0.15) & (u < 0.4), inner & (u > 0.6) & (u < 0.85)
    np.testing.assert_allclose(rough[left], 0.02, atol=1.0 / 255)
    np.testing.assert_allclose(rough[right], 0.4, atol=1.0 / 255)
