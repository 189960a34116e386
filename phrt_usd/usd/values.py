"""Attribute values and time handling shared by the stage readers.

Values: an attribute at a time code with a default (``attr_value``), whether attributes
may vary in time (``varies``).
Time: ``TimeContext`` answers transform queries at one time code (USD's row-vector
convention, ``p' = p @ M``, stage units), ``AnimationProbe`` whether a prim's world
transform may vary. Numeric helpers the readers share: unit rows (``safe_normalize``),
the normal transform of a linear map (``normal_matrix``) and the rotation of a
row-vector matrix (``rotation_columns``).
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdGeom

#: Normals shorter than this (degenerate triangles, zero scale) are replaced by a
#: fallback direction instead of being divided by ~0.
MIN_NORMAL_LENGTH = 1e-30


def safe_normalize(v: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """Normalise rows of ``v`` (..., 3); rows of ~zero length become ``fallback`` (or +Z)."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = length > MIN_NORMAL_LENGTH
    out = v / np.where(ok, length, 1.0)
    if fallback is None:
        fallback = np.array([0.0, 0.0, 1.0])
    return np.where(ok, out, fallback)


def normal_matrix(m3: np.ndarray) -> np.ndarray:
    """(3, 3) row-vector normal transform of the row-vector linear map ``m3``.

    ``n_world = n_local @ N`` with ``N`` the inverse-transpose, computed as the cofactor
    matrix times sign(det) so that a singular (zero-scale) transform gives finite normals
    instead of an exception.
    """
    (a, b, c), (d, e, f), (g, h, i) = m3.tolist()
    cof = np.array(
        [
            [e * i - f * h, f * g - d * i, d * h - e * g],  # r1 x r2
            [h * c - i * b, i * a - g * c, g * b - h * a],  # r2 x r0
            [b * f - c * e, c * d - a * f, a * e - b * d],  # r0 x r1
        ]
    )
    det = a * (e * i - f * h) + b * (f * g - d * i) + c * (d * h - e * g)
    return -cof if det < 0 else cof


def attr_value(prim: Usd.Prim, name: str, time: Usd.TimeCode, default):
    """Value of attribute ``name`` at ``time``, or ``default`` when absent/unauthored."""
    a = prim.GetAttribute(name)
    if not a:
        return default
    v = a.Get(time)
    return default if v is None else v


def varies(prim: Usd.Prim, names: tuple[str, ...]) -> bool:
    """True when any of the prim's attributes ``names`` might vary in time."""
    return any((a := prim.GetAttribute(n)) and a.ValueMightBeTimeVarying() for n in names)


class TimeContext:
    """Transform queries at one time code (stage units, USD row-vector matrices)."""

    def __init__(self, time: float):
        self.time = float(time)
        self.code = Usd.TimeCode(time)
        self.cache = UsdGeom.XformCache(self.code)
        self._instances: dict[str, np.ndarray] = {}

    def world(self, prim: Usd.Prim) -> np.ndarray:
        """(4, 4) local → world (stage units), row-vector convention (p' = p @ M)."""
        return np.array(self.cache.GetLocalToWorldTransform(prim))

    def instance_xforms(self, instancer: Usd.Prim) -> np.ndarray:
        """(n, 4, 4) per-instance prototype → instancer transforms (mask ignored)."""
        key = str(instancer.GetPath())
        if key not in self._instances:
            pi = UsdGeom.PointInstancer(instancer)
            xf = pi.ComputeInstanceTransformsAtTime(
                self.code,
                self.code,
                UsdGeom.PointInstancer.IncludeProtoXform,
                UsdGeom.PointInstancer.IgnoreMask,
            )
            arr = np.array([np.array(m) for m in xf]).reshape(-1, 4, 4) if xf else None
            self._instances[key] = np.zeros((0, 4, 4)) if arr is None else arr
        return self._instances[key]


class AnimationProbe:
    """Memoised 'might this prim's world transform vary in time' up the ancestor chain."""

    def __init__(self):
        self._memo: dict[str, bool] = {}

    def xform_varies(self, prim: Usd.Prim) -> bool:
        if not prim or prim.IsPseudoRoot():
            return False
        key = str(prim.GetPath())
        if key not in self._memo:
            xf = UsdGeom.Xformable(prim)
            own = bool(xf) and xf.TransformMightBeTimeVarying()
            reset = bool(xf) and xf.GetResetXformStack()
            self._memo[key] = own or (not reset and self.xform_varies(prim.GetParent()))
        return self._memo[key]


def first_per_location(messages: list[str]) -> list[str]:
    """Messages ``"<where>: <what>"`` whose location is new (a problem that lasts over
    several time samples is reported once, at its first)."""
    seen: set[str] = set()
    out = []
    for message in messages:
        where = message.partition(": ")[0]
        if where not in seen:
            seen.add(where)
            out.append(message)
    return out


def rotation_columns(m_row: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal rotation (column-vector convention) of a row-vector matrix.

    Scale is stripped by Gram-Schmidt, keeping the -Z (view / light) axis exact. A
    degenerate matrix falls back to the identity rotation.
    """
    cols = m_row[:3, :3].T.astype(np.float64)  # column j = image of axis j
    z = cols[:, 2]
    if np.linalg.norm(z) < MIN_NORMAL_LENGTH:
        return np.eye(3)
    z = z / np.linalg.norm(z)
    y = cols[:, 1] - np.dot(cols[:, 1], z) * z
    if np.linalg.norm(y) < 1e-12 * max(np.linalg.norm(cols[:, 1]), 1e-300):
        y = np.eye(3)[int(np.argmin(np.abs(z)))]
        y = y - np.dot(y, z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def stage_up_axis(stage: Usd.Stage) -> tuple[str, str | None]:
    """The stage's up axis, "Y" or "Z", and a one-line warning when the authored
    ``upAxis`` is neither: USD returns whatever token is authored ("X", any string),
    and UsdGeom defines only Y and Z, so such a stage is read with USD's fallback axis."""
    axis = str(UsdGeom.GetStageUpAxis(stage))
    if axis in ("Y", "Z"):
        return axis, None
    fallback = str(UsdGeom.GetFallbackUpAxis())
    where = stage.GetRootLayer().identifier
    return fallback, f"{where}: upAxis {axis!r} is not Y or Z; read as {fallback} (USD's fallback)"
