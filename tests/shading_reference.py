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
    SHININESS,
    SPECULAR_STRENGTH,
    LightPairs,
    ambient_radiance,
    light_ranges,
    shaped_lights,
)
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, Lights, LocalLight, Scene

_MIN_DIRECTION_LENGTH = 1e-30
_SHININESS_SQUARINGS = (
    int(np.log2(SHININESS))
    if SHININESS >= 1
    and float(SHININESS).is_integer()
    and (int(SHININESS) & (int(SHININESS) - 1)) == 0
    else None
)


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
    albedo: np.ndarray,
    view_dirs: np.ndarray,
    emissive: np.ndarray,
    lights: Lights,
    visibility: np.ndarray | None,
    local_pairs: LightPairs | tuple | None = None,
    lit_sums: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """``shade_local`` on one chunk of points (same arguments and result)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = positions.shape[0]
    normals = np.asarray(normals, dtype=np.float32).reshape(n, 3)
    albedo = np.asarray(albedo, dtype=np.float32).reshape(n, 3)
    to_eye = -np.asarray(view_dirs, dtype=np.float32).reshape(n, 3)
    colour = albedo * ambient_radiance(lights)[None, :]
    colour += np.broadcast_to(np.asarray(emissive, dtype=np.float32), (n, 3))
    if lit_sums is not None:
        colour += albedo * lit_sums[0] + lit_sums[1]
    if not lights.has_direct or n == 0:
        return colour.astype(np.float32)
    # Per point and light colour: the summed diffuse weights (cosine x fall-off x
    # visibility) and highlight weights of the lights of that radiance, times the
    # radiance once at the end (lamps usually share a colour: the sewer's 13 lights
    # have 2, so 2 instead of 13 (n, 3) products).
    radiance, group = np.unique(
        np.array(
            [li.radiance for li in lights.distant] + [li.radiance for li in lights.local],
            dtype=np.float32,
        ).reshape(-1, 3),
        axis=0,
        return_inverse=True,
    )
    group = group.reshape(-1)
    diffuse = np.zeros((len(radiance), n), dtype=np.float32)
    highlight = np.zeros((len(radiance), n), dtype=np.float32)
    for j, light in enumerate(lights.distant):
        d = np.asarray(light.direction, dtype=np.float64)
        l_dir = (d / max(np.linalg.norm(d), _MIN_DIRECTION_LENGTH)).astype(np.float32)
        lit = np.maximum(normals @ l_dir, 0.0)
        if visibility is not None:
            lit = lit * visibility[:, j]
        idx = np.flatnonzero(lit > 0.0)
        lit = lit[idx]
        diffuse[group[j], idx] += lit
        highlight[group[j], idx] += lit * _highlight(
            np.take(normals, idx, axis=0), np.take(to_eye, idx, axis=0), l_dir[None, :]
        )
    n_distant = len(lights.distant)
    ranges = light_ranges(lights)
    if local_pairs is not None:
        point, light, l_dir, dist, weight = LightPairs(*local_pairs)
        j = n_distant + np.asarray(light, np.int64)
        nrm = np.take(normals, point, axis=0)
        l_dir = np.asarray(l_dir, np.float32)
        dist = np.maximum(np.asarray(dist, np.float64), MIN_LIGHT_DISTANCE)
        n_dot_l = np.maximum(np.einsum("ij,ij->i", nrm, l_dir), 0.0)
        lit = (n_dot_l * _window(dist, ranges[j]) / dist**2).astype(np.float32)
        if weight is not None:
            lit *= weight
        if shaped_lights(lights):  # the cone of each shaped light on its own pairs
            for k in np.unique(light).tolist():
                if lights.local[k].shaped:
                    on = np.flatnonzero(light == k)
                    lit[on] *= cone_falloff(lights.local[k], -l_dir[on])
        spec = lit * _highlight(nrm, np.take(to_eye, point, axis=0), l_dir)
        # Pairs of one light never repeat a point, but several lights share a colour
        # group: sum with bincount over (group, point).
        key = group[j] * n + point
        size = len(radiance) * n
        diffuse += np.bincount(key, weights=lit, minlength=size).reshape(-1, n)
        highlight += np.bincount(key, weights=spec, minlength=size).reshape(-1, n)
    # Light-major visibility: each light's column becomes one contiguous row.
    vis_rows = None if visibility is None else np.ascontiguousarray(visibility.T)
    skip_local = local_pairs is not None or lit_sums is not None
    for k, light in enumerate([] if skip_local else lights.local):
        j = n_distant + k
        # Only points that see the light (visibility > 0), within its range (the window
        # is exactly 0 beyond) and on the lit side of their normal are shaded.
        if vis_rows is None:
            idx = np.arange(n)
            to_light = np.asarray(light.position, dtype=np.float64) - positions
        else:
            idx = np.flatnonzero(vis_rows[j] > 0.0)
            to_light = np.asarray(light.position, dtype=np.float64) - np.take(
                positions, idx, axis=0
            )
        dist2 = np.einsum("ij,ij->i", to_light, to_light)
        near = dist2 < ranges[j] ** 2
        if not near.all():  # shadow maps already zero these: usually nothing to drop
            idx, to_light, dist2 = idx[near], to_light[near], dist2[near]
        dist2 = np.maximum(dist2, MIN_LIGHT_DISTANCE**2)
        inv_dist = 1.0 / np.sqrt(dist2)
        l_dir = (to_light * inv_dist[:, None]).astype(np.float32)
        nrm = np.take(normals, idx, axis=0)
        n_dot_l = np.einsum("ij,ij->i", nrm, l_dir)
        front = n_dot_l > 0.0
        if not front.all():
            idx, nrm, l_dir = idx[front], nrm[front], l_dir[front]
            dist2, n_dot_l = dist2[front], n_dot_l[front]
        # Window and 1/d² in float64: d up to ~1e154 stays finite, and the float32 cast
        # of a tiny fall-off underflows to 0 instead of overflowing d² to Inf.
        lit = (n_dot_l * (_window_sq(dist2, ranges[j]) / dist2)).astype(np.float32)
        if vis_rows is not None:
            lit *= vis_rows[j, idx]
        if light.shaped:
            lit *= cone_falloff(light, -l_dir)
        # idx has no repeats, so the buffered fancy-index += is exact.
        diffuse[group[j], idx] += lit
        highlight[group[j], idx] += lit * _highlight(nrm, np.take(to_eye, idx, axis=0), l_dir)
    for g, rad in enumerate(radiance):
        colour += (albedo * diffuse[g][:, None] + highlight[g][:, None]) * rad
    return colour.astype(np.float32)


def _highlight(normals: np.ndarray, to_eye: np.ndarray, l_dir: np.ndarray) -> np.ndarray:
    """(m,) float32 Blinn-Phong highlight SPECULAR_STRENGTH * max(n·h, 0)**SHININESS for
    unit normals, directions to the eye (m, 3) and to the light (m, 3) or (1, 3)."""
    half = l_dir + to_eye
    half_len = np.sqrt(np.einsum("ij,ij->i", half, half))
    # l and the eye direction exactly opposite: no meaningful half vector, no highlight.
    n_dot_h = np.einsum("ij,ij->i", normals, half) / np.maximum(half_len, 1e-12)
    x = np.maximum(n_dot_h, 0.0)
    if _SHININESS_SQUARINGS is not None:  # x**64 as 6 squarings: ~10x faster than pow
        for _ in range(_SHININESS_SQUARINGS):
            x *= x
    else:
        x = x**SHININESS
    return SPECULAR_STRENGTH * x


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
