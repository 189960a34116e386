"""Stage validation: USD's own validators (``pxr.UsdValidation``) plus the Phrt rules.

Every problem is one ``Issue`` with a location (``/prim/path``, ``/prim/path.attribute``,
or a layer for layer-level problems) and a message. Severity: ``error`` makes the stage
unusable or wrong for rendering (exit 1 in ``phrt validate``); ``warning`` is suspicious
but renders (e.g. a zero-area mirror). USD validator results keep USD's own severity
(Error -> error, Warn/Info -> warning).

Validate agrees with render: the render's refusal rules live in ``phrt_usd.usd.stage``,
``phrt_usd.usd.meshes``, ``phrt_usd.usd.composition`` and ``phrt_usd.usd.camera_path``
as functions returning the message the render raises; validation calls the same
functions and reports each message as an error, with the same text (``Issue.line()`` is
``"ERROR " + message``). Checked where the render reads:

- composition: every sublayer, reference and payload USD could not open, one line each
  (prim and asset, or layer and sublayer), and other composition errors — errors here,
  warnings in ``StageScene.warnings`` (the render goes on without them);
- stage: metersPerUnit > 0; a camera to render (``choose_camera``);
- the render's camera (``choose_camera``, no ``--camera``): the camera path that drives it
  (``camera_path_problems``) and ``camera_problems`` at the start and end of the frame
  range and at every time sample inside it; other cameras and their paths get the same
  checks as warnings (they render only with ``--camera``); a camera path that drives no
  camera is a warning (the render ignores it);
- every gprim the render reads (``rendered_gprims``: not invisible / guide / proxy at
  the start of the frame range, PointInstancer prototypes included): reflector K and F
  (``reflector_problems``), mesh points and topology at the start and at every time
  sample of an animated shape (``mesh_problems_in_range``);
- finally ``read_stage`` itself, so that anything else it refuses (textures, primvar
  sizes, instancers, lights) is reported too (one message: it stops at the first).

Warnings only (the render accepts these): reflector F outside [0, 1] (clamped), a
reflector on a prim the render does not draw as geometry, a Mesh reflector with no faces,
faces of fewer than 3 vertices (skipped), zero area.

Render settings with PhrtRenderSettingsAPI: budgets >= 0 (budgetRays >= -1), bounce limit
0..MAX_BOUNCE_LIMIT, selection weight finite >= 0, heuristic and mode allowed.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdRender, UsdValidation

from phrt_usd.errors import PhrtError
from phrt_usd.usd import schema
from phrt_usd.usd.camera_path import camera_path_problems, find_camera_path_prim, read_camera_path
from phrt_usd.usd.composition import CompositionProblem, composition_problems
from phrt_usd.usd.meshes import RENDERED_GPRIM_TYPES, mesh_area, mesh_problems_in_range
from phrt_usd.usd.stage import (
    camera_check_times,
    camera_problems,
    choose_camera,
    frame_range,
    open_usd,
    read_stage,
    reflector_problems,
    rendered_gprims,
    stage_problems,
)

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Issue:
    """One problem: ``where`` is ``/prim/path``, ``/prim/path.attribute`` or a layer."""

    severity: str
    where: str
    message: str

    def line(self) -> str:
        return f"{self.severity.upper()} {self.where}: {self.message}"

    def as_dict(self) -> dict:
        return {"where": self.where, "message": self.message}

    @classmethod
    def of(cls, severity: str, message: str) -> Issue:
        """An issue from a render message ``"<where>: <text>"``: its ``line()`` is the
        severity and the message, unchanged."""
        where, sep, text = message.partition(": ")
        return cls(severity, where, text) if sep else cls(severity, "/", message)


@dataclass(frozen=True)
class ValidationReport:
    stage: str
    issues: list[Issue]

    @property
    def errors(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == ERROR]

    @property
    def warnings(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == WARNING]

    @property
    def ok(self) -> bool:
        return not self.errors

    def as_dict(self) -> dict:
        return {
            "stage": self.stage,
            "ok": self.ok,
            "errors": [i.as_dict() for i in self.errors],
            "warnings": [i.as_dict() for i in self.warnings],
        }


# --- USD's own validators -----------------------------------------------------------------
#: Replaced by ``composition_problems`` (one line per missing arc, naming the prim).
_REPLACED_VALIDATORS = ("usdValidation:CompositionErrorTest",)
_UNRESOLVABLE = re.compile(r"unresolvable external dependency '(?P<asset>[^']*)'")


def _usd_issues(stage: Usd.Stage, composition: list[CompositionProblem]) -> list[Issue]:
    registry = UsdValidation.ValidationRegistry()
    validators = [
        v
        for v in registry.GetOrLoadAllValidators()
        if v.GetMetadata().name not in _REPLACED_VALIDATORS
    ]
    context = UsdValidation.ValidationContext(validators)
    missing = {p.asset for p in composition if p.asset}
    issues = []
    for err in context.Validate(stage):
        if err.HasNoError():
            continue
        message = " ".join(err.GetMessage().split())
        m = _UNRESOLVABLE.search(message)
        if m and m["asset"] in missing:
            continue  # the same missing layer, already reported with its prim
        where = "/"
        for site in err.GetSites():
            if site.IsProperty():
                where = str(site.GetProperty().GetPath())
                break
            if site.IsPrim():
                where = str(site.GetPrim().GetPath())
                break
        severity = ERROR if err.GetType() == UsdValidation.ValidationErrorType.Error else WARNING
        issues.append(Issue(severity, where, f"{message} [{err.GetIdentifier()}]"))
    return issues


# --- Phrt rules ---------------------------------------------------------------------------
def _attr_where(prim: Usd.Prim, name: str) -> str:
    return f"{prim.GetPath()}.{name}"


def _first_per_where(messages: list[str]) -> list[str]:
    """Messages with a new location only (a problem that lasts is reported once)."""
    seen, out = set(), []
    for m in messages:
        where = m.partition(": ")[0]
        if where not in seen:
            seen.add(where)
            out.append(m)
    return out


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
    messages += _first_per_where(at_times)
    return [Issue.of(severity, m + note) for m in messages], frames


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
            )
        )
    if kind != "Mesh":
        return issues
    code = Usd.TimeCode(time)
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(code) or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(code) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(code) or [], dtype=np.int64)
    if counts.size == 0:
        return issues + [
            Issue(WARNING, _attr_where(prim, "faceVertexCounts"), "mesh reflector has no faces")
        ]
    small = (counts >= 0) & (counts < 3)
    if small.any():
        issues.append(
            Issue(
                WARNING,
                _attr_where(prim, "faceVertexCounts"),
                f"{int(small.sum())} face(s) with fewer than 3 vertices (first: face "
                f"{int(np.argmax(small))}, {int(counts[np.argmax(small)])} vertices) are "
                "skipped by the renderer",
            )
        )
    if mesh_area(points, counts, indices) <= 0.0:
        issues.append(Issue(WARNING, _attr_where(prim, "points"), "mesh reflector has zero area"))
    return issues


def _gprim_issues(stage: Usd.Stage, frames: tuple[float, float]) -> list[Issue]:
    """The render's reflector and mesh rules on every gprim it reads, plus warnings."""
    issues = []
    for kind, prim in rendered_gprims(stage, frames[0]):
        messages = reflector_problems(prim)
        if kind == "Mesh":
            messages += mesh_problems_in_range(prim, frames)
        issues += [Issue.of(ERROR, m) for m in messages]
        if schema.is_reflector(prim) and not messages:
            issues += _reflector_warnings(prim, kind, frames[0])
    for prim in schema.find_reflectors(stage):
        if prim.GetTypeName() not in RENDERED_GPRIM_TYPES:
            issues.append(
                Issue(
                    WARNING,
                    str(prim.GetPath()),
                    f"{schema.REFLECTOR_API} on a {prim.GetTypeName() or 'typeless prim'}: "
                    f"the renderer draws only {', '.join(RENDERED_GPRIM_TYPES)} and "
                    "ignores it",
                )
            )
    return issues


def render_issues(
    stage: Usd.Stage, composition: list[CompositionProblem] | None = None
) -> list[Issue]:
    """The render's own rules (module doc): an error for each refusal, with the render's
    message; warnings for what it accepts with doubts."""
    if composition is None:
        composition = composition_problems(stage)
    issues = [Issue.of(ERROR, p.message) for p in composition]
    issues += [Issue.of(ERROR, m) for m in stage_problems(stage)]
    try:
        camera = choose_camera(stage)
    except PhrtError as exc:
        camera = None
        issues.append(Issue.of(ERROR, str(exc)))
    frames = frame_range(stage, None)
    if camera is not None:
        found, frames = _camera_issues(stage, camera, default=True)
        issues += found
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera) and (camera is None or prim != camera):
            issues += _camera_issues(stage, prim, default=False)[0]
    issues += _idle_camera_path_issues(stage)
    issues += _gprim_issues(stage, frames)
    lines = {i.line() for i in issues}
    try:
        read_stage(stage)
    except PhrtError as exc:
        last = Issue.of(ERROR, str(exc))
        if last.line() not in lines:
            issues.append(last)
    return issues


def _render_settings_issues(prim: Usd.Prim) -> list[Issue]:
    """Checks authored values through RenderParams of this very prim."""
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
    issues = [Issue(ERROR, _attr_where(prim, n), msg) for n, ok, msg in checks if not ok]
    w, h = params.resolution
    if w <= 0 or h <= 0:
        issues.append(Issue(ERROR, _attr_where(prim, "resolution"), f"{w}x{h} (need > 0)"))
    return issues


def phrt_issues(
    stage: Usd.Stage, composition: list[CompositionProblem] | None = None
) -> list[Issue]:
    """The Phrt rules: the render's own (``render_issues``) and the render settings'."""
    issues = render_issues(stage, composition)
    for prim in stage.Traverse():
        if prim.IsA(UsdRender.Settings) and schema.has_api(prim, schema.RENDER_SETTINGS_API):
            issues.extend(_render_settings_issues(prim))
    return issues


def validate_stage(stage: Usd.Stage, label: str | None = None) -> ValidationReport:
    """USD's validators and the Phrt rules on an open stage."""
    name = label or stage.GetRootLayer().identifier
    composition = composition_problems(stage)
    return ValidationReport(name, _usd_issues(stage, composition) + phrt_issues(stage, composition))


def validate_file(path: str | Path) -> ValidationReport:
    """Open and validate; PhrtError when the file cannot be opened as USD."""
    return validate_stage(open_usd(path), str(path))
