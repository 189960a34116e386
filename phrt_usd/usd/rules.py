"""The Phrt rules: what ``phrt validate`` and any USD tool (through the UsdValidation
validators of ``phrt_usd.usd.validators``) report about a stage, as ``Issue``s.

Every problem is one ``Issue`` with a location (``/prim/path``, ``/prim/path.attribute``,
or a layer for layer-level problems) and a message. Severity: ``error`` makes the stage
unusable or wrong for rendering; ``warning`` is suspicious but renders (e.g. a zero-area
mirror). ``rule`` names the group of rules an issue comes from (the ValidationError's
name).

The rules agree with render: the render's refusal rules live in ``phrt_usd.usd.stage``,
``phrt_usd.usd.meshes``, ``phrt_usd.usd.composition`` and ``phrt_usd.usd.camera_path``
as functions returning the message the render raises; these rules call the same
functions and report each message as an error, with the same text (``Issue.line()`` is
``"ERROR " + message``). Checked where the render reads:

- composition (``composition_issues``): every sublayer, reference and payload USD could
  not open, one line each (prim and asset, or layer and sublayer), and other composition
  errors — errors here, warnings in ``StageScene.warnings`` (the render goes on without
  them);
- stage: metersPerUnit > 0; the camera to render (``choose_camera``); a stage without
  any UsdGeomCamera is a warning (the render frames its bounds with a default camera,
  ``phrt_usd.usd.default_camera``; without geometry either, the render refuses it);
- the render's camera (``choose_camera``, no ``--camera``): the camera path that drives it
  (``camera_path_problems``) and ``camera_problems`` at the start and end of the frame
  range and at every time sample inside it; other cameras and their paths get the same
  checks as warnings (they render only with ``--camera``); a camera path that drives no
  camera is a warning (the render ignores it);
- every gprim the render reads (``rendered_gprims``: visible at the start of the frame
  range, of a purpose the render settings' ``includedPurposes`` draw (``included_purposes``,
  UsdRender's fallback ``default`` and ``render``; an unknown token is a warning),
  PointInstancer prototypes included): reflector K and F (``reflector_problems``), mesh
  points and topology at the start and at every time sample of an animated shape
  (``mesh_problems_in_range``);
- finally ``read_stage`` itself, so that anything else it refuses (textures, primvar
  sizes, instancers, lights) is reported too (one message: it stops at the first).

Warnings only (the render accepts these): reflector F outside [0, 1] (clamped), a
reflector on a prim the render does not draw as geometry, a Mesh reflector with no faces,
faces of fewer than 3 vertices (skipped), zero area (``holeIndices`` faces not counted).

Render settings with PhrtRenderSettingsAPI (``render_settings_issues``, one prim at a
time): budgets >= 0 (budgetRays >= -1), bounce limit 0..MAX_BOUNCE_LIMIT, selection weight
finite >= 0, heuristic and mode allowed, resolution > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pxr import Usd, UsdGeom, UsdRender

from phrt_usd.errors import PhrtError
from phrt_usd.usd import schema
from phrt_usd.usd.camera_path import camera_path_problems, find_camera_path_prim, read_camera_path
from phrt_usd.usd.composition import CompositionProblem, composition_problems
from phrt_usd.usd.lights import fallback_intensity
from phrt_usd.usd.meshes import RENDERED_GPRIM_TYPES, mesh_area, mesh_problems_in_range
from phrt_usd.usd.render_settings import included_purposes
from phrt_usd.usd.stage import (
    camera_check_times,
    camera_problems,
    choose_camera,
    frame_range,
    read_stage,
    reflector_problems,
    rendered_gprims,
    stage_problems,
)
from phrt_usd.usd.values import first_per_location

ERROR = "error"
WARNING = "warning"

#: Rule groups (``Issue.rule``, the name of the ValidationError a validator reports).
COMPOSITION = "Composition"
STAGE = "Stage"
CAMERA = "Camera"
CAMERA_PATH = "CameraPath"
GEOMETRY = "Geometry"
READ = "Read"
RENDER_SETTINGS = "RenderSettings"
LIGHTS = "Lights"


@dataclass(frozen=True)
class Issue:
    """One problem: ``where`` is ``/prim/path``, ``/prim/path.attribute`` or a layer."""

    severity: str
    where: str
    message: str
    rule: str = field(default="", compare=False)

    def line(self) -> str:
        return f"{self.severity.upper()} {self.where}: {self.message}"

    def text(self) -> str:
        """``where: message``, the form of a render message (``Issue.of`` reads it back)."""
        return f"{self.where}: {self.message}"

    def as_dict(self) -> dict:
        return {"where": self.where, "message": self.message}

    @classmethod
    def of(cls, severity: str, message: str, rule: str = "") -> Issue:
        """An issue from a render message ``"<where>: <text>"``: its ``line()`` is the
        severity and the message, unchanged."""
        where, sep, text = message.partition(": ")
        return cls(severity, where, text, rule) if sep else cls(severity, "/", message, rule)


def _attr_where(prim: Usd.Prim, name: str) -> str:
    return f"{prim.GetPath()}.{name}"


def composition_issues(
    stage: Usd.Stage, composition: list[CompositionProblem] | None = None
) -> list[Issue]:
    """One error per sublayer, reference or payload USD could not open (and per other
    composition error)."""
    if composition is None:
        composition = composition_problems(stage)
    return [Issue.of(ERROR, p.message, COMPOSITION) for p in composition]


def _camera_issues(
    stage: Usd.Stage, camera: Usd.Prim, default: bool
) -> tuple[list[Issue], tuple[float, float]]:
    """The render's checks of ``camera`` and the camera path driving it, and its frame
    range. Errors for the camera rendered by default, warnings for the others."""
    severity = ERROR if default else WARNING
    note = "" if default else f" (camera {camera.GetPath()} renders only with --camera)"
    messages = []
    path_prim = find_camera_path_prim(stage, str(camera.GetPath()))
    driver = None
    if path_prim is not None:
        messages += camera_path_problems(path_prim)
        if not messages:
            driver = read_camera_path(path_prim)
    frames = frame_range(stage, driver)
    driven = path_prim is not None
    at_times = []
    for t in camera_check_times(camera, frames, driven):
        at_times += camera_problems(camera, t, driven)
    messages += first_per_location(at_times)
    return [Issue.of(severity, m + note, CAMERA) for m in messages], frames


def _idle_camera_path_issues(stage: Usd.Stage) -> list[Issue]:
    """Camera paths the render ignores: no camera target, or another path drives it."""
    issues = []
    for prim in schema.find_camera_paths(stage):
        rel = prim.GetRelationship(schema.CAMERA)
        targets = list(rel.GetForwardedTargets()) if rel else []
        cameras = [t for t in targets if (c := stage.GetPrimAtPath(t)) and c.IsA(UsdGeom.Camera)]
        if not cameras:
            shown = ", ".join(str(t) for t in targets) or "nothing"
            issues.append(
                Issue(
                    WARNING,
                    _attr_where(prim, schema.CAMERA),
                    f"targets {shown}, not a UsdGeomCamera: the renderer ignores this path",
                    CAMERA_PATH,
                )
            )
            continue
        drivers = {str(c): find_camera_path_prim(stage, str(c)) for c in cameras}
        if all(d is not None and d.GetPath() != prim.GetPath() for d in drivers.values()):
            first = next(iter(drivers.items()))
            issues.append(
                Issue(
                    WARNING,
                    str(prim.GetPath()),
                    f"ignored: {first[1].GetPath()} already drives {first[0]}",
                    CAMERA_PATH,
                )
            )
    return issues


def _reflector_warnings(prim: Usd.Prim, kind: str, time: float) -> list[Issue]:
    """What the render accepts but is probably not meant: F clamped, faces skipped,
    nothing to reflect in."""
    issues = []
    f = schema.reflector_reflectivity(prim)
    if math.isfinite(f) and not 0.0 <= f <= 1.0:
        issues.append(
            Issue(
                WARNING,
                _attr_where(prim, schema.REFLECTIVITY),
                f"reflectivity F = {f} is outside 0..1: the renderer clamps it",
                GEOMETRY,
            )
        )
    if kind != "Mesh":
        return issues
    code = Usd.TimeCode(time)
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(code) or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(code) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(code) or [], dtype=np.int64)
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get(code) or [], dtype=np.int64)
    faces = _attr_where(prim, "faceVertexCounts")
    if counts.size == 0:
        return issues + [Issue(WARNING, faces, "mesh reflector has no faces", GEOMETRY)]
    small = (counts >= 0) & (counts < 3)
    if small.any():
        issues.append(
            Issue(
                WARNING,
                faces,
                f"{int(small.sum())} face(s) with fewer than 3 vertices (first: face "
                f"{int(np.argmax(small))}, {int(counts[np.argmax(small)])} vertices) are "
                "skipped by the renderer",
                GEOMETRY,
            )
        )
    if mesh_area(points, counts, indices, holes) <= 0.0:  # hole faces are not drawn
        issues.append(
            Issue(WARNING, _attr_where(prim, "points"), "mesh reflector has zero area", GEOMETRY)
        )
    return issues


def stage_reflectors(stage: Usd.Stage) -> list[Usd.Prim]:
    """Every reflector of the stage in traversal order, instance proxies included: a
    reflector inside an instanced reference appears once per instance, at its
    per-instance path (``/World/Tree_3/Leaves``), the path the render names its element
    by. ``Usd.Prim.GetPrimInPrototype`` gives the prototype prim of such a proxy."""
    return [
        p
        for p in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies())
        if schema.is_reflector(p)
    ]


def _gprim_issues(stage: Usd.Stage, frames: tuple[float, float]) -> list[Issue]:
    """The render's reflector and mesh rules on every gprim it reads (the purposes the
    render settings include, as the render: ``included_purposes``), plus warnings."""
    purposes, warnings = included_purposes(stage)
    issues = [Issue.of(WARNING, w, RENDER_SETTINGS) for w in warnings]
    for kind, prim in rendered_gprims(stage, frames[0], purposes):
        messages = reflector_problems(prim)
        if kind == "Mesh":
            messages += mesh_problems_in_range(prim, frames)
        issues += [Issue.of(ERROR, m, GEOMETRY) for m in messages]
        if schema.is_reflector(prim) and not messages:
            issues += _reflector_warnings(prim, kind, frames[0])
    for prim in stage_reflectors(stage):
        if prim.GetTypeName() not in RENDERED_GPRIM_TYPES:
            issues.append(
                Issue(
                    WARNING,
                    str(prim.GetPath()),
                    f"{schema.REFLECTOR_API} on a {prim.GetTypeName() or 'typeless prim'}: "
                    f"the renderer draws only {', '.join(RENDERED_GPRIM_TYPES)} and "
                    "ignores it",
                    GEOMETRY,
                )
            )
    return issues


def _light_issues(stage: Usd.Stage, scene) -> list[Issue]:
    """Warnings for the lights as the render reads them: what the light readers read
    with a fallback (``StageScene.light_warnings``), and a DistantLight whose
    ``inputs:intensity`` is UsdLux's fallback (50000: in phrt's units a sun that clips
    the frame, the render's clipping warning; ``lights.fallback_intensity``)."""
    issues = [Issue.of(WARNING, w, LIGHTS) for w in scene.light_warnings]
    for light in scene.scene.lights.distant:
        value = fallback_intensity(stage, light.path)
        if value is not None:
            issues.append(
                Issue(
                    WARNING,
                    f"{light.path}.inputs:intensity",
                    f"unauthored: UsdLux's fallback {value:g}: a sun that clips the frame "
                    "in phrt's units; author inputs:intensity or render with --exposure",
                    LIGHTS,
                )
            )
    return issues


def render_issues(stage: Usd.Stage) -> list[Issue]:
    """The render's own rules but composition (module doc): an error for each refusal,
    with the render's message; warnings for what it accepts with doubts."""
    issues = [Issue.of(ERROR, m, STAGE) for m in stage_problems(stage)]
    try:
        camera = choose_camera(stage)
    except PhrtError as exc:
        camera = None
        issues.append(Issue.of(ERROR, str(exc), CAMERA))
    frames = frame_range(stage, None)
    if camera is not None:
        found, frames = _camera_issues(stage, camera, default=True)
        issues += found
    elif not any(i.rule == CAMERA for i in issues):
        issues.append(
            Issue(
                WARNING,
                stage.GetRootLayer().identifier,
                "stage has no UsdGeomCamera: the render uses a default camera framing "
                "the stage's bounds",
                CAMERA,
            )
        )
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera) and (camera is None or prim != camera):
            issues += _camera_issues(stage, prim, default=False)[0]
    issues += _idle_camera_path_issues(stage)
    issues += _gprim_issues(stage, frames)
    lines = {i.line() for i in issues}
    try:
        scene = read_stage(stage)
    except PhrtError as exc:
        last = Issue.of(ERROR, str(exc), READ)
        if last.line() not in lines:
            issues.append(last)
    else:
        issues += _light_issues(stage, scene)
        # A texture the render cannot read renders with the input's fallback (a
        # warning there); validation, like ``--strict``, calls it an error.
        issues += [Issue.of(ERROR, m, READ) for m in scene.texture_problems]
    return issues


def render_settings_issues(prim: Usd.Prim) -> list[Issue]:
    """The heuristic's parameters on one RenderSettings prim, as ``RenderParams`` of this
    very prim reads them (none unless it has PhrtRenderSettingsAPI)."""
    if not (prim.IsA(UsdRender.Settings) and schema.has_api(prim, schema.RENDER_SETTINGS_API)):
        return []
    params = schema.read_render_params(prim.GetStage(), str(prim.GetPath()))
    rays = prim.GetAttribute(schema.BUDGET_RAYS)
    raw_rays = rays.Get() if rays else None
    checks = [
        (schema.HEURISTIC, params.heuristic in schema.HEURISTICS,
         f"'{params.heuristic}' is not one of {', '.join(schema.HEURISTICS)}"),
        (schema.MODE, params.mode in schema.MODES,
         f"'{params.mode}' is not one of {', '.join(schema.MODES)}"),
        (schema.BUDGET_MS, math.isfinite(params.budget_ms) and params.budget_ms >= 0,
         f"budget {params.budget_ms} ms (need finite >= 0)"),
        (schema.BUDGET_RAYS, raw_rays is None or raw_rays >= -1,
         f"budget {raw_rays} rays (need >= 0, or -1 for unused)"),
        (schema.BOUNCE_LIMIT, 0 <= params.bounce_limit <= schema.MAX_BOUNCE_LIMIT,
         f"bounce limit {params.bounce_limit} (need 0..{schema.MAX_BOUNCE_LIMIT})"),
        (schema.SELECTION_WEIGHT,
         math.isfinite(params.selection_weight) and params.selection_weight >= 0,
         f"selection weight I = {params.selection_weight} (need finite >= 0)"),
    ]  # fmt: skip
    issues = [
        Issue(ERROR, _attr_where(prim, n), msg, RENDER_SETTINGS) for n, ok, msg in checks if not ok
    ]
    w, h = params.resolution
    if w <= 0 or h <= 0:
        issues.append(
            Issue(ERROR, _attr_where(prim, "resolution"), f"{w}x{h} (need > 0)", RENDER_SETTINGS)
        )
    return issues
