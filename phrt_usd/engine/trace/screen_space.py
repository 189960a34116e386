"""Screen-space reflections before Embree: the first reflection ray of a reflector pixel
resolved from the frame's own G-buffer where the answer is on screen and unambiguous
(docs/screen-space.md).

``Tracer.trace_reflections(..., screen=ScreenFrame(...))`` hands its first rays here
(``resolve``): each is marched through the G-buffer (``screen_space_kernels.march``:
the rule, its thickness and tolerances). A resolved ray's hit is exact — the triangle it
crosses at a pixel next to where the march found the crossing, hit in float64 — and is
lit as the bounce loop lights its hits (``HitSurfaces.geometry`` / ``colour`` and
``HitLighting.shade``: the same surface rule, shadow maps, light sampling and per-pixel
dither), so its radiance is the traced one for that hit: the local shading of a
non-reflecting, opaque surface seen along the reflected direction (emission included).
Rays that leave the screen, pass behind a surface, march too far, land ambiguously,
on a cut-out hole, or on a reflector (the recursion) or a transmissive surface are
traced by the bounce loop exactly as without this step, and ``merge`` makes one
``ReflectionResult`` of both: resolved pixels of kind ``pixel_kinds.SCREEN_SPACE``, the
records counting every pixel and only the rays cast (the resolved hits' shadow rays).

The march is bounded (``MAX_STEPS`` pixels, measured: the module constant says why);
hierarchical (min-depth mip) marching was not built: it pays for long marches, and the
bound keeps them short (docs/screen-space.md).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from phrt_usd import kernels
from phrt_usd.model import pixel_kinds, surface
from phrt_usd.model.frame import FrameCamera, ReflectionResult

#: The compiled march (``screen_space_kernels``, through ``phrt_usd.kernels``).
ssk = kernels.load("phrt_usd.engine.trace.screen_space_kernels")

#: Pixels a ray is marched at most before it is traced instead. See docs/screen-space.md
#: for the measurement (sewer frame 241, 640x480): a step costs a few nanoseconds, a
#: traced first ray (Embree, its hit's surface and bookkeeping) about a microsecond, and
#: the resolved rays' marches are mostly short while unresolved rays that march far
#: (into the sky, along a wall) end off screen anyway; past this bound the march costs
#: more than the trace it might save.
MAX_STEPS = 32


@dataclass(frozen=True)
class ScreenFrame:
    """What the screen-space step needs of a frame beyond its G-buffer.

    camera : the frame's matrices (``FrameCamera``: world-to-camera and projection at
        the G-buffer's width x height);
    max_steps : pixels a ray is marched at most (``MAX_STEPS``)."""

    camera: FrameCamera
    max_steps: int = MAX_STEPS


@dataclass
class ScreenHits:
    """What ``resolve`` made of n first rays.

    outcome : (n,) int8 ``screen_space_kernels`` codes (RESOLVED, OFF_SCREEN, ...);
    steps : (n,) int32 pixels marched;
    rows : (k,) int64 the resolved rays (indices into the n), radiance (k, 3) float32
        their reflected radiance, distance (k,) float32 metres to their hit, shadow_rays
        (k,) int64 shadow rays their lighting cast (shadow_cast their sum)."""

    outcome: np.ndarray
    steps: np.ndarray
    rows: np.ndarray
    radiance: np.ndarray
    distance: np.ndarray
    shadow_rays: np.ndarray
    shadow_cast: int

    @property
    def unresolved(self) -> np.ndarray:
        """(n - k,) int64 the rays left for the bounce loop."""
        return np.flatnonzero(self.outcome != ssk.RESOLVED)


def clip_from_rel(camera: FrameCamera, origin: np.ndarray) -> np.ndarray:
    """(4, 4) float64: rel points (world minus ``origin``) to the frame's clip space."""
    shift = np.eye(4)
    shift[:3, 3] = np.asarray(origin, np.float64)
    return camera.clip_from_world @ shift


def resolve(screen: ScreenFrame, depth, pix, origins, dirs, images, origin, frame, surfaces,
            lighting, lights, split) -> ScreenHits:  # fmt: skip
    """The first rays (pix (n,) their pixels, origins (n, 3) float32 rel offset origins,
    dirs (n, 3) float32 unit) marched through a G-buffer of view depths ``depth`` (H, W)
    whose flat ``images`` are the tracer's (triangle, world position, normal, view direction);
    ``origin`` Scene.origin; ``frame`` the BVH's ``TriangleTable.frame``; ``surfaces``
    the tracer's ``HitSurfaces``; the resolved hits lit by ``lighting`` (``HitLighting``,
    prepared for this frame) with rel ``lights``; ``split`` the tracer's ``_split``."""
    height, width = depth.shape
    n = len(pix)
    tri_img, pos_img, _, view_img = images
    out = (
        np.empty(n, np.int64), np.empty(n, np.float32), np.empty(n, np.float32),
        np.empty(n, np.float32), np.empty(n, np.int8), np.empty(n, np.int32),
    )  # fmt: skip
    split(
        ssk.march, n, np.ascontiguousarray(origins, np.float32),
        np.ascontiguousarray(dirs, np.float32), np.asarray(pix, np.int64),
        clip_from_rel(screen.camera, origin), width, height, tri_img, pos_img, view_img,
        np.ascontiguousarray(depth, np.float32).reshape(-1), np.asarray(origin, np.float64),
        frame, surfaces.tri_table, bool(surfaces.transmission), int(screen.max_steps), out=out,
    )  # fmt: skip
    tri, u, v, distance, outcome, steps = out
    rows = np.flatnonzero(outcome == ssk.RESOLVED)
    if surfaces.cutouts.any and len(rows):  # a hole is no hit: the bounce loop re-casts
        holes = surfaces.cutouts.holes(tri[rows], surface.weights_from_uv(u[rows], v[rows]))
        outcome[rows[holes]] = ssk.HOLE
        rows = rows[~holes]
    t, hu, hv = tri[rows], u[rows], v[rows]
    d_in = np.ascontiguousarray(dirs[rows], np.float32)
    rel, ng, ns = surfaces.geometry(t, hu, hv, d_in)
    if len(rows):
        radiance, shadow_rays, cast = lighting.shade(
            t, hu, hv, rel, ng, ns, d_in, lights, np.take(pix, rows)
        )
    else:
        radiance, shadow_rays, cast = np.zeros((0, 3), np.float32), np.zeros(0, np.int64), 0
    return ScreenHits(
        outcome, steps, rows, np.asarray(radiance, np.float32), distance[rows],
        np.asarray(shadow_rays, np.int64), int(cast),
    )  # fmt: skip


def merge(traced: ReflectionResult, traced_src: np.ndarray, hits: ScreenHits, pix, src,
          sources, start: float) -> tuple[ReflectionResult, np.ndarray]:  # fmt: skip
    """One result of the bounce loop's ``traced`` (its pixels' sources ``traced_src``)
    and the screen-space ``hits`` of the first rays pix, src (n,): traced pixels first,
    then the resolved ones (kind SCREEN_SPACE); per source the records count every pixel,
    the rays cast (the resolved hits' shadow rays added), the reflector chains averaged
    over every pixel (0 for a resolved one), the seconds since ``start`` shared by rays.
    Returns the result and its pixels' sources."""
    n_src = len(sources)
    ss_src = np.asarray(src, np.int64)[hits.rows]
    ss_pixels = np.bincount(ss_src, minlength=n_src).tolist()
    ss_rays = np.bincount(ss_src, weights=hits.shadow_rays, minlength=n_src)
    ss_rays = np.rint(ss_rays).astype(np.int64).tolist()
    rays = traced.rays + hits.shadow_cast
    seconds = time.perf_counter() - start
    records = []
    for record, extra, extra_rays in zip(traced.records, ss_pixels, ss_rays, strict=True):
        pixels = record.pixels + extra
        record_rays = record.rays + extra_rays
        records.append(dataclasses.replace(
            record, pixels=pixels, rays=record_rays,
            mean_reflector_bounces=record.mean_reflector_bounces * record.pixels / max(pixels, 1),
            seconds=seconds * record_rays / rays if rays else 0.0,
        ))  # fmt: skip
    n_traced = len(traced.pixel_index)
    kinds = np.full(n_traced + len(hits.rows), pixel_kinds.SCREEN_SPACE, np.uint8)
    kinds[:n_traced] = pixel_kinds.TRACED if traced.kinds is None else traced.kinds
    hit_distance = None
    if traced.hit_distance is not None:
        hit_distance = np.concatenate([traced.hit_distance, hits.distance]).astype(np.float32)
    result = ReflectionResult(
        pixel_index=np.concatenate([traced.pixel_index, np.asarray(pix, np.int64)[hits.rows]]),
        radiance=np.concatenate([traced.radiance, hits.radiance]).astype(np.float32),
        records=records,
        rays=rays,
        seconds=seconds,
        kinds=kinds,
        hit_distance=hit_distance,
    )
    return result, np.concatenate([np.asarray(traced_src, np.int64), ss_src])

