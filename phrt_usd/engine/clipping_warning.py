"""The clipping warning: a frame most of whose covered pixels are clipped after exposure
(display white) gets one warning per run, naming the brightest light and the
``--exposure`` that would bring the frame to mid-grey (``FrameRenderer`` gives it once);
when the camera's own exposure attributes are what clips it (without their scale the
frame would not be mostly clipped), the warning names the camera instead of a light.
"""

from __future__ import annotations

import numpy as np

from phrt_usd.engine import frame_pixels
from phrt_usd.engine.shading import MIN_LIGHT_DISTANCE, ambient_radiance
from phrt_usd.model.frame import GBuffer
from phrt_usd.model.scene import Lights
from phrt_usd.usd.lights import intensity_note

#: A frame whose covered pixels are clipped (some channel > CLIP_LEVEL after exposure:
#: display white) for more than CLIPPED_SHARE of them is "mostly clipped"; once per run.
#: The suggested exposure brings the covered pixels' median brightest channel to
#: SUGGESTED_MEDIAN (mid-grey of the display range).
CLIP_LEVEL = 1.0
CLIPPED_SHARE = 0.5
SUGGESTED_MEDIAN = 0.5
#: The clipping check looks at every CLIP_SAMPLE_STRIDE-th row and column: a share and a
#: median need no more than a quarter of the pixels, and the check runs every frame until
#: it warns (at 640 x 480 the full check costs ~2 ms of frame time).
CLIP_SAMPLE_STRIDE = 2


def clipping_warning(
    image: np.ndarray,
    gb: GBuffer,
    t: float,
    ev: float,
    lights: Lights,
    stage,
    camera_scale: float = 1.0,
    camera_path: str = "",
) -> str | None:
    """When more than CLIPPED_SHARE of the covered pixels of ``image`` (H, W, 3, after
    exposure ``ev`` and the camera's linear exposure scale ``camera_scale``) exceed
    CLIP_LEVEL in some channel, the warning for frame ``t``: the share, the cause and
    the ``--exposure`` that would bring the covered pixels' median to SUGGESTED_MEDIAN;
    else None. The cause is the camera ``camera_path``'s exposure attributes when
    ``camera_scale`` > 1 and the image divided by it would not be mostly clipped, else
    the brightest light (``brightest_light``, with its intensity note from ``stage``,
    the ``Usd.Stage``)."""
    step = CLIP_SAMPLE_STRIDE
    covered = gb.covered
    share = frame_pixels.clipped_share(image, covered, step, CLIP_LEVEL)
    if share <= CLIPPED_SHARE:
        return None
    unscaled_share = share
    if camera_scale > 1.0:
        unscaled_share = frame_pixels.clipped_share(image, covered, step, CLIP_LEVEL * camera_scale)
    covered = covered[::step, ::step]
    peak = image[::step, ::step][covered].max(axis=1)
    median = float(np.median(peak))
    suggest = ev + float(np.log2(SUGGESTED_MEDIAN / median)) if median > 0 else ev
    if unscaled_share <= CLIPPED_SHARE:
        return (
            f"frame {t:g}: {share:.0%} of the covered pixels are clipped (> {CLIP_LEVEL:g} "
            f"after exposure) by the exposure attributes of camera {camera_path} ("
            f"x{camera_scale:.3g}, {np.log2(camera_scale):+.1f} EV; "
            f"without them {unscaled_share:.0%} would be); lower them or try "
            f"--exposure {suggest:.1f}"
        )
    centre = gb.position[::step, ::step][covered].mean(axis=0)
    path, level = brightest_light(lights, centre)
    note = intensity_note(stage, path)
    return (
        f"frame {t:g}: {share:.0%} of the covered pixels are clipped (> {CLIP_LEVEL:g} "
        f"after exposure); brightest light {path} (~{level:.3g} at the scene{note}); "
        f"try --exposure {suggest:.1f}"
    )


def brightest_light(lights: Lights, centre: np.ndarray) -> tuple[str, float]:
    """(prim path, brightest channel of its irradiance) of the light that gives most at
    ``centre`` (3,) world metres, the covered pixels' mean position: a DistantLight its
    radiance, a LocalLight radiance / d² (unshadowed, no cone), the dome its mean
    radiance (``shading.ambient_radiance``)."""
    best = ("(no light)", 0.0)
    for li in lights.distant:
        best = max(best, (li.path, float(np.max(li.radiance))), key=lambda b: b[1])
    for li in lights.local:
        d2 = max(float(np.sum((np.asarray(li.position) - centre) ** 2)), MIN_LIGHT_DISTANCE**2)
        best = max(best, (li.path, float(np.max(li.radiance)) / d2), key=lambda b: b[1])
    if lights.dome is not None:
        level = float(np.max(ambient_radiance(lights)))
        best = max(best, (lights.dome.path, level), key=lambda b: b[1])
    return best
