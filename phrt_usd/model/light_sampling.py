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


def shadow_rays_per_hit(n_lights: int) -> int:
    """The most shadow rays a hit casts with ``n_lights`` lights (no shadow maps)."""
    return min(max(int(n_lights), 0), HIT_LIGHT_PICKS)


def maps_light_hits(lights) -> bool:
    """The shadow maps light the traced hits of a stage with these ``Lights``: it has
    more direct lights than a hit may trace. With at most HIT_LIGHT_PICKS every pair is
    traced, exactly, and its rays cost less than the maps' lookup pass (one light, 400
    hits: 0.07 ms by rays against 0.81 ms with the maps, docs/hit-lighting.md)."""
    return len(lights.distant) + len(lights.local) > HIT_LIGHT_PICKS
