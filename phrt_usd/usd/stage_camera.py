"""The render camera of a stage at a time code: its attribute values and every reason the
render refuses them (``camera_values``, ``camera_problems``, at the times
``camera_check_times`` names), and ``StageCamera``, the ``CameraFrame`` at a time code in
world metres, each time code read from the stage once.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Usd, UsdGeom

from phrt_usd.model.scene import CameraFrame
from phrt_usd.usd.camera_path import CameraPath
from phrt_usd.usd.render_settings import CameraSettings
from phrt_usd.usd.values import rotation_columns


@dataclass
class CameraValues:
    """A camera's attribute values at one time code and every reason the render refuses
    them (``camera_values``)."""


    world: np.ndarray | None  # (4, 4) row-vector local → world, stage units (None: driven)
    focal: float
    aperture: float
    near: float
    far: float
    problems: list[str]
    vertical: float = 0.0  # verticalAperture
    offsets: tuple[float, float] = (0.0, 0.0)  # horizontal, vertical aperture offsets
    exposure_scale: float = 1.0  # UsdGeomCamera.ComputeLinearExposureScale


#: Largest camera linear exposure scale accepted (2^40: beyond it float32 radiance
#: of ordinary scenes, ~1e-6..1e6, leaves float32's range, 3.4e38, within a few frames'
#: worth of headroom only).
MAX_CAMERA_EXPOSURE_SCALE = 2.0**40


def camera_values(prim: Usd.Prim, time: float, driven: bool) -> CameraValues:
    """The camera's attributes at ``time`` and every reason the render refuses them."""
    code = Usd.TimeCode(float(time))
    cam = UsdGeom.Camera(prim)
    where = str(prim.GetPath())
    problems = []
    if cam.GetProjectionAttr().Get(code) == UsdGeom.Tokens.orthographic:
        problems.append(f"{where}.projection: orthographic cameras are not supported")
    world = None
    if not driven:
        world = np.array(UsdGeom.XformCache(code).GetLocalToWorldTransform(prim))
        if not np.all(np.isfinite(world)):
            problems.append(f"{where}: non-finite camera transform at time {time}")
    focal = float(cam.GetFocalLengthAttr().Get(code))
    aperture = float(cam.GetHorizontalApertureAttr().Get(code))
    near, far = (float(x) for x in cam.GetClippingRangeAttr().Get(code))
    if not (np.isfinite(focal) and focal > 0):
        problems.append(f"{where}.focalLength: must be > 0 at time {time}, got {focal}")
    if not (np.isfinite(aperture) and aperture > 0):
        problems.append(f"{where}.horizontalAperture: must be > 0 at time {time}, got {aperture}")
    vertical = float(cam.GetVerticalApertureAttr().Get(code))
    if not (np.isfinite(vertical) and vertical > 0):
        problems.append(f"{where}.verticalAperture: must be > 0 at time {time}, got {vertical}")
    offsets = (
        float(cam.GetHorizontalApertureOffsetAttr().Get(code)),
        float(cam.GetVerticalApertureOffsetAttr().Get(code)),
    )
    for name, value in zip(_OFFSET_ATTRS, offsets, strict=True):
        if not np.isfinite(value):
            problems.append(f"{where}.{name}: must be finite at time {time}, got {value}")
    if not (np.isfinite(near) and np.isfinite(far) and far > near):
        problems.append(f"{where}.clippingRange: need near < far, got ({near}, {far})")
    # USD's own formula: 2^exposure x time x ISO/100 x responsivity / fStop² (1 unauthored).
    exposure_scale = float(cam.ComputeLinearExposureScale(code))
    if not (np.isfinite(exposure_scale) and 0.0 <= exposure_scale <= MAX_CAMERA_EXPOSURE_SCALE):
        problems.append(
            f"{where}.exposure: the exposure attributes give a linear scale of "
            f"{exposure_scale} at time {time}, need 0..{MAX_CAMERA_EXPOSURE_SCALE:g}"
        )
    return CameraValues(
        world, focal, aperture, near, far, problems, vertical, offsets, exposure_scale
    )


def camera_problems(prim: Usd.Prim, time: float, driven: bool = False) -> list[str]:
    """Every reason the render refuses the camera at ``time`` (the first is what
    ``StageScene.camera`` raises): orthographic projection, a non-finite transform
    (unless a camera path drives it, ``driven``), focal length or an aperture not > 0,
    an aperture offset not finite, clipping range not near < far."""
    return camera_values(prim, time, driven).problems


_OFFSET_ATTRS = ("horizontalApertureOffset", "verticalApertureOffset")
_CAMERA_ATTRS = (
    "projection",
    "focalLength",
    "horizontalAperture",
    "verticalAperture",
    *_OFFSET_ATTRS,
    "clippingRange",
)


def camera_check_times(prim: Usd.Prim, frames: tuple[float, float], driven: bool) -> list[float]:
    """Times at which ``camera_problems`` covers the whole frame range: its start and end
    and every time sample inside it of the camera attributes and (unless driven) of the
    transforms of the camera and its ancestors. Values between samples are linear
    interpolations, so their extremes are at these times."""
    start, end = frames
    interval = Gf.Interval(start, end)
    times = {start, end}
    for name in _CAMERA_ATTRS:
        attr = prim.GetAttribute(name)
        if attr:
            times.update(attr.GetTimeSamplesInInterval(interval))
    p = prim
    while not driven and p and not p.IsPseudoRoot():
        xf = UsdGeom.Xformable(p)
        if xf:
            times.update(xf.GetTimeSamplesInInterval(interval))
            if xf.GetResetXformStack():
                break
        p = p.GetParent()
    return sorted(float(t) for t in times)


#: Camera evaluations ``StageScene`` keeps, by time code (the oldest dropped first):
#: more than the 97 a renderer looks at per frame (the frame's and the 96 ahead of it,
#: ``select.heu1_policy.UPCOMING_CAMERAS``), so ``set_time`` and the renderer read each
#: camera from the stage once (~0.2 ms each on the example stages).
CAMERA_CACHE_SIZE = 128


class StageCamera:
    """The camera a ``StageScene`` renders through, as a ``CameraFrame`` per time code.

    prim : the UsdGeomCamera, or None when ``default`` (``default_camera``) frames the
    stage; path_driver : the ``CameraPath`` driving it, or None; image : the render
    settings' conform policy, pixel aspect and data window; meters_per_unit : the stage's.
    """

    def __init__(
        self,
        prim: Usd.Prim | None,
        path_driver: CameraPath | None,
        image: CameraSettings,
        meters_per_unit: float,
        default: CameraFrame | None,
    ) -> None:
        self.prim = prim
        self.path_driver = path_driver
        self.image = image
        self.meters_per_unit = meters_per_unit
        self.default = default
        self._cache: dict[float, tuple[CameraFrame | None, list[str]]] = {}

    def at(self, time: float) -> tuple[CameraFrame | None, list[str]]:
        """(the camera at ``time``, []) or (None, every reason the render refuses it),
        each of the last CAMERA_CACHE_SIZE time codes asked for read once."""
        time = float(time)
        if time not in self._cache:
            if len(self._cache) >= CAMERA_CACHE_SIZE:
                del self._cache[next(iter(self._cache))]  # the oldest
            self._cache[time] = self._read(time)
        return self._cache[time]

    def _read(self, time: float) -> tuple[CameraFrame | None, list[str]]:
        """``at`` read from the stage: world metres, orthonormal rotation."""
        image = self.image
        if self.default is not None:
            camera = dataclasses.replace(
                self.default,
                conform_policy=image.conform_policy,
                pixel_aspect=image.pixel_aspect,
                data_window=image.data_window,
            )
            return camera, []
        v = camera_values(self.prim, time, self.path_driver is not None)
        if v.problems:
            return None, v.problems
        if self.path_driver is not None:
            world_from_camera = self.path_driver.world_from_camera(time, self.meters_per_unit)
        else:
            m = v.world
            world_from_camera = np.eye(4)
            world_from_camera[:3, :3] = rotation_columns(m)
            world_from_camera[:3, 3] = m[3, :3] * self.meters_per_unit
        focal, aperture, near, far = v.focal, v.aperture, v.near, v.far
        # A zero near plane gives a singular depth projection: keep it a tiny positive
        # fraction of the far plane.
        near = max(near, far * 1e-7)
        camera = CameraFrame(
            world_from_camera=world_from_camera,
            focal_length=focal,
            horizontal_aperture=aperture,
            near=near * self.meters_per_unit,
            far=far * self.meters_per_unit,
            vertical_aperture=v.vertical,
            horizontal_aperture_offset=v.offsets[0],
            vertical_aperture_offset=v.offsets[1],
            conform_policy=image.conform_policy,
            pixel_aspect=image.pixel_aspect,
            data_window=image.data_window,
            exposure_scale=v.exposure_scale,
        )
        return camera, []


def same_camera(a: CameraFrame, b: CameraFrame) -> bool:
    """Every field of the two cameras is equal (pose, lens, clipping, image settings)."""
    return all(
        np.array_equal(getattr(a, f.name), getattr(b, f.name))
        for f in dataclasses.fields(CameraFrame)
    )
