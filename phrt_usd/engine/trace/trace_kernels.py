"""The trace phase compiled: the per-ray loops around Embree of ``tracer`` and ``paths``.

A hybrid round is small (farm: 50-8,000 rays), so as numpy its time went to dozens of
array passes and temporaries per bounce rather than to Embree. Here each step is one
loop per ray, compiled by numba (``nogil``: callers may run them on their own pools;
numba's ``parallel`` is not used, its threading layer is not safe for concurrent
callers), writing into buffers the caller allocates:

- ``source_rays``: G-buffer pixels of the chosen sources → snapped rel positions,
  normals, view directions, and (for reflections) the mirror direction and the offset
  float32 origin of the first ray;
- ``offset_origins``: the ray-origin offset rule (``bvh.Float32Boundary``) with the
  float32 cast of the result;
- ``gather_spans``: the pixels of several sources, one slice each, and their source;
- ``split_hits``: Embree's answer → hit rows and miss rows (``bvh.Hits``);
- ``start_rays`` / ``bounce``: the first rays into the bounce loop's buffers; one
  depth of the bounce loop from Embree's answers of both BVHs — the
  surface at the hits, environment entries of misses, the local-shading entries,
  reflector keys, the reflector chains, and the children (mirror and refracted rays
  with their offset origins), appended to the caller's call-long buffers;
- ``accumulate``: the gathered radiance summed per pixel;
- ``hit_distances``: how far the first rays went (a guide of the reduced densities'
  fill, ``sparse_pixels``; the fill itself is ``fill_kernels``);
- ``source_tallies``: the per-source figures of ``TraceRecord``;
- ``shadow_rays`` / ``shadow_results``: the shadow rays of (point, light) pairs, and
  visibility and the lit LocalLight pairs from Embree's answer; ``shadow_shade``: those
  results shaded at once (``shade_kernels.shade_kernel``);
- ``primary_rays`` / ``primary_fill``: the ``rt`` mode's pixel rays (the raster
  G-buffer's direction rule, ``surface_kernels._pixel_dir``) and its G-buffer rows.

Numpy forms of these loops are the tests' reference (``tests/engine/test_trace_kernels.py``):
same operations in the same precision (float64 positions and offsets, float32
directions and shading normals), so results agree to the rounding of a sum's order.

Array arguments are read and written only in the kernels themselves (numba counts the
references of an array handed to another compiled function); the helpers take and
return scalars. Kernels return counts, never arrays (boxing a returned array costs ~1
us, more than a small kernel's work). Spaces: rel = world metres minus
``Scene.origin`` (float64).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.engine.shade_kernels import cone_at, light_draws, light_share, shade_kernel
from phrt_usd.engine.trace.bounce_layout import (
    G_ENV_DIR,
    G_ENV_SLOT,
    G_ENV_W,
    G_KEY,
    G_LIT_ALBEDO,
    G_LIT_DIR,
    G_LIT_NG,
    G_LIT_NS,
    G_LIT_POS,
    G_LIT_SLOT,
    G_LIT_SRC,
    G_LIT_TRI,
    G_LIT_U,
    G_LIT_V,
    G_LIT_W,
    RAY_CHAIN,
    RAY_DIR,
    RAY_ORIGIN,
    RAY_REFRACTED,
    RAY_SLOT,
    RAY_SRC,
    T_ENV,
    T_KEYS,
    T_LIT,
    T_SOURCES,
    T_TEXTURED,
    TRI_ALPHA,
    TRI_F,
    TRI_IOR,
    TRI_REFLECTOR,
    TRI_TEXTURED,
)
from phrt_usd.kernels import KERNEL_OPTIONS
from phrt_usd.model.surface import TERMINATOR_FADE
from phrt_usd.model.surface_kernels import (
    _inside,
    _orient,
    _pixel_dir,
    _smooth_lift,
    _weighted,
)

_KERNEL = KERNEL_OPTIONS
_HELPER = {**_KERNEL, "inline": "always"}

_ZERO32 = np.float32(0.0)
_ONE32 = np.float32(1.0)
_TWO32 = np.float32(2.0)


@njit(**_HELPER)
def _unit32(x, y, z):
    """(x, y, z) float32 scaled to unit length in float32 (``paths.unit``: a zero
    vector stays zero)."""
    length = np.float32(math.sqrt(x * x + y * y + z * z))
    if not (length > _ZERO32):
        length = _ONE32
    return x / length, y / length, z / length


@njit(**_HELPER)
def _unit64(x, y, z):
    """(x, y, z) float64 scaled to unit length (a zero vector stays zero)."""
    length = math.sqrt(x * x + y * y + z * z)
    if not (length > 0.0):
        length = 1.0
    return x / length, y / length, z / length


@njit(**_HELPER)
def _answer(r, prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map, animated, mapped):
    """Ray r's hit in Embree's answer merged by ``bvh.Bvh.merge``'s rule (the animated
    BVH's hit where it has one: only nearer hits are kept there): (global triangle id,
    barycentrics w1, w2), the id -1 for a miss."""
    if animated and far_prim[r] >= 0:
        return dynamic_map[far_prim[r]], far_u[r], far_v[r]
    if prim[r] >= 0:
        return (static_map[prim[r]] if mapped else np.int64(prim[r])), u[r], v[r]
    return np.int64(-1), u[r], v[r]


@njit(**_HELPER)
def _epsilon(px, py, pz, floor, relative):
    """The offset epsilon at rel (px, py, pz) (``Float32Boundary.epsilon``): max(floor,
    relative * largest |coordinate|), float64 metres."""
    largest = max(max(abs(px), abs(py)), abs(pz))
    return max(floor, relative * largest)


@njit(**_HELPER)
def _side(eps, dx, dy, dz, nx, ny, nz):
    """+eps when the direction leaves on the normal's side (d·n ≥ 0, float64), else
    -eps (``Float32Boundary.offset``)."""
    return eps if float(dx) * nx + float(dy) * ny + float(dz) * nz >= 0.0 else -eps


@njit(**_KERNEL)
def offset_origins(rel, normals, dirs, floor, relative, out):
    """Ray origins off their surface (``Float32Boundary.offset``), cast to float32.

    rel (n, 3) float64 positions; normals (n, 3) float64 unit geometric normals; dirs
    (n, 3) the directions the rays leave along; floor, relative: the epsilon's absolute
    part (metres) and relative factor. Writes out (n, 3) float32."""
    for i in range(rel.shape[0]):
        px, py, pz = rel[i, 0], rel[i, 1], rel[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        s = _side(_epsilon(px, py, pz, floor, relative), dirs[i, 0], dirs[i, 1], dirs[i, 2],
                  nx, ny, nz)  # fmt: skip
        out[i, 0], out[i, 1], out[i, 2] = px + s * nx, py + s * ny, pz + s * nz


@njit(**_KERNEL)
def source_rays(
    cand, tri_img, pos_img, nrm_img, view_img, origin, frame, floor, relative, lo, hi,
    out_tri, out_rel, out_ng, out_ns, out_view, out_dir, out_org,
):  # fmt: skip
    """The first rays of paths from G-buffer pixels cand[lo:hi] into rows lo..hi.

    cand (k,) int64 flat pixels of sources. Images flat over H*W: tri_img int32, pos_img
    (·, 3) float64 world, nrm_img and view_img (·, 3) float32. origin (3,)
    ``Scene.origin``; frame ``TriangleTable.frame``; floor, relative: the offset epsilon
    (``Float32Boundary``).

    Per pixel: out_tri (k,) int64. The surface, written when out_rel has rows: out_rel
    (k, 3) float64 the position snapped onto its triangle's plane; out_ng (k, 3) float64
    the triangle's unit front normal (the shading normal where there is no triangle);
    out_ns (k, 3) float32 the unit shading normal turned to face the viewer; out_view
    (k, 3) float32 unit view direction. The mirror ray, written when out_dir has rows:
    out_dir (k, 3) float32 the mirror direction and out_org (k, 3) float32 its offset
    origin."""
    surface = out_rel.shape[0] > 0
    reflect = out_dir.shape[0] > 0
    for i in range(lo, hi):
        p = cand[i]
        t = np.int64(tri_img[p])
        vx, vy, vz = _unit32(view_img[p, 0], view_img[p, 1], view_img[p, 2])
        nx, ny, nz = _unit32(nrm_img[p, 0], nrm_img[p, 1], nrm_img[p, 2])
        if nx * vx + ny * vy + nz * vz > _ZERO32:
            nx, ny, nz = -nx, -ny, -nz
        px = pos_img[p, 0] - origin[0]
        py = pos_img[p, 1] - origin[1]
        pz = pos_img[p, 2] - origin[2]
        if t >= 0:  # onto the triangle's plane (``HitSurfaces.snap``)
            gx, gy, gz = frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2]
            ox, oy, oz = px - frame[t, 0, 0], py - frame[t, 0, 1], pz - frame[t, 0, 2]
            dist = ox * gx + oy * gy + oz * gz
            px = ox - dist * gx + frame[t, 0, 0]
            py = oy - dist * gy + frame[t, 0, 1]
            pz = oz - dist * gz + frame[t, 0, 2]
        else:
            gx, gy, gz = float(nx), float(ny), float(nz)
        out_tri[i] = t
        if surface:
            out_rel[i, 0], out_rel[i, 1], out_rel[i, 2] = px, py, pz
            out_ng[i, 0], out_ng[i, 1], out_ng[i, 2] = gx, gy, gz
            out_ns[i, 0], out_ns[i, 1], out_ns[i, 2] = nx, ny, nz
            out_view[i, 0], out_view[i, 1], out_view[i, 2] = vx, vy, vz
        if reflect:
            k = _TWO32 * (vx * nx + vy * ny + vz * nz)
            dx, dy, dz = _unit32(vx - k * nx, vy - k * ny, vz - k * nz)
            out_dir[i, 0], out_dir[i, 1], out_dir[i, 2] = dx, dy, dz
            e = _side(_epsilon(px, py, pz, floor, relative), dx, dy, dz, gx, gy, gz)
            out_org[i, 0], out_org[i, 1], out_org[i, 2] = px + e * gx, py + e * gy, pz + e * gz


@njit(**_KERNEL)
def gather_spans(pixels, spans, out_pix, out_src):
    """Slices of ``pixels`` (m,) int64 one after the other into out_pix, each row's
    ``spans`` (S, 3) int64 (start, stop, value) value into out_src (both (k,) int64,
    k the slices' total length)."""
    at = 0
    for j in range(spans.shape[0]):
        for p in range(spans[j, 0], spans[j, 1]):
            out_pix[at] = pixels[p]
            out_src[at] = spans[j, 2]
            at += 1


@njit(**_KERNEL)
def split_hits(prim, u, v, out_ray, out_tri, out_u, out_v, out_miss):
    """Embree's answer for n rays (prim (n,) int32 / int64 triangle or < 0, u, v (n,)
    float32) into hit rows (out_ray, out_tri (n,) int64, out_u, out_v (n,) float32) and
    miss rows (out_miss (n,) int64). Returns the hit count h (the misses: n - h)."""
    h = 0
    m = 0
    for i in range(prim.shape[0]):
        t = prim[i]
        if t >= 0:
            out_ray[h], out_tri[h], out_u[h], out_v[h] = i, t, u[i], v[i]
            h += 1
        else:
            out_miss[m] = i
            m += 1
    return h


@njit(**_KERNEL)
def start_rays(src, dirs, origins, refracted, rays_i, rays_w, rays_v):
    """The first rays of ``paths.PathTracer.run`` into live half 0 of ``bounce``'s
    buffers (rays_i, rays_w, rays_v, ``RAY_*`` rows): ray i starts pixel slot i of
    source src[i] (k,) int64, weight 1, no reflector chain yet, ``refracted`` 0 / 1,
    along dirs (k, 3) float32 from origins (k, 3) float32 (already offset)."""
    for i in range(src.shape[0]):
        rays_i[0, RAY_SLOT, i], rays_i[0, RAY_SRC, i] = i, src[i]
        rays_i[0, RAY_CHAIN, i], rays_i[0, RAY_REFRACTED, i] = 0, refracted
        rays_w[0, i] = 1.0
        for c in range(3):
            rays_v[0, RAY_DIR, i, c] = dirs[i, c]
            rays_v[0, RAY_ORIGIN, i, c] = origins[i, c]


@njit(**_HELPER)
def _child(rays_i, rays_w, rays_v, nxt, at, slot, s, ch, refracted, w, cx, cy, cz, last,
           px, py, pz, gx, gy, gz, floor, relative):  # fmt: skip
    """Write child ray ``at`` of the next live-ray buffers ``nxt`` (``bounce``): its
    slot, source, chain, kind (``refracted`` 0 / 1), weight ``w``, direction (cx, cy, cz)
    and, unless this is the ``last`` depth, its origin offset from the hit (px, py, pz)
    along the geometric normal (gx, gy, gz) to the side it leaves to."""
    rays_i[nxt, RAY_SLOT, at], rays_i[nxt, RAY_SRC, at] = slot, s
    rays_i[nxt, RAY_CHAIN, at], rays_i[nxt, RAY_REFRACTED, at] = ch, refracted
    rays_w[nxt, at] = w
    rays_v[nxt, RAY_DIR, at, 0], rays_v[nxt, RAY_DIR, at, 1] = cx, cy
    rays_v[nxt, RAY_DIR, at, 2] = cz
    if not last:
        e = _side(_epsilon(px, py, pz, floor, relative), cx, cy, cz, gx, gy, gz)
        rays_v[nxt, RAY_ORIGIN, at, 0] = px + e * gx
        rays_v[nxt, RAY_ORIGIN, at, 1] = py + e * gy
        rays_v[nxt, RAY_ORIGIN, at, 2] = pz + e * gz


@njit(**_HELPER)
def _refract(dx, dy, dz, nx, ny, nz, fx, fy, fz, ior):
    """Snell refraction of one unit direction (``paths.refract``): shading normal n
    (either side), outward front normal f, ior; float64 result, made unit. Total
    internal reflection gives the mirror direction."""
    eta = 1.0 / ior if dx * fx + dy * fy + dz * fz < 0.0 else ior
    if dx * nx + dy * ny + dz * nz > 0.0:
        nx, ny, nz = -nx, -ny, -nz
    cos_i = min(max(-(dx * nx + dy * ny + dz * nz), 0.0), 1.0)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    if k < 0.0:
        return _unit64(dx + 2.0 * cos_i * nx, dy + 2.0 * cos_i * ny, dz + 2.0 * cos_i * nz)
    c = eta * cos_i - math.sqrt(k)
    return _unit64(eta * dx + c * nx, eta * dy + c * ny, eta * dz + c * nz)


# The buffers' layout (TRI_*, RAY_*, G_*, T_*): ``bounce_layout``.


@njit(**_KERNEL)
def bounce(
    prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map, ns_given, rays_i, rays_w,
    rays_v, parity, k, tri_table, frame, corners,
    split, last, floor, relative, n_elem, n_src, tally, g_i, g_w, g_x, g_v, g_uv,
):  # fmt: skip
    """One depth of the bounce loop (``paths.PathTracer.run``): Embree's answer for the
    k live rays → the surface at the hits, what the paths gather, and the next rays.

    Embree's answer (``bvh.Bvh.answers``, merged here by ``Bvh.merge``'s rule): prim (k,)
    int32 / int64 triangle of the static BVH or < 0 (a miss), u, v (k,) float32
    barycentrics; far_prim, far_u, far_v the same of the animated BVH (only nearer hits;
    (0,) without one); static_map, dynamic_map (·,) int64 each BVH's global triangle ids
    (static_map (0,): the static ids are global). ns_given (k, 3) float32 shading
    normals to use instead of the surface rule's (normal-mapped stages), or (0, 3).

    Live rays, double-buffered (this depth's in half ``parity``, the children written to
    half 1 - parity): rays_i (2, 4, L) int64 (``RAY_*`` rows), rays_w (2, L) float64 path
    weight, rays_v (2, 2, L, 3) float32 direction and origin, L >= 2k. Tables: tri_table
    (T, 5) float64 (``TRI_*`` columns); frame (T, 4, 3) float64 and corners (T, 3, 6)
    float32 (``TriangleTable``). split: the stage has transmissive materials (α and
    refraction); last: the bounce limit's depth (the children are not cast: they read
    the environment); floor, relative: the offset epsilon (``Float32Boundary``); n_elem:
    key stride; n_src: sources.

    Per hit (the surface rule of ``surface_kernels.hit_geometry``: rel position, front
    normal against the ray, shading normal by the side rule): a local-shading entry
    where it carries weight (w α (1 - F) > 0; with the corner albedo, as
    ``surface_kernels.hit_albedo``), a reflector key source * n_elem +
    element, the pixel slot's longest chain, a mirror child (w α F > 0) and, with
    ``split``, a refracted child (w (1 - α) > 0; all after the mirror ones), each with
    its origin offset off the surface (float32). Per miss, and at ``last`` per child, an
    environment entry. Entries are appended to the gather buffers (``G_*`` rows, at the
    counts in ``tally``; they have room for 2k more entries of each kind).
    Returns (children, refracted children)."""
    cur, nxt = parity, 1 - parity
    n_env, n_lit, n_keys = tally[T_ENV], tally[T_LIT], tally[T_KEYS]
    chains = T_SOURCES + n_src
    given = ns_given.shape[0] > 0
    animated = far_prim.shape[0] > 0
    mapped = static_map.shape[0] > 0
    for r in range(k):
        if prim[r] < 0 and not (animated and far_prim[r] >= 0):
            g_i[G_ENV_SLOT, n_env] = rays_i[cur, RAY_SLOT, r]
            g_w[G_ENV_W, n_env] = rays_w[cur, r]
            for c in range(3):
                g_v[G_ENV_DIR, n_env, c] = rays_v[cur, RAY_DIR, r, c]
            n_env += 1
    n_child = 0
    n_refr = 0
    for r in range(k):
        t, w1, w2 = _answer(r, prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map,
                            animated, mapped)  # fmt: skip
        if t < 0:
            continue
        slot = rays_i[cur, RAY_SLOT, r]
        s = rays_i[cur, RAY_SRC, r]
        w = rays_w[cur, r]
        d = rays_v[cur, RAY_DIR, r]
        dx, dy, dz = d[0], d[1], d[2]
        fdx, fdy, fdz = float(dx), float(dy), float(dz)
        # The surface (``surface_kernels.hit_geometry``).
        fu, fv = float(w1), float(w2)
        px = frame[t, 0, 0] + fu * frame[t, 1, 0] + fv * frame[t, 2, 0]
        py = frame[t, 0, 1] + fu * frame[t, 1, 1] + fv * frame[t, 2, 1]
        pz = frame[t, 0, 2] + fu * frame[t, 1, 2] + fv * frame[t, 2, 2]
        fx, fy, fz = frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2]
        side = -1.0 if fx * fdx + fy * fdy + fz * fdz > 0.0 else 1.0
        gx, gy, gz = fx * side, fy * side, fz * side
        w0 = _ONE32 - w1 - w2
        if given:
            nx, ny, nz = ns_given[r, 0], ns_given[r, 1], ns_given[r, 2]
        else:
            nx, ny, nz = _orient(
                _weighted(w0, w1, w2, corners[t, 0, 0], corners[t, 1, 0], corners[t, 2, 0]),
                _weighted(w0, w1, w2, corners[t, 0, 1], corners[t, 1, 1], corners[t, 2, 1]),
                _weighted(w0, w1, w2, corners[t, 0, 2], corners[t, 1, 2], corners[t, 2, 2]),
                side, fdx, fdy, fdz, fx, fy, fz,
            )  # fmt: skip
        f = tri_table[t, TRI_F]
        alpha = tri_table[t, TRI_ALPHA] if split else 1.0
        w_local = w * alpha * (1.0 - f)
        if w_local > 0.0:
            g_i[G_LIT_SLOT, n_lit], g_i[G_LIT_SRC, n_lit], g_i[G_LIT_TRI, n_lit] = slot, s, t
            if tri_table[t, TRI_TEXTURED] > 0.0:
                tally[T_TEXTURED] += 1
            g_w[G_LIT_W, n_lit] = w_local
            g_uv[G_LIT_U, n_lit], g_uv[G_LIT_V, n_lit] = w1, w2
            pos, ng = g_x[G_LIT_POS, n_lit], g_x[G_LIT_NG, n_lit]
            ns, d_in = g_v[G_LIT_NS, n_lit], g_v[G_LIT_DIR, n_lit]
            pos[0], pos[1], pos[2] = px, py, pz
            ng[0], ng[1], ng[2] = gx, gy, gz
            ns[0], ns[1], ns[2] = nx, ny, nz
            d_in[0], d_in[1], d_in[2] = dx, dy, dz
            albedo = g_v[G_LIT_ALBEDO, n_lit]  # ``surface_kernels.hit_albedo``
            for j in range(3):
                albedo[j] = _weighted(
                    w0, w1, w2, corners[t, 0, 3 + j], corners[t, 1, 3 + j], corners[t, 2, 3 + j]
                )
            n_lit += 1
        ch = rays_i[cur, RAY_CHAIN, r]
        element = np.int64(tri_table[t, TRI_REFLECTOR])
        if element >= 0:
            ch += 1
            g_i[G_KEY, n_keys] = s * n_elem + element
            n_keys += 1
        if ch > tally[chains + slot]:
            tally[chains + slot] = ch
        w_refl = w * alpha * f
        if w_refl > 0.0:
            # Mirror of a unit vector about a unit normal (float32, as the first rays).
            kk = _TWO32 * (dx * nx + dy * ny + dz * nz)
            cx, cy, cz = dx - kk * nx, dy - kk * ny, dz - kk * nz
            _child(rays_i, rays_w, rays_v, nxt, n_child, slot, s, ch, 0, w_refl, cx, cy, cz,
                   last, px, py, pz, gx, gy, gz, floor, relative)  # fmt: skip
            n_child += 1
        if split:
            w_refr = w * (1.0 - tri_table[t, TRI_ALPHA])
            if w_refr > 0.0:  # staged after the live rays, moved after the mirror ones
                cx, cy, cz = _refract(
                    fdx, fdy, fdz, float(nx), float(ny), float(nz), fx, fy, fz,
                    tri_table[t, TRI_IOR],
                )  # fmt: skip
                cx, cy, cz = np.float32(cx), np.float32(cy), np.float32(cz)
                _child(rays_i, rays_w, rays_v, nxt, k + n_refr, slot, s, ch, 1, w_refr, cx, cy,
                       cz, last, px, py, pz, gx, gy, gz, floor, relative)  # fmt: skip
                n_refr += 1
    for j in range(n_refr):  # the refracted children after all mirror ones
        for row in range(4):
            rays_i[nxt, row, n_child + j] = rays_i[nxt, row, k + j]
        rays_w[nxt, n_child + j] = rays_w[nxt, k + j]
        for c in range(3):
            rays_v[nxt, RAY_DIR, n_child + j, c] = rays_v[nxt, RAY_DIR, k + j, c]
            rays_v[nxt, RAY_ORIGIN, n_child + j, c] = rays_v[nxt, RAY_ORIGIN, k + j, c]
    n_child += n_refr
    for c in range(n_child):
        if last:  # the children read the environment
            g_i[G_ENV_SLOT, n_env] = rays_i[nxt, RAY_SLOT, c]
            g_w[G_ENV_W, n_env] = rays_w[nxt, c]
            for a in range(3):
                g_v[G_ENV_DIR, n_env, a] = rays_v[nxt, RAY_DIR, c, a]
            n_env += 1
        else:  # the children about to be cast, per source
            tally[T_SOURCES + rays_i[nxt, RAY_SRC, c]] += 1
    tally[T_ENV], tally[T_LIT], tally[T_KEYS] = n_env, n_lit, n_keys
    return n_child, n_refr


@njit(**_KERNEL)
def accumulate(total, slot, weight, value):
    """total[slot[i]] += weight[i] * value[i] for i < k: slot (k,) int64, weight (k,)
    float64, value (k, 3) float32 (or (3,)-broadcast when it has one row), total
    (pixels, 3) float64."""
    broadcast = value.shape[0] == 1
    for i in range(slot.shape[0]):
        row = 0 if broadcast else i
        p = slot[i]
        w = weight[i]
        for c in range(3):
            total[p, c] += w * value[row, c]


@njit(**_KERNEL)
def source_tallies(src, tally, first_cast, shadow_src, shadow_rays, keys, n_keys, out,
                   out_keys):  # fmt: skip
    """Per-source figures of ``TraceRecord`` into ``out`` (4, S) int64 rows: pixels,
    the sum and the longest of their reflector chains, rays cast. From the paths' src
    (n,) int64 and ``bounce``'s ``tally`` (rays cast per source after the first rays,
    longest chain per path); ``first_cast``: the first rays were cast (one per path);
    shadow_rays (m,) int64 cast per shading point of source shadow_src (m,) int64.
    The reflector keys (h,) int64 (``bounce``'s, each < n_keys) counted: each key that
    occurs and its count into out_keys (2, h) int64, in ascending key order. Returns how
    many distinct keys."""
    n_src = out.shape[1]
    out[:] = 0
    for s in range(n_src):
        out[3, s] = tally[T_SOURCES + s]
    chains = T_SOURCES + n_src
    for i in range(src.shape[0]):
        s = src[i]
        out[0, s] += 1
        out[1, s] += tally[chains + i]
        out[2, s] = max(out[2, s], tally[chains + i])
        if first_cast:
            out[3, s] += 1
    for i in range(shadow_src.shape[0]):
        out[3, shadow_src[i]] += shadow_rays[i]
    if keys.shape[0] == 0:
        return 0
    counts = np.zeros(n_keys, np.int64)
    for i in range(keys.shape[0]):
        counts[keys[i]] += 1
    found = 0
    for key in range(n_keys):
        if counts[key]:
            out_keys[0, found], out_keys[1, found] = key, counts[key]
            found += 1
    return found


@njit(**_KERNEL)
def primary_rays(xs, ys, rot, renormalise, eye, fwd, near, lo, hi, d64, o32, d32):
    """Rays through the centres of flat pixels lo..hi (row-major, width = len(xs)).

    xs (W,), ys (H,) float64 the pixel plane (``CameraFrame.pixel_plane``); rot (3, 3)
    the camera-to-world rotation, ``renormalise`` when it has scale or shear; eye (3,)
    rel; fwd (3,) unit view direction; near: the clipping distance (metres of view
    depth) where rays start. Writes per pixel p the unit direction d64[p] (float64,
    the raster G-buffer's rule) and the float32 rays: d32[p] and o32[p] = eye + d * near
    / max(d·fwd, 1e-6) (view depth grows by d·fwd per metre along the ray)."""
    width = xs.shape[0]
    start = max(near, 0.0)
    for p in range(lo, hi):
        row, col = p // width, p % width
        x, y = xs[col], ys[row]
        s = 1.0 / math.sqrt(x * x + y * y + 1.0)
        dx, dy, dz = _pixel_dir(
            y, x, s, rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2],
            rot[2, 0], rot[2, 1], rot[2, 2], renormalise,
        )  # fmt: skip
        d64[p, 0], d64[p, 1], d64[p, 2] = dx, dy, dz
        d32[p, 0], d32[p, 1], d32[p, 2] = dx, dy, dz
        t = start / max(dx * fwd[0] + dy * fwd[1] + dz * fwd[2], 1e-6)
        o32[p, 0], o32[p, 1], o32[p, 2] = eye[0] + dx * t, eye[1] + dy * t, eye[2] + dz * t


@njit(**_KERNEL)
def primary_fill(
    ray, tri, rel, ns, albedo, eye, fwd, far, origin, tri_element,
    out_elem, out_tri, out_depth, out_pos, out_normal, out_albedo,
):  # fmt: skip
    """The ``rt`` G-buffer rows of m primary hits: ray (m,) int64 pixel, tri (m,) int64,
    rel (m, 3) float64 hit positions, ns and albedo (m, 3) float32 (``HitSurfaces.at``);
    eye (3,) rel, fwd (3,) unit view direction, far: the clipping distance (a hit
    deeper is a miss, as is a NaN depth); origin (3,) ``Scene.origin``. Writes the
    pixel's element and triangle (int32), view depth (float32), world position
    (float64), normal and albedo (float32); pixels not written keep the caller's fill."""
    for h in range(ray.shape[0]):
        px, py, pz = rel[h, 0], rel[h, 1], rel[h, 2]
        depth = (px - eye[0]) * fwd[0] + (py - eye[1]) * fwd[1] + (pz - eye[2]) * fwd[2]
        if not (depth <= far):
            continue
        p = ray[h]
        t = tri[h]
        out_elem[p] = tri_element[t]
        out_tri[p] = t
        out_depth[p] = depth
        out_pos[p, 0], out_pos[p, 1], out_pos[p, 2] = px + origin[0], py + origin[1], pz + origin[2]
        for c in range(3):
            out_normal[p, c] = ns[h, c]
            out_albedo[p, c] = albedo[h, c]


@njit(**_KERNEL)
def hit_distances(prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map, origins, frame,
                  out):  # fmt: skip
    """Metres from each ray's origin to its nearest hit, from Embree's answer for n rays
    (the eight arrays of ``bvh.Bvh.answers``, merged by ``Bvh.merge``'s rule as
    ``bounce`` merges them) into out (n,) float32: |hit - origin|, the hit at the
    barycentrics on its triangle (``surface_kernels.hit_geometry``), origins (n, 3)
    float32 rel; +inf for a miss. ``sparse_pixels`` reads the first rays' distances
    (how far the reflected surface is) as a guide of its fill."""
    animated = far_prim.shape[0] > 0
    mapped = static_map.shape[0] > 0
    for r in range(prim.shape[0]):
        t, w1, w2 = _answer(r, prim, u, v, far_prim, far_u, far_v, static_map, dynamic_map,
                            animated, mapped)  # fmt: skip
        if t < 0:
            out[r] = np.inf
            continue
        fu, fv = float(w1), float(w2)
        d2 = 0.0
        for c in range(3):
            e = frame[t, 0, c] + fu * frame[t, 1, c] + fv * frame[t, 2, c] - origins[r, c]
            d2 += e * e
        out[r] = math.sqrt(d2)


def warm_up() -> None:
    """Compile (or load from phrt's kernel cache) every kernel on tiny inputs of the types
    the tracer passes."""
    i64, f64, f32 = np.zeros(1, np.int64), np.zeros(1), np.zeros(1, np.float32)
    v64, v32 = np.zeros((1, 3)), np.zeros((1, 3), np.float32)
    i32 = np.zeros(1, np.int32)
    frame = np.zeros((1, 4, 3))
    b = np.zeros(1, bool)
    offset_origins(v64, v64, v32, 1e-6, 1e-5, v32.copy())
    offset_origins(v64, v64, v64, 1e-6, 1e-5, v32.copy())
    source_rays(i64, i32, v64, v32, v32, np.zeros(3), frame, 1e-6, 1e-5, 0, 1, i64.copy(),
                v64.copy(), v64.copy(), v32.copy(), v32.copy(), v32.copy(), v32.copy())  # fmt: skip
    gather_spans(i64, np.zeros((1, 3), np.int64), i64.copy(), i64.copy())
    split_hits(i32, f32, f32, i64.copy(), i64.copy(), f32.copy(), f32.copy(), i64.copy())
    split_hits(i64, f32, f32, i64.copy(), i64.copy(), f32.copy(), f32.copy(), i64.copy())
    rays = (np.zeros((2, 4, 2), np.int64), np.zeros((2, 2)), np.zeros((2, 2, 2, 3), np.float32))
    start_rays(i64, v32, v32, 0, *rays)
    tables = (np.zeros((1, 5)), frame, np.zeros((1, 3, 6), np.float32))
    gather = (np.zeros((5, 3), np.int64), np.zeros((2, 3)), np.zeros((2, 3, 3)),
              np.zeros((4, 3, 3), np.float32), np.zeros((2, 3), np.float32))  # fmt: skip
    answers = ((i32, f32, f32, i32, f32, f32, i64, i64),
               (i64, f32, f32, i32[:0], f32[:0], f32[:0], i64[:0], i64[:0]))  # fmt: skip
    for answer in answers:
        for split in (False, True):
            bounce(*answer, v32[:0], *rays, 0, 1, *tables, split, False, 1e-6, 1e-5, 1,
                   1, np.zeros(6, np.int64), *gather)  # fmt: skip
    primary_rays(f64, f64, np.eye(3), False, np.zeros(3), np.ones(3), 0.1, 0, 1, v64.copy(),
                 v32.copy(), v32.copy())  # fmt: skip
    gb_rows = (i32.copy(), i32.copy(), f32.copy(), v64.copy(), v32.copy(), v32.copy())
    primary_fill(i64, i64, v64, v32, v32, np.zeros(3), np.ones(3), 1.0, np.zeros(3), i64,
                 *gb_rows)  # fmt: skip
    accumulate(np.zeros((1, 3)), i64, f64, v32)
    accumulate(np.zeros((1, 3)), i64, f64, v64)
    source_tallies(i64, np.zeros(6, np.int64), True, i64, i64, i64, 1, np.zeros((4, 1), np.int64),
                   np.zeros((2, 1), np.int64))  # fmt: skip
    shadow = (np.zeros((2, 1), np.int64), np.zeros((2, 1, 3), np.float32),
              np.zeros((3, 1), np.float32))  # fmt: skip
    for u0 in (f64, f64[:0]):  # sampled (the hit-lighting rule) or every pair
        for on in (i64[:0], i64):  # points anywhere, or on their triangles
            shadow_rays(v64, v32, v32, np.array([[0.0, 1.0, 0.0]]), np.zeros((0, 3)), f64[:0],
                        np.zeros((0, 0), bool), 1e-6, 1e-5, 1e-3, 1e30, f64, np.zeros((0, 7)),
                        len(u0), u0, on, np.zeros((1, 13)), frame, np.zeros((1, 3, 6), np.float32),
                        *shadow)  # fmt: skip
    shadow_results(*shadow, b, 1, np.zeros((1, 1), np.float32), i64.copy(),
                   np.zeros((2, 1), np.int64), v32.copy(), f64.copy(), f32.copy())  # fmt: skip
    for answer in answers:
        hit_distances(*answer, v32, frame, f32.copy())
    light = (np.zeros(3), np.array([[0.0, 1.0, 0.0]]), np.ones((1, 3)), np.zeros((0, 3)),
             np.zeros((0, 3)), np.zeros(0), np.zeros((0, 7)))  # fmt: skip
    surface = np.zeros((1, 16), np.float32)
    lut = np.zeros((2, 3, 2), np.float32)
    shadow_shade(*shadow, b, v64, v32, surface, v32, v32, *light, np.zeros(4), lut,
                 v32.copy(), i64.copy(), np.zeros((1, 3)), i64, f64)  # fmt: skip


@njit(**_KERNEL)
def shadow_rays(
    rel, ng, ns, dirs, pos, ranges, want, floor, relative, min_distance, far, power, cone,
    picks, u0, tri, plane, frame, corners, out_i, out_v, out_f,
):  # fmt: skip
    """The shadow rays of ``ShadowRays.cast``: for each point i (rel (n, 3) float64,
    offset normal ng and shading normal ns (n, 3) float32) and each light j
    (DistantLights dirs (D, 3) unit, then LocalLights pos (P, 3) rel metres of range
    ranges (P,)) wanted (``want`` (n, D + P) bool, or (0, 0): all) whose light can
    matter there (in front of ns; LocalLights: within range), one ray, point-major.
    ``picks`` > 0 (``hit_lighting``'s rule): at most ``picks`` rays a point, chosen and
    weighted by ``light_draws`` from the pairs' ``light_share`` (power (D + P,) the
    brightest channels, cone (P, 7) as ``shade_kernel``'s l_cone) and offset u0[i].

    Writes ray r's point and light (distant then local index) into out_i (2, ·) int64,
    its float32 origin and unit direction into out_v (2, ·, 3), its tfar, distance and
    weight into out_f (3, ·) float32 (distance: metres to a LocalLight, >=
    ``min_distance``, or ``far``); the buffers have n (D + P) columns. Origins leave the
    surface by the offset epsilon (floor, relative: ``Float32Boundary``) along ng on the
    ray's side (``_side``); LocalLight rays stop that epsilon short of the light.

    With ``tri`` (n,) int64 each point's triangle (or -1; ``TriangleTable``'s plane,
    frame, corners), a point's rays start from it lifted onto the smooth surface its
    triangle's corner normals imply (the shadow terminator: Hanika's tangent-plane rule,
    faded by TERMINATOR_FADE) and leave by the epsilon along the triangle's own normal
    to the lit side (ns's), whatever side of the flat triangle the light is on; a ray
    that would cross its own triangle (the light below its plane) starts just past it
    (production renderers skip a ray's own triangle). ``tri`` (0,): as above (ng, the
    ray's side). Returns the ray count."""
    n, n_distant = rel.shape[0], dirs.shape[0]
    n_lights = n_distant + pos.shape[0]
    every = want.shape[0] == 0
    ray = np.empty((n_lights, 4))  # point i's ray to each light: direction, length
    share, weight = np.empty(n_lights), np.empty(n_lights)
    r = 0
    for i in range(n):
        px, py, pz = rel[i, 0], rel[i, 1], rel[i, 2]
        e = _epsilon(px, py, pz, floor, relative)
        t = tri[i] if tri.shape[0] > 0 else -1
        # The offset normal: on a triangle, its own to the lit side (ns's).
        gx, gy, gz = float(ng[i, 0]), float(ng[i, 1]), float(ng[i, 2])
        s = 1.0
        if t >= 0:
            gx, gy, gz = frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2]
            s = 1.0 if gx * ns[i, 0] + gy * ns[i, 1] + gz * ns[i, 2] >= 0.0 else -1.0
            gx, gy, gz = s * gx, s * gy, s * gz
        lifted, lx, ly, lz = False, 0.0, 0.0, 0.0  # the lift, once a ray needs it
        for j in range(n_lights):
            share[j] = -1.0  # no ray
            if not (every or want[i, j]):
                continue
            q = j - n_distant
            if q < 0:
                t0, t1, t2, length = dirs[j, 0], dirs[j, 1], dirs[j, 2], far
            else:
                t0, t1, t2 = pos[q, 0] - px, pos[q, 1] - py, pos[q, 2] - pz
                square = t0 * t0 + t1 * t1 + t2 * t2
                if not square < ranges[q] * ranges[q]:
                    continue
                length = max(math.sqrt(square), min_distance)
                t0, t1, t2 = t0 / length, t1 / length, t2 / length
            lit = ns[i, 0] * t0 + ns[i, 1] * t1 + ns[i, 2] * t2
            if not lit > 0.0:
                continue
            f = 1.0
            if q >= 0 and cone[q, 6] > 0.0:
                cos = -(t0 * cone[q, 0] + t1 * cone[q, 1] + t2 * cone[q, 2])
                f = cone_at(cos, cone[q, 3], cone[q, 4], cone[q, 5])
            reach = ranges[q] if q >= 0 else 0.0
            share[j] = light_share(power[j], lit, length * length, reach, q >= 0, f)
            ray[j, 0], ray[j, 1], ray[j, 2], ray[j, 3] = t0, t1, t2, length
        light_draws(share, weight, picks, u0[i] if picks > 0 else 0.0)
        for j in range(n_lights):
            if not weight[j] > 0.0:
                continue
            d0, d1, d2, length = ray[j, 0], ray[j, 1], ray[j, 2], ray[j, 3]
            stop = far if j < n_distant else max(length - e, 0.0)  # short of a LocalLight
            if t >= 0:  # from the smooth surface, to the lit side (see the docstring)
                up = gx * d0 + gy * d1 + gz * d2
                fade = min(max(1.0 - up / TERMINATOR_FADE, 0.0), 1.0)
                if fade > 0.0 and not lifted:
                    lifted = True
                    lx, ly, lz = _smooth_lift(t, px, py, pz, s, plane, frame, corners)
                ox, oy, oz = px + fade * lx + e * gx, py + fade * ly + e * gy, pz + fade * lz
                oz += e * gz
                down = -up
                if down > 0.0:  # into its own plane: past the triangle if it is there
                    reach = ((ox - px) * gx + (oy - py) * gy + (oz - pz) * gz) / down
                    cx, cy, cz = ox + reach * d0, oy + reach * d1, oz + reach * d2
                    if _inside(t, cx, cy, cz, plane):
                        ox, oy, oz = cx - e * gx, cy - e * gy, cz - e * gz
                        stop = stop if j < n_distant else max(stop - reach, 0.0)
                out_v[0, r, 0], out_v[0, r, 1], out_v[0, r, 2] = ox, oy, oz
            else:
                side = _side(e, d0, d1, d2, gx, gy, gz)
                out_v[0, r, 0], out_v[0, r, 1] = px + side * gx, py + side * gy
                out_v[0, r, 2] = pz + side * gz
            out_v[1, r, 0], out_v[1, r, 1], out_v[1, r, 2] = d0, d1, d2
            out_i[0, r], out_i[1, r] = i, j
            out_f[0, r], out_f[1, r], out_f[2, r] = stop, length, weight[j]
            r += 1
    return r


@njit(**_KERNEL)
def shadow_results(rays_i, rays_v, rays_f, occluded, n_distant, vis, rays, lit_i, lit_dir,
                   lit_dist, lit_w):  # fmt: skip
    """What ``ShadowRays.cast`` answers from Embree's ``occluded`` (k,) bool on the k
    rays of ``shadow_rays`` (its out_i, out_v, out_f): visibility (a free ray's weight,
    else 0) into ``vis`` (n, L) float32, shadow rays per point into ``rays`` (n,) int64,
    and the lit LocalLight pairs (``shading.LightPairs``): point and LocalLight index
    into lit_i (2, k) int64, direction, distance and weight into lit_dir (k, 3) float32,
    lit_dist (k,) float64, lit_w (k,) float32. Returns the lit LocalLight pairs' count."""
    vis[:] = 0.0
    rays[:] = 0
    m = 0
    for r in range(occluded.shape[0]):
        i, j = rays_i[0, r], rays_i[1, r]
        rays[i] += 1
        if occluded[r]:
            continue
        vis[i, j] = rays_f[2, r]
        if j >= n_distant:
            lit_i[0, m], lit_i[1, m] = i, j - n_distant
            for c in range(3):
                lit_dir[m, c] = rays_v[1, r, c]
            lit_dist[m], lit_w[m] = rays_f[1, r], rays_f[2, r]
            m += 1
    return m


@njit(**_KERNEL)
def shadow_shade(
    rays_i, rays_v, rays_f, occluded, positions, normals, surface, view_dirs, emissive,
    ambient, d_dir, d_radiance, l_pos, l_radiance, l_range, l_cone, model, lut, out, rays,
    total, slot, weight,
):  # fmt: skip
    """``shadow_results`` of Embree's ``occluded`` (k,) bool on the k rays of
    ``shadow_rays`` (rays_i, rays_v, rays_f) for n points, then the shading model of the
    points with that visibility and those lit LocalLight pairs, weighted
    (``shade_kernels.shade_kernel``, as ``shading.shade_local`` calls it with
    ``local_pairs``): one call instead of two and the Python between them, the same
    code (to float32 rounding). positions (n, 3) float64 rel; normals, view_dirs (n, 3)
    float32; surface (n, 16) float32 (``model.preview_surface`` rows); emissive (1 or
    n, 3) float32; the lights as ``shading.LightTable`` (distant then local); model
    ``shading.MODEL``, lut ``preview_surface.specular_albedo_table``. Writes out (n, 3)
    float32, the shadow rays per point into rays (n,) int64, and when ``total`` (P, 3)
    float64 has rows adds weight (n,) float64 times out into its rows slot (n,) int64."""
    n, k = positions.shape[0], occluded.shape[0]
    n_distant = d_dir.shape[0]
    vis = np.empty((n, n_distant + l_pos.shape[0]), np.float32)
    lit_i, lit_dir = np.empty((2, k), np.int64), np.empty((k, 3), np.float32)
    lit_dist, lit_w = np.empty(k), np.empty(k, np.float32)
    m = shadow_results(rays_i, rays_v, rays_f, occluded, n_distant, vis, rays, lit_i, lit_dir,
                       lit_dist, lit_w)  # fmt: skip
    no_sums = np.empty((0, 3), np.float32)
    shade_kernel(
        positions, normals, surface, view_dirs, emissive, ambient, no_sums, d_dir,
        d_radiance, vis, l_pos, l_radiance, l_range, l_cone, False,
        lit_i[0, :m], lit_i[1, :m], lit_dir[:m], lit_dist[:m], lit_w[:m], True, model, lut,
        out,
    )  # fmt: skip
    if total.shape[0] > 0:
        accumulate(total, slot, weight, out)
