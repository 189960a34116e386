"""What every raster pass shares: the OpenGL context, pyrender's renderer with our program
cache, the id framebuffer, the uploaded geometry and what moved when it changes.

The context is made on the platform OpenGL was loaded with (``gl_platform.activate``
chose it: EGL or OSMesa) and its worker pool has the process's thread setting
(``phrt_usd.threads``); llvmpipe's own render threads were fixed by ``LP_NUM_THREADS``
when the process's first context was created.

Upload (``RasterContext.upload``, ``update_geometry``). All triangles go into ONE
pyrender node (one mesh, one indexed primitive): pyrender costs several ms per node on
llvmpipe. Vertices are origin-relative (``Scene.origin`` subtracted in float64, then
cast to float32) so a stage 1e6 m from the world origin rasterizes as precisely as one
at the origin. The static and the animated triangles (``Element.animated``) are also
drawable on their own (``batch``) from the same vertex buffer, for the shadow maps.
What changed is never found by comparing arrays: the scene's versions
(``Scene.versions``) say which elements changed since the version uploaded, and only
their vertices are re-sent; ``batch_versions`` count the changes of each batch for the
shadow maps' cache.

pyrender's 4x multisampled framebuffer would blend ids at triangle edges, so the
renderer instance gets our single-sampled id framebuffer (RGBA8 + 32-bit float depth)
instead, and reads back the id image only (``read_ids``).

Coordinate spaces: "world" is ``Scene`` world metres (float64); "rel" is world minus
``Scene.origin`` (what OpenGL sees, float32 on the GPU, float64 in numpy).

Limits: one OpenGL context per ``RasterContext``; triangle count below 2**32 - 1 (the id
encoding). Element ``animated`` flags are read when the topology is uploaded.
"""

from __future__ import annotations

import ctypes
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pyrender
from OpenGL import GL
from pyrender.constants import RenderFlags
from pyrender.shader_program import ShaderProgramCache

from phrt_usd.engine.raster.gl_platform import loaded_platform, make_platform
from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import ElementTriangles, Scene
from phrt_usd.threads import current_threads

#: Directory of our GLSL files (``flat.*``: id pass, ``depth.*``: shadow-map pass,
#: ``cube_lookup.*``: the light pass).
SHADER_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shaders")

#: Clip ranges tightened to the scene's bounds (nothing exists outside them) are padded
#: by this fraction of the scene extent so that bounding geometry is not clipped.
CLIP_PADDING = 1e-3


class _ProgramCache(ShaderProgramCache):
    """pyrender's program cache over our shader directory, keyed by shader names and
    defines only. pyrender keys by the current context too, but under OSMesa every
    ``getContext()`` returns a new pointer object that never compares equal, so its
    cache misses on every call and recompiles (and leaks) the program each frame. Each
    ``RasterContext`` owns its context and its cache, so the context is not needed here."""

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        defines = defines or {}
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted(defines.items())))
        if key not in self._program_cache:
            self._program_cache[key] = super().get_program(
                vertex_shader, fragment_shader, geometry_shader, defines
            )
        return self._program_cache[key]


def transform_rows(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(n, k) = v (n, 3) times m (k, 3) transposed, i.e. each row of v mapped by m.

    An einsum instead of ``v @ m.T``: numpy hands such skinny products to the
    multithreaded BLAS, which on this 2-core machine, next to llvmpipe's render threads,
    was seen to take up to 12 ms for 76 800 rows (einsum's own loop: ~1 ms)."""
    return np.einsum("ij,kj->ik", v, m)


def vertices_of(triangles: np.ndarray, rows: np.ndarray, n_vertices: int) -> np.ndarray:
    """Increasing indices (k,) int64 of the vertices that the ``triangles`` (T, 3) picked
    by ``rows`` (a (T,) bool mask or indices) use: ``np.unique`` of their corners as a
    scatter into a flag per vertex, O(T + V) instead of a sort (the chess set's 4.3 M
    corners: 0.5-0.75 s sorted)."""
    used = np.zeros(n_vertices, dtype=bool)
    used[triangles[rows]] = True
    return np.flatnonzero(used)


def check_framebuffer(name: str) -> None:
    """Raise when the bound framebuffer (called ``name`` in the message) is incomplete."""
    status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
    if status != GL.GL_FRAMEBUFFER_COMPLETE:
        raise RuntimeError(f"OpenGL {name} framebuffer incomplete (status {status:#x})")


def id_framebuffer(width: int, height: int, name: str):
    """A single-sampled framebuffer of ``width`` x ``height`` with an RGBA8 colour (the
    ids) and a float depth renderbuffer, checked (``name`` in the message), unbound
    again. Returns (renderbuffers (2,), framebuffer) for the caller to delete."""
    rb = GL.glGenRenderbuffers(2)
    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb[0])
    GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, width, height)
    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb[1])
    GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, width, height)
    fb = GL.glGenFramebuffers(1)
    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
    GL.glFramebufferRenderbuffer(
        GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, rb[0]
    )
    GL.glFramebufferRenderbuffer(
        GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, rb[1]
    )
    check_framebuffer(name)
    GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
    GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)
    return rb, fb


@dataclass
class GeometryChange:
    """What ``RasterContext.update_geometry`` changed.

    rebuilt    : everything was uploaded anew (another scene, topology or origin, or a
                 changed element's winding flipped)
    elements   : (k,) int64 ascending, the elements whose vertices were re-sent (every
                 element when rebuilt)
    moved_rows : (m,) int64 ascending, their triangles (all when rebuilt)
    vertices   : how many vertices were sent to the GPU (all when rebuilt)
    """

    rebuilt: bool
    elements: np.ndarray
    moved_rows: np.ndarray
    vertices: int


#: ``GeometryChange.elements`` / ``moved_rows`` of an update that changed nothing.
_NOTHING = np.zeros(0, dtype=np.int64)


class RasterContext:
    """One OpenGL context and what the raster passes share in it (see the module).

    Attributes the passes read (rel space, see the module):
    scene, origin (3,) float64; width, height; renderer (pyrender, id framebuffer),
    pscene (pyrender scene, one mesh node), mesh_node (None without triangles);
    uploaded (V, 3) float32 vertices as on the GPU; triangles (T, 3) int64;
    animated_tri (T,) bool; geometry_version: the ``Scene.versions.geometry`` uploaded;
    batch_versions: per batch ("static", "dynamic") a counter bumped whenever its
    triangles' vertices change (what the shadow maps cache on); upload_version: a
    counter bumped by every ``upload`` (the scene, its lights or the origin of rel space
    may be others); bounds_rel (2, 3)
    float64 and extent (metres, > 0) of all vertices; threads and pool: the workers
    deriving the G-buffer from the id image and looking points up in the shadow maps
    (numpy releases the GIL in its loops, so the pixels / points are split into
    ``threads`` chunks; ``phrt_usd.threads``); gl: the platform the context runs on
    (``egl`` / ``osmesa``).
    """

    def __init__(self, scene: Scene, width: int, height: int) -> None:
        self.width = int(width)
        self.height = int(height)
        self.scene = scene
        self.origin = np.asarray(scene.origin, dtype=np.float64).copy()
        self.gl = loaded_platform() or "osmesa"
        self._platform = make_platform(self.gl, self.width, self.height)
        self._platform.init_context()
        self._platform.make_current()
        self.renderer = pyrender.Renderer(self.width, self.height)
        #: The OpenGL implementation's name (``GL_RENDERER``, e.g. "llvmpipe (LLVM 19.1.7,
        #: 256 bits)" for Mesa's software rasterizer).
        self.gl_renderer = GL.glGetString(GL.GL_RENDERER).decode("utf-8", "replace")
        self.renderer._program_cache = _ProgramCache(shader_dir=SHADER_DIR)
        self._create_id_framebuffer()
        # Our single-sampled framebuffer replaces pyrender's multisampled one.
        self.renderer._configure_main_framebuffer = lambda: None
        self.renderer._read_main_framebuffer = lambda _scene, _flags: self.read_ids()
        self._ids = np.zeros((self.height, self.width, 4), dtype=np.uint8)  # readback
        self.pscene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0])
        self.mesh_node = None
        self.uploaded: np.ndarray | None = None  # (V, 3) float32 rel, as on the GPU
        self._batches: dict[str, tuple[int, int, int]] = {}  # name → (vao, ebo, count)
        self.geometry_version = 0
        self.batch_versions = {"static": 0, "dynamic": 0}
        self.upload_version = 0
        self.threads = current_threads()
        self.pool = ThreadPoolExecutor(self.threads, thread_name_prefix="phrt-gbuffer")

    def make_current(self) -> None:
        self._platform.make_current()

    def program(self, vertex_shader: str, fragment_shader: str):
        """pyrender shader program of two files in SHADER_DIR (cached)."""
        return self.renderer._program_cache.get_program(vertex_shader, fragment_shader)

    # ------------------------------------------------------------------ geometry upload

    def upload(self, scene: Scene) -> None:
        """Build the single mesh node (rel space) and the static / animated split, at
        ``scene``'s current version; both batches count as changed."""
        geo = scene.geometry
        if geo.triangle_count >= 2**32 - 1:
            raise PhrtError(f"{geo.triangle_count} triangles exceed the id encoding")
        self.origin = np.asarray(scene.origin, dtype=np.float64).copy()
        rel = geo.vertices - self.origin
        self.uploaded = np.ascontiguousarray(rel, dtype=np.float32)
        self.triangles = np.array(geo.triangles, dtype=np.int64)
        self._element_triangles = ElementTriangles(geo.tri_element, len(scene.elements))
        self.geometry_version = scene.versions.geometry
        self.upload_version += 1
        for name in self.batch_versions:
            self.batch_versions[name] += 1
        self.delete_batches()
        if self.mesh_node is not None:
            self.pscene.remove_node(self.mesh_node)
            self.mesh_node = None
        if geo.triangle_count > 0:
            material = pyrender.MetallicRoughnessMaterial(doubleSided=True)
            prim = pyrender.Primitive(
                positions=self.uploaded,
                indices=np.ascontiguousarray(geo.triangles, dtype=np.uint32),
                material=material,
            )
            self.mesh_node = self.pscene.add(pyrender.Mesh([prim]))
            self._primitive = prim
        self._scene_changed(scene)

    def _scene_changed(self, scene: Scene) -> None:
        """Refresh what depends on the whole scene: bounds and the static / animated
        triangle split used by the shadow maps.

        animated_tri : (T,) bool, triangles of ``Element.animated`` elements.
        """
        geo = scene.geometry
        flags = np.array([e.animated for e in scene.elements] + [False], dtype=bool)
        #: (E,) bool, ``Element.animated`` when uploaded.
        self.animated_element = flags[:-1]
        el = np.where(
            (geo.tri_element >= 0) & (geo.tri_element < len(scene.elements)),
            geo.tri_element,
            len(scene.elements),
        )
        self.animated_tri = flags[el]
        rel = self.uploaded
        #: Increasing vertex indices of the static and the animated triangles
        #: (``vertices_of``), what the bounds and the shadow maps' footprints read.
        self.static_vertices = vertices_of(self.triangles, ~self.animated_tri, len(rel))
        self.animated_vertices = vertices_of(self.triangles, self.animated_tri, len(rel))
        if len(self.static_vertices):
            sv = rel[self.static_vertices]
            self._static_bounds = np.stack([sv.min(axis=0), sv.max(axis=0)]).astype(np.float64)
        else:
            self._static_bounds = None
        self._update_bounds()
        self.scene = scene

    def _update_bounds(self) -> None:
        """bounds_rel (2, 3) float64: rel bounds of all triangle vertices (static part
        cached, animated part recomputed); extent: their diagonal in metres (> 0)."""
        boxes = [] if self._static_bounds is None else [self._static_bounds]
        if len(self.animated_vertices):
            av = self.uploaded[self.animated_vertices]
            boxes.append(np.stack([av.min(axis=0), av.max(axis=0)]).astype(np.float64))
        if boxes:
            lo = np.min([b[0] for b in boxes], axis=0)
            hi = np.max([b[1] for b in boxes], axis=0)
        else:
            lo = hi = np.zeros(3)
        self.bounds_rel = np.stack([lo, hi])
        self.extent = float(max(np.linalg.norm(hi - lo), 1e-12))

    def update_geometry(self, scene: Scene) -> GeometryChange:
        """Bring the uploaded geometry to ``scene``'s current version.

        Versions are compared, never arrays (``Scene.versions``): the version uploaded
        → nothing to do; the same scene, elements changed since → only their vertices
        are re-sent (``glBufferSubData``, one call per contiguous run of vertex
        indices) and the batches they belong to counted as changed
        (``batch_versions``). Another ``Scene`` object, vertex or triangle count or
        origin, or a changed element whose winding flipped (a transform's determinant
        changed sign): the node is rebuilt (``upload``).
        """
        self.make_current()
        geo = scene.geometry
        same_scene = (
            scene is self.scene
            and self.uploaded is not None
            and geo.vertices.shape == self.uploaded.shape
            and geo.triangle_count == len(self.triangles)
            and np.array_equal(np.asarray(scene.origin, dtype=np.float64), self.origin)
        )
        if same_scene and scene.versions.geometry == self.geometry_version:
            return GeometryChange(False, _NOTHING, _NOTHING, 0)
        elements = scene.versions.changed_since(self.geometry_version)
        rows = self._element_triangles.rows(elements) if same_scene else _NOTHING
        if not same_scene or not np.array_equal(geo.triangles[rows], self.triangles[rows]):
            self.upload(scene)
            every = np.arange(len(scene.elements), dtype=np.int64)
            return GeometryChange(
                True, every, np.arange(len(self.triangles)), len(self.uploaded)
            )
        vertices = vertices_of(self.triangles, rows, len(self.uploaded))
        self.uploaded[vertices] = geo.vertices[vertices] - self.origin
        self._send_vertices(vertices)
        self.geometry_version = scene.versions.geometry
        animated = self.animated_element[elements]
        if animated.any():
            self.batch_versions["dynamic"] += 1
        if not animated.all():
            # Static casters moved (the caller animated a prim not flagged so): their
            # cached bounds too.
            self.batch_versions["static"] += 1
            self._static_bounds_stale()
        self._update_bounds()
        return GeometryChange(False, elements, rows, len(vertices))

    def _send_vertices(self, vertices: np.ndarray) -> None:
        """Re-send ``uploaded``'s rows ``vertices`` (k,) int64 ascending to the GPU's
        vertex buffer, one ``glBufferSubData`` per contiguous run."""
        if self.mesh_node is None or not len(vertices):
            return
        self._primitive.positions = self.uploaded  # pyrender's copy (the same array)
        if self._primitive._vaid is None:  # not on the GPU yet: sent whole when it is
            return
        breaks = np.flatnonzero(np.diff(vertices) > 1) + 1
        firsts = vertices[np.concatenate([[0], breaks])]
        lasts = vertices[np.concatenate([breaks - 1, [len(vertices) - 1]])] + 1
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
        for first, last in zip(firsts.tolist(), lasts.tolist(), strict=True):
            chunk = self.uploaded[first:last]
            GL.glBufferSubData(GL.GL_ARRAY_BUFFER, first * 12, chunk.nbytes, chunk)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def _static_bounds_stale(self) -> None:
        """A non-animated vertex moved: recompute the cached static bounds."""
        sv = self.uploaded[self.static_vertices]
        self._static_bounds = np.stack([sv.min(axis=0), sv.max(axis=0)]).astype(np.float64)

    def batch(self, name: str) -> tuple[int, int, int]:
        """(vao, ebo, index count) drawing the static (``name == "static"``) or animated
        (``"dynamic"``) triangles from the mesh's own vertex buffer.

        pyrender's VAO draws every triangle; these VAOs share its vertex buffer (so
        ``update_geometry`` uploads reach them) with their own index buffers."""
        if name not in self._batches:
            r = self.renderer
            r._update_context(self.pscene, RenderFlags.FLAT)  # vertex buffer on the GPU
            mask = self.animated_tri if name == "dynamic" else ~self.animated_tri
            idx = np.ascontiguousarray(self.triangles[mask], dtype=np.uint32)
            vao = GL.glGenVertexArrays(1)
            GL.glBindVertexArray(vao)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
            GL.glEnableVertexAttribArray(0)
            GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 12, ctypes.c_void_p(0))
            ebo = GL.glGenBuffers(1)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
            if idx.size:
                GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, GL.GL_STATIC_DRAW)
            GL.glBindVertexArray(0)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
            self._batches[name] = (int(vao), int(ebo), int(idx.size))
        return self._batches[name]

    def delete_batches(self) -> None:
        if self._batches:
            self._platform.make_current()
            for vao, ebo, _ in self._batches.values():
                GL.glDeleteVertexArrays(1, [vao])
                GL.glDeleteBuffers(1, [ebo])
        self._batches = {}

    # ------------------------------------------------------------------ id framebuffer

    def _create_id_framebuffer(self) -> None:
        """Single-sampled id framebuffer (RGBA8 + float depth) at the image size."""
        self._id_rb, self._id_fb = id_framebuffer(self.width, self.height, "id")
        r = self.renderer
        r._main_fb = r._main_fb_ms = self._id_fb
        r._main_fb_dims = (self.width, self.height)

    def read_ids(self) -> np.ndarray:
        """(H, W) uint32 id image (triangle index + 1, 0 = background), row 0 at top."""
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._id_fb)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glReadPixels(0, 0, self.width, self.height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, self._ids)
        # Four bytes R, G, B, A read as one little-endian uint32 = R + 256 G + ...
        ids = self._ids.view("<u4")[..., 0]
        return ids[::-1].astype(np.uint32)

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        """Stop the workers, free the shared OpenGL objects and the context (the passes
        free their own objects first)."""
        self.pool.shutdown(wait=True)
        self._platform.make_current()
        self.delete_batches()
        r = self.renderer
        r._main_fb = r._main_fb_ms = None
        r._main_cb = r._main_cb_ms = r._main_db = r._main_db_ms = None
        r.delete()
        GL.glDeleteFramebuffers(1, [self._id_fb])
        GL.glDeleteRenderbuffers(2, list(self._id_rb))
        self._platform.delete_context()
