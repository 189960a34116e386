"""The reconstruction of reduced densities compiled: the radiance of a reflector's skipped
pixels from its traced ones (``sparse_pixels.fill_skipped``), an edge-aware Catmull-Rom
interpolation on the traced pattern's lattice.

Four kernels, in the order a round calls them:

- ``fill_table``: each traced pixel's row in a pixel table, and the depth share of its
  reflection's path (``v`` below, its hit-distance guide);
- ``fill_curvature``: each traced pixel's second differences along the lattice's two
  axes (the Catmull-Rom term, below);
- ``fill_skipped``: the skipped pixels;
- ``clear_table``: the table back to all -1.

The last three take a range lo..hi of their rows (callers split them over a pool: the
table is read-only while they run).

The lattice of a pattern (the density's regular pattern: ``sparse_pixels``): a grid
of spacing s (axes (0, s) and (s, 0)) or the checkerboard of the grid of spacing q (axes
(q, q) and (q, -q): q = 1 the checkerboard, 2 the eighth's); a skipped pixel p lies in the
cell of four traced lattice points (its corners), at fractions (t1, t2) along the two
axes. A density between two regular patterns traces more pixels than its lattice's:
they keep their traced values, and the fill still interpolates on the lattice.

Guides. A traced pixel q weighs ``guide(p, q)``: the normals' agreement
(n_p . n_q)^(2^FILL_NORMAL_SQUARINGS) times the plane weight (how far the line between
p and q leaves either tangent plane: full below FILL_PLANE_SINE_FULL, none above
FILL_PLANE_SINE_ZERO, linear between), and its reflection's hit distance t through
v = z / (z + t) (z its view depth: 1 at the mirror, 0 for a ray that left the scene):
p's estimate v̂ is the corners' bilinear mean of v, and a corner weighs
max(1 - |v - v̂| / FILL_HIT_TOLERANCE, FILL_HIT_FLOOR) more, so at an edge of the
reflected image (a near object over a far one) p takes the side its estimate lies on.

Catmull-Rom. Along one axis, the Catmull-Rom interpolation of f-1, f0, f1, f2 at t is
the linear one of f0 - t (1 - t) / 2 D0 and f1 - t (1 - t) / 2 D1, D the second
difference f-1 - 2 f0 + f1 at each corner (its cubic Hermite form with central
tangents). ``fill_curvature`` computes D once per traced pixel and axis, from its two
lattice neighbours along it, times their guides to it (no curvature across an edge:
there the interpolation is linear, as with a missing neighbour). The skipped pixel is
then the mean of its corners' values corrected along both axes, weighed by their
bilinear weights times their guides (the separable Catmull-Rom less its cross term,
t1 (1 - t1) t2 (1 - t2) / 4 <= 1/64 times a mixed fourth difference), clamped per
channel to the range of the corners it used: no ringing, and nothing from the other
side of an edge. On a linear ramp D is 0 and the value exact.

The sky. A traced sample whose reflection ray left the scene (v = 0) shows the
environment in its own mirror direction, which is what the raster fallback shows at
every pixel (``compositing.base_image``). For such a sample the pixel takes its own
fallback reflection instead of the sample's value (no curvature term; the range clamp
includes it): exact where the pixel's ray leaves the scene too, so a reflector that
reflects only the sky is reconstructed exactly at any density (a normal-mapped pond's
ripples in the sky included), and one reflecting the sky beside geometry keeps the
sky's detail up to the reflected edge. The fallback reflection is
(fallback - (1 - F) local) / F, F the pixel's reflectivity (``FillGuides.raster``);
below ENV_MIN_REFLECTIVITY (float32 rounding divided by F) and on stages with
transmissive materials (whose traced radiance mixes in refraction) the rule is off.

A pixel whose cell has no corner of its reflector (an edge, an irregular traced
subset) takes the tent-weighted mean of its reflector's traced lattice points within
the window's radius (``_axes``; the guides' weights, or without them when they leave
none), as the bilinear fill did; none: not filled.

Arrays: G-buffer images flat over H*W (normal (H*W, 3) float32 unit, position (H*W, 3)
float64 world, depth (H*W,) float32 view depth).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS

_KERNEL = KERNEL_OPTIONS
_HELPER = {**_KERNEL, "inline": "always"}

#: The normal guide (n_p . n_q)^(2^FILL_NORMAL_SQUARINGS): 256 weighs 1/2 at 4.2 degrees
#: and under 1 % beyond 10 (SVGF weighs (n . n')^128). As sharp as that because a wet or
#: normal-mapped reflector's ripples decide what it reflects: the samples whose normal
#: matches the pixel's are the ones that reflect what it does (on the sewer's wet tunnel
#: at 320 x 240, with an earlier form of this fill, FLIP against full density was 0.4-1 %
#: lower than with 64 and 2-4 % lower than with a ramp from 30 to 60 degrees).
FILL_NORMAL_SQUARINGS = 8
#: Normals further apart weigh nothing (cos 21.5 degrees: (n . n')^256 < 1e-8 beyond it;
#: the weights stay clear of subnormal numbers, which cost the processor a slow path).
FILL_NORMAL_MIN_COSINE = 0.93
#: The plane guide: full weight while the line between p and a tap leaves both tangent
#: planes at a sine below FILL_PLANE_SINE_FULL (a surface curving by less than ~60
#: degrees between them), none above FILL_PLANE_SINE_ZERO (a depth step or a fold of the
#: same mesh), linear between.
FILL_PLANE_SINE_FULL = 0.5
FILL_PLANE_SINE_ZERO = 0.8
#: The hit-distance guide: taps whose v = z / (z + t) differs from p's estimate by this
#: much weigh FILL_HIT_FLOOR only (0.1-0.35 measured on the sewer and a mirror sphere:
#: 0.2 lowest overall; a relative distance instead dilated near objects over the sky).
FILL_HIT_TOLERANCE = 0.2
#: What a tap far from p's hit-distance estimate still weighs: never nothing, so that a
#: pixel between two equally far estimates takes a mix of both, as the bilinear fill.
FILL_HIT_FLOOR = 1e-3
#: The sky rule (module docstring) needs the pixel's fallback reflection back from the
#: raster frame, (fallback - (1 - F) local) / F: float32 rounding of ~1e-7 of the local
#: term divided by F stays below 1e-5 for F >= 0.01; a reflector reflecting less than
#: that keeps the interpolation.
ENV_MIN_REFLECTIVITY = 0.01
#: The weight the cell's corners add to their bilinear weight in v̂ (and in the value
#: where the bilinear weights leave none), so that a corner at the far end of p's cell
#: still counts where the nearer ones are missing.
_CORNER_FLOOR = 1e-3
_PLANE_FULL2 = FILL_PLANE_SINE_FULL * FILL_PLANE_SINE_FULL
_PLANE_ZERO2 = FILL_PLANE_SINE_ZERO * FILL_PLANE_SINE_ZERO


@njit(**_HELPER)
def _guide(nx, ny, nz, px, py, pz, q, normal, position):
    """The geometric weight in [0, 1] of the pixel q (flat index) for a pixel of unit
    normal (nx, ny, nz) at world (px, py, pz): the normals' and the planes' agreement
    (module docstring)."""
    mx, my, mz = float(normal[q, 0]), float(normal[q, 1]), float(normal[q, 2])
    w = nx * mx + ny * my + nz * mz
    if not (w > FILL_NORMAL_MIN_COSINE):
        return 0.0
    for _ in range(FILL_NORMAL_SQUARINGS):
        w *= w
    dx, dy, dz = position[q, 0] - px, position[q, 1] - py, position[q, 2] - pz
    a = dx * nx + dy * ny + dz * nz
    b = dx * mx + dy * my + dz * mz
    off = max(a * a, b * b)
    length2 = dx * dx + dy * dy + dz * dz
    if off <= _PLANE_FULL2 * length2:
        return w
    if off >= _PLANE_ZERO2 * length2:
        return 0.0
    return w * (_PLANE_ZERO2 * length2 - off) / ((_PLANE_ZERO2 - _PLANE_FULL2) * length2)


@njit(**_HELPER)
def _environment(p, fallback, local, reflectivity, sky):
    """Writes the raster fallback's reflection at pixel p into sky (3,) float64 and
    returns True, or False when the rule is off (no raster images given, or the pixel's
    reflectivity below ENV_MIN_REFLECTIVITY)."""
    if fallback.shape[0] == 0:
        return False
    f = float(reflectivity[p])
    if not (f >= ENV_MIN_REFLECTIVITY):
        return False
    for c in range(3):
        sky[c] = (float(fallback[p, c]) - (1.0 - f) * float(local[p, c])) / f
    return True


@njit(**_HELPER)
def _sky(state, p, fallback, local, reflectivity, sky):
    """The sky rule's state for pixel p after its first sky sample: ``state`` 0 (not
    read yet) becomes 1 with p's fallback reflection in sky (``_environment``) or -1
    (the rule off); read once a pixel, only where a sample's ray left the scene."""
    if state == 0:
        state = 1 if _environment(p, fallback, local, reflectivity, sky) else -1
    return state


@njit(**_KERNEL)
def fill_table(table, traced_pix, hit, depth, out_v):
    """Traced pixel i's row into table[traced_pix[i]] (table (H*W,) int32 all -1), and
    its v = z / (z + t) into out_v (n,) float64: z its view depth (depth (H*W,)), t its
    hit distance hit (n,) float32 (+inf: 0)."""
    for i in range(traced_pix.shape[0]):
        q = traced_pix[i]
        table[q] = i
        z, t = float(depth[q]), float(hit[i])
        out_v[i] = 0.0 if not (t < np.inf) else (z / (z + t) if z + t > 0.0 else 1.0)


@njit(**_KERNEL)
def clear_table(table, traced_pix):
    """``fill_table``'s rows back to -1."""
    for i in range(traced_pix.shape[0]):
        table[traced_pix[i]] = -1


@njit(**_HELPER)
def _axes(lat):
    """The lattice's two axes (rows, columns each) and the fallback window's radius
    (the farthest a pixel of the image lies from a lattice point in it, in rows or
    columns): ``lat`` -q the checkerboard of the grid of spacing q (2q - 1: along the
    image's edges its points are 2q apart), else the grid's spacing s (s - 1)."""
    if lat < 0:
        return -lat, -lat, -lat, lat, -2 * lat - 1
    return 0, lat, lat, 0, lat - 1


@njit(**_HELPER)
def _traced(table, traced_src, s, y, x, width, height):
    """The row of the traced pixel (y, x) of source s, -1 when there is none."""
    if 0 <= y < height and 0 <= x < width:
        at = table[y * width + x]
        if at >= 0 and traced_src[at] == s:
            return at
    return -1


@njit(**_HELPER)
def _hit_weight(v, vhat):
    """The hit-distance guide of a tap of v against the estimate vhat."""
    return max(1.0 - abs(v - vhat) * (1.0 / FILL_HIT_TOLERANCE), FILL_HIT_FLOOR)


@njit(**_KERNEL)
def fill_curvature(table, traced_pix, traced_src, radiance, v, lattice, width, height, normal,
                   position, lo, hi, out_d):  # fmt: skip
    """The second differences of traced pixels lo..hi along the two axes of their
    lattice (``lattice`` (n,) int64: -q the checkerboard of the grid q, s >= 2 the grid, 1 none:
    0)
    into out_d (n, 2, 3) float32, each times its two neighbours' guides (module
    docstring); 0 without both. traced_pix, traced_src (n,) int64, radiance
    (n, 3) float32, v (n,) float64 (``fill_table``'s)."""
    for i in range(lo, hi):
        q, s = traced_pix[i], traced_src[i]
        y = q // width
        x = q - y * width
        ar, ac, br, bc, _ = _axes(lattice[i])
        nx, ny, nz = float(normal[q, 0]), float(normal[q, 1]), float(normal[q, 2])
        px, py, pz = position[q, 0], position[q, 1], position[q, 2]
        for axis in range(2):
            dr, dc = (ar, ac) if axis == 0 else (br, bc)
            before = _traced(table, traced_src, s, y - dr, x - dc, width, height)
            after = _traced(table, traced_src, s, y + dr, x + dc, width, height)
            w = 0.0
            if lattice[i] != 1 and before >= 0 and after >= 0:
                w = (
                    _guide(nx, ny, nz, px, py, pz, traced_pix[before], normal, position)
                    * _hit_weight(v[before], v[i])
                    * _guide(nx, ny, nz, px, py, pz, traced_pix[after], normal, position)
                    * _hit_weight(v[after], v[i])
                )
            for c in range(3):
                out_d[i, axis, c] = 0.0 if w == 0.0 else w * (
                    radiance[before, c] - 2.0 * radiance[i, c] + radiance[after, c]
                )


@njit(**_KERNEL)
def fill_skipped(
    table, traced_src, radiance, v, curvature, traced_pix, skipped_pix, skipped_src, lattice,
    phase, width, height, normal, position, depth, fallback, local, reflectivity, lo, hi,
    out_rad, out_hit, out_ok, out_low, out_high,
):  # fmt: skip
    """The skipped pixels lo..hi (module docstring).

    table: ``fill_table``'s; traced_src (n,) int64, radiance (n, 3) float32, v (n,)
    float64 (``fill_table``'s), curvature (n, 2, 3) float32 (``fill_curvature``'s) and
    traced_pix (n,) int64 of the traced pixels; skipped_pix, skipped_src (m,) int64;
    lattice (m,) int64 each one's pattern: -q the checkerboard of the grid of spacing q
    (rows phase[0] + i q, columns phase[1] + j q, i + j even), s >= 2 the grid of spacing
    s (rows phase[0] + i s, columns phase[1] + j s); phase (2,) int64; the guides
    (normal, position, depth); the raster frame's fallback (H*W, 3), local (H*W, 3)
    float32 and reflectivity (H*W,) float32 images for the sky rule (fallback of 0 rows:
    off).
    Writes out_rad (m, 3) float32 the radiance, out_hit (m,) float32 the hit distance
    the corners' v̂ gives (+inf: its rays leave the scene), out_low, out_high (m, 3)
    float32 per channel the least and the greatest of the values it was made of, and
    out_ok (m,) bool whether the pixel got them (the others are left as they were)."""
    corner = np.empty(4, np.int64)
    weight, bilinear = np.empty(4), np.empty(4)
    sky = np.empty(3)
    for j in range(lo, hi):
        p, s, lat = skipped_pix[j], skipped_src[j], lattice[j]
        r = p // width
        c = p - r * width
        ar, ac, br, bc, radius = _axes(lat)
        if lat < 0:  # along the diagonals u = rows + columns, w = rows - columns
            q2 = -2 * lat  # lattice points lie at multiples of 2q of both
            u = (r - phase[0]) + (c - phase[1])
            w = (r - phase[0]) - (c - phase[1])
            fu, fw = u // q2, w // q2
            r0 = phase[0] + (fu + fw) * (-lat)
            c0 = phase[1] + (fu - fw) * (-lat)
            t1, t2 = (u - fu * q2) / q2, (w - fw * q2) / q2
        else:
            r0 = phase[0] + ((r - phase[0]) // lat) * lat
            c0 = phase[1] + ((c - phase[1]) // lat) * lat
            t1, t2 = (c - c0) / lat, (r - r0) / lat
        nx, ny, nz = float(normal[p, 0]), float(normal[p, 1]), float(normal[p, 2])
        px, py, pz = position[p, 0], position[p, 1], position[p, 2]
        sky_state = 0  # the fallback reflection: 0 not read yet, 1 in sky, -1 rule off
        total = vhat = exact = 0.0
        for k in range(4):  # the corners (0, 0), (1, 0), (0, 1), (1, 1) along the axes
            a1, a2 = k & 1, k >> 1
            at = _traced(table, traced_src, s, r0 + a1 * ar + a2 * br, c0 + a1 * ac + a2 * bc,
                         width, height)  # fmt: skip
            corner[k] = at
            weight[k] = bilinear[k] = 0.0
            if at >= 0:
                g = _guide(nx, ny, nz, px, py, pz, traced_pix[at], normal, position)
                b1, b2 = (t1 if a1 else 1.0 - t1), (t2 if a2 else 1.0 - t2)
                bilinear[k] = b1 * b2 * g
                weight[k] = (b1 + _CORNER_FLOOR) * (b2 + _CORNER_FLOOR) * g
                total += weight[k]
                vhat += weight[k] * v[at]
                exact += bilinear[k]
        if total > 0.0:
            vhat /= total
            if exact > 0.0:  # the bilinear weights where they leave a corner, else floored
                for k in range(4):
                    weight[k] = bilinear[k]
            s1, s2 = 0.5 * t1 * (1.0 - t1), 0.5 * t2 * (1.0 - t2)
            total = x0 = x1 = x2 = 0.0
            lo0 = lo1 = lo2 = np.inf
            hi0 = hi1 = hi2 = -np.inf
            for k in range(4):
                if weight[k] > 0.0:
                    at = corner[k]
                    w = weight[k] * _hit_weight(v[at], vhat)
                    total += w
                    if v[at] == 0.0:  # a ray that left the scene: the sky (docstring)
                        sky_state = _sky(sky_state, p, fallback, local, reflectivity, sky)
                    if v[at] == 0.0 and sky_state > 0:
                        f0, f1, f2 = sky[0], sky[1], sky[2]
                        x0, x1, x2 = x0 + w * f0, x1 + w * f1, x2 + w * f2
                    else:
                        f0, f1, f2 = radiance[at, 0], radiance[at, 1], radiance[at, 2]
                        x0 += w * (f0 - s1 * curvature[at, 0, 0] - s2 * curvature[at, 1, 0])
                        x1 += w * (f1 - s1 * curvature[at, 0, 1] - s2 * curvature[at, 1, 1])
                        x2 += w * (f2 - s1 * curvature[at, 0, 2] - s2 * curvature[at, 1, 2])
                    lo0, hi0 = min(lo0, f0), max(hi0, f0)
                    lo1, hi1 = min(lo1, f1), max(hi1, f1)
                    lo2, hi2 = min(lo2, f2), max(hi2, f2)
            out_low[j, 0], out_low[j, 1], out_low[j, 2] = lo0, lo1, lo2
            out_high[j, 0], out_high[j, 1], out_high[j, 2] = hi0, hi1, hi2
            out_rad[j, 0] = min(max(x0 / total, lo0), hi0)
            out_rad[j, 1] = min(max(x1 / total, lo1), hi1)
            out_rad[j, 2] = min(max(x2 / total, lo2), hi2)
            out_hit[j] = depth[p] * (1.0 / vhat - 1.0) if vhat > 0.0 else np.inf
            out_ok[j] = True
            continue
        # The tent window, read at the lattice's points first (the grid's, or the
        # checkerboard's of spacing q: ~4 of the 49 positions of a sixteenth's window),
        # at every position only when none of those is the reflector's (a rate's extra
        # traced pixels, an irregular subset).
        step = lat if lat > 0 else -lat
        for every in (False, True):
            stride = 1 if every else step
            y0 = r - radius + (0 if every else (phase[0] - (r - radius)) % step)
            xs = c - radius + (0 if every else (phase[1] - (c - radius)) % step)
            for guided in (True, False):
                total = x0 = x1 = x2 = vhat = 0.0
                lo0 = lo1 = lo2 = np.inf
                hi0 = hi1 = hi2 = -np.inf
                for y in range(y0, r + radius + 1, stride):
                    for x in range(xs, c + radius + 1, stride):
                        if not every and lat < 0 and \
                                ((y - phase[0]) // step + (x - phase[1]) // step) & 1:  # fmt: skip
                            continue  # off the checkerboard
                        dy, dx = y - r, x - c
                        at = _traced(table, traced_src, s, y, x, width, height)
                        if at < 0 or not (dy or dx):
                            continue
                        w = float((radius + 1 - abs(dy)) * (radius + 1 - abs(dx)))
                        if guided:
                            w *= _guide(nx, ny, nz, px, py, pz, traced_pix[at], normal,
                                        position)  # fmt: skip
                        if not w > 0.0:
                            continue
                        total += w
                        if v[at] == 0.0:  # a ray that left the scene: the sky (docstring)
                            sky_state = _sky(sky_state, p, fallback, local, reflectivity, sky)
                        if v[at] == 0.0 and sky_state > 0:
                            f0, f1, f2 = sky[0], sky[1], sky[2]
                        else:
                            f0, f1, f2 = radiance[at, 0], radiance[at, 1], radiance[at, 2]
                        x0, x1, x2 = x0 + w * f0, x1 + w * f1, x2 + w * f2
                        lo0, hi0 = min(lo0, f0), max(hi0, f0)
                        lo1, hi1 = min(lo1, f1), max(hi1, f1)
                        lo2, hi2 = min(lo2, f2), max(hi2, f2)
                        vhat += w * v[at]
                if total > 0.0:
                    out_rad[j, 0], out_rad[j, 1] = x0 / total, x1 / total
                    out_rad[j, 2] = x2 / total
                    out_low[j, 0], out_low[j, 1], out_low[j, 2] = lo0, lo1, lo2
                    out_high[j, 0], out_high[j, 1], out_high[j, 2] = hi0, hi1, hi2
                    vhat /= total
                    out_hit[j] = depth[p] * (1.0 / vhat - 1.0) if vhat > 0.0 else np.inf
                    out_ok[j] = True
                    break
            if out_ok[j]:
                break


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs of the types
    ``sparse_pixels`` passes."""
    i64, i32 = np.zeros(1, np.int64), np.full(4, -1, np.int32)
    v32, f32 = np.zeros((1, 3), np.float32), np.zeros(4, np.float32)
    v, d = np.zeros(1), np.zeros((1, 2, 3), np.float32)
    images = (np.ones((4, 3), np.float32), np.zeros((4, 3)))
    fill_table(i32, i64, f32[:1], f32, v)
    fill_curvature(i32, i64, i64, v32, v, i64 + 2, 2, 2, *images, 0, 1, d)
    raster = (np.zeros((4, 3), np.float32), np.zeros((4, 3), np.float32), f32)
    for fallback, local, reflectivity in (raster, (v32[:0], v32[:0], f32[:0])):
        fill_skipped(i32, i64, v32, v, d, i64, i64 + 1, i64, i64 + 2, np.zeros(2, np.int64), 2,
                     2, *images, f32, fallback, local, reflectivity, 0, 1, v32.copy(),
                     f32[:1].copy(), np.zeros(1, bool), v32.copy(), v32.copy())  # fmt: skip
    clear_table(i32, i64)
