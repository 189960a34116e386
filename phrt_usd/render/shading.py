"""Local shading shared by the raster path and the ray tracer, so both agree exactly.

Everything here works on world-space arrays (metres, linear RGB float32, no tone mapping);
the per-point work runs in compiled kernels (numba, ``nogil``: ``_shade_kernel``,
``_latlong_bilinear``; their numpy reference is ``tests/shading_reference.py``). The model,
deliberately simple and the same everywhere:

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

import math
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numba
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

#: SHININESS = 2**k: the highlight's power is computed as k squarings (else with pow:
#: -1).
_SQUARINGS = (
    int(np.log2(SHININESS))
    if SHININESS >= 1
    and float(SHININESS).is_integer()
    and (int(SHININESS) & (int(SHININESS) - 1)) == 0
    else -1
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
    texture = np.ascontiguousarray(dome.texture, dtype=np.float32)
    rotation = np.ascontiguousarray(dome.world_from_light, dtype=np.float64)
    d = np.empty((n, 3))
    _dome_directions(directions, rotation, d)
    # The angles by numpy's vectorised arcsin / arctan2 (~3x faster than scalar libm
    # calls in a kernel).
    latitude = np.arcsin(np.clip(d[:, 1], -1.0, 1.0))
    longitude = np.arctan2(d[:, 0], d[:, 2])
    out = np.empty((n, 3), np.float32)
    _latlong_bilinear(latitude, longitude, texture, colour.astype(np.float64), out)
    return out


@numba.njit(nogil=True, cache=True)
def _dome_directions(directions, rotation, out):  # pragma: no cover - compiled
    """World directions (n, 3) (any length) as unit directions (n, 3) float64 in the
    dome's space (``rotation`` = ``world_from_light`` (3, 3), a rotation: its inverse is
    its transpose); zero, tiny or non-finite ones become the dome's +Y pole."""
    for i in range(directions.shape[0]):
        x, y, z = float(directions[i, 0]), float(directions[i, 1]), float(directions[i, 2])
        big = max(abs(x), abs(y), abs(z))
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        if not (finite and big > _MIN_DIRECTION_LENGTH):  # no direction: the pole
            out[i, 0], out[i, 1], out[i, 2] = 0.0, 1.0, 0.0
            continue
        # Scaled by the largest component first so huge vectors do not overflow.
        x, y, z = x / big, y / big, z / big
        norm = math.sqrt(x * x + y * y + z * z)
        x, y, z = x / norm, y / norm, z / norm
        for c in range(3):
            out[i, c] = x * rotation[0, c] + y * rotation[1, c] + z * rotation[2, c]


@numba.njit(nogil=True, cache=True)
def _latlong_bilinear(latitude, longitude, texture, colour, out):  # pragma: no cover
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


@numba.njit(nogil=True, cache=True, inline="always")
def window_at(distance2, light_range):  # pragma: no cover - compiled
    """``range_window`` of one squared distance (metres²) and range (metres)."""
    if not light_range > 0.0:
        return 0.0
    x = distance2 / (light_range * light_range)
    w = min(max(1.0 - x * x, 0.0), 1.0)
    return w * w


@numba.njit(nogil=True, cache=True)
def _window_kernel(distance, light_range, out):  # pragma: no cover - compiled
    for i in range(distance.shape[0]):
        out[i] = window_at(distance[i] * distance[i], light_range)


def range_window(distance: np.ndarray, light_range: float) -> np.ndarray:
    """Smooth cut-off factor (n,) float64 in [0, 1] of a LocalLight at ``distance`` (n,)
    metres: ``clamp(1 - (d / r)**4, 0, 1)**2`` (the Frostbite / Unreal window): 1 near
    the light, falling to exactly 0 at and beyond ``light_range`` with zero slope there,
    so no ring marks the range. ``light_range`` <= 0 gives 0 everywhere."""
    distance = np.asarray(distance, dtype=np.float64)
    out = np.empty(distance.size)
    _window_kernel(distance.reshape(-1), float(light_range), out)
    return out.reshape(distance.shape)


@numba.njit(nogil=True, cache=True, inline="always")
def cone_at(cos, cone_angle, softness, focus):  # pragma: no cover - compiled
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


@numba.njit(nogil=True, cache=True)
def _cone_kernel(emission, axis, cone_angle, softness, focus, out):  # pragma: no cover
    for i in range(emission.shape[0]):
        cos = emission[i, 0] * axis[0] + emission[i, 1] * axis[1] + emission[i, 2] * axis[2]
        out[i] = cone_at(cos, cone_angle, softness, focus)


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
    out = np.empty(m, np.float32)
    _cone_kernel(
        np.asarray(emission, np.float64).reshape(m, 3),
        np.asarray(light.axis, np.float64).reshape(3),
        float(light.cone_angle),
        float(light.cone_softness),
        float(light.focus),
        out,
    )
    return out


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
    """``shade_local`` on one chunk of points (same arguments and result), by
    ``_shade_kernel``."""
    positions = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
    n = positions.shape[0]
    f32 = np.float32

    def rows(a, dtype=f32, width=3):
        return np.ascontiguousarray(a, dtype=dtype).reshape(-1, width)

    emissive = rows(emissive)
    if len(emissive) != 1:
        emissive = emissive.reshape(n, 3)
    distant, local = lights.distant, lights.local
    d_dir = np.array([li.direction for li in distant], np.float64).reshape(-1, 3)
    d_dir /= np.maximum(np.linalg.norm(d_dir, axis=1, keepdims=True), _MIN_DIRECTION_LENGTH)
    cone = np.array(
        [[*li.axis, li.cone_angle, li.cone_softness, li.focus, li.shaped] for li in local],
        np.float64,
    ).reshape(-1, 7)
    pairs = _NO_PAIRS if local_pairs is None else LightPairs(*local_pairs)
    has_weight = pairs.weight is not None
    out = np.empty((n, 3), np.float32)
    if n:
        _shade_kernel(
            positions,
            rows(normals).reshape(n, 3),
            rows(albedo).reshape(n, 3),
            rows(view_dirs).reshape(n, 3),
            emissive,
            ambient_radiance(lights).astype(np.float64),
            *(rows(s) for s in (lit_sums if lit_sums is not None else (_NO_ROWS, _NO_ROWS))),
            d_dir,
            np.array([li.radiance for li in distant], np.float64).reshape(-1, 3),
            _NO_VISIBILITY if visibility is None else rows(visibility, width=1).reshape(n, -1),
            np.array([li.position for li in local], np.float64).reshape(-1, 3),
            np.array([li.radiance for li in local], np.float64).reshape(-1, 3),
            light_ranges(lights)[len(distant) :],
            cone,
            local_pairs is None and lit_sums is None,
            np.ascontiguousarray(pairs.point, np.int64),
            np.ascontiguousarray(pairs.light, np.int64),
            rows(pairs.l_dir),
            np.ascontiguousarray(pairs.dist, np.float64),
            np.ascontiguousarray(pairs.weight if has_weight else _NO_WEIGHT, np.float32),
            has_weight,
            out,
        )
    return out


_NO_ROWS = np.zeros((0, 3), np.float32)
_NO_VISIBILITY = np.zeros((0, 0), np.float32)
_NO_WEIGHT = np.zeros(0, np.float32)
_NO_PAIRS = LightPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), _NO_ROWS, np.zeros(0))


@numba.njit(nogil=True, cache=True, inline="always")
def highlight_at(n0, n1, n2, e0, e1, e2, l0, l1, l2):  # pragma: no cover - compiled
    """Blinn-Phong highlight SPECULAR_STRENGTH * max(n·h, 0)**SHININESS of unit normal
    n, direction to the eye e and direction to the light l (world, unit)."""
    h0, h1, h2 = l0 + e0, l1 + e1, l2 + e2
    length = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
    # l and the eye direction exactly opposite: no meaningful half vector, no highlight.
    x = max((n0 * h0 + n1 * h1 + n2 * h2) / max(length, 1e-12), 0.0)
    if _SQUARINGS >= 0:  # x**64 as 6 squarings: several times faster than pow
        for _ in range(_SQUARINGS):
            x *= x
    else:
        x = x**SHININESS
    return SPECULAR_STRENGTH * x


@numba.njit(nogil=True, cache=True)
def _shade_kernel(
    positions,
    normals,
    albedo,
    view_dirs,
    emissive,
    ambient,
    sum_diffuse,
    sum_highlight,
    d_dir,
    d_radiance,
    visibility,
    l_pos,
    l_radiance,
    l_range,
    l_cone,
    local_columns,
    p_point,
    p_light,
    p_dir,
    p_dist,
    p_weight,
    has_weight,
    out,
):  # pragma: no cover - compiled
    """The shading model of the module docstring, per point (see ``shade_local``).

    positions (n, 3) float64 world metres; normals, albedo, view_dirs (n, 3) float32;
    emissive (1 or n, 3); ambient (3,); sum_diffuse, sum_highlight (n, 3) or (0, 3):
    ``lit_sums``; d_dir (D, 3) unit, d_radiance (D, 3); visibility (n, D + P) or (0, 0):
    all lit; l_pos (P, 3) world metres, l_radiance (P, 3), l_range (P,) metres, l_cone
    (P, 7) (axis, cone angle, softness, focus, shaped); local_columns: shade every
    LocalLight from its visibility column (else only the pairs); pairs p_point (m,),
    p_light (m,), p_dir (m, 3) unit, p_dist (m,) metres, p_weight (m,) if has_weight.
    Writes out (n, 3) float32. Sums in float64 per point."""
    n = positions.shape[0]
    n_distant = d_dir.shape[0]
    has_vis = visibility.shape[0] > 0
    has_sums = sum_diffuse.shape[0] > 0
    one_emissive = emissive.shape[0] == 1
    min_d2 = MIN_LIGHT_DISTANCE * MIN_LIGHT_DISTANCE
    for i in range(n):
        n0, n1, n2 = float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])
        e0, e1, e2 = -float(view_dirs[i, 0]), -float(view_dirs[i, 1]), -float(view_dirs[i, 2])
        em = 0 if one_emissive else i
        # Radiance-weighted Lambert terms of the lights (d) and their highlights (s), RGB.
        d0 = d1 = d2 = s0 = s1 = s2 = 0.0
        for j in range(n_distant):
            lit = n0 * d_dir[j, 0] + n1 * d_dir[j, 1] + n2 * d_dir[j, 2]
            if has_vis:
                lit *= visibility[i, j]
            if not lit > 0.0:
                continue
            hl = lit * highlight_at(n0, n1, n2, e0, e1, e2, d_dir[j, 0], d_dir[j, 1], d_dir[j, 2])
            r, g, b = d_radiance[j, 0], d_radiance[j, 1], d_radiance[j, 2]
            d0, d1, d2 = d0 + r * lit, d1 + g * lit, d2 + b * lit
            s0, s1, s2 = s0 + r * hl, s1 + g * hl, s2 + b * hl
        for k in range(l_pos.shape[0] if local_columns else 0):
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
            lit = n0 * l0 + n1 * l1 + n2 * l2
            if not lit > 0.0:
                continue
            lit *= window_at(dist2, l_range[k]) / dist2 * vis
            if l_cone[k, 6] > 0.0:
                cos = -(l0 * l_cone[k, 0] + l1 * l_cone[k, 1] + l2 * l_cone[k, 2])
                lit *= cone_at(cos, l_cone[k, 3], l_cone[k, 4], l_cone[k, 5])
            hl = lit * highlight_at(n0, n1, n2, e0, e1, e2, l0, l1, l2)
            r, g, b = l_radiance[k, 0], l_radiance[k, 1], l_radiance[k, 2]
            d0, d1, d2 = d0 + r * lit, d1 + g * lit, d2 + b * lit
            s0, s1, s2 = s0 + r * hl, s1 + g * hl, s2 + b * hl
        if has_sums:
            d0, d1, d2 = d0 + sum_diffuse[i, 0], d1 + sum_diffuse[i, 1], d2 + sum_diffuse[i, 2]
            s0 += sum_highlight[i, 0]
            s1 += sum_highlight[i, 1]
            s2 += sum_highlight[i, 2]
        a0, a1, a2 = float(albedo[i, 0]), float(albedo[i, 1]), float(albedo[i, 2])
        out[i, 0] = a0 * (ambient[0] + d0) + s0 + emissive[em, 0]
        out[i, 1] = a1 * (ambient[1] + d1) + s1 + emissive[em, 1]
        out[i, 2] = a2 * (ambient[2] + d2) + s2 + emissive[em, 2]
    for q in range(p_point.shape[0]):  # lit LocalLight pairs, any order
        i, k = p_point[q], p_light[q]
        l0, l1, l2 = float(p_dir[q, 0]), float(p_dir[q, 1]), float(p_dir[q, 2])
        n0, n1, n2 = float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])
        lit = n0 * l0 + n1 * l1 + n2 * l2
        if not lit > 0.0:
            continue
        dist2 = max(p_dist[q] * p_dist[q], min_d2)
        lit *= window_at(dist2, l_range[k]) / dist2
        if has_weight:
            lit *= p_weight[q]
        if l_cone[k, 6] > 0.0:
            cos = -(l0 * l_cone[k, 0] + l1 * l_cone[k, 1] + l2 * l_cone[k, 2])
            lit *= cone_at(cos, l_cone[k, 3], l_cone[k, 4], l_cone[k, 5])
        e0, e1, e2 = -float(view_dirs[i, 0]), -float(view_dirs[i, 1]), -float(view_dirs[i, 2])
        hl = lit * highlight_at(n0, n1, n2, e0, e1, e2, l0, l1, l2)
        out[i, 0] += l_radiance[k, 0] * (float(albedo[i, 0]) * lit + hl)
        out[i, 1] += l_radiance[k, 1] * (float(albedo[i, 1]) * lit + hl)
        out[i, 2] += l_radiance[k, 2] * (float(albedo[i, 2]) * lit + hl)


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
    (the kernel releases the GIL).
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
