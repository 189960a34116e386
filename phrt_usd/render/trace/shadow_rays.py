"""Shadow rays: which lights each point sees, by Embree occlusion queries.

``ShadowRays.cast`` takes rel points (see ``bvh.Float32Boundary``) with their offset
(geometric) and shading normals and answers (n, L) visibility, light order distant then
local. Rays go only where they can matter: to lights in front of the shading normal and,
for LocalLights, within their range (``shading.light_ranges``); all (point, light) pairs
of a batch are chosen and built into one float32 Embree batch in one compiled pass
(``_shadow_rays``: numba, ``nogil``, so the pool's chunks run side by side). Origins
are offset by the boundary's epsilon along the offset normal, on the side the ray
leaves to. Shadows are hard (light size ignored); transmissive surfaces are opaque;
cut-out holes let light through (``HitSurfaces.occluded``, given ``surfaces``).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from phrt_usd.model.scene import Lights
from phrt_usd.render import shading
from phrt_usd.render.trace.bvh import FAR, Bvh
from phrt_usd.render.trace.hit_surfaces import HitSurfaces

#: Shading work (numpy + shadow rays) on many points is split over the pool only from
#: this many shadow rays (points x lights) on: measured on the sewer (13 lights, 2
#: cores), 10.6k rays take 2.2 ms split vs 1.9 ms on one thread, 349k rays 49 ms vs 63 ms.
PARALLEL_MIN_SHADE_RAYS = 32768


class ShadowRays:
    """Shadow rays against one ``Bvh`` (its current geometry and boundary), split over
    ``pool`` (None: one thread) in ``threads`` chunks for large batches; occlusion through
    ``surfaces`` (cut-out holes let light through) when given."""

    def __init__(
        self,
        bvh: Bvh,
        pool: ThreadPoolExecutor | None,
        threads: int,
        surfaces: HitSurfaces | None = None,
    ) -> None:
        self._bvh = bvh
        self._surfaces = surfaces
        self.pool = pool
        self.threads = threads
        self._light_cache: tuple | None = None

    def split(self, work: int, n: int) -> list[tuple[int, int]] | None:
        """(start, stop) chunks of ``n`` points to shade over the pool, or None when
        ``work`` (shadow rays they may cast) is below PARALLEL_MIN_SHADE_RAYS or there
        is no pool."""
        if self.pool is None or work < PARALLEL_MIN_SHADE_RAYS or n < self.threads:
            return None
        edges = np.linspace(0, n, self.threads + 1).astype(int).tolist()
        return list(zip(edges[:-1], edges[1:], strict=True))

    def visibility(self, rel, normals, lights: Lights, pairs=None):
        """``cast`` for rel points (n, 3) whose offset and shading normals are both
        ``normals`` (n, 3), in chunks on the pool when the batch is large (numpy and
        Embree work of each chunk on its own thread). Returns (n, L) float32 visibility
        and (n,) int64 shadow rays cast per point."""
        n, n_lights = len(rel), len(lights.distant) + len(lights.local)
        bounds = self.split(n * max(n_lights, 1), n)
        if bounds is None:
            vis, rays, _ = self.cast(rel, normals, normals, lights, pairs)
            return vis, rays
        parts = [
            self.pool.submit(
                self.cast,
                rel[lo:hi],
                normals[lo:hi],
                normals[lo:hi],
                lights,
                None if pairs is None else pairs[lo:hi],
                1,
            )
            for lo, hi in bounds
        ]
        done = [f.result() for f in parts]
        return np.concatenate([d[0] for d in done]), np.concatenate([d[1] for d in done])

    def light_arrays(self, lights: Lights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(D, 3) unit DistantLight directions, (P, 3) LocalLight positions (both
        float64, as given) and (P,) LocalLight ranges in metres
        (``shading.light_ranges``) of ``lights``; cached for the latest ``Lights``
        object (the tracer's render-relative lights are one object per scene)."""
        cached = self._light_cache
        if cached is not None and cached[0] is lights:
            return cached[1]
        dirs = np.array([li.direction for li in lights.distant], np.float64).reshape(-1, 3)
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
        pos = np.array([li.position for li in lights.local], np.float64).reshape(-1, 3)
        ranges = shading.light_ranges(lights)[len(lights.distant) :]
        self._light_cache = (lights, (dirs, pos, ranges))
        return dirs, pos, ranges

    def cast(self, rel, offset_normals, shading_normals, lights: Lights, pairs=None, threads=None):
        """(n, L) float32 visibility, (n,) int64 shadow rays cast per point and the lit
        LocalLight pairs (``shading.shade_local``'s ``local_pairs``, or None), for
        render-relative positions ``rel`` (n, 3) and render-relative ``lights``.

        Rays are cast only where they can matter: the light in front of the shading
        normal (elsewhere the Lambert term is 0) and, for LocalLights, the point within
        the light's range (``shading.light_ranges``; beyond it the light contributes 0).
        Such pairs, and pairs outside ``pairs`` ((n, L) bool, None = all), report 0.

        The (point, light) pairs are chosen and their rays built in one compiled pass
        (``_shadow_rays``: float32 Embree batch, point-major, so the lit LocalLight
        pairs come out sorted by point), then cast as one batch."""
        n = rel.shape[0]
        n_distant = len(lights.distant)
        n_lights = n_distant + len(lights.local)
        if not lights.has_direct or n == 0:
            return np.ones((n, n_lights), np.float32), np.zeros(n, np.int64), None
        rel = np.ascontiguousarray(rel, np.float64)
        dirs, pos, ranges = self.light_arrays(lights)
        want = _ALL_PAIRS if pairs is None else np.asarray(pairs, dtype=bool).reshape(n, n_lights)
        eps = self._bvh.boundary.epsilon(rel)
        point, light, origins, d, tfar, dist = _shadow_rays(
            rel,
            np.ascontiguousarray(offset_normals, np.float32),
            np.ascontiguousarray(shading_normals, np.float32),
            dirs,
            pos,
            ranges,
            np.ascontiguousarray(want),
            eps,
            shading.MIN_LIGHT_DISTANCE,
            FAR,
        )
        vis = np.zeros((n, n_lights), np.float32)
        local = None
        if len(point):
            if self._surfaces is None:
                occluded = self._bvh.run("OCCLUDED", origins, d, tfar, threads)
            else:
                occluded = self._surfaces.occluded(origins, d, tfar, threads)
            vis.reshape(-1)[point * n_lights + light] = ~occluded
        else:
            occluded = np.zeros(0, bool)
        if len(pos):  # the lit LocalLight pairs, for shade_local
            free = np.flatnonzero(~occluded & (light >= n_distant))
            local = shading.LightPairs(
                point[free], light[free] - n_distant, d[free], dist[free].astype(np.float64)
            )
        return vis, np.bincount(point, minlength=n).astype(np.int64), local


#: ``_shadow_rays``' "every pair wanted" (an empty mask).
_ALL_PAIRS = np.zeros((0, 0), bool)


@numba.njit(nogil=True, cache=True)
def _shadow_rays(
    rel, ng, ns, dirs, pos, ranges, want, eps, min_distance, far
):  # pragma: no cover - compiled
    """The shadow rays of ``ShadowRays.cast``: for each point i (rel (n, 3) float64,
    offset normal ng and shading normal ns (n, 3) float32, offset epsilon eps (n,)
    metres) and each light j (DistantLights dirs (D, 3) unit, then LocalLights pos
    (P, 3) rel metres of range ranges (P,)) wanted (``want`` (n, D + P) bool, or (0, 0):
    all) whose light can matter there (in front of ns; LocalLights: within range),
    one ray. Returns point (k,) int64, light (k,) int64 (distant then local index),
    origins (k, 3), dirs (k, 3), tfar (k,) float32 and dist (k,) float32 (LocalLights:
    metres to the light, >= ``min_distance``; DistantLights: ``far``), point-major.
    Origins leave the surface by eps along ng on the ray's side; LocalLight rays stop
    eps short of the light."""
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
            side = e if d0 * ng[i, 0] + d1 * ng[i, 1] + d2 * ng[i, 2] >= 0.0 else -e
            for c in range(3):
                origins[r, c] = rel[i, c] + side * ng[i, c]
            out_dirs[r, 0], out_dirs[r, 1], out_dirs[r, 2] = d0, d1, d2
            point[r], light[r], tfar[r], dist[r] = i, j, stop, length
            r += 1
    return point, light, origins, out_dirs, tfar, dist
