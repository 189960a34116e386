"""What a stage uses that the render ignores or approximates, with counts and prim paths.

``support_report(stage)`` walks the composed stage (active, defined, loaded prims,
instance proxies included, so a prim inside an instanced reference counts once per
instance at its per-instance path) and matches every prim against ``KINDS``, the one
declared table of what the render does not read as USD defines it: each row a kind, the
prims it matches, how the render treats them (``ignored``, or ``approximated: ...``) and
why. ``phrt inspect`` prints the rows that match (text and ``--json`` key ``support``)
and ``phrt render --json`` adds them to its summary (``support``).

The table describes the renderer of this tree; a row's ``treatment`` must change with
the reader it names (``usd/materials.py``, ``usd/lights.py``, ``usd/meshes.py``,
``usd/skinning.py``, ``usd/stage.py``). docs/usd-support.md ("What inspect reports")
lists the rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import PurePosixPath

from pxr import Ar, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel, UsdVol

from phrt_usd.model.reflection_roughness import FADE_END, FADE_START
from phrt_usd.usd import materialx, schema
from phrt_usd.usd.curves import TUBE_SIDES
from phrt_usd.usd.lights import READ_LIGHT_TYPE_NAMES
from phrt_usd.usd.materials import (
    TEXTURED_INPUTS,
    MaterialBank,
    binding_purposes,
    bound_material,
)
from phrt_usd.usd.meshes import is_subdivided

#: Prim paths listed per kind (the count is always complete).
EXAMPLE_PATHS = 5

IGNORED = "ignored"


@dataclass(frozen=True)
class SupportKind:
    """One row of the table: ``what`` completes "N <what>", ``treatment`` is ``ignored``
    or ``approximated: ...``, ``matches(prim)`` says whether a prim is of this kind."""

    kind: str
    what: str
    treatment: str
    reason: str
    matches: Callable[[Usd.Prim], bool]


# --- predicates --------------------------------------------------------------------------


def _preview_surface(material: UsdShade.Material) -> UsdShade.Shader | None:
    """The material's universal surface shader when it is a UsdPreviewSurface."""
    shader = material.ComputeSurfaceSource()[0]
    if shader and shader.GetPrim().IsValid() and shader.GetShaderId() == "UsdPreviewSurface":
        return shader
    return None


def _materialx_only(prim: Usd.Prim) -> bool:
    """A material without a UsdPreviewSurface whose surface is MaterialX: its ``mtlx``
    output connected, or a MaterialX node the render maps on its universal output."""
    if not prim.IsA(UsdShade.Material):
        return False
    material = UsdShade.Material(prim)
    if _preview_surface(material) is not None:
        return False
    out = material.GetSurfaceOutput("mtlx")
    connected = bool(out and out.HasConnectedSource())
    return connected or _materialx_surface_id(prim) in materialx.SURFACE_KINDS


def _materialx_surface_id(prim: Usd.Prim) -> str:
    """The shader id of a material's ``mtlx`` (else universal) surface ("" if none)."""
    shader = UsdShade.Material(prim).ComputeSurfaceSource("mtlx")[0]
    return str(shader.GetIdAttr().Get() or "") if shader else ""


def _materialx_approximated(prim: Usd.Prim) -> bool:
    """MaterialX-only, mapped onto UsdPreviewSurface (``usd/materialx.py``) without some
    input it authors (the render's notice names them)."""
    if not _materialx_only(prim):
        return False
    mapped = MaterialBank(Usd.TimeCode.Default()).materialx_mapping(UsdShade.Material(prim))[1]
    return mapped is not None and bool(mapped.dropped)


def _materialx_grey(prim: Usd.Prim) -> bool:
    """MaterialX-only, of a surface ``usd/materials.py`` does not read (grey)."""
    return _materialx_only(prim) and _materialx_surface_id(prim) not in materialx.SURFACE_KINDS


def _other_surface_only(prim: Usd.Prim) -> bool:
    """A material with a surface of some other render context only (``ri``, ``arnold``,
    a non-preview universal shader) and no MaterialX surface."""
    if not prim.IsA(UsdShade.Material) or _materialx_only(prim):
        return False
    material = UsdShade.Material(prim)
    if _preview_surface(material) is not None:
        return False
    return any(output.HasConnectedSource() for output in material.GetSurfaceOutputs())


def _preview_input(prim: Usd.Prim, name: str):
    """(value, connected) of a UsdPreviewSurface shader's input, followed as the render
    reads it (``GetValueProducingAttributes``: an input of the Material or a NodeGraph
    gives its value); connected = fed by a node's output. (None, False) when the prim
    is not one or the input has no value."""
    source = _input_source(prim, name)
    if source is None:
        return None, False
    if UsdShade.Utils.GetType(source.GetName()) == UsdShade.AttributeType.Output:
        return None, True
    return source.Get(), False


def _input_source(prim: Usd.Prim, name: str) -> Usd.Attribute | None:
    """The attribute producing the value of input ``name`` of a UsdPreviewSurface
    shader prim (itself, an input it is connected to, or a node's output), or None."""
    if not prim.IsA(UsdShade.Shader):
        return None
    shader = UsdShade.Shader(prim)
    if shader.GetShaderId() != "UsdPreviewSurface":
        return None
    inp = shader.GetInput(name)
    attrs = inp.GetValueProducingAttributes() if inp else []
    return attrs[0] if attrs else None


def _unread_node(prim: Usd.Prim) -> bool:
    """A UsdPreviewSurface with an input fed by a node ``usd/materials.py`` does not read:
    anything but a UsdUVTexture on a texturable input (``materials.TEXTURED_INPUTS``)
    or a UsdPrimvarReader on ``diffuseColor``; the input takes its fallback."""
    if not prim.IsA(UsdShade.Shader):
        return False
    for inp in UsdShade.Shader(prim).GetInputs():
        name = inp.GetBaseName()
        source = _input_source(prim, name)
        if source is None:
            continue
        if UsdShade.Utils.GetType(source.GetName()) != UsdShade.AttributeType.Output:
            continue
        node = str(UsdShade.Shader(source.GetPrim()).GetShaderId() or "")
        if node == "UsdUVTexture" and name in TEXTURED_INPUTS:
            continue
        if node.startswith("UsdPrimvarReader") and name == "diffuseColor":
            continue
        return True
    return False


def _texture_opacity_without_threshold(prim: Usd.Prim) -> bool:
    """A textured opacity with opacityThreshold 0: not a cut-out, drawn opaque."""
    if not _preview_input(prim, "opacity")[1]:
        return False
    value, connected = _preview_input(prim, "opacityThreshold")
    return not connected and (value is None or float(value) <= 0.0)


def _rough_reflector(prim: Usd.Prim) -> bool:
    """A reflector whose bound UsdPreviewSurface has a roughness from the glossy
    reflections' fade on (``model.reflection_roughness.FADE_START``; authored, or the
    spec's fallback 0.5) or a connected one (a texture may reach it): its reflection is
    the raster's environment fallback there, in part or whole. The material
    is the one the render binds (``materials.bound_material`` for the binding purposes
    of the render settings, ``materials.binding_purposes``)."""
    if not (prim.IsA(UsdGeom.Gprim) and schema.is_reflector(prim)):
        return False
    material = bound_material(prim, binding_purposes(prim.GetStage()))
    bound = isinstance(material, UsdShade.Material)
    shader = _preview_surface(material) if bound else None
    if shader is None:
        return False
    inp = shader.GetInput("roughness")
    if inp and inp.HasConnectedSource():
        return True
    value = inp.Get() if inp and inp.GetAttr().HasAuthoredValue() else 0.5
    return value is not None and float(value) >= FADE_START


def _displacement(prim: Usd.Prim) -> bool:
    if not prim.IsA(UsdShade.Material):
        return False
    output = UsdShade.Material(prim).GetDisplacementOutput()
    return bool(output and output.HasConnectedSource())


def _texture_file(prim: Usd.Prim) -> str | None:
    if not prim.IsA(UsdShade.Shader) or UsdShade.Shader(prim).GetShaderId() != "UsdUVTexture":
        return None
    inp = UsdShade.Shader(prim).GetInput("file")
    value = inp.Get() if inp else None
    return value.path if value is not None and value.path else None


def _readable_extensions() -> frozenset[str]:
    """File extensions OpenImageIO reads (its ``extension_list``), lower case."""
    import OpenImageIO as oiio

    found = set()
    for entry in oiio.get_string_attribute("extension_list").split(";"):
        _, _, extensions = entry.partition(":")
        found.update(e.strip().lower() for e in extensions.split(",") if e.strip())
    return frozenset(found)


def _udim_texture(prim: Usd.Prim) -> bool:
    path = _texture_file(prim)
    return path is not None and "<UDIM>" in path


def _unreadable_texture_format(prim: Usd.Prim) -> bool:
    path = _texture_file(prim)
    if path is None or "<UDIM>" in path:
        return False
    inner = Ar.SplitPackageRelativePathInner(path)[1] if Ar.IsPackageRelativePath(path) else ""
    suffix = PurePosixPath(inner or path).suffix.lower().lstrip(".")
    return suffix not in _readable_extensions()


#: UsdLux types the render reads (``usd/lights.py``); DomeLight_1 is the current dome.
_READ_LIGHT_TYPES = READ_LIGHT_TYPE_NAMES
_AREA_LIGHT_TYPES = ("SphereLight", "RectLight", "DiskLight", "CylinderLight")


def _unsupported_light(prim: Usd.Prim) -> bool:
    """A light the render does not read: PortalLight, GeometryLight, PluginLight, or a
    LightAPI on a prim of another type (a mesh light)."""
    if prim.IsA(UsdLux.LightFilter):
        return False
    return prim.HasAPI(UsdLux.LightAPI) and prim.GetTypeName() not in _READ_LIGHT_TYPES


def _ies_profile(prim: Usd.Prim) -> bool:
    attr = prim.GetAttribute("inputs:shaping:ies:file")
    value = attr.Get() if attr and attr.HasAuthoredValue() else None
    return prim.HasAPI(UsdLux.LightAPI) and value is not None and bool(value.path)


def _light_filter(prim: Usd.Prim) -> bool:
    return prim.IsA(UsdLux.LightFilter)


def _area_light(prim: Usd.Prim) -> bool:
    return prim.GetTypeName() in _AREA_LIGHT_TYPES


def _skinned(prim: Usd.Prim) -> bool:
    if not prim.IsA(UsdGeom.PointBased) or not prim.HasAPI(UsdSkel.BindingAPI):
        return False
    binding = UsdSkel.BindingAPI(prim)
    return bool(binding.GetJointIndicesPrimvar() or binding.GetBlendShapesAttr().HasValue())


def _animated_visibility(prim: Usd.Prim) -> bool:
    if not prim.IsA(UsdGeom.Imageable):
        return False
    return UsdGeom.Imageable(prim).GetVisibilityAttr().ValueMightBeTimeVarying()


def _animated_instance_mask(prim: Usd.Prim) -> bool:
    if not prim.IsA(UsdGeom.PointInstancer):
        return False
    # inactiveIds is list-op metadata, never animated: only invisibleIds can vary.
    return UsdGeom.PointInstancer(prim).GetInvisibleIdsAttr().ValueMightBeTimeVarying()


def _orthographic(prim: Usd.Prim) -> bool:
    if not prim.IsA(UsdGeom.Camera):
        return False
    return UsdGeom.Camera(prim).GetProjectionAttr().Get() == UsdGeom.Tokens.orthographic


def _of_types(*types) -> Callable[[Usd.Prim], bool]:
    return lambda prim: any(prim.IsA(t) for t in types)


# --- the table ---------------------------------------------------------------------------

#: What the render does not read as USD defines it, one row per kind (module doc).
KINDS: tuple[SupportKind, ...] = (
    SupportKind(
        "materialx_approximated", "materials MaterialX",
        "approximated: mapped onto UsdPreviewSurface without some inputs",
        "a MaterialX standard_surface, open_pbr_surface or UsdPreviewSurface is mapped onto "
        "UsdPreviewSurface's inputs (usd/materialx.py); inputs it authors that the mapping "
        "leaves out (sheen, subsurface scattering, a metal's edge tint, ...) are named in "
        "the render's notice",
        _materialx_approximated,
    ),
    SupportKind(
        "materialx_only", "materials MaterialX", "approximated: grey",
        "a MaterialX material of another surface shader renders as the default grey "
        "material (usd/materialx.py maps SURFACE_KINDS)",
        _materialx_grey,
    ),
    SupportKind(
        "other_surface_only", "materials without a UsdPreviewSurface", "approximated: grey",
        "surfaces of other render contexts (ri, arnold, custom shaders) are not read",
        _other_surface_only,
    ),
    SupportKind(
        "subdivided_mesh", "meshes subdivided", "approximated: cage",
        "subdivisionScheme (authored or USD's fallback catmullClark) is not none: the "
        "control cage is drawn, not the limit surface (usd/meshes.py is_subdivided)",
        lambda p: p.IsA(UsdGeom.Mesh) and is_subdivided(p),
    ),
    SupportKind(
        "animated_visibility", "prims with animated visibility",
        "approximated: visibility of the first frame",
        "usd/traversal.py reads visibility once, at the first time code of the range",
        _animated_visibility,
    ),
    SupportKind(
        "animated_instance_mask", "PointInstancers with animated invisibleIds",
        "approximated: the mask of the first frame",
        "usd/instancers.py reads the instance mask once, at the first time code",
        _animated_instance_mask,
    ),
    SupportKind(
        "skinned_mesh", "meshes skinned (UsdSkel)",
        "approximated: skinned per frame (linear blend or dual quaternion, blend shapes); "
        "inside PointInstancer prototypes the rest shape",
        "usd/skinning.py skins through UsdSkel.Cache; instancer prototypes are read once",
        _skinned,
    ),
    SupportKind(
        "basis_curves", "BasisCurves",
        f"approximated: tubes of {TUBE_SIDES} sides, open ends; with normals, flat ribbons",
        "usd/curves.py sweeps a circle of the widths along each curve, or, where the curves "
        "author normals, a strip of the widths facing them",
        _of_types(UsdGeom.BasisCurves),
    ),
    SupportKind(
        "curves", "curves (NurbsCurves, HermiteCurves)", IGNORED,
        "the render draws surfaces and BasisCurves only (meshes.RENDERED_GPRIM_TYPES)",
        _of_types(UsdGeom.NurbsCurves, UsdGeom.HermiteCurves),
    ),
    SupportKind(
        "points", "point clouds (Points)", IGNORED,
        "the render draws surfaces only (meshes.RENDERED_GPRIM_TYPES)",
        _of_types(UsdGeom.Points),
    ),
    SupportKind(
        "nurbs_patch", "NURBS patches", IGNORED,
        "no NURBS tessellation (meshes.RENDERED_GPRIM_TYPES)",
        _of_types(UsdGeom.NurbsPatch),
    ),
    SupportKind(
        "tet_mesh", "tetrahedral meshes (TetMesh)", IGNORED,
        "the render draws surfaces only (meshes.RENDERED_GPRIM_TYPES)",
        _of_types(UsdGeom.TetMesh),
    ),
    SupportKind(
        "volume", "volumes (UsdVolVolume)", IGNORED,
        "no volume rendering", _of_types(UsdVol.Volume),
    ),
    SupportKind(
        "texture_opacity_opaque", "UsdPreviewSurface shaders with a textured opacity "
        "and no opacityThreshold", "approximated: opaque",
        "texture alpha is read as a cut-out mask (opacityThreshold > 0); without a "
        "threshold the surface is drawn opaque, not blended",
        _texture_opacity_without_threshold,
    ),
    SupportKind(
        "unread_shader_node", "UsdPreviewSurface shaders with an input fed by a node "
        "the render does not read (the input takes its fallback)", IGNORED,
        "usd/materials.py reads UsdUVTexture outputs on texturable inputs and a "
        "UsdPrimvarReader on diffuseColor; other nodes (math, other readers) are not run",
        _unread_node,
    ),
    SupportKind(
        "rough_reflector", f"reflectors with roughness >= {FADE_START}",
        "approximated: the environment's reflection, faded in",
        f"glossy reflections are traced up to roughness {FADE_START} and faded into the "
        f"raster's environment fallback (no geometry in it) up to {FADE_END}, where no "
        "ray is traced (engine/trace/glossy.py)",
        _rough_reflector,
    ),
    SupportKind(
        "displacement", "materials with displacement", IGNORED,
        "no displacement: the mesh is drawn as authored",
        _displacement,
    ),
    SupportKind(
        "udim_texture", "textures with <UDIM> tiles", IGNORED,
        "UDIM tile sets are not resolved: the texture is not read",
        _udim_texture,
    ),
    SupportKind(
        "texture_format", "textures of a format OpenImageIO cannot read", IGNORED,
        "textures are read through OpenImageIO; this extension is not in its list",
        _unreadable_texture_format,
    ),
    SupportKind(
        "area_light", "area lights (Sphere, Rect, Disk, Cylinder)",
        "approximated: Sphere and Cylinder a point light at the light's centre; Rect and "
        "Disk an area's irradiance everywhere, its shadow the centre's where the shadow "
        "maps decide it",
        "usd/lights.py: emitted power kept; engine/trace/area_light_kernels.py: Rect and "
        "Disk areas wherever shaded (soft shadows where shadow rays decide)",
        _area_light,
    ),
    SupportKind(
        "unsupported_light", "lights of unsupported types (PortalLight, GeometryLight, ...)",
        IGNORED, "usd/lights.py reads Distant, Sphere, Rect, Disk, Cylinder and Dome lights",
        _unsupported_light,
    ),
    SupportKind(
        "ies_profile", "lights with an IES profile", IGNORED,
        "shaping:ies:file is not read; the light shines without the profile",
        _ies_profile,
    ),
    SupportKind(
        "light_filter", "light filters", IGNORED, "UsdLuxLightFilter is not read",
        _light_filter,
    ),
    SupportKind(
        "orthographic_camera", "orthographic cameras", IGNORED,
        "only perspective cameras render (an orthographic one is refused when chosen)",
        _orthographic,
    ),
)  # fmt: skip


def support_report(stage: Usd.Stage) -> list[dict]:
    """The rows of ``KINDS`` the stage uses, in table order: ``{"kind", "what", "count",
    "paths" (the first EXAMPLE_PATHS in traversal order), "treatment", "reason"}``."""
    found: dict[str, list[str]] = {k.kind: [] for k in KINDS}
    for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if prim.IsPseudoRoot():
            continue
        for kind in KINDS:
            if kind.matches(prim):
                found[kind.kind].append(str(prim.GetPath()))
    return [
        {
            "kind": k.kind,
            "what": k.what,
            "count": len(found[k.kind]),
            "paths": found[k.kind][:EXAMPLE_PATHS],
            "treatment": k.treatment,
            "reason": k.reason,
        }
        for k in KINDS
        if found[k.kind]
    ]


def support_lines(rows: list[dict]) -> list[str]:
    """One line per row: ``4 materials MaterialX: approximated: grey (/a, /b, ...)``."""
    lines = []
    for row in rows:
        more = ", ..." if row["count"] > len(row["paths"]) else ""
        lines.append(
            f"{row['count']} {row['what']}: {row['treatment']} ({', '.join(row['paths'])}{more})"
        )
    return lines
