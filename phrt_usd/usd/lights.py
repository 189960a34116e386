"""Lights: UsdLux Distant, Sphere, Rect, Disk, Cylinder and Dome lights as ``Lights``.

Read once, at the start of the frame range (not animated; colour temperature ignored).
Positions are world metres, directions world unit vectors.

- DistantLight: the direction towards the light (its +Z axis) and
  ``radiance = color * intensity * 2**exposure``.
- SphereLight: that radiance used as an intensity with 1/d² fall-off. Rect / Disk /
  Cylinder lights: the same times the light's (lateral) area in m² (unless
  ``inputs:normalize`` is on), placed at its centre as a point ``LocalLight``.
- DomeLight: ``color`` holds ``color * intensity * 2**exposure`` and ``texture`` the raw
  linear lat-long map; the environment radiance is ``texture * color``. Only the first
  DomeLight is used, lat-long textures only.
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdLux

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import DistantLight, DomeLight, Lights, LocalLight
from phrt_usd.usd.materials import read_texture
from phrt_usd.usd.values import (
    TimeContext,
    asset_file,
    attr_value,
    rotation_columns,
    safe_normalize,
)


def _light_radiance(prim: Usd.Prim, code: Usd.TimeCode) -> np.ndarray:
    """(3,) color * intensity * 2**exposure, finite and >= 0."""
    color = np.asarray(attr_value(prim, "inputs:color", code, (1.0, 1.0, 1.0)), dtype=np.float64)
    intensity = float(attr_value(prim, "inputs:intensity", code, 1.0))
    exposure = float(attr_value(prim, "inputs:exposure", code, 0.0))
    # Exposure is a log2 scale; clamp so 2**exposure stays finite in float64.
    value = color * intensity * 2.0 ** np.clip(exposure, -1000.0, 1000.0)
    return np.clip(np.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


#: UsdLux lights approximated as a point ``LocalLight`` at their centre.
_LOCAL_LIGHT_TYPES = (UsdLux.SphereLight, UsdLux.RectLight, UsdLux.DiskLight, UsdLux.CylinderLight)


def read_light(prim: Usd.Prim, ctx: TimeContext, mpu: float, lights: Lights) -> None:
    """Append the UsdLux light ``prim`` at ``ctx`` to ``lights`` (module doc);
    ``mpu`` is the stage's metres per unit. Other light types are ignored."""
    code = ctx.code
    m = ctx.world(prim)
    path = str(prim.GetPath())
    if prim.IsA(UsdLux.DistantLight):
        # The light shines down its -Z axis; store the direction towards the light.
        towards = safe_normalize(m[2, :3])
        angle = float(attr_value(prim, "inputs:angle", code, 0.53))
        lights.distant.append(DistantLight(towards, _light_radiance(prim, code), angle))
    elif any(prim.IsA(t) for t in _LOCAL_LIGHT_TYPES):
        radiance = _light_radiance(prim, code)
        scale = np.linalg.norm(m[:3, :3], axis=1) * mpu  # metres per light-space unit
        normalize = bool(attr_value(prim, "inputs:normalize", code, False))
        if prim.IsA(UsdLux.SphereLight):
            radius = float(attr_value(prim, "inputs:radius", code, 0.5)) * float(scale.max())
        elif prim.IsA(UsdLux.RectLight):
            w = float(attr_value(prim, "inputs:width", code, 1.0)) * scale[0]
            h = float(attr_value(prim, "inputs:height", code, 1.0)) * scale[1]
            radius = 0.5 * float(np.hypot(w, h))
            if not normalize:
                radiance = radiance * w * h  # area light → point intensity
        elif prim.IsA(UsdLux.DiskLight):
            r = float(attr_value(prim, "inputs:radius", code, 0.5))
            radius = r * float(max(scale[0], scale[1]))
            if not normalize:
                radiance = radiance * np.pi * (r * scale[0]) * (r * scale[1])
        else:  # CylinderLight: a tube along its local X axis
            r = float(attr_value(prim, "inputs:radius", code, 0.5)) * float(max(scale[1], scale[2]))
            length = float(attr_value(prim, "inputs:length", code, 1.0)) * scale[0]
            radius = 0.5 * float(np.hypot(length, 2 * r))
            if not normalize:
                radiance = radiance * 2.0 * np.pi * r * length  # lateral area
        if not np.isfinite(radius):
            raise PhrtError(f"{path}: non-finite light size")
        lights.local.append(LocalLight(m[3, :3] * mpu, radiance, abs(radius)))
    elif prim.IsA(UsdLux.DomeLight):
        if lights.dome is not None:
            return  # one environment: the first dome light wins
        fmt = str(attr_value(prim, "inputs:texture:format", code, "automatic"))
        if fmt not in ("automatic", "latlong"):
            raise PhrtError(f"{path}.inputs:texture:format: {fmt!r} unsupported (latlong only)")
        file_value = attr_value(prim, "inputs:texture:file", code, None)
        where = f"{path}.inputs:texture:file"
        file = asset_file(file_value, where) if file_value is not None else ""
        texture = read_texture(file, where, "auto") if file else None
        lights.dome = DomeLight(_light_radiance(prim, code), texture, rotation_columns(m))
