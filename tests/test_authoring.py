"""phrt_usd.authoring: opinions in a new layer over the stage; the input stays untouched."""

import pytest
from pxr import Sdf, Usd, UsdGeom

from phrt_usd import schema
from phrt_usd.authoring import author_reflectors, default_overlay_path
from phrt_usd.errors import PhrtError


@pytest.fixture()
def stage_file(tmp_path):
    path = tmp_path / "scene.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Z")
    UsdGeom.Xform.Define(stage, "/World")
    UsdGeom.Cube.Define(stage, "/World/Box")
    UsdGeom.Sphere.Define(stage, "/World/Ball")
    stage.GetRootLayer().Save()
    return path


def test_default_writes_overlay_and_keeps_input_bytes(stage_file):
    before = stage_file.read_bytes()
    result = author_reflectors(stage_file, ["/World/Box", "/World/Ball"], 4.0, reflectivity=0.5)
    assert stage_file.read_bytes() == before
    overlay = default_overlay_path(stage_file)
    assert result.layer == str(overlay) and overlay.name == "scene.phrt.usda"
    layer = Sdf.Layer.FindOrOpen(str(overlay))
    assert list(layer.subLayerPaths) == ["scene.usda"]  # relative to the overlay
    assert layer.GetPrimAtPath("/World/Box").specifier == Sdf.SpecifierOver
    stage = Usd.Stage.Open(str(overlay))
    for path in ("/World/Box", "/World/Ball"):
        prim = stage.GetPrimAtPath(path)
        assert schema.is_reflector(prim)
        assert schema.reflector_priority(prim) == 4.0
        assert schema.reflector_reflectivity(prim) == 0.5
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert not list(stage_file.parent.glob(".*"))  # no temp file left behind


def test_out_in_other_directory_uses_relative_sublayer(stage_file, tmp_path, capfd):
    out = tmp_path / "sub" / "k.usda"
    author_reflectors(stage_file, ["/World/Box"], 2.0, out=out)
    # USD warns on stderr (C++) if a stage recomposes against the not-yet-saved path.
    assert "Could not load sublayer" not in capfd.readouterr().err
    assert list(Sdf.Layer.FindOrOpen(str(out)).subLayerPaths) == ["../scene.usda"]
    assert schema.reflector_priority(Usd.Stage.Open(str(out)).GetPrimAtPath("/World/Box")) == 2.0


def test_in_place_edits_root_layer(stage_file):
    author_reflectors(stage_file, ["/World/Box"], 3.0, in_place=True)
    Sdf.Layer.FindOrOpen(str(stage_file)).Reload()
    assert "PhrtReflectorAPI" in stage_file.read_text()
    stage = Usd.Stage.Open(str(stage_file))
    prim = stage.GetPrimAtPath("/World/Box")
    assert schema.is_reflector(prim) and schema.reflector_priority(prim) == 3.0
    assert not default_overlay_path(stage_file).exists()


@pytest.mark.parametrize(
    "prims, priority, message",
    [
        (["/World/Nope"], 1.0, "/World/Nope: no such prim"),
        (["/World"], 1.0, "/World: is a Xform, not a gprim"),
        (["/World/Box", "/World"], 1.0, "/World: is a Xform"),
        (["/World/Box"], -2.0, "--priority -2.0"),
        (["/World/Box"], float("nan"), "--priority nan"),
    ],
)
def test_errors_write_nothing(stage_file, prims, priority, message):
    before = stage_file.read_bytes()
    with pytest.raises(PhrtError, match=message.replace("(", r"\(")):
        author_reflectors(stage_file, prims, priority)
    assert stage_file.read_bytes() == before
    assert sorted(p.name for p in stage_file.parent.iterdir()) == ["scene.usda"]
