"""Rasterized G-buffer with exact triangle ids, and shadow maps for every light.

Pipeline, per phase:

1. **Upload** (``Rasterizer.__init__``, ``update_geometry``). All triangles go into ONE
   pyrender node (one mesh, one indexed primitive): pyrender costs several ms per node on
   llvmpipe. Vertices are origin-relative (``Scene.origin`` subtracted in float64, then
   cast to float32) so a stage 1e6 m from the world origin rasterizes as precisely as
   one at the origin.
2. **Id pass** (``Rasterizer.render``). pyrender's ``Renderer`` draws the node with
   ``RenderFlags.FLAT``; its program cache points at ``phrt_usd/render/raster/shaders``, whose
   ``flat.frag`` writes ``gl_PrimitiveID + 1`` (= triangle index + 1, 0 = background)
   as four exact bytes. pyrender's 4x multisampled framebuffer would blend ids at
   triangle edges, so the renderer instance gets our single-sampled framebuffer
   (RGBA8 + 32-bit float depth) instead. Read back: the id image only.
3. **Derivation** (numpy, covered pixels only). The pixel ray (same pixel centres as
   ``CameraFrame.pixel_rays``) is intersected with its triangle's plane in float64:
   position (exact, not limited by depth-buffer precision), view depth, barycentrics →
   interpolated shading normal and albedo (texture lookup when the material has one).
4. **Shadow maps** (``Rasterizer.shadow_visibility``). Per DistantLight, orthographic
   depth renders along the light: one of the static casters (SHADOW_MAP_SIZE², over
   their light-space footprint, rendered once) and one of the animated casters
   (``Element.animated``; same texel size, over their footprint only, re-rendered after
   ``update_geometry`` moved them). Points are projected into light space, compared
   with a slope-scaled bias and filtered with bilinear 2x2 percentage-closer
   filtering; a point's visibility is the product over the two maps. Points whose
   texel neighbourhood holds both occluding and clear depths (shadow edges, casters
   thinner than a texel) are *uncertain*; given a ``refine`` callable (the tracer's
   shadow rays) only those get an exact answer (~2-15 % of the points on the farm).
5. **Cube shadow maps** (LocalLights, same ``shadow_visibility`` call). Per light, six
   90° perspective depth renders (CUBE_MAP_SIZE², plus a guard band) of the static
   casters out to the light's range (``shading.light_ranges``), and six of the animated
   casters when there are any; cached like the distant maps and re-rendered only for
   a light that moved / changed range or geometry that moved. The per-point test runs
   on the GPU (``shaders/cube_lookup.frag``: one fragment per point, 16 lights a pass;
   ``_cube_visibility`` is its numpy twin): only points within the light's range and
   facing it are looked up, with a bias that follows the receiver's own depth slope;
   the nearest texel's neighbourhood min / max decide lit / shadowed / *uncertain*.
   Uncertain pairs go to ``refine`` (hybrid) or get 2x2 PCF in numpy (raster mode).
   Measured on the sewer (13 lights, 320x240): ~1.1 s to render all cubes once; the
   lookup ~20-25 ms of CPU time per frame (llvmpipe spreads it over the cores), about
   3 % of (point, light) pairs uncertain.

Coordinate spaces: "world" is ``Scene`` world metres (float64); "rel" is world minus
``Scene.origin`` (what OpenGL sees, float32 on the GPU, float64 in numpy).

Limits: opaque triangles only (transmission is a tracer concern); one OpenGL context per
``Rasterizer``; triangle count must stay below 2**32 - 1 (id encoding). Element
``animated`` flags and materials are read when the topology is uploaded (``__init__``,
or ``update_geometry`` with a changed topology). Without ``refine``, casters much
thinner than a shadow-map texel (scene extent / 2048) cast broken shadows; cube maps
miss casters nearer to the light than CUBE_NEAR_FRACTION of its range. Coincident
(coplanar, overlapping) surfaces z-fight here as they do in Embree: either may win.
"""

from __future__ import annotations

import ctypes
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import NO_HIT, CameraFrame, Scene
from phrt_usd.render.shading import (
    MIN_LIGHT_DISTANCE,
    SHININESS,
    SPECULAR_STRENGTH,
    LightPairs,
    light_ranges,
    pair_directions,
)

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import pyrender  # noqa: E402  (after the platform is chosen)
from OpenGL import GL  # noqa: E402
from OpenGL.GL import shaders as gl_shaders  # noqa: E402
from pyrender.constants import RenderFlags  # noqa: E402
from pyrender.platforms.osmesa import OSMesaPlatform  # noqa: E402
from pyrender.shader_program import ShaderProgramCache  # noqa: E402

#: Directory of our GLSL files (``flat.*``: id pass, ``depth.*``: shadow-map pass).
SHADER_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "shaders")

#: Smallest allowed near / far ratio of the perspective projection. The depth buffer
#: resolves view depth z to about z**2 / (near * 2**24); as near → 0 that diverges and
#: the projection degenerates (every depth maps to 1, all surfaces z-fight). near / far
#: is first tightened to the scene's bounds (``_clip_range``), so this clamp only acts
#: for a camera inside or at the scene with a tiny clipping near: it then clips what is
#: nearer than 1e-6 * far (1 mm at far = 1 km) and keeps depth resolution finite. Ids
#: only need the depth order of surfaces; positions never come from the depth buffer.
MIN_NEAR_OVER_FAR = 1e-6

#: Near / far are also tightened to the scene's bounds (nothing exists outside them), and
#: padded by this fraction of the scene extent so that bounding geometry is not clipped.
CLIP_PADDING = 1e-3

#: Worker threads deriving the G-buffer from the id image and looking points up in the
#: shadow maps (numpy releases the GIL in its loops, so the pixels / points are split
#: into this many chunks).
DERIVE_THREADS = max(1, min(2, os.cpu_count() or 1))

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
#: ``_ShadowMap``): 1 covers the PCF taps. 2 would also catch casters thinner than a
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
#: Query points per row of the GPU lookup pass's point texture (rows as needed).
LOOKUP_TEXTURE_WIDTH = 1024
#: LocalLights per GPU lookup pass (one RGBA32UI colour attachment, one byte each).
LOOKUP_LIGHTS_PER_PASS = 16
#: DistantLights the GPU lookup pass shades itself (more are looked up in numpy).
LOOKUP_MAX_DISTANT = 2
#: Per-light codes the GPU lookup packs one byte each (``shaders/cube_lookup.frag``).
LOOKUP_SHADOWED, LOOKUP_LIT, LOOKUP_UNCERTAIN = 0, 1, 2
#: The two axes spanning a cube face, per major axis of the light-to-point vector.
_CUBE_FACE_AXES = ((1, 2), (0, 2), (0, 1))

#: Denominator floor (relative to |face normal|) of the ray-plane intersection. A pixel
#: is only covered by a triangle the rasterizer saw with non-zero screen area, so the ray
#: is not parallel to its plane; the floor only guards against rounding, and the
#: resulting distance is clamped to the near/far range the rasterizer used.
GRAZING_EPS = 1e-12


class _ProgramCache(ShaderProgramCache):
    """pyrender's program cache over our shader directory, keyed by shader names and
    defines only. pyrender keys by the current context too, but under OSMesa every
    ``getContext()`` returns a new pointer object that never compares equal, so its
    cache misses on every call and recompiles (and leaks) the program each frame. Each
    ``Rasterizer`` owns its context and its cache, so the context is not needed here."""

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        defines = defines or {}
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted(defines.items())))
        if key not in self._program_cache:
            self._program_cache[key] = super().get_program(
                vertex_shader, fragment_shader, geometry_shader, defines
            )
        return self._program_cache[key]


class _ExactPerspective(pyrender.camera.Camera):
    """pyrender camera whose projection matrix is given explicitly (camera → clip)."""

    def __init__(self) -> None:
        super().__init__(znear=0.01, zfar=100.0)
        self.matrix = np.eye(4)

    def get_projection_matrix(self, width=None, height=None) -> np.ndarray:
        return self.matrix


def perspective_matrix(tan_x: float, tan_y: float, near: float, far: float) -> np.ndarray:
    """OpenGL clip_from_camera (4, 4) float64 for a symmetric frustum with half-angle
    tangents ``tan_x``/``tan_y`` (so that ``CameraFrame.project`` and the rasterizer put
    a point on the same pixel) and clip planes ``near`` < ``far`` (metres)."""
    p = np.zeros((4, 4))
    p[0, 0] = 1.0 / tan_x
    p[1, 1] = 1.0 / tan_y
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


@dataclass
class _ShadowMap:
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
class _CubeMap:
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
                 (r = SHADOW_REFINE_RADIUS), for the *uncertain* test as in _ShadowMap
    """

    light_rel: np.ndarray
    near: float
    far: float
    tan_half: float
    depth: np.ndarray
    depth_min: np.ndarray
    depth_max: np.ndarray


def _cube_visibility(
    cube: _CubeMap, rel: np.ndarray, normals: np.ndarray, filtered: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Visibility of points ``rel`` (m, 3) (rel metres, within the cube's far plane)
    with unit ``normals`` (m, 3) facing the light, against one cube map. The numpy
    reference of ``shaders/cube_lookup.frag`` (which does the same per pixel on the
    GPU; keep the two in step), also used for the few uncertain points' PCF.

    Bias: ``CUBE_BIAS_TEXELS`` texel widths plus the receiver's own depth change over
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


def _cube_pair_visibility(
    pair: tuple[_CubeMap | None, _CubeMap | None],
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
            v, u = _cube_visibility(cube, rel, normals, filtered)
            # Uncertain in one map matters only where the other lets light by.
            u_all = (u_all & (v > 0)) | (u & (v_all > 0))
            v_all *= v
    return v_all, u_all


def _cube_pcf(cube: _CubeMap, base, fx, fy, test) -> np.ndarray:
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


def _transform(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(n, k) = v (n, 3) times m (k, 3) transposed, i.e. each row of v mapped by m.

    An einsum instead of ``v @ m.T``: numpy hands such skinny products to the
    multithreaded BLAS, which on this 2-core machine, next to llvmpipe's render threads,
    was seen to take up to 12 ms for 76 800 rows (einsum's own loop: ~1 ms)."""
    return np.einsum("ij,kj->ik", v, m)


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


def _filtered_visibility(
    mp: _ShadowMap, rel: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Visibility of points ``rel`` (n, 3) (rel metres) with ``normals`` (n, 3) against
    one map: slope-scaled bias, bilinear 2x2 PCF. Points outside the map's footprint
    are lit (none of its casters is above them).

    Returns (n,) float64 visibility in [0, 1] and (n,) bool *uncertain* (see
    ``_ShadowMap.depth_min``)."""
    s = mp.depth.shape[0]
    lp = _transform(rel, mp.light_from_rel)
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
    n_z = _transform(np.take(normals, inside, axis=0), mp.light_from_rel[2:3])[:, 0]
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


@dataclass
class LightTerms:
    """What shading G-buffer points needs from the shadow maps (``Rasterizer.light_terms``,
    consumed by ``shading.shade_local``). n points, D DistantLights.

    distant_visibility : (n, D) float32 in [0, 1]: DistantLight visibility of the pairs
                         *not* in ``lit_sums`` (0 for the pairs summed there)
    lit_sums           : diffuse (n, 3) and highlight (n, 3) float32 sums over the
                         (point, light) pairs the maps decided are lit, shaded on the GPU
                         (LocalLights and up to LOOKUP_MAX_DISTANT DistantLights)
    local_pairs        : the (point, LocalLight) pairs the maps could not decide, with
                         their visibility from shadow rays or PCF (lit ones only), or
                         None
    """

    distant_visibility: np.ndarray
    lit_sums: tuple[np.ndarray, np.ndarray] | None
    local_pairs: LightPairs | None


class Rasterizer:
    """Rasterizes a ``Scene`` into ``GBuffer`` s (one OpenGL context per instance).

    Usage::

        r = Rasterizer(scene, 320, 240)
        g = r.render(camera_frame)                 # GBuffer, every field filled
        vis = r.shadow_visibility(points, normals)  # (n, len(scene.lights.distant))
        r.update_geometry(scene)                   # after animated prims moved
        r.close()
    """

    def __init__(self, scene: Scene, width: int, height: int) -> None:
        if width <= 0 or height <= 0:
            raise PhrtError(f"image size {width}x{height} must be positive")
        self.width = int(width)
        self.height = int(height)
        self._scene = scene
        self._origin = np.asarray(scene.origin, dtype=np.float64).copy()
        self._platform = OSMesaPlatform(self.width, self.height)
        self._platform.init_context()
        self._platform.make_current()
        self._renderer = pyrender.Renderer(self.width, self.height)
        self._renderer._program_cache = _ProgramCache(shader_dir=SHADER_DIR)
        self._create_framebuffers()
        # Our single-sampled framebuffer replaces pyrender's multisampled one.
        self._renderer._configure_main_framebuffer = lambda: None
        self._renderer._read_main_framebuffer = lambda _scene, _flags: self._read_ids()
        self._ids = np.zeros((self.height, self.width, 4), dtype=np.uint8)  # readback
        self._pcamera = _ExactPerspective()
        self._pscene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0])
        self._cam_node = self._pscene.add(self._pcamera, pose=np.eye(4))
        self._mesh_node = None
        self._uploaded: np.ndarray | None = None  # (V, 3) float32 rel, as on the GPU
        self._dirs_key: tuple | None = None
        self._dirs_grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._static_maps: list[_ShadowMap | None] | None = None
        self._dynamic_maps: list[_ShadowMap | None] | None = None
        self._batches: dict[str, tuple[int, int, int]] = {}  # name → (vao, ebo, count)
        self._map_dirs: list[np.ndarray] = []
        self.last_refined = 0  # points handed to shadow_visibility's refine last call
        self.last_refined_pairs = 0  # (point, light) pairs among them
        self.last_cube_build_seconds = 0.0
        self._cube_keys: list[tuple] = []  # per LocalLight: (rel position, range)
        self._cube_static: list[_CubeMap | None] = []
        self._cube_dynamic: list[_CubeMap | None] = []
        self._cube_fresh: list[tuple[bool, bool]] = []  # (static, animated) map valid
        # GPU lookup pass (``_cube_lookup``): program, empty VAO, cube texture array and
        # the cube objects it holds (by layer block), point textures, output framebuffer.
        self._lookup_programs: dict[tuple[int, int, bool, bool], int] = {}
        self._dmap_tex: list[int] = []  # DistantLight map textures (``_upload_distant``)
        self._dmap_held: list[_ShadowMap | None] = []
        self._lookup_vao: int | None = None
        self._cube_tex: int | None = None
        self._cube_tex_layers = 0
        self._cube_tex_held: list[_CubeMap | None] = []
        self._point_tex: list[int] = []
        self._lookup_fb: int | None = None
        self._lookup_rb: list[int] = []
        self._lookup_rows = 0
        #: LocalLight cube lookups on the GPU (False: the numpy reference, same answers
        #: up to float32 rounding at the test's boundaries).
        self.cube_lookup_on_gpu = True
        self._pool = ThreadPoolExecutor(DERIVE_THREADS, thread_name_prefix="phrt-gbuffer")
        self._closed = False
        _OPEN.add(self)
        try:
            self._upload(scene)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ geometry upload

    def _upload(self, scene: Scene) -> None:
        """Build the single mesh node and all per-triangle tables (rel space)."""
        geo = scene.geometry
        if geo.triangle_count >= 2**32 - 1:
            raise PhrtError(f"{geo.triangle_count} triangles exceed the id encoding")
        rel = geo.vertices - self._origin
        self._uploaded = np.ascontiguousarray(rel, dtype=np.float32)
        self._triangles = np.array(geo.triangles, dtype=np.int64)
        self._delete_shadow_batches()
        if self._mesh_node is not None:
            self._pscene.remove_node(self._mesh_node)
            self._mesh_node = None
        if geo.triangle_count > 0:
            material = pyrender.MetallicRoughnessMaterial(doubleSided=True)
            prim = pyrender.Primitive(
                positions=self._uploaded,
                indices=np.ascontiguousarray(geo.triangles, dtype=np.uint32),
                material=material,
            )
            self._mesh_node = self._pscene.add(pyrender.Mesh([prim]))
            self._primitive = prim
        n = geo.triangle_count
        self._tri64 = np.zeros((n, 13))
        self._tri32 = np.zeros((n, 3, 6), dtype=np.float32)
        self._fill_tables(scene, np.arange(n))
        self._scene_changed(scene)
        self._static_maps = self._dynamic_maps = None
        self._invalidate_cubes(static=True, dynamic=True)

    def _fill_tables(self, scene: Scene, rows: np.ndarray) -> None:
        """Recompute the per-triangle tables of triangles ``rows``; packed so that each
        frame does one gather per table.

        _tri64 : (T, 13) float64, rel space. Columns: g1 (3), c1, g2 (3), c2, n_g (3),
                 h, |n_g|. n_g = e1 x e2 (unnormalised geometric normal, e1 = b - a,
                 e2 = c - a), h = n_g·a. For a point p on the plane, the barycentric
                 weights of b and c are v = p·g1 - c1 and w = p·g2 - c2 (g1, g2: the dual
                 basis of e1, e2 within the plane).
        _tri32 : (T, 3, 6) float32, per corner its normal then its albedo
                 (``Geometry.corner_normals`` / ``corner_albedo``), so that one
                 weighted sum over the corners interpolates both.
        """
        geo = scene.geometry
        tri = geo.vertices[geo.triangles[rows]] - self._origin
        a = tri[:, 0]
        e1 = tri[:, 1] - a
        e2 = tri[:, 2] - a
        ng = np.cross(e1, e2)
        d00 = np.einsum("ij,ij->i", e1, e1)
        d01 = np.einsum("ij,ij->i", e1, e2)
        d11 = np.einsum("ij,ij->i", e2, e2)
        den = d00 * d11 - d01**2
        # Degenerate (zero-area) triangles never cover a pixel; guard the division anyway.
        inv = np.where(den > 0.0, 1.0 / np.where(den > 0.0, den, 1.0), 0.0)[:, None]
        g1 = (d11[:, None] * e1 - d01[:, None] * e2) * inv
        g2 = (d00[:, None] * e2 - d01[:, None] * e1) * inv
        self._tri64[rows] = np.concatenate(
            [
                g1,
                np.einsum("ij,ij->i", a, g1)[:, None],
                g2,
                np.einsum("ij,ij->i", a, g2)[:, None],
                ng,
                np.einsum("ij,ij->i", a, ng)[:, None],
                np.linalg.norm(ng, axis=1)[:, None],
            ],
            axis=1,
        )
        self._tri32[rows] = np.concatenate(
            [geo.corner_normals[rows], geo.corner_albedo[rows]], axis=2
        )

    def _scene_changed(self, scene: Scene) -> None:
        """Refresh what depends on the whole scene: bounds, texture flags, the
        static / animated triangle split used by the shadow maps.

        _tri_textured : (T,) bool, True where the material has a texture and uvs exist.
        _animated_tri : (T,) bool, triangles of ``Element.animated`` elements.
        """
        geo = scene.geometry
        textures = scene.materials.textures
        has_tex = np.array([t is not None for t in textures] + [False], dtype=bool)
        mat = np.where(
            (geo.tri_material >= 0) & (geo.tri_material < len(textures)),
            geo.tri_material,
            len(textures),
        )
        self._tri_textured = has_tex[mat] & (geo.corner_uv is not None)
        flags = np.array([e.animated for e in scene.elements] + [False], dtype=bool)
        el = np.where(
            (geo.tri_element >= 0) & (geo.tri_element < len(scene.elements)),
            geo.tri_element,
            len(scene.elements),
        )
        self._animated_tri = flags[el]
        rel = self._uploaded
        static_vertices = np.unique(self._triangles[~self._animated_tri])
        if len(static_vertices):
            sv = rel[static_vertices]
            self._static_bounds = np.stack([sv.min(axis=0), sv.max(axis=0)]).astype(np.float64)
        else:
            self._static_bounds = None
        self._animated_vertices = np.unique(self._triangles[self._animated_tri])
        self._update_bounds()
        self._scene = scene

    def _update_bounds(self) -> None:
        """_bounds_rel (2, 3) float64: rel bounds of all triangle vertices (static part
        cached, animated part recomputed); _extent: their diagonal in metres (> 0)."""
        boxes = [] if self._static_bounds is None else [self._static_bounds]
        if len(self._animated_vertices):
            av = self._uploaded[self._animated_vertices]
            boxes.append(np.stack([av.min(axis=0), av.max(axis=0)]).astype(np.float64))
        if boxes:
            lo = np.min([b[0] for b in boxes], axis=0)
            hi = np.max([b[1] for b in boxes], axis=0)
        else:
            lo = hi = np.zeros(3)
        self._bounds_rel = np.stack([lo, hi])
        self._extent = float(max(np.linalg.norm(hi - lo), 1e-12))

    def update_geometry(self, scene: Scene) -> None:
        """Re-upload geometry after animated prims moved.

        Same topology and origin: only the changed vertex range is re-sent
        (``glBufferSubData``) and only the changed triangles' tables are recomputed;
        otherwise the node is rebuilt. The animated-geometry shadow maps are invalidated,
        the static ones only if a non-animated triangle changed.
        """
        self._check_open()
        self._platform.make_current()
        geo = scene.geometry
        same_topology = (
            self._mesh_node is not None
            and np.array_equal(np.asarray(scene.origin, dtype=np.float64), self._origin)
            and geo.vertices.shape == self._uploaded.shape
            and np.array_equal(geo.triangles, self._triangles)
            and len(scene.elements) == len(self._scene.elements)
        )
        if not same_topology:
            self._origin = np.asarray(scene.origin, dtype=np.float64).copy()
            self._upload(scene)
            return
        rel = np.ascontiguousarray(geo.vertices - self._origin, dtype=np.float32)
        changed = np.unique(np.flatnonzero(rel.reshape(-1) != self._uploaded.reshape(-1)) // 3)
        moved = np.zeros(len(rel), dtype=bool)
        moved[changed] = True
        if len(changed):
            first, last = int(changed[0]), int(changed[-1]) + 1
            self._uploaded = rel
            if self._primitive._vaid is not None:  # already on the GPU
                chunk = np.ascontiguousarray(rel[first:last])
                GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
                GL.glBufferSubData(GL.GL_ARRAY_BUFFER, first * 12, chunk.nbytes, chunk)
                GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
            self._primitive.positions = rel  # keeps pyrender's copy consistent
        tri_moved = (
            moved[self._triangles].any(axis=1)
            if len(changed)
            else np.zeros(len(self._triangles), dtype=bool)
        )
        # Shading (normals, albedo) is re-read for moved and animated triangles only:
        # other elements' shading is static (materials are not animated).
        check = np.flatnonzero(tri_moved | self._animated_tri)
        if len(check):
            shading = np.concatenate([geo.corner_normals[check], geo.corner_albedo[check]], axis=2)
            differs = np.any(shading != self._tri32[check], axis=(1, 2))
            rows = check[tri_moved[check] | differs]
            if len(rows):
                self._fill_tables(scene, rows)
        self._scene = scene
        if len(changed):
            self._update_bounds()
        if np.any(tri_moved & ~self._animated_tri):
            self._static_maps = None
            self._static_bounds_stale()
            self._invalidate_cubes(static=True, dynamic=False)
        if np.any(tri_moved & self._animated_tri):
            self._dynamic_maps = None
            self._invalidate_cubes(static=False, dynamic=True)

    def _static_bounds_stale(self) -> None:
        """A non-animated vertex moved (the caller animated a prim not flagged as
        such): recompute the cached static bounds."""
        static_vertices = np.unique(self._triangles[~self._animated_tri])
        sv = self._uploaded[static_vertices]
        self._static_bounds = np.stack([sv.min(axis=0), sv.max(axis=0)]).astype(np.float64)
        self._update_bounds()

    # ------------------------------------------------------------------ framebuffers

    def _create_framebuffers(self) -> None:
        """Single-sampled id framebuffer (RGBA8 + float depth) at the image size, and a
        depth-only framebuffer for shadow maps."""
        self._id_rb = GL.glGenRenderbuffers(2)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._id_rb[0])
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, self.width, self.height)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._id_rb[1])
        GL.glRenderbufferStorage(
            GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, self.width, self.height
        )
        self._id_fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._id_fb)
        GL.glFramebufferRenderbuffer(
            GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._id_rb[0]
        )
        GL.glFramebufferRenderbuffer(
            GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._id_rb[1]
        )
        self._check_fb("id")
        r = self._renderer
        r._main_fb = r._main_fb_ms = self._id_fb
        r._main_fb_dims = (self.width, self.height)

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
        self._check_fb("shadow")
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)

    @staticmethod
    def _check_fb(name: str) -> None:
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"OpenGL {name} framebuffer incomplete (status {status:#x})")

    def _read_ids(self) -> np.ndarray:
        """(H, W) uint32 id image (triangle index + 1, 0 = background), row 0 at top."""
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._id_fb)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glReadPixels(0, 0, self.width, self.height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, self._ids)
        # Four bytes R, G, B, A read as one little-endian uint32 = R + 256 G + ...
        ids = self._ids.view("<u4")[..., 0]
        return ids[::-1].astype(np.uint32)

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
        lo, hi = self._bounds_rel
        pad = CLIP_PADDING * self._extent
        nearest = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - eye_rel, eye_rel - hi))))
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
        farthest = float(np.linalg.norm(corners.reshape(-1, 3) - eye_rel, axis=1).max())
        tx, ty = camera.tan_half_fov(self.width, self.height)
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
        tx, ty = camera.tan_half_fov(self.width, self.height)
        key = (tx, ty)
        if key != self._dirs_key:
            xs = ((np.arange(self.width) + 0.5) / self.width * 2.0 - 1.0) * tx
            ys = (1.0 - (np.arange(self.height) + 0.5) / self.height * 2.0) * ty
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
        self._check_open()
        h, w = self.height, self.width
        cam = np.asarray(camera.world_from_camera, dtype=np.float64)
        rot = cam[:3, :3]
        eye_rel = cam[:3, 3] - self._origin
        tx, ty = camera.tan_half_fov(w, h)
        if not (np.isfinite(tx) and np.isfinite(ty) and tx > 0.0 and ty > 0.0):
            raise PhrtError(
                f"camera: focal length {camera.focal_length} and horizontal aperture "
                f"{camera.horizontal_aperture} give no field of view"
            )
        clip = self._clip_range(camera, eye_rel) if self._mesh_node is not None else None
        if clip is not None:
            near, far = clip
            pose = cam.copy()
            pose[:3, 3] = eye_rel
            self._pcamera.matrix = perspective_matrix(tx, ty, near, far)
            self._pcamera.znear, self._pcamera.zfar = near, far
            self._pscene.set_pose(self._cam_node, pose)
            self._platform.make_current()
            flags = RenderFlags.FLAT | RenderFlags.OFFSCREEN | RenderFlags.SKIP_CULL_FACES
            ids = self._renderer.render(self._pscene, flags).reshape(-1)
        else:  # no geometry, or none inside the camera's clipping range
            near, far = 0.0, 0.0
            ids = np.zeros(h * w, dtype=np.uint32)

        # Directions: rotate the cached unit camera-space rays (as pixel_rays does; a
        # camera transform with scale or shear needs the normalisation again).
        d = self._world_dirs(camera, rot)
        if not np.allclose(rot.T @ rot, np.eye(3), rtol=0.0, atol=1e-12):
            d /= np.linalg.norm(d, axis=1, keepdims=True)

        covered = np.flatnonzero((ids > 0) & (ids <= len(self._tri64)))
        tid = ids[covered].astype(np.int64) - 1

        triangle_id = np.full(h * w, NO_HIT, dtype=np.int32)
        element_id = np.full(h * w, NO_HIT, dtype=np.int32)
        depth = np.full(h * w, np.inf, dtype=np.float32)
        position = np.zeros((h * w, 3), dtype=np.float64)
        view_dir = d.astype(np.float32)
        normal = -view_dir
        albedo = np.zeros((h * w, 3), dtype=np.float32)

        out = _Outputs(triangle_id, element_id, depth, position, normal, albedo)
        fwd = -rot[:, 2] / np.linalg.norm(rot[:, 2])
        chunks = [c for c in np.array_split(np.arange(len(covered)), DERIVE_THREADS) if len(c)]
        jobs = [
            self._pool.submit(self._derive, covered[c], tid[c], d, eye_rel, near, far, fwd, out)
            for c in chunks
        ]
        for job in jobs:
            job.result()  # re-raises a worker's exception here

        return GBuffer(
            element_id=element_id.reshape(h, w),
            triangle_id=triangle_id.reshape(h, w),
            depth=depth.reshape(h, w),
            position=position.reshape(h, w, 3),
            normal=normal.reshape(h, w, 3),
            albedo=albedo.reshape(h, w, 3),
            view_dir=view_dir.reshape(h, w, 3),
        )

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
        tab = np.take(self._tri64, tid, axis=0)  # (n, 13), see _fill_tables
        ng = tab[:, 8:11]
        # Ray-plane intersection in float64, rel space: t = (h - n·o) / n·d.
        den = np.einsum("ij,ij->i", ng, dc)
        floor = GRAZING_EPS * tab[:, 12]
        den = np.where(np.abs(den) < floor, np.where(den < 0, -floor, floor), den)
        den[den == 0.0] = 1.0  # zero-area triangle: t is clamped just below
        t = np.clip((tab[:, 11] - _transform(ng, eye_rel[None])[:, 0]) / den, near, far)
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

        # (n, 6): interpolated normal then albedo (corners (n, 3, 6), see _fill_tables).
        values = np.einsum("ij,ijk->ik", bary, np.take(self._tri32, tid, axis=0))
        n = values[:, :3]
        col = values[:, 3:]

        # Shading normal on the camera's side of the triangle; where it still faces
        # away (or is degenerate), use the geometric normal.
        side = np.where(den > 0.0, -1.0, 1.0)  # n_g·d > 0: the back face is seen
        n *= side[:, None].astype(np.float32)
        n_len = np.sqrt(np.einsum("ij,ij->i", n, n))
        bad = (n_len < 1e-6) | (np.einsum("ij,ij->i", n, dc) >= 0.0)
        n /= np.maximum(n_len, 1e-6)[:, None]
        if bad.any():
            g = ng[bad] * (side[bad] / np.maximum(tab[bad, 12], 1e-300))[:, None]
            n[bad] = g.astype(np.float32)

        textured = self._tri_textured[tid]
        if textured.any():
            col[textured] = self._texture_albedo(tid[textured], bary[textured])
        # Sorted pixel indices without gaps (every pixel of an enclosed view is covered):
        # slice writes, much faster than scattering.
        if covered[-1] - covered[0] + 1 == len(covered):
            covered = slice(int(covered[0]), int(covered[-1]) + 1)
        out.normal[covered] = n
        out.albedo[covered] = col
        out.triangle_id[covered] = tid
        out.element_id[covered] = np.take(geo.tri_element, tid)
        out.position[covered] = p_rel + self._origin
        out.depth[covered] = t * _transform(dc, fwd[None])[:, 0]

    def _texture_albedo(self, tid: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(n, 3) float32 linear RGB for pixels on textured triangles: bilinear, wrapping
        lookup of the material's texture at the interpolated uv (image row 0 = top, so
        v = 0 is the bottom row: the USD ``st`` convention).

        tid : (n,) triangle ids, all textured; bary : (n, 3) float32 weights.
        """
        geo = self._scene.geometry
        textures = self._scene.materials.textures
        uv = (bary[:, :, None] * geo.corner_uv[tid]).sum(axis=1)
        mats = geo.tri_material[tid]
        out = np.zeros((len(tid), 3), dtype=np.float32)
        for m in np.unique(mats):  # loop over the few textured materials in view
            sel = mats == m
            out[sel] = sample_bilinear_wrap(textures[m], uv[sel])
        return out

    # ------------------------------------------------------------------ shadows

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

    def _batch(self, name: str) -> tuple[int, int, int]:
        """(vao, ebo, index count) drawing the static (``name == "static"``) or animated
        triangles from the mesh's own vertex buffer, for the shadow-map passes.

        pyrender's VAO draws every triangle; these VAOs share its vertex buffer (so
        ``update_geometry`` uploads reach them) with their own index buffers."""
        if name not in self._batches:
            r = self._renderer
            r._update_context(self._pscene, RenderFlags.FLAT)  # vertex buffer on the GPU
            mask = self._animated_tri if name == "dynamic" else ~self._animated_tri
            idx = np.ascontiguousarray(self._triangles[mask], dtype=np.uint32)
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

    def _delete_shadow_batches(self) -> None:
        if self._batches:
            self._platform.make_current()
            for vao, ebo, _ in self._batches.values():
                GL.glDeleteVertexArrays(1, [vao])
                GL.glDeleteBuffers(1, [ebo])
        self._batches = {}

    def _depth_render(self, clip_from_rel: np.ndarray, name: str, size: int) -> np.ndarray:
        """Depth-only render of batch ``name`` ("static" / "dynamic") through the (4, 4)
        ``clip_from_rel`` matrix, ``size`` texels square. Returns (size, size) float32
        window depth in [0, 1] (1 = no caster), row 0 at the bottom (OpenGL order)."""
        self._platform.make_current()
        vao, _, count = self._batch(name)
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
        program = self._renderer._program_cache.get_program("depth.vert", "depth.frag")
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

    def _render_shadow_map(self, frame: np.ndarray, name: str, size: int) -> _ShadowMap | None:
        """Orthographic depth map of batch ``name`` ("static" / "dynamic") along -z of
        the light ``frame`` (3, 3), ``size`` texels square, covering exactly that
        batch's casters (plus a margin). None when the batch is empty."""
        mask = self._animated_tri if name == "dynamic" else ~self._animated_tri
        if self._mesh_node is None or not mask.any():
            return None
        used = np.unique(self._triangles[mask])
        lp = _transform(self._uploaded[used].astype(np.float64), frame)
        # Extents clamped away from 0 (flat casters) so the matrix is invertible.
        min_span = 1e-6 * max(self._extent, 1e-9)
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
        # Texels no caster covered stay at the clear value: nothing there occludes.
        depth_m = np.where(depth01 >= 1.0, np.inf, lo_d + depth01.astype(np.float64) * span_d)
        depth_m = depth_m.astype(np.float32)
        return _ShadowMap(
            light_from_rel=frame,
            lo=lo_xy,
            texel=span_xy / size,
            depth=depth_m,
            depth_min=_box_extremum(depth_m, SHADOW_REFINE_RADIUS, np.minimum),
            depth_max=_box_extremum(depth_m, SHADOW_REFINE_RADIUS, np.maximum),
        )

    def shadow_maps(self) -> list[tuple[_ShadowMap | None, _ShadowMap | None]]:
        """(static map, animated-geometry map) per DistantLight, either None when it has
        no casters. Static maps are rendered once (again only if static geometry or the
        lights changed); animated maps again after ``update_geometry`` moved animated
        prims, at the static map's texel size over the animated casters only."""
        self._check_open()
        dirs = [np.asarray(lt.direction, dtype=np.float64) for lt in self._scene.lights.distant]
        if self._static_maps is not None and (
            len(dirs) != len(self._map_dirs)
            or any(not np.array_equal(a, b) for a, b in zip(dirs, self._map_dirs, strict=False))
        ):
            self._static_maps = self._dynamic_maps = None
        self._map_dirs = dirs
        frames = [self._light_frame(d) for d in dirs]
        if self._static_maps is None:
            self._static_maps = [
                self._render_shadow_map(f, "static", SHADOW_MAP_SIZE) for f in frames
            ]
        if self._dynamic_maps is None:
            self._dynamic_maps = []
            for f, static in zip(frames, self._static_maps, strict=True):
                texel = (
                    float(static.texel.max())
                    if static is not None
                    else max(self._extent, 1e-9) / SHADOW_MAP_SIZE
                )
                self._dynamic_maps.append(
                    self._render_shadow_map(f, "dynamic", self._dynamic_size(f, texel))
                )
        return list(zip(self._static_maps, self._dynamic_maps, strict=True))

    def _dynamic_size(self, frame: np.ndarray, texel: float) -> int:
        """Texels per side for the animated casters' map: their light-space footprint
        at ``texel`` metres per texel, between MIN_DYNAMIC_MAP_SIZE and SHADOW_MAP_SIZE."""
        if not self._animated_tri.any():
            return MIN_DYNAMIC_MAP_SIZE
        used = np.unique(self._triangles[self._animated_tri])
        lp = _transform(self._uploaded[used].astype(np.float64), frame[:2])
        span = float((lp.max(axis=0) - lp.min(axis=0)).max())
        size = int(np.ceil(span / max(texel, 1e-300))) + 4
        return int(np.clip(size, MIN_DYNAMIC_MAP_SIZE, SHADOW_MAP_SIZE))

    def _render_cube(self, light_rel: np.ndarray, light_range: float, name: str) -> _CubeMap | None:
        """Cube depth map of batch ``name`` ("static" / "dynamic") around the light at
        ``light_rel`` (3,) rel metres, out to ``light_range`` metres (or the farthest
        scene point, if nearer). None when the batch is empty or nothing is in range."""
        mask = self._animated_tri if name == "dynamic" else ~self._animated_tri
        if self._mesh_node is None or not mask.any() or not light_range > 0.0:
            return None
        lo, hi = self._bounds_rel
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
        farthest = float(np.linalg.norm(corners.reshape(-1, 3) - light_rel, axis=1).max())
        far = min(float(light_range), farthest + CLIP_PADDING * self._extent)
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
        return _CubeMap(
            np.asarray(light_rel, np.float64).copy(),
            near,
            far,
            tan_half,
            depth,
            depth_min,
            depth_max,
        )

    def cube_maps(self) -> list[tuple[_CubeMap | None, _CubeMap | None]]:
        """(static map, animated-geometry map) per LocalLight (cube maps, see
        ``_CubeMap``), either None when it has no casters. Rendered when first needed
        and again only for a light that moved or changed range, for static geometry
        that moved (static maps) or after ``update_geometry`` moved animated prims
        (animated maps). ``last_cube_build_seconds``: time the latest call spent
        rendering cube maps."""
        self._check_open()
        start = time.perf_counter()
        lights = self._scene.lights
        ranges = light_ranges(lights)[len(lights.distant) :]
        keys = [
            (tuple(np.asarray(li.position, np.float64) - self._origin), float(r))
            for li, r in zip(lights.local, ranges, strict=True)
        ]
        if len(keys) != len(self._cube_keys):
            self._cube_static = [None] * len(keys)
            self._cube_dynamic = [None] * len(keys)
            self._cube_fresh = [(False, False)] * len(keys)
        for i, key in enumerate(keys):
            static_ok, dynamic_ok = self._cube_fresh[i]
            if i < len(self._cube_keys) and self._cube_keys[i] != key:
                static_ok = dynamic_ok = False
            light_rel = np.array(key[0])
            if not static_ok:
                self._cube_static[i] = self._render_cube(light_rel, key[1], "static")
            if not dynamic_ok:
                self._cube_dynamic[i] = self._render_cube(light_rel, key[1], "dynamic")
            self._cube_fresh[i] = (True, True)
        self._cube_keys = keys
        self.last_cube_build_seconds = time.perf_counter() - start
        return list(zip(self._cube_static, self._cube_dynamic, strict=True))

    def _invalidate_cubes(self, static: bool, dynamic: bool) -> None:
        self._cube_fresh = [
            (ok_s and not static, ok_d and not dynamic) for ok_s, ok_d in self._cube_fresh
        ]

    def _local_visibility(
        self,
        rel: np.ndarray,
        normals: np.ndarray,
        cubes: list[tuple[_CubeMap | None, _CubeMap | None]],
        ranges: np.ndarray,
        filtered: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(n, len(cubes)) float32 visibility and bool uncertain of points ``rel`` (n, 3)
        (rel metres) with ``normals`` (n, 3) for every LocalLight: 0 outside its range
        ``ranges`` (len(cubes),) or facing away; uncertain pairs get PCF (``filtered``)
        or 0.5. The bulk runs on the GPU (``cube_lookup_on_gpu``), else in numpy."""
        n = len(rel)
        vis = np.zeros((n, len(cubes)), dtype=np.float32)
        unsure = np.zeros((n, len(cubes)), dtype=bool)
        if self.cube_lookup_on_gpu:
            codes = self._cube_lookup(rel, normals, cubes, ranges)
            np.equal(codes, LOOKUP_LIT, out=vis, casting="unsafe")
            np.equal(codes, LOOKUP_UNCERTAIN, out=unsure)
            if not filtered:  # the caller resolves the uncertain pairs itself
                vis[unsure] = 0.5
                return vis, unsure
        for k, pair in enumerate(cubes):
            if self.cube_lookup_on_gpu:
                idx = np.flatnonzero(unsure[:, k])  # only these need more work
                if len(idx) == 0:
                    continue
            else:
                to_light = np.asarray(self._cube_keys[k][0]) - rel
                reach = np.einsum("ij,ij->i", to_light, to_light) < ranges[k] ** 2
                reach &= np.einsum("ij,ij->i", normals, to_light) > 0.0
                idx = np.flatnonzero(reach)
            vis[idx, k], unsure[idx, k] = _cube_pair_visibility(
                pair, rel[idx], normals[idx], filtered
            )
        return vis, unsure

    def light_terms(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        to_eye: np.ndarray,
        refine: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> LightTerms:
        """The shadow-mapped lighting of points, for ``shading.shade_local``: as
        ``shadow_visibility`` (same maps, same ``refine`` contract), but the (point,
        light) pairs the maps decide are lit, for every LocalLight and up to
        LOOKUP_MAX_DISTANT DistantLights, are also *shaded* on the GPU in the lookup pass
        (``shaders/cube_lookup.frag``): no (n, L) visibility matrix and no numpy shading
        of them; only the undecided pairs are resolved (``refine``, else PCF) and
        returned. Requires ``cube_lookup_on_gpu``.

        positions : (n, 3) float64 world metres; normals : (n, 3) unit, facing the
        viewer; to_eye : (n, 3) unit directions from the points to the viewer.
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        lights = self._scene.lights
        n, n_distant = len(positions), len(lights.distant)
        distant = np.ones((n, n_distant), dtype=np.float32)
        distant_unsure = np.zeros((n, n_distant), dtype=bool)
        self.last_refined = self.last_refined_pairs = 0
        if n == 0 or not lights.has_direct:
            return LightTerms(distant, None, None)
        rel = positions - self._origin
        # Up to LOOKUP_MAX_DISTANT DistantLights are looked up and shaded on the GPU
        # too; more are looked up in numpy meanwhile (and shaded by shade_local).
        gpu_distant = n_distant <= LOOKUP_MAX_DISTANT
        maps = self.shadow_maps() if gpu_distant and n_distant else []
        jobs = [] if gpu_distant else self._distant_lookups(rel, normals, distant, distant_unsure)
        cubes = self.cube_maps() if lights.local else []
        ranges = light_ranges(lights)[n_distant:]
        diffuse, highlight, bits = self._cube_lookup(rel, normals, cubes, ranges, to_eye, maps)
        for job in jobs:
            job.result()
        if maps:
            # Lit pairs are in the sums already: ``distant`` keeps only what shade_local
            # must still add, the uncertain pairs once resolved below.
            distant[:] = 0.0
            shifts = 16 + np.arange(n_distant, dtype=np.uint32)
            distant_unsure = (bits[:, :1] >> shifts) & 1 > 0
        # The pairs the maps could not decide, on the few rows that have any: the
        # LocalLight ones are shaded from their visibility (exact from ``refine``, else
        # the maps' PCF), the DistantLight ones are corrected in ``distant``.
        unsure_rows = bits.any(axis=1)
        if n_distant:
            unsure_rows |= distant_unsure.any(axis=1)
        rows = np.flatnonzero(unsure_rows)
        local_unsure = np.zeros((len(rows), len(cubes)), dtype=bool)
        for p, start in enumerate(range(0, len(cubes), LOOKUP_LIGHTS_PER_PASS)):
            count = min(LOOKUP_LIGHTS_PER_PASS, len(cubes) - start)
            shifts = np.arange(count, dtype=np.uint32)
            local_unsure[:, start : start + count] = (bits[rows, p, None] >> shifts) & 1 > 0
        if maps and refine is None:  # the uncertain DistantLight pairs: the maps' PCF
            for k, pair in enumerate(maps):
                on = np.flatnonzero(distant_unsure[:, k])
                distant[on, k] = 1.0
                for mp in pair:
                    if mp is not None and len(on):
                        distant[on, k] *= _filtered_visibility(mp, rel[on], normals[on])[0]
        at, light = np.nonzero(local_unsure)
        point = rows[at]
        if refine is not None and len(rows):
            pairs = np.concatenate([distant_unsure[rows], local_unsure], axis=1)
            exact = np.asarray(
                refine(positions[rows], normals[rows], pairs), dtype=np.float32
            ).reshape(pairs.shape)
            distant[rows] = np.where(pairs[:, :n_distant], exact[:, :n_distant], distant[rows])
            weight = exact[:, n_distant:][at, light]
            self.last_refined = len(rows)
            self.last_refined_pairs = int(pairs.sum())
        else:
            weight = np.zeros(len(point), dtype=np.float32)
            for k, pair in enumerate(cubes):
                on = np.flatnonzero(light == k)
                if len(on):
                    p = point[on]
                    weight[on] = _cube_pair_visibility(pair, rel[p], normals[p], True)[0]
        lit = np.flatnonzero(weight > 0.0)
        point, light, weight = point[lit], light[lit], weight[lit]
        l_dir, dist = pair_directions(lights, positions, point, light)
        return LightTerms(
            distant, (diffuse, highlight), LightPairs(point, light, l_dir, dist, weight)
        )

    def _distant_lookups(
        self, rel: np.ndarray, normals: np.ndarray, out: np.ndarray, uncertain: np.ndarray
    ) -> list:
        """Start the DistantLights' shadow-map lookups of points ``rel`` (n, 3) rel
        metres on the worker threads: they multiply into ``out`` (n, D) and flag
        ``uncertain`` (n, D). Returns the futures (empty without DistantLights)."""
        maps = self.shadow_maps() if len(self._scene.lights.distant) else []
        if not maps:
            return []

        def lookup(part: slice) -> None:  # one chunk of points, all maps (disjoint rows)
            r, nr = rel[part], normals[part]
            for k, pair in enumerate(maps):
                for mp in pair:
                    if mp is not None:
                        vis, unsure = _filtered_visibility(mp, r, nr)
                        out[part, k] *= vis
                        uncertain[part, k] |= unsure

        bounds = np.linspace(0, len(rel), DERIVE_THREADS + 1).astype(int)
        return [
            self._pool.submit(lookup, slice(a, b))
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
            if b > a
        ]

    def _refined(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        vis: np.ndarray,
        uncertain: np.ndarray,
        refine: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None,
    ) -> np.ndarray:
        """``vis`` (n, L) with its ``uncertain`` (n, L) pairs replaced by ``refine``'s
        answer (in place; unchanged without ``refine``). Sets ``last_refined`` (points)
        and ``last_refined_pairs``."""
        if refine is None or not uncertain.any():
            return vis
        idx = np.flatnonzero(uncertain.any(axis=1))
        pairs = uncertain[idx]
        exact = np.asarray(refine(positions[idx], normals[idx], pairs), dtype=np.float32)
        sub = vis[idx]
        sub[pairs] = exact.reshape(pairs.shape)[pairs]
        vis[idx] = sub
        self.last_refined = len(idx)
        self.last_refined_pairs = int(pairs.sum())
        return vis

    def shadow_visibility(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        refine: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> np.ndarray:
        """Fraction of every light reaching each point, by shadow mapping.

        positions : (n, 3) float64 world metres
        normals   : (n, 3) unit shading normals facing the viewer (for DistantLights
                    only |n·L| is used, for the bias; LocalLights also skip points
                    facing away)
        refine    : optional exact shadow test, ``refine(positions (m, 3), normals
                    (m, 3), pairs (m, L) bool) -> (m, L)`` visibility (e.g. Embree
                    shadow rays), needed only at ``pairs``. It is called once, on the
                    points with *uncertain* (point, light) pairs (shadow edges and
                    casters thinner than a texel, where a map's answer is unreliable),
                    and its answer replaces the maps' at those pairs.
        Returns (n, L) float32 in [0, 1], 1 = lit, L = len(distant) + len(local) in that
        order (``shading``'s light order). DistantLights: the product of the static and
        the animated casters' filtered orthographic maps. LocalLights: cube maps, looked
        up only for points within the light's range (``shading.light_ranges``) and
        facing it; other pairs get 0 (the light contributes nothing there).
        ``last_refined`` holds how many points were handed to ``refine``,
        ``last_refined_pairs`` how many (point, light) pairs.
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        lights = self._scene.lights
        n_distant = len(lights.distant)
        cubes = self.cube_maps() if lights.local else []
        n_lights = n_distant + len(cubes)
        self.last_refined = self.last_refined_pairs = 0
        if len(positions) == 0 or n_lights == 0:
            return np.ones((len(positions), n_lights), dtype=np.float32)
        rel = positions - self._origin
        if n_distant:  # else the LocalLight lookup's own arrays are used (see below)
            out = np.ones((len(positions), n_lights), dtype=np.float32)
            uncertain = np.zeros(out.shape, dtype=bool)
            # The DistantLight columns are filled in place (views, disjoint from the
            # LocalLight columns written below on this thread).
            jobs = self._distant_lookups(rel, normals, out[:, :n_distant], uncertain[:, :n_distant])
        else:
            jobs = []
        ranges = light_ranges(lights)
        if cubes:  # meanwhile, on this thread (the GL context's)
            local_vis, local_unsure = self._local_visibility(
                rel, normals, cubes, ranges[n_distant:], filtered=refine is None
            )
            if n_distant:
                out[:, n_distant:] = local_vis
                uncertain[:, n_distant:] = local_unsure
            else:  # local lights only: the lookup's arrays are the answer (no copies)
                out, uncertain = local_vis, local_unsure
        for job in jobs:
            job.result()
        return self._refined(positions, normals, out, uncertain, refine)

    # ------------------------------------------------------------------ GPU cube lookups

    def _lookup_program_for(self, n_lights: int, n_distant: int, shade: bool) -> int:
        """The lookup program for a pass of ``n_lights`` LocalLights and ``n_distant``
        DistantLights (with shading or not), compiled on first use with the defines
        ``shaders/cube_lookup.frag`` expects."""
        has_dynamic = bool(self._animated_tri.any())
        key = (n_lights, n_distant, has_dynamic, shade)
        if key not in self._lookup_programs:
            with open(os.path.join(SHADER_DIR, "cube_lookup.vert")) as f:
                vert = f.read()
            with open(os.path.join(SHADER_DIR, "cube_lookup.frag")) as f:
                version, frag = f.read().split("\n", 1)
            squarings = np.log2(SHININESS) if SHININESS >= 1.0 else 0.5
            defines = (
                f"#define N_LIGHTS {n_lights}\n#define N_DISTANT {n_distant}\n"
                f"#define HAS_DYNAMIC {int(has_dynamic)}\n"
                f"#define SHADE {int(shade)}\n"
                f"#define SQUARINGS {int(squarings) if squarings % 1 == 0 else -1}\n"
            )
            self._lookup_programs[key] = int(
                gl_shaders.compileProgram(
                    gl_shaders.compileShader(vert, GL.GL_VERTEX_SHADER),
                    gl_shaders.compileShader(f"{version}\n{defines}{frag}", GL.GL_FRAGMENT_SHADER),
                    validate=False,
                )
            )
        return self._lookup_programs[key]

    def _lookup_setup(self) -> None:
        """Create the lookup pass's empty VAO and point textures."""
        if self._lookup_vao is not None:
            return
        self._lookup_vao = int(GL.glGenVertexArrays(1))
        self._point_tex = [int(t) for t in GL.glGenTextures(3)]  # points, normals, to_eye
        for tex in self._point_tex:
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def _upload_cubes(self, cubes: list[tuple[_CubeMap | None, _CubeMap | None]]) -> list[int]:
        """Cube (min, max) texels into the RG32F texture array, re-sending only cubes
        that changed. Layout: static cube of light k at layers 6 k, animated cube at
        6 (L + k) when the scene has animated triangles. Returns the first layer of
        every held cube in that order (static block then animated block), -1 = none."""
        n = len(cubes)
        blocks = [c[0] for c in cubes] + ([c[1] for c in cubes] if self._animated_tri.any() else [])
        layers = 6 * len(blocks)
        size = CUBE_MAP_SIZE
        if self._cube_tex is None or layers != self._cube_tex_layers:
            if self._cube_tex is not None:
                GL.glDeleteTextures(1, [self._cube_tex])
            self._cube_tex = int(GL.glGenTextures(1))
            GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, self._cube_tex)
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
            GL.glTexImage3D(
                GL.GL_TEXTURE_2D_ARRAY,
                0,
                GL.GL_RG32F,
                size,
                size,
                max(layers, 1),
                0,
                GL.GL_RG,
                GL.GL_FLOAT,
                None,
            )
            self._cube_tex_layers = layers
            self._cube_tex_held = [None] * len(blocks)
        GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, self._cube_tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        for b, cube in enumerate(blocks):
            if cube is not None and self._cube_tex_held[b] is not cube:
                for f in range(6):
                    texels = np.ascontiguousarray(
                        np.stack([cube.depth_min[f], cube.depth_max[f]], axis=-1), np.float32
                    )
                    GL.glTexSubImage3D(
                        GL.GL_TEXTURE_2D_ARRAY,
                        0,
                        0,
                        0,
                        6 * b + f,
                        size,
                        size,
                        1,
                        GL.GL_RG,
                        GL.GL_FLOAT,
                        texels,
                    )
            self._cube_tex_held[b] = cube
        GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, 0)
        first = [6 * b if cube is not None else -1 for b, cube in enumerate(blocks)]
        return first[:n] + (first[n:] if len(first) > n else [-1] * n)

    def _upload_distant(self, maps: list[tuple[_ShadowMap | None, _ShadowMap | None]]) -> None:
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
        maps: list[tuple[_ShadowMap | None, _ShadowMap | None]],
        loc: Callable[[str], int],
    ) -> None:
        """Set the lookup program's DistantLight uniforms (``shaders/cube_lookup.frag``)
        for ``maps`` (per light: static, animated), textures on units 4 + 2 k (+ 1)."""
        lights = self._scene.lights.distant
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

    def _lookup_framebuffer(self, rows: int) -> None:
        """The outputs of ``shaders/cube_lookup.frag``, LOOKUP_TEXTURE_WIDTH x >= ``rows``
        each: RGBA32UI packed per-light codes, RGBA32F diffuse sums (+ uncertain bits),
        RGBA32F highlight sums."""
        if self._lookup_fb is not None and rows <= self._lookup_rows:
            return
        if self._lookup_fb is not None:
            GL.glDeleteFramebuffers(1, [self._lookup_fb])
            GL.glDeleteRenderbuffers(len(self._lookup_rb), self._lookup_rb)
        self._lookup_rows = rows
        self._lookup_rb = [int(rb) for rb in GL.glGenRenderbuffers(3)]
        self._lookup_fb = int(GL.glGenFramebuffers(1))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._lookup_fb)
        formats = (GL.GL_RGBA32UI, GL.GL_RGBA32F, GL.GL_RGBA32F)
        for i, (rb, fmt) in enumerate(zip(self._lookup_rb, formats, strict=True)):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rb)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, LOOKUP_TEXTURE_WIDTH, rows)
            GL.glFramebufferRenderbuffer(
                GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + i, GL.GL_RENDERBUFFER, rb
            )
        GL.glDrawBuffers(3, [GL.GL_COLOR_ATTACHMENT0 + i for i in range(3)])
        self._check_fb("cube lookup")
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)

    def _cube_lookup(
        self,
        rel: np.ndarray,
        normals: np.ndarray,
        cubes: list[tuple[_CubeMap | None, _CubeMap | None]],
        ranges: np.ndarray,
        to_eye: np.ndarray | None = None,
        distant: list[tuple[_ShadowMap | None, _ShadowMap | None]] | None = None,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every point against every LocalLight's cube maps on the GPU (the test of
        ``_cube_visibility``, in ``shaders/cube_lookup.frag``).

        rel : (n, 3) float64 rel metres; normals : (n, 3) unit, facing the viewer;
        ranges : (len(cubes),) light ranges in metres.
        Without ``to_eye``: returns (n, len(cubes)) uint8 codes: LOOKUP_LIT,
        LOOKUP_SHADOWED (also out of range / facing away) or LOOKUP_UNCERTAIN.
        With ``to_eye`` (n, 3) unit directions to the viewer: the lit pairs are also
        shaded on the GPU; returns diffuse (n, 3) and highlight (n, 3) float32 sums over
        the lit pairs (``shading.shade_local``'s ``lit_sums``) and (n, passes) uint32
        uncertain pairs (not in the sums): bit j of pass p is LocalLight
        p * LOOKUP_LIGHTS_PER_PASS + j. ``distant`` (with ``to_eye`` only): the
        (static, animated) maps of up to LOOKUP_MAX_DISTANT DistantLights, looked up
        and shaded in the first pass too (uncertain: bit 16 + k of pass 0)."""
        n, n_local = len(rel), len(cubes)
        self._platform.make_current()
        self._lookup_setup()
        first = self._upload_cubes(cubes)
        distant = distant if to_eye is not None and distant else []
        self._upload_distant(distant)
        width = LOOKUP_TEXTURE_WIDTH
        rows = -(-n // width)
        self._lookup_framebuffer(rows)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        shading = to_eye is not None
        # Without shading the to_eye texture is never read for a result: send no data.
        inputs = (rel, normals, to_eye if shading else np.zeros((0, 3)))
        for tex, data in zip(self._point_tex, inputs, strict=True):
            texels = np.zeros((rows * width if len(data) else 1, 4), dtype=np.float32)
            texels[: len(data), :3] = data
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexImage2D(
                GL.GL_TEXTURE_2D,
                0,
                GL.GL_RGBA32F,
                width if len(data) else 1,
                rows if len(data) else 1,
                0,
                GL.GL_RGBA,
                GL.GL_FLOAT,
                texels,
            )
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._lookup_fb)
        GL.glViewport(0, 0, width, rows)
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_CULL_FACE)
        targets = [GL.GL_TEXTURE_2D, GL.GL_TEXTURE_2D, GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_2D]
        textures = [self._point_tex[0], self._point_tex[1], self._cube_tex, self._point_tex[2]]
        targets += [GL.GL_TEXTURE_2D] * 2 * len(distant)  # units 4 + 2 k (+1): maps
        textures += self._dmap_tex[: 2 * len(distant)]
        for unit, (target, tex) in enumerate(zip(targets, textures, strict=True)):
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(target, tex)
        GL.glBindVertexArray(self._lookup_vao)
        passes = max(-(-n_local // LOOKUP_LIGHTS_PER_PASS), 1 if distant else 0)
        if shading:
            diffuse = np.zeros((n, 3), dtype=np.float32)
            highlight = np.zeros((n, 3), dtype=np.float32)
            bits = np.zeros((n, passes), dtype=np.uint32)
            sums = np.empty((rows, width, 4), dtype=np.float32)
        else:
            out = np.zeros((n, n_local), dtype=np.uint8)
            # One byte per light, 16 per texel (see the shader): the readback viewed as
            # (texels, 16) uint8 is light-ordered on little-endian hosts.
            readback = np.empty((rows, width, 4), dtype="<u4")
        lights = self._scene.lights
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        for p in range(passes):
            start = p * LOOKUP_LIGHTS_PER_PASS
            ks = list(range(start, min(start + LOOKUP_LIGHTS_PER_PASS, n_local)))
            n_distant = len(distant) if p == 0 else 0
            pad = LOOKUP_LIGHTS_PER_PASS - len(ks)
            pos = [self._cube_keys[k][0] for k in ks]
            near = [
                (c[0] or c[1]).near if (c[0] or c[1]) is not None else 0.0
                for c in (cubes[k] for k in ks)
            ]
            # A light without any cube (no casters at all) is lit within its range:
            # its layers stay -1 and cube_test answers 1.
            prog = self._lookup_program_for(len(ks), n_distant, shading)

            def loc(name: str, prog: int = prog) -> int:
                return GL.glGetUniformLocation(prog, name)

            GL.glUseProgram(prog)
            GL.glUniform1i(loc("points"), 0)
            GL.glUniform1i(loc("normals"), 1)
            GL.glUniform1i(loc("cubes"), 2)
            GL.glUniform1i(loc("to_eye"), 3)
            GL.glUniform1i(loc("n_points"), n)
            GL.glUniform1i(loc("width"), width)
            GL.glUniform1i(loc("size"), CUBE_MAP_SIZE)
            tan_half = CUBE_MAP_SIZE / (CUBE_MAP_SIZE - 2.0 * CUBE_GUARD_TEXELS)
            GL.glUniform1f(loc("tan_half"), tan_half)
            GL.glUniform1f(loc("bias_texels"), SHADOW_BIAS_TEXELS)
            GL.glUniform1f(loc("box_radius"), SHADOW_REFINE_RADIUS + 0.5)
            GL.glUniform1f(loc("slope_clamp"), 1.0 / SHADOW_MIN_COS)
            GL.glUniform1f(loc("min_light_distance"), MIN_LIGHT_DISTANCE)
            GL.glUniform1f(loc("shininess"), SHININESS)
            GL.glUniform1f(loc("specular_strength"), SPECULAR_STRENGTH)
            if n_distant:
                self._distant_uniforms(distant, loc)
            pos_arr = np.zeros((LOOKUP_LIGHTS_PER_PASS, 3), np.float32)
            pos_arr[: len(ks)] = np.reshape(pos, (-1, 3))
            rad_arr = np.zeros((LOOKUP_LIGHTS_PER_PASS, 3), np.float32)
            rad_arr[: len(ks)] = np.reshape([lights.local[k].radiance for k in ks], (-1, 3))
            GL.glUniform3fv(loc("light_pos"), LOOKUP_LIGHTS_PER_PASS, pos_arr)
            GL.glUniform3fv(loc("light_radiance"), LOOKUP_LIGHTS_PER_PASS, rad_arr)
            GL.glUniform1fv(
                loc("light_range"),
                LOOKUP_LIGHTS_PER_PASS,
                np.array([ranges[k] for k in ks] + [0.0] * pad, np.float32),
            )
            GL.glUniform1fv(
                loc("light_near"), LOOKUP_LIGHTS_PER_PASS, np.array(near + [0.0] * pad, np.float32)
            )
            GL.glUniform1iv(
                loc("static_layer"),
                LOOKUP_LIGHTS_PER_PASS,
                np.array([first[k] for k in ks] + [-1] * pad, np.int32),
            )
            GL.glUniform1iv(
                loc("dynamic_layer"),
                LOOKUP_LIGHTS_PER_PASS,
                np.array([first[n_local + k] for k in ks] + [-1] * pad, np.int32),
            )
            GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
            if shading:
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT1)
                GL.glReadPixels(0, 0, width, rows, GL.GL_RGBA, GL.GL_FLOAT, sums)
                flat = sums.reshape(-1, 4)[:n]
                diffuse += flat[:, :3]
                bits[:, p] = flat[:, 3]
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT2)
                GL.glReadPixels(0, 0, width, rows, GL.GL_RGBA, GL.GL_FLOAT, sums)
                highlight += sums.reshape(-1, 4)[:n, :3]
            else:
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
                GL.glReadPixels(0, 0, width, rows, GL.GL_RGBA_INTEGER, GL.GL_UNSIGNED_INT, readback)
                codes = readback.view(np.uint8).reshape(-1, 16)[:n, : len(ks)]
                out[:, start : start + len(ks)] = codes
        GL.glBindVertexArray(0)
        for unit, target in enumerate(targets):
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(target, 0)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glEnable(GL.GL_DEPTH_TEST)
        if shading:
            return diffuse, highlight, bits
        return out

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
        self._pool.shutdown(wait=True)
        self._platform.make_current()
        self._delete_shadow_batches()
        r = self._renderer
        r._main_fb = r._main_fb_ms = None
        r._main_cb = r._main_cb_ms = r._main_db = r._main_db_ms = None
        r.delete()
        GL.glDeleteFramebuffers(2, [self._id_fb, self._shadow_fb])
        GL.glDeleteRenderbuffers(3, [*self._id_rb, self._shadow_rb])
        self._platform.delete_context()

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


def sample_bilinear_wrap(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup with wrap-around.

    texture : (h, w, 3) float32 linear RGB, row 0 = top of the image
    uv      : (n, 2) texture coordinates, (0, 0) = bottom-left, period 1
    Returns (n, 3) float32.
    """
    th, tw = texture.shape[:2]
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    uv = uv - np.floor(uv)  # wrap first: keeps the integer texel indices small
    fx = uv[:, 0] * tw - 0.5
    fy = (1.0 - uv[:, 1]) * th - 0.5
    x0 = np.floor(fx)
    y0 = np.floor(fy)
    wx = (fx - x0)[:, None]
    wy = (fy - y0)[:, None]
    x0 = x0.astype(np.int64) % tw
    y0 = y0.astype(np.int64) % th
    x1 = (x0 + 1) % tw
    y1 = (y0 + 1) % th
    top = texture[y0, x0] * (1 - wx) + texture[y0, x1] * wx
    bottom = texture[y1, x0] * (1 - wx) + texture[y1, x1] * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)
