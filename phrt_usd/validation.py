"""Stage validation: USD's own validators (``pxr.UsdValidation``) plus the Phrt rules.

Every problem is one ``Issue`` with a location (``/prim/path`` or ``/prim/path.attribute``)
and a message. Severity: ``error`` makes the stage unusable or wrong for rendering (exit 1
in ``phrt validate``); ``warning`` is suspicious but renders (e.g. a zero-area mirror).
USD validator results keep USD's own severity (Error -> error, Warn/Info -> warning).

Phrt rules:
- reflectors: K finite and >= 0, F in [0, 1], the prim is a UsdGeomGprim; a Mesh reflector
  has points, all finite, a valid topology (counts >= 3, sum(counts) == len(indices),
  indices in range) and non-zero area (warning);
- camera paths: positions/targets/keyTimes the same length >= 2, key times strictly
  increasing and finite, startFrame <= endFrame, the camera relationship targets one
  UsdGeomCamera, interpolation allowed;
- render settings with PhrtRenderSettingsAPI: budgets >= 0 (budgetRays >= -1), bounce limit
  0..MAX_BOUNCE_LIMIT, selection weight finite >= 0, heuristic and mode allowed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, UsdRender, UsdValidation

from phrt_usd import schema
from phrt_usd.errors import PhrtError

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Issue:
    """One problem: ``where`` is ``/prim/path`` or ``/prim/path.attribute``."""

    severity: str
    where: str
    message: str

    def line(self) -> str:
        return f"{self.severity.upper()} {self.where}: {self.message}"

    def as_dict(self) -> dict:
        return {"where": self.where, "message": self.message}


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


def open_stage(path: str | Path) -> Usd.Stage:
    """Open a USD stage read-only-ish; PhrtError (one line) for a missing file, a
    directory, or a file USD cannot read."""
    p = Path(path)
    if not p.exists():
        raise PhrtError(f"{path}: no such file")
    if p.is_dir():
        raise PhrtError(f"{path}: is a directory, not a USD stage")
    if not Sdf.FileFormat.FindByExtension(p.suffix.lstrip(".")):
        raise PhrtError(f"{path}: not a USD file (unknown extension '{p.suffix}')")
    try:
        stage = Usd.Stage.Open(str(p))
    except Tf.ErrorException:
        raise PhrtError(f"{path}: cannot open as USD (unreadable or invalid syntax)") from None
    if stage is None:
        raise PhrtError(f"{path}: cannot open as USD")
    return stage


# --- USD's own validators -----------------------------------------------------------------
def _usd_issues(stage: Usd.Stage) -> list[Issue]:
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    issues = []
    for err in context.Validate(stage):
        if err.HasNoError():
            continue
        where = "/"
        for site in err.GetSites():
            if site.IsProperty():
                where = str(site.GetProperty().GetPath())
                break
            if site.IsPrim():
                where = str(site.GetPrim().GetPath())
                break
        severity = ERROR if err.GetType() == UsdValidation.ValidationErrorType.Error else WARNING
        message = " ".join(err.GetMessage().split())
        issues.append(Issue(severity, where, f"{message} [{err.GetIdentifier()}]"))
    return issues


# --- Phrt rules ---------------------------------------------------------------------------
def _attr_where(prim: Usd.Prim, name: str) -> str:
    return f"{prim.GetPath()}.{name}"


def _mesh_issues(prim: Usd.Prim) -> list[Issue]:
    """Topology and geometry of a Mesh reflector (default-time values)."""
    mesh = UsdGeom.Mesh(prim)
    points = mesh.GetPointsAttr().Get()
    counts = mesh.GetFaceVertexCountsAttr().Get()
    indices = mesh.GetFaceVertexIndicesAttr().Get()
    if points is None or len(points) == 0:
        return [Issue(ERROR, _attr_where(prim, "points"), "mesh reflector has no points")]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    issues = []
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, "points"),
                f"{int(bad.sum())} point(s) are NaN or infinite (first at index "
                f"{int(np.argmax(bad))})",
            )
        )
    counts_a = np.asarray(counts if counts is not None else [], dtype=np.int64)
    idx = np.asarray(indices if indices is not None else [], dtype=np.int64)
    if counts_a.size == 0:
        issues.append(Issue(ERROR, _attr_where(prim, "faceVertexCounts"), "mesh has no faces"))
        return issues
    topology_ok = True
    if (counts_a < 3).any():
        topology_ok = False
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, "faceVertexCounts"),
                f"face {int(np.argmax(counts_a < 3))} has {int(counts_a.min())} vertices "
                "(need >= 3)",
            )
        )
    if int(counts_a.sum()) != idx.size:
        topology_ok = False
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, "faceVertexIndices"),
                f"has {idx.size} entries but faceVertexCounts sum to {int(counts_a.sum())}",
            )
        )
    out_of_range = (idx < 0) | (idx >= len(pts))
    if out_of_range.any():
        topology_ok = False
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, "faceVertexIndices"),
                f"index {int(idx[np.argmax(out_of_range)])} out of range (mesh has "
                f"{len(pts)} points)",
            )
        )
    if topology_ok and not bad.any() and _mesh_area(pts, counts_a, idx) <= 0.0:
        issues.append(Issue(WARNING, _attr_where(prim, "points"), "mesh reflector has zero area"))
    return issues


def _mesh_area(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> float:
    """Total area of a polygon mesh, fan-triangulated (stage units squared).

    points : (p, 3) float64; counts : (f,) int64 >= 3; indices : (sum(counts),) int64.
    """
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tris = counts - 2
    face = np.repeat(np.arange(counts.size), n_tris)
    # k-th triangle of a face: (v0, v(k+1), v(k+2))
    k = np.arange(n_tris.sum()) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris)
    a = points[indices[starts[face]]]
    b = points[indices[starts[face] + k + 1]]
    c = points[indices[starts[face] + k + 2]]
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def _reflector_issues(prim: Usd.Prim) -> list[Issue]:
    issues = []
    k = schema.reflector_priority(prim)
    if not math.isfinite(k) or k < 0:
        issues.append(
            Issue(ERROR, _attr_where(prim, schema.PRIORITY), f"priority K = {k} (need finite >= 0)")
        )
    f = schema.reflector_reflectivity(prim)
    if not (0.0 <= f <= 1.0):  # also false for NaN
        issues.append(
            Issue(
                ERROR, _attr_where(prim, schema.REFLECTIVITY), f"reflectivity F = {f} (need 0..1)"
            )
        )
    if not prim.IsA(UsdGeom.Gprim):
        issues.append(
            Issue(
                ERROR,
                str(prim.GetPath()),
                f"{schema.REFLECTOR_API} on a {prim.GetTypeName() or 'typeless prim'}; "
                "reflectors must be gprims (Mesh, Sphere, Cube, ...)",
            )
        )
    elif prim.IsA(UsdGeom.Mesh):
        issues.extend(_mesh_issues(prim))
    return issues


def _camera_path_issues(stage: Usd.Stage, prim: Usd.Prim) -> list[Issue]:
    data = schema.read_camera_path(prim)
    issues = []
    n_pos, n_tgt, n_key = len(data.positions), len(data.targets), len(data.key_times)
    if not (n_pos == n_tgt == n_key):
        issues.append(
            Issue(
                ERROR,
                str(prim.GetPath()),
                f"{schema.POSITIONS}, {schema.TARGETS}, {schema.KEY_TIMES} have different "
                f"lengths ({n_pos}, {n_tgt}, {n_key})",
            )
        )
    if min(n_pos, n_tgt, n_key) < 2:
        issues.append(
            Issue(ERROR, str(prim.GetPath()), "camera path needs at least 2 control points")
        )
    for name, arr in ((schema.POSITIONS, data.positions), (schema.TARGETS, data.targets)):
        if arr.size and not np.isfinite(arr).all():
            issues.append(Issue(ERROR, _attr_where(prim, name), "contains NaN or infinite values"))
    keys = data.key_times
    if keys.size and not np.isfinite(keys).all():
        issues.append(Issue(ERROR, _attr_where(prim, schema.KEY_TIMES), "NaN or infinite"))
    elif keys.size >= 2 and not (np.diff(keys) > 0).all():
        at = int(np.argmax(np.diff(keys) <= 0)) + 1
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, schema.KEY_TIMES),
                f"not strictly increasing (index {at}: {keys[at - 1]} then {keys[at]})",
            )
        )
    if not (math.isfinite(data.start) and math.isfinite(data.end)) or data.start > data.end:
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, schema.START_FRAME),
                f"startFrame {data.start} > endFrame {data.end} (or not finite)",
            )
        )
    if data.camera is None:
        issues.append(Issue(ERROR, _attr_where(prim, schema.CAMERA), "targets no camera"))
    else:
        cam = stage.GetPrimAtPath(data.camera)
        if not cam or not cam.IsA(UsdGeom.Camera):
            issues.append(
                Issue(
                    ERROR,
                    _attr_where(prim, schema.CAMERA),
                    f"target {data.camera} is not a UsdGeomCamera",
                )
            )
    if data.interpolation not in schema.INTERPOLATIONS:
        issues.append(
            Issue(
                ERROR,
                _attr_where(prim, schema.INTERPOLATION),
                f"'{data.interpolation}' is not one of {', '.join(schema.INTERPOLATIONS)}",
            )
        )
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


def phrt_issues(stage: Usd.Stage) -> list[Issue]:
    """The Phrt rules over every prim of the stage."""
    issues = []
    for prim in stage.Traverse():
        if schema.is_reflector(prim):
            issues.extend(_reflector_issues(prim))
        if prim.GetTypeName() == schema.CAMERA_PATH_TYPE:
            issues.extend(_camera_path_issues(stage, prim))
        if prim.IsA(UsdRender.Settings) and schema.has_api(prim, schema.RENDER_SETTINGS_API):
            issues.extend(_render_settings_issues(prim))
    return issues


def validate_stage(stage: Usd.Stage, label: str | None = None) -> ValidationReport:
    """USD's validators and the Phrt rules on an open stage."""
    name = label or stage.GetRootLayer().identifier
    return ValidationReport(name, _usd_issues(stage) + phrt_issues(stage))


def validate_file(path: str | Path) -> ValidationReport:
    """Open and validate; PhrtError when the file cannot be opened as USD."""
    return validate_stage(open_stage(path), str(path))
