"""Where a frame's G-buffer comes from (``--primary``, ``RenderOptions.primary``).

Two sources fill the same ``GBuffer`` fields (``model.frame``) by the same surface rule:
the raster id pass (``render.raster.gbuffer``) and Embree's primary rays
(``Tracer.primary_gbuffer``, the ``rt`` mode's). Their element ids agree on >= 99.5 %
of covered pixels (they may differ where coplanar surfaces z-fight), so the images
agree within the hybrid-against-rt thresholds whichever runs.

Which is cheaper depends on the rasterizer. A GPU draws triangles almost for free. A
software rasterizer (Mesa's llvmpipe, the CPU OpenGL of a machine without a GPU) pays for
every triangle's vertices and set-up, primary rays for every pixel. Measured here
(2 cores, llvmpipe; G-buffer ms, raster / rays): the paper stages at 640 x 480 (0.15-0.18
triangles a pixel) 12.9 / 29.1 and 14.0 / 25.2; at 320 x 240 (0.58-0.70) 7.3 / 7.3 and
10.4 / 6.9; at 160 x 120 (2.3-2.8) 5.2 / 2.2 and 7.0 / 3.7; a 1M-triangle ground at
640 x 480 (3.3) 60-80 / 32. The rays win from about half a triangle a pixel on.

- ``raster``: the id pass;
- ``rays``: primary rays (an Embree scene is built for them if the mode has none);
- ``auto``: ``rays`` where the raster phase runs on a software rasterizer and the stage
  has more than RAYS_TRIANGLES_PER_PIXEL triangles a pixel, in every mode (a ``raster``
  render then builds an Embree scene for its primary rays alone: on the 1.4 M-triangle
  stages where this holds, the BVH's build costs about what two raster id passes do,
  and every frame after it is cheaper, so ``raster`` is never the slowest mode on a
  heavy stage); ``raster`` otherwise (``choose``).

``auto`` decides from the stage, the image size and the OpenGL renderer only, never from
a timing: the same run on the same machine always takes the same source, so a rays
budget stays deterministic and ``--resume`` continues with the pixels it began with.
``rt`` mode always traces its primary rays.
"""

from __future__ import annotations

from phrt_usd.model.render_options import OPTIONS, PRIMARY_SOURCES  # noqa: F401

DEFAULT_PRIMARY = OPTIONS["primary"].default

#: ``auto`` takes the rays above this many triangles a pixel on a software rasterizer:
#: twice the measured crossover (module docstring), so that near the crossover the
#: paper's raster path stays (a run there loses at most what the crossover's scatter
#: does; the stages that lose most, meshes of millions of triangles, are far above it).
RAYS_TRIANGLES_PER_PIXEL = 1.0

#: Substrings of ``GL_RENDERER`` that name a software rasterizer (Mesa's).
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast")


def check_primary(value: object) -> str:
    """``value`` as one of PRIMARY_SOURCES; BadOption (one line) otherwise."""
    return OPTIONS["primary"].check(value)


def is_software(gl_renderer: str) -> bool:
    """True when the OpenGL renderer string names a software rasterizer."""
    name = gl_renderer.lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


def choose(option: str, software_gl: bool, triangles: int, pixels: int) -> str:
    """The source ("raster" or "rays") for ``option`` (one of PRIMARY_SOURCES) in a
    raster or hybrid renderer: ``software_gl`` whether its raster phase runs on a
    software rasterizer, and the stage's ``triangles`` and the image's ``pixels``."""
    if option != "auto":
        return option
    dense = triangles > RAYS_TRIANGLES_PER_PIXEL * max(pixels, 1)
    return "rays" if software_gl and dense else "raster"
