"""What the shadow maps say about the lighting of points: the (n, L) visibility matrix,
or the light terms of ``shading.shade_local`` with the lit pairs shaded on the GPU, each
with the (point, light) pairs the maps could not decide left open.

The maps answer most pairs (``shadow_maps``: numpy lookups of the DistantLights' maps on
the worker threads; ``light_pass``: the GPU lookup of every LocalLight's cube maps and
of up to LOOKUP_MAX_DISTANT DistantLights, meanwhile). A pair whose texel neighbourhood
holds both occluding and clear depths is *uncertain*. The result (``MapVisibility``,
``PendingLightTerms``) names those pairs (``uncertain``) and is finished in one of two
ways, chosen by the caller (``render.lighting``): ``resolved`` with an exact answer for
exactly those pairs (the tracer's shadow rays), or ``filtered``, the maps' own
percentage-closer filtering; once, as both settle the result's arrays in place.

Shapes: n points, D DistantLights, L lights in all (``shading``'s order: distant, then
local). Positions are world metres (float64); lookups run in rel space (``context``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phrt_usd import kernels
from phrt_usd.engine.raster.context import RasterContext
from phrt_usd.engine.raster.light_pass import (
    LOOKUP_LIGHTS_PER_PASS,
    LOOKUP_LIT,
    LOOKUP_MAX_DISTANT,
    LOOKUP_UNCERTAIN,
    LightPass,
)
from phrt_usd.engine.raster.shadow_maps import (
    CubeMap,
    ShadowMap,
    ShadowMaps,
    cube_pair_visibility,
    filtered_visibility,
)
from phrt_usd.engine.shading import (
    LightPairs,
    gather_rows,
    light_ranges,
    pair_directions,
    surface_rows,
)
from phrt_usd.engine.terminator import Terminator
from phrt_usd.model.scene import Lights


@dataclass
class UncertainPairs:
    """The (point, light) pairs the maps could not decide, as an exact shadow test
    (``Tracer.shadow_visibility``) takes them: m points with at least one such pair.

    positions : (m, 3) float64 world metres; normals : (m, 3) float64 unit, facing the
    viewer; pairs : (m, L) bool, the undecided pairs (light order distant, then local);
    rows : (m,) int64, which of the looked-up points these are
    """

    positions: np.ndarray
    normals: np.ndarray
    pairs: np.ndarray
    rows: np.ndarray


@dataclass
class LightTerms:
    """What shading G-buffer points needs from the shadow maps (``PendingLightTerms``,
    consumed by ``shading.shade_local``). n points, D DistantLights.

    distant_visibility : (n, D) float32 in [0, 1]: DistantLight visibility of the pairs
                         *not* in ``lit_sums`` (0 for the pairs summed there)
    lit_sums           : (n, 4) float32, channels 0-2 the direct light of the (point,
                         light) pairs the maps decided are lit, shaded on the GPU
                         with the points' BRDF (LocalLights and up to
                         LOOKUP_MAX_DISTANT DistantLights)
    local_pairs        : the (point, LocalLight) pairs the maps could not decide, with
                         their visibility from shadow rays or PCF (lit ones only), or
                         None
    """

    distant_visibility: np.ndarray
    lit_sums: np.ndarray | None
    local_pairs: LightPairs | None


@dataclass
class MapVisibility:
    """Shadow-map visibility of n points to L lights, before the undecided pairs are
    settled (``MapLighting.visibility``).

    positions, normals : (n, 3) float64, as looked up
    visibility : (n, L) float32 in [0, 1], 1 = lit; at the uncertain pairs the maps'
                 PCF (looked up ``filtered``) or 0.5 (left to ``resolved``)
    uncertain  : (n, L) bool
    """

    positions: np.ndarray
    normals: np.ndarray
    visibility: np.ndarray
    uncertain: np.ndarray

    def uncertain_pairs(self) -> UncertainPairs | None:
        """The undecided pairs, None when there are none."""
        if not self.uncertain.any():
            return None
        idx = np.flatnonzero(self.uncertain.any(axis=1))
        return UncertainPairs(self.positions[idx], self.normals[idx], self.uncertain[idx], idx)

    def resolved(self, exact: np.ndarray) -> np.ndarray:
        """(n, L) ``visibility`` with the uncertain pairs replaced (in place) by
        ``exact`` (m, L), an exact test's answer for ``uncertain_pairs()``."""
        vis = self.visibility
        idx = np.flatnonzero(self.uncertain.any(axis=1))
        pairs = self.uncertain[idx]
        exact = np.asarray(exact, dtype=np.float32)
        sub = vis[idx]
        sub[pairs] = exact.reshape(pairs.shape)[pairs]
        vis[idx] = sub
        return vis

    def filtered(self) -> np.ndarray:
        """(n, L) ``visibility`` as the maps have it (their PCF, when looked up so)."""
        return self.visibility


@dataclass
class PendingLightTerms:
    """``LightTerms`` before the undecided pairs are settled (``MapLighting.light_terms``).

    positions       : (n, 3) float64 world metres
    normals         : (n, 3) unit normals (float32 or float64), facing the viewer
    origin          : (3,) ``Scene.origin``: rel = positions - origin
    lights          : the scene's lights at the lookup
    distant         : (n, D) float32 DistantLight visibility (0 where in ``lit_sums``)
    distant_unsure  : (n, D) bool, the DistantLight pairs the maps could not decide
    maps            : the (static, animated) maps of the DistantLights shaded on the GPU
                      (empty when they were looked up in numpy: ``distant`` holds their
                      PCF then)
    cubes           : (static, animated) cube maps per LocalLight
    lit_sums        : as ``LightTerms.lit_sums``; None: nothing to shade (no points or
                      no direct light), the result is ``distant`` alone
    rows            : (m,) int64 points with an undecided pair
    local_unsure    : (m, len(cubes)) bool, their undecided LocalLight pairs
    terminator      : the points' moves onto their smooth meshes' surface for the shadow
                      tests (``engine/terminator.py``), or None
    """

    positions: np.ndarray
    normals: np.ndarray
    origin: np.ndarray
    lights: Lights
    distant: np.ndarray
    distant_unsure: np.ndarray
    maps: list[tuple[ShadowMap | None, ShadowMap | None]]
    cubes: list[tuple[CubeMap | None, CubeMap | None]]
    lit_sums: np.ndarray | None
    rows: np.ndarray
    local_unsure: np.ndarray
    terminator: Terminator | None = None

    def uncertain_pairs(self) -> UncertainPairs | None:
        """The undecided pairs (DistantLight columns first), None when there are none."""
        rows = self.rows
        if not len(rows):
            return None
        positions, normals = (gather_rows(a, rows) for a in (self.positions, self.normals))
        return UncertainPairs(positions, normals, self._pairs(), rows)

    def _pairs(self) -> np.ndarray:
        """(m, L) bool: the undecided pairs of ``rows``, DistantLights first."""
        if not self.distant_unsure.shape[1]:
            return self.local_unsure
        distant = np.take(self.distant_unsure, self.rows, axis=0)
        return np.concatenate([distant, self.local_unsure], axis=1)

    def resolved(self, exact: np.ndarray) -> LightTerms:
        """The light terms with ``exact`` (m, L), an exact test's answer for
        ``uncertain_pairs()``, at the undecided pairs."""
        rows, distant = self.rows, self.distant
        n_distant = distant.shape[1]
        exact = np.asarray(exact, dtype=np.float32).reshape(len(rows), -1)
        if n_distant:
            pairs = self.distant_unsure[rows]
            distant[rows] = np.where(pairs, exact[:, :n_distant], distant[rows])
        point, light, weight = _shade().lit_local_pairs(
            rows, self.local_unsure, np.ascontiguousarray(exact[:, n_distant:])
        )
        return self._terms(point, light, weight)

    def filtered(self) -> LightTerms:
        """The light terms with the maps' PCF at the undecided pairs."""
        if self.lit_sums is None:
            return LightTerms(self.distant, None, None)
        normals, distant = self.normals, self.distant

        def rel_normals(at: np.ndarray, towards) -> tuple[np.ndarray, np.ndarray]:
            """rel metres (moved for a light in directions ``towards(rel)`` (m, 3) or (3,):
            ``Terminator.lifted``) and float64 normals of the points ``at``."""
            rel = self.positions[at] - self.origin
            if self.terminator is not None:
                rel = self.terminator.lifted(rel, at, towards(rel))
            return rel, normals[at].astype(np.float64)

        for k, pair in enumerate(self.maps):  # the uncertain DistantLight pairs
            on = np.flatnonzero(self.distant_unsure[:, k])
            distant[on, k] = 1.0
            direction = self.lights.distant[k].direction
            for mp in pair:
                if mp is not None and len(on):
                    rel, nrm = rel_normals(on, lambda rel, d=direction: d)
                    distant[on, k] *= filtered_visibility(mp, rel, nrm)[0]
        at, light = np.nonzero(self.local_unsure)
        point = self.rows[at]
        weight = np.zeros(len(point), dtype=np.float32)
        # Only the lights with undecided pairs, each once (grouped by a sort rather than
        # a pass over every pair per light: a stage of many lights has few here).
        order = np.argsort(light, kind="stable")
        present, first = np.unique(light[order], return_index=True)
        ends = np.append(first[1:], len(order))[: len(first)]
        for k, lo, hi in zip(present, first, ends, strict=True):
            on = order[lo:hi]
            cube = self.cubes[k][0] or self.cubes[k][1]  # a light with undecided pairs has one
            rel, nrm = rel_normals(point[on], lambda rel, c=cube: c.light_rel - rel)
            weight[on] = cube_pair_visibility(self.cubes[k], rel, nrm, True)[0]
        lit = np.flatnonzero(weight > 0.0)
        return self._terms(point[lit], light[lit], weight[lit])

    def _terms(self, point: np.ndarray, light: np.ndarray, weight: np.ndarray) -> LightTerms:
        """LightTerms with the lit LocalLight pairs (``point``, ``light``) (k,) of
        visibility ``weight`` (k,) float32 in (0, 1]."""
        l_dir, dist = pair_directions(self.lights, self.positions, point, light)
        return LightTerms(
            self.distant, self.lit_sums, LightPairs(point, light, l_dir, dist, weight)
        )


class MapLighting:
    """Looks points up in a ``RasterContext``'s shadow maps (see the module)."""

    def __init__(self, ctx: RasterContext, maps: ShadowMaps, light_pass: LightPass) -> None:
        self._ctx = ctx
        self._maps = maps
        self._light_pass = light_pass

    def visibility(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        filtered: bool,
        on_gpu: bool,
        terminator: Terminator | None = None,
    ) -> MapVisibility:
        """Fraction of every light reaching each point, by shadow mapping.

        positions : (n, 3) float64 world metres
        normals   : (n, 3) unit shading normals facing the viewer (for DistantLights
                    only |n·L| is used, for the bias; LocalLights also skip points
                    facing away)
        filtered  : the uncertain LocalLight pairs get the maps' PCF here; else 0.5, for
                    the caller to resolve (``MapVisibility.resolved``)
        on_gpu    : LocalLight cube lookups on the GPU, else their numpy reference (same
                    answers up to float32 rounding at the test's boundaries)
        terminator: the points' moves onto their smooth meshes' surface for the shadow
                    tests, or None (``engine/terminator.py``)
        DistantLights: the product of the static and the animated casters' filtered
        orthographic maps. LocalLights: cube maps, looked up only for points within the
        light's range (``shading.light_ranges``) and facing it; other pairs get 0 (the
        light contributes nothing there).
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        lights = self._ctx.scene.lights
        n_distant = len(lights.distant)
        cubes = self._maps.cube_maps() if lights.local else []
        n_lights = n_distant + len(cubes)
        if len(positions) == 0 or n_lights == 0:
            out = np.ones((len(positions), n_lights), dtype=np.float32)
            return MapVisibility(positions, normals, out, np.zeros(out.shape, dtype=bool))
        rel = positions - self._ctx.origin
        if n_distant:  # else the LocalLight lookup's own arrays are used (see below)
            out = np.ones((len(positions), n_lights), dtype=np.float32)
            uncertain = np.zeros(out.shape, dtype=bool)
            # The DistantLight columns are filled in place (views, disjoint from the
            # LocalLight columns written below on this thread).
            jobs = self._maps.distant_lookups(
                rel, normals, out[:, :n_distant], uncertain[:, :n_distant], terminator
            )
        else:
            jobs = []
        ranges = light_ranges(lights)
        if cubes:  # meanwhile, on this thread (the GL context's)
            local_vis, local_unsure = self._local_visibility(
                rel, normals, cubes, ranges[n_distant:], filtered, on_gpu, terminator
            )
            if n_distant:
                out[:, n_distant:] = local_vis
                uncertain[:, n_distant:] = local_unsure
            else:  # local lights only: the lookup's arrays are the answer (no copies)
                out, uncertain = local_vis, local_unsure
        for job in jobs:
            job.result()
        return MapVisibility(positions, normals, out, uncertain)

    def _local_visibility(
        self,
        rel: np.ndarray,
        normals: np.ndarray,
        cubes: list[tuple[CubeMap | None, CubeMap | None]],
        ranges: np.ndarray,
        filtered: bool,
        on_gpu: bool,
        terminator: Terminator | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(n, len(cubes)) float32 visibility and bool uncertain of points ``rel`` (n, 3)
        (rel metres) with ``normals`` (n, 3) for every LocalLight: 0 outside its range
        ``ranges`` (len(cubes),) or facing away; uncertain pairs get PCF (``filtered``) or
        0.5; points tested as the ``terminator`` moves them. The bulk runs on the GPU
        (``on_gpu``), else in numpy."""
        n = len(rel)
        vis = np.zeros((n, len(cubes)), dtype=np.float32)
        unsure = np.zeros((n, len(cubes)), dtype=bool)
        if on_gpu:
            codes = self._light_pass.lookup(rel, normals, cubes, ranges, terminator=terminator)
            np.equal(codes, LOOKUP_LIT, out=vis, casting="unsafe")
            np.equal(codes, LOOKUP_UNCERTAIN, out=unsure)
            if not filtered:  # the caller resolves the uncertain pairs itself
                vis[unsure] = 0.5
                return vis, unsure
        for k, pair in enumerate(cubes):
            if on_gpu:
                idx = np.flatnonzero(unsure[:, k])  # only these need more work
                if len(idx) == 0:
                    continue
            else:
                to_light = np.asarray(self._maps.cube_keys[k][0]) - rel
                reach = np.einsum("ij,ij->i", to_light, to_light) < ranges[k] ** 2
                reach &= np.einsum("ij,ij->i", normals, to_light) > 0.0
                idx = np.flatnonzero(reach)
            at = rel[idx]
            cube = pair[0] or pair[1]
            if terminator is not None and cube is not None:  # as the GPU pass tests them
                at = terminator.lifted(at, idx, cube.light_rel - at)
            vis[idx, k], unsure[idx, k] = cube_pair_visibility(pair, at, normals[idx], filtered)
        return vis, unsure

    def light_terms(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        to_eye: np.ndarray,
        surface: np.ndarray | None = None,
        terminator: Terminator | None = None,
    ) -> PendingLightTerms:
        """The shadow-mapped lighting of points, for ``shading.shade_local``: as
        ``visibility`` (same maps), but the (point, light) pairs the maps decide are
        lit, for every LocalLight and up to LOOKUP_MAX_DISTANT DistantLights, are also
        *shaded* on the GPU in the lookup pass (``shaders/cube_lookup.frag``): no (n, L)
        visibility matrix and no numpy shading of them; only the undecided pairs are
        left to settle. Needs the GPU lookup.

        positions : (n, 3) float64 world metres; normals : (n, 3) unit, facing the
        viewer; to_eye : (n, 3) unit directions from the points to the viewer; surface :
        (n, SURFACE_COLUMNS) float32 rows of their UsdPreviewSurface
        (``model.preview_surface``), or (n, 3) albedo, or None (albedo 1): the fallback
        material of that colour; terminator : the points' moves for their shadow tests,
        or None (``engine/terminator.py``).
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals).reshape(-1, 3)
        lights = self._ctx.scene.lights
        n, n_distant = len(positions), len(lights.distant)
        distant = np.ones((n, n_distant), dtype=np.float32)
        distant_unsure = np.zeros((n, n_distant), dtype=bool)
        origin = np.asarray(self._ctx.origin, np.float64)
        if n == 0 or not lights.has_direct:  # nothing to look up: ``distant`` is all
            return PendingLightTerms(
                positions,
                normals,
                origin,
                lights,
                distant,
                distant_unsure,
                maps=[],
                cubes=[],
                lit_sums=None,
                rows=np.zeros(0, dtype=np.int64),
                local_unsure=np.zeros((0, 0), dtype=bool),
            )
        # Up to LOOKUP_MAX_DISTANT DistantLights are looked up and shaded on the GPU
        # too; more are looked up in numpy meanwhile (and shaded by shade_local).
        gpu_distant = n_distant <= LOOKUP_MAX_DISTANT
        maps = self._maps.distant_maps() if gpu_distant and n_distant else []
        jobs = (
            []
            if gpu_distant
            else self._maps.distant_lookups(
                positions - origin, normals.astype(np.float64), distant, distant_unsure,
                terminator,
            )  # fmt: skip
        )
        cubes = self._maps.cube_maps() if lights.local else []
        ranges = light_ranges(lights)[n_distant:]
        rows_of = surface_rows(np.ones((n, 3), np.float32) if surface is None else surface, n)
        # Each tile of points looks up and shades only the LocalLights whose range
        # reaches it (``light_pass.LOOKUP_TILE``): the others light none of its points.
        direct, bits, tiles = self._light_pass.lookup(
            positions, normals, cubes, ranges, to_eye, maps, origin=origin, surface=rows_of,
            terminator=terminator,
        )  # fmt: skip
        for job in jobs:
            job.result()
        if maps:
            # Lit pairs are in the sums already: ``distant`` keeps only what shade_local
            # must still add, the uncertain pairs once resolved.
            distant[:] = 0.0
        # The pairs the maps could not decide, on the few rows that have any: the
        # LocalLight ones are shaded from their visibility (exact, else the maps' PCF),
        # the DistantLight ones are corrected in ``distant``.
        rows, local_unsure = _shade().undecided_rows(
            bits, len(cubes), tiles.slots, LOOKUP_LIGHTS_PER_PASS, bool(maps), distant_unsure,
            tiles.point_tile,
        )  # fmt: skip
        return PendingLightTerms(
            positions,
            normals,
            origin,
            lights,
            distant,
            distant_unsure,
            maps,
            cubes,
            direct,
            rows,
            local_unsure,
            terminator,
        )


def _shade():
    """The compiled kernels (``shade_kernels``), taken on first use."""
    return kernels.load("phrt_usd.engine.shade_kernels")
