"""The in-memory scene every render phase reads: what the renderer needs of a USD stage.

Coordinate space: **world space in metres**, +Y up or +Z up as the stage authored it (the
camera's own transform carries the orientation, so nothing here depends on the up axis
except camera paths). Positions are float64; they are cast to float32 only at the
OpenGL / Embree boundary, and only after subtracting ``Scene.origin`` (the "render
origin", the centre of the scene's bounds) so that a scene 1e6 m from the world origin
keeps its float32 precision.

Ids: an *element* is one renderable prim (a gprim, or one instance of an instanced
prototype). Element ids index ``Scene.elements``; ``-1`` means background / no hit.
Triangle ids index ``Geometry.triangles``.

Changes: whoever changes a scene after it was read (``StageScene.set_time``) announces
it on ``Scene.versions`` (``SceneVersions``: a geometry version stamped on the elements
that changed, a lights and a camera version); the renderer's caches compare versions,
never arrays. ``SceneChange`` is what one ``set_time`` changed.

Nothing here reads USD: ``phrt_usd.usd.stage`` fills these structures.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Id written for pixels and rays that hit nothing.
NO_HIT = -1


@dataclass
class Element:
    """One renderable prim.

    ``bounds_min``/``bounds_max`` are the world-space (metres) axis-aligned bounds at the
    current time; ``reflectivity`` is F in ``pixel = (1 - F) * local + F * reflected``
    (0 for non-reflectors) where ``reflectivity_authored`` (an explicit override, the
    default); where not (``phrt:reflectivity`` unauthored) the reflection follows the
    material: ``local + W * reflected``, W its specular lobes' albedo
    (``engine/compositing.py``).
    """

    path: str
    is_reflector: bool
    priority: float  # K, the designer priority (phrt:priority); 0 for non-reflectors
    reflectivity: float  # F in [0, 1]
    bounds_min: np.ndarray  # (3,) float64, world metres
    bounds_max: np.ndarray  # (3,) float64, world metres
    animated: bool = False
    reflectivity_authored: bool = True

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 world-space bounding-box centre."""
        return 0.5 * (self.bounds_min + self.bounds_max)


@dataclass
class Geometry:
    """All triangles of the scene, flattened into one batch (at the current time).

    vertices        : (V, 3) float64, world metres
    triangles       : (T, 3) int64 indices into ``vertices``, counter-clockwise = front
                      (``orientation = "leftHanded"`` prims are already flipped)
    tri_element     : (T,) int32, element id of each triangle
    tri_material    : (T,) int32, index into ``MaterialTable`` of each triangle
    corner_normals  : (T, 3, 3) float32 world-space unit shading normals per corner
    corner_albedo   : (T, 3, 3) float32 linear RGB per corner (material diffuseColor or
                      primvars:displayColor, any interpolation, expanded to corners)
    corner_uv       : (T, 3, 2) float32 texture coordinates, or None if no texture is used
    """

    vertices: np.ndarray
    triangles: np.ndarray
    tri_element: np.ndarray
    tri_material: np.ndarray
    corner_normals: np.ndarray
    corner_albedo: np.ndarray
    corner_uv: np.ndarray | None = None

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])


@dataclass
class MaterialTable:
    """UsdPreviewSurface inputs, one row per material (struct of arrays, M rows).

    diffuse   : (M, 3) float32 linear RGB (diffuseColor; informative, the per-corner
                ``Geometry.corner_albedo`` is what shading uses)
    metallic  : (M,) float32
    roughness : (M,) float32
    opacity   : (M,) float32, < 1 means transmissive (refraction pass needed)
    ior       : (M,) float32
    emissive  : (M, 3) float32 linear RGB radiance added to the shaded colour
    textures  : M entries, each None or an (h, w, 3) float32 linear RGB diffuse texture
                (UsdUVTexture), sampled with ``Geometry.corner_uv`` and replacing albedo
    texture_inputs : M dicts, UsdPreviewSurface input name ("diffuseColor", "opacity",
                "emissiveColor", "metallic", ...) → ``TextureInput``; the diffuse one's
                ``image`` is ``textures[m]``; empty (or missing rows): not textured,
                default sampling (repeat, no transform) of ``textures``
    opacity_threshold : (M,) float32 UsdPreviewSurface ``opacityThreshold``; > 0 makes
                the material a cut-out: a point whose opacity is below it is not there
                (no hit, no pixel, no shadow), any other point is opaque. Empty: all 0.
    specular_color, use_specular_workflow, clearcoat, clearcoat_roughness, occlusion :
                (M, 3), (M,), (M,), (M,), (M,) float32, the other UsdPreviewSurface
                inputs of the BRDF (``model/preview_surface.py``); empty (or shorter):
                the specification's fallbacks.
    glossy    : (M,) bool, the materials whose roughness blurs their reflections (a
                bound UsdPreviewSurface: ``engine/trace/glossy.py``); empty (or
                shorter): mirror reflections (a reflector of ``displayColor`` only).
    """

    diffuse: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    opacity: np.ndarray
    ior: np.ndarray
    emissive: np.ndarray
    textures: list[np.ndarray | None] = field(default_factory=list)
    texture_inputs: list[dict[str, TextureInput]] = field(default_factory=list)
    opacity_threshold: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    specular_color: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    use_specular_workflow: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    clearcoat: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    clearcoat_roughness: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    occlusion: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    glossy: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def threshold(self, m: int) -> float:
        """``opacity_threshold`` of row ``m`` (0 where the table has none)."""
        return float(self.opacity_threshold[m]) if m < len(self.opacity_threshold) else 0.0

    def texture_input(self, m: int, name: str) -> TextureInput | None:
        """The ``TextureInput`` feeding input ``name`` of row ``m``, or None."""
        return self.texture_inputs[m].get(name) if m < len(self.texture_inputs) else None

    @property
    def cutouts(self) -> list[int]:
        """Rows that are cut-outs: ``opacity_threshold`` > 0 (UsdPreviewSurface: the
        opacity is then a presence mask, not a translucency)."""
        return [int(m) for m in np.flatnonzero(np.asarray(self.opacity_threshold) > 0.0)]

    @property
    def has_transmission(self) -> bool:
        """Some material is translucent: opacity < 1 on a row that is not a cut-out
        (a cut-out's opacity masks presence; where present it is opaque)."""
        cut = np.zeros(len(self.opacity), dtype=bool)
        cut[[m for m in self.cutouts if m < len(cut)]] = True
        return bool(np.any((self.opacity < 1.0) & ~cut))


#: UsdUVTexture ``wrapS``/``wrapT`` modes the sampler knows (``useMetadata`` is resolved
#: when the texture is read: the file's own wrap metadata, else ``black``, as the
#: UsdPreviewSurface specification says).
WRAP_MODES = ("repeat", "mirror", "clamp", "black")


@dataclass
class TextureInput:
    """One UsdUVTexture (through an optional UsdTransform2d) feeding one input.

    image    : (h, w, c) float32 linear, row 0 = **top** of the file (USD ``st`` has
               v = 0 at the bottom); c = the file's channels (1 grey, 2 grey+alpha, 3 RGB,
               4 RGBA), colour space already applied to the colour channels
    channels : the output's components as channel indices into ``image`` (``rgb`` of a
               grey file is (0, 0, 0)); ``ALPHA_ONE`` (-1) reads 1 (``a`` of a file
               without alpha, as the spec says)
    scale, bias : (k,) float32 per component, ``value = sample * scale + bias``
    wrap     : (wrapS, wrapT), each of ``WRAP_MODES``
    transform : (2, 3) float64 affine st → st' (UsdTransform2d: scale, then rotation,
               then translation), None = identity
    """

    image: np.ndarray
    channels: tuple[int, ...]
    scale: np.ndarray
    bias: np.ndarray
    wrap: tuple[str, str] = ("repeat", "repeat")
    transform: np.ndarray | None = None

    @property
    def default_sampling(self) -> bool:
        """Repeat in both directions and no transform (the legacy diffuse lookup)."""
        return self.wrap == ("repeat", "repeat") and self.transform is None


#: ``TextureInput.channels`` entry of an alpha the file does not have (reads 1).
ALPHA_ONE = -1


@dataclass
class DistantLight:
    """direction: (3,) unit vector from the surface *towards* the light (world space).
    radiance: (3,) linear RGB irradiance scale (color * intensity * 2**exposure).
    angle: angular diameter in degrees (UsdLux inputs:angle)."""

    direction: np.ndarray
    radiance: np.ndarray
    angle: float = 0.53
    path: str = ""  # the light's prim path ("" for the default rig's headlight)


@dataclass
class LocalLight:
    """A Sphere, Rect, Disk or Cylinder light: a point at its centre, but that Rect and
    Disk lights are shaded as their areas wherever a pair is shaded (``area_shape``,
    ``engine/trace/area_light_kernels.py``).

    position: (3,) world metres; radiance: (3,) linear RGB intensity (W/sr-like units,
    falls off with 1/d^2); radius: metres (for the shadow-ray offset only).
    UsdLux ShapingAPI (``shading.cone_falloff``): axis (3,) world unit vector the light
    shines along (its -Z); cone_angle degrees off the axis beyond which it emits nothing
    (>= 180: no cone); cone_softness in [0, 1]; focus >= 0 (0: none).
    The emitting surface of a RectLight or DiskLight (UsdLux: in its local XY plane,
    emitting along its -Z, ``axis``): area_shape "rect" or "disk" ("" for any other
    light), area_u and area_v (3,) world metres: the rect's half width and half height
    along its local X and Y, or the disk's radius along them (a scaled disk is an
    ellipse).
    """

    position: np.ndarray
    radiance: np.ndarray
    radius: float = 0.0
    path: str = ""
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    cone_angle: float = 180.0
    cone_softness: float = 0.0
    focus: float = 0.0
    area_shape: str = ""
    area_u: np.ndarray = field(default_factory=lambda: np.zeros(3))
    area_v: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def shaped(self) -> bool:
        """The emission depends on direction (a cone narrower than the sphere, or focus)."""
        return self.cone_angle < 180.0 or self.focus > 0.0


@dataclass
class DomeLight:
    """Environment radiance for ray misses and the ambient term.

    texture: (h, w, 3) float32 linear RGB lat-long map, or None for a constant ``color``.
    world_from_light: (3, 3) float64 rotation, dome-light space → world space
    (UsdLux lat-long convention: +Y up in light space).
    """

    color: np.ndarray  # (3,) linear RGB (color * intensity * 2**exposure)
    texture: np.ndarray | None = None
    world_from_light: np.ndarray = field(default_factory=lambda: np.eye(3))
    path: str = ""
    #: Seen by primary rays (UsdLux ``visibleInPrimaryRay`` / Hydra's camera visibility):
    #: False leaves the background of camera-ray misses black (alpha 0); it still lights.
    camera_visible: bool = True


@dataclass
class Lights:
    distant: list[DistantLight] = field(default_factory=list)
    local: list[LocalLight] = field(default_factory=list)
    dome: DomeLight | None = None
    #: These are the default rig of a stage without lights (``usd/default_lights.py``):
    #: its headlight, ``distant[0]``, follows the camera every frame.
    default_rig: bool = False

    @property
    def has_direct(self) -> bool:
        """True when shadow rays / shadow maps are needed at all."""
        return bool(self.distant or self.local)


#: Environment colour (linear RGB) used on a ray miss when the stage has no DomeLight.
DEFAULT_ENVIRONMENT = np.array([0.05, 0.05, 0.05])


#: UsdRender ``aspectRatioConformPolicy`` tokens (``CameraFrame.image_window``).
CONFORM_POLICIES = (
    "expandAperture",
    "cropAperture",
    "adjustApertureWidth",
    "adjustApertureHeight",
    "adjustPixelAspectRatio",
)
#: Relative difference below which the aperture's and the image's aspect ratios count
#: as equal; the window is then the horizontal fit, bit for bit the window of a camera
#: without vertical aperture (both conform choices are the same window up to rounding).
ASPECT_EQUAL_RTOL = 1e-12


def perspective_matrix(
    window: tuple[float, float, float, float], near: float, far: float
) -> np.ndarray:
    """OpenGL clip_from_camera (4, 4) float64 for the image-plane ``window`` (left,
    right, bottom, top) at distance 1 (``CameraFrame.image_window``, so that
    ``CameraFrame.project``, the primary rays and the rasterizer put a point on the same
    pixel; off-centre for aperture offsets) and clip planes ``near`` < ``far``
    (metres). NDC (x, y) is pixel ((x + 1) W / 2, (1 - y) H / 2), row 0 at the top."""
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
class CameraFrame:
    """The camera at one time code (``GfCamera`` semantics, perspective only).

    world_from_camera: (4, 4) float64, camera space → world metres. Camera space is
    USD's / OpenGL's: the camera looks down -Z, +Y is up, +X right.
    Apertures, aperture offsets and focal length in the same unit (USD: tenths of a
    scene unit; only their ratios matter). ``vertical_aperture`` None: the horizontal
    aperture fills the image width and the vertical field of view follows from the image
    aspect (the window of ``adjustApertureHeight``).
    conform_policy: UsdRender ``aspectRatioConformPolicy`` (``CONFORM_POLICIES``), how
    the aperture is fitted to the image's aspect ratio; pixel_aspect: UsdRender
    ``pixelAspectRatio`` (pixel width / pixel height, > 0).
    data_window: UsdRender ``dataWindowNDC`` (xmin, ymin, xmax, ymax), NDC of the image
    with (0, 0) at the bottom left; ``data_window_pixels`` says which pixels it holds.
    near, far: clipping range in metres.
    """

    world_from_camera: np.ndarray
    focal_length: float
    horizontal_aperture: float
    near: float
    far: float
    vertical_aperture: float | None = None
    horizontal_aperture_offset: float = 0.0
    vertical_aperture_offset: float = 0.0
    conform_policy: str = "expandAperture"
    pixel_aspect: float = 1.0
    data_window: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)
    #: UsdGeomCamera's linear exposure scale (``ComputeLinearExposureScale``: 2^exposure
    #: x time x ISO/100 x responsivity / fStop²), multiplied into the frame's radiance.
    exposure_scale: float = 1.0

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 world-space eye position."""
        return self.world_from_camera[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """(3,) float64 world-space unit view direction (camera -Z)."""
        f = -self.world_from_camera[:3, 2]
        return f / np.linalg.norm(f)

    def image_window(self, width: int, height: int) -> tuple[float, float, float, float]:
        """The image plane's (left, right, bottom, top) in camera space at distance 1
        (x right, y up): the one window both the raster projection and the primary rays
        use, for an image of ``width`` x ``height`` pixels.

        As ``GfCamera::GetFrustum`` and ``CameraUtilConformedWindow``: the aperture
        window is ``(±horizontal_aperture/2 + horizontal_aperture_offset,
        ±vertical_aperture/2 + vertical_aperture_offset) / focal_length``, then conformed
        about its centre to the image aspect ``width * pixel_aspect / height``:
        expandAperture grows the too-narrow side (the whole aperture stays visible),
        cropAperture shrinks the too-wide side, adjustApertureWidth keeps the height,
        adjustApertureHeight keeps the width, adjustPixelAspectRatio keeps the aperture
        (the pixels are stretched instead). Aspects equal to ``ASPECT_EQUAL_RTOL``: the
        width is kept.
        """
        par = self.pixel_aspect
        hx = 0.5 * self.horizontal_aperture / self.focal_length
        cx = self.horizontal_aperture_offset / self.focal_length
        cy = self.vertical_aperture_offset / self.focal_length
        keep = "width"
        if self.vertical_aperture is not None:
            ay = 0.5 * self.vertical_aperture / self.focal_length
            # Aperture aspect hx / ay against image aspect width * par / height.
            lhs, rhs = hx * height, ay * width * par
            equal = abs(lhs - rhs) <= ASPECT_EQUAL_RTOL * max(abs(lhs), abs(rhs))
            policy = self.conform_policy
            if policy == "adjustPixelAspectRatio":
                keep = "both"
            elif policy == "adjustApertureWidth":
                keep = "height"
            elif policy == "expandAperture" and not equal and lhs < rhs:
                keep = "height"  # aperture narrower than the image: widen it
            elif policy == "cropAperture" and not equal and lhs > rhs:
                keep = "height"  # aperture wider than the image: crop its width
        if keep == "width":
            hy = hx * height / (width * par)
        elif keep == "height":
            hy = ay
            hx = ay * width * par / height
        else:
            hy = ay
        return cx - hx, cx + hx, cy - hy, cy + hy

    def tan_half_fov(self, width: int, height: int) -> tuple[float, float]:
        """Half the width and height of ``image_window`` (tan of the half field of view
        when the window is centred, i.e. without aperture offsets)."""
        left, right, bottom, top = self.image_window(width, height)
        return 0.5 * (right - left), 0.5 * (top - bottom)

    def pixel_plane(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Camera-space image-plane coordinates of pixel centres at distance 1:
        xs (width,) float64 per column (left to right), ys (height,) float64 per row
        (row 0 is the top). Pixel (row, col) is at ((col + 0.5) / width, (row + 0.5) /
        height) of ``image_window``."""
        left, right, bottom, top = self.image_window(width, height)
        cx, hx = 0.5 * (left + right), 0.5 * (right - left)
        cy, hy = 0.5 * (bottom + top), 0.5 * (top - bottom)
        xs = cx + ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * hx
        ys = cy + (1.0 - (np.arange(height) + 0.5) / height * 2.0) * hy
        return xs, ys

    def pixel_rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through pixel centres (``pixel_plane``).

        Returns origins (H*W, 3) float64 world metres (all the eye) and unit directions
        (H*W, 3) float64 world space, in row-major pixel order.
        """
        xs, ys = self.pixel_plane(width, height)
        gx, gy = np.meshgrid(xs, ys)
        d_cam = np.stack([gx, gy, -np.ones_like(gx)], axis=-1).reshape(-1, 3)
        d = d_cam @ self.world_from_camera[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.position, d.shape).copy()
        return o, d

    def project(self, points: np.ndarray, width: int, height: int) -> np.ndarray:
        """World points (n, 3) → (n, 3): pixel x (cols), pixel y (rows, 0 at top), and
        view depth (metres along the view direction; <= 0 means behind the camera)."""
        cam_from_world = np.linalg.inv(self.world_from_camera)
        pc = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        depth = -pc[:, 2]
        safe = np.where(np.abs(depth) < 1e-300, 1e-300, depth)  # avoid /0 at the eye plane
        left, right, bottom, top = self.image_window(width, height)
        cx, tx = 0.5 * (left + right), 0.5 * (right - left)
        cy, ty = 0.5 * (bottom + top), 0.5 * (top - bottom)
        ndc_x = (pc[:, 0] - cx * safe) / (safe * tx)
        ndc_y = (pc[:, 1] - cy * safe) / (safe * ty)
        px = (ndc_x + 1.0) * 0.5 * width
        py = (1.0 - ndc_y) * 0.5 * height
        return np.stack([px, py, depth], axis=1)

    @property
    def camera_from_world(self) -> np.ndarray:
        """(4, 4) float64 world-to-camera: world metres → camera space (the inverse of
        ``world_from_camera``), column vectors."""
        return np.linalg.inv(self.world_from_camera)

    def projection(self, width: int, height: int) -> np.ndarray:
        """(4, 4) float64 OpenGL clip_from_camera of this camera for an image of ``width``
        x ``height`` pixels: ``image_window`` (so a point projects to the pixel
        ``project`` gives) and the clipping range ``near`` .. ``far`` (metres)."""
        return perspective_matrix(self.image_window(width, height), self.near, self.far)

    def data_window_pixels(self, width: int, height: int) -> tuple[int, int, int, int]:
        """The pixels of ``data_window`` as (col0, row0, col1, row1), half-open, row 0 at
        the top, clamped to the image: the pixels whose centres lie inside the NDC window
        (UsdRender ``dataWindowNDC``; y of NDC is up, rows go down). The whole image for
        the default window."""
        x0, y0, x1, y1 = self.data_window
        col0 = int(np.clip(np.ceil(x0 * width - 0.5), 0, width))
        col1 = int(np.clip(np.floor(x1 * width - 0.5) + 1, col0, width))
        row0 = int(np.clip(np.ceil((1.0 - y1) * height - 0.5), 0, height))
        row1 = int(np.clip(np.floor((1.0 - y0) * height - 0.5) + 1, row0, height))
        return col0, row0, col1, row1


@dataclass
class SceneVersions:
    """Change counters of a ``Scene``, bumped by whoever changes it (``StageScene.set_time``,
    or a caller editing the scene in memory through ``Scene.geometry_changed`` /
    ``Scene.replace_lights``). A consumer (raster buffers, BVH, shadow maps) keeps the
    counter it last brought itself to and compares: equal means nothing it holds is
    stale, and no array is looked at to find out (hdEmbree's scene version).

    geometry : bumped whenever any element's vertices, winding or corner normals change
    lights   : bumped whenever ``Scene.lights`` is replaced
    camera   : bumped whenever the stage's camera differs from the one at the previous
               ``set_time`` (pose, lens, clipping range or image settings)
    element_geometry : (E,) int64, the ``geometry`` version at which each element last
               changed (0: as read), so that a consumer that last synced at version v
               finds what changed since, however many changes it missed
               (``changed_since``)
    """

    element_geometry: np.ndarray
    geometry: int = 0
    lights: int = 0
    camera: int = 0

    def changed_since(self, version: int) -> np.ndarray:
        """(k,) int64 ascending ids of the elements whose geometry changed after
        ``version`` (a ``geometry`` value)."""
        return np.flatnonzero(self.element_geometry > version).astype(np.int64)


@dataclass(frozen=True)
class SceneChange:
    """What one ``StageScene.set_time`` changed (plain data).

    moved    : (m,) int64 ascending ids of the elements placed anew by a changed rigid
               transform, their own points and normals unchanged
    deformed : (d,) int64 ascending ids of the elements whose points or normals changed
               (their transform may have changed too); disjoint from ``moved``
    geometry_version, lights_version, camera_version : ``Scene.versions`` after the
               change (``SceneVersions``)

    True (``bool``) when some element moved or deformed.
    """

    moved: np.ndarray
    deformed: np.ndarray
    geometry_version: int
    lights_version: int
    camera_version: int

    @property
    def changed(self) -> np.ndarray:
        """(k,) int64 ascending ids of every element that moved or deformed."""
        return np.union1d(self.moved, self.deformed).astype(np.int64)

    def __bool__(self) -> bool:
        return bool(len(self.moved) or len(self.deformed))


class ElementTriangles:
    """The triangle rows of each element (CSR over ``Geometry.tri_element``), so that a
    consumer finds the rows of the few elements that changed without a pass over every
    triangle. Built once per topology. tri_element : (T,) element id per triangle
    (ids outside 0 .. ``n_elements`` - 1 belong to no element)."""

    def __init__(self, tri_element: np.ndarray, n_elements: int) -> None:
        tri_element = np.asarray(tri_element, dtype=np.int64)
        #: Triangle rows sorted by element ...
        self.row_order = np.argsort(tri_element, kind="stable")
        #: ... where element e's begin (element_start[e] .. element_start[e + 1] - 1).
        self.element_start = np.searchsorted(
            tri_element[self.row_order], np.arange(n_elements + 1)
        )

    def rows(self, elements: np.ndarray) -> np.ndarray:
        """(m,) int64 ascending triangle rows of ``elements`` (k,) ids, in O(their rows)."""
        elements = np.asarray(elements, dtype=np.int64)
        start = self.element_start[elements]
        counts = self.element_start[elements + 1] - start
        total = int(counts.sum())
        if total == 0:
            return np.zeros(0, dtype=np.int64)
        # The positions start[i] .. start[i] + counts[i] - 1 of every element, one array.
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        return np.sort(self.row_order[np.repeat(start, counts) + offsets]).astype(np.int64)


@dataclass
class Scene:
    """Everything a frame needs. ``geometry`` and element bounds are valid at the time
    last passed to ``StageScene.set_time`` (see ``phrt_usd.usd.stage``); ``versions``
    count the changes since the scene was read. Whoever edits ``geometry`` or ``lights``
    after a consumer saw them announces it (``geometry_changed``, ``replace_lights``):
    consumers compare versions, never arrays."""

    elements: list[Element]
    geometry: Geometry
    materials: MaterialTable
    lights: Lights
    origin: np.ndarray  # (3,) float64 world metres: subtract before casting to float32
    meters_per_unit: float = 1.0
    up_axis: str = "Y"
    versions: SceneVersions | None = None  # None: new counters at 0

    def __post_init__(self) -> None:
        if self.versions is None:
            self.versions = SceneVersions(np.zeros(len(self.elements), dtype=np.int64))

    def geometry_changed(self, elements) -> int:
        """Announce that the geometry of ``elements`` ((k,) ids) changed in ``geometry``
        (vertices, winding, corner normals; their bounds): bumps ``versions.geometry``
        and stamps those elements with it. Returns the geometry version (unchanged when
        ``elements`` is empty)."""
        elements = np.asarray(elements, dtype=np.int64).reshape(-1)
        if len(elements):
            self.versions.geometry += 1
            self.versions.element_geometry[elements] = self.versions.geometry
        return self.versions.geometry

    def replace_lights(self, lights: Lights) -> None:
        """Make ``lights`` the scene's lights and bump ``versions.lights`` (nothing when
        they are the scene's lights already)."""
        if lights is not self.lights:
            self.lights = lights
            self.versions.lights += 1

    @property
    def reflector_ids(self) -> np.ndarray:
        """(R,) int32 element ids of all reflectors, ascending."""
        return np.array(
            [i for i, e in enumerate(self.elements) if e.is_reflector], dtype=np.int32
        )

    @property
    def reflectivity(self) -> np.ndarray:
        """(E,) float32 F per element (0 for non-reflectors)."""
        return np.array([e.reflectivity for e in self.elements], dtype=np.float32)

    @property
    def extent(self) -> float:
        """Diagonal of the scene's bounds in metres (> 0)."""
        v = self.geometry.vertices
        if len(v) == 0:
            return 1.0
        return float(max(np.linalg.norm(v.max(axis=0) - v.min(axis=0)), 1e-12))
