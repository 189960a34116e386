"""The light rig of a stage without any light: a dim uniform dome and a headlight.

As USD's viewers do (usdview's camera light and dome, the default lighting of Hydra's
Storm when a stage has none), so that such a stage is not rendered near-black in
silence. The headlight is a DistantLight shining from the camera along its view
direction; ``aim_headlight`` turns it with the camera every frame (the renderer calls it,
``engine/renderer.py``). Values in the renderer's convention (``engine/shading.py``: a
white surface facing a unit DistantLight shows 1.0):

- ``HEADLIGHT_IRRADIANCE`` 0.6 and ``DOME_RADIANCE`` 0.25: a white surface of
  UsdPreviewSurface's fallback material facing the camera shows 0.6 x 1.19 (diffuse and
  the GGX highlight at roughness 0.5, ``model/preview_surface.py``) + 0.25 (ambient) =
  0.96, about display white and no more; a grazing one still shows the dome's 0.25, so
  shapes read everywhere.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phrt_usd.model.scene import CameraFrame, DistantLight, DomeLight, Lights

#: Irradiance of the headlight (white, linear), see the module doc.
HEADLIGHT_IRRADIANCE = 0.6
#: Radiance of the uniform dome (white, linear): the ambient term, see the module doc.
DOME_RADIANCE = 0.25
#: Name of the rig in notices, inspection and ``render --json``.
DEFAULT_RIG_NAME = "default light rig"


def default_light_rig() -> Lights:
    """The rig (``Lights.default_rig``): ``distant[0]`` the headlight (aimed along world
    -Z until ``aim_headlight``), the dome uniform, visible to the camera."""
    headlight = DistantLight(
        np.array([0.0, 0.0, 1.0]), np.full(3, HEADLIGHT_IRRADIANCE), 0.0, "(headlight)"
    )
    dome = DomeLight(np.full(3, DOME_RADIANCE), None, np.eye(3), "(default dome)")
    return Lights(distant=[headlight], dome=dome, default_rig=True)


def aim_headlight(lights: Lights, camera: CameraFrame) -> Lights:
    """``lights`` with the headlight pointing from ``camera`` along its view direction
    (``DistantLight.direction`` is towards the light: the camera's +Z axis, world
    space): the same object when already aimed so, else a new ``Lights`` (new objects,
    so the shadow-map and shadow-ray caches, which key on identity and direction, see
    the change). Lights that are not the default rig are returned as they are."""
    if not lights.default_rig or not lights.distant:
        return lights
    towards = -camera.forward
    head = lights.distant[0]
    if np.array_equal(head.direction, towards):
        return lights
    moved = dataclasses.replace(head, direction=towards)
    return dataclasses.replace(lights, distant=[moved, *lights.distant[1:]])
