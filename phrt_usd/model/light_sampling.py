"""How many shadow rays a traced hit casts at most, and where the shadow maps light the
hits instead: the tracer's hit-lighting rule (``engine.trace.hit_lighting``), the
renderer (whose ``rt`` mode renders the maps only where they are used) and the
policies' first guess of a reflector's rays (``select.policies``) share them.
"""

from __future__ import annotations

#: The hit-lighting rule's light sampling: a hit with more lights to trace than this
#: (of a positive unshadowed share) casts this many shadow rays, the dominant lights
#: traced and the rest drawn by their shares; with at most this many it traces them
#: all. 2, measured on the sewer (13 lights, frame 241, 640x480, every reflector traced,
#: hits without maps): mean FLIP against every pair traced 0.0079 at 2 picks (3.7 rays
#: a traced pixel), 0.0045 at 3 (4.9), 0.0027 at 4 (6.1); with the shadow maps deciding
#: most pairs the picks matter only where a hit has more undecided pairs than this.
HIT_LIGHT_PICKS = 2


#: A Rect or Disk light sampled as an area at the traced hits (``engine/trace/
#: shadow_rays.py``): its visible share at a hit is estimated by AREA_LIGHT_RAYS rays to
#: points drawn, by their share of the light's integral, from a Fibonacci lattice of
#: AREA_LIGHT_POINTS points over its surface (AREA_LIGHT_STEP: the Fibonacci number
#: before it), shifted by the hit's pixel and frame. One ray: a pair costs a point
#: light's, and a penumbra is a dither between pixels that changes each frame (where
#: the whole light is seen its irradiance is exact). More rays a pair make smoother
#: penumbrae, but a hit's cost then grows with the area lights it sees, which a
#: reflector's cost per pixel does not follow at reduced densities: with 13 (and 5) a
#: policy replay of a sewer capture at 96 x 72 chose differently from the render at one
#: frame (``tests/select/test_selection_rounds.py``).
AREA_LIGHT_RAYS = 1
AREA_LIGHT_POINTS = 13
AREA_LIGHT_STEP = 8


def shadow_rays_per_hit(n_lights: int) -> int:
    """The most shadow rays a hit casts with ``n_lights`` lights (no shadow maps)."""
    return min(max(int(n_lights), 0), HIT_LIGHT_PICKS)


def has_area_lights(lights) -> bool:
    """Some LocalLight of these ``Lights`` is a Rect or Disk light, an area at the traced
    hits (``LocalLight.area_shape``)."""
    return any(light.area_shape for light in lights.local)


def maps_light_hits(lights) -> bool:
    """The shadow maps light the traced hits of a stage with these ``Lights``: it has
    more direct lights than a hit may trace. With at most HIT_LIGHT_PICKS every pair is
    traced, exactly, and its rays cost less than the maps' lookup pass (one light, 400
    hits: 0.07 ms by rays against 0.81 ms with the maps, docs/hit-lighting.md). Where the
    maps light a batch of hits a Rect or Disk light keeps its area's irradiance with the
    maps' shadow from its centre (soft shadows where rays decide,
    ``engine/trace/shadow_rays.py``)."""
    return len(lights.distant) + len(lights.local) > HIT_LIGHT_PICKS
