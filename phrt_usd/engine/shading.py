"""Local shading shared by the raster path and the ray tracer, so both agree exactly.

Everything here works on world-space arrays (metres, linear RGB float32, no tone mapping);
the per-point work runs in compiled kernels (``shade_kernels``: numba, ``nogil``,
imported on first use). The model, the same everywhere::

    colour = Σ_lights  visibility * E_light * π f(l, v) max(n·l, 0)
             + ambient_weight(v) * ambient_radiance(lights) + emissive

* ``f`` is UsdPreviewSurface's BRDF (``model/preview_surface.py`` states it: GGX with
  height-correlated Smith masking, Schlick's Fresnel from F0 / F90 of the metallic or
  specular workflow, the diffuse lobe taking what the specular leaves, the clear coat),
  evaluated per point from its *surface row* (``preview_surface.surface_columns``).
* ``E_light`` is the light's ``radiance`` for a DistantLight and
  ``radiance / d**2 * range_window(d, r)`` for a LocalLight (d clamped to
  ``MIN_LIGHT_DISTANCE``): every LocalLight has a finite range ``r`` (``light_ranges``,
  from ``LIGHT_CUTOFF_IRRADIANCE``) beyond which it contributes nothing, so neither its
  shading nor its shadow rays / shadow-map lookups are computed there.
* The π: a light's radiance is the irradiance a surface facing it receives over π (the
  preview-renderer convention), so a white Lambert surface facing a unit DistantLight
  shows 1.0.
* The ambient term is the mean environment radiance, unshadowed, times the surface's
  directional albedo under a uniform environment (``shade_kernels.ambient_weight``:
  its occlusion, and the specular part only where no mirror reflection stands in for it).
* A LocalLight with UsdLux ShapingAPI (a cone, focus) scales ``E_light`` by
  ``cone_falloff`` of the direction it emits towards the point.
* A Rect or Disk light scales it by its area factor (``area_table``,
  ``trace.area_light_kernels``: the exact irradiance of its surface over the point
  light's; 0 behind it), whoever decided the pair's visibility (a shadow map's test
  from its centre, or the share of it a shadow ray's area rule saw).

Light order, wherever a per-light axis appears (``visibility`` (n, L), ``light_directions``):
all ``lights.distant`` first, then all ``lights.local``, each in list order.

Environment: a DomeLight's lat-long texture (times the dome colour), else the dome colour,
else ``scene.DEFAULT_ENVIRONMENT``. The lat-long convention is UsdLux's (OpenEXR's), in the
dome's own space (+Y up): pixel column 0 is longitude +π, the last column longitude -π,
row 0 latitude +π/2; longitude 0 points to +Z and longitude +π/2 to +X.
``DomeLight.world_from_light`` carries the dome's orientation (e.g. a Z-up stage's rotation).
"""

from __future__ import annotations

import operator
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from phrt_usd import kernels
from phrt_usd.model import preview_surface
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

#: Threads ``shade_local`` splits large batches over (points are independent): None is
#: the process's setting (``phrt_usd.threads.current_threads``, which every renderer
#: applies; tests pin a number); and the smallest batch worth splitting (below it thread
#: hand-off costs more than it saves).
SHADE_THREADS: int | None = None
SHADE_MIN_THREADED_POINTS = 8192

#: Environment lookups of at most this many directions run as one compiled pass
#: (``shade_kernels.latlong_lookup``, scalar libm angles: ~14 ns a direction), larger
#: ones take numpy's vectorised arcsin / arctan2 (~5 ns a direction, but ~2.5 us of
#: calls): measured 2026-12-03, equal at ~300 directions.
ENV_ONE_PASS_MAX = 256

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
    m = len(point)
    l_dir, dist = np.empty((m, 3), np.float32), np.empty(m)
    if m:
        _kernels().pair_directions(
            centres,
            np.ascontiguousarray(positions, np.float64),
            np.asarray(point, np.int64),
            np.asarray(light, np.int64),
            MIN_LIGHT_DISTANCE,
            l_dir,
            dist,
        )
    return l_dir, dist


def _dome_colour(dome: DomeLight) -> np.ndarray:
    return np.asarray(dome.color, dtype=np.float32).reshape(3)


#: The latest ``_dome_arrays``: (identity key, arrays). Converting them per lookup would
#: cost ~1.5 us of every trace round that reads the environment.
_DOME_CACHE: list = [None]


def _dome_arrays(dome: DomeLight) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured ``dome`` as the lat-long kernels take it: texture (h, w, 3) float32,
    rotation (3, 3) float64 (both C-contiguous) and colour (3,) float64; cached while
    the dome and its three arrays stay the same objects (identity, as ``light_table``:
    lights are replaced, never modified in place)."""
    key = (dome, dome.texture, dome.world_from_light, dome.color)
    cached = _DOME_CACHE[0]
    if cached is not None and all(map(operator.is_, cached[0], key)):
        return cached[1]
    arrays = (
        np.ascontiguousarray(dome.texture, dtype=np.float32),
        np.ascontiguousarray(dome.world_from_light, dtype=np.float64),
        _dome_colour(dome).astype(np.float64),
    )
    _DOME_CACHE[0] = (key, arrays)
    return arrays


def environment_radiance(lights: Lights, directions: np.ndarray) -> np.ndarray:
    """Radiance arriving from the environment along world directions.

    directions : (n, 3) world-space directions (any length; zero or non-finite ones look
                 up the dome's +Y pole instead of producing NaN)
    Returns (n, 3) float32 linear RGB. A textured dome's lookups run as one compiled
    pass up to ENV_ONE_PASS_MAX directions; larger batches are split over the shading
    pool, as ``shade_local``'s.
    """
    directions = np.asarray(directions).reshape(-1, 3)
    n = directions.shape[0]
    dome = lights.dome
    if dome is None:
        return np.broadcast_to(DEFAULT_ENVIRONMENT.astype(np.float32), (n, 3)).copy()
    if dome.texture is None:
        return np.broadcast_to(_dome_colour(dome), (n, 3)).copy()
    texture, rotation, colour64 = _dome_arrays(dome)
    compiled = _kernels()
    out = np.empty((n, 3), np.float32)
    if n <= ENV_ONE_PASS_MAX:
        compiled.latlong_lookup(directions, rotation, _MIN_DIRECTION_LENGTH, texture, colour64, out)
        return out

    def run(part: slice) -> None:
        d = np.empty((len(out[part]), 3))
        compiled.dome_directions(directions[part], rotation, _MIN_DIRECTION_LENGTH, d)
        # The angles by numpy's vectorised arcsin / arctan2 (~3x faster than scalar
        # libm calls in a kernel).
        latitude = np.arcsin(np.clip(d[:, 1], -1.0, 1.0))
        longitude = np.arctan2(d[:, 0], d[:, 2])
        compiled.latlong_bilinear(latitude, longitude, texture, colour64, out[part])

    on_pool(run, n)
    return out


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


def range_window(distance: np.ndarray, light_range: float) -> np.ndarray:
    """Smooth cut-off factor (n,) float64 in [0, 1] of a LocalLight at ``distance`` (n,)
    metres: ``clamp(1 - (d / r)**4, 0, 1)**2`` (the Frostbite / Unreal window): 1 near
    the light, falling to exactly 0 at and beyond ``light_range`` with zero slope there,
    so no ring marks the range. ``light_range`` <= 0 gives 0 everywhere."""
    distance = np.asarray(distance, dtype=np.float64)
    out = np.empty(distance.size)
    _kernels().window_kernel(distance.reshape(-1), float(light_range), out)
    return out.reshape(distance.shape)


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
    _kernels().cone_kernel(
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


class LightTable(NamedTuple):
    """The lights as ``shade_kernels.shade_kernel`` takes them (float64, light order
    distant then local): ambient (3,), d_dir (D, 3) unit towards the light, d_radiance
    (D, 3), l_position (K, 3) in the shaded points' space, l_radiance (K, 3), l_range
    (K,) metres (``light_ranges``), cone (K, 7): axis, angle, softness, focus, shaped."""

    ambient: np.ndarray
    d_dir: np.ndarray
    d_radiance: np.ndarray
    l_position: np.ndarray
    l_radiance: np.ndarray
    l_range: np.ndarray
    cone: np.ndarray


#: The latest ``light_table``: (identity key, table). One entry: a frame shades with one
#: ``Lights`` (the tracer's rel copy or the scene's); rebuilding it per call was a fixed
#: cost of every trace round.
_LIGHT_TABLE_CACHE: list = [None]


def light_table(lights: Lights) -> LightTable:
    """``lights`` as the shading kernel's tables, cached while ``lights``, its dome and
    every light object stay the same objects (identity, as the tracer's light caches:
    lights are replaced, never modified in place, e.g. ``aim_headlight``)."""
    key = (lights, lights.dome, *lights.distant, *lights.local)
    cached = _LIGHT_TABLE_CACHE[0]
    if cached is not None and len(cached[0]) == len(key) and all(map(operator.is_, cached[0], key)):
        return cached[1]
    distant, local = lights.distant, lights.local
    d_dir = np.array([li.direction for li in distant], np.float64).reshape(-1, 3)
    d_dir /= np.maximum(np.linalg.norm(d_dir, axis=1, keepdims=True), _MIN_DIRECTION_LENGTH)
    cone = np.array(
        [[*li.axis, li.cone_angle, li.cone_softness, li.focus, li.shaped] for li in local],
        np.float64,
    ).reshape(-1, 7)
    table = LightTable(
        ambient_radiance(lights).astype(np.float64),
        d_dir,
        np.array([li.radiance for li in distant], np.float64).reshape(-1, 3),
        np.array([li.position for li in local], np.float64).reshape(-1, 3),
        np.array([li.radiance for li in local], np.float64).reshape(-1, 3),
        np.ascontiguousarray(light_ranges(lights)[len(distant) :]),
        cone,
    )
    _LIGHT_TABLE_CACHE[0] = (key, table)
    return table


#: The latest ``area_table``: (identity key, table), as ``_LIGHT_TABLE_CACHE``.
_AREA_TABLE_CACHE: list = [None]


def area_table(lights: Lights) -> np.ndarray | None:
    """(P, ``area_light_kernels.AREA_COLUMNS``) float64: each LocalLight's emitting
    surface (``LocalLight.area_shape``: its kind, centre, half axes u and v, unit axis, in
    the lights' space; zeros for a light that is no area), or None when no light is a
    Rect or Disk light; cached as ``light_table``."""
    key = (lights, *lights.local)
    cached = _AREA_TABLE_CACHE[0]
    if cached is not None and len(cached[0]) == len(key) and all(map(operator.is_, cached[0], key)):
        return cached[1]
    compiled = _areas()
    kinds = {"rect": compiled.RECT, "disk": compiled.DISK}
    table = None
    if any(li.area_shape in kinds for li in lights.local):
        table = np.zeros((len(lights.local), compiled.AREA_COLUMNS))
        for q, li in enumerate(lights.local):
            if li.area_shape not in kinds:
                continue
            table[q, compiled.AREA_KIND] = kinds[li.area_shape]
            table[q, compiled.AREA_CENTRE : compiled.AREA_CENTRE + 3] = li.position
            table[q, compiled.AREA_U : compiled.AREA_U + 3] = li.area_u
            table[q, compiled.AREA_V : compiled.AREA_V + 3] = li.area_v
            table[q, compiled.AREA_AXIS : compiled.AREA_AXIS + 3] = li.axis
        table = np.ascontiguousarray(np.nan_to_num(table))
    _AREA_TABLE_CACHE[0] = (key, table)
    return table


def _with_areas(lights, positions, normals, visibility, pairs: LightPairs, columns: bool):
    """The visibility and the pairs of ``_shade_chunk`` with each Rect or Disk light's
    area factor (``area_light_kernels._factor``: its exact unshadowed irradiance over the
    point light's) multiplied in: into copies of its visibility columns when the kernel
    shades the columns (``columns``), else of the pairs' weights. Unchanged without such
    lights."""
    area = area_table(lights)
    if area is None:
        return visibility, pairs
    n = positions.shape[0]
    if columns:
        n_lights = len(lights.distant) + len(lights.local)
        if visibility is None:
            visibility = np.ones((n, n_lights), np.float32)
        else:
            visibility = np.array(_rows(visibility, _F32, n, n_lights))
        _areas().area_columns(area, len(lights.distant), positions, normals,
                              MIN_LIGHT_DISTANCE, visibility)  # fmt: skip
        return visibility, pairs
    m = len(pairs.point)
    if m == 0:
        return visibility, pairs
    weight = np.ones(m, np.float32) if pairs.weight is None else np.array(pairs.weight, _F32)
    point, light = _rows(pairs.point, _I64, m), _rows(pairs.light, _I64, m)
    _areas().area_pairs(area, positions, normals, point, light, _rows(pairs.l_dir, _F32, m, 3),
                        _rows(pairs.dist, _F64, m), weight)  # fmt: skip
    return visibility, LightPairs(point, light, pairs.l_dir, pairs.dist, weight)


def _shade_chunk(
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
    """``shade_local`` on one chunk of points (same arguments and result), by
    ``shade_kernels.shade_kernel``."""
    positions = _rows(positions, _F64, -1, 3)
    n = positions.shape[0]
    emissive = _rows(emissive, _F32, -1, 3)
    if len(emissive) != 1:
        emissive = _rows(emissive, _F32, n, 3)
    table = light_table(lights)
    pairs = _NO_PAIRS if local_pairs is None else LightPairs(*local_pairs)
    columns = local_pairs is None and lit_sums is None
    normals = _rows(normals, _F32, n, 3)
    visibility, pairs = _with_areas(lights, positions, normals, visibility, pairs, columns)
    has_weight = pairs.weight is not None
    m = len(pairs.point)
    out = np.empty((n, 3), np.float32)
    if n:
        _kernels().shade_kernel(
            positions,
            normals,
            surface_rows(surface, n),
            _rows(view_dirs, _F32, n, 3),
            emissive,
            table.ambient,
            _sums(lit_sums, n),
            table.d_dir,
            table.d_radiance,
            _NO_VISIBILITY if visibility is None else _rows(visibility, _F32, n, -1),
            table.l_position,
            table.l_radiance,
            table.l_range,
            table.cone,
            columns,
            _rows(pairs.point, _I64, m),
            _rows(pairs.light, _I64, m),
            _rows(pairs.l_dir, _F32, m, 3),
            _rows(pairs.dist, _F64, m),
            _rows(pairs.weight, _F32, m) if has_weight else _NO_WEIGHT,
            has_weight,
            MODEL,
            preview_surface.specular_albedo_table(),
            out,
        )
    return out


def surface_rows(surface: np.ndarray, n: int) -> np.ndarray:
    """``surface`` as the kernels take it: (n, SURFACE_COLUMNS) float32 rows
    (``model.preview_surface``) as they are, or an (n, 3) albedo as the rows of
    UsdPreviewSurface's fallback material of that diffuse colour."""
    surface = np.asarray(surface)
    if surface.ndim == 2 and surface.shape[1] == preview_surface.SURFACE_COLUMNS:
        return _rows(surface, _F32, n, preview_surface.SURFACE_COLUMNS)
    return preview_surface.fallback_surface(np.asarray(surface).reshape(n, 3))


_F32, _F64, _I64 = np.dtype(np.float32), np.dtype(np.float64), np.dtype(np.int64)


def _rows(a, dtype: np.dtype, *shape: int) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype`` and ``shape`` (one -1 allowed): ``a``
    itself when it already is one (the tracer's gathered rows: checking costs a third of
    numpy's converting calls, which would cost ~5 us of a small trace round), else a converted
    copy or view."""
    if (
        type(a) is np.ndarray
        and a.dtype is dtype
        and a.shape == shape
        and a.flags.c_contiguous
    ):
        return a
    return np.ascontiguousarray(a, dtype=dtype).reshape(shape)


_NO_ROWS = np.zeros((0, 3), np.float32)
#: The model's constants as ``shade_kernels.shade_kernel`` takes them.
MODEL = np.array(
    [MIN_LIGHT_DISTANCE, preview_surface.MIN_ROUGHNESS, preview_surface.MIN_COSINE, 0.0],
    np.float64,
)


def _sums(a: np.ndarray | None, n: int) -> np.ndarray:
    """A ``lit_sums`` array as ``shade_kernels.shade_kernel`` reads it: (n, 3 or 4)
    float32 C order, channels 0-2 used ((0, 3): none)."""
    if a is None:
        return _NO_ROWS
    return _rows(a, _F32, n, -1)


_NO_VISIBILITY = np.zeros((0, 0), np.float32)
_NO_WEIGHT = np.zeros(0, np.float32)
_NO_PAIRS = LightPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), _NO_ROWS, np.zeros(0))


def shade_local(
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
    """Direct + ambient + emitted radiance leaving surface points towards the viewer.

    positions  : (n, 3) float64 world metres
    normals    : (n, 3) world unit shading normals (facing the viewer)
    surface    : (n, SURFACE_COLUMNS) float32 surface rows (``model.preview_surface``:
                 the UsdPreviewSurface inputs at each point), or (n, 3) linear RGB
                 albedo: the fallback material of that diffuse colour
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
    lit_sums   : optional (n, 3) float32 (or (n, 4), channel 3 ignored: the GPU's
                 readback as it is): the direct light of (point, light) pairs already
                 shaded elsewhere (``LightTerms.lit_sums`` of
                 ``render.raster.map_lighting``, on the GPU, the same BRDF), added as
                 it is; LocalLights are then evaluated only at ``local_pairs``, and
                 ``visibility`` needs only its DistantLight columns, 0 for pairs
                 already in the sums.
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
            surface,
            view_dirs,
            emissive,
            lights,
            visibility,
            local_pairs,
            lit_sums,
        )
    normals = np.asarray(normals).reshape(n, 3)
    surface = surface_rows(surface, n)
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
            surface[part],
            view_dirs[part],
            emissive if emissive.ndim == 1 else emissive[part],
            lights,
            None if visibility is None else visibility[part],
            chunk_pairs,
            None if lit_sums is None else lit_sums[part],
        )

    on_pool(run, n)
    return out


_POOL: dict[int, ThreadPoolExecutor] = {}  # the shading pool, by its thread count


def on_pool(run, n: int) -> None:
    """``run(part)`` over ``n`` independent points: on ``_shade_threads()`` contiguous
    slices on the shading pool from SHADE_MIN_THREADED_POINTS points on, else at once
    (compiled kernels and large numpy calls release the GIL)."""
    threads = _shade_threads()
    if threads < 2 or n < SHADE_MIN_THREADED_POINTS:
        run(slice(0, n))
        return
    bounds = np.linspace(0, n, threads + 1).astype(int)
    pool = _shade_pool(threads)
    jobs = [pool.submit(run, slice(a, b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    for job in jobs:
        job.result()


def gather_rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``np.take(a, index, axis=0)`` (m, ...) for ``index`` (m,) valid int64 rows of
    ``a`` (n, ...), gathered in slices on the shading pool (``on_pool``: np.take
    releases the GIL; mode "clip" as the indices are valid: "raise" buffers ``out``)."""
    out = np.empty((len(index), *a.shape[1:]), a.dtype)

    def run(part: slice) -> None:
        np.take(a, index[part], axis=0, out=out[part], mode="clip")

    on_pool(run, len(index))
    return out


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


def _areas():
    """The area lights' compiled kernels (``trace.area_light_kernels``: the one exact
    irradiance of a Rect or Disk light), taken on first use."""
    return kernels.load("phrt_usd.engine.trace.area_light_kernels")


def _kernels():
    """The compiled kernels (``shade_kernels`` through ``phrt_usd.kernels``), taken on
    first use: importing this module (the renderer, the API) loads no kernel."""
    return kernels.load("phrt_usd.engine.shade_kernels")


#: The latest ``material_input_rows``: (materials, rows), by identity.
_INPUT_ROWS: list = [None]
_NO_INDEX = np.zeros(0, np.int64)


def material_input_rows(materials) -> np.ndarray:
    """``preview_surface.input_rows`` of a ``MaterialTable``, cached while it stays the
    same object (materials are read once a run)."""
    cached = _INPUT_ROWS[0]
    if cached is not None and cached[0] is materials:
        return cached[1]
    rows = preview_surface.input_rows(materials)
    _INPUT_ROWS[0] = (materials, rows)
    return rows


def point_surface(
    materials, tri_material, tri, albedo, corner_uv, weights, specular_ambient=None
) -> np.ndarray:
    """(m, SURFACE_COLUMNS) float32 surface rows (``model.preview_surface``) of m points
    on triangles ``tri`` (m,) of a geometry whose triangles have materials
    ``tri_material`` (T,) (rows of ``materials``, a ``MaterialTable``): their ``albedo``
    (m, 3) (diffuseColor, textured already) and their material's inputs, sampled where
    textured at the barycentric ``weights`` (m, 3) (or a callable giving them: called
    only then) on ``corner_uv``; ``specular_ambient`` (m,) (None: 1 everywhere): 0 where
    a mirror reflection stands in for the ambient's specular part."""
    tri = np.asarray(tri, np.int64).reshape(-1)
    n = len(tri)
    out = np.empty((n, preview_surface.SURFACE_COLUMNS), np.float32)
    if n == 0:
        return out
    albedo = _rows(albedo, _F32, n, 3)
    ambient = _NO_WEIGHT if specular_ambient is None else _rows(specular_ambient, _F32, n)
    constant = material_input_rows(materials)
    if corner_uv is not None and preview_surface.textured_inputs(materials):
        at = weights() if callable(weights) else weights
        inputs = preview_surface.textured_input_rows(
            materials, constant, tri, at, tri_material, corner_uv
        )
        _kernels().surface_rows(albedo, _NO_INDEX, inputs, True, ambient, out)
    else:
        material = np.take(np.asarray(tri_material), tri).astype(np.int64)
        _kernels().surface_rows(albedo, material, constant, False, ambient, out)
    return out


def surface_weights(surface: np.ndarray, normals: np.ndarray, to_eye: np.ndarray):
    """(ambient, reflection) (n, 3) float32 each: what n points of ``surface`` rows
    return of a uniform unit environment (``shade_kernels.ambient_weight``) and the
    weight of their mirror reflection (``reflection_weight``: the specular lobes'
    directional albedo, split sum), seen from unit ``to_eye`` (n, 3) about unit
    ``normals`` (n, 3)."""
    n = len(surface)
    ambient = np.empty((n, 3), np.float32)
    reflection = np.empty((n, 3), np.float32)
    if n:
        _kernels().weights_kernel(
            _rows(surface, _F32, n, preview_surface.SURFACE_COLUMNS),
            _rows(normals, _F32, n, 3),
            _rows(to_eye, _F32, n, 3),
            preview_surface.specular_albedo_table(),
            preview_surface.MIN_ROUGHNESS,
            ambient,
            reflection,
        )
    return ambient, reflection
