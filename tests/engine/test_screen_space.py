"""Screen-space reflections before Embree (``engine/trace/screen_space.py``, its kernel
``screen_space_kernels.march``): resolved pixels equal the traced ones, everything the
G-buffer cannot decide is traced as without the step, and the merged result counts
every pixel and only the rays cast.

Scenes are built without USD (``scenes.parts_scene``) and seen through ``rt`` primary
rays (``Tracer.primary_gbuffer``), so the G-buffer and the rays share one geometry."""

from __future__ import annotations

import numpy as np
import pytest
from scenes import box_between, look_at, parts_scene, quad

from phrt_usd.engine.trace import screen_space
from phrt_usd.engine.trace import screen_space_kernels as ssk
from phrt_usd.engine.trace.screen_space import ScreenFrame
from phrt_usd.engine.trace.tracer import Tracer
from phrt_usd.model import pixel_kinds as pk
from phrt_usd.model import surface
from phrt_usd.model.frame import FrameCamera
from phrt_usd.model.scene import DistantLight, Lights, LocalLight

W, H = 160, 120
#: Marches long enough to cross the whole image (its diagonal is 200 pixels): these tests
#: check the rule, not the bound (``screen_space.MAX_STEPS``, tested on its own).
STEPS = 256
#: A resolved pixel's radiance against the traced one's: the same triangle, surface rule
#: and lighting (same per-pixel light draws), only the barycentrics differ (float64
#: Moller-Trumbore cast to float32 against Embree's float32): rounding, far below 1e-4.
RADIANCE_ATOL = 1e-4
#: Its hit distance (metres, scenes of a few metres): float32 rounding of the two hits.
DISTANCE_ATOL = 1e-4

BOX = dict(mesh=box_between((-0.5, 0.0, -1.0), (0.5, 1.0, 0.0)), albedo=(0.8, 0.3, 0.2))


def _lights() -> Lights:
    d = np.array([0.3, 1.0, 0.4])
    return Lights(
        distant=[DistantLight(d / np.linalg.norm(d), np.full(3, 2.0))],
        local=[LocalLight(np.array([1.5, 2.5, 1.0]), np.full(3, 4.0))],
    )


def _setup(parts, eye=(0.0, 1.5, 4.0), target=(0.0, 0.3, -0.5), near=0.01, size=(W, H)):
    tracer = Tracer(parts_scene(parts, _lights()))
    camera = look_at(eye, target, near=near)
    gb = tracer.primary_gbuffer(camera, *size)
    return tracer, gb, ScreenFrame(FrameCamera.of(0.0, camera, *size), STEPS)


def _both(tracer, gb, screen, sources=(0,), limit=3, density="full"):
    """(traced without the step, with it, traced rows in the order of ``with``)."""
    ref = tracer.trace_reflections(gb, list(sources), limit, density)
    res = tracer.trace_reflections(gb, list(sources), limit, density, screen=screen)
    row = {p: i for i, p in enumerate(ref.pixel_index.tolist())}
    order = np.array([row[p] for p in res.pixel_index.tolist()], np.int64)
    return ref, res, order


def _first_hits(tracer, gb, sources=(0,)):
    """Per first ray of ``sources``' pixels: (pixels, element first hit, -1: none), by
    Embree, as the bounce loop casts it."""
    first = tracer._source_pixels(gb, list(sources), None, reflect=True, surface=False)
    hits, _ = tracer.surfaces.intersect(first["org"], first["dir"])
    element = np.full(len(first["pix"]), -1, np.int64)
    element[hits.ray] = tracer.bvh.tri_element[hits.tri]
    return first["pix"], element


def _outcomes(tracer, gb, screen, sources=(0,)):
    """Each first ray's march outcome (``screen_space_kernels`` codes) and its pixel."""
    first = tracer._source_pixels(gb, list(sources), None, reflect=True, surface=False)
    tracer._paths.lighting.prepare(None, 0.0, gb.shape[1], False)
    hits = screen_space.resolve(
        screen, gb.depth, first["pix"], first["org"], first["dir"], tracer._images(gb),
        tracer.bvh.boundary.origin, tracer.bvh.table.frame, tracer.surfaces,
        tracer._paths.lighting, tracer._relative_lights(), tracer._split,
    )  # fmt: skip
    return first["pix"], hits.outcome


def _assert_resolved_equal_traced(ref, res, order):
    ss = res.kinds == pk.SCREEN_SPACE
    np.testing.assert_allclose(res.radiance[ss], ref.radiance[order][ss], atol=RADIANCE_ATOL)
    np.testing.assert_allclose(
        res.hit_distance[ss], ref.hit_distance[order][ss], atol=DISTANCE_ATOL
    )
    # The traced pixels are traced as without the step (the same rays, same draws).
    tr = ~ss
    np.testing.assert_allclose(res.radiance[tr], ref.radiance[order][tr], atol=1e-6)
    assert np.all(np.isfinite(res.radiance))


def test_mirror_floor_under_box_resolves_box_pixels_as_traced():
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX])
    ref, res, order = _both(tracer, gb, screen)
    _assert_resolved_equal_traced(ref, res, order)
    pix, element = _first_hits(tracer, gb)
    on_box = set(pix[element == 1].tolist())
    ss = set(res.pixel_index[res.kinds == pk.SCREEN_SPACE].tolist())
    assert ss <= on_box  # only box hits are resolved
    # The box's reflected faces are the ones the camera sees: all but the pixels where
    # the crossing lands on a silhouette (a pixel or so of the reflection's outline).
    assert len(ss) >= 0.95 * len(on_box) and len(on_box) > 500
    # A ray leaving the screen (the sky) is traced.
    sky = set(pix[element < 0].tolist())
    traced = set(res.pixel_index[res.kinds == pk.TRACED].tolist())
    assert sky and sky <= traced


def test_merged_result_counts_every_pixel_and_only_rays_cast():
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX])
    tracer.reset_counters()
    res = tracer.trace_reflections(gb, [0], 3, screen=screen)
    counters = dict(tracer.rays_cast)
    (record,) = res.records
    n_ss = int(np.count_nonzero(res.kinds == pk.SCREEN_SPACE))
    n_traced = int(np.count_nonzero(res.kinds == pk.TRACED))
    assert record.pixels == len(res.pixel_index) == int((gb.element_id == 0).sum())
    assert n_ss + n_traced == record.pixels and n_ss > 0
    assert record.rays == res.rays == sum(counters.values())
    # First rays are cast only for traced pixels (no reflector here: one bounce each).
    assert counters["reflection"] == n_traced
    # Two lights, both unshadowed over the box's lit faces: every resolved hit's
    # lighting casts at most two shadow rays (none for the faces turned away).
    assert counters["shadow"] <= 2 * (n_ss + n_traced)
    assert record.hits == {} and record.mean_reflector_bounces == 0.0
    assert len(np.unique(res.pixel_index)) == len(res.pixel_index)


def test_ray_passing_behind_a_surface_is_traced():
    # A box floating 40 cm over the mirror: the mirror shows its underside, which the
    # camera (above) does not see; rays to it pass behind the box's front face.
    floating = dict(mesh=box_between((-0.5, 0.4, -1.0), (0.5, 1.2, 0.0)), albedo=(0.8, 0.3, 0.2))
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), floating])
    ref, res, order = _both(tracer, gb, screen)
    _assert_resolved_equal_traced(ref, res, order)
    # Rays whose first hit (Embree's) the camera does not see: the G-buffer's depth at
    # the hit's pixel is nearer than the hit by more than 5 cm (the box is 1 m deep).
    first = tracer._source_pixels(gb, [0], None, reflect=True, surface=False)
    hits, _ = tracer.surfaces.intersect(first["org"], first["dir"])
    frame = np.take(tracer.bvh.table.frame, hits.tri, axis=0)
    world = surface.positions(frame, hits.u, hits.v) + tracer.bvh.boundary.origin
    clip = np.c_[world, np.ones(len(world))] @ (screen.camera.projection
                                                @ screen.camera.camera_from_world).T
    col = ((clip[:, 0] / clip[:, 3] + 1) * W / 2).astype(int)
    row = ((1 - clip[:, 1] / clip[:, 3]) * H / 2).astype(int)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    hidden = inside.copy()
    hidden[inside] = gb.depth[row[inside], col[inside]] < clip[inside, 3] - 0.05
    behind = set(first["pix"][hits.ray[hidden]].tolist())
    assert len(behind) > 20  # the scene makes such rays
    traced = set(res.pixel_index[res.kinds == pk.TRACED].tolist())
    assert behind <= traced


def test_ray_hitting_another_reflector_is_traced():
    wall = dict(mesh=quad(3.0, (0.0, 1.5, -2.5), "z"), F=0.8)
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX, wall])
    ref, res, order = _both(tracer, gb, screen)
    _assert_resolved_equal_traced(ref, res, order)
    pix, element = _first_hits(tracer, gb)
    on_wall = set(pix[element == 2].tolist())
    assert len(on_wall) > 100
    traced = set(res.pixel_index[res.kinds == pk.TRACED].tolist())
    assert on_wall <= traced
    _, outcome = _outcomes(tracer, gb, screen)
    assert np.count_nonzero(outcome == ssk.REFLECTOR) > 100
    # The recursion still reaches the wall: its hits are counted as without the step.
    assert res.records[0].hits == ref.records[0].hits


def test_transmissive_hit_is_traced():
    glass = dict(mesh=box_between((-0.5, 0.0, -1.0), (0.5, 1.0, 0.0)), opacity=0.5)
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), glass])
    ref, res, order = _both(tracer, gb, screen)
    _assert_resolved_equal_traced(ref, res, order)
    _, outcome = _outcomes(tracer, gb, screen)
    assert np.count_nonzero(outcome == ssk.TRANSMISSIVE) > 100
    assert not np.any(res.kinds == pk.SCREEN_SPACE)


@pytest.mark.parametrize(
    "eye, target, near",
    [
        ((0.0, 0.04, 4.0), (0.0, 0.04, -3.0), 0.01),  # grazing: eye 4 cm over the mirror
        ((0.0, 3.0, 0.5), (0.0, 0.0, 0.49), 0.01),  # straight down: rays towards the camera
        ((0.0, 1.5, 4.0), (0.0, 0.3, -0.5), 3.5),  # near plane cutting the box's front
    ],
    ids=["grazing", "towards-camera", "near-plane"],
)
def test_extreme_views_stay_exact_and_finite(eye, target, near):
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX], eye, target, near)
    ref, res, order = _both(tracer, gb, screen)
    _assert_resolved_equal_traced(ref, res, order)
    assert np.all(np.isfinite(res.hit_distance[res.kinds == pk.SCREEN_SPACE]))
    assert len(res.pixel_index) == len(ref.pixel_index)


def test_rays_towards_the_camera_leave_through_the_near_plane():
    # The mirror alone under a camera looking straight down: every ray rises towards it.
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0)], (0.0, 3.0, 0.5),
                                (0.0, 0.0, 0.49))  # fmt: skip
    _, outcome = _outcomes(tracer, gb, screen)
    assert len(outcome) > 1000 and np.all(outcome == ssk.OFF_SCREEN)


def test_reduced_density_fills_from_screen_space_samples():
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX])
    res = tracer.trace_reflections(gb, [0], 3, "quarter", screen=screen)
    counts = pk.kind_counts(res.kinds)
    assert counts["screen-space"] > 0 and counts["traced"] > 0 and counts["filled"] > 0
    assert res.records[0].pixels == len(res.pixel_index) == int((gb.element_id == 0).sum())
    # A quarter of the pixels start rays or marches; the others are filled.
    started = counts["screen-space"] + counts["traced"]
    assert abs(started / len(res.pixel_index) - 0.25) < 0.02
    assert np.all(np.isfinite(res.radiance)) and np.all(~np.isnan(res.hit_distance))


def test_no_bounce_or_no_pixels_skip_the_step():
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX])
    env = tracer.trace_reflections(gb, [0], 0, screen=screen)
    assert env.kinds is None and env.rays == 0
    none = tracer.trace_reflections(gb, [], 3, screen=screen)
    assert len(none.pixel_index) == 0 and none.rays == 0


def test_march_stops_at_its_bound():
    tracer, gb, screen = _setup([dict(mesh=quad(8.0), F=1.0), BOX])
    short = ScreenFrame(screen.camera, 8)
    pix, outcome = _outcomes(tracer, gb, short)
    _, full = _outcomes(tracer, gb, screen)
    assert np.count_nonzero(outcome == ssk.STEPS) > 1000
    # A bound only turns resolved or other outcomes into STEPS, never resolves more.
    assert np.all((outcome == full) | (outcome == ssk.STEPS))
    ref, res, order = _both(tracer, gb, short)
    _assert_resolved_equal_traced(ref, res, order)
