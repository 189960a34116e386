"""The numpy reference of the compiled shading kernels (``phrt_usd.engine.shading``,
``phrt_usd.engine.compositing``): the vectorised code the kernels replaced, kept as the
specification they are tested against (``tests/engine/test_shading_kernels.py``). Same
arguments, shapes and coordinate spaces as the functions they mirror (``shade_chunk`` is
one ``shade_local`` chunk).
"""

from __future__ import annotations

import numpy as np

from phrt_usd.engine.shading import (
    MIN_LIGHT_DISTANCE,
    LightPairs,
    ambient_radiance,
    light_ranges,
    shaped_lights,
)
from phrt_usd.model import preview_surface as ps
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, Lights, LocalLight, Scene

_MIN_DIRECTION_LENGTH = 1e-30
def _safe_normalize(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (n, 3) scaled to unit length; rows of (near) zero length or
    non-finite become ``fallback`` (3,). Returns float64 (n, 3)."""
    v = np.asarray(v, dtype=np.float64)
    length2 = np.einsum("ij,ij->i", v, v)
    if np.all((length2 > _MIN_DIRECTION_LENGTH**2) & (length2 < np.inf)):
        # The usual case (finite, not tiny, |v|² not overflowing): plain division.
        return v / np.sqrt(length2)[:, None]
    finite = np.all(np.isfinite(v), axis=1)
    v = np.where(finite[:, None], v, 0.0)
    # Scale by the largest component first so huge vectors do not overflow when squared.
    big = np.max(np.abs(v), axis=1)
    ok = big > _MIN_DIRECTION_LENGTH
    v = v / np.where(ok, big, 1.0)[:, None]
    norm = np.linalg.norm(v, axis=1)
    out = v / np.where(ok, norm, 1.0)[:, None]
    out[~ok] = fallback
    return out


def _bilinear(texture: np.ndarray, x: np.ndarray, y: np.ndarray, wrap_y: bool) -> np.ndarray:
    """Bilinear sample at continuous pixel coordinates (x: column, y: row; texel centres
    at integer + 0.5 - 0.5 = integers). x always wraps; y wraps or clamps."""
    h, w = texture.shape[:2]
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    c0 = x0 % w
    c1 = (x0 + 1) % w
    if wrap_y:
        r0 = y0 % h
        r1 = (y0 + 1) % h
    else:
        r0 = np.clip(y0, 0, h - 1)
        r1 = np.clip(y0 + 1, 0, h - 1)
    # Gathers from the flattened texture (1-D takes are several times faster than
    # 2-D fancy indexing).
    flat = np.ascontiguousarray(texture, dtype=np.float32).reshape(h * w, -1)
    r0 *= w
    r1 *= w
    top = flat.take(r0 + c0, axis=0) * (1.0 - fx) + flat.take(r0 + c1, axis=0) * fx
    bottom = flat.take(r1 + c0, axis=0) * (1.0 - fx) + flat.take(r1 + c1, axis=0) * fx
    return top * (1.0 - fy) + bottom * fy


def environment_radiance(lights: Lights, directions: np.ndarray) -> np.ndarray:
    """Radiance arriving from the environment along world directions.

    directions : (n, 3) world-space directions (any length; zero or non-finite ones look
                 up the dome's +Y pole instead of producing NaN)
    Returns (n, 3) float32 linear RGB.
    """
    directions = np.asarray(directions).reshape(-1, 3)
    n = directions.shape[0]
    dome = lights.dome
    if dome is None:
        return np.broadcast_to(DEFAULT_ENVIRONMENT.astype(np.float32), (n, 3)).copy()
    colour = np.asarray(dome.color, dtype=np.float32).reshape(3)
    if dome.texture is None:
        return np.broadcast_to(colour, (n, 3)).copy()
    # World → dome space: world_from_light is a rotation, so its inverse is its transpose;
    # for row vectors d_light = d_world @ world_from_light.
    d = _safe_normalize(directions, np.array([0.0, 1.0, 0.0]) @ dome.world_from_light.T)
    d = d @ np.asarray(dome.world_from_light, dtype=np.float64)
    latitude = np.arcsin(np.clip(d[:, 1], -1.0, 1.0))
    longitude = np.arctan2(d[:, 0], d[:, 2])
    h, w = dome.texture.shape[:2]
    x = (np.pi - longitude) / (2.0 * np.pi) * w - 0.5
    y = (0.5 * np.pi - latitude) / np.pi * h - 0.5
    return _bilinear(dome.texture, x, y, wrap_y=False) * colour


def _window(distance: np.ndarray, light_range: np.ndarray) -> np.ndarray:
    """``range_window`` with a range per distance (both (m,) float64; ranges > 0)."""
    x = (distance / light_range) ** 2
    return np.clip(1.0 - x * x, 0.0, 1.0) ** 2


def _window_sq(distance2: np.ndarray, light_range: float) -> np.ndarray:
    """``range_window`` from squared distances (m,) float64 (saves the square root)."""
    if not light_range > 0.0:
        return np.zeros(np.shape(distance2))
    x = distance2 / (light_range * light_range)
    return np.clip(1.0 - x * x, 0.0, 1.0) ** 2


def range_window(distance: np.ndarray, light_range: float) -> np.ndarray:
    """Smooth cut-off factor (n,) float64 in [0, 1] of a LocalLight at ``distance`` (n,)
    metres: ``clamp(1 - (d / r)**4, 0, 1)**2`` (the Frostbite / Unreal window): 1 near
    the light, falling to exactly 0 at and beyond ``light_range`` with zero slope there,
    so no ring marks the range. ``light_range`` <= 0 gives 0 everywhere."""
    return _window_sq(np.asarray(distance, dtype=np.float64) ** 2, light_range)


def cone_falloff(light: LocalLight, emission: np.ndarray) -> np.ndarray:
    """UsdLux ShapingAPI factor (m,) float32 in [0, 1] of ``light``'s emission along
    ``emission`` (m, 3) world unit directions *from the light* to the points: the one
    cone of raster and trace alike.

    As the schema defines it (``inputs:shaping:cone:angle`` / ``:softness`` /
    ``:focus``): with θ the angle between ``light.axis`` and the emission, θc the cone
    angle and θs = θc (1 - softness), the factor is ``1 - smoothstep(θs, θc, θ)`` (0
    beyond the cone; at softness 0 a hard edge, 1 up to θc) times ``|cos θ|**focus``
    (``focusTint`` black). A light that is not ``shaped`` gives 1."""
    m = len(emission)
    if not light.shaped:
        return np.ones(m, dtype=np.float32)
    cos = np.clip(np.asarray(emission, np.float64) @ np.asarray(light.axis, np.float64), -1, 1)
    factor = np.ones(m)
    if light.cone_angle < 180.0:
        theta = np.arccos(cos)
        cutoff = np.radians(light.cone_angle)
        start = cutoff * (1.0 - light.cone_softness)
        width = cutoff - start
        if width > 0.0:
            x = np.clip((theta - start) / width, 0.0, 1.0)
            factor = 1.0 - x * x * (3.0 - 2.0 * x)
        factor = np.where(theta > cutoff, 0.0, factor)
    if light.focus > 0.0:
        factor = factor * np.abs(cos) ** light.focus
    return factor.astype(np.float32)


def shade_chunk(
    positions: np.ndarray,
    normals: np.ndarray,
    surface: np.ndarray,
    view_dirs: np.ndarray,
    emissive: np.ndarray,
    lights: Lights,
    visibility: np.ndarray | None,
    local_pairs: LightPairs | tuple | None = None,
    lit_sums: np.ndarray | None = None,
) -> np.ndarray:
    """``shade_local`` on one chunk of points (same arguments and result)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = positions.shape[0]
    normals = np.asarray(normals, dtype=np.float32).reshape(n, 3)
    surface = np.asarray(surface, np.float32)
    if surface.shape[-1] != ps.SURFACE_COLUMNS:
        surface = ps.fallback_surface(surface.reshape(n, 3))
    to_eye = -np.asarray(view_dirs, dtype=np.float32).reshape(n, 3)
    colour = ambient_weight(surface, normals, to_eye) * ambient_radiance(lights)[None, :]
    colour += np.broadcast_to(np.asarray(emissive, dtype=np.float32), (n, 3))
    if lit_sums is not None:
        colour += np.asarray(lit_sums)[:, :3]
    if not lights.has_direct or n == 0:
        return colour.astype(np.float32)
    # Every (point, light) pair with its direction and E, the light's radiance times
    # fall-off and visibility, then the BRDF once over all of them.
    point_rows, l_rows, e_rows = [], [], []
    for j, light in enumerate(lights.distant):
        d = np.asarray(light.direction, dtype=np.float64)
        l_dir = (d / max(np.linalg.norm(d), _MIN_DIRECTION_LENGTH)).astype(np.float32)
        lit = np.ones(n) if visibility is None else visibility[:, j].astype(np.float64)
        idx = np.flatnonzero((lit > 0.0) & (normals @ l_dir > 0.0))
        point_rows.append(idx)
        l_rows.append(np.broadcast_to(l_dir, (len(idx), 3)))
        e_rows.append(lit[idx, None] * np.asarray(light.radiance, np.float64)[None, :])
    n_distant = len(lights.distant)
    ranges = light_ranges(lights)
    if local_pairs is not None:
        point, light, l_dir, dist, weight = LightPairs(*local_pairs)
        j = n_distant + np.asarray(light, np.int64)
        l_dir = np.asarray(l_dir, np.float32)
        dist = np.maximum(np.asarray(dist, np.float64), MIN_LIGHT_DISTANCE)
        e = _window(dist, ranges[j]) / dist**2
        if weight is not None:
            e = e * weight
        if shaped_lights(lights):  # the cone of each shaped light on its own pairs
            for k in np.unique(light).tolist():
                if lights.local[k].shaped:
                    on = np.flatnonzero(light == k)
                    e[on] *= cone_falloff(lights.local[k], -l_dir[on])
        rad = np.array([li.radiance for li in lights.local], np.float64).reshape(-1, 3)
        point_rows.append(np.asarray(point, np.int64))
        l_rows.append(l_dir)
        e_rows.append(e[:, None] * rad[np.asarray(light, np.int64)])
    skip_local = local_pairs is not None or lit_sums is not None
    for k, light in enumerate([] if skip_local else lights.local):
        j = n_distant + k
        to_light = np.asarray(light.position, dtype=np.float64) - positions
        dist2 = np.einsum("ij,ij->i", to_light, to_light)
        keep = dist2 < ranges[j] ** 2
        if visibility is not None:
            keep &= visibility[:, j] > 0.0
        idx = np.flatnonzero(keep)
        dist2 = np.maximum(dist2[idx], MIN_LIGHT_DISTANCE**2)
        l_dir = (to_light[idx] / np.sqrt(dist2)[:, None]).astype(np.float32)
        # Window and 1/d² in float64: d up to ~1e154 stays finite.
        e = _window_sq(dist2, ranges[j]) / dist2
        if visibility is not None:
            e = e * visibility[idx, j]
        if light.shaped:
            e = e * cone_falloff(light, -l_dir)
        point_rows.append(idx)
        l_rows.append(l_dir)
        e_rows.append(e[:, None] * np.asarray(light.radiance, np.float64)[None, :])
    point = np.concatenate(point_rows)
    f = brdf_cos(surface[point], normals[point], to_eye[point], np.concatenate(l_rows))
    direct = np.zeros((n, 3))
    np.add.at(direct, point, f * np.concatenate(e_rows))
    return (colour + direct).astype(np.float32)


def _lut(r: np.ndarray, mu: np.ndarray, mean: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the albedo table at roughness r and cosine mu (bilinear, clamped), or
    its row means (``mean``): ``shade_kernels.lut_albedo`` / ``lut_mean``."""
    lut = ps.specular_albedo_table().astype(np.float64)
    n_r, n_c = lut.shape[0], lut.shape[1] - 1
    y = np.clip(r, 0.0, 1.0) * (n_r - 1)
    y0 = np.minimum(y.astype(np.int64), n_r - 2)
    fy = (y - y0)[:, None]
    if mean:
        out = lut[y0, n_c] * (1.0 - fy) + lut[y0 + 1, n_c] * fy
        return out[:, 0], out[:, 1]
    x = np.clip(mu, 0.0, 1.0) * (n_c - 1)
    x0 = np.minimum(x.astype(np.int64), n_c - 2)
    fx = (x - x0)[:, None]
    top = lut[y0, x0] * (1.0 - fx) + lut[y0, x0 + 1] * fx
    bottom = lut[y0 + 1, x0] * (1.0 - fx) + lut[y0 + 1, x0 + 1] * fx
    out = top * (1.0 - fy) + bottom * fy
    return out[:, 0], out[:, 1]


def _ggx_dv(alpha, nl, nv, nh):
    a2 = alpha * alpha
    d = nh * nh * (a2 - 1.0) + 1.0
    v = nl * np.sqrt(nv * nv * (1.0 - a2) + a2) + nv * np.sqrt(nl * nl * (1.0 - a2) + a2)
    return a2 / (np.pi * d * d) * 0.5 / np.maximum(v, 1e-30)


def brdf_cos(surface, normals, to_eye, to_light) -> np.ndarray:
    """(m, 3) π f(l, v) n·l of UsdPreviewSurface rows (m, 16) (the model of
    ``model/preview_surface.py``, ``shade_kernels.brdf_cos``), in numpy."""
    s = np.asarray(surface, np.float64)
    n, e, lt = (np.asarray(a, np.float64) for a in (normals, to_eye, to_light))
    nl = np.einsum("ij,ij->i", n, lt)
    nv = np.maximum(np.einsum("ij,ij->i", n, e), ps.MIN_COSINE)
    h = lt + e
    length = np.linalg.norm(h, axis=1)
    h = np.where(length[:, None] > 1e-12, h / np.maximum(length, 1e-300)[:, None], n)
    nh = np.maximum(np.einsum("ij,ij->i", n, h), 0.0)
    vh = np.clip(np.einsum("ij,ij->i", e, h), 0.0, 1.0)
    s5 = (1.0 - vh) ** 5
    r = np.maximum(s[:, ps.ROUGHNESS], ps.MIN_ROUGHNESS)
    dv = _ggx_dv(r * r, nl, nv, nh)
    av, bv = _lut(r, nv)
    al, bl = _lut(r, nl)
    am, bm = _lut(r, nv, mean=True)
    c, fc0 = s[:, ps.CLEARCOAT], s[:, ps.CLEARCOAT_F0]
    rc = np.maximum(s[:, ps.CLEARCOAT_ROUGHNESS], ps.MIN_ROUGHNESS)
    coat = c * (fc0 + (1.0 - fc0) * s5) * _ggx_dv(rc * rc, nl, nv, nh)
    acv, bcv = _lut(rc, nv)
    acl, bcl = _lut(rc, nl)
    t = (1.0 - c * np.minimum(fc0 * acv + bcv, 1.0)) * (1.0 - c * np.minimum(fc0 * acl + bcl, 1.0))
    f0, f90 = s[:, ps.F0 : ps.F0 + 3], s[:, ps.F90 : ps.F90 + 3]
    ev = np.minimum(f0 * av[:, None] + f90 * bv[:, None], 1.0)
    el = np.minimum(f0 * al[:, None] + f90 * bl[:, None], 1.0)
    mean = np.minimum(f0 * am[:, None] + f90 * bm[:, None], 1.0)
    diffuse = s[:, :3] * (1.0 - ev) * (1.0 - el) / np.maximum(1.0 - mean, 1e-4)
    spec = (f0 + (f90 - f0) * s5[:, None]) * dv[:, None]
    out = ((coat[:, None] + t[:, None] * spec) * np.pi + t[:, None] * diffuse) * nl[:, None]
    return np.where(nl[:, None] > 0.0, out, 0.0)


def ambient_weight(surface, normals, to_eye) -> np.ndarray:
    """(n, 3) ``shade_kernels.ambient_weight`` in numpy."""
    s = np.asarray(surface, np.float64)
    nv = np.maximum(np.einsum("ij,ij->i", np.asarray(normals, np.float64), to_eye), ps.MIN_COSINE)
    r = np.maximum(s[:, ps.ROUGHNESS], ps.MIN_ROUGHNESS)
    av, bv = _lut(r, nv)
    c, fc0 = s[:, ps.CLEARCOAT], s[:, ps.CLEARCOAT_F0]
    rc = np.maximum(s[:, ps.CLEARCOAT_ROUGHNESS], ps.MIN_ROUGHNESS)
    acv, bcv = _lut(rc, nv)
    acm, bcm = _lut(rc, nv, mean=True)
    coat_v = np.where(c > 0.0, c * np.minimum(fc0 * acv + bcv, 1.0), 0.0)
    base = (1.0 - coat_v) * (1.0 - np.where(c > 0.0, c * np.minimum(fc0 * acm + bcm, 1.0), 0.0))
    f0, f90 = s[:, ps.F0 : ps.F0 + 3], s[:, ps.F90 : ps.F90 + 3]
    ev = np.minimum(f0 * av[:, None] + f90 * bv[:, None], 1.0)
    spec, occ = s[:, ps.SPECULAR_AMBIENT, None], s[:, ps.OCCLUSION, None]
    return occ * (spec * coat_v[:, None] + base[:, None] * (spec * ev + s[:, :3] * (1.0 - ev)))


def reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Mirror ``directions`` (n, 3) about unit ``normals`` (n, 3): d - 2 (d·n) n."""
    return directions - 2.0 * np.sum(directions * normals, axis=1, keepdims=True) * normals


def base_image(
    gbuffer: GBuffer, scene: Scene, local: np.ndarray, reflectivity: np.ndarray
) -> np.ndarray:
    """The raster frame: local shading everywhere, environment fallback in reflectors.

    local        : (H, W, 3) float32 local shading (zero where uncovered)
    reflectivity : (H, W) float32 F per pixel
    Returns (H, W, 3) float32.
    """
    # Flat pixel indices and np.take: several times faster than boolean-mask indexing.
    image = np.array(local, dtype=np.float32)  # local is zero where uncovered
    flat = image.reshape(-1, 3)
    view = gbuffer.view_dir.reshape(-1, 3)
    background = np.flatnonzero(~gbuffer.covered.reshape(-1))
    dome = scene.lights.dome
    if len(background) and (dome is None or dome.camera_visible):
        flat[background] = environment_radiance(scene.lights, np.take(view, background, axis=0))
    mirror = np.flatnonzero(reflectivity.reshape(-1) > 0.0)
    if len(mirror):
        f = np.take(reflectivity.reshape(-1), mirror)[:, None]
        normals = np.take(gbuffer.normal.reshape(-1, 3), mirror, axis=0)
        env = environment_radiance(scene.lights, reflect(np.take(view, mirror, axis=0), normals))
        flat[mirror] = (1.0 - f) * np.take(flat, mirror, axis=0) + f * env
    return image


def pair_directions(
    lights: Lights, positions: np.ndarray, point: np.ndarray, light: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (m, 3) float32 and distances (m,) float64 metres (clamped to
    ``MIN_LIGHT_DISTANCE``) from ``positions[point]`` ((n, 3) world metres) to
    ``lights.local[light]``, for m pairs."""
    centres = np.array([li.position for li in lights.local], dtype=np.float64).reshape(-1, 3)
    to_light = np.take(centres, light, axis=0) - np.take(positions, point, axis=0)
    dist = np.maximum(np.sqrt(np.einsum("ij,ij->i", to_light, to_light)), MIN_LIGHT_DISTANCE)
    return (to_light / dist[:, None]).astype(np.float32), dist


def rect_light_integral(p, centre, a: float, b: float) -> float:
    """∫ cos θ_e cos θ_p / d² dA of a rect of half sizes a (along x) and b (along y) at
    ``centre`` facing down (-Z) onto a point ``p`` below it facing up (+Z): the corner sum
    of the parallel rectangle's form factor (times π), G(x, y) = ½ [X / √(1 + X²)
    atan(Y / √(1 + X²)) + Y / √(1 + Y²) atan(X / √(1 + Y²))], X = x / h, Y = y / h."""
    h = centre[2] - p[2]

    def g(x, y):
        x, y = x / h, y / h
        sx, sy = np.sqrt(1 + x * x), np.sqrt(1 + y * y)
        return 0.5 * (x / sx * np.arctan(y / sx) + y / sy * np.arctan(x / sy))

    x0, y0 = centre[0] - p[0], centre[1] - p[1]
    return float(g(x0 + a, y0 + b) - g(x0 - a, y0 + b) - g(x0 + a, y0 - b) + g(x0 - a, y0 - b))


def disk_light_integral(p, centre, r: float) -> float:
    """The same for a disk of radius r: π / 2 [1 - (h² + x² - r²) / √((h² + x² + r²)² -
    4 r² x²)], x the point's distance from the disk's axis (π r² / (r² + h²) on it)."""
    h = centre[2] - p[2]
    x2 = (centre[0] - p[0]) ** 2 + (centre[1] - p[1]) ** 2
    root = np.sqrt((h * h + x2 + r * r) ** 2 - 4.0 * r * r * x2)
    return float(0.5 * np.pi * (1.0 - (h * h + x2 - r * r) / root))


def area_light_factor(p, centre, area: float, integral: float) -> float:
    """The area factor (``area_light_kernels._factor``) of a light facing down at
    ``centre`` of ``area`` m² and irradiance ``integral`` (``rect_light_integral``,
    ``disk_light_integral``) at a point ``p`` facing up: the integral over the point
    light's A cos θ_p,c / d_c²."""
    d = np.asarray(centre, float) - np.asarray(p, float)
    return integral / (area * d[2] / float(np.linalg.norm(d)) ** 3)
