"""Rect and Disk lights as areas, compiled: the area factor every (point, area light)
pair is shaded with, and the sample rays that answer its visible share where rays decide
it (``shadow_rays.ShadowRays``; docs/usd-support.md "Lights").

Wherever a pair is shaded (``shade_kernel``, the GPU light pass), it is lit as a point
of the light's intensity I (its luminance L times its area A) at its centre, d_c away,
``I / d_c² × π f(l_c) n·l_c``, times the pair's visibility. For an area light (UsdLux:
a rect or a disk in its local XY plane, a Lambertian emitter along its -Z) that point
term is multiplied by the *area factor* (``_factor``)

    F = ∫ cos θ_e cos θ_p / d² dA  /  (A cos θ_p,c / d_c²)

so the pair's light is ``L ∫ cos θ_e cos θ_p / d² dA × (visibility) × π f(l_c)``: the
irradiance of the whole surface, exact (Lambert's formula for a polygon over its
outline clipped to the point's horizon, ``_unshadowed``; a disk as a regular polygon of
its area; 0 behind the light), θ_e at a point y of the light between its axis and the
direction to the point, θ_p at the point between its shading normal and the direction
to y. The BRDF is the centre direction's (a Lambert surface is exact; a highlight keeps
the point's shape). One formula, everywhere: the compiled shading multiplies it into
the pairs' visibility (``area_columns``, ``area_pairs``, from ``shading.shade_local``),
the traced hits' ray weights carry it (``area_rays``), the GPU light pass has its GLSL
copy (``shaders/cube_lookup.frag``'s ``area_factor``, tied to ``_factor`` by
tests/engine/test_area_light_shading.py).

The visibility is whoever decides the pair's: a shadow map's test from the light's
centre (the raster, and the pairs the maps decide in hybrid and at the hits: a shadow
with the centre's hard edge, under the area's irradiance), or the rays' visible share
(rt's primary surface, the pairs the maps leave undecided, the hits lit by rays): a few
rays (``picks``) to points y_s drawn from a lattice of N points of the surface in
proportion to their g = cos θ_e cos θ_p / d² (systematic draws), each ray's visibility
V_s weighing alike, the estimate the lattice's Σ g V / Σ g in expectation. A point that
sees the whole light is exact and without noise; a penumbra is a dither between pixels.

The points y_s: a Fibonacci lattice of N (``count``, a Fibonacci number; ``step`` the
one before it), point c at (c / N, fract(c step / N + 1 / 2N)) of the unit square: each
in a strip of its own along either axis, so an edge along an axis of the light (a
card's shadow) is resolved to 1 / N, spread evenly in 2D; the lattice shifted around
the square by a per-point offset in [0, 1)² (Cranley-Patterson), which keeps it a
lattice and makes each point uniform over the surface; a disk takes the square's points
through Shirley and Chiu's concentric map, which keeps areas.

Spaces: rel (world metres minus ``Scene.origin``), float64 positions, float32 ray
directions as Embree takes them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.engine.trace.trace_kernels import _epsilon
from phrt_usd.kernels import KERNEL_OPTIONS

_KERNEL = KERNEL_OPTIONS

#: Columns of the area table (``shadow_rays.area_table``), one row per LocalLight: its
#: shape (0: a point, RECT, DISK), centre rel (3), u and v (3 each: the rect's half
#: width and height along its local X and Y, or the disk's radius along them) and the
#: unit axis it emits along (3, its -Z).
AREA_KIND, AREA_CENTRE, AREA_U, AREA_V, AREA_AXIS = 0, 1, 4, 7, 10
AREA_COLUMNS = 13
RECT, DISK = 1.0, 2.0


#: A disk's outline in the exact irradiance (``_unshadowed``): a regular polygon of this
#: many corners, of the disk's area (its corners DISK_CORNER_SCALE radii out): within
#: 0.1 % of the disk's irradiance wherever the receiver sees it whole.
DISK_CORNERS = 24
DISK_CORNER_SCALE = math.sqrt(2.0 * math.pi / (DISK_CORNERS * math.sin(2.0 * math.pi
                                                                        / DISK_CORNERS)))
#: The largest area factor (``_factor``): a point whose normal grazes the direction to
#: the centre sees the light at an n·l near 0 that the factor divides by (their product
#: stays the irradiance); the cap keeps it finite in float32.
MAX_FACTOR = 1e30
#: The most corners a clipped outline has (a plane cuts a convex polygon's outline
#: twice, adding one corner).
_MAX_CORNERS = DISK_CORNERS + 1


@njit(**_KERNEL)
def _unshadowed(area, q, ox, oy, oz, n0, n1, n2, corners, clipped):
    """∫ cos θ_e cos θ_p / d² dA of light q's whole surface (``area``'s row) at a point
    (ox, oy, oz) of normal n, unshadowed: Lambert's formula for a polygon, ½ Σ_edges
    Θ_k n·ĝ_k (Θ_k the angle an edge subtends, ĝ_k the unit normal of the plane through
    it and the point), over the outline clipped to the point's horizon; 0 on the side
    the light does not emit to. ``corners``, ``clipped`` (_MAX_CORNERS, 3) float64
    scratch."""
    cx = area[q, AREA_CENTRE] - ox
    cy = area[q, AREA_CENTRE + 1] - oy
    cz = area[q, AREA_CENTRE + 2] - oz
    facing = cx * area[q, AREA_AXIS] + cy * area[q, AREA_AXIS + 1] + cz * area[q, AREA_AXIS + 2]
    if not facing < 0.0:
        return 0.0  # the point is behind the light (or in its plane)
    m = 4 if area[q, AREA_KIND] == RECT else DISK_CORNERS
    for c in range(m):  # the outline, in order around the centre
        if m == 4:
            a = 1.0 if c == 1 or c == 2 else -1.0
            b = 1.0 if c >= 2 else -1.0
        else:
            phi = 2.0 * math.pi * c / m
            a, b = DISK_CORNER_SCALE * math.cos(phi), DISK_CORNER_SCALE * math.sin(phi)
        corners[c, 0] = cx + a * area[q, AREA_U] + b * area[q, AREA_V]
        corners[c, 1] = cy + a * area[q, AREA_U + 1] + b * area[q, AREA_V + 1]
        corners[c, 2] = cz + a * area[q, AREA_U + 2] + b * area[q, AREA_V + 2]
    # Clip to the horizon n·x >= 0 (Sutherland-Hodgman).
    kept = 0
    for c in range(m):
        a0, a1, a2 = corners[c, 0], corners[c, 1], corners[c, 2]
        e = (c + 1) % m
        b0, b1, b2 = corners[e, 0], corners[e, 1], corners[e, 2]
        ha, hb = n0 * a0 + n1 * a1 + n2 * a2, n0 * b0 + n1 * b1 + n2 * b2
        if ha >= 0.0:
            clipped[kept, 0], clipped[kept, 1], clipped[kept, 2] = a0, a1, a2
            kept += 1
        if (ha >= 0.0) != (hb >= 0.0):
            t = ha / (ha - hb)
            clipped[kept, 0] = a0 + t * (b0 - a0)
            clipped[kept, 1] = a1 + t * (b1 - a1)
            clipped[kept, 2] = a2 + t * (b2 - a2)
            kept += 1
    total = 0.0
    for c in range(kept):
        e = (c + 1) % kept
        a0, a1, a2 = clipped[c, 0], clipped[c, 1], clipped[c, 2]
        b0, b1, b2 = clipped[e, 0], clipped[e, 1], clipped[e, 2]
        la = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        lb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        if not (la > 0.0 and lb > 0.0):
            continue
        cos = min(max((a0 * b0 + a1 * b1 + a2 * b2) / (la * lb), -1.0), 1.0)
        g0, g1, g2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        lg = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        if lg > 0.0:
            total += math.acos(cos) * (n0 * g0 + n1 * g1 + n2 * g2) / lg
    return 0.5 * abs(total)


@njit(**_KERNEL)
def _area(area, q):
    """Light q's area in m² (its intensity is its luminance times it): 4 |u x v| for a
    rect, π |u x v| for a disk (an ellipse of half axes u, v)."""
    u0, u1, u2 = area[q, AREA_U], area[q, AREA_U + 1], area[q, AREA_U + 2]
    v0, v1, v2 = area[q, AREA_V], area[q, AREA_V + 1], area[q, AREA_V + 2]
    g0, g1, g2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    size = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    return max((4.0 if area[q, AREA_KIND] == RECT else math.pi) * size, 1e-300)


@njit(**_KERNEL)
def _factor(area, q, ox, oy, oz, n0, n1, n2, l0, l1, l2, dist, corners, clipped):
    """The area factor of light q at a point (ox, oy, oz) of unit normal n (module
    docstring): its exact unshadowed irradiance (``_unshadowed``) over the point light's
    at its centre, A n·l / d² (l the unit direction to the centre, ``dist`` metres away),
    at most MAX_FACTOR; 0 behind the light, or for a point facing away from the centre
    (whose point term is 0) or a light of no area."""
    nl = n0 * l0 + n1 * l1 + n2 * l2
    if not nl > 0.0:
        return 0.0
    whole = _unshadowed(area, q, ox, oy, oz, n0, n1, n2, corners, clipped)
    return min(whole / (max(nl, 1e-12) / (dist * dist) * _area(area, q)), MAX_FACTOR)


@njit(**_KERNEL)
def area_columns(area, n_distant, positions, normals, min_distance, visibility):
    """Each area light's column of ``visibility`` (n, D + P) float32 (light order distant
    then local, ``n_distant`` distant; ``area`` (P, AREA_COLUMNS)) times the pair's area
    factor (``_factor``) in place, where it is positive: points ``positions`` (n, 3)
    float64 in the lights' space, unit ``normals`` (n, 3) float32, the distance to the
    centre clamped to ``min_distance`` as the shading's."""
    corners, clipped = np.empty((_MAX_CORNERS, 3)), np.empty((_MAX_CORNERS, 3))
    for i in range(positions.shape[0]):
        n0, n1, n2 = float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])
        ox, oy, oz = positions[i, 0], positions[i, 1], positions[i, 2]
        for q in range(area.shape[0]):
            j = n_distant + q
            if area[q, AREA_KIND] == 0.0 or not visibility[i, j] > 0.0:
                continue
            t0 = area[q, AREA_CENTRE] - ox
            t1 = area[q, AREA_CENTRE + 1] - oy
            t2 = area[q, AREA_CENTRE + 2] - oz
            d = max(math.sqrt(t0 * t0 + t1 * t1 + t2 * t2), min_distance)
            f = _factor(area, q, ox, oy, oz, n0, n1, n2, t0 / d, t1 / d, t2 / d, d, corners,
                        clipped)  # fmt: skip
            visibility[i, j] = visibility[i, j] * f


@njit(**_KERNEL)
def area_pairs(area, positions, normals, point, light, l_dir, dist, weight):
    """``weight`` (m,) float32 of m lit (point, LocalLight) pairs (``shading.LightPairs``:
    point, light (m,) int64, unit l_dir (m, 3) float32 to the centre, dist (m,) float64
    metres) times the pair's area factor (``_factor``) in place where its light is an
    area; positions (n, 3) float64, normals (n, 3) float32 unit, as ``area_columns``'."""
    corners, clipped = np.empty((_MAX_CORNERS, 3)), np.empty((_MAX_CORNERS, 3))
    for r in range(point.shape[0]):
        q, i = light[r], point[r]
        if area[q, AREA_KIND] == 0.0:
            continue
        f = _factor(area, q, positions[i, 0], positions[i, 1], positions[i, 2],
                    float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2]),
                    float(l_dir[r, 0]), float(l_dir[r, 1]), float(l_dir[r, 2]), dist[r],
                    corners, clipped)  # fmt: skip
        weight[r] = weight[r] * f


@njit(**_KERNEL)
def area_rays(rays_i, rays_v, rays_f, k, n_distant, ns, area, offsets, count, step, picks,
              floor, relative, with_factor, parent, out_v, out_f, unshadowed):  # fmt: skip
    """The sample rays of the first ``k`` shadow rays (``trace_kernels.shadow_rays``'
    out_i, out_v, out_f) whose light is an area (``area`` (P, AREA_COLUMNS) float64, rel;
    lights distant then local, ``n_distant`` distant): of the ``count`` points of the
    pair's lattice (``step``; shifted by point i's ``offsets`` (n, 3) float64 in [0, 1),
    columns 0 and 1; module docstring), ``picks`` drawn by their terms g = cos θ_e cos θ_p
    / d² (systematic: at (offsets[i, 2] + j) / picks of the terms' running sum), one ray
    each from the pair's ray origin; ``ns`` (n, 3) the points' shading normals.
    Writes each sample ray's pair (its ray's column) into ``parent`` (·,) int64, origin
    and unit direction into out_v (2, ·, 3) float32, its tfar (the epsilon short of the
    light) and its weight (the terms' sum over ``picks``) into out_f (2, ·) float32; each
    pair's area factor (``_factor``: the area's exact integral over the point light's),
    or 1 without ``with_factor`` (the caller's shading applies it), into ``unshadowed``
    (k,) float64 (-1 for a ray whose light is no area; a pair of factor 0, or of no
    lattice point it could see, gets no samples). Returns the sample ray count."""
    s = 0
    corners, clipped = np.empty((_MAX_CORNERS, 3)), np.empty((_MAX_CORNERS, 3))
    points = np.empty((count, 5))  # direction, distance, term of each lattice point
    for r in range(k):
        unshadowed[r] = -1.0
        q = rays_i[1, r] - n_distant
        if q < 0 or area[q, AREA_KIND] == 0.0:
            continue
        i = rays_i[0, r]
        n0, n1, n2 = float(ns[i, 0]), float(ns[i, 1]), float(ns[i, 2])
        d0, d1, d2 = float(rays_v[1, r, 0]), float(rays_v[1, r, 1]), float(rays_v[1, r, 2])
        length = float(rays_f[1, r])
        ox, oy, oz = float(rays_v[0, r, 0]), float(rays_v[0, r, 1]), float(rays_v[0, r, 2])
        unshadowed[r] = 1.0
        if with_factor:
            unshadowed[r] = _factor(area, q, ox, oy, oz, n0, n1, n2, d0, d1, d2, length,
                                    corners, clipped)  # fmt: skip
        if not unshadowed[r] > 0.0:
            continue
        e = _epsilon(ox, oy, oz, floor, relative)
        total = 0.0
        for c in range(count):
            # The lattice's point c, shifted around the torus (Cranley-Patterson).
            a = c / count + offsets[i, 0]
            b = ((c * step) % count) / count + 0.5 / count + offsets[i, 1]
            a = 2.0 * (a - math.floor(a)) - 1.0  # in [-1, 1)
            b = 2.0 * (b - math.floor(b)) - 1.0
            if area[q, AREA_KIND] == DISK and (a != 0.0 or b != 0.0):
                # Shirley-Chiu: the square's cells onto the disk, areas kept.
                if abs(a) > abs(b):
                    rad, phi = a, 0.25 * math.pi * b / a
                    a, b = rad * math.cos(phi), rad * math.sin(phi)
                else:
                    rad, phi = b, 0.5 * math.pi - 0.25 * math.pi * a / b
                    a, b = rad * math.cos(phi), rad * math.sin(phi)
            y0 = area[q, AREA_CENTRE] + a * area[q, AREA_U] + b * area[q, AREA_V]
            y1 = area[q, AREA_CENTRE + 1] + a * area[q, AREA_U + 1] + b * area[q, AREA_V + 1]
            y2 = area[q, AREA_CENTRE + 2] + a * area[q, AREA_U + 2] + b * area[q, AREA_V + 2]
            t0, t1, t2 = y0 - ox, y1 - oy, y2 - oz
            d = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            g = 0.0
            if d > e:
                t0, t1, t2 = t0 / d, t1 / d, t2 / d
                cos_e = -(t0 * area[q, AREA_AXIS] + t1 * area[q, AREA_AXIS + 1]
                          + t2 * area[q, AREA_AXIS + 2])  # fmt: skip
                cos_p = n0 * t0 + n1 * t1 + n2 * t2
                if cos_e > 0.0 and cos_p > 0.0:
                    g = cos_e * cos_p / (d * d)
            points[c, 0], points[c, 1], points[c, 2], points[c, 3] = t0, t1, t2, d
            points[c, 4] = g
            total += g
        if not total > 0.0:
            continue
        c, running = 0, points[0, 4]
        for j in range(picks):  # systematic draws over the terms' running sum
            target = (offsets[i, 2] + j) / picks * total
            while running <= target and c < count - 1:
                c += 1
                running += points[c, 4]
            parent[s] = r
            out_v[0, s, 0], out_v[0, s, 1], out_v[0, s, 2] = ox, oy, oz
            out_v[1, s, 0], out_v[1, s, 1] = points[c, 0], points[c, 1]
            out_v[1, s, 2] = points[c, 2]
            out_f[0, s] = points[c, 3] - e
            out_f[1, s] = total / picks
            s += 1
    return s


@njit(**_KERNEL)
def area_weights(rays_i, rays_f, occluded, unshadowed, parent, terms, sample_occluded, extra):
    """Each area pair's weight from its sample rays' answer (module docstring): the
    pair's ray weight rays_f[2, r] times its unshadowed weight (``area_rays``; -1: no
    area) times the share of its samples' terms that are free, and occluded[r] set when
    that is 0 (its own ray was not cast); ``parent`` and ``terms`` (m,) the sample rays'
    pairs and terms, ``sample_occluded`` (m,) bool Embree's answer. Adds to ``extra``
    (n,) int64 the rays each point cast beyond one a pair (its sample rays, less its
    pairs' own rays, which were not cast)."""
    k = unshadowed.shape[0]
    free, every = np.zeros(k), np.zeros(k)
    for s in range(parent.shape[0]):
        r = parent[s]
        extra[rays_i[0, r]] += 1
        every[r] += terms[s]
        if not sample_occluded[s]:
            free[r] += terms[s]
    for r in range(k):
        if unshadowed[r] >= 0.0:
            extra[rays_i[0, r]] -= 1
            w = unshadowed[r] * free[r] / every[r] if every[r] > 0.0 else 0.0
            rays_f[2, r] = rays_f[2, r] * w
            occluded[r] = not w > 0.0


def warm_up() -> None:
    """Compile (or load from phrt's kernel cache) the kernels on tiny inputs of the types
    the shadow rays and the shading pass."""
    rays_i, rays_v = np.zeros((2, 1), np.int64), np.zeros((2, 1, 3), np.float32)
    rays_f = np.zeros((3, 1), np.float32)
    ns, area = np.zeros((1, 3), np.float32), np.zeros((1, AREA_COLUMNS))
    parent, out_v = np.zeros(4, np.int64), np.zeros((2, 4, 3), np.float32)
    out_f, unshadowed = np.zeros((2, 4), np.float32), np.zeros(1)
    area_rays(rays_i, rays_v, rays_f, 1, 0, ns, area, np.zeros((1, 3)), 3, 2, 1, 1e-6, 1e-5,
              True, parent, out_v, out_f, unshadowed)  # fmt: skip
    area_weights(rays_i, rays_f, np.zeros(1, bool), unshadowed, parent, out_f[1],
                 np.zeros(4, bool), np.zeros(1, np.int64))  # fmt: skip
    positions, vis = np.zeros((1, 3)), np.ones((1, 1), np.float32)
    area_columns(area, 0, positions, ns, 1e-4, vis)
    area_pairs(area, positions, ns, np.zeros(1, np.int64), np.zeros(1, np.int64), ns,
               np.ones(1), vis[0])  # fmt: skip
