"""The surface rule compiled: the per-pixel and per-hit loops of ``model.surface``.

The raster G-buffer's derivation (``derive``: a pixel ray
against its triangle's plane) and the tracer's hit geometry (``hit_geometry``: Embree's
barycentrics on a triangle) are the hot loops of a frame: per point a gather of one
``TriangleTable`` row, a few dot products and the side rule. As numpy they are a dozen
array passes with temporaries each; here one fused loop per point, compiled by numba
(``nogil``: callers split the work over their own thread pools, so ``--threads`` is the
only thread setting; numba's ``parallel`` is not used, its default threading layer is
not safe for concurrent callers).

One rule, one implementation: the side rule of every shading normal (raster and trace)
is ``_orient`` below, the corner interpolation ``_weighted``. ``model.surface`` keeps
the numpy interpolation for the rest of its API (normal maps, textures); a numpy form
of the side rule is the tests' reference (``tests/surface_reference.py``):
the same operations in the same order and precision (float64 planes and positions,
float32 weights and corner data), so results agree to rounding of a sum's order.

Spaces and shapes as in ``model.surface``: rel = world metres minus ``Scene.origin``
(float64); T triangles; pixels flat over an H x W image (row 0 = top).

Callers take the kernels through ``phrt_usd.kernels.load`` (numba, compiled once into
phrt's kernel cache); ``warm_up`` compiles each with the argument types the renderer
passes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from phrt_usd.kernels import KERNEL_OPTIONS
from phrt_usd.model.scene import NO_HIT
from phrt_usd.model.surface import MIN_NORMAL_LENGTH

#: Denominator floor (relative to |face normal|) of the ray-plane intersection. A pixel
#: is only covered by a triangle the rasterizer saw with non-zero screen area, so the ray
#: is not parallel to its plane; the floor only guards against rounding, and the
#: resulting distance is clamped to the near/far range the rasterizer used.
GRAZING_EPS = 1e-12
#: Floor of the barycentric weights' sum before they are renormalised (clamping onto the
#: triangle can zero them all only for a degenerate triangle; any positive floor keeps
#: the division finite).
MIN_WEIGHT_SUM = 1e-12

_MIN_LEN32 = np.float32(MIN_NORMAL_LENGTH)

# Array arguments are read and written only in the kernels themselves: numba counts the
# references of an array handed to another compiled function (two atomic operations per
# array per call), which in a per-point helper cost more than the arithmetic. The
# helpers take and return scalars.
_KERNEL = KERNEL_OPTIONS
_HELPER = {**_KERNEL, "inline": "always"}


@njit(**_HELPER)
def _weighted(w0, w1, w2, a0, a1, a2):
    """One channel of the corner interpolation (``surface.interpolate``): float32
    w0 a0 + w1 a1 + w2 a2, summed in that order."""
    return w0 * a0 + w1 * a1 + w2 * a2


@njit(**_HELPER)
def _orient(nx, ny, nz, side, dx, dy, dz, fx, fy, fz):
    """The side rule (``model.surface``'s docstring) for one point: the interpolated
    corner normal (nx, ny, nz) float32 turned to the viewer's ``side`` (+1, or -1 where
    the ray runs along the front normal) and made unit; where it is degenerate (shorter
    than MIN_NORMAL_LENGTH, or NaN) or still faces along the unit incoming ray (dx, dy,
    dz) float64, the triangle's unit front normal (fx, fy, fz) times ``side``. Returns
    three float32."""
    s = np.float32(side)
    nx, ny, nz = nx * s, ny * s, nz * s
    length = np.float32(math.sqrt(nx * nx + ny * ny + nz * nz))
    along = float(nx) * dx + float(ny) * dy + float(nz) * dz
    if not (length >= _MIN_LEN32) or along >= 0.0:
        return np.float32(fx * side), np.float32(fy * side), np.float32(fz * side)
    inv = max(length, _MIN_LEN32)
    return nx / inv, ny / inv, nz / inv


@njit(**_HELPER)
def _plane_weights(bv, bw):
    """The barycentric weights (w0, w1, w2) float64 of a point whose weights of corners
    1 and 2 on its triangle's plane are bv, bw (``TriangleTable.plane``), clamped onto
    the triangle (a point on an edge may lie a rounding error outside) and renormalised."""
    b0 = min(max(1.0 - bv - bw, 0.0), 1.0)
    b1 = min(max(bv, 0.0), 1.0)
    b2 = min(max(bw, 0.0), 1.0)
    total = max(b0 + b1 + b2, MIN_WEIGHT_SUM)
    return b0 / total, b1 / total, b2 / total


@njit(**_HELPER)
def _below(ox, oy, oz, nx, ny, nz):
    """How far (metres, <= 0) a point p lies below the tangent plane of a corner v of
    normal n (float32, any length), from o = p - v: min(0, o·n̂), and n̂ (float64);
    a degenerate normal gives 0 (no plane). The smooth surface a triangle's corner
    normals imply passes through p's projections onto these planes (Hanika's rule,
    ``trace_kernels.shadow_rays``)."""
    length = math.sqrt(float(nx) * nx + float(ny) * ny + float(nz) * nz)
    if not (length > 1e-12):
        return 0.0, 0.0, 0.0, 0.0
    ux, uy, uz = nx / length, ny / length, nz / length
    return min(ox * ux + oy * uy + oz * uz, 0.0), ux, uy, uz


@njit(**_HELPER)
def _smooth_lift(t, px, py, pz, s, plane, frame, corners):
    """The move (float64 metres) of a point p on triangle t onto the smooth surface its
    corner normals imply (Hanika, "Hacking the Shadow Terminator", Ray Tracing Gems II
    ch. 4): p projected onto each corner's tangent plane it lies below (a convex corner;
    a concave one leaves it), the projections weighted by p's barycentrics; ``s`` (+1 /
    -1) turns the corner normals to the lit side. Tables: ``TriangleTable``'s (read only
    where a shadow ray needs the lift: the terminator's few points)."""
    w0, w1, w2 = _plane_weights(
        px * plane[t, 0] + py * plane[t, 1] + pz * plane[t, 2] - plane[t, 3],
        px * plane[t, 4] + py * plane[t, 5] + pz * plane[t, 6] - plane[t, 7],
    )  # fmt: skip
    lx = ly = lz = 0.0
    for k in range(3):  # corner k at v0 + e_k (e_0 = 0)
        w, c = (w0, 0.0) if k == 0 else ((w1, 1.0) if k == 1 else (w2, 1.0))
        h, ux, uy, uz = _below(
            px - frame[t, 0, 0] - c * frame[t, k, 0],
            py - frame[t, 0, 1] - c * frame[t, k, 1],
            pz - frame[t, 0, 2] - c * frame[t, k, 2],
            s * corners[t, k, 0], s * corners[t, k, 1], s * corners[t, k, 2],
        )  # fmt: skip
        lx, ly, lz = lx - w * h * ux, ly - w * h * uy, lz - w * h * uz
    return lx, ly, lz


@njit(**_KERNEL)
def terminator_lifts(points, origin, tri, ns, smooth, plane, frame, corners, distant, local,
                     fade, normals, lifts):  # fmt: skip
    """The shadow terminator's data of n points (n, 3) float64 (rel = points - origin
    (3,), the tables' space) on triangles tri (n,) int64 (-1: none) with shading normals
    ns (n, 3): into lifts (n, 3) float32 each point's move onto the smooth surface its
    triangle's corner normals imply (``_smooth_lift``, the corners turned to ns's side),
    and into normals (n, 3) float32 its triangle's unit face normal n_g turned to ns's
    side; both 0 where the move is 0 (a triangle not ``smooth`` (T,) bool,
    ``TriangleTable.smooth``; a concave corner; no triangle) or is never taken: without
    LocalLights (``local`` False), where for each DistantLight's unit direction l of
    ``distant`` (D, 3) n_g·l >= ``fade`` (``TERMINATOR_FADE``) or ns·l <= 0 (no light to
    shadow). Returns how many points move."""
    count = 0
    for i in range(tri.shape[0]):
        normals[i, 0], normals[i, 1], normals[i, 2] = 0.0, 0.0, 0.0
        lifts[i, 0], lifts[i, 1], lifts[i, 2] = 0.0, 0.0, 0.0
        t = tri[i]
        if t < 0 or not smooth[t]:
            continue
        gx, gy, gz = frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2]
        s = 1.0 if gx * ns[i, 0] + gy * ns[i, 1] + gz * ns[i, 2] >= 0.0 else -1.0
        taken = local
        for k in range(distant.shape[0]):  # lit by the shading normal, face within the fade
            lit = ns[i, 0] * distant[k, 0] + ns[i, 1] * distant[k, 1] + ns[i, 2] * distant[k, 2]
            up = s * (gx * distant[k, 0] + gy * distant[k, 1] + gz * distant[k, 2])
            if lit > 0.0 and up < fade:
                taken = True
        if not taken:
            continue
        px, py, pz = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        lx, ly, lz = _smooth_lift(t, px, py, pz, s, plane, frame, corners)
        if lx == 0.0 and ly == 0.0 and lz == 0.0:
            continue
        normals[i, 0], normals[i, 1], normals[i, 2] = s * gx, s * gy, s * gz
        lifts[i, 0], lifts[i, 1], lifts[i, 2] = lx, ly, lz
        count += 1
    return count


@njit(**_HELPER)
def _inside(t, px, py, pz, plane):
    """The point p of triangle t's plane lies on the triangle (its weights >= 0)."""
    b1 = px * plane[t, 0] + py * plane[t, 1] + pz * plane[t, 2] - plane[t, 3]
    b2 = px * plane[t, 4] + py * plane[t, 5] + pz * plane[t, 6] - plane[t, 7]
    return b1 >= 0.0 and b2 >= 0.0 and b1 + b2 <= 1.0


@njit(**_HELPER)
def _pixel_dir(ys_row, xs_col, s, r00, r01, r02, r10, r11, r12, r20, r21, r22,
               renormalise):  # fmt: skip
    """The unit world direction through the centre of a pixel (as
    ``CameraFrame.pixel_rays``): (y rot_y - rot_z + x rot_x) * s, s = 1 / |(x, y, -1)|,
    for the camera-to-world rotation rows r (3, 3)."""
    dx = ((ys_row * r01 - r02) + xs_col * r00) * s
    dy = ((ys_row * r11 - r12) + xs_col * r10) * s
    dz = ((ys_row * r21 - r22) + xs_col * r20) * s
    if renormalise:  # a camera transform with scale or shear
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx / length, dy / length, dz / length
    return dx, dy, dz


@njit(**_KERNEL)
def derive(
    pixels, tris, lo, hi, ids, tri_map, xs, ys, inv_len, rot, renormalise, eye, near, far,
    fwd, origin, plane, corners, frame, tri_element,
    out_tri, out_elem, out_depth, out_pos, out_normal, out_albedo, out_view, out_bary,
):  # fmt: skip
    """The G-buffer rows of pixels, from the id image (the raster's pass) or given
    triangles.

    Which pixels: with ``pixels`` (k,) int64 non-empty, those pixels on triangles
    ``tris`` (k,) int64 (cut-out peeling: the surface behind a hole; ``out_view`` is then
    not written); else flat pixels ``lo``..``hi`` of ``ids`` (H*W,) uint32 (0 background,
    id k = row k - 1 of ``tri_map``, or triangle k - 1 when ``tri_map`` is empty).

    xs (W,), ys (H,), inv_len (H, W): the pixel plane (``CameraFrame.pixel_plane``) and
    1 / |(x, y, -1)|; rot (3, 3) the camera-to-world rotation; eye (3,) rel; near, far:
    the projection's clip range (metres); fwd (3,) unit view direction; origin (3,)
    ``Scene.origin``; plane, corners, frame: ``TriangleTable``; tri_element (T,) int64.

    Writes per pixel out_tri / out_elem (H*W,) int32, out_depth (H*W,) float32 view
    depth, out_pos (H*W, 3) float64 world, out_normal and out_albedo (H*W, 3) float32,
    out_view (H*W, 3) float32 unit view directions, out_bary (H*W, 3) float32 weights
    (only when it has rows). A background pixel of the id image gets ids NO_HIT, depth
    inf, position and albedo 0, its view direction and normal = -view direction (its
    weights are not written)."""
    width = xs.shape[0]
    listed = pixels.shape[0] > 0
    count = pixels.shape[0] if listed else hi - lo
    n_ids = tri_map.shape[0] if tri_map.shape[0] else plane.shape[0]
    keep_weights = out_bary.shape[0] > 0
    for i in range(count):
        p = pixels[i] if listed else lo + i
        row, col = p // width, p % width
        dx, dy, dz = _pixel_dir(
            ys[row], xs[col], inv_len[row, col], rot[0, 0], rot[0, 1], rot[0, 2],
            rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0], rot[2, 1], rot[2, 2], renormalise,
        )  # fmt: skip
        if listed:
            t = tris[i]
        else:
            vx, vy, vz = np.float32(dx), np.float32(dy), np.float32(dz)
            out_view[p, 0], out_view[p, 1], out_view[p, 2] = vx, vy, vz
            k = np.int64(ids[p])
            if k <= 0 or k > n_ids:  # background (see the docstring)
                out_normal[p, 0], out_normal[p, 1], out_normal[p, 2] = -vx, -vy, -vz
                out_tri[p] = NO_HIT
                out_elem[p] = NO_HIT
                out_depth[p] = np.inf
                for j in range(3):
                    out_pos[p, j] = 0.0
                    out_albedo[p, j] = 0.0
                continue
            t = tri_map[k - 1] if tri_map.shape[0] else k - 1
        # Ray-plane intersection in float64, rel space: dist = (h - n·o) / n·d.
        ngx, ngy, ngz = plane[t, 8], plane[t, 9], plane[t, 10]
        den = ngx * dx + ngy * dy + ngz * dz
        floor = GRAZING_EPS * plane[t, 12]
        if abs(den) < floor:
            den = -floor if den < 0.0 else floor
        if den == 0.0:
            den = 1.0  # zero-area triangle: dist is clamped just below
        side = -1.0 if den > 0.0 else 1.0  # the back face is seen where n_g · d > 0
        dist = (plane[t, 11] - (ngx * eye[0] + ngy * eye[1] + ngz * eye[2])) / den
        dist = min(max(dist, near), far)
        px, py, pz = eye[0] + dist * dx, eye[1] + dist * dy, eye[2] + dist * dz
        # Barycentrics clamped onto the triangle (a pixel centre on an edge may lie a
        # rounding error outside) and renormalised; float32 from here on.
        bv = px * plane[t, 0] + py * plane[t, 1] + pz * plane[t, 2] - plane[t, 3]
        bw = px * plane[t, 4] + py * plane[t, 5] + pz * plane[t, 6] - plane[t, 7]
        b0, b1, b2 = _plane_weights(bv, bw)
        w0, w1, w2 = np.float32(b0), np.float32(b1), np.float32(b2)
        nx, ny, nz = _orient(
            _weighted(w0, w1, w2, corners[t, 0, 0], corners[t, 1, 0], corners[t, 2, 0]),
            _weighted(w0, w1, w2, corners[t, 0, 1], corners[t, 1, 1], corners[t, 2, 1]),
            _weighted(w0, w1, w2, corners[t, 0, 2], corners[t, 1, 2], corners[t, 2, 2]),
            side, dx, dy, dz, frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2],
        )  # fmt: skip
        out_normal[p, 0], out_normal[p, 1], out_normal[p, 2] = nx, ny, nz
        for j in range(3, 6):
            out_albedo[p, j - 3] = _weighted(
                w0, w1, w2, corners[t, 0, j], corners[t, 1, j], corners[t, 2, j]
            )
        if keep_weights:
            out_bary[p, 0], out_bary[p, 1], out_bary[p, 2] = w0, w1, w2
        out_tri[p] = t
        out_elem[p] = tri_element[t]
        out_pos[p, 0] = px + origin[0]
        out_pos[p, 1] = py + origin[1]
        out_pos[p, 2] = pz + origin[2]
        out_depth[p] = dist * (dx * fwd[0] + dy * fwd[1] + dz * fwd[2])


@njit(**_KERNEL)
def hit_geometry(tri, u, v, incoming, frame, corners, pos, ng, ns):
    """The surface at ray hits (the tracer's side): rel position v0 + u e1 + v e2 into
    ``pos`` (m, 3) float64, the front normal turned against the ray into ``ng`` (m, 3)
    float64 and the shading normal by the side rule into ``ns`` (m, 3) float32.

    tri (m,) int64 triangle ids; u, v (m,) float32 Embree barycentrics (weights of corners
    1 and 2, ``surface.weights_from_uv``); incoming (m, 3) float64 unit ray directions;
    frame, corners: ``TriangleTable``."""
    for i in range(tri.shape[0]):
        t = tri[i]
        fu, fv = float(u[i]), float(v[i])
        for j in range(3):
            pos[i, j] = frame[t, 0, j] + fu * frame[t, 1, j] + fv * frame[t, 2, j]
        dx, dy, dz = incoming[i, 0], incoming[i, 1], incoming[i, 2]
        fx, fy, fz = frame[t, 3, 0], frame[t, 3, 1], frame[t, 3, 2]
        side = -1.0 if fx * dx + fy * dy + fz * dz > 0.0 else 1.0
        ng[i, 0], ng[i, 1], ng[i, 2] = fx * side, fy * side, fz * side
        w1, w2 = u[i], v[i]
        w0 = np.float32(1.0) - w1 - w2
        ns[i, 0], ns[i, 1], ns[i, 2] = _orient(
            _weighted(w0, w1, w2, corners[t, 0, 0], corners[t, 1, 0], corners[t, 2, 0]),
            _weighted(w0, w1, w2, corners[t, 0, 1], corners[t, 1, 1], corners[t, 2, 1]),
            _weighted(w0, w1, w2, corners[t, 0, 2], corners[t, 1, 2], corners[t, 2, 2]),
            side, dx, dy, dz, fx, fy, fz,
        )  # fmt: skip


@njit(**_KERNEL)
def hit_albedo(tri, u, v, corners, out):
    """Interpolated corner albedo (m, 3) float32 into ``out`` at hits on ``tri`` (m,)
    with Embree barycentrics u, v (m,) float32."""
    for i in range(tri.shape[0]):
        t = tri[i]
        w1, w2 = u[i], v[i]
        w0 = np.float32(1.0) - w1 - w2
        for j in range(3, 6):
            out[i, j - 3] = _weighted(
                w0, w1, w2, corners[t, 0, j], corners[t, 1, j], corners[t, 2, j]
            )


def warm_up() -> None:
    """Compile (or load from phrt's kernel cache) every kernel on tiny inputs of the types
    the renderer passes."""
    plane = np.zeros((1, 13))
    plane[0, 8:13] = (0.0, 0.0, 1.0, 0.0, 1.0)
    corners = np.zeros((1, 3, 6), np.float32)
    frame = np.zeros((1, 4, 3))
    frame[0, 3] = (0.0, 0.0, 1.0)
    one = np.zeros(1, np.int64)
    i32, f32 = np.zeros(1, np.int32), np.zeros(1, np.float32)
    v64, v32 = np.zeros((1, 3)), np.zeros((1, 3), np.float32)
    view = (np.zeros(1), np.zeros(1), np.ones((1, 1)), np.eye(3), False, np.zeros(3), 0.1,
            10.0, np.array([0.0, 0.0, -1.0]), np.zeros(3))  # fmt: skip
    outs = (i32, i32.copy(), f32, v64, v32, v32.copy(), v32.copy(), v32.copy())
    derive(one[:0], one[:0], 0, 1, np.ones(1, np.uint32), one[:0], *view, plane, corners,
           frame, one, *outs)  # fmt: skip
    hit_geometry(one, f32, f32, v64, frame, corners, v64.copy(), v64.copy(), v32.copy())
    hit_albedo(one, f32, f32, corners, v32.copy())
    terminator_lifts(v64.copy(), np.zeros(3), one, v32.copy(), np.ones(1, np.bool_), plane,
                     frame, corners, v64.copy(), True, 0.1, v32.copy(), v32.copy())  # fmt: skip
