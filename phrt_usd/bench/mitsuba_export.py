"""Export a ``Scene`` + ``CameraFrame`` to a Mitsuba 3 scene, for the peer benchmark only.

Mitsuba (PyPI ``mitsuba``, the optional ``bench`` extra) is never needed by the renderer
or its tests: it is imported inside the functions that need it, and the caller chooses the
variant (``mi.set_variant("scalar_rgb")`` / ``"llvm_ad_rgb"``) before calling them.

What is exported (only what ``phrt_usd.model.scene.Scene`` holds, at its current time):

* **Geometry**, render-relative like our renderer (``scene.origin`` subtracted) so float32
  keeps its precision. Mitsuba meshes are indexed per *vertex*, ours carry normals and
  colours per *corner*, so every triangle gets its own three vertices (3 T vertices):
  positions, ``corner_normals`` as vertex normals and the per-corner albedo as a
  ``vertex_color`` mesh attribute (textured materials: their texture sampled at the
  corners' ``corner_uv``; between corners Mitsuba interpolates linearly, so a texture
  finer than the triangles is blurred: the export is for timing and a visual check).
* **Materials**: a Mitsuba shape takes one BSDF, so triangles are grouped by their
  element's reflectivity F (quantised to ``F_STEP``), one mesh per group (a handful):
  F = 0 → ``diffuse`` reading ``vertex_color``; F = 1 → a perfect-mirror ``conductor``;
  0 < F < 1 → ``blendbsdf`` with weight F between the two, which is our
  ``pixel = (1 - F) * local + F * reflected``. All are ``twosided``: our shading flips
  normals to face the viewer, Mitsuba's BSDFs are one-sided otherwise. Caveat, measured
  with Mitsuba 3.9.1 (scalar_rgb, ``path`` and ``direct`` alike, 256 spp, a black diffuse
  blended with a perfect mirror under a constant environment): the mirror term comes out
  at 0.28 / 0.77 / 0.97 of F x environment for F = 0.1 / 0.5 / 0.9 (and the diffuse term
  of a blend ~1.2x too bright), so partial reflectors differ in brightness from ours; the
  work per path, which is what the benchmark times, is the same. F = 0 and F = 1 match
  exactly (``tests/top/test_mitsuba_export.py``).
* **Lights**, scaled to our model's brightness. Our Lambert term has no 1/π (a white
  surface facing a unit DistantLight shows 1.0, see ``phrt_usd.engine.shading``); Mitsuba's
  diffuse BRDF is albedo/π, so irradiance / intensity are multiplied by π.
  DistantLight → ``directional`` (direction of travel = -direction towards the light),
  LocalLight → ``point`` (our tracer treats them as points too), DomeLight with a texture
  → ``envmap`` (texture × colour as a bitmap; Mitsuba's lat-long convention is UsdLux's:
  +Y up, +Z at u = 0.5, +X at u = 0.25, so ``to_world`` = ``world_from_light``), a
  colour-only dome → ``constant``, no dome → ``constant`` ``DEFAULT_ENVIRONMENT`` (what our
  rays see on a miss). Our ambient term (albedo × mean environment) is what a path tracer
  gets from the environment unoccluded, so no extra term is needed.
* **Camera**: ``perspective`` with the horizontal field of view (``fov_axis = "x"``), the
  camera's clip range, an ``hdrfilm`` with a box filter and an ``independent`` sampler.
* **Integrator**: ``path`` with ``max_depth`` (Mitsuba counts the camera segment: 7 means
  up to 6 bounces).

Not exported: materials' emissive (zero in the paper stages), transmission (opacity < 1),
the specular highlight of our shading model (Mitsuba's diffuse has none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, CameraFrame, Scene
from phrt_usd.model.surface import sample_bilinear_wrap

#: Reflectivity groups are F rounded to this step: a handful of meshes per scene.
F_STEP = 0.05

#: Our model's diffuse term has no 1/π (preview convention), Mitsuba's BRDF does: light
#: strengths are scaled by π so that both renderers show the same brightness.
LAMBERT_SCALE = math.pi

#: Mitsuba's default path-tracer depth used by the benchmark (camera segment included).
DEFAULT_MAX_DEPTH = 7

#: USD camera space (looks down -Z, +X right) → Mitsuba camera space (looks down +Z,
#: image x grows towards camera -X): a 180° turn about +Y.
_USD_TO_MITSUBA_CAMERA = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclass
class MeshGroup:
    """Triangles exported as one Mitsuba mesh.

    reflectivity : F of the group (quantised to ``F_STEP``)
    positions    : (3 n, 3) float32 render-relative metres, one vertex per corner
    normals      : (3 n, 3) float32 world unit shading normals per corner
    colors       : (3 n, 3) float32 linear RGB albedo per corner
    faces        : (n, 3) uint32 = arange(3 n).reshape(n, 3)
    """

    reflectivity: float
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    faces: np.ndarray

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])


def corner_colors(scene: Scene) -> np.ndarray:
    """(T, 3, 3) float32 linear RGB albedo per corner: ``corner_albedo``, replaced by the
    material's texture sampled at ``corner_uv`` where a material has one (as our shading
    does)."""
    geo = scene.geometry
    colors = np.array(geo.corner_albedo, dtype=np.float32, copy=True)
    textures = scene.materials.textures
    if geo.corner_uv is None or not any(t is not None for t in textures):
        return colors
    for m, texture in enumerate(textures):  # loop over the few textured materials
        if texture is None:
            continue
        tris = np.flatnonzero(geo.tri_material == m)
        if len(tris):
            uv = geo.corner_uv[tris].reshape(-1, 2)
            colors[tris] = sample_bilinear_wrap(texture, uv).reshape(-1, 3, 3)
    return colors


def mesh_groups(scene: Scene) -> list[MeshGroup]:
    """Split the scene's triangles into one group per quantised element reflectivity.

    Groups are ordered by F; empty groups are not returned. Positions are
    render-relative (``scene.origin`` subtracted) float32.
    """
    geo = scene.geometry
    if geo.triangle_count == 0:
        return []
    element_f = np.clip(scene.reflectivity, 0.0, 1.0)  # F outside [0, 1] is not physical
    tri_f = np.round(element_f[geo.tri_element] / F_STEP) * F_STEP
    corners = (geo.vertices[geo.triangles] - scene.origin).astype(np.float32)  # (T, 3, 3)
    colors = corner_colors(scene)
    groups = []
    for f in np.unique(tri_f):  # a handful of distinct F values
        tris = np.flatnonzero(tri_f == f)
        n = len(tris)
        groups.append(
            MeshGroup(
                reflectivity=float(f),
                positions=corners[tris].reshape(-1, 3),
                normals=np.asarray(geo.corner_normals[tris], np.float32).reshape(-1, 3),
                colors=colors[tris].reshape(-1, 3),
                faces=np.arange(3 * n, dtype=np.uint32).reshape(n, 3),
            )
        )
    return groups


def sensor_to_world(camera: CameraFrame, origin: np.ndarray) -> np.ndarray:
    """(4, 4) float64 Mitsuba ``to_world`` of the camera, render-relative (``origin``
    subtracted): column-vector convention, maps Mitsuba camera space to world."""
    m = np.array(camera.world_from_camera, dtype=np.float64)
    m[:3, 3] -= np.asarray(origin, dtype=np.float64)
    return m @ _USD_TO_MITSUBA_CAMERA


def horizontal_fov_degrees(camera: CameraFrame, width: int, height: int) -> float:
    """Horizontal field of view in degrees (``fov_axis = "x"``)."""
    tx, _ = camera.tan_half_fov(width, height)
    # A degenerate aperture would give fov 0 or 180: keep Mitsuba's projection finite.
    return float(np.clip(np.degrees(2.0 * np.arctan(tx)), 1e-3, 179.0))


def _mi():
    try:
        import mitsuba as mi
    except ImportError as exc:  # the optional ``bench`` extra
        raise PhrtError("mitsuba is not installed (optional extra: phrt-usd[bench])") from exc
    if mi.variant() is None:
        raise PhrtError("mitsuba: call mi.set_variant(...) before exporting a scene")
    return mi


def _bsdf(reflectivity: float) -> dict[str, Any]:
    diffuse = {
        "type": "diffuse",
        "reflectance": {"type": "mesh_attribute", "name": "vertex_color"},
    }
    mirror = {"type": "conductor", "material": "none"}  # "none": a perfect mirror
    if reflectivity <= 0.0:
        inner = diffuse
    elif reflectivity >= 1.0:
        inner = mirror
    else:
        inner = {"type": "blendbsdf", "weight": reflectivity, "bsdf_0": diffuse, "bsdf_1": mirror}
    return {"type": "twosided", "material": inner}


def _mesh(group: MeshGroup, name: str):
    """A Mitsuba mesh of ``group`` with its BSDF, buffers filled through ``mi.traverse``."""
    mi = _mi()
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(group.reflectivity))
    n_vertices = group.positions.shape[0]
    mesh = mi.Mesh(name, n_vertices, group.triangle_count, props=props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.ascontiguousarray(group.positions, np.float32).ravel()
    params["vertex_normals"] = np.ascontiguousarray(group.normals, np.float32).ravel()
    params["faces"] = np.ascontiguousarray(group.faces, np.uint32).ravel()
    mesh.add_attribute("vertex_color", 3, np.ascontiguousarray(group.colors, np.float32).ravel())
    params.update()
    return mesh


def _rgb(value: np.ndarray) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(v) for v in np.asarray(value).reshape(3)]}


def _light_dicts(scene: Scene) -> dict[str, dict[str, Any]]:
    mi = _mi()
    lights = scene.lights
    out: dict[str, dict[str, Any]] = {}
    for i, light in enumerate(lights.distant):
        towards = np.asarray(light.direction, dtype=np.float64)
        out[f"distant_{i}"] = {
            "type": "directional",
            "direction": [float(v) for v in -towards],
            "irradiance": _rgb(LAMBERT_SCALE * np.asarray(light.radiance)),
        }
    for i, light in enumerate(lights.local):
        out[f"local_{i}"] = {
            "type": "point",
            "position": [float(v) for v in np.asarray(light.position) - scene.origin],
            "intensity": _rgb(LAMBERT_SCALE * np.asarray(light.radiance)),
        }
    dome = lights.dome
    if dome is None:
        out["environment"] = {"type": "constant", "radiance": _rgb(DEFAULT_ENVIRONMENT)}
    elif dome.texture is None:
        out["environment"] = {"type": "constant", "radiance": _rgb(dome.color)}
    else:
        texture = np.asarray(dome.texture, np.float32) * np.asarray(dome.color, np.float32)
        to_world = np.eye(4)
        to_world[:3, :3] = dome.world_from_light
        out["environment"] = {
            "type": "envmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(texture[..., :3], np.float32)),
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
        }
    return out


def scene_dict(
    scene: Scene,
    camera: CameraFrame,
    width: int,
    height: int,
    max_depth: int = DEFAULT_MAX_DEPTH,
) -> dict[str, Any]:
    """The Mitsuba scene description (for ``mi.load_dict``) of ``scene`` seen by
    ``camera`` at ``width`` x ``height``, path tracer with ``max_depth``, 1 spp sampler.
    Meshes are already-built Mitsuba objects (keys ``mesh_<k>``, one per ``MeshGroup``)."""
    mi = _mi()
    if width < 1 or height < 1:
        raise PhrtError(f"mitsuba export: resolution {width}x{height} must be >= 1x1")
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {
            "type": "perspective",
            "fov_axis": "x",
            "fov": horizontal_fov_degrees(camera, width, height),
            # Mitsuba needs 0 < near < far.
            "near_clip": float(max(camera.near, 1e-6)),
            "far_clip": float(max(camera.far, 2.0 * max(camera.near, 1e-6))),
            "to_world": mi.ScalarTransform4f(sensor_to_world(camera, scene.origin).tolist()),
            "sampler": {"type": "independent", "sample_count": 1},
            "film": {
                "type": "hdrfilm",
                "width": int(width),
                "height": int(height),
                "pixel_format": "rgb",
                "rfilter": {"type": "box"},
            },
        },
    }
    for k, group in enumerate(mesh_groups(scene)):
        d[f"mesh_{k}"] = _mesh(group, f"phrt_F{group.reflectivity:.2f}")
    d.update(_light_dicts(scene))
    return d


def load_scene(
    scene: Scene,
    camera: CameraFrame,
    width: int,
    height: int,
    max_depth: int = DEFAULT_MAX_DEPTH,
):
    """``mi.load_dict(scene_dict(...))``: a ready-to-render ``mi.Scene``."""
    return _mi().load_dict(scene_dict(scene, camera, width, height, max_depth))


def set_camera(mi_scene, camera: CameraFrame, origin: np.ndarray) -> None:
    """Move the Mitsuba scene's sensor to ``camera`` (render-relative to ``origin``), the
    per-frame update of an animation (field of view and clip range stay as exported)."""
    mi = _mi()
    params = mi.traverse(mi_scene)
    params["sensor.to_world"] = mi.ScalarTransform4f(sensor_to_world(camera, origin).tolist())
    params.update()
