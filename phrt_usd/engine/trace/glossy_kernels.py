"""Glossy reflections compiled (``engine/trace/glossy.py``, whose docstring has the rule):
the first rays of glossy pixels drawn from their GGX lobe's visible normals, and the
spatial reconstruction of their one-sample-a-pixel radiance.

Three kernels over a range lo..hi of their rows (callers may split them over a pool:
each only reads shared arrays and writes its own rows):

- ``glossy_rays``: a pixel's reflection direction drawn from the visible normals of its
  lobe (Heitz 2018, "Sampling the GGX Distribution of Visible Normals"), two uniforms
  from a hash of the pixel and the frame (``_uniform``), the ray's offset origin on the
  side it leaves to, and the sample's weight (G2 / G1, over the lobe's mean of it:
  ``glossy.conditional_albedo_table``);
- ``clamp_fireflies``: a sample's radiance scaled down to at most FIREFLY_RATIO times
  the median luminance of the samples around it, the range of the samples around each
  (the accumulation's clamp) and the mean of a guide around it (the filter's reach);
- ``denoise_pass``: one axis of the edge-aware Gaussian filter of the samples within a
  radius that grows with roughness (run along rows, then columns).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS

_HELPER = {**KERNEL_OPTIONS, "inline": "always"}
_MASK32 = 0xFFFFFFFF
#: Rec. 709 luminance weights (linear RGB).
_LUM_R, _LUM_G, _LUM_B = 0.2126, 0.7152, 0.0722


@njit(**_HELPER)
def _hash32(x):
    """A 32-bit integer hash (lowbias32, Wellons 2020) of x (int64, its low 32 bits)."""
    x &= _MASK32
    x ^= x >> 16
    x = (x * 0x7FEB352D) & _MASK32
    x ^= x >> 15
    x = (x * 0x846CA68B) & _MASK32
    x ^= x >> 16
    return x


@njit(**_HELPER)
def _uniform(pixel, draw, seed):
    """Two uniforms in [0, 1) of ``pixel``'s ``draw``-th sample in the frame of ``seed``
    (int64): the same pixel, frame and draw always give the same pair."""
    h = _hash32(pixel * 8 + draw + _hash32(seed))
    g = _hash32(h ^ 0x5BD1E995)
    return h * (1.0 / 4294967296.0), g * (1.0 / 4294967296.0)


#: The R2 sequence's steps (Roberts 2018: 1 / g and 1 / g², g the plastic number): the
#: first draw's uniforms are its dither of the pixel, shifted per frame, so that the
#: pixels of any small window sample the lobe evenly (the filter's mean of them is a
#: stratified estimate, not one of independent draws).
_R2_A, _R2_B = 0.7548776662466927, 0.5698402909980532


@njit(**_HELPER)
def _dither(pixel, width, seed):
    """The first draw's two uniforms in [0, 1) of ``pixel`` (flat, in an image ``width``
    pixels wide) in the frame of ``seed``: the R2 dither of its column and row and of
    its row and column, each shifted by a hash of the frame."""
    x, y = pixel % width, pixel // width
    h = _hash32(seed + 0x632BE5AB)
    s1, s2 = h * (1.0 / 4294967296.0), _hash32(h) * (1.0 / 4294967296.0)
    u1 = x * _R2_A + y * _R2_B + s1
    u2 = y * _R2_A + x * _R2_B + s2
    return u1 - math.floor(u1), u2 - math.floor(u2)


@njit(**_HELPER)
def _smith_lambda(c, a2):
    """Smith's Λ of GGX at cosine c to the normal, a2 = alpha²."""
    c = max(c, 1e-7)
    return 0.5 * (math.sqrt(1.0 + a2 * (1.0 - c * c) / (c * c)) - 1.0)


@njit(**_HELPER)
def _table_lookup(table, rough, mu):
    """Bilinear read of ``table`` (R, M) at roughness ``rough`` in [0, 1] (rows) and
    cosine ``mu`` in [0, 1] (columns)."""
    rows, cols = table.shape[0], table.shape[1]
    x = min(max(rough, 0.0), 1.0) * (rows - 1)
    y = min(max(mu, 0.0), 1.0) * (cols - 1)
    i, j = min(int(x), rows - 2), min(int(y), cols - 2)
    fx, fy = x - i, y - j
    top = table[i, j] * (1.0 - fy) + table[i, j + 1] * fy
    bottom = table[i + 1, j] * (1.0 - fy) + table[i + 1, j + 1] * fy
    return top * (1.0 - fx) + bottom * fx


@njit(**KERNEL_OPTIONS)
def glossy_rays(
    pix, rel, ng, ns, view, rough, seed, table, mirror_roughness, floor, relative, draws,
    width, lo, hi, out_dir, out_org, out_weight,
):  # fmt: skip
    """The first rays of rows lo..hi whose roughness ``rough`` (n,) float32 is above
    ``mirror_roughness``: out_dir (n, 3) float32 (in: the mirror direction; out: a
    direction drawn from the visible normals of the GGX lobe of alpha = roughness², about
    the shading normal ``ns`` (n, 3) float32 facing the viewer, seen along ``view`` (n, 3)
    float32), out_org (n, 3) float32 its origin offset from ``rel`` (n, 3) float64 along
    the front normal ``ng`` (n, 3) float64 on the side it leaves to (the offset rule of
    ``bvh.Float32Boundary``: floor, relative), out_weight (n,) float32 its weight G2 / G1
    over ``table``'s conditional mean of it (``glossy.conditional_albedo_table``).

    A draw leaving below the shading or the geometric plane is drawn again (``draws``
    tries); after the last the row keeps its mirror ray (weight 1). Rows at or below
    ``mirror_roughness`` keep theirs, weight 1. ``pix`` (n,) int64 the rows' flat pixels
    (in an image ``width`` pixels wide) and ``seed`` int64 the frame's: the first draw's
    uniforms are the pixel's R2 dither (``_dither``), the others a hash (``_uniform``)."""
    for i in range(lo, hi):
        out_weight[i] = 1.0
        r = float(rough[i])
        if not r > mirror_roughness:
            continue
        alpha = r * r
        a2 = alpha * alpha
        nx, ny, nz = float(ns[i, 0]), float(ns[i, 1]), float(ns[i, 2])
        # An orthonormal basis about n (Duff et al. 2017).
        sign = 1.0 if nz >= 0.0 else -1.0
        a = -1.0 / (sign + nz)
        b = nx * ny * a
        tx, ty, tz = 1.0 + sign * nx * nx * a, sign * b, -sign * nx
        bx, by, bz = b, sign + ny * ny * a, -ny
        # V: towards the eye, in the basis.
        ex, ey, ez = -float(view[i, 0]), -float(view[i, 1]), -float(view[i, 2])
        vx, vy = ex * tx + ey * ty + ez * tz, ex * bx + ey * by + ez * bz
        vz = ex * nx + ey * ny + ez * nz
        if not vz > 1e-4:
            continue
        # The view direction stretched to the unit-roughness configuration.
        hx, hy, hz = alpha * vx, alpha * vy, vz
        length = math.sqrt(hx * hx + hy * hy + hz * hz)
        hx, hy, hz = hx / length, hy / length, hz / length
        lensq = hx * hx + hy * hy
        if lensq > 0.0:
            inv = 1.0 / math.sqrt(lensq)
            t1x, t1y, t1z = -hy * inv, hx * inv, 0.0
        else:
            t1x, t1y, t1z = 1.0, 0.0, 0.0
        t2x, t2y, t2z = hy * t1z - hz * t1y, hz * t1x - hx * t1z, hx * t1y - hy * t1x
        lam_v = _smith_lambda(vz, a2)
        for draw in range(draws):
            if draw == 0:
                u1, u2 = _dither(pix[i], width, seed)
            else:
                u1, u2 = _uniform(pix[i], draw, seed)
            rad, phi = math.sqrt(u1), 2.0 * math.pi * u2
            p1, p2 = rad * math.cos(phi), rad * math.sin(phi)
            s = 0.5 * (1.0 + hz)
            p2 = (1.0 - s) * math.sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2
            up = math.sqrt(max(1.0 - p1 * p1 - p2 * p2, 0.0))
            mx = p1 * t1x + p2 * t2x + up * hx
            my = p1 * t1y + p2 * t2y + up * hy
            mz = p1 * t1z + p2 * t2z + up * hz
            mx, my, mz = alpha * mx, alpha * my, max(mz, 0.0)
            length = math.sqrt(mx * mx + my * my + mz * mz)
            if not length > 0.0:
                continue
            mx, my, mz = mx / length, my / length, mz / length
            vm = vx * mx + vy * my + vz * mz
            lx, ly, lz = 2.0 * vm * mx - vx, 2.0 * vm * my - vy, 2.0 * vm * mz - vz
            if not lz > 1e-4:
                continue
            # Back to world space.
            dx = lx * tx + ly * bx + lz * nx
            dy = lx * ty + ly * by + lz * ny
            dz = lx * tz + ly * bz + lz * nz
            gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
            dg = dx * gx + dy * gy + dz * gz
            mirror_g = (float(out_dir[i, 0]) * gx + float(out_dir[i, 1]) * gy
                        + float(out_dir[i, 2]) * gz)  # fmt: skip
            if mirror_g > 0.0 and not dg > 0.0:
                continue  # below the surface the mirror ray leaves
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            out_dir[i, 0], out_dir[i, 1], out_dir[i, 2] = dx / length, dy / length, dz / length
            px, py, pz = rel[i, 0], rel[i, 1], rel[i, 2]
            eps = max(floor, relative * max(max(abs(px), abs(py)), abs(pz)))
            e = eps if dg >= 0.0 else -eps
            out_org[i, 0], out_org[i, 1], out_org[i, 2] = px + e * gx, py + e * gy, pz + e * gz
            g2_g1 = (1.0 + lam_v) / (1.0 + lam_v + _smith_lambda(lz, a2))
            mean = _table_lookup(table, r, vz)
            out_weight[i] = g2_g1 / mean if mean > 0.0 else 1.0
            break


@njit(**_HELPER)
def _luminance(rad, q):
    return _LUM_R * rad[q, 0] + _LUM_G * rad[q, 1] + _LUM_B * rad[q, 2]


@njit(**_HELPER)
def _median(values, work, k):
    """The median (the upper one of an even count) of values[:k], sorted into ``work``
    (insertion sort: k <= 9, no allocation)."""
    for a in range(k):
        v = values[a]
        b = a
        while b > 0 and work[b - 1] > v:
            work[b] = work[b - 1]
            b -= 1
        work[b] = v
    return work[k // 2]


@njit(**KERNEL_OPTIONS)
def clamp_fireflies(pix, rad, active, spacing, table, element, reach, width, height, ratio,
                    lo, hi, out, low, high, reach_mean):  # fmt: skip
    """Rows lo..hi of out (n, 3) float32: ``rad`` (n, 3) float32 of the round's pixels
    ``pix`` (n,) int64, scaled down where its luminance exceeds ``ratio`` times the median
    luminance of the samples of its element in the 3 x 3 around it (step ``spacing`` (n,)
    int64 pixels; ``table`` (H*W,) int32 each pixel's row, -1: none; ``element`` (H*W,)
    int32); low, high (n, 3) float32 the per-channel range of those samples (each capped
    as it would be: the accumulation's clamp); reach_mean (n,) float32 the mean of
    ``reach`` (H*W,) float32 over them where it is finite (NaN: unknown; none: NaN).
    Rows whose ``active`` (n,) bool is False are copied as they are (mirrors)."""
    window, sorted_window = np.empty(9), np.empty(9)
    rows = np.empty(9, np.int64)
    for i in range(lo, hi):
        for c in range(3):
            out[i, c] = rad[i, c]
            low[i, c] = rad[i, c]
            high[i, c] = rad[i, c]
        reach_mean[i] = np.nan
        if not active[i]:
            continue
        p = pix[i]
        row, col = p // width, p % width
        s = spacing[i]
        e = element[p]
        k = 0
        v_sum, v_count = 0.0, 0
        for dr in range(-1, 2):
            rr = row + dr * s
            if rr < 0 or rr >= height:
                continue
            for dc in range(-1, 2):
                cc = col + dc * s
                if cc < 0 or cc >= width:
                    continue
                q = rr * width + cc
                j = table[q]
                if j < 0 or element[q] != e:
                    continue
                window[k] = _luminance(rad, j)
                rows[k] = j
                k += 1
                v = reach[q]
                if math.isfinite(v):
                    v_sum += v
                    v_count += 1
        if v_count:
            reach_mean[i] = v_sum / v_count
        if k < 3:
            continue
        cap = ratio * _median(window, sorted_window, k)
        for m in range(k):
            j = rows[m]
            scale = cap / window[m] if window[m] > cap else 1.0
            for c in range(3):
                v = rad[j, c] * scale
                low[i, c] = min(low[i, c], v)
                high[i, c] = max(high[i, c], v)
                if j == i:
                    out[i, c] = v


@njit(**_HELPER)
def _power(x, n):
    """x ** n for a power of two n (repeated squaring)."""
    while n > 1:
        x = x * x
        n //= 2
    return x


@njit(**KERNEL_OPTIONS)
def denoise_pass(pix, acc, radius, spacing, table, element, normal, position, depth, width,
                 height, normal_power, plane_tolerance, axis, lo, hi, out):  # fmt: skip
    """Rows lo..hi of out (n, 4) float64: one axis (``axis`` 0: along the row, 1: along
    the column) of the edge-aware Gaussian filter, as sums (w L, w) of ``acc`` (n, 4)
    float64 (the first pass: each sample's weight times its radiance, and its weight;
    the second: the first's sums) over the pixels within ``radius`` (n,) int64 steps of
    ``spacing`` (n,) int64 pixels along the axis of each pixel ``pix`` (n,) int64 (sigma
    half the radius plus half a step), each weighed by the normals' agreement
    (n·n')^normal_power (a power of two) and kept only on the pixel's element and
    within ``plane_tolerance`` times its view depth of its tangent plane (``normal``
    (H*W, 3) float32, ``position`` (H*W, 3) float64, ``depth`` (H*W,) float32,
    ``element`` (H*W,) int32; ``table`` (H*W,) int32 each pixel's row). The two passes
    make the separable approximation of the square window's filter (the ratio of the
    sums: the weights' scale cancels). Rows of radius 0 keep their sums."""
    for i in range(lo, hi):
        for c in range(4):
            out[i, c] = acc[i, c]
        rad_i = radius[i]
        if rad_i <= 0:
            continue
        p = pix[i]
        s = spacing[i]
        row, col = p // width, p % width
        e = element[p]
        nx, ny, nz = normal[p, 0], normal[p, 1], normal[p, 2]
        px, py, pz = position[p, 0], position[p, 1], position[p, 2]
        tol = plane_tolerance * max(float(depth[p]), 1e-6)
        sigma = 0.5 * rad_i + 0.5
        inv2s2 = 1.0 / (2.0 * sigma * sigma)
        a0 = a1 = a2 = a3 = 0.0
        for d in range(-rad_i, rad_i + 1):
            rr, cc = row, col
            if axis == 0:
                cc = col + d * s
            else:
                rr = row + d * s
            if rr < 0 or rr >= height or cc < 0 or cc >= width:
                continue
            q = rr * width + cc
            j = table[q]
            if j < 0 or element[q] != e:
                continue
            cos = nx * normal[q, 0] + ny * normal[q, 1] + nz * normal[q, 2]
            if not cos > 0.0:
                continue
            off = ((position[q, 0] - px) * nx + (position[q, 1] - py) * ny
                   + (position[q, 2] - pz) * nz)  # fmt: skip
            if abs(off) > tol:
                continue
            w = math.exp(-d * d * inv2s2) * _power(float(cos), normal_power)
            a0 += w * acc[j, 0]
            a1 += w * acc[j, 1]
            a2 += w * acc[j, 2]
            a3 += w * acc[j, 3]
        if a3 > 0.0:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = a0, a1, a2, a3


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs of the types
    ``glossy`` passes."""
    i64, f32 = np.zeros(1, np.int64), np.zeros(1, np.float32)
    v32, v64 = np.zeros((1, 3), np.float32), np.zeros((1, 3))
    table = np.ones((4, 4), np.float32)
    glossy_rays(i64, v64, v64, v32, v32, f32, 0, table, 0.03, 1e-6, 1e-5, 4, 1, 0, 1,
                v32.copy(), v32.copy(), f32.copy())  # fmt: skip
    i32 = np.zeros(1, np.int32)
    b1 = np.ones(1, np.bool_)
    clamp_fireflies(i64, v32, b1, i64 + 1, i32, i32, f32, 1, 1, 4.0, 0, 1, v32.copy(),
                    v32.copy(), v32.copy(), f32.copy())  # fmt: skip
    a4 = np.zeros((1, 4))
    denoise_pass(i64, a4, i64, i64 + 1, i32, i32, v32, v64, f32, 1, 1, 32, 0.01, 0, 0, 1,
                 a4.copy())  # fmt: skip
