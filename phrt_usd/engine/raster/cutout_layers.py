"""Cut-out id layers: depth peeling of an id render through cut-out holes.

UsdPreviewSurface ``opacityThreshold`` cut-outs (``model.surface.Cutouts``) decide per
point whether a surface is there; that rule is numpy (one implementation for raster and
trace). The GPU's part is only to find, per pixel, the *next* surface behind the one a
layer showed: ``IdLayers.render`` draws the triangles with ``shaders/peel.*`` (the id
pass's encoding, ``flat.frag``) and, given the layer before, keeps only fragments after
it in (window depth, id) order. The caller decides on the CPU which pixels of a layer
are holes and peels those again, at most ``surface.MAX_CUTOUT_LAYERS`` times.

Used by the G-buffer (``gbuffer.GBufferPass``: camera pixels) and the shadow maps
(``shadow_maps``: ``first_present_depth`` of map texels). Scenes without cut-outs never
come here.

Ids: a draw of batches ("static", "dynamic") numbers their triangles one after another
(``id_base``); ``global_ids`` maps an encoded id (triangle number + 1, 0 = nothing)
back to the scene's triangle index. Images are in OpenGL row order (row 0 = bottom).
Coordinate spaces as in ``context``: "rel" is world minus ``Scene.origin``.
"""

from __future__ import annotations

import ctypes

import numpy as np
from OpenGL import GL

from phrt_usd.engine.raster.context import RasterContext, id_framebuffer
from phrt_usd.model import surface

#: Texture unit of the previous layer's (id, depth) image in ``peel.frag`` (the last of
#: the 16 units OpenGL 3.3 guarantees; no other pass of ours binds it).
PREVIOUS_UNIT = 15


class IdLayers:
    """An id framebuffer of up to ``width`` x ``height`` pixels (RGBA8 + 32-bit float
    depth) and the previous-layer texture, in ``ctx``'s OpenGL context."""

    def __init__(self, ctx: RasterContext, width: int, height: int) -> None:
        self._ctx = ctx
        self.width, self.height = int(width), int(height)
        ctx.make_current()
        self._rb, self._fb = id_framebuffer(self.width, self.height, "cut-out id")
        self._previous = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._previous)
        for name in (GL.GL_TEXTURE_MIN_FILTER, GL.GL_TEXTURE_MAG_FILTER):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, name, GL.GL_NEAREST)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def close(self) -> None:
        self._ctx.make_current()
        GL.glDeleteFramebuffers(1, [self._fb])
        GL.glDeleteRenderbuffers(2, list(self._rb))
        GL.glDeleteTextures([self._previous])

    def batch_triangles(self, batches: tuple[str, ...]) -> np.ndarray:
        """(k,) int64 scene triangle index of every id a draw of ``batches`` gives, in
        id order (static: the non-animated triangles, dynamic: the animated ones)."""
        animated = self._ctx.animated_tri
        parts = [np.flatnonzero(animated if b == "dynamic" else ~animated) for b in batches]
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)

    def render(
        self,
        clip_from_rel: np.ndarray,
        width: int,
        height: int,
        batches: tuple[str, ...] = ("static", "dynamic"),
        previous: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One layer: (height, width) uint32 encoded ids (0 = nothing) and float32
        window depths (1 where nothing), OpenGL row order, of ``batches`` seen through
        ``clip_from_rel`` (4, 4). ``previous``: the layer before as (ids, depths) of the
        same shape; pixels with id 0 there are not peeled (read 0 / 1)."""
        ctx = self._ctx
        ctx.make_current()
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fb)
        GL.glViewport(0, 0, width, height)
        GL.glScissor(0, 0, width, height)
        GL.glEnable(GL.GL_SCISSOR_TEST)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthRange(0.0, 1.0)
        GL.glDisable(GL.GL_CULL_FACE)  # double-sided, as the id pass and shadow maps
        GL.glDisable(GL.GL_BLEND)
        GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClearDepth(1.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        program = ctx.program("peel.vert", "peel.frag")
        if not program._in_context():
            program._add_to_context()
        program._bind()
        program.set_uniform("clip_from_rel", clip_from_rel)
        program.set_uniform("peeling", 0 if previous is None else 1)
        if previous is not None:
            ids, depth = previous
            data = np.ascontiguousarray(
                np.stack([ids.astype(np.uint32), depth.astype(np.float32).view(np.uint32)], -1)
            )
            GL.glActiveTexture(GL.GL_TEXTURE0 + PREVIOUS_UNIT)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._previous)
            GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
            GL.glTexImage2D(
                GL.GL_TEXTURE_2D, 0, GL.GL_RG32UI, width, height, 0,
                GL.GL_RG_INTEGER, GL.GL_UNSIGNED_INT, data,
            )  # fmt: skip
            program.set_uniform("previous", PREVIOUS_UNIT)
        base = 0
        for name in batches:
            vao, _, count = ctx.batch(name)
            program.set_uniform("id_base", base)
            if count:
                GL.glBindVertexArray(vao)
                GL.glDrawElements(GL.GL_TRIANGLES, count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))
                GL.glBindVertexArray(0)
            base += count // 3
        program._unbind()
        if previous is not None:
            GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
            GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        rgba = np.zeros((height, width, 4), np.uint8)
        GL.glReadPixels(0, 0, width, height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, rgba)
        depth01 = np.ones((height, width), np.float32)
        GL.glReadPixels(0, 0, width, height, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT, depth01)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return rgba.view("<u4")[..., 0].copy(), depth01

    def first_present_depth(
        self,
        clip_from_rel: np.ndarray,
        size: int,
        batch: str,
        plane: np.ndarray,
        cutouts: surface.Cutouts,
    ) -> np.ndarray:
        """(size, size) float32 window depth (1 = nothing) of the nearest caster that
        is there (not a cut-out hole) per texel of a square depth render of ``batch``
        through ``clip_from_rel``: shadow maps of scenes with cut-outs. A texel's ray is
        its centre unprojected (near to far plane); ``plane``: the scene's
        ``TriangleTable.plane`` (T, 13); holes by ``cutouts``, peeled at most
        ``surface.MAX_CUTOUT_LAYERS`` times (then: no caster)."""
        ids, depth = self.render(clip_from_rel, size, size, (batch,))
        ids, depth = ids.reshape(-1), depth.reshape(-1)
        tri_of = np.append(self.batch_triangles((batch,)), -1)
        out = np.where(ids > 0, depth, np.float32(1.0)).astype(np.float32)
        inverse = np.linalg.inv(clip_from_rel)
        pending = np.flatnonzero(ids > 0)
        for layer in range(surface.MAX_CUTOUT_LAYERS + 1):
            tri = tri_of[ids[pending].astype(np.int64) - 1]
            pending = pending[cutouts.tri_cutout[tri]]
            if len(pending) == 0:
                break
            tri = tri_of[ids[pending].astype(np.int64) - 1]
            origins, dirs = _texel_rays(inverse, pending, size)
            holes = cutouts.holes(tri, surface.ray_plane_weights(plane[tri], origins, dirs))
            pending = pending[holes]
            if len(pending) == 0:
                break
            if layer == surface.MAX_CUTOUT_LAYERS:
                out[pending] = 1.0  # still in holes after the bound: no caster
                break
            prev_ids = np.zeros(size * size, np.uint32)
            prev_depth = np.ones(size * size, np.float32)
            prev_ids[pending] = ids[pending]
            prev_depth[pending] = depth[pending]
            shape = (size, size)
            ids2, depth2 = self.render(
                clip_from_rel,
                size,
                size,
                (batch,),
                (prev_ids.reshape(shape), prev_depth.reshape(shape)),
            )
            ids2, depth2 = ids2.reshape(-1), depth2.reshape(-1)
            ids[pending], depth[pending] = ids2[pending], depth2[pending]
            out[pending] = np.where(ids2[pending] > 0, depth2[pending], np.float32(1.0))
            pending = pending[ids2[pending] > 0]
        return out.reshape(size, size)


def _texel_rays(inverse: np.ndarray, texels: np.ndarray, size: int):
    """Rel origins (m, 3) on the near plane and unit directions (m, 3) through the
    centres of ``texels`` (m,) (flat, OpenGL row order) of a ``size``² render whose
    clip_from_rel inverse is ``inverse`` (4, 4)."""
    x = (texels % size + 0.5) * (2.0 / size) - 1.0
    y = (texels // size + 0.5) * (2.0 / size) - 1.0
    # inverse @ (x, y, z, 1) per texel, as sums of columns (no (m, 4) operand).
    xy = x[:, None] * inverse[:, 0] + y[:, None] * inverse[:, 1]
    ends = []
    for z in (-1.0, 1.0):
        p = xy + (z * inverse[:, 2] + inverse[:, 3])
        ends.append(p[:, :3] / p[:, 3:4])
    d = ends[1] - ends[0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return ends[0], d
