"""Python API of the Phrt USD schemas: author and read them without attribute-name strings.

The schemas themselves live in ``schemas/phrt/schema.usda`` (codeless plugin registered by
``import phrt_usd``). Every attribute and schema name is defined once here, but for the
render settings' ones, declared with their render options (their attribute, default and
range: ``phrt_usd.model.render_options.OPTIONS``); other modules import these constants.

Reads work with and without the plugin registered: applied schemas are detected through
the composed apiSchemas (``has_api``) and unauthored values fall back to the defaults below, which
match the schema fallbacks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdRender, Vt

from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.model.render_options import (  # noqa: F401 - usd.rules reads them here
    HEURISTICS,
    MAX_BOUNCE_LIMIT,
    MODES,
    OPTIONS,
)

# --- schema names -------------------------------------------------------------------------
REFLECTOR_API = "PhrtReflectorAPI"
CAMERA_PATH_TYPE = "PhrtCameraPath"
RENDER_SETTINGS_API = "PhrtRenderSettingsAPI"

# --- PhrtReflectorAPI ---------------------------------------------------------------------
PRIORITY = "phrt:priority"  # float K, designer priority
REFLECTIVITY = "phrt:reflectivity"  # float F in [0, 1]
# Per-frame figures written by renders into the selection layer (time-sampled).
SELECTED = "phrt:selected"  # bool
VISIBLE = "phrt:visible"  # bool
FIGURE_V = "phrt:V"  # float, V = A * P / D
FIGURE_C = "phrt:C"  # float, cost
FIGURE_R = "phrt:R"  # float, relevance
FIGURE_Q = "phrt:Q"  # float, cost factor
FIGURE_S = "phrt:S"  # bool, selected in the previous frame

DEFAULT_PRIORITY = 1.0
DEFAULT_REFLECTIVITY = 1.0

# --- PhrtCameraPath -----------------------------------------------------------------------
CAMERA = "phrt:camera"  # rel -> UsdGeomCamera
POSITIONS = "phrt:positions"  # point3d[], world, stage units
TARGETS = "phrt:targets"  # point3d[], world, stage units
KEY_TIMES = "phrt:keyTimes"  # double[], increasing time codes
START_FRAME = "phrt:startFrame"  # double
END_FRAME = "phrt:endFrame"  # double
INTERPOLATION = "phrt:interpolation"  # token
INTERPOLATIONS = ("linear", "catmullRom")
DEFAULT_INTERPOLATION = "catmullRom"

# --- PhrtRenderSettingsAPI ----------------------------------------------------------------
# Each attribute sets a render option; names, fallbacks and ranges are the options' table's
# (HEURISTICS, MODES and MAX_BOUNCE_LIMIT are imported from there too).
HEURISTIC = OPTIONS["heuristic"].schema_attribute  # token
MODE = OPTIONS["mode"].schema_attribute  # token
SELECTION_WEIGHT = OPTIONS["selection_weight"].schema_attribute  # float I
BUDGET_MS = OPTIONS["budget_ms"].schema_attribute  # float T, milliseconds
BUDGET_RAYS = OPTIONS["budget_rays"].schema_attribute  # int, -1 = not used
TARGET_FPS = OPTIONS["target_fps"].schema_attribute  # float fps, 0 = not used (then budgetMs)
BOUNCE_LIMIT = OPTIONS["bounce_limit"].schema_attribute  # int
DEFAULT_HEURISTIC = OPTIONS["heuristic"].default
DEFAULT_MODE = OPTIONS["mode"].default
DEFAULT_SELECTION_WEIGHT = OPTIONS["selection_weight"].default
DEFAULT_BUDGET_MS = OPTIONS["budget_ms"].default
DEFAULT_BUDGET_RAYS = OPTIONS["budget_rays"].schema_unset
DEFAULT_TARGET_FPS = OPTIONS["target_fps"].schema_unset
DEFAULT_BOUNCE_LIMIT = OPTIONS["bounce_limit"].default
# Image size when there is no UsdRenderSettings prim (the project's benchmark size).
DEFAULT_RESOLUTION = (OPTIONS["width"].default, OPTIONS["height"].default)

# Value type of every authored property, so authoring never depends on the plugin.
_TYPES = {
    PRIORITY: Sdf.ValueTypeNames.Float,
    REFLECTIVITY: Sdf.ValueTypeNames.Float,
    SELECTED: Sdf.ValueTypeNames.Bool,
    VISIBLE: Sdf.ValueTypeNames.Bool,
    FIGURE_V: Sdf.ValueTypeNames.Float,
    FIGURE_C: Sdf.ValueTypeNames.Float,
    FIGURE_R: Sdf.ValueTypeNames.Float,
    FIGURE_Q: Sdf.ValueTypeNames.Float,
    FIGURE_S: Sdf.ValueTypeNames.Bool,
    POSITIONS: Sdf.ValueTypeNames.Point3dArray,
    TARGETS: Sdf.ValueTypeNames.Point3dArray,
    KEY_TIMES: Sdf.ValueTypeNames.DoubleArray,
    START_FRAME: Sdf.ValueTypeNames.Double,
    END_FRAME: Sdf.ValueTypeNames.Double,
    INTERPOLATION: Sdf.ValueTypeNames.Token,
    HEURISTIC: Sdf.ValueTypeNames.Token,
    MODE: Sdf.ValueTypeNames.Token,
    SELECTION_WEIGHT: Sdf.ValueTypeNames.Float,
    BUDGET_MS: Sdf.ValueTypeNames.Float,
    BUDGET_RAYS: Sdf.ValueTypeNames.Int,
    TARGET_FPS: Sdf.ValueTypeNames.Float,
    BOUNCE_LIMIT: Sdf.ValueTypeNames.Int,
}


def _set(prim: Usd.Prim, name: str, value, time: Usd.TimeCode | None = None) -> None:
    attr = prim.GetAttribute(name)  # valid when the schema defines it or it is authored
    if not attr:
        attr = prim.CreateAttribute(name, _TYPES[name])
    attr.Set(value, Usd.TimeCode.Default() if time is None else time)


def _get(prim: Usd.Prim, name: str, default, time: Usd.TimeCode | float | None = None):
    """Value of ``name`` at ``time`` (default time if None), or ``default`` when it has
    none: unauthored without the plugin registered, or a property without a fallback."""
    attr = prim.GetAttribute(name)
    if not attr:
        return default
    value = attr.Get(Usd.TimeCode.Default() if time is None else time)
    return default if value is None else value


def _f32(value) -> float:
    """A float attribute value as the shortest Python float that reads back as the same
    float32 (0.001, not 0.0010000000474974513); NaN/Inf pass through for validation."""
    return float(np.format_float_positional(np.float32(value), unique=True, trim="0"))


def _add_api(prim: Usd.Prim, api: str) -> None:
    """Apply ``api``; plain ``AddAppliedSchema`` when the plugin is not registered."""
    if has_api(prim, api):
        return
    if Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(api):
        prim.ApplyAPI(api)
    else:
        prim.AddAppliedSchema(api)


# --- reflectors ---------------------------------------------------------------------------
def apply_reflector(
    prim: Usd.Prim, priority: float | None = None, reflectivity: float | None = None
) -> None:
    """Apply PhrtReflectorAPI to a gprim in the current edit target, optionally setting K
    and F (left unauthored when None: the schema fallbacks 1 and 1 apply)."""
    if not prim or not prim.IsValid():
        raise PhrtError(f"{prim.GetPath() if prim else '<invalid prim>'}: prim does not exist")
    if not prim.IsA(UsdGeom.Gprim):
        raise PhrtError(
            f"{prim.GetPath()}: is a {prim.GetTypeName() or 'typeless prim'}, not a gprim; "
            f"{REFLECTOR_API} applies to gprims only"
        )
    _add_api(prim, REFLECTOR_API)
    if priority is not None:
        _set(prim, PRIORITY, float(priority))
    if reflectivity is not None:
        _set(prim, REFLECTIVITY, float(reflectivity))


def has_api(prim: Usd.Prim, api: str) -> bool:
    """True when ``api`` is in the prim's composed apiSchemas. Unlike
    ``prim.GetAppliedSchemas()``, which drops schemas unknown to the registry, this also
    works in a process where the Phrt plugin is not registered."""
    return bool(prim) and api in prim.GetPrimTypeInfo().GetAppliedAPISchemas()


def is_reflector(prim: Usd.Prim) -> bool:
    """True when the prim has PhrtReflectorAPI applied (with or without the plugin)."""
    return has_api(prim, REFLECTOR_API)


def reflector_priority(prim: Usd.Prim) -> float:
    """K of a reflector (1 when unauthored)."""
    return _f32(_get(prim, PRIORITY, DEFAULT_PRIORITY))


def reflector_reflectivity(prim: Usd.Prim) -> float:
    """F of a reflector (1 when unauthored)."""
    return _f32(_get(prim, REFLECTIVITY, DEFAULT_REFLECTIVITY))


def reflectivity_authored(prim: Usd.Prim) -> bool:
    """Whether a reflector's ``phrt:reflectivity`` has an authored value (an explicit F
    that overrides the material's Fresnel, ``engine/compositing.py``)."""
    attr = prim.GetAttribute(REFLECTIVITY)
    return bool(attr) and attr.HasAuthoredValue()


def mark_material_reflections(stage: Usd.Stage, elements) -> None:
    """Set ``reflectivity_authored`` False on the reflector elements (``model.scene.
    Element``) whose prim leaves ``phrt:reflectivity`` unauthored: their reflection
    follows their material (``engine/compositing.py``). A point instancer's instance
    (``<prototype>.instance[i]``) is its prototype gprim's; an element whose prim cannot
    be found keeps its F as an override."""
    for element in elements:
        if not element.is_reflector:
            continue
        path = element.path.split(".instance[")[0]
        if not Sdf.Path.IsValidPathString(path):
            continue
        prim = stage.GetPrimAtPath(path)
        if prim and prim.IsValid() and not reflectivity_authored(prim):
            element.reflectivity_authored = False


def find_reflectors(stage: Usd.Stage) -> list[Usd.Prim]:
    """Active, defined reflectors of the stage, in traversal order."""
    return [p for p in stage.Traverse() if is_reflector(p)]


# --- camera paths -------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraPathData:
    """A PhrtCameraPath as arrays.

    positions, targets : (n, 3) float64, world space, stage units
    key_times : (n,) float64, time codes
    """

    path: str
    camera: str | None
    positions: np.ndarray
    targets: np.ndarray
    key_times: np.ndarray
    start: float
    end: float
    interpolation: str


def define_camera_path(
    stage: Usd.Stage,
    path: str | Sdf.Path,
    camera: str | Sdf.Path,
    positions: Sequence[Sequence[float]] | np.ndarray,
    targets: Sequence[Sequence[float]] | np.ndarray,
    key_times: Sequence[float] | np.ndarray,
    start: float | None = None,
    end: float | None = None,
    interpolation: str = DEFAULT_INTERPOLATION,
) -> Usd.Prim:
    """Define a PhrtCameraPath prim at ``path`` driving the camera prim at ``camera``.

    positions, targets : (n, 3) world space, stage units; key_times : (n,) time codes.
    start/end default to the first/last key time. Values are written as given; run
    ``phrt validate`` (or ``phrt_usd.usd.validation``) to check them.
    """
    if interpolation not in INTERPOLATIONS:
        raise PhrtError(
            f"{path}.{INTERPOLATION}: '{interpolation}' is not one of {', '.join(INTERPOLATIONS)}"
        )
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    keys = np.asarray(key_times, dtype=np.float64).reshape(-1)
    prim = stage.DefinePrim(Sdf.Path(str(path)), CAMERA_PATH_TYPE)
    prim.CreateRelationship(CAMERA).SetTargets([Sdf.Path(str(camera))])
    _set(prim, POSITIONS, Vt.Vec3dArray.FromNumpy(pos))
    _set(prim, TARGETS, Vt.Vec3dArray.FromNumpy(tgt))
    _set(prim, KEY_TIMES, Vt.DoubleArray.FromNumpy(keys))
    if start is None:
        start = float(keys[0]) if keys.size else 0.0
    if end is None:
        end = float(keys[-1]) if keys.size else 0.0
    _set(prim, START_FRAME, float(start))
    _set(prim, END_FRAME, float(end))
    _set(prim, INTERPOLATION, interpolation)
    return prim


def find_camera_paths(stage: Usd.Stage) -> list[Usd.Prim]:
    """All PhrtCameraPath prims of the stage, in traversal order (type name compared, so
    this works with and without the plugin registered)."""
    return [p for p in stage.Traverse() if p.GetTypeName() == CAMERA_PATH_TYPE]


def read_camera_path(prim: Usd.Prim) -> CameraPathData:
    """The path's values; missing arrays read as empty, start/end default to the first/last
    key time (0 when there are none)."""

    def array(name: str, width: int) -> np.ndarray:
        value = _get(prim, name, None)
        arr = np.asarray(value if value is not None else [], dtype=np.float64)
        return arr.reshape(-1, width) if width > 1 else arr.reshape(-1)

    keys = array(KEY_TIMES, 1)
    targets = prim.GetRelationship(CAMERA).GetTargets() if prim.GetRelationship(CAMERA) else []
    first = float(keys[0]) if keys.size else 0.0
    last = float(keys[-1]) if keys.size else 0.0
    return CameraPathData(
        path=str(prim.GetPath()),
        camera=str(targets[0]) if targets else None,
        positions=array(POSITIONS, 3),
        targets=array(TARGETS, 3),
        key_times=keys,
        start=float(_get(prim, START_FRAME, first)),
        end=float(_get(prim, END_FRAME, last)),
        interpolation=str(_get(prim, INTERPOLATION, DEFAULT_INTERPOLATION)),
    )


# --- render settings ----------------------------------------------------------------------
@dataclass(frozen=True)
class RenderParams:
    """Renderer parameters read from a UsdRenderSettings prim (or defaults)."""

    heuristic: str = DEFAULT_HEURISTIC
    mode: str = DEFAULT_MODE
    selection_weight: float = DEFAULT_SELECTION_WEIGHT  # I
    budget_ms: float = DEFAULT_BUDGET_MS  # T
    budget_rays: int | None = None  # None when phrt:budgetRays is -1 / unauthored
    target_fps: float | None = None  # None when phrt:targetFps is 0 / unauthored
    bounce_limit: int = DEFAULT_BOUNCE_LIMIT
    resolution: tuple[int, int] = DEFAULT_RESOLUTION  # (width, height) pixels
    camera_path: str | None = None  # the UsdRenderSettings camera relationship target
    settings_path: str | None = None  # the UsdRenderSettings prim, None for defaults


def apply_render_settings(
    prim: Usd.Prim,
    heuristic: str | None = None,
    mode: str | None = None,
    selection_weight: float | None = None,
    budget_ms: float | None = None,
    budget_rays: int | None = None,
    bounce_limit: int | None = None,
    target_fps: float | None = None,
) -> None:
    """Apply PhrtRenderSettingsAPI to a UsdRenderSettings prim; set the given values."""
    if not prim or not prim.IsA(UsdRender.Settings):
        where = prim.GetPath() if prim else "<invalid prim>"
        raise PhrtError(f"{where}: {RENDER_SETTINGS_API} applies to RenderSettings prims only")
    if heuristic is not None and heuristic not in HEURISTICS:
        raise PhrtError(f"{prim.GetPath()}.{HEURISTIC}: '{heuristic}' is not one of {HEURISTICS}")
    if mode is not None and mode not in MODES:
        raise PhrtError(f"{prim.GetPath()}.{MODE}: '{mode}' is not one of {MODES}")
    _add_api(prim, RENDER_SETTINGS_API)
    for name, value, cast in (
        (HEURISTIC, heuristic, str),
        (MODE, mode, str),
        (SELECTION_WEIGHT, selection_weight, float),
        (BUDGET_MS, budget_ms, float),
        (BUDGET_RAYS, budget_rays, int),
        (BOUNCE_LIMIT, bounce_limit, int),
        (TARGET_FPS, target_fps, float),
    ):
        if value is not None:
            _set(prim, name, cast(value))


def find_render_settings(stage: Usd.Stage, settings_path: str | None = None) -> Usd.Prim | None:
    """The UsdRenderSettings prim to use: ``settings_path`` if given (``BadOption``,
    listing the stage's RenderSettings prims, if it is not the path of one), else the
    stage's ``renderSettingsPrimPath`` metadata, else the first RenderSettings prim in
    traversal order, else None."""
    if settings_path:
        valid = Sdf.Path.IsValidPathString(settings_path) and settings_path.startswith("/")
        prim = stage.GetPrimAtPath(settings_path) if valid else None
        if not prim or not prim.IsA(UsdRender.Settings):
            have = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
            raise BadOption(
                f"--settings {settings_path}: no RenderSettings prim at this path "
                f"(RenderSettings prims: {', '.join(have) or 'none'})"
            )
        return prim
    stage_settings = UsdRender.Settings.GetStageRenderSettings(stage)
    if stage_settings:
        return stage_settings.GetPrim()
    for prim in stage.Traverse():
        if prim.IsA(UsdRender.Settings):
            return prim
    return None


def read_render_params(stage: Usd.Stage, settings_path: str | None = None) -> RenderParams:
    """RenderParams from the stage's render settings (see find_render_settings); defaults
    when there is none. Values are read as authored; ``phrt_usd.usd.validation`` checks them."""
    prim = find_render_settings(stage, settings_path)
    if prim is None:
        return RenderParams()
    settings = UsdRender.Settings(prim)
    res = settings.GetResolutionAttr().Get()
    cameras = settings.GetCameraRel().GetTargets()
    rays = int(_get(prim, BUDGET_RAYS, DEFAULT_BUDGET_RAYS))
    fps = _f32(_get(prim, TARGET_FPS, DEFAULT_TARGET_FPS))
    return RenderParams(
        heuristic=str(_get(prim, HEURISTIC, DEFAULT_HEURISTIC)),
        mode=str(_get(prim, MODE, DEFAULT_MODE)),
        selection_weight=_f32(_get(prim, SELECTION_WEIGHT, DEFAULT_SELECTION_WEIGHT)),
        budget_ms=_f32(_get(prim, BUDGET_MS, DEFAULT_BUDGET_MS)),
        budget_rays=None if rays < 0 else rays,
        target_fps=fps if fps != 0.0 else None,
        bounce_limit=int(_get(prim, BOUNCE_LIMIT, DEFAULT_BOUNCE_LIMIT)),
        resolution=(int(res[0]), int(res[1])) if res is not None else DEFAULT_RESOLUTION,
        camera_path=str(cameras[0]) if cameras else None,
        settings_path=str(prim.GetPath()),
    )
