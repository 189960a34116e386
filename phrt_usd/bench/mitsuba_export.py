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
  material row and, for reflectors that author ``phrt:reflectivity``, their F
  (quantised to ``F_STEP``), one mesh per group. All BSDFs are ``twosided``: our shading
  flips normals to face the viewer, Mitsuba's BSDFs are one-sided otherwise.

  A material's constant UsdPreviewSurface inputs (``material_bsdf``) become the sum of
  our BRDF's lobes (``model/preview_surface.py``), each a Mitsuba BSDF with the same
  parameters, summed by nested ``blendbsdf``s whose lobes' colours are scaled by the
  number of lobes (a blend is a convex mix, raw bitmaps carry colours above 1):

  - the dielectric specular lobe: ``roughconductor``, GGX, ``alpha`` = roughness² (at
    least ``preview_surface.MIN_ROUGHNESS``²), ``eta`` = the input's ior and ``k`` = 0
    (a conductor without absorption reflects with a dielectric's exact Fresnel: F0 =
    ((1 - ior) / (1 + ior))², ours is Schlick's from the same F0 with F90 = 1), weighted
    1 - metallic;
  - the metal's: ``roughconductor`` ``material="none"`` (F = 1) with
    ``specular_reflectance`` = albedo, weighted metallic (our metallic F0 = F90 =
    albedo: the same lobe);
  - the specular workflow's: the dielectric lobe of the ior whose F0 is specularColor's
    mean, tinted by specularColor / that mean;
  - the clear coat's: the dielectric lobe at clearcoatRoughness weighted clearcoat, the
    base's lobes weighted by its face-on transmission (1 - clearcoat Ec(1))²;
  - the diffuse lobe: ``diffuse`` (Lambert) of the albedo times our diffuse lobe's
    factor face on (``diffuse_face_on``: (1 - E(1))² / (1 - E_avg) per channel, which
    takes what the specular lobe leaves; 0.98 for a dielectric of ior 1.5 at roughness
    0.6, (0.54, 0.69, 0.89) for metallic 0.5 of albedo (0.9, 0.6, 0.2) at roughness
    0.4), times 1 - metallic.

  What differs: Mitsuba's Smith masking is separable (G1 G1), ours height-correlated;
  Mitsuba's Fresnel is exact where ours is Schlick's; our diffuse lobe darkens towards
  grazing angles by (1 - E(v)) (1 - E(l)) where the Lambert lobe does not (~4-5 % at
  n·v = 0.3 on a floor of roughness 0.6). Measured against our renders on spheres and a
  floor (``bench/mitsuba_comparison.py``, ``tools/compare_mitsuba.py``): mean FLIP
  0.03-0.05. Mitsuba's ``roughplastic`` (a diffuse substrate under a dielectric
  interface) is further from ours: its diffuse lobe is 0.93 and 0.64 of ours face on
  (roughness 0.3 and 0.6, ior 1.5) and falls 13 % more by 70°; on the comparison's
  ``plastics`` stage (96 x 72) it measured a mean FLIP of 0.41, 0.11 with its diffuse
  colour scaled to ours face on, against 0.034 for the lobes above. ``principled`` has a
  Disney diffuse and a GTR1 coat. A mesh of many colours (per-corner albedo, a diffuse
  texture sampled at the corners) reads them as mesh attributes (``vertex_color``,
  scaled copies for the scaled lobes), its diffuse factor a mid grey's. Other textured
  inputs read their constant value.

  A reflector with an authored F blends that BSDF with a perfect-mirror ``conductor``
  by weight F: our ``pixel = (1 - F) * local + F * reflected`` (F = 1: the mirror alone).
  Caveat, measured with Mitsuba 3.9.1 (scalar_rgb, ``path`` and ``direct`` alike, 256
  spp, a black diffuse blended with a perfect mirror under a constant environment): the
  mirror term comes out at 0.28 / 0.77 / 0.97 of F x environment for F = 0.1 / 0.5 /
  0.9 (and the diffuse term of a blend ~1.2x too bright), so partial reflectors differ in
  brightness from ours; the work per path, which is what the benchmark times, is the
  same. F = 1 matches exactly (``tests/top/test_mitsuba_export.py``).
* **Lights**, scaled to our model's brightness. A light of radiance E leaves ``π f (n·l)
  E`` in our shading (a white Lambert surface facing a unit DistantLight shows 1.0, see
  ``phrt_usd.engine.shading``; the same π for every lobe of the BRDF), Mitsuba's ``f (n·l)
  E``, so irradiance / intensity are multiplied by π (checked for the whole BRDF against
  our numpy model in ``tests/top/test_mitsuba_export.py``: within 0.2 % under a light
  face on).
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
the ``occlusion`` input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from phrt_usd.errors import PhrtError
from phrt_usd.model import preview_surface
from phrt_usd.model.scene import DEFAULT_ENVIRONMENT, CameraFrame, MaterialTable, Scene
from phrt_usd.model.surface import sample_bilinear_wrap

#: Reflectivity groups are F rounded to this step: a handful of meshes per scene.
F_STEP = 0.05

#: Our model's diffuse term has no 1/π (preview convention), Mitsuba's BRDF does: light
#: strengths are scaled by π so that both renderers show the same brightness.
LAMBERT_SCALE = math.pi

#: The range of a specular-workflow F0 mapped onto a dielectric's ior (``material_bsdf``):
#: above 0 (an ior of 1 reflects nothing) and below 1 (an infinite ior).
MIN_SPECULAR_F0 = 1e-4
MAX_SPECULAR_F0 = 0.9

#: The largest spread (per channel) of a mesh's corner albedos exported as one colour.
UNIFORM_ALBEDO = 1e-6

#: Mitsuba's default path-tracer depth used by the benchmark (camera segment included).
DEFAULT_MAX_DEPTH = 7

#: USD camera space (looks down -Z, +X right) → Mitsuba camera space (looks down +Z,
#: image x grows towards camera -X): a 180° turn about +Y.
_USD_TO_MITSUBA_CAMERA = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclass
class MeshGroup:
    """Triangles exported as one Mitsuba mesh.

    reflectivity : F of the group (quantised to ``F_STEP``) where the group's elements
                   author it (``phrt:reflectivity``), else None: the material decides
    material     : the ``MaterialTable`` row of the group's triangles
    positions    : (3 n, 3) float32 render-relative metres, one vertex per corner
    normals      : (3 n, 3) float32 world unit shading normals per corner
    colors       : (3 n, 3) float32 linear RGB albedo per corner
    faces        : (n, 3) uint32 = arange(3 n).reshape(n, 3)
    """

    reflectivity: float | None
    material: int
    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    faces: np.ndarray

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])

    @property
    def name(self) -> str:
        """The mesh's name in Mitsuba: its material row and authored F."""
        f = "" if self.reflectivity is None else f"_F{self.reflectivity:.2f}"
        return f"phrt_M{self.material}{f}"


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
    """Split the scene's triangles into one group per (material row, authored F quantised
    to ``F_STEP``, or none where the element's reflection follows its material).

    Groups are ordered by material row, then F (none first); empty groups are not
    returned. Positions are render-relative (``scene.origin`` subtracted) float32.
    """
    geo = scene.geometry
    if geo.triangle_count == 0:
        return []
    # F outside [0, 1] is not physical; -1 marks elements whose material decides.
    element_f = np.array(
        [
            np.clip(e.reflectivity, 0.0, 1.0) if e.is_reflector and e.reflectivity_authored
            else -1.0
            for e in scene.elements
        ]
        or [-1.0]
    )  # fmt: skip
    tri_f = np.round(element_f[geo.tri_element] / F_STEP) * F_STEP
    tri_f[element_f[geo.tri_element] < 0.0] = -1.0
    keys = np.stack([np.asarray(geo.tri_material, np.float64), tri_f], axis=1)
    corners = (geo.vertices[geo.triangles] - scene.origin).astype(np.float32)  # (T, 3, 3)
    colors = corner_colors(scene)
    groups = []
    for material, f in np.unique(keys, axis=0):  # a handful of materials and F values
        tris = np.flatnonzero((keys[:, 0] == material) & (keys[:, 1] == f))
        n = len(tris)
        groups.append(
            MeshGroup(
                reflectivity=None if f < 0.0 else float(f),
                material=int(material),
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


#: The per-corner albedo scaled by s is the mesh attribute ``vertex_color_x<1000 s>``.
_SCALED_COLOR = "vertex_color_x"


def _vertex_color(scale: float = 1.0) -> dict[str, Any]:
    """The texture of the albedo read per corner times ``scale`` (a mesh attribute of
    the mesh, ``_mesh`` adds every one its BSDF reads)."""
    if scale == 1.0:
        return {"type": "mesh_attribute", "name": "vertex_color"}
    return {"type": "mesh_attribute", "name": f"{_SCALED_COLOR}{round(1000 * scale)}"}


def _attribute_names(description: Any) -> set[str]:
    """The mesh attributes a BSDF description reads."""
    if isinstance(description, dict):
        names = {description["name"]} if description.get("type") == "mesh_attribute" else set()
        for item in description.values():
            names |= _attribute_names(item)
        return names
    return set()


def _ior_of_reflectance(f0: float) -> float:
    """The ior whose face-on reflectance ((1 - ior) / (1 + ior))² is ``f0`` (in (0, 1))."""
    root = math.sqrt(min(max(f0, MIN_SPECULAR_F0), MAX_SPECULAR_F0))
    return (1.0 + root) / (1.0 - root)


def _constant(value) -> dict[str, Any]:
    """A constant colour as a Mitsuba texture that may exceed 1 (a raw 1x1 bitmap: an
    ``rgb`` reflectance is refused above 1)."""
    mi = _mi()
    pixel = np.asarray(value, np.float32).reshape(1, 1, 3)
    return {"type": "bitmap", "bitmap": mi.Bitmap(pixel), "raw": True, "filter_type": "nearest"}


def _lobe_sum(lobes: list[tuple[str, dict[str, Any], str, Any]]) -> dict[str, Any]:
    """The sum of BSDF lobes, each (type, parameters, name of its colour parameter,
    colour: (3,) array, or a float s: the per-corner albedo times s), as Mitsuba's
    ``blendbsdf`` makes it: a convex mix of the lobes with their colours scaled by their
    count."""
    k = len(lobes)

    def lobe(kind, params, colour_name, colour):
        texture = _vertex_color(k * colour) if np.isscalar(colour) else _constant(k * colour)
        return {"type": kind, **params, colour_name: texture}

    if k == 1:
        kind, params, colour_name, colour = lobes[0]
        return lobe(kind, params, colour_name, colour)
    mix = lobe(*lobes[-1])
    for i in range(k - 2, -1, -1):  # lobe i weighs 1 / (k - i) of what is left
        mix = {"type": "blendbsdf", "weight": 1.0 - 1.0 / (k - i), "bsdf_0": lobe(*lobes[i]),
               "bsdf_1": mix}  # fmt: skip
    return mix


def diffuse_face_on(roughness: float, f0, f90) -> np.ndarray:
    """(3,) our diffuse lobe's factor ``(1 - E(1))² / (1 - E_avg)`` at normal view and
    light (``preview_surface``: the diffuse lobe takes what the specular lobe leaves) of
    a specular lobe of ``f0`` and ``f90`` (3,) each at ``roughness``."""
    fine = (np.arange(64) + 0.5) / 64.0
    a1, b1 = preview_surface.lobe_albedo(roughness, np.ones(1))
    a, b = preview_surface.lobe_albedo(roughness, fine)
    f0, f90 = np.asarray(f0, np.float64), np.asarray(f90, np.float64)
    e1 = f0 * a1[0] + f90 * b1[0]
    e_avg = 2.0 * (f0 * (a * fine).mean() + f90 * (b * fine).mean())
    return (1.0 - e1) ** 2 / np.maximum(1.0 - e_avg, 1e-6)


def material_bsdf(materials: MaterialTable, m: int, albedo: np.ndarray | None) -> dict[str, Any]:
    """The Mitsuba BSDF (a dict for ``mi.load_dict``, one-sided) of ``materials`` row
    ``m``'s constant UsdPreviewSurface inputs, the albedo ``albedo`` (3,) where the mesh's
    is one colour, else (None) read per corner from the mesh's attributes: the sum of
    our BRDF's lobes (the mapping is the module's docstring, "Materials")."""
    m = int(np.clip(m, 0, max(len(materials.opacity) - 1, 0)))

    def value(name: str) -> np.ndarray:
        return np.nan_to_num(preview_surface.material_inputs(materials, name)[m])

    def ggx(roughness: float) -> dict[str, Any]:
        r = float(np.clip(roughness, preview_surface.MIN_ROUGHNESS, 1.0))
        return {"distribution": "ggx", "alpha": r * r}

    def dielectric(f0: float) -> dict[str, Any]:
        # A conductor without absorption (k = 0) reflects as a dielectric of its eta.
        return {"eta": _ior_of_reflectance(f0), "k": 0.0}

    rough = float(value("roughness")[0])
    ior = float(value("ior")[0])
    ior = ior if np.isfinite(ior) and ior > 0.0 else preview_surface.FALLBACK_IOR
    r2 = float(preview_surface.ior_reflectance(ior))
    lobes: list[tuple[str, dict[str, Any], str, Any]] = []
    # Where the colour is per corner, the diffuse lobe's factor is a mid grey's.
    colour = np.full(3, 0.5) if albedo is None else np.clip(albedo, 0.0, 1.0)
    if value("useSpecularWorkflow")[0] != 0.0:
        specular = np.clip(value("specularColor").astype(np.float64), 0.0, 1.0)
        f0 = float(specular.mean())
        if f0 > 0.0:
            params = {**ggx(rough), **dielectric(f0)}
            lobes.append(("roughconductor", params, "specular_reflectance", specular / f0))
        diffuse_weight = diffuse_face_on(rough, specular, np.ones(3))
    else:
        metallic = float(np.clip(value("metallic")[0], 0.0, 1.0))
        if metallic < 1.0:
            params = {**ggx(rough), **dielectric(r2)}
            tint = np.full(3, 1.0 - metallic)
            lobes.append(("roughconductor", params, "specular_reflectance", tint))
        if metallic > 0.0:
            params = {**ggx(rough), "material": "none"}
            tint = metallic if albedo is None else metallic * np.asarray(albedo)
            lobes.append(("roughconductor", params, "specular_reflectance", tint))
        f0, f90 = r2 + (colour - r2) * metallic, 1.0 + (colour - 1.0) * metallic
        diffuse_weight = (1.0 - metallic) * diffuse_face_on(rough, f0, f90)
    if np.any(diffuse_weight > 0.0):
        scaled = float(diffuse_weight.mean()) if albedo is None else diffuse_weight * albedo
        lobes.append(("diffuse", {}, "reflectance", scaled))
    clearcoat = float(np.clip(value("clearcoat")[0], 0.0, 1.0))
    if clearcoat > 0.0:
        # The coat's layer takes its albedo out of the base on the way in and out:
        # t(v) t(l), here face on.
        coat_rough = float(value("clearcoatRoughness")[0])
        a1, b1 = preview_surface.lobe_albedo(coat_rough, np.ones(1))
        through = (1.0 - clearcoat * float(r2 * a1[0] + b1[0])) ** 2
        lobes = [(kind, params, name, through * c) for kind, params, name, c in lobes]
        params = {**ggx(coat_rough), **dielectric(r2)}
        lobes.append(("roughconductor", params, "specular_reflectance", np.full(3, clearcoat)))
    if not lobes:  # black: no lobe reflects anything
        return {"type": "diffuse", "reflectance": _constant(np.zeros(3))}
    return _lobe_sum(lobes)


def group_bsdf(group: MeshGroup, materials: MaterialTable) -> dict[str, Any]:
    """The two-sided Mitsuba BSDF of ``group``: its material's (``material_bsdf``), blended
    with a perfect mirror by an authored F."""
    uniform = np.ptp(group.colors, axis=0).max(initial=0.0) <= UNIFORM_ALBEDO
    albedo = group.colors[0] if uniform and len(group.colors) else None
    local = material_bsdf(materials, group.material, albedo)
    mirror = {"type": "conductor", "material": "none"}  # "none": a perfect mirror
    f = group.reflectivity
    if f is None or f <= 0.0:
        inner = local
    elif f >= 1.0:
        inner = mirror
    else:
        inner = {"type": "blendbsdf", "weight": f, "bsdf_0": local, "bsdf_1": mirror}
    return {"type": "twosided", "material": inner}


def _mesh(group: MeshGroup, materials: MaterialTable):
    """A Mitsuba mesh of ``group`` with its BSDF, buffers filled through ``mi.traverse``."""
    mi = _mi()
    name = group.name
    props = mi.Properties()
    description = group_bsdf(group, materials)
    props["bsdf"] = mi.load_dict(description)
    n_vertices = group.positions.shape[0]
    mesh = mi.Mesh(name, n_vertices, group.triangle_count, props=props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.ascontiguousarray(group.positions, np.float32).ravel()
    params["vertex_normals"] = np.ascontiguousarray(group.normals, np.float32).ravel()
    params["faces"] = np.ascontiguousarray(group.faces, np.uint32).ravel()
    for attribute in _attribute_names(description) | {"vertex_color"}:
        scale = 1.0
        if attribute.startswith(_SCALED_COLOR):
            scale = int(attribute[len(_SCALED_COLOR) :]) / 1000.0
        colors = np.ascontiguousarray(scale * group.colors, np.float32).ravel()
        mesh.add_attribute(attribute, 3, colors)
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
        d[f"mesh_{k}"] = _mesh(group, scene.materials)
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
