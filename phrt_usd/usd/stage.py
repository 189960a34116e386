"""Read a USD stage into the in-memory ``phrt_usd.model.scene.Scene`` — only what the render sees.

Pipeline (``read_stage``):

1. **Camera.** Explicit prim path > the render settings' ``camera`` relationship
   (``renderSettingsPrimPath`` stage metadata, else the first ``UsdRenderSettings``) >
   the first ``UsdGeomCamera``. A ``PhrtCameraPath`` whose ``phrt:camera`` targets the
   chosen camera drives it (``phrt_usd.usd.camera_path``); otherwise the camera's own
   (possibly time-sampled) world transform does.
2. **Traversal.** ``Usd.PrimRange`` with instance proxies, default predicate (inactive,
   undefined, abstract and unloaded prims are pruned). Subtrees whose root is authored
   ``invisible`` or has purpose ``guide``/``proxy`` are pruned before anything below is
   read (visibility and purpose are inherited, so this equals ``ComputeVisibility`` /
   ``ComputePurpose`` on every prim below). Visibility is evaluated once, at the start
   of the frame range: animated visibility is not supported.
3. **Geometry.** Every ``Mesh``, ``Sphere``, ``Cube``, ``Cylinder``, ``Cone``,
   ``Capsule`` and ``Plane`` becomes one element; every PointInstancer instance × gprim
   of its prototype becomes one element (path ``/Instancer.instance[i]``, or
   ``/Instancer.instance[i]/rel/path`` when the prototype holds several gprims). Each
   element's triangles are prepared once in its local space (fan triangulation,
   ``leftHanded`` flipped, normals and colours expanded to triangle corners), then
   transformed into one world-space batch in **metres**. Elements whose transform or
   points may vary in time are re-transformed in ``StageScene.set_time``; the others are
   never touched again. Element vertex / triangle ranges stay fixed (topology must not
   change over time).
4. **Materials.** ``ComputeBoundMaterial`` per gprim and per ``materialBind`` GeomSubset,
   UsdPreviewSurface inputs (connections followed; ``diffuseColor`` may come from a
   ``UsdUVTexture``), deduplicated into one ``MaterialTable`` (row 0 = no material).
   Materials are read once (not animated).
5. **Lights.** UsdLux Distant, Sphere, Rect, Disk, Cylinder and Dome lights, read once at
   the start of the frame range (not animated; colour temperature ignored).

Refusals and warnings: every reason ``read_stage`` refuses a stage is a one-line
``PhrtError`` ``"<where>: <what>"``; the rules that ``phrt validate`` must agree with are
functions here returning those messages (``stage_problems``, ``choose_camera``,
``camera_problems``, ``reflector_problems``, ``mesh_problems`` /
``mesh_problems_in_range``; ``phrt_usd.usd.camera_path.camera_path_problems``), and the render
raises their first message. The camera is checked at the start of the frame range before
any geometry is read, and again at every ``camera(time)``. Sublayers, references and
payloads USD could not open do not stop the render: ``StageScene.warnings`` holds one
line per missing asset (``composition_problems`` / ``composition_warnings``).

Decisions where USD leaves room:

- Normals: authored ``primvars:normals`` (preferred) or ``normals`` in any interpolation;
  otherwise smooth, area-weighted vertex normals — what Hydra / usdview draw for a mesh
  without normals, whatever its ``subdivisionScheme``. Implicit gprims get their exact
  analytic normals (flat on planar faces, smooth on curved ones).
- A transform with negative determinant flips the winding (as Hydra does), so the front
  face stays consistent with the transformed normals.
- Albedo per corner: the bound material's ``diffuseColor`` when authored (a texture's
  mean colour when it is textured; ``MaterialTable.textures`` holds the texture itself),
  else ``primvars:displayColor`` (linear by USD convention, any interpolation), else the
  UsdPreviewSurface default 0.18 when a material is bound, else mid grey 0.5.
- Textures are stored as read, row 0 = **top** of the image; USD ``st`` has v = 0 at the
  **bottom**, so a sampler reads row ``(1 - v) * h``.
- Faces with fewer than 3 vertices are skipped (they have no area). Non-finite points,
  face counts that do not add up, and out-of-range indices raise ``PhrtError``.
- SphereLight: ``radiance = color * intensity * 2**exposure`` used as an intensity with
  1/d² fall-off. Rect / Disk / Cylinder lights: the same times the light's (lateral)
  area in m² (unless ``inputs:normalize`` is on), placed at its centre. DomeLight: ``color`` holds
  ``color * intensity * 2**exposure`` and ``texture`` the raw linear lat-long map; the
  environment radiance is ``texture * color``.
- ``Scene.origin`` is the centre of all geometry bounds at the first time and is kept
  fixed afterwards, so float32 buffers built from it stay valid.

Limits: no subdivision (cage is rendered), no curves/points/volumes, no primvar
inheritance from ancestors, implicit gprims take only a constant displayColor and no
texture coordinates, nested PointInstancers are not expanded, prototype-internal
transforms of PointInstancers are taken at the first time only. Visibility, purpose,
materials and lights are read once (first time code); topology (point, face and instance
counts) must not change over time (``PhrtError`` if it does). ``doubleSided`` is not
represented: front faces are counter-clockwise, culling is the renderer's choice. Only
the first DomeLight is used, lat-long textures only; orthographic cameras are rejected.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Pcp, Sdf, Tf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade

from phrt_usd.errors import PhrtError, usd_error_reason
from phrt_usd.model.scene import (
    CameraFrame,
    DistantLight,
    DomeLight,
    Element,
    Geometry,
    Lights,
    LocalLight,
    MaterialTable,
    Scene,
)
from phrt_usd.usd import schema
from phrt_usd.usd.camera_path import CameraPath, find_camera_path

#: Albedo of a gprim with neither a material nor ``primvars:displayColor``.
DEFAULT_GREY = 0.5

#: UsdPreviewSurface's own fallback ``diffuseColor`` (used when a material is bound but
#: its diffuseColor is unauthored and the gprim has no displayColor).
PREVIEW_SURFACE_DIFFUSE = 0.18

#: Tessellation of implicit gprims: segments around the axis, rings pole to pole.
IMPLICIT_SEGMENTS = 32
IMPLICIT_RINGS = 16

#: Normals shorter than this (degenerate triangles, zero scale) are replaced by a
#: fallback direction instead of being divided by ~0.
_MIN_NORMAL_LENGTH = 1e-30

#: Gprim types read as geometry.
_IMPLICIT_TYPES = ("Sphere", "Cube", "Cylinder", "Cone", "Capsule", "Plane")


# --------------------------------------------------------------------------------------
# Small numeric helpers
# --------------------------------------------------------------------------------------


def _safe_normalize(v: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """Normalise rows of ``v`` (..., 3); rows of ~zero length become ``fallback`` (or +Z)."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = length > _MIN_NORMAL_LENGTH
    out = v / np.where(ok, length, 1.0)
    if fallback is None:
        fallback = np.array([0.0, 0.0, 1.0])
    return np.where(ok, out, fallback)


def _normal_matrix(m3: np.ndarray) -> np.ndarray:
    """(3, 3) row-vector normal transform of the row-vector linear map ``m3``.

    ``n_world = n_local @ N`` with ``N`` the inverse-transpose, computed as the cofactor
    matrix times sign(det) so that a singular (zero-scale) transform gives finite normals
    instead of an exception.
    """
    (a, b, c), (d, e, f), (g, h, i) = m3.tolist()
    cof = np.array(
        [
            [e * i - f * h, f * g - d * i, d * h - e * g],  # r1 x r2
            [h * c - i * b, i * a - g * c, g * b - h * a],  # r2 x r0
            [b * f - c * e, c * d - a * f, a * e - b * d],  # r0 x r1
        ]
    )
    det = a * (e * i - f * h) + b * (f * g - d * i) + c * (d * h - e * g)
    return -cof if det < 0 else cof


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function, inverse (values in [0, 1])."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _fan_corners(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons without a per-face loop.

    counts : (F,) int vertex count of each face (faces with < 3 vertices are skipped).
    Returns corner ids (T, 3) int64 into the flat face-vertex list and the face of each
    triangle (T,) int64, T = sum(max(count - 2, 0)).
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else counts
    ntri = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts), dtype=np.int64), ntri)
    first = np.concatenate([[0], np.cumsum(ntri)[:-1]]) if len(counts) else ntri
    k = np.arange(len(tri_face), dtype=np.int64) - np.repeat(first, ntri)
    base = starts[tri_face]
    corners = np.stack([base, base + k + 1, base + k + 2], axis=1)
    return corners, tri_face


def _expand(
    values: np.ndarray,
    interpolation: str,
    corners: np.ndarray,
    tri_face: np.ndarray,
    triangles: np.ndarray,
    where: str,
) -> np.ndarray:
    """Expand primvar values (k, c) of any interpolation to triangle corners (T, 3, c).

    corners : (T, 3) face-vertex ids; tri_face : (T,) face ids; triangles : (T, 3) point
    ids. Raises ``PhrtError`` naming ``where`` when there are too few values.
    """
    values = np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    if interpolation == "constant":
        need, idx = 1, None
    elif interpolation == "uniform":
        idx = tri_face
        need = int(idx.max()) + 1 if len(idx) else 0
        if len(values):
            idx = np.repeat(idx[:, None], 3, axis=1)
    elif interpolation in ("vertex", "varying"):
        idx = triangles
        need = int(idx.max()) + 1 if idx.size else 0
    elif interpolation == "faceVarying":
        idx = corners
        need = int(idx.max()) + 1 if idx.size else 0
    else:
        raise PhrtError(f"{where}: unknown interpolation {interpolation!r}")
    if len(values) < need:
        raise PhrtError(
            f"{where}: {len(values)} values for {interpolation} interpolation, need {need}"
        )
    if idx is None:
        return np.broadcast_to(values[0], (len(triangles), 3, values.shape[1])).copy()
    return values[idx]


def _read_primvar(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> tuple[np.ndarray, str] | None:
    """Flattened values and interpolation of an authored primvar, or None."""
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    if not pv or not pv.HasAuthoredValue():
        return None
    value = pv.ComputeFlattened(time)
    if value is None or len(value) == 0:
        return None
    return np.asarray(value, dtype=np.float64), str(pv.GetInterpolation())


def _attr(prim: Usd.Prim, name: str, time: Usd.TimeCode, default):
    """Value of attribute ``name`` at ``time``, or ``default`` when absent/unauthored."""
    a = prim.GetAttribute(name)
    if not a:
        return default
    v = a.Get(time)
    return default if v is None else v


# --------------------------------------------------------------------------------------
# Materials
# --------------------------------------------------------------------------------------


@dataclass
class _MaterialRow:
    diffuse: np.ndarray  # (3,) linear RGB (texture mean when textured)
    diffuse_authored: bool
    metallic: float = 0.0
    roughness: float = 0.5
    opacity: float = 1.0
    ior: float = 1.5
    emissive: np.ndarray = field(default_factory=lambda: np.zeros(3))
    texture: np.ndarray | None = None  # (h, w, 3) float32 linear, row 0 = top
    uv_primvar: str = "st"


def read_texture(path: str, where: str, color_space: str = "auto") -> np.ndarray:
    """Read an image with OpenImageIO as (h, w, 3) float32 linear RGB, row 0 = top.

    color_space: UsdUVTexture ``sourceColorSpace`` — "sRGB" converts to linear, "raw"
    does not, "auto" converts 8-bit files only. Grey images are replicated to RGB.
    """
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise PhrtError(f"{where}: cannot read texture {path!r} ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        eight_bit = spec.format.basetype in (oiio.UINT8, oiio.INT8)
    finally:
        inp.close()
    if pixels is None:
        raise PhrtError(f"{where}: cannot decode texture {path!r}")
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, -1)
    rgb = np.repeat(pixels[..., :1], 3, axis=2) if pixels.shape[2] < 3 else pixels[..., :3]
    if color_space == "sRGB" or (color_space == "auto" and eight_bit):
        rgb = _srgb_to_linear(np.clip(rgb, 0.0, 1.0))
    # Float files may hold Inf/NaN (e.g. broken HDR exports); render them as black.
    rgb = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def _asset_file(value, where: str) -> str:
    """Resolved filesystem path of an ``SdfAssetPath`` (raises when it cannot resolve)."""
    path = value.resolvedPath if isinstance(value, Sdf.AssetPath) else str(value or "")
    if not path and isinstance(value, Sdf.AssetPath) and value.path:
        raise PhrtError(f"{where}: texture file {value.path!r} not found")
    return path


def material_key(material: UsdShade.Material | None) -> str:
    """Identity of a material for deduplication: its path, or for a material reached
    through an instance proxy the path of its prim in the prototype (all instances of a
    prototype share one row). "" for no material."""
    if not material:
        return ""
    prim = material.GetPrim()
    return str(prim.GetPrimInPrototype().GetPath() if prim.IsInstanceProxy() else prim.GetPath())


class _MaterialBank:
    """Deduplicates bound materials into table rows. Row 0 = no material bound."""

    def __init__(self, time: Usd.TimeCode):
        self.time = time
        self.rows: list[_MaterialRow] = [
            _MaterialRow(np.full(3, PREVIEW_SURFACE_DIFFUSE), diffuse_authored=False)
        ]
        self._index: dict[str, int] = {"": 0}
        self._textures: dict[tuple[str, str], np.ndarray] = {}

    def index(self, material: UsdShade.Material | None) -> int:
        key = material_key(material)
        if key not in self._index:
            self._index[key] = len(self.rows)
            self.rows.append(self._read(material))
        return self._index[key]

    def _value(self, shader: UsdShade.Shader, name: str):
        """(value, source shader or None) of an input, following connections."""
        inp = shader.GetInput(name)
        if not inp:
            return None, None
        attrs = inp.GetValueProducingAttributes()
        if not attrs:
            return None, None
        attr = attrs[0]
        if UsdShade.Utils.GetType(attr.GetName()) == UsdShade.AttributeType.Output:
            return attr.GetBaseName(), UsdShade.Shader(attr.GetPrim())
        return attr.Get(self.time), None

    def _read(self, material: UsdShade.Material) -> _MaterialRow:
        row = _MaterialRow(np.full(3, PREVIEW_SURFACE_DIFFUSE), diffuse_authored=False)
        shader = material.ComputeSurfaceSource()[0]
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            return row  # not a preview surface: fall back like a bare material
        for name, attr_name in (
            ("metallic", "metallic"),
            ("roughness", "roughness"),
            ("opacity", "opacity"),
            ("ior", "ior"),
        ):
            value, src = self._value(shader, name)
            if src is None and value is not None and np.isfinite(float(value)):
                setattr(row, attr_name, float(value))
        row.metallic = float(np.clip(row.metallic, 0.0, 1.0))
        row.roughness = float(np.clip(row.roughness, 0.0, 1.0))
        row.opacity = float(np.clip(row.opacity, 0.0, 1.0))
        value, src = self._value(shader, "emissiveColor")
        if src is None and value is not None:
            row.emissive = np.nan_to_num(np.asarray(value, dtype=np.float64))
        value, src = self._value(shader, "diffuseColor")
        if src is not None:
            self._read_texture_input(row, src, value, str(material.GetPath()))
        elif value is not None:
            row.diffuse = np.clip(np.nan_to_num(np.asarray(value, dtype=np.float64)), 0, None)
            row.diffuse_authored = True
        return row

    def _read_texture_input(
        self, row: _MaterialRow, tex: UsdShade.Shader, output: str, where: str
    ) -> None:
        """Fill ``row`` from a UsdUVTexture feeding ``diffuseColor``."""
        if tex.GetIdAttr().Get() != "UsdUVTexture":
            return  # some other node (e.g. a primvar reader): keep the default colour
        file_value, _ = self._value(tex, "file")
        path = _asset_file(file_value, f"{tex.GetPath()}.inputs:file")
        fallback, _ = self._value(tex, "fallback")
        if not path:
            if fallback is not None:
                row.diffuse = np.asarray(fallback, dtype=np.float64)[:3]
                row.diffuse_authored = True
            return
        space, _ = self._value(tex, "sourceColorSpace")
        space = str(space or "auto")
        key = (path, space)
        if key not in self._textures:
            self._textures[key] = read_texture(path, f"{tex.GetPath()}.inputs:file", space)
        image = self._textures[key]
        scale, _ = self._value(tex, "scale")
        bias, _ = self._value(tex, "bias")
        if scale is not None or bias is not None:
            s = np.asarray(scale if scale is not None else (1, 1, 1, 1), np.float32)[:3]
            b = np.asarray(bias if bias is not None else (0, 0, 0, 0), np.float32)[:3]
            image = image * s + b
        channel = {"r": 0, "g": 1, "b": 2}.get(output)
        if channel is not None:
            image = np.repeat(image[..., channel : channel + 1], 3, axis=2)
        row.texture = np.ascontiguousarray(image, dtype=np.float32)
        row.diffuse = image.reshape(-1, 3).mean(axis=0).astype(np.float64)
        row.diffuse_authored = True
        st, reader = self._value(tex, "st")
        if reader is not None:
            varname, _ = self._value(reader, "varname")
            if varname:
                row.uv_primvar = str(varname)

    def table(self) -> MaterialTable:
        rows = self.rows
        return MaterialTable(
            diffuse=np.array([r.diffuse for r in rows], dtype=np.float32).reshape(-1, 3),
            metallic=np.array([r.metallic for r in rows], dtype=np.float32),
            roughness=np.array([r.roughness for r in rows], dtype=np.float32),
            opacity=np.array([r.opacity for r in rows], dtype=np.float32),
            ior=np.array([r.ior for r in rows], dtype=np.float32),
            emissive=np.array([r.emissive for r in rows], dtype=np.float32).reshape(-1, 3),
            textures=[r.texture for r in rows],
        )


# --------------------------------------------------------------------------------------
# Local (object-space) geometry of one gprim
# --------------------------------------------------------------------------------------


@dataclass
class _LocalMesh:
    """Triangles of one gprim in its own space (stage units).

    points         : (n, 3) float64
    triangles      : (T, 3) int64 into points, counter-clockwise = front
    corner_normals : (T, 3, 3) float64 unit normals (authored, analytic, or smooth)
    corner_albedo  : (T, 3, 3) float32 linear RGB
    tri_material   : (T,) int32 MaterialTable rows
    corner_uv      : (T, 3, 2) float32, or None when the gprim has no texture
    """

    points: np.ndarray
    triangles: np.ndarray
    corner_normals: np.ndarray
    corner_albedo: np.ndarray
    tri_material: np.ndarray
    corner_uv: np.ndarray | None = None
    smooth: bool = False  # normals are smooth_corner_normals(points): redo on deformation


def smooth_corner_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals, gathered to corners: (T, 3, 3) float64."""
    p = points[triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 * area
    acc = np.zeros_like(points)
    for c in range(3):
        for axis in range(3):
            acc[:, axis] += np.bincount(triangles[:, c], face[:, axis], minlength=len(points))
    vertex = _safe_normalize(acc)
    corner = vertex[triangles]
    # Vertices whose incident faces cancel (or have zero area) take their face normal.
    face_n = _safe_normalize(face)[:, None, :]
    bad = np.linalg.norm(acc, axis=1)[triangles] <= _MIN_NORMAL_LENGTH
    return np.where(bad[..., None], face_n, corner)


def _points_problems(points: np.ndarray, where: str) -> list[str]:
    """Render refusal of a point array (n, 3): non-finite values."""
    finite = np.all(np.isfinite(points), axis=1)
    if finite.all():
        return []
    return [f"{where}: non-finite point at index {int(np.argmax(~finite))}"]


def _check_points(points: np.ndarray, where: str) -> None:
    for problem in _points_problems(points, where):
        raise PhrtError(problem)


def _mesh_counts_indices(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[np.ndarray, np.ndarray]:
    """faceVertexCounts and faceVertexIndices at ``time`` as int64 arrays."""
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    return counts, indices


def _topology_problems(path, counts: np.ndarray, indices: np.ndarray, n_points: int) -> list[str]:
    """Render refusals of a mesh topology: negative counts, counts that do not add up to
    the indices, indices outside the points."""
    problems = []
    if np.any(counts < 0):
        problems.append(f"{path}.faceVertexCounts: negative face vertex count")
    if int(counts.sum()) != len(indices):
        problems.append(
            f"{path}.faceVertexIndices: {len(indices)} indices but faceVertexCounts "
            f"sums to {int(counts.sum())}"
        )
    if len(indices) and (indices.min() < 0 or indices.max() >= n_points):
        problems.append(
            f"{path}.faceVertexIndices: index out of range [0, {n_points}) "
            f"(min {indices.min()}, max {indices.max()})"
        )
    return problems


def mesh_problems(prim: Usd.Prim, time: float) -> list[str]:
    """Every reason the render refuses this UsdGeomMesh's points and topology at ``time``
    (the first is the message it raises), ``[]`` when it reads. Faces with fewer than
    3 vertices are not a refusal (they are skipped)."""
    code = Usd.TimeCode(float(time))
    points = _mesh_points_at(prim, code)
    counts, indices = _mesh_counts_indices(prim, code)
    path = prim.GetPath()
    return _points_problems(points, f"{path}.points") + _topology_problems(
        path, counts, indices, len(points)
    )


def mesh_problems_in_range(prim: Usd.Prim, frames: tuple[float, float]) -> list[str]:
    """``mesh_problems`` wherever the render reads this mesh over the frame range: at its
    start and, when the shape is animated (points or normals may vary, as the render
    decides), at every time sample inside the range of points and topology, with the
    refusal of a point count that changes. One message per location, the earliest."""
    start, end = frames
    problems = mesh_problems(prim, start)
    if problems or not _varies(prim, _SHAPE_ATTRS["Mesh"]):
        return problems
    n_points = len(_mesh_points_at(prim, Usd.TimeCode(start)))
    interval = Gf.Interval(start, end)
    times: set[float] = set()
    for name in (*_SHAPE_ATTRS["Mesh"], "faceVertexCounts", "faceVertexIndices"):
        attr = prim.GetAttribute(name)
        if attr:
            times.update(attr.GetTimeSamplesInInterval(interval))
    seen: set[str] = set()
    for t in sorted(times - {start}):
        found = mesh_problems(prim, t)
        if not found and len(_mesh_points_at(prim, Usd.TimeCode(t))) != n_points:
            found = [f"{prim.GetPath()}: topology changes at time {t} (not supported)"]
        for problem in found:
            where = problem.partition(": ")[0]
            if where not in seen:
                seen.add(where)
                problems.append(problem)
    return problems


def _mesh_topology(prim: Usd.Prim, time: Usd.TimeCode, n_points: int):
    """Validated fan triangulation of a UsdGeomMesh.

    Returns corners (T, 3) face-vertex ids, tri_face (T,), triangles (T, 3) point ids,
    all int64, with ``leftHanded`` winding already flipped.
    """
    mesh = UsdGeom.Mesh(prim)
    counts, indices = _mesh_counts_indices(prim, time)
    for problem in _topology_problems(prim.GetPath(), counts, indices, n_points):
        raise PhrtError(problem)
    corners, tri_face = _fan_corners(counts)
    if mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        corners = corners[:, [0, 2, 1]]
    return corners, tri_face, indices[corners]


def _mesh_points_at(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    """(n, 3) float64 points at ``time`` (unchecked; empty when unauthored)."""
    pts = UsdGeom.Mesh(prim).GetPointsAttr().Get(time)
    return np.asarray(pts if pts is not None else [], dtype=np.float64).reshape(-1, 3)


def _read_mesh_points(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    points = _mesh_points_at(prim, time)
    _check_points(points, f"{prim.GetPath()}.points")
    return points


def _mesh_normals(prim, time, corners, tri_face, triangles) -> np.ndarray | None:
    """Authored normals expanded to corners (T, 3, 3), or None (compute smooth)."""
    path = prim.GetPath()
    pv = _read_primvar(prim, "normals", time)
    if pv is not None:
        values, interp = pv
        where = f"{path}.primvars:normals"
    else:
        mesh = UsdGeom.Mesh(prim)
        attr = mesh.GetNormalsAttr()
        if not attr.HasAuthoredValue():
            return None
        raw = attr.Get(time)
        if raw is None or len(raw) == 0:
            return None
        values = np.asarray(raw, dtype=np.float64)
        interp = str(mesh.GetNormalsInterpolation())
        where = f"{path}.normals"
    values = np.nan_to_num(values.reshape(-1, 3))  # bad normals shade, not crash
    return _safe_normalize(_expand(values, interp, corners, tri_face, triangles, where))


def _display_color(prim, time, corners, tri_face, triangles) -> np.ndarray | None:
    """primvars:displayColor expanded to corners (T, 3, 3), or None when unauthored."""
    pv = _read_primvar(prim, "displayColor", time)
    if pv is None:
        return None
    values, interp = pv
    values = np.clip(np.nan_to_num(values.reshape(-1, 3)), 0.0, None)
    where = f"{prim.GetPath()}.primvars:displayColor"
    return _expand(values, interp, corners, tri_face, triangles, where)


def _face_materials(prim: Usd.Prim, n_faces: int, bank: _MaterialBank) -> tuple[np.ndarray, int]:
    """Material row per face (F,) int32 from the prim binding and materialBind subsets."""
    binding = UsdShade.MaterialBindingAPI(prim)
    base = bank.index(binding.ComputeBoundMaterial()[0])
    face_mat = np.full(n_faces, base, dtype=np.int32)
    for subset in binding.GetMaterialBindSubsets():
        sub_mat = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()[0]
        if not sub_mat:
            continue
        idx = np.asarray(subset.GetIndicesAttr().Get(bank.time) or [], dtype=np.int64)
        if len(idx) and (idx.min() < 0 or idx.max() >= n_faces):
            raise PhrtError(f"{subset.GetPath()}.indices: face index out of range")
        face_mat[idx] = bank.index(sub_mat)
    return face_mat, base


def _albedo(
    tri_material: np.ndarray, display: np.ndarray | None, bank: _MaterialBank
) -> np.ndarray:
    """Corner albedo (T, 3, 3) float32: material diffuse, else displayColor, else grey."""
    rows = bank.rows
    diffuse = np.array([r.diffuse for r in rows])[tri_material]  # (T, 3)
    authored = np.array([r.diffuse_authored for r in rows], dtype=bool)[tri_material]
    if display is None:
        no_material = tri_material == 0
        diffuse[no_material] = DEFAULT_GREY
        out = np.repeat(diffuse[:, None, :], 3, axis=1)
    else:
        out = np.where(authored[:, None, None], diffuse[:, None, :], display)
    return out.astype(np.float32)


def _read_mesh(prim: Usd.Prim, time: Usd.TimeCode, bank: _MaterialBank) -> _LocalMesh:
    points = _read_mesh_points(prim, time)
    corners, tri_face, triangles = _mesh_topology(prim, time, len(points))
    normals = _mesh_normals(prim, time, corners, tri_face, triangles)
    n_faces = len(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get(time) or [])
    face_mat, _ = _face_materials(prim, n_faces, bank)
    tri_material = face_mat[tri_face] if len(tri_face) else np.zeros(0, np.int32)
    display = _display_color(prim, time, corners, tri_face, triangles)
    albedo = _albedo(tri_material, display, bank)
    uv = None
    textured = [m for m in np.unique(tri_material) if bank.rows[m].texture is not None]
    if textured:
        name = bank.rows[textured[0]].uv_primvar
        pv = _read_primvar(prim, name, time)
        if pv is None:
            uv = np.zeros((len(triangles), 3, 2), np.float32)
        else:
            values, interp = pv
            where = f"{prim.GetPath()}.primvars:{name}"
            values = np.nan_to_num(values.reshape(len(values), -1)[:, :2])
            uv = _expand(values, interp, corners, tri_face, triangles, where).astype(np.float32)
    return _LocalMesh(
        points=points,
        triangles=triangles,
        corner_normals=normals if normals is not None else smooth_corner_normals(points, triangles),
        corner_albedo=albedo,
        tri_material=tri_material.astype(np.int32),
        corner_uv=uv,
        smooth=normals is None,
    )


# ---- implicit gprims (built along +Z, then rotated onto their axis) ------------------


def _grid_surface(profile_r: np.ndarray, profile_z: np.ndarray, normal_rz: np.ndarray):
    """Surface of revolution around +Z from a profile curve (ring k at radius r[k], z[k]).

    normal_rz : (k, 2) profile normals (radial, z). Returns points (n, 3), triangles
    (T, 3) and per-point normals (n, 3), counter-clockwise seen from outside.
    """
    seg = IMPLICIT_SEGMENTS
    phi = np.linspace(0.0, 2.0 * np.pi, seg, endpoint=False)
    c, s = np.cos(phi), np.sin(phi)
    pts = np.stack(
        [np.outer(profile_r, c), np.outer(profile_r, s), np.repeat(profile_z[:, None], seg, 1)],
        axis=-1,
    ).reshape(-1, 3)
    nrm = np.stack(
        [
            np.outer(normal_rz[:, 0], c),
            np.outer(normal_rz[:, 0], s),
            np.repeat(normal_rz[:, 1:2], seg, 1),
        ],
        axis=-1,
    ).reshape(-1, 3)
    k = len(profile_r)
    ring = np.arange(k - 1)[:, None] * seg
    j = np.arange(seg)[None, :]
    a = (ring + j).ravel()
    b = (ring + (j + 1) % seg).ravel()
    a2, b2 = a + seg, b + seg
    tris = np.concatenate([np.stack([a, b, b2], 1), np.stack([a, b2, a2], 1)])
    return pts, tris, _safe_normalize(nrm)


def _disk(radius: float, z: float, up: bool):
    """A flat disk at height z facing +Z (up) or -Z: points, triangles, normals."""
    seg = IMPLICIT_SEGMENTS
    phi = np.linspace(0.0, 2.0 * np.pi, seg, endpoint=False)
    pts = np.concatenate(
        [
            [[0.0, 0.0, z]],
            np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(seg, z)], 1),
        ]
    )
    j = np.arange(seg)
    tris = np.stack([np.zeros(seg, np.int64), 1 + j, 1 + (j + 1) % seg], 1)
    if not up:
        tris = tris[:, [0, 2, 1]]
    nrm = np.tile([0.0, 0.0, 1.0 if up else -1.0], (seg + 1, 1))
    return pts, tris, nrm


def _merge(parts):
    pts, tris, nrms, off = [], [], [], 0
    for p, t, n in parts:
        pts.append(p)
        tris.append(t + off)
        nrms.append(n)
        off += len(p)
    return np.concatenate(pts), np.concatenate(tris), np.concatenate(nrms)


def _sphere_profile(radius: float, z0: float, lat0: float, lat1: float, rings: int):
    lat = np.linspace(lat0, lat1, rings + 1)
    r = radius * np.cos(lat)
    z = z0 + radius * np.sin(lat)
    return r, z, np.stack([np.cos(lat), np.sin(lat)], 1)


def _implicit_z(kind: str, prim: Usd.Prim, time: Usd.TimeCode):
    """Tessellate an implicit gprim along +Z: points (n, 3), triangles, point normals."""
    g = lambda name, d: float(_attr(prim, name, time, d))  # noqa: E731
    if kind == "Sphere":
        r, z, n = _sphere_profile(g("radius", 1.0), 0.0, -np.pi / 2, np.pi / 2, IMPLICIT_RINGS)
        return _grid_surface(r, z, n)
    if kind == "Cube":
        h = 0.5 * g("size", 2.0)
        faces = []
        for axis in range(3):
            for sign in (1.0, -1.0):
                u, v = (axis + 1) % 3, (axis + 2) % 3
                quad = np.zeros((4, 3))
                quad[:, axis] = sign * h
                quad[:, u] = [-h, h, h, -h]
                quad[:, v] = [-h, -h, h, h]
                tri = np.array([[0, 1, 2], [0, 2, 3]])
                if sign < 0:
                    tri = tri[:, [0, 2, 1]]
                nrm = np.zeros((4, 3))
                nrm[:, axis] = sign
                faces.append((quad, tri, nrm))
        return _merge(faces)
    if kind == "Cylinder":
        r, hh = g("radius", 1.0), 0.5 * g("height", 2.0)
        side = _grid_surface(np.array([r, r]), np.array([-hh, hh]), np.array([[1, 0], [1, 0.0]]))
        return _merge([side, _disk(r, hh, True), _disk(r, -hh, False)])
    if kind == "Cone":
        r, h = g("radius", 1.0), g("height", 2.0)
        slope = np.array([h, r]) / max(np.hypot(h, r), _MIN_NORMAL_LENGTH)
        # Apex ring of radius 0 (duplicated per segment) keeps per-segment normals.
        side = _grid_surface(np.array([r, 0.0]), np.array([-h / 2, h / 2]), np.stack([slope] * 2))
        return _merge([side, _disk(r, -h / 2, False)])
    if kind == "Capsule":
        r, hh = g("radius", 0.5), 0.5 * g("height", 1.0)
        half = IMPLICIT_RINGS // 2
        lo = _sphere_profile(r, -hh, -np.pi / 2, 0.0, half)
        hi = _sphere_profile(r, hh, 0.0, np.pi / 2, half)
        prof = [np.concatenate([a, b]) for a, b in zip(lo, hi, strict=True)]
        return _grid_surface(*prof)
    raise AssertionError(kind)


#: UsdGeomPlane: (width axis, length axis) for each value of ``axis`` (the normal).
_PLANE_AXES = {"X": (2, 1), "Y": (0, 2), "Z": (0, 1)}


def _plane(prim: Usd.Prim, time: Usd.TimeCode):
    """A UsdGeomPlane as two triangles facing +axis: points, triangles, point normals.

    Single-sided (front = +axis); ``doubleSided`` is left to the renderer's culling.
    """
    axis = str(_attr(prim, "axis", time, "Z"))
    u, v = _PLANE_AXES.get(axis, _PLANE_AXES["Z"])
    n = 3 - u - v
    half_w = 0.5 * float(_attr(prim, "width", time, 2.0))
    half_l = 0.5 * float(_attr(prim, "length", time, 2.0))
    pts = np.zeros((4, 3))
    pts[:, u] = [-half_w, half_w, half_w, -half_w]
    pts[:, v] = [-half_l, -half_l, half_l, half_l]
    normal = np.eye(3)[n]
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    if np.dot(np.cross(pts[1] - pts[0], pts[2] - pts[0]), normal) < 0:
        tris = tris[:, [0, 2, 1]]  # (u, v, n) is a left-handed frame for axis X
    return pts, tris, np.tile(normal, (4, 1))


#: Cyclic permutations (proper rotations, det +1) taking the +Z-built shape onto axis X
#: or Y: ``new = old[:, perm]`` moves the old Z column to the new axis.
_AXIS_PERMUTATION = {"Z": [0, 1, 2], "X": [2, 0, 1], "Y": [1, 2, 0]}


def _implicit_geometry(kind: str, prim: Usd.Prim, time: Usd.TimeCode):
    """Points (n, 3), triangles (T, 3), corner normals (T, 3, 3) in prim space."""
    if kind == "Plane":
        pts, tris, nrm = _plane(prim, time)
    else:
        pts, tris, nrm = _implicit_z(kind, prim, time)
        axis = str(_attr(prim, "axis", time, "Z")) if kind not in ("Sphere", "Cube") else "Z"
        perm = _AXIS_PERMUTATION.get(axis, [0, 1, 2])
        pts, nrm = pts[:, perm], nrm[:, perm]
    _check_points(pts, f"{prim.GetPath()} (size attributes)")
    return pts, tris.astype(np.int64), nrm[tris]


def _read_implicit(
    kind: str, prim: Usd.Prim, time: Usd.TimeCode, bank: _MaterialBank
) -> _LocalMesh:
    pts, tris, normals = _implicit_geometry(kind, prim, time)
    mat = bank.index(UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0])
    tri_material = np.full(len(tris), mat, dtype=np.int32)
    display = None
    pv = _read_primvar(prim, "displayColor", time)
    if pv is not None:
        color = np.clip(np.nan_to_num(pv[0].reshape(-1, 3)[0]), 0.0, None)
        display = np.broadcast_to(color, (len(tris), 3, 3))
    albedo = _albedo(tri_material, display, bank)
    uv = np.zeros((len(tris), 3, 2), np.float32) if bank.rows[mat].texture is not None else None
    return _LocalMesh(pts, tris, normals, albedo, tri_material, uv)


# --------------------------------------------------------------------------------------
# Elements and their transforms
# --------------------------------------------------------------------------------------


class _TimeContext:
    """Transform queries at one time code (stage units, USD row-vector matrices)."""

    def __init__(self, time: float):
        self.time = float(time)
        self.code = Usd.TimeCode(time)
        self.cache = UsdGeom.XformCache(self.code)
        self._instances: dict[str, np.ndarray] = {}

    def world(self, prim: Usd.Prim) -> np.ndarray:
        """(4, 4) local → world (stage units), row-vector convention (p' = p @ M)."""
        return np.array(self.cache.GetLocalToWorldTransform(prim))

    def instance_xforms(self, instancer: Usd.Prim) -> np.ndarray:
        """(n, 4, 4) per-instance prototype → instancer transforms (mask ignored)."""
        key = str(instancer.GetPath())
        if key not in self._instances:
            pi = UsdGeom.PointInstancer(instancer)
            xf = pi.ComputeInstanceTransformsAtTime(
                self.code,
                self.code,
                UsdGeom.PointInstancer.IncludeProtoXform,
                UsdGeom.PointInstancer.IgnoreMask,
            )
            arr = np.array([np.array(m) for m in xf]).reshape(-1, 4, 4) if xf else None
            self._instances[key] = np.zeros((0, 4, 4)) if arr is None else arr
        return self._instances[key]


@dataclass
class _Part:
    """One element's geometry: its local mesh and how to place it at a time."""

    element: int
    path: str
    mesh: _LocalMesh
    matrix_at: Callable[[_TimeContext], np.ndarray]  # (4, 4) row-vector, stage units
    shape_at: _ShapeAt | None  # deforming points / normals, or None
    animated: bool
    v0: int = 0
    t0: int = 0
    matrix: np.ndarray | None = None
    flipped: bool = False  # winding flipped for a negative-determinant transform


def reflector_problems(prim: Usd.Prim, path: str | None = None) -> list[str]:
    """Every reason the render refuses a reflector gprim's K and F (``path`` names the
    element, default the prim path): K must be finite and >= 0, F finite (F outside
    [0, 1] is clamped, not refused). ``[]`` for a valid reflector or a non-reflector."""
    if not schema.is_reflector(prim):
        return []
    path = str(prim.GetPath()) if path is None else path
    k = schema.reflector_priority(prim)
    f = schema.reflector_reflectivity(prim)
    problems = []
    if not np.isfinite(k) or k < 0:
        problems.append(f"{path}.{schema.PRIORITY}: must be a finite number >= 0, got {k}")
    if not np.isfinite(f):
        problems.append(f"{path}.{schema.REFLECTIVITY}: must be finite, got {f}")
    return problems


def _element_flags(prim: Usd.Prim, path: str) -> tuple[bool, float, float]:
    """(is_reflector, K, F) of a gprim; K and F are 0 for non-reflectors."""
    if not schema.is_reflector(prim):
        return False, 0.0, 0.0
    for problem in reflector_problems(prim, path):
        raise PhrtError(problem)
    k = schema.reflector_priority(prim)
    f = schema.reflector_reflectivity(prim)
    return True, k, float(np.clip(f, 0.0, 1.0))  # F is a blend weight: clamp to [0, 1]


class _AnimationProbe:
    """Memoised 'might this prim's world transform vary in time' up the ancestor chain."""

    def __init__(self):
        self._memo: dict[str, bool] = {}

    def xform_varies(self, prim: Usd.Prim) -> bool:
        if not prim or prim.IsPseudoRoot():
            return False
        key = str(prim.GetPath())
        if key not in self._memo:
            xf = UsdGeom.Xformable(prim)
            own = bool(xf) and xf.TransformMightBeTimeVarying()
            reset = bool(xf) and xf.GetResetXformStack()
            self._memo[key] = own or (not reset and self.xform_varies(prim.GetParent()))
        return self._memo[key]


def _varies(prim: Usd.Prim, names: tuple[str, ...]) -> bool:
    return any((a := prim.GetAttribute(n)) and a.ValueMightBeTimeVarying() for n in names)


#: Attributes whose animation changes a gprim's local shape.
_SHAPE_ATTRS = {
    "Mesh": ("points", "normals", "primvars:normals"),
    "Sphere": ("radius",),
    "Cube": ("size",),
    "Cylinder": ("radius", "height"),
    "Cone": ("radius", "height"),
    "Capsule": ("radius", "height"),
    "Plane": ("width", "length"),
}


#: Prim types the render reads as geometry (other gprims, e.g. curves, are not drawn).
RENDERED_GPRIM_TYPES = tuple(_SHAPE_ATTRS)


def _shape_kind(prim: Usd.Prim) -> str | None:
    t = prim.GetTypeName()
    return t if t in _SHAPE_ATTRS else None


#: Deformation reader: time → (local points (n, 3), corner normals (T, 3, 3) or None
#: when the normals are analytic or smooth).
_ShapeAt = Callable[[Usd.TimeCode], tuple[np.ndarray, np.ndarray | None]]


def _local_shape_fn(kind: str, prim: Usd.Prim) -> _ShapeAt:
    """Reader of a deforming gprim's points (and authored normals) at a time."""
    if kind != "Mesh":
        return lambda code: (_implicit_geometry(kind, prim, code)[0], None)

    def mesh_at(code: Usd.TimeCode):
        points = _read_mesh_points(prim, code)
        corners, tri_face, triangles = _mesh_topology(prim, code, len(points))
        return points, _mesh_normals(prim, code, corners, tri_face, triangles)

    return mesh_at


# --------------------------------------------------------------------------------------
# Lights
# --------------------------------------------------------------------------------------


def _light_radiance(prim: Usd.Prim, code: Usd.TimeCode) -> np.ndarray:
    """(3,) color * intensity * 2**exposure, finite and >= 0."""
    color = np.asarray(_attr(prim, "inputs:color", code, (1.0, 1.0, 1.0)), dtype=np.float64)
    intensity = float(_attr(prim, "inputs:intensity", code, 1.0))
    exposure = float(_attr(prim, "inputs:exposure", code, 0.0))
    # Exposure is a log2 scale; clamp so 2**exposure stays finite in float64.
    value = color * intensity * 2.0 ** np.clip(exposure, -1000.0, 1000.0)
    return np.clip(np.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def _rotation_columns(m_row: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal rotation (column-vector convention) of a row-vector matrix.

    Scale is stripped by Gram-Schmidt, keeping the -Z (view / light) axis exact. A
    degenerate matrix falls back to the identity rotation.
    """
    cols = m_row[:3, :3].T.astype(np.float64)  # column j = image of axis j
    z = cols[:, 2]
    if np.linalg.norm(z) < _MIN_NORMAL_LENGTH:
        return np.eye(3)
    z = z / np.linalg.norm(z)
    y = cols[:, 1] - np.dot(cols[:, 1], z) * z
    if np.linalg.norm(y) < 1e-12 * max(np.linalg.norm(cols[:, 1]), 1e-300):
        y = np.eye(3)[int(np.argmin(np.abs(z)))]
        y = y - np.dot(y, z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


#: UsdLux lights approximated as a point ``LocalLight`` at their centre.
_LOCAL_LIGHT_TYPES = (UsdLux.SphereLight, UsdLux.RectLight, UsdLux.DiskLight, UsdLux.CylinderLight)


def _read_light(prim: Usd.Prim, ctx: _TimeContext, mpu: float, lights: Lights) -> None:
    code = ctx.code
    m = ctx.world(prim)
    path = str(prim.GetPath())
    if prim.IsA(UsdLux.DistantLight):
        # The light shines down its -Z axis; store the direction towards the light.
        towards = _safe_normalize(m[2, :3])
        angle = float(_attr(prim, "inputs:angle", code, 0.53))
        lights.distant.append(DistantLight(towards, _light_radiance(prim, code), angle))
    elif any(prim.IsA(t) for t in _LOCAL_LIGHT_TYPES):
        radiance = _light_radiance(prim, code)
        scale = np.linalg.norm(m[:3, :3], axis=1) * mpu  # metres per light-space unit
        normalize = bool(_attr(prim, "inputs:normalize", code, False))
        if prim.IsA(UsdLux.SphereLight):
            radius = float(_attr(prim, "inputs:radius", code, 0.5)) * float(scale.max())
        elif prim.IsA(UsdLux.RectLight):
            w = float(_attr(prim, "inputs:width", code, 1.0)) * scale[0]
            h = float(_attr(prim, "inputs:height", code, 1.0)) * scale[1]
            radius = 0.5 * float(np.hypot(w, h))
            if not normalize:
                radiance = radiance * w * h  # area light → point intensity
        elif prim.IsA(UsdLux.DiskLight):
            r = float(_attr(prim, "inputs:radius", code, 0.5))
            radius = r * float(max(scale[0], scale[1]))
            if not normalize:
                radiance = radiance * np.pi * (r * scale[0]) * (r * scale[1])
        else:  # CylinderLight: a tube along its local X axis
            r = float(_attr(prim, "inputs:radius", code, 0.5)) * float(max(scale[1], scale[2]))
            length = float(_attr(prim, "inputs:length", code, 1.0)) * scale[0]
            radius = 0.5 * float(np.hypot(length, 2 * r))
            if not normalize:
                radiance = radiance * 2.0 * np.pi * r * length  # lateral area
        if not np.isfinite(radius):
            raise PhrtError(f"{path}: non-finite light size")
        lights.local.append(LocalLight(m[3, :3] * mpu, radiance, abs(radius)))
    elif prim.IsA(UsdLux.DomeLight):
        if lights.dome is not None:
            return  # one environment: the first dome light wins
        fmt = str(_attr(prim, "inputs:texture:format", code, "automatic"))
        if fmt not in ("automatic", "latlong"):
            raise PhrtError(f"{path}.inputs:texture:format: {fmt!r} unsupported (latlong only)")
        file_value = _attr(prim, "inputs:texture:file", code, None)
        where = f"{path}.inputs:texture:file"
        file = _asset_file(file_value, where) if file_value is not None else ""
        texture = read_texture(file, where, "auto") if file else None
        lights.dome = DomeLight(_light_radiance(prim, code), texture, _rotation_columns(m))


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


def choose_camera(stage: Usd.Stage, camera: str | None = None) -> Usd.Prim:
    """The camera the render uses (module doc, step 1). Raises ``PhrtError`` when there is
    none, or when the chosen path / the render settings' target is not a UsdGeomCamera."""
    if camera:
        prim = stage.GetPrimAtPath(camera) if Sdf.Path.IsValidPathString(camera) else None
        if not prim or not prim.IsA(UsdGeom.Camera):
            raise PhrtError(f"{camera}: no UsdGeomCamera prim at this path (--camera)")
        return prim
    settings_prim = schema.find_render_settings(stage)
    if settings_prim is not None:
        settings = UsdRender.Settings(settings_prim)
        targets = settings.GetCameraRel().GetForwardedTargets()
        if targets:
            prim = stage.GetPrimAtPath(targets[0])
            if not prim or not prim.IsA(UsdGeom.Camera):
                raise PhrtError(
                    f"{settings.GetPath()}.camera: target {targets[0]} is not a UsdGeomCamera"
                )
            return prim
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera):
            return prim
    raise PhrtError(f"{stage.GetRootLayer().identifier}: stage has no UsdGeomCamera")


def stage_problems(stage: Usd.Stage) -> list[str]:
    """Render refusals of the stage metadata: metersPerUnit must be finite and > 0."""
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    if np.isfinite(mpu) and mpu > 0:
        return []
    return [f"{stage.GetRootLayer().identifier}: metersPerUnit must be > 0, got {mpu}"]


def frame_range(stage: Usd.Stage, path_driver: CameraPath | None) -> tuple[float, float]:
    """(start, end) time codes rendered by default: the driving camera path's, else the
    stage's start/end time codes."""
    if path_driver is not None:
        return (path_driver.start_frame, path_driver.end_frame)
    return (float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode()))


@dataclass
class _CameraValues:
    world: np.ndarray | None  # (4, 4) row-vector local → world, stage units (None: driven)
    focal: float
    aperture: float
    near: float
    far: float
    problems: list[str]


def _camera_values(prim: Usd.Prim, time: float, driven: bool) -> _CameraValues:
    """The camera's attributes at ``time`` and every reason the render refuses them."""
    code = Usd.TimeCode(float(time))
    cam = UsdGeom.Camera(prim)
    where = str(prim.GetPath())
    problems = []
    if cam.GetProjectionAttr().Get(code) == UsdGeom.Tokens.orthographic:
        problems.append(f"{where}.projection: orthographic cameras are not supported")
    world = None
    if not driven:
        world = np.array(UsdGeom.XformCache(code).GetLocalToWorldTransform(prim))
        if not np.all(np.isfinite(world)):
            problems.append(f"{where}: non-finite camera transform at time {time}")
    focal = float(cam.GetFocalLengthAttr().Get(code))
    aperture = float(cam.GetHorizontalApertureAttr().Get(code))
    near, far = (float(x) for x in cam.GetClippingRangeAttr().Get(code))
    if not (np.isfinite(focal) and focal > 0):
        problems.append(f"{where}.focalLength: must be > 0 at time {time}, got {focal}")
    if not (np.isfinite(aperture) and aperture > 0):
        problems.append(f"{where}.horizontalAperture: must be > 0 at time {time}, got {aperture}")
    if not (np.isfinite(near) and np.isfinite(far) and far > near):
        problems.append(f"{where}.clippingRange: need near < far, got ({near}, {far})")
    return _CameraValues(world, focal, aperture, near, far, problems)


def camera_problems(prim: Usd.Prim, time: float, driven: bool = False) -> list[str]:
    """Every reason the render refuses the camera at ``time`` (the first is what
    ``StageScene.camera`` raises): orthographic projection, a non-finite transform
    (unless a camera path drives it, ``driven``), focal length or horizontal aperture
    not > 0, clipping range not near < far."""
    return _camera_values(prim, time, driven).problems


_CAMERA_ATTRS = ("projection", "focalLength", "horizontalAperture", "clippingRange")


def camera_check_times(prim: Usd.Prim, frames: tuple[float, float], driven: bool) -> list[float]:
    """Times at which ``camera_problems`` covers the whole frame range: its start and end
    and every time sample inside it of the camera attributes and (unless driven) of the
    transforms of the camera and its ancestors. Values between samples are linear
    interpolations, so their extremes are at these times."""
    start, end = frames
    interval = Gf.Interval(start, end)
    times = {start, end}
    for name in _CAMERA_ATTRS:
        attr = prim.GetAttribute(name)
        if attr:
            times.update(attr.GetTimeSamplesInInterval(interval))
    p = prim
    while not driven and p and not p.IsPseudoRoot():
        xf = UsdGeom.Xformable(p)
        if xf:
            times.update(xf.GetTimeSamplesInInterval(interval))
            if xf.GetResetXformStack():
                break
        p = p.GetParent()
    return sorted(float(t) for t in times)


# --------------------------------------------------------------------------------------
# What the render reads
# --------------------------------------------------------------------------------------


def _walk_subtree(root: Usd.Prim, code: Usd.TimeCode, top: bool = True):
    """(kind, prim) of what the render reads under ``root`` at ``code``, in its order.

    kind: a gprim type (``_SHAPE_ATTRS``), or with ``top`` "PointInstancer" (its subtree
    is not walked: prototypes render only through the instancer) and "Light". Subtrees
    that are invisible, guide or proxy are pruned (``_pruned``). Inside a prototype
    (``top`` False) only gprims are yielded and nested instancers are walked through, not
    expanded.
    """
    if not root:
        return
    it = iter(Usd.PrimRange(root, Usd.TraverseInstanceProxies()))
    for prim in it:
        if _pruned(prim, code):
            it.PruneChildren()
            continue
        kind = _shape_kind(prim)
        if kind is not None:
            yield kind, prim
        elif not top:
            continue
        elif prim.IsA(UsdGeom.PointInstancer):
            yield "PointInstancer", prim
            it.PruneChildren()
        elif prim.HasAPI(UsdLux.LightAPI):
            yield "Light", prim


def rendered_gprims(stage: Usd.Stage, time: float):
    """(kind, prim) of every gprim the render reads at ``time`` (the start of the frame
    range): those of the stage and, once each, those of the PointInstancer prototypes."""
    code = Usd.TimeCode(float(time))
    seen: set[str] = set()
    prototypes: list[Sdf.Path] = []
    for kind, prim in _walk_subtree(stage.GetPseudoRoot(), code):
        if kind == "PointInstancer":
            prototypes += UsdGeom.PointInstancer(prim).GetPrototypesRel().GetForwardedTargets()
        elif kind != "Light" and str(prim.GetPath()) not in seen:
            seen.add(str(prim.GetPath()))
            yield kind, prim
    for proto in dict.fromkeys(prototypes):
        for kind, prim in _walk_subtree(stage.GetPrimAtPath(proto), code, top=False):
            if str(prim.GetPath()) not in seen:
                seen.add(str(prim.GetPath()))
                yield kind, prim


# --------------------------------------------------------------------------------------
# Composition: sublayers, references and payloads USD could not open
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CompositionProblem:
    """One composition error of the stage (``Usd.Stage.GetCompositionErrors``).

    kind    : "sublayer", "reference", "payload", or "other" (any other Pcp error)
    where   : the prim whose arc failed; for a sublayer, the layer that lists it
    asset   : the asset path USD could not open, as USD resolved it ("" for "other")
    message : one line, ``"<where>: <what>"`` (``phrt validate`` reports it as an error)
    """

    kind: str
    where: str
    asset: str
    message: str


_ASSET_ERROR = re.compile(
    r"Could not open asset @(?P<asset>.*?)@ for (?P<arc>\w+) introduced by "
    r"@(?P<layer>.*?)@<(?P<site>[^>]*)>\.?(?:\s*--\s*(?P<reason>.*?))?\.?$"
)
_SUBLAYER_ERROR = re.compile(r"Could not load sublayer @(?P<asset>.*?)@ of layer @(?P<layer>.*?)@")


def composition_problems(stage: Usd.Stage) -> list[CompositionProblem]:
    """Sublayers, references and payloads the stage names but USD could not open, and
    the stage's other composition errors, one each, sorted by location (USD's own order
    varies). Muted layers are intentional and not reported."""
    problems = []
    for err in stage.GetCompositionErrors():
        if err.errorType == Pcp.ErrorType_MutedAssetPath:
            continue
        text = " ".join(str(err).split())
        prim = str(err.rootSite.path)
        m = _ASSET_ERROR.search(text)
        if m and err.errorType == Pcp.ErrorType_InvalidAssetPath:
            arc = m["arc"] if m["arc"] in ("reference", "payload") else "reference"
            reason = f" ({m['reason']})" if m["reason"] else ""
            problems.append(
                CompositionProblem(
                    arc, prim, m["asset"], f"{prim}: cannot open {arc} {m['asset']}{reason}"
                )
            )
            continue
        m = _SUBLAYER_ERROR.search(text)
        if m and err.errorType == Pcp.ErrorType_InvalidSublayerPath:
            problems.append(
                CompositionProblem(
                    "sublayer",
                    m["layer"],
                    m["asset"],
                    f"{m['layer']}: cannot open sublayer {m['asset']}",
                )
            )
            continue
        problems.append(CompositionProblem("other", prim, "", f"{prim}: {text}"))
    return sorted(problems, key=lambda p: (p.where, p.message))


#: Prim paths listed in one composition warning before "and N more".
_WARNING_PATHS = 5


def composition_warnings(problems: list[CompositionProblem]) -> list[str]:
    """One-line render warnings for ``composition_problems``: per missing reference or
    payload asset, the number of prims that render without its content and their paths;
    per missing sublayer, the layer (the number of prims it held is unknown)."""
    by_asset: dict[tuple[str, str], list[str]] = {}
    warnings = []
    for p in problems:
        if p.kind in ("reference", "payload"):
            by_asset.setdefault((p.kind, p.asset), []).append(p.where)
        elif p.kind == "sublayer":
            warnings.append(
                f"missing sublayer {p.asset} of {p.where}: not rendered "
                "(how many prims it held is unknown)"
            )
        else:
            warnings.append(f"composition error: {p.message}")
    for (kind, asset), prims in by_asset.items():
        shown = ", ".join(prims[:_WARNING_PATHS])
        if len(prims) > _WARNING_PATHS:
            shown += f" and {len(prims) - _WARNING_PATHS} more"
        n = len(prims)
        count = "1 prim renders" if n == 1 else f"{n} prims render"
        warnings.append(f"missing {kind} {asset}: {count} without its content ({shown})")
    return warnings


# --------------------------------------------------------------------------------------
# The stage scene
# --------------------------------------------------------------------------------------


class StageScene:
    """A USD stage read for rendering.

    stage                 : the opened ``Usd.Stage``
    scene                 : ``phrt_usd.model.scene.Scene``, valid at the last ``set_time``
    camera_path           : prim path of the camera used
    frame_range           : (start, end) time codes — the PhrtCameraPath's if one drives
                            the camera, else the stage's start/end time codes
    time_codes_per_second : from the stage
    warnings              : list[str], one line each: what the render goes on without
                            (missing sublayers, references, payloads; ``composition_warnings``)
    """

    def __init__(self, stage: Usd.Stage, camera: str | None = None):
        self.stage = stage
        for problem in stage_problems(stage):
            raise PhrtError(problem)
        self.meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(stage))
        self.up_axis = str(UsdGeom.GetStageUpAxis(stage))
        self.time_codes_per_second = float(stage.GetTimeCodesPerSecond())
        self.warnings: list[str] = composition_warnings(composition_problems(stage))
        cam_prim = choose_camera(stage, camera)
        self.camera_path = str(cam_prim.GetPath())
        self._camera_prim = cam_prim
        self.path_driver: CameraPath | None = find_camera_path(stage, self.camera_path)
        self.frame_range = frame_range(stage, self.path_driver)
        self._time = self.frame_range[0]
        # Refuse a camera that cannot render the first frame before reading any geometry.
        for problem in camera_problems(cam_prim, self._time, self.path_driver is not None):
            raise PhrtError(problem)
        self._build(_TimeContext(self._time))

    # ---- reading ------------------------------------------------------------------

    def _build(self, ctx: _TimeContext) -> None:
        bank = _MaterialBank(ctx.code)
        probe = _AnimationProbe()
        lights = Lights()
        parts: list[_Part] = []
        elements: list[Element] = []
        mesh_cache: dict[tuple, _LocalMesh] = {}

        def local_mesh(prim: Usd.Prim, kind: str) -> _LocalMesh:
            # Instance proxies of one prototype share their triangulation (materials
            # may differ per instance, so the binding is part of the key).
            key = None
            if prim.IsInstanceProxy():
                mat = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
                proto = prim.GetPrimInPrototype().GetPath()
                key = (str(proto), material_key(mat))
                if key in mesh_cache:
                    return mesh_cache[key]
            if kind == "Mesh":
                mesh = _read_mesh(prim, ctx.code, bank)
            else:
                mesh = _read_implicit(kind, prim, ctx.code, bank)
            if key is not None:
                mesh_cache[key] = mesh
            return mesh

        def add(prim, path, kind, mesh, matrix_at, xform_animated):
            shape_animated = _varies(prim, _SHAPE_ATTRS[kind])
            refl, k, f = _element_flags(prim, path)
            if shape_animated:
                mesh = dataclasses.replace(mesh)  # deforms on its own, even if shared
            elements.append(Element(path, refl, k, f, np.zeros(3), np.zeros(3)))
            parts.append(
                _Part(
                    element=len(elements) - 1,
                    path=path,
                    mesh=mesh,
                    matrix_at=matrix_at,
                    shape_at=_local_shape_fn(kind, prim) if shape_animated else None,
                    animated=xform_animated or shape_animated,
                )
            )
            elements[-1].animated = parts[-1].animated

        for kind, prim in _walk_subtree(self.stage.GetPseudoRoot(), ctx.code):
            if kind == "PointInstancer":
                self._expand_instancer(prim, ctx, probe, bank, add)
            elif kind == "Light":
                _read_light(prim, ctx, self.meters_per_unit, lights)
            else:
                mesh = local_mesh(prim, kind)
                add(
                    prim,
                    str(prim.GetPath()),
                    kind,
                    mesh,
                    lambda c, p=prim: c.world(p),
                    probe.xform_varies(prim),
                )

        self._parts = parts
        self._animated = [p for p in parts if p.animated]
        self._assemble(parts, elements, bank, lights, ctx)

    def _expand_instancer(self, prim, ctx, probe, bank, add) -> None:
        """One element per (instance, prototype gprim) of a PointInstancer."""
        pi = UsdGeom.PointInstancer(prim)
        where = str(prim.GetPath())
        protos = pi.GetPrototypesRel().GetForwardedTargets()
        proto_idx = np.asarray(pi.GetProtoIndicesAttr().Get(ctx.code) or [], dtype=np.int64)
        if len(proto_idx) and (proto_idx.min() < 0 or proto_idx.max() >= len(protos)):
            raise PhrtError(f"{where}.protoIndices: index out of range [0, {len(protos)})")
        xforms = ctx.instance_xforms(prim)
        if len(xforms) != len(proto_idx):
            raise PhrtError(f"{where}: instance transforms do not match protoIndices")
        if not np.all(np.isfinite(xforms)):
            raise PhrtError(f"{where}: non-finite instance transform (positions/scales)")
        mask = pi.ComputeMaskAtTime(ctx.code)  # inactive and invisible ids → False
        visible = np.ones(len(proto_idx), bool) if not mask else np.asarray(mask, bool)
        animated = probe.xform_varies(prim) or _varies(
            prim,
            (
                "positions",
                "orientations",
                "orientationsf",
                "scales",
                "protoIndices",
                "velocities",
                "angularVelocities",
            ),
        )
        # Gprims of each prototype, with their transform relative to the prototype root.
        proto_gprims: list[list[tuple[Usd.Prim, str, str, np.ndarray, _LocalMesh]]] = []
        for proto_path in protos:
            root = self.stage.GetPrimAtPath(proto_path)
            found = []
            for kind, g in _walk_subtree(root, ctx.code, top=False):
                rel = np.array(ctx.cache.ComputeRelativeTransform(g, root)[0])
                if g == root:
                    rel = np.eye(4)  # the root's own xform is in the instance transform
                suffix = str(g.GetPath().MakeRelativePath(root.GetPath()))
                mesh = (
                    _read_mesh(g, ctx.code, bank)
                    if kind == "Mesh"
                    else _read_implicit(kind, g, ctx.code, bank)
                )
                found.append((g, kind, suffix, rel, mesh))
            proto_gprims.append(found)
        for i in np.flatnonzero(visible):
            gprims = proto_gprims[proto_idx[i]]
            for g, kind, suffix, rel, mesh in gprims:
                path = f"{where}.instance[{i}]"
                if len(gprims) > 1 or suffix != ".":
                    path += f"/{suffix}" if suffix != "." else ""

                def matrix_at(c, rel=rel, i=int(i)):
                    inst = c.instance_xforms(prim)
                    if i >= len(inst):
                        raise PhrtError(
                            f"{where}: instance count changed at time {c.time} (not supported)"
                        )
                    return rel @ inst[i] @ c.world(prim)

                add(g, path, kind, mesh, matrix_at, animated or probe.xform_varies(g))

    def _assemble(self, parts, elements, bank, lights, ctx) -> None:
        """Allocate the world-space batch and fill it at ``ctx``."""
        v = t = 0
        for p in parts:
            p.v0, p.t0 = v, t
            v += len(p.mesh.points)
            t += len(p.mesh.triangles)
        any_uv = any(p.mesh.corner_uv is not None for p in parts)
        tri_element = np.zeros(t, np.int32)
        triangles = np.zeros((t, 3), np.int64)
        for p in parts:
            sl = slice(p.t0, p.t0 + len(p.mesh.triangles))
            tri_element[sl] = p.element
            triangles[sl] = p.mesh.triangles + p.v0

        def cat(arrays, shape, dtype):
            return np.concatenate(arrays).astype(dtype) if arrays else np.zeros(shape, dtype)

        geometry = Geometry(
            vertices=np.zeros((v, 3)),
            triangles=triangles,
            tri_element=tri_element,
            tri_material=cat([p.mesh.tri_material for p in parts], (0,), np.int32),
            corner_normals=np.zeros((t, 3, 3), np.float32),
            corner_albedo=cat([p.mesh.corner_albedo for p in parts], (0, 3, 3), np.float32),
            corner_uv=None,
        )
        if any_uv:
            geometry.corner_uv = cat(
                [
                    p.mesh.corner_uv
                    if p.mesh.corner_uv is not None
                    else np.zeros((len(p.mesh.triangles), 3, 2), np.float32)
                    for p in parts
                ],
                (0, 3, 2),
                np.float32,
            )
        self.scene = Scene(
            elements=elements,
            geometry=geometry,
            materials=bank.table(),
            lights=lights,
            origin=np.zeros(3),
            meters_per_unit=self.meters_per_unit,
            up_axis=self.up_axis,
        )
        for p in parts:
            self._place(p, ctx, force=True)
        if v:
            self.scene.origin = 0.5 * (
                geometry.vertices.min(axis=0) + geometry.vertices.max(axis=0)
            )

    def _place(self, p: _Part, ctx: _TimeContext, force: bool = False) -> bool:
        """Transform part ``p`` to world metres at ``ctx``; True if anything changed."""
        m = p.matrix_at(ctx)
        if not np.all(np.isfinite(m)):
            raise PhrtError(f"{p.path}: non-finite transform at time {ctx.time}")
        mesh = p.mesh
        new_points = new_normals = None
        if p.shape_at is not None:
            new_points, new_normals = p.shape_at(ctx.code)
            if len(new_points) != len(mesh.points) or (
                new_normals is not None and len(new_normals) != len(mesh.triangles)
            ):
                raise PhrtError(f"{p.path}: topology changes at time {ctx.time} (not supported)")
        same_xform = p.matrix is not None and np.array_equal(m, p.matrix)
        if not force and same_xform:
            if new_points is None or (
                np.array_equal(new_points, mesh.points)
                and (new_normals is None or np.array_equal(new_normals, mesh.corner_normals))
            ):
                return False
        if new_points is not None:
            mesh.points = new_points
            if new_normals is not None:
                mesh.corner_normals = new_normals
            elif mesh.smooth:
                mesh.corner_normals = smooth_corner_normals(new_points, mesh.triangles)
        p.matrix = m
        g = self.scene.geometry
        nv, nt = len(mesh.points), len(mesh.triangles)
        vs, ts = slice(p.v0, p.v0 + nv), slice(p.t0, p.t0 + nt)
        world = (mesh.points @ m[:3, :3] + m[3, :3]) * self.meters_per_unit
        g.vertices[vs] = world
        n = mesh.corner_normals.reshape(-1, 3) @ _normal_matrix(m[:3, :3])
        corner_n = _safe_normalize(n).reshape(-1, 3, 3)
        flipped = float(np.linalg.det(m[:3, :3])) < 0
        if flipped:
            corner_n = corner_n[:, [0, 2, 1]]
        if force or flipped != p.flipped:
            order = [0, 2, 1] if flipped else [0, 1, 2]
            g.triangles[ts] = mesh.triangles[:, order] + p.v0
            start = p.t0
            g.corner_albedo[ts] = mesh.corner_albedo[:, order]
            if g.corner_uv is not None and mesh.corner_uv is not None:
                g.corner_uv[start : start + nt] = mesh.corner_uv[:, order]
            p.flipped = flipped
        g.corner_normals[ts] = corner_n
        e = self.scene.elements[p.element]
        if nv:
            e.bounds_min = world.min(axis=0)
            e.bounds_max = world.max(axis=0)
        else:
            e.bounds_min = e.bounds_max = m[3, :3] * self.meters_per_unit
        return True

    # ---- public API ---------------------------------------------------------------

    def set_time(self, time: float) -> bool:
        """Re-evaluate animated elements at ``time``; True if any geometry changed.

        Static elements are never recomputed; with no animated element this is O(1).
        """
        time = float(time)
        if not np.isfinite(time):
            raise PhrtError(f"set_time: time code {time} is not finite")
        if not self._animated:
            self._time = time
            return False
        ctx = _TimeContext(time)
        changed = False
        for p in self._animated:
            changed |= self._place(p, ctx)
        self._time = time
        return changed

    @property
    def time(self) -> float:
        """Time code of the last ``set_time`` (the start of the frame range at first)."""
        return self._time

    def camera(self, time: float) -> CameraFrame:
        """The camera at ``time``: world metres, orthonormal rotation."""
        v = _camera_values(self._camera_prim, time, self.path_driver is not None)
        for problem in v.problems:
            raise PhrtError(problem)
        if self.path_driver is not None:
            world_from_camera = self.path_driver.world_from_camera(time, self.meters_per_unit)
        else:
            m = v.world
            world_from_camera = np.eye(4)
            world_from_camera[:3, :3] = _rotation_columns(m)
            world_from_camera[:3, 3] = m[3, :3] * self.meters_per_unit
        focal, aperture, near, far = v.focal, v.aperture, v.near, v.far
        # A zero near plane gives a singular depth projection: keep it a tiny positive
        # fraction of the far plane.
        near = max(near, far * 1e-7)
        return CameraFrame(
            world_from_camera=world_from_camera,
            focal_length=focal,
            horizontal_aperture=aperture,
            near=near * self.meters_per_unit,
            far=far * self.meters_per_unit,
        )


def _pruned(prim: Usd.Prim, code: Usd.TimeCode) -> bool:
    """True for subtrees the render never sees: authored invisible, guide or proxy."""
    if prim.IsPseudoRoot() or not prim.IsA(UsdGeom.Imageable):
        return False
    img = UsdGeom.Imageable(prim)
    if img.GetVisibilityAttr().Get(code) == UsdGeom.Tokens.invisible:
        return True
    purpose = img.GetPurposeAttr()
    return purpose.HasAuthoredValue() and purpose.Get() in (
        UsdGeom.Tokens.guide,
        UsdGeom.Tokens.proxy,
    )


def read_stage(stage: Usd.Stage, camera: str | None = None) -> StageScene:
    """Read an open stage for rendering (see the module doc). Raises ``PhrtError``."""
    return StageScene(stage, camera)


#: File extensions of the stage files ``open_usd`` accepts (USD picks the file format
#: from the extension; ``.usd`` may hold text or crate).
USD_EXTENSIONS = (".usda", ".usdc", ".usd", ".usdz")


def open_usd(path: str | os.PathLike) -> Usd.Stage:
    """Open a USD stage file with every payload loaded.

    Raises ``PhrtError`` (one line naming the path and what is wrong) for a missing path,
    a directory, a file without one of ``USD_EXTENSIONS``, or a file USD cannot read
    (garbage bytes, invalid syntax, unreadable). A file without an extension is refused,
    not sniffed: USD chooses the file format from the extension, and the same file
    must open the same way in every USD tool — rename it to ``.usd`` (text or crate).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise PhrtError(f"{path}: no such file")
    if os.path.isdir(path):
        raise PhrtError(f"{path}: is a directory, not a USD file")
    ext = os.path.splitext(path)[1]
    expected = "/".join(USD_EXTENSIONS)
    if not ext or ext == ".":
        raise PhrtError(f"{path}: no USD file extension ({expected})")
    if not Sdf.FileFormat.FindByExtension(ext[1:]):
        raise PhrtError(f"{path}: not a USD file (extension {ext!r}, expected {expected})")
    try:
        stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise PhrtError(f"{path}: cannot open as USD ({usd_error_reason(exc)})") from None
    if stage is None:
        raise PhrtError(f"{path}: cannot open as USD")
    return stage


def open_stage(path: str | os.PathLike, camera: str | None = None) -> StageScene:
    """Open a stage file (``open_usd``) and read it (``read_stage``). Raises
    ``PhrtError`` (one line) for an unusable file, a stage without camera, or invalid
    data."""
    return read_stage(open_usd(path), camera)


__all__ = [
    "USD_EXTENSIONS",
    "CompositionProblem",
    "StageScene",
    "camera_check_times",
    "camera_problems",
    "choose_camera",
    "composition_problems",
    "composition_warnings",
    "frame_range",
    "RENDERED_GPRIM_TYPES",
    "mesh_problems",
    "mesh_problems_in_range",
    "open_stage",
    "open_usd",
    "read_stage",
    "read_texture",
    "reflector_problems",
    "rendered_gprims",
    "smooth_corner_normals",
    "stage_problems",
]
