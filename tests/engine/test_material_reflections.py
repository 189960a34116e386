"""Reflections follow the material (``engine/compositing.py``): a reflector without an
authored ``phrt:reflectivity`` reflects by its UsdPreviewSurface's Fresnel (tinted for a
metal), in raster, hybrid and rt alike; an authored F stays an explicit override."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdShade
from scenes import sky_view_stage

from phrt_usd.engine import lighting, shading
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.usd import schema
from phrt_usd.usd.stage import open_stage

#: Float32 image arithmetic against the same weights computed again (the composite's
#: (1 - f) local + f env form and its inverse): a few float32 ulps of values near 1.
ATOL = 1e-5


def _floor_stage(path, metallic: float, colour, reflectivity: float | None) -> str:
    """A 10 m floor (a reflector, ``reflectivity`` authored or not) of a UsdPreviewSurface
    (``metallic``, ``colour``, roughness 0) under a white dome of radiance 1, no other
    light; the camera 2 m above, looking down at 40°."""
    stage = sky_view_stage(path, (1.0, 1.0, 1.0), (0.0, 2.0, 2.4), (0.0, 0.0, 0.0))
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    h = 5.0
    floor.CreatePointsAttr([(-h, 0, -h), (-h, 0, h), (h, 0, h), (h, 0, -h)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    material = UsdShade.Material.Define(stage, "/World/Looks/Floor")
    shader = UsdShade.Shader.Define(stage, "/World/Looks/Floor/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(metallic)
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(floor.GetPrim()).Bind(material)
    schema.apply_reflector(floor.GetPrim(), priority=1.0, reflectivity=reflectivity)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.GetRootLayer().Save()
    return str(path)


def _render(path: str, mode: str, density: str = "full"):
    stage = open_stage(path)
    options = RenderOptions(mode=mode, heuristic="all", width=48, height=36, budget_ms=None,
                            trace_density=density)  # fmt: skip
    renderer = FrameRenderer(stage, options)
    try:
        return renderer.render(1.0), stage.scene
    finally:
        renderer.close()


def _uniform_look(gb, scene) -> np.ndarray:
    """(H, W, 3) what each floor pixel of ``gb`` shows under the uniform unit dome as a
    non-reflector of its material: its ambient weight with the specular part
    (``shading.surface_weights``)."""
    cov = gb.covered
    surface = lighting.gbuffer_surface(scene, gb.triangle_id[cov], gb.element_id[cov],
                                       gb.albedo[cov], gb.position[cov])  # fmt: skip
    surface[:, 14] = 1.0  # the specular ambient on: what the reflection stands in for
    out = np.zeros((*gb.shape, 3), np.float32)
    out[cov] = shading.surface_weights(surface, gb.normal[cov], -gb.view_dir[cov])[0]
    return out


@pytest.mark.slow
@pytest.mark.parametrize("metallic,colour", [(1.0, (0.9, 0.3, 0.1)), (0.0, (0.1, 0.2, 0.8))],
                         ids=["red metal", "blue plastic"])  # fmt: skip
def test_probe_reflection_follows_the_material(tmp_path, metallic, colour):
    """A red metal and a blue plastic floor (phrt:reflectivity unauthored) reflecting a
    white sky: every pixel shows what the material returns of a uniform environment
    (diffuse ambient plus the reflection weighted by the lobe's directional albedo, the
    split sum), in raster, hybrid (every reflector traced) and rt. The metal mirrors
    white as its own colour; the plastic reflects a few per cent face on."""
    path = _floor_stage(tmp_path / "floor.usda", metallic, colour, None)
    frames = {mode: _render(path, mode) for mode in ("raster", "hybrid", "rt")}
    out, scene = frames["raster"]
    floor = out.gbuffer.covered
    assert floor.mean() > 0.5  # the floor below the horizon, the sky above
    want = _uniform_look(out.gbuffer, scene)
    for mode, (frame, _) in frames.items():
        np.testing.assert_allclose(frame.beauty[floor], want[floor], atol=ATOL, err_msg=mode)
    if metallic:  # F0 = F90 = the albedo: a tinted mirror
        np.testing.assert_allclose(want[floor], np.broadcast_to(colour, want[floor].shape),
                                   atol=0.02)  # the GGX lobe's albedo at roughness 0: ~1
    else:  # F0 = 0.04 face on, rising towards grazing; the reflection is not a mirror
        reflection = want[floor] - np.asarray(colour) * 0.9
        assert float(reflection.min()) > 0.0 and float(want[floor].max()) < 1.0


@pytest.mark.slow
def test_authored_reflectivity_stays_an_override(tmp_path):
    """The same red metal floor with phrt:reflectivity = 0.5 authored: (1 - F) local +
    F reflected as before the material rule: half the white sky, grey, with no diffuse
    from a metal (its local part is its diffuse ambient alone, 0)."""
    path = _floor_stage(tmp_path / "floor.usda", 1.0, (0.9, 0.3, 0.1), 0.5)
    for mode in ("raster", "hybrid"):
        frame, _ = _render(path, mode)
        floor = frame.gbuffer.covered
        assert floor.mean() > 0.5
        np.testing.assert_allclose(frame.beauty[floor], 0.5, atol=ATOL, err_msg=mode)


@pytest.mark.slow
def test_tinted_reflection_reconstructs_at_reduced_density(tmp_path):
    """At a sixteenth of the pixels traced, the fill's sky rule reads the fallback's
    reflected environment back (the composite's local image is made for it,
    ``compositing._material_local``): the red metal's untraced pixels are tinted once,
    as the fully traced frame's, not twice."""
    path = _floor_stage(tmp_path / "floor.usda", 1.0, (0.9, 0.3, 0.1), None)
    full, _ = _render(path, "hybrid")
    sparse, _ = _render(path, "hybrid", density="sixteenth")
    np.testing.assert_allclose(sparse.beauty, full.beauty, atol=ATOL)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sewer", "farm"])
def test_paper_stages_keep_their_reflection_weights(name):
    """The paper's stages author phrt:reflectivity on every reflector: their reflections
    keep the explicit (1 - F) local + F reflected (their local shading is the BRDF's)."""
    from repo_paths import STAGES

    stage = open_stage(STAGES / f"{name}.usda")
    schema.mark_material_reflections(stage.stage, stage.scene.elements)
    reflectors = [e for e in stage.scene.elements if e.is_reflector]
    assert reflectors and all(e.reflectivity_authored for e in reflectors)
