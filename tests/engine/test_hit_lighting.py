"""The direct light at the tracer's hits (``engine/trace/hit_lighting.py``): at analytic
hits the shadow maps give the exact answer with no ray where they decide, an undecided
pair still casts its ray, the light sampling is unbiased and reproducible, and a traced
pixel of a many-light stage costs a few rays, not one per light."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux
from scenes import _look_at_matrix, box_between, mirror_floor_stage, parts_scene

from phrt_usd.engine import lighting, shading
from phrt_usd.engine.raster.rasterizer import Rasterizer
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace import hit_lighting
from phrt_usd.engine.trace.hit_lighting import HitLighting, frame_seed
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model.light_sampling import HIT_LIGHT_PICKS
from phrt_usd.model.scene import Lights, LocalLight
from phrt_usd.usd.stage import open_stage

#: The slab scene's light: one LocalLight 4 m above the floor, bright enough that its
#: range (31.6 m) covers every hit.
LAMP = np.array([0.0, 4.0, 0.0])
#: The 2 m slab between lamp and floor (y 1.9 to 2.0) shadows the floor within |x| < 1.9
#: (its lower edge seen from the lamp); its upper edge's shadow ends at |x| = 2.
SLAB = ((-1.0, 1.9, -1.0), (1.0, 2.0, 1.0))
#: GPU (float32) against compiled float64 shading of the same lit pair: the G-buffer's
#: own tolerance for the light pass (tests/engine/test_light_pass.py).
SHADING_RTOL = 1e-4


def _slab_scene(shaped: bool = False):
    """The floor, the slab and the lamp; ``shaped``: the lamp a downward 80° cone (the
    maps then only look pairs up and the shading evaluates the cone, ``map_lookup``),
    which every hit of the tests lies well inside (56° off its axis at most)."""
    cone = dict(axis=np.array([0.0, -1.0, 0.0]), cone_angle=80.0) if shaped else {}
    lights = Lights(local=[LocalLight(LAMP, np.full(3, 20.0), **cone)])
    floor = box_between((-10, -0.1, -10), (10, 0.0, 10))
    parts = [dict(mesh=floor), dict(mesh=box_between(*SLAB))]
    return parts_scene(parts, lights)


def _floor_hits(tracer: Tracer, xz: np.ndarray):
    """Hits of rays cast straight down at floor points ``xz`` (m, 2), from below the
    slab: the arrays ``HitLighting.shade`` takes (tri, u, v, rel, ng, ns, d_in)."""
    origins = np.column_stack([xz[:, 0], np.full(len(xz), 1.0), xz[:, 1]])
    rel = (origins - tracer.bvh.boundary.origin).astype(np.float32)
    down = np.tile(np.float32([0.0, -1.0, 0.0]), (len(xz), 1))
    hits, _ = tracer.surfaces.intersect(rel, down)
    assert len(hits.ray) == len(xz)  # every ray lands on the floor
    order = np.argsort(hits.ray)
    tri, u, v = hits.tri[order], hits.u[order], hits.v[order]
    pos, ng, ns = tracer.surfaces.geometry(tri, u, v, down)
    return tri, u, v, pos, ng, ns, down


@pytest.fixture(params=[False, True], ids=["lamp", "cone"])
def slab(monkeypatch, request):
    """(tracer, hit lighting with the slab scene's shadow maps, exact hit lighting)."""
    # The maps' step at any batch size and for one light (the rule leaves batches of
    # fewer pairs than MAP_MIN_PAIRS, and stages of at most HIT_LIGHT_PICKS lights, to
    # rays only because there the lookup pass costs more than the rays).
    monkeypatch.setattr(hit_lighting, "MAP_MIN_PAIRS", 1)
    monkeypatch.setattr(hit_lighting, "maps_light_hits", lambda lights: True)
    scene = _slab_scene(request.param)
    tracer = Tracer(scene, threads=1)
    with Rasterizer(scene, 64, 48) as raster:
        rule = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
        rule.maps = lambda p, n, d, s, t: lighting.map_lookup(
            raster, scene.lights, p, n, d, surface=s, terminator=t
        )
        exact = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
        exact.exact = True
        yield tracer, rule, exact


def _shade(rule: HitLighting, tracer: Tracer, hits):
    """(radiance (m, 3), shadow rays per hit (m,)) of ``hits`` by ``rule``."""
    pixels = np.arange(len(hits[0]))
    local, rays, _ = rule.shade(*hits, tracer._relative_lights(), pixels)
    return local, rays


@pytest.mark.parametrize("where", ["lit", "shadowed"])
def test_hit_the_maps_decide_is_exact_without_rays(slab, where):
    tracer, rule, exact = slab
    rng = np.random.default_rng(3)
    # Far from the shadow's edge (|x| 1.9 to 2.0): fully lit at 4-6 m, fully under the
    # slab within 1 m of its centre.
    lo, hi = (4.0, 6.0) if where == "lit" else (-1.0, 1.0)
    xz = np.column_stack([rng.uniform(lo, hi, 200), rng.uniform(-1.0, 1.0, 200)])
    hits = _floor_hits(tracer, xz)
    local, rays = _shade(rule, tracer, hits)
    want, want_rays = _shade(exact, tracer, hits)
    assert rays.sum() == 0 and want_rays.sum() == 200  # the exact evaluation: one a hit
    np.testing.assert_allclose(local, want, rtol=SHADING_RTOL, atol=1e-6)
    # Analytically: under the slab the ambient term alone (the mean environment times
    # the surface's directional albedo, ``shade_kernels.ambient_weight``); in the open
    # the lamp's 20 / d² x the range window x the BRDF's π f n·l on top of it (the
    # numpy BRDF of tests/shading_reference.py).
    import shading_reference as ref

    tri, u, v, pos, _, ns, down = hits
    surf = tracer.surfaces.surface(tri, u, v, tracer.surfaces.colour(tri, u, v)[0])
    ambient = ref.ambient_weight(surf, ns, -down) * shading.ambient_radiance(
        tracer.scene.lights
    )
    if where == "shadowed":
        np.testing.assert_allclose(want, ambient, rtol=1e-5)
    else:
        to_lamp = LAMP - (pos + tracer.bvh.boundary.origin)
        d2 = np.einsum("ij,ij->i", to_lamp, to_lamp)
        window = shading.range_window(np.sqrt(d2), shading.light_ranges(tracer.scene.lights)[0])
        to_lamp /= np.sqrt(d2)[:, None]
        lamp = (20.0 * window / d2)[:, None] * ref.brdf_cos(surf, ns, -down, to_lamp)
        np.testing.assert_allclose(want, ambient + lamp, rtol=1e-4)


def test_undecided_pair_casts_its_ray(slab):
    tracer, rule, exact = slab
    # Across the shadow's edge: some pairs the maps cannot decide.
    xz = np.column_stack([np.linspace(1.7, 2.2, 400), np.linspace(-0.5, 0.5, 400)])
    hits = _floor_hits(tracer, xz)
    world = hits[3] + tracer.bvh.boundary.origin
    undecided = np.zeros(len(xz), bool)
    query = rule.maps(world, hits[5], hits[6], None, None).uncertain_pairs()
    assert query is not None and 5 <= len(query.rows) < len(xz)
    undecided[query.rows] = query.pairs.any(axis=1)
    local, rays = _shade(rule, tracer, hits)
    want, _ = _shade(exact, tracer, hits)
    # One light, fewer than HIT_LIGHT_PICKS: every undecided pair is traced, none other.
    np.testing.assert_array_equal(rays, undecided.astype(np.int64))
    np.testing.assert_allclose(local[undecided], want[undecided], rtol=SHADING_RTOL, atol=1e-6)
    # Both sides of the edge are among the traced hits (lit and shadowed answers).
    assert want[undecided].max() > 2 * want[undecided].min()


def test_few_lights_are_traced_exactly_without_maps():
    # One light: every hit traces it (no sampling, no maps), whatever the batch.
    scene = _slab_scene()
    tracer = Tracer(scene, threads=1)
    rule = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
    rule.maps = lambda *_: pytest.fail("a one-light stage looked its hits up in the maps")
    xz = np.random.default_rng(4).uniform(-8.0, 8.0, (20_000, 2))  # > MAP_MIN_PAIRS pairs
    hits = _floor_hits(tracer, xz)
    exact = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
    exact.exact = True
    local, rays = _shade(rule, tracer, hits)
    want, want_rays = _shade(exact, tracer, hits)
    np.testing.assert_array_equal(rays, want_rays)
    np.testing.assert_array_equal(local, want)


def _many_lights_scene():
    """A floor under 8 LocalLights of different brightness, with pillars that hide some
    of them from some floor points."""
    rng = np.random.default_rng(11)
    lamps = [
        LocalLight(np.array([x, rng.uniform(2.0, 4.0), z]), np.full(3, rng.uniform(2.0, 30.0)))
        for x, z in rng.uniform(-6.0, 6.0, (8, 2))
    ]
    parts = [dict(mesh=box_between((-10, -0.1, -10), (10, 0.0, 10)))]
    for x, z in rng.uniform(-5.0, 5.0, (6, 2)):
        parts.append(dict(mesh=box_between((x - 0.3, 0.0, z - 0.3), (x + 0.3, 3.0, z + 0.3))))
    return parts_scene(parts, Lights(local=lamps))


#: Frames the sampling's mean is taken over; how many standard errors a hit's mean may
#: be off the exact sum (its frames' estimates are independent draws, one shift each:
#: over 300 hits x 3 channels the largest of normal deviations is ~3.5, 2.9 measured);
#: and the relative
#: error allowed of the mean over every hit and frame (~0.0002 measured: the per-frame
#: spread of a hit is ~0.23 of its light, over 256 x 300 estimates ~0.001).
UNBIASED_FRAMES = 256
UNBIASED_SIGMAS = 5.0
UNBIASED_RTOL_ALL = 0.005


def test_light_sampling_is_unbiased():
    scene = _many_lights_scene()
    tracer = Tracer(scene, threads=1)
    rng = np.random.default_rng(5)
    xz = rng.uniform(-7.0, 7.0, (300, 2))
    hits = _floor_hits(tracer, xz)
    rule = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)  # no maps: rays only
    rule.width = 20
    exact = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
    exact.exact = True
    want, want_rays = _shade(exact, tracer, hits)
    frames = []
    for f in range(UNBIASED_FRAMES):
        rule.frame_seed = frame_seed(float(f))
        local, rays = _shade(rule, tracer, hits)
        assert rays.max() <= HIT_LIGHT_PICKS
        frames.append(local)
    frames = np.asarray(frames, np.float64)
    mean = frames.mean(axis=0)
    assert want_rays.mean() > 2 * HIT_LIGHT_PICKS  # the sampling had lights to choose from
    assert np.abs(frames - want).max() > 0.05 * float(want.max())  # single frames differ
    standard_error = frames.std(axis=0) / np.sqrt(UNBIASED_FRAMES)
    # (+ float32 rounding of radiance ~1: where every frame drew the same rays)
    assert np.all(np.abs(mean - want) <= UNBIASED_SIGMAS * standard_error + 1e-6)
    assert abs(mean.sum() / want.sum() - 1.0) < UNBIASED_RTOL_ALL


def test_light_sampling_is_reproducible_per_frame():
    scene = _many_lights_scene()
    tracer = Tracer(scene, threads=1)
    hits = _floor_hits(tracer, np.random.default_rng(2).uniform(-7.0, 7.0, (200, 2)))
    rule = HitLighting(tracer.bvh, tracer.surfaces, tracer._shadows)
    rule.width = 16
    images = []
    for t in (12.0, 12.0, 13.0):
        rule.frame_seed = frame_seed(t)
        images.append(_shade(rule, tracer, hits)[0])
    np.testing.assert_array_equal(images[0], images[1])
    assert not np.array_equal(images[0], images[2])


#: Rays a traced pixel may cost (the trace rounds' reflection and shadow rays over the
#: traced pixels) on the many-light room: the target set for the sewer (13 lights) at
#: 640x480, where every reflection hit cast one shadow ray per light (13.3 rays a pixel).
MAX_RAYS_PER_TRACED_PIXEL = 3.0


def _room_stage(path):
    """mirror_floor_stage's mirror floor and ball in a closed room (walls and a ceiling
    4 m up) lit by 8 sphere lights under the ceiling: the reflections hit walls, the
    ceiling and the ball, each seeing several lights, some hidden behind the ball or
    two pillars."""
    mirror_floor_stage(path, 128, 96)
    stage = Usd.Stage.Open(str(path))
    for name, (lo, hi) in {
        "Ceiling": ((-5, 4.0, -5), (5, 4.1, 5)),
        "Back": ((-5, 0, -5.1), (5, 4, -5)),
        "Front": ((-5, 0, 5), (5, 4, 5.1)),
        "Left": ((-5.1, 0, -5), (-5, 4, 5)),
        "Right": ((5, 0, -5), (5.1, 4, 5)),
        "PillarA": ((-2.2, 0, -1.2), (-1.8, 3.2, -0.8)),
        "PillarB": ((1.6, 0, -2.2), (2.0, 3.2, -1.8)),
    }.items():
        cube = UsdGeom.Cube.Define(stage, f"/World/{name}")
        cube.CreateSizeAttr(1.0)
        cube.CreateDisplayColorAttr([(0.6, 0.55, 0.5)])
        xf = UsdGeom.Xformable(cube)
        xf.AddTranslateOp().Set(Gf.Vec3d(*((np.add(lo, hi)) / 2.0)))
        xf.AddScaleOp().Set(Gf.Vec3f(*np.subtract(hi, lo)))
    spots = [(-3, -3), (0, -3), (3, -3), (-3, 0), (3, 0), (-3, 3), (0, 3), (3, 3)]
    for i, (x, z) in enumerate(spots):
        lamp = UsdLux.SphereLight.Define(stage, f"/World/Lamp{i}")
        lamp.CreateNormalizeAttr(True)  # intensity / 4: 8 + 2i (usd/lights.local_intensity)
        lamp.CreateIntensityAttr(4.0 * (8.0 + 2.0 * i))
        lamp.CreateRadiusAttr(0.05)
        UsdGeom.Xformable(lamp).AddTranslateOp().Set(Gf.Vec3d(x, 3.5, z))
    (view,) = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Camera")).GetOrderedXformOps()
    view.Set(_look_at_matrix(np.array([0.0, 2.5, 4.5]), np.array([0.0, 0.0, -1.0])))
    stage.GetRootLayer().Save()
    return path


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["hybrid", "rt"])
def test_probe_traced_pixel_ray_cost(tmp_path, mode):
    stage = open_stage(_room_stage(tmp_path / "room.usda"))
    assert len(stage.scene.lights.local) == 8
    figures = {}
    for exact in (False, True):
        options = RenderOptions(mode=mode, heuristic="all", width=128, height=96, budget_ms=None)
        renderer = FrameRenderer(stage, options)
        try:
            renderer.tracer.exact_hit_lighting = exact
            out = renderer.render(1.0)
        finally:
            renderer.close()
        assert renderer.gl is not None  # rt too renders the shadow maps of 9 lights
        traced = int(out.traced_mask.sum())
        assert traced > 4000  # the mirror fills most of the frame
        figures[exact] = out.stats.rays / traced
    # Counted, not timed: the rule against one shadow ray per light at every hit.
    assert figures[False] <= MAX_RAYS_PER_TRACED_PIXEL
    assert figures[True] > 3 * figures[False]
