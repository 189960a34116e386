"""Cut-outs beyond the camera's own rays: reflected rays pass holes as primary rays do
(HitSurfaces.intersect in the bounce loop), and a local light's cube shadow maps are
peeled like the distant maps (the last test). A mirror seen by the camera reflects the
cut-out quad of ``test_cutouts`` placed behind the camera, and beyond the quad's cut half
the wall (``textured_stages.mirrored_cutout_stage``).

Geometry (metres): camera at z = 5 looking down -z; a mirror (PhrtReflectorAPI, F = 1)
at z = -1; the cut-out quad (2 m, red, alpha 0 for x < 0) at z = 6 and the blue wall at
z = 7, both behind the camera. A pixel ray of slope dx = x / z reaches the mirror at
x = 6 dx and, reflected, the quad's plane at x = 13 dx and the wall's at 14 dx. A
DistantLight travelling +z lights the faces the mirror sees.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import UsdGeom, UsdLux
from textured_stages import (
    HEIGHT,
    WIDTH,
    cutout_stage,
    mirrored_cutout_stage,
    pixel_at,
    render_first_frame,
)

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd.stage import read_stage


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["rt", "hybrid"])
def test_the_mirror_shows_the_wall_through_the_cut_half(tmp_path, mode):
    scene = read_stage(mirrored_cutout_stage(tmp_path))
    t = scene.frame_range[0]
    opts = RenderOptions(mode=mode, heuristic="all", width=WIDTH, height=HEIGHT, budget_ms=None)
    renderer = FrameRenderer(scene, opts)
    try:
        out = renderer.render(t)
    finally:
        renderer.close()
    camera = scene.camera(t)

    def pixel(x_at_quad):  # the mirror point whose reflection meets the quad at x
        x, y, _ = camera.project(np.array([[6.0 * x_at_quad / 13.0, 0.0, -1.0]]), WIDTH, HEIGHT)[0]
        return int(y), int(x)

    hole, solid = pixel(-0.5), pixel(0.5)
    assert out.gbuffer.element_id[hole] == out.gbuffer.element_id[solid] == 0  # the mirror
    assert out.traced_mask[hole] and out.traced_mask[solid]
    b = out.beauty
    # F = 1: the pixel is the reflected radiance; the wall's blue through the hole, the
    # quad's red where it is there (each channel over twice the others).
    assert b[hole][2] > 2 * max(b[hole][0], b[hole][1]), b[hole]
    assert b[solid][0] > 2 * max(b[solid][1], b[solid][2]), b[solid]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_a_local_light_shines_through_the_cut_half(tmp_path, mode):
    """The cube shadow maps of a SphereLight are peeled like the distant maps, and its
    finite shadow rays (rt) pass the holes with the rest of their length: the
    test_cutouts stage lit by a small SphereLight at (0, 0, 1) instead of the sun. Wall
    point (-0.5, 0, -1), seen through the hole, reaches the light through the quad's
    plane at x = -0.25 (cut half): lit exactly as with no quad; wall point (1.5, 0, -1),
    beside the quad from the camera, crosses at x = 0.75 (present half): shadowed."""
    def lit_by_bulb(stage):
        stage.RemovePrim("/Sun")
        bulb = UsdLux.SphereLight.Define(stage, "/Bulb")
        bulb.CreateRadiusAttr(0.01)
        bulb.CreateNormalizeAttr(True)  # intensity 4 / 4 = 1 (usd/lights.local_intensity)
        bulb.CreateIntensityAttr(4.0)
        bulb.AddTranslateOp().Set((0.0, 0.0, 1.0))
        stage.GetRootLayer().Save()
        return stage

    (tmp_path / "cut").mkdir()
    (tmp_path / "bare").mkdir()
    cut = lit_by_bulb(cutout_stage(tmp_path / "cut"))
    bare = lit_by_bulb(cutout_stage(tmp_path / "bare"))
    UsdGeom.Imageable(bare.GetPrimAtPath("/Quad")).MakeInvisible()
    out, camera = render_first_frame(cut, mode)
    ref, _ = render_first_frame(bare, mode)
    through = pixel_at(camera, (-0.5, 0.0, -1.0))
    np.testing.assert_allclose(out.beauty[through], ref.beauty[through], rtol=1e-5)
    shadowed = pixel_at(camera, (1.5, 0.0, -1.0))
    assert out.beauty[shadowed][2] < 0.5 * ref.beauty[shadowed][2]
