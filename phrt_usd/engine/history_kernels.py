"""The reprojection of reflection history compiled (``engine/reflection_history.py``, whose
docstring has the rule): for each pixel of this frame, the previous frame's pixel that
showed the same reflected point, and whether its history passes the per-pixel tests.

Two kernels over a range lo..hi of their rows (callers may split them over a pool: they
only read shared arrays): ``history_lookup``, and ``accumulate``, which blends filled
pixels' previous values in by the same rule (``_previous_pixel``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS

_HELPER = {**KERNEL_OPTIONS, "inline": "always"}


@njit(**KERNEL_OPTIONS)
def _project(m, x, y, z, w, width, height, max_offset):
    """Flat pixel of the point (x, y, z, w) (w 1 a point, 0 a direction) through the
    clip-from-world matrix ``m`` (4, 4), -1 behind the camera, off screen or farther
    than ``max_offset`` pixels (along either axis) from the pixel's centre (NDC (x, y)
    → ((x + 1) W / 2, (1 - y) H / 2), row 0 at the top: ``model.frame.FrameCamera``)."""
    cw = m[3, 0] * x + m[3, 1] * y + m[3, 2] * z + m[3, 3] * w
    if not cw > 0.0:
        return -1
    cx = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3] * w
    cy = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3] * w
    col = (cx / cw * 0.5 + 0.5) * width
    row = (0.5 - cy / cw * 0.5) * height
    if not (col >= 0.0 and col < width and row >= 0.0 and row < height):
        return -1
    if abs(col - int(col) - 0.5) > max_offset or abs(row - int(row) - 0.5) > max_offset:
        return -1
    return int(row) * width + int(col)


@njit(**_HELPER)
def _previous_pixel(
    p, h, own_hit, element, normal, position, view, depth, period, moved, prev_element,
    prev_age, prev_normal, prev_position, prev_hit, clip_from_world, width, height,
    max_offset, normal_agreement, plane_tolerance,
):  # fmt: skip
    """(q, ok) for pixel p of this frame: ``history_lookup``'s rule for one pixel (its
    docstring), ``h`` its hit distance when ``own_hit``, ``period`` its age limit."""
    px, py, pz = position[p, 0], position[p, 1], position[p, 2]
    if not own_hit:
        q0 = _project(clip_from_world, px, py, pz, 1.0, width, height, 0.5)
        h = prev_hit[q0] if q0 >= 0 else np.inf
    vx, vy, vz = view[p, 0], view[p, 1], view[p, 2]
    if math.isfinite(h):
        q = _project(clip_from_world, px + vx * h, py + vy * h, pz + vz * h, 1.0,
                     width, height, max_offset)  # fmt: skip
    else:
        q = _project(clip_from_world, vx, vy, vz, 0.0, width, height, max_offset)
    e = element[p]
    if q < 0 or prev_element[q] != e or moved[e]:
        return q, False
    if int(prev_age[q]) + 1 >= period:
        return q, False
    nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
    if nx * prev_normal[q, 0] + ny * prev_normal[q, 1] + nz * prev_normal[q, 2] < \
            normal_agreement:  # fmt: skip
        return q, False
    off = ((prev_position[q, 0] - px) * nx + (prev_position[q, 1] - py) * ny
           + (prev_position[q, 2] - pz) * nz)  # fmt: skip
    return q, abs(off) <= plane_tolerance * depth[p]


@njit(**KERNEL_OPTIONS)
def history_lookup(
    pix, hit, own_hit, element, normal, position, view, depth, period, moved,
    prev_element, prev_age, prev_normal, prev_position, prev_hit, clip_from_world,
    width, height, max_offset, normal_agreement, plane_tolerance, lo, hi, out_q, out_ok,
):  # fmt: skip
    """Rows lo..hi: pixel ``pix[i]`` (flat, this frame) → ``out_q[i]`` the previous
    frame's pixel showing its reflected point (-1: none, or farther than ``max_offset``
    pixels from that pixel's centre) and ``out_ok[i]`` its history
    valid (on screen, same element, age + 1 < ``period[i]``, element not ``moved``,
    normals within ``normal_agreement``, on the tangent plane within ``plane_tolerance``
    of the view depth).

    hit (n,) float32 this frame's hit distances, read when ``own_hit``; otherwise the
    previous frame's at the surface's own reprojection. This frame's images flat over
    H*W: element int32, normal (., 3) float32, position (., 3) float64, view (., 3)
    float32, depth float32; moved (E + 1,) bool per element id (+1: id -1); the
    previous frame's element int32, age int16, normal float32, position float64, hit
    float32; clip_from_world (4, 4) float64 the previous camera's."""
    for i in range(lo, hi):
        out_q[i], out_ok[i] = _previous_pixel(
            pix[i], hit[i] if own_hit else 0.0, own_hit, element, normal, position, view,
            depth, period[i], moved, prev_element, prev_age, prev_normal, prev_position,
            prev_hit, clip_from_world, width, height, max_offset, normal_agreement,
            plane_tolerance,
        )  # fmt: skip


@njit(**KERNEL_OPTIONS)
def accumulate(
    pix, hit, low, high, weight, period, element, normal, position, view, depth, moved,
    prev_element, prev_age, prev_normal, prev_position, prev_hit, prev_radiance,
    clip_from_world, width, height, max_offset, normal_agreement, plane_tolerance, lo, hi,
    radiance,
):  # fmt: skip
    """Rows lo..hi: filled pixel ``pix[i]`` blends ``weight`` of its previous value into
    ``radiance[i]`` (n, 3) float32 in place, where ``history_lookup``'s rule finds one
    (for the pixel's hit distance ``hit[i]`` (n,) float32, the fill's estimate; age limit
    ``period``), clamped per channel to
    [low[i], high[i]] (n, 3) float32; the other arguments as ``history_lookup``'s, the
    previous frame's radiance prev_radiance (H*W, 3) float32."""
    for i in range(lo, hi):
        q, ok = _previous_pixel(
            pix[i], hit[i], True, element, normal, position, view, depth, period, moved,
            prev_element, prev_age, prev_normal, prev_position, prev_hit, clip_from_world,
            width, height, max_offset, normal_agreement, plane_tolerance,
        )  # fmt: skip
        if ok:
            for c in range(3):
                h = min(max(prev_radiance[q, c], low[i, c]), high[i, c])
                radiance[i, c] += weight * (h - radiance[i, c])


def warm_up() -> None:
    """Compile (or load from the cache) the kernel on tiny inputs of the types
    ``reflection_history`` passes."""
    i64, f32 = np.zeros(1, np.int64), np.zeros(1, np.float32)
    v32, v64 = np.zeros((1, 3), np.float32), np.zeros((1, 3))
    i32, i16 = np.zeros(1, np.int32), np.zeros(1, np.int16)
    history_lookup(i64, f32, True, i32, v32, v64, v32, f32, i64 + 2, np.zeros(2, np.bool_),
                   i32, i16, v32, v64, f32, np.eye(4), 1, 1, 0.25, 0.95, 0.005, 0, 1, i64.copy(),
                   np.zeros(1, np.bool_))  # fmt: skip
    accumulate(i64, f32, v32, v32, 0.5, 2, i32, v32, v64, v32, f32, np.zeros(2, np.bool_), i32, i16,
               v32, v64, f32, v32, np.eye(4), 1, 1, 0.5, 0.95, 0.005, 0, 1, v32.copy())  # fmt: skip
