"""The paper's Table 1 metrics as array functions over candidate reflectors (float64,
finite for any input; every interpretation is spelled out in ``docs/heuristic.md``).

* ``A`` visible projected area: pixels of the element in the G-buffer / (W * H), in [0, 1].
* ``P`` centrality of the bounding-box centre: ``1 - max(|ndc_x|, |ndc_y|)`` clamped to
  [0, 1] (1 at the view centre, 0 on or outside the image border, 0 behind the camera);
  from screen-space boxes of the visible pixels with ``screen_centrality``.
* ``D`` Euclidean distance from the eye to the bounding-box centre, metres, >= ``D_MIN``.
* ``V = A * P / D`` (1 / metre).
* ``Q = 1 + reflector-to-reflector bounces`` of the reflector's rays, learned from its
  ``TraceRecord``s by the policies (``phrt_usd.select.policies``), in [1, bounce limit].
* ``O`` for a reflector ``i`` reflecting ``j``: 1 while |c_i - c_j| <= D_i, then +1 per
  doubling: ``1 + floor(log2(|c_i - c_j| / D_i))``.
* ``C_i = V_i * Q_i + sum_j V_j' * Q_j / O_ij`` over the reflectors ``j`` that ``i`` was
  seen to reflect, with ``V_j' = max(V_j, V_i * f_ij)`` (``f_ij``: fraction of i's pixels
  whose rays hit j), so a reflector seen only through ``i`` still adds to ``C_i``.
* ``R = (S * I + V * G) * K``, G the reflector's gain from tracing at its roughness
  (``model.reflection_roughness``: 1 - the share its reflection fades into the raster's
  environment, 1 for a mirror; applied by the policies, ``select/policies.py``).

Points and boxes are world-space metres; screen boxes and areas are pixels of a W x H image,
projected through the camera's ``CameraFrame.image_window`` (aperture offsets, conform
policy and pixel aspect as the render draws them; ``CameraFrame.project``).
``box_screen_area`` (the screen rectangle of a box per camera) feeds HEU1's lookahead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from phrt_usd.model.scene import CameraFrame

#: Smallest camera distance D in metres. D is a bounding-box-centre distance, so it can be
#: ~0 when the eye is inside a large reflector's box; V = A*P/D then stays <= 1 / D_MIN.
#: A micrometre is below any sensible camera near plane, so it never changes a real ranking.
D_MIN = 1e-6

#: K (phrt:priority) and I (phrt:selectionWeight) are clipped to [0, WEIGHT_MAX] (NaN → 0)
#: so R = (S*I + V)*K <= ~1e24 stays finite in float64 whatever the stage says.
WEIGHT_MAX = 1e12


def visible_area(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """A: (n,) pixel counts → (n,) float64 fraction of the image, in [0, 1]."""
    total = max(int(width) * int(height), 1)
    return np.clip(np.asarray(pixels, dtype=np.float64) / total, 0.0, 1.0)


def centrality(centers: np.ndarray, camera: CameraFrame, width: int, height: int) -> np.ndarray:
    """P: (n, 3) world-metre points → (n,) float64 in [0, 1].

    ``1 - max(|ndc_x|, |ndc_y|)``: 1 at the view centre, falling linearly to 0 on the
    image border (a square falloff matching the rectangular view plane), 0 outside the
    image and behind the camera.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if len(centers) == 0:
        return np.zeros(0)
    with np.errstate(over="ignore", invalid="ignore"):
        projected = camera.project(centers, width, height)
        ndc_x = projected[:, 0] / width * 2.0 - 1.0
        ndc_y = 1.0 - projected[:, 1] / height * 2.0
        p = 1.0 - np.maximum(np.abs(ndc_x), np.abs(ndc_y))
    p = np.where(projected[:, 2] > 0.0, p, 0.0)  # behind the eye: not in view
    # Points on the eye plane project to +-inf (or NaN for 0/0): they are not in view.
    return np.clip(np.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)


def screen_centrality(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """P from screen-space boxes: (n, 4) pixel (col_min, row_min, col_max, row_max) →
    (n,) float64 in [0, 1], the falloff of ``centrality`` at the box centre (pixel
    centres at +0.5)."""
    boxes = np.nan_to_num(np.asarray(boxes, dtype=np.float64).reshape(-1, 4), nan=-1e9)
    cx = 0.5 * (boxes[:, 0] + boxes[:, 2]) + 0.5
    cy = 0.5 * (boxes[:, 1] + boxes[:, 3]) + 0.5
    ndc_x = cx / max(width, 1) * 2.0 - 1.0
    ndc_y = 1.0 - cy / max(height, 1) * 2.0
    return np.clip(1.0 - np.maximum(np.abs(ndc_x), np.abs(ndc_y)), 0.0, 1.0)


def box_screen_area(
    bounds_min: np.ndarray,
    bounds_max: np.ndarray,
    cameras: Sequence[CameraFrame],
    width: int,
    height: int,
) -> np.ndarray:
    """Pixels covered by the screen rectangle of axis-aligned boxes, clipped to the image,
    for each of several cameras.

    bounds_min, bounds_max: (n, 3) float64 world metres → (len(cameras), n) float64 in
    [0, W * H]. A box wholly behind a camera's eye covers 0; one that reaches from in front
    of the eye to behind it projects to an unbounded rectangle and counts as the whole
    image (the camera is at or inside it). Occlusion is not considered: this bounds what
    the box's contents can cover, and is used for ratios between cameras.
    """
    lo = np.asarray(bounds_min, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(bounds_max, dtype=np.float64).reshape(-1, 3)
    n, m = len(lo), len(cameras)
    if n == 0 or m == 0:
        return np.zeros((m, n))
    # (n * 8, 3) corners: bit k of the corner index picks lo or hi on axis k.
    pick = ((np.arange(8)[:, None] >> np.arange(3)) & 1).astype(bool)
    corners = np.where(pick[None], hi[:, None, :], lo[:, None, :]).reshape(-1, 3)
    cam_from_world = np.linalg.inv(np.stack([c.world_from_camera for c in cameras]))
    # (m, n * 8, 3) camera-space corners, as CameraFrame.project computes them.
    pc = corners @ cam_from_world[:, :3, :3].transpose(0, 2, 1) + cam_from_world[:, None, :3, 3]
    # (m, 4) image windows (left, right, bottom, top) at distance 1: aperture offsets and
    # the conform policy as the render projects (CameraFrame.image_window); the centre
    # (cx, cy) is 0 for a centred camera, so its figures are those of tan_half_fov.
    window = np.array([c.image_window(width, height) for c in cameras], dtype=np.float64)
    centre = 0.5 * (window[:, [0, 2]] + window[:, [1, 3]])  # (m, 2) cx, cy
    tan = 0.5 * (window[:, [1, 3]] - window[:, [0, 2]])  # (m, 2) half width, half height
    depth = (-pc[..., 2]).reshape(m, n, 8)
    in_front = np.any(depth > 0.0, axis=2)
    straddles = in_front & np.any(depth <= 0.0, axis=2)
    # A corner on the eye plane divides by ~0; such a box straddles or touches the eye
    # and is replaced below, so its (inf / NaN) rectangle is only clipped away here.
    safe = np.where(np.abs(depth) < 1e-300, 1e-300, depth)
    with np.errstate(over="ignore", invalid="ignore"):
        ndc_x = (pc[..., 0].reshape(m, n, 8) - centre[:, 0, None, None] * safe) / (
            safe * tan[:, 0, None, None]
        )
        ndc_y = (pc[..., 1].reshape(m, n, 8) - centre[:, 1, None, None] * safe) / (
            safe * tan[:, 1, None, None]
        )
        # Near-overflow NDC (a corner almost on the eye plane) overflows to inf here:
        # clipped to the image like any corner beyond its edge.
        x = np.clip(np.nan_to_num((ndc_x + 1.0) * 0.5 * width, nan=0.0), 0.0, float(width))
        y = np.clip(np.nan_to_num((1.0 - ndc_y) * 0.5 * height, nan=0.0), 0.0, float(height))
    area = (x.max(axis=2) - x.min(axis=2)) * (y.max(axis=2) - y.min(axis=2))
    area = np.where(straddles, float(width) * float(height), area)
    return np.where(in_front, area, 0.0)


def camera_distance(centers: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """D: (n, 3) world-metre points, (3,) eye → (n,) float64 metres, >= D_MIN."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = np.linalg.norm(centers - np.asarray(eye, dtype=np.float64), axis=1)
    return np.clip(np.nan_to_num(d, nan=D_MIN, posinf=np.finfo(np.float64).max), D_MIN, None)


def visibility(A: np.ndarray, P: np.ndarray, D: np.ndarray) -> np.ndarray:
    """V = A * P / D (paper eq. 1), float64, finite: D is clamped to >= D_MIN."""
    A = np.clip(np.asarray(A, dtype=np.float64), 0.0, 1.0)
    P = np.clip(np.asarray(P, dtype=np.float64), 0.0, 1.0)
    D = np.clip(np.asarray(D, dtype=np.float64), D_MIN, None)
    return A * P / D


def distance_factor(separation: np.ndarray, D: np.ndarray | float) -> np.ndarray:
    """O: 1 while ``separation <= D``, +1 each time it doubles: 1 + floor(log2(sep / D)).

    separation: (n,) metres between the two reflectors' bounding-box centres;
    D: the reflecting element's camera distance (metres, clamped >= D_MIN). Result (n,)
    float64 >= 1, at most ~2100 even for 1e300 m / 1e-6 m.
    """
    D = np.clip(np.asarray(D, dtype=np.float64), D_MIN, None)
    sep = np.nan_to_num(np.asarray(separation, dtype=np.float64), nan=0.0)
    with np.errstate(over="ignore"):
        ratio = np.maximum(sep / D, 1.0)  # <= D counts as 1 (no doubling yet)
    ratio = np.minimum(ratio, np.finfo(np.float64).max)  # inf/huge → largest float
    return 1.0 + np.floor(np.log2(ratio))


def processing_costs(
    V: np.ndarray,
    Q: np.ndarray,
    owner: np.ndarray,
    reflected_V: np.ndarray,
    reflected_Q: np.ndarray,
    reflected_O: np.ndarray,
) -> np.ndarray:
    """C = V*Q + sum_j V_j*Q_j/O_j (paper eq. 2) for n elements at once.

    V, Q: (n,) the elements' own figures; owner: (m,) int index into the n elements of
    each reflected reflector; reflected_V, reflected_Q, reflected_O: (m,) its figures.
    All inputs finite and >= 0 (O >= 1), so every C is finite and >= 0. Returns (n,)."""
    V = np.asarray(V, dtype=np.float64)
    rv = np.asarray(reflected_V, dtype=np.float64)
    rq = np.asarray(reflected_Q, dtype=np.float64)
    ro = np.maximum(np.asarray(reflected_O, dtype=np.float64), 1.0)
    reflected = np.bincount(np.asarray(owner, dtype=np.int64), rv * rq / ro, minlength=len(V))
    return V * np.asarray(Q, dtype=np.float64) + reflected


def processing_cost(
    V: float, Q: float, reflected_V: np.ndarray, reflected_Q: np.ndarray, reflected_O: np.ndarray
) -> float:
    """``processing_costs`` of one element reflecting the (m,) reflectors given."""
    owner = np.zeros(len(np.atleast_1d(reflected_V)), dtype=np.int64)
    return float(processing_costs([V], [Q], owner, reflected_V, reflected_Q, reflected_O)[0])


def relevance(S: np.ndarray, weight: float, V: np.ndarray, K: np.ndarray) -> np.ndarray:
    """R = (S * I + V) * K (paper eq. 3) with I = ``weight``; I and K clipped to
    [0, WEIGHT_MAX]."""
    I_ = clip_weight(weight)
    K_ = clip_weight(K)
    S_ = np.asarray(S, dtype=np.float64)
    V_ = np.nan_to_num(np.asarray(V, dtype=np.float64), nan=0.0, posinf=1.0 / D_MIN)
    return (S_ * I_ + V_) * K_


def clip_weight(w: np.ndarray | float) -> np.ndarray:
    """K or I as float64 in [0, WEIGHT_MAX]; NaN → 0 (see WEIGHT_MAX)."""
    w = np.nan_to_num(np.asarray(w, dtype=np.float64), nan=0.0, posinf=WEIGHT_MAX)
    return np.clip(w, 0.0, WEIGHT_MAX)
