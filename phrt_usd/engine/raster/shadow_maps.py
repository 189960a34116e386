"""Shadow maps of every light: rendering, caching on versions, and their numpy
lookups with percentage-closer filtering (PCF).

DistantLights (``ShadowMaps.distant_maps``): orthographic depth renders along the light,
one of the static casters (SHADOW_MAP_SIZE², over their light-space footprint, rendered
once) and one of the animated casters (``Element.animated``; same texel size, over their
footprint only, re-rendered when they moved: ``ShadowMaps`` caches on the context's
``batch_versions``). Points are projected into light space, compared with a slope-scaled
bias and filtered with bilinear 2x2 PCF (``filtered_visibility``); a point's
visibility is the product over the two maps. Points whose texel neighbourhood holds both
occluding and clear depths (shadow edges, casters thinner than a texel) are *uncertain*:
the caller may resolve only those exactly (the tracer's shadow rays in hybrid mode,
~2-15 % of the points on the farm).

LocalLights (``ShadowMaps.cube_maps``): per light, six 90° perspective depth renders
(CUBE_MAP_SIZE², plus a guard band) of the static casters out to the light's range
(``shading.light_ranges``), and six of the animated casters when there are any; cached
like the distant maps and re-rendered only for a light that moved / changed range or
geometry that moved. The per-point test runs on the GPU (``light_pass``,
``shaders/cube_lookup.frag``); ``cube_visibility`` here is its numpy twin, also the PCF of
the few uncertain pairs: only points within the light's range and facing it are looked
up, with a bias that follows the receiver's own depth slope; the nearest texel's
neighbourhood min / max decide lit / shadowed / *uncertain*. Measured on the sewer (13
lights, 320x240): ~1.1 s to render all cubes once, about 3 % of (point, light) pairs
uncertain.

Coordinate spaces as in ``context``: "rel" is world minus ``Scene.origin``, metres.

Cut-outs (UsdPreviewSurface ``opacityThreshold``): in a scene with cut-out materials
every depth render is a peeled id render instead (``cutout_layers.IdLayers.
first_present_depth``): a texel's depth is that of the nearest caster that is there by
the one cut-out rule (``model.surface.Cutouts``, the tracer's too), so a cut-out casts
no shadow through its holes (``use_cutouts``).

Limits: without an exact resolution of the uncertain pairs, casters much thinner than a
shadow-map texel (scene extent / 2048) cast broken shadows; cube maps miss casters nearer
to the light than CUBE_NEAR_FRACTION of its range.
"""

from __future__ import annotations

import ctypes
import time
from dataclasses import dataclass

import numpy as np
from OpenGL import GL

from phrt_usd.engine.raster.context import (
    CLIP_PADDING,
    RasterContext,
    check_framebuffer,
    transform_rows,
)
from phrt_usd.engine.raster.cutout_layers import IdLayers
from phrt_usd.engine.shading import light_ranges
from phrt_usd.engine.terminator import Terminator

#: Static shadow-map resolution (texels per side).
SHADOW_MAP_SIZE = 2048
#: Smallest side of the animated casters' shadow map (it is sized to their footprint at
#: the static map's texel size, so that both maps resolve the same detail).
MIN_DYNAMIC_MAP_SIZE = 16

#: Shadow bias: a point is lit when its light depth minus the bias is <= the map's depth.
#: Constant part in shadow-map texel widths (covers depth-render rounding and the
#: float32 vertex positions) ...
SHADOW_BIAS_TEXELS = 1.0
#: ... plus this many texel widths times tan(angle between normal and light): 2x2 PCF
#: compares against texels up to ~1.5 texels away, where a sloped surface's own depth
#: differs by up to that distance times its slope.
SHADOW_SLOPE_BIAS_TEXELS = 2.0
#: Texel radius of the neighbourhood that decides whether a point is *uncertain* (see
#: ``ShadowMap``): 1 covers the PCF taps. 2 would also catch casters thinner than a
#: texel that the map sampled only every other texel along their length, but it sends
#: ~1.5x as many pairs to shadow rays (sewer: 26k vs 17k per frame) for no better match
#: with the ``rt`` reference (hybrid-all vs rt mean FLIP over 8 frames: sewer 0.0072 vs
#: 0.0064, farm 0.0042 vs 0.0050).
SHADOW_REFINE_RADIUS = 1
#: |cos| floor for the slope term (tan <= ~10): at grazing light the bias would grow
#: without bound; such points get almost no direct light anyway (n.L ~ 0).
SHADOW_MIN_COS = 0.1

#: LocalLight cube shadow maps: texels per side of each of the 6 faces. One cube is
#: 6 x 512² x 3 float32 arrays (depth, min, max) = 18 MB in numpy plus 12 MB of
#: (min, max) texture on the GPU; the sewer's 13 lights hold ~400 MB in all.
CUBE_MAP_SIZE = 512
#: Guard band of every cube face, in texels: a face is rendered over a slightly wider
#: field than its 90° square, so the texel neighbourhood any lookup reads (PCF taps,
#: the uncertainty box of radius SHADOW_REFINE_RADIUS) lies on the same face.
CUBE_GUARD_TEXELS = SHADOW_REFINE_RADIUS + 2
#: Near plane of the cube faces as a fraction of the far plane (the light's range, or
#: the farthest scene point if nearer). The 32-bit float depth buffer then resolves
#: forward distance w to about w**2 / (near * 2**24): 5 mm at w = 20 m for a 40 m
#: range, well under the 1-texel bias (8 cm there). Casters nearer to the light than
#: the near plane (4 mm for that light) are missed.
CUBE_NEAR_FRACTION = 1e-4
#: The two axes spanning a cube face, per major axis of the light-to-point vector.
_CUBE_FACE_AXES = ((1, 2), (0, 2), (0, 1))


@dataclass
class ShadowMap:
    """One orthographic depth map of a set of casters for one distant light.

    light_from_rel : (3, 3) float64 rows x, y, z of the light frame (z = towards light)
    lo, texel      : (2,) float64 lower corner (x, y) of the map and texel size, metres
    depth          : (S, S) float32 caster depth in metres along the light's travel
                     direction (-z), inf where no caster; row 0 at y = lo[1] (OpenGL's
                     bottom-up order, not flipped)
    depth_min/max  : the same filtered to the min / max over a texel neighbourhood: a
                     point is *uncertain* when its neighbourhood holds both occluding
                     and non-occluding texels (a shadow edge, or a caster thinner than
                     a texel that the map caught only in places)
    """

    light_from_rel: np.ndarray
    lo: np.ndarray
    texel: np.ndarray
    depth: np.ndarray
    depth_min: np.ndarray  # (S, S) float32: min / max of depth over the
    depth_max: np.ndarray  # (2 r + 1)^2 texels around, r = SHADOW_REFINE_RADIUS


@dataclass
class CubeMap:
    """Omnidirectional depth map of a set of casters around one LocalLight.

    Face ``f = 2 * axis + (0 for +, 1 for -)`` looks along ±axis from the light; a point
    at ``v = rel - light_rel`` with major axis ``a`` (|v_a| largest) lies on face
    ``2 a + (v_a < 0)`` at forward distance ``w = |v_a|`` and face coordinates
    ``(v_b / w, v_c / w)``, (b, c) = ``_CUBE_FACE_AXES[a]``, each in [-1, 1].

    light_rel  : (3,) float64 rel metres; near, far : the faces' clip planes, metres
    tan_half   : tangent of a face's half field of view (> 1: guard band)
    depth      : (6, S, S) float32 caster forward distance w in metres, inf where no
                 caster; [face, row (along c), column (along b)]
    depth_min/max : the same, min / max over the (2 r + 1)² texels around
                 (r = SHADOW_REFINE_RADIUS), for the *uncertain* test as in ShadowMap
    """

    light_rel: np.ndarray
    near: float
    far: float
    tan_half: float
    depth: np.ndarray
    depth_min: np.ndarray
    depth_max: np.ndarray


def cube_visibility(
    cube: CubeMap, rel: np.ndarray, normals: np.ndarray, filtered: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Visibility of points ``rel`` (m, 3) (rel metres, within the cube's far plane)
    with unit ``normals`` (m, 3) facing the light, against one cube map. The numpy
    reference of ``shaders/cube_lookup.frag`` (which does the same per pixel on the
    GPU; keep the two in step), also used for the few uncertain points' PCF.

    Bias: SHADOW_BIAS_TEXELS texel widths plus the receiver's own depth change over
    the texels read. For the receiver plane, forward distance w changes per texel by
    ``texel * w * (|n_b| + |n_c|) / |n·v|`` (sum over both face axes; clamped to
    ``texel / SHADOW_MIN_COS`` at grazing light). The nearest texel's neighbourhood
    (radius SHADOW_REFINE_RADIUS, ``depth_min`` / ``depth_max``) decides: all casters
    beyond the biased point: lit; all in front: shadowed; else *uncertain*.
    ``filtered``: uncertain points get bilinear 2x2 PCF (bias for the PCF taps only),
    else 0.5 (for a caller resolving them otherwise). Returns (m,) float32 visibility
    and (m,) bool uncertain."""
    size = cube.depth.shape[1]
    v = rel - cube.light_rel
    a = np.abs(v)
    on_x = (a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2])
    axis = np.where(on_x, 0, np.where(a[:, 1] >= a[:, 2], 1, 2))
    rows = np.arange(len(v))
    w = a[rows, axis]
    face = 2 * axis + (v[rows, axis] < 0)
    vb = np.where(axis == 0, v[:, 1], v[:, 0])
    vc = np.where(axis == 2, v[:, 1], v[:, 2])
    nb = np.where(axis == 0, normals[:, 1], normals[:, 0])
    nc = np.where(axis == 2, normals[:, 1], normals[:, 2])
    # w > 0 unless the point is at the light (no light reaches it then: n·l = 0).
    inv_w = 1.0 / np.maximum(w, 1e-300)
    texel = 2.0 * cube.tan_half * w / size  # texel width in metres at distance w
    n_dot_v = np.maximum(np.abs(np.einsum("ij,ij->i", normals, v)), 1e-30)
    slope = np.minimum(texel * w * (np.abs(nb) + np.abs(nc)) / n_dot_v, texel / SHADOW_MIN_COS)
    flat_bias = w - texel * SHADOW_BIAS_TEXELS
    test = flat_bias - (SHADOW_REFINE_RADIUS + 0.5) * slope
    scale = 0.5 * size / cube.tan_half
    xn = np.clip(np.floor(vb * inv_w * scale + 0.5 * size).astype(np.int64), 0, size - 1)
    yn = np.clip(np.floor(vc * inv_w * scale + 0.5 * size).astype(np.int64), 0, size - 1)
    base = face * (size * size)
    nearest = base + yn * size + xn
    lo = cube.depth_min.reshape(-1)[nearest]
    hi = cube.depth_max.reshape(-1)[nearest]
    # Points nearer than the near plane: nothing was rendered in front of them.
    inside = w > cube.near
    vis = np.where(test <= lo, 1.0, 0.0).astype(np.float32)
    uncertain = inside & (lo < test) & (hi >= test)
    vis[~inside] = 1.0
    if uncertain.any():
        if filtered:
            u = uncertain
            fx = vb[u] * inv_w[u] * scale + (0.5 * size - 0.5)  # texel centres at integers
            fy = vc[u] * inv_w[u] * scale + (0.5 * size - 0.5)
            vis[u] = _cube_pcf(cube, base[u], fx, fy, flat_bias[u] - slope[u])
        else:
            vis[uncertain] = 0.5
    return vis, uncertain


def cube_pair_visibility(
    pair: tuple[CubeMap | None, CubeMap | None],
    rel: np.ndarray,
    normals: np.ndarray,
    filtered: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(m,) float32 visibility and (m,) bool uncertain of points ``rel`` (m, 3) through a
    light's (static, animated) cube maps: the product of both maps' answers."""
    v_all = np.ones(len(rel), dtype=np.float32)
    u_all = np.zeros(len(rel), dtype=bool)
    for cube in pair:
        if cube is not None:
            v, u = cube_visibility(cube, rel, normals, filtered)
            # Uncertain in one map matters only where the other lets light by.
            u_all = (u_all & (v > 0)) | (u & (v_all > 0))
            v_all *= v
    return v_all, u_all


def _cube_pcf(cube: CubeMap, base, fx, fy, test) -> np.ndarray:
    """Bilinear 2x2 percentage-closer filtering on one face each (guard band: the taps
    never leave it). base (m,) flat offset of the face, fx / fy (m,) texel coordinates,
    test (m,) biased forward distances. Returns (m,) float32."""
    size = cube.depth.shape[1]
    return _bilinear_pcf(cube.depth.reshape(-1), size, base, fx, fy, test).astype(np.float32)


def _bilinear_pcf(flat, size: int, base, fx, fy, test) -> np.ndarray:
    """Share of the 2x2 texels around (fx, fy) whose depth is >= ``test``, bilinearly
    weighted. flat: square ``size`` x ``size`` depth maps flattened (several maps one
    after another, ``base`` (m,) or 0 picks the map); fx, fy, test: (m,) texel
    coordinates and biased depths. Taps are clamped to the map. Returns (m,) float64."""
    x0 = np.floor(fx).astype(np.int64)
    y0 = np.floor(fy).astype(np.int64)
    wx = fx - x0
    wy = fy - y0
    vis = np.zeros(len(fx))
    for dx, dy, weight in (
        (0, 0, (1 - wx) * (1 - wy)),
        (1, 0, wx * (1 - wy)),
        (0, 1, (1 - wx) * wy),
        (1, 1, wx * wy),
    ):
        xi = np.clip(x0 + dx, 0, size - 1)
        yi = np.clip(y0 + dy, 0, size - 1)
        vis += weight * (test <= np.take(flat, base + yi * size + xi))
    return vis


def _box_extremum(a: np.ndarray, r: int, op: np.ufunc) -> np.ndarray:
    """``op`` (np.minimum / np.maximum) of 2D ``a`` over the (2 r + 1)^2 box around each
    element, edges clamped: separable passes over shifted slices (much faster here than
    scipy.ndimage's min / max filters)."""
    rows = np.pad(a, [(r, r), (0, 0)], mode="edge")
    n0, n1 = a.shape
    acc = rows[0:n0].copy()
    for k in range(1, 2 * r + 1):
        op(acc, rows[k : k + n0], out=acc)
    cols = np.pad(acc, [(0, 0), (r, r)], mode="edge")
    out = cols[:, 0:n1].copy()
    for k in range(1, 2 * r + 1):
        op(out, cols[:, k : k + n1], out=out)
    return out


def filtered_visibility(
    mp: ShadowMap, rel: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Visibility of points ``rel`` (n, 3) (rel metres) with ``normals`` (n, 3) against
    one map: slope-scaled bias, bilinear 2x2 PCF. Points outside the map's footprint
    are lit (none of its casters is above them).

    Returns (n,) float64 visibility in [0, 1] and (n,) bool *uncertain* (see
    ``ShadowMap.depth_min``)."""
    s = mp.depth.shape[0]
    lp = transform_rows(rel, mp.light_from_rel)
    # Texel coordinates (texel centres at +0.5); only points over the map's footprint
    # need the rest (an animated caster's map covers a small part of the view).
    fx = (lp[:, 0] - mp.lo[0]) / mp.texel[0] - 0.5
    fy = (lp[:, 1] - mp.lo[1]) / mp.texel[1] - 0.5
    inside = np.flatnonzero((fx > -1.0) & (fx < s) & (fy > -1.0) & (fy < s))
    vis = np.ones(len(rel))
    uncertain = np.zeros(len(rel), dtype=bool)
    if len(inside) == 0:
        return vis, uncertain
    fx, fy = fx[inside], fy[inside]
    texel = float(mp.texel.max())
    n_z = transform_rows(np.take(normals, inside, axis=0), mp.light_from_rel[2:3])[:, 0]
    cos = np.clip(np.abs(n_z), SHADOW_MIN_COS, 1.0)
    tan = np.sqrt(1.0 - cos**2) / cos
    test = -lp[inside, 2] - texel * (SHADOW_BIAS_TEXELS + SHADOW_SLOPE_BIAS_TEXELS * tan)
    finite = np.isfinite(test)
    # Bilinear PCF over the 2x2 texels around the point.
    vis[inside] = np.where(finite, _bilinear_pcf(mp.depth.reshape(-1), s, 0, fx, fy, test), 1.0)
    nearest = np.clip(np.rint(fy).astype(np.int64), 0, s - 1) * s + np.clip(
        np.rint(fx).astype(np.int64), 0, s - 1
    )
    uncertain[inside] = (
        finite
        & (np.take(mp.depth_min.reshape(-1), nearest) < test)
        & (np.take(mp.depth_max.reshape(-1), nearest) >= test)
    )
    return vis, uncertain


class ShadowMaps:
    """The shadow maps of a ``RasterContext``'s scene, rendered when first needed and
    cached on versions: each batch's maps on the context's ``batch_versions`` of that
    batch (its casters), the lights' directions, positions and ranges on the scene's
    lights version and the context's ``upload_version`` (the origin of rel space). A
    map is rendered again only when a version it was rendered for has changed; nothing
    else is compared. ``maps_rendered`` counts the renders per batch ("static",
    "dynamic"; a cube map counts once)."""

    def __init__(self, ctx: RasterContext) -> None:
        self._ctx = ctx
        self._static_maps: list[ShadowMap | None] | None = None
        self._dynamic_maps: list[ShadowMap | None] | None = None
        #: The batch version each list of distant maps was rendered from.
        self._distant_for = {"static": -1, "dynamic": -1}
        self._map_dirs: list[np.ndarray] = []
        self._distant_lights_for: tuple[int, int] | None = None  # (upload, lights) versions
        self.last_cube_build_seconds = 0.0
        self._cube_keys: list[tuple] = []  # per LocalLight: (rel position, range)
        self._cube_lights_for: tuple[int, int] | None = None  # (upload, lights) versions
        self._cube_static: list[CubeMap | None] = []
        self._cube_dynamic: list[CubeMap | None] = []
        #: Per LocalLight, the batch versions its (static, animated) cube was rendered
        #: from (-1: not rendered for its current position and range).
        self._cube_for: list[tuple[int, int]] = []
        self.maps_rendered = {"static": 0, "dynamic": 0}
        self._cutouts = None  # (surface.Cutouts, TriangleTable) with cut-outs, else None
        self._layers: IdLayers | None = None
        self._create_framebuffer()

    def use_cutouts(self, cutouts, table) -> None:
        """Render the maps through cut-out holes (module): ``cutouts`` the scene's
        ``surface.Cutouts``, ``table`` its ``surface.TriangleTable`` (rel), as the
        G-buffer holds them; a scene without cut-outs renders plain depth."""
        self._cutouts = (cutouts, table) if cutouts.any else None
        if self._cutouts is not None and self._layers is None:
            self._layers = IdLayers(self._ctx, SHADOW_MAP_SIZE, SHADOW_MAP_SIZE)

    def _create_framebuffer(self) -> None:
        """The depth-only framebuffer every shadow-map render draws into."""
        self._shadow_rb = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._shadow_rb)
        GL.glRenderbufferStorage(
            GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, SHADOW_MAP_SIZE, SHADOW_MAP_SIZE
        )
        self._shadow_fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._shadow_fb)
        GL.glFramebufferRenderbuffer(
            GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._shadow_rb
        )
        GL.glDrawBuffer(GL.GL_NONE)
        GL.glReadBuffer(GL.GL_NONE)
        check_framebuffer("shadow")
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)

    def close(self) -> None:
        """Free the shadow framebuffer (before the context goes)."""
        if self._layers is not None:
            self._layers.close()
            self._layers = None
        self._ctx.make_current()
        GL.glDeleteFramebuffers(1, [self._shadow_fb])
        GL.glDeleteRenderbuffers(1, [self._shadow_rb])

    def _lights_version(self) -> tuple[int, int]:
        """(the context's upload version, the scene's lights version): what the lights'
        directions, rel positions and ranges depend on."""
        return self._ctx.upload_version, self._ctx.scene.versions.lights

    @property
    def cube_keys(self) -> list[tuple]:
        """Per LocalLight of the latest ``cube_maps``: (rel position (3,) tuple, range)."""
        return self._cube_keys

    @staticmethod
    def _light_frame(direction: np.ndarray) -> np.ndarray:
        """(3, 3) rows x, y, z of an orthonormal frame with z = unit ``direction``."""
        z = np.asarray(direction, dtype=np.float64)
        z = z / max(np.linalg.norm(z), 1e-300)
        helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return np.stack([x, y, z])

    def _depth_render(self, clip_from_rel: np.ndarray, name: str, size: int) -> np.ndarray:
        """Depth-only render of batch ``name`` ("static" / "dynamic") through the (4, 4)
        ``clip_from_rel`` matrix, ``size`` texels square. Returns (size, size) float32
        window depth in [0, 1] (1 = no caster), row 0 at the bottom (OpenGL order).
        With cut-outs: the nearest caster that is there (module)."""
        if self._cutouts is not None:
            cutouts, table = self._cutouts
            return self._layers.first_present_depth(clip_from_rel, size, name, table.plane, cutouts)
        self._ctx.make_current()
        vao, _, count = self._ctx.batch(name)
        depth01 = np.ones((size, size), dtype=np.float32)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._shadow_fb)
        GL.glViewport(0, 0, size, size)
        GL.glScissor(0, 0, size, size)
        GL.glEnable(GL.GL_SCISSOR_TEST)  # clear only the part of the buffer in use
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthRange(0.0, 1.0)
        GL.glDisable(GL.GL_CULL_FACE)  # double-sided casters
        GL.glDisable(GL.GL_BLEND)
        GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
        GL.glClearDepth(1.0)
        GL.glClear(GL.GL_DEPTH_BUFFER_BIT)
        program = self._ctx.program("depth.vert", "depth.frag")
        if not program._in_context():
            program._add_to_context()
        program._bind()
        program.set_uniform("light_clip_from_world", clip_from_rel)
        GL.glBindVertexArray(vao)
        GL.glDrawElements(GL.GL_TRIANGLES, count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))
        GL.glBindVertexArray(0)
        program._unbind()
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glReadPixels(0, 0, size, size, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT, depth01)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return depth01

    def _render_shadow_map(self, frame: np.ndarray, name: str, size: int) -> ShadowMap | None:
        """Orthographic depth map of batch ``name`` ("static" / "dynamic") along -z of
        the light ``frame`` (3, 3), ``size`` texels square, covering exactly that
        batch's casters (plus a margin). None when the batch is empty."""
        mask = self._ctx.animated_tri if name == "dynamic" else ~self._ctx.animated_tri
        if self._ctx.mesh_node is None or not mask.any():
            return None
        self.maps_rendered[name] += 1
        used = self._ctx.animated_vertices if name == "dynamic" else self._ctx.static_vertices
        lp = transform_rows(self._ctx.uploaded[used].astype(np.float64), frame)
        # Extents clamped away from 0 (flat casters) so the matrix is invertible.
        min_span = 1e-6 * max(self._ctx.extent, 1e-9)
        pad = 2.0 / size  # two texels of margin on each side
        lo_xy, hi_xy = lp[:, :2].min(axis=0), lp[:, :2].max(axis=0)
        span_xy = np.maximum(hi_xy - lo_xy, min_span)
        lo_xy = lo_xy - pad * span_xy
        span_xy = span_xy * (1.0 + 2.0 * pad)
        dep = -lp[:, 2]  # distance along the light's travel direction
        span_d = max(dep.max() - dep.min(), min_span)
        lo_d = dep.min() - 0.01 * span_d
        span_d *= 1.02

        # clip = 2 (x - lo) / span - 1 per axis; window depth = (dep - lo_d) / span_d.
        m = np.zeros((4, 4))
        m[0, :3] = 2.0 * frame[0] / span_xy[0]
        m[0, 3] = -2.0 * lo_xy[0] / span_xy[0] - 1.0
        m[1, :3] = 2.0 * frame[1] / span_xy[1]
        m[1, 3] = -2.0 * lo_xy[1] / span_xy[1] - 1.0
        m[2, :3] = -2.0 * frame[2] / span_d
        m[2, 3] = -2.0 * lo_d / span_d - 1.0
        m[3, 3] = 1.0

        depth01 = self._depth_render(m, name, size)
        # Metres in float64 (then stored as float32), in place: no temporaries of the
        # map's size beyond the one (a 2048² map: about 20 ms less than np.where).
        depth_m = depth01.astype(np.float64)
        depth_m *= span_d
        depth_m += lo_d
        # Texels no caster covered stay at the clear value: nothing there occludes.
        depth_m[depth01 >= 1.0] = np.inf
        depth_m = depth_m.astype(np.float32)
        return ShadowMap(
            light_from_rel=frame,
            lo=lo_xy,
            texel=span_xy / size,
            depth=depth_m,
            depth_min=_box_extremum(depth_m, SHADOW_REFINE_RADIUS, np.minimum),
            depth_max=_box_extremum(depth_m, SHADOW_REFINE_RADIUS, np.maximum),
        )

    def distant_maps(self) -> list[tuple[ShadowMap | None, ShadowMap | None]]:
        """(static map, animated-geometry map) per DistantLight, either None when it has
        no casters. Static maps are rendered once (again only when the static batch's
        version changed, or a light's direction after the lights were replaced);
        animated maps again when the animated batch's version changed (animated
        elements moved), at the static map's texel size over the animated casters
        only."""
        if self._distant_lights_for != self._lights_version():
            self._distant_lights_for = self._lights_version()
            lights = self._ctx.scene.lights.distant
            dirs = [np.asarray(lt.direction, dtype=np.float64) for lt in lights]
            if len(dirs) != len(self._map_dirs) or any(
                not np.array_equal(a, b) for a, b in zip(dirs, self._map_dirs, strict=False)
            ):
                self._static_maps = self._dynamic_maps = None
            self._map_dirs = dirs
        frames = [self._light_frame(d) for d in self._map_dirs]
        versions = self._ctx.batch_versions
        if self._static_maps is None or self._distant_for["static"] != versions["static"]:
            self._distant_for["static"] = versions["static"]
            self._static_maps = [
                self._render_shadow_map(f, "static", SHADOW_MAP_SIZE) for f in frames
            ]
        if self._dynamic_maps is None or self._distant_for["dynamic"] != versions["dynamic"]:
            self._distant_for["dynamic"] = versions["dynamic"]
            self._dynamic_maps = []
            for f, static in zip(frames, self._static_maps, strict=True):
                texel = (
                    float(static.texel.max())
                    if static is not None
                    else max(self._ctx.extent, 1e-9) / SHADOW_MAP_SIZE
                )
                self._dynamic_maps.append(
                    self._render_shadow_map(f, "dynamic", self._dynamic_size(f, texel))
                )
        return list(zip(self._static_maps, self._dynamic_maps, strict=True))

    def _dynamic_size(self, frame: np.ndarray, texel: float) -> int:
        """Texels per side for the animated casters' map: their light-space footprint
        at ``texel`` metres per texel, between MIN_DYNAMIC_MAP_SIZE and SHADOW_MAP_SIZE."""
        if not self._ctx.animated_tri.any():
            return MIN_DYNAMIC_MAP_SIZE
        used = self._ctx.animated_vertices
        lp = transform_rows(self._ctx.uploaded[used].astype(np.float64), frame[:2])
        span = float((lp.max(axis=0) - lp.min(axis=0)).max())
        size = int(np.ceil(span / max(texel, 1e-300))) + 4
        return int(np.clip(size, MIN_DYNAMIC_MAP_SIZE, SHADOW_MAP_SIZE))

    def _render_cube(self, light_rel: np.ndarray, light_range: float, name: str) -> CubeMap | None:
        """Cube depth map of batch ``name`` ("static" / "dynamic") around the light at
        ``light_rel`` (3,) rel metres, out to ``light_range`` metres (or the farthest
        scene point, if nearer). None when the batch is empty or nothing is in range."""
        mask = self._ctx.animated_tri if name == "dynamic" else ~self._ctx.animated_tri
        if self._ctx.mesh_node is None or not mask.any() or not light_range > 0.0:
            return None
        self.maps_rendered[name] += 1
        lo, hi = self._ctx.bounds_rel
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
        farthest = float(np.linalg.norm(corners.reshape(-1, 3) - light_rel, axis=1).max())
        far = min(float(light_range), farthest + CLIP_PADDING * self._ctx.extent)
        if not far > 0.0:
            return None
        near = CUBE_NEAR_FRACTION * far
        size = CUBE_MAP_SIZE
        tan_half = size / (size - 2.0 * CUBE_GUARD_TEXELS)
        # Clip z = A w + B with w the forward distance: window depth 0 at near, 1 at far.
        a_z = (far + near) / (far - near)
        b_z = -2.0 * far * near / (far - near)
        depth = np.empty((6, size, size), dtype=np.float32)
        for axis in range(3):
            b, c = _CUBE_FACE_AXES[axis]
            for k, sign in enumerate((1.0, -1.0)):
                m = np.zeros((4, 4))
                m[0, b] = 1.0 / tan_half
                m[0, 3] = -light_rel[b] / tan_half
                m[1, c] = 1.0 / tan_half
                m[1, 3] = -light_rel[c] / tan_half
                m[3, axis] = sign
                m[3, 3] = -sign * light_rel[axis]
                m[2] = a_z * m[3]
                m[2, 3] += b_z
                d01 = self._depth_render(m, name, size).astype(np.float64)
                w = b_z / np.minimum(2.0 * d01 - 1.0 - a_z, -1e-300)
                depth[2 * axis + k] = np.where(d01 >= 1.0, np.inf, w)
        depth_min = np.empty_like(depth)
        depth_max = np.empty_like(depth)
        for f in range(6):
            depth_min[f] = _box_extremum(depth[f], SHADOW_REFINE_RADIUS, np.minimum)
            depth_max[f] = _box_extremum(depth[f], SHADOW_REFINE_RADIUS, np.maximum)
        return CubeMap(
            np.asarray(light_rel, np.float64).copy(),
            near,
            far,
            tan_half,
            depth,
            depth_min,
            depth_max,
        )

    def cube_maps(self) -> list[tuple[CubeMap | None, CubeMap | None]]:
        """(static map, animated-geometry map) per LocalLight (cube maps, see
        ``CubeMap``), either None when it has no casters. Rendered when first needed
        and again only for a light that moved or changed range (looked at only after
        the lights were replaced), or when the version of the batch of its casters
        changed (static or animated elements moved). ``last_cube_build_seconds``: time
        the latest call spent rendering cube maps."""
        start = time.perf_counter()
        if self._cube_lights_for != self._lights_version():
            self._cube_lights_for = self._lights_version()
            self._cube_lights_changed()
        versions = self._ctx.batch_versions
        for i, key in enumerate(self._cube_keys):
            static_for, dynamic_for = self._cube_for[i]
            light_rel = np.array(key[0])
            if static_for != versions["static"]:
                self._cube_static[i] = self._render_cube(light_rel, key[1], "static")
            if dynamic_for != versions["dynamic"]:
                self._cube_dynamic[i] = self._render_cube(light_rel, key[1], "dynamic")
            self._cube_for[i] = (versions["static"], versions["dynamic"])
        self.last_cube_build_seconds = time.perf_counter() - start
        return list(zip(self._cube_static, self._cube_dynamic, strict=True))

    def _cube_lights_changed(self) -> None:
        """The lights were replaced: per LocalLight its rel position and range
        (``cube_keys``); a light whose key changed, or every light when their number
        did, has its cubes rendered again."""
        lights = self._ctx.scene.lights
        ranges = light_ranges(lights)[len(lights.distant) :]
        keys = [
            (tuple(np.asarray(li.position, np.float64) - self._ctx.origin), float(r))
            for li, r in zip(lights.local, ranges, strict=True)
        ]
        if len(keys) != len(self._cube_keys):
            self._cube_static = [None] * len(keys)
            self._cube_dynamic = [None] * len(keys)
            self._cube_for = [(-1, -1)] * len(keys)
        for i, key in enumerate(keys):
            if i < len(self._cube_keys) and self._cube_keys[i] != key:
                self._cube_for[i] = (-1, -1)
        self._cube_keys = keys

    def distant_lookups(
        self,
        rel: np.ndarray,
        normals: np.ndarray,
        out: np.ndarray,
        uncertain: np.ndarray,
        terminator: Terminator | None = None,
    ) -> list:
        """Start the DistantLights' shadow-map lookups of points ``rel`` (n, 3) rel
        metres on the worker threads: they multiply into ``out`` (n, D) and flag
        ``uncertain`` (n, D); points tested as the ``terminator`` moves them
        (``engine/terminator.py``). Returns the futures (empty without DistantLights)."""
        maps = self.distant_maps() if len(self._ctx.scene.lights.distant) else []
        if not maps:
            return []
        lights = self._ctx.scene.lights.distant

        def lookup(part: slice) -> None:  # one chunk of points, all maps (disjoint rows)
            r, nr = rel[part], normals[part]
            rows = np.arange(part.start or 0, part.stop)
            for k, pair in enumerate(maps):
                at = r
                if terminator is not None:  # tested from the smooth surface
                    at = terminator.lifted(r, rows, lights[k].direction)
                for mp in pair:
                    if mp is not None:
                        vis, unsure = filtered_visibility(mp, at, nr)
                        out[part, k] *= vis
                        uncertain[part, k] |= unsure

        bounds = np.linspace(0, len(rel), self._ctx.threads + 1).astype(int)
        return [
            self._ctx.pool.submit(lookup, slice(a, b))
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            if b > a
        ]
