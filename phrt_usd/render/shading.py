"""Local shading shared by the raster path and the ray tracer, so both agree exactly.

Everything here is pure numpy on world-space arrays (metres, linear RGB float32, no tone
mapping). The model, deliberately simple and the same everywhere:

    colour = Σ_lights  visibility * E_light * (albedo * max(n·l, 0)
                                               + SPECULAR_STRENGTH * max(n·h, 0)**SHININESS)
             + albedo * ambient_radiance(lights) + emissive

* ``E_light`` is the light's ``radiance`` for a DistantLight and
  ``radiance / d**2 * range_window(d, r)`` for a LocalLight (d clamped to
  ``MIN_LIGHT_DISTANCE``): every LocalLight has a finite range ``r`` (``light_ranges``,
  from ``LIGHT_CUTOFF_IRRADIANCE``) beyond which it contributes nothing, so neither its
  shading nor its shadow rays / shadow-map lookups are computed there.
* Lambert without the 1/π factor (the preview-renderer convention): a white surface facing
  a unit DistantLight shows 1.0.
* ``h`` is the Blinn-Phong half vector between the light and the direction to the eye.
* The ambient term is the mean environment radiance, unshadowed.
* A LocalLight with UsdLux ShapingAPI (a cone, focus) scales ``E_light`` by
  ``cone_falloff`` of the direction it emits towards the point.

Light order, wherever a per-light axis appears (``visibility`` (n, L), ``light_directions``):
all ``lights.distant`` first, then all ``lights.local``, each in list order.

Environment: a DomeLight's lat-long texture (times the dome colour), else the dome colour,
else ``scene.DEFAULT_ENVIRONMENT``. The lat-long convention is UsdLux's (OpenEXR's), in the
dome's own space (+Y up): pixel column 0 is longitude +π, the last column longitude -π,
row 0 latitude +π/2; longitude 0 points to +Z and longitude +π/2 to +X.
``DomeLight.world_from_light`` carries the dome's orientation (e.g. a Z-up stage's rotation).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, DomeLight, Lights, LocalLight
from phrt_usd.threads import current_threads

#: Smallest light-to-surface distance in metres used for the 1/d² fall-off of LocalLights.
#: A surface point at (or numerically on) a point light would otherwise get Inf irradiance.
MIN_LIGHT_DISTANCE = 1e-4

#: Irradiance (linear, same units as the shaded colour: a white surface facing a unit
#: DistantLight shows 1.0) below which a LocalLight is cut off. A light of radiance ``I``
#: (brightest channel) reaches ``LIGHT_CUTOFF_IRRADIANCE`` at distance
#: ``r = sqrt(I / LIGHT_CUTOFF_IRRADIANCE)``, its *range*; ``range_window`` fades it to 0
#: there smoothly. 0.02 is 2 % of display white (about the ambient level of a dim dome):
#: the sewer's lamps (I = 30) reach 39 m, and the window still keeps > 97 % of the
#: 1/d² light within a third of the range.
LIGHT_CUTOFF_IRRADIANCE = 0.02

#: Blinn-Phong exponent of the specular highlight (one value for every material).
SHININESS = 64.0

#: SHININESS = 2**k: the highlight's power is computed as k squarings (else with pow).
_SHININESS_SQUARINGS = (
    int(np.log2(SHININESS))
    if SHININESS >= 1
    and float(SHININESS).is_integer()
    and (int(SHININESS) & (int(SHININESS) - 1)) == 0
    else None
)

#: Weight of the white Blinn-Phong highlight relative to the diffuse term.
SPECULAR_STRENGTH = 0.25

#: Threads ``shade_local`` splits large batches over (points are independent): None is
#: the process's setting (``phrt_usd.threads.current_threads``, which every renderer
#: applies; tests pin a number); and the smallest batch worth splitting (below it thread
#: hand-off costs more than it saves).
SHADE_THREADS: int | None = None
SHADE_MIN_THREADED_POINTS = 8192

#: Directions shorter than this are treated as zero-length (looked up as dome-space +Y)
#: instead of being divided by ~0 into NaN/Inf.
_MIN_DIRECTION_LENGTH = 1e-30

#: Cache of ambient radiance per DomeLight texture: id(texture) -> (texture, mean (3,)).
#: The texture object is kept so that a recycled id can never alias another array.
_AMBIENT_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}
_AMBIENT_CACHE_SIZE = 8


class LightPairs(NamedTuple):
    """m (point, LocalLight) pairs known to be lit, with what shading them needs.

    point  : (m,) int64 index of the point
    light  : (m,) int64 index into ``lights.local``
    l_dir  : (m, 3) float32 unit directions from the point to the light
    dist   : (m,) metres from the point to the light
    weight : (m,) float32 visibility in (0, 1], or None: fully lit
    """

    point: np.ndarray
    light: np.ndarray
    l_dir: np.ndarray
    dist: np.ndarray
    weight: np.ndarray | None = None


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


def _dome_colour(dome: DomeLight) -> np.ndarray:
    return np.asarray(dome.color, dtype=np.float32).reshape(3)


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
    colour = _dome_colour(dome)
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


def ambient_radiance(lights: Lights) -> np.ndarray:
    """(3,) float32 mean environment radiance over the sphere (solid-angle weighted),
    used as the unshadowed ambient term. Cached per dome texture."""
    dome = lights.dome
    if dome is None:
        return DEFAULT_ENVIRONMENT.astype(np.float32)
    colour = _dome_colour(dome)
    if dome.texture is None:
        return colour.copy()
    key = id(dome.texture)
    cached = _AMBIENT_CACHE.get(key)
    if cached is None or cached[0] is not dome.texture:
        tex = np.asarray(dome.texture, dtype=np.float64)
        h = tex.shape[0]
        # Row r covers latitudes around (0.5 - (r + 0.5) / h) * π; its solid angle ∝ cos(lat).
        weight = np.cos((0.5 - (np.arange(h) + 0.5) / h) * np.pi)
        mean = np.einsum("r,rwc->c", weight, tex) / (weight.sum() * tex.shape[1])
        if len(_AMBIENT_CACHE) >= _AMBIENT_CACHE_SIZE:
            _AMBIENT_CACHE.clear()
        cached = (dome.texture, mean.astype(np.float32))
        _AMBIENT_CACHE[key] = cached
    return cached[1] * colour


def light_directions(lights: Lights, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions from surface points towards every light, and how far to look.

    positions : (n, 3) float64 world metres
    Returns dirs (n, L, 3) float64 world unit vectors and max_distance (n, L) float64
    metres: ``inf`` for DistantLights, the distance to the light centre (clamped to
    ``MIN_LIGHT_DISTANCE``) for LocalLights. Light order: distant, then local.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = positions.shape[0]
    n_lights = len(lights.distant) + len(lights.local)
    dirs = np.empty((n, n_lights, 3))
    dist = np.empty((n, n_lights))
    for j, light in enumerate(lights.distant):
        d = np.asarray(light.direction, dtype=np.float64)
        dirs[:, j] = d / max(np.linalg.norm(d), _MIN_DIRECTION_LENGTH)
        dist[:, j] = np.inf
    offset = len(lights.distant)
    for k, light in enumerate(lights.local):
        to_light = np.asarray(light.position, dtype=np.float64) - positions
        d = np.maximum(np.linalg.norm(to_light, axis=1), MIN_LIGHT_DISTANCE)
        dirs[:, offset + k] = to_light / d[:, None]
        dist[:, offset + k] = d
    return dirs, dist


def light_ranges(lights: Lights) -> np.ndarray:
    """(L,) float64 metres: how far each light reaches, light order distant (``inf``)
    then local (``sqrt(max channel of radiance / LIGHT_CUTOFF_IRRADIANCE)``, 0 for a
    black or negative light). Beyond it a light contributes nothing (``range_window``)."""
    local = [
        max(float(np.max(np.asarray(li.radiance, dtype=np.float64))), 0.0) for li in lights.local
    ]
    # A non-finite radiance (never authored, but clamp anyway) would give an infinite
    # range: cap it at the largest finite float so the window stays well defined.
    ranges = np.sqrt(
        np.nan_to_num(np.asarray(local, np.float64), posinf=1e300) / LIGHT_CUTOFF_IRRADIANCE
    )
    return np.concatenate([np.full(len(lights.distant), np.inf), ranges])


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


def shaped_lights(lights: Lights) -> bool:
    """Some LocalLight has a cone or focus (``LocalLight.shaped``): its pairs are then
    shaded here (``cone_falloff``), not in the GPU lookup pass."""
    return any(li.shaped for li in lights.local)


def _shade_chunk(
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


def shade_local(
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
    """Direct + ambient + emitted radiance leaving surface points towards the viewer.

    positions  : (n, 3) float64 world metres
    normals    : (n, 3) world unit shading normals (facing the viewer)
    albedo     : (n, 3) linear RGB
    view_dirs  : (n, 3) world unit directions from the viewer (eye or previous bounce)
                 to the point
    emissive   : (n, 3) linear RGB, or (3,) for all points
    visibility : (n, L) in [0, 1] (1 = lit), L = len(distant) + len(local) in that order;
                 None means everything is lit
    local_pairs : optional ``LightPairs`` (or its first four fields as a tuple): the lit
                 (point, LocalLight) pairs, already known to be visible, in range and
                 in front of the normal (the tracer has them from its shadow rays).
                 They replace the LocalLight columns of ``visibility``, and the same
                 model is evaluated on them without recomputing directions.
    lit_sums   : optional (diffuse (n, 3), highlight (n, 3)) float32: the terms of
                 (point, light) pairs already shaded elsewhere (``LightTerms.lit_sums``
                 of ``render.raster.map_lighting``, on the GPU), per pair
                 ``radiance * n·l`` (LocalLights also ``* window / d²``) and that times
                 the highlight. Added as
                 ``albedo * diffuse + highlight``; LocalLights are then evaluated only
                 at ``local_pairs``, and ``visibility`` needs only its DistantLight
                 columns, 0 for pairs already in the sums.
    Returns (n, 3) float32 linear RGB.

    Points are independent: large batches are split into ``_shade_threads()`` contiguous
    chunks (``local_pairs`` with them, when sorted by point) shaded on a thread pool
    (numpy releases the GIL).
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = positions.shape[0]
    pairs = None if local_pairs is None else LightPairs(*local_pairs)
    # Pairs sorted by point (as the tracer and the rasterizer make them) split with the
    # points; unsorted ones are shaded in one chunk.
    if (
        _shade_threads() < 2
        or n < SHADE_MIN_THREADED_POINTS
        or (pairs is not None and not bool(np.all(np.diff(pairs.point) >= 0)))
    ):
        return _shade_chunk(
            positions,
            normals,
            albedo,
            view_dirs,
            emissive,
            lights,
            visibility,
            local_pairs,
            lit_sums,
        )
    normals = np.asarray(normals).reshape(n, 3)
    albedo = np.asarray(albedo).reshape(n, 3)
    view_dirs = np.asarray(view_dirs).reshape(n, 3)
    emissive = np.asarray(emissive)
    out = np.empty((n, 3), dtype=np.float32)

    def run(part: slice) -> None:
        chunk_pairs = None
        if pairs is not None:
            lo, hi = np.searchsorted(pairs.point, [part.start, part.stop])
            chunk_pairs = LightPairs(
                pairs.point[lo:hi] - part.start,
                *(None if a is None else a[lo:hi] for a in pairs[1:]),
            )
        out[part] = _shade_chunk(
            positions[part],
            normals[part],
            albedo[part],
            view_dirs[part],
            emissive if emissive.ndim == 1 else emissive[part],
            lights,
            None if visibility is None else visibility[part],
            chunk_pairs,
            None if lit_sums is None else (lit_sums[0][part], lit_sums[1][part]),
        )

    threads = _shade_threads()
    bounds = np.linspace(0, n, threads + 1).astype(int)
    pool = _shade_pool(threads)
    jobs = [pool.submit(run, slice(a, b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    for job in jobs:
        job.result()
    return out


_POOL: dict[int, ThreadPoolExecutor] = {}  # the shading pool, by its thread count


def _shade_threads() -> int:
    """SHADE_THREADS, or the process's thread setting when it is None."""
    return SHADE_THREADS or current_threads()


def _shade_pool(threads: int) -> ThreadPoolExecutor:
    """The module's shading pool of ``threads`` workers, created on first use; a pool of
    another size is shut down (its workers finish their chunks)."""
    pool = _POOL.get(threads)
    if pool is None:
        for old in _POOL.values():
            old.shutdown(wait=False)
        _POOL.clear()
        pool = _POOL[threads] = ThreadPoolExecutor(threads, thread_name_prefix="phrt-shade")
    return pool


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
