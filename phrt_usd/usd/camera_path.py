"""Camera paths: the ``PhrtCameraPath`` prim and look-at camera transforms.

A ``PhrtCameraPath`` prim holds control points in **stage units, world space**:

- ``point3d[] phrt:positions`` and ``point3d[] phrt:targets`` — eye and look-at point,
- ``double[] phrt:keyTimes`` — time code of each control point, strictly increasing
  (when unauthored, spread evenly over [startFrame, endFrame], or 0, 1, 2, ...),
- ``token phrt:interpolation`` — ``"linear"`` or ``"catmullRom"`` (default),
- ``double phrt:startFrame`` / ``double phrt:endFrame`` — the frame range to render
  (default: first and last key time),
- ``rel phrt:camera`` — the ``UsdGeomCamera`` it drives.

Evaluation at a time code clamps to the first/last control point outside the key range.
Catmull-Rom here is the cubic Hermite spline whose tangent at each key is the finite
difference of its neighbours over their time span (``(p[i+1] - p[i-1]) / (t[i+1] -
t[i-1])``; end points duplicated, i.e. half the one-sided difference at the ends). It
passes through every control point, is C1 in time for uneven key spacing, and equals the
uniform Catmull-Rom spline (``tools/make_stages.py: evaluate_camera_path``) for evenly
spaced keys.

The camera looks from position to target with the stage up axis as up. Two degenerate
cases are handled without NaN: target == position (the camera keeps a fixed horizontal
view direction, see ``_FALLBACK_FORWARD``) and a view direction parallel to up (the up
hint falls back to the world axis least aligned with the view direction).

Matrices returned here use the column-vector convention of ``phrt_usd.model.scene.CameraFrame``
(``world_from_camera[:3, 3]`` is the eye), not USD's row-vector ``GfMatrix4d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd

from phrt_usd.errors import PhrtError
from phrt_usd.usd import schema
from phrt_usd.usd.values import stage_up_axis

#: Below this length (stage units) a view direction counts as zero: target == position.
_DEGENERATE_LENGTH = 1e-12

#: Below this sine of the angle between view direction and up, they count as parallel.
_PARALLEL_SINE = 1e-9

#: View direction used when target == position, per up axis: horizontal, "into the
#: screen" of the default USD camera for Y-up (-Z) and its Z-up counterpart (+Y).
_FALLBACK_FORWARD = {"Y": np.array([0.0, 0.0, -1.0]), "Z": np.array([0.0, 1.0, 0.0])}

#: World up vector per stage up axis.
UP_VECTORS = {"Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world matrix of a camera at ``position`` looking at ``target``.

    position, target : (3,) float64, world space (any unit; the translation is
    ``position`` unchanged). up : (3,) float64 world up hint (unit).

    Returns (4, 4) float64, column-vector convention: camera space (looks down -Z,
    +Y up, +X right) → world. The rotation is orthonormal and free of NaN for every
    finite input.
    """
    up = np.asarray(up, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    length = float(np.linalg.norm(forward))
    if not np.isfinite(length) or length < _DEGENERATE_LENGTH:
        # target == position: no view direction; keep a fixed horizontal one.
        axis = "Z" if abs(up[2]) > abs(up[1]) else "Y"
        forward = _FALLBACK_FORWARD[axis]
    else:
        forward = forward / length
    right = np.cross(forward, up)
    if np.linalg.norm(right) < _PARALLEL_SINE:
        # Looking straight along up: any up perpendicular to forward will do; take the
        # world axis least aligned with the view direction.
        alt_up = np.eye(3)[int(np.argmin(np.abs(forward)))]
        right = np.cross(forward, alt_up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    m = np.eye(4)
    m[:3, 0] = right
    m[:3, 1] = cam_up
    m[:3, 2] = -forward
    m[:3, 3] = position
    return m


def _hermite_tangents(points: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(n, 3) Catmull-Rom tangents d(point)/d(time) at each key (finite differences)."""
    n = len(points)
    tangents = np.zeros_like(points)
    if n < 2:
        return tangents
    tangents[1:-1] = (points[2:] - points[:-2]) / (times[2:] - times[:-2])[:, None]
    # End points count twice (p[-1] = p[0]), the usual Catmull-Rom end condition: half
    # the one-sided difference.
    tangents[0] = 0.5 * (points[1] - points[0]) / (times[1] - times[0])
    tangents[-1] = 0.5 * (points[-1] - points[-2]) / (times[-1] - times[-2])
    return tangents


def interpolate(
    points: np.ndarray, times: np.ndarray, t: np.ndarray | float, method: str
) -> np.ndarray:
    """Evaluate a key-framed curve.

    points : (n, 3) float64 control points; times : (n,) strictly increasing key times;
    t : scalar or (m,) evaluation times (clamped to [times[0], times[-1]]);
    method : "linear" or "catmullRom".

    Returns (3,) for a scalar ``t``, else (m, 3) float64.
    """
    scalar = np.ndim(t) == 0
    tt = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), times[0], times[-1])
    if len(points) == 1:
        out = np.repeat(points[:1], len(tt), axis=0)
        return out[0] if scalar else out
    seg = np.clip(np.searchsorted(times, tt, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[seg], times[seg + 1]
    dt = t1 - t0
    s = ((tt - t0) / dt)[:, None]
    p0, p1 = points[seg], points[seg + 1]
    if method == "linear":
        out = p0 + s * (p1 - p0)
    else:
        m = _hermite_tangents(points, times)
        m0, m1 = m[seg] * dt[:, None], m[seg + 1] * dt[:, None]
        s2, s3 = s * s, s * s * s
        out = (
            (2 * s3 - 3 * s2 + 1) * p0
            + (s3 - 2 * s2 + s) * m0
            + (-2 * s3 + 3 * s2) * p1
            + (s3 - s2) * m1
        )
    return out[0] if scalar else out


@dataclass(frozen=True)
class CameraPath:
    """A camera path read from a ``PhrtCameraPath`` prim.

    positions, targets : (n, 3) float64, stage units, world space
    key_times          : (n,) float64 strictly increasing time codes
    interpolation      : "linear" | "catmullRom"
    start_frame, end_frame : frame range to render (time codes)
    up_axis            : "Y" | "Z", the stage up axis
    """

    path: str
    camera: str
    positions: np.ndarray
    targets: np.ndarray
    key_times: np.ndarray
    interpolation: str
    start_frame: float
    end_frame: float
    up_axis: str = "Y"

    def position_target(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Eye and target, (3,) float64 each in stage units, at ``time`` (clamped)."""
        pos = interpolate(self.positions, self.key_times, time, self.interpolation)
        tgt = interpolate(self.targets, self.key_times, time, self.interpolation)
        return pos, tgt

    def world_from_camera(self, time: float, meters_per_unit: float = 1.0) -> np.ndarray:
        """(4, 4) float64 camera → world **metres** (column-vector convention)."""
        pos, tgt = self.position_target(time)
        return look_at(pos * meters_per_unit, tgt * meters_per_unit, UP_VECTORS[self.up_axis])


def camera_path_problems(prim: Usd.Prim) -> list[str]:
    """Every reason ``read_camera_path`` refuses the prim, one line each (``[]`` when it
    reads). The first is the message ``read_camera_path`` raises;
    ``phrt_usd.usd.validation`` reports all of them."""
    return _read(prim)[1]


def read_camera_path(prim: Usd.Prim) -> CameraPath:
    """Read (``phrt_usd.usd.schema``) and validate a ``PhrtCameraPath`` prim.

    Raises ``PhrtError`` (one line naming the prim and attribute) for missing or
    non-finite control points, mismatched lengths, non-increasing key times, an unknown
    interpolation or an end frame before the start frame (``camera_path_problems``).
    """
    path, problems = _read(prim)
    if path is None:
        raise PhrtError(problems[0])
    return path


def _read(prim: Usd.Prim) -> tuple[CameraPath | None, list[str]]:
    """The camera path, or None and the reasons it is refused (in checking order)."""
    data = schema.read_camera_path(prim)
    where = data.path
    problems = []
    for name, pts in ((schema.POSITIONS, data.positions), (schema.TARGETS, data.targets)):
        if len(pts) == 0:
            problems.append(f"{where}.{name}: camera path has no control points")
        elif not np.all(np.isfinite(pts)):
            problems.append(f"{where}.{name}: non-finite control point")
    n = len(data.positions)
    if len(data.targets) != n:
        problems.append(
            f"{where}: {schema.POSITIONS} has {n} points but {schema.TARGETS} "
            f"has {len(data.targets)}"
        )
    start_attr = prim.GetAttribute(schema.START_FRAME)
    end_attr = prim.GetAttribute(schema.END_FRAME)
    has_start = bool(start_attr) and start_attr.HasAuthoredValue()
    has_end = bool(end_attr) and end_attr.HasAuthoredValue()
    key_times = data.key_times
    if len(key_times) == 0:
        # Unauthored key times: spread the points evenly over the frame range.
        lo = data.start if has_start else 0.0
        hi = data.end if has_end else float(n - 1)
        key_times = np.linspace(lo, hi, n) if n > 1 else np.array([lo])
    keys_ok = len(key_times) == n and n > 0
    if n == 0:
        pass  # no control points (reported above): nothing to time
    elif len(key_times) != n:
        problems.append(
            f"{where}.{schema.KEY_TIMES}: {len(key_times)} times for {n} control points"
        )
    elif not np.all(np.isfinite(key_times)) or np.any(np.diff(key_times) <= 0):
        keys_ok = False
        problems.append(f"{where}.{schema.KEY_TIMES}: times must be finite and strictly increasing")
    if data.interpolation not in schema.INTERPOLATIONS:
        problems.append(
            f"{where}.{schema.INTERPOLATION}: {data.interpolation!r} is not one of "
            f"{', '.join(schema.INTERPOLATIONS)}"
        )
    # Frame range defaults come from the key times: only when those are usable.
    start = data.start if has_start else (float(key_times[0]) if keys_ok else None)
    end = data.end if has_end else (float(key_times[-1]) if keys_ok else None)
    if start is not None and end is not None:
        if not (np.isfinite(start) and np.isfinite(end)) or end < start:
            problems.append(f"{where}: frame range [{start}, {end}] is empty or not finite")
    if problems:
        return None, problems
    return (
        CameraPath(
            path=where,
            camera=data.camera or "",
            positions=data.positions,
            targets=data.targets,
            key_times=np.asarray(key_times, dtype=np.float64),
            interpolation=data.interpolation,
            start_frame=float(start),
            end_frame=float(end),
            up_axis=stage_up_axis(prim.GetStage())[0],
        ),
        [],
    )


def find_camera_path_prim(stage: Usd.Stage, camera: str) -> Usd.Prim | None:
    """The first active ``PhrtCameraPath`` prim whose ``phrt:camera`` targets ``camera``
    (the one that drives it; later ones are ignored), or None."""
    for prim in schema.find_camera_paths(stage):
        rel = prim.GetRelationship(schema.CAMERA)
        if rel and any(str(t) == camera for t in rel.GetForwardedTargets()):
            return prim
    return None


def find_camera_path(stage: Usd.Stage, camera: str) -> CameraPath | None:
    """The camera path driving ``camera`` (``find_camera_path_prim``), read and
    validated (``PhrtError``), or None."""
    prim = find_camera_path_prim(stage, camera)
    return None if prim is None else read_camera_path(prim)
