"""The rasterizer a renderer holds: one OpenGL context (``context``) and its passes, the
G-buffer (``gbuffer``), the shadow maps (``shadow_maps``) and the GPU light pass
(``light_pass``) with what they say about points (``map_lighting``).

The shadow queries return the (point, light) pairs the maps could not decide
(``map_visibility``, ``map_light_terms``); who settles them is the caller's choice
(``render.lighting``: the tracer's shadow rays in hybrid mode, the maps' PCF in raster
mode). ``shadow_visibility`` and ``light_terms`` settle them at once, with PCF or a
given exact test, for callers that hold no renderer (tests, tools).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from phrt_usd.engine.raster.context import GeometryChange, RasterContext
from phrt_usd.engine.raster.gbuffer import GBufferPass
from phrt_usd.engine.raster.light_pass import LightPass
from phrt_usd.engine.raster.map_lighting import (
    LightTerms,
    MapLighting,
    MapVisibility,
    PendingLightTerms,
)
from phrt_usd.engine.raster.shadow_maps import CubeMap, ShadowMap, ShadowMaps
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import CameraFrame, Scene
from phrt_usd.model.surface import TriangleTable

#: An exact shadow test of the undecided pairs: ``(positions (m, 3), normals (m, 3),
#: pairs (m, L) bool) -> (m, L)`` visibility, needed only at ``pairs`` (e.g. Embree
#: shadow rays).
ExactTest = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


class Rasterizer:
    """Rasterizes a ``Scene`` into ``GBuffer`` s and answers shadow queries from its maps
    (one OpenGL context per instance).

    Usage::

        r = Rasterizer(scene, 320, 240)
        g = r.render(camera_frame)                 # GBuffer, every field filled
        vis = r.shadow_visibility(points, normals)  # (n, L) lights distant, then local
        r.update_geometry(scene)                   # after set_time: what changed
        r.close()
    """

    def __init__(self, scene: Scene, width: int, height: int) -> None:
        if width <= 0 or height <= 0:
            raise PhrtError(f"image size {width}x{height} must be positive")
        self.width = int(width)
        self.height = int(height)
        self._ctx = RasterContext(scene, self.width, self.height)
        self._gbuffer = GBufferPass(self._ctx)
        self._maps = ShadowMaps(self._ctx)
        self._lookups = MapLighting(self._ctx, self._maps, LightPass(self._ctx, self._maps))
        #: LocalLight cube lookups on the GPU (False: the numpy reference, same answers
        #: up to float32 rounding at the test's boundaries).
        self.cube_lookup_on_gpu = True
        self.last_refined = 0  # points handed to the exact test by the latest query
        self.last_refined_pairs = 0  # (point, light) pairs among them
        self._closed = False
        _OPEN.add(self)
        try:
            self._upload(scene)
        except BaseException:
            self.close()
            raise

    def _upload(self, scene: Scene) -> None:
        self._ctx.upload(scene)
        self._gbuffer.upload(scene)
        self._use_cutouts()

    def _use_cutouts(self) -> None:
        """The shadow maps render through the G-buffer's cut-outs (its surface table
        only when there are any: ``GBufferPass.table`` is built on first use)."""
        cutouts = self._gbuffer.cutouts
        self._maps.use_cutouts(cutouts, self._gbuffer.table if cutouts.any else None)

    @property
    def gl_renderer(self) -> str:
        """The OpenGL implementation's name (``GL_RENDERER``)."""
        return self._ctx.gl_renderer

    def update_geometry(self, scene: Scene) -> GeometryChange:
        """Bring the uploaded geometry to ``scene``'s current version
        (``RasterContext.update_geometry``): nothing when it is the version uploaded;
        else only the vertices and G-buffer table rows of the elements that changed
        since, or everything after a rebuild. The shadow maps of the batches that
        changed are rendered again when next asked for (they compare the context's
        ``batch_versions``). Returns what was re-sent (``GeometryChange``).
        """
        self._check_open()
        change = self._ctx.update_geometry(scene)
        if change.rebuilt:
            self._gbuffer.upload(scene)
            self._use_cutouts()
        else:
            self._gbuffer.geometry_moved(scene, change.moved_rows)
        return change

    @property
    def triangle_table(self) -> TriangleTable:
        """The uploaded geometry's per-triangle tables (rel; built on first use)."""
        return self._gbuffer.table

    def render(self, camera: CameraFrame) -> GBuffer:
        """Rasterize one frame (``GBufferPass.render``)."""
        self._check_open()
        return self._gbuffer.render(camera)

    # ------------------------------------------------------------------ shadow maps

    def shadow_maps(self) -> list[tuple[ShadowMap | None, ShadowMap | None]]:
        """(static, animated-casters) map per DistantLight (``ShadowMaps.distant_maps``)."""
        self._check_open()
        return self._maps.distant_maps()

    def cube_maps(self) -> list[tuple[CubeMap | None, CubeMap | None]]:
        """(static, animated-casters) cube map per LocalLight (``ShadowMaps.cube_maps``)."""
        self._check_open()
        return self._maps.cube_maps()

    def map_visibility(
        self, positions: np.ndarray, normals: np.ndarray, filtered: bool, terminator=None
    ) -> MapVisibility:
        """(n, L) shadow-map visibility of points and the pairs the maps could not decide
        (``MapLighting.visibility``): ``filtered`` gives those the maps' PCF, else they
        wait for ``MapVisibility.resolved``; ``terminator``: the points' moves for their
        shadow tests (``engine/terminator.py``), or None."""
        self._check_open()
        return self._lookups.visibility(
            positions, normals, filtered, self.cube_lookup_on_gpu, terminator
        )

    def map_light_terms(
        self, positions: np.ndarray, normals: np.ndarray, to_eye: np.ndarray, surface=None,
        terminator=None,
    ) -> PendingLightTerms:  # fmt: skip
        """Light terms of points with the lit pairs shaded on the GPU with the points'
        ``surface`` rows (``model.preview_surface``; None: the fallback material of
        albedo 1), the undecided pairs still open (``MapLighting.light_terms``;
        ``terminator`` as ``map_visibility``'s). Requires ``cube_lookup_on_gpu``."""
        self._check_open()
        return self._lookups.light_terms(positions, normals, to_eye, surface, terminator)

    def shadow_visibility(
        self, positions: np.ndarray, normals: np.ndarray, refine: ExactTest | None = None
    ) -> np.ndarray:
        """(n, L) float32 in [0, 1], 1 = lit: ``map_visibility`` with the undecided pairs
        settled by ``refine`` (an ``ExactTest``, called once on the points that have
        any), else by the maps' PCF. positions : (n, 3) float64 world metres;
        normals : (n, 3) unit, facing the viewer. ``last_refined`` holds how many
        points were handed to ``refine``, ``last_refined_pairs`` how many pairs."""
        return self._settle(self.map_visibility(positions, normals, refine is None), refine)

    def light_terms(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        to_eye: np.ndarray,
        refine: ExactTest | None = None,
        surface: np.ndarray | None = None,
    ) -> LightTerms:
        """``map_light_terms`` with the undecided pairs settled as in
        ``shadow_visibility``; to_eye : (n, 3) unit directions to the viewer."""
        return self._settle(self.map_light_terms(positions, normals, to_eye, surface), refine)

    def _settle(
        self, pending: MapVisibility | PendingLightTerms, refine: ExactTest | None
    ) -> np.ndarray | LightTerms:
        self.last_refined = self.last_refined_pairs = 0
        query = pending.uncertain_pairs()
        if refine is None or query is None:
            return pending.filtered()
        self.last_refined = len(query.pairs)
        self.last_refined_pairs = int(query.pairs.sum())
        return pending.resolved(refine(query.positions, query.normals, query.pairs))

    # ------------------------------------------------------------------ lifetime

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("Rasterizer used after close()")

    def close(self) -> None:
        """Free the OpenGL resources and the context (idempotent)."""
        if self._closed:
            return
        self._closed = True
        _OPEN.discard(self)
        self._maps.close()
        self._gbuffer.close()
        self._ctx.close()

    def __enter__(self) -> Rasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: Every rasterizer not closed yet. pyrender's own finalisers delete GL objects in whatever
#: context is current, and the garbage collector can run them in the middle of another
#: rasterizer's render (any allocation may trigger it), deleting that one's framebuffers:
#: so a rasterizer is referenced from here until ``close()`` (or the end of the process)
#: and is never collected while open.
_OPEN: set[Rasterizer] = set()
