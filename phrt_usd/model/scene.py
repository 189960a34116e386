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
    (0 for non-reflectors).
    """

    path: str
    is_reflector: bool
    priority: float  # K, the designer priority (phrt:priority); 0 for non-reflectors
    reflectivity: float  # F in [0, 1]
    bounds_min: np.ndarray  # (3,) float64, world metres
    bounds_max: np.ndarray  # (3,) float64, world metres
    animated: bool = False

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
    """

    diffuse: np.ndarray
    metallic: np.ndarray
    roughness: np.ndarray
    opacity: np.ndarray
    ior: np.ndarray
    emissive: np.ndarray
    textures: list[np.ndarray | None] = field(default_factory=list)

    @property
    def has_transmission(self) -> bool:
        return bool(np.any(self.opacity < 1.0))


@dataclass
class DistantLight:
    """direction: (3,) unit vector from the surface *towards* the light (world space).
    radiance: (3,) linear RGB irradiance scale (color * intensity * 2**exposure).
    angle: angular diameter in degrees (UsdLux inputs:angle)."""

    direction: np.ndarray
    radiance: np.ndarray
    angle: float = 0.53


@dataclass
class LocalLight:
    """A SphereLight or a RectLight approximated as a point with an area factor.

    position: (3,) world metres; radiance: (3,) linear RGB intensity (W/sr-like units,
    falls off with 1/d^2); radius: metres (for the shadow-ray offset only).
    """

    position: np.ndarray
    radiance: np.ndarray
    radius: float = 0.0


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


@dataclass
class Lights:
    distant: list[DistantLight] = field(default_factory=list)
    local: list[LocalLight] = field(default_factory=list)
    dome: DomeLight | None = None

    @property
    def has_direct(self) -> bool:
        """True when shadow rays / shadow maps are needed at all."""
        return bool(self.distant or self.local)


#: Environment colour (linear RGB) used on a ray miss when the stage has no DomeLight.
DEFAULT_ENVIRONMENT = np.array([0.05, 0.05, 0.05])


@dataclass
class CameraFrame:
    """The camera at one time code.

    world_from_camera: (4, 4) float64, camera space → world metres. Camera space is
    USD's / OpenGL's: the camera looks down -Z, +Y is up, +X right.
    Apertures and focal length in the same unit (USD: tenths of a scene unit; only
    their ratio matters). Horizontal fit: the horizontal aperture fills the image
    width, the vertical field of view follows from the image aspect.
    near, far: clipping range in metres.
    """

    world_from_camera: np.ndarray
    focal_length: float
    horizontal_aperture: float
    near: float
    far: float

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 world-space eye position."""
        return self.world_from_camera[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """(3,) float64 world-space unit view direction (camera -Z)."""
        f = -self.world_from_camera[:3, 2]
        return f / np.linalg.norm(f)

    def tan_half_fov(self, width: int, height: int) -> tuple[float, float]:
        """(tan(hfov/2), tan(vfov/2)) for an image of ``width`` x ``height`` pixels."""
        tx = 0.5 * self.horizontal_aperture / self.focal_length
        return tx, tx * height / width

    def pixel_rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through pixel centres.

        Pixel (row, col): row 0 is the *top* of the image, col 0 the left; the ray goes
        through ((col + 0.5) / width, (row + 0.5) / height) of the image plane.

        Returns origins (H*W, 3) float64 world metres (all the eye) and unit directions
        (H*W, 3) float64 world space, in row-major pixel order.
        """
        tx, ty = self.tan_half_fov(width, height)
        xs = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * tx
        ys = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * ty
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
        tx, ty = self.tan_half_fov(width, height)
        ndc_x = pc[:, 0] / (safe * tx)
        ndc_y = pc[:, 1] / (safe * ty)
        px = (ndc_x + 1.0) * 0.5 * width
        py = (1.0 - ndc_y) * 0.5 * height
        return np.stack([px, py, depth], axis=1)


@dataclass
class Scene:
    """Everything a frame needs. ``geometry`` and element bounds are valid at the time
    last passed to ``StageScene.set_time`` (see ``phrt_usd.usd.stage``)."""

    elements: list[Element]
    geometry: Geometry
    materials: MaterialTable
    lights: Lights
    origin: np.ndarray  # (3,) float64 world metres: subtract before casting to float32
    meters_per_unit: float = 1.0
    up_axis: str = "Y"

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
