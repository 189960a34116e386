"""The numpy shadow-ray set-up that ``ShadowRays.cast``'s compiled pass
(``render.trace.trace_kernels.shadow_rays``) replaced, kept as the reference of
``tests/engine/test_shadow_rays_kernel.py``: ``cast`` is the old method, called with the
``ShadowRays`` object as ``self``."""

from __future__ import annotations

import numpy as np

from phrt_usd.engine import shading
from phrt_usd.engine.trace.bvh import FAR
from phrt_usd.model.scene import Lights


def cast(self, rel, offset_normals, shading_normals, lights: Lights, pairs=None, threads=None):
    """(n, L) float32 visibility, (n,) int64 shadow rays cast per point and the lit
    LocalLight pairs (``shading.shade_local``'s ``local_pairs``, or None), for
    render-relative positions ``rel`` (n, 3) and render-relative ``lights``.

    Rays are cast only where they can matter: the light in front of the shading
    normal (elsewhere the Lambert term is 0) and, for LocalLights, the point within
    the light's range (``shading.light_ranges``; beyond it the light contributes 0).
    Such pairs, and pairs outside ``pairs`` ((n, L) bool, None = all), report 0.

    All (point, light) pairs are tested at once on (n, L) arrays (with ``pairs``,
    only the wanted pairs, one by one), then one Embree batch is built in float32
    directly (no per-light passes, no extra copies)."""
    n = rel.shape[0]
    n_distant = len(lights.distant)
    n_lights = n_distant + len(lights.local)
    if not lights.has_direct or n == 0:
        return np.ones((n, n_lights), np.float32), np.zeros(n, np.int64), None
    rel = np.asarray(rel, np.float64)
    ns = np.asarray(shading_normals, np.float32)
    dirs, pos, ranges, *_ = self.light_arrays(lights)  # (power and cones: sampling only)
    # Facing: n·l > 0. For LocalLights n·(p_L - p) = n·p_L - n·p, with the squared
    # distance |p_L|² - 2 p·p_L + |p|² (render-relative: |p| is at most the scene
    # extent, so the cancellation error stays ~1e-16 extent², far below any range²).
    # Written per column (_columns), not as a BLAS product (see _columns).
    if pairs is not None:
        # Only the wanted pairs (e.g. a shadow map's uncertain few per cent): facing
        # and range are tested per pair further down, not on (n, L) arrays.
        want = np.asarray(pairs, dtype=bool).reshape(n, n_lights)
    else:
        want = np.empty((n, n_lights), dtype=bool)
        if n_distant:
            want[:, :n_distant] = _columns(ns, dirs.astype(np.float32)) > 0.0
        if len(pos):
            n_dot_p = np.einsum("ij,ij->i", ns, rel.astype(np.float32))
            want[:, n_distant:] = _columns(ns, pos.astype(np.float32)) > n_dot_p[:, None]
            dist2 = (
                np.einsum("ij,ij->i", pos, pos)[None, :]
                - 2.0 * _columns(rel, pos)
                + np.einsum("ij,ij->i", rel, rel)[:, None]
            )
            want[:, n_distant:] &= dist2 < (ranges**2)[None, :]
    vis = np.zeros((n, n_lights), np.float32)
    # Per pair, float32 is enough: positions are render-relative (|p| <= extent) and
    # the offset epsilon is >= 160 float32 ulps of |p| (RAY_OFFSET_RELATIVE), so the
    # offset survives the rounding; Embree sees float32 anyway.
    rel32 = rel.astype(np.float32)
    ng32 = np.asarray(offset_normals, np.float32)
    eps = self._bvh.boundary.epsilon(rel).astype(np.float32)
    batches = []  # (point, light, dirs (m, 3), tfar (m,), p (m, 3), eps (m,)) per kind
    local = None
    if n_distant:
        point, light = np.nonzero(want[:, :n_distant])
        d = np.take(dirs.astype(np.float32), light, axis=0)
        if pairs is not None:  # facing (see above), per wanted pair
            front = np.flatnonzero(np.einsum("ij,ij->i", np.take(ns, point, axis=0), d) > 0)
            point, light, d = point[front], light[front], d[front]
        far = np.full(len(point), FAR, np.float32)
        batches.append((point, light, d, far, np.take(rel32, point, axis=0), eps[point]))
    if len(pos):
        point, light = np.nonzero(want[:, n_distant:])
        # np.take: ~3x faster than fancy indexing for row gathers.
        p = np.take(rel32, point, axis=0)
        e = np.take(eps, point)
        to = np.take(pos.astype(np.float32), light, axis=0)
        to -= p
        if pairs is not None:  # facing and range (see above), per wanted pair
            keep = np.einsum("ij,ij->i", np.take(ns, point, axis=0), to) > 0.0
            keep &= np.einsum("ij,ij->i", to, to) < np.take(ranges**2, light)
            keep = np.flatnonzero(keep)
            point, light, p, e, to = point[keep], light[keep], p[keep], e[keep], to[keep]
        dist = np.sqrt(np.einsum("ij,ij->i", to, to))
        np.maximum(dist, np.float32(shading.MIN_LIGHT_DISTANCE), out=dist)
        to /= dist[:, None]
        local = shading.LightPairs(point, light, to, dist)
        # Stop short of the light by the offset so the light's own position is free.
        tfar = np.maximum(dist - e, np.float32(0.0))
        batches.append((point, light + n_distant, to, tfar, p, e))
    point, light, d, tfar, p, e = (
        np.concatenate(parts) if len(batches) > 1 else parts[0]
        for parts in zip(*batches, strict=True)
    )
    m = len(point)
    if m:
        ng = np.take(ng32, point, axis=0)
        ng *= np.where(np.einsum("ij,ij->i", d, ng) >= 0.0, e, -e)[:, None]
        ng += p  # the offset origins
        if self._surfaces is None:
            occluded = self._bvh.run("OCCLUDED", ng, d, tfar, threads)
        else:
            occluded = self._surfaces.occluded(ng, d, tfar, threads)
        vis.reshape(-1)[point * n_lights + light] = ~occluded
        if local is not None:  # the lit LocalLight pairs, for shade_local
            free = np.flatnonzero(~occluded[len(point) - len(local[0]) :])
            local = shading.LightPairs(*(np.take(a, free, axis=0) for a in local[:4]))
    return vis, np.bincount(point, minlength=n).astype(np.int64), local


def _columns(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(n, k) = v (n, 3) @ m (k, 3).T, written per coordinate: numpy hands such skinny
    products to the multithreaded BLAS, whose threads then compete with Embree's."""
    return v[:, 0:1] * m[:, 0][None] + v[:, 1:2] * m[:, 1][None] + v[:, 2:3] * m[:, 2][None]
