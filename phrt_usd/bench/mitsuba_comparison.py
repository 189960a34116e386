"""Our renders against Mitsuba 3's on small stages of UsdPreviewSurface spheres on a floor,
lit by a constant environment and a distant light (``tools/compare_mitsuba.py`` and
``tests/top/test_mitsuba_comparison.py`` measure the mean FLIP between them).

The stages (``STAGES``, built in memory by ``comparison_stage``): a 40 m floor (grey, a
rough dielectric) at y = 0, three spheres of radius 0.5 m on it at x = -1.2, 0, 1.2, a
constant dome of ``DOME_RADIANCE`` and a distant light of intensity ``SUN_INTENSITY``
(angle 0) from ``SUN_ELEVATION`` above the horizon, seen from above (``EYE``, 56° down
to the spheres). Each sphere's material is a ``SphereMaterial``: UsdPreviewSurface inputs
only, none textured, none a ``PhrtReflectorAPI`` reflector.

Where the two are meant to agree, and the choices that follow from it:

* **Direct light only**: our shading is the distant light's (shadowed) and the
  environment's through the BRDF's directional albedo, unshadowed (the ambient term, the
  split sum for the specular lobes); no light bounces between surfaces. Mitsuba's
  ``path`` integrator runs at depth 2 (``MITSUBA_MAX_DEPTH``): emission and direct light
  from both emitters, MIS, no interreflection. Left different: Mitsuba's environment is
  occluded (the floor hides the lower half of the sky from the spheres' lower halves,
  the spheres darken the floor around them), ours is not; the dim dome and the view
  from above keep that share small (it is most of the error left, at the spheres' rims
  and the floor around them).
* **No traced reflections**: our reflection of a reflector is a mirror's at any
  roughness (its lobe's Fresnel weighs it, nothing blurs it), Mitsuba's a glossy lobe;
  the spheres are not reflectors, so both see the environment through the lobe.
* **Views that are not grazing**: our diffuse lobe takes what the specular lobe leaves,
  (1 - E(v)) (1 - E(l)) / (1 - E_avg); Mitsuba's closest lobes add a Lambert lobe to the
  GGX one (``mitsuba_export.material_bsdf``), equal to ours face on (the export scales
  it) but ~4-5 % brighter at n·v ~ 0.3 (a floor seen 18° above the horizon).
* **Pixels**: ours are supersampled (``SUPERSAMPLING``), as Mitsuba's box filter averages
  its samples over a pixel; Mitsuba's are multi-jittered at ``DEFAULT_SPP``.

``render_stage`` renders a stage in ``rt`` and ``hybrid`` (every reflector traced, no
budget) and in Mitsuba (``mitsuba_export``, ``scalar_rgb``). Mitsuba is imported there
only: the optional ``bench`` extra.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

from phrt_usd.engine.renderer import FrameRenderer
from phrt_usd.errors import PhrtError
from phrt_usd.model.render_options import RenderOptions
from phrt_usd.usd.camera_path import UP_VECTORS, look_at
from phrt_usd.usd.stage import read_stage

#: The environment's radiance and the distant light's intensity (UsdLux units: a white
#: Lambert floor facing the light shows its intensity), its elevation and azimuth
#: (degrees). The dome is dim: its occlusion is what the two renderers do not share
#: (module docstring); at (0.28, 0.32, 0.36) with a sun of 1.6 the mean FLIP of
#: ``plastics`` and ``metals`` was 0.071 and 0.108 (96 x 72, 1024 spp) against 0.034
#: and 0.047 here.
DOME_RADIANCE = (0.06, 0.07, 0.09)
SUN_INTENSITY = 2.2
SUN_ELEVATION = 50.0
SUN_AZIMUTH = 30.0

#: The floor's material: a mid grey rough dielectric.
FLOOR_COLOR = (0.4, 0.4, 0.4)
FLOOR_ROUGHNESS = 0.6

#: Mitsuba's path depth (camera segment included): 2 = emission and direct light only,
#: as our shading (module docstring). At 3 (the floor's light bounced onto the spheres'
#: lower halves, which our model leaves out) the mean FLIP of ``plastics`` and
#: ``metals`` was 0.087 and 0.165 (96 x 72, 1024 spp).
MITSUBA_MAX_DEPTH = 2

#: Samples a pixel of the Mitsuba reference (a stratified sampler: a square number): its
#: noise stays well under the FLIP threshold compared (measured at 96 x 72 on
#: ``plastics``: two independent-sampler references of 256 spp differ by a mean FLIP
#: of 0.035; two stratified ones of 2025 spp by 0.007).
DEFAULT_SPP = 2025

#: Our renders are made at this many times the size and box-filtered down, as Mitsuba's
#: box pixel filter averages its samples over each pixel (ours take one ray through the
#: pixel's centre: the spheres' silhouettes would differ by their aliasing).
SUPERSAMPLING = 3


@dataclass(frozen=True)
class SphereMaterial:
    """One sphere's UsdPreviewSurface inputs (the others at their fallbacks)."""

    color: tuple[float, float, float]
    roughness: float
    metallic: float = 0.0
    ior: float = 1.5
    specular_color: tuple[float, float, float] | None = None  # the specular workflow
    clearcoat: float = 0.0
    clearcoat_roughness: float = 0.01


#: The stages compared, three spheres each (left to right). ``plastics``: dielectrics
#: (ior 1.5) at roughness 0.3, 0.45, 0.6; ``metals``: metallic 1 (gold, copper, silver)
#: at roughness 0.3, 0.45, 0.6; ``mixed``: metallic 0.5, the specular workflow (F0 0.2)
#: and a dielectric of ior 1.8; ``coated``: clear coats over a dielectric and a metal.
#: Left out: textures, transmission, and reflectors (module docstring).
STAGES: dict[str, tuple[SphereMaterial, ...]] = {
    "plastics": (
        SphereMaterial((0.8, 0.1, 0.1), 0.3),
        SphereMaterial((0.1, 0.7, 0.2), 0.45),
        SphereMaterial((0.15, 0.25, 0.85), 0.6),
    ),
    "metals": (
        SphereMaterial((1.0, 0.78, 0.34), 0.3, metallic=1.0),
        SphereMaterial((0.95, 0.64, 0.54), 0.45, metallic=1.0),
        SphereMaterial((0.91, 0.92, 0.92), 0.6, metallic=1.0),
    ),
    "mixed": (
        SphereMaterial((0.9, 0.6, 0.2), 0.4, metallic=0.5),
        SphereMaterial((0.2, 0.3, 0.6), 0.35, specular_color=(0.2, 0.2, 0.2)),
        SphereMaterial((0.7, 0.7, 0.1), 0.5, ior=1.8),
    ),
    "coated": (
        SphereMaterial((0.7, 0.1, 0.1), 0.5, clearcoat=1.0, clearcoat_roughness=0.2),
        SphereMaterial((1.0, 0.78, 0.34), 0.4, metallic=1.0, clearcoat=0.5,
                       clearcoat_roughness=0.3),
        SphereMaterial((0.1, 0.2, 0.6), 0.6, clearcoat=1.0, clearcoat_roughness=0.4),
    ),
}

#: The camera: eye and target (world metres, +Y up), focal length and aperture (mm).
#: From above, so that the floor is seen at n·v >= 0.6 (module docstring): from (0, 2.4,
#: 3.8), 29° down, the far floor's grazing rows alone had a mean FLIP of 0.06-0.1 and
#: ``plastics`` and ``metals`` 0.067 and 0.080 (96 x 72, 1024 spp).
EYE = (0.0, 3.6, 2.4)
TARGET = (0.0, 0.3, 0.0)
FOCAL_LENGTH, HORIZONTAL_APERTURE = 30.0, 36.0


@dataclass
class StageImages:
    """One stage's renders, (H, W, 3) float32 linear RGB each."""

    name: str
    rt: np.ndarray
    hybrid: np.ndarray
    mitsuba: np.ndarray


def _material(stage: Usd.Stage, path: str, m: SphereMaterial) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    inputs = {"diffuseColor": (Sdf.ValueTypeNames.Color3f, Gf.Vec3f(*m.color)),
              "roughness": (Sdf.ValueTypeNames.Float, m.roughness),
              "metallic": (Sdf.ValueTypeNames.Float, m.metallic),
              "ior": (Sdf.ValueTypeNames.Float, m.ior)}  # fmt: skip
    if m.clearcoat > 0.0:
        inputs["clearcoat"] = (Sdf.ValueTypeNames.Float, m.clearcoat)
        inputs["clearcoatRoughness"] = (Sdf.ValueTypeNames.Float, m.clearcoat_roughness)
    if m.specular_color is not None:
        inputs["useSpecularWorkflow"] = (Sdf.ValueTypeNames.Int, 1)
        inputs["specularColor"] = (Sdf.ValueTypeNames.Color3f, Gf.Vec3f(*m.specular_color))
    for name, (kind, value) in inputs.items():
        shader.CreateInput(name, kind).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def _bind(prim: Usd.Prim, material: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def comparison_stage(name: str, width: int, height: int) -> Usd.Stage:
    """The in-memory stage ``name`` of ``STAGES`` (module docstring), its camera's
    aperture of the ``width`` x ``height`` image's aspect."""
    if name not in STAGES:
        raise PhrtError(f"no comparison stage {name!r} (one of {', '.join(STAGES)})")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(SUN_INTENSITY)
    sun.CreateAngleAttr(0.0)  # Mitsuba's directional light is a point in the sky
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-SUN_ELEVATION, SUN_AZIMUTH, 0.0))
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(*DOME_RADIANCE))
    dome.CreateIntensityAttr(1.0)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(FOCAL_LENGTH)
    cam.CreateHorizontalApertureAttr(HORIZONTAL_APERTURE)
    cam.CreateVerticalApertureAttr(HORIZONTAL_APERTURE * height / width)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    # look_at is column-vector camera-to-world; USD matrices are row-vector: transposed.
    world_from_camera = look_at(np.asarray(EYE, float), np.asarray(TARGET, float), UP_VECTORS["Y"])
    UsdGeom.Xformable(cam).AddTransformOp().Set(Gf.Matrix4d(world_from_camera.T.tolist()))
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    h = 20.0
    floor.CreatePointsAttr([(-h, 0, -h), (-h, 0, h), (h, 0, h), (h, 0, -h)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    _bind(floor.GetPrim(), _material(stage, "/World/Looks/Floor",
                                     SphereMaterial(FLOOR_COLOR, FLOOR_ROUGHNESS)))  # fmt: skip
    for i, m in enumerate(STAGES[name]):
        sphere = UsdGeom.Sphere.Define(stage, f"/World/Sphere{i}")
        sphere.CreateRadiusAttr(0.5)
        UsdGeom.Xformable(sphere).AddTranslateOp().Set(Gf.Vec3d(1.2 * (i - 1), 0.5, 0.0))
        _bind(sphere.GetPrim(), _material(stage, f"/World/Looks/Sphere{i}", m))
    return stage


def _ours(stage: Usd.Stage, mode: str, width: int, height: int):
    """(StageScene, (H, W, 3) image): ``mode`` at ``SUPERSAMPLING`` times the size, each
    pixel the mean of its block."""
    k = SUPERSAMPLING
    scene = read_stage(stage)
    options = RenderOptions(mode=mode, heuristic="all", width=k * width, height=k * height,
                            budget_ms=None)  # fmt: skip
    renderer = FrameRenderer(scene, options)
    try:
        out = renderer.render(scene.frame_range[0])
    finally:
        renderer.close()
    beauty = np.asarray(out.beauty, np.float64).reshape(height, k, width, k, 3)
    return scene, beauty.mean(axis=(1, 3)).astype(np.float32)


def mitsuba_image(scene, width: int, height: int, spp: int, seed: int = 1) -> np.ndarray:
    """(H, W, 3) float32: Mitsuba's render of a read stage (``StageScene``) at its first
    frame, at least ``spp`` samples a pixel (the next square), ``MITSUBA_MAX_DEPTH``."""
    try:
        import mitsuba as mi
    except ImportError as exc:  # the optional ``bench`` extra
        raise PhrtError("mitsuba is not installed (optional extra: phrt-usd[bench])") from exc
    from phrt_usd.bench import mitsuba_export

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    t = scene.frame_range[0]
    scene.set_time(t)
    description = mitsuba_export.scene_dict(
        scene.scene, scene.camera(t), width, height, MITSUBA_MAX_DEPTH
    )
    side = max(int(math.isqrt(max(int(spp), 1) - 1)) + 1, 1)  # the square at least spp
    description["sensor"]["sampler"] = {"type": "stratified", "sample_count": side * side}
    mi_scene = mi.load_dict(description)
    return np.asarray(mi.render(mi_scene, spp=int(spp), seed=seed), np.float32)


def render_stage(name: str, width: int, height: int, spp: int = DEFAULT_SPP) -> StageImages:
    """Stage ``name`` rendered in ``rt``, ``hybrid`` (every reflector, no budget) and
    Mitsuba at ``width`` x ``height``."""
    stage = comparison_stage(name, width, height)
    scene, rt = _ours(stage, "rt", width, height)
    _, hybrid = _ours(stage, "hybrid", width, height)
    return StageImages(name, rt, hybrid, mitsuba_image(scene, width, height, spp))
