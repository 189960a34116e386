"""BasisCurves drawn as tubes (``usd/curves.py``): the cubic bases evaluated as the
schema defines them, and a tube's silhouette and colour at analytic pixels in raster
and rt.

The render stage: a camera at (0, 0, 5) looking down -Z (focal 50 mm, aperture 20 x 20
mm: the image spans +-1 m at z = 0, 16 x 16 pixels, pixel rows at y = 1 - (k + 0.5) / 8
there), a white dome of radiance 1, and a straight curve along X through the origin,
bound to a red UsdPreviewSurface.
"""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade
from scenes import first_frame, front_view_stage, preview_shade

from phrt_usd.usd import curves

W = H = 16
MODES = ("raster", "rt")
RED = (1.0, 0.0, 0.0)
S = curves.SEGMENT_SAMPLES


def test_bezier_segment_midpoint():
    """A cubic Bezier (0,0,0) (1,1,0) (2,1,0) (3,0,0) is at (1.5, 0.75, 0) at t = 1/2
    and ends on its end point."""
    pts = np.array([(0, 0, 0), (1, 1, 0), (2, 1, 0), (3, 0, 0)], float)
    samples, owner, _ = curves._polylines(pts, np.array([4]), "cubic", "bezier", "nonperiodic")
    assert len(samples) == S + 1 and (owner == 0).all()
    np.testing.assert_allclose(samples[S // 2], (1.5, 0.75, 0), atol=1e-12)
    np.testing.assert_allclose(samples[[0, -1]], pts[[0, 3]], atol=1e-12)


@pytest.mark.parametrize(
    ("wrap", "through"), [("nonperiodic", [1, 2, 3]), ("pinned", [0, 1, 2, 3, 4])]
)
def test_catmull_rom_passes_through_its_points(wrap, through):
    """Catmull-Rom interpolates its points: nonperiodic from the second to the
    next-to-last, pinned from the first to the last."""
    pts = np.array([(0, 0, 0), (1, 2, 0), (2, -1, 1), (4, 0, 0), (5, 3, 2)], float)
    samples, _, _ = curves._polylines(pts, np.array([5]), "cubic", "catmullRom", wrap)
    np.testing.assert_allclose(samples[::S], pts[through], atol=1e-12)


def test_periodic_bspline_closes():
    pts = np.array([(1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0)], float)
    samples, _, _ = curves._polylines(pts, np.array([4]), "cubic", "bspline", "periodic")
    assert len(samples) == 4 * S + 1
    np.testing.assert_allclose(samples[0], samples[-1], atol=1e-12)
    # A uniform B-spline starts at (P0 + 4 P1 + P2) / 6.
    np.testing.assert_allclose(samples[0], (pts[0] + 4 * pts[1] + pts[2]) / 6, atol=1e-12)


def _curve_stage(tmp_path, kind: str, basis: str, width: float) -> Usd.Stage:
    stage = front_view_stage(tmp_path / "curves.usda")
    hair = UsdGeom.BasisCurves.Define(stage, "/Hair")
    hair.CreateTypeAttr(kind)
    hair.CreateBasisAttr(basis)
    hair.CreateWrapAttr("pinned")
    hair.CreatePointsAttr([(-3, 0, 0), (-1, 0, 0), (1, 0, 0), (3, 0, 0)])
    hair.CreateCurveVertexCountsAttr([4])
    hair.CreateWidthsAttr([width])
    hair.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    mat = UsdShade.Material.Define(stage, "/Red")
    surf = UsdShade.Shader.Define(stage, "/Red/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*RED))
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(hair.GetPrim()).Bind(mat)
    return stage


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize(("kind", "basis"), [("linear", "bezier"), ("cubic", "catmullRom")])
def test_curve_is_drawn_as_a_tube(tmp_path, kind, basis, mode):
    """A tube of width 1 along X: the centre column covers rows 4..11 (|y| < 0.5: the
    silhouette of a radius-0.5 octagonal tube seen from 5 m lies at |y| between 0.46
    and 0.50 at z = 0, and the row centres nearest it are 0.4375 and 0.5625), and the
    tube's front, whose normal faces the camera, shades as the red material."""
    stage = _curve_stage(tmp_path, kind, basis, width=1.0)
    out = first_frame(stage, mode, W, H)
    covered = np.flatnonzero(out.gbuffer.element_id[:, W // 2] >= 0)
    assert covered.tolist() == list(range(4, 12))
    # Row 7's centre (y = 0.0625) sees the front facets within 8 degrees of facing the
    # camera: their directional albedo is within 0.03 of the facing one's.
    front = preview_shade(RED, (0.0, 0.0, 0.5), (0.0, 0.0, 5.0), ambient=1.0)
    np.testing.assert_allclose(out.beauty[7, W // 2], front, atol=0.03)


@pytest.mark.parametrize("mode", MODES)
def test_vertex_colours_vary_along_the_tube(tmp_path, mode):
    """displayColor per vertex (red, red, blue, blue) on the pinned Catmull-Rom through
    x = -3, -1, 1, 3 (evenly spaced and collinear: its parameter is linear in x), no
    material: the ray of pixel (7, 8) meets the front of the tube (z = 0.5) at x =
    0.0625 * 4.5 / 5, parameter u = (x + 3) / 6, i.e. 3u = 1.528 vertex steps: a
    blend of 47 % red and 53 % blue."""
    stage = _curve_stage(tmp_path, "cubic", "catmullRom", width=1.0)
    hair = stage.GetPrimAtPath("/Hair")
    UsdShade.MaterialBindingAPI(hair).UnbindAllBindings()
    UsdGeom.PrimvarsAPI(hair).CreatePrimvar(
        "displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex
    ).Set([RED, RED, (0, 0, 1), (0, 0, 1)])
    out = first_frame(stage, mode, W, H)
    f = 3 * (0.0625 * 4.5 / 5 + 3) / 6 - 1
    colour = (1 - f, 0.0, f)
    expected = preview_shade(colour, (0.0, 0.0, 0.5), (0.0, 0.0, 5.0), ambient=1.0)
    # 0.03: the front facets' tilt (within 8 degrees) as in the test above.
    np.testing.assert_allclose(out.beauty[7, W // 2], expected, atol=0.03)


@pytest.mark.parametrize("mode", MODES)
def test_curves_with_normals_are_ribbons_facing_them(tmp_path, mode):
    """The same curve with ``normals`` (0, 0, 1) authored: a flat strip of width 1 at
    z = 0 facing the camera, so the centre column covers rows 4..11 (|y| < 0.5, the row
    centres nearest the edges being 0.4375 and 0.5625), and the pixel (7, 8), which sees
    the strip's point (0.0625, 0.0625, 0) along its normal, shades as the red material
    there (float32 shading: 1e-4). Normals (0, 1, 0) turn the strip edge-on to the
    camera: no pixel sees it (a tube would cover the same rows 4..11)."""
    stage = _curve_stage(tmp_path, "cubic", "catmullRom", width=1.0)
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Hair"))
    hair.CreateNormalsAttr([(0, 0, 1)] * 4)  # vertex interpolation (the fallback)
    out = first_frame(stage, mode, W, H)
    covered = np.flatnonzero(out.gbuffer.element_id[:, W // 2] >= 0)
    assert covered.tolist() == list(range(4, 12))
    facing = preview_shade(RED, (0.0625, 0.0625, 0.0), (0.0, 0.0, 5.0), ambient=1.0)
    np.testing.assert_allclose(out.beauty[7, W // 2], facing, atol=1e-4)
    hair.GetNormalsAttr().Set([(0, 1, 0)] * 4)
    edge_on = first_frame(stage, mode, W, H)
    assert not (edge_on.gbuffer.element_id >= 0).any()


def test_ribbon_geometry_faces_its_normals():
    """A ribbon's triangles are wound to face the authored normal (their geometric
    normal along it) and carry it at every corner; 2 vertices a sample."""
    stage = Usd.Stage.CreateInMemory()
    hair = UsdGeom.BasisCurves.Define(stage, "/Hair")
    hair.CreateTypeAttr("linear")
    hair.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (2, 0, 1)])
    hair.CreateCurveVertexCountsAttr([3])
    hair.CreateWidthsAttr([0.2])
    hair.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    hair.CreateNormalsAttr([(0, 1, 0)])
    hair.SetNormalsInterpolation(UsdGeom.Tokens.constant)
    pts, tris, nrm = curves.tube_geometry(hair.GetPrim(), Usd.TimeCode.Default())
    assert pts.shape == (6, 3) and tris.shape == (4, 3)
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    geometric = np.cross(b - a, c - a)
    assert (geometric[:, 1] > 0).all()  # every triangle faces +y, the normal
    np.testing.assert_allclose(nrm.reshape(-1, 3), np.tile((0.0, 1.0, 0.0), (12, 1)), atol=1e-12)
    # The strip is 0.2 wide across the curve: the first pair straddles the first point.
    np.testing.assert_allclose(np.linalg.norm(pts[0] - pts[1]), 0.2, atol=1e-12)
