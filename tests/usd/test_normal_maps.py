"""UsdPreviewSurface ``normal`` (tangent-space normal maps), the one rule of raster and
trace (model/surface.py NormalMaps): the quad of ``textured_stages.textured_quad_stage`` (facing
+z, st along +x / +y, so T = +x, B = +y, N = +z) with a constant normal map tilting the normal
by 30° towards +x; the G-buffer normal is the tilted one in raster and rt."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Gf, Sdf
from textured_stages import (
    define_texture,
    pixel_at,
    render_first_frame,
    textured_quad_stage,
    write_image,
)

TILT = math.radians(30.0)


def _tilted(tmp_path):
    """The stage with a normal map of one texel value, (sin 30°, 0, cos 30°) after the
    author's scale 2 and bias -1 (8-bit raw: the texel is quantised; the expected
    normal is computed from the same bytes)."""
    stage, surf = textured_quad_stage(tmp_path)
    want = np.array([math.sin(TILT), 0.0, math.cos(TILT)])
    texel = np.round((want * 0.5 + 0.5) * 255) / 255
    write_image(tmp_path / "normal.png", np.tile(texel, (4, 4, 1)))
    f4 = Sdf.ValueTypeNames.Float4
    tex = define_texture(
        stage, "/Looks/Quad/Normal", "normal.png",
        sourceColorSpace=(Sdf.ValueTypeNames.Token, "raw"),
        scale=(f4, Gf.Vec4f(2, 2, 2, 1)), bias=(f4, Gf.Vec4f(-1, -1, -1, 0)),
    )  # fmt: skip
    surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
        tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    stage.GetRootLayer().Save()
    m = texel * 2 - 1
    return stage, m / np.linalg.norm(m)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raster", "rt"])
def test_normal_map_tilts_the_shading_normal(tmp_path, mode):
    stage, expected = _tilted(tmp_path)
    out, camera = render_first_frame(stage, mode)
    for x in (-0.5, 0.5):
        normal = out.gbuffer.normal[pixel_at(camera, (x, 0.3, 0.0))]
        # float32 G-buffer normal of a unit vector: 1e-6.
        np.testing.assert_allclose(normal, expected, atol=1e-6)


def test_support_report_no_longer_lists_a_normal_map(tmp_path):
    from phrt_usd.usd.support_report import support_report

    stage, _ = _tilted(tmp_path)
    assert "unshaded_texture" not in {r["kind"] for r in support_report(stage)}
