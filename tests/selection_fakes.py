"""Fake frames for the selection tests: a Scene of Elements only (no geometry), camera
frames looking down world -Z, frame views with pixel counts, and one frame through the
renderer's round loop with a fake tracer. No rendering."""

from __future__ import annotations

import math

import numpy as np

from phrt_usd.model.frame import Budget, FrameView, TraceRecord
from phrt_usd.model.scene import (
    CameraFrame,
    DistantLight,
    Element,
    Geometry,
    Lights,
    MaterialTable,
    Scene,
)
from phrt_usd.model.trace_density import traced_fraction
from phrt_usd.select.policies import make_policy
from phrt_usd.select.rounds import TracedRound, run_rounds

W, H = 320, 240
TAN_X = 0.36  # focal 50, aperture 36 → tan(hfov / 2)


def camera(eye=(0.0, 0.0, 0.0)) -> CameraFrame:
    """A camera at ``eye`` looking down world -Z (camera space = world space, shifted)."""
    m = np.eye(4)
    m[:3, 3] = eye
    return CameraFrame(m, focal_length=50.0, horizontal_aperture=36.0, near=0.1, far=1e4)


def element(center, K=1.0, half=0.5, reflector=True, path=None) -> Element:
    c = np.asarray(center, dtype=np.float64)
    return Element(
        path=path or f"/R{tuple(center)}",
        is_reflector=reflector,
        priority=K if reflector else 0.0,
        reflectivity=1.0 if reflector else 0.0,
        bounds_min=c - half,
        bounds_max=c + half,
    )


def scene(elements, lights=0) -> Scene:
    empty3 = np.zeros((0, 3))
    geometry = Geometry(
        vertices=empty3,
        triangles=np.zeros((0, 3), dtype=np.int64),
        tri_element=np.zeros(0, dtype=np.int32),
        tri_material=np.zeros(0, dtype=np.int32),
        corner_normals=np.zeros((0, 3, 3), dtype=np.float32),
        corner_albedo=np.zeros((0, 3, 3), dtype=np.float32),
    )
    zeros = np.zeros(0, dtype=np.float32)
    materials = MaterialTable(
        diffuse=np.zeros((0, 3), np.float32), metallic=zeros, roughness=zeros,
        opacity=zeros, ior=zeros, emissive=np.zeros((0, 3), np.float32),
    )  # fmt: skip
    light_list = Lights(
        distant=[DistantLight(np.array([0.0, 1.0, 0.0]), np.ones(3)) for _ in range(lights)]
    )
    return Scene(elements, geometry, materials, light_list, origin=np.zeros(3))


def view(pixels, cam=None, time=0.0, trace_density="full") -> FrameView:
    pixels = np.asarray(pixels, dtype=np.int64)
    return FrameView(time, cam or camera(), W, H, pixels, trace_density=trace_density)


def traced_rays(policy, ids, pixels, rays_per_pixel) -> list[int]:
    """A fake tracer's rays for a round's ``ids``: pixels times rays per pixel (a number
    or one per element), times the share a density the policy chose traces (HEU1's
    density steps; at the view's own density a record counts every covered pixel)."""
    view_density = policy._require_frame().view.trace_density
    rpp = np.broadcast_to(np.asarray(rays_per_pixel, dtype=np.float64), (len(pixels),))
    out = []
    for e, d in zip(ids, policy.round_densities(ids), strict=True):
        share = traced_fraction(pixels[e], d) if d != view_density else 1.0
        out.append(int(math.ceil(pixels[e] * rpp[e] * share)))
    return out


def run_frame(policy, sc, fv, budget_rays=None, rays_per_pixel=1.0, hits=None, bounces=None):
    """One frame through the renderer's round loop (``run_rounds``) with a fake tracer.
    Returns (metrics, rounds) where rounds is the list of id lists each round traced."""
    hits = hits or {}
    bounces = bounces or {}
    rounds = []
    px = fv.pixel_counts

    def trace(ids, densities):
        rounds.append(ids)
        records = [
            TraceRecord(e, int(px[e]), rays, dict(hits.get(e, {})), bounces.get(e, 0), 0.0)
            for e, rays in zip(ids, traced_rays(policy, ids, px, rays_per_pixel), strict=True)
        ]
        return TracedRound(records, sum(r.rays for r in records), 1.0)

    visible = [int(e) for e in np.flatnonzero(px > 0)]
    out = run_rounds(policy, fv, sc, visible, Budget(rays=budget_rays), trace)
    return out.metrics, rounds


def transitions(selections: list[set[int]], ids) -> int:
    return sum(
        (e in a) != (e in b) for a, b in zip(selections, selections[1:], strict=False) for e in ids
    )


def policy_of(name, weight=0.001):
    return make_policy(name, selection_weight=weight, bounce_limit=5)

