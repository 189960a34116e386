"""The camera a stage without any ``UsdGeomCamera`` renders with (most assets have none).

As ``usdrecord`` does (``UsdAppUtilsFrameRecorder``: ``_ComputeCameraToFrameStage``), the
camera is USD's default ``GfCamera`` (50 mm focal length, 20.955 x 15.2908 mm film back,
the ``UsdGeomCamera`` schema fallbacks), looking at the centre of the stage's bounds along
the stage's up-axis convention: for ``upAxis = Y`` from +Z looking down -Z, for
``upAxis = Z`` from -Y looking down +Y (camera rotated +90 degrees about X, +Z up in the
image). Where usdrecord backs off so that the front face of the bounds fills the
horizontal field of view, this camera backs off so that the bounds' *bounding sphere*
fits the aperture's smaller (vertical) field of view: the whole stage is then in view
whatever its shape, and under ``expandAperture`` (UsdRender's fallback) for any image
aspect, since the conformed window contains the aperture.

The bounds are those of the geometry the render reads, at the first time of the frame
range, in world metres; the camera does not move (animated geometry may leave the view).
"""

from __future__ import annotations

import numpy as np
from pxr import Gf

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import CameraFrame, Scene

#: What ``StageScene.camera_path`` holds for the default camera (stats, image headers):
#: not a prim path, so it never names a prim of the stage.
DEFAULT_CAMERA_NAME = "<default camera>"

_GF_CAMERA = Gf.Camera()  # USD's default camera: the focal length and film back used
#: Focal length and apertures of the default camera (mm; only their ratios matter).
FOCAL_LENGTH = float(_GF_CAMERA.focalLength)
HORIZONTAL_APERTURE = float(_GF_CAMERA.horizontalAperture)
VERTICAL_APERTURE = float(_GF_CAMERA.verticalAperture)

#: Smallest bounding-sphere radius, relative to the distance of the bounds from the world
#: origin (and at least 1 µm): a stage of one point (or coincident points) still gives a
#: finite, non-zero camera distance that float64 positions resolve.
MIN_RADIUS_REL = 1e-9
MIN_RADIUS_M = 1e-6

#: Clipping range around the bounding sphere, as factors of its near and far distances:
#: the sphere holds every vertex, so anything wider only costs depth precision (the
#: raster pass tightens the range to the bounds again).
NEAR_FACTOR = 0.5
FAR_FACTOR = 2.0


def default_camera(scene: Scene, up_axis: str, where: str) -> CameraFrame:
    """The default camera framing ``scene``'s vertices (module doc), world metres.

    ``where`` names the stage in the one-line ``PhrtError`` raised when there is no
    geometry to frame."""
    v = scene.geometry.vertices
    finite = v[np.all(np.isfinite(v), axis=1)] if len(v) else v
    if len(finite) == 0:
        raise PhrtError(
            f"{where}: stage has no UsdGeomCamera and no geometry to frame with a "
            "default camera (nothing to render)"
        )
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    radius = max(radius, MIN_RADIUS_REL * float(np.linalg.norm(centre)), MIN_RADIUS_M)
    half_fov = np.arctan(0.5 * min(HORIZONTAL_APERTURE, VERTICAL_APERTURE) / FOCAL_LENGTH)
    distance = radius / np.sin(half_fov)  # the sphere is tangent to the view cone
    world_from_camera = np.eye(4)
    if up_axis == "Z":
        # Columns: camera x, y, z axes in world space (rotation of +90 degrees about X).
        world_from_camera[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
        world_from_camera[:3, 3] = centre - np.array([0.0, distance, 0.0])
    else:
        world_from_camera[:3, 3] = centre + np.array([0.0, 0.0, distance])
    return CameraFrame(
        world_from_camera=world_from_camera,
        focal_length=FOCAL_LENGTH,
        horizontal_aperture=HORIZONTAL_APERTURE,
        vertical_aperture=VERTICAL_APERTURE,
        near=NEAR_FACTOR * (distance - radius),
        far=FAR_FACTOR * (distance + radius),
    )
