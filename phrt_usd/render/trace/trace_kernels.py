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
- ``split_hits``: Embree's answer → hit rows and miss rows (``bvh.Hits``);
- ``bounce``: what the bounce loop does at one depth's hits — environment entries of
  misses, the local-shading entries, reflector keys, the reflector chains, and the
  children (mirror and refracted rays with their offset origins);
- ``accumulate``: the gathered radiance summed per pixel;
- ``source_tallies``: the per-source figures of ``TraceRecord``;
- ``primary_rays`` / ``primary_fill``: the ``rt`` mode's pixel rays (the raster
  G-buffer's direction rule, ``surface_kernels._pixel_dir``) and its G-buffer rows.

The numpy forms these replace are the tests' reference (``tests/test_trace_kernels.py``):
same operations in the same precision (float64 positions and offsets, float32
directions and shading normals), so results agree to the rounding of a sum's order.

Array arguments are read and written only in the kernels themselves (numba counts the
references of an array handed to another compiled function); the helpers take and
return scalars. Spaces: rel = world metres minus ``Scene.origin`` (float64).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS
from phrt_usd.model.surface_kernels import _pixel_dir

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
    cand, cand_elem, table, tri_img, pos_img, nrm_img, view_img, origin, frame, floor,
    relative, lo, hi, out_src, out_tri, out_rel, out_ng, out_ns, out_view, out_dir, out_org,
):  # fmt: skip
    """The first rays of paths from G-buffer pixels cand[lo:hi] into rows lo..hi.

    cand (k,) int64 flat pixels of sources, cand_elem (k,) their element ids; table
    (E + 1,) int64 element → index into the sources. Images flat over H*W: tri_img
    int32, pos_img (·, 3) float64 world, nrm_img and view_img (·, 3) float32. origin (3,)
    ``Scene.origin``; frame ``TriangleTable.frame``; floor, relative: the offset epsilon
    (``Float32Boundary``).

    Per pixel: out_src, out_tri (k,) int64. The surface, written when out_rel has rows:
    out_rel (k, 3) float64 the position snapped onto its triangle's plane; out_ng (k, 3)
    float64 the triangle's unit front normal (the shading normal where there is no
    triangle); out_ns (k, 3) float32 the unit shading normal turned to face the viewer;
    out_view (k, 3) float32 unit view direction. The mirror ray, written when out_dir
    has rows: out_dir (k, 3) float32 the mirror direction and out_org (k, 3) float32 its
    offset origin."""
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
        out_src[i], out_tri[i] = table[cand_elem[i]], t
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


#: The rows of ``bounce``'s output buffers (int64, float64, float32 (·, 3)).
BOUNCE_ROWS = (8, 3, 3)


@njit(**_KERNEL)
def bounce(
    ray, miss, tri, rel, ng, ns, slot, src, weight, chain, dirs,
    tri_reflector, tri_f, tri_material, tri_element, opacity, ior, frame,
    split, last, floor, relative, n_elem, chain_pix, rays_src, out_i, out_w, out_v, c_refr,
):  # fmt: skip
    """One depth of the bounce loop (``paths.PathTracer.run``) over k live rays, of
    which m hit (``ray`` (m,) rows, ``miss`` (k - m,) rows, int64).

    Hits: tri (m,) int64; rel (m, 3) float64; ng (m, 3) float64 facing the ray; ns (m, 3)
    float32 shading normals. Live rays: slot, src (k,) int64 pixel slot and source;
    weight (k,) float64; chain (k,) int64 reflector hits so far; dirs (k, 3) float32.
    Tables: per triangle reflector flag, F, material, element; per material opacity and
    ior; frame (``TriangleTable``). split: the stage has transmissive materials (α and
    refraction); last: this is the bounce limit's depth (children are not cast: they
    read the environment); floor, relative: the offset epsilon; n_elem: key stride.

    Updates chain_pix (pixels,) int64 (longest reflector chain per slot) and rays_src
    (sources,) int64 (the children about to be cast, per source). Writes the
    environment entries (misses, then at ``last`` the children) into env_slot, env_w,
    env_dir (k + 2m); the hits whose local shading carries weight into lit (hit rows),
    lit_w (their weight), lit_slot and lit_src (m); reflector keys src * n_elem +
    element into keys (m); the children (m, or 2m with ``split``) into c_slot, c_src,
    c_w, c_chain, c_refr (bool), c_dir float32 and c_org float32 (offset origins; not
    written at ``last``).

    The outputs come as four buffers of L >= k + 2m columns (four arguments and four
    allocations per depth instead of fifteen: a fixed cost of every depth): ``out_i``
    (8, L) int64 rows env_slot, lit, lit_slot, lit_src, keys, c_slot, c_src, c_chain;
    ``out_w`` (3, L) float64 rows env_w, lit_w, c_w; ``out_v`` (3, L, 3) float32
    env_dir, c_dir, c_org; ``c_refr`` (L,) bool (``BOUNCE_ROWS``).

    Returns (environment entries, lit hits, keys, children, refracted children)."""
    env_slot, lit, lit_slot, lit_src, keys = out_i[0], out_i[1], out_i[2], out_i[3], out_i[4]
    c_slot, c_src, c_chain = out_i[5], out_i[6], out_i[7]
    env_w, lit_w, c_w = out_w[0], out_w[1], out_w[2]
    env_dir, c_dir, c_org = out_v[0], out_v[1], out_v[2]
    n_env = 0
    for j in range(miss.shape[0]):
        r = miss[j]
        env_slot[n_env], env_w[n_env] = slot[r], weight[r]
        env_dir[n_env, 0], env_dir[n_env, 1], env_dir[n_env, 2] = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        n_env += 1
    n_lit = 0
    n_keys = 0
    n_child = 0
    n_refr = 0
    for h in range(ray.shape[0]):
        r = ray[h]
        t = tri[h]
        alpha = opacity[tri_material[t]] if split else 1.0
        f = tri_f[t]
        w = weight[r]
        s = src[r]
        w_local = w * alpha * (1.0 - f)
        if w_local > 0.0:
            lit[n_lit], lit_w[n_lit] = h, w_local
            lit_slot[n_lit], lit_src[n_lit] = slot[r], s
            n_lit += 1
        ch = chain[r]
        if tri_reflector[t]:
            ch += 1
            keys[n_keys] = s * n_elem + tri_element[t]
            n_keys += 1
        if ch > chain_pix[slot[r]]:
            chain_pix[slot[r]] = ch
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        nx, ny, nz = ns[h, 0], ns[h, 1], ns[h, 2]
        gx, gy, gz = ng[h, 0], ng[h, 1], ng[h, 2]
        w_refl = w * alpha * f
        if w_refl > 0.0:
            # Mirror of a unit vector about a unit normal (float32, as the first rays).
            k = _TWO32 * (np.float32(dx) * nx + np.float32(dy) * ny + np.float32(dz) * nz)
            cx, cy, cz = dx - k * nx, dy - k * ny, dz - k * nz
            c_slot[n_child], c_src[n_child], c_w[n_child] = slot[r], s, w_refl
            c_chain[n_child], c_refr[n_child] = ch, False
            c_dir[n_child, 0], c_dir[n_child, 1], c_dir[n_child, 2] = cx, cy, cz
            if not last:
                px, py, pz = rel[h, 0], rel[h, 1], rel[h, 2]
                e = _side(_epsilon(px, py, pz, floor, relative), cx, cy, cz, gx, gy, gz)
                c_org[n_child, 0] = px + e * gx
                c_org[n_child, 1] = py + e * gy
                c_org[n_child, 2] = pz + e * gz
                rays_src[s] += 1
            n_child += 1
    if split:  # refracted children after all mirror ones (the numpy order)
        for h in range(ray.shape[0]):
            r = ray[h]
            t = tri[h]
            w_refr = weight[r] * (1.0 - opacity[tri_material[t]])
            if not (w_refr > 0.0):
                continue
            ch = chain[r] + (1 if tri_reflector[t] else 0)
            cx, cy, cz = _refract(
                float(dirs[r, 0]), float(dirs[r, 1]), float(dirs[r, 2]),
                float(ns[h, 0]), float(ns[h, 1]), float(ns[h, 2]),
                frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2], ior[tri_material[t]],
            )  # fmt: skip
            c_slot[n_child], c_src[n_child], c_w[n_child] = slot[r], src[r], w_refr
            c_chain[n_child], c_refr[n_child] = ch, True
            c_dir[n_child, 0], c_dir[n_child, 1], c_dir[n_child, 2] = cx, cy, cz
            if not last:
                gx, gy, gz = ng[h, 0], ng[h, 1], ng[h, 2]
                px, py, pz = rel[h, 0], rel[h, 1], rel[h, 2]
                dx32, dy32, dz32 = c_dir[n_child, 0], c_dir[n_child, 1], c_dir[n_child, 2]
                e = _side(_epsilon(px, py, pz, floor, relative), dx32, dy32, dz32, gx, gy, gz)
                c_org[n_child, 0] = px + e * gx
                c_org[n_child, 1] = py + e * gy
                c_org[n_child, 2] = pz + e * gz
                rays_src[src[r]] += 1
            n_child += 1
            n_refr += 1
    if last:  # the children read the environment
        for c in range(n_child):
            env_slot[n_env], env_w[n_env] = c_slot[c], c_w[c]
            env_dir[n_env, 0], env_dir[n_env, 1], env_dir[n_env, 2] = (
                c_dir[c, 0],
                c_dir[c, 1],
                c_dir[c, 2],
            )
            n_env += 1
    return n_env, n_lit, n_keys, n_child, n_refr


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
def source_tallies(src, chain_pix, shadow_src, shadow_rays, pixels, chain_sum, chain_max,
                   rays_src):  # fmt: skip
    """Per-source figures of ``TraceRecord``: pixels (sources,) int64, chain_sum float64,
    chain_max int64 from the paths' src (n,) and chain_pix (n,) int64, and rays_src
    (sources,) int64 += shadow_rays (m,) int64 per shading point of source shadow_src
    (m,) int64."""
    for i in range(src.shape[0]):
        s = src[i]
        pixels[s] += 1
        chain_sum[s] += chain_pix[i]
        if chain_pix[i] > chain_max[s]:
            chain_max[s] = chain_pix[i]
    for i in range(shadow_src.shape[0]):
        rays_src[shadow_src[i]] += shadow_rays[i]


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


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel on tiny inputs of the types
    the tracer passes."""
    i64, f64, f32 = np.zeros(1, np.int64), np.zeros(1), np.zeros(1, np.float32)
    v64, v32 = np.zeros((1, 3)), np.zeros((1, 3), np.float32)
    i32 = np.zeros(1, np.int32)
    frame = np.zeros((1, 4, 3))
    b = np.zeros(1, bool)
    offset_origins(v64, v64, v32, 1e-6, 1e-5, v32.copy())
    offset_origins(v64, v64, v64, 1e-6, 1e-5, v32.copy())
    source_rays(i64, i64, i64, i32, v64, v32, v32, np.zeros(3), frame, 1e-6, 1e-5, 0, 1,
                i64.copy(), i64.copy(), v64.copy(), v64.copy(), v32.copy(), v32.copy(),
                v32.copy(), v32.copy())  # fmt: skip
    split_hits(i32, f32, f32, i64.copy(), i64.copy(), f32.copy(), f32.copy(), i64.copy())
    split_hits(i64, f32, f32, i64.copy(), i64.copy(), f32.copy(), f32.copy(), i64.copy())
    hits = (i64, i64[:0], i64, v64, v64, v32)
    state = (i64, i64, f64, i64, v32)
    tables = (b, f64, i64, i64, f64 + 1.0, f64 + 1.0, frame)
    n_i, n_w, n_v = BOUNCE_ROWS
    out = (np.zeros((n_i, 3), np.int64), np.zeros((n_w, 3)), np.zeros((n_v, 3, 3), np.float32))
    for split in (False, True):
        bounce(*hits, *state, *tables, split, False, 1e-6, 1e-5, 1, i64.copy(), i64.copy(),
               *out, np.zeros(3, bool))  # fmt: skip
    primary_rays(f64, f64, np.eye(3), False, np.zeros(3), np.ones(3), 0.1, 0, 1, v64.copy(),
                 v32.copy(), v32.copy())  # fmt: skip
    gb_rows = (i32.copy(), i32.copy(), f32.copy(), v64.copy(), v32.copy(), v32.copy())
    primary_fill(i64, i64, v64, v32, v32, np.zeros(3), np.ones(3), 1.0, np.zeros(3), i64,
                 *gb_rows)  # fmt: skip
    accumulate(np.zeros((1, 3)), i64, f64, v32)
    accumulate(np.zeros((1, 3)), i64, f64, v64)
    source_tallies(i64, i64, i64, i64, i64.copy(), f64.copy(), i64.copy(), i64.copy())
    shadow_rays(v64, v32, v32, np.array([[0.0, 1.0, 0.0]]), np.zeros((0, 3)), np.zeros(0),
                np.zeros((0, 0), bool), f64 + 1e-6, 1e-3, 1e30)  # fmt: skip


@njit(**_KERNEL)
def shadow_rays(rel, ng, ns, dirs, pos, ranges, want, eps, min_distance, far):
    """The shadow rays of ``ShadowRays.cast``: for each point i (rel (n, 3) float64,
    offset normal ng and shading normal ns (n, 3) float32, offset epsilon eps (n,)
    metres) and each light j (DistantLights dirs (D, 3) unit, then LocalLights pos
    (P, 3) rel metres of range ranges (P,)) wanted (``want`` (n, D + P) bool, or (0, 0):
    all) whose light can matter there (in front of ns; LocalLights: within range),
    one ray. Returns point (k,) int64, light (k,) int64 (distant then local index),
    origins (k, 3), dirs (k, 3), tfar (k,) float32 and dist (k,) float32 (LocalLights:
    metres to the light, >= ``min_distance``; DistantLights: ``far``), point-major.
    Origins leave the surface by eps along ng on the ray's side (``_side``, the
    boundary's rule); LocalLight rays stop eps short of the light."""
    n, n_distant, n_local = rel.shape[0], dirs.shape[0], pos.shape[0]
    n_lights = n_distant + n_local
    every = want.shape[0] == 0
    take = np.zeros((n, n_lights), np.bool_)
    k = 0
    for i in range(n):
        for j in range(n_lights):
            if not (every or want[i, j]):
                continue
            if j < n_distant:
                nl = ns[i, 0] * dirs[j, 0] + ns[i, 1] * dirs[j, 1] + ns[i, 2] * dirs[j, 2]
                ok = nl > 0.0
            else:
                q = j - n_distant
                t0, t1, t2 = pos[q, 0] - rel[i, 0], pos[q, 1] - rel[i, 1], pos[q, 2] - rel[i, 2]
                nl = ns[i, 0] * t0 + ns[i, 1] * t1 + ns[i, 2] * t2
                ok = nl > 0.0 and t0 * t0 + t1 * t1 + t2 * t2 < ranges[q] * ranges[q]
            take[i, j] = ok
            k += ok
    point = np.empty(k, np.int64)
    light = np.empty(k, np.int64)
    origins = np.empty((k, 3), np.float32)
    out_dirs = np.empty((k, 3), np.float32)
    tfar = np.empty(k, np.float32)
    dist = np.empty(k, np.float32)
    r = 0
    for i in range(n):
        for j in range(n_lights):
            if not take[i, j]:
                continue
            e = eps[i]
            if j < n_distant:
                d0, d1, d2 = dirs[j, 0], dirs[j, 1], dirs[j, 2]
                length = far
                stop = far
            else:
                q = j - n_distant
                t0, t1, t2 = pos[q, 0] - rel[i, 0], pos[q, 1] - rel[i, 1], pos[q, 2] - rel[i, 2]
                length = max(math.sqrt(t0 * t0 + t1 * t1 + t2 * t2), min_distance)
                d0, d1, d2 = t0 / length, t1 / length, t2 / length
                # Stop short of the light by the offset so the light's own position is free.
                stop = max(length - e, 0.0)
            side = _side(e, d0, d1, d2, ng[i, 0], ng[i, 1], ng[i, 2])
            for c in range(3):
                origins[r, c] = rel[i, c] + side * ng[i, c]
            out_dirs[r, 0], out_dirs[r, 1], out_dirs[r, 2] = d0, d1, d2
            point[r], light[r], tfar[r], dist[r] = i, j, stop, length
            r += 1
    return point, light, origins, out_dirs, tfar, dist
