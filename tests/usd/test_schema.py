"""Phrt schema plugin: generated files current, registration both ways, Python API."""

import os
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender
from repo_paths import REPO

import phrt_usd
from phrt_usd.usd import schema


def _mesh_stage():
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.Mesh.Define(stage, "/World/Mirror").GetPrim()
    return stage, prim


@pytest.mark.slow
def test_generated_plugin_files_are_current():
    proc = subprocess.run(
        [sys.executable, str(REPO / "tools" / "gen_schema.py"), "--check"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr


def test_import_registers_schemas_with_fallbacks():
    stage, prim = _mesh_stage()
    assert prim.ApplyAPI(schema.REFLECTOR_API)
    # Schema fallbacks, nothing authored but the API.
    assert prim.GetAttribute(schema.PRIORITY).Get() == 1.0
    assert prim.GetAttribute(schema.REFLECTIVITY).Get() == 1.0
    assert not prim.GetAttribute(schema.PRIORITY).IsAuthored()
    path = stage.DefinePrim("/P", schema.CAMERA_PATH_TYPE)
    assert path.IsA(schema.CAMERA_PATH_TYPE)
    assert {schema.POSITIONS, schema.TARGETS, schema.KEY_TIMES, schema.INTERPOLATION} <= set(
        path.GetPropertyNames()
    )
    assert path.GetAttribute(schema.INTERPOLATION).Get() == "catmullRom"
    settings = UsdRender.Settings.Define(stage, "/Render/Settings").GetPrim()
    assert settings.ApplyAPI(schema.RENDER_SETTINGS_API)
    assert settings.GetAttribute(schema.BUDGET_RAYS).Get() == -1
    assert (
        abs(settings.GetAttribute(schema.SELECTION_WEIGHT).Get() - schema.DEFAULT_SELECTION_WEIGHT)
        < 1e-9
    )
    # Re-registering is harmless.
    from pxr import Plug

    Plug.Registry().RegisterPlugins(str(phrt_usd.PLUGIN_DIR))
    assert Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(schema.REFLECTOR_API)


def test_every_class_and_property_is_documented():
    reg = Usd.SchemaRegistry()
    for definition in (
        reg.FindAppliedAPIPrimDefinition(schema.REFLECTOR_API),
        reg.FindAppliedAPIPrimDefinition(schema.RENDER_SETTINGS_API),
        reg.FindConcretePrimDefinition(schema.CAMERA_PATH_TYPE),
    ):
        assert definition.GetDocumentation()
        for name in definition.GetPropertyNames():
            if name.startswith("phrt:"):
                assert definition.GetPropertyDocumentation(name), name


def test_reflector_api_only_applies_to_gprims():
    stage, prim = _mesh_stage()
    xform = stage.DefinePrim("/X", "Xform")
    assert prim.CanApplyAPI(schema.REFLECTOR_API)
    assert not xform.CanApplyAPI(schema.REFLECTOR_API)


@pytest.mark.slow
def test_plugin_path_env_registers_without_importing_phrt_usd(tmp_path):
    code = (
        "import sys\n"
        "from pxr import Usd, UsdGeom\n"
        "s = Usd.Stage.CreateInMemory()\n"
        "m = UsdGeom.Mesh.Define(s, '/M').GetPrim()\n"
        "m.ApplyAPI('PhrtReflectorAPI')\n"
        "p = s.DefinePrim('/P', 'PhrtCameraPath')\n"
        "assert 'phrt_usd' not in sys.modules\n"
        "print(m.GetAttribute('phrt:priority').Get(), p.IsA('PhrtCameraPath'))\n"
    )
    env = dict(os.environ, PXR_PLUGINPATH_NAME=str(phrt_usd.PLUGIN_DIR))
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["1.0", "True"]


def test_plain_usd_authoring_reads_back():
    """Authoring the common brief's plain-USD way is what the schema API reads."""
    stage, prim = _mesh_stage()
    prim.ApplyAPI("PhrtReflectorAPI")
    prim.GetAttribute("phrt:priority").Set(4.0)
    assert schema.is_reflector(prim)
    assert schema.reflector_priority(prim) == 4.0
    assert schema.reflector_reflectivity(prim) == 1.0
    other = UsdGeom.Sphere.Define(stage, "/World/Ball").GetPrim()
    other.AddAppliedSchema("PhrtReflectorAPI")
    other.CreateAttribute("phrt:reflectivity", Sdf.ValueTypeNames.Float).Set(0.25)
    assert schema.reflector_reflectivity(other) == 0.25
    assert [p.GetName() for p in schema.find_reflectors(stage)] == ["Mirror", "Ball"]


@pytest.mark.slow
def test_reader_without_plugin_uses_same_defaults(tmp_path):
    """A process where the schemas are unknown still reads reflectors and defaults."""
    layer = tmp_path / "plain.usda"
    stage, prim = _mesh_stage()
    prim.AddAppliedSchema("PhrtReflectorAPI")
    stage.GetRootLayer().Export(str(layer))
    code = (
        "from pxr import Usd\n"
        f"s = Usd.Stage.Open({str(layer)!r})\n"
        "import warnings; warnings.simplefilter('ignore')\n"
        "from phrt_usd.usd import schema\n"  # registered too late for this process
        "p = s.GetPrimAtPath('/World/Mirror')\n"
        "assert p.GetAttribute('phrt:priority').Get() is None\n"
        "print(schema.is_reflector(p), schema.reflector_priority(p))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["True", "1.0"]


def test_camera_path_round_trip():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Camera.Define(stage, "/Cam")
    pos = np.array([[0, 1, 5], [2, 1, 5], [4, 1, 3]], dtype=np.float64)
    tgt = np.zeros((3, 3))
    schema.define_camera_path(stage, "/Path", "/Cam", pos, tgt, [1, 12, 24], interpolation="linear")
    (prim,) = schema.find_camera_paths(stage)
    data = schema.read_camera_path(prim)
    np.testing.assert_array_equal(data.positions, pos)
    np.testing.assert_array_equal(data.targets, tgt)
    np.testing.assert_array_equal(data.key_times, [1, 12, 24])
    assert (data.start, data.end, data.camera, data.interpolation) == (1, 24, "/Cam", "linear")


def test_render_params_defaults_metadata_and_first_prim():
    stage = Usd.Stage.CreateInMemory()
    params = schema.read_render_params(stage)
    assert params == schema.RenderParams()
    assert params.settings_path is None and params.budget_rays is None
    first = UsdRender.Settings.Define(stage, "/Render/A")
    second = UsdRender.Settings.Define(stage, "/Render/B")
    schema.apply_render_settings(first.GetPrim(), heuristic="heu2", budget_ms=4.0)
    schema.apply_render_settings(second.GetPrim(), mode="rt", budget_rays=5000, bounce_limit=2)
    second.GetResolutionAttr().Set(Gf.Vec2i(640, 360))
    second.GetCameraRel().SetTargets(["/Cam"])
    a = schema.read_render_params(stage)  # first RenderSettings prim
    assert (a.settings_path, a.heuristic, a.budget_ms, a.selection_weight) == (
        "/Render/A",
        "heu2",
        4.0,
        schema.DEFAULT_SELECTION_WEIGHT,
    )
    stage.GetRootLayer().pseudoRoot.SetInfo("renderSettingsPrimPath", "/Render/B")
    b = schema.read_render_params(stage)
    assert (b.settings_path, b.mode, b.budget_rays, b.bounce_limit) == ("/Render/B", "rt", 5000, 2)
    assert b.resolution == (640, 360) and b.camera_path == "/Cam"
