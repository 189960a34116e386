"""The screen-space step of reflections compiled: each first reflection ray marched
through the frame's own G-buffer (``screen_space``, docs/screen-space.md).

``march`` follows one ray per row over the pixels its projection crosses, one pixel a
step along the major axis (a DDA in screen space, perspective-correct in the ray's
parameter), and either resolves it — the triangle it hits, its barycentrics and the
distance — or says why not (the ``OUTCOME_*`` codes), for the bounce loop to trace it.

The rule, per step (the sample X at the step's end, the step's start X0):

- X lies on the camera's side of the plane of the triangle the pixel shows: the ray is
  in front of what the frame saw there, nothing there can block it; go on.
- Else, if X0 was behind that plane too, by more than one pixel footprint (the
  thickness, along the plane's normal): the ray passed behind a surface the frame
  shows, what lies behind it is unknown (``BEHIND``).
- Else the ray crossed the surface within this step: the hit is looked for exactly,
  the ray against the triangles of the pixel and its eight neighbours (Moller-Trumbore
  in float64 on ``TriangleTable.frame``); the nearest one hit is the ray's hit if the
  hit pixel is covered, its G-buffer position lies on the ray within
  ``POSITION_TOLERANCE_PIXELS`` footprints (grown as the surface turns away from the
  view), the triangle faces the ray from the camera's side, and it is neither a
  reflector (the recursion: ``REFLECTOR``) nor transmissive (``TRANSMISSIVE``); no
  triangle hit there is ``AMBIGUOUS``.

A ray that reaches the view volume's edge (a screen side, the near plane: a ray towards
the camera, the far plane) without a crossing is ``OFF_SCREEN``; one still marching after
``max_steps`` pixels is ``STEPS``. Spaces: positions rel (world minus ``Scene.origin``),
float64; the camera matrices map rel points (the caller folds the origin in).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.engine.trace.bounce_layout import TRI_ALPHA, TRI_REFLECTOR
from phrt_usd.kernels import KERNEL_OPTIONS

_KERNEL = KERNEL_OPTIONS
_HELPER = {**_KERNEL, "inline": "always"}

#: What ``march`` made of a ray (``out_outcome``).
RESOLVED = 0
OFF_SCREEN = 1
BEHIND = 2
STEPS = 3
AMBIGUOUS = 4
REFLECTOR = 5
TRANSMISSIVE = 6
#: Set by the caller (``screen_space``), not the kernel: the hit is on a cut-out hole.
HOLE = 7
#: The crossing's triangle is hit from the side the camera does not see, or along it.
FAR_SIDE = 8
#: The crossing pixel's G-buffer position is off the ray (beyond the footprint rule).
OFF_RAY = 9

#: The hit pixel's G-buffer position may lie this many pixel footprints from the ray
#: (divided by the cosine between the pixel's view ray and its normal, floored at
#: ``COS_FLOOR``): the hit is in the 3x3 neighbourhood of the pixel, so its surface point
#: is at most 1.5 pixels from the pixel centre's on screen; half a pixel more for the
#: sample's position inside the crossing pixel.
POSITION_TOLERANCE_PIXELS = 2.0
#: The floor of that cosine: a surface seen at more than ~87° is 20 footprints a pixel.
COS_FLOOR = 0.05
#: A ray behind a pixel's plane by more than this many footprints (along the plane's
#: normal) that hits none of the neighbourhood's triangles passed behind the surface
#: (``BEHIND``); within it, it grazes the surface without a hit there (``AMBIGUOUS``).
#: Both are traced: the split only says which (a march that went on past a grazing miss
#: lost hidden occluders on the sewer, measured in docs/screen-space.md).
THICKNESS_PIXELS = 1.0
#: Barycentric slack of the exact test (a hit on a shared edge belongs to either
#: triangle; float64 rounding of the test stays far below it).
BARY_EPS = 1e-7
#: Below this |d . n| the ray runs along the triangle's plane: not resolved.
MIN_FACING = 1e-6


@njit(**_HELPER)
def _clip_range(c0, c1):
    """The ray's parameter range [0, t1] inside the view volume, from its clip-space
    start c0 (4,) and direction c1 (4,) (clip(t) = c0 + t c1): -w <= x, y, z <= w.
    Returns (t_lo, t_hi); empty when t_lo >= t_hi."""
    t_lo, t_hi = 0.0, 1e30
    for axis in range(3):
        for sign in (-1.0, 1.0):
            # w + sign * x >= 0 (x the axis' coordinate)
            a0 = c0[3] + sign * c0[axis]
            a1 = c1[3] + sign * c1[axis]
            if a1 == 0.0:
                if a0 < 0.0:
                    return 1.0, 0.0
            elif a1 > 0.0:
                t_lo = max(t_lo, -a0 / a1)
            else:
                t_hi = min(t_hi, -a0 / a1)
    return t_lo, t_hi


@njit(**_HELPER)
def _plane_side(frame, t, x, y, z):
    """Signed distance of rel (x, y, z) to triangle t's plane (its unit normal's side)."""
    return (
        (x - frame[t, 0, 0]) * frame[t, 3, 0]
        + (y - frame[t, 0, 1]) * frame[t, 3, 1]
        + (z - frame[t, 0, 2]) * frame[t, 3, 2]
    )


@njit(**_HELPER)
def _triangle_hit(frame, t, ox, oy, oz, dx, dy, dz):
    """Moller-Trumbore of the ray (o, d) against triangle t (v0, e1, e2 of ``frame``):
    (distance, u, v), distance inf when it misses (outside by more than BARY_EPS, or
    at t <= 0)."""
    e1x, e1y, e1z = frame[t, 1, 0], frame[t, 1, 1], frame[t, 1, 2]
    e2x, e2y, e2z = frame[t, 2, 0], frame[t, 2, 1], frame[t, 2, 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.inf, 0.0, 0.0
    inv = 1.0 / det
    tx, ty, tz = ox - frame[t, 0, 0], oy - frame[t, 0, 1], oz - frame[t, 0, 2]
    u = (tx * px + ty * py + tz * pz) * inv
    if u < -BARY_EPS or u > 1.0 + BARY_EPS:
        return np.inf, 0.0, 0.0
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < -BARY_EPS or u + v > 1.0 + BARY_EPS:
        return np.inf, 0.0, 0.0
    dist = (e2x * qx + e2y * qy + e2z * qz) * inv
    if not (dist > 0.0):
        return np.inf, 0.0, 0.0
    return dist, u, v


@njit(**_KERNEL)
def march(
    origins, dirs, start_pix, clip_from_rel, width, height, tri_img, pos_img, view_img,
    depth_img, origin, frame, tri_table, split, max_steps, lo, hi, out_tri, out_u, out_v, out_t,
    out_outcome, out_steps,
):  # fmt: skip
    """Rays lo..hi through the G-buffer (see the module). origins (n, 3) float32 rel
    offset origins and dirs (n, 3) float32 unit directions of the first rays,
    start_pix (n,) int64 the pixel each starts from; clip_from_rel (4, 4) float64 the
    frame's projection times its camera_from_world with Scene.origin folded in; the
    G-buffer flat over width * height: tri_img int32 triangle (-1: background), pos_img
    (·, 3) float64 world position, view_img (·, 3) float32 unit view direction, depth_img
    (·,) float32 view depth; origin
    (3,) ``Scene.origin``; frame
    ``TriangleTable.frame``, tri_table the bounce loop's (``bounce_layout.TRI_*``);
    split: the stage has transmissive materials; max_steps: pixels marched at most.

    Per ray: out_tri (n,) int64 the triangle hit (-1 unless resolved), out_u, out_v (n,)
    float32 its barycentrics, out_t (n,) float32 metres from the origin, out_outcome
    (n,) int8 (``RESOLVED`` ...), out_steps (n,) int32 pixels marched."""
    half_w, half_h = 0.5 * width, 0.5 * height
    # A pixel's footprint at clip w: the image height at distance w over ``height``.
    foot_per_w = 2.0 / (height * abs(clip_from_rel[1, 1]))
    c0 = np.empty(4)
    c1 = np.empty(4)
    for r in range(lo, hi):
        out_tri[r] = -1
        out_u[r] = 0.0
        out_v[r] = 0.0
        out_t[r] = np.inf
        out_steps[r] = 0
        ox, oy, oz = float(origins[r, 0]), float(origins[r, 1]), float(origins[r, 2])
        dx, dy, dz = float(dirs[r, 0]), float(dirs[r, 1]), float(dirs[r, 2])
        for i in range(4):
            c0[i] = (clip_from_rel[i, 0] * ox + clip_from_rel[i, 1] * oy
                     + clip_from_rel[i, 2] * oz + clip_from_rel[i, 3])  # fmt: skip
            c1[i] = clip_from_rel[i, 0] * dx + clip_from_rel[i, 1] * dy + clip_from_rel[i, 2] * dz
        t_lo, t_hi = _clip_range(c0, c1)
        if not (t_lo < t_hi) or t_lo > 0.0:  # the origin outside the view volume
            out_outcome[r] = OFF_SCREEN
            continue
        w0 = c0[3]
        w1 = c0[3] + t_hi * c1[3]
        sx0 = (c0[0] / w0 + 1.0) * half_w
        sy0 = (1.0 - c0[1] / w0) * half_h
        sx1 = ((c0[0] + t_hi * c1[0]) / w1 + 1.0) * half_w
        sy1 = (1.0 - (c0[1] + t_hi * c1[1]) / w1) * half_h
        n_steps = int(math.ceil(max(abs(sx1 - sx0), abs(sy1 - sy0))))
        start = start_pix[r]
        outcome = OFF_SCREEN
        for i in range(1, n_steps + 1):
            if i > max_steps:
                outcome = STEPS
                break
            s = i / n_steps
            # Perspective-correct: the ray's parameter at screen fraction s.
            t = t_hi * s * w0 / ((1.0 - s) * w1 + s * w0)
            col = min(max(int(sx0 + s * (sx1 - sx0)), 0), width - 1)
            row = min(max(int(sy0 + s * (sy1 - sy0)), 0), height - 1)
            p = row * width + col
            x, y, z = ox + t * dx, oy + t * dy, oz + t * dz
            if p == start:
                continue
            out_steps[r] = i
            tp = np.int64(tri_img[p])
            if tp < 0:  # background: nothing the frame saw there
                continue
            # The camera's side of the pixel's plane: against its view direction.
            cam = -(view_img[p, 0] * frame[tp, 3, 0] + view_img[p, 1] * frame[tp, 3, 1]
                    + view_img[p, 2] * frame[tp, 3, 2])  # fmt: skip
            sign = 1.0 if cam >= 0.0 else -1.0
            h = sign * _plane_side(frame, tp, x, y, z)
            if h >= 0.0:  # in front of what the pixel shows
                continue
            foot = foot_per_w * (c0[3] + t * c1[3])
            outcome = _resolve(
                r, p, col, row, ox, oy, oz, dx, dy, dz, width, height, tri_img, pos_img,
                view_img, depth_img, clip_from_rel, origin, frame, tri_table, split, foot,
                out_tri, out_u, out_v, out_t,
            )  # fmt: skip
            if outcome == AMBIGUOUS and -h > foot * THICKNESS_PIXELS:
                outcome = BEHIND  # no triangle hit, deeper than the thickness
            break
        out_outcome[r] = outcome


@njit(**_HELPER)
def _resolve(r, p, col, row, ox, oy, oz, dx, dy, dz, width, height, tri_img, pos_img,
             view_img, depth_img, clip_from_rel, origin, frame, tri_table, split, foot,
             out_tri, out_u, out_v, out_t):  # fmt: skip
    """The exact hit of ray r crossing the surface at pixel p (col, row): the nearest of
    the 3x3 neighbourhood's triangles it hits, checked (the module's rule); writes row
    r of the outputs when resolved and returns the outcome."""
    best, best_tri, best_u, best_v = np.inf, np.int64(-1), 0.0, 0.0
    for j in range(-1, 2):
        for i in range(-1, 2):
            c, q = col + i, row + j
            if c < 0 or c >= width or q < 0 or q >= height:
                continue
            tq = np.int64(tri_img[q * width + c])
            if tq < 0:
                continue
            dist, u, v = _triangle_hit(frame, tq, ox, oy, oz, dx, dy, dz)
            if dist < best:
                best, best_tri, best_u, best_v = dist, tq, u, v
    if best_tri < 0:
        return AMBIGUOUS
    nx, ny, nz = frame[best_tri, 3, 0], frame[best_tri, 3, 1], frame[best_tri, 3, 2]
    d_n = dx * nx + dy * ny + dz * nz
    v_n = view_img[p, 0] * nx + view_img[p, 1] * ny + view_img[p, 2] * nz
    if abs(d_n) < MIN_FACING or d_n * v_n <= 0.0:  # along it, or from the far side
        return FAR_SIDE
    # The pixel's G-buffer position on the ray, within the footprint rule.
    ex = pos_img[p, 0] - origin[0] - ox
    ey = pos_img[p, 1] - origin[1] - oy
    ez = pos_img[p, 2] - origin[2] - oz
    along = ex * dx + ey * dy + ez * dz
    ax, ay, az = ex - along * dx, ey - along * dy, ez - along * dz
    tp = np.int64(tri_img[p])
    cos_view = abs(view_img[p, 0] * frame[tp, 3, 0] + view_img[p, 1] * frame[tp, 3, 1]
                   + view_img[p, 2] * frame[tp, 3, 2])  # fmt: skip
    tolerance = POSITION_TOLERANCE_PIXELS * foot / max(cos_view, COS_FLOOR)
    if ax * ax + ay * ay + az * az > tolerance * tolerance:
        return OFF_RAY
    # The hit itself on screen in the neighbourhood, and not behind what its pixel shows.
    hx, hy, hz = ox + best * dx, oy + best * dy, oz + best * dz
    cx = clip_from_rel[0, 0] * hx + clip_from_rel[0, 1] * hy + clip_from_rel[0, 2] * hz
    cy = clip_from_rel[1, 0] * hx + clip_from_rel[1, 1] * hy + clip_from_rel[1, 2] * hz
    cw = clip_from_rel[3, 0] * hx + clip_from_rel[3, 1] * hy + clip_from_rel[3, 2] * hz
    cx += clip_from_rel[0, 3]
    cy += clip_from_rel[1, 3]
    cw += clip_from_rel[3, 3]
    if not (cw > 0.0):
        return AMBIGUOUS
    hc = int(math.floor((cx / cw + 1.0) * 0.5 * width))
    hr = int(math.floor((1.0 - cy / cw) * 0.5 * height))
    if abs(hc - col) > 1 or abs(hr - row) > 1 or hc < 0 or hc >= width or hr < 0 or hr >= height:
        return AMBIGUOUS
    if depth_img[hr * width + hc] < cw - tolerance:  # hidden at its own pixel
        return AMBIGUOUS
    if tri_table[best_tri, TRI_REFLECTOR] >= 0.0:
        return REFLECTOR
    if split and tri_table[best_tri, TRI_ALPHA] < 1.0:
        return TRANSMISSIVE
    out_tri[r] = best_tri
    out_u[r] = best_u
    out_v[r] = best_v
    out_t[r] = best
    return RESOLVED


def warm_up() -> None:
    """Compile (or load from the cache) ``march`` on tiny inputs of the types
    ``screen_space`` passes."""
    v32 = np.zeros((1, 3), np.float32)
    frame, table = np.zeros((1, 4, 3)), np.zeros((1, 5))
    march(
        v32, v32, np.zeros(1, np.int64), np.eye(4), 1, 1, np.full(1, -1, np.int32),
        np.zeros((1, 3)), v32, np.zeros(1, np.float32), np.zeros(3), frame, table, False, 8,
        0, 1, np.zeros(1, np.int64),
        np.zeros(1, np.float32), np.zeros(1, np.float32), np.zeros(1, np.float32),
        np.zeros(1, np.int8), np.zeros(1, np.int32),
    )  # fmt: skip
