"""The compiled per-pixel kernels of the render phase (numba, ``phrt_usd.kernels``): the
local shading model and the lat-long environment of ``shading``, the raster fallback of
``compositing``, the frame's reflector boxes and clipped share (``frame_pixels``), the
light pass's texel packing (``raster.light_pass``), the lights it looks up and its
undecided pairs (``raster.map_lighting``). Taken through ``phrt_usd.kernels.load`` on first use (by
those modules' functions), so that importing the renderer does not load numba; the
numpy-facing functions, their arguments, shapes and coordinate spaces are those
modules'. The constants of the model come in as arguments: the kernel cache is named
by the sources of ``kernels.SOURCE_MODULES`` only, which leave ``shading`` out. The
numpy form of these kernels, ``tests/shading_reference.py``, is checked against them in
``tests/engine/test_shading_kernels.py``.
"""

from __future__ import annotations

import math
import re

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS

_KERNEL = KERNEL_OPTIONS
_HELPER = {**_KERNEL, "inline": "always"}


@njit(**_KERNEL)
def dome_directions(directions, rotation, min_length, out):
    """World directions (n, 3) (any length) as unit directions (n, 3) float64 in the
    dome's space (``rotation`` = ``world_from_light`` (3, 3), a rotation: its inverse is
    its transpose); zero, shorter than ``min_length`` or non-finite ones become the
    dome's +Y pole."""
    for i in range(directions.shape[0]):
        x, y, z = float(directions[i, 0]), float(directions[i, 1]), float(directions[i, 2])
        big = max(abs(x), abs(y), abs(z))
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        if not (finite and big > min_length):  # no direction: the pole
            out[i, 0], out[i, 1], out[i, 2] = 0.0, 1.0, 0.0
            continue
        # Scaled by the largest component first so huge vectors do not overflow.
        x, y, z = x / big, y / big, z / big
        norm = math.sqrt(x * x + y * y + z * z)
        x, y, z = x / norm, y / norm, z / norm
        for c in range(3):
            out[i, c] = x * rotation[0, c] + y * rotation[1, c] + z * rotation[2, c]


@njit(**_KERNEL)
def latlong_bilinear(latitude, longitude, texture, colour, out):
    """Bilinear samples (n, 3) of the lat-long ``texture`` (h, w, 3) (the module's
    convention) at ``latitude``, ``longitude`` (n,) radians, times ``colour`` (3,):
    columns wrap, rows clamp at the poles."""
    h, wd = texture.shape[0], texture.shape[1]
    for i in range(latitude.shape[0]):
        col = (math.pi - longitude[i]) / (2.0 * math.pi) * wd - 0.5
        row = (0.5 * math.pi - latitude[i]) / math.pi * h - 0.5
        c0f, r0f = math.floor(col), math.floor(row)
        fx, fy = col - c0f, row - r0f
        # col in [-0.5, wd - 0.5] (longitude in [-pi, pi]): c0 in [-1, wd - 1].
        c0 = int(c0f)
        c0 = c0 + wd if c0 < 0 else c0
        c1 = c0 + 1 if c0 + 1 < wd else 0
        r0 = min(max(int(r0f), 0), h - 1)
        r1 = min(max(int(r0f) + 1, 0), h - 1)
        w00, w01 = (1.0 - fy) * (1.0 - fx), (1.0 - fy) * fx
        w10, w11 = fy * (1.0 - fx), fy * fx
        for c in range(3):
            v = texture[r0, c0, c] * w00 + texture[r0, c1, c] * w01
            v += texture[r1, c0, c] * w10 + texture[r1, c1, c] * w11
            out[i, c] = v * colour[c]


@njit(**_KERNEL)
def latlong_lookup(directions, rotation, min_length, texture, colour, out):
    """``dome_directions``, the angles and ``latlong_bilinear`` in one call, for small
    batches (``shading.ENV_ONE_PASS_MAX``): directions (n, 3), rotation (3, 3), texture
    (h, w, 3), colour (3,) as theirs; writes out (n, 3) float32. The angles by scalar
    libm calls, within 1e-15 rad of numpy's vectorised ones."""
    n = directions.shape[0]
    d = np.empty((n, 3))
    dome_directions(directions, rotation, min_length, d)
    latitude, longitude = np.empty(n), np.empty(n)
    for i in range(n):
        latitude[i] = math.asin(min(max(d[i, 1], -1.0), 1.0))
        longitude[i] = math.atan2(d[i, 0], d[i, 2])
    latlong_bilinear(latitude, longitude, texture, colour, out)


@njit(**_HELPER)
def window_at(distance2, light_range):
    """``range_window`` of one squared distance (metres²) and range (metres)."""
    if not light_range > 0.0:
        return 0.0
    x = distance2 / (light_range * light_range)
    w = min(max(1.0 - x * x, 0.0), 1.0)
    return w * w


@njit(**_KERNEL)
def window_kernel(distance, light_range, out):
    for i in range(distance.shape[0]):
        out[i] = window_at(distance[i] * distance[i], light_range)


@njit(**_HELPER)
def cone_at(cos, cone_angle, softness, focus):
    """``cone_falloff`` of one emission: ``cos`` the cosine between the light's axis and
    the direction it emits to the point; cone angle in degrees, softness, focus."""
    cos = min(max(cos, -1.0), 1.0)
    factor = 1.0
    if cone_angle < 180.0:
        theta = math.acos(cos)
        cutoff = math.radians(cone_angle)
        if theta > cutoff:
            return 0.0
        start = cutoff * (1.0 - softness)
        width = cutoff - start
        if width > 0.0:
            x = min(max((theta - start) / width, 0.0), 1.0)
            factor = 1.0 - x * x * (3.0 - 2.0 * x)
    if focus > 0.0:
        factor *= abs(cos) ** focus
    return factor


@njit(**_HELPER)
def light_share(power, lit, dist2, light_range, local, cone):
    """A light's unshadowed share of a point's direct light, by which the tracer samples
    lights at hits (``shadow_rays``): ``power`` (its brightest radiance channel) times
    ``lit`` (n·l of unit vectors); for a LocalLight (``local``) also its range window
    and 1/d² at ``dist2`` (metres², clamped to MIN_LIGHT_DISTANCE²) and ``cone``, its
    ``cone_at`` factor (1 unshaped). 0 where the light adds nothing."""
    if not (lit > 0.0 and power > 0.0):
        return 0.0
    if local:
        return power * lit * cone * window_at(dist2, light_range) / dist2
    return power * lit


@njit(**_HELPER)
def light_draws(share, weight, picks, u0):
    """The hit-lighting rule's choice of one point's shadow rays (``trace_kernels.
    shadow_rays``): share (L,) each light's ``light_share`` (< 0: no ray wanted), picks
    the rays the point may cast (0: every wanted one), u0 in [0, 1) its draws' offset;
    writes weight (L,): 0 for no ray, else the ray's weight (share is overwritten).
    Sampling (picks > 0) traces only lights of a positive share, each of weight 1 when
    there are at most ``picks``. With more, while two picks or more are left a light of
    at least the mean share per pick left is traced exactly (weight 1, largest first);
    the picks left are systematic draws over the other lights' shares from u0: a light
    of share s drawn c times out of S in all over p picks weighs c S / (p s), 1 in
    expectation (unbiased)."""
    n = share.shape[0]
    count, total = 0, 0.0
    for j in range(n):
        if picks > 0 and not share[j] > 0.0:
            share[j] = -1.0
        weight[j] = 1.0 if share[j] >= 0.0 else 0.0
        if share[j] >= 0.0:
            count, total = count + 1, total + share[j]
    left = picks
    while 1 < left < count:  # the dominant lights, exact (weight 1, out of the draws)
        big = np.argmax(share)
        if share[big] * left < total:
            break
        count, total, left, share[big] = count - 1, total - share[big], left - 1, -1.0
    if picks == 0 or count <= left:
        return
    last = -1  # the last light drawn from takes the draws rounding left over
    for j in range(n):
        last = j if share[j] >= 0.0 else last
    step = total / left
    mark, cum = u0 * step, 0.0
    for j in range(n):
        if share[j] < 0.0:  # no ray, or traced exactly
            continue
        cum += share[j]
        draws = 0
        while draws < left and (j == last or mark < cum):
            draws, mark = draws + 1, mark + step
        left -= draws
        weight[j] = draws * step / share[j]


@njit(**_KERNEL)
def cone_kernel(emission, axis, cone_angle, softness, focus, out):
    for i in range(emission.shape[0]):
        cos = emission[i, 0] * axis[0] + emission[i, 1] * axis[1] + emission[i, 2] * axis[2]
        out[i] = cone_at(cos, cone_angle, softness, focus)


@njit(**_HELPER)
def lut_albedo(lut, roughness, cosine):
    """(A, B) of ``preview_surface.specular_albedo_table`` ``lut`` (R, C + 1, 2) at
    ``roughness`` and ``cosine`` (n·v), bilinear between its nodes (clamped)."""
    n_r, n_c = lut.shape[0], lut.shape[1] - 1
    x = min(max(cosine, 0.0), 1.0) * (n_c - 1)
    y = min(max(roughness, 0.0), 1.0) * (n_r - 1)
    x0, y0 = min(int(x), n_c - 2), min(int(y), n_r - 2)
    fx, fy = x - x0, y - y0
    a = (lut[y0, x0, 0] * (1.0 - fx) + lut[y0, x0 + 1, 0] * fx) * (1.0 - fy)
    a += (lut[y0 + 1, x0, 0] * (1.0 - fx) + lut[y0 + 1, x0 + 1, 0] * fx) * fy
    b = (lut[y0, x0, 1] * (1.0 - fx) + lut[y0, x0 + 1, 1] * fx) * (1.0 - fy)
    b += (lut[y0 + 1, x0, 1] * (1.0 - fx) + lut[y0 + 1, x0 + 1, 1] * fx) * fy
    return a, b


@njit(**_HELPER)
def lut_mean(lut, roughness):
    """The cosine-weighted means (A, B) of ``lut``'s row at ``roughness`` (linear)."""
    n_r, c = lut.shape[0], lut.shape[1] - 1
    y = min(max(roughness, 0.0), 1.0) * (n_r - 1)
    y0 = min(int(y), n_r - 2)
    fy = y - y0
    a = lut[y0, c, 0] * (1.0 - fy) + lut[y0 + 1, c, 0] * fy
    b = lut[y0, c, 1] * (1.0 - fy) + lut[y0 + 1, c, 1] * fy
    return a, b


@njit(**_HELPER)
def put(ch, v, a, b, c):
    """(a, b, c) with channel ``ch`` (0, 1, 2) set to ``v``."""
    return (v, b, c) if ch == 0 else ((a, v, c) if ch == 1 else (a, b, v))


@njit(**_HELPER)
def ggx_dv(alpha, nl, nv, nh):
    """GGX D times the height-correlated Smith V = G / (4 n·l n·v) of ``alpha``."""
    a2 = alpha * alpha
    d = nh * nh * (a2 - 1.0) + 1.0
    v = nl * math.sqrt(nv * nv * (1.0 - a2) + a2) + nv * math.sqrt(nl * nl * (1.0 - a2) + a2)
    return a2 / (math.pi * d * d) * 0.5 / max(v, 1e-30)


@njit(**_HELPER)
def point_terms(s, i, nv, lut, min_rough):
    """What ``brdf_cos`` and ``ambient_weight`` read of point i's surface row ``s[i]``
    (``model.preview_surface`` columns) at n·v: (roughness, A(v), B(v), mean A, mean B,
    clear coat amount, its roughness, A_c(v), B_c(v), mean A_c, mean B_c)."""
    r = max(float(s[i, 9]), min_rough)
    av, bv = lut_albedo(lut, r, nv)
    am, bm = lut_mean(lut, r)
    c = float(s[i, 10])
    rc = max(float(s[i, 11]), min_rough)
    acv = bcv = acm = bcm = 0.0
    if c > 0.0:
        acv, bcv = lut_albedo(lut, rc, nv)
        acm, bcm = lut_mean(lut, rc)
    return r, av, bv, am, bm, c, rc, acv, bcv, acm, bcm


@njit(**_HELPER)
def brdf_cos(s, i, t, n0, n1, n2, e0, e1, e2, l0, l1, l2, nv, lut):
    """π f(l, v) n·l (RGB) of point i's UsdPreviewSurface BRDF (``model.preview_surface``
    states it) for unit normal n, direction to the eye e (n·e = ``nv``, clamped) and
    direction to the light l, with ``t`` its ``point_terms``: what a light of radiance E
    adds is E times this. 0 where n·l <= 0."""
    nl = n0 * l0 + n1 * l1 + n2 * l2
    if not nl > 0.0:
        return 0.0, 0.0, 0.0
    r, av, bv, am, bm, c, rc, acv, bcv, acm, bcm = t
    h0, h1, h2 = l0 + e0, l1 + e1, l2 + e2
    length = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
    # l and the eye direction exactly opposite: no half vector (n·l > 0 then means a
    # grazing eye); h = n keeps it finite.
    if length > 1e-12:
        h0, h1, h2 = h0 / length, h1 / length, h2 / length
    else:
        h0, h1, h2 = n0, n1, n2
    nh = max(n0 * h0 + n1 * h1 + n2 * h2, 0.0)
    vh = min(max(e0 * h0 + e1 * h1 + e2 * h2, 0.0), 1.0)
    s5 = (1.0 - vh) ** 5
    dv = ggx_dv(r * r, nl, nv, nh)
    al, bl = lut_albedo(lut, r, nl)
    coat = 0.0
    t_in = t_out = 1.0
    if c > 0.0:
        fc0 = float(s[i, 12])
        coat = c * (fc0 + (1.0 - fc0) * s5) * ggx_dv(rc * rc, nl, nv, nh)
        acl, bcl = lut_albedo(lut, rc, nl)
        t_out = 1.0 - c * min(fc0 * acv + bcv, 1.0)
        t_in = 1.0 - c * min(fc0 * acl + bcl, 1.0)
    out0 = out1 = out2 = 0.0
    for ch in range(3):
        f0, f90 = float(s[i, 3 + ch]), float(s[i, 6 + ch])
        ev = min(f0 * av + f90 * bv, 1.0)
        el = min(f0 * al + f90 * bl, 1.0)
        mean = min(f0 * am + f90 * bm, 1.0)
        diffuse = float(s[i, ch]) * (1.0 - ev) * (1.0 - el) / max(1.0 - mean, 1e-4)
        # π f n·l: the diffuse lobe's 1/π cancels.
        v = (coat + t_out * t_in * (f0 + (f90 - f0) * s5) * dv) * math.pi + t_out * t_in * diffuse
        v *= nl
        out0, out1, out2 = put(ch, v, out0, out1, out2)
    return out0, out1, out2


@njit(**_HELPER)
def ambient_weight(s, i, t, nv):
    """(RGB) what point i returns of a uniform environment of unit radiance
    (``model.preview_surface``): occlusion times the clear coat's and the base's
    directional albedo, the specular parts only where its ``specular ambient`` column
    is 1 (no mirror reflection stands in for them: ``reflection_weight``)."""
    r, av, bv, am, bm, c, rc, acv, bcv, acm, bcm = t
    occ, spec = float(s[i, 13]), float(s[i, 14])
    fc0 = float(s[i, 12])
    coat_v = c * min(fc0 * acv + bcv, 1.0)
    base = (1.0 - coat_v) * (1.0 - c * min(fc0 * acm + bcm, 1.0))
    out0 = out1 = out2 = 0.0
    for ch in range(3):
        f0, f90 = float(s[i, 3 + ch]), float(s[i, 6 + ch])
        ev = min(f0 * av + f90 * bv, 1.0)
        v = occ * (spec * coat_v + base * (spec * ev + float(s[i, ch]) * (1.0 - ev)))
        out0, out1, out2 = put(ch, v, out0, out1, out2)
    return out0, out1, out2


@njit(**_HELPER)
def reflection_weight(s, i, t):
    """(RGB) the weight of point i's mirror reflection: the specular parts of
    ``ambient_weight`` (split sum: the lobes' directional albedo at n·v), occlusion
    left out (an occlusion map darkens the ambient, not what a ray finds)."""
    r, av, bv, am, bm, c, rc, acv, bcv, acm, bcm = t
    fc0 = float(s[i, 12])
    coat_v = c * min(fc0 * acv + bcv, 1.0)
    base = (1.0 - coat_v) * (1.0 - c * min(fc0 * acm + bcm, 1.0))
    out0 = out1 = out2 = 0.0
    for ch in range(3):
        f0, f90 = float(s[i, 3 + ch]), float(s[i, 6 + ch])
        v = coat_v + base * min(f0 * av + f90 * bv, 1.0)
        out0, out1, out2 = put(ch, v, out0, out1, out2)
    return out0, out1, out2


@njit(**_KERNEL)
def brdf_kernel(surface, normals, to_eye, to_light, lut, min_rough, out):
    """``brdf_cos`` of n points (surface (n, 16) float32, normals, to_eye, to_light
    (n, 3) float64 unit) into out (n, 3) float64: the BRDF as the shading evaluates
    it, for tests and tools."""
    for i in range(surface.shape[0]):
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        e0, e1, e2 = to_eye[i, 0], to_eye[i, 1], to_eye[i, 2]
        nv = max(n0 * e0 + n1 * e1 + n2 * e2, 1e-4)
        t = point_terms(surface, i, nv, lut, min_rough)
        r, g, b = brdf_cos(surface, i, t, n0, n1, n2, e0, e1, e2,
                           to_light[i, 0], to_light[i, 1], to_light[i, 2], nv, lut)  # fmt: skip
        out[i, 0], out[i, 1], out[i, 2] = r, g, b


@njit(**_KERNEL)
def weights_kernel(surface, normals, to_eye, lut, min_rough, ambient, reflection):
    """``ambient_weight`` and ``reflection_weight`` (n, 3) float32 of n points (surface
    (n, 16) float32, normals and to_eye (n, 3) unit, float32 or float64)."""
    for i in range(surface.shape[0]):
        nv = normals[i, 0] * to_eye[i, 0] + normals[i, 1] * to_eye[i, 1]
        nv = max(nv + normals[i, 2] * to_eye[i, 2], 1e-4)
        t = point_terms(surface, i, nv, lut, min_rough)
        ambient[i, 0], ambient[i, 1], ambient[i, 2] = ambient_weight(surface, i, t, nv)
        reflection[i, 0], reflection[i, 1], reflection[i, 2] = reflection_weight(surface, i, t)


@njit(**_KERNEL)
def surface_rows(albedo, material, inputs, per_point, specular_ambient, out):
    """The surface rows (``model.preview_surface.surface_columns``) of n points into out
    (n, 16) float32: albedo (n, 3) float32 (diffuseColor), their inputs
    (``preview_surface.input_rows`` columns) ``inputs[material[i]]`` (material (n,)
    int64, clamped to the table) or, with ``per_point``, ``inputs[i]``;
    specular_ambient (n,) float32 or (0,): 1 for all."""
    m_rows = inputs.shape[0]
    every = specular_ambient.shape[0] == 0
    for i in range(albedo.shape[0]):
        k = i if per_point else min(max(material[i], 0), m_rows - 1)
        metallic, spec = float(inputs[k, 0]), inputs[k, 1] != 0.0
        r2 = float(inputs[k, 8])
        for c in range(3):
            a = max(float(albedo[i, c]), 0.0)
            if not a == a:  # NaN albedo: black
                a = 0.0
            colour = min(a, 1.0)
            if spec:
                out[i, c], out[i, 3 + c], out[i, 6 + c] = a, inputs[k, 2 + c], 1.0
            else:
                out[i, c] = a * (1.0 - metallic)
                out[i, 3 + c] = r2 + (colour - r2) * metallic
                out[i, 6 + c] = 1.0 + (colour - 1.0) * metallic
        out[i, 9], out[i, 10], out[i, 11] = inputs[k, 5], inputs[k, 6], inputs[k, 7]
        out[i, 12], out[i, 13] = r2, inputs[k, 9]
        out[i, 14] = 1.0 if every else specular_ambient[i]
        out[i, 15] = 0.0


#: Consecutive points ``shade_kernel`` culls LocalLights for at once (G-buffer pixels
#: in row order, a tracer's hits: neighbours, mostly): a block walks only the lights
#: reaching its bounding box (``block_lights``), so a point costs by the lights that
#: reach it, not the stage's. 32 points, 64 lights: two box tests a point.
CULL_BLOCK_POINTS = 32


@njit(**_HELPER)
def box_lights(lo, hi, centres, ranges, margin, out):
    """The lights (centres (P, 3), ranges (P,) metres) whose range plus ``margin``
    reaches the box ``lo``..``hi`` (3,), in increasing order into out (P,) int64;
    returns their count. With no margin exact, not conservative: a light left out has,
    for every point in the box, a squared distance at least its range² also in float64
    (each axis gap of the box is at most the point's, rounded the same way). A NaN box
    keeps every light (the points' own tests decide)."""
    count = 0
    for k in range(centres.shape[0]):
        d2 = 0.0
        for c in range(3):
            e = max(lo[c] - centres[k, c], 0.0, centres[k, c] - hi[c])
            d2 += e * e
        reach = ranges[k] + margin
        if ranges[k] > 0.0 and not d2 >= reach * reach:
            out[count] = k
            count += 1
    return count


@njit(**_HELPER)
def block_lights(positions, start, stop, l_pos, l_range, box, out):
    """``box_lights`` (no margin) of the bounding box of positions[start:stop]; box
    (2, 3) float64 scratch."""
    for c in range(3):
        box[0, c] = box[1, c] = positions[start, c]
        for i in range(start + 1, stop):
            box[0, c], box[1, c] = min(box[0, c], positions[i, c]), max(box[1, c], positions[i, c])
    return box_lights(box[0], box[1], l_pos, l_range, 0.0, out)


@njit(**_KERNEL)
def shade_kernel(
    positions, normals, surface, view_dirs, emissive, ambient, sum_direct, d_dir, d_radiance,
    visibility, l_pos, l_radiance, l_range, l_cone, local_columns, p_point, p_light, p_dir,
    p_dist, p_weight, has_weight, model, lut, out,
):  # fmt: skip
    """The shading model of the module docstring, per point (see ``shade_local``).

    positions (n, 3) float64 world metres; normals, view_dirs (n, 3) float32; surface
    (n, 16) float32 (``model.preview_surface`` columns); emissive (1 or n, 3); ambient
    (3,); sum_direct (n, 3 or 4) or (0, 3): ``lit_sums``, the direct light of pairs
    shaded elsewhere; d_dir (D, 3) unit, d_radiance (D, 3); visibility (n, D + P) or
    (0, 0): all lit; l_pos (P, 3) world metres, l_radiance (P, 3), l_range (P,) metres,
    l_cone (P, 7) (axis, cone angle, softness, focus, shaped); local_columns: shade
    every LocalLight from its visibility column (else only the pairs); pairs p_point
    (m,), p_light (m,), p_dir (m, 3) unit, p_dist (m,) metres, p_weight (m,) if
    has_weight; model (4,) float64: the shading module's MIN_LIGHT_DISTANCE, the
    preview surface's MIN_ROUGHNESS and MIN_COSINE, 0; lut its albedo table. Writes out
    (n, 3) float32. Sums in float64 per point."""
    n = positions.shape[0]
    n_distant = d_dir.shape[0]
    has_vis = visibility.shape[0] > 0
    has_sums = sum_direct.shape[0] > 0
    one_emissive = emissive.shape[0] == 1
    min_d2 = model[0] * model[0]
    min_rough, min_cos = model[1], model[2]
    reach = np.empty(l_pos.shape[0], np.int64)  # the LocalLights reaching the block
    block_end, n_reach, box = 0, 0, np.empty((2, 3))
    for i in range(n):
        n0, n1, n2 = float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])
        e0, e1, e2 = -float(view_dirs[i, 0]), -float(view_dirs[i, 1]), -float(view_dirs[i, 2])
        nv = max(n0 * e0 + n1 * e1 + n2 * e2, min_cos)
        t = point_terms(surface, i, nv, lut, min_rough)
        em = 0 if one_emissive else i
        a0, a1, a2 = ambient_weight(surface, i, t, nv)
        d0 = a0 * ambient[0] + emissive[em, 0]
        d1 = a1 * ambient[1] + emissive[em, 1]
        d2 = a2 * ambient[2] + emissive[em, 2]
        for j in range(n_distant):
            vis = visibility[i, j] if has_vis else 1.0
            if not vis > 0.0:
                continue
            f0, f1, f2 = brdf_cos(surface, i, t, n0, n1, n2, e0, e1, e2,
                                  d_dir[j, 0], d_dir[j, 1], d_dir[j, 2], nv, lut)  # fmt: skip
            d0 += d_radiance[j, 0] * vis * f0
            d1 += d_radiance[j, 1] * vis * f1
            d2 += d_radiance[j, 2] * vis * f2
        if local_columns and i >= block_end:  # the next block's LocalLights
            block_end = min(i + CULL_BLOCK_POINTS, n)
            n_reach = block_lights(positions, i, block_end, l_pos, l_range, box, reach)
        for q in range(n_reach if local_columns else 0):
            k = reach[q]
            vis = visibility[i, n_distant + k] if has_vis else 1.0
            if not vis > 0.0:
                continue
            t0 = l_pos[k, 0] - positions[i, 0]
            t1 = l_pos[k, 1] - positions[i, 1]
            t2 = l_pos[k, 2] - positions[i, 2]
            dist2 = t0 * t0 + t1 * t1 + t2 * t2
            # Beyond the range (or non-finite) the window is 0: nothing to add, and no
            # direction computed from an overflowed distance.
            if not dist2 < l_range[k] * l_range[k]:
                continue
            dist2 = max(dist2, min_d2)
            inv = 1.0 / math.sqrt(dist2)
            l0, l1, l2 = t0 * inv, t1 * inv, t2 * inv
            if not n0 * l0 + n1 * l1 + n2 * l2 > 0.0:
                continue
            e = window_at(dist2, l_range[k]) / dist2 * vis
            if l_cone[k, 6] > 0.0:
                cos = -(l0 * l_cone[k, 0] + l1 * l_cone[k, 1] + l2 * l_cone[k, 2])
                e *= cone_at(cos, l_cone[k, 3], l_cone[k, 4], l_cone[k, 5])
            f0, f1, f2 = brdf_cos(surface, i, t, n0, n1, n2, e0, e1, e2, l0, l1, l2, nv, lut)
            d0 += l_radiance[k, 0] * e * f0
            d1 += l_radiance[k, 1] * e * f1
            d2 += l_radiance[k, 2] * e * f2
        if has_sums:
            d0, d1, d2 = d0 + sum_direct[i, 0], d1 + sum_direct[i, 1], d2 + sum_direct[i, 2]
        out[i, 0], out[i, 1], out[i, 2] = d0, d1, d2
    for q in range(p_point.shape[0]):  # lit LocalLight pairs, any order
        i, k = p_point[q], p_light[q]
        l0, l1, l2 = float(p_dir[q, 0]), float(p_dir[q, 1]), float(p_dir[q, 2])
        n0, n1, n2 = float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])
        if not n0 * l0 + n1 * l1 + n2 * l2 > 0.0:
            continue
        dist2 = max(p_dist[q] * p_dist[q], min_d2)
        e = window_at(dist2, l_range[k]) / dist2
        if has_weight:
            e *= p_weight[q]
        if l_cone[k, 6] > 0.0:
            cos = -(l0 * l_cone[k, 0] + l1 * l_cone[k, 1] + l2 * l_cone[k, 2])
            e *= cone_at(cos, l_cone[k, 3], l_cone[k, 4], l_cone[k, 5])
        e0, e1, e2 = -float(view_dirs[i, 0]), -float(view_dirs[i, 1]), -float(view_dirs[i, 2])
        nv = max(n0 * e0 + n1 * e1 + n2 * e2, min_cos)
        t = point_terms(surface, i, nv, lut, min_rough)
        f0, f1, f2 = brdf_cos(surface, i, t, n0, n1, n2, e0, e1, e2, l0, l1, l2, nv, lut)
        out[i, 0] += l_radiance[k, 0] * e * f0
        out[i, 1] += l_radiance[k, 1] * e * f1
        out[i, 2] += l_radiance[k, 2] * e * f2


@njit(**_KERNEL)
def fallback_rays(covered, reflectivity, view, normal, background):
    """The pixels whose colour comes from the environment: (m,) int64 flat indices of
    the reflector pixels (F > 0) and, with ``background``, the uncovered ones, and their
    (m, 3) float32 world directions (the view direction mirrored about the normal,
    ``reflect``; the view direction itself). covered (P,) bool, reflectivity (P,), view
    and normal (P, 3) of the P = H W pixels."""
    m = 0
    for i in range(covered.shape[0]):
        if reflectivity[i] > 0.0 or (background and not covered[i]):
            m += 1
    pixels = np.empty(m, np.int64)
    directions = np.empty((m, 3), np.float32)
    q = 0
    for i in range(covered.shape[0]):
        if reflectivity[i] > 0.0:
            dn = 2.0 * (
                view[i, 0] * normal[i, 0] + view[i, 1] * normal[i, 1] + view[i, 2] * normal[i, 2]
            )
            for c in range(3):
                directions[q, c] = view[i, c] - dn * normal[i, c]
        elif background and not covered[i]:
            for c in range(3):
                directions[q, c] = view[i, c]
        else:
            continue
        pixels[q] = i
        q += 1
    return pixels, directions


@njit(**_KERNEL)
def blend(local, reflectivity, pixels, env, out):
    """out (P, 3) = local (P, 3), except at ``pixels`` (m,): ``(1 - F) local + F env``
    for reflector pixels, ``env`` (m, 3) for the background (F = 0 there, local 0)."""
    out[:] = local
    for q in range(pixels.shape[0]):
        i = pixels[q]
        f = reflectivity[i]
        for c in range(3):
            out[i, c] = (1.0 - f) * local[i, c] + f * env[q, c] if f > 0.0 else env[q, c]


@njit(**_KERNEL)
def pair_directions(
    centres, positions, point, light, min_distance, l_dir, dist
):
    """``shading.pair_directions``: for m pairs, the unit direction l_dir (m, 3)
    float32 and distance dist (m,) (clamped to ``min_distance``) from
    ``positions[point]`` to ``centres[light]`` (world metres)."""
    for q in range(point.shape[0]):
        i, k = point[q], light[q]
        t0 = centres[k, 0] - positions[i, 0]
        t1 = centres[k, 1] - positions[i, 1]
        t2 = centres[k, 2] - positions[i, 2]
        d = max(math.sqrt(t0 * t0 + t1 * t1 + t2 * t2), min_distance)
        l_dir[q, 0], l_dir[q, 1], l_dir[q, 2] = t0 / d, t1 / d, t2 / d
        dist[q] = d


@njit(**_KERNEL)
def screen_box_bounds(element_id, index, n_reflectors):
    """(R, 4) int64 (col_min, row_min, col_max, row_max) of the pixels whose element has
    reflector index ``index[id]`` >= 0; col_max -1 for a reflector without pixels."""
    h, w = element_id.shape
    found = np.empty((n_reflectors, 4), np.int64)
    found[:, 0], found[:, 1], found[:, 2], found[:, 3] = w, h, -1, -1
    for row in range(h):
        for col in range(w):
            e = element_id[row, col]
            if e < 0:
                continue
            k = index[e]
            if k < 0:
                continue
            found[k, 0] = min(found[k, 0], col)
            found[k, 1] = min(found[k, 1], row)
            found[k, 2] = max(found[k, 2], col)
            found[k, 3] = max(found[k, 3], row)
    return found


@njit(**_KERNEL)
def clipped_counts(image, covered, step, level):
    """(covered, clipped) pixel counts of ``clipped_share``."""
    covered_n = clipped_n = 0
    for row in range(0, image.shape[0], step):
        for col in range(0, image.shape[1], step):
            if not covered[row, col]:
                continue
            covered_n += 1
            r, g, b = image[row, col, 0], image[row, col, 1], image[row, col, 2]
            if r != r or g != g or b != b:  # NaN: numpy's max would be NaN, not > level
                continue
            if max(r, g, b) > level:
                clipped_n += 1
    return covered_n, clipped_n


@njit(**_KERNEL)
def pack_texels(data, minus, out):
    """``data`` (n, 3) (less ``minus`` (3,), in float64, if given) as float32 texels
    into ``out`` (>= n, 3); the rows after n (the last texture row's rest) are 0."""
    n = data.shape[0]
    for i in range(n):
        for c in range(3):
            v = float(data[i, c])
            if minus is not None:
                v -= minus[c]
            out[i, c] = v
    out[n:] = 0.0


@njit(**_KERNEL)
def lit_local_pairs(rows, unsure, exact):
    """The undecided LocalLight pairs an exact test found lit, in point order: point
    (k,) int64 (of ``rows`` (m,)), light (k,) int64 and weight (k,) float32 in (0, 1],
    from ``unsure`` (m, P) bool and the test's ``exact`` (m, P) visibility."""
    k = 0
    for r in range(unsure.shape[0]):
        for j in range(unsure.shape[1]):
            if unsure[r, j] and exact[r, j] > 0.0:
                k += 1
    point = np.empty(k, np.int64)
    light = np.empty(k, np.int64)
    weight = np.empty(k, np.float32)
    k = 0
    for r in range(unsure.shape[0]):
        for j in range(unsure.shape[1]):
            if unsure[r, j] and exact[r, j] > 0.0:
                point[k], light[k], weight[k] = rows[r], j, exact[r, j]
                k += 1
    return point, light, weight


@njit(**_KERNEL)
def undecided_rows(bits, n_local, slots, per_pass, gpu_distant, distant_unsure, point_tile):
    """The points with a pair the maps could not decide, from the GPU lookup's ``bits``
    (n, passes) uint32: bit j of pass p is LocalLight ``slots[point_tile[i], per_pass p +
    j]`` of point i's tile (point_tile (n,) int32; slots (T, S) int64, ``tile_lights``),
    bit 16 + k of pass 0 DistantLight k when ``gpu_distant``, written into
    ``distant_unsure`` (n, D) bool (else that array holds the numpy lookups' answer).
    Returns rows (m,) int64 and their undecided LocalLight pairs (m, n_local) bool."""
    n, passes = bits.shape
    rows = np.empty(n, np.int64)
    m = 0
    for i in range(n):  # branch-free: row i is kept by counting it
        any_bit = False
        for p in range(passes):
            any_bit = any_bit or bits[i, p] != 0
        for k in range(distant_unsure.shape[1]):
            if gpu_distant:
                distant_unsure[i, k] = (bits[i, 0] >> (16 + k)) & 1 != 0
            any_bit = any_bit or distant_unsure[i, k]
        rows[m] = i
        m += any_bit
    rows = rows[:m].copy()
    local = np.zeros((m, n_local), np.bool_)
    for r in range(m):
        t = point_tile[rows[r]]
        for p in range(passes):
            word, s = bits[rows[r], p] & 0xFFFF, p * per_pass  # bits 16 + k: distant
            while word != 0 and s < slots.shape[1]:
                if word & 1 and slots[t, s] >= 0:
                    local[r, slots[t, s]] = True
                word, s = word >> 1, s + 1
    return rows, local


@njit(**_KERNEL)
def tile_lights(points, offset, tile, jump, centres, ranges, margin, point_tile):
    """Each tile's LocalLights, for the light pass: points (n, 3) float64 metres less
    ``offset`` (3,) (the rel space of ``centres`` (P, 3); ranges (P,) metres) cut into
    tiles of at most ``tile`` consecutive points, a tile also ending where the next
    point is more than ``jump`` times the tile's longest step away (a row's end, an
    edge in depth: its box stays near its points), while tiles average ``tile`` / 2
    points or more; a tile's lights are ``box_lights`` of its points' box. Writes each
    point's tile into point_tile (n,) int32; returns slots (T, P) int64 (each tile's
    lights in increasing order, then -1) and counts (T,) int64."""
    n = points.shape[0]
    starts = np.empty(n + 1, np.int64)
    t, step2, longest = 0, 0.0, 0.0
    for i in range(n):
        if i > 0:
            step2 = 0.0
            for c in range(3):
                step2 += (points[i, c] - points[i - 1, c]) ** 2
        size = i - starts[t - 1] if t else 0
        if t == 0 or size >= tile or (
            size >= 2 and step2 > jump * jump * longest and t * tile < 2 * n
        ):
            starts[t], t, longest = i, t + 1, 0.0
        elif step2 > longest:
            longest = step2
        point_tile[i] = t - 1
    starts[t] = n
    slots = np.full((t, centres.shape[0]), -1, np.int64)
    counts = np.zeros(t, np.int64)
    box = np.empty((2, 3))
    for k in range(t):
        for c in range(3):
            box[0, c] = box[1, c] = points[starts[k], c] - offset[c]
            for i in range(starts[k] + 1, starts[k + 1]):
                v = points[i, c] - offset[c]
                box[0, c], box[1, c] = min(box[0, c], v), max(box[1, c], v)
        counts[k] = box_lights(box[0], box[1], centres, ranges, margin, slots[k])
    return slots, counts


#: The argument types each kernel is compiled for (``warm_up``), as the render phase
#: passes them: ``phrt kernels`` compiles exactly these. A scalar type name or an
#: array ``dtype[:, ::1]`` (C-contiguous, one ``:`` per dimension), ``none`` for an
#: optional array left out.
SIGNATURES = {
    "dome_directions": ["f4[:, ::1], f8[:, ::1], f8, f8[:, ::1]",
                        "f8[:, ::1], f8[:, ::1], f8, f8[:, ::1]"],
    "latlong_bilinear": ["f8[::1], f8[::1], f4[:, :, ::1], f8[::1], f4[:, ::1]"],
    "latlong_lookup": [
        "f4[:, ::1], f8[:, ::1], f8, f4[:, :, ::1], f8[::1], f4[:, ::1]",
        "f8[:, ::1], f8[:, ::1], f8, f4[:, :, ::1], f8[::1], f4[:, ::1]",
    ],
    "window_kernel": ["f8[::1], f8, f8[::1]"],
    "cone_kernel": ["f8[:, ::1], f8[::1], f8, f8, f8, f4[::1]"],
    "shade_kernel": [
        "f8[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], f8[::1], f4[:, ::1], "
        "f8[:, ::1], f8[:, ::1], f4[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], "
        "f8[:, ::1], b1, i8[::1], i8[::1], f4[:, ::1], f8[::1], f4[::1], b1, f8[::1], "
        "f4[:, :, ::1], f4[:, ::1]"
    ],
    "brdf_kernel": ["f4[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f4[:, :, ::1], f8, "
                    "f8[:, ::1]"],
    "weights_kernel": ["f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, :, ::1], f8, f4[:, ::1], "
                       "f4[:, ::1]",
                       "f4[:, ::1], f8[:, ::1], f8[:, ::1], f4[:, :, ::1], f8, f4[:, ::1], "
                       "f4[:, ::1]"],
    "surface_rows": ["f4[:, ::1], i8[::1], f4[:, ::1], b1, f4[::1], f4[:, ::1]"],
    "fallback_rays": ["b1[::1], f4[::1], f4[:, ::1], f4[:, ::1], b1"],
    "blend": ["f4[:, ::1], f4[::1], i8[::1], f4[:, ::1], f4[:, ::1]"],
    "pair_directions": ["f8[:, ::1], f8[:, ::1], i8[::1], i8[::1], f8, f4[:, ::1], f8[::1]"],
    "screen_box_bounds": ["i4[:, ::1], i8[::1], i8"],
    "clipped_counts": ["f4[:, :, ::1], b1[:, ::1], i8, f8"],
    "pack_texels": ["f8[:, ::1], f8[::1], f4[:, ::1]", "f4[:, ::1], none, f4[:, ::1]",
                    "f8[:, ::1], none, f4[:, ::1]"],
    "lit_local_pairs": ["i8[::1], b1[:, ::1], f4[:, ::1]"],
    "undecided_rows": ["u4[:, ::1], i8, i8[:, ::1], i8, b1, b1[:, ::1], i4[::1]"],
    "tile_lights": ["f8[:, ::1], f8[::1], i8, f8, f8[:, ::1], f8[::1], f8, i4[::1]"],
}


_SCALARS = {"f8": "float64", "f4": "float32", "i8": "int64", "i4": "int32", "u4": "uint32",
            "b1": "boolean", "none": "none"}  # fmt: skip


def _numba_type(text: str):
    """The numba type of one SIGNATURES entry, e.g. ``f4[:, ::1]`` or ``i8``."""
    from numba.core import types

    name, _, dims = text.strip().partition("[")
    scalar = getattr(types, _SCALARS[name])
    if not dims:
        return scalar
    return types.Array(scalar, dims.count(":") - dims.count("::1"), "C")


def warm_up() -> None:
    """Compile every kernel for its SIGNATURES (or load them from phrt's kernel cache)."""
    for name, signatures in SIGNATURES.items():
        for signature in signatures:
            args = re.findall(r"\w+(?:\[[^\]]*\])?", signature)  # "f4[:, ::1]" stays one
            globals()[name].compile(tuple(_numba_type(t) for t in args))
