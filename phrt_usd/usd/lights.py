"""Lights: UsdLux Distant, Sphere, Rect, Disk, Cylinder, Dome and DomeLight_1 as ``Lights``.

Read once, at the start of the frame range (not animated). Positions are world metres,
directions world unit vectors. Conventions (docs/usd-support.md, "Lights"):

- Every light's emission is ``color * intensity * 2**exposure`` times, with
  ``enableColorTemperature``, the blackbody colour of ``colorTemperature``
  (``blackbody.blackbody_rec709``: 6500 K white, luminance 1), as UsdLux's LightAPI
  defines it.
- DistantLight: the direction towards the light (its +Z axis); the emission is the
  irradiance on a surface facing it (a white surface shows it: the preview-renderer
  convention of ``engine/shading.py``), whatever ``angle`` and ``normalize`` say, so the
  fallback intensity 50000 is a very bright sun (the clipping warning of the render
  names it and ``--exposure``).
- Local lights (Sphere, Rect, Disk, Cylinder): each a point ``LocalLight`` at its
  centre (Rect and Disk lights also carry their emitting surface, ``_area``: the trace
  samples it) whose intensity follows ``local_intensity``, the one place of the unit rule:
  every length is in metres (the light's sizes times its transform's scale times the
  stage's ``metersPerUnit``), the emission is the luminance of the light's surface and
  the intensity is that luminance times the light's area seen face-on in m² (sphere
  πr², rect w·h, disk πr², cylinder side-on 2rℓ); with ``normalize`` the luminance is
  first divided by the emitting surface area in m² (sphere 4πr², cylinder 2πrℓ), as
  UsdLux's LightAPI says, so the intensity is the emission times face-on / surface
  (1/4, 1, 1, 1/π) whatever the size. ``treatAsPoint`` makes a SphereLight a point
  (radius 0: no shadow-ray offset) of the normalized sphere's intensity, emission / 4.
  Distances are metres too (1/d² in ``engine/shading.py``), so a stage authored in
  centimetres and the same stage in metres render the same image.
- ShapingAPI (local lights): ``shaping:cone:angle`` (fallback 90 once the API is
  applied), ``shaping:cone:softness``, ``shaping:focus`` along the light's -Z axis,
  evaluated by ``shading.cone_falloff``; ``focusTint`` and IES profiles are not read.
- DomeLight / DomeLight_1: ``color`` holds the emission, ``texture`` the raw linear
  lat-long map; the environment radiance is ``texture * color``; a texture that cannot
  be read is a warning (an error with ``--strict``) and the dome renders in its colour.
  DomeLight_1's ``poleAxis`` ("scene": the stage's up axis, "Y", "Z") turns the map's
  pole to +Z for Z (UsdLux: latitude 0, longitude 0 then points to -Y).
  ``inputs:texture:format`` other than ``automatic`` / ``latlong``: one warning, the
  dome untextured. The dome is hidden from camera rays (still lighting) when one of
  ``CAMERA_VISIBILITY_ATTRS`` says so. Only the first dome is used.
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdLux

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import DistantLight, DomeLight, Lights, LocalLight
from phrt_usd.usd.blackbody import blackbody_rec709
from phrt_usd.usd.materials import read_texture
from phrt_usd.usd.textures import TextureError
from phrt_usd.usd.values import (
    TimeContext,
    attr_value,
    rotation_columns,
    safe_normalize,
)

#: Largest |exposure| (EV) read: 2**1000 is still finite in float64.
MAX_LIGHT_EXPOSURE_EV = 1000.0

#: Dome texture formats read as a lat-long map (``inputs:texture:format``).
LATLONG_FORMATS = ("automatic", "latlong")

#: Bool attributes that hide a dome from camera rays when authored false, in the order
#: read: ``visibleInPrimaryRay`` (the name Omniverse's RTX renderer and the UsdLux
#: proposals use) and Karma's ``karma:light:renderlightgeo`` (its "render light
#: geometry", which for a dome is the background seen by the camera).
CAMERA_VISIBILITY_ATTRS = ("visibleInPrimaryRay", "karma:light:renderlightgeo")

#: UsdLux ``DomeLight_1.poleAxis`` → rotation (columns: images of the dome-space axes)
#: from the OpenEXR lat-long frame (+Y pole, longitude 0 at +Z) to the pole's frame:
#: for Z, +Y → +Z and +Z → -Y (a +90° turn about X), as the schema describes.
_POLE_ROTATIONS = {
    "Y": np.eye(3),
    "Z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}

#: Type names of the lights ``read_light`` reads (a stage with none of them gets the
#: default light rig, ``default_lights``).
READ_LIGHT_TYPE_NAMES = (
    "DistantLight",
    "SphereLight",
    "RectLight",
    "DiskLight",
    "CylinderLight",
    "DomeLight",
    "DomeLight_1",
)

#: UsdLux lights approximated as a point ``LocalLight`` at their centre.
_LOCAL_LIGHT_TYPES = (UsdLux.SphereLight, UsdLux.RectLight, UsdLux.DiskLight, UsdLux.CylinderLight)
#: The dome light schemas, oldest first.
_DOME_TYPES = (UsdLux.DomeLight, UsdLux.DomeLight_1)


def light_emission(prim: Usd.Prim, code: Usd.TimeCode) -> np.ndarray:
    """(3,) UsdLux emission ``color * intensity * 2**exposure`` (times the blackbody
    colour of ``colorTemperature`` when ``enableColorTemperature``), finite and >= 0.
    Unauthored inputs read the schema's fallbacks (DistantLight's intensity: 50000)."""
    color = np.asarray(attr_value(prim, "inputs:color", code, (1.0, 1.0, 1.0)), dtype=np.float64)
    intensity = float(attr_value(prim, "inputs:intensity", code, 1.0))
    exposure = float(attr_value(prim, "inputs:exposure", code, 0.0))
    limit = MAX_LIGHT_EXPOSURE_EV
    value = color * intensity * 2.0 ** float(np.clip(np.nan_to_num(exposure), -limit, limit))
    if bool(attr_value(prim, "inputs:enableColorTemperature", code, False)):
        kelvin = float(attr_value(prim, "inputs:colorTemperature", code, 6500.0))
        value = value * blackbody_rec709(kelvin)
    return np.clip(np.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def _shaping(prim: Usd.Prim, code: Usd.TimeCode, m: np.ndarray) -> dict:
    """LocalLight ShapingAPI fields: the world axis (the light's -Z) and the cone and
    focus inputs (an unapplied API without authored inputs: no cone, no focus)."""
    angle = float(attr_value(prim, "inputs:shaping:cone:angle", code, 180.0))
    softness = float(attr_value(prim, "inputs:shaping:cone:softness", code, 0.0))
    focus = float(attr_value(prim, "inputs:shaping:focus", code, 0.0))
    return {
        "axis": safe_normalize(-np.asarray(m[2, :3], dtype=np.float64)),
        "cone_angle": float(np.clip(np.nan_to_num(angle, nan=180.0), 0.0, 180.0)),
        "cone_softness": float(np.clip(np.nan_to_num(softness), 0.0, 1.0)),
        # UsdLux: "values < 0 are ignored".
        "focus": float(max(np.nan_to_num(focus), 0.0)),
    }


def _camera_visible(prim: Usd.Prim, code: Usd.TimeCode) -> bool:
    for name in CAMERA_VISIBILITY_ATTRS:
        attr = prim.GetAttribute(name)
        if attr and attr.HasAuthoredValue():
            return bool(attr.Get(code))
    return True


def _dome(
    prim: Usd.Prim,
    code: Usd.TimeCode,
    m: np.ndarray,
    up_axis: str,
    warnings: list[str],
    texture_problems: list[str],
) -> DomeLight:
    """The dome light ``prim``; a texture that cannot be read is one line in
    ``texture_problems`` and the dome untextured, in its colour (the fallback of
    ``inputs:texture:file``, as for a surface texture)."""
    path = str(prim.GetPath())
    rotation = rotation_columns(m)
    if prim.IsA(UsdLux.DomeLight_1):
        pole = str(attr_value(prim, "poleAxis", code, "scene"))
        pole = up_axis if pole == "scene" else pole
        if pole not in _POLE_ROTATIONS:
            raise PhrtError(f"{path}.poleAxis: {pole!r} is not one of scene, Y, Z")
        rotation = rotation @ _POLE_ROTATIONS[pole]
    fmt = str(attr_value(prim, "inputs:texture:format", code, "automatic"))
    file_value = attr_value(prim, "inputs:texture:file", code, None)
    where = f"{path}.inputs:texture:file"
    authored = str(getattr(file_value, "path", file_value) or "") if file_value else ""
    texture = None
    if authored and fmt not in LATLONG_FORMATS:
        warnings.append(
            f"{path}.inputs:texture:format: {fmt!r} not supported (latlong, automatic); "
            "the dome is rendered untextured in its colour"
        )
    elif authored:
        try:
            texture = read_texture(file_value, where, "auto")
        except TextureError as problem:  # as a surface texture: its input's fallback
            texture_problems.append(str(problem))
    return DomeLight(
        light_emission(prim, code), texture, rotation, path, _camera_visible(prim, code)
    )


#: A local light's area seen face-on over its emitting surface area (both in m²), by
#: shape: what ``normalize`` leaves of the emission (``local_intensity``). A sphere
#: shows πr² of its 4πr²; a rect and a disk are one face; a cylinder seen side-on
#: shows 2rℓ of its lateral 2πrℓ (its caps do not emit).
FACE_ON_PER_SURFACE = {
    "SphereLight": 0.25,
    "RectLight": 1.0,
    "DiskLight": 1.0,
    "CylinderLight": 1.0 / np.pi,
}
#: A SphereLight with ``treatAsPoint``: the limit of a normalized sphere shrunk to its
#: centre (constant power), face-on / surface 1/4 at every radius.
POINT_SHAPE = "SphereLight"


def local_intensity(
    emission: np.ndarray, shape: str, face_on_m2: float, normalize: bool
) -> np.ndarray:
    """(3,) intensity of a local light (module doc; docs/usd-support.md "Lights"): its
    emission (``light_emission``, the luminance of its surface) times its area seen
    face-on ``face_on_m2`` in m², or with ``normalize`` (the luminance divided by the
    emitting surface area in m², UsdLux LightAPI) times ``FACE_ON_PER_SURFACE[shape]``,
    independent of the size. ``face_on_m2`` in metres (``metersPerUnit`` applied) makes
    a stage authored in centimetres and the same stage in metres give one intensity."""
    if normalize:
        return emission * FACE_ON_PER_SURFACE[shape]
    return emission * abs(face_on_m2)


def _local_shape(prim: Usd.Prim, code: Usd.TimeCode, scale: np.ndarray):
    """(shape name, radius in m offsetting shadow rays, area seen face-on in m²) of the
    local light ``prim``; ``scale`` (3,) metres per light-space unit along its axes."""
    if prim.IsA(UsdLux.SphereLight):
        r = float(attr_value(prim, "inputs:radius", code, 0.5)) * float(scale.max())
        return "SphereLight", r, np.pi * r * r
    if prim.IsA(UsdLux.RectLight):
        w = float(attr_value(prim, "inputs:width", code, 1.0)) * scale[0]
        h = float(attr_value(prim, "inputs:height", code, 1.0)) * scale[1]
        return "RectLight", 0.5 * float(np.hypot(w, h)), w * h
    if prim.IsA(UsdLux.DiskLight):
        r = float(attr_value(prim, "inputs:radius", code, 0.5))
        radius = r * float(max(scale[0], scale[1]))
        return "DiskLight", radius, np.pi * (r * scale[0]) * (r * scale[1])
    # CylinderLight: a tube along its local X axis.
    r = float(attr_value(prim, "inputs:radius", code, 0.5)) * float(max(scale[1], scale[2]))
    length = float(attr_value(prim, "inputs:length", code, 1.0)) * scale[0]
    return "CylinderLight", 0.5 * float(np.hypot(length, 2 * r)), 2.0 * r * length


def _area(prim: Usd.Prim, code: Usd.TimeCode, m: np.ndarray, mpu: float) -> dict:
    """A Rect or Disk light's emitting surface (``LocalLight.area_shape``, ``area_u``,
    ``area_v``): its half sizes along its local X and Y axes, world metres; {} for any
    other light."""
    x, y = np.asarray(m[0, :3], np.float64) * mpu, np.asarray(m[1, :3], np.float64) * mpu
    if prim.IsA(UsdLux.RectLight):
        w = float(attr_value(prim, "inputs:width", code, 1.0))
        h = float(attr_value(prim, "inputs:height", code, 1.0))
        return {"area_shape": "rect", "area_u": 0.5 * w * x, "area_v": 0.5 * h * y}
    if prim.IsA(UsdLux.DiskLight):
        r = float(attr_value(prim, "inputs:radius", code, 0.5))
        return {"area_shape": "disk", "area_u": r * x, "area_v": r * y}
    return {}


def read_light(
    prim: Usd.Prim,
    ctx: TimeContext,
    mpu: float,
    lights: Lights,
    up_axis: str = "Y",
    warnings: list[str] | None = None,
    texture_problems: list[str] | None = None,
) -> None:
    """Append the UsdLux light ``prim`` at ``ctx`` to ``lights`` (module doc); ``mpu``
    is the stage's metres per unit, ``up_axis`` its up axis (DomeLight_1's "scene"
    pole); what is read with a fallback is appended to ``warnings``, a dome texture
    that cannot be read (``textures.TextureError``) to ``texture_problems`` (the dome
    then renders in its colour). Other light types are ignored."""
    code = ctx.code
    m = ctx.world(prim)
    path = str(prim.GetPath())
    warnings = [] if warnings is None else warnings
    texture_problems = [] if texture_problems is None else texture_problems
    if prim.IsA(UsdLux.DistantLight):
        # The light shines down its -Z axis; store the direction towards the light.
        towards = safe_normalize(m[2, :3])
        angle = float(attr_value(prim, "inputs:angle", code, 0.53))
        lights.distant.append(DistantLight(towards, light_emission(prim, code), angle, path))
    elif any(prim.IsA(t) for t in _LOCAL_LIGHT_TYPES):
        scale = np.linalg.norm(m[:3, :3], axis=1) * mpu  # metres per light-space unit
        shape, radius, face_on = _local_shape(prim, code, scale)
        normalize = bool(attr_value(prim, "inputs:normalize", code, False))
        if shape == "SphereLight" and bool(attr_value(prim, "treatAsPoint", code, False)):
            shape, radius, normalize = POINT_SHAPE, 0.0, True
        intensity = local_intensity(light_emission(prim, code), shape, face_on, normalize)
        if not np.isfinite(radius) or not np.all(np.isfinite(intensity)):
            raise PhrtError(f"{path}: non-finite light size")
        lights.local.append(
            LocalLight(m[3, :3] * mpu, intensity, abs(radius), path, **_shaping(prim, code, m),
                       **_area(prim, code, m, mpu))  # fmt: skip
        )
    elif any(prim.IsA(t) for t in _DOME_TYPES):
        if lights.dome is not None:
            return  # one environment: the first dome light wins
        lights.dome = _dome(prim, code, m, up_axis, warnings, texture_problems)


def fallback_intensity(stage: Usd.Stage, path: str) -> float | None:
    """The schema's fallback ``inputs:intensity`` the light at ``path`` reads because
    none is authored (DistantLight's is 50000, a sun for a physically based renderer),
    else None (authored, or no such prim)."""
    prim = stage.GetPrimAtPath(path) if path.startswith("/") else None
    attr = prim.GetAttribute("inputs:intensity") if prim else None
    if not attr or attr.HasAuthoredValue():
        return None
    return float(attr.Get())


def intensity_note(stage: Usd.Stage, path: str) -> str:
    """``"; inputs:intensity unauthored: UsdLux's fallback N"`` when the light at
    ``path`` reads its intensity from the schema's fallback, else ``""``."""
    value = fallback_intensity(stage, path)
    return "" if value is None else f"; inputs:intensity unauthored: UsdLux's fallback {value:g}"
