"""The id pass and its derivation into the ``GBuffer``.

1. **Id pass** (``GBufferPass.render``). pyrender's ``Renderer`` (``context``) draws the
   one mesh node with ``RenderFlags.FLAT``; its program cache points at
   ``phrt_usd/render/raster/shaders``, whose ``flat.frag`` writes ``gl_PrimitiveID + 1``
   (= triangle index + 1, 0 = background) as four exact bytes into the single-sampled
   id framebuffer. Read back: the id image only.
2. **Derivation** (numpy, covered pixels only, on the context's worker threads). The
   pixel ray (same pixel centres as ``CameraFrame.pixel_rays``) is intersected with its
   triangle's plane in float64: position (exact, not limited by depth-buffer precision),
   view depth, barycentrics → interpolated shading normal and albedo (texture lookup
   when the material has one).

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

from phrt_usd.errors import PhrtError
from phrt_usd.model import surface
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import NO_HIT, CameraFrame, Scene
from phrt_usd.render.raster.context import (
    CLIP_PADDING,
    RasterContext,
    transform_rows,
)
from phrt_usd.render.raster.cutout_layers import IdLayers

#: Smallest allowed near / far ratio of the perspective projection. The depth buffer
#: resolves view depth z to about z**2 / (near * 2**24); as near → 0 that diverges and
#: the projection degenerates (every depth maps to 1, all surfaces z-fight). near / far
#: is first tightened to the scene's bounds (``_clip_range``), so this clamp only acts
#: for a camera inside or at the scene with a tiny clipping near: it then clips what is
#: nearer than 1e-6 * far (1 mm at far = 1 km) and keeps depth resolution finite. Ids
#: only need the depth order of surfaces; positions never come from the depth buffer.
MIN_NEAR_OVER_FAR = 1e-6

#: Denominator floor (relative to |face normal|) of the ray-plane intersection. A pixel
#: is only covered by a triangle the rasterizer saw with non-zero screen area, so the ray
#: is not parallel to its plane; the floor only guards against rounding, and the
#: resulting distance is clamped to the near/far range the rasterizer used.
GRAZING_EPS = 1e-12


class _ExactPerspective(pyrender.camera.Camera):
    """pyrender camera whose projection matrix is given explicitly (camera → clip)."""

    def __init__(self) -> None:
        super().__init__(znear=0.01, zfar=100.0)
        self.matrix = np.eye(4)

    def get_projection_matrix(self, width=None, height=None) -> np.ndarray:
        return self.matrix


def perspective_matrix(
    window: tuple[float, float, float, float], near: float, far: float
) -> np.ndarray:
    """OpenGL clip_from_camera (4, 4) float64 for the image-plane ``window`` (left,
    right, bottom, top) at distance 1 (``CameraFrame.image_window``, so that
    ``CameraFrame.project``, the primary rays and the rasterizer put a point on the same
    pixel; off-centre for aperture offsets) and clip planes ``near`` < ``far``
    (metres)."""
    left, right, bottom, top = window
    p = np.zeros((4, 4))
    p[0, 0] = 2.0 / (right - left)
    p[0, 2] = (right + left) / (right - left)
    p[1, 1] = 2.0 / (top - bottom)
    p[1, 2] = (top + bottom) / (top - bottom)
    p[2, 2] = (far + near) / (near - far)
    p[2, 3] = 2.0 * far * near / (near - far)
    p[3, 2] = -1.0
    return p


@dataclass
class _Outputs:
    """The G-buffer arrays being filled, flat over pixels (H*W rows); see ``GBuffer``."""

    triangle_id: np.ndarray
    element_id: np.ndarray
    depth: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
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
        """All per-triangle tables, after the context uploaded ``scene``'s topology."""
        n = scene.geometry.triangle_count
        self._table = surface.TriangleTable(n)
        self._fill_tables(scene, slice(None))  # a slice: no gather over every row
        self._textured(scene)
        geo = scene.geometry
        #: The cut-out rule of the uploaded triangles (``surface.Cutouts``).
        self.cutouts = surface.Cutouts(scene.materials, geo.tri_material, geo.corner_uv)
        self.normal_maps = surface.NormalMaps(scene.materials, geo.tri_material, geo.corner_uv)
        if self.cutouts.any and self._layers is None:
            self._layers = IdLayers(self._ctx, self.width, self.height)

    @property
    def table(self) -> surface.TriangleTable:
        """The per-triangle tables of the uploaded geometry (rel)."""
        return self._table

    def close(self) -> None:
        """Free the cut-out layers' OpenGL objects (before the context goes)."""
        if self._layers is not None:
            self._layers.close()
            self._layers = None

    def geometry_moved(self, scene: Scene, tri_moved: np.ndarray) -> None:
        """Refresh the tables of moved triangles ``tri_moved`` (T,) bool (same topology)."""
        geo = scene.geometry
        # Shading (normals, albedo) is re-read for moved and animated triangles only:
        # other elements' shading is static (materials are not animated).
        check = np.flatnonzero(tri_moved | self._ctx.animated_tri)
        if len(check):
            differs = self._table.corners_differ(geo.corner_normals, geo.corner_albedo, check)
            rows = check[tri_moved[check] | differs]
            if len(rows):
                self._fill_tables(scene, rows)

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

    def _world_dirs(self, camera: CameraFrame, rot: np.ndarray) -> np.ndarray:
        """(H*W, 3) float64 unit world directions through pixel centres, in the order
        and with the formula of ``CameraFrame.pixel_rays``, for the camera-to-world
        rotation ``rot`` (3, 3). Pixel (row, col) is ``(ys[row] rot_y + xs[col] rot_x -
        rot_z) / |(xs[col], ys[row], -1)|``: one broadcast sum of a per-row and a
        per-column term, the lengths cached per field of view."""
        key = camera.image_window(self.width, self.height)
        if key != self._dirs_key:
            xs, ys = camera.pixel_plane(self.width, self.height)
            inv_len = 1.0 / np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
            self._dirs_grid = (xs, ys, inv_len[:, :, None])
            self._dirs_key = key
        xs, ys, inv_len = self._dirs_grid
        per_row = ys[:, None] * rot[:, 1] - rot[:, 2]  # (H, 3)
        per_col = xs[:, None] * rot[:, 0]  # (W, 3)
        d = per_row[:, None, :] + per_col[None, :, :]
        d *= inv_len
        return d.reshape(-1, 3)

    # ------------------------------------------------------------------ render

    def render(self, camera: CameraFrame) -> GBuffer:
        """Rasterize one frame. Returns a ``GBuffer`` with every field filled:
        background pixels have ids -1, depth inf, position 0, normal = -view_dir,
        albedo 0."""
        h, w = self.height, self.width
        cam = np.asarray(camera.world_from_camera, dtype=np.float64)
        rot = cam[:3, :3]
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
        if clip is not None:
            near, far = clip
            pose = cam.copy()
            pose[:3, 3] = eye_rel
            self._pcamera.matrix = perspective_matrix(window, near, far)
            self._pcamera.znear, self._pcamera.zfar = near, far
            if self.cutouts.any:
                clip_from_rel = self._pcamera.matrix @ np.linalg.inv(pose)
                layer = self._layers.render(clip_from_rel, w, h)
                ids, layer_depth = (a[::-1].reshape(-1) for a in layer)  # row 0 = top
            else:
                self._ctx.pscene.set_pose(self._cam_node, pose)
                self._ctx.make_current()
                flags = RenderFlags.FLAT | RenderFlags.OFFSCREEN | RenderFlags.SKIP_CULL_FACES
                ids = self._ctx.renderer.render(self._ctx.pscene, flags).reshape(-1)
        else:  # no geometry, or none inside the camera's clipping range
            near, far = 0.0, 0.0
            ids = np.zeros(h * w, dtype=np.uint32)

        # Directions: rotate the cached unit camera-space rays (as pixel_rays does; a
        # camera transform with scale or shear needs the normalisation again).
        d = self._world_dirs(camera, rot)
        if not np.allclose(rot.T @ rot, np.eye(3), rtol=0.0, atol=1e-12):
            d /= np.linalg.norm(d, axis=1, keepdims=True)

        covered = np.flatnonzero((ids > 0) & (ids <= len(self._table)))
        tid = ids[covered].astype(np.int64) - 1
        if clip is not None and self.cutouts.any:  # layer ids number static, then animated
            tid = self._layers.batch_triangles(("static", "dynamic"))[tid]

        triangle_id = np.full(h * w, NO_HIT, dtype=np.int32)
        element_id = np.full(h * w, NO_HIT, dtype=np.int32)
        depth = np.full(h * w, np.inf, dtype=np.float32)
        position = np.zeros((h * w, 3), dtype=np.float64)
        view_dir = d.astype(np.float32)
        normal = -view_dir
        albedo = np.zeros((h * w, 3), dtype=np.float32)

        out = _Outputs(triangle_id, element_id, depth, position, normal, albedo)
        fwd = -rot[:, 2] / np.linalg.norm(rot[:, 2])
        if self.cutouts.any:
            out.hole = np.zeros(h * w, dtype=bool)
        derive = (d, eye_rel, near, far, fwd, out)
        self._derive_all(covered, tid, derive)
        if clip is not None and self.cutouts.any:
            self._peel(clip_from_rel, ids, layer_depth, out, derive)

        return GBuffer(
            element_id=element_id.reshape(h, w),
            triangle_id=triangle_id.reshape(h, w),
            depth=depth.reshape(h, w),
            position=position.reshape(h, w, 3),
            normal=normal.reshape(h, w, 3),
            albedo=albedo.reshape(h, w, 3),
            view_dir=view_dir.reshape(h, w, 3),
        )

    def _derive_all(self, covered: np.ndarray, tid: np.ndarray, derive: tuple) -> None:
        """``_derive`` of pixels ``covered`` (n,) with triangles ``tid`` (n,) in chunks
        on the worker threads; ``derive``: the rest of its arguments."""
        chunks = [c for c in np.array_split(np.arange(len(covered)), self._ctx.threads) if len(c)]
        jobs = [self._pool.submit(self._derive, covered[c], tid[c], *derive) for c in chunks]
        for job in jobs:
            job.result()  # re-raises a worker's exception here

    def _peel(self, clip_from_rel, ids, layer_depth, out: _Outputs, derive: tuple) -> None:
        """Cut-out holes (``out.hole``) peeled (module, step 3): pixels showing a hole
        get the next surface behind it, derived again, until none is a hole or
        ``surface.MAX_CUTOUT_LAYERS`` layers were peeled. ids, layer_depth : (H*W,) the
        layer's encoded ids and window depths (row 0 = top), updated in place."""
        h, w = self.height, self.width
        tri_of = np.append(self._layers.batch_triangles(("static", "dynamic")), -1)
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
            _background(out, pending, derive[0])
            found = pending[ids2[pending] > 0]
            ids[found], layer_depth[found] = ids2[found], depth2[found]
            if len(found):
                self._derive_all(found, tri_of[ids[found].astype(np.int64) - 1], derive)
            pending = found[out.hole[found]]
        _background(out, pending, derive[0])  # still in holes after the bound: nothing (module)

    def _derive(
        self,
        covered: np.ndarray,
        tid: np.ndarray,
        d: np.ndarray,
        eye_rel: np.ndarray,
        near: float,
        far: float,
        fwd: np.ndarray,
        out: _Outputs,
    ) -> None:
        """Fill ``out`` at flat pixel indices ``covered`` (n,) from their triangle ids
        ``tid`` (n,): ray-plane hit, barycentrics, interpolated normal and albedo.

        d : (H*W, 3) float64 unit world directions; eye_rel : (3,) rel metres;
        near, far : the projection's clip range; fwd : (3,) unit view direction.
        Runs on chunks of pixels in worker threads (numpy releases the GIL), writing
        disjoint pixels.
        """
        geo = self._scene.geometry
        # np.take: several times faster than fancy indexing for row gathers.
        dc = np.take(d, covered, axis=0)
        tab = np.take(self._table.plane, tid, axis=0)  # (n, 13), see surface.TriangleTable
        ng = tab[:, 8:11]
        # Ray-plane intersection in float64, rel space: t = (h - n·o) / n·d.
        den = np.einsum("ij,ij->i", ng, dc)
        floor = GRAZING_EPS * tab[:, 12]
        den = np.where(np.abs(den) < floor, np.where(den < 0, -floor, floor), den)
        den[den == 0.0] = 1.0  # zero-area triangle: t is clamped just below
        t = np.clip((tab[:, 11] - transform_rows(ng, eye_rel[None])[:, 0]) / den, near, far)
        p_rel = eye_rel + t[:, None] * dc

        # Barycentrics of p, clamped onto the triangle (pixel centres on an edge may
        # lie a rounding error outside) and renormalised; float32 from here on.
        bv = np.einsum("ij,ij->i", p_rel, tab[:, 0:3]) - tab[:, 3]
        bw = np.einsum("ij,ij->i", p_rel, tab[:, 4:7]) - tab[:, 7]
        b0 = np.clip(1.0 - bv - bw, 0.0, 1.0)
        b1 = np.clip(bv, 0.0, 1.0)
        b2 = np.clip(bw, 0.0, 1.0)
        bary = np.stack([b0, b1, b2], axis=1)
        bary /= np.maximum(b0 + b1 + b2, 1e-12)[:, None]
        bary = bary.astype(np.float32)  # (n, 3)

        # (n, 6): interpolated normal then albedo (corners (n, 3, 6), surface.TriangleTable),
        # the normal turned by the side rule (the sign of den = n_g·d decides the side).
        values = surface.interpolate(np.take(self._table.corners, tid, axis=0), bary)
        side = surface.viewer_side(den)
        n = surface.orient_shading_normals(values[:, :3], side, dc, self._table, tid)
        self.normal_maps.apply(n, tid, bary, dc, self._table)
        col = values[:, 3:]
        textured = self._tri_textured[tid]
        if textured.any():
            col[textured] = surface.texture_albedo(
                col[textured],
                tid[textured],
                bary[textured],
                geo.tri_material,
                geo.corner_uv,
                self._scene.materials.textures,
                inputs=self._scene.materials.texture_inputs,
            )
        if out.hole is not None:
            out.hole[covered] = self.cutouts.holes(tid, bary)
        # Sorted pixel indices without gaps (every pixel of an enclosed view is covered):
        # slice writes, much faster than scattering.
        if covered[-1] - covered[0] + 1 == len(covered):
            covered = slice(int(covered[0]), int(covered[-1]) + 1)
        out.normal[covered] = n
        out.albedo[covered] = col
        out.triangle_id[covered] = tid
        out.element_id[covered] = np.take(geo.tri_element, tid)
        out.position[covered] = p_rel + self._origin
        out.depth[covered] = t * transform_rows(dc, fwd[None])[:, 0]


def _background(out: _Outputs, pixels: np.ndarray, dirs: np.ndarray) -> None:
    """Reset ``pixels`` (k,) of ``out`` to the background (``GBufferPass.render``);
    dirs : (H*W, 3) the pixels' unit world directions."""
    out.normal[pixels] = -np.take(dirs, pixels, axis=0)
    out.triangle_id[pixels] = NO_HIT
    out.element_id[pixels] = NO_HIT
    out.depth[pixels] = np.inf
    out.position[pixels] = 0.0
    out.albedo[pixels] = 0.0
    out.hole[pixels] = False
