"""The id pass and its derivation into the ``GBuffer``.

1. **Id pass** (``GBufferPass.render``). pyrender's ``Renderer`` (``context``) draws the
   one mesh node with ``RenderFlags.FLAT``; its program cache points at
   ``phrt_usd/engine/raster/shaders``, whose ``flat.frag`` writes ``gl_PrimitiveID + 1``
   (= triangle index + 1, 0 = background) as four exact bytes into the single-sampled
   id framebuffer. Read back: the id image only.
2. **Derivation** (``model.surface_kernels.derive``: one compiled loop over the
   pixels, in row blocks on the context's worker threads). The pixel ray (same pixel
   centres as ``CameraFrame.pixel_rays``) is intersected with its triangle's plane in
   float64: position (exact, not limited by depth-buffer precision), view depth,
   barycentrics → interpolated shading normal (the side rule) and albedo. Texture
   lookups, normal maps and cut-out holes follow in numpy (``model.surface``) at the
   pixels whose material has them, from the weights the kernel kept.

Coordinate spaces as in ``context``: "world" is ``Scene`` world metres (float64); "rel"
is world minus ``Scene.origin``.

3. **Cut-outs** (UsdPreviewSurface ``opacityThreshold``; scenes with cut-out materials
   only). The id pass is then drawn by ``cutout_layers.IdLayers`` (same ids, and the
   window depths); a covered pixel whose point is a hole (``model.surface.Cutouts`` at
   the derivation's barycentrics, the rule the tracer uses) is peeled: the next layer's
   triangle behind it is derived instead, at most ``surface.MAX_CUTOUT_LAYERS`` times
   (then, or where nothing is behind, the pixel is background).

Limits: opaque triangles only (transmission is a tracer concern). Materials are read when
the topology is uploaded. Coincident (coplanar, overlapping) surfaces z-fight here as
they do in Embree: either may win.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyrender
from pyrender.constants import RenderFlags

from phrt_usd import kernels
from phrt_usd.engine.raster.context import CLIP_PADDING, RasterContext
from phrt_usd.engine.raster.cutout_layers import IdLayers
from phrt_usd.errors import PhrtError
from phrt_usd.model import surface
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import NO_HIT, CameraFrame, Scene, perspective_matrix

#: The compiled surface rule (``model.surface_kernels``, through ``phrt_usd.kernels``).
_SURFACE = kernels.load("phrt_usd.model.surface_kernels")

#: Smallest allowed near / far ratio of the perspective projection. The depth buffer
#: resolves view depth z to about z**2 / (near * 2**24); as near → 0 that diverges and
#: the projection degenerates (every depth maps to 1, all surfaces z-fight). near / far
#: is first tightened to the scene's bounds (``_clip_range``), so this clamp only acts
#: for a camera inside or at the scene with a tiny clipping near: it then clips what is
#: nearer than 1e-6 * far (1 mm at far = 1 km) and keeps depth resolution finite. Ids
#: only need the depth order of surfaces; positions never come from the depth buffer.
MIN_NEAR_OVER_FAR = 1e-6

#: Pixel blocks per worker thread of the derivation. Covered pixels cost ~20x a
#: background pixel, and sky or floor fill whole bands of rows, so one block per thread
#: leaves a thread idle (farm, 640x480: 2 threads no faster than 1); 4 blocks each even
#: out the bands for a few microseconds of scheduling.
DERIVE_BLOCKS_PER_THREAD = 4

#: The kernels' empty arguments: no pixel list, no id map (id k of the id pass is
#: triangle k - 1), no id image.
_NONE = np.zeros(0, dtype=np.int64)
_NO_IDS = np.zeros(0, dtype=np.uint32)


class _ExactPerspective(pyrender.camera.Camera):
    """pyrender camera whose projection matrix is given explicitly (camera → clip)."""

    def __init__(self) -> None:
        super().__init__(znear=0.01, zfar=100.0)
        self.matrix = np.eye(4)

    def get_projection_matrix(self, width=None, height=None) -> np.ndarray:
        return self.matrix


@dataclass
class _Outputs:
    """The G-buffer arrays being filled, flat over pixels (H*W rows); see ``GBuffer``.
    bary : (H*W, 3) float32 each covered pixel's barycentric weights, or (0, 3) when no
    surface input needs them (``GBufferPass.upload``)."""

    triangle_id: np.ndarray
    element_id: np.ndarray
    depth: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    view_dir: np.ndarray
    bary: np.ndarray
    hole: np.ndarray | None = None  # (H*W,) bool: the derived point is a cut-out hole


class GBufferPass:
    """The id pass over a ``RasterContext``'s geometry and the per-triangle tables its
    derivation reads (see the module)."""

    def __init__(self, ctx: RasterContext) -> None:
        self._ctx = ctx
        self.width, self.height = ctx.width, ctx.height
        self._pcamera = _ExactPerspective()
        self._cam_node = ctx.pscene.add(self._pcamera, pose=np.eye(4))
        self._pool = ctx.pool
        self._dirs_key: tuple | None = None
        self._dirs_grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._layers: IdLayers | None = None  # made for the first scene with cut-outs

    @property
    def _scene(self) -> Scene:
        return self._ctx.scene

    @property
    def _origin(self) -> np.ndarray:
        """(3,) float64 ``Scene.origin`` of the uploaded geometry."""
        return self._ctx.origin

    # ------------------------------------------------------------------ tables

    def upload(self, scene: Scene) -> None:
        """The per-triangle tables, after the context uploaded ``scene``'s topology (the
        surface table on first use, ``table``)."""
        # Built when the id pass or the cut-out maps first need it: a renderer whose
        # G-buffer comes from primary rays (render.primary_source) may never (~0.6 s
        # for 1M triangles).
        self._table: surface.TriangleTable | None = None
        self._tri_element = np.ascontiguousarray(scene.geometry.tri_element, dtype=np.int64)
        self._textured(scene)
        geo = scene.geometry
        #: The cut-out rule of the uploaded triangles (``surface.Cutouts``).
        self.cutouts = surface.Cutouts(scene.materials, geo.tri_material, geo.corner_uv)
        self.normal_maps = surface.NormalMaps(scene.materials, geo.tri_material, geo.corner_uv)
        #: Some surface input is looked up per pixel after the kernel (textures, normal
        #: maps, cut-out holes): the kernel then keeps each pixel's barycentric weights.
        self._needs_weights = bool(
            self._tri_textured.any() or self.normal_maps.any or self.cutouts.any
        )
        if self.cutouts.any and self._layers is None:
            self._layers = IdLayers(self._ctx, self.width, self.height)

    @property
    def table(self) -> surface.TriangleTable:
        """The per-triangle tables of the uploaded geometry (rel), built on first use."""
        if self._table is None:
            self._table = surface.TriangleTable(self._scene.geometry.triangle_count)
            self._fill_tables(self._scene, slice(None))  # a slice: no gather over every row
        return self._table

    def close(self) -> None:
        """Free the cut-out layers' OpenGL objects (before the context goes)."""
        if self._layers is not None:
            self._layers.close()
            self._layers = None

    def geometry_moved(self, scene: Scene, moved_rows: np.ndarray) -> None:
        """Refresh the tables of ``moved_rows`` (m,) int64 ascending, the triangles of
        the elements that changed (``RasterContext.update_geometry``; same topology):
        their positions and shading (normals, albedo), nothing else."""
        if self._table is None:  # not built yet: it will be from the geometry as it is
            return
        if len(moved_rows):
            self._fill_tables(scene, moved_rows)

    def _fill_tables(self, scene: Scene, rows: np.ndarray | slice) -> None:
        """Recompute the per-triangle tables (``_table``, a ``surface.TriangleTable``,
        rel space) of triangles ``rows`` (index array or slice)."""
        geo = scene.geometry
        self._table.fill(
            geo.vertices, geo.triangles, self._origin, geo.corner_normals, geo.corner_albedo, rows
        )

    def _textured(self, scene: Scene) -> None:
        """_tri_textured : (T,) bool, True where the material has a texture and uvs exist."""
        geo = scene.geometry
        textures = scene.materials.textures
        has_tex = np.array([t is not None for t in textures] + [False], dtype=bool)
        mat = np.where(
            (geo.tri_material >= 0) & (geo.tri_material < len(textures)),
            geo.tri_material,
            len(textures),
        )
        self._tri_textured = has_tex[mat] & (geo.corner_uv is not None)

    # ------------------------------------------------------------------ camera

    def _clip_range(self, camera: CameraFrame, eye_rel: np.ndarray) -> tuple[float, float] | None:
        """(near, far) view depths in metres for the projection, or None when the
        camera's clipping range holds no geometry.

        The camera's clipping range, tightened to the scene's bounds (nothing exists
        outside them, and a tighter range means finer depth resolution): far to the
        farthest bounds corner, near to the nearest bounds point's distance times the
        frustum's smallest cos (a point that near may sit at the image corner, where
        depth = distance * cos), both padded by CLIP_PADDING * extent. Then
        near >= far * MIN_NEAR_OVER_FAR (see there).
        """
        lo, hi = self._ctx.bounds_rel
        pad = CLIP_PADDING * self._ctx.extent
        nearest = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - eye_rel, eye_rel - hi))))
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
        farthest = float(np.linalg.norm(corners.reshape(-1, 3) - eye_rel, axis=1).max())
        left, right, bottom, top = camera.image_window(self.width, self.height)
        tx, ty = max(abs(left), abs(right)), max(abs(bottom), abs(top))  # farthest corner
        min_cos = 1.0 / np.sqrt(1.0 + tx * tx + ty * ty)
        far = min(float(camera.far), farthest + pad)
        near = max(float(camera.near), nearest * min_cos - pad)
        if not far > near:  # also catches NaN clipping ranges
            return None
        near = max(near, far * MIN_NEAR_OVER_FAR)
        return near, far

    def _pixel_grid(self, camera: CameraFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """xs (W,), ys (H,) float64 pixel-plane coordinates (``CameraFrame.pixel_plane``)
        and inv_len (H, W) float64 = 1 / |(xs[col], ys[row], -1)|: with the camera's
        rotation they give every pixel's unit world direction (the kernels'
        ``_pixel_dir``). Cached per field of view."""
        key = camera.image_window(self.width, self.height)
        if key != self._dirs_key:
            xs, ys = camera.pixel_plane(self.width, self.height)
            inv_len = 1.0 / np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
            self._dirs_grid = (xs, ys, np.ascontiguousarray(inv_len))
            self._dirs_key = key
        return self._dirs_grid

    # ------------------------------------------------------------------ render

    def render(self, camera: CameraFrame) -> GBuffer:
        """Rasterize one frame. Returns a ``GBuffer`` with every field filled:
        background pixels have ids -1, depth inf, position 0, normal = -view_dir,
        albedo 0."""
        h, w = self.height, self.width
        cam = np.asarray(camera.world_from_camera, dtype=np.float64)
        rot = np.ascontiguousarray(cam[:3, :3])
        eye_rel = cam[:3, 3] - self._origin
        window = camera.image_window(w, h)
        tx, ty = camera.tan_half_fov(w, h)
        if not (np.all(np.isfinite(window)) and tx > 0.0 and ty > 0.0):
            raise PhrtError(
                f"camera: focal length {camera.focal_length} and apertures "
                f"{camera.horizontal_aperture} x {camera.vertical_aperture} give no "
                "field of view"
            )
        clip = self._clip_range(camera, eye_rel) if self._ctx.mesh_node is not None else None
        tri_map = _NONE  # no id map: id k is triangle k - 1
        if clip is not None:
            near, far = clip
            pose = cam.copy()
            pose[:3, 3] = eye_rel
            self._pcamera.matrix = perspective_matrix(window, near, far)
            self._pcamera.znear, self._pcamera.zfar = near, far
            if self.cutouts.any:
                clip_from_rel = self._pcamera.matrix @ np.linalg.inv(pose)
                layer = self._layers.render(clip_from_rel, w, h)
                ids, layer_depth = (np.ascontiguousarray(a[::-1]).reshape(-1) for a in layer)
                # Layer ids number the static triangles, then the animated ones.
                tri_map = self._layers.batch_triangles(("static", "dynamic")).astype(np.int64)
            else:
                self._ctx.pscene.set_pose(self._cam_node, pose)
                self._ctx.make_current()
                flags = RenderFlags.FLAT | RenderFlags.OFFSCREEN | RenderFlags.SKIP_CULL_FACES
                ids = self._ctx.renderer.render(self._ctx.pscene, flags).reshape(-1)
        else:  # no geometry, or none inside the camera's clipping range
            near, far = 0.0, 0.0
            ids = np.zeros(h * w, dtype=np.uint32)

        n = h * w
        # Every row of every pixel is written by the kernel (background too).
        out = _Outputs(
            triangle_id=np.empty(n, dtype=np.int32),
            element_id=np.empty(n, dtype=np.int32),
            depth=np.empty(n, dtype=np.float32),
            position=np.empty((n, 3), dtype=np.float64),
            normal=np.empty((n, 3), dtype=np.float32),
            albedo=np.empty((n, 3), dtype=np.float32),
            view_dir=np.empty((n, 3), dtype=np.float32),
            bary=np.empty((n if self._needs_weights else 0, 3), dtype=np.float32),
        )
        if self.cutouts.any:
            out.hole = np.zeros(n, dtype=bool)
        fwd = -rot[:, 2] / np.linalg.norm(rot[:, 2])
        # Directions: rotated unit camera-space rays (as pixel_rays); a camera transform
        # with scale or shear needs the normalisation again.
        renormalise = not np.allclose(rot.T @ rot, np.eye(3), rtol=0.0, atol=1e-12)
        view = (
            *self._pixel_grid(camera), rot, renormalise, eye_rel, float(near), float(far), fwd,
        )  # fmt: skip
        self._derive_frame(np.ascontiguousarray(ids, dtype=np.uint32), tri_map, view, out)
        if self._needs_weights:
            covered = np.flatnonzero(out.triangle_id >= 0)
            self._surface_inputs(covered, out)
        if clip is not None and self.cutouts.any:
            self._peel(clip_from_rel, ids, layer_depth, tri_map, view, out)

        return GBuffer(
            element_id=out.element_id.reshape(h, w),
            triangle_id=out.triangle_id.reshape(h, w),
            depth=out.depth.reshape(h, w),
            position=out.position.reshape(h, w, 3),
            normal=out.normal.reshape(h, w, 3),
            albedo=out.albedo.reshape(h, w, 3),
            view_dir=out.view_dir.reshape(h, w, 3),
        )

    def _tables(self) -> tuple:
        """The kernels' per-triangle arguments: plane, corners, frame, tri_element."""
        table = self.table
        return (table.plane, table.corners, table.frame, self._tri_element)

    def _outputs(self, out: _Outputs) -> tuple:
        """The kernels' output arguments (``surface_kernels.derive``)."""
        return (out.triangle_id, out.element_id, out.depth, out.position, out.normal,
                out.albedo)  # fmt: skip

    def _derive_frame(self, ids: np.ndarray, tri_map: np.ndarray, view: tuple, out) -> None:
        """Every pixel of ``out`` from the id image ``ids`` (H*W,) uint32
        (``surface_kernels.derive``), in DERIVE_BLOCKS_PER_THREAD contiguous pixel blocks
        per worker thread (the kernel releases the GIL; each block writes its own
        pixels)."""
        n = len(ids)
        view = (ids, tri_map, *view, self._origin, *self._tables())
        outs = (*self._outputs(out), out.view_dir, out.bary)
        blocks = self._ctx.threads * DERIVE_BLOCKS_PER_THREAD if self._ctx.threads > 1 else 1
        bounds = np.linspace(0, n, blocks + 1).astype(np.int64)
        jobs = [
            self._pool.submit(_SURFACE.derive, _NONE, _NONE, int(lo), int(hi), *view, *outs)
            for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)
            if hi > lo
        ]
        for job in jobs:
            job.result()  # re-raises a worker's exception here

    def _derive_pixels(self, pixels: np.ndarray, tid: np.ndarray, view: tuple, out) -> None:
        """Pixels ``pixels`` (k,) re-derived on triangles ``tid`` (k,) (the surface behind
        a cut-out hole), then their surface inputs."""
        _SURFACE.derive(
            pixels.astype(np.int64), tid.astype(np.int64), 0, 0, _NO_IDS, _NONE, *view,
            self._origin, *self._tables(), *self._outputs(out), out.view_dir, out.bary,
        )  # fmt: skip
        self._surface_inputs(pixels, out)

    def _surface_inputs(self, covered: np.ndarray, out: _Outputs) -> None:
        """What the kernel leaves to ``model.surface`` at covered pixels (k,): texture
        albedo, normal maps, cut-out holes, from each pixel's triangle and weights."""
        if len(covered) == 0:
            return
        geo = self._scene.geometry
        tid = np.take(out.triangle_id, covered).astype(np.int64)
        bary = np.take(out.bary, covered, axis=0)
        if self.normal_maps.any:
            incoming = np.take(out.view_dir, covered, axis=0).astype(np.float64)
            n = np.take(out.normal, covered, axis=0)
            out.normal[covered] = self.normal_maps.apply(n, tid, bary, incoming, self.table)
        textured = np.flatnonzero(self._tri_textured[tid])
        if len(textured):
            rows = covered[textured]
            out.albedo[rows] = surface.texture_albedo(
                np.take(out.albedo, rows, axis=0),
                tid[textured],
                bary[textured],
                geo.tri_material,
                geo.corner_uv,
                self._scene.materials.textures,
                inputs=self._scene.materials.texture_inputs,
            )
        if out.hole is not None:
            out.hole[covered] = self.cutouts.holes(tid, bary)

    def _peel(self, clip_from_rel, ids, layer_depth, tri_map, view, out: _Outputs) -> None:
        """Cut-out holes (``out.hole``) peeled (module, step 3): pixels showing a hole
        get the next surface behind it, derived again, until none is a hole or
        ``surface.MAX_CUTOUT_LAYERS`` layers were peeled. ids, layer_depth : (H*W,) the
        layer's encoded ids and window depths (row 0 = top), updated in place; tri_map:
        the layers' id → triangle map."""
        h, w = self.height, self.width
        pending = np.flatnonzero(out.hole)
        for _ in range(surface.MAX_CUTOUT_LAYERS):
            if len(pending) == 0:
                return
            prev_ids = np.zeros(h * w, np.uint32)
            prev_depth = np.ones(h * w, np.float32)
            prev_ids[pending] = ids[pending]
            prev_depth[pending] = layer_depth[pending]
            previous = (prev_ids.reshape(h, w)[::-1], prev_depth.reshape(h, w)[::-1])
            layer = self._layers.render(clip_from_rel, w, h, previous=previous)
            ids2, depth2 = (a[::-1].reshape(-1) for a in layer)
            _background(out, pending)
            found = pending[ids2[pending] > 0]
            ids[found], layer_depth[found] = ids2[found], depth2[found]
            if len(found):
                self._derive_pixels(found, tri_map[ids[found].astype(np.int64) - 1], view, out)
            pending = found[out.hole[found]]
        _background(out, pending)  # still in holes after the bound: nothing (module)


def _background(out: _Outputs, pixels: np.ndarray) -> None:
    """Reset ``pixels`` (k,) of ``out`` to the background (``GBufferPass.render``)."""
    out.normal[pixels] = -np.take(out.view_dir, pixels, axis=0)
    out.triangle_id[pixels] = NO_HIT
    out.element_id[pixels] = NO_HIT
    out.depth[pixels] = np.inf
    out.position[pixels] = 0.0
    out.albedo[pixels] = 0.0
    out.hole[pixels] = False
