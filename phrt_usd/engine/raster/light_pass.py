"""The GPU lookup pass (``shaders/cube_lookup.frag``): every query point against every
light's shadow maps in one fragment per point, and the shading of the (point, light)
pairs the maps decide are lit.

Inputs are textures: the points, their normals and directions to the eye (RGB32F, as
many points a row as the frame has pixels, ``LightPass.row_width``), the LocalLights'
cube maps (``shadow_maps.CubeMap`` (min, max) texels in one RG32F buffer texture) and
up to LOOKUP_MAX_DISTANT DistantLights' orthographic maps (``shadow_maps.ShadowMap``,
RG32F each); a pass handles LOOKUP_LIGHTS_PER_PASS LocalLights, the same for every
point, or, with shading past that many lights, each tile of points its own
(LOOKUP_TILE: the lights whose range reaches the tile; docs/light-reach.md). Outputs
(``LightPass.lookup``): either a code per (point, LocalLight) pair (LOOKUP_LIT /
LOOKUP_SHADOWED / LOOKUP_UNCERTAIN), or the direct light of the lit pairs (each
point's UsdPreviewSurface BRDF, its surface rows a texture of four RGBA32F texels a
point, ``model/preview_surface.py``; the lobe's albedo table an RG32F texture) with
bits flagging the uncertain ones, which the caller resolves (``map_lighting``). The
test is ``shadow_maps.cube_visibility``'s and ``shadow_maps.filtered_visibility``'s,
the shading ``shade_kernels.shade_kernel``'s and ``brdf_cos``'s, a Rect or Disk light's
area factor ``trace.area_light_kernels._factor``'s: keep the shader and those in step
(``tests/engine/test_preview_surface.py`` compares the BRDFs,
``tests/engine/test_area_light_shading.py`` the area factors).

Measured on the sewer (13 lights, 640x480): the lookup takes ~45 ms of CPU time per
frame (llvmpipe spreads it over the cores), nearly all of it the fragment shader
(llvmpipe runs every branch under masks; the shading pass walks only the lights a
fragment group can see and then those that light it, as bit-mask loops, which end
when no lane goes on; the cube texel fetches, mostly cache misses, ~1/4); packing,
uploads and readback ~4 ms.

Coordinate spaces as in ``context``: "rel" is world minus ``Scene.origin``, metres.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from OpenGL import GL
from OpenGL.GL import shaders as gl_shaders

from phrt_usd import kernels
from phrt_usd.engine.raster.context import SHADER_DIR, RasterContext, check_framebuffer
from phrt_usd.engine.raster.shadow_maps import (
    CUBE_GUARD_TEXELS,
    CUBE_MAP_SIZE,
    SHADOW_BIAS_TEXELS,
    SHADOW_MIN_COS,
    SHADOW_REFINE_RADIUS,
    SHADOW_SLOPE_BIAS_TEXELS,
    CubeMap,
    ShadowMap,
    ShadowMaps,
)
from phrt_usd.engine.shading import MIN_LIGHT_DISTANCE, area_table
from phrt_usd.engine.terminator import Terminator
from phrt_usd.model import preview_surface
from phrt_usd.model.light_sampling import has_area_lights
from phrt_usd.model.scene import Lights
from phrt_usd.model.surface import TERMINATOR_FADE

#: Most rows of the GPU lookup pass's point texture (llvmpipe's largest renderbuffer
#: side); more points than the frame's width times this make the rows wider.
LOOKUP_MAX_ROWS = 16384
#: LocalLights per GPU lookup pass (one RGBA32UI colour attachment, one byte each):
#: with shading, the slots of each tile's list a pass walks.
LOOKUP_LIGHTS_PER_PASS = 16
#: Most consecutive points of a tile of the shading pass (G-buffer pixels in image
#: order: a run of a row; the tracer's hits in path order). Each tile walks only the
#: LocalLights whose range reaches the bounding box of its points
#: (``shade_kernels.tile_lights``), as a tiled deferred renderer does: a fragment's cost
#: grows with the lights near it, not with the stage's, and the passes a frame needs
#: with the most lights one tile has. Runs rather than squares: the G-buffer's points
#: leave uncovered pixels out, so the point texture's rows do not stay aligned with the
#: image's. 64: on the light-grid bench at 640x480 a run spans 8.5 m of floor and
#: reaches ~6 of its 64 lights.
LOOKUP_TILE = 64
#: A tile also ends where the next point is more than this many times its longest step
#: away (``tile_lights``): the end of an image row (the next starts at the other side),
#: an edge in depth; its box then stays near its points.
LOOKUP_TILE_JUMP = 4.0
#: Tiles a row of the slot texture (``_upload_slots``).
SLOT_TILES_A_ROW = 256
#: Metres added to a light's range when choosing a tile's lights (``tile_lights``): the
#: shader's own reach test runs in float32 rel metres (rounding under 0.1 mm within
#: 1 km of ``Scene.origin``), so the lists hold every light the shader could find in
#: reach; a light kept by the margin alone adds exactly 0 (its window is 0 there).
LOOKUP_CULL_MARGIN = 1e-3
#: DistantLights the GPU lookup pass shades itself (more are looked up in numpy).
LOOKUP_MAX_DISTANT = 2
#: Bytes of one cube texel on the GPU: (min, max) float32 (RG32F).
CUBE_TEXEL_BYTES = 8
_ORIGIN = np.zeros(3)


class PointTiles(NamedTuple):
    """The shading pass's tiles (``shade_kernels.tile_lights``): slots (T, S) int64, the
    LocalLights each tile walked (increasing, then -1); point_tile (n,) int32, each
    point's tile."""

    slots: np.ndarray
    point_tile: np.ndarray
#: Per-light codes the GPU lookup packs one byte each (``shaders/cube_lookup.frag``).
LOOKUP_SHADOWED, LOOKUP_LIT, LOOKUP_UNCERTAIN = 0, 1, 2


class LightPass:
    """The lookup pass's OpenGL objects in a ``RasterContext`` (programs, textures,
    output framebuffer), created when first used, and the pass itself (``lookup``)."""

    def __init__(self, ctx: RasterContext, maps: ShadowMaps) -> None:
        self._ctx = ctx
        self._maps = maps  # whose ``cube_keys`` place the LocalLights
        self._lookup_programs: dict[tuple[int, int, bool, bool, bool, bool, bool, bool], int] = {}
        self._dmap_tex: list[int] = []  # DistantLight map textures (``_upload_distant``)
        self._dmap_held: list[ShadowMap | None] = []
        self._lookup_vao: int | None = None
        self._cube_tex: int | None = None  # buffer texture of ``_cube_buf``
        self._cube_buf: int | None = None
        self._cube_tex_layers = 0
        self._cube_tex_held: list[CubeMap | None] = []
        self._point_tex: list[int] = []
        self._surface_tex: int | None = None  # the points' surface rows (RGBA32F)
        self._lut_tex: int | None = None  # preview_surface.specular_albedo_table (RG32F)
        self._slot_tex: int | None = None  # the tiles' light slots of a pass (R32I)
        self._tile_tex: int | None = None  # each point's tile (R32I)
        self._light_buf: int | None = None  # the LocalLights' table (``_upload_lights``)
        self._light_tex: int | None = None
        self._lookup_fb: int | None = None
        self._lookup_rb: list[int] = []
        self._lookup_size = (0, 0)  # (width, rows) of ``_lookup_fb``

    def _program_for(
        self, n_lights: int, n_distant: int, shade: bool, tiled: bool, coat: bool,
        terminator: bool,
    ) -> int:  # fmt: skip
        """The lookup program for a pass of ``n_lights`` LocalLight slots and
        ``n_distant`` DistantLights (with shading or not; per tile or not; with the
        clear coat's lobe, the area lights' factor or not; with points on smooth meshes or
        not), compiled on first use with the defines ``shaders/cube_lookup.frag`` expects."""
        has_dynamic = bool(self._ctx.animated_tri.any())
        area = shade and has_area_lights(self._ctx.scene.lights)
        key = (n_lights, n_distant, has_dynamic, shade, tiled, coat, area, terminator)
        if key not in self._lookup_programs:
            with open(os.path.join(SHADER_DIR, "cube_lookup.vert")) as f:
                vert = f.read()
            with open(os.path.join(SHADER_DIR, "cube_lookup.frag")) as f:
                version, frag = f.read().split("\n", 1)
            tan_half = CUBE_MAP_SIZE / (CUBE_MAP_SIZE - 2.0 * CUBE_GUARD_TEXELS)
            lut_rows, lut_columns = preview_surface.specular_albedo_table().shape[:2]
            defines = (
                f"#define N_LIGHTS {n_lights}\n#define N_DISTANT {n_distant}\n"
                f"#define N_SLOTS {LOOKUP_LIGHTS_PER_PASS}\n#define SLOT_TILES {SLOT_TILES_A_ROW}\n"
                f"#define HAS_DYNAMIC {int(has_dynamic)}\n"
                f"#define SHADE {int(shade)}\n#define TILED {int(tiled)}\n"
                f"#define COAT {int(coat)}\n#define LUT_ROWS {lut_rows}\n"
                f"#define TERMINATOR {int(terminator)}\n"
                f"#define TERMINATOR_FADE {TERMINATOR_FADE!r}\n"
                f"#define LUT_COSINES {lut_columns - 1}\n"
                f"#define CUBE_SIZE {CUBE_MAP_SIZE}\n#define TAN_HALF {tan_half!r}\n"
                f"#define LINE_W {CUBE_LINE_TILE[0]}u\n#define LINE_H {CUBE_LINE_TILE[1]}u\n"
                f"#define PAGE_W {CUBE_PAGE_TILE[0]}u\n#define PAGE_H {CUBE_PAGE_TILE[1]}u\n"
            ) + _area_defines(area)
            self._lookup_programs[key] = int(
                gl_shaders.compileProgram(
                    gl_shaders.compileShader(vert, GL.GL_VERTEX_SHADER),
                    gl_shaders.compileShader(f"{version}\n{defines}{frag}", GL.GL_FRAGMENT_SHADER),
                    validate=False,
                )
            )
        return self._lookup_programs[key]

    def _setup(self) -> None:
        """Create the lookup pass's empty VAO and point textures."""
        if self._lookup_vao is not None:
            return
        self._lookup_vao = int(GL.glGenVertexArrays(1))
        # points, normals, to_eye, surface rows, the albedo table, the tiles' slots, the
        # points' tiles, their terminator normals and lifts
        textures = [int(t) for t in GL.glGenTextures(9)]
        for tex in textures:
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        self._point_tex = textures[:3] + textures[7:]
        self._surface_tex, self._lut_tex, self._slot_tex = textures[3], textures[4], textures[5]
        self._tile_tex = textures[6]
        self._light_buf = int(GL.glGenBuffers(1))
        self._light_tex = int(GL.glGenTextures(1))
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self._light_buf)
        GL.glBufferData(GL.GL_TEXTURE_BUFFER, 48, None, GL.GL_DYNAMIC_DRAW)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self._light_tex)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_RGBA32F, self._light_buf)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, 0)
        lut = preview_surface.specular_albedo_table()
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._lut_tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RG32F, lut.shape[1], lut.shape[0], 0,
                        GL.GL_RG, GL.GL_FLOAT, np.ascontiguousarray(lut, np.float32))  # fmt: skip
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def _upload_cubes(self, cubes: list[tuple[CubeMap | None, CubeMap | None]]) -> list[int]:
        """Cube (min, max) texels into the RG32F buffer texture, re-sending only cubes
        that changed. Layout: ``CUBE_MAP_SIZE``² texels per face (``_tiled``), face
        after face; the static cube of light k holds faces 6 k .. 6 k + 5, the animated
        cube 6 (L + k) .. when the scene has animated triangles. Returns the first face
        of every held cube in that order (static block then animated block), -1 = none.

        A buffer texture rather than a 2D array texture: llvmpipe's buffer fetch has no
        layer, level or 2D addressing to do, ~13 % less time for the whole sewer pass
        (13 lights, 640x480)."""
        n = len(cubes)
        blocks = [c[0] for c in cubes] + (
            [c[1] for c in cubes] if self._ctx.animated_tri.any() else []
        )
        face_texels = CUBE_MAP_SIZE * CUBE_MAP_SIZE
        face_bytes = face_texels * CUBE_TEXEL_BYTES
        layers = 6 * len(blocks)
        if self._cube_tex is None or layers != self._cube_tex_layers:
            limit = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_BUFFER_SIZE))
            if layers * face_texels > limit:
                raise RuntimeError(
                    f"{len(blocks)} cube shadow maps of {CUBE_MAP_SIZE}² texels a face "
                    f"exceed the OpenGL buffer texture limit of {limit} texels "
                    f"({limit // (6 * face_texels)} cubes)"
                )
            if self._cube_tex is not None:
                GL.glDeleteTextures(1, [self._cube_tex])
                GL.glDeleteBuffers(1, [self._cube_buf])
            self._cube_buf = int(GL.glGenBuffers(1))
            GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self._cube_buf)
            GL.glBufferData(
                GL.GL_TEXTURE_BUFFER, max(layers, 1) * face_bytes, None, GL.GL_STATIC_DRAW
            )
            self._cube_tex = int(GL.glGenTextures(1))
            GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self._cube_tex)
            GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_RG32F, self._cube_buf)
            GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
            self._cube_tex_layers = layers
            self._cube_tex_held = [None] * len(blocks)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self._cube_buf)
        for b, cube in enumerate(blocks):
            if cube is not None and self._cube_tex_held[b] is not cube:
                texels = _tiled(np.stack([cube.depth_min, cube.depth_max], axis=-1))
                GL.glBufferSubData(GL.GL_TEXTURE_BUFFER, 6 * b * face_bytes, 6 * face_bytes, texels)
            self._cube_tex_held[b] = cube
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, 0)
        first = [6 * b if cube is not None else -1 for b, cube in enumerate(blocks)]
        return first[:n] + (first[n:] if len(first) > n else [-1] * n)

    def _upload_distant(self, maps: list[tuple[ShadowMap | None, ShadowMap | None]]) -> None:
        """(min, max) texels of each DistantLight's static and animated maps into RG32F
        textures (slot 2 k and 2 k + 1), re-sending only maps that changed."""
        slots = [mp for pair in maps for mp in pair]
        while len(self._dmap_tex) < len(slots):
            tex = int(GL.glGenTextures(1))
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
            self._dmap_tex.append(tex)
            self._dmap_held.append(None)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        for i, mp in enumerate(slots):
            if mp is None or self._dmap_held[i] is mp:
                continue
            s = mp.depth.shape[0]
            texels = np.ascontiguousarray(np.stack([mp.depth_min, mp.depth_max], -1), np.float32)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._dmap_tex[i])
            GL.glTexImage2D(
                GL.GL_TEXTURE_2D, 0, GL.GL_RG32F, s, s, 0, GL.GL_RG, GL.GL_FLOAT, texels
            )
            self._dmap_held[i] = mp
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def _distant_uniforms(
        self,
        maps: list[tuple[ShadowMap | None, ShadowMap | None]],
        loc: Callable[[str], int],
    ) -> None:
        """Set the lookup program's DistantLight uniforms (``shaders/cube_lookup.frag``)
        for ``maps`` (per light: static, animated), textures on units 4 + 2 k (+ 1)."""
        lights = self._ctx.scene.lights.distant
        d = len(maps)
        dirs = np.array([li.direction for li in lights[:d]], np.float64).reshape(d, 3)
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
        radiance = np.array([li.radiance for li in lights[:d]], np.float32).reshape(d, 3)
        GL.glUniform3fv(loc("distant_dir"), d, dirs.astype(np.float32))
        GL.glUniform3fv(loc("distant_radiance"), d, radiance)
        frames = np.zeros((2 * d, 3, 3), np.float32)
        lo = np.zeros((2 * d, 2), np.float32)
        texel = np.ones((2 * d, 2), np.float32)
        size = np.zeros(2 * d, np.int32)
        for m, mp in enumerate(mp for pair in maps for mp in pair):
            if mp is not None:
                frames[m], lo[m], texel[m] = mp.light_from_rel, mp.lo, mp.texel
                size[m] = mp.depth.shape[0]
        for row, name in enumerate(("map_x", "map_y", "map_z")):
            GL.glUniform3fv(loc(name), 2 * d, np.ascontiguousarray(frames[:, row]))
        GL.glUniform2fv(loc("map_lo"), 2 * d, lo)
        GL.glUniform2fv(loc("map_texel"), 2 * d, texel)
        GL.glUniform1iv(loc("map_size"), 2 * d, size)
        GL.glUniform1f(loc("slope_bias_texels"), SHADOW_SLOPE_BIAS_TEXELS)
        GL.glUniform1f(loc("min_cos"), SHADOW_MIN_COS)
        for k in range(d):
            GL.glUniform1i(loc(f"dmap_s{k}"), 4 + 2 * k)
            GL.glUniform1i(loc(f"dmap_d{k}"), 5 + 2 * k)

    def row_width(self, n: int) -> int:
        """Points a row of the lookup pass's textures for ``n`` points: the frame's width,
        so that the G-buffer's points (row-major, in pixel order, the few uncovered
        pixels left out) lie on the texture as on the image. llvmpipe shades 4 x 4
        fragment blocks: neighbouring pixels then read neighbouring cube texels, which
        share cache lines (sewer 640x480: ~15 % less time for the pass than with rows of
        1024 points, whose blocks spanned four distant image regions)."""
        return max(self._ctx.width, -(-n // LOOKUP_MAX_ROWS))

    def _framebuffer(self, width: int, rows: int) -> None:
        """The outputs of ``shaders/cube_lookup.frag``, >= ``width`` x ``rows`` each:
        RGBA32UI packed per-light codes, RGBA32F direct light (+ uncertain bits)."""
        held_width, held_rows = self._lookup_size
        if self._lookup_fb is not None and width <= held_width and rows <= held_rows:
            return  # the pass draws into the lower left width x rows
        if self._lookup_fb is not None:
            GL.glDeleteFramebuffers(1, [self._lookup_fb])
            GL.glDeleteRenderbuffers(len(self._lookup_rb), self._lookup_rb)
        self._lookup_size = (width, rows)
        self._lookup_rb = [int(rb) for rb in GL.glGenRenderbuffers(2)]
        self._lookup_fb = int(GL.glGenFramebuffers(1))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._lookup_fb)
        formats = (GL.GL_RGBA32UI, GL.GL_RGBA32F)
        for i, (rb, fmt) in enumerate(zip(self._lookup_rb, formats, strict=True)):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, width, rows)
            GL.glFramebufferRenderbuffer(
                GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + i, GL.GL_RENDERBUFFER, rb
            )
        GL.glDrawBuffers(2, [GL.GL_COLOR_ATTACHMENT0 + i for i in range(2)])
        check_framebuffer("cube lookup")
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)

    def lookup(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        cubes: list[tuple[CubeMap | None, CubeMap | None]],
        ranges: np.ndarray,
        to_eye: np.ndarray | None = None,
        distant: list[tuple[ShadowMap | None, ShadowMap | None]] | None = None,
        origin: np.ndarray | None = None,
        surface: np.ndarray | None = None,
        terminator: Terminator | None = None,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray, PointTiles]:
        """Every point against every LocalLight's cube maps on the GPU (the test of
        ``shadow_maps.cube_visibility``, in ``shaders/cube_lookup.frag``).

        points : (n, 3) float64 rel metres, or world metres with ``origin`` (3,) (the
        ``Scene.origin``; subtracted in float64 as the points are packed for the GPU);
        normals : (n, 3) unit, facing the viewer; ranges : (len(cubes),) light ranges in
        metres.
        Without ``to_eye``: returns (n, len(cubes)) uint8 codes: LOOKUP_LIT,
        LOOKUP_SHADOWED (also out of range / facing away) or LOOKUP_UNCERTAIN.
        With ``to_eye`` (n, 3) unit directions to the viewer and ``surface`` (n,
        SURFACE_COLUMNS) float32 the points' UsdPreviewSurface rows: the lit pairs are
        also shaded on the GPU, each tile of up to LOOKUP_TILE consecutive points
        walking only the LocalLights that reach it
        (``shade_kernels.tile_lights``); returns the direct light (n, 4) float32 of the
        lit pairs in channels 0-2 (``shading.shade_local``'s ``lit_sums``), (n, passes)
        uint32 uncertain pairs (not in the sums): bit j of pass p is LocalLight
        ``slots[point_tile[i], p * LOOKUP_LIGHTS_PER_PASS + j]`` of point i's tile
        (``shade_kernels.undecided_rows`` reads them), and those tiles (``PointTiles``).
        ``distant`` (with ``to_eye`` only): the (static, animated) maps of up to
        LOOKUP_MAX_DISTANT DistantLights, looked up and shaded in the first pass too
        (uncertain: bit 16 + k of pass 0). ``terminator``: the points' moves onto the
        smooth surface of their meshes for their shadow tests (``engine/terminator.py``),
        or None (no point moves)."""
        n, n_local = len(points), len(cubes)
        self._ctx.make_current()
        self._setup()
        first = self._upload_cubes(cubes)
        distant = distant if to_eye is not None and distant else []
        self._upload_distant(distant)
        width = self.row_width(n)
        rows = -(-n // width)
        self._framebuffer(width, rows)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        shading = to_eye is not None
        # Without shading the to_eye texture is never read for a result: send no data.
        offset = None if origin is None else np.asarray(origin, np.float64)
        moves = (None, None) if terminator is None else (terminator.normals, terminator.lifts)
        inputs = ((points, offset), (normals, None), (to_eye if shading else None, None),
                  (moves[0], None), (moves[1], None))  # fmt: skip
        for tex, (data, minus) in zip(self._point_tex, inputs, strict=True):
            size = (width, rows) if data is not None and len(data) else (1, 1)
            if _texels_already(data, minus, size):
                texels = data  # float32 rows filling the texture: sent as they are
            else:
                texels = np.empty((size[0] * size[1], 3), dtype=np.float32)
                _shade().pack_texels(_NO_POINTS if data is None else data, minus, texels)
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexImage2D(
                GL.GL_TEXTURE_2D, 0, GL.GL_RGB32F, *size, 0, GL.GL_RGB, GL.GL_FLOAT, texels
            )
        # The clear coat's lobe only where a point has one: llvmpipe would run its code
        # for every lit pair (branches run under masks).
        coat = shading and surface is not None and bool(
            np.any(surface[:, preview_surface.CLEARCOAT] > 0.0)
        )
        if shading:  # the surface rows: four RGBA texels a point, rows as the points'
            _upload_surface(self._surface_tex, surface, n, width, rows)
        centres = np.array([self._maps.cube_keys[k][0] for k in range(n_local)], np.float64)
        # Per tile only when the lights do not fit one pass: else every point walks the
        # lights that reach any of them (uniform arrays, fewer fetches a fragment).
        tiled = shading and n_local > LOOKUP_LIGHTS_PER_PASS
        point_tile = np.zeros(rows * width, np.int32)
        if shading:  # each tile's lights (one tile of every point unless tiled)
            slots, counts = _shade().tile_lights(
                np.ascontiguousarray(points, np.float64).reshape(n, 3),
                _ORIGIN if offset is None else offset,
                LOOKUP_TILE if tiled else max(n, 1), LOOKUP_TILE_JUMP if tiled else np.inf,
                centres.reshape(n_local, 3),
                np.ascontiguousarray(ranges, np.float64).reshape(n_local),
                LOOKUP_CULL_MARGIN, point_tile[:n],
            )  # fmt: skip
            most = int(counts.max()) if len(counts) else 0
        else:
            slots, most = np.arange(n_local, dtype=np.int64).reshape(1, n_local), n_local
        slots = np.ascontiguousarray(slots[:, :most])
        if tiled:
            table = _light_table(cubes, ranges, first, self._ctx.scene.lights,
                                 [key[0] for key in self._maps.cube_keys])  # fmt: skip
            GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self._light_buf)
            GL.glBufferData(GL.GL_TEXTURE_BUFFER, table.nbytes, table, GL.GL_DYNAMIC_DRAW)
            GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, 0)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._tile_tex)
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_R32I, width, rows, 0,
                            GL.GL_RED_INTEGER, GL.GL_INT, point_tile)  # fmt: skip
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._lookup_fb)
        GL.glViewport(0, 0, width, rows)
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_CULL_FACE)
        targets = [GL.GL_TEXTURE_2D, GL.GL_TEXTURE_2D, GL.GL_TEXTURE_BUFFER, GL.GL_TEXTURE_2D]
        textures = [self._point_tex[0], self._point_tex[1], self._cube_tex, self._point_tex[2]]
        targets += [GL.GL_TEXTURE_2D] * 2 * len(distant)  # units 4 + 2 k (+1): maps
        textures += self._dmap_tex[: 2 * len(distant)]
        # The next units: surface rows, albedo table, light table, the tiles' slots, the
        # points' tiles.
        targets += [GL.GL_TEXTURE_2D, GL.GL_TEXTURE_2D, GL.GL_TEXTURE_BUFFER]
        targets += [GL.GL_TEXTURE_2D] * 2
        textures += [self._surface_tex, self._lut_tex, self._light_tex, self._slot_tex]
        textures += [self._tile_tex]
        surface_unit = len(textures) - 5
        targets += [GL.GL_TEXTURE_2D] * 2  # the terminator's normals and lifts, after the
        textures += self._point_tex[3:]  # points' tiles
        for unit, (target, tex) in enumerate(zip(targets, textures, strict=True)):
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(target, tex)
        GL.glActiveTexture(GL.GL_TEXTURE0 + surface_unit + 3)  # the slots, per pass
        GL.glBindVertexArray(self._lookup_vao)
        # Only the attachments this pass writes are drawn to (llvmpipe stores every
        # drawn attachment of every fragment, written by the shader or not: the codes
        # are 16 of the shading pass's 48 bytes a point).
        attachments = [GL.GL_COLOR_ATTACHMENT0 + i for i in range(2)]
        if shading:
            GL.glDrawBuffers(2, [GL.GL_NONE, attachments[1]])
        else:
            GL.glDrawBuffers(2, [attachments[0], GL.GL_NONE])
        passes = max(-(-most // LOOKUP_LIGHTS_PER_PASS), 1 if distant else 0)
        if shading:
            # Read back straight into the result (one pass: no sums, no copies): direct
            # light RGBA rows, of which the first n are the points'.
            direct = np.empty((rows * width, 4), dtype=np.float32)
            bits = np.empty((n, passes), dtype=np.uint32)
            sums = np.empty((rows * width, 4), dtype=np.float32) if passes > 1 else None
            if passes == 0:  # nothing for the GPU to shade (DistantLights in numpy)
                direct[:] = 0.0
        else:
            out = np.zeros((n, n_local), dtype=np.uint8)
            # One byte per light, 16 per texel (see the shader): the readback viewed as
            # (texels, 16) uint8 is light-ordered on little-endian hosts.
            readback = np.empty((rows, width, 4), dtype="<u4")
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        for p in range(passes):
            start = p * LOOKUP_LIGHTS_PER_PASS
            count = min(LOOKUP_LIGHTS_PER_PASS, most - start)
            n_distant = len(distant) if p == 0 else 0
            if tiled:
                _upload_slots(self._slot_tex, slots[:, start : start + count])
            prog = self._program_for(
                max(count, 0), n_distant, shading, tiled, coat, terminator is not None
            )

            def loc(name: str, prog: int = prog) -> int:
                return GL.glGetUniformLocation(prog, name)

            GL.glUseProgram(prog)
            GL.glUniform1i(loc("points"), 0)
            GL.glUniform1i(loc("normals"), 1)
            GL.glUniform1i(loc("cubes"), 2)
            GL.glUniform1i(loc("to_eye"), 3)
            GL.glUniform1i(loc("n_points"), n)
            GL.glUniform1i(loc("width"), width)
            GL.glUniform1f(loc("bias_texels"), SHADOW_BIAS_TEXELS)
            GL.glUniform1f(loc("box_radius"), SHADOW_REFINE_RADIUS + 0.5)
            GL.glUniform1f(loc("slope_clamp"), 1.0 / SHADOW_MIN_COS)
            GL.glUniform1f(loc("min_light_distance"), MIN_LIGHT_DISTANCE)
            GL.glUniform1i(loc("surface"), surface_unit)
            GL.glUniform1i(loc("albedo_lut"), surface_unit + 1)
            GL.glUniform1f(loc("min_roughness"), preview_surface.MIN_ROUGHNESS)
            GL.glUniform1f(loc("min_cosine"), preview_surface.MIN_COSINE)
            GL.glUniform1i(loc("terminator"), surface_unit + 5)
            GL.glUniform1i(loc("lifts"), surface_unit + 6)
            if tiled:
                GL.glUniform1i(loc("light_table"), surface_unit + 2)
                GL.glUniform1i(loc("tile_slots"), surface_unit + 3)
                GL.glUniform1i(loc("point_tiles"), surface_unit + 4)
            else:
                ks = [int(k) for k in slots[0, start : start + count]] if len(slots) else []
                _pass_lights(loc, ks, cubes, ranges, first, self._ctx.scene.lights,
                             [key[0] for key in self._maps.cube_keys])  # fmt: skip
            if n_distant:
                self._distant_uniforms(distant, loc)
            # A light without any cube (no casters at all) is lit within its range:
            # its first faces are -1 and cube_test answers 1.
            GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
            if shading:
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT1)
                into = direct if p == 0 else sums
                GL.glReadPixels(0, 0, width, rows, GL.GL_RGBA, GL.GL_FLOAT, into)
                bits[:, p] = into[:n, 3]  # channel 3: the pass's uncertain bits
                if p > 0:
                    direct[:, :3] += sums[:, :3]
            else:
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
                GL.glReadPixels(0, 0, width, rows, GL.GL_RGBA_INTEGER, GL.GL_UNSIGNED_INT, readback)
                codes = readback.view(np.uint8).reshape(-1, 16)[:n, :count]
                out[:, start : start + count] = codes
        GL.glBindVertexArray(0)
        for unit, target in enumerate(targets):
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(target, 0)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glEnable(GL.GL_DEPTH_TEST)
        if shading:
            return direct[:n], bits, PointTiles(slots, point_tile[:n])
        return out


def _upload_surface(texture: int, surface: np.ndarray | None, n: int, width: int, rows: int):
    """The points' surface rows (n, SURFACE_COLUMNS) float32 (None: the fallback
    material of albedo 1) into the RGBA32F ``texture`` of ``4 width`` x ``rows`` texels
    (point k's four texels at (4 (k % width) + i, k / width))."""
    columns = preview_surface.SURFACE_COLUMNS
    if surface is None:
        surface = preview_surface.fallback_surface(np.ones((n, 3)))
    surface = np.ascontiguousarray(surface, np.float32).reshape(n, columns)
    if n == width * rows:
        texels = surface
    else:
        texels = np.zeros((max(width * rows, 1), columns), np.float32)
        texels[:n] = surface
    GL.glBindTexture(GL.GL_TEXTURE_2D, texture)
    GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA32F, 4 * max(width, 1), max(rows, 1), 0,
                    GL.GL_RGBA, GL.GL_FLOAT, texels)  # fmt: skip


#: The texel tiles of the cube buffer (``_tiled``): (columns, rows) of a 64-byte cache
#: line and of a 4 KB page of RG32F texels.
CUBE_LINE_TILE = (4, 2)
CUBE_PAGE_TILE = (32, 16)


def _tiled(texels: np.ndarray) -> np.ndarray:
    """(6, S, S, 2) float cube faces (``CubeMap`` order: face, row, column, (min, max))
    as the GPU's buffer holds them (S = CUBE_MAP_SIZE, a multiple of 32): per face,
    pages of CUBE_PAGE_TILE texels row-major, in each page lines of CUBE_LINE_TILE
    texels row-major, in each line its texels row-major (``cube_test`` in
    ``shaders/cube_lookup.frag`` addresses it). Texels near each other on a face share
    a line or a page, as neighbouring pixels' lookups do (sewer 640x480: ~3 % less
    time for the pass than row-major faces). Returns (6 S², 2) float32."""
    size = texels.shape[1]
    (lx, ly), (px, py) = CUBE_LINE_TILE, CUBE_PAGE_TILE
    blocks = texels.reshape(6, size // py, py // ly, ly, size // px, px // lx, lx, 2)
    # (face, page row, line row, row, page column, line column, column) ->
    # (face, page row, page column, line row, line column, row, column)
    order = blocks.transpose(0, 1, 4, 2, 5, 3, 6, 7)
    return np.ascontiguousarray(order, np.float32).reshape(-1, 2)


#: An empty point array (``pack_texels`` of a texture that holds no points).
_NO_POINTS = np.zeros((0, 3), np.float32)


def _texels_already(data: np.ndarray | None, minus: np.ndarray | None, size) -> bool:
    """``data`` (n, 3) is a texture of ``size`` (width, rows) as it is: float32,
    C-contiguous, nothing to subtract, one row per texel (a frame covering every pixel:
    its normals and view directions need no packing copy)."""
    return (
        data is not None
        and minus is None
        and data.dtype == np.float32
        and data.flags.c_contiguous
        and data.shape == (size[0] * size[1], 3)
    )


def _pass_lights(loc, ks: list[int], cubes, ranges, first: list[int], lights: Lights, centres):
    """An untiled lookup pass's LocalLights ``ks`` (indices into ``cubes``) as its
    program's uniform arrays (slot j: light ks[j]): ``loc`` the program's uniform
    locations, ``first`` as ``LightPass._upload_cubes`` returns it, ``lights`` the
    scene's, ``centres`` its LocalLights' rel positions (``ShadowMaps.cube_keys``)."""
    n_local, pad = len(cubes), LOOKUP_LIGHTS_PER_PASS - len(ks)
    pos = np.zeros((LOOKUP_LIGHTS_PER_PASS, 3), np.float32)
    pos[: len(ks)] = np.reshape([centres[k] for k in ks], (-1, 3))
    radiance = np.zeros((LOOKUP_LIGHTS_PER_PASS, 3), np.float32)
    radiance[: len(ks)] = np.reshape([lights.local[k].radiance for k in ks], (-1, 3))
    cube = [c[0] or c[1] for c in (cubes[k] for k in ks)]
    near = [c.near if c is not None else 0.0 for c in cube] + [0.0] * pad
    GL.glUniform3fv(loc("light_pos"), LOOKUP_LIGHTS_PER_PASS, pos)
    GL.glUniform3fv(loc("light_radiance"), LOOKUP_LIGHTS_PER_PASS, radiance)
    GL.glUniform1fv(loc("light_range"), LOOKUP_LIGHTS_PER_PASS,
                    np.array([ranges[k] for k in ks] + [0.0] * pad, np.float32))
    GL.glUniform1fv(loc("light_near"), LOOKUP_LIGHTS_PER_PASS, np.array(near, np.float32))
    GL.glUniform1iv(loc("static_face"), LOOKUP_LIGHTS_PER_PASS,
                    np.array([first[k] for k in ks] + [-1] * pad, np.int32))
    GL.glUniform1iv(loc("dynamic_face"), LOOKUP_LIGHTS_PER_PASS,
                    np.array([first[n_local + k] for k in ks] + [-1] * pad, np.int32))
    shapes = _area_texels(lights)
    if shapes is not None:  # the program's AREA uniforms
        texels = np.zeros((LOOKUP_LIGHTS_PER_PASS, 3, 4), np.float32)
        texels[: len(ks)] = shapes[ks]
        GL.glUniform4fv(loc("light_u"), LOOKUP_LIGHTS_PER_PASS, texels[:, 0])
        GL.glUniform3fv(loc("light_v"), LOOKUP_LIGHTS_PER_PASS,
                        np.ascontiguousarray(texels[:, 1, :3]))
        GL.glUniform3fv(loc("light_axis"), LOOKUP_LIGHTS_PER_PASS,
                        np.ascontiguousarray(texels[:, 2, :3]))


def _light_table(cubes, ranges, first: list[int], lights: Lights, centres) -> np.ndarray:
    """The LocalLights' table of a tiled pass (``shaders/cube_lookup.frag``'s
    ``light_table``), (max(L, 1), LIGHT_TEXELS, 4) float32: per light (rel position,
    range), (radiance, the cube's near plane), (first face of the static cube, of the
    animated one, 0, 0) and, where some light is a Rect or Disk light, its shape
    (``_area_texels``); arguments as ``_pass_lights``'."""
    n_local = len(cubes)
    shapes = _area_texels(lights)
    table = np.zeros((max(n_local, 1), _light_texels(shapes is not None), 4), np.float32)
    if shapes is not None:
        table[:n_local, 3:] = shapes
    for k, pair in enumerate(cubes):
        cube = pair[0] or pair[1]
        table[k, 0, :3], table[k, 0, 3] = centres[k], ranges[k]
        table[k, 1, :3] = lights.local[k].radiance
        table[k, 1, 3] = cube.near if cube is not None else 0.0
        table[k, 2, :2] = first[k], first[n_local + k]
    return table


def _area_defines(area: bool) -> str:
    """The shader's defines of the area lights' factor (``area_factor``): whether it is
    compiled in, the light table's texels a light, a disk's outline."""
    return (
        f"#define AREA {int(area)}\n#define LIGHT_TEXELS {_light_texels(area)}\n"
        f"#define DISK_CORNERS {_areas().DISK_CORNERS}\n"
        f"#define DISK_SCALE {_areas().DISK_CORNER_SCALE!r}\n"
    )


def _light_texels(area: bool) -> int:
    """Texels a light of the tiled pass's light table (the shader's LIGHT_TEXELS): three,
    and three more of its shape (``_area_texels``) when a light is a Rect or Disk light."""
    return 6 if area else 3


def _area_texels(lights: Lights) -> np.ndarray | None:
    """(L, 3, 4) float32: each LocalLight's shape as the shader's ``area_factor`` reads it,
    (half axis u in metres, kind: 0 none, ``area_light_kernels.RECT`` or ``DISK``),
    (half axis v, 0), (the unit direction it emits along, 0), taken from the shading's
    table of the shapes (``shading.area_table``); None when no light of ``lights`` is a
    Rect or Disk light."""
    area = area_table(lights)
    if area is None:
        return None
    a = _areas()
    texels = np.zeros((len(area), 3, 4), np.float32)
    texels[:, 0, :3], texels[:, 0, 3] = area[:, a.AREA_U : a.AREA_U + 3], area[:, a.AREA_KIND]
    texels[:, 1, :3] = area[:, a.AREA_V : a.AREA_V + 3]
    texels[:, 2, :3] = area[:, a.AREA_AXIS : a.AREA_AXIS + 3]
    return texels


def _upload_slots(texture: int, slots: np.ndarray) -> None:
    """One pass's slots of each tile (T, <= LOOKUP_LIGHTS_PER_PASS) int64 into the R32I
    ``texture``, bound on the active unit: tile t's slot j at texel
    (LOOKUP_LIGHTS_PER_PASS (t % SLOT_TILES_A_ROW) + j, t / SLOT_TILES_A_ROW), -1 where
    the tile has no light left."""
    n_tiles = max(len(slots), 1)
    across = min(n_tiles, SLOT_TILES_A_ROW)
    texels = np.full((-(-n_tiles // across) * across, LOOKUP_LIGHTS_PER_PASS), -1, np.int32)
    texels[: len(slots), : slots.shape[1]] = slots
    GL.glBindTexture(GL.GL_TEXTURE_2D, texture)
    GL.glTexImage2D(
        GL.GL_TEXTURE_2D, 0, GL.GL_R32I, across * LOOKUP_LIGHTS_PER_PASS,
        len(texels) // across, 0, GL.GL_RED_INTEGER, GL.GL_INT, texels,
    )  # fmt: skip


def _areas():
    """The area lights' kernels (``trace.area_light_kernels``: the shape table's kinds and
    a disk's outline, which the shader's ``area_factor`` mirrors), taken on first use."""
    return kernels.load("phrt_usd.engine.trace.area_light_kernels")


def _shade():
    """The compiled kernels (``shade_kernels``), taken on first use."""
    return kernels.load("phrt_usd.engine.shade_kernels")
