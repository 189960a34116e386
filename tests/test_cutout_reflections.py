"""Cut-outs beyond the camera's own rays: reflected rays pass holes as primary rays do
(HitSurfaces.intersect in the bounce loop), and a local light's cube shadow maps are
peeled like the distant maps (the last test). A mirror seen by the camera reflects the
cut-out quad of ``test_cutouts`` placed behind the camera, and beyond the quad's cut half
the wall.

Geometry (metres): camera at z = 5 looking down -z; a mirror (PhrtReflectorAPI, F = 1)
at z = -1; the cut-out quad (2 m, red, alpha 0 for x < 0) at z = 6 and the blue wall at
z = 7, both behind the camera. A pixel ray of slope dx = x / z reaches the mirror at
x = 6 dx and, reflected, the quad's plane at x = 13 dx and the wall's at 14 dx. A
DistantLight travelling +z lights the faces the mirror sees.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade
from test_cutouts import HEIGHT, QUAD, WALL, WIDTH, _half_alpha, _material, _quad, _texture

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd import schema
from phrt_usd.usd.stage import read_stage


def _stage(tmp_path) -> Usd.Stage:
    _half_alpha(tmp_path / "half_alpha.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / "mirror.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mirror = _quad(stage, "/Mirror", 3.0, -1.0, st=False)
    schema.apply_reflector(mirror.GetPrim(), priority=1.0, reflectivity=1.0)
    # The quad and wall face +z as in test_cutouts; their back faces look at the mirror.
    wall = _quad(stage, "/Wall", 3.0, 7.0, st=False)
    quad = _quad(stage, "/Quad", 1.0, 6.0)
    wall_mat, _ = _material(stage, "/Looks/Wall", WALL)
    quad_mat, surf = _material(stage, "/Looks/Quad", QUAD)
    tex = _texture(stage, "/Looks/Quad/Alpha", "half_alpha.png")
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
    )
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    UsdShade.MaterialBindingAPI.Apply(wall.GetPrim()).Bind(wall_mat)
    UsdShade.MaterialBindingAPI.Apply(quad.GetPrim()).Bind(quad_mat)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set((0.0, 0.0, 5.0))
    cam.CreateFocalLengthAttr(25.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(1.0)
    sun.AddRotateYOp().Set(180.0)  # -Z turned to +Z: light travelling towards the wall
    stage.GetRootLayer().Save()
    return stage


@pytest.mark.parametrize("mode", ["rt", "hybrid"])
def test_the_mirror_shows_the_wall_through_the_cut_half(tmp_path, mode):
    scene = read_stage(_stage(tmp_path))
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


@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_a_local_light_shines_through_the_cut_half(tmp_path, mode):
    """The cube shadow maps of a SphereLight are peeled like the distant maps, and its
    finite shadow rays (rt) pass the holes with the rest of their length: the
    test_cutouts stage lit by a small SphereLight at (0, 0, 1) instead of the sun. Wall
    point (-0.5, 0, -1), seen through the hole, reaches the light through the quad's
    plane at x = -0.25 (cut half): lit exactly as with no quad; wall point (1.5, 0, -1),
    beside the quad from the camera, crosses at x = 0.75 (present half): shadowed."""
    from test_cutouts import _pixel, _render
    from test_cutouts import _stage as cutout_stage

    def lit_by_bulb(stage):
        stage.RemovePrim("/Sun")
        bulb = UsdLux.SphereLight.Define(stage, "/Bulb")
        bulb.CreateRadiusAttr(0.01)
        bulb.CreateIntensityAttr(1.0)
        bulb.AddTranslateOp().Set((0.0, 0.0, 1.0))
        stage.GetRootLayer().Save()
        return stage

    (tmp_path / "cut").mkdir()
    (tmp_path / "bare").mkdir()
    cut = lit_by_bulb(cutout_stage(tmp_path / "cut"))
    bare = lit_by_bulb(cutout_stage(tmp_path / "bare"))
    UsdGeom.Imageable(bare.GetPrimAtPath("/Quad")).MakeInvisible()
    out, camera = _render(cut, mode)
    ref, _ = _render(bare, mode)
    through = _pixel(camera, (-0.5, 0.0, -1.0))
    np.testing.assert_allclose(out.beauty[through], ref.beauty[through], rtol=1e-5)
    shadowed = _pixel(camera, (1.5, 0.0, -1.0))
    assert out.beauty[shadowed][2] < 0.5 * ref.beauty[shadowed][2]
